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
   the period found, drift, Zernike modes); :func:`~hartrao_jax.solver.mixed_chunk` gives its
   normal equations at the current solution with the columns of the surface cells (per panel,
   common to all scans: an offset and two tilts). The scans' equations are summed into one
   joint system (separate object parameters per scan, instrument parameters shared by all
   scans, motion per scan, Zernike coefficients linear in gravity across positions). The score
   tests' null carries the surface (``physics.md``, Statistics): the cells' variances and the
   noise's are estimated at this linearisation as the two-face adjustment estimates them; the
   cells are eliminated (Schur complement), their tilts as a random effect with that prior,
   their offsets free (they take up the reflector's shape at every scale above a cell); the
   panel-offset test and the model step keep the offsets alone as fixed nuisance. For every
   candidate the score statistic, its one-step estimate, the predicted improvement in metres
   and its multiple correlation with the model follow from the partitioned system; candidates
   inseparable from the model are reported as ``confounded``.
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
from pathlib import Path

import numpy as np

from .._config import each_in_threads
from ..campaign._campaign import Campaign, ScanData, ScanMeta, load_campaign
from ..model._model import parse_model
from ..physics._catalog import EFFECTS, two_face_parameters
from ._apply_catalog import _apply_catalog
from ._apply_covariate import _apply_covariate, _apply_dish
from ._checks import _alternatives, _signature_check
from ._detectability import _detectability
from ._estimates import surface_estimates
from ._explain import _candidates, _Joint, _local_candidates, _log_sf, _want
from ._find import _covariate_cv, _locate_time
from ._local import final_estimates, local_step
from ._options import (
    UNEXPLAINED_MIN_DROP,
    UNEXPLAINED_MIN_DROP_M,
    _Option,
    _option_key,
    _options,
    _static_confounded,
)
from ._panels import _apply_panels
from ._recording import capabilities, skipped_searches
from ._result import Diagnosis
from ._start import _start_scans
from ._state import (
    DiagnoseConfig,
    Finding,
    _Context,
    _evaluate,
    _global_sigma0,
    _num,
    _restore,
    _rms,
    _save,
    _Scan,
    _Spec,
)
from ._summary import _cells_not_panels, _compare, _extent, _snapshot
from ._thermal import _thermal

log = logging.getLogger("hartrao_jax")

_NULL_DESCRIPTION = (
    "catalog score tests judged against the reflector's surface: per panel (or grid cell, "
    "common to all scans) a free offset and two tilts as a random effect, the variances and "
    "the noise's estimated at the last step (Foerstner); sigma0 is the noise's")


# ============================================================================================
# set-up
# ============================================================================================


def _one_face(metas: Sequence[ScanMeta], start_names: tuple[str, ...], wanted,
              notes: list[str]) -> tuple[tuple[str, ...], list[dict]]:
    """A recording with one face: the two-face-sensitive calibration parameters are not
    identifiable; returns the start model without them and their ``not_identifiable`` rows."""
    if not any(m.cycle not in (1, 2) for m in metas):
        return start_names, []
    tf = two_face_parameters()
    drop = [n for n in start_names if n in tf]
    if drop:
        start_names = tuple(n for n in start_names if n not in drop)
        notes.append(f"one-face recording: {', '.join(drop)} dropped from the start model "
                     "(two-face-sensitive calibration parameters are not identifiable from "
                     "one face)")
    return start_names, [
        {"parameter": k, "identifiable": False, "value": None, "sigma": None,
         "note": "two-face-sensitive calibration parameter: a one-face recording cannot "
                 "separate it from the pose and the reflector (it needs the second face)"}
        for k in tf if wanted is None or k in wanted]


def _start_spec(ctx: _Context, S: Sequence[_Scan], start_names: tuple[str, ...], wanted,
                notes: list[str]) -> tuple[_Spec, list[dict]]:
    """The start model and what the recording allows (times, intensities, two faces, a panel
    layout); returns it with the searches skipped, after evaluating every scan."""
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
        notes.append(ctx.layout_note)
    each_in_threads(lambda sc: _evaluate(ctx, sc, spec), S, "evaluate")
    return spec, skipped


# ============================================================================================
# one step of the loop
# ============================================================================================


def _search(ctx: _Context, S: Sequence[_Scan], spec: _Spec, confounded: dict, wanted):
    """Locate and explain: the joint system, its tests and every option of this step."""
    if spec.times:  # each scan's own searches, the scans over the cores
        each_in_threads(lambda sc: _locate_time(sc, ctx.config), S, "locate")
    local = _local_candidates(ctx, S, spec)
    joint = _Joint(ctx, S, spec, local)
    tests = [joint.test(c) for c in _candidates(joint, S, local)]
    options = _options(ctx, S, spec, joint, tests, confounded, wanted)
    spec.skip |= set(confounded)
    return joint, tests, options


def _choose(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint,
            options: Sequence[_Option], refused: set[tuple]) -> _Option | None:
    """Decide: the eligible option with the smallest adjusted p-value that shows its family's
    signature. Structure no catalog entry explains comes after the catalog, unless it is far
    stronger (twice the orders of magnitude): a catalog effect then explains only part (never
    before the panel offsets: their maps are modelled on top of the panels)."""
    for o in options:
        if _option_key(o) in refused:
            o.eligible, o.reason = False, "did not survive the refit"
    ok = [o for o in options if o.eligible]
    lp_cat = min((o.log_p for o in ok if o.kind in ("catalog", "panel")), default=0.0)
    panel_first = any(o.kind == "panel" for o in ok)
    tier = sorted(ok, key=lambda o: (o.kind != "panel" if panel_first else False,
                                     o.kind in ("dish", "covariate")
                                     and not o.log_p < 2.0 * lp_cat, o.log_p))
    for o in tier:
        why = _signature_check(ctx, S, spec, joint, o, options)
        if not why:
            return o
        o.eligible, o.reason = False, why
    return None


def _apply(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint, o: _Option) -> Finding:
    """Model the accepted explanation, refit, and describe it as a finding (statistics of the
    step and the fit before and after are filled in by :func:`_model_step`)."""
    eff = EFFECTS.get(o.effect)
    expl = eff.explanation if eff else o.effect
    if o.kind == "catalog":
        part = _apply_catalog(ctx, S, spec, joint, o, expl)
    elif o.kind == "panel":
        part = _apply_panels(ctx, S, spec, joint, expl)
    elif o.kind == "dish":
        part = _apply_dish(ctx, S, spec, joint, o)
    elif o.kind == "covariate":
        part = _apply_covariate(ctx, S, spec, o)
    else:
        part = {}
    return Finding(effect=o.effect, family=part.get("family", o.family),
                   scans=part.get("scans", [sc.id for sc in S]), where=part.get("where", {}),
                   estimate=part.get("estimate", {}), statistic=o.T, dof=o.dof, p_value=0.0,
                   sigma0_before=0.0, sigma0_after=0.0, rms_before_m=0.0, rms_after_m=0.0,
                   explanation=part.get("explanation", expl), extra=part.get("extra", {}))


def _ambiguity(effect: str, alternatives: Sequence[dict]) -> str:
    """One sentence naming the alternatives the data hardly tell apart from ``effect``."""
    alts = "; ".join(f"{a['effect']} (correlation {a['correlation']:+.3f}, likelihood ratio "
                     f"{a['likelihood_ratio']:.3g} in favour of {effect})" for a in alternatives)
    return (f"The data hardly tell it apart from {alts}: the choice rests on that ratio "
            "alone.")


def _record(f: Finding, best: _Option, before: tuple[float, float],
            after: tuple[float, float]) -> None:
    """The statistics of the step and sigma0 / rms (m) before and after it, on the finding."""
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


def _model_step(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint, best: _Option,
                options: Sequence[_Option], refused: set[tuple],
                notes: list[str]) -> tuple[_Spec, Finding | None]:
    """Model ``best`` and refit. A finding must survive the refit (sigma0 must not grow, no
    scan may stop converging): else the state is restored, the option refused and ``None``
    returned with the restored spec."""
    before = (_global_sigma0(S), _rms(S))
    saved = _save(S, spec)
    alternatives = _alternatives(joint, best, options)
    f = _apply(ctx, S, spec, joint, best)
    if alternatives:
        f.extra["alternatives"] = alternatives
        f.explanation += " " + _ambiguity(f.effect, alternatives)
    after = (_global_sigma0(S), _rms(S))
    lost = any(st["converged"] and not sc.converged for sc, st in zip(S, saved[0]))
    if after[0] > before[0] * (1.0 + 1e-3) or lost:
        log.info("refused %s: the refit did not improve the fit (sigma0 %.4f -> %.4f)",
                 best.effect, before[0], after[0])
        refused.add(_option_key(best))
        notes.append(f"{best.effect} ({', '.join(f.scans)}) was significant but did not "
                     f"survive the refit (sigma0 {before[0]:.4f} -> {after[0]:.4f})")
        return _restore(S, saved), None
    _record(f, best, before, after)
    return spec, f


# ============================================================================================
# results
# ============================================================================================


# ============================================================================================
# the loop
# ============================================================================================


def _local_search(ctx, S, spec, record: list[dict], notes: list[str], findings: list,
                  history: list[dict], stage: str) -> None:
    """One round of the local-deformation search (:func:`._local.local_step`) on the current
    residuals: its summaries go to ``record`` (with ``stage``), what it models to
    ``findings`` and ``history``."""
    n0 = len(record)
    for f in local_step(ctx, S, spec, record, notes):
        findings.append(f)
        spec.accepted.append(f.effect)
        history.append({"step": len(history), "label": f.effect, "maps": _snapshot(S),
                        "scans": f.scans})
    for r in record[n0:]:
        r["stage"] = stage


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
        a :class:`Diagnosis` (``to_json()``: schema ``hartrao-diagnosis/1``; metres, radians,
        seconds; ``timing_s`` in seconds).
    """
    t_all = time.time()
    camp = campaign if isinstance(campaign, Campaign) else load_campaign(campaign)
    cfg = config or DiagnoseConfig()
    ctx = _Context(camp, cfg)
    timing: dict[str, float] = {}
    wanted = set(cfg.effects) if cfg.effects else None
    notes: list[str] = []
    metas = [camp.scan(s) for s in scans] if scans else list(camp.scans)
    start_names, not_identifiable = _one_face(metas, parse_model(start), wanted, notes)
    t0 = time.time()
    S = _start_scans(ctx, start_names, keep, scans)
    spec, skipped = _start_spec(ctx, S, start_names, wanted, notes)
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
        _local_search(ctx, S, spec, local_search, notes, findings, history, "start model")
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
        joint, tests, options = _search(ctx, S, spec, confounded, wanted)
        best = _choose(ctx, S, spec, joint, options, refused)
        last_rows = [o.row() for o in sorted(options, key=lambda o: o.log_p)]
        log.info("step %d: %d candidates, best %s (%.1f s)", step, len(options),
                 best.effect if best else "none", time.time() - ts)
        if best is None:
            break
        spec, f = _model_step(ctx, S, spec, joint, best, options, refused, notes)
        if f is None:
            continue  # refused: look again
        findings.append(f)
        spec.accepted.append(f.effect)
        history.append({"step": step, "label": f.effect, "maps": _snapshot(S),
                        "evidence": f.extra.pop("_evidence", None), "scans": f.scans})
        log.info("accepted %s (%s): T=%.1f dof=%d, sigma0 %.3f -> %.3f, rms %.3f -> %.3f mm",
                 f.effect, ",".join(f.scans), best.T, best.dof, f.sigma0_before,
                 f.sigma0_after, 1e3 * f.rms_before_m, 1e3 * f.rms_after_m)
    timing["loop"] = time.time() - t_loop
    if (_want(wanted, "local_deformation") and not spec.bumps and not ctx.has_layout
            and any(f.effect == "panel_offset" for f in findings)):
        # the grid cells' offsets modelled: search again on residuals without them (a known
        # panel layout needs no second search: its panels are the first search's nuisance)
        t_l = time.time()
        _local_search(ctx, S, spec, local_search, notes, findings, history,
                      "after the panel offsets were modelled")
        timing["local_search"] = timing.get("local_search", 0.0) + time.time() - t_l
    final_estimates(ctx, S, spec, findings)
    if _want(wanted, "thermal"):
        th = _thermal(ctx, S, len(last_rows) + 1)
        if th is not None and th[0] == "finding":
            findings.append(th[1])
        elif th is not None:
            confounded.setdefault("thermal", th[1])
    detect = (_detectability(ctx, joint, tests, len(options), S if spec.times else ())
              if step_done else [])
    if spec.shared:
        notes.append("instrument parameters found are shared by all scans (joint estimate): "
                     + ", ".join(f"{k}={v:.4g}" for k, v in spec.shared.items()))
    t_e = time.time()
    final = surface_estimates(ctx, S, spec)
    timing["estimates"] = time.time() - t_e
    if final["note"]:
        notes.append(final["note"])
    timing["total"] = time.time() - t_all
    diag = Diagnosis(
        campaign=str(camp.root), start_model=list(start_names), final_model=spec.names(),
        sigma0_start=sigma0_start, sigma0_final=_global_sigma0(S), rms_start_m=rms_start,
        rms_final_m=_rms(S), findings=findings, confounded=list(confounded.values()),
        comparison=comparison, candidates=last_rows, timing_s=timing, notes=notes,
        scans_final=final["scans"], positions=final["positions"],
        shared_estimates=final["shared"], history=history, detectability=detect, skipped=skipped,
        not_identifiable=not_identifiable, local_search=local_search, layout=ctx.layout_note,
        extents={sc.id: _extent(sc) for sc in S},
        covariates=cov_cmp,
        score_null=({"surface_random_effect": joint.surface.to_json(),
                     "description": _NULL_DESCRIPTION} if joint is not None else {}),
    )
    if not ctx.has_layout:
        for f in findings:
            _cells_not_panels(ctx, f)
    return diag
