"""Rigorous Gauss-Helmert adjustment, generic over a per-point condition ``F(l, x, c) = 0``.

Model (Pope 1972; Lenzmann & Lenzmann 2004): every point ``i`` has observations ``l_i`` (here
three: range, horizontal and vertical angle) with a priori standard deviations ``sigma_l`` and
one condition ``F(l_i + v_i, x, c_i) = 0`` with the unknowns ``x`` and per-point constants
``c_i``. The adjustment is re-linearised at ``l + v`` (not at ``l``), so it converges to the
exact least-squares solution ``min v^T Sigma^-1 v`` even for strongly non-linear conditions.

Per iteration, at the linearisation point ``(l0 = l + v, x0)``:

* ``a_i = dF/dx``, ``b_i = dF/dl`` by JAX autodiff of the scalar condition (vmapped over points),
* misclosure ``w_i = F(l0, x0) + b_i . (l_i - l0_i)``,
* ``m_i = b_i Sigma_i b_i^T`` (a scalar: one condition per point),
* normal equations ``N = sum a a^T / m``, ``n = sum a w / m``, accumulated chunk by chunk with
  ``lax.scan`` so the memory is bounded whatever the number of points,
* ``dx = -N^-1 n``, ``k_i = -(a_i . dx + w_i) / m_i``, ``v_i = Sigma_i b_i k_i``.

``sigma0^2 = v^T Sigma^-1 v / (n - u)`` and the covariance of the unknowns is ``sigma0^2 N^-1``.

Masks/weights (``weights`` in [0, 1]) serve three purposes with one mechanism: padding of batches
to one shape, rejection of outliers (weight 0), and robust down-weighting.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._config import on_device
from .._programs import cached_jit
from ._kernel import (
    REJECT_BELOW,
    chunk_for,
    gh_one_pass,
    host_sum,
    linearize_rev,
    newton_step,
    next_rate,
    part_chunk,
    part_final,
    part_omega,
    part_pass,
    part_start,
    pass_threads,
    point_weights,
    remaining_error,
    thread_pool,
)

Condition = Callable[[Float[Array, "3"], Float[Array, " u"], Float[Array, " k"]], Float[Array, ""]]


class AbstractAdjustment(eqx.Module):
    """What every adjustment result offers from its covariance ``cov`` of the unknowns
    (:class:`GHResult`, :class:`~hartrao_jax.solver.MixedResult`); subclasses declare ``cov``
    (no field here, so that each keeps its own field order)."""

    @property
    def sigma(self) -> Float[Array, " u"]:
        """Standard deviations of the unknowns."""
        return jnp.sqrt(jnp.diagonal(self.cov, axis1=-2, axis2=-1))

    @property
    def correlation(self) -> Float[Array, "u u"]:
        """Correlation matrix of the unknowns."""
        s = self.sigma
        return self.cov / (s[..., :, None] * s[..., None, :])


class GHResult(AbstractAdjustment):
    """Result of a Gauss-Helmert adjustment (all arrays; batched results carry a leading axis).

    Attributes:
        x: estimated unknowns (units of each parameter).
        cov: covariance of the unknowns, ``sigma0^2 N^-1``.
        N: normal matrix at the solution (with a priori sigma0 = 1).
        sigma0: a posteriori standard deviation of unit weight (dimensionless, ~1 if the
            a priori sigmas are right).
        v: residuals of the observations, shape (n, 3), same units as ``l``.
        misclosure: ``F(l, x)`` at the observations (units of the condition; metres here).
        normalized: standardized residual of each point, ``|k_i| sqrt(m_i) / sigma0``.
        weights: the weights used at the end (0 for rejected or padded points).
        redundancy: number of used points minus number of unknowns.
        iterations: Gauss-Newton iterations done.
        converged: True if the last step was below the tolerance.
    """

    x: Float[Array, " u"]
    cov: Float[Array, "u u"]
    N: Float[Array, "u u"]
    sigma0: Float[Array, ""]
    v: Float[Array, "n 3"]
    misclosure: Float[Array, " n"]
    normalized: Float[Array, " n"]
    weights: Float[Array, " n"]
    redundancy: Int[Array, ""]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]


def host_result(*, keep_host: tuple[str, ...] = (), **fields) -> GHResult:
    """A :class:`GHResult` of host values (NumPy arrays, Python numbers; its fields by name)
    put on the device by ``device_put``: ``jnp.asarray`` lowers and loads a program per shape
    and dtype in every process (10-25 ms each). The fields named in ``keep_host`` stay the
    host's NumPy arrays (no device copy beside them)."""
    fields = {k: np.asarray(v) for k, v in fields.items()}
    host = {k: fields.pop(k) for k in keep_host}
    return GHResult(**jax.device_put(fields), **host)


def _linearize(condition: Condition, l0, x, c):
    """Value of the condition and its gradients ``a = dF/dx``, ``b = dF/dl`` for one point."""
    F, (a, b) = jax.value_and_grad(lambda xx, ll: condition(ll, xx, c), argnums=(0, 1))(x, l0)
    return F, a, b


def _chunked(arrays, chunk: int):
    """Reshape per-point arrays (n, ...) to (n_chunks, chunk, ...), padding the tail.

    The tail repeats the last point (``edge`` mode), so the condition stays finite there; the
    weights array must come padded with zeros (its pad is replaced by 0 by the caller).
    """
    n = arrays[0].shape[0]
    n_chunks = max(1, -(-n // chunk))
    pad = n_chunks * chunk - n
    out = []
    for a in arrays:
        a = jnp.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1), mode="edge")
        out.append(a.reshape((n_chunks, chunk) + a.shape[1:]))
    return out, n


def _unchunk(a, n):
    return a.reshape((-1,) + a.shape[2:])[:n]


def _solve_normal(N, rhs):
    """Solve ``N y = rhs`` with Jacobi scaling and a Cholesky factorisation (lineax)."""
    d = 1.0 / jnp.sqrt(jnp.where(jnp.diagonal(N) > 0, jnp.diagonal(N), 1.0))
    Ns = N * d[:, None] * d[None, :]
    op = lx.MatrixLinearOperator(Ns, lx.positive_semidefinite_tag)
    y = lx.linear_solve(op, rhs * d, lx.Cholesky(), throw=False).value
    return y * d


def _inverse(N):
    d = 1.0 / jnp.sqrt(jnp.where(jnp.diagonal(N) > 0, jnp.diagonal(N), 1.0))
    Ns = N * d[:, None] * d[None, :]
    L = jnp.linalg.cholesky(Ns)
    I = jnp.eye(N.shape[0], dtype=N.dtype)
    Li = jax.scipy.linalg.solve_triangular(L, I, lower=True)
    return (Li.T @ Li) * d[:, None] * d[None, :]


def _pass_normals(condition, L, V, C, W, S2, x):
    """One pass over the chunks: accumulate ``N``, ``n`` at the linearisation point (l+v, x)."""
    u = x.shape[0]
    lin = jax.vmap(partial(_linearize, condition), in_axes=(0, None, 0))

    def body(carry, chunk):
        N, n = carry
        l, v, c, w8, s2 = chunk
        F, a, b = lin(l + v, x, c)
        wm, m, ok, q = point_weights(F, b, v, w8, s2)
        a = jnp.where(ok[:, None], a, 0.0)
        aq = a * q[:, None]
        return (N + aq.T @ a, n + aq.T @ jnp.where(ok, wm, 0.0)), None

    init = (jnp.zeros((u, u), x.dtype), jnp.zeros((u,), x.dtype))
    (N, n), _ = jax.lax.scan(body, init, (L, V, C, W, S2))
    return N, n


def _pass_residuals(condition, L, V, C, W, S2, x, dx):
    """Second pass: new residuals ``v``, the weighted square sum and standardized residuals."""
    lin = jax.vmap(partial(_linearize, condition), in_axes=(0, None, 0))

    def body(omega, chunk):
        l, v, c, w8, s2 = chunk
        F, a, b = lin(l + v, x, c)
        wm = F - jnp.sum(b * v, axis=-1)
        m = jnp.sum(b * b * s2, axis=-1)
        msafe = jnp.where(m > 0, m, 1.0)
        k = -(a @ dx + wm) / msafe
        v_new = s2 * b * k[:, None]
        e = jnp.abs(k) * jnp.sqrt(msafe)
        return omega + jnp.sum(jnp.where(w8 > 0, w8 * k * k * m, 0.0)), (v_new, e)

    omega, (Vn, E) = jax.lax.scan(body, jnp.zeros((), x.dtype), (L, V, C, W, S2))
    return Vn, E, omega


def _pass_misclosure(condition, L, C, x):
    f = jax.vmap(condition, in_axes=(0, None, 0))
    return jax.lax.map(lambda lc: f(lc[0], x, lc[1]), (L, C))


def _gauss_helmert(condition, l, x0, sigma_l, consts, weights, v0, tol, *, max_iter, chunk_size,
                   robust_k=None, max_rounds=6, on=None):
    """One adjustment: the one-pass kernel (:mod:`._kernel`) and the result's statistics
    (``robust_k``: the kernel's rejection inside the iteration, a runtime scalar). ``on``: the
    materialising switch (True); inside a trace it must come in as an argument of the traced
    function, a value made there would be a constant that XLA folds away."""
    u = x0.shape[0]
    x, N, Ninv, V, K, M, F0, omega, it, done, weights = gh_one_pass(
        condition, l, x0, sigma_l, consts, weights, v0,
        on_device(True, bool) if on is None else on, tol,
        lin=linearize_rev, chunk=chunk_size, max_iter=max_iter, robust_k=robust_k,
        max_rounds=max_rounds)
    red = jnp.sum(weights > 0) - u
    sigma0 = jnp.sqrt(omega / jnp.maximum(red, 1).astype(omega.dtype))
    return GHResult(
        x=x, cov=sigma0**2 * Ninv, N=N, sigma0=sigma0, v=V, misclosure=F0,
        normalized=jnp.abs(K) * jnp.sqrt(M) / sigma0, weights=weights, redundancy=red,
        iterations=it, converged=done,
    )


def _gauss_helmert_split(condition, l, x0, sigma_l, consts, weights, v0, tol, *, max_iter,
                         chunk_size, threads, robust_k=None, max_rounds=6):
    """:func:`_gauss_helmert` with each pass split into ``threads`` parts of whole chunks, each
    part's pass (:func:`._kernel.part_pass`, its store updated in place) a jitted call in its
    own thread, the normal equations added: XLA runs one call on one core, concurrent calls
    from threads run at the same time. The iteration is that of :func:`._kernel.gh_one_pass`
    (same steps, rejection, convergence test), driven from Python; equal to it up to the order
    of the sums' additions."""
    n, u = l.shape[0], x0.shape[0]
    f = l.dtype
    on = on_device(True, bool)
    robust_k = None if robust_k is None else float(robust_k)  # the limit on the host
    chunk = chunk_size
    m = -(-n // (threads * chunk)) * chunk
    cuts = [(s0, min(s0 + m, n)) for s0 in range(0, n, m)]
    per_s2 = sigma_l.ndim == 2
    # host arrays to the device by device_put (jnp.asarray lowers a conversion per shape)
    parts = [dict(l=jax.device_put(np.asarray(l[a:b])), c=jax.device_put(np.asarray(consts[a:b])),
                  s=sigma_l[a:b] if per_s2 else sigma_l, chunk=min(chunk, b - a))
             for a, b in cuts]
    pool = thread_pool(len(parts))

    def each(fn):
        return list(pool.map(lambda ip: jax.block_until_ready(fn(*ip)), enumerate(parts)))

    stores = each(lambda i, p: part_start(
        condition, p["l"], p["c"], np.asarray(weights[cuts[i][0]:cuts[i][1]]), p["s"],
        None if v0 is None else np.asarray(v0[cuts[i][0]:cuts[i][1]]), on, u=u,
        chunk=p["chunk"]))
    robust = robust_k is not None
    x, dx, it, ratio, rounds, done = x0, np.zeros(np.shape(x0), f), 0, np.inf, 0, False
    rate = 1.0  # the contraction of the steps (as gh_one_pass)
    while it < max_iter and not done:
        judge = robust and it >= 1 and ratio < REJECT_BELOW and rounds < max_rounds
        # the bookkeeping between the passes on the host, in NumPy (the same arithmetic; each
        # eager JAX operation would be a program to lower and load in every process)
        limit = np.asarray(np.inf, f)
        if judge:  # sigma0 of the current solution, the candidates included
            om = each(lambda i, p: part_omega(condition, p["l"], p["c"], p["s"], stores[i], dx,
                                              on, chunk=p["chunk"]))
            red = max(int(sum(int(o[1]) for o in om)) - u, 1)
            limit = np.asarray(robust_k * robust_k * host_sum([o[0] for o in om]) / red)
        outs = each(lambda i, p: part_pass(
            (condition, p["l"], p["c"], p["s"], x, dx, limit, on, p["chunk"]), stores[i]))
        stores = [o[2] for o in outs]
        N, nv = (host_sum([o[j] for o in outs]) for j in (0, 1))
        n_bad = int(sum(int(o[3]) for o in outs))
        judged = judge or not robust or rounds >= max_rounds
        rounds += n_bad > 0
        outs = None
        dx, Ninv, r = newton_step(N, nv)
        rate = float(next_rate(rate, ratio, float(r), n_bad > 0))
        ratio = float(r)
        x = np.asarray(x) + np.asarray(dx)
        it += 1
        done = float(remaining_error(ratio, rate)) < tol and judged and n_bad == 0
    fins = each(lambda i, p: part_final(condition, p["l"], p["c"], p["s"], stores[i], x, dx, on,
                                        chunk=p["chunk"]))
    stores = None
    omega = host_sum([fp[0] for fp in fins])
    V, K, M, F0, W = (np.concatenate([np.asarray(fp[j]) for fp in fins]) for j in range(1, 6))
    if not robust:
        W = np.asarray(weights, f)
    red = np.sum(W > 0) - u
    sigma0 = np.sqrt(omega / np.maximum(red, 1).astype(f))
    Ninv = np.asarray(Ninv)
    return host_result(
        x=x, cov=sigma0**2 * Ninv, N=N, sigma0=sigma0, v=V, misclosure=F0,
        normalized=np.abs(K) * np.sqrt(M) / sigma0, weights=W, redundancy=red, iterations=it,
        converged=done)


def _host_inputs(l, consts, weights, v0):
    """The per-point inputs as float64 host arrays (defaults: no constants, weights 1; ``v0``
    stays None): copied to the device once, whole or per part, by :func:`_adjust`."""
    l = np.asarray(l, np.float64)
    n = l.shape[0]
    consts = np.zeros((n, 0)) if consts is None else np.asarray(consts, np.float64)
    weights = np.ones(n) if weights is None else np.asarray(weights, np.float64)
    return l, consts, weights, None if v0 is None else np.asarray(v0, np.float64)


def _adjust(condition, l, x0, sigma_l, consts, weights, v0, tol, *, max_iter, chunk_size,
            threads=None, robust_k=None, max_rounds=6):
    """One adjustment of host arrays (:func:`_host_inputs`), its passes split over the cores
    when the points are many (:func:`~._kernel.pass_threads` parts, ``threads`` to override),
    else the single jitted loop."""
    n = l.shape[0]
    t = pass_threads(n) if threads is None else max(1, int(threads))
    chunk_size = part_chunk(chunk_size, t)
    t = min(t, max(1, n // chunk_size))
    kw = dict(max_iter=max_iter, chunk_size=chunk_size, robust_k=robust_k,
              max_rounds=max_rounds)
    if t > 1:
        return _gauss_helmert_split(condition, l, x0, sigma_l, consts, weights, v0, tol,
                                    threads=t, **kw)
    return _gauss_helmert(condition, jnp.asarray(l), x0, sigma_l, jnp.asarray(consts),
                          jnp.asarray(weights), None if v0 is None else jnp.asarray(v0), tol,
                          **kw)


def gauss_helmert(
    condition: Condition,
    l: Float[Array, "n 3"],
    x0: Float[Array, " u"],
    sigma_l: Float[Array, " 3"] | Float[Array, "n 3"],
    consts: Float[Array, "n k"] | None = None,
    weights: Float[Array, " n"] | None = None,
    *,
    v0: Float[Array, "n 3"] | None = None,
    max_iter: int = 30,
    tol: float = 1e-6,
    chunk_size: int = 4096,
    threads: int | None = None,
) -> GHResult:
    """Rigorous Gauss-Helmert adjustment of ``condition(l_i + v_i, x, c_i) = 0`` for all points.

    Args:
        condition: pure function ``(l (3,), x (u,), c (k,)) -> scalar``: a plain function or a
            callable ``eqx.Module`` (its arrays are traced, so a new model with other fixed
            values does not recompile).
        l: observations, one row per point (here range m, phi rad, theta rad).
        x0: initial unknowns.
        sigma_l: a priori standard deviations of the observations, per column or per point.
        consts: per-point constants passed to the condition (for example the time stamp).
        weights: per-point weights in [0, 1]; 0 excludes a point (padding, rejection).
        v0: initial residuals (default zero).
        max_iter: maximum Gauss-Newton iterations.
        tol: convergence when every ``|dx_j|`` is below ``tol`` times its a priori standard
            deviation ``sqrt((N^-1)_jj)``.
        chunk_size: points per chunk of the normal-equation accumulation (bounds memory;
            at most :data:`~._kernel.PART_CHUNK` where the pass is split into parts).
        threads: parts each pass is split into, one thread each (None: as the random effect,
            :func:`~._kernel.pass_threads`: the usable cores, one part per 2^17 points at
            most); the estimates do not depend on it beyond round-off.
    """
    l, consts, weights, v0 = _host_inputs(l, consts, weights, v0)
    chunk = int(min(chunk_size, l.shape[0]))
    return _adjust(
        condition, l, jnp.asarray(x0, l.dtype), jnp.asarray(sigma_l, l.dtype), consts, weights,
        v0, float(tol), max_iter=max_iter, chunk_size=chunk, threads=threads,
    )


def gauss_helmert_batch(
    condition: Condition,
    l: Float[Array, "b n 3"],
    x0: Float[Array, "b u"],
    sigma_l: Float[Array, " 3"],
    consts: Float[Array, "b n k"],
    weights: Float[Array, "b n"],
    *,
    max_iter: int = 30,
    tol: float = 1e-6,
    chunk_size: int = 4096,
) -> GHResult:
    """Fit a batch of problems padded to one shape (weights 0 on padding) in one compiled call.

    ``vmap`` of the adaptive loop: each member stops updating once it has converged (JAX masks
    finished members), so each member's result equals fitting it alone; the batch runs as
    long as its slowest member.
    """
    l = jnp.asarray(l, jnp.float64)
    n = l.shape[1]
    chunk = int(min(chunk_size, n))
    fn = lambda ll, xx, cc, ww, on: _gauss_helmert(
        condition, ll, xx, jnp.asarray(sigma_l, l.dtype), cc, ww, None,
        float(tol), max_iter=max_iter, chunk_size=chunk, on=on,
    )
    return eqx.filter_jit(jax.vmap(fn, in_axes=(0, 0, 0, 0, None)))(
        l, jnp.asarray(x0, l.dtype), jnp.asarray(consts, l.dtype), jnp.asarray(weights, l.dtype),
        on_device(True, bool))


def robust_gauss_helmert(
    condition: Condition,
    l, x0, sigma_l, consts=None, weights=None, *,
    k: float = 4.0, max_rounds: int = 6, v0=None, max_iter: int = 30, tol: float = 1e-6,
    chunk_size: int = 4096, threads: int | None = None,
) -> GHResult:
    """Gauss-Helmert with rejection of points beyond ``k`` a-posteriori sigmas, inside the
    iteration (one adjustment, not one per round).

    Rule: a point whose standardized residual ``|k_i| sqrt(m_i) / sigma0`` exceeds ``k`` is
    given weight 0 and stays rejected (no oscillation); ``k = 4`` keeps 99.994 % of normally
    distributed points. It is judged at every iterate from the second on whose previous step
    was below one sigma of the unknowns (``sigma0`` of that iterate, outliers included, as
    after a converged solve), and the iteration ends when a step is below ``tol`` with no
    point rejected in its pass, so at the end no used point is beyond the limit. At most
    ``max_rounds`` passes reject. Until 2026-11 each round was a full adjustment to
    convergence, then rejection, then the next adjustment from that solution (2-3 rounds of
    3-5 iterations); judging at the iterates gives the same rejections on the profile
    campaign (``benchmarks/profile.py``) in about half the passes. ``threads``: as
    :func:`gauss_helmert`.
    """
    l, consts, w, v0 = _host_inputs(l, consts, weights, v0)  # v0 None: zero, no (n, 3) array
    chunk = int(min(chunk_size, l.shape[0]))
    return _adjust(
        condition, l, jnp.asarray(x0, l.dtype), jnp.asarray(sigma_l, l.dtype), consts, w, v0,
        float(tol), max_iter=max_iter, chunk_size=chunk, threads=threads,
        robust_k=on_device(k, l.dtype), max_rounds=int(max_rounds))


class NormalEquations(eqx.Module):
    """Normal equations of a linearisation, optionally with per-group sums (for nuisance groups).

    With ``groups`` (an integer id per point, ``-1`` for none) the sums
    ``S_g = sum 1/m``, ``s_g = sum a/m``, ``t_g = sum w/m`` over each group are returned as well:
    eliminating one free offset per group (e.g. a panel offset common to both cycles) from
    ``[N n]`` is then the Schur complement ``N - sum_g s_g s_g^T / S_g`` (Frisch-Waugh), without
    ever forming a column per group.
    """

    N: Float[Array, "u u"]
    n: Float[Array, " u"]
    wMw: Float[Array, ""]
    S: Float[Array, " g"]
    s: Float[Array, "g u"]
    t: Float[Array, " g"]

    def eliminate_groups(self, d_offset: Float[Array, " u"] | None = None):
        """``(N, n, wMw)`` with one additive offset per group eliminated.

        ``d_offset`` is the derivative of the condition with respect to a group's offset relative
        to ``a`` (default: the offset enters the condition with derivative 1, so the sums over
        ``a/m`` are the coupling). Groups with no points are ignored.
        """
        S = jnp.where(self.S > 0, self.S, 1.0)
        live = (self.S > 0).astype(self.N.dtype)
        N = self.N - jnp.einsum("g,gi,gj->ij", live / S, self.s, self.s)
        n = self.n - jnp.einsum("g,gi,g->i", live / S, self.s, self.t)
        wMw = self.wMw - jnp.sum(live * self.t**2 / S)
        return N, n, wMw


@cached_jit
def _normal_equations(condition, l, x, s2, consts, weights, v, groups, n_groups, chunk_size,
                      offset_derivative):
    u = x.shape[0]
    lin = jax.vmap(partial(_linearize, condition), in_axes=(0, None, 0))
    n_pts = l.shape[0]
    (L, C, W, S2, V, G), n = _chunked([l, consts, weights, s2, v, groups], chunk_size)
    W = W.reshape(-1).at[n_pts:].set(0.0).reshape(W.shape)

    def body(carry, chunk):
        N, nv, wmw, S, sg, tg = carry
        ll, c, w8, ss2, vv, gg = chunk
        F, a, b = lin(ll + vv, x, c)
        wm, m, ok, q = point_weights(F, b, vv, w8, ss2)
        a = jnp.where(ok[:, None], a, 0.0)
        wm = jnp.where(ok, wm, 0.0)
        # derivative of the condition w.r.t. a group offset (1 for a normal offset scaled by
        # the caller through ``offset_derivative`` = index of a constant column, or -1 for 1)
        dg = jnp.ones_like(wm) if offset_derivative < 0 else c[:, offset_derivative]
        gid = jnp.where((gg >= 0) & ok, gg, n_groups)  # a dump group for the rest
        aq = a * q[:, None]
        S = S + jax.ops.segment_sum(q * dg * dg, gid, n_groups + 1)[:n_groups]
        sg = sg + jax.ops.segment_sum(aq * dg[:, None], gid, n_groups + 1)[:n_groups]
        tg = tg + jax.ops.segment_sum(q * wm * dg, gid, n_groups + 1)[:n_groups]
        return (N + aq.T @ a, nv + aq.T @ wm, wmw + jnp.sum(q * wm * wm), S, sg, tg), None

    init = (jnp.zeros((u, u), x.dtype), jnp.zeros((u,), x.dtype), jnp.zeros((), x.dtype),
            jnp.zeros((n_groups,), x.dtype), jnp.zeros((n_groups, u), x.dtype),
            jnp.zeros((n_groups,), x.dtype))
    (N, nv, wmw, S, sg, tg), _ = jax.lax.scan(body, init, (L, C, W, S2, V, G))
    return NormalEquations(N=N, n=nv, wMw=wmw, S=S, s=sg, t=tg)


def normal_equations(
    condition: Condition,
    l: Float[Array, "n 3"],
    x: Float[Array, " u"],
    sigma_l,
    consts=None,
    weights=None,
    v=None,
    *,
    groups: Int[Array, " n"] | None = None,
    n_groups: int = 0,
    offset_column: int = -1,
    chunk_size: int = 1 << 16,
) -> NormalEquations:
    """Normal equations ``N = sum a a^T/m``, ``n = sum a w/m``, ``w^T M^-1 w`` at ``(l + v, x)``.

    The building block of score (Lagrange-multiplier) tests, of joint adjustments (per-scan
    normal equations reduced by Schur complement) and of sensitivity studies: evaluate it with
    a model whose free parameters include the extra ones (at their null values) and partition.
    ``groups``/``n_groups``: also accumulate per-group sums to eliminate one offset per group
    (see :class:`NormalEquations`); ``offset_column``: index of a per-point constant holding
    the derivative of the condition w.r.t. the group offset (-1: derivative 1).
    """
    l = jnp.asarray(l, jnp.float64)
    n = l.shape[0]
    consts = jnp.zeros((n, 0), l.dtype) if consts is None else jnp.asarray(consts, l.dtype)
    weights = jnp.ones((n,), l.dtype) if weights is None else jnp.asarray(weights, l.dtype)
    v = jnp.zeros_like(l) if v is None else jnp.asarray(v, l.dtype)
    groups = -jnp.ones((n,), jnp.int32) if groups is None else jnp.asarray(groups, jnp.int32)
    s2 = jnp.broadcast_to(jnp.asarray(sigma_l, l.dtype) ** 2, l.shape)
    chunk = chunk_for(n, chunk_size)
    return _normal_equations(condition, l, jnp.asarray(x, l.dtype), s2, consts, weights, v, groups,
                             int(n_groups), chunk, int(offset_column))


# padded shapes: scans of similar size share one compiled program


def bucket_size(n: int, *, granularity: int = 8, minimum: int = 4096) -> int:
    """Padded length for ``n`` points: a multiple of ``next_pow2(n) / granularity``.

    Scans of similar size share one padded shape, hence one compiled program.
    """
    p2 = 1 << max(0, int(math.ceil(math.log2(max(n, 1)))))
    q = max(minimum, p2 // granularity)
    return int(-(-n // q) * q)
