"""Sensitivity of the estimates to calibration parameters held fixed and to the scan design.

Implicit derivatives through the converged Gauss-Helmert solver (implicit function theorem), not
differentiation through its iterations. At the solution of a scan with unknowns ``x`` and a
calibration parameter vector ``p`` held fixed, the normal-equation gradient vanishes:

    ``g(x, p) = A^T M^-1 w = 0``  (``n`` of :func:`._ghm.normal_equations`),

so ``dx/dp = -(dg/dx)^-1 dg/dp = -N_xx^-1 N_xp``: ``N_xx`` and ``N_xp`` are blocks of the normal
matrix of a model whose free parameters are ``x`` *and* ``p``, linearised at the converged
``(l + v, x, p)`` -- one small linear solve (lineax, Cholesky with Jacobi scaling). The terms
dropped against the exact Hessian are of the order residual x curvature (Gauss-Newton), well
below 1e-3 relative here; the tests check against refits with ``p`` perturbed.

From ``dx/dp``:

* focal length per scan and position: the ``f`` row;
* panel deviations: ``d dev_i/dp = (d dev_i/d(x, p)) . (dx/dp, e_p)`` per point by ``jax.jvp``,
  averaged per panel (north-aligned panel ids);
* sigma0: ``Omega = v^T Sigma^-1 v`` changes by ``2 n_p dp + Nr_pp dp^2`` with
  ``Nr_pp = N_pp - N_px N_xx^-1 N_xp`` (envelope theorem; ``n_p = 0`` when ``p`` sits at its
  estimate), ``sigma0^2 = Omega / (n - u)``.

Two-face positions (the default of ``fit``): the same theorem applied to the adjustment with
the surface random effect (:func:`position_sensitivity`): the cells' predictions are eliminated
from the normal matrix over ``(x, p)`` by Schur complement (their priors and the smooth modes'
priors included, variance components held), with exact second derivatives by autodiff, so
``dx/dp`` is the derivative of the estimates ``fit`` reports (refits agree to 0.2 % of the
largest element; Gauss-Newton alone was 2 % off there, because a cell's residuals are pulled by
its prior and the dropped residual x curvature terms no longer average out). ``positions[]``
of ``sensitivity.json`` carry these, the per-cycle white-noise derivatives beside them.

Scan design: white-noise covariances scale with ``1 / n_points`` and ``n_points ~ step^-2``,
so the white part of sigma(f) goes as ``step / step0``; the part the surface random effect
puts into sigma(f) (the panel pattern blurs f however many points sample it) does not, so
given the two-face adjustments of the positions ``sigma_f(step)^2 = sigma_w^2 (step /
step0)^2 + sigma_s^2`` (``sigma_w``: the white-noise sigma of both faces together,
``sigma_s^2 = sigma_f^2 - sigma_w^2``); one face instead of two: the normal equations
restricted to the face-1 points (x4, x6, x7 flip sign between faces; with one face they are
not separable from the pose -- the condition number says so).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax import lax

from .._programs import cached_jit
from ..campaign._safeio import write_file_atomic, write_json_atomic
from ..fit._fit import scan_arrays, sigma_vector
from ..fit._joint import ScanProblem, bucket_size, chunk_for, condition_number
from ..fit._projection import hit_points
from ..fit._results import CampaignFit, ScanFit
from ..geometry._geometry import face_of, panel_cells, panel_ids, paraboloid_deviation
from ..model._model import make_model, parameter_unit
from ..physics._catalog import CALIBRATION, INSTRUMENT
from ..solver._ghm import gauss_helmert, normal_equations
from ..solver._mixed import gauss_helmert_mixed

SENSITIVITY_SCHEMA = "hartrao-sensitivity/1"
ARCSEC = math.pi / (180 * 3600)
DEFAULT_PARAMS = CALIBRATION
DESIGN_STEPS_RAD = (0.00063, 0.001, 0.0016, 0.003, 0.006, 0.01, 0.02, 0.03)


# --------------------------------------------------------------------------------------------
# Core: implicit derivatives of one converged scan
# --------------------------------------------------------------------------------------------


def solve_columns(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A^-1 B`` for a symmetric positive definite ``A`` (lineax Cholesky, Jacobi scaled)."""
    A = jnp.asarray(A, jnp.float64)
    B = jnp.asarray(B, jnp.float64).reshape(A.shape[0], -1)
    d = 1.0 / jnp.sqrt(jnp.where(jnp.diagonal(A) > 0, jnp.diagonal(A), 1.0))
    op = lx.MatrixLinearOperator(A * d[:, None] * d[None, :], lx.positive_semidefinite_tag)
    sol = jax.vmap(lambda b: lx.linear_solve(op, b * d, lx.Cholesky()).value * d,
                   in_axes=1, out_axes=1)(B)
    return np.asarray(sol)


@cached_jit
def _deviation_jvp(model, l, c, xp, T, f_index):
    """``d dev_i / d xp . T`` for every point: (n, q) (m per unit of the tangent columns)."""

    def dev(xx, li, ci):
        return paraboloid_deviation(model.telescope_point(li, xx, ci), xx[f_index])

    def one(li, ci):
        return jax.vmap(lambda t: jax.jvp(lambda xx: dev(xx, li, ci), (xp,), (t,))[1],
                        in_axes=1)(T)

    return jax.lax.map(lambda lc: one(*lc), (l, c), batch_size=4096)


@dataclass
class ScanSensitivity:
    """Implicit derivatives of one scan's estimates w.r.t. the held-fixed parameters ``params``.

    ``dxdp[i, j] = d x_i / d p_j`` (units of x_i per unit of p_j); ``names`` the estimated
    unknowns; ``N`` the normal matrix over ``names + params`` at the solution (sigma0 = 1);
    ``n_p`` the gradient w.r.t. ``p`` (0 when p sits at its estimate); ``Nr_pp`` the reduced
    normal matrix of ``p``; ``panel_dp`` (panels, q) the derivative of each panel's mean
    deviation (m per unit of p; NaN for panels without points).
    """

    id: str
    position: str
    cycle: int
    names: tuple[str, ...]
    params: tuple[str, ...]
    p: np.ndarray
    x: np.ndarray
    dxdp: np.ndarray
    N: np.ndarray
    n_p: np.ndarray
    Nr_pp: np.ndarray
    sigma0: float
    redundancy: int
    n_points: int
    elevation_deg: float
    panel_dp: np.ndarray | None = None
    design: dict = field(default_factory=dict)

    @property
    def df_dp(self) -> np.ndarray:
        return self.dxdp[self.names.index("f")]

    def dsigma0_dp(self) -> np.ndarray:
        """First derivative of sigma0 (per unit of p)."""
        return self.n_p / (self.sigma0 * self.redundancy)

    def sigma0_after(self, dp: np.ndarray) -> float:
        """sigma0 with ``p`` off by ``dp`` and ``x`` re-estimated (second order)."""
        dp = np.asarray(dp, float)
        om = self.sigma0**2 * self.redundancy + 2 * self.n_p @ dp + dp @ self.Nr_pp @ dp
        return math.sqrt(max(om, 0.0) / self.redundancy)

    def correlation(self, with_params: bool = True) -> tuple[tuple[str, ...], np.ndarray]:
        """Correlation matrix of the unknowns (with ``p`` estimated too, or held fixed)."""
        u = len(self.names)
        N = self.N if with_params else self.N[:u, :u]
        names = self.names + self.params if with_params else self.names
        d = np.diag(N)
        s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
        Q = np.linalg.inv(N * s[:, None] * s[None, :]) * s[:, None] * s[None, :]
        q = np.sqrt(np.diag(Q))
        return names, Q / np.outer(q, q)


def _p_values(s: ScanFit, params: Sequence[str]) -> np.ndarray:
    fixed = dict(zip(s.model.fixed_names, np.asarray(s.model.fixed_values).tolist()))
    return np.array([s.value(p) if p in s.names else fixed.get(p, 0.0) for p in params], float)


def scan_problem_model(s: ScanFit, params: Sequence[str], aperture_radius_m: float):
    """``(names, model_x, model_xp, x, p)``: the model with ``params`` held fixed at their
    values, and the one with them free (the latter gives ``N_xp``)."""
    params = tuple(params)
    names = tuple(n for n in s.names if n not in params)
    p = _p_values(s, params)
    fixed = dict(zip(s.model.fixed_names, np.asarray(s.model.fixed_values).tolist()))
    fixed_x = {**{k: v for k, v in fixed.items() if k not in params}, **dict(zip(params, p))}
    fixed_xp = {k: v for k, v in fixed.items() if k not in params}
    kw = dict(shift_window_s=s.model.shift_window_s, osc_period_s=s.model.osc_period_s,
              kappa_rad=s.model.kappa_rad, aperture_radius_m=aperture_radius_m)
    model_x = make_model(names, fixed_x, check_separable=False, **kw)
    model_xp = make_model(names + params, fixed_xp, check_separable=False, **kw)
    if tuple(model_xp.free) != names + params:
        raise ValueError(f"parameter order {model_xp.free} != {names + params}: object "
                         "parameters must come first")
    x = np.array([s.value(n) for n in names])
    return names, model_x, model_xp, x, p


def scan_sensitivity(campaign, s: ScanFit, params: Sequence[str] = DEFAULT_PARAMS, *,
                     n_pad: int | None = None, panels: bool = True, design: bool = True
                     ) -> ScanSensitivity:
    """Implicit derivatives of one converged scan fit (see the module docstring)."""
    params = tuple(params)
    tel = campaign.telescope
    names, model_x, model_xp, x, p = scan_problem_model(s, params, tel.diameter_m / 2)
    sig = sigma_vector(campaign)
    prob = ScanProblem.from_fit(s, sig, n_pad or bucket_size(len(s.data)))
    xp = np.concatenate([x, p])
    ne = normal_equations(model_xp, prob.l, xp, sig, prob.c, prob.w, prob.v,
                          chunk_size=chunk_for(len(prob.l)))
    N = np.asarray(ne.N)
    u = len(names)
    Nxx, Nxp, Npp = N[:u, :u], N[:u, u:], N[u:, u:]
    dxdp = -solve_columns(Nxx, Nxp)
    n_p = np.asarray(ne.n)[u:]
    # omega at the solution with p fixed: from the fit (x, v converged for this problem)
    red = int(prob.n_used - u)
    omega = float(s.sigma0**2 * (prob.n_used - len(s.names)))
    sigma0 = math.sqrt(omega / max(red, 1))
    out = ScanSensitivity(
        s.meta.id, s.meta.position, s.meta.cycle, names, params, p, x, dxdp, N, n_p,
        Npp + Nxp.T @ dxdp, sigma0, red, prob.n_used, s.elevation_deg)
    if panels and tel.ring_edges_m is not None and tel.panels_per_ring is not None:
        out.panel_dp = panel_derivatives(s, model_xp, xp, dxdp, names.index("f"), tel)
    if design:
        out.design = face_design(campaign, s, prob, model_x, model_xp, x, xp, u)
    return out


def panel_derivatives(s: ScanFit, model_xp, xp, dxdp, f_index: int, tel) -> np.ndarray:
    """Derivative (m per unit of p) of each panel's mean deviation, shape (panels, q)."""

    l, c = scan_arrays(s.data)
    used = s.used
    q = dxdp.shape[1]
    T = np.vstack([dxdp, np.eye(q)])
    n = int(used.sum())
    n_pad = bucket_size(n)
    lu, cu = l[used], c[used]
    if n_pad > n:
        lu = np.concatenate([lu, np.repeat(lu[-1:], n_pad - n, 0)])
        cu = np.concatenate([cu, np.repeat(cu[-1:], n_pad - n, 0)])
    D = np.asarray(_deviation_jvp(model_xp, jnp.asarray(lu), jnp.asarray(cu), jnp.asarray(xp),
                                  jnp.asarray(T), f_index))[:n]
    X = s.X_tel[used]
    rho = np.hypot(X[:, 0], X[:, 1])
    psi = np.mod(np.arctan2(X[:, 1], X[:, 0]), 2 * np.pi)
    pid = panel_ids(rho, psi, tel.ring_edges_m, tel.panels_per_ring)
    n_panels = int(sum(tel.panels_per_ring))
    ok = pid >= 0
    cnt = np.bincount(pid[ok], minlength=n_panels).astype(float)
    out = np.full((n_panels, q), np.nan)
    for j in range(q):
        tot = np.bincount(pid[ok], weights=D[ok, j], minlength=n_panels)
        out[:, j] = np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)
    return out


# --------------------------------------------------------------------------------------------
# Two-face position adjustment (surface random effect)
# --------------------------------------------------------------------------------------------


@dataclass
class PositionSensitivity:
    """Implicit derivatives of one position's two-face adjustment with the surface random
    effect (the default of ``fit``) w.r.t. the held-fixed ``params``.

    At the solution of :func:`..solver.gauss_helmert_mixed` the penalised normal equations in
    the unknowns ``x`` and the cells' predictions ``u`` vanish; with the variance components
    held at their estimates, ``dx/dp = -Nr_xx^-1 Nr_xp``, where ``Nr`` is the normal matrix over
    ``(x, p)`` with the cells eliminated (Schur complement, their priors included) and the
    smooth modes' priors added: the derivative of exactly the estimates ``fit`` reports.
    ``dudp`` (cells, k, q): how each cell's prediction moves (offset m, tilts rad per unit of
    p): ``du/dp = -(S_g + Lambda)^-1 (s_gx dx/dp + s_gp)``; ``panel_dp`` its offset column
    (NaN for cells without points).
    """

    position: str
    faces: int
    elevation_deg: float
    names: tuple[str, ...]
    params: tuple[str, ...]
    p: np.ndarray
    x: np.ndarray
    dxdp: np.ndarray
    dudp: np.ndarray
    n_points: int

    @property
    def df_dp(self) -> np.ndarray:
        return self.dxdp[self.names.index("f")]

    @property
    def panel_dp(self) -> np.ndarray:
        return self.dudp[:, 0, :]


def _position_arrays(campaign, pf, model):
    """Observations, constants, weights, cells and design of a position's adjusted points,
    padded to a size bucket (weight 0, no cell), the cells as :func:`..fit.fit_position`
    assigns them (:func:`..fit.hit_points`)."""
    st = pf.mixed
    tel = campaign.telescope
    parts = [scan_arrays(s.data) for s in pf.scans]
    l = np.concatenate([a for a, _ in parts])
    c = np.concatenate([b for _, b in parts])
    w = np.concatenate([s.used for s in pf.scans]).astype(float)
    n = len(l)
    size = bucket_size(n)
    if size > n:
        l = np.concatenate([l, np.repeat(l[:1], size - n, 0)])
        c = np.concatenate([c, np.zeros((size - n, c.shape[1]))])
        w = np.concatenate([w, np.zeros(size - n)])
    sig = sigma_vector(campaign)
    X = np.asarray(hit_points(model, l, jnp.asarray(st.x), c, sig, st.kappa_rad))
    cell, local, _, _ = panel_cells(X, tel.ring_edges_m, tel.panels_per_ring, cell_m=st.cell_m,
                                    keys=st.cell_keys)
    cell = np.where(w > 0, cell, -1)
    design = np.column_stack([np.ones(size), local]) * (cell >= 0)[:, None]
    return l, c, w, cell, design, sig, n


@cached_jit
def _exact_sums(model, l, c, w, s2, cell, design, x, U, n_cells: int, chunk: int = 4096):
    """Half-Hessians of the objective ``sum_i w_i F_i^2 / (b_i Sigma b_i^T)`` (the points'
    ``v^T Sigma^-1 v`` to first order; the cells' prior is added by the caller) at
    ``(x, U)``, summed as the mixed solver sums its normal equations: ``N`` (u, u), per cell
    ``S`` (g, k, k) and ``s_g`` (g, k, u). Exact second derivatives by autodiff, not the
    Gauss-Newton ``q a a^T``: at a random-effect solution the residuals of a cell are pulled
    by its prior (``sum q d r = -Lambda u``), so the dropped terms do not average out (2 % of
    dx/dp on the test campaign)."""
    u, k = x.shape[0], design.shape[1]
    live = cell >= 0
    gi = jnp.where(live, cell, 0)
    dev = jnp.where(live, jnp.sum(design * U[gi], axis=-1), 0.0)

    def one(li, ci, wi, di, Di):
        def phi(z):  # the point's v^T Sigma^-1 v to first order: F^2 / (b Sigma b^T), / 2
            def F(ll):
                return model(ll, z[:u], ci.at[1].add(z[u]))

            Fv, b = jax.value_and_grad(F)(li)
            m = jnp.sum(b * b * s2)
            return 0.5 * jnp.where(m > 0, Fv * Fv / jnp.where(m > 0, m, 1.0), 0.0)

        H = jnp.where(wi > 0, wi, 0.0) * jax.hessian(phi)(jnp.concatenate([x, di[None]]))
        return H[:u, :u], H[u, u] * jnp.outer(Di, Di), Di[:, None] * H[u, :u][None, :]

    n = l.shape[0]
    nc = -(-n // chunk)
    pad = nc * chunk - n

    def shaped(a):
        return jnp.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1)).reshape((nc, chunk) + a.shape[1:])

    def body(carry, ch):
        N, S, sg = carry
        Hxx, Huu, Hux = jax.vmap(one)(*ch[:5])
        seg = jnp.where(ch[5] >= 0, ch[5], n_cells)
        S = S + jax.ops.segment_sum(Huu, seg, n_cells + 1)[:n_cells]
        sg = sg + jax.ops.segment_sum(Hux, seg, n_cells + 1)[:n_cells]
        return (N + jnp.sum(Hxx, 0), S, sg), None

    f = x.dtype
    init = (jnp.zeros((u, u), f), jnp.zeros((n_cells, k, k), f), jnp.zeros((n_cells, k, u), f))
    (N, S, sg), _ = lax.scan(body, init, tuple(shaped(a) for a in (l, c, w, dev, design, cell)))
    return N, S, sg


def _held(pf, params: tuple[str, ...]):
    """Split a two-face position's unknowns for :func:`position_sensitivity` and its refits:
    ``(model, free, fixed, xs, names)`` -- the fit's model and unknowns, its fixed values,
    the estimates by name, and the unknowns left once ``params`` are held."""
    mdl = pf.mixed.model
    free = tuple(mdl.free)
    fixed = dict(zip(mdl.fixed_names, np.asarray(mdl.fixed_values).tolist()))
    xs = dict(zip(free, np.asarray(pf.mixed.x).tolist()))
    return mdl, free, fixed, xs, tuple(n for n in free if n not in params)


def _model_like(mdl, free, fixed):
    """A model with ``free`` unknowns and ``fixed`` values, otherwise as ``mdl``."""
    return make_model(free, fixed, check_separable=False, shift_window_s=mdl.shift_window_s,
                      osc_period_s=mdl.osc_period_s, kappa_rad=mdl.kappa_rad,
                      aperture_radius_m=mdl.aperture_radius_m)


def position_sensitivity(campaign, pf, params: Sequence[str] = DEFAULT_PARAMS
                         ) -> PositionSensitivity:
    """Implicit derivatives of a two-face position fit (:class:`..fit.PositionFit` with its
    random-effect state ``mixed``): see :class:`PositionSensitivity`. Parameters free in the
    fit are held at their estimates, the others at the model's fixed values (0 if not given);
    the smooth modes stay random effects with their estimated variance."""
    st = pf.mixed
    if st is None:
        raise ValueError(f"position {pf.position}: no surface random effect to differentiate")
    params = tuple(params)
    mdl, free, fixed, xs, names = _held(pf, params)
    p = np.array([xs[k] if k in xs else fixed.get(k, 0.0) for k in params], float)
    model_xp = _model_like(mdl, names + params,
                           {k: v for k, v in fixed.items() if k not in params})
    order = tuple(model_xp.free)
    ix = np.array([order.index(k) for k in names])
    ip = np.array([order.index(k) for k in params], int)
    xp = np.array([xs.get(k, 0.0) if k in names else p[params.index(k)] for k in order])
    l, c, w, cell, design, sig, n = _position_arrays(campaign, pf, mdl)
    se2, cell_var, ridge_var = st.var
    N, S, sg = (np.asarray(a) for a in _exact_sums(
        model_xp, jnp.asarray(l), jnp.asarray(c), jnp.asarray(w), jnp.asarray(sig**2),
        jnp.asarray(cell), jnp.asarray(design), jnp.asarray(xp), jnp.asarray(st.u), len(st.u)))
    lam = float(se2) / np.asarray(cell_var)
    Dinv = np.linalg.inv(S + np.diag(lam)[None])
    Nr = N - np.einsum("gki,gkl,glj->ij", sg, Dinv, sg)
    for j, (group, idx) in enumerate((st.ridge or {}).items()):
        for i in idx:  # the modes' priors: positions of the same names in the (x, p) order
            k = order.index(free[i])
            Nr[k, k] += float(se2) / float(np.asarray(ridge_var)[j])
    dxdp = -solve_columns(Nr[np.ix_(ix, ix)], Nr[np.ix_(ix, ip)])
    dudp = -np.einsum("gkl,glq->gkq", Dinv, np.einsum("gli,iq->glq", sg[:, :, ix], dxdp)
                      + sg[:, :, ip])
    empty = np.bincount(cell[cell >= 0], minlength=len(S)) == 0
    dudp[empty] = np.nan
    el = pf.scans[0].elevation_deg if pf.scans else float("nan")
    return PositionSensitivity(pf.position, pf.faces, el, names, params, p,
                               np.array([xs[k] for k in names]), dxdp, dudp,
                               int(np.sum(w > 0)))


def refit_position_with(campaign, pf, params: Sequence[str], p: Sequence[float], *,
                        max_iter: int = 8) -> tuple[tuple[str, ...], np.ndarray]:
    """Refit a two-face position with ``params`` held at ``p``: same points and cells, the
    variance components held at the fit's estimates, from its solution (the finite-difference
    check of :func:`position_sensitivity`). Returns ``(names, x)``."""
    st = pf.mixed
    params = tuple(params)
    mdl, free, fixed, xs, names = _held(pf, params)
    model = _model_like(mdl, names, {**{k: v for k, v in fixed.items() if k not in params},
                                     **dict(zip(params, map(float, p)))})
    l, c, w, cell, design, sig, _ = _position_arrays(campaign, pf, mdl)
    ridge = {g: [model.free.index(free[i]) for i in idx]
             for g, idx in (st.ridge or {}).items()} or None
    res = gauss_helmert_mixed(
        model, l, np.array([xs[k] for k in model.free]), sig, c, w, cell, design, len(st.u),
        cell_var0=np.asarray(st.var[1]), ridge=ridge,
        ridge_var0=np.asarray(st.var[2]) if ridge else 1e-8, noise_var0=float(st.var[0]),
        u0=np.asarray(st.u), estimate_variances=False, robust_k=None, tol=1e-9,
        max_iter=max_iter)
    return tuple(model.free), np.asarray(res.x)


def face_design(campaign, s: ScanFit, prob: ScanProblem, model_x, model_xp, x, xp, u) -> dict:
    """Condition numbers and sigma(f) with both faces and with face 1 only.

    ``calibrated``: the model with ``p`` free (two-face-sensitive calibration estimated);
    ``fixed``: ``p`` held (calibration known). With one face the calibrated model is close to
    singular: x4, x6, x7 are then inestimable.
    """
    sig = sigma_vector(campaign)
    face1 = (face_of(prob.l[:, 2]) == 1).astype(float)
    out = {}
    sigma0 = s.sigma0
    for label, w in (("two_faces", prob.w), ("one_face", prob.w * face1)):
        ne = normal_equations(model_xp, prob.l, xp, sig, prob.c, w, prob.v,
                              chunk_size=chunk_for(len(prob.l)))
        N = np.asarray(ne.N)
        i_f = list(model_xp.free).index("f")
        row = {"n_points": int(np.sum(w > 0))}
        for kind, M in (("calibrated", N), ("fixed", N[:u, :u])):
            k = condition_number(M)
            try:
                d = np.diag(M)
                sc = 1.0 / np.sqrt(d)
                Q = np.linalg.inv(M * sc[:, None] * sc[None, :]) * sc[:, None] * sc[None, :]
                sf = float(sigma0 * math.sqrt(Q[i_f, i_f])) if Q[i_f, i_f] > 0 else math.inf
            except np.linalg.LinAlgError:
                sf = math.inf
            row[kind] = {"condition_number": k, "sigma_f_m": sf if np.isfinite(k) and k < 1e15
                         else math.inf}
        out[label] = row
    return out


# --------------------------------------------------------------------------------------------
# Finite-difference check: refit with p perturbed (used by the tests and the benchmark)
# --------------------------------------------------------------------------------------------


def refit_with(campaign, s: ScanFit, params: Sequence[str], p: Sequence[float], *,
               n_pad: int | None = None, max_iter: int = 30, tol: float = 1e-10):
    """Refit one scan with ``params`` held at ``p``, from its solution and residuals (same
    points, no new rejection). Returns ``(names, x, sigma0)``."""
    params = tuple(params)
    tel = campaign.telescope
    names, _, _, x, _ = scan_problem_model(s, params, tel.diameter_m / 2)
    fixed = dict(zip(s.model.fixed_names, np.asarray(s.model.fixed_values).tolist()))
    fixed = {**{k: v for k, v in fixed.items() if k not in params}, **dict(zip(params, p))}
    model = make_model(names, fixed, check_separable=False, shift_window_s=s.model.shift_window_s,
                       osc_period_s=s.model.osc_period_s, kappa_rad=s.model.kappa_rad,
                       aperture_radius_m=tel.diameter_m / 2)
    sig = sigma_vector(campaign)
    prob = ScanProblem.from_fit(s, sig, n_pad or bucket_size(len(s.data)))
    res = gauss_helmert(model, prob.l, x, sig, prob.c, prob.w, v0=prob.v, max_iter=max_iter,
                        tol=tol, chunk_size=chunk_for(len(prob.l)))
    return names, np.asarray(res.x), float(res.sigma0)


def finite_difference(campaign, s: ScanFit, params: Sequence[str], *, step: float = ARCSEC,
                      n_pad: int | None = None) -> dict:
    """Central differences ``dx/dp`` and sigma0 at ``p +- step`` by refitting."""
    params = tuple(params)
    p0 = _p_values(s, params)
    cols, s0 = [], []
    for j in range(len(params)):
        e = np.zeros(len(params))
        e[j] = step
        names, xp, sp = refit_with(campaign, s, params, p0 + e, n_pad=n_pad)
        _, xm, sm = refit_with(campaign, s, params, p0 - e, n_pad=n_pad)
        cols.append((xp - xm) / (2 * step))
        s0.append((sp, sm))
    return {"names": names, "dxdp": np.array(cols).T, "sigma0_pm": s0}


# --------------------------------------------------------------------------------------------
# Campaign level
# --------------------------------------------------------------------------------------------


@dataclass
class CampaignSensitivity:
    campaign: object
    params: tuple[str, ...]
    scans: list[ScanSensitivity]
    model_names: tuple[str, ...]
    position_fits: list = field(default_factory=list)
    position_sens: list[PositionSensitivity] = field(default_factory=list)

    def positions(self) -> list[dict]:
        """Per position: the derivatives of its two-face adjustment (surface random effect;
        :func:`position_sensitivity`) where it has one, else the inverse-variance weighted mean
        of its scans' (cycles') white-noise derivatives; both are given for comparison."""
        by: dict[str, list[ScanSensitivity]] = {}
        for s in self.scans:
            by.setdefault(s.position, []).append(s)
        two = {ps.position: ps for ps in self.position_sens}
        rows = []
        for pos, ss in by.items():
            i_f = ss[0].names.index("f")
            w = []
            for s in ss:
                q = np.linalg.inv(s.N[: len(s.names), : len(s.names)])
                w.append(1.0 / q[i_f, i_f])
            w = np.array(w) / np.sum(w)
            dfdp = np.sum([wi * s.df_dp for wi, s in zip(w, ss)], axis=0)
            row = {"position": pos, "scans": [s.id for s in ss],
                   "elevation_deg": ss[0].elevation_deg,
                   "method": "per cycle (white noise), inverse-variance mean over the cycles",
                   "df_dp_m_per_unit": dict(zip(self.params, dfdp.tolist()))}
            if ss[0].panel_dp is not None:
                with np.errstate(all="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    P = np.nanmean(np.stack([s.panel_dp for s in ss]), axis=0)
                row["panel_dp"] = P
            if pos in two:
                ps = two[pos]
                row.update({
                    "method": "two-face adjustment, surface random effect (variance components "
                              "held): the derivatives of the estimates fit reports",
                    "faces": ps.faces,
                    "df_dp_m_per_unit": dict(zip(self.params, ps.df_dp.tolist())),
                    "df_dp_per_cycle_m_per_unit": dict(zip(self.params, dfdp.tolist())),
                    "dx_dp": {p: dict(zip(ps.names, ps.dxdp[:, j].tolist()))
                              for j, p in enumerate(self.params)},
                    "panel_dp": ps.panel_dp})
            rows.append(row)
        return rows

    def table_per_arcsec(self) -> list[dict]:
        """What an error of 1 arcsec (or 0.1 mm for a length) in each parameter does to f,
        the panel deviations and sigma0, per position."""
        out = []
        for row in self.positions():
            entry = {"position": row["position"], "elevation_deg": row["elevation_deg"]}
            for j, p in enumerate(self.params):
                unit = error_unit(p)
                d = {"error": unit[0], "error_unit": unit[1],
                     "delta_f_m": row["df_dp_m_per_unit"][p] * unit[0]}
                if "panel_dp" in row:
                    col = row["panel_dp"][:, j] * unit[0]
                    d["delta_panel_rms_m"] = float(np.sqrt(np.nanmean(col**2)))
                    d["delta_panel_max_m"] = float(np.nanmax(np.abs(col)))
                scans = [s for s in self.scans if s.position == row["position"]]
                dp = np.zeros(len(self.params))
                dp[j] = unit[0]
                d["sigma0_before"] = float(np.mean([s.sigma0 for s in scans]))
                d["sigma0_after"] = float(np.mean([s.sigma0_after(dp) for s in scans]))
                entry[p] = d
            out.append(entry)
        return out

    def surface_limited_f(self) -> list[dict]:
        """Per two-face position fit: sigma(f) (m) with the surface random effect, its white
        part ``sigma_w`` (the position fit's ``sigma_white``: what the noise contributes) and
        the surface part ``sigma_s = sqrt(sigma_f^2 - sigma_w^2)``."""
        rows = []
        for p in self.position_fits:
            if "f" not in p.names or p.sigma_white is None:
                continue
            i_f = list(p.names).index("f")
            total, white = float(p.sigma[i_f]), float(p.sigma_white[i_f])
            rows.append({"position": p.position, "faces": p.faces, "sigma_f_m": total,
                         "sigma_f_white_m": white,
                         "sigma_f_surface_m": math.sqrt(max(total**2 - white**2, 0.0))})
        return rows

    def surface_limited_median(self, lim: list[dict] | None = None) -> dict | None:
        """Medians over :meth:`surface_limited_f`'s positions (``lim`` if already computed),
        m: ``sigma_f_m``, ``sigma_f_white_m``, ``sigma_f_surface_m`` and ``n``; None without
        two-face fits."""
        lim = self.surface_limited_f() if lim is None else lim
        if not lim:
            return None
        keys = ("sigma_f_m", "sigma_f_white_m", "sigma_f_surface_m")
        return {**{k: float(np.median([r[k] for r in lim])) for k in keys}, "n": len(lim)}

    def design(self) -> dict:
        """Scan design: sigma(f) against the angular step; one face against two."""
        step0 = float(self.campaign.scanner.angular_step_rad)
        sf = {}
        for s in self.scans:
            q = np.linalg.inv(s.N[: len(s.names), : len(s.names)])
            sf.setdefault(s.position, []).append(s.sigma0 * math.sqrt(q[s.names.index("f"),
                                                                           s.names.index("f")]))
        sig_f = float(np.median([np.median(v) for v in sf.values()]))
        steps = sorted(set(DESIGN_STEPS_RAD) | {step0})
        lim = self.surface_limited_f()
        med = self.surface_limited_median(lim)
        sw, ss = (med["sigma_f_white_m"], med["sigma_f_surface_m"]) if med else (None, None)
        step_rows = [{"step_rad": st, "n_points_factor": (step0 / st) ** 2,
                      "sigma_f_m": sig_f * st / step0,
                      **({"sigma_f_two_face_m": math.hypot(sw * st / step0, ss)} if lim else {})}
                     for st in steps]
        faces = {}
        for key in ("two_faces", "one_face"):
            rows = [s.design[key] for s in self.scans if s.design]
            if not rows:
                continue
            faces[key] = {
                "n_points_median": float(np.median([r["n_points"] for r in rows])),
                **{kind: {
                    "condition_number_median": float(np.median([r[kind]["condition_number"]
                                                                for r in rows])),
                    "condition_number_max": float(np.max([r[kind]["condition_number"]
                                                          for r in rows])),
                    "sigma_f_m_median": float(np.median([r[kind]["sigma_f_m"] for r in rows]))}
                   for kind in ("calibrated", "fixed")}}
        return {
            "step": {"reference_step_rad": step0, "sigma_f_m_at_reference": sig_f,
                     "dsigma_f_dstep": sig_f / step0,
                     "model": "sigma_f_m: one scan, white noise: ~ 1/sqrt(n_points), n_points ~ "
                              "step^-2 (same coverage)" + (
                                  "; sigma_f_two_face_m: both faces with the surface random "
                                  "effect, sqrt(sigma_w^2 (step/step0)^2 + sigma_s^2): the "
                                  "surface part does not shrink with more points" if lim else ""),
                     "table": step_rows,
                     **({"two_face": {"sigma_f_white_m": sw, "sigma_f_surface_m": ss,
                                      "positions": lim}} if lim else {})},
            "faces": faces,
            "note": "with one face the two-face-sensitive parameters (" + ", ".join(
                p for p in self.params if INSTRUMENT.get(p) and INSTRUMENT[p].two_face != "no")
                + ") are not separable from the pose: the calibrated normal matrix is close to "
                  "singular (condition number); only a fixed (known) calibration gives a usable f",
        }


def error_unit(p: str) -> tuple[float, str]:
    """The error size used in the tables: 1 arcsec for angles, 0.1 mm for lengths, 1e-5 else."""
    u = parameter_unit(p)
    if u == "rad":
        return ARCSEC, "arcsec"
    if u == "m":
        return 1e-4, "0.1 mm"
    return 1e-5, "1e-5"


def sensitivity(
    campaign,
    start: CampaignFit,
    params: Sequence[str] = DEFAULT_PARAMS,
    *,
    panels: bool = True,
    design: bool = True,
    positions: Sequence = (),
) -> CampaignSensitivity:
    """Sensitivities of every scan of ``start`` (converged fits) to ``params`` held fixed.

    Parameters free in ``start`` are held at their estimates (the solution of the reduced
    problem is then the same point); the others at the model's fixed values (0 if not given).
    ``start`` may be a joint fit (:class:`._joint.JointFit`): the shared parameters are then held
    at their joint estimates. ``positions``: the two-face position fits of the same scans
    (:class:`..fit.PositionFit`, the default of ``fit``): the design then also says how much
    of sigma(f) is the surface's and does not shrink with a finer step.
    """
    if hasattr(start, "campaign_fit"):
        start = start.campaign_fit()
    params = tuple(params)
    scans = list(start.scans)
    n_pad = max(bucket_size(len(s.data)) for s in scans)
    out = [scan_sensitivity(campaign, s, params, n_pad=n_pad, panels=panels, design=design)
           for s in scans]
    two = [position_sensitivity(campaign, p, params) for p in positions
           if getattr(p, "mixed", None) is not None]
    return CampaignSensitivity(campaign, params, out, tuple(start.model_names),
                               list(positions), two)


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------


def _f(v):
    v = float(v)
    return v if math.isfinite(v) else None


def _clean(o):
    """JSON-safe copy: NumPy to Python, non-finite floats to None."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return _f(o)
    return o


def sensitivity_json(cs: CampaignSensitivity, *, figures: Sequence[str] = (),
                     validation: dict | None = None) -> dict:
    scans = []
    for s in cs.scans:
        names_c, C = s.correlation(True)
        names_x, Cx = s.correlation(False)
        rec = {
            "id": s.id, "position": s.position, "cycle": s.cycle,
            "elevation_deg": s.elevation_deg, "sigma0": s.sigma0, "redundancy": s.redundancy,
            "held_fixed": dict(zip(s.params, s.p.tolist())),
            "dx_dp": {p: dict(zip(s.names, s.dxdp[:, j].tolist())) for j, p in enumerate(s.params)},
            "dsigma0_dp": dict(zip(s.params, s.dsigma0_dp().tolist())),
            "gradient_n_p": dict(zip(s.params, s.n_p.tolist())),
            "reduced_normal_pp": s.Nr_pp.tolist(),
            "correlation_with_params": {"names": list(names_c), "matrix": C.tolist()},
            "correlation": {"names": list(names_x), "matrix": Cx.tolist()},
            "max_abs_corr_f_params": {p: float(abs(C[names_c.index("f"), names_c.index(p)]))
                                      for p in s.params},
        }
        if s.panel_dp is not None:
            rms = np.sqrt(np.nanmean(s.panel_dp**2, 0))
            rec["panel_dp_rms"] = dict(zip(s.params, rms.tolist()))
        if s.design:
            rec["design"] = s.design
        scans.append(rec)
    positions = []
    for row in cs.positions():
        r = {k: v for k, v in row.items() if k != "panel_dp"}
        if "panel_dp" in row:
            r["panel_dp_m_per_unit"] = {p: [_f(v) for v in row["panel_dp"][:, j]]
                                        for j, p in enumerate(cs.params)}
        positions.append(r)
    doc = {
        "schema": SENSITIVITY_SCHEMA,
        "campaign": str(cs.campaign.root),
        "model": list(cs.model_names),
        "params": list(cs.params),
        "units": {"dx_dp": "unit of the estimate per unit of the parameter",
                  **{p: parameter_unit(p) for p in cs.params}},
        "method": "implicit function theorem at the converged solution: dx/dp = "
                  "-N_xx^-1 N_xp; scans[]: each cycle's white-noise GH (lineax Cholesky), "
                  "sigma0 from Omega + 2 n_p dp + Nr_pp dp^2; positions[]: the two-face "
                  "adjustment with the surface random effect, N reduced over the cells (Schur "
                  "complement) with the modes' priors, variance components held",
        "scans": scans,
        "positions": positions,
        "table_per_error": cs.table_per_arcsec(),
        "design": cs.design(),
    }
    if validation:
        doc["validation"] = validation
    if figures:
        doc["figures"] = list(figures)
    return doc


def plot_sensitivity(cs: CampaignSensitivity, out_dir) -> list[str]:
    """``sensitivity_f.png``: change of f per 1 arcsec error of each parameter, per position."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tab = cs.table_per_arcsec()
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.2))
    x = np.arange(len(tab))
    wbar = 0.8 / max(len(cs.params), 1)
    for j, p in enumerate(cs.params):
        vals = [r[p]["delta_f_m"] * 1e6 for r in tab]
        ax[0].bar(x + (j - (len(cs.params) - 1) / 2) * wbar, vals, wbar,
                  label=f"{p} ({tab[0][p]['error_unit']})")
        ax[1].plot([r["elevation_deg"] for r in tab], vals, "o", label=p)
    ax[0].set_xticks(x)
    ax[0].set_xticklabels([r["position"] for r in tab], rotation=90, fontsize=6)
    ax[0].set_ylabel("change of f [um]")
    ax[0].set_title("what an error of 1 arcsec does to f")
    ax[0].legend(fontsize=8)
    ax[0].axhline(0, color="k", lw=0.5)
    ax[1].set_xlabel("elevation [deg]")
    ax[1].set_ylabel("change of f [um] per arcsec")
    ax[1].axhline(0, color="k", lw=0.5)
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    p = out / "sensitivity_f.png"

    write_file_atomic(p, lambda t: fig.savefig(t, format="png", dpi=110), durable=False)
    plt.close(fig)
    return [p.name]


def sensitivity_table(cs: CampaignSensitivity) -> str:
    """Markdown table: change of f (um), panel rms (um) and sigma0 per 1 arcsec error."""
    tab = cs.table_per_arcsec()
    head = "| position | elevation [deg] | " + " | ".join(
        f"df per {tab[0][p]['error_unit']} of {p} [um] | panel rms [um]" for p in cs.params) + " |"
    rows = [head, "|---|---:|" + "---:|---:|" * len(cs.params)]
    for r in tab:
        cells = [r["position"], f"{r['elevation_deg']:.1f}"]
        for p in cs.params:
            cells.append(f"{r[p]['delta_f_m'] * 1e6:+.2f}")
            cells.append(f"{r[p].get('delta_panel_rms_m', float('nan')) * 1e6:.2f}")
        rows.append("| " + " | ".join(cells) + " |")
    if cs.position_sens:
        rows += ["", f"df: the two-face adjustment with the surface random effect at "
                 f"{len(cs.position_sens)} of {len(tab)} positions (the estimates fit reports); "
                 "panel rms: the change of its panels' predicted offsets"]
    med = cs.surface_limited_median()
    if med:
        rows += ["", f"sigma(f), both faces with the surface random effect (median over "
                 f"{med['n']} positions): {med['sigma_f_m'] * 1e6:.1f} um = white "
                 f"{med['sigma_f_white_m'] * 1e6:.1f} um (shrinks with a finer step) (+) "
                 f"surface {med['sigma_f_surface_m'] * 1e6:.1f} um (does not)"]
    return "\n".join(rows)


def write_sensitivity(path, cs: CampaignSensitivity, *, figures_dir=None,
                      validation: dict | None = None) -> Path:
    """``sensitivity.json`` (strict JSON, written last through a temporary name) after its
    figures (each written atomically)."""

    path = Path(path)
    figs = plot_sensitivity(cs, figures_dir or path.parent) if figures_dir is not False else []
    doc = _clean(sensitivity_json(cs, figures=figs, validation=validation))
    return write_json_atomic(path, doc, indent=1)


__all__ = ["ARCSEC", "CampaignSensitivity", "DEFAULT_PARAMS", "SENSITIVITY_SCHEMA",
           "ScanSensitivity", "error_unit", "finite_difference", "plot_sensitivity",
           "refit_with", "scan_sensitivity", "sensitivity", "sensitivity_json",
           "sensitivity_table", "solve_columns", "write_sensitivity"]
