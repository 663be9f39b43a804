"""Preprocessing: initial values, range window, angular patches, RANSAC planes, keep masks."""

from ._initial import choose_initial_values, initial_values, InitialValues
from ._preprocess import (
    keep_mask_fn,
    preprocess_campaign,
    preprocess_scan,
    PreprocessConfig,
    PreprocessResult,
)

__all__ = [
    "choose_initial_values",
    "initial_values",
    "InitialValues",
    "keep_mask_fn",
    "preprocess_campaign",
    "preprocess_scan",
    "PreprocessConfig",
    "PreprocessResult",
]
