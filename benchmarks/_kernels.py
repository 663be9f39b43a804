"""Candidate linearisation kernels and Gauss-Helmert loops for ``hartrao_jax._ghm`` (benchmarks only).

Everything here is written so that it can be copied into ``_ghm.py`` as is:

* :func:`materialize_trig` -- wraps any per-point condition so that ``sin``/``cos``/``tan`` of
  each distinct argument are computed ONCE per point and stored, instead of being recomputed by
  XLA in every fusion that uses them (the dominant cost of the linearisation on the CPU).
* :func:`linearize_rev` / :func:`linearize_fwd` -- ``(F, a, b)`` of a chunk of points by
  reverse mode (``value_and_grad`` under ``vmap``, what ``_ghm`` does now) or forward mode
  (``jacfwd`` over the concatenated ``(x, l)`` tangents).
* :func:`gh_one_pass` -- the Gauss-Helmert iteration with ONE linearisation per point and
  iteration: the residual update of iteration k is fused into the normal-equation pass of
  iteration k+1, from per-point quantities stored by pass k (``a``, ``b``, ``w``, ``m``; storage
  dtype selectable, float32 by default).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jcore

# --------------------------------------------------------------------------------------------
# sin/cos computed once: custom-JVP sincos materialised behind a runtime lax.cond
# --------------------------------------------------------------------------------------------


def _sincos_impl(x, on):
    # A conditional is a fusion boundary: XLA cannot duplicate sin/cos into each consumer fusion.
    # ``on`` must be a runtime, unbatched boolean (True), else XLA folds the cond away (constant)
    # or vmap turns it into a select (batched) and the trig is duplicated again.
    return lax.cond(on, lambda v: (jnp.sin(v), jnp.cos(v)),
                    lambda v: (jnp.zeros_like(v), jnp.ones_like(v)), x)


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
                return ("lit", float(v.val))
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
            pk = _hashable(eqn.params)
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
    """Reverse mode under vmap (what ``_ghm._linearize`` does); ``on``: materialise trig."""
    if on is not None:
        condition = materialize_trig(condition, on)

    def one(ll, cc):
        F, (a, b) = jax.value_and_grad(lambda xx, l2: condition(l2, xx, cc), argnums=(0, 1))(x, ll)
        return F, a, b

    return jax.vmap(one)(l, c)


def linearize_fwd(condition, l, x, c, on=None):
    """Forward mode: ``jacfwd`` over the concatenated ``(x, l)``; value as ``has_aux``."""
    if on is not None:
        condition = materialize_trig(condition, on)
    u = x.shape[0]

    def one(ll, cc):
        z = jnp.concatenate([x, ll])

        def g(z):
            F = condition(z[u:], z[:u], cc)
            return F, F

        J, F = jax.jacfwd(g, has_aux=True)(z)
        return F, J[:u], J[u:]

    return jax.vmap(one)(l, c)


def make_hand_linearize(hand):
    """A chunk linearisation from a hand-derived ``hand(xp, r, phi, theta, x)`` (see _common)."""
    def lin(condition, l, x, c, on=None):
        cache = {}

        class _XP:
            def __getattr__(self, k):
                if k in ("sin", "cos") and on is not None:
                    def f(v):
                        if jnp.ndim(v) == 0:
                            return getattr(jnp, k)(v)
                        if id(v) not in cache:
                            cache[id(v)] = (v, sincos(v, on))
                        return cache[id(v)][1][0 if k == "sin" else 1]
                    return f
                return getattr(jnp, k)

        F, a, b = hand(_XP(), l[:, 0], l[:, 1], l[:, 2], x)
        a = jnp.stack([jnp.broadcast_to(ai, F.shape) for ai in a], axis=1)
        return F, a, jnp.stack(b, axis=1)

    return lin


# --------------------------------------------------------------------------------------------
# Gauss-Helmert loops
# --------------------------------------------------------------------------------------------


def _chunk(a, chunk):
    n = a.shape[0]
    nc = -(-n // chunk)
    pad = nc * chunk - n
    if pad:
        a = jnp.concatenate([a, jnp.broadcast_to(a[-1:], (pad,) + a.shape[1:])])
    return a.reshape((nc, chunk) + a.shape[1:])


def _solve(N, rhs):
    d = 1.0 / jnp.sqrt(jnp.where(jnp.diagonal(N) > 0, jnp.diagonal(N), 1.0))
    Ns = N * d[:, None] * d[None, :]
    L = jnp.linalg.cholesky(Ns)
    y = jax.scipy.linalg.cho_solve((L, True), rhs * d)
    Li = jax.scipy.linalg.solve_triangular(L, jnp.eye(N.shape[0], dtype=N.dtype), lower=True)
    Ninv = (Li.T @ Li) * d[:, None] * d[None, :]
    return y * d, Ninv


@partial(jax.jit, static_argnames=("lin", "chunk", "max_iter", "compute_dtype", "store_dtype",
                                   "trig"))
def gh_one_pass(condition, l, x0, sigma_l, consts, weights, on, tol=1e-6, *, lin, chunk=1 << 16,
                max_iter=30, compute_dtype=jnp.float64, store_dtype=jnp.float32, trig=True):
    """Rigorous GH with one linearisation per point and iteration.

    Pass k (one ``lax.scan`` over the chunks), per chunk:

    1. residuals of iteration k-1 from the stored ``a, b, w, m`` and ``dx_{k-1}``:
       ``k = -(a.dx + w) / m``, ``v = Sigma b k`` (``dx_{-1} = 0`` and ``b = 0`` at start: v = 0);
    2. linearise at ``(l + v, x_k)``: ``F, a, b``; ``w = F - b.v``; ``m = b Sigma b``;
    3. accumulate ``N``, ``n`` and store ``a, b, w, m`` (``store_dtype``) for the next pass.

    ``dx_k = -N^-1 n``. After convergence one last cheap sweep gives ``v`` at the solution.
    ``w`` and ``m`` are stored in float64 (they set the residuals at the fixed point); ``a`` and
    ``b`` may be float32: they only scale the correction ``a.dx`` (-> 0 at convergence) and ``v``
    to 1e-7 relative, which changes the solution by < 1e-10 relative.

    Returns ``(x, N^-1, v, omega, iterations, converged)``.
    """
    n_pts, u = l.shape[0], x0.shape[0]
    cd = compute_dtype
    s2 = jnp.asarray(sigma_l, l.dtype) ** 2  # (3,): per-column sigmas are not broadcast to (n, 3)
    L, C = _chunk(l, chunk), _chunk(consts, chunk)
    W = _chunk(weights, chunk)
    W = W.reshape(-1).at[n_pts:].set(0.0).reshape(W.shape)  # padding: weight 0
    nc = L.shape[0]
    store0 = (jnp.zeros((nc, chunk, u), store_dtype), jnp.zeros((nc, chunk, 3), store_dtype),
              jnp.zeros((nc, chunk), l.dtype), jnp.ones((nc, chunk), l.dtype))

    def residuals(st, dx, w8):
        a, b, wm, m = st
        k = -((a.astype(l.dtype) @ dx) + wm) / m
        v = s2 * b.astype(l.dtype) * k[:, None]
        return k, v

    def one_pass(x, dx_prev, store):
        def body(carry, ch):
            N, nv, omega = carry
            lc, cc, w8, st = ch
            k, v = residuals(st, dx_prev, w8)
            omega = omega + jnp.sum(jnp.where(w8 > 0, w8 * k * k * st[3], 0.0))
            F, a, b = lin(condition, (lc + v).astype(cd), x.astype(cd), cc.astype(cd),
                          on if trig else None)
            F, a, b = F.astype(l.dtype), a.astype(l.dtype), b.astype(l.dtype)
            wm = F - jnp.sum(b * v, axis=-1)
            m = jnp.sum(b * b * s2, axis=-1)
            ok = (w8 > 0) & (m > 0)
            q = jnp.where(ok, w8 / jnp.where(ok, m, 1.0), 0.0)
            a0 = jnp.where(ok[:, None], a, 0.0)
            aq = a0 * q[:, None]
            N = N + aq.T @ a0
            nv = nv + aq.T @ jnp.where(ok, wm, 0.0)
            new = (a.astype(store_dtype), b.astype(store_dtype), wm, jnp.where(m > 0, m, 1.0))
            return (N, nv, omega), new

        init = (jnp.zeros((u, u), l.dtype), jnp.zeros((u,), l.dtype), jnp.zeros((), l.dtype))
        (N, nv, omega), new = lax.scan(body, init, (L, C, W, store))
        return N, nv, omega, new

    def step(state):
        x, dx_prev, store, it, _, _, _ = state
        N, nv, _, store = one_pass(x, dx_prev, store)
        dx, Ninv = _solve(N, -nv)
        ratio = jnp.max(jnp.abs(dx) / jnp.sqrt(jnp.where(jnp.diagonal(Ninv) > 0, jnp.diagonal(Ninv), 1.0)))
        return x + dx, dx, store, it + 1, Ninv, ratio < tol, ratio

    def cond(state):
        return (state[3] < max_iter) & ~state[5]

    state = (x0, jnp.zeros_like(x0), store0, jnp.array(0), jnp.zeros((u, u), l.dtype),
             jnp.array(False), jnp.array(jnp.inf, l.dtype))
    x, dx, store, it, Ninv, done, _ = lax.while_loop(cond, step, state)

    # final residuals at the solution (no relinearisation: k from the last pass and dx)
    def fin(omega, ch):
        w8, st = ch
        k, v = residuals(st, dx, w8)
        return omega + jnp.sum(jnp.where(w8 > 0, w8 * k * k * st[3], 0.0)), v

    omega, V = lax.scan(fin, jnp.zeros((), l.dtype), (W, store))
    return x, Ninv, V.reshape(-1, 3)[:n_pts], omega, it, done
