"""The explanations of one step: every catalog test, the panel offsets, within-panel and
covariate structure, each with its Bonferroni-adjusted p-value, effect size and eligibility.

Units: effect sizes and rms drops in metres; p-values as natural logs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..physics._catalog import INSTRUMENT
from ._explain import _Candidate, _inseparable, _Joint, _log_sf, _Test, _want
from ._find import COVARIATES, _covariate_cv, _covariate_tests, _dish_test
from ._state import DiagnoseConfig, _Context, _num, _Scan, _Spec

#: practical effect size of an ``unexplained`` finding: the rms of its footprint must drop by
#: at least this fraction or this much (m)
UNEXPLAINED_MIN_DROP = 0.01
UNEXPLAINED_MIN_DROP_M = 1.0e-5


@dataclass
class _Option:
    """An eligible explanation of one step (catalog test or unexplained structure)."""

    kind: str  # "catalog" | "panel" | "dish" | "covariate"
    effect: str
    family: str
    log_p: float  # log of the Bonferroni-adjusted p-value
    T: float
    dof: int
    effect_m: float
    payload: Any
    eligible: bool = True
    reason: str = ""
    rms_drop_m: float | None = None  # practical effect of unexplained structure (footprint)
    rms_drop_fraction: float | None = None

    def row(self) -> dict:
        """A ``last_candidates`` row (statistic, log10 of the adjusted p-value, effect size
        and rms drop in m)."""
        return {"kind": self.kind, "effect": self.effect, "family": self.family,
                "statistic": _num(self.T), "dof": self.dof,
                "log10_p_adjusted": _num(self.log_p / math.log(10)),
                "effect_size_m": _num(self.effect_m), "eligible": self.eligible,
                **({"rms_drop_m": _num(self.rms_drop_m),
                    "rms_drop_fraction": _num(self.rms_drop_fraction)}
                   if self.rms_drop_m is not None else {}),
                "reason": self.reason,
                "scans": getattr(self.payload, "cand", None) and self.payload.cand.scans,
                **({"covariate": self.payload["covariate"]} if self.kind == "covariate" else {})}


def _static_confounded(start: Sequence[str], wanted) -> list[dict]:
    """Catalog parameters with the same shape as a model parameter (no test possible)."""
    out = []
    for k in INSTRUMENT:
        if k in start or (wanted is not None and k not in wanted):
            continue
        pairs = _inseparable(tuple(start) + (k,))
        if pairs:
            a, b, c = pairs[0]
            other = b if a == k else a
            out.append({"effect": k, "with": [other], "correlation": float(abs(c)),
                        "reason": "same correction shape (physics catalog)"})
    return out


def _option_key(o: _Option) -> tuple:
    """Identity of an option across steps (kind, effect, first scan, covariate): a refused
    option stays refused."""
    scans = tuple(o.payload.cand.scans) if o.kind == "catalog" else ()
    sub = o.payload.get("covariate") if o.kind == "covariate" else None
    return (o.kind, o.effect, scans[:1], sub)


def _raw_T(joint: _Joint, cand: _Candidate) -> float:
    """Statistic of a confounded candidate ignoring the confounding (for information)."""
    m = cand.H.T @ joint.n[cand.idx]
    Nj = cand.H.T @ joint.N[np.ix_(cand.idx, cand.idx)] @ cand.H
    return float(m @ np.linalg.pinv(Nj) @ m) / joint.sigma0**2


def _judge(o: _Option, cfg: DiagnoseConfig, footprint_rms_m: float) -> _Option:
    """Eligibility of one option: significant, large enough, and for structure without a
    physics signature a footprint whose rms drops by millimetres that matter (a significant
    but tiny structure is the panel pattern seen through a covariate, not a finding)."""
    if o.log_p >= math.log(cfg.alpha):
        o.eligible, o.reason = False, "not significant"
    elif o.effect_m < cfg.min_effect_m:
        o.eligible, o.reason = False, "below the practical effect size"
    elif o.effect == "unexplained":
        rms = footprint_rms_m
        drop = rms - math.sqrt(max(rms * rms - o.effect_m**2, 0.0))
        o.rms_drop_m, o.rms_drop_fraction = drop, drop / max(rms, 1e-300)
        if drop < UNEXPLAINED_MIN_DROP_M and drop / max(rms, 1e-300) < UNEXPLAINED_MIN_DROP:
            o.eligible = False
            o.reason = (f"below the practical effect size: the rms of its footprint drops by "
                        f"{drop * 1e6:.2f} um ({100 * drop / max(rms, 1e-300):.2f} %), "
                        f"needs {UNEXPLAINED_MIN_DROP_M * 1e6:.0f} um or "
                        f"{100 * UNEXPLAINED_MIN_DROP:.0f} %")
    return o


def _catalog_options(joint: _Joint, tests: Sequence[_Test], confounded: dict,
                     lm: float) -> list[_Option]:
    """Catalog tests; confounded instrument parameters go to ``confounded`` instead."""
    out = []
    for t in tests:
        c = t.cand
        if c.family == "instrument" and t.confounded:
            confounded.setdefault(c.effect, {
                "effect": c.effect, "with": t.with_, "correlation": t.correlation,
                "correlations": dict(zip(t.with_, t.corr_with)),
                "statistic": _num(t.T if t.T else _raw_T(joint, c)),
                "reason": "inseparable from the estimated parameters (augmented normal matrix)",
            })
            continue
        if t.dof == 0:
            continue
        lp = _log_sf(t.T, t.dof) + lm + math.log(c.penalty)
        out.append(_Option("catalog", c.effect, c.family, lp, t.T, t.dof, t.effect_m, t))
    return out


def _panel_option(joint: _Joint, lm: float) -> _Option:
    """Panel offsets: the drop of the joint statistic when they are estimated."""
    s0 = joint.sigma0
    T = (joint.omega0_raw - joint.omega0) / s0**2
    dof = joint.G_live - 1
    eff = math.sqrt(max(T - dof, 0.0) * s0**2 / joint.sum_q)
    return _Option("panel", "panel_offset", "reflector", _log_sf(T, dof) + lm, T, dof, eff, None)


def _dish_option(ctx: _Context, S: Sequence[_Scan], s0: float,
                 lm: float) -> tuple[_Option, float] | None:
    """Within-panel structure of the panels flagged one by one (Bonferroni over the panels),
    with the rms of its footprint; None when no panel is flagged."""
    la = math.log(ctx.config.alpha)
    Tg, dofg, est, cells = _dish_test(ctx, S, s0)
    G = ctx.n_panels
    flagged = [g for g in range(G) if dofg[g] > 0
               and _log_sf(Tg[g], dofg[g]) + math.log(G) + lm < la]
    if not flagged:
        return None
    T = float(np.sum(Tg[flagged]))
    dof = int(np.sum(dofg[flagged]))
    qf = sum(float(np.sum((1.0 / sc.m)[sc.used & np.isin(sc.panel, flagged)])) for sc in S)
    nf = sum(int(np.sum(sc.used & np.isin(sc.panel, flagged))) for sc in S)
    eff = math.sqrt(max(T - dof, 0.0) * s0**2 / max(qf, 1e-300))
    o = _Option("dish", "unexplained", "generic", _log_sf(T, dof) + lm, T, dof, eff,
                {"flagged": flagged, "est": est, "cells": cells, "Tg": Tg})
    return o, s0 * math.sqrt(nf / max(qf, 1e-300))


def _covariate_option(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint,
                      lm: float) -> _Option | None:
    """Structure following a covariate: the most significant one, or (when significant) the
    one that predicts held-out points best (correlated covariates share the structure)."""
    s0 = joint.sigma0
    la = math.log(ctx.config.alpha)
    ct = _covariate_tests(ctx, S, s0, skip=spec.modelled | spec.no_covariates)
    if not ct:
        return None
    cv = None
    name = min(ct, key=lambda k: _log_sf(ct[k]["T"], ct[k]["dof"]))
    if _log_sf(ct[name]["T"], ct[name]["dof"]) + lm + math.log(len(COVARIATES)) < la:
        cv = _covariate_cv(S, spec, only=set(ct))
        b = cv.get("best")
        if b and b["cv_explained"] > 0 and b["covariate"] in ct:
            name = b["covariate"]
    r = ct[name]
    eff = math.sqrt(max(r["T"] - r["dof"], 0.0) * s0**2 / joint.sum_q)
    return _Option("covariate", "unexplained", "generic",
                   _log_sf(r["T"], r["dof"]) + lm + math.log(len(COVARIATES)), r["T"],
                   r["dof"], eff, {"covariate": name, **r, "cv": cv,
                                   "all": {k: (v["T"], v["dof"]) for k, v in ct.items()}})


def _options(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint,
             tests: Sequence[_Test], confounded: dict, wanted) -> list[_Option]:
    """Every explanation of this step with its adjusted p-value, effect size and eligibility."""
    cfg = ctx.config
    do_unexp = _want(wanted, "unexplained")
    lm = math.log(len(tests) + 3)
    rms_all = joint.sigma0 * math.sqrt(joint.n_used / max(joint.sum_q, 1e-300))
    opts = [_judge(o, cfg, rms_all) for o in _catalog_options(joint, tests, confounded, lm)]
    if spec.panels is None and _want(wanted, "panel_offset") and joint.G_live > 1:
        opts.append(_judge(_panel_option(joint, lm), cfg, rms_all))
    if do_unexp and ctx.has_layout:  # within-panel structure needs real panels
        dish = _dish_option(ctx, S, joint.sigma0, lm)
        if dish is not None:
            opts.append(_judge(dish[0], cfg, dish[1] or rms_all))
    if do_unexp:
        o = _covariate_option(ctx, S, spec, joint, lm)
        if o is not None:
            opts.append(_judge(o, cfg, rms_all))
    return opts
