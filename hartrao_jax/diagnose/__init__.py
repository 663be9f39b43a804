"""Diagnosis without plotting: locate (searches by covariate), explain (score tests), model
(grow and refit). Figures and HTML of a diagnosis live in ``report/``."""

from ._diagnose import diagnose
from ._result import Diagnosis, write_json
from ._state import DiagnoseConfig, Finding

__all__ = ["diagnose", "DiagnoseConfig", "Diagnosis", "Finding", "write_json"]
