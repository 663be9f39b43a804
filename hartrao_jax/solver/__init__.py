"""Gauss-Helmert adjustment (plain, robust, batched), normal equations, random effects
(Schur complement, variance components) and identifiability."""

from ._ghm import (
    GHResult,
    gauss_helmert,
    gauss_helmert_batch,
    normal_equations,
    robust_gauss_helmert,
)
from ._identifiable import unidentifiable
from ._mixed import MixedResult, gauss_helmert_mixed

__all__ = [
    "gauss_helmert",
    "gauss_helmert_batch",
    "gauss_helmert_mixed",
    "GHResult",
    "MixedResult",
    "normal_equations",
    "robust_gauss_helmert",
    "unidentifiable",
]
