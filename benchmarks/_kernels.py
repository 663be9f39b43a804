"""Solver kernels for the benchmarks: the package's one-pass kernel plus the variants it was
chosen against (forward mode, hand-derived derivatives).

The production pieces -- ``sincos``, :func:`materialize_trig`, :func:`linearize_rev`,
:func:`gh_one_pass` -- live in :mod:`hartrao_jax.solver._kernel` and are re-exported here.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from hartrao_jax.solver._kernel import (  # noqa: F401
    _materialize,
    _window,
    gh_one_pass,
    linearize_rev,
    make_pass,
    materialize_trig,
    sincos,
)


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


def fit(condition, l, x0, sigma_l, consts=None, weights=None, v0=None, *, lin=None,
        chunk_size=4096, tol=1e-6, max_iter=30, store_dtype=jnp.float32, trig=True):
    """Python wrapper: defaults, chunk size, the runtime ``on`` flag (must be an argument)."""
    l = jnp.asarray(l, jnp.float64)
    n = l.shape[0]
    consts = jnp.zeros((n, 0), l.dtype) if consts is None else jnp.asarray(consts, l.dtype)
    weights = jnp.ones((n,), l.dtype) if weights is None else jnp.asarray(weights, l.dtype)
    v0 = None if v0 is None else jnp.asarray(v0, l.dtype)
    chunk = int(min(chunk_size, n))
    return gh_one_pass(condition, l, jnp.asarray(x0, l.dtype), jnp.asarray(sigma_l, l.dtype),
                       consts, weights, v0, jnp.ones((), bool), tol, lin=lin or linearize_rev,
                       chunk=chunk, max_iter=max_iter, store_dtype=store_dtype, trig=trig)
