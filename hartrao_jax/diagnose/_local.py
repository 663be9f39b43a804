"""The ``local_deformation`` step of the diagnosis: search, judge, model, refit, report.

The residual surface of the start fit (recording minus simulation along the normal, all scans
together: the reflector is common to them) is searched by :func:`._locate.search` (matched
filter over centres and widths, significance against the maximum the reflector's own roughness
produces). The search sees the points the robust fit keeps and the rejected ones that agree
with their neighbours (:func:`readmitted`, :func:`._locate.coherent`): a structure deeper than
the rejection limit is searched with its core, not only its rim. On a reflector of known panel
layout the panels' offsets and tilts are the filter's nuisance (the "Panels" section of
:mod:`._locate`), so the search runs once, on the start model, and a bump inside a panel is
neither hidden by the panel pattern nor taken by its panel's offset; the refit of a candidate gets
those points back near it (its robust rejection may drop them again). A bump as wide as the
panels is their offsets to that filter: when it finds nothing, the widths of 1.5 m and more
are searched by :func:`._wide.search_wide` (the windowed filter against a parametric bootstrap
of the panels' random effect), and any accepted bump that wide has its sigmas widened by the
panels' factor (:func:`._wide.panel_factor`). Up to
:data:`MAX_BUMPS` rounds, each stopping at the first candidate that does not stand out.
An accepted candidate becomes the catalog's ``local_deformation`` term of the model
(``bump_x_m, bump_y_m, bump_amp_m, bump_width_m``, :func:`._physics.local_deformation`), free
in the Gauss-Helmert adjustment of every scan that covers it; the scans are refitted and the
finding must survive the refit (sigma0 drops, the amplitude stays clear of zero). Its
parameters stay free there, so what is modelled after it (the panel offsets above all) refines
them: the finding reports the final model's estimates (:func:`final_estimates`). A candidate
that does not stand out is described as the largest local structure and never as a finding.

Sigmas: the adjustment's sigmas treat the points as independent; on a real reflector the
panel-scale roughness correlates them, so every reported sigma is multiplied by the search's
roughness factor at the candidate's width (the spread of the matched-filter scores over the
surface relative to white noise); the white sigmas are kept beside them.

Units: metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..geometry._geometry import polar_to_cartesian
from ..model._model import bump_names
from ._locate import NOT_DISTINGUISHABLE, Search, coherent, covered_ids, scan_point, search
from ._state import Finding, _evaluate, _global_sigma0, _refit_all, _restore, _rms, _save
from ._wide import WIDE_WIDTHS_M, panel_factor, search_wide

ALPHA_LOCAL = 1e-3  # of the maximum over the reflector's placements
MAX_BUMPS = 4  # rounds of search and model; each stops at the first insignificant candidate


def rejection_limit(sc, robust_k: float | None) -> np.ndarray:
    """Every point's rejection limit as a normal deviation (m): ``k`` a-posteriori sigmas of
    its misclosure, ``k sigma0 sqrt(m_i) / s_i`` (the robust adjustment's test; infinite when
    the fit is not robust)."""
    if robust_k is None or not np.isfinite(sc.sigma0) or sc.m is None:
        return np.full(len(sc.s_rho), np.inf)
    return robust_k * sc.sigma0 * np.sqrt(np.maximum(sc.m, 0.0)) / sc.s_rho


def readmitted(S, robust_k: float | None = 4.0) -> list[np.ndarray]:
    """Per scan, the points the robust fit rejected that the search takes back (bool masks
    over the scan's points): rejected points of the window that agree with their neighbours
    (:func:`._locate.coherent`; the neighbourhood spans all scans, the reflector being
    common to them)."""
    sel = [sc.window & ~sc.cut for sc in S]
    xy = np.concatenate([sc.X_tel[s, :2] for sc, s in zip(S, sel)])
    r = np.concatenate([sc.mismatch_m[s] for sc, s in zip(S, sel)])
    kept = np.concatenate([sc.used[s] for sc, s in zip(S, sel)])
    lim = np.concatenate([rejection_limit(sc, robust_k)[s] for sc, s in zip(S, sel)])
    adm = coherent(xy, r, kept, lim)
    out, k = [], 0
    for sc, s in zip(S, sel):
        m = np.zeros(len(s), bool)
        m[np.flatnonzero(s)] = adm[k:k + int(s.sum())]
        k += int(s.sum())
        out.append(m)
    return out


def search_points(S, robust_k: float | None = 4.0, back=None, panels: bool = False):
    """Aperture positions (m) and residual normal deviations (m) of what the search sees, all
    scans together: the points the fit keeps and the rejected ones that agree with their
    neighbours (:func:`readmitted`, or the masks ``back`` when given); with ``panels`` also
    their panel ids (-1: none)."""
    back = readmitted(S, robust_k) if back is None else back
    xy = np.concatenate([sc.X_tel[sc.used | b, :2] for sc, b in zip(S, back)])
    r = np.concatenate([sc.mismatch_m[sc.used | b] for sc, b in zip(S, back)])
    if panels:
        return xy, r, np.concatenate([sc.panel[sc.used | b] for sc, b in zip(S, back)])
    return xy, r


def _raw_xyz(sc) -> np.ndarray:
    """The scan's points in its own Cartesian frame as recorded (file coordinates on import)."""

    return polar_to_cartesian(sc.l[:, 0], sc.l[:, 1], sc.l[:, 2], np)


def _place(ctx, S, x0: float, y0: float, w: float) -> dict:
    """``where`` of a centre: aperture coordinates, panels (or grid cells), scan-frame point."""
    where = {"x_m": float(x0), "y_m": float(y0)}
    best = max(S, key=lambda sc: int(np.sum(np.hypot(sc.X_tel[sc.used, 0] - x0,
                                                     sc.X_tel[sc.used, 1] - y0) < w)))
    u = best.used
    ids = covered_ids(best.X_tel[u, :2], best.panel[u], x0, y0, max(w, 0.3))
    if ctx.has_layout:
        where["panels"] = ids
    else:
        g = ctx.geo
        where["cells"] = [{"cell": k, "x_m": float(g["rho_c"][k] * math.cos(g["psi_c"][k])),
                           "y_m": float(g["rho_c"][k] * math.sin(g["psi_c"][k]))} for k in ids]
        where["grid"] = ctx.layout_note
    pt = scan_point(best.X_tel[u, :2], _raw_xyz(best)[u], x0, y0, w)
    return where, pt, best.id


def _describe(c, ctx, S) -> dict:
    where, pt, sid = _place(ctx, S, c.x_m, c.y_m, c.width_m)
    kind = "bump" if c.amplitude_m > 0 else "dent"
    sig = ("no calibrated significance (too few placements)" if c.p_value is None
           else f"p = {c.p_value:.2g} against the largest of {c.n_peaks} local structures of "
                f"the same surface")
    statement = (f"largest local structure: a {kind} of {1e3 * c.amplitude_m:+.2f} mm, width "
                 f"{c.width_m:.2f} m at x {c.x_m:.2f} m, y {c.y_m:.2f} m ({sig}, roughness "
                 f"factor {c.roughness:.1f}): " + ("it stands out from the reflector's own "
                                                   "roughness" if c.significant
                                                   else NOT_DISTINGUISHABLE))
    return {**c.to_json(), "where": where, "centre_scan_m": pt, "scan": sid,
            "accepted": False, "statement": statement}


def local_step(ctx, S: Sequence, spec, record: list[dict], notes: list[str]) -> list:
    """Search, and model what stands out (at most :data:`MAX_BUMPS`); returns the findings and
    appends one summary per search to ``record`` (maps under the private ``_maps`` key)."""

    out = []
    for k in range(1, MAX_BUMPS + 1):
        back = readmitted(S, ctx.config.robust_k)
        # on a reflector of known panels, the panels' offsets and tilts are the filter's
        # nuisance (a grid of cells is no physical structure: the local background there)
        xy, r, ids = search_points(S, back=back, panels=True)
        exclude = [(b["values"][b["names"][0]], b["values"][b["names"][1]],
                    abs(b["values"][b["names"][3]])) for b in spec.bumps]
        srch = search(xy, r, alpha=ALPHA_LOCAL, min_amplitude_m=ctx.config.min_effect_m * 5,
                      exclude=exclude, groups=ids if ctx.has_layout else None)
        if ctx.has_layout and (srch.candidate is None or not srch.candidate.significant):
            # as wide as the panels: the windowed filter against the panels' random effect
            wide = search_wide(xy, r, ids, alpha=ALPHA_LOCAL, exclude=exclude,
                               min_amplitude_m=ctx.config.min_effect_m * 5, seed=k)
            if wide.candidate is not None and wide.candidate.significant:
                srch = Search(list(srch.maps) + list(wide.maps), wide.candidate, srch.sigma_m,
                              [w for w in srch.skipped_widths if w not in WIDE_WIDTHS_M])
        c = srch.candidate
        if c is None:
            record.append({"search": k, "statement": "no place of the surface is covered densely "
                           "enough for the local-deformation search", "accepted": False,
                           "skipped_widths_m": srch.skipped_widths, "_maps": srch.maps})
            break
        desc = _describe(c, ctx, S)
        desc.update(search=k, skipped_widths_m=srch.skipped_widths, _maps=srch.maps,
                    readmitted_points=int(sum(b.sum() for b in back)))
        record.append(desc)
        if not c.significant:
            break
        # ---- model it: the catalog term, free in the scans that cover it
        names = bump_names(k)
        hint = dict(zip(names, (c.x_m, c.y_m, c.amplitude_m, c.width_m)))
        covering = [sc.id for sc, b in zip(S, back) if int(np.sum(np.hypot(
            sc.X_tel[sc.used | b, 0] - c.x_m, sc.X_tel[sc.used | b, 1] - c.y_m)
            < 2 * c.width_m)) >= 20]
        if not covering:
            break
        saved = _save(S, spec)
        # the refit sees the candidate's re-admitted points (its core, when the start fit
        # rejected it); sigma0 and rms before are taken on the same points
        _readmit_near(ctx, S, spec, back, covering, c)
        before = (_global_sigma0(S), _rms(S))
        # all four parameters free; when that nonlinear refit fails (a compact bump of low
        # signal can send the width through zero), the amplitude alone, centre and width held
        # at the search's values (linear: it converges)
        for free in (names, names[2:3]):
            if free is not names:
                _readmit_near(ctx, S, spec, back, covering, c)
            spec.bumps.append({"names": names, "values": dict(hint), "scans": covering,
                               "free": list(free)})
            _refit_all(ctx, S, spec, only=[sc for sc in S if sc.id in covering],
                       hints={sid: hint for sid in covering}, from_used=True, others=True)
            est = _combine(S, covering, free)
            after = (_global_sigma0(S), _rms(S))
            if est is not None and len(free) < len(names):
                est.update({n: (hint[n], None) for n in names if n not in free})
            ok = (est is not None and after[0] < before[0] and all(sc.converged for sc in S)
                  and 0.02 < est[names[3]][0] < 20.0
                  and abs(est[names[2]][0]) > 3 * est[names[2]][1] * c.roughness
                  and math.hypot(est[names[0]][0] - c.x_m, est[names[1]][0] - c.y_m)
                  < 3 * c.width_m)
            if ok:
                break
            spec2 = _restore(S, saved)
            spec.__dict__.update(spec2.__dict__)
        if not ok:
            desc["statement"] = desc["statement"].replace(
                "largest local structure:", "largest local structure (significant in the search "
                "but it did not survive the refit):") + (
                "; refitted as the catalog's local_deformation it did not converge or did "
                f"not lower sigma0 ({before[0]:.4f} -> " + (f"{after[0]:.4f}" if math.isfinite(
                    after[0]) else "not finite") + "): not modelled")
            notes.append("local deformation candidate did not survive the refit (sigma0 "
                         f"{before[0]:.4f} -> " + (f"{after[0]:.4f})" if math.isfinite(after[0])
                                                   else "not finite)"))
            break
        spec.bumps[-1]["values"] = {n: est[n][0] for n in names}
        if ctx.has_layout and abs(est[names[3]][0]) >= WIDE_WIDTHS_M[0]:
            # as wide as the panels (whichever search found it): the panels' random effect
            # blurs its amplitude beyond the narrow search's roughness
            c.roughness = max(c.roughness, panel_factor(
                xy, r, ids, est[names[0]][0], est[names[1]][0], abs(est[names[3]][0])))
        estimate, where, pt, sid = _estimate(ctx, S, names, est, c.roughness)
        expl = _sentence(estimate, c.p_value, c.n_peaks, before[1], after[1])
        f_ = c.roughness
        desc.update(accepted=True, statement=expl, estimate=estimate, where=where,
                    centre_scan_m=pt)
        p = c.p_value if c.p_value is not None else 1.0
        out.append(Finding(
            effect="local_deformation", family="reflector", scans=covering, where=where,
            estimate=estimate, statistic=c.t * c.t, dof=1, p_value=p,
            sigma0_before=before[0], sigma0_after=after[0], rms_before_m=before[1],
            rms_after_m=after[1], explanation=expl,
            effect_size_m=abs(estimate["amplitude_m"]["value"]),
            extra={"centre_scan_m": pt, "centre_scan_of": sid, "parameters": list(names),
                   "null": {"method": (
                                "maximum of the windowed matched filter against a parametric "
                                "bootstrap of the panels' random effect"
                                if c.tail.get("null") == "panel random effect" else
                                "maximum of the matched filter over the reflector's own "
                                "placements (peak-height tail, same surface)"),
                            "p_value": c.p_value, "t": c.t, "n_peaks": c.n_peaks,
                            "roughness_factor": c.roughness, "tail": c.tail},
                   "sigma_note": "sigmas are the adjustment's times the roughness factor "
                                 f"{f_:.2f} (correlated panel-scale roughness)"}))
    return out


def _estimate(ctx, S, names, est, f_):
    """``estimate`` of a finding from the combined bump parameters ``est`` (``{name: (value,
    sigma)}``; sigma None: held), its sigmas times the roughness factor ``f_``; with its
    ``where``, scan-frame centre and the scan that gives it."""

    def vs(name):
        v, s = est[name]
        v = abs(v) if name == names[3] else v
        if s is None:  # held at the search's grid value
            return {"value": v, "sigma": None, "held": "at the search's grid value"}
        return {"value": v, "sigma": s * f_, "sigma_white": s}

    estimate = {"amplitude_m": vs(names[2]), "width_m": vs(names[3]), "x_m": vs(names[0]),
                "y_m": vs(names[1])}
    where, pt, sid = _place(ctx, S, est[names[0]][0], est[names[1]][0], abs(est[names[3]][0]))
    return estimate, where, pt, sid


def _sentence(estimate: dict, p_value, n_peaks: int, rms_before: float, rms_after: float,
              final: bool = False) -> str:
    """The finding's one sentence (metres in, millimetres out)."""
    a, w = estimate["amplitude_m"], estimate["width_m"]
    x, y = estimate["x_m"]["value"], estimate["y_m"]["value"]
    kind = "bump" if a["value"] > 0 else "dent"
    wtxt = (f"width {w['value']:.2f} m (held at the search's value: the free refit did not "
            f"converge)" if w["sigma"] is None else f"width {w['value']:.2f} ± {w['sigma']:.2f} m")
    p = "no calibrated significance" if p_value is None else f"p = {p_value:.2g}"
    return (f"a smooth local {kind} of {1e3 * a['value']:+.2f} ± {1e3 * a['sigma']:.2f} mm and "
            f"{wtxt} at x {x:.2f} m, y {y:.2f} m of the aperture stands out from the "
            f"reflector's own roughness ({p} against its {n_peaks} local structures); modelled "
            f"as local_deformation, rms {1e3 * rms_before:.4f} -> {1e3 * rms_after:.4f} mm"
            + ("; estimates of the final model (every finding modelled)" if final else ""))


def final_estimates(ctx, S, spec, findings) -> None:
    """Each local-deformation finding's estimate in the final model: its parameters stay free
    in the scans that cover it, so the steps after it (the panel offsets above all, which it
    had to share its panels' points with) refine them. ``estimate``, ``where`` and the
    sentence are updated; the values at acceptance are kept as ``estimate_at_acceptance``."""
    for f in findings:
        if f.effect != "local_deformation":
            continue
        names = f.extra["parameters"]
        b = next((b for b in spec.bumps if list(b["names"]) == list(names)), None)
        if b is None:
            continue
        free = [n for n in names if n in b.get("free", names)]
        est = _combine(S, b["scans"], free)
        if est is None:
            continue
        est.update({n: (b["values"][n], None) for n in names if n not in free})
        null = f.extra["null"]
        estimate, where, pt, sid = _estimate(ctx, S, names, est, null["roughness_factor"])
        f.extra["estimate_at_acceptance"] = f.estimate
        f.estimate, f.where = estimate, where
        f.extra.update(centre_scan_m=pt, centre_scan_of=sid)
        f.effect_size_m = abs(estimate["amplitude_m"]["value"])
        f.explanation = _sentence(estimate, null["p_value"], null["n_peaks"], f.rms_before_m,
                                  f.rms_after_m, final=True)


def _readmit_near(ctx, S, spec, back, covering, c) -> None:
    """Give the covering scans' re-admitted points within ``3 w`` of candidate ``c`` back to
    the adjustment (its robust rejection may drop them again) and re-evaluate those scans."""
    for sc, b in zip(S, back):
        near = b & (np.hypot(sc.X_tel[:, 0] - c.x_m, sc.X_tel[:, 1] - c.y_m) < 3 * c.width_m)
        if sc.id in covering and near.any():
            sc.used = sc.used | near
            _evaluate(ctx, sc, spec)


def _combine(S, ids, names):
    """Mean of the bump parameters over the scans where they are free: ``{name: (value,
    sigma)}``, or None when an adjustment failed.

    The cycles of one position see the same surface, and a bump's error comes mostly from
    that surface (the panel offsets and tilts around it), not from the noise: their estimates
    are combined as fully correlated (weighted mean, sigma the weighted mean of their sigmas).
    Combined as independent, the amplitude's z over 19 seeded campaigns had sd 1.37 (about
    sqrt 2), the width's 1.21. Positions are independent (inverse-variance mean)."""
    vals: dict[str, dict[str, list]] = {n: {} for n in names}
    for sc in S:
        if sc.id not in ids or not all(n in sc.names for n in names):
            continue
        sd = np.sqrt(np.maximum(np.diag(sc.cov), 0.0))
        for n in names:
            i = sc.names.index(n)
            if not (np.isfinite(sc.x[i]) and np.isfinite(sd[i]) and sd[i] > 0):
                return None
            vals[n].setdefault(sc.meta.position, []).append((float(sc.x[i]), float(sd[i])))
    out = {}
    for n, per_pos in vals.items():
        if not per_pos:
            return None
        xs, ss = [], []
        for v in per_pos.values():
            w = np.array([1 / s**2 for _, s in v])
            xs.append(float(np.sum(w * np.array([x for x, _ in v])) / w.sum()))
            ss.append(float(np.sum(w * np.array([s for _, s in v])) / w.sum()))
        w = 1 / np.array(ss) ** 2
        out[n] = (float(np.sum(w * np.array(xs)) / w.sum()), float(1 / math.sqrt(w.sum())))
    wname = next((n for n in names if n.endswith("width_m")), None)
    if wname is not None and out[wname][0] < 0:  # the sign of the width is not observable
        out[wname] = (-out[wname][0], out[wname][1])
    return out
