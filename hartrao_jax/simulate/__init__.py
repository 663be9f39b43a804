"""Simulation of campaigns: ray casting of the scan grid, every effect from ``physics/``."""

from ._simulate import (
    CLASSES,
    PRESETS,
    EffectError,
    parse_effects,
    simulate_campaign,
    simulate_scan,
)

__all__ = [
    "CLASSES",
    "EffectError",
    "parse_effects",
    "PRESETS",
    "simulate_campaign",
    "simulate_scan",
]
