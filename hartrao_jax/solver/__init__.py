"""Gauss-Helmert adjustment (plain, robust, batched), normal equations, random effects
(Schur complement, variance components) and identifiability."""

from ._ghm import (
    gauss_helmert,
    gauss_helmert_batch,
    GHResult,
    normal_equations,
    robust_gauss_helmert,
)
from ._mixed import gauss_helmert_mixed, MixedResult, unidentifiable

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
