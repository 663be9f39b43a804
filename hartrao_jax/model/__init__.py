"""A model: catalog names plus fixed values -> the condition ``F(l, x)`` for one point."""

from ._model import (
    ModelError,
    ParaboloidModel,
    format_estimate,
    make_model,
    parameter_unit,
    parse_model,
)

__all__ = ["format_estimate", "make_model", "ModelError", "ParaboloidModel", "parameter_unit",
           "parse_model"]
