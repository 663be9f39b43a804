"""The final model's estimates with honest sigmas: the surface as a random effect.

The loop's per-scan adjustments are white-noise fits (each scan alone, the modelled panel
offsets taken as known): their sigmas are the noise's only, several times too small wherever
the reflector's panel pattern matters (``physics.md``, Statistics; on the demo campaign the
per-scan tx/ry/x6 had z up to 7). At the end the joint system of all scans is built once more
at the final solution with the surface cells (panels, or the stated grid) as a random effect --
per cell an offset (m) and two tilts (rad), variances estimated with the noise's by the
two-face adjustment's variance-component estimation (:class:`._explain._SurfaceNull`) -- and
solved by Gauss-Newton, each scan re-linearised until no unknown moves by a tenth of its sigma
(:func:`_iterate`; one step where the white fit was close, a few on a narrow strip):

* **per scan**: each scan's own unknowns; the other scans inform them only through the cells
  they share;
* **per position**: both faces adjusted together, as ``fit`` does (one pose, one f, one set of
  calibration and local-deformation parameters; the motions of a scan stay its own). A position
  with one usable cycle says ``"faces": 1``.

Unlike the score tests' null (offsets free, so that a real reflector's millimetre-scale
shape never becomes a finding), the offsets carry their prior here: the estimates are then
those of ``fit``'s adjustment (without its smooth modes), and a parameter the data cannot
determine (near-confounding or a sigma above the parameter's typical size) is reported with
``"identifiable": false`` and a note instead of a value.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from ..fit._identify import undetermined_parameters
from ..geometry._geometry import pointing_elevation_deg
from ._explain import _Joint, _scaled_pinv, _SurfaceNull, eliminate_cells
from ._state import ZERNIKE_TESTED, _Context, _num, _Scan, _Spec

log = logging.getLogger("hartrao_jax")

#: Angles of the pose: two cycles' values are brought to the same turn before they are merged.
_ANGLES = ("rx", "ry", "rz")


def _current(joint: _Joint, S: Sequence[_Scan], spec: _Spec) -> np.ndarray:
    """The current value of every null unknown of ``joint`` (``I0`` order): the scans' own
    from their final fits, the accepted shared ones from ``spec``."""
    by_id = {sc.id: dict(zip(sc.names, map(float, sc.x))) for sc in S}
    zern = [f"C{j}{a}" for j in ZERNIKE_TESTED for a in "xyz"]
    out = []
    for i in joint.I0:
        label = joint.labels[i]
        if "@" in label:
            name, sid = label.split("@")
            out.append(by_id[sid].get(name, 0.0))
        elif label in spec.shared:
            out.append(float(spec.shared[label]))
        else:  # a Zernike coefficient per unit g (gravity accepted)
            out.append(float(np.asarray(spec.zern_C).reshape(-1)[zern.index(label)]))
    return np.asarray(out, float)


def _merge(joint: _Joint, S: Sequence[_Scan], spec: _Spec) -> tuple[np.ndarray, list[tuple]]:
    """``P`` (null unknowns, merged unknowns): a scan's unknown goes to its position's
    ``(position, name)`` unless it is a motion of that scan (``(scan id, name)``); accepted
    shared unknowns stay themselves (``("shared", label)``)."""
    pos = {sc.id: sc.meta.position for sc in S}
    motion = {sc.id: set(spec.motion.get(sc.id, {}).get("names", ())) for sc in S}
    keys: list[tuple] = []
    col = []
    for i in joint.I0:
        label = joint.labels[i]
        if "@" in label:
            name, sid = label.split("@")
            key = (sid, name) if name in motion[sid] else (pos[sid], name)
        else:
            key = ("shared", label)
        if key not in keys:
            keys.append(key)
        col.append(keys.index(key))
    P = np.zeros((len(joint.I0), len(keys)))
    P[np.arange(len(col)), col] = 1.0
    return P, keys


def _same_turn(x: np.ndarray, P: np.ndarray, labels: list[str]) -> np.ndarray:
    """Angles of the pose merged into one unknown, brought to the turn of the first."""
    x = x.copy()
    for j in range(P.shape[1]):
        rows = np.flatnonzero(P[:, j])
        if len(rows) > 1 and labels[rows[0]].split("@")[0] in _ANGLES:
            ref = x[rows[0]]
            x[rows] = ref + (x[rows] - ref + math.pi) % (2 * math.pi) - math.pi
    return x


def _identifiability(cov: np.ndarray, names: list[str], elevation_deg: float) -> dict[str, str]:
    """Per calibration parameter the data cannot determine: the note saying why (as ``fit``
    says it, :func:`..fit._identify.undetermined_parameters`)."""
    return undetermined_parameters(cov, names, elevation_deg,
                                   then="the diagnosis's value is not an estimate")


#: Gauss-Newton steps of the random-effect system at most, and the step (in sigmas of each
#: unknown) below which it has converged. One step suffices where the white fit is close (the
#: usual case); a narrow strip, where f is barely determined, needs a few.
MAX_STEPS, STEP_TOL = 6, 0.1


class _Solved(NamedTuple):
    """The random-effect system at its last linearisation: the solution is ``x - Ki k``."""

    surface: _SurfaceNull  # noise and cell variances
    K: np.ndarray  # reduced normal matrix of the null unknowns (cells eliminated)
    k: np.ndarray  # its right side
    Ki: np.ndarray  # its (scaled pseudo-) inverse
    x: np.ndarray  # the linearisation point, merged angles on one turn
    labels: list[str]  # "name@scan" or a shared name, per null unknown
    P: np.ndarray  # null unknowns -> merged unknowns (:func:`_merge`)
    keys: list[tuple]  # the merged unknowns


def _iterate(ctx: _Context, S: Sequence[_Scan], spec: _Spec) -> _Solved | None:
    """Gauss-Newton on the joint system with the cells as a random effect, from the scans'
    final solutions: each step re-linearises every scan at the step's result for its own
    unknowns (their ``x`` is moved; the caller restores it). None when the variances are not
    estimable."""
    P = keys = None
    for step in range(MAX_STEPS):
        joint = _Joint(ctx, S, spec, {sc.id: [] for sc in S})
        sn = joint.surface
        if sn.note:
            return None
        N, n = eliminate_cells(joint, sn.noise_var, sn.cell_var, offsets_random=True)
        I0 = joint.I0
        K, k = N[np.ix_(I0, I0)], n[I0]
        labels = [joint.labels[i] for i in I0]
        if P is None:  # the layout of the unknowns does not change between steps
            P, keys = _merge(joint, S, spec)
        x = _same_turn(_current(joint, S, spec), P, labels)
        Ki = _scaled_pinv(K)
        dx = -Ki @ k
        own = np.array(["@" in lab for lab in labels])
        sd = np.sqrt(sn.noise_var * np.maximum(np.diag(Ki), 1e-300))
        worst = float(np.max(np.abs(dx[own]) / sd[own])) if own.any() else 0.0
        log.debug("final estimates, step %d: largest step %.3g sigma", step, worst)
        if worst < STEP_TOL or step == MAX_STEPS - 1:
            break
        for sc in S:
            xs = np.array(sc.x, float)
            for i, lab in enumerate(labels):
                name, _, sid = lab.partition("@")
                if sid == sc.id:
                    xs[sc.names.index(name)] = x[i] + dx[i]
            sc.x = xs
    log.debug("final estimates: %d Gauss-Newton steps", step + 1)
    return _Solved(sn, K, k, Ki, x, labels, P, keys)


def _entry(value: float, sigma: float, **more) -> dict[str, Any]:
    return {"value": _num(value), "sigma": _num(sigma), **more}


def _scan_record(sc: _Scan, estimates: dict[str, dict]) -> dict[str, Any]:
    """A scan's entry of the diagnosis JSON: its final model, ``estimates``, sigma0, counts."""
    return {"model": list(sc.names), "estimates": estimates, "sigma0": _num(sc.sigma0),
            "n_points": int(sc.used.sum()), "converged": sc.converged,
            "cut_points": int(sc.cut.sum())}


def surface_estimates(ctx: _Context, S: Sequence[_Scan], spec: _Spec) -> dict[str, Any]:
    """The final estimates per scan and per position with the surface as a random effect.

    Returns ``{"scans", "positions", "shared", "note"}``: ``scans`` maps each scan id to its
    model, estimates ``{name: {value, sigma, sigma_white}}`` (parameter units; ``sigma_white``
    the loop's white-noise sigma), sigma0, counts and convergence; ``positions`` lists per
    position its ``faces``, scans and merged ``estimates`` (calibration parameters the data
    cannot determine as ``{"value": null, "sigma": null, "identifiable": false, "note": ...}``)
    with the variance components; ``shared`` the accepted parameters common to all scans;
    ``note`` is empty unless the random effect could not be estimated (the white-noise sigmas
    are then reported and say so)."""
    white = {sc.id: dict(zip(sc.names, np.sqrt(np.maximum(np.diag(sc.cov), 0.0))))
             if sc.cov.size else {} for sc in S}
    saved = [np.array(sc.x, float) for sc in S]
    try:
        r = _iterate(ctx, S, spec)
    finally:
        for sc, x0 in zip(S, saved):
            sc.x = x0
    if r is None:
        scans = {sc.id: _scan_record(sc, {
            n: _entry(v, white[sc.id].get(n, float("nan")),
                      sigma_white=_num(white[sc.id].get(n, float("nan"))))
            for n, v in zip(sc.names, map(float, sc.x))}) for sc in S}
        return {"scans": scans, "positions": [], "shared": {},
                "note": "surface random effect not estimable: the sigmas are the noise's alone"}
    sn, K, k, Ki, x, labels, P, keys = r
    x_scan, sd_scan = x - Ki @ k, np.sqrt(sn.noise_var * np.maximum(np.diag(Ki), 0.0))
    # per position: the faces' shared unknowns merged (minimum of the same quadratic form)
    Kp_inv = _scaled_pinv(P.T @ K @ P)
    y = Kp_inv @ (P.T @ (K @ x - k))
    cov_y = sn.noise_var * Kp_inv
    sd_y = np.sqrt(np.maximum(np.diag(cov_y), 0.0))
    scans: dict[str, dict] = {}
    for sc in S:
        est = {}
        for i, label in enumerate(labels):
            name, _, sid = label.partition("@")
            if sid == sc.id:
                est[name] = _entry(x_scan[i], sd_scan[i],
                                   sigma_white=_num(white[sc.id].get(name, float("nan"))))
        scans[sc.id] = _scan_record(sc, est)
    positions = []
    tel, site = ctx.campaign.telescope, ctx.campaign.site
    for p in dict.fromkeys(sc.meta.position for sc in S):
        members = [sc for sc in S if sc.meta.position == p]
        idx = [j for j, key in enumerate(keys) if key[0] == p]
        names = [keys[j][1] for j in idx]
        elev = pointing_elevation_deg(members[0].meta, tel, site)
        held = _identifiability(cov_y[np.ix_(idx, idx)], names, elev)
        est = {}
        for j, name in zip(idx, names):
            est[name] = ({"value": None, "sigma": None, "identifiable": False,
                          "note": held[name]} if name in held else _entry(y[j], sd_y[j]))
        positions.append({
            "position": p, "faces": len({sc.meta.cycle for sc in members}),
            "scans": [sc.id for sc in members], "elevation_deg": _num(elev),
            "estimates": est,
            "variance_components": {"noise": _num(sn.noise_var),
                                    "panel_offset_m": _num(math.sqrt(sn.cell_var[0])),
                                    "panel_tilt_rad": _num(math.sqrt(np.mean(sn.cell_var[1:])))},
        })
    shared = {key[1]: _entry(y[j], sd_y[j]) for j, key in enumerate(keys) if key[0] == "shared"}
    return {"scans": scans, "positions": positions, "shared": shared, "note": ""}
