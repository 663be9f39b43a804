"""Preprocessing: initial values, range window, angular patches, RANSAC planes, keep masks."""

from ._initial import InitialValues, choose_initial_values, initial_values
from ._preprocess import (
    PreprocessConfig,
    PreprocessResult,
    keep_mask_fn,
    preprocess_campaign,
    preprocess_scan,
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
