"""Preprocessing (paper section 2.3): initial values, range window, angular patches, RANSAC planes,
keep masks.

* ``_initial``: initial values of the object parameters (pointing + heading search, quadric)
* ``_types``: :class:`PreprocessConfig`, :class:`PreprocessResult`, the reason codes
* ``_frames``: the windows' geometry (pose, "flat" frame, pose refinement, range window)
* ``_patches``: angular patch keys, sorting by patch, padded size buckets
* ``_planes``: RANSAC + total-least-squares planes of padded patches (JAX, vmapped)
* ``_preprocess``: one scan and a campaign, stage by stage; the keep mask for the fitter
* ``_outputs``: ``preprocess.json``, masks, the summary table
"""

from ._frames import default_range_window, refine_pose, reflector_distance_range
from ._initial import InitialValues, choose_initial_values, initial_values
from ._outputs import (
    preprocess_json,
    preprocess_table,
    write_masks,
    write_preprocess_json,
    write_preprocess_result,
)
from ._planes import PlaneCondition, fit_planes, ransac_uniforms
from ._preprocess import keep_mask_fn, preprocess_campaign, preprocess_keep, preprocess_scan
from ._types import PREPROCESS_SCHEMA, REASONS, PreprocessConfig, PreprocessResult

__all__ = [
    "PREPROCESS_SCHEMA", "REASONS", "InitialValues", "PlaneCondition", "PreprocessConfig",
    "PreprocessResult", "choose_initial_values", "default_range_window", "fit_planes",
    "initial_values", "keep_mask_fn", "preprocess_campaign", "preprocess_json", "preprocess_keep",
    "preprocess_scan", "preprocess_table", "ransac_uniforms", "reflector_distance_range",
    "refine_pose", "write_masks", "write_preprocess_json", "write_preprocess_result",
]
