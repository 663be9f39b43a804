"""The Gauss-Helmert iteration kernel: ONE linearisation per point and iteration.

Used by :func:`hartrao_jax.solver.gauss_helmert`. Two measures make autodiff as fast as
hand-derived derivatives on XLA-CPU (``benchmarks/results/kernels.md``):

* :func:`materialize_trig` rewrites the per-point condition's jaxpr so that ``sin``/``cos``/
  ``tan`` of each distinct argument are computed once per point (a custom-JVP ``sincos`` behind a
  runtime ``lax.cond``, a fusion boundary XLA cannot see through) and merges expressions the
  model builds twice; XLA otherwise recomputes the trig in every fusion that uses it.
* :func:`gh_one_pass` fuses the residual update of iteration k into the normal-equation pass of
  iteration k+1, from per-point ``a, b`` (float32) and ``w, m`` (float64) stored in place, so
  each iteration linearises every point once; the observations are never padded or copied.

Every function needs ``on``: a runtime boolean scalar (True) passed into the jitted function as
an argument and not batched by ``vmap``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jcore

from .._config import (
    THREADS_ENV,  # noqa: F401  (this module's name before)
    machine_cores,
    usable_cores,
)
from .._config import thread_pool as _config_pool
from .._programs import cached_jit
from ..geometry._trig import sincos_f64

# --------------------------------------------------------------------------------------------
# sin/cos computed once: custom-JVP sincos materialised behind a runtime lax.cond
# --------------------------------------------------------------------------------------------



def point_weights(F, b, v, w, s2):
    """Per point of a Gauss-Helmert linearisation at ``(l + v, x)``: the misclosure at the
    observations ``wm = F - b.v``, its variance ``m = b Sigma b^T`` (``s2``: variances of the
    observations) and the weight ``q = w / m`` (0 where ``w`` or ``m`` is 0).

    Returns ``(wm, m, ok, q)`` with ``ok`` the points that enter the sums.
    """
    wm = F - jnp.sum(b * v, axis=-1)
    m = jnp.sum(b * b * s2, axis=-1)
    ok = (w > 0) & (m > 0)
    q = jnp.where(ok, w / jnp.where(ok, m, 1.0), 0.0)
    return wm, m, ok, q


def _trig(v):
    if v.dtype == jnp.float64:
        return sincos_f64(v)
    return jnp.sin(v), jnp.cos(v)


def _no_trig(v):
    return jnp.zeros_like(v), jnp.ones_like(v)


def _sincos_impl(x, on):
    # A conditional is a fusion boundary: XLA cannot duplicate sin/cos into each consumer fusion.
    # ``on`` must be a runtime, unbatched boolean (True), else XLA folds the cond away (constant)
    # or vmap turns it into a select (batched) and the trig is duplicated again. The branches
    # are module functions, not lambdas: JAX then traces each once per shape instead of at
    # every sin/cos of every condition traced.
    return lax.cond(on, _trig, _no_trig, x)


@jax.custom_jvp
def sincos(x, on):
    """``(sin x, cos x)`` computed once and stored (see ``_sincos_impl``)."""
    return _sincos_impl(x, on)


@sincos.defjvp
def _sincos_jvp(primals, tangents):
    x, on = primals
    dx, _ = tangents
    s, c = sincos(x, on)
    return (s, c), (c * dx, -s * dx)


_TRIG = {"sin", "cos", "tan"}


def _hashable(params):
    try:
        key = tuple(sorted(params.items()))
        hash(key)
        return key
    except TypeError:
        return None


def _eval_cse(jaxpr, consts, args, on, memo):
    """Evaluate ``jaxpr`` with common-subexpression elimination and materialised trig.

    ``memo`` maps (primitive, params, ids of inputs) -> outputs, so an expression traced twice
    by the model (e.g. the corrected theta, built once for the range/angle terms and again for
    the phi terms) is evaluated once, and sin/cos/tan of one argument share one ``sincos``.
    """
    env = {}

    def read(v):
        return v.val if isinstance(v, jcore.Literal) else env[v]

    def key_of(v):
        if isinstance(v, jcore.Literal):
            try:
                return ("lit", float(v.val), str(v.aval))
            except TypeError:
                return ("lit", id(v.val))
        return id(env[v])

    for v, x in zip(jaxpr.constvars, consts):
        env[v] = x
    for v, x in zip(jaxpr.invars, args):
        env[v] = x
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        invals = [read(v) for v in eqn.invars]
        if name in _TRIG:
            x = invals[0]
            k = ("sincos", id(x))
            if k not in memo:
                memo[k] = (x, sincos(x, on))
            s, c = memo[k][1]
            out = [s if name == "sin" else c if name == "cos" else s / c]
        elif name in ("pjit", "jit", "closed_call", "core_call") and "jaxpr" in eqn.params:
            sub = eqn.params["jaxpr"]
            out = _eval_cse(sub.jaxpr, sub.consts, invals, on, memo)
        else:
            pk = None if eqn.effects else _hashable(eqn.params)  # never merge effectful ops
            k = None if pk is None else (name, pk, tuple(key_of(v) for v in eqn.invars))
            if k is not None and k in memo:
                out = memo[k][1]
            else:
                ans = eqn.primitive.bind(*invals, **eqn.primitive.get_bind_params(eqn.params))
                out = list(ans) if eqn.primitive.multiple_results else [ans]
                if k is not None:
                    memo[k] = (invals, out)  # keep the inputs alive: ids stay unique
        for v, x in zip(eqn.outvars, out):
            if not isinstance(v, jcore.DropVar):
                env[v] = x
    return [read(v) for v in jaxpr.outvars]


def materialize_trig(fun, on):
    """``fun`` with each distinct ``sin``/``cos``/``tan`` argument evaluated once per call.

    ``fun`` is any pure JAX function (here the per-point condition ``(l, x, c) -> F``); ``on``
    a runtime boolean scalar equal to True that is NOT batched (pass it into the jitted solver
    as an argument). Works under ``vmap``, ``jacfwd``, ``grad`` and ``jit``.
    """

    def wrapped(*args):
        flat, tree = jax.tree_util.tree_flatten(args)
        closed, out_shape = jax.make_jaxpr(lambda *f: fun(*jax.tree_util.tree_unflatten(tree, f)),
                                           return_shape=True)(*flat)
        out = _eval_cse(closed.jaxpr, closed.consts, flat, on, {})
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(out_shape), out)

    return wrapped


# --------------------------------------------------------------------------------------------
# Linearisations of a chunk of points: (F (n,), a (n, u), b (n, 3))
# --------------------------------------------------------------------------------------------


def linearize_rev(condition, l, x, c, on=None):
    """``(F, a, b)`` of a chunk: reverse mode under vmap; ``on``: materialise the trig."""
    if on is not None:
        condition = materialize_trig(condition, on)

    def one(ll, cc):
        F, (a, b) = jax.value_and_grad(lambda xx, l2: condition(l2, xx, cc), argnums=(0, 1))(x, ll)
        return F, a, b

    return jax.vmap(one)(l, c)


# --------------------------------------------------------------------------------------------
# Gauss-Helmert loop: one linearisation per point and iteration
# --------------------------------------------------------------------------------------------


def solve_scaled(N, rhs):
    """``N^-1 rhs`` and ``N^-1`` with Jacobi scaling and Cholesky (symmetric positive definite
    ``N``; the mixed model's reduced normal equations use it too)."""
    d = 1.0 / jnp.sqrt(jnp.where(jnp.diagonal(N) > 0, jnp.diagonal(N), 1.0))
    Ns = N * d[:, None] * d[None, :]
    L = jnp.linalg.cholesky(Ns)
    Li = jax.scipy.linalg.solve_triangular(L, jnp.eye(N.shape[0], dtype=N.dtype), lower=True)
    Ninv_s = Li.T @ Li
    return (Ninv_s @ (rhs * d)) * d, Ninv_s * d[:, None] * d[None, :]


def _materialize(on, tree):
    """Identity behind a runtime ``lax.cond``: a fusion boundary, so XLA computes ``tree``
    once instead of duplicating its producers into every consumer fusion."""
    return lax.cond(on, _identity, _zeros_like, tree)


def _identity(t):
    return t


def _zeros_like(t):
    return jax.tree_util.tree_map(jnp.zeros_like, t)


def _window(i, chunk, n):
    """Start of chunk ``i`` (the last one is shifted back to end at ``n``: no padding copy) and
    the mask of its points not already covered by chunk ``i - 1``."""
    start = jnp.minimum(i * chunk, n - chunk)
    fresh = start + jnp.arange(chunk) >= i * chunk
    return start, fresh


def make_pass(condition, l, consts, weights, sigma_l, on, *, lin, chunk, trig=True,
              store_dtype=jnp.float32, mat=True):
    """The per-iteration pass of :func:`gh_one_pass`: ``one_pass(x, dx_prev, store)``.

    Returns ``(one_pass, residuals, store0(v0), nc)``; ``one_pass`` gives ``(N, n, store)``.
    The store is ``(a, b, wm, m)``, one row of ``chunk`` points per chunk; a fifth member
    ``W`` (nc, chunk) carries the weights in the same layout (:func:`chunk_weights`) instead of
    ``weights`` (their rejections are then kept there). ``one_pass(x, dx_prev, store, limit)``
    with such a store also rejects: a point whose residual of the previous solution (from the
    store and ``dx_prev``) has ``k^2 m > limit`` gets weight 0 before it enters the sums; it
    then returns ``(N, n, store, rejected)`` (points newly at weight 0 in this pass).
    """
    n = l.shape[0]
    nc = -(-n // chunk)
    f = l.dtype
    s2 = jnp.asarray(sigma_l, f) ** 2  # (3,) or (n, 3)
    per_point_s2 = s2.ndim == 2

    def sl(a, start):
        return lax.dynamic_slice_in_dim(a, start, chunk, axis=0)

    def chunk_s2(start):
        return sl(s2, start) if per_point_s2 else s2

    def store0(u, v0=None):
        if v0 is None:
            b_start = jnp.zeros((nc, chunk, 3), store_dtype)
        else:
            b0 = (v0 / s2).astype(store_dtype)
            b_start = jax.vmap(lambda i: sl(b0, _window(i, chunk, n)[0]))(jnp.arange(nc))
        return (jnp.zeros((nc, chunk, u), store_dtype), b_start,
                -jnp.ones((nc, chunk), f), jnp.ones((nc, chunk), f))

    def read(st, i):
        # materialise the chunk's slice of the store before it is overwritten in place: else
        # XLA fuses the slice into several consumers and, unable to order them before the
        # in-place update, copies the WHOLE store every chunk (O(n^2 / chunk) traffic). The
        # runtime cond is a fusion boundary (an optimization_barrier is not: XLA drops it).
        return lax.cond(on, lambda st: tuple(s[i] for s in st),
                        lambda st: tuple(jnp.zeros(s.shape[1:], s.dtype) for s in st), st)

    def chunk_residuals(a, b, wm, m, dx, start):
        k = -((a.astype(f) @ dx) + wm) / m
        return k, chunk_s2(start) * b.astype(f) * k[:, None], m

    def residuals(st, i, dx, start):
        return chunk_residuals(*read(st, i)[:4], dx, start)

    def one_pass(x, dx_prev, store, limit=None):
        u = x.shape[0]
        own_w = len(store) == 5  # the weights in the store's layout

        def body(i, carry):
            N, nv, store, n_bad = carry
            start, fresh = _window(i, chunk, n)
            s2c = chunk_s2(start)
            a_, b_, wm_, m_, *w_ = read(store, i)
            k, v, m_prev = chunk_residuals(a_, b_, wm_, m_, dx_prev, start)
            w8 = w_[0] if own_w else jnp.where(fresh, sl(weights, start), 0.0)
            if limit is not None:  # the previous solution's residual beyond it: out for good
                bad = (w8 > 0) & (k * k * m_prev > limit)
                w8 = jnp.where(bad, 0.0, w8)
                n_bad = n_bad + jnp.sum(bad, dtype=jnp.int32)
            F, a, b = lin(condition, sl(l, start) + v, x, sl(consts, start), on if trig else None)
            # materialise the linearisation once: a, b have several consumers (store, masked
            # normals) and XLA would otherwise re-run the whole derivative per consumer (2x)
            if mat:
                F, a, b = _materialize(on, (F, a, b))
            wm, m, ok, q = point_weights(F, b, v, w8, s2c)
            a0 = jnp.where(ok[:, None], a, 0.0)
            aq = a0 * q[:, None]
            N = N + aq.T @ a0
            nv = nv + aq.T @ jnp.where(ok, wm, 0.0)
            new = (a.astype(store_dtype), b.astype(store_dtype), wm, jnp.where(m > 0, m, 1.0))
            store = tuple(s.at[i].set(v_) for s, v_ in zip(store, new + (w8,) * own_w))
            return N, nv, store, n_bad

        init = (jnp.zeros((u, u), f), jnp.zeros((u,), f), store, jnp.zeros((), jnp.int32))
        N, nv, store, n_bad = lax.fori_loop(0, nc, body, init)
        return (N, nv, store) if limit is None else (N, nv, store, n_bad)

    return one_pass, residuals, store0, nc


def chunk_weights(weights, chunk):
    """Per-point weights (n,) in the store's layout (nc, chunk): the last chunk ends at ``n``
    (overlapping the one before), its rows already in that chunk at weight 0."""
    n = weights.shape[0]

    def one(i):
        start, fresh = _window(i, chunk, n)
        return jnp.where(fresh, lax.dynamic_slice_in_dim(weights, start, chunk), 0.0)

    return jax.vmap(one)(jnp.arange(-(-n // chunk)))


def store_omega(residuals, store, dx):
    """``omega = sum w k^2 m`` of the residuals ``k`` that the stored linearisation and the
    step ``dx`` give (a store with its weights, :func:`make_pass`; no linearisation, one read
    of the store): the weighted square sum of the solution ``x + dx``, whence ``sigma0``."""
    W = store[4]

    def body(i, om):
        k, _, m = residuals(store, i, dx, 0)  # (start only places per-point sigmas: unused)
        return om + jnp.sum(jnp.where(W[i] > 0, W[i] * k * k * m, 0.0))

    return lax.fori_loop(0, W.shape[0], body, jnp.zeros((), W.dtype))


#: Robust rejection is judged once the previous step was below this many sigmas of the
#: unknowns (``max_j |dx_j| / sqrt((N^-1)_jj)``): near the solution, not at the first guess.
REJECT_BELOW = 1.0


def array_namespace(*args):
    """``jax.numpy`` where any of ``args`` (pytrees) is traced, else NumPy: the small
    bookkeeping functions below serve both the compiled loops and the host's, and each
    ``jax.numpy`` call on concrete values lowers and loads a program of its own per shape (30
    of them, 0.1 s, for :func:`._mixed._settled` alone in one ``fit``)."""
    traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree.leaves(args))
    return jnp if traced else np


def host_sum(values):
    """The parts' values (device or host arrays of one shape) added on the host in NumPy, in
    their order: the same additions as XLA's, without a program per shape to lower and load
    in every process."""
    total = np.asarray(values[0])
    for v in values[1:]:
        total = total + np.asarray(v)
    return total


def remaining_error(step, rate):
    """The error left in a solution after a Gauss-Newton step of ``step`` sigmas (largest
    ``|dx_j| / sigma_j``) when the iteration contracts by ``rate`` per step (the ratio of two
    consecutive steps with nothing else changed between them): the rest of the geometric
    series ``step rate / (1 - rate)`` where ``rate < 0.5`` (near the solution), else the step
    itself. The iterations stop when it is below tol: one pass fewer where the steps contract
    fast (3.1, 0.082, then 4.5e-5 sigma on a full-resolution position: the third step only
    confirmed the second). Floats or JAX scalars (:func:`array_namespace`)."""
    xp = array_namespace(step, rate)
    step, rate = xp.asarray(step), xp.asarray(rate)
    fast = rate < 0.5
    return xp.where(fast, step * rate / (1.0 - xp.where(fast, rate, 0.0)), step)


def next_rate(rate, previous, step, restarted):
    """The iteration's contraction after a step of ``step`` sigmas that followed one of
    ``previous``: ``step / previous``; unchanged (``rate``) where the step restarted (a
    rejection moved the solution between the two: not a contraction) or where there was no
    previous step (``previous`` 0 or infinite): the start value, 1 (no extrapolation) or a
    contraction measured on the same problem. Floats or JAX scalars
    (:func:`array_namespace`)."""
    xp = array_namespace(rate, previous, step, restarted)
    rate, previous, step, restarted = map(xp.asarray, (rate, previous, step, restarted))
    has = xp.isfinite(previous) & (previous > 0)
    return xp.where(restarted | ~has, rate, step / xp.where(has, previous, 1.0))


@cached_jit
def gh_one_pass(condition, l, x0, sigma_l, consts, weights, v0, on, tol=1e-6, *, lin,
                chunk=4096, max_iter=30, store_dtype=jnp.float32, trig=True, robust_k=None,
                max_rounds=6, reject_below=REJECT_BELOW):
    """Rigorous Gauss-Helmert adjustment with ONE linearisation per point and iteration.

    Pass k (a ``fori_loop`` over chunks), per chunk:

    1. residuals of iteration k-1 from the stored ``a, b, w, m`` and ``dx_{k-1}``:
       ``k = -(a.dx + w) / m``, ``v = Sigma b k``;
    2. linearise at ``(l + v, x_k)`` -> ``F, a, b``; ``w = F - b.v``; ``m = b Sigma b``;
    3. accumulate ``N``, ``n`` and overwrite the chunk's stored ``a, b, w, m`` in place.

    ``dx_k = -N^-1 n``. After convergence one sweep over the store gives ``v``, ``k`` at the
    solution (no further linearisation). The start store encodes ``v0``: ``a = 0``,
    ``b = v0 / sigma^2``, ``w = -1``, ``m = 1`` gives ``k = 1``, ``v = v0``.

    ``a`` and ``b`` are stored in ``store_dtype`` (float32: 48 instead of 96 bytes per point):
    they only enter the correction ``a.dx`` (-> 0 at convergence) and ``v = Sigma b k`` (to
    1e-7 relative, ~1e-10 m); ``w``, ``m`` stay float64. The observations are never copied
    or padded: the last chunk overlaps the previous one, its repeated points masked.

    Robust rejection inside the iteration (``robust_k``, a runtime scalar; None: none): before
    pass k (k >= 1, once the previous step was below ``reject_below`` of its sigma
    ``sqrt((N^-1)_jj)``), ``sigma0^2 = omega / (n_used - u)`` of the current solution (one
    read of the store, :func:`store_omega`), and in the pass a point with
    ``|k| sqrt(m) / sigma0 > robust_k`` gets weight 0 for good before it enters the sums: the
    rule of the repeated solves (standardized residual beyond ``robust_k`` a-posteriori
    sigmas), judged at each iterate instead of at each converged solve. At most
    ``max_rounds`` passes reject; the iteration has converged when a step is below ``tol`` and
    its pass rejected nothing (a step below tol: :func:`remaining_error`, the rest of the
    steps at the contraction of the last two with no rejection in the later one's pass).

    Returns ``(x, N, N^-1, v (n, 3), k (n,), m (n,), F(l, x) (n,), omega, iterations,
    converged, weights)``; ``normalized = |k| sqrt(m) / sigma0``.
    """
    u = x0.shape[0]
    f = l.dtype
    one_pass, residuals, store0_fn, nc = make_pass(
        condition, l, consts, weights, sigma_l, on, lin=lin, chunk=chunk, trig=trig,
        store_dtype=store_dtype)
    robust = robust_k is not None
    # with rejection the weights live in the store (its layout), where the pass updates them
    store0 = store0_fn(u, v0) + ((chunk_weights(weights, chunk),) if robust else ())

    def rejecting_pass(x, dx_prev, store, it, ratio_prev, rounds):
        judge = (it >= 1) & (ratio_prev < reject_below) & (rounds < max_rounds)
        red = jnp.maximum(jnp.sum(store[4] > 0) - u, 1).astype(f)
        limit = lax.cond(  # the read of the store only where the points are judged
            judge, lambda: robust_k * robust_k * store_omega(residuals, store, dx_prev) / red,
            lambda: jnp.asarray(jnp.inf, f))
        N, nv, store, n_bad = one_pass(x, dx_prev, store, limit)
        judged = judge | (rounds >= max_rounds)
        return N, nv, store, rounds + (n_bad > 0), judged & (n_bad == 0)

    def step(state):
        x, dx_prev, store, it, _, _, _, ratio_prev, rounds, rate = state
        if robust:
            rounds_before = rounds
            N, nv, store, rounds, clean = rejecting_pass(x, dx_prev, store, it, ratio_prev,
                                                         rounds)
            moved = rounds > rounds_before  # this pass rejected points: a new start
        else:
            N, nv, store = one_pass(x, dx_prev, store)
            clean, moved = True, False
        dx, Ninv = solve_scaled(N, -nv)
        ratio = step_sigmas(dx, Ninv)
        rate = next_rate(rate, ratio_prev, ratio, moved)
        done = (remaining_error(ratio, rate) < tol) & clean
        return x + dx, dx, store, it + 1, N, Ninv, done, ratio, rounds, rate

    def cond(state):
        return (state[3] < max_iter) & ~state[6]

    zu = jnp.zeros((u, u), f)
    state = (x0, jnp.zeros_like(x0), store0, jnp.array(0), zu, zu, jnp.array(False),
             jnp.asarray(jnp.inf, f), jnp.array(0), jnp.ones((), f))
    x, dx, store, it, N, Ninv, done, _, _, _ = lax.while_loop(cond, step, state)

    omega, V, K, M, F0, weights = final_sweep(condition, l, consts, weights, store, residuals,
                                              x, dx, on, chunk=chunk, trig=trig)
    return x, N, Ninv, V, K, M, F0, omega, it, done, weights




def final_sweep(condition, l, consts, weights, store, residuals, x, dx, on, *, chunk, trig=True):
    """At the solution ``x`` (= the last linearisation's ``x`` + ``dx``): residuals from the
    store (no linearisation) and the misclosure ``F(l, x)`` at the observations (a primal-only
    evaluation), in one sweep. Returns ``(omega, v (n, 3), k (n,), m (n,), F (n,), weights
    (n,))``; the weights are the store's (its fifth member) when it has them."""
    n = l.shape[0]
    f = l.dtype
    own_w = len(store) == 5
    cond_mt = materialize_trig(condition, on) if trig else condition
    misclosure = jax.vmap(cond_mt, in_axes=(0, None, 0))

    def fin(i, carry):
        omega, V, K, M, F0, Wn = carry
        start, fresh = _window(i, chunk, n)
        sl = partial(lax.dynamic_slice_in_dim, start_index=start, slice_size=chunk)
        w8 = store[4][i] if own_w else jnp.where(fresh, sl(weights), 0.0)
        k, v, m = residuals(store, i, dx, start)
        omega = omega + jnp.sum(jnp.where(w8 > 0, w8 * k * k * m, 0.0))
        f0 = misclosure(sl(l), x, sl(consts))
        # rows of the overlapped last chunk already written by chunk i-1 keep their value
        V = lax.dynamic_update_slice_in_dim(V, jnp.where(fresh[:, None], v, sl(V)), start, 0)
        K = lax.dynamic_update_slice_in_dim(K, jnp.where(fresh, k, sl(K)), start, 0)
        M = lax.dynamic_update_slice_in_dim(M, jnp.where(fresh, m, sl(M)), start, 0)
        F0 = lax.dynamic_update_slice_in_dim(F0, jnp.where(fresh, f0, sl(F0)), start, 0)
        if own_w:
            Wn = lax.dynamic_update_slice_in_dim(Wn, jnp.where(fresh, w8, sl(Wn)), start, 0)
        return omega, V, K, M, F0, Wn

    z = jnp.zeros((n,), f)
    W0 = jnp.zeros((n,), f) if weights is None else weights
    return lax.fori_loop(0, -(-n // chunk), fin,
                         (jnp.zeros((), f), jnp.zeros((n, 3), f), z, jnp.ones((n,), f), z, W0))


# --------------------------------------------------------------------------------------------
# The same iteration with each pass split over the cores (a part of the points per thread)
# --------------------------------------------------------------------------------------------

#: Points per part below which a pass is not split (one part, the single jitted loop).
PARALLEL_MIN_POINTS = 1 << 17
#: Points per chunk of a pass that is to take one core, at most: XLA's runtime spreads a
#: larger chunk's loops over its threads (every core of the machine), which another pass
#: needs at the same time. Two parts of the random effect's pass over 1e6 points each at once
#: (2 cores): 0.46-0.50 s with chunks of 2048, 0.52-0.56 s with 4096, 0.54-0.56 s with 8192;
#: the white adjustment of 2e6 points in two parts (4 passes) 0.81-0.88 s with 2048, 0.87-0.98
#: s with 4096; two full-resolution positions streamed at once on 2 Dask workers of one thread
#: (4.9e7 rows) 49.1-51.1 s with 2048, 54.7 s with 4096, 57.5-61.0 s with 8192. A pass that
#: has the machine to itself keeps larger chunks, which XLA spreads over the cores (the random
#: effect's over 1e6 points alone: 0.35-0.37 s with 8192, 0.47 s with 2048).
PART_CHUNK = 2048


def part_chunk(chunk: int, threads: int) -> int:
    """The chunk of a pass run in ``threads`` parts at once: ``chunk``, at most
    :data:`PART_CHUNK` where each part is to take one core: the pass is split (``threads >
    1``), or this process is to use fewer cores than XLA's threads span
    (``$HARTRAO_JAX_THREADS`` below :func:`machine_cores`: a Dask worker of one thread, the
    other workers on the other cores)."""
    return (min(chunk, PART_CHUNK) if threads > 1 or usable_cores() < machine_cores()
            else chunk)


def chunk_for(n: int, chunk: int = 1 << 16) -> int:
    """Points per chunk of a pass over ``n`` points: ``chunk``, at most the power of two at or
    above ``n`` (at least 256), so that a pass over few points is not padded to a large
    chunk."""
    return int(min(chunk, max(256, 1 << int(np.ceil(np.log2(max(n, 1)))))))


def pass_threads(n: int) -> int:
    """Parts (threads) a pass over ``n`` points is split into: :func:`usable_cores`, at most 8
    and at most one part per :data:`PARALLEL_MIN_POINTS` points.

    A pass is one loop over chunks, and XLA spreads a chunk's loops over its threads only
    where they are large: one jitted call's loop uses at most part of the cores. Two calls
    from two threads run at the same time (the runtime executes concurrent calls
    concurrently), so the points are split into parts, each part's pass runs in its own
    thread on chunks of at most :data:`PART_CHUNK` points (one core each), and the sums are
    added."""
    return int(max(1, min(usable_cores(), 8, n // PARALLEL_MIN_POINTS)))


def thread_pool(threads: int) -> ThreadPoolExecutor:
    """A pool of ``threads`` threads for the parts of a pass (one per process and size)."""
    return _config_pool(threads, "mixed")


@cached_jit
def part_start(condition, l, consts, weights, sigma_l, v0, on, *, u, chunk):
    """A part's start store with its weights (the layout of :func:`make_pass`)."""
    _, _, store0, _ = make_pass(condition, l, consts, weights, sigma_l, on, lin=linearize_rev,
                                chunk=chunk)
    return store0(u, v0) + (chunk_weights(weights, chunk),)


def _part_pass(args, store):
    condition, l, consts, sigma_l, x, dx_prev, limit, on, chunk = args
    one_pass, _, _, _ = make_pass(condition, l, consts, None, sigma_l, on, lin=linearize_rev,
                                  chunk=chunk)
    return one_pass(x, dx_prev, store, limit)


#: A part's pass (:func:`make_pass` with the rejection at ``limit``):
#: ``part_pass((condition, l, consts, sigma_l, x, dx_prev, limit, on, chunk), store)`` ->
#: ``(N, n, store, rejected)``; the store is donated (updated in place, no copy).
part_pass = cached_jit(_part_pass, donate="all-except-first")


@cached_jit
def part_omega(condition, l, consts, sigma_l, store, dx, on, *, chunk):
    """A part's ``(sum w k^2 m, points used)`` at the solution ``x + dx`` (:func:`store_omega`)."""
    _, residuals, _, _ = make_pass(condition, l, consts, None, sigma_l, on, lin=linearize_rev,
                                   chunk=chunk)
    return store_omega(residuals, store, dx), jnp.sum(store[4] > 0)


@cached_jit
def part_final(condition, l, consts, sigma_l, store, x, dx, on, *, chunk):
    """A part's :func:`final_sweep`."""
    _, residuals, _, _ = make_pass(condition, l, consts, None, sigma_l, on, lin=linearize_rev,
                                   chunk=chunk)
    return final_sweep(condition, l, consts, None, store, residuals, x, dx, on, chunk=chunk)


def step_sigmas(dx, Q):
    """The convergence measure of a step: its largest component in its sigmas,
    ``max |dx_j| / sqrt(Q_jj)`` (``Q`` the step's cofactor matrix; a zero diagonal counts as
    1)."""
    q = jnp.diagonal(Q)
    return jnp.max(jnp.abs(dx) / jnp.sqrt(jnp.where(q > 0, q, 1.0)))


@cached_jit
def newton_step(N, nv):
    """``dx = -N^-1 n``, ``N^-1`` and the convergence measure ``max |dx_j| / sqrt((N^-1)_jj)``
    (as one step of :func:`gh_one_pass`)."""
    dx, Ninv = solve_scaled(N, -nv)
    return dx, Ninv, step_sigmas(dx, Ninv)
