"""Gauss-Helmert adjustment with the reflector's surface as a random effect.

Why: the reflector's own surface (panel offsets and tilts, smooth deformation; 0.1-1 mm) is
common to both faces and to every point of a panel. Treated as white noise, it makes every sigma
shrink as ``1/sqrt(n)`` while the error it causes in f, pose and calibration does not: with
1e5-1e7 points the estimates sit 10-50 sigma from the truth (``shared/spec/physics.md``,
Statistics). Here the surface enters the condition as a *random* deviation, whose variances are
estimated from the data, and the covariance of the unknowns includes it.

Model (one condition per point ``i`` in surface cell ``g(i)``)::

    F(l_i + v_i, x, c_i + dev_i) = 0,     dev_i = D_i . u_g(i)      (normal deviation, m)
    v ~ N(0, s_e^2 Sigma_l),  u_g ~ N(0, diag(s_1^2 .. s_k^2)),  x_j ~ N(0, s_r^2) for j in R

* ``u_g`` (k per cell): the cell's offset (m) and its tilts (rad) about the cell centre, with
  ``D_i = (1, xi_radial, xi_tangential)`` the point's local coordinates in the cell (m); the
  deviation enters the model's condition through its per-point constant ``c[dev_column]``
  (the "known deviation"), so its derivative ``dF/ddev`` comes from autodiff like ``a`` and ``b``.
* ``R``: optional "ridge" unknowns of ``x`` (smooth surface modes, e.g. Zernike coefficients)
  that are random effects as well, with one variance ``s_r^2`` per ridge group.
* The variance components ``s_e^2`` (a factor on the a priori ``Sigma_l``), ``s_1^2 .. s_k^2``
  and ``s_r^2`` are estimated by Foerstner's iterative variance-component estimation (the
  Helmert/REML-type estimator of geodesy): ``s^2 = (quadratic form of its residuals) / (its
  redundancy)``, with redundancies from the traces of the cofactor matrix, iterated to their
  fixed point at every Gauss-Newton step from that step's stored linearisation (no extra pass
  over the points: the quadratic form comes from the normal-equation sums).

Per iteration, with ``lambda = s_e^2 / s^2`` per component and the per-cell sums
``S_g = sum q d d^T``, ``s_g = sum q d a^T``, ``t_g = sum q d w`` (``q = 1/m``,
``d_i = dF/ddev * D_i``), the cell parameters are eliminated by Schur complement, so the cost is
linear in points and in cells (one small k x k block per cell)::

    (N - sum_g s_g^T (S_g + Lambda)^-1 s_g + Lambda_R) dx
        = -(n - sum_g s_g^T (S_g + Lambda)^-1 (t_g + Lambda u_g) + Lambda_R x)
    du_g = -(S_g + Lambda)^-1 (t_g + Lambda u_g + s_g dx)

``cov(x) = s_e^2 Q_xx`` with ``Q_xx`` the inverse of the reduced matrix: the generalised least
squares covariance under ``Var = s_e^2 M + B-part of the surface``, i.e. the sigmas include the
surface's blur. The cells' predictions ``u_g`` (BLUPs) come with their prediction-error
covariance ``s_e^2 [(S_g + Lambda)^-1 + (S_g + Lambda)^-1 s_g Q_xx s_g^T (S_g + Lambda)^-1]``.

The pass over the points and what is computed per point from its kept terms are in
:mod:`._mixed_pass`; here the step, the variance components, the iteration (in one compiled
loop, :func:`_solve`, or with every pass split over threads, :func:`_solve_split`) and the
result.
"""

from __future__ import annotations

import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from .._config import lend_to_device, lendable_empty, on_device, return_free_heap, row_blocks
from .._programs import cached_jit
from ._ghm import AbstractAdjustment
from ._kernel import (
    PARALLEL_MIN_POINTS,  # noqa: F401  (re-exported: this module's name since 520202b)
    THREADS_ENV,  # noqa: F401
    array_namespace,
    chunk_for,
    host_sum,
    next_rate,
    part_chunk,
    pass_threads,
    remaining_error,
    solve_scaled,
    step_sigmas,
    thread_pool,
)
from ._mixed_pass import (
    DROP_ROWS,
    STORE_DTYPE,
    _dropped_sums,
    _final_terms,
    _pass,
    _rejected,
    _residual_k,
    design_dtype,
)

#: Smallest variance a component may take (relative to its start value): a component the data do
#: not support tends to zero, which the iteration reaches only asymptotically.
_FLOOR = 1e-8


class MixedResult(AbstractAdjustment):
    """Result of :func:`gauss_helmert_mixed` (SI units; ``k`` components per cell).

    Attributes:
        x: estimated unknowns (fixed effects and ridge modes), model order.
        cov: covariance of ``x`` including the surface random effect, ``s_e^2 Q_xx``.
        Qxx: cofactor matrix of ``x`` (reduced normal matrix inverted).
        u: predictions (BLUPs) of the cell parameters, shape (g, k): offset (m), tilts (rad).
        u_cov: their prediction-error covariances, (g, k, k).
        noise_var: ``s_e^2``, variance factor of the a priori observation sigmas.
        cell_var: ``s_1^2 .. s_k^2`` (m^2, rad^2).
        ridge_var: variance of each ridge group's modes (m^2), shape (r,).
        redundancy_noise, redundancy_cells (k,), redundancy_ridge (r,): the redundancy shares.
        sigma0: ``sqrt(v^T Sigma^-1 v / (n - u))`` at the solution (the classical figure).
        v: observation residuals (n, 3); normalized: ``|k_i| sqrt(m_i) / s_e`` per point.
        dev: the surface deviation ``D_i . u_g(i)`` (m) at every point.
        omega_point: ``k_i^2 m_i`` per point (its share of ``v^T Sigma^-1 v``).
        weights: weights used; n_used: their count; iterations; converged.
        x_response: ``d x_hat / d u_g`` per cell, (g, u, k): how a cell's true deviation moves
            the estimates (``Q_xx s_g^T D_g^-1 Lambda``). The surface's share of ``cov`` is
            ``sum_g R_g diag(cell_var) R_g^T``; cells seen by other adjustments of the same
            reflector make their estimates' surface errors correlated (``gravity``).
        contraction: the ratio of its last two steps with no rejection between them (its
            ``rate0`` where it measured none): how fast the iteration converges on this
            problem, for an adjustment of the same problem started from this one.
        ridge_fixed, ridge_fixed_cov: the ridge unknowns estimated as *fixed* effects (no prior:
            one Newton step from the solution with their priors removed, the cells still
            random) and their covariance ``s_e^2 Q``: ``ridge_fixed_g^T cov_g^-1 ridge_fixed_g``
            is chi-square with ``|g|`` degrees of freedom when group ``g``'s modes are absent
            (the test of whether the data show them at all, :func:`ridge_chi2`).
    """

    x: Float[Array, " u"]
    cov: Float[Array, "u u"]
    Qxx: Float[Array, "u u"]
    u: Float[Array, "g k"]
    u_cov: Float[Array, "g k k"]
    noise_var: Float[Array, ""]
    cell_var: Float[Array, " k"]
    ridge_var: Float[Array, " r"]
    redundancy_noise: Float[Array, ""]
    redundancy_cells: Float[Array, " k"]
    redundancy_ridge: Float[Array, " r"]
    sigma0: Float[Array, ""]
    v: Float[Array, "n 3"]
    normalized: Float[Array, " n"]
    dev: Float[Array, " n"]
    omega_point: Float[Array, " n"]
    weights: Float[Array, " n"]
    n_used: Int[Array, ""]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]
    x_response: Float[Array, "g u k"]
    ridge_fixed: Float[Array, " r"]
    ridge_fixed_cov: Float[Array, "r r"]
    contraction: Float[Array, ""]


def _reduce(N, nv, S, sg, tg, U, x, lam, ridge_idx, ridge_lam):
    """Schur complement over the cells, plus the ridge priors: ``(dx, dU, Qxx, Dinv)``."""
    Dinv = jnp.linalg.inv(S + jnp.diag(lam)[None])
    rhs_u = tg + lam[None, :] * U
    Nr = N - jnp.einsum("gki,gkl,glj->ij", sg, Dinv, sg)
    nr = nv - jnp.einsum("gki,gkl,gl->i", sg, Dinv, rhs_u)
    if ridge_idx.shape[0]:
        Nr = Nr.at[ridge_idx, ridge_idx].add(ridge_lam)
        nr = nr.at[ridge_idx].add(ridge_lam * x[ridge_idx])
    dx, Qxx = solve_scaled(Nr, -nr)
    dU = -jnp.einsum("gkl,gl->gk", Dinv, rhs_u + jnp.einsum("gli,i->gl", sg, dx))
    return dx, dU, Qxx, Dinv


def _x_response(lin, var, Qxx):
    """``d x_hat / d u_g = Q_xx s_g^T D_g^-1 Lambda`` per cell, (g, u, k) (Henderson's
    equations with the data ``Z u``: ``x_hat = Q_xx sum_g s_g^T (I - D_g^-1 S_g) u_g``)."""
    lam = var[0] / var[1]
    Dinv = jnp.linalg.inv(lin.S + jnp.diag(lam)[None])
    return jnp.einsum("ij,gkj,gkl,l->gil", Qxx, lin.sg, Dinv, lam)


def mixed_response(sums, var: tuple, Qxx: Float[Array, "u u"]) -> Float[Array, "g u k"]:
    """``d x_hat / d u_g`` per cell from the :class:`._mixed_stream.MixedSums` of a streamed
    adjustment (see :attr:`MixedResult.x_response`); ``var`` the variance components, ``Qxx``
    the step's."""
    return _x_response(sums, var, Qxx)


def _cell_cofactors(Dinv, sg, Qxx):
    """Prediction-error cofactors of the cells: ``D^-1 + D^-1 s Q_xx s^T D^-1`` per cell."""
    T = jnp.einsum("gkl,gli->gki", Dinv, sg)
    return Dinv + jnp.einsum("gki,ij,glj->gkl", T, Qxx, T)


class _Linearization(eqx.Module):
    """Sums and per-point terms of one linearisation (independent of the variances)."""

    N: Array
    nv: Array
    S: Array
    sg: Array
    tg: Array
    wMw: Array
    a: Array
    b: Array
    d: Array
    wm: Array
    m: Array


class _Update(eqx.Module):
    """The step and the variance-component statistics at given variances."""

    dx: Array
    dU: Array
    Qxx: Array
    Quu: Array
    omega: Array
    r_e: Array
    r_cells: Array
    r_ridge: Array
    var_new: tuple


def _update(lin, var, var0, x, U, n_used, ridge_idx, ridge_group, ridge_count,
            n_ridge_groups):
    """Solve the linearised mixed model at the variances ``var`` and re-estimate them
    (Foerstner: each component's quadratic form over its redundancy share)."""
    f = x.dtype
    se2, cv, rv = var
    lam = se2 / cv
    rl = (se2 / rv)[ridge_group] if n_ridge_groups else jnp.zeros((0,), f)
    dx, dU, Qxx, Dinv = _reduce(lin.N, lin.nv, lin.S, lin.sg, lin.tg, U, x, lam, ridge_idx, rl)
    # v^T Sigma^-1 v after the step, from the sums (the linearised residual is
    # -(a.dx + d.du + w) / m per point): no pass over the points
    omega = (lin.wMw + 2 * lin.nv @ dx + dx @ lin.N @ dx
             + 2 * jnp.sum(lin.tg * dU) + 2 * jnp.einsum("gk,gki,i->", dU, lin.sg, dx)
             + jnp.einsum("gk,gkl,gl->", dU, lin.S, dU))
    omega = jnp.maximum(omega, 0.0)
    x_new, U_new = x + dx, U + dU
    Quu = _cell_cofactors(Dinv, lin.sg, Qxx)
    r_cells = jnp.sum(1.0 - lam[None, :] * jnp.diagonal(Quu, axis1=1, axis2=2), axis=0)
    uu = jnp.sum(U_new**2, axis=0)
    if n_ridge_groups:
        qr = jnp.diagonal(Qxx)[ridge_idx]
        r_ridge = jax.ops.segment_sum(1.0 - rl * qr, ridge_group, n_ridge_groups)
        xx = jax.ops.segment_sum(x_new[ridge_idx] ** 2, ridge_group, n_ridge_groups)
    else:
        r_ridge = jnp.zeros((0,), f)
        xx = jnp.zeros((0,), f)
    u = x.shape[0]
    r_e = n_used - u - jnp.sum(r_cells) + (jnp.sum(ridge_count) - jnp.sum(r_ridge))
    se2_new = omega / jnp.maximum(r_e, 1.0)
    cv_new = jnp.where(r_cells > 0.5, uu / jnp.maximum(r_cells, 1e-12), cv)
    cv_new = jnp.maximum(cv_new, _FLOOR * var0[1])
    rv_new = jnp.where(r_ridge > 0.25, xx / jnp.maximum(r_ridge, 1e-12), rv)
    rv_new = jnp.maximum(rv_new, _FLOOR * var0[2])
    return _Update(dx, dU, Qxx, Quu, omega, r_e, r_cells, r_ridge, (se2_new, cv_new, rv_new))


def _point_residuals(lin, up, groups):
    """``k_i = -(a.dx + d.du_g + w) / m`` of every point after the step."""
    return _residual_k(lin.a, lin.d, lin.wm, lin.m, up.dx, up.dU, groups)


#: Rounds of rejection, sums taken out and the step again, at one linearisation.
DROP_ROUNDS = 4


#: Stopping rule of the random effect's iteration: the error left in the solution below this
#: fraction of every unknown's sigma (the last step, or the rest of the contracting steps,
#: :func:`remaining_error`). The answer depends on the points a start is drawn from, on the
#: cells' alignment and on the rejections by a few hundredths of a sigma (0.05-0.08 over
#: seeds, ``fit._fit.SAMPLE_POINTS``); an iteration error ten times smaller changes no z-score
#: beyond 0.01. The streamed position (``fit.stream_fit_position``) stops at the same.
MIXED_TOL = 1e-2


def iteration_converged(step, rate, tol, var, var_prev, var0):
    """The step is below tol, or the rest of the contracting steps is (:func:`remaining_error`)
    while the variance components have settled (:func:`_settled`): a step that moves them
    moves the solution again, whatever the contraction of ``x`` so far."""
    return ((step < tol)
            | ((remaining_error(step, rate) < tol) & _settled(var, var_prev, var0, rate)))


def _settled(new, old, var0, rate=1.0):
    """Every component's rest of change below 0.5 % (0.25 % in its sigma), or the component
    at its floor (traced or concrete: :func:`._kernel.array_namespace`).

    The components are the fixed point of their estimator at every linearisation (:func:`_vce`):
    what moves them from one linearisation to the next is the linearisation's own move, which
    contracts by ``rate`` per step as the unknowns' steps do. Their rest of change is
    therefore predicted as the steps' (:func:`remaining_error` of the change ``|log(new /
    old)|``): the change itself where no contraction is measured (``rate`` 1), a small part
    of it on a problem whose contraction is known. This overstates the rest where the change
    came from elsewhere: from a start on other data (a sample's components, or the start
    values' floor) or from points rejected at this linearisation."""
    xp = array_namespace(new, old, var0, rate)
    new, old, var0 = ([xp.asarray(v) for v in t] for t in (new, old, var0))

    def ok(a, b, floor):
        rest = remaining_error(xp.abs(xp.log(a / b)), rate)
        return xp.all((rest < 5e-3) | (a <= floor * 1.0001))
    return (ok(new[0], old[0], 0.0) & ok(new[1], old[1], _FLOOR * var0[1])
            & ok(new[2], old[2], _FLOOR * var0[2]))


def _ridge_args(ridge_idx, ridge_group, n_ridge_groups) -> dict:
    f = jnp.float64
    return dict(ridge_idx=ridge_idx, ridge_group=ridge_group, n_ridge_groups=n_ridge_groups,
                ridge_count=jax.ops.segment_sum(jnp.ones_like(ridge_idx, f), ridge_group,
                                                n_ridge_groups))


def _vce(upd, lin, var, var0, x, U, n_used):
    """The variance components at this linearisation: a fixed point of ``_update`` (cheap: no
    pass over the condition, only the normal-equation sums)."""

    def body(c):
        v, _, i = c
        new = upd(lin, v, x=x, U=U, n_used=n_used).var_new
        return new, _settled(new, v, var0), i + 1

    v, _, _ = lax.while_loop(lambda c: (~c[1]) & (c[2] < 200), body,
                             (var, jnp.array(False), jnp.array(0)))
    return v


def _blank_step(n: int, x0, U0, var0):
    """Zeros shaped as one step's ``(linearisation, (x, U, update))`` of :func:`_solve`
    (the loop's carry before its first step)."""
    u, (g, k) = x0.shape[0], U0.shape
    z = partial(jnp.zeros, dtype=x0.dtype)
    zs = partial(jnp.zeros, dtype=STORE_DTYPE)
    lin = _Linearization(z((u, u)), z((u,)), z((g, k, k)), z((g, k, u)), z((g, k)), z(()),
                         zs((n, u)), zs((n, 3)), zs((n, k)), zs((n,)), zs((n,)))
    return lin, (z((u,)), z((g, k)), _zero_update(x0, U0, var0))


def _zero_update(x0, U0, var0) -> _Update:
    """Zeros shaped as an :class:`_Update` of these unknowns, cells and ridge groups."""
    u, (g, k), r = x0.shape[0], U0.shape, var0[2].shape[0]
    z = partial(jnp.zeros, dtype=x0.dtype)
    return _Update(z((u,)), z((g, k)), z((u, u)), z((g, k, k)), z(()), z(()), z((k,)), z((r,)),
                   (z(()), z((k,)), z((r,))))


class _Settings(eqx.Module):
    """What shapes an adjustment's programs (static fields): the condition's deviation column,
    the cells, the chunk of a pass, the stopping rule (``tol`` sigma, ``max_iter`` passes),
    whether the variance components are estimated, the number of ridge groups."""

    dev_column: int
    n_cells: int
    chunk: int
    tol: float
    max_iter: int
    estimate_variances: bool
    n_ridge_groups: int


#: The per-point arrays of an adjustment or of one of its parts, a dict with these keys:
#: observations ``L`` (n, 3), their residuals ``V`` (n, 3), constants
#: ``C`` (n, c), weights ``W`` (n,), variances ``S2`` (n, 3) or (3,) for all, cells ``G`` (n,),
#: the cell design ``DM`` (n, k) and the smooth modes' design ``MZ`` (n, r).
POINT_KEYS = ("L", "V", "C", "W", "S2", "G", "DM", "MZ")


def _pass_of(condition, cfg: _Settings, on, pts: dict, x, U, V=None, W=None, into=None):
    """:func:`_pass` over the points ``pts`` (:data:`POINT_KEYS`; ``V``, ``W`` in their stead
    where given)."""
    return _pass(condition, cfg.dev_column, on, cfg.n_cells, cfg.chunk, pts["L"],
                 pts["V"] if V is None else V, pts["C"], pts["W"] if W is None else W,
                 pts["S2"], pts["G"], pts["DM"], x, U, pts["MZ"], into=into, rows=pts.get("R"))


@cached_jit
def _solve(condition, cfg: _Settings, pts: dict, x0, U0, var0, ridge_idx, ridge_group,
           robust_k, on, reject_from, rate0):
    """The adjustment as one compiled loop (:func:`gauss_helmert_mixed`; ``pts`` the points,
    :data:`POINT_KEYS`)."""
    f = pts["L"].dtype
    s2, groups = pts["S2"], pts["G"]
    n_cells, tol = cfg.n_cells, cfg.tol
    upd = partial(_update, var0=var0, **_ridge_args(ridge_idx, ridge_group, cfg.n_ridge_groups))

    def linearize(x, U, V, weights):
        (N, nv, S, sg, tg, wmw), (a, b, d, wm, m, _) = _pass_of(condition, cfg, on, pts, x, U,
                                                                 V, weights)
        return _Linearization(N, nv, S, sg, tg, wmw, a, b, d, wm, m)

    def vce(lin, var, x, U, weights):
        if not cfg.estimate_variances:
            return var
        return _vce(upd, lin, var, var0, x, U, jnp.sum(weights > 0))

    def step(state):
        x, U, V, var_prev, it, _, weights, _, _, (prev, prev_pending, rate) = state
        lin = linearize(x, U, V, weights)
        # robust rejection inside the iteration: points beyond robust_k noise sigmas (judged
        # once the surface is taken out, from step ``reject_from`` on) leave for good; their
        # share leaves the sums at once and the step is taken again (_dropped_sums), up to
        # DROP_ROWS points and DROP_ROUNDS rounds; beyond that the next pass starts without
        # them. One loop of rounds, the first with nothing to take out: the variance
        # components and the step are compiled once (half the program of a loop of its own)
        judge = it >= reject_from

        def round_(c):
            sums, var, _, weights, _, bad, r, first = c
            idx = jnp.nonzero(bad, size=DROP_ROWS, fill_value=-1)[0]
            drop = _dropped_sums(lin.a, lin.d, lin.wm, lin.m, weights, groups, idx, n_cells)
            sums = tuple(s - t for s, t in zip(sums, drop))
            weights = jnp.where(bad, 0.0, weights)
            now = _Linearization(*sums, lin.a, lin.b, lin.d, lin.wm, lin.m)
            var = vce(now, var, x, U, weights)
            up = upd(now, var, x=x, U=U, n_used=jnp.sum(weights > 0))
            kk = _point_residuals(now, up, groups)
            bad = _rejected(kk, lin.m, weights, var[0], judge, robust_k)
            first = jnp.where(r == 0, step_sigmas(up.dx, up.Qxx), first)
            return sums, var, up, weights, kk, bad, r + 1, first

        def more(c):
            n_bad = jnp.sum(c[5])
            return (c[6] == 0) | ((n_bad > 0) & (n_bad <= DROP_ROWS) & (c[6] <= DROP_ROUNDS))

        blank = _zero_update(x, U, var_prev)
        sums, var, up, weights, kk, bad, _, first = lax.while_loop(
            more, round_, ((lin.N, lin.nv, lin.S, lin.sg, lin.tg, lin.wMw), var_prev, blank,
                           weights, jnp.zeros_like(weights), jnp.zeros_like(weights, bool),
                           jnp.array(0), jnp.zeros((), f)))
        lin = _Linearization(*sums, lin.a, lin.b, lin.d, lin.wm, lin.m)
        # the contraction from the last two steps with no rejection left between them (a
        # rejection not yet in the step moves the solution: the step after it is a new start)
        rate = next_rate(rate, prev, first, prev_pending)
        ratio = step_sigmas(up.dx, up.Qxx)
        step_ok = iteration_converged(ratio, rate, tol, var, var_prev, var0)
        pending = jnp.any(bad)
        weights = jnp.where(bad, 0.0, weights)
        V_new = s2 * lin.b * kk[:, None]
        return (x + up.dx, U + up.dU, V_new, var, it + 1, step_ok & ~pending, weights, lin,
                (x, U, up), (ratio, pending, rate))

    def cond(state):
        return (state[4] < cfg.max_iter) & ~state[5]

    # the last step's linearisation and solution are carried: the statistics at the solution
    # come from them (its step was below tol sigma: no further pass over the points)
    state = (x0, U0, pts["V"], var0, jnp.array(0), jnp.array(False), pts["W"],
             *_blank_step(pts["L"].shape[0], x0, U0, var0),
             (jnp.zeros((), f), jnp.array(False), jnp.asarray(rate0, f)))
    x, U, V, var, it, done, weights, lin, (x_lin, U_lin, up), (_, _, rate) = lax.while_loop(
        cond, step, state)
    _, omega_pt, dev_final = _final_terms(lin.a, lin.d, lin.wm, lin.m, weights, groups,
                                          pts["DM"], U, up.dx, up.dU)
    se2 = var[0]
    n_used = jnp.sum(weights > 0)
    u = x.shape[0]
    sigma0 = jnp.sqrt(jnp.sum(weights * omega_pt) / jnp.maximum(n_used - u, 1))
    if cfg.n_ridge_groups:  # the modes as fixed effects: one step with their priors removed
        dx0, _, Q0, _ = _reduce(lin.N, lin.nv, lin.S, lin.sg, lin.tg, U_lin, x_lin,
                                se2 / var[1], ridge_idx, jnp.zeros_like(ridge_idx, f))
        ridge_fixed = (x_lin + dx0)[ridge_idx]
        ridge_fixed_cov = se2 * Q0[ridge_idx][:, ridge_idx]
    else:
        ridge_fixed, ridge_fixed_cov = jnp.zeros((0,), f), jnp.zeros((0, 0), f)
    return MixedResult(
        x=x, cov=se2 * up.Qxx, Qxx=up.Qxx, u=U, u_cov=se2 * up.Quu, noise_var=se2,
        cell_var=var[1], ridge_var=var[2], redundancy_noise=up.r_e, redundancy_cells=up.r_cells,
        redundancy_ridge=up.r_ridge, sigma0=sigma0, v=V,
        normalized=jnp.sqrt(omega_pt) / jnp.sqrt(se2), dev=dev_final, omega_point=omega_pt,
        weights=weights, n_used=n_used, iterations=it, converged=done,
        x_response=_x_response(lin, var, up.Qxx), ridge_fixed=ridge_fixed,
        ridge_fixed_cov=ridge_fixed_cov, contraction=rate)


# --------------------------------------------------------------------------------------------
# The same iteration with each pass split over the cores
# --------------------------------------------------------------------------------------------

#: Rows per part from which each pass gives the heap's free blocks back first
#: (:func:`.._config.return_free_heap`; a smaller position's heap stays as it is).
TRIM_ROWS = 2**20

# the parts and their threads: :func:`._kernel.pass_threads`, :func:`._kernel.thread_pool`
# (shared with the white adjustment; ``mixed_threads`` is this module's name for the first)
mixed_threads = pass_threads


@cached_jit
def _part_pass(condition, cfg: _Settings, on, p: dict, x, U, into=None):
    """A part's pass: its sums, its per-point terms ``(a, b, d, wm, m)``, its points in use."""
    sums, per = _pass_of(condition, cfg, on, p, x, U, into=into)
    return sums, tuple(per[:5]), jnp.sum(p["W"] > 0)


@cached_jit(donate="all-except-first")
def _part_pass_over(args: tuple, store):
    """:func:`_part_pass` of ``args``, its per-point terms written over the last pass's
    ``store`` (donated: the same memory again instead of new pages from the kernel)."""
    return _part_pass(*args, into=store)


@cached_jit
def _part_update(cfg: _Settings, sums, var, var0, x, U, n_used, ridge_idx, ridge_group):
    """Variance components (Foerstner) and the step from the added sums, as one step of
    :func:`_solve`."""
    upd = partial(_update, var0=var0, **_ridge_args(ridge_idx, ridge_group, cfg.n_ridge_groups))
    lin = _Linearization(*sums, None, None, None, None, None)
    if cfg.estimate_variances:
        var = _vce(upd, lin, var, var0, x, U, n_used)
    up = upd(lin, var, x=x, U=U, n_used=n_used)
    return var, up, step_sigmas(up.dx, up.Qxx)


@cached_jit(donate="all-except-first", keep_unused=True)  # V unused: kept to be reused
def _part_residuals(args: tuple, V):
    """A part's residuals after the step and, where ``judge``, the points its robust rule
    rejects (as :func:`_solve`): ``(v, rejected)``. ``args = (per, G, S2, dx, dU, se2, W,
    judge, robust_k)``; the part's last residuals ``V`` are donated: the new ones are written
    over them (no new pages). The rejected points are counted and found on the host, and
    their share taken out by :func:`_part_reject`: a count and a ``nonzero`` in the program
    took 100 MiB of temporaries per 6.3e6 points, every round, for a few rejections."""
    del V
    per, G, S2, dx, dU, se2, W, judge, robust_k = args
    a, b, d, wm, m = per
    kk = _residual_k(a, d, wm, m, dx, dU, G)
    return S2 * b * kk[:, None], _rejected(kk, m, W, se2, judge, robust_k)


@cached_jit(donate="all-except-first")
def _part_reject(args: tuple, W):
    """A part's weights ``W`` (donated) without its ``rejected`` points, and the share of its
    points ``idx`` (the first :data:`DROP_ROWS` rejected ones, -1 padded) of the sums
    (:func:`_dropped_sums`). ``args = (per, G, rejected, idx, n_cells)``."""
    per, G, bad, idx, n_cells = args
    a, _, d, wm, m = per
    return jnp.where(bad, 0.0, W), _dropped_sums(a, d, wm, m, W, G, idx, n_cells)


def _first_rows(bad: np.ndarray) -> tuple[int, np.ndarray]:
    """``(count, the first DROP_ROWS indices, -1 padded)`` of a part's rejected points."""
    idx = np.flatnonzero(bad)
    first = np.full(DROP_ROWS, -1, np.int64)
    first[:min(len(idx), DROP_ROWS)] = idx[:DROP_ROWS]
    return len(idx), first


@cached_jit(donate="all-except-first", keep_unused=True)
def _part_final(args: tuple, per, V):
    """A part's per-point statistics at the solution (as :func:`_solve`); ``args = (G, S2, W,
    DM, R, U, dx, dU, se2)``, ``R`` the part's rows of the design table ``DM`` (None: ``DM``
    is the part's own). Its last per-point terms ``per`` and residuals ``V`` are donated: the
    statistics are written over them."""
    del V
    G, S2, W, DM, R, U, dx, dU, se2 = args
    a, b, d, wm, m = per
    kk, omega_pt, dev = _final_terms(a, d, wm, m, W, G, DM if R is None else DM[R], U, dx, dU)
    return (S2 * b * kk[:, None], jnp.sqrt(omega_pt) / jnp.sqrt(se2), dev, omega_pt,
            jnp.sum(W * omega_pt))


@cached_jit
def _part_stats(sums, var, x, U, Qxx, ridge_idx, n_ridge_groups):
    """The modes as fixed effects and the cells' responses (as :func:`_solve`)."""
    f = x.dtype
    lin = _Linearization(*sums, None, None, None, None, None)
    if n_ridge_groups:
        dx0, _, Q0, _ = _reduce(lin.N, lin.nv, lin.S, lin.sg, lin.tg, U, x, var[0] / var[1],
                                ridge_idx, jnp.zeros_like(ridge_idx, f))
        ridge_fixed = (x + dx0)[ridge_idx]
        ridge_fixed_cov = var[0] * Q0[ridge_idx][:, ridge_idx]
    else:
        ridge_fixed, ridge_fixed_cov = jnp.zeros((0,), f), jnp.zeros((0, 0), f)
    return ridge_fixed, ridge_fixed_cov, _x_response(lin, var, Qxx)


def _solve_parts(condition, cfg: _Settings, parts: list[dict], x0, U0, var0, ridge_idx,
                 ridge_group, robust_k, reject_from: int, rate0: float, back):
    """:func:`_solve` with every pass split into ``parts`` (dicts of equal-length point
    arrays, :data:`POINT_KEYS`), each part's pass in its own thread; the normal-equation
    sums of the parts are added, the step and the variance components computed from them as
    before. Same iteration, same arithmetic up to the order of the sums' additions.
    ``back``: the parts' per-point arrays (a list) -> one array in the caller's order."""
    on = on_device(True, bool)
    pool = thread_pool(len(parts))

    large = parts[0]["L"].shape[0] >= TRIM_ROWS

    def linearize(x, U, old):
        if large:  # the free blocks of the last pass back to the kernel (return_free_heap)
            return_free_heap()

        def one(i):
            args = (condition, cfg, on, parts[i], x, U)
            return jax.block_until_ready(_part_pass(*args) if old is None else
                                         _part_pass_over(args, old[i]))
        outs = list(pool.map(one, range(len(parts))))
        sums = tuple(host_sum(t) for t in zip(*(o[0] for o in outs)))
        return sums, [o[1] for o in outs], np.asarray(sum(int(o[2]) for o in outs))

    def update(sums, var, x, U, n_used):
        return _part_update(cfg, sums, var, var0, x, U, n_used, ridge_idx, ridge_group)

    x, U, var, it, done, pers = x0, U0, var0, 0, False, None
    prev, pending, rate = 0.0, False, float(rate0)
    while it < cfg.max_iter and not done:
        # the last linearisation's per-point terms, their memory the next one's
        sums, pers, n_used = linearize(x, U, pers)
        var_prev = var
        var, up, ratio = update(sums, var, x, U, n_used)
        # as in _solve: the contraction of the last two steps with no rejection left between
        rate = float(next_rate(rate, prev, float(ratio), pending))
        # as in _solve: the rejected points' share out of the sums and the step again
        judge = jnp.asarray(it >= reject_from)
        for r in range(DROP_ROUNDS + 1):

            def judged(i):  # each part in its thread, as its pass
                p = parts[i]
                p["V"], bad = jax.block_until_ready(_part_residuals(
                    (pers[i], p["G"], p["S2"], up.dx, up.dU, var[0], p["W"], judge, robust_k),
                    p.pop("V")))
                count, idx = _first_rows(np.asarray(bad))
                if not count:
                    return 0, None
                p["W"], drop = jax.block_until_ready(_part_reject(
                    (pers[i], p["G"], bad, idx, cfg.n_cells), p.pop("W")))
                return count, drop

            outs = list(pool.map(judged, range(len(parts))))
            n_bad = sum(o[0] for o in outs)
            drops = [o[1] for o in outs if o[1] is not None]
            outs = None
            pending = n_bad > 0
            if not pending or n_bad > DROP_ROWS or r == DROP_ROUNDS:
                break
            for drop in drops:
                sums = tuple(s - np.asarray(t) for s, t in zip(sums, drop))
            n_used = n_used - n_bad
            var, up, ratio = update(sums, var, x, U, n_used)
        drops = None
        ratio = float(ratio)
        step_ok = bool(iteration_converged(ratio, rate, cfg.tol, var, var_prev, var0))
        prev = ratio
        x_lin, U_lin = x, U
        x, U = x + up.dx, U + up.dU
        it += 1
        done = step_ok and not pending
    # statistics at the solution from the last step's linearisation (its step was below tol
    # sigma: no further pass over the points); each part's store and observations are let go
    # once its statistics are out, and each statistic once it is in the caller's order, so
    # that the footprint does not peak here
    se2 = var[0]
    if large:
        return_free_heap()
    fin = []
    for i, p in enumerate(parts):
        per, pers[i] = pers[i], None
        fin.append(list(_part_final((p["G"], p["S2"], p["W"], p["DM"], p.get("R"), U, up.dx,
                                     up.dU, se2), per, p.pop("V"))))
        per = None
        for k in ("L", "C", "DM", "MZ", "R"):
            p[k] = None
    u = x.shape[0]
    sigma0 = jax.device_put(np.sqrt(host_sum([fp[4] for fp in fin]) / max(int(n_used) - u, 1)))
    ridge_fixed, ridge_fixed_cov, response = _part_stats(sums, var, x_lin, U_lin, up.Qxx,
                                                          ridge_idx, cfg.n_ridge_groups)

    def cat(i):
        arrays = [fp[i] for fp in fin]
        for fp in fin:
            fp[i] = None
        return back(arrays)

    return MixedResult(
        x=x, cov=se2 * up.Qxx, Qxx=up.Qxx, u=U, u_cov=se2 * up.Quu, noise_var=se2,
        cell_var=var[1], ridge_var=var[2], redundancy_noise=up.r_e, redundancy_cells=up.r_cells,
        redundancy_ridge=up.r_ridge, sigma0=sigma0, v=cat(0), normalized=cat(1), dev=cat(2),
        omega_point=cat(3), weights=back([p["W"] for p in parts]),
        n_used=n_used, iterations=jnp.asarray(it), converged=jnp.asarray(done),
        x_response=response, ridge_fixed=ridge_fixed, ridge_fixed_cov=ridge_fixed_cov,
        contraction=jnp.asarray(rate))


def _solve_split(condition, cfg: _Settings, threads: int, pts: dict, x0, U0, var0,
                 ridge_idx, ridge_group, robust_k, reject_from: int, rate0: float):
    """The points cut into at most ``threads`` consecutive parts of equal length (whole
    chunks; the last part's tail padded with copies of its last point at weight 0, outside
    every cell), each part copied from the caller's arrays ``pts`` (:data:`POINT_KEYS`; ``V``
    None: zeros) but for the tables ``L``, ``C``, ``DM``, ``MZ``, which the parts read by
    their rows' numbers ``R``; :func:`_solve_parts`; the per-point results in the caller's
    order."""
    n = pts["L"].shape[0]
    m = -(-n // (threads * cfg.chunk)) * cfg.chunk
    # (a part would be empty where whole chunks run out first, e.g. 4 chunks in 3 parts)
    spans = [(i * m, min((i + 1) * m, n)) for i in range(threads) if i * m < n]

    # the tables every pass reads (observations, constants, the designs) stay the caller's,
    # lent to the device (no copy where they are aligned, ``lend_to_device``): each part holds
    # the numbers of its rows instead (``R``; :func:`_pass` takes each chunk's rows in its
    # loop, at no cost measured against a part's own copy), 52 B per point less than copies
    f = np.float64
    tables = {"L": lend_to_device(pts["L"], f), "C": lend_to_device(pts["C"], f),
              **{k: lend_to_device(pts[k], design_dtype(pts[k])) for k in ("DM", "MZ")}}

    def part(span):
        start, stop = span
        size = stop - start
        pad = m - size

        def take(a, dtype, value=None, lend=True):
            # copied on the host, no device copy of the caller's whole arrays; each part in its
            # own thread, a block of rows at a time into the part's array (a caller's float32
            # or bool array is converted block by block, not by a whole copy). The copy is new,
            # nobody else's and, where ``lend``, aligned for the device (lendable_empty):
            # ``device_put`` lends it to the device without a copy. The residuals and weights
            # are not lent: the programs that update them write over them (donated), which XLA
            # does only in its own memory (a lent array's update took new memory at the
            # footprint's peak, the store's time)
            a = np.asarray(a)
            out = (lendable_empty if lend else np.empty)((m,) + a.shape[1:], dtype)
            for rows in row_blocks(size):
                out[rows] = a[start + rows.start:start + rows.stop]
            if pad:
                out[size:] = out[size - 1] if value is None else value
            return jax.device_put(out)

        idx = np.int32 if n < 2**31 else np.int64
        R = lendable_empty((m,), idx)  # the tail: the last row again (weight 0 there)
        R[:size] = np.arange(start, stop, dtype=idx)
        R[size:] = stop - 1
        S2, V0 = pts["S2"], pts["V"]
        return {**tables, "R": jax.device_put(R), "G": take(pts["G"], np.int32, -1),
                "W": take(pts["W"], f, 0.0, lend=False),
                "V": jax.device_put(np.zeros((m, 3), f)) if V0 is None else take(V0, f, lend=False),
                "S2": take(S2, f) if S2.ndim == 2 else S2}

    pool = thread_pool(len(spans))
    parts = list(pool.map(part, spans))

    def back(arrays):
        """The parts' rows put back in one array of the caller's rows (the padding rows
        left out), on the host, each part in its thread."""
        arrays = [np.asarray(a) for a in arrays]
        out = np.empty((n,) + arrays[0].shape[1:], arrays[0].dtype)

        def one(i):
            start, stop = spans[i]
            out[start:stop] = arrays[i][:stop - start]

        list(pool.map(one, range(len(spans))))
        return out

    return _solve_parts(condition, cfg, parts, x0, U0, var0, ridge_idx, ridge_group, robust_k,
                        reject_from, rate0, back)


def gauss_helmert_mixed(
    condition,
    l: Float[Array, "n 3"],
    x0: Float[Array, " u"],
    sigma_l: Float[Array, " 3"] | Float[Array, "n 3"],
    consts: Float[Array, "n c"],
    weights: Float[Array, " n"],
    groups: Int[Array, " n"],
    design: Float[Array, "n k"],
    n_cells: int,
    *,
    dev_column: int = 1,
    cell_var0: Float[Array, " k"],
    ridge: dict[str, list[int]] | None = None,
    ridge_var0: float | Float[Array, " r"] = 1e-8,
    noise_var0: float = 1.0,
    v0: Float[Array, "n 3"] | None = None,
    u0: Float[Array, "g k"] | None = None,
    estimate_variances: bool = True,
    robust_k: float | None = None,
    tol: float = MIXED_TOL,
    max_iter: int = 60,
    chunk_size: int = 8192,
    threads: int | None = None,
    mode_design: Float[Array, "n r"] | None = None,
    rate0: float = 1.0,
) -> MixedResult:
    """Gauss-Helmert adjustment of ``condition`` with the surface as a random effect.

    Args:
        condition: ``(l (3,), x (u,), c) -> F`` whose per-point constant ``c[dev_column]`` is a
            normal deviation of the surface (m) that the condition subtracts (the models of
            :mod:`._model` read it as the known deviation).
        l, x0, sigma_l, consts, weights: as :func:`._ghm.gauss_helmert`.
        groups: surface cell of each point (0 .. n_cells-1; -1: no cell, e.g. the cone).
        design: ``D_i`` (n, k): the deviation of point i per unit of its cell's k parameters
            (1 for the offset, local radial/tangential coordinates in m for the tilts); a
            float32 design is kept in float32 (half the memory; 0.1 um on 2-m coordinates).
        cell_var0: start values of the cells' variances (m^2, rad^2), shape (k,).
        ridge: ``{group name: indices into x}``: unknowns that are random effects themselves
            (smooth modes), one variance per group, start ``ridge_var0`` (m^2).
        estimate_variances: False holds every variance at its start value.
        robust_k: reject, during the iteration, points whose residual exceeds ``robust_k``
            noise sigmas once the surface is taken out (None: no rejection); a rejected point
            stays rejected, and its share of the normal-equation sums leaves them at once:
            the step is taken again at the same linearisation (no pass over the points; up
            to :data:`DROP_ROWS` points per step). Points are judged from the second step on,
            or from the first when the start carries the cells (``u0``: another random-effect
            adjustment's solution, so the first step does not move the surface into the cells
            and the residuals after it are already the surface-free ones; it saves a pass over
            the points).
        tol: convergence when the error left in every unknown is below ``tol`` times its
            sigma (:data:`MIXED_TOL`) and every variance component's rest of change below
            0.5 % (:func:`iteration_converged`).
        threads: parts each pass over the points is split into, one thread each (None:
            :func:`mixed_threads`); the estimates do not depend on it beyond round-off.
        chunk_size: points per chunk of a pass (at most :data:`~._kernel.PART_CHUNK` where
            the pass is split into parts).
        mode_design: ``(n, r)`` (float32 kept in float32): the last ``r`` unknowns of ``x``
            are coefficients (m) of deviations known per point, ``dev_i += mode_design_i .
            x[u - r:]`` (e.g. Zernike modes at each point's aperture coordinates); ``condition``
            then takes the first ``u - r`` unknowns. The same model as a condition that
            evaluates the modes at the observed point itself, when the columns are evaluated
            where the observations are (their hit points on the fitted surface: estimates
            within 0.02 sigma, sigmas within 0.5 %, ``tests/solver/test_mixed.py``; at the
            points' true positions 0.05 sigma, as range noise moves an observation across the
            surface by up to 15 mm), at half the cost of the pass (the derivatives of seven
            Zernike terms doubled it).
        rate0: the contraction of the iteration on this problem where known (the
            ``contraction`` of an adjustment of the same model and points, or of a sample of
            them, that this one starts from); until it measures its own, a step is converged
            when the rest it predicts, ``step rate0 / (1 - rate0)``, is below ``tol``
            (:func:`._kernel.remaining_error`). 1: no prediction (the step itself). Taken
            only with the start's residuals ``v0`` and where no smooth modes are carried
            (``ridge`` None). Without ``v0`` the first linearisation is at the observations
            themselves, whose error the contraction does not describe (a start from a quarter
            of the points, ``tests/solver/test_mixed.py``: 0.049 sigma left after a first
            step it predicted to 0.0024 sigma). With modes, the covariance of tz (the
            modes' partner through the aperture's coverage) moved by up to 0.8 % at the
            second linearisation (1.8 % where the modes started from zero), the estimates by
            < 0.005 sigma (positions of 1e5 points started from a sample of 2.5e4, 12 seeds
            of the ``gravity`` case of ``benchmarks/uncertainty_calibration.py``): the first
            step's statistics would keep that.

    The statistics at the solution (covariance, variance components, residuals) come from the
    last step's linearisation: its step, or the rest of the steps its contraction predicts,
    was below ``tol`` sigma, so no further pass is made.
    """
    n = np.shape(l)[0]
    max_iter = max(int(max_iter), 1)
    MZ = (np.zeros((n, 0)) if mode_design is None
          else np.asarray(mode_design, design_dtype(mode_design)).reshape(n, -1))
    f = jnp.float64
    k = design.shape[1]
    ridge_idx, ridge_group, n_groups = ridge_indices(ridge)
    var0 = (jnp.asarray(noise_var0, f), jnp.asarray(cell_var0, f).reshape(k),
            jnp.broadcast_to(jnp.asarray(ridge_var0, f), (n_groups,)))
    U0 = jnp.zeros((n_cells, k), f) if u0 is None else jnp.asarray(u0, f)
    threads = mixed_threads(n) if threads is None else max(1, int(threads))
    chunk = chunk_for(n, part_chunk(chunk_size, threads))
    g_np = np.asarray(groups)
    threads = min(threads, -(-n // chunk))  # whole chunks per part: no empty part
    reject_from = 0 if u0 is not None else 1
    rate0 = 1.0 if v0 is None or ridge else rate0
    cfg = _Settings(dev_column=int(dev_column), n_cells=int(n_cells), chunk=chunk,
                    tol=float(tol), max_iter=int(max_iter),
                    estimate_variances=bool(estimate_variances), n_ridge_groups=n_groups)
    k_rob = jnp.asarray(np.inf if robust_k is None else robust_k, f)
    x0 = jnp.asarray(x0, f)
    if threads > 1:
        sig2 = jnp.asarray(sigma_l, f) ** 2
        pts = {"L": l, "V": v0, "C": consts, "W": weights,
               "S2": sig2 if sig2.ndim == 2 else jnp.broadcast_to(sig2, (3,)), "G": g_np,
               "DM": design, "MZ": MZ}
        return _solve_split(condition, cfg, threads, pts, x0, U0, var0, ridge_idx,
                            ridge_group, k_rob, reject_from, float(rate0))
    l = jnp.asarray(l, f)
    pts = {"L": l, "V": jnp.zeros_like(l) if v0 is None else jnp.asarray(v0, f),
           "C": jnp.asarray(consts, f), "W": jnp.asarray(weights, f),
           "S2": jnp.broadcast_to(jnp.asarray(sigma_l, f) ** 2, l.shape),
           "G": jnp.asarray(g_np, jnp.int32), "DM": jnp.asarray(design, f),
           "MZ": jnp.asarray(MZ, f)}
    return _solve(condition, cfg, pts, x0, U0, var0, ridge_idx, ridge_group, k_rob,
                  on_device(True, bool), on_device(reject_from), on_device(rate0, f))


def ridge_chi2(result: MixedResult, ridge: dict[str, list[int]] | None) -> dict[str, tuple]:
    """Per ridge group: ``(chi2, dof, p)`` of its modes estimated as fixed effects against zero
    (``shared/spec/physics.md``, Statistics): whether the data show the group at all, beyond
    the noise and the cells' random effect. ``p`` large: the data do not show these modes, and
    a variance estimated for them is noise (a few coefficients cannot carry a variance)."""
    out, start = {}, 0
    xf = np.asarray(result.ridge_fixed)
    C = np.asarray(result.ridge_fixed_cov)
    for name, idx in (ridge or {}).items():
        sl = slice(start, start + len(idx))
        start += len(idx)
        c = C[sl, sl]
        t = float(xf[sl] @ np.linalg.lstsq(c, xf[sl], rcond=1e-12)[0])
        out[name] = (t, len(idx), chi2_sf(len(idx), t))
    return out


def chi2_sf(dof: int, t: float) -> float:
    """``P(chi2_dof > t)``, the chi-square survival function of an integer number of degrees
    of freedom, in closed form (``Q(k/2, t/2)``: a finite Poisson sum for even ``k``, with
    ``erfc`` for odd ``k``; each term in logarithms, so no term overflows). Equal to
    ``scipy.special.chdtrc`` within 5e-13 relative down to p = 1e-290 for 1-1000 degrees of
    freedom (``tests/solver/test_mixed.py``), without importing ``scipy.special`` (0.08 s of
    every ``fit`` command, for a few mode tests). 1 for ``t <= 0``, NaN for NaN. The package's
    one chi-square survival: the mode tests' and the diagnosis' p-values."""
    k = int(dof)
    if k < 1:
        raise ValueError(f"degrees of freedom: expected an integer >= 1, found {dof}")
    if math.isnan(t):
        return math.nan
    if t <= 0:
        return 1.0
    x = 0.5 * float(t)
    if math.isinf(x):
        return 0.0
    if k % 2 == 0:  # exp(-x) sum_{i < k/2} x^i / i!
        terms = [i * math.log(x) - x - math.lgamma(i + 1) for i in range(k // 2)]
        head = 0.0
    else:  # erfc(sqrt x) + exp(-x) sum_{1 <= i <= (k-1)/2} x^(i-1/2) / Gamma(i+1/2)
        terms = [(i - 0.5) * math.log(x) - x - math.lgamma(i + 0.5)
                 for i in range(1, (k - 1) // 2 + 1)]
        head = math.erfc(math.sqrt(x))
    top = max(terms, default=-math.inf)
    tail = 0.0 if top == -math.inf else math.exp(top) * math.fsum(
        math.exp(e - top) for e in terms)
    return min(1.0, head + tail)


def ridge_indices(ridge: dict[str, list[int]] | None) -> tuple[Array, Array, int]:
    """``(indices into x, their group, number of groups)`` of a ridge specification."""
    ridge = ridge or {}
    names = list(ridge)
    return (jnp.asarray([i for g in names for i in ridge[g]], jnp.int32),
            jnp.asarray([j for j, g in enumerate(names) for _ in ridge[g]], jnp.int32),
            len(names))
