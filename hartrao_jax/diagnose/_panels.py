"""Panel offsets and shared parameters from the joint system: the step of the null unknowns,
the offsets fed back as known deviation (without the part a paraboloid absorbs), panel planes
for the report, and the modelling of accepted panel offsets (:func:`_apply_panels`).

Units: metres (offsets), radians (tilts)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ._explain import _Joint, _Test
from ._find import _add_plane_sums, _panel_points
from ._state import ZERNIKE_TESTED, _Context, _panel_known, _refit_all, _Scan, _Spec


def _estimate_panels(ctx: _Context, scans: Sequence[_Scan], spec: _Spec) -> dict[str, np.ndarray]:
    """Panel planes (offset m, radial and tangential tilt rad) common to all scans, by weighted
    least squares of the mismatch plus the currently modelled panel deviation."""
    G = ctx.n_panels
    M = np.zeros((G, 3, 3))
    u = np.zeros((G, 3))
    cnt = np.zeros(G)
    for sc in scans:
        ok, q, P, pid = _panel_points(ctx, sc)
        r = (sc.mismatch_m + _panel_known(ctx, sc, spec.panels))[ok]  # the whole deviation
        cnt += np.bincount(pid, minlength=G)
        _add_plane_sums(M, u, pid, q, P, r)
    sol = np.zeros((G, 3))
    for g in range(G):
        if cnt[g] >= 12:
            sol[g] = np.linalg.lstsq(M[g], u[g], rcond=1e-10)[0]
        elif cnt[g] > 0:
            sol[g, 0] = u[g, 0] / M[g, 0, 0]
    return {"offset": sol[:, 0], "tilt_r": sol[:, 1], "tilt_t": sol[:, 2], "n_points": cnt}


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
    """Shared (instrument) parameters and Zernike coefficients (m per unit g) of the joint
    solution: add their increments ``dz``."""
    for i, k in enumerate(joint.shared_names):
        spec.shared[k] += float(dz[joint.sidx[i]])
    if spec.zern_C is not None:
        base = len(joint.shared_names)
        d = dz[joint.sidx[base: base + 3 * len(ZERNIKE_TESTED)]].reshape(len(ZERNIKE_TESTED), 3)
        spec.zern_C = spec.zern_C + d


def _panel_summary(joint: _Joint, P: dict[str, np.ndarray]) -> tuple[dict, dict, dict]:
    """``where`` (the 12 panels with the largest offsets in sigma), ``estimate`` (rms of the
    offsets in m, its sigma the rms of one offset's sigma: the noise floor; the five largest
    offsets) and ``extra`` (every offset in m and tilt in rad) of modelled panel planes."""
    live = P["n_points"] > 0
    off = P["offset"]
    Sg = joint.group[0]
    sig = np.where(Sg > 0, joint.sigma0 / np.sqrt(np.where(Sg > 0, Sg, 1.0)), np.inf)
    order = np.argsort(-np.abs(np.where(live, off / sig, 0.0)))
    top = [int(g) for g in order[:12]]
    where = {"panels": top, "covariate": "panel"}
    estimate = {"offset_rms_m": {"value": float(np.sqrt(np.mean(off[live] ** 2))),
                                 "sigma": float(np.sqrt(np.mean(sig[live] ** 2)))}}
    for g in top[:5]:
        estimate[f"panel_{g}_offset_m"] = {"value": float(off[g]), "sigma": float(sig[g])}
    extra = {"panels": {"offset_m": [float(v) for v in off],
                        "tilt_radial_rad": [float(v) for v in P["tilt_r"]],
                        "tilt_tangential_rad": [float(v) for v in P["tilt_t"]]}}
    return where, estimate, extra


def _apply_panels(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint,
                  expl: str) -> dict[str, Any]:
    """Model the panel offsets (m) of the joint solution as known deviation, refit every scan,
    and describe them (tilts are reported, not modelled); returns the finding's fields."""
    dz = _joint_step(joint, None)
    _update_shared(spec, joint, dz)
    spec.panels = {"offset": _panel_datum(joint, joint.panel_step(dz)),
                   "n_points": joint.group_count}
    _refit_all(ctx, S, spec)
    P = {**spec.panels, **{k: v for k, v in _estimate_panels(ctx, S, spec).items()
                           if k in ("tilt_r", "tilt_t")}}
    where, estimate, extra = _panel_summary(joint, P)
    rms_mm = 1e3 * estimate["offset_rms_m"]["value"]
    n_live = int((P["n_points"] > 0).sum())
    return {"where": where, "estimate": estimate, "extra": extra,
            "explanation": f"{expl}; {n_live} panels, offsets {rms_mm:.3f} mm rms"}
