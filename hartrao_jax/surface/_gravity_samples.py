"""Per-scan samples for the gravity model (:mod:`._gravity`): what one scan's (or one
position's) fit gives it -- gravity vector, f with its sigma, the used points and their
deviations -- and, for a white-noise adjustment, the scan's linear response to the surface
modes it does not model (:func:`mode_response`); for a two-face adjustment, each panel's
``d f / d u`` and the surface variances (positions that see the same panels share errors).
From a fit in memory (:func:`samples_from_fit`) or a results directory (:func:`samples_from_dir`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._programs import cached_jit
from ..campaign._campaign import load_campaign
from ..campaign._safeio import verify_result_dir
from ..fit._fit import scan_arrays, sigma_vector
from ..geometry._geometry import zernike, zernike_columns
from ..model._model import N_CONSTS, make_model
from ..solver._ghm import bucket_size

log = logging.getLogger("hartrao_jax")

NUISANCE_MODES = (1, 2, 3)  # piston, tilts: absorbed by the pose, estimated and dropped


# --------------------------------------------------------------------------------------------
# Per-scan samples
# --------------------------------------------------------------------------------------------


@dataclass
class ScanSample:
    """What the gravity model needs of one scan (SI units)."""

    id: str
    position: str
    gravity: np.ndarray
    f: float
    sigma_f: float
    ha_deg: float | None = None
    dec_deg: float | None = None
    elevation_deg: float | None = None
    temperature_c: float | None = None
    X: np.ndarray | None = None  # used points, north-aligned telescope frame (m)
    deviation_m: np.ndarray | None = None
    # response of the scan's adjustment to the surface modes (see mode_response):
    # leak[j] = d f_hat / d a_j, retention[j, k] = d (projection j of the residuals) / d a_k
    leak: np.ndarray | None = None
    retention: np.ndarray | None = None
    # True when f comes from the position's two-face adjustment, shared by its scans: the
    # position then contributes f once (not once per scan, as independent cycles would)
    shared_f: bool = False
    # two-face adjustment: d f / d (offset, tilt, tilt) of each panel {panel id: (3,)} and the
    # surface variances (m^2, rad^2, rad^2): positions seeing the same panels share errors
    f_response: dict[int, np.ndarray] | None = None
    cell_var: np.ndarray | None = None


def samples_from_fit(cf, *, with_points: bool = True, modes: Sequence[int] = (),
                     aperture_radius_m: float | None = None, shared: Sequence[str] | None = None,
                     sigma_l: np.ndarray | None = None) -> list[ScanSample]:
    """Samples from a :class:`~hartrao_jax.fit.CampaignFit` or a joint fit
    (:class:`~hartrao_jax.fit._joint.JointFit`).

    With ``modes`` (and the scans' points) each sample also gets its :func:`mode_response`;
    ``shared``: parameters estimated jointly with other scans, held fixed in it (default: the
    fit's ``shared``, which a joint fit and its ``campaign_fit()`` carry).
    """
    scans = cf.scans if hasattr(cf, "scans") else cf
    shared = tuple(getattr(cf, "shared", ()) or ()) if shared is None else tuple(shared)
    if modes and not shared and any(str(n).startswith("joint adjustment")
                                    for s in scans for n in (getattr(s, "notes", None) or ())):
        # the scans of a joint fit without the names of its shared parameters: treating those
        # as per-scan unknowns gives a wrong response (worse than none) -- pass the JointFit
        log.warning("gravity model: scans of a joint adjustment without its shared parameters "
                    "(pass the JointFit, not its campaign_fit()): mode take-up not corrected")
        modes = ()
    camp = getattr(cf, "campaign", None)
    if sigma_l is None and camp is not None:
        sigma_l = sigma_vector(camp)
    if aperture_radius_m is None:
        aperture_radius_m = camp.telescope.diameter_m / 2 if camp is not None else 12.95
    two_face = bool(getattr(cf, "position_fits", None))
    resp = {p.position: _response_of_fit(p) for p in getattr(cf, "position_fits", None) or ()}
    out = []
    for s in scans:
        v, sg = s.estimates["f"]
        m = s.meta
        resp_m = (None, None)
        # the mode take-up of a white-noise adjustment; a two-face adjustment carries the
        # smooth modes as random effects itself
        if with_points and modes and not two_face and sigma_l is not None and s.model is not None \
                and getattr(s, "data", None) is not None and len(s.data) == len(s.used):
            obs, c = scan_arrays(s.data)
            model, x = _per_scan_model(s.model, s.x, shared)
            resp_m = mode_response(model, obs, s.v, c, s.used, x, sigma_l, s.X_tel[s.used],
                                 aperture_radius_m, modes)
        out.append(ScanSample(
            m.id, m.position, np.asarray(s.gravity, float), v, sg, m.ha_deg, m.dec_deg,
            s.elevation_deg, m.temperature_c,
            s.X_tel[s.used] if with_points else None,
            s.deviation_m[s.used] if with_points else None, *resp_m, shared_f=two_face,
            **_response_fields(resp.get(m.position) if two_face else None)))
    return out


# --------------------------------------------------------------------------------------------
# How a scan's focal length responds to a surface deformation
# --------------------------------------------------------------------------------------------


def _per_scan_model(model, x, shared: Sequence[str]):
    """The model with the ``shared`` parameters (estimated jointly with other scans) moved from
    the free to the fixed ones at their values; returns ``(model, x_free)``."""

    free = tuple(model.free)
    hold = [n for n in shared if n in free]
    if not hold:
        return model, np.asarray(x, float)
    x = np.asarray(x, float)
    fixed = dict(zip(model.fixed_names, np.asarray(model.fixed_values, float)))
    fixed.update({n: float(x[free.index(n)]) for n in hold})
    keep = [n for n in free if n not in hold]
    m = make_model(keep, fixed, shift_window_s=model.shift_window_s,
                   osc_period_s=model.osc_period_s, kappa_rad=model.kappa_rad,
                   aperture_radius_m=model.aperture_radius_m, check_separable=False)
    return m, np.array([x[free.index(n)] for n in keep])


def _linearize_dev(model, L, x, C, s2):
    """Per point: ``a = dF/dx``, ``m = b Sigma b^T`` and ``s = dF/d(known deviation)``."""

    def one(obs, c, s2_):
        _, (a, b, dc) = jax.value_and_grad(lambda xx, ll, cc: model(ll, xx, cc),
                                           argnums=(0, 1, 2))(x, obs, c)
        return a, jnp.sum(b * b * s2_), dc[1]

    return jax.vmap(one)(L, C, s2)


_linearize_dev_jit = cached_jit(_linearize_dev)


def _linear_response(model, obs: np.ndarray, v: np.ndarray, consts: np.ndarray,
                     used: np.ndarray, x: np.ndarray, sigma_l: np.ndarray):
    """``(Q, G, i_f)`` of an adjusted scan, for its used points (rows).

    A normal deviation ``dev`` of the reflector that the adjustment model does not contain
    enters each point's condition as ``dev_i s_i`` (:func:`._physics.paraboloid_condition`).
    At the solution the estimates then move by ``dx = sum_i Q_i dev_i``,
    ``Q_i = N^-1 a_i s_i / m_i`` (``a = dF/dx``, ``m = b Sigma b^T``, linearised at
    ``(l + v, x)``), and the deviation of point ``i`` from the fitted paraboloid by
    ``dev_i - G_i . dx`` with ``G_i = a_i / s_i``. ``i_f``: index of ``f`` in ``x``.
    The rows are padded to :func:`._joint.bucket_size`, so a campaign compiles once.
    """
    used = np.asarray(used, bool)
    n = len(obs)
    n_pad = bucket_size(n)
    idx = np.concatenate([np.arange(n), np.zeros(n_pad - n, np.int64)])
    L = (np.asarray(obs, float) + np.asarray(v, float))[idx]
    C = np.array(np.asarray(consts, float)[idx])
    C[:, 1] = 0.0
    s2 = np.broadcast_to(np.asarray(sigma_l, float) ** 2, (n_pad, 3))
    a, m, sc = (np.asarray(t)[:n][used] for t in _linearize_dev_jit(
        model, L, np.asarray(x, float), C, s2))
    q = np.where(m > 0, 1.0 / np.where(m > 0, m, 1.0), 0.0)
    N = (a * q[:, None]).T @ a
    Q = np.linalg.solve(N, (a * (q * sc)[:, None]).T).T  # N symmetric
    G = a / sc[:, None]
    return Q, G, list(model.free).index("f")


def mode_response(model, obs, v, consts, used, x, sigma_l, X: np.ndarray,
                  aperture_radius_m: float, modes: Sequence[int],
                  nuisance: Sequence[int] = NUISANCE_MODES
                  ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """How an adjusted scan responds to the Zernike surface modes it does not model.

    ``X``: the used points (north-aligned telescope frame, the frame of the modes). Returns
    ``(leak, retention)``: ``leak[j] = d f_hat / d a_j`` (m of focal length per m of mode
    coefficient) and ``retention[j, k]`` = the change of the residuals' projection on mode ``j``
    (:func:`zernike_projection`) per unit of mode ``k``. A mode the adjustment cannot take up
    stays in the residuals (``retention`` = identity, ``leak`` = 0); on a tilted scan with
    per-scan calibration the focal length took up 4 to 10 m per m of astigmatism, and the
    residuals kept only part of it -- the gravity model must account for both
    (:func:`gravity_model`).
    """
    try:
        Q, G, i_f = _linear_response(model, obs, v, consts, used, x, sigma_l)
    except np.linalg.LinAlgError:  # a singular scan: no response, no correction
        return None, None
    allm = tuple(nuisance) + tuple(j for j in modes if j not in nuisance)
    A = zernike_columns(X, allm, aperture_radius_m)
    Zm = A[:, [allm.index(j) for j in modes]]
    dX = Q.T @ Zm  # (u, modes): parameter change per unit mode
    R = Zm - G @ dX  # what each mode leaves in the deviations
    coef, *_ = np.linalg.lstsq(A, R, rcond=None)
    return dX[i_f], coef[[allm.index(j) for j in modes]]


def samples_from_dir(results_dir, *, with_points: bool = True, modes: Sequence[int] = (),
                     aperture_radius_m: float | None = None) -> list[ScanSample]:
    """Samples from a results directory: ``fit.json`` and ``residuals/<scan>.parquet``.

    With ``modes`` each sample also gets its :func:`mode_response`, rebuilt from the residual
    table (observations, residuals, time) and the campaign of ``fit.json`` (scanner sigmas);
    without the campaign it is left out.
    """
    import pyarrow.parquet as pq


    root = Path(results_dir)
    doc = verify_result_dir(root, "fit.json")  # a complete fit, or a one-line refusal
    pos = {q["position"]: q for q in doc.get("positions", [])}
    temps: dict[str, float | None] = {}
    camp = doc.get("campaign")
    sigma_l = None
    if camp and (Path(camp) / "campaign.toml").is_file():
        try:
            c = load_campaign(camp)
            temps = {m.id: m.temperature_c for m in c.scans}
            sigma_l = sigma_vector(c)
            if aperture_radius_m is None:
                aperture_radius_m = c.telescope.diameter_m / 2
        except Exception:  # noqa: BLE001 - temperatures are optional
            temps = {}
    if aperture_radius_m is None:
        aperture_radius_m = 12.95
    out = []
    shared = doc.get("shared", {})
    shared_f = shared.get("f")
    cols = ["used", "X_m", "Y_m", "Z_m", "deviation_m"]
    lcols = ["range_m", "phi_rad", "theta_rad", "v_range_m", "v_phi_rad", "v_theta_rad",
             "time_s"]
    two_face = str(doc.get("adjustment", "")).startswith("two-face")
    for s in doc["scans"]:
        est = s["estimates"].get("f") or shared_f
        q = pos.get(s["position"], {})
        X = dev = None
        resp = (None, None)
        if with_points:
            rp = root / "residuals" / f"{s['id']}.parquet"
            if rp.is_file():
                names = pq.ParquetFile(rp).schema_arrow.names
                lin = bool(modes) and not two_face and sigma_l is not None \
                    and "f" in s["estimates"] and all(c in names for c in lcols)
                t = pq.read_table(rp, columns=cols + (lcols if lin else []))
                used = t.column("used").to_numpy(zero_copy_only=False)
                X = np.column_stack([t.column(c).to_numpy() for c in ("X_m", "Y_m", "Z_m")])[used]
                dev = t.column("deviation_m").to_numpy()[used]
                if lin:
                    resp = _response_from_table(t, used, X, s, doc.get("model", []), shared,
                                                sigma_l, aperture_radius_m, modes)
        out.append(ScanSample(
            s["id"], s["position"], np.asarray(s.get("gravity") or q.get("gravity"), float),
            float(est["value"]), float(est["sigma"]), q.get("ha_deg"), q.get("dec_deg"),
            s.get("elevation_deg", q.get("elevation_deg")), temps.get(s["id"]), X, dev, *resp,
            shared_f=two_face, **_response_fields(_response_of_record(q) if two_face else None)))
    return out


def _response_fields(r) -> dict:
    """``ScanSample`` keywords from ``({panel: d f / d u}, cell variances)`` or None."""
    if r is None or not r[0]:
        return {}
    return {"f_response": r[0], "cell_var": r[1]}


def _response_of_fit(p):
    """``({panel: d f / d u}, variances)`` of a two-face :class:`..fit.PositionFit` whose cells
    are panels (their ids are the same at every position), else None."""
    if (p.response is None or p.surface is None or p.mixed is None or "f" not in p.names
            or not p.surface.cells.startswith("panels")):
        return None
    i_f = list(p.names).index("f")
    return ({int(g): p.response[g, i_f] for g in np.flatnonzero(p.surface.n)},
            np.asarray(p.mixed.var[1], float))


def _response_of_record(q: dict):
    """``({panel: d f / d u}, variances)`` of a ``positions[]`` record of fit.json (panels with
    ``f_response``; the tilt variance is the mean of the two stated as ``tilt_rad``)."""
    vc = q.get("variance_components") or {}
    rows = [r for r in q.get("panels") or () if "panel" in r and r.get("f_response")]
    if not rows or vc.get("surface_m") is None or vc.get("tilt_rad") is None:
        return None
    var = np.array([vc["surface_m"] ** 2, vc["tilt_rad"] ** 2, vc["tilt_rad"] ** 2])
    return {int(r["panel"]): np.asarray([a or 0.0 for a in r["f_response"]], float)
            for r in rows}, var


def _response_from_table(t, used, X, rec: dict, names: Sequence[str], shared: dict, sigma_l,
                         aperture_radius_m: float, modes: Sequence[int]):
    """:func:`mode_response` of a scan from its residual table and ``fit.json`` record.

    The model is rebuilt from the names of ``fit.json``: the scan's estimates free, the shared
    parameters of a joint fit fixed at their group's values (parameters held fixed in the fit
    are not recorded there and are taken as 0 -- their values hardly change the derivatives).
    """

    est = rec["estimates"]
    free = [n for n in names if n in est]
    fixed = {}
    for n in names:
        if n in est:
            continue
        sh = shared.get(n)
        if sh is None:
            continue
        g = (sh.get("by_group") or {}).get(rec.get("shared_group"), sh)
        fixed[n] = float(g["value"])
    try:
        model = make_model(free, fixed, check_separable=False)
    except Exception:  # noqa: BLE001 - a model we cannot rebuild: no correction for it
        return None, None
    col = lambda c: t.column(c).to_numpy()  # noqa: E731
    obs = np.column_stack([col("range_m"), col("phi_rad"), col("theta_rad")])
    v = np.column_stack([col("v_range_m"), col("v_phi_rad"), col("v_theta_rad")])
    c = np.zeros((len(obs), N_CONSTS))
    c[:, 0] = col("time_s")
    x = np.array([est[n]["value"] if est[n]["value"] is not None else est[n]["value_in_fit"]
                  for n in model.free])
    return mode_response(model, obs, v, c, used, x, sigma_l, X, aperture_radius_m, modes)


def zernike_np(j: int, u: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """:func:`~hartrao_jax.geometry.zernike` evaluated with NumPy (Noll index, unit rms)."""
    return zernike(j, u, psi, xp=np)
