"""The effect catalog: each effect once, as a pure JAX function with its metadata
(parameters, units, family, faces, defaults)."""

from ._catalog import (
    Effect,
    EFFECTS,
    EXTENDED,
    inseparable_pairs,
    INSTRUMENT,
    paraboloid_condition,
    SIMPLIFIED,
)

__all__ = [
    "Effect",
    "EFFECTS",
    "EXTENDED",
    "inseparable_pairs",
    "INSTRUMENT",
    "paraboloid_condition",
    "SIMPLIFIED",
]
