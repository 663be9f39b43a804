"""Diagnosis without plotting: locate (searches by covariate), explain (score tests), model
(grow and refit). Figures and HTML of a diagnosis live in ``report/``."""

from ._state import DiagnoseConfig, Finding
from ._diagnose import diagnose, Diagnosis, write_json

__all__ = ["diagnose", "DiagnoseConfig", "Diagnosis", "Finding", "write_json"]
