"""Discrepancy engine: compare recordings with the model, locate the mismatch, explain it with the
catalog, model it and show the fit improve (``hartrao-jax diagnose``).

The model is the simulator: with the fitted parameters, the condition ``F(l, x, c)`` of a
recorded point is the mismatch between the recording and the simulation of that point (zero for
a perfect simulation). It is reported in observation space (range-equivalent, ``F / (dF/dr)``)
and as surface deviation (``-F / sqrt(1 + rho^2/4f^2)``, m along the normal, positive towards
the focus).

One step of the loop (``physics.md``, "Statistics"):

1. *Locate.* Per scan, the mismatch is reduced to time bins (the scan's phi clock) by the
   derivatives of the condition with respect to a small scanner translation and rotation: a box
   search over windows (change points: impulsive shift) and a periodogram (oscillation) follow;
   binned structure along theta, range, incidence angle, intensity, dish radius, azimuth and time
   (per face) and within-panel structure on the dish (after panel planes) are measured.
2. *Explain.* One augmented model per scan holds every catalog parameter not yet in the model,
   free at value 0 (instrument parameters, the shift with the window found, the oscillation with
   the period found, drift, Zernike modes); :func:`~hartrao_jax.solver.normal_equations` gives its
   normal equations at the current solution, with one offset per panel (common to all scans)
   as nuisance. The scans' equations are summed into one joint system (separate object
   parameters per scan, instrument parameters shared by all scans, motion per scan, Zernike
   coefficients linear in gravity across positions) and the panel offsets are eliminated
   (Schur complement). For every candidate the score statistic, its one-step estimate, the
   predicted improvement in metres and its multiple correlation with the model follow from the
   partitioned system; candidates inseparable from the model are reported as ``confounded``.
3. *Decide.* Among the candidates that are significant (Bonferroni over the candidates and
   the windows/periods searched), large enough (``min_effect_m``, the predicted rms change of
   the fit, debiased by the degrees of freedom) and show their family's signature (instrument:
   one value explains every scan; motion: not the same deviation in the other cycle unless the
   same motion is there too), the one with the smallest adjusted p-value is accepted. Catalog
   explanations come first; unexplained structure (within-panel cells after one plane per
   panel, covariate bins after the panel planes) is taken before them only when it is far
   stronger.
4. *Model.* It is added to the functional model (instrument parameter shared by all scans;
   motion parameters of a scan with their window or period; panel offsets from the group
   elimination and an empirical map as known deviation ``c[1]``; Zernike coefficients linear in
   gravity; a cut of the affected time range), the panel offsets and shared parameters follow
   the joint step, and the scans are refitted. A finding must survive the refit: if sigma0
   does not drop, the state is restored and the candidate refused.

Units: metres, radians, seconds; ``_deg`` keys are degrees.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from ..campaign._campaign import (
    Campaign,
    ScanData,
    ScanMeta,
    load_campaign,
)
from ..model._model import (
    OSC_FREQUENCY,
    OSCILLATION,
    SHIFT,
    parameter_unit,
    parse_model,
)
from ..physics._catalog import EFFECTS, INSTRUMENT
from ._explain import (
    _Candidate,
    _candidates,
    _inseparable,
    _Joint,
    _local_candidates,
    _log_sf,
    _Test,
    _want,
)
from ._find import (
    COVARIATES,
    _covariate_cv,
    _covariate_tests,
    _covariate_values,
    _dish_test,
    _locate_time,
    _panel_cells,
    _panel_columns,
    _periodogram_points,
)
from ._local import local_step
from ._recording import capabilities, skipped_searches, two_face_parameters
from ._result import (
    Diagnosis,
)
from ._start import _start_scans
from ._state import (
    ZERNIKE_TESTED,
    DiagnoseConfig,
    Finding,
    _adjust,
    _Context,
    _evaluate,
    _fixed,
    _global_sigma0,
    _npad,
    _num,
    _pad,
    _panel_known,
    _refit,
    _refit_all,
    _restore,
    _rms,
    _save,
    _Scan,
    _scan_model,
    _set_known,
    _Spec,
)

log = logging.getLogger("hartrao_jax")






# ============================================================================================
# per-scan state
# ============================================================================================
















# --------------------------------------------------------------------------------------------
# fitting
# --------------------------------------------------------------------------------------------



















# ============================================================================================
# locate: time (change points, periodogram), covariates, dish
# ============================================================================================




























# ============================================================================================
# explain: augmented normal equations, joint system, tests
# ============================================================================================






















# ============================================================================================
# results
# ============================================================================================








# ============================================================================================
# statistics helpers
# ============================================================================================




# ============================================================================================
# modelling helpers
# ============================================================================================




def _estimate_panels(ctx: _Context, scans: Sequence[_Scan], spec: _Spec) -> dict[str, np.ndarray]:
    """Panel planes (offset m, radial and tangential tilt rad) common to all scans, by weighted
    least squares of the mismatch plus the currently modelled panel deviation."""
    G = ctx.n_panels
    M = np.zeros((G, 3, 3))
    u = np.zeros((G, 3))
    cnt = np.zeros(G)
    for sc in scans:
        ok = sc.used & (sc.m > 0) & (sc.panel >= 0)
        q = np.where(ok, 1.0 / np.where(sc.m > 0, sc.m, 1.0), 0.0) * sc.s_rho**2
        r = sc.mismatch_m + _panel_known(ctx, sc, spec.panels)  # the whole panel deviation
        P = _panel_columns(ctx, sc)
        pid = sc.panel[ok]
        cnt += np.bincount(pid, minlength=G)
        for a in range(3):
            u[:, a] += np.bincount(pid, (q * r * P[:, a])[ok], minlength=G)
            for b in range(3):
                M[:, a, b] += np.bincount(pid, (q * P[:, a] * P[:, b])[ok], minlength=G)
    sol = np.zeros((G, 3))
    for g in range(G):
        if cnt[g] >= 12:
            sol[g] = np.linalg.lstsq(M[g], u[g], rcond=1e-10)[0]
        elif cnt[g] > 0:
            sol[g, 0] = u[g, 0] / M[g, 0, 0]
    return {"offset": sol[:, 0], "tilt_r": sol[:, 1], "tilt_t": sol[:, 2], "n_points": cnt}




@eqx.filter_jit
def _columns(model, l, x, c, idx):
    """Per point derivatives of the condition w.r.t. the free parameters ``idx``."""

    def one(args):
        ll, cc = args
        return jax.grad(lambda xx: model(ll, xx, cc))(x)[idx]

    return jax.lax.map(one, (l, c), batch_size=8192)


def _signature(ctx: _Context, sc: _Scan, spec: _Spec, names: Sequence[str], values: np.ndarray,
               window_s=None, period_s=None) -> np.ndarray:
    """Predicted change of the condition of every point (m) by ``names = values``."""
    model = _scan_model(sc, spec, ctx.aperture, extra=list(names), window_s=window_s,
                        period_s=period_s)
    fixed = _fixed(sc, spec)
    prev = dict(zip(sc.names, sc.x))
    x = np.array([prev.get(k, fixed.get(k, 0.0)) for k in model.free])
    idx = np.array([model.free.index(n) for n in names])
    npad = _npad(len(sc.l))
    A = np.asarray(_columns(model, jnp.asarray(_pad(sc.l, npad)), jnp.asarray(x),
                            jnp.asarray(_pad(sc.consts(), npad)), jnp.asarray(idx)))[: len(sc.l)]
    return A @ np.asarray(values, float)


def _where_of_signature(ctx: _Context, sc: _Scan, sig: np.ndarray, motion: bool) -> dict:
    """Where a predicted signature lives: faces, phi range, panels, the covariate it follows."""
    u = sc.used
    dev = -sig / sc.s_rho
    out: dict[str, Any] = {}
    rms_face = {fc: float(np.sqrt(np.mean(dev[u & (sc.face == fc)] ** 2)))
                if np.any(u & (sc.face == fc)) else 0.0 for fc in (1, 2)}
    big = max(rms_face.values())
    faces = [fc for fc in (1, 2) if rms_face[fc] > 0.25 * big]
    if len(faces) == 1:
        out["face"] = faces[0]
    if motion:
        out["cycle"] = sc.meta.cycle
        amax = np.max(np.abs(dev[u])) if u.any() else 0.0
        hit = u & (np.abs(dev) > 0.3 * amax)
        if hit.any():
            ph = np.degrees(sc.data.phi_rad[hit])
            out["phi_deg"] = [float(ph.min()), float(ph.max())]
            pn, cnt = np.unique(sc.panel[hit & (sc.panel >= 0)], return_counts=True)
            out["panels"] = [int(p) for p in pn[np.argsort(-cnt)][:40]]
    # covariate: the one whose binned means (per face) explain most of the signature variance
    # left after the face means (the face flip of two-face effects is reported as face_split)
    vals = _covariate_values(sc)
    best, frac = None, -1.0
    fc = sc.face[u]
    d = dev[u].copy()
    tot0 = float(np.sum(d**2)) or 1.0
    for f in (1, 2):
        if np.any(fc == f):
            d[fc == f] -= d[fc == f].mean()
    out["face_split"] = float(1.0 - np.sum(d**2) / tot0)
    tot = float(np.sum(d**2)) or 1.0
    for name in COVARIATES:
        v = vals[name][u]
        expl = 0.0
        for f in (1, 2):
            s = fc == f
            if s.sum() < 64:
                continue
            qs = np.quantile(v[s], np.linspace(0, 1, 33)[1:-1])
            ids = np.searchsorted(qs, v[s], side="right")
            sums = np.bincount(ids, d[s], minlength=32)
            cnt = np.bincount(ids, minlength=32)
            expl += float(np.sum(sums[cnt > 0] ** 2 / cnt[cnt > 0]))
        if expl / tot > frac:
            best, frac = name, expl / tot
    if best is not None:
        out["covariate"] = best
    return out


def _extent(sc: _Scan) -> list[float]:
    """Square ``[x0, x1, y0, y1]`` (m, telescope frame) around the scan's points in the window."""
    w = sc.window & np.all(np.isfinite(sc.X_tel[:, :2]), 1)
    if not w.any():
        return [-1.0, 1.0, -1.0, 1.0]
    lo, hi = sc.X_tel[w, :2].min(0), sc.X_tel[w, :2].max(0)
    c, h = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) * 1.02 + 1e-3
    return [float(c[0] - h), float(c[0] + h), float(c[1] - h), float(c[1] + h)]


def _cells_not_panels(ctx: _Context, f: Finding) -> None:
    """Grid cells instead of panel ids for a telescope without a panel layout: centres (m)."""
    g = ctx.geo
    if "panels" in f.where:
        ids = f.where.pop("panels")
        f.where["cells"] = [{"cell": int(k), "x_m": float(g["rho_c"][k] * np.cos(g["psi_c"][k])),
                             "y_m": float(g["rho_c"][k] * np.sin(g["psi_c"][k]))} for k in ids]
        f.where["grid"] = ctx.layout_note
    if f.effect == "panel_offset":
        f.explanation = f.explanation.replace(" panels, offsets", " grid cells (no panel layout), "
                                              "offsets")
    for k in [k for k in f.estimate if k.startswith("panel_") and k.endswith("_offset_m")]:
        f.estimate[k.replace("panel_", "cell_", 1)] = f.estimate.pop(k)


def _dish_map(sc: _Scan, values: np.ndarray, n: int = 96):
    """Binned mean of ``values`` on an ``n x n`` grid of telescope X, Y over the scan's extent
    (for figures)."""
    u = sc.used & np.all(np.isfinite(sc.X_tel[:, :2]), 1)
    x0, x1, y0, y1 = _extent(sc)
    X, Y = sc.X_tel[u, 0], sc.X_tel[u, 1]
    i = np.clip(((X - x0) / (x1 - x0) * n).astype(int), 0, n - 1)
    j = np.clip(((Y - y0) / (y1 - y0) * n).astype(int), 0, n - 1)
    k = i * n + j
    s = np.bincount(k, values[u], minlength=n * n)
    c = np.bincount(k, minlength=n * n)
    out = np.full(n * n, np.nan)
    out[c > 0] = s[c > 0] / c[c > 0]
    return out.reshape(n, n)


def _snapshot(scans: Sequence[_Scan]) -> dict[str, np.ndarray]:
    return {sc.id: _dish_map(sc, sc.mismatch_m).astype(np.float32) for sc in scans}


def _compare(sc: _Scan) -> dict:
    """Recording minus simulation of one scan, summarised (m)."""
    u = sc.used
    d = sc.mismatch_m
    rr = sc.mismatch_range_m
    row = {"scan": sc.id, "position": sc.meta.position, "cycle": sc.meta.cycle,
           "n_points": int(u.sum()), "sigma0": _num(sc.sigma0),
           "rms_deviation_m": _num(np.sqrt(np.mean(d[u] ** 2))),
           "rms_range_m": _num(np.sqrt(np.mean(rr[u] ** 2))), "faces": {}}
    for fc in (1, 2):
        s = u & (sc.face == fc)
        if s.any():
            row["faces"][str(fc)] = {"n_points": int(s.sum()),
                                     "mean_deviation_m": _num(np.mean(d[s])),
                                     "rms_deviation_m": _num(np.sqrt(np.mean(d[s] ** 2)))}
    return row


# ============================================================================================
# the loop
# ============================================================================================


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


def diagnose(
    campaign: Campaign | str | Path,
    start: str | Iterable[str] = "extended",
    *,
    config: DiagnoseConfig | None = None,
    scans: Sequence[str] | None = None,
    keep: Callable[[ScanMeta, ScanData], np.ndarray] | None = None,
) -> Diagnosis:
    """Find, explain and model the mismatch between the recordings and the model.

    Figures and HTML: :func:`hartrao_jax.report.diagnose_with_report` (``report_dir``).

    Args:
        campaign: a campaign (or its directory).
        start: start model: ``"simplified"``, ``"extended"`` or parameter names.
        config: thresholds and search settings (:class:`DiagnoseConfig`).
        scans: scan ids to diagnose (default all: they are tested jointly).
        keep: optional ``keep(meta, data) -> bool mask`` of points to consider (preprocessing).

    Returns:
        a :class:`Diagnosis` (``to_json()``: schema ``hartrao-diagnosis/1``).
    """
    t_all = time.time()
    camp = campaign if isinstance(campaign, Campaign) else load_campaign(campaign)
    cfg = config or DiagnoseConfig()
    ctx = _Context(camp, cfg)
    start_names = parse_model(start)
    timing: dict[str, float] = {}
    wanted = set(cfg.effects) if cfg.effects else None
    notes: list[str] = []
    not_identifiable: list[dict] = []
    metas = [camp.scan(s) for s in scans] if scans else list(camp.scans)
    if any(m.cycle not in (1, 2) for m in metas):
        # one face: the two-face-sensitive calibration parameters are not identifiable
        tf = two_face_parameters()
        drop = [n for n in start_names if n in tf]
        if drop:
            start_names = tuple(n for n in start_names if n not in drop)
            notes.append(f"one-face recording: {', '.join(drop)} dropped from the start model "
                         "(two-face-sensitive calibration parameters are not identifiable from "
                         "one face)")
        not_identifiable = [
            {"parameter": k, "identifiable": False, "value": None, "sigma": None,
             "note": "two-face-sensitive calibration parameter: a one-face recording cannot "
                     "separate it from the pose and the reflector (it needs the second face)"}
            for k in tf if wanted is None or k in wanted]
    t0 = time.time()
    S = _start_scans(ctx, start_names, keep, scans)
    spec = _Spec(start=start_names)
    cap = capabilities([sc.meta for sc in S], [sc.data for sc in S])
    spec.times = cap.times
    spec.no_covariates = ({"time"} if not cap.times else set()) | (
        {"intensity"} if not cap.intensity else set())
    if not cap.two_faces:
        spec.skip |= set(two_face_parameters())
    skipped = skipped_searches(cap, wanted)
    if not ctx.has_layout:
        skipped.append({"search": "within-panel structure", "why": ctx.layout_note})
    if not ctx.has_layout:
        notes.append(ctx.layout_note)
    for sc in S:
        _evaluate(ctx, sc, spec)
    timing["start_fit"] = time.time() - t0
    sigma0_start, rms_start = _global_sigma0(S), _rms(S)
    comparison = [_compare(sc) for sc in S]
    confounded: dict[str, dict] = {c["effect"]: c for c in _static_confounded(start_names, wanted)}
    findings: list[Finding] = []
    history: list[dict] = [{"step": 0, "label": "start", "maps": _snapshot(S)}]
    last_rows: list[dict] = []
    local_search: list[dict] = []
    if _want(wanted, "local_deformation"):
        t_l = time.time()
        for f in local_step(ctx, S, spec, local_search, notes):
            findings.append(f)
            spec.accepted.append(f.effect)
            history.append({"step": len(history), "label": f.effect, "maps": _snapshot(S),
                            "scans": f.scans})
        timing["local_search"] = time.time() - t_l
    # which covariate carries the structure left after the start model (and any local
    # deformation), compared on held-out points: recorded whatever the loop then accepts
    cov_cmp = ({k: v for k, v in _covariate_cv(S, spec).items() if k != "all"}
               if _want(wanted, "unexplained") else {})
    t_loop = time.time()
    step_done = False
    joint, tests, options = None, [], []
    refused: set[tuple] = set()
    for step in range(1, cfg.max_steps + 1):
        ts = time.time()
        step_done = True
        if spec.times:
            for sc in S:
                _locate_time(sc, cfg)
        local = _local_candidates(ctx, S, spec)
        joint = _Joint(ctx, S, spec, local)
        cands = _candidates(joint, S, local)
        tests = [joint.test(c) for c in cands]
        options = _options(ctx, S, spec, joint, tests, confounded, wanted)
        spec.skip |= set(confounded)
        for o in options:
            if _option_key(o) in refused:
                o.eligible, o.reason = False, "did not survive the refit"
        best = None
        # structure no catalog entry explains comes after the catalog, unless it is far
        # stronger (twice the orders of magnitude): a catalog effect then explains only part
        # (never before the panel offsets: their maps are modelled on top of the panels)
        ok = [o for o in options if o.eligible]
        lp_cat = min((o.log_p for o in ok if o.kind in ("catalog", "panel")), default=0.0)
        panel_first = any(o.kind == "panel" for o in ok)
        tier = sorted(ok, key=lambda o: (o.kind != "panel" if panel_first else False,
                                         o.kind in ("dish", "covariate")
                                         and not o.log_p < 2.0 * lp_cat, o.log_p))
        for o in tier:
            why = _signature_check(ctx, S, spec, joint, o, options)
            if why:
                o.eligible, o.reason = False, why
                continue
            best = o
            break
        last_rows = [o.row() for o in sorted(options, key=lambda o: o.log_p)]
        log.info("step %d: %d candidates, best %s (%.1f s)", step, len(options),
                 best.effect if best else "none", time.time() - ts)
        if best is None:
            break
        before = (_global_sigma0(S), _rms(S))
        saved = _save(S, spec)
        alternatives = _alternatives(joint, best, options)
        f = _apply(ctx, S, spec, joint, best)
        if alternatives:
            f.extra["alternatives"] = alternatives
        after = (_global_sigma0(S), _rms(S))
        lost = any(st["converged"] and not sc.converged for sc, st in zip(S, saved[0]))
        if after[0] > before[0] * (1.0 + 1e-3) or lost:
            # a finding must survive the refit: undo, refuse, and look again
            log.info("refused %s: the refit did not improve the fit (sigma0 %.4f -> %.4f)",
                     best.effect, before[0], after[0])
            spec = _restore(S, saved)
            refused.add(_option_key(best))
            notes.append(f"{best.effect} ({', '.join(f.scans)}) was significant but did not "
                         f"survive the refit (sigma0 {before[0]:.4f} -> {after[0]:.4f})")
            continue
        f.sigma0_before, f.rms_before_m = before
        f.sigma0_after, f.rms_after_m = after
        f.statistic, f.dof = best.T, best.dof
        f.p_value = math.exp(max(_log_sf(best.T, best.dof), -745.0))
        f.extra["log10_p_adjusted"] = _num(best.log_p / math.log(10))
        f.effect_size_m = best.effect_m
        if best.rms_drop_m is not None:
            f.extra["practical_effect"] = {
                "rms_drop_m": _num(best.rms_drop_m),
                "rms_drop_fraction": _num(best.rms_drop_fraction),
                "rule": f"rms of the footprint drops by >= {100 * UNEXPLAINED_MIN_DROP:.0f} % "
                        f"or >= {UNEXPLAINED_MIN_DROP_M * 1e6:.0f} um"}
        findings.append(f)
        spec.accepted.append(f.effect)
        history.append({"step": step, "label": f.effect, "maps": _snapshot(S),
                        "evidence": f.extra.pop("_evidence", None), "scans": f.scans})
        log.info("accepted %s (%s): T=%.1f dof=%d, sigma0 %.3f -> %.3f, rms %.3f -> %.3f mm",
                 f.effect, ",".join(f.scans), best.T, best.dof, before[0], after[0],
                 1e3 * before[1], 1e3 * after[1])
    timing["loop"] = time.time() - t_loop
    if _want(wanted, "thermal"):
        th = _thermal(ctx, S, len(last_rows) + 1)
        if th is not None and th[0] == "finding":
            findings.append(th[1])
        elif th is not None:
            confounded.setdefault("thermal", th[1])
    detect = (_detectability(ctx, joint, tests, len(options), S if spec.times else ())
              if step_done else [])
    scans_final = {}
    for sc in S:
        cv = np.sqrt(np.maximum(np.diag(sc.cov), 0.0)) if sc.cov.size else np.zeros(0)
        scans_final[sc.id] = {
            "model": list(sc.names),
            "estimates": {n: {"value": float(sc.x[i]), "sigma": float(cv[i])}
                          for i, n in enumerate(sc.names)},
            "sigma0": _num(sc.sigma0), "n_points": int(sc.used.sum()),
            "converged": sc.converged,
            "cut_points": int(sc.cut.sum()),
        }
    if spec.shared:
        notes.append("instrument parameters found are shared by all scans (joint estimate): "
                     + ", ".join(f"{k}={v:.4g}" for k, v in spec.shared.items()))
    timing["total"] = time.time() - t_all
    diag = Diagnosis(
        campaign=str(camp.root), start_model=list(start_names), final_model=spec.names(),
        sigma0_start=sigma0_start, sigma0_final=_global_sigma0(S), rms_start_m=rms_start,
        rms_final_m=_rms(S), findings=findings, confounded=list(confounded.values()),
        comparison=comparison, candidates=last_rows, timing_s=timing, notes=notes,
        scans_final=scans_final, history=history, detectability=detect, skipped=skipped,
        not_identifiable=not_identifiable, local_search=local_search, layout=ctx.layout_note,
        extents={sc.id: _extent(sc) for sc in S},
        covariates=cov_cmp,
    )
    if not ctx.has_layout:
        for f in findings:
            _cells_not_panels(ctx, f)
    return diag








def _option_key(o: _Option) -> tuple:
    scans = tuple(o.payload.cand.scans) if o.kind == "catalog" else ()
    sub = o.payload.get("covariate") if o.kind == "covariate" else None
    return (o.kind, o.effect, scans[:1], sub)


def _options(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint,
             tests: Sequence[_Test], confounded: dict, wanted) -> list[_Option]:
    """Every explanation of this step with its adjusted p-value, effect size and eligibility."""
    cfg = ctx.config
    s0 = joint.sigma0
    do_unexp = _want(wanted, "unexplained")
    m_tests = len(tests) + 3
    la = math.log(cfg.alpha)
    lm = math.log(m_tests)
    opts: list[_Option] = []

    rms_all = s0 * math.sqrt(joint.n_used / max(joint.sum_q, 1e-300))

    def add(o: _Option, footprint_rms_m: float | None = None):
        if o.log_p >= la:
            o.eligible, o.reason = False, "not significant"
        elif o.effect_m < cfg.min_effect_m:
            o.eligible, o.reason = False, "below the practical effect size"
        elif o.effect == "unexplained":
            # structure with no physics signature must matter in millimetres: the rms of its
            # own footprint must drop by >= 1 % or >= 10 micrometres (a significant but tiny
            # structure is the panel pattern seen through a covariate, not a finding)
            rms = footprint_rms_m or rms_all
            drop = rms - math.sqrt(max(rms * rms - o.effect_m**2, 0.0))
            o.rms_drop_m, o.rms_drop_fraction = drop, drop / max(rms, 1e-300)
            if drop < UNEXPLAINED_MIN_DROP_M and drop / max(rms, 1e-300) < UNEXPLAINED_MIN_DROP:
                o.eligible = False
                o.reason = (f"below the practical effect size: the rms of its footprint drops by "
                            f"{drop * 1e6:.2f} um ({100 * drop / max(rms, 1e-300):.2f} %), "
                            f"needs {UNEXPLAINED_MIN_DROP_M * 1e6:.0f} um or "
                            f"{100 * UNEXPLAINED_MIN_DROP:.0f} %")
        opts.append(o)

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
        add(_Option("catalog", c.effect, c.family, lp, t.T, t.dof, t.effect_m, t))
    if spec.panels is None and _want(wanted, "panel_offset") and joint.G_live > 1:
        T = (joint.omega0_raw - joint.omega0) / s0**2
        dof = joint.G_live - 1
        eff = math.sqrt(max(T - dof, 0.0) * s0**2 / joint.sum_q)
        add(_Option("panel", "panel_offset", "reflector", _log_sf(T, dof) + lm, T, dof, eff,
                    None))
    if do_unexp and ctx.has_layout:  # within-panel structure needs real panels
        Tg, dofg, est, cells = _dish_test(ctx, S, s0)
        G = ctx.n_panels
        flagged = [g for g in range(G) if dofg[g] > 0
                   and _log_sf(Tg[g], dofg[g]) + math.log(G) + lm < la]
    else:
        flagged = []
    if flagged:
        T = float(np.sum(Tg[flagged]))
        dof = int(np.sum(dofg[flagged]))
        qf = sum(float(np.sum((1.0 / sc.m)[sc.used & np.isin(sc.panel, flagged)])) for sc in S)
        nf = sum(int(np.sum(sc.used & np.isin(sc.panel, flagged))) for sc in S)
        eff = math.sqrt(max(T - dof, 0.0) * s0**2 / max(qf, 1e-300))
        add(_Option("dish", "unexplained", "generic", _log_sf(T, dof) + lm, T, dof, eff,
                    {"flagged": flagged, "est": est, "cells": cells, "Tg": Tg}),
            footprint_rms_m=s0 * math.sqrt(nf / max(qf, 1e-300)))
    if do_unexp:
        ct = _covariate_tests(ctx, S, s0, skip=spec.modelled | spec.no_covariates)
        cv = None
        if ct:
            name = min(ct, key=lambda k: _log_sf(ct[k]["T"], ct[k]["dof"]))
            if _log_sf(ct[name]["T"], ct[name]["dof"]) + lm + math.log(len(COVARIATES)) < la:
                # correlated covariates share the structure: the one that carries it is the
                # one that predicts held-out points best (bins or a period)
                cv = _covariate_cv(S, spec, only=set(ct))
                b = cv.get("best")
                if b and b["cv_explained"] > 0 and b["covariate"] in ct:
                    name = b["covariate"]
            r = ct[name]
            eff = math.sqrt(max(r["T"] - r["dof"], 0.0) * s0**2 / joint.sum_q)
            add(_Option("covariate", "unexplained", "generic",
                        _log_sf(r["T"], r["dof"]) + lm + math.log(len(COVARIATES)), r["T"],
                        r["dof"], eff, {"covariate": name, **r, "cv": cv,
                                        "all": {k: (v["T"], v["dof"]) for k, v in ct.items()}}))
    return opts


#: practical effect size of an ``unexplained`` finding: the rms of its footprint must drop by
#: at least this fraction or this much (m)
UNEXPLAINED_MIN_DROP = 0.01
UNEXPLAINED_MIN_DROP_M = 1.0e-5

THERMAL_REFERENCE_C = 15.0
THERMAL_MIN_POSITIONS = 10  # with 7 the temperature term took up 0.4 mm/K of pointing effects


def _thermal(ctx: _Context, S: Sequence[_Scan], m_tests: int):
    """Focal length against temperature across the scans (catalog effect ``thermal``).

    The focal length is estimated per scan, so a thermal change of f leaves no mismatch in the
    points: it shows in the scans' focal lengths. They are regressed (weights ``1/sigma_f^2``)
    on a constant, the gravity vector (when the positions span it, so that a gravity change of
    f is not taken for a thermal one: at least :data:`THERMAL_MIN_POSITIONS` positions then)
    and ``T - 15 C``; the statistic of the
    temperature term is scaled by the variance factor of the regression (scatter of f beyond
    its formal sigma, e.g. from unmodelled surface modes). Returns ``("finding", Finding)``,
    ``("confounded", dict)`` when temperature and gravity cannot be told apart (fewer
    positions), or None (too few scans or temperatures, not significant).
    """
    from scipy import stats as st

    rows = [sc for sc in S if sc.meta.temperature_c is not None and "f" in sc.names
            and sc.converged]
    if len(rows) < 4:
        return None
    T = np.array([sc.meta.temperature_c for sc in rows], float) - THERMAL_REFERENCE_C
    if np.ptp(T) < 1.0:
        return None
    j = [sc.names.index("f") for sc in rows]
    f = np.array([sc.x[k] for sc, k in zip(rows, j)])
    sf = np.array([math.sqrt(max(sc.cov[k, k], 0.0)) for sc, k in zip(rows, j)])
    if np.any(sf <= 0):
        return None
    G = np.array([sc.g for sc in rows], float)
    n_pos = len({sc.meta.position for sc in rows})
    with_g = float(np.ptp(G, axis=0).max()) > 0.05
    if with_g and n_pos < THERMAL_MIN_POSITIONS:
        # f also follows the pointing (gravity, and surface modes the fit of f takes up):
        # with few positions a temperature drift over the night is indistinguishable from it
        r = max(abs(float(np.corrcoef(T, G[:, a])[0, 1])) for a in range(3)
                if np.ptp(G[:, a]) > 1e-6)
        return "confounded", {"effect": "thermal", "with": ["gravity"], "correlation": r,
                              "reason": f"{n_pos} positions: f against temperature needs at "
                                        f"least {THERMAL_MIN_POSITIONS} to be told apart from "
                                        f"f against gravity"}
    base = [np.ones(len(rows))] + ([G[:, a] for a in range(3)] if with_g else [])
    w = 1.0 / sf**2

    def wls(cols):
        X = np.column_stack(cols)
        N = X.T @ (X * w[:, None])
        c = np.linalg.solve(N, X.T @ (w * f))
        r = f - X @ c
        return c, np.linalg.inv(N), float(np.sum(w * r * r)), r

    p1 = len(base) + 1
    dof = len(rows) - p1
    if dof < 1:
        return None
    _, _, chi0, r0 = wls(base)
    c1, Q1, chi1, r1 = wls(base + [T])
    vf = max(1.0, chi1 / dof)
    stat = (chi0 - chi1) / vf
    p = float(st.chi2.sf(stat, 1))
    b, sb = float(c1[-1]), float(math.sqrt(Q1[-1, -1] * vf))
    size = abs(b) * float(np.ptp(T))
    cfg = ctx.config
    log.info("thermal: df/dT %.4f +- %.4f mm/K over %.1f K, statistic %.1f (variance factor "
             "%.2f, %d scans, gravity terms %s)", 1e3 * b, 1e3 * sb, np.ptp(T), stat, vf,
             len(rows), with_g)
    if not (p * max(m_tests, 1) < cfg.alpha and size > cfg.min_effect_m):
        return None
    s0 = _global_sigma0(S)
    rms = _rms(S)
    rms_f = (float(np.sqrt(np.mean(r0**2))), float(np.sqrt(np.mean(r1**2))))
    expl = (f"{EFFECTS['thermal'].explanation}; "
            f"df/dT = {1e3 * b:.3f} ± {1e3 * sb:.3f} mm/K over {np.ptp(T):.1f} K "
            f"({len(rows)} scans, {n_pos} positions{', gravity terms estimated' if with_g else ''})"
            f"; the points' fit is unchanged (f is estimated per scan): the focal lengths "
            f"scatter {1e3 * rms_f[0]:.3f} -> {1e3 * rms_f[1]:.3f} mm about the model")
    return "finding", Finding(
        "thermal", "reflector", [sc.id for sc in rows],
        {"covariate": "temperature", "temperature_c": [float(T.min() + THERMAL_REFERENCE_C),
                                                       float(T.max() + THERMAL_REFERENCE_C)],
         "positions": sorted({sc.meta.position for sc in rows})},
        {"df_dT_m_per_K": {"value": b, "sigma": sb}}, stat, 1, p, s0, s0, rms, rms, expl,
        effect_size_m=size,
        extra={"reference_c": THERMAL_REFERENCE_C, "gravity_terms": with_g,
               "variance_factor": vf, "focal_rms_before_m": rms_f[0],
               "focal_rms_after_m": rms_f[1]})


def _detectability(ctx: _Context, joint: _Joint, tests: Sequence[_Test],
                   m_tests: int, S: Sequence[_Scan] = ()) -> list[dict]:
    """Minimal detectable amplitude of every candidate at the final solution (Baarda).

    The noncentrality ``lam`` gives 80 % power at the Bonferroni-adjusted level of a step; the
    amplitude of parameter j alone is ``sigma0 sqrt(lam / S_jj)`` (S: the Schur complement of
    the candidate with the model and the panel offsets eliminated), or what reaches
    ``min_effect_m``, whichever is larger. ``rms_effect_m`` is the rms change of the points'
    condition at that amplitude before the model absorbs part of it;
    ``relative_to_range_noise`` divides it by ``sigma_range_m``.
    """
    from scipy import optimize

    cfg = ctx.config
    out = []
    s0 = joint.sigma0
    sq = joint.sum_q
    for t in tests:
        if t.S is None or t.dof == 0 or t.confounded or t.cand.effect == "impulsive_shift":
            continue
        q = t.dof
        a = cfg.alpha / max(m_tests, 1) / t.cand.penalty
        crit = stats.chi2.isf(a, q)
        lam = optimize.brentq(lambda L: stats.ncx2.sf(crit, q, L) - 0.8, 1e-6, 1e6)
        for j, name in enumerate(t.cand.names):
            if t.S[j, j] <= 0:
                continue
            # a bias of this parameter alone: noncentrality d^2 S_jj / sigma0^2
            mdb_stat = s0 * math.sqrt(lam / t.S[j, j])
            mdb_eff = cfg.min_effect_m * math.sqrt(sq / t.S[j, j])
            mdb = max(mdb_stat, mdb_eff)
            raw = mdb * math.sqrt(max(t.Draw[j, j], 0.0) / sq)
            out.append({"effect": t.cand.effect, "parameter": name, "scans": t.cand.scans,
                        "minimal_detectable": mdb,
                        "limited_by": "statistic" if mdb_stat >= mdb_eff else "effect_size",
                        "rms_effect_m": raw,
                        "relative_to_range_noise": raw / float(ctx.sigma[0]),
                        "correlation_with_model": t.correlation})
    # an impulsive shift: for a reference window (the middle 5 % of the first scan's time),
    # from the translation derivatives of the points (the windows found in noise are arbitrary)
    for sc in S[:1]:
        u = sc.used & (sc.m > 0)
        t_ = sc.data.time_s[u]
        a = sc.probe[u][:, :3]
        q_ = 1.0 / sc.m[u]
        lo, hi = np.quantile(t_, [0.475, 0.525])
        w = (t_ >= lo) & (t_ < hi)
        Ntot = (a * q_[:, None]).T @ a
        NW = (a[w] * q_[w, None]).T @ a[w]
        SW = NW - NW @ np.linalg.pinv(Ntot) @ NW
        pen = float(sc.search.get("n_windows", 1))
        crit = stats.chi2.isf(cfg.alpha / max(m_tests, 1) / pen, 3)
        lam = optimize.brentq(lambda L: stats.ncx2.sf(crit, 3, L) - 0.8, 1e-6, 1e6)
        for j, name in enumerate(SHIFT):
            mdb_stat = s0 * math.sqrt(lam / max(SW[j, j], 1e-300))
            mdb_eff = cfg.min_effect_m * math.sqrt(sq / max(SW[j, j], 1e-300))
            mdb = max(mdb_stat, mdb_eff)
            raw = mdb * math.sqrt(NW[j, j] / float(np.sum(q_[w])))  # rms inside the window
            out.append({"effect": "impulsive_shift", "parameter": name, "scans": [sc.id],
                        "minimal_detectable": mdb,
                        "limited_by": "statistic" if mdb_stat >= mdb_eff else "effect_size",
                        "rms_effect_m": raw, "relative_to_range_noise": raw / float(ctx.sigma[0]),
                        "window": "middle 5 % of the scan (rms effect inside the window)",
                        "correlation_with_model": None})
    return out


def _raw_T(joint: _Joint, cand: _Candidate) -> float:
    """Statistic of a confounded candidate ignoring the confounding (for information)."""
    m = cand.H.T @ joint.n[cand.idx]
    Nj = cand.H.T @ joint.N[np.ix_(cand.idx, cand.idx)] @ cand.H
    return float(m @ np.linalg.pinv(Nj) @ m) / joint.sigma0**2


def _signature_check(ctx, S, spec, joint, o: _Option, options: Sequence[_Option] = ()) -> str:
    """The family's physics signature; returns a reason to refuse, or ``""``."""
    cfg = ctx.config
    if o.kind == "catalog" and o.family == "instrument":
        t: _Test = o.payload
        Td, dd = joint.scan_difference(t.cand, t)
        t.T_diff, t.dof_diff = Td, dd
        if dd > 0 and _log_sf(Td, dd) < math.log(cfg.alpha) and Td > cfg.scan_consistency * t.T:
            return (f"not one instrument constant: freeing it per scan adds T={Td:.0f} "
                    f"({dd} dof) to T={t.T:.0f}")
        return ""
    if o.kind == "catalog" and o.family == "motion":
        t = o.payload
        sc = next(s for s in S if s.id == t.cand.scans[0])
        names = t.cand.names
        sig = _signature(ctx, sc, spec, names, t.estimate, window_s=sc.window_s,
                         period_s=sc.period_s)
        t.notes.append("signature")
        o.payload.cand.info["signature"] = sig
        others = [s for s in S if s.meta.position == sc.meta.position and s.id != sc.id]
        if not others:
            return ""
        slope, z = _common_slope(ctx, sc, others, sig / sc.s_rho)
        o.payload.cand.info["common_slope"] = (slope, z)
        # the two cycles see a dish point at the same time of their scans: the same motion in
        # both (a significant candidate there too) shows the same pattern in both
        twin = [x for x in options if x is not o and x.kind == "catalog" and x.effect == o.effect
                and x.log_p < math.log(cfg.alpha)
                and set(x.payload.cand.scans) & {s.id for s in others}
                and _same_motion(o.effect, sc, next(s for s in others
                                                   if s.id == x.payload.cand.scans[0]))]
        if twin:  # modelled together (one step), see _apply
            best = {}
            for x in sorted(twin, key=lambda x: x.log_p):
                best.setdefault(x.payload.cand.scans[0], x)
            o.payload.cand.info["twins"] = list(best.values())
            return ""
        if slope > cfg.common_slope and z > 4.0:
            return (f"the other cycle shows the same deviation in the same dish cells "
                    f"(slope {slope:.2f}, z {z:.1f}): a reflector effect, not motion")
    return ""


def _alternatives(joint: _Joint, best: _Option, options: Sequence[_Option]) -> list[dict]:
    """Other significant candidates of the same family that the data hardly tell apart from
    the accepted one (|correlation of the estimates| > 0.9): the choice between them rests on
    a small difference of their statistics."""
    if best.kind != "catalog" or best.family != "instrument":
        return []
    cb = best.payload.cand
    out = []
    for o in options:
        if o is best or o.kind != "catalog" or o.family != "instrument" or not o.log_p < 0:
            continue
        c = o.payload.cand
        pair = _Candidate("pair", "instrument", np.concatenate([cb.idx, c.idx]),
                          np.kron(np.eye(2), np.ones((len(cb.idx), 1))), [cb.effect, c.effect],
                          cb.scans)
        t = joint.test(pair)
        if t.cov is None or t.dof < 2:
            continue
        r = t.cov[0, 1] / math.sqrt(max(t.cov[0, 0] * t.cov[1, 1], 1e-300))
        if abs(r) > 0.9:
            out.append({"effect": c.effect, "statistic": _num(o.T),
                        "correlation": float(r), "joint_statistic": _num(t.T)})
    return out


def _same_motion(effect: str, a: _Scan, b: _Scan) -> bool:
    """The same motion in two cycles: overlapping windows, or periods within 5 %."""
    if effect == "impulsive_shift":
        (s0, d0), (s1, d1) = a.window_s, b.window_s
        inter = max(0.0, min(s0 + d0, s1 + d1) - max(s0, s1))
        return inter > 0.5 * max(d0, d1)
    if effect == "oscillation":
        return abs(a.period_s / b.period_s - 1.0) < 0.05
    return True


def _common_slope(ctx, sc: _Scan, others: Sequence[_Scan], pred: np.ndarray):
    """Regression slope of the other scans' mismatch on the predicted deviation, per dish cell."""
    cell = _panel_cells(ctx, sc)
    u = sc.used & (cell >= 0)
    nc = ctx.n_panels * ctx.config.panel_cells[0] * ctx.config.panel_cells[1]
    cnt = np.bincount(cell[u], minlength=nc)
    p = np.bincount(cell[u], pred[u], minlength=nc) / np.maximum(cnt, 1)
    pmax = np.max(np.abs(p)) if len(p) else 0.0
    hot = (cnt > 0) & (np.abs(p) > 0.5 * pmax)
    so = np.zeros(nc)
    co = np.zeros(nc)
    ss = 0.0
    n = 0
    for o in others:
        c2 = _panel_cells(ctx, o)
        u2 = o.used & (c2 >= 0)
        so += np.bincount(c2[u2], o.mismatch_m[u2], minlength=nc)
        co += np.bincount(c2[u2], minlength=nc)
        ss += float(np.sum(o.mismatch_m[u2] ** 2))
        n += int(u2.sum())
    hot &= co > 0
    if hot.sum() < 3 or pmax == 0:
        return 0.0, 0.0
    om = so[hot] / co[hot]
    w = co[hot]
    pp = p[hot]
    slope = float(np.sum(w * pp * om) / np.sum(w * pp * pp))
    s2 = ss / max(n, 1)  # per-point variance of the other scans' mismatch
    se = math.sqrt(s2 / float(np.sum(w * pp * pp)))
    return slope, slope / se


def _joint_step(joint: _Joint, t: _Test | None):
    """Joint increments of the null unknowns with (optionally) a candidate at its estimate
    (placed in its own slots, so that :meth:`_Joint.panel_step` sees it too)."""
    n0 = joint.n[joint.I0].copy()
    dz = np.zeros(joint.D)
    if t is not None:
        c = t.cand
        dz[c.idx] = c.H @ t.estimate
        n0 = n0 + joint.N[np.ix_(joint.I0, c.idx)] @ dz[c.idx]
    dz[joint.I0] = -joint.K_inv @ n0
    return dz


def _update_panels(spec: _Spec, joint: _Joint, dz: np.ndarray) -> None:
    """Panel offsets of the joint solution (group elimination), fed back as known deviation."""
    if spec.panels is not None:
        spec.panels["offset"] = _panel_datum(joint, spec.panels["offset"] + joint.panel_step(dz))


def _panel_datum(joint: _Joint, off: np.ndarray) -> np.ndarray:
    """Offsets without the part a paraboloid absorbs (``a + b rho^2`` over the panel centres):
    the focal length and the vertex stay those of the best-fit paraboloid."""
    w = joint.group_count
    rc = joint.ctx.geo["rho_c"]
    A = np.column_stack([np.ones_like(rc), rc**2])
    live = w > 0
    beta = np.linalg.lstsq(A[live] * np.sqrt(w[live, None]), off[live] * np.sqrt(w[live]),
                           rcond=None)[0]
    return np.where(live, off - A @ beta, 0.0)


def _update_shared(spec: _Spec, joint: _Joint, dz: np.ndarray) -> None:
    for i, k in enumerate(joint.shared_names):
        spec.shared[k] += float(dz[joint.sidx[i]])
    if spec.zern_C is not None:
        base = len(joint.shared_names)
        d = dz[joint.sidx[base: base + 3 * len(ZERNIKE_TESTED)]].reshape(len(ZERNIKE_TESTED), 3)
        spec.zern_C = spec.zern_C + d




def _refine_periods(ctx: _Context, spec: _Spec, refit) -> None:
    """Period of a modelled oscillation from the periodogram of the misclosures without it,
    now that the panel offsets no longer hold part of it; refit when it moved."""
    for sc, names in refit:
        mot = spec.motion[sc.id]
        vals = np.array([sc.value(n) for n in names])
        sig = _signature(ctx, sc, spec, names, vals)
        f0 = 1.0 / mot["period_s"]
        fz = f0 * (1.0 + np.linspace(-0.01, 0.01, 41))
        Pz = _periodogram_points(sc, fz, sc.F - sig)
        j = int(np.argmax(Pz))
        fbest = fz[j]
        if 0 < j < len(Pz) - 1:
            den = Pz[j - 1] - 2 * Pz[j] + Pz[j + 1]
            if den < 0:
                fbest = fz[j] + 0.5 * (Pz[j - 1] - Pz[j + 1]) / den * (fz[1] - fz[0])
        if abs(fbest / f0 - 1.0) > 2e-4:
            log.debug("period of %s refined: %.5f -> %.5f s", sc.id, 1 / f0, 1 / fbest)
            mot["period_s"] = sc.period_s = float(1.0 / fbest)
            _set_known(ctx, sc, spec)
            _refit(ctx, sc, spec, from_used=True)


def _free_frequency(ctx: _Context, spec: _Spec, refit) -> dict[str, dict]:
    """Estimate the oscillation frequency with the amplitudes (one more GH adjustment per scan).

    The amplitudes of a fixed period are conditional on it: a period off by 0.1 % turns the
    phase by 0.07 rad over an 11 s scan, many sigma of the amplitudes. With the frequency
    correction ``osc_df_hz`` free the period is corrected and the amplitude covariance grows
    by ``C_free - C_fixed`` (the part the period's uncertainty adds); the scan is then refitted
    at the corrected period. Returns per scan id the added covariance over its oscillation
    names, the period and its sigma (s).
    """
    out = {}
    for sc, names in refit:
        mot = spec.motion[sc.id]
        osc = [n for n in names if n in OSCILLATION]
        if not osc:
            continue
        model = _scan_model(sc, spec, ctx.aperture, extra=(OSC_FREQUENCY,))
        x0 = np.array([sc.value(n) if n in sc.names else 0.0 for n in model.free])
        w = (sc.used & ~sc.cut).astype(float)
        res = _adjust(ctx, model, sc.l, x0, sc.consts(), w)
        free = list(model.free)
        j = free.index(OSC_FREQUENCY)
        C = np.asarray(res.cov)
        if not res.converged or not np.isfinite(C[j, j]) or C[j, j] <= 0:
            continue
        f0 = 1.0 / mot["period_s"]
        df = float(res.x[j])
        a = [free.index(n) for n in osc]
        b = [sc.names.index(n) for n in osc]
        D = C[np.ix_(a, a)] - sc.cov[np.ix_(b, b)]
        w_, V = np.linalg.eigh(0.5 * (D + D.T))
        D = (V * np.maximum(w_, 0.0)) @ V.T
        period = 1.0 / (f0 + df)
        mot["period_s"] = sc.period_s = float(period)
        _refit(ctx, sc, spec, from_used=True)
        out[sc.id] = {"names": osc, "added_cov": D, "period_s": float(period),
                      "period_sigma_s": float(math.sqrt(C[j, j]) * period**2)}
    return out


def _apply(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint, o: _Option) -> Finding:
    """Model the accepted explanation, refit, and describe it as a finding."""
    eff = EFFECTS.get(o.effect)
    expl = eff.explanation if eff else o.effect
    fam = o.family
    where: dict[str, Any] = {}
    estimate: dict[str, dict[str, float]] = {}
    scans = [sc.id for sc in S]
    extra: dict[str, Any] = {}
    if o.kind == "catalog":
        t: _Test = o.payload
        c = t.cand
        if fam == "motion" and c.info.get("twins"):
            # the same motion in the other cycle(s) of the position: one joint step
            members, idx, names = [], [], []
            for cc in [c] + [tw.payload.cand for tw in c.info["twins"]]:
                members.append((cc.scans[0], list(cc.names),
                                slice(len(names), len(names) + len(cc.names))))
                idx.append(cc.idx)
                names += [f"{n}@{cc.scans[0]}" for n in cc.names]
            comb = _Candidate(c.effect, fam, np.concatenate(idx), np.eye(len(names)), names,
                              [m[0] for m in members], penalty=c.penalty,
                              info={**c.info, "members": members})
            tc = joint.test(comb)
            # a twin must add significantly to the first scan's own explanation (the panel
            # offsets shared by the cycles make a ghost of one scan's motion in the other)
            dT, dd = tc.T - t.T, tc.dof - t.dof
            lm = math.log(max(2, len(members)))
            if dd > 0 and _log_sf(dT, dd) + lm + math.log(c.penalty) < math.log(ctx.config.alpha):
                c, t = comb, tc
                o.T, o.dof = t.T, t.dof
            else:
                c.info["twin_rejected"] = {"statistic": dT, "dof": dd}
        scans = list(c.scans)
        dz = _joint_step(joint, t)
        _update_panels(spec, joint, dz)
        if fam == "instrument":
            k = c.names[0]
            _update_shared(spec, joint, dz)
            spec.shared[k] = float(t.estimate[0])
            spec.shared_sigma[k] = float(t.sigma[0])
            estimate[k] = {"value": float(t.estimate[0]), "sigma": float(t.sigma[0])}
            sig0 = _signature(ctx, S[0], spec, [k], t.estimate[:1] * 0 + 1.0)
            where = {k2: v for k2, v in _where_of_signature(ctx, S[0], sig0, False).items()
                     if k2 in ("covariate", "face_split")}
            extra["scan_difference"] = {"statistic": _num(t.T_diff), "dof": t.dof_diff}
            _refit_all(ctx, S, spec)
            expl = (f"{expl}; {k} = {_fmt(k, t.estimate[0], t.sigma[0])}, one value for all "
                    f"scans")
        elif fam == "motion":
            _update_shared(spec, joint, dz)
            members = c.info.get("members") or [(c.scans[0], list(c.names), slice(0, len(c.names)))]
            multi = len(members) > 1
            refit, hints, first = [], {}, None
            for sid, mnames, sl in members:
                sc = next(s for s in S if s.id == sid)
                first = first or (sc, mnames, t.estimate[sl])
                # parameters individually separable from the model (drift has confounded ones)
                names = [n for n in mnames if joint.test(_Candidate(
                    c.effect, fam, np.array([joint.cidx[(sid, n)]]), np.ones((1, 1)), [n],
                    [sid])).correlation < ctx.config.confounded_correlation]
                mot = spec.motion.setdefault(sid, {"names": []})
                mot["names"] = list(mot["names"]) + names
                if c.effect == "impulsive_shift":
                    mot["window_s"] = sc.window_s
                if c.effect == "oscillation":
                    mot["period_s"] = sc.period_s
                hints[sid] = {n: float(v) for n, v in zip(mnames, t.estimate[sl]) if n in names}
                refit.append((sc, names))
            sc, mnames, est0 = first
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
            log.debug("%s one-step estimate %s", c.effect, hints)
            _refit_all(ctx, S, spec, only=[s for s, _ in refit], hints=hints, from_used=False,
                       others=True)
            freq: dict[str, dict] = {}
            if c.effect == "oscillation":
                _refine_periods(ctx, spec, refit)
                freq = _free_frequency(ctx, spec, refit)
                where["period_s"] = spec.motion[sc.id]["period_s"]
                if sc.id in freq:
                    where["period_sigma_s"] = freq[sc.id]["period_sigma_s"]
                if multi:
                    where["period_s_by_scan"] = {s.id: spec.motion[s.id]["period_s"]
                                                 for s, _ in refit}
            # values from the refit; covariance from the joint system (the panel offsets,
            # estimated from the same points, are eliminated there, not held fixed)
            # (an oscillation: plus what the uncertainty of its period adds)
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
                        cov[p_, q_] += fq["added_cov"][fq["names"].index(n_p),
                                                       fq["names"].index(n_q)]
            for p_, (s_, n, key) in enumerate(rows):
                estimate[key] = {"value": s_.value(n), "sigma": float(math.sqrt(cov[p_, p_]))}
            extra["covariance"] = cov.tolist()
            vals = {k.split("@")[0]: v["value"] for k, v in estimate.items()
                    if k.endswith(f"@{sc.id}") or "@" not in k}
            span = ", ".join(s.id for s, _ in refit)
            if c.effect == "impulsive_shift":
                d = np.array([vals.get(n, 0.0) for n in SHIFT])
                ph = where.get("phi_deg", [0.0, 0.0])
                expl = (f"{expl}; cycle {sc.meta.cycle}, phi {ph[0]:.1f}-{ph[1]:.1f} deg, "
                        f"{1e3 * np.linalg.norm(d):.2f} mm for {sc.window_s[1]:.2f} s")
            elif c.effect == "oscillation":
                a = [vals.get(n, 0.0) for n in OSCILLATION]
                amp = max(math.hypot(a[0], a[1]), math.hypot(a[2], a[3]))
                expl = (f"{expl}; period {sc.period_s:.3f} s, amplitude {amp * 206264.8:.2f} "
                        f"arcsec ({span})")
            else:
                expl = f"{expl} ({span})"
        elif c.effect == "gravity_deformation":
            _update_shared(spec, joint, dz)
            C = t.estimate.reshape(len(ZERNIKE_TESTED), 3)
            spec.zern_C = C
            sg = t.sigma.reshape(len(ZERNIKE_TESTED), 3)
            for i, j in enumerate(ZERNIKE_TESTED):
                for a, ax in enumerate("xyz"):
                    estimate[f"zern_{j}_per_g{ax}"] = {"value": float(C[i, a]),
                                                       "sigma": float(sg[i, a])}
            where = {"covariate": "gravity", "positions": sorted({s.meta.position for s in S})}
            extra["covariance"] = t.cov.tolist()
            _refit_all(ctx, S, spec)
            expl = f"{expl}; Zernike modes {', '.join(map(str, ZERNIKE_TESTED))} linear in g"
    elif o.kind == "panel":
        dz = _joint_step(joint, None)
        _update_shared(spec, joint, dz)
        spec.panels = {"offset": _panel_datum(joint, joint.panel_step(dz)),
                       "n_points": joint.group_count}
        _refit_all(ctx, S, spec)
        P = {**spec.panels, **{k: v for k, v in _estimate_panels(ctx, S, spec).items()
                               if k in ("tilt_r", "tilt_t")}}  # tilts: reported, not modelled
        live = P["n_points"] > 0
        off = P["offset"]
        Sg = joint.group[0]
        sig = np.where(Sg > 0, joint.sigma0 / np.sqrt(np.where(Sg > 0, Sg, 1.0)), np.inf)
        order = np.argsort(-np.abs(np.where(live, off / sig, 0.0)))
        top = [int(g) for g in order[:12]]
        where = {"panels": top, "covariate": "panel"}
        # sigma of the rms: the standard deviation of one offset (the noise floor of the rms)
        estimate = {"offset_rms_m": {"value": float(np.sqrt(np.mean(off[live] ** 2))),
                                     "sigma": float(np.sqrt(np.mean(sig[live] ** 2)))}}
        for g in top[:5]:
            estimate[f"panel_{g}_offset_m"] = {"value": float(off[g]), "sigma": float(sig[g])}
        extra["panels"] = {"offset_m": [float(v) for v in off],
                           "tilt_radial_rad": [float(v) for v in P["tilt_r"]],
                           "tilt_tangential_rad": [float(v) for v in P["tilt_t"]]}
        rms_mm = 1e3 * estimate["offset_rms_m"]["value"]
        expl = f"{expl}; {int(live.sum())} panels, offsets {rms_mm:.3f} mm rms"
    if o.kind == "dish":
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
        fam = "generic"
    elif o.kind == "covariate":
        pl = o.payload
        name = pl["covariate"]
        nb, ps = ctx.config.covariate_bins, pl["per_scan"]
        est, se = pl["est"], pl["se"]
        spec.modelled.add(name)
        scans, where, parts = [], {"covariate": name}, []
        zmax = 0.0
        for k, sc in enumerate(S):
            ids = pl["ids"][k]
            e = est[k * ps: (k + 1) * ps]
            sg = se[k * ps: (k + 1) * ps]
            z = np.where(sg > 0, e / np.where(sg > 0, sg, 1.0), 0.0)
            big = np.nonzero((np.abs(z) > 5.0) & (np.abs(e) > ctx.config.min_effect_m))[0]
            if not len(big):
                continue
            zmax = max(zmax, float(np.max(np.abs(z))))
            scans.append(sc.id)
            hit = sc.used & np.isin(ids, big)
            ph = np.degrees(sc.data.phi_rad[hit])
            v = _covariate_values(sc)[name][hit]
            parts.append({"scan": sc.id, "cycle": sc.meta.cycle,
                          "faces": sorted({int(b // nb) + 1 for b in big}),
                          "phi_deg": [float(ph.min()), float(ph.max())],
                          f"{name}_range": [float(v.min()), float(v.max())],
                          "range_error_m": [float(e[b]) for b in big]})
            if name == "time":
                sc.cut = sc.cut | np.isin(ids, big)
            else:
                # the joint solution: range error per bin and the panel planes it implies
                ok = ids >= 0
                er = pl["raw"][k * ps: (k + 1) * ps]
                kp = np.where(sc.panel >= 0, sc.panel, 0)
                plane = np.where(sc.panel >= 0, np.sum(_panel_columns(ctx, sc)
                                                       * pl["planes"][kp], 1), 0.0)
                sc.extra_known = sc.extra_known + np.where(
                    ok, -sc.b0 * er[np.where(ok, ids, 0)] / sc.s_rho, 0.0) - plane
        if len(parts) == 1:
            where.update({k: v for k, v in parts[0].items() if k not in ("scan", "faces",
                                                                         "range_error_m")})
            if len(parts[0]["faces"]) == 1:
                where["face"] = parts[0]["faces"][0]
        elif parts:
            where["cycle"] = [p["cycle"] for p in parts]
            where[f"{name}_range"] = [min(p[f"{name}_range"][0] for p in parts),
                                      max(p[f"{name}_range"][1] for p in parts)]
        extra["by_scan"] = parts
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
        cv = pl.get("cv") or {}
        physics = ""
        if cv.get("ranking"):
            extra["covariate_comparison"] = {"method": cv["method"],
                                             "ranking": cv["ranking"][:5]}
            b = cv["ranking"][0]
            if b["covariate"] == name and b["model"] == "periodic" and "note" not in cv:
                where["period"] = b["period"]
                where["period_unit"] = "m" if name in ("range", "rho") else (
                    "s" if name == "time" else "rad" if name != "intensity" else "1")
                extra["periodic_amplitude_m"] = b.get("amplitude_m")
            if b["covariate"] == name and cv.get("physics"):
                physics = f" ({cv['physics']})"
        expl = (f"residual structure in {', '.join(scans) or 'the scans'} following "
                f"{name.replace('_', ' ')} that no catalog effect explains{physics}; {action}")
        fam = "generic"
    return Finding(effect=o.effect, family=fam, scans=scans, where=where, estimate=estimate,
                   statistic=o.T, dof=o.dof, p_value=0.0, sigma0_before=0.0, sigma0_after=0.0,
                   rms_before_m=0.0, rms_after_m=0.0, explanation=expl, extra=extra)


def _fmt(name: str, v: float, s: float) -> str:
    unit = parameter_unit(name)
    if unit == "rad":
        return f"{v * 206264.806:.2f} ± {s * 206264.806:.2f} arcsec"
    if unit == "m":
        return f"{v * 1e3:.4f} ± {s * 1e3:.4f} mm"
    return f"{v:.4g} ± {s:.2g} {unit}".strip()


# ============================================================================================
# outputs
# ============================================================================================








