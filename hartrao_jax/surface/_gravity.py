"""Gravity model over the sky: focal length and low-order surface modes linear in gravity.

The catalog's ``gravity_deformation`` (``physics.md``): elastic sag linear in the unit gravity
vector ``g`` of the telescope frame (``campaign-format.md``; ``g = (0, 0, -1)`` at the zenith):

* focal length ``f = f0 + c . g`` (m), and
* surface modes: Zernike coefficients over the aperture ``a_j = a0_j + C_j . g`` (m, normal
  deviation, Noll index ``j``, unit-rms normalisation, north-aligned telescope frame).

Inputs are the per-scan fits of a campaign (in memory, or a results directory with ``fit.json``
and ``residuals/*.parquet``), turned into samples by :mod:`._gravity_samples`. Each scan's
deviations from its fitted paraboloid are projected onto Zernike modes (least squares over the
used points, with piston and tilt as nuisance terms; defocus is mostly absorbed by ``f`` and
``tz`` and comes out small); cycles of one position are averaged; then ``f`` and every mode are
regressed on ``g`` by weighted least squares over the positions, with the fit's sigmas. The
hypothesis "``f`` depends on ``g_z`` only" is tested against "also on the transverse components
``g_x``, ``g_y``" with the nested-model F-test and the chi-square difference test. Positions
from two-face adjustments share the errors of the panels they all see: f is then regressed with
that covariance (:func:`f_covariance`), not as independent numbers.

The per-scan adjustment has no surface modes: a scan's ``f`` takes up part of them and its
residuals keep only part (astigmatism above all: on a tilted scan the calibration and the pose
mimic it, by amounts that depend on where the scanner hangs, i.e. on ``g``). Regressing ``f``
alone on ``g`` then puts the modes' gravity dependence into ``df/dg``. Each scan's linear
response to the modes (:func:`mode_response`: ``d f_hat / d a_j`` and what the residual
projections keep, from the adjustment's own normal equations) lets ``f`` and the modes be
regressed together (:func:`_joint_regression`), which removes that bias.

The model then predicts ``f`` and the surface rms over the whole working range (HA/DEC grid),
and the Ruze gain loss ``G/G0 = exp(-(4 pi eps / lambda)^2)`` at 2.5 cm and 1.3 cm.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np

from ..campaign._campaign import default_campaign, load_campaign
from ..campaign._safeio import OutputDir, verify_result_dir, write_file_atomic
from ..campaign._schedule import DEC_LIMITS_DEG, HA_LIMIT_DEG
from ..geometry._geometry import panel_cells, panel_ids, telescope_axes_hadec, zernike_columns
from ..physics._catalog import DEFAULT_ZERNIKE_MODES
from ._gravity_samples import (
    NUISANCE_MODES,
    ScanSample,
    mode_response,
    samples_from_dir,
    samples_from_fit,
    zernike_np,
)

GRAVITY_SCHEMA = "hartrao-gravity/1"
FOCUS_MODES = (4,)  # defocus: a change of the focal length, owned by f
WAVELENGTHS_M = (0.025, 0.013)


def gravity_grid(ha_deg: np.ndarray, dec_deg: np.ndarray, latitude_deg: float):
    """Unit gravity vectors (telescope frame) and elevations (deg) on an HA x DEC grid.

    :func:`..geometry._geometry.telescope_axes_hadec` over the grid (``F = R(P, -h)
    R(E, lat - d) [N, -E, U]``): returns ``G`` (len(dec), len(ha), 3) and ``el``
    (len(dec), len(ha)).
    """
    lat = math.radians(latitude_deg)
    h = np.radians(np.asarray(ha_deg, float))[None, :]
    d = np.radians(np.asarray(dec_deg, float))[:, None]
    h, d = np.broadcast_arrays(h, d)
    axes = jax.vmap(telescope_axes_hadec, in_axes=(0, 0, None))
    F = np.asarray(axes(h.reshape(-1), d.reshape(-1), lat)).reshape(h.shape + (3, 3))
    G = -F[..., 2, :]  # F^T (0, 0, -1)
    el = np.degrees(np.arcsin(np.clip(F[..., 2, 2], -1.0, 1.0)))
    return G, el


def zernike_projection(X: np.ndarray, dev: np.ndarray, aperture_radius_m: float,
                       modes: Sequence[int] = DEFAULT_ZERNIKE_MODES,
                       nuisance: Sequence[int] = NUISANCE_MODES, layout=None):
    """Least-squares Zernike coefficients (m) of a normal deviation sampled at points ``X``.

    Returns ``(coef, sigma, surface_rms)`` for ``modes`` (nuisance modes dropped). ``sigma`` is
    the cluster-robust (sandwich) standard error clustered by panel (by the square cells of
    :func:`._geometry.panel_cells` without a layout): the residuals of one panel share its
    offset and tilt, so treating the points as independent would make the sigma shrink as
    ``1/sqrt(n)`` while the panel pattern's blur of the coefficients does not.
    ``surface_rms``: rms of the surface the modes leave, at panel scale -- the rms of
    the per-panel mean residuals with their noise variance removed (``layout = (ring_edges_m,
    panels_per_ring)``; without a layout the point rms, which includes the measurement noise).
    """

    allm = tuple(nuisance) + tuple(j for j in modes if j not in nuisance)
    A = zernike_columns(X, allm, aperture_radius_m)
    coef, *_ = np.linalg.lstsq(A, dev, rcond=None)
    r = dev - A @ coef
    cells, _, n_cells, _ = panel_cells(X, *(layout or (None, None)))
    live = cells >= 0
    score = np.zeros((n_cells, A.shape[1]))
    np.add.at(score, cells[live], A[live] * r[live, None])
    iA = np.linalg.inv(A.T @ A)
    g = max(int(np.sum(np.any(score != 0, axis=1))), 2)
    cov = iA @ (score.T @ score) @ iA * g / (g - 1)
    keep = [allm.index(j) for j in modes]
    return coef[keep], np.sqrt(np.diag(cov))[keep], surface_rms(X, r, layout)


def surface_rms(X: np.ndarray, r: np.ndarray, layout=None) -> float:
    """rms (m) of a residual surface at panel scale, measurement noise removed.

    Per panel the mean residual ``m_k`` and its noise variance ``s_k^2 / n_k``; the result is
    ``sqrt(max(mean(m_k^2 - s_k^2 / n_k), 0))`` over panels with points (weighted by area share
    through the point counts). Without a panel layout: the rms of the points.
    """
    if layout is None or len(r) == 0:
        return float(np.sqrt(np.mean(r * r))) if len(r) else math.nan

    edges, counts = layout
    rho = np.hypot(X[:, 0], X[:, 1])
    psi = np.mod(np.arctan2(X[:, 1], X[:, 0]), 2 * np.pi)
    pid = panel_ids(rho, psi, edges, counts)
    ok = pid >= 0
    n_p = int(sum(counts))
    n = np.bincount(pid[ok], minlength=n_p).astype(float)
    s1 = np.bincount(pid[ok], weights=r[ok], minlength=n_p)
    s2 = np.bincount(pid[ok], weights=r[ok] ** 2, minlength=n_p)
    live = n >= 3
    m = s1[live] / n[live]
    var = (s2[live] - n[live] * m * m) / (n[live] - 1)
    val = np.sum(n[live] * (m * m - var / n[live])) / np.sum(n[live])
    return float(math.sqrt(max(val, 0.0)))


# --------------------------------------------------------------------------------------------
# Weighted regression on g
# --------------------------------------------------------------------------------------------


@dataclass
class LinearFit:
    """Weighted LS ``y = A beta`` over positions (``names`` of the columns of ``A``)."""

    names: tuple[str, ...]
    beta: np.ndarray
    cov: np.ndarray  # formal: (A^T W A)^-1 with the input sigmas
    chi2: float
    dof: int

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def scale(self) -> float:
        """A posteriori variance factor ``chi2 / dof`` (1 if the input sigmas are right)."""
        return self.chi2 / self.dof if self.dof > 0 else math.nan

    @property
    def sigma_scaled(self) -> np.ndarray:
        return self.sigma * math.sqrt(max(self.scale, 1.0)) if self.dof > 0 else self.sigma

    def as_dict(self, unit: str = "m") -> dict:
        return {"coefficients": {n: {"value": float(b), "sigma": float(s), "sigma_scaled":
                                     float(ss), "unit": unit}
                                 for n, b, s, ss in zip(self.names, self.beta, self.sigma,
                                                        self.sigma_scaled)},
                "chi2": self.chi2, "dof": self.dof, "variance_factor": self.scale}


def weighted_lsq(A: np.ndarray, y: np.ndarray, sigma: np.ndarray, names: Sequence[str],
                 cov_y: np.ndarray | None = None) -> LinearFit:
    """Weighted LS of ``y = A beta`` with independent rows of ``sigma``, or generalised LS with
    the full covariance ``cov_y`` of the rows when given (positions whose f share the errors
    of the panels they all see: :func:`f_covariance`). ``chi2 = r^T Cov^-1 r``."""
    y = np.asarray(y, float)
    if cov_y is None:
        W = np.diag(1.0 / np.asarray(sigma, float) ** 2)
    else:
        W = np.linalg.inv(np.asarray(cov_y, float))
    cov = np.linalg.inv(A.T @ W @ A)
    beta = cov @ (A.T @ W @ y)
    r = y - A @ beta
    return LinearFit(tuple(names), beta, cov, float(r @ W @ r), len(y) - A.shape[1])


def f_covariance(rows: Sequence[PositionRow]) -> np.ndarray | None:
    """Covariance (m^2) of the positions' f when every row comes from a two-face adjustment
    with its panel responses: ``sigma_f^2`` on the diagonal and, between positions, the
    surface errors they share, ``sum_panels r_i^T sqrt(G_i G_j) r_j`` (``r``: d f / d (offset,
    tilt, tilt) of the panel, ``G``: the surface variances). None otherwise (independent)."""
    if not rows or any(r.f_response is None or r.cell_var is None for r in rows):
        return None
    panels = sorted(set().union(*(r.f_response for r in rows)))
    col = {k: i for i, k in enumerate(panels)}
    Rs = np.zeros((len(rows), len(panels), 3))  # d f / d u scaled by the surface sigmas
    for i, r in enumerate(rows):
        for k, v in r.f_response.items():
            Rs[i, col[k]] = v * np.sqrt(np.asarray(r.cell_var, float))
    Rs = Rs.reshape(len(rows), -1)
    C = Rs @ Rs.T
    np.fill_diagonal(C, [r.sigma_f**2 for r in rows])
    # a valid covariance: clip correlations to [-1, 1] against round-off of mixed variances
    d = np.sqrt(np.diag(C))
    R = np.clip(C / np.outer(d, d), -1.0, 1.0)
    return R * np.outer(d, d)


def _design(G: np.ndarray, cols: Sequence[str], T: np.ndarray | None = None,
            reference_c: float = 15.0) -> np.ndarray:
    out = []
    for c in cols:
        if c == "f0" or c == "a0":
            out.append(np.ones(len(G)))
        elif c in ("gx", "gy", "gz"):
            out.append(G[:, "xyz".index(c[1])])
        elif c == "dT":
            out.append(np.asarray(T, float) - reference_c)
    return np.column_stack(out)


def nested_test(reduced: LinearFit, full: LinearFit) -> dict:
    """F-test and chi-square difference test of nested weighted LS models."""
    from scipy import stats

    q = full.names.__len__() - reduced.names.__len__()
    d = reduced.chi2 - full.chi2
    F = (d / q) / (full.chi2 / full.dof) if full.dof > 0 and full.chi2 > 0 else math.inf
    p_F = float(stats.f.sf(F, q, full.dof)) if full.dof > 0 else math.nan
    p_chi2 = float(stats.chi2.sf(d, q))
    return {"q": q, "chi2_reduced": reduced.chi2, "chi2_full": full.chi2, "chi2_difference": d,
            "p_value_chi2": p_chi2, "F": float(F), "F_dof": [q, full.dof], "p_value_F": p_F}


# --------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------


@dataclass
class PositionRow:
    position: str
    gravity: np.ndarray
    f: float
    sigma_f: float
    ha_deg: float | None
    dec_deg: float | None
    elevation_deg: float | None
    temperature_c: float | None
    zernike: np.ndarray | None
    zernike_sigma: np.ndarray | None
    residual_rms_m: float | None
    scans: list[str] = field(default_factory=list)
    # d f / d a_j: how much of each surface mode the position's focal length absorbed (1/1),
    # and d z_j / d a_k: how much of each mode its residual projections kept (mode_response)
    leak: np.ndarray | None = None
    retention: np.ndarray | None = None
    f_response: dict[int, np.ndarray] | None = None  # see ScanSample (two-face adjustments)
    cell_var: np.ndarray | None = None


@dataclass
class GravityModel:
    """``f = f0 + c . g`` (+ ``df/dT (T - 15 C)``), ``a_j = a0_j + C_j . g`` and the tests.

    ``focal``: the full regression (columns ``f0 gx gy gz [dT]``); ``focal_gz``: ``f0 gz [dT]``;
    ``test``: the nested test of the two; ``modes``/``zernike``: one regression per mode
    (columns ``a0 gx gy gz``); ``panel_rms_m``: median over scans of the panel-scale rms of the
    surface left after the modes (measurement noise removed, :func:`surface_rms`).
    """

    positions: list[PositionRow]
    focal: LinearFit
    focal_gz: LinearFit
    test: dict
    modes: tuple[int, ...]
    zernike: list[LinearFit]
    panel_rms_m: float | None
    aperture_radius_m: float
    latitude_deg: float
    reference_g: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    temperature: bool = False
    corrected_modes: tuple[int, ...] = ()  # modes whose take-up by f was corrected

    # --- predictions ---------------------------------------------------------------------
    @property
    def c(self) -> np.ndarray:
        """``df/dg`` (m per unit g component)."""
        return np.array([self.focal.beta[self.focal.names.index(k)] for k in ("gx", "gy", "gz")])

    @property
    def f0(self) -> float:
        return float(self.focal.beta[0])

    @property
    def C(self) -> np.ndarray:
        """Zernike coefficients per unit g, shape (modes, 3) (m)."""
        if not self.zernike:
            return np.zeros((0, 3))
        return np.array([z.beta[1:4] for z in self.zernike])

    @property
    def a0(self) -> np.ndarray:
        return np.array([z.beta[0] for z in self.zernike])

    def predict_f(self, g: np.ndarray) -> np.ndarray:
        """Focal length (m) at unit gravity vectors ``g`` (..., 3) (temperature at 15 C)."""
        return self.f0 + np.asarray(g) @ self.c

    def predict_zernike(self, g: np.ndarray) -> np.ndarray:
        """Zernike coefficients (m) at ``g`` (..., 3) -> (..., modes)."""
        return self.a0 + np.asarray(g) @ self.C.T

    def gravity_rms(self, g: np.ndarray) -> np.ndarray:
        """rms (m) of the modelled change of the surface modes from the reference ``g``."""
        d = (np.asarray(g) - self.reference_g) @ self.C.T
        return np.sqrt(np.sum(d * d, axis=-1))

    def surface_rms(self, g: np.ndarray) -> np.ndarray:
        """rms (m) of the modelled low-order surface (a0 + C g) plus the panel rms."""
        a = self.predict_zernike(g)
        p = self.panel_rms_m or 0.0
        return np.sqrt(np.sum(a * a, axis=-1) + p * p)

    def effect_parameters(self) -> dict:
        """The catalog's ``gravity_deformation`` parameters (simulator/diagnosis form)."""
        return {"df_dg_m": self.c.tolist(), "zernike_modes": list(self.modes),
                "zernike_per_g_m": self.C.tolist(), "f0_m": self.f0}

    # --- sky map -----------------------------------------------------------------------
    def sky_map(self, *, ha_deg: np.ndarray | None = None, dec_deg: np.ndarray | None = None,
                step_deg: float = 2.0, min_elevation_deg: float = 0.0) -> dict:
        """Predicted f, surface rms and Ruze gain over an HA/DEC grid (NaN below the horizon)."""

        ha = np.arange(-HA_LIMIT_DEG, HA_LIMIT_DEG + 1e-9, step_deg) if ha_deg is None else ha_deg
        dec = (np.arange(DEC_LIMITS_DEG[0], DEC_LIMITS_DEG[1] + 1e-9, step_deg)
               if dec_deg is None else dec_deg)
        G, el = gravity_grid(ha, dec, self.latitude_deg)
        mask = el < min_elevation_deg
        f = np.where(mask, np.nan, self.predict_f(G))
        grms = np.where(mask, np.nan, self.gravity_rms(G))
        srms = np.where(mask, np.nan, self.surface_rms(G))
        out = {"ha_deg": ha, "dec_deg": dec, "elevation_deg": el, "f_m": f,
               "gravity_rms_m": grms, "surface_rms_m": srms}
        for lam in WAVELENGTHS_M:
            out[f"ruze_gain_{lam * 100:g}cm"] = ruze_gain(srms, lam)
            out[f"ruze_gain_gravity_{lam * 100:g}cm"] = ruze_gain(grms, lam)
        return out

    def to_json(self, *, sky: dict | None = None, figures: Sequence[str] = ()) -> dict:
        names = ("gx", "gy", "gz")
        doc: dict = {
            "schema": GRAVITY_SCHEMA,
            "model": "f = f0 + c . g" + (" + df_dT (T - 15 C)" if self.temperature else "")
                     + "; a_j = a0_j + C_j . g (Zernike, Noll, unit rms, north-aligned frame)",
            "n_positions": len(self.positions),
            "focal_length": {**self.focal.as_dict(), "f0_m": self.f0,
                             "df_dg_m": dict(zip(names, self.c.tolist())),
                             "mode_take_up_corrected": list(self.corrected_modes)},
            "focal_length_gz_only": self.focal_gz.as_dict(),
            "test_transverse": {
                **self.test, "null": "f depends on g_z only",
                "alternative": "f depends on g_z and on the transverse components g_x, g_y",
                "reject_null_at_0.01": bool(self.test["p_value_F"] < 0.01)},
            "zernike": {
                "modes": list(self.modes),
                "aperture_radius_m": self.aperture_radius_m,
                "per_mode": {f"zern_{j}": z.as_dict() for j, z in zip(self.modes, self.zernike)},
                "per_g_m": self.C.tolist(),
                "panel_rms_m": self.panel_rms_m,
            },
            "effect_parameters": self.effect_parameters(),
            "positions": [
                {"position": p.position, "ha_deg": p.ha_deg, "dec_deg": p.dec_deg,
                 "elevation_deg": p.elevation_deg, "gravity": p.gravity.tolist(),
                 "temperature_c": p.temperature_c, "scans": p.scans,
                 "f": {"value": p.f, "sigma": p.sigma_f,
                       "predicted": float(self.predict_f(p.gravity)),
                       "predicted_gz_only": float(self._predict_gz(p))},
                 "zernike_m": None if p.zernike is None else
                 {f"zern_{j}": {"value": float(a), "sigma": float(s)}
                  for j, a, s in zip(self.modes, p.zernike, p.zernike_sigma)},
                 "residual_rms_m": p.residual_rms_m,
                 "df_dmode": None if p.leak is None else
                 {f"zern_{j}": float(k) for j, k in zip(self.modes, p.leak)}}
                for p in self.positions],
        }
        if sky is not None:
            doc["sky_map"] = sky_summary(sky)
        if figures:
            doc["figures"] = list(figures)
        return doc

    def _predict_gz(self, p: PositionRow) -> float:
        b = dict(zip(self.focal_gz.names, self.focal_gz.beta))
        v = b["f0"] + b["gz"] * p.gravity[2]
        if "dT" in b and p.temperature_c is not None:
            v += b["dT"] * (p.temperature_c - 15.0)
        return float(v)


def ruze_gain(eps_m, wavelength_m: float):
    """Ruze: ``G/G0 = exp(-(4 pi eps / lambda)^2)`` for an rms surface error ``eps`` (m)."""
    return np.exp(-((4 * np.pi * np.asarray(eps_m) / wavelength_m) ** 2))


def sky_summary(sky: dict) -> dict:
    """JSON form of a sky map: the grids and their extremes."""
    def arr(a):
        return [[None if not np.isfinite(v) else float(v) for v in row] for row in np.asarray(a)]

    out: dict = {"ha_deg": [float(h) for h in sky["ha_deg"]],
                 "dec_deg": [float(d) for d in sky["dec_deg"]]}
    for k, v in sky.items():
        if k in ("ha_deg", "dec_deg"):
            continue
        out[k] = arr(v)
        a = np.asarray(v, float)
        if np.any(np.isfinite(a)) and k != "elevation_deg":
            i = np.unravel_index(np.nanargmin(a), a.shape)
            j = np.unravel_index(np.nanargmax(a), a.shape)
            out[f"{k}_range"] = {
                "min": float(a[i]), "at_min": {"ha_deg": float(sky["ha_deg"][i[1]]),
                                               "dec_deg": float(sky["dec_deg"][i[0]])},
                "max": float(a[j]), "at_max": {"ha_deg": float(sky["ha_deg"][j[1]]),
                                               "dec_deg": float(sky["dec_deg"][j[0]])}}
    return out


def _positions(samples: Sequence[ScanSample], modes, aperture: float, layout=None
               ) -> list[PositionRow]:
    by: dict[str, list[ScanSample]] = {}
    for s in samples:
        by.setdefault(s.position, []).append(s)
    rows = []
    for pos, ss in by.items():
        w = np.array([1.0 / s.sigma_f**2 for s in ss])
        f = float(np.sum(w * np.array([s.f for s in ss])) / np.sum(w))
        sf = float(1.0 / math.sqrt(np.sum(w)))
        fr = cv = None
        if all(s.shared_f for s in ss):  # one two-face estimate, repeated by its scans
            f, sf, fr, cv = ss[0].f, ss[0].sigma_f, ss[0].f_response, ss[0].cell_var
        z = zs = rr = leak = ret = None
        ok = [s for s in ss if s.X is not None and len(s.X) > 3 * (len(modes) + 3)]
        if ok and all(s.shared_f for s in ss):  # one surface seen by both faces: one projection
            proj = [zernike_projection(np.concatenate([s.X for s in ok]),
                                       np.concatenate([s.deviation_m for s in ok]), aperture,
                                       modes, layout=layout)]
        else:
            proj = [zernike_projection(s.X, s.deviation_m, aperture, modes, layout=layout)
                    for s in ok]
        if proj and modes:
            a = np.array([p[0] for p in proj])
            sa = np.array([p[1] for p in proj])
            wz = 1.0 / sa**2
            z = np.sum(wz * a, 0) / np.sum(wz, 0)
            zs = 1.0 / np.sqrt(np.sum(wz, 0))
            rr = float(np.median([p[2] for p in proj]))
            if len(ok) == len(ss) and all(s.leak is not None for s in ss):
                # the position's f and mode coefficients are weighted means of its scans':
                # so are their responses to the modes
                leak = np.sum(w[:, None] * np.array([s.leak for s in ss]), 0) / np.sum(w)
                ret = np.sum(wz[:, :, None] * np.array([s.retention for s in ss]), 0) \
                    / np.sum(wz, 0)[:, None]
        temps = [s.temperature_c for s in ss if s.temperature_c is not None]
        s0 = ss[0]
        rows.append(PositionRow(pos, np.mean([s.gravity for s in ss], 0), f, sf, s0.ha_deg,
                                s0.dec_deg, s0.elevation_deg,
                                float(np.mean(temps)) if temps else None, z, zs, rr,
                                [s.id for s in ss], leak, ret, fr, cv))
    return rows


def _joint_regression(G, y, sy, T, cols_f: Sequence[str], Z, SZ, K, M):
    """Focal length and modes regressed on g together, with the positions' mode responses.

    ``f_p = design_f(p) beta_f + sum_k K_pk (a0_k + C_k . g_p)`` and
    ``z_pj = sum_k M_pjk (a0_k + C_k . g_p)`` (the residuals' mode projections), weighted by
    ``1 / sigma^2``. Returns the focal :class:`LinearFit` (its block of the covariance, chi2
    over the focal rows) and one per mode (chi2 over that mode's rows).
    """
    zc = ("a0", "gx", "gy", "gz")
    Af = _design(G, cols_f, T)
    Ag = _design(G, zc)
    n, pf = Af.shape
    nm = Z.shape[1]
    A = np.zeros((n * (1 + nm), pf + 4 * nm))
    A[:n, :pf] = Af
    for k in range(nm):
        cols = slice(pf + 4 * k, pf + 4 * k + 4)
        A[:n, cols] = K[:, k: k + 1] * Ag
        for j in range(nm):
            A[n * (1 + j): n * (2 + j), cols] = M[:, j, k: k + 1] * Ag
    yy = np.concatenate([y, Z.T.reshape(-1)])
    ss = np.concatenate([sy, SZ.T.reshape(-1)])
    w = 1.0 / ss**2
    cov = np.linalg.inv(A.T @ (A * w[:, None]))
    beta = cov @ (A.T @ (w * yy))
    r2 = w * (yy - A @ beta) ** 2
    focal = LinearFit(tuple(cols_f), beta[:pf], cov[:pf, :pf], float(np.sum(r2[:n])), n - pf)
    zfits = []
    for j in range(nm):
        b = slice(pf + 4 * j, pf + 4 * j + 4)
        zfits.append(LinearFit(zc, beta[b], cov[b, b],
                               float(np.sum(r2[n * (1 + j): n * (2 + j)])), n - 4))
    return focal, zfits


def corrected_modes(modes: Sequence[int], M: np.ndarray, *, min_retention: float = 0.2
                    ) -> tuple[int, ...]:
    """The modes whose take-up by the adjustment is corrected: kept in the residuals at
    least ``min_retention`` (median over positions of ``M_jj``), defocus excepted.

    Defocus (Noll 4) *is* a change of focal length: the fitted ``f`` absorbs it by definition.
    Modes the pose absorbs almost completely (coma) are left uncorrected: their residual
    projections carry too little of them to be estimated, and they hardly move ``f``.
    """
    d = np.median(np.array([np.diag(m) for m in M]), axis=0)
    return tuple(j for k, j in enumerate(modes) if j not in FOCUS_MODES
                 and d[k] >= min_retention)


def gravity_model(
    source,
    *,
    modes: Sequence[int] = DEFAULT_ZERNIKE_MODES,
    temperature: bool = False,
    aperture_radius_m: float | None = None,
    latitude_deg: float | None = None,
    reference_g: Sequence[float] = (0.0, 0.0, -1.0),
    correct_leakage: bool = True,
) -> GravityModel:
    """Estimate the gravity model from per-scan fits.

    ``source``: a :class:`~hartrao_jax.fit.CampaignFit`, a joint fit
    (:class:`~hartrao_jax.fit._joint.JointFit` or its ``campaign_fit()``: both carry the shared
    calibration), a results directory
    (``fit.json`` + ``residuals/``), or a list of :class:`ScanSample`. ``temperature``: add
    ``df/dT (T - 15 C)`` to the focal-length model (needs the scans' temperatures).
    ``reference_g``: gravity at which the surface was set (the change of the modes is measured
    from there; default the zenith).

    ``correct_leakage``: the per-scan adjustment has no surface modes, so a scan's ``f`` takes
    up part of them (astigmatism above all, through its geometry-dependent correlation with the
    calibration and the pose) and its residuals keep only part: regressing ``f`` on ``g`` alone
    then biases ``df/dg`` by the modes' own gravity dependence (on the simulated campaign the
    transverse terms by -0.1 and -0.2 mm, 2 and 6 sigma). With each scan's
    :func:`mode_response` (needs the points: in memory, or the residual tables and the
    campaign), ``f`` and the modes are regressed on ``g`` together
    (:func:`_joint_regression`) for the modes :func:`corrected_modes` selects.
    """
    camp = getattr(source, "campaign", None)
    modes = tuple(int(j) for j in modes)
    if isinstance(source, (str, Path)):
        doc = json.loads((Path(source) / "fit.json").read_text()) \
            if (Path(source) / "fit.json").is_file() else {}
        if doc.get("campaign") and (Path(doc["campaign"]) / "campaign.toml").is_file():
            camp = load_campaign(doc["campaign"])
    if aperture_radius_m is None:
        aperture_radius_m = camp.telescope.diameter_m / 2 if camp is not None else 12.95
    want = modes if correct_leakage else ()
    if isinstance(source, (str, Path)):
        samples = samples_from_dir(source, with_points=bool(modes), modes=want,
                                   aperture_radius_m=aperture_radius_m)
    elif isinstance(source, (list, tuple)) and source and isinstance(source[0], ScanSample):
        samples = list(source)
    else:
        samples = samples_from_fit(source, with_points=bool(modes), modes=want,
                                   aperture_radius_m=aperture_radius_m)
    if latitude_deg is None:
        latitude_deg = camp.site.latitude_deg if camp is not None else -25.8897
    tel = camp.telescope if camp is not None else None
    if tel is None:
        tel = default_campaign().telescope
    layout = ((tel.ring_edges_m, tel.panels_per_ring)
              if tel.ring_edges_m is not None and tel.panels_per_ring is not None else None)
    rows = _positions(samples, modes, aperture_radius_m, layout)
    G = np.array([r.gravity for r in rows])
    y = np.array([r.f for r in rows])
    sy = np.array([r.sigma_f for r in rows])
    T = None
    if temperature:
        if any(r.temperature_c is None for r in rows):
            raise ValueError("gravity model with temperature: some scans have no temperature_c")
        T = np.array([r.temperature_c for r in rows])
    extra = ("dT",) if temperature else ()
    cols_full = ("f0", "gx", "gy", "gz") + extra
    cols_red = ("f0", "gz") + extra
    if len(rows) < len(cols_full) + 1:
        raise ValueError(f"gravity model: {len(rows)} positions, need at least "
                         f"{len(cols_full) + 1} for the test of the transverse components")
    zfits = []
    with_modes = bool(modes) and all(r.zernike is not None for r in rows)
    corrected: tuple[int, ...] = ()
    if with_modes and correct_leakage and all(r.leak is not None for r in rows):
        M = np.array([r.retention for r in rows])
        corrected = corrected_modes(modes, M)
    if corrected:
        Z = np.array([r.zernike for r in rows])
        SZ = np.array([r.zernike_sigma for r in rows])
        K = np.array([r.leak for r in rows])
        fix = [k for k, j in enumerate(modes) if j not in corrected]
        K[:, fix] = 0.0  # f owns them (defocus) or they hardly move it (coma)
        M[:, fix, :] = 0.0
        M[:, :, fix] = 0.0
        M[:, fix, fix] = 1.0  # as before: the residual projection is the mode
        full, zfits = _joint_regression(G, y, sy, T, cols_full, Z, SZ, K, M)
        red, _ = _joint_regression(G, y, sy, T, cols_red, Z, SZ, K, M)
    else:
        cov_y = f_covariance(rows)
        full = weighted_lsq(_design(G, cols_full, T), y, sy, cols_full, cov_y)
        red = weighted_lsq(_design(G, cols_red, T), y, sy, cols_red, cov_y)
    test = nested_test(red, full)
    if with_modes and not corrected:
        Z = np.array([r.zernike for r in rows])
        SZ = np.array([r.zernike_sigma for r in rows])
        A = _design(G, ("a0", "gx", "gy", "gz"))
        zfits = [weighted_lsq(A, Z[:, k], SZ[:, k], ("a0", "gx", "gy", "gz"))
                 for k in range(len(modes))]
    elif not with_modes:
        modes = ()
    rms = [r.residual_rms_m for r in rows if r.residual_rms_m is not None]
    return GravityModel(rows, full, red, test, modes, zfits,
                        float(np.median(rms)) if rms else None, float(aperture_radius_m),
                        float(latitude_deg), np.asarray(reference_g, float), temperature,
                        corrected)


# --------------------------------------------------------------------------------------------
# Figures and files
# --------------------------------------------------------------------------------------------


def plot_gravity(gm: GravityModel, sky: dict, out_dir) -> list[str]:
    """``gravity_f.png`` (f against g_z, both models) and ``gravity_sky.png`` (maps).

    ``out_dir``: a directory (each PNG written atomically) or a :class:`._safeio.OutputDir`
    transaction (the PNGs become files of its result).
    """

    def save(fig, name):
        if isinstance(out_dir, OutputDir):
            out_dir.savefig(name, fig, dpi=110)
        else:
            write_file_atomic(Path(out_dir) / name, lambda t: fig.savefig(t, format="png",
                                                                          dpi=110))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir.root if isinstance(out_dir, OutputDir) else out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    gz = np.array([p.gravity[2] for p in gm.positions])
    f = np.array([p.f for p in gm.positions])
    sf = np.array([p.sigma_f for p in gm.positions])
    pred = np.array([gm.predict_f(p.gravity) for p in gm.positions])
    predz = np.array([gm._predict_gz(p) for p in gm.positions])
    ax[0].errorbar(gz, (f - gm.f0) * 1e3, yerr=sf * 1e3, fmt="o", ms=3, label="per position")
    o = np.argsort(gz)
    ax[0].plot(gz[o], (predz[o] - gm.f0) * 1e3, "-", label="model: g_z only")
    ax[0].plot(gz, (pred - gm.f0) * 1e3, "x", label="model: g_x, g_y, g_z")
    ax[0].set_xlabel("g_z (telescope frame)")
    ax[0].set_ylabel("f - f0 [mm]")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"focal length; transverse terms: p = {gm.test['p_value_F']:.2g} (F-test)")
    ax[1].errorbar(np.arange(len(f)), (f - pred) * 1e3, yerr=sf * 1e3, fmt="o", ms=3)
    ax[1].axhline(0, color="k", lw=0.5)
    ax[1].set_xticks(np.arange(len(f)))
    ax[1].set_xticklabels([p.position for p in gm.positions], rotation=90, fontsize=6)
    ax[1].set_ylabel("f - model [mm]")
    ax[1].set_title("residuals of the full model")
    fig.tight_layout()
    p = out / "gravity_f.png"
    save(fig, p.name)
    plt.close(fig)
    files.append(p.name)

    keys = [("f_m", "predicted f - f(zenith) [mm]", 1e3, -float(gm.predict_f(gm.reference_g))),
            ("surface_rms_m", "surface rms (modes + panels) [mm]", 1e3, 0.0),
            ("ruze_gain_2.5cm", "Ruze G/G0 at 2.5 cm", 1.0, 0.0),
            ("ruze_gain_1.3cm", "Ruze G/G0 at 1.3 cm", 1.0, 0.0)]
    fig, axs = plt.subplots(2, 2, figsize=(11, 8))
    ha, dec = sky["ha_deg"], sky["dec_deg"]
    for a, (k, title, scale, off) in zip(axs.ravel(), keys):
        m = a.pcolormesh(ha, dec, (np.asarray(sky[k]) + off) * scale, shading="auto")
        fig.colorbar(m, ax=a)
        a.contour(ha, dec, sky["elevation_deg"], levels=[10, 30, 60], colors="w",
                  linewidths=0.5)
        a.plot([p.ha_deg for p in gm.positions], [p.dec_deg for p in gm.positions], "k.", ms=3)
        a.set_title(title)
        a.set_xlabel("HA [deg]")
        a.set_ylabel("DEC [deg]")
    fig.tight_layout()
    p = out / "gravity_sky.png"
    save(fig, p.name)
    plt.close(fig)
    files.append(p.name)
    return files


def write_gravity(results_dir, out_dir=None, *, modes: Sequence[int] = DEFAULT_ZERNIKE_MODES,
                  temperature: bool = False, step_deg: float = 2.0, figures: bool = True,
                  source=None) -> tuple[Path, GravityModel]:
    """``gravity.json`` (schema ``hartrao-gravity/1``) and figures for a results directory.

    The results directory must hold a complete fit (:func:`._safeio.verify_result_dir`).
    Crash-safe: the figures go to temporary names, ``gravity.json`` (strict JSON, listing
    them) is written last.
    """

    if source is None:
        verify_result_dir(results_dir, "fit.json")
    out = Path(out_dir or results_dir)
    gm = gravity_model(source if source is not None else results_dir, modes=modes,
                       temperature=temperature)
    sky = gm.sky_map(step_deg=step_deg)
    with OutputDir(out, "gravity.json") as od:
        figs = plot_gravity(gm, sky, od) if figures else []
        p = od.commit(gm.to_json(sky=sky, figures=figs), indent=1)
    return p, gm


__all__ = ["FOCUS_MODES", "GRAVITY_SCHEMA", "GravityModel", "LinearFit", "ScanSample",
           "corrected_modes", "gravity_grid", "gravity_model", "mode_response",
           "nested_test", "plot_gravity", "ruze_gain",
           "samples_from_dir", "samples_from_fit", "weighted_lsq", "write_gravity",
           "surface_rms", "zernike_np", "zernike_projection"]
