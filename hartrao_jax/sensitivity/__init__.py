"""Sensitivity of the estimates to the panel pattern and the model (derivatives, refits)."""

from ._sensitivity import sensitivity, sensitivity_json, write_sensitivity

__all__ = ["sensitivity", "sensitivity_json", "write_sensitivity"]
