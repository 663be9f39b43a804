"""The effect catalog: each effect once, as a pure JAX function with its metadata
(parameters, units, family, faces, defaults)."""

from ._catalog import (
    EFFECTS,
    EXTENDED,
    INSTRUMENT,
    SIMPLIFIED,
    Effect,
    inseparable_pairs,
    paraboloid_condition,
    two_face_parameters,
)

__all__ = [
    "Effect",
    "EFFECTS",
    "EXTENDED",
    "inseparable_pairs",
    "INSTRUMENT",
    "paraboloid_condition",
    "SIMPLIFIED",
    "two_face_parameters",
]
