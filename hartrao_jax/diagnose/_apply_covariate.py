"""Modelling accepted ``unexplained`` structure: a range correction per covariate bin (or a
cut of the affected time range), and a measured deviation map within flagged panels.

Each ``_apply_*`` returns the fields of the :class:`~._state.Finding` it describes (``where``,
``estimate``, ``extra``, ``explanation``, ``family``, ``scans``). Units: metres, radians,
seconds; ``_deg`` keys are degrees.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ._explain import _Joint
from ._find import _covariate_values, _panel_columns
from ._options import _Option
from ._state import _Context, _num, _refit_all, _Scan, _Spec


def _apply_dish(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint,
                o: _Option) -> dict[str, Any]:
    """Within-panel structure: the cell means (m) of the flagged panels become known
    deviation of every scan; all scans are refitted."""
    pl = o.payload
    flagged = pl["flagged"]
    est = pl["est"]
    amp = []
    for sc, cell in zip(S, pl["cells"]):
        inf = np.isin(sc.panel, flagged) & (cell >= 0)
        add = np.where(inf, est[np.where(cell >= 0, cell, 0)], 0.0)
        sc.extra_known = sc.extra_known + add
        amp.append(add[sc.used & inf])
    _refit_all(ctx, S, spec)
    g = ctx.geo
    rc = np.array([g["rho_c"][p] for p in flagged])
    pc = np.array([g["psi_c"][p] for p in flagged])
    wts = pl["Tg"][flagged]
    psi_m = float(np.degrees(np.angle(np.sum(wts * np.exp(1j * pc)))) % 360)
    where = {"panels": [int(p) for p in flagged],
             "rho_m": float(np.sum(wts * rc) / np.sum(wts)),
             "psi_deg": psi_m,
             "covariate": "rho" if np.ptp(rc) < np.ptp(pc) * np.mean(rc) else "psi"}
    a = np.concatenate(amp) if amp else np.zeros(1)
    estimate = {"amplitude_m": {"value": float(np.max(np.abs(a))) if a.size else 0.0,
                                "sigma": float(joint.sigma0 * 0.0008)},
                "rms_m": {"value": float(np.sqrt(np.mean(a**2))) if a.size else 0.0,
                          "sigma": 0.0}}
    expl = (f"structure within {len(flagged)} panel(s) common to all scans that neither panel "
            f"offsets and tilts nor any catalog effect explain, near rho "
            f"{where['rho_m']:.1f} m, "
            f"psi {psi_m:.0f} deg; modelled as a measured deviation map")
    return {"where": where, "estimate": estimate, "explanation": expl, "family": "generic"}


def _correct_scan(ctx: _Context, sc: _Scan, pl: dict, k: int, big: np.ndarray) -> None:
    """Model the significant bins ``big`` of scan ``k``: a cut of their points (time), or the
    joint solution's range error per bin (m) and the panel planes it implies as known
    deviation (any other covariate)."""
    ids = pl["ids"][k]
    if pl["covariate"] == "time":
        sc.cut = sc.cut | np.isin(ids, big)
        return
    ps = pl["per_scan"]
    ok = ids >= 0
    er = pl["raw"][k * ps: (k + 1) * ps]
    kp = np.where(sc.panel >= 0, sc.panel, 0)
    plane = np.where(sc.panel >= 0, np.sum(_panel_columns(ctx, sc) * pl["planes"][kp], 1), 0.0)
    sc.extra_known = sc.extra_known + np.where(
        ok, -sc.b0 * er[np.where(ok, ids, 0)] / sc.s_rho, 0.0) - plane


def _covariate_scan(ctx: _Context, sc: _Scan, pl: dict, k: int) -> dict | None:
    """The bins of scan ``k`` whose range error (m) is both significant (|z| > 5) and larger
    than ``min_effect_m``, modelled (:func:`_correct_scan`) and described (faces, phi range in
    degrees, covariate range, range errors in m); None when the scan has none."""
    name = pl["covariate"]
    nb, ps = ctx.config.covariate_bins, pl["per_scan"]
    ids = pl["ids"][k]
    e = pl["est"][k * ps: (k + 1) * ps]
    sg = pl["se"][k * ps: (k + 1) * ps]
    z = np.where(sg > 0, e / np.where(sg > 0, sg, 1.0), 0.0)
    big = np.nonzero((np.abs(z) > 5.0) & (np.abs(e) > ctx.config.min_effect_m))[0]
    if not len(big):
        return None
    hit = sc.used & np.isin(ids, big)
    ph = np.degrees(sc.data.phi_rad[hit])
    v = _covariate_values(sc)[name][hit]
    part = {"scan": sc.id, "cycle": sc.meta.cycle,
            "faces": sorted({int(b // nb) + 1 for b in big}),
            "phi_deg": [float(ph.min()), float(ph.max())],
            f"{name}_range": [float(v.min()), float(v.max())],
            "range_error_m": [float(e[b]) for b in big]}
    _correct_scan(ctx, sc, pl, k, big)
    return part


def _covariate_where(name: str, parts: Sequence[dict]) -> dict[str, Any]:
    """Where the structure lives: one scan's phi and covariate range (and face), or the cycles
    and the covariate range over several scans."""
    where: dict[str, Any] = {"covariate": name}
    if len(parts) == 1:
        where.update({k: v for k, v in parts[0].items() if k not in ("scan", "faces",
                                                                     "range_error_m")})
        if len(parts[0]["faces"]) == 1:
            where["face"] = parts[0]["faces"][0]
    elif parts:
        where["cycle"] = [p["cycle"] for p in parts]
        where[f"{name}_range"] = [min(p[f"{name}_range"][0] for p in parts),
                                  max(p[f"{name}_range"][1] for p in parts)]
    return where


def _covariate_comparison(name: str, cv: dict, where: dict, extra: dict) -> str:
    """The held-out comparison of the covariates (top five to ``extra``); a period of the
    accepted covariate (m for range and rho, s for time, rad for angles, 1 for intensity) goes
    to ``where``. Returns the physics hint for the explanation (``""`` if none)."""
    if not cv.get("ranking"):
        return ""
    extra["covariate_comparison"] = {"method": cv["method"], "ranking": cv["ranking"][:5]}
    b = cv["ranking"][0]
    if b["covariate"] == name and b["model"] == "periodic" and "note" not in cv:
        where["period"] = b["period"]
        where["period_unit"] = "m" if name in ("range", "rho") else (
            "s" if name == "time" else "rad" if name != "intensity" else "1")
        extra["periodic_amplitude_m"] = b.get("amplitude_m")
    if b["covariate"] == name and cv.get("physics"):
        return f" ({cv['physics']})"
    return ""


def _apply_covariate(ctx: _Context, S: Sequence[_Scan], spec: _Spec,
                     o: _Option) -> dict[str, Any]:
    """Structure following a covariate: a range correction (m) per bin of it, or a cut of the
    affected time range; the scans concerned are refitted."""
    pl = o.payload
    name = pl["covariate"]
    se = pl["se"]
    spec.modelled.add(name)
    scans, parts = [], []
    for k, sc in enumerate(S):
        part = _covariate_scan(ctx, sc, pl, k)
        if part is not None:
            scans.append(sc.id)
            parts.append(part)
    where = _covariate_where(name, parts)
    extra: dict[str, Any] = {"by_scan": parts}
    if name == "time":
        action = f"cut {sum(int(sc.cut.sum()) for sc in S)} points of the affected time range"
    else:
        action = f"modelled as a range correction per {name.replace('_', ' ')} bin"
    _refit_all(ctx, S, spec, only=[sc for sc in S if sc.id in scans], from_used=False)
    allb = np.concatenate([p["range_error_m"] for p in parts]) if parts else np.zeros(1)
    estimate = {"range_error_rms_m": {"value": float(np.sqrt(np.mean(allb**2))),
                                      "sigma": float(np.median(se[se > 0]))}}
    extra["covariate_statistics"] = {k: {"statistic": _num(v[0]), "dof": v[1]}
                                     for k, v in pl["all"].items()}
    physics = _covariate_comparison(name, pl.get("cv") or {}, where, extra)
    expl = (f"residual structure in {', '.join(scans) or 'the scans'} following "
            f"{name.replace('_', ' ')} that no catalog effect explains{physics}; {action}")
    return {"scans": scans, "where": where, "estimate": estimate, "extra": extra,
            "explanation": expl, "family": "generic"}
