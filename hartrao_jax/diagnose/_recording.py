"""What a recording holds, and which searches of the diagnosis it therefore supports.

An imported export (XYZ, PTX, E57) can lack what the simulated two-face campaigns have: scan
times (an XYZ export, often a random sample, has only a nominal clock in row order), the
second face (cycle 0: software-corrected one-face coordinates), intensity (``x y z`` only).
A search that needs what is missing is not run; it is listed under ``"skipped"`` of the
diagnosis with the reason, instead of crashing or inventing a finding.

Units: metres, radians, seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..physics._catalog import two_face_parameters

NOMINAL_TIME_FORMATS = ("xyz", "ptx")  # imports whose time_s is a nominal clock


@dataclass(frozen=True)
class Capabilities:
    """What the scans of one diagnosis hold."""

    times: bool  # recorded scan times (the phi clock of the scanner)
    two_faces: bool  # every scan is one face of a two-face position (cycle 1 or 2)
    intensity: bool  # a non-constant intensity per point
    why_no_times: str = ""
    why_no_intensity: str = ""


def scan_has_times(meta, data=None) -> tuple[bool, str]:
    """``(True, "")`` when the scan's ``time_s`` was recorded, else ``(False, reason)``."""
    ex = getattr(meta, "extra", {}) or {}
    fmt = str(ex.get("source_format", "")).lower()
    if ex.get("time_nominal") or fmt in NOMINAL_TIME_FORMATS:
        return False, (f"scan {meta.id}: imported {fmt or 'export'} with nominal times only "
                       "(row order, no acquisition clock)")
    if data is not None:
        t = np.asarray(data.time_s, float)
        if t.size < 2 or not np.all(np.isfinite(t)) or np.ptp(t) <= 0:
            return False, f"scan {meta.id}: no usable time_s (constant or missing)"
    return True, ""


def scan_has_intensity(meta, data) -> tuple[bool, str]:
    ex = getattr(meta, "extra", {}) or {}
    fields = str(ex.get("fields", ""))
    if fields and "intensity" not in fields.split():
        return False, f"scan {meta.id}: the export has no intensity column ({fields})"
    i = np.asarray(data.intensity, float)
    if i.size == 0 or not np.all(np.isfinite(i)) or np.ptp(i) <= 0:
        return False, f"scan {meta.id}: intensity is constant (not recorded)"
    return True, ""


def capabilities(metas: Sequence, datas: Sequence) -> Capabilities:
    """The capabilities common to all scans (a search runs only when every scan supports it)."""
    times, why_t, inten, why_i = True, "", True, ""
    for m, d in zip(metas, datas):
        ok, why = scan_has_times(m, d)
        if not ok and times:
            times, why_t = False, why
        ok, why = scan_has_intensity(m, d)
        if not ok and inten:
            inten, why_i = False, why
    two = all(int(m.cycle) in (1, 2) for m in metas)
    return Capabilities(times, two, inten, why_t, why_i)


def skipped_searches(cap: Capabilities, wanted=None) -> list[dict]:
    """The ``"skipped"`` entries of the diagnosis for these capabilities."""
    out = []

    def want(e):
        return wanted is None or e in wanted

    if not cap.times:
        for s in ("impulsive_shift", "oscillation", "drift"):
            if want(s):
                out.append({"search": s, "why": f"needs scan times; {cap.why_no_times}"})
        out.append({"search": "covariate:time", "why": f"needs scan times; {cap.why_no_times}"})
    if not cap.two_faces:
        tf = [k for k in two_face_parameters() if want(k)]
        if tf:
            out.append({"search": "two-face instrument parameters",
                        "parameters": tf,
                        "why": "one face (cycle 0): two-face-sensitive calibration parameters "
                               "are not identifiable without the second face"})
        out.append({"search": "face split", "why": "one face: no face-flipping signature"})
    if not cap.intensity:
        out.append({"search": "covariate:intensity", "why": cap.why_no_intensity})
    return out
