"""A two-face position's ``positions[]`` record of ``fit.json`` (``shared/spec/outputs.md``).

:func:`position_record` writes a :class:`._fit.PositionFit` (``p`` below; not imported:
:mod:`._fit` imports this module) as strict JSON: the shared pose, f
and calibration (``{value, sigma, sigma_white, unit}``; held parameters with ``identifiable:
false`` and their note), the variance components, the smooth modes and their tests, what a
mode that is not modelled would move, and the panels' predictions (:func:`panel_predictions`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..model._model import parameter_unit
from ._identify import CONFOUNDING_AMPLITUDE_M, CONFOUNDING_SHIFT_MIN, confounding_shifts


def _value_sigma(v: float, s: float | None, unit: str) -> dict:
    return {"value": _num(v), "sigma": None if s is None else _num(s), "unit": unit}


def panel_predictions(p: Any) -> list[dict]:
    """The surface random effect's predictions (BLUPs) per cell with points, with their sigmas.

    Offsets in m (positive towards the focus), tilts in rad (``tilt_radial_rad``: outer edge up,
    ``tilt_tangential_rad``: counter-clockwise edge up; for square cells ``tilt_x_rad``,
    ``tilt_y_rad``), from every point of both faces. Deviations are from the fitted paraboloid
    plus the smooth modes (``surface_modes``). ``f_response``: ``d f_hat / d (offset, tilt,
    tilt)`` of the cell (1, m/rad): how the cell's true deviation moved f.
    """
    if p.surface is None:
        return []
    sf = p.surface
    names = (("tilt_radial_rad", "tilt_tangential_rad") if sf.cells.startswith("panels")
             else ("tilt_x_rad", "tilt_y_rad"))
    i_f = (list(p.names).index("f") if p.response is not None and "f" in p.names else None)
    out = []
    for g in np.flatnonzero(sf.n > 0):
        sd = np.sqrt(np.clip(np.diag(sf.u_cov[g]), 0.0, None))
        out.append({"panel" if sf.cells.startswith("panels") else "cell": int(g),
                    "offset_m": _num(sf.u[g, 0]), "offset_sigma_m": _num(sd[0]),
                    names[0]: _num(sf.u[g, 1]), names[0][:-4] + "_sigma_rad": _num(sd[1]),
                    names[1]: _num(sf.u[g, 2]), names[1][:-4] + "_sigma_rad": _num(sd[2]),
                    "n": int(sf.n[g]),
                    **({"f_response": [_num(a) for a in p.response[g, i_f]]}
                       if i_f is not None else {})})
    return out


def position_record(p: Any) -> dict:
    """The ``positions[]`` entry of ``fit.json`` for a position adjustment."""
    m = p.scans[0].meta
    s0 = p.scans[0]
    row: dict = {"position": p.position}
    if m.ha_deg is not None:
        row.update(ha_deg=m.ha_deg, dec_deg=m.dec_deg)
    if m.azimuth_deg is not None:
        row.update(azimuth_deg=m.azimuth_deg)
    row.update(elevation_deg=s0.elevation_deg, faces=p.faces,
               kind="two-face adjustment" if p.faces == 2 else "one face",
               scans=[s.meta.id for s in p.scans])
    share = p.surface.mode_prior.get("share", {}) if p.surface is not None else {}
    for i, n in enumerate(p.names):
        row[n] = _value_sigma(p.x[i], p.sigma[i], parameter_unit(n))
        if p.sigma_white is not None:
            row[n]["sigma_white"] = _num(p.sigma_white[i])
        if n in share:
            row[n]["mode_prior_share"] = _num(share[n])
    for n, h in p.held.items():
        row[n] = {"value": _num(h.value), "sigma": None, "identifiable": False, "note": h.note,
                  "unit": parameter_unit(n)}
    row["sigma0"] = _num(p.sigma0)
    row["n_points"] = p.n_points
    row["iterations"] = p.iterations
    row["converged"] = p.converged
    if p.surface is not None:
        v = p.surface.variances
        row["variance_components"] = {
            "noise": _num(v["noise"]), "surface_m": _num(math.sqrt(v["offset_m2"])),
            "tilt_rad": _num(math.sqrt(v["tilt_rad2"])),
            **({"modes_m": _num(math.sqrt(v["modes_m2"]))} if "modes_m2" in v else {}),
            **({"mode_groups_m": {k: _num(math.sqrt(x)) for k, x in v["mode_groups_m2"].items()}}
               if "mode_groups_m2" in v else {}),
            "redundancy": {k: _num(x) for k, x in p.surface.redundancy.items()},
            "cells": p.surface.cells}
        if p.surface.modes:
            det = p.surface.mode_prior.get("determined", {})
            row["surface_modes"] = {
                k: {**_value_sigma(a, b, "m"),
                    **({"determined_by_data": _num(det[k])} if k in det else {})}
                for k, (a, b) in p.surface.modes.items()}
        conf = p.surface.mode_confounding
        if conf:
            shifts = confounding_shifts(conf, p.names, p.sigma)
            for n, v in shifts.items():  # said next to each estimate it concerns
                if v > CONFOUNDING_SHIFT_MIN:
                    row[n]["not_separable_from"] = list(conf["modes"])
                    row[n]["shift_sigma_per_10um"] = _num(v)
            row["surface_mode_confounding"] = {
                "modes": list(conf["modes"]),
                "multiple_correlation": {k: _num(v) for k, v in conf["correlation"].items()},
                "amplitude_m": CONFOUNDING_AMPLITUDE_M,
                "shift_sigma": {k: _num(v) for k, v in shifts.items()},
                "note": "not modelled: the estimates move by shift_sigma of their sigmas "
                        "per amplitude_m of these modes (root sum square of their "
                        "coefficients), which the data cannot determine at one position"}
        if p.surface.mode_tests:
            row["surface_mode_tests"] = {
                k: {"chi2": _num(t["chi2"]), "dof": t["dof"], "p": _num(t["p"]),
                    "carried": bool(t["carried"])} for k, t in p.surface.mode_tests.items()}
        row["panels"] = panel_predictions(p)
    row["gravity"] = [float(a) for a in s0.gravity]
    row["notes"] = list(p.notes)
    return row


def _num(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None
