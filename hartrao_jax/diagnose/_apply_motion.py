"""Modelling an accepted motion (impulsive shift, oscillation, drift) of one scan, or of the
same motion in the other cycles of its position in one joint step, and describing it."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..model._model import OSCILLATION, SHIFT
from ._explain import _Candidate, _Joint, _log_sf, _Test
from ._motion import _free_frequency, _refine_periods
from ._options import _Option
from ._panels import _update_shared
from ._signature import _signature, _where_of_signature
from ._state import _Context, _num, _refit_all, _Scan, _Spec

log = logging.getLogger("hartrao_jax")


def _with_twins(ctx: _Context, joint: _Joint, o: _Option, t: _Test) -> tuple[_Candidate, _Test]:
    """The same motion in the other cycle(s) of the position as one candidate, when the twins
    add significantly to the first scan's own explanation (the panel offsets shared by the
    cycles make a ghost of one scan's motion in the other); else the candidate alone."""
    c = t.cand
    members, idx, names = [], [], []
    for cc in [c] + [tw.payload.cand for tw in c.info["twins"]]:
        members.append((cc.scans[0], list(cc.names),
                        slice(len(names), len(names) + len(cc.names))))
        idx.append(cc.idx)
        names += [f"{n}@{cc.scans[0]}" for n in cc.names]
    comb = _Candidate(c.effect, c.family, np.concatenate(idx), np.eye(len(names)), names,
                      [m[0] for m in members], penalty=c.penalty,
                      info={**c.info, "members": members})
    tc = joint.test(comb)
    dT, dd = tc.T - t.T, tc.dof - t.dof
    lm = math.log(max(2, len(members)))
    if dd > 0 and _log_sf(dT, dd) + lm + math.log(c.penalty) < math.log(ctx.config.alpha):
        o.T, o.dof = tc.T, tc.dof
        return comb, tc
    c.info["twin_rejected"] = {"statistic": dT, "dof": dd}
    return c, t


def _model_members(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint,
                   c: _Candidate, t: _Test, members):
    """Add the motion parameters (those individually separable from the model: drift has
    confounded ones) of every member scan to the spec; returns ``(refit, hints, first)``."""
    refit, hints, first = [], {}, None
    for sid, mnames, sl in members:
        sc = next(s for s in S if s.id == sid)
        first = first or (sc, mnames, t.estimate[sl])
        names = [n for n in mnames if joint.test(_Candidate(
            c.effect, c.family, np.array([joint.cidx[(sid, n)]]), np.ones((1, 1)), [n],
            [sid])).correlation < ctx.config.confounded_correlation]
        mot = spec.motion.setdefault(sid, {"names": []})
        mot["names"] = list(mot["names"]) + names
        if c.effect == "impulsive_shift":
            mot["window_s"] = sc.window_s
        if c.effect == "oscillation":
            mot["period_s"] = sc.period_s
        hints[sid] = {n: float(v) for n, v in zip(mnames, t.estimate[sl]) if n in names}
        refit.append((sc, names))
    return refit, hints, first


def _motion_where(ctx: _Context, spec: _Spec, c: _Candidate, first, refit,
                  extra: dict) -> dict:
    """Where the motion lives (phi, panels, time window or period); its search evidence and
    the other cycle's slope go to ``extra``."""
    sc, mnames, est0 = first
    multi = len(refit) > 1
    sig = c.info.get("signature")
    if sig is None:
        sig = _signature(ctx, sc, spec, mnames, est0, window_s=sc.window_s,
                         period_s=sc.period_s)
    where = _where_of_signature(ctx, sc, sig, True)
    where["covariate"] = "time"
    if multi:
        where["cycle"] = [s.meta.cycle for s, _ in refit]
        where.pop("phi_deg", None)
    if c.effect == "impulsive_shift":
        where["time_s"] = [sc.window_s[0], sc.window_s[0] + sc.window_s[1]]
        extra["_evidence"] = {"kind": "change_point", "scan": sc.id,
                              "edges": sc.search["edges"],
                              "profile": sc.search["box_profile"],
                              "translation": sc.search["translation"],
                              "window_s": sc.window_s}
    elif c.effect == "oscillation":
        where["period_s"] = sc.period_s
        if multi:
            where["period_s_by_scan"] = {s.id: s.period_s for s, _ in refit}
        extra["_evidence"] = {"kind": "periodogram", "scan": sc.id,
                              "periods": sc.search["periods"],
                              "periodogram": sc.search["periodogram"],
                              "period_s": sc.period_s}
    if "common_slope" in c.info:
        extra["other_cycle_slope"] = _num(c.info["common_slope"][0])
    return where


def _oscillation_period(ctx: _Context, spec: _Spec, sc: _Scan, refit, where: dict) -> dict:
    """Refine the period and estimate it with the amplitudes; returns the per-scan added
    covariance of :func:`._motion._free_frequency`."""
    _refine_periods(ctx, spec, refit)
    freq = _free_frequency(ctx, spec, refit)
    where["period_s"] = spec.motion[sc.id]["period_s"]
    if sc.id in freq:
        where["period_sigma_s"] = freq[sc.id]["period_sigma_s"]
    if len(refit) > 1:
        where["period_s_by_scan"] = {s.id: spec.motion[s.id]["period_s"] for s, _ in refit}
    return freq


def _motion_estimates(t: _Test, refit, members, freq: dict) -> tuple[dict, np.ndarray]:
    """Values from the refit; covariance from the joint system (the panel offsets, estimated
    from the same points, are eliminated there, not held fixed), plus what the uncertainty of
    an oscillation's period adds."""
    multi = len(members) > 1
    sel, rows = [], []
    for (s_, names), (sid, mnames, sl) in zip(refit, members):
        for n in names:
            sel.append(np.arange(len(t.estimate))[sl][mnames.index(n)])
            rows.append((s_, n, f"{n}@{s_.id}" if multi else n))
    cov = t.cov[np.ix_(sel, sel)].copy()
    for p_, (sp, n_p, _) in enumerate(rows):
        for q_, (sq, n_q, _) in enumerate(rows):
            fq = freq.get(sp.id)
            if sp is sq and fq and n_p in fq["names"] and n_q in fq["names"]:
                cov[p_, q_] += fq["added_cov"][fq["names"].index(n_p), fq["names"].index(n_q)]
    estimate = {key: {"value": s_.value(n), "sigma": float(math.sqrt(cov[p_, p_]))}
                for p_, (s_, n, key) in enumerate(rows)}
    return estimate, cov


def _motion_explanation(expl: str, effect: str, sc: _Scan, where: dict, estimate: dict,
                        refit) -> str:
    """The finding's explanation: a shift's phi range (deg), size (mm) and duration (s), an
    oscillation's period (s) and amplitude (arcsec), or the scans of any other motion."""
    vals = {k.split("@")[0]: v["value"] for k, v in estimate.items()
            if k.endswith(f"@{sc.id}") or "@" not in k}
    span = ", ".join(s.id for s, _ in refit)
    if effect == "impulsive_shift":
        d = np.array([vals.get(n, 0.0) for n in SHIFT])
        ph = where.get("phi_deg", [0.0, 0.0])
        return (f"{expl}; cycle {sc.meta.cycle}, phi {ph[0]:.1f}-{ph[1]:.1f} deg, "
                f"{1e3 * np.linalg.norm(d):.2f} mm for {sc.window_s[1]:.2f} s")
    if effect == "oscillation":
        a = [vals.get(n, 0.0) for n in OSCILLATION]
        amp = max(math.hypot(a[0], a[1]), math.hypot(a[2], a[3]))
        return (f"{expl}; period {sc.period_s:.3f} s, amplitude {amp * 206264.8:.2f} "
                f"arcsec ({span})")
    return f"{expl} ({span})"


def _apply_motion(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint, c: _Candidate,
                  t: _Test, dz: np.ndarray, expl: str) -> dict[str, Any]:
    """Model a motion (per scan, with its window or period), refit the scans it concerns, and
    describe it: ``where``, ``estimate``, ``extra`` and the explanation."""
    _update_shared(spec, joint, dz)
    members = c.info.get("members") or [(c.scans[0], list(c.names), slice(0, len(c.names)))]
    refit, hints, first = _model_members(ctx, S, spec, joint, c, t, members)
    sc = first[0]
    extra: dict[str, Any] = {}
    where = _motion_where(ctx, spec, c, first, refit, extra)
    log.debug("%s one-step estimate %s", c.effect, hints)
    _refit_all(ctx, S, spec, only=[s for s, _ in refit], hints=hints, from_used=False,
               others=True)
    freq = _oscillation_period(ctx, spec, sc, refit, where) if c.effect == "oscillation" else {}
    estimate, cov = _motion_estimates(t, refit, members, freq)
    extra["covariance"] = cov.tolist()
    return {"where": where, "estimate": estimate, "extra": extra,
            "explanation": _motion_explanation(expl, c.effect, sc, where, estimate, refit)}
