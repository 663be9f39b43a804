"""The diagnosis result: `Diagnosis` (schema ``hartrao-diagnosis/1``) and its JSON file."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..campaign._safeio import write_json_atomic
from ._state import (
    Finding,
    _num,
)

DIAGNOSIS_SCHEMA = "hartrao-diagnosis/1"


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`; ``to_json()`` gives the ``hartrao-diagnosis/1`` document."""

    campaign: str
    start_model: list[str]
    final_model: list[str]
    sigma0_start: float
    sigma0_final: float
    rms_start_m: float
    rms_final_m: float
    findings: list[Finding]
    confounded: list[dict]
    comparison: list[dict]
    candidates: list[dict]
    timing_s: dict[str, float]
    notes: list[str] = field(default_factory=list)
    scans_final: dict[str, dict] = field(default_factory=dict)  # per scan, surface random effect
    positions: list[dict] = field(default_factory=list)  # both faces adjusted together
    shared_estimates: dict[str, dict] = field(default_factory=dict)  # common to all scans
    history: list[dict] = field(default_factory=list)
    detectability: list[dict] = field(default_factory=list)
    skipped: list[dict] = field(default_factory=list)  # searches the recording cannot support
    not_identifiable: list[dict] = field(default_factory=list)
    local_search: list[dict] = field(default_factory=list)  # local-deformation searches
    layout: str = ""  # panels of the telescope's layout, or the stated grid
    covariates: dict = field(default_factory=dict)  # cross-validated covariate comparison
    extents: dict = field(default_factory=dict)  # scan id -> map extent (m), for figures
    score_null: dict = field(default_factory=dict)  # the score tests' surface random effect

    def to_json(self) -> dict:
        return {
            "schema": DIAGNOSIS_SCHEMA,
            "campaign": self.campaign,
            "start_model": self.start_model,
            "final_model": self.final_model,
            "sigma0_start": _num(self.sigma0_start),
            "sigma0_final": _num(self.sigma0_final),
            "rms_start_m": _num(self.rms_start_m),
            "rms_final_m": _num(self.rms_final_m),
            "findings": [f.to_json() for f in self.findings],
            "confounded": self.confounded,
            "comparison": self.comparison,
            "last_candidates": self.candidates,
            "scans": self.scans_final,
            "positions": self.positions,
            "shared_estimates": self.shared_estimates,
            "detectability": self.detectability,
            "timing_s": self.timing_s,
            "notes": self.notes,
            "skipped": self.skipped,
            "not_identifiable": self.not_identifiable,
            "local_deformation_search": [
                {k: v for k, v in d.items() if not k.startswith("_")} for d in self.local_search],
            "layout": self.layout,
            "covariate_comparison": self.covariates,
            "score_test_null": self.score_null,
        }

    def effects(self) -> list[str]:
        return [f.effect for f in self.findings]


def write_json(diag: Diagnosis, path: str | Path) -> Path:
    """Write the ``hartrao-diagnosis/1`` document (strict JSON, temporary name + rename)."""

    return write_json_atomic(path, diag.to_json(), indent=2, default=_json_default)


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(type(o))
