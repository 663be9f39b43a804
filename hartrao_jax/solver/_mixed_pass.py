"""One pass of the random-effect adjustment (:mod:`._mixed`) over its points, and the per-point
algebra around it.

:func:`_pass` linearises every point at ``(l + v, x, c + dev)`` (``dev = D . u`` of its cell),
adds its share to the normal-equation sums (``N``, ``nv``, and per cell ``S``, ``s``, ``t``,
segment sums over the points in the caller's order) and keeps per point what the step's
residual update needs (in :data:`STORE_DTYPE`). From those kept terms, without a pass:
the corrections and residuals after a step (:func:`_residual_k`), the robust rule's rejections
(:func:`_rejected`), a rejected point's share of the sums (:func:`_dropped_sums`) and the
statistics at the solution (:func:`_final_terms`).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ._kernel import _materialize, materialize_trig, point_weights

#: dtype of the per-point terms a pass keeps (``a = dF/dx``, ``b = dF/dl``, ``d = e D``, the
#: misclosure ``wm`` and its variance ``m``): as the white kernel's store
#: (:func:`._kernel.gh_one_pass`), they only enter the correction ``k = -(a.dx + d.du + wm) /
#: m`` (``a.dx + d.du`` -> 0 at convergence), ``v = Sigma b k`` (to 1e-7 relative, ~1e-10 m),
#: the points' ``omega = k^2 m`` (sigma0 to 1e-7 relative) and the rejected points' share of the
#: sums (:func:`_dropped_sums`, 1e-7 of a few points' share); the sums themselves are made in
#: float64. 68 of their 136 bytes per point (9 unknowns; 1.26e7 points: 0.86 GB less at the
#: footprint's peak).
STORE_DTYPE = jnp.float32


def _linearize(condition, dev_column, on, l0, x, c):
    """``F``, ``a = dF/dx``, ``b = dF/dl`` and ``e = dF/dc[dev_column]`` of one point; sin/cos
    of each distinct argument computed once (:func:`._kernel.materialize_trig`)."""
    cond = materialize_trig(condition, on)
    F, (a, b, gc) = jax.value_and_grad(lambda xx, ll, cc: cond(ll, xx, cc),
                                       argnums=(0, 1, 2))(x, l0, c)
    return F, a, b, gc[dev_column]


def _chunks(arrays, chunk):
    """(n, ...) -> (n_chunks, chunk, ...), the tail padded by repeating the last row."""
    n = arrays[0].shape[0]
    nc = max(1, -(-n // chunk))
    pad = nc * chunk - n
    out = [jnp.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1), mode="edge").reshape(
        (nc, chunk) + a.shape[1:]) for a in arrays]
    return out, pad


def _pass(condition, dev_column, on, n_cells, chunk, L, V, C, W, S2, G, DM, x, U, MZ=None,
          robust=None, into=None, rows=None):
    """Linearise every point at ``(l + v, x, c + dev)``; accumulate the normal equations and the
    per-cell sums; keep per point what the residual update needs.

    ``MZ`` (n, r): the design of the last ``r`` unknowns, which enter the deviation linearly
    (``dev += MZ_i . x[u - r:]``, see ``mode_design`` of :func:`._mixed.gauss_helmert_mixed`); the
    condition then takes the first ``u - r``. Their columns of ``a`` are ``dF/ddev MZ_i``.

    ``robust = (noise_var, robust_k)``: ``V`` is not given but computed in the same loop, the
    first-order residuals at ``(l, x, c + dev)`` (see :func:`._mixed_stream.mixed_chunk`),
    points beyond ``robust_k`` get weight 0, and the sums gain ``n_used`` and ``omega``; per
    point ``(v, e, weight)`` are kept instead (one pass over the points' memory, not three).

    ``into``: arrays of the shapes of the kept ``(a, b, d, wm, m)`` (a last pass's, of the
    same points, whole chunks of them, donated by the caller), written over chunk by chunk and
    returned in their stead (``dev`` is then not kept): XLA gives a scan's stacked outputs new
    memory even where a donated input would do, and 1.7 GB of new pages per pass over 1.26e7
    points cost a quarter of the pass in page faults.

    ``rows`` (n,): the points are rows ``rows`` of the tables ``L``, ``C``, ``DM``, ``MZ`` (the
    caller's, in its order), each chunk's taken in the loop; ``V``, ``W``, ``S2``, ``G`` are
    the points' own. The tables are then not copied into the points' order (as a part of a
    split pass: 52 B per point less, :func:`._mixed._solve_split`)."""
    u, k = x.shape[0], U.shape[1]
    if MZ is None:
        MZ = jnp.zeros((L.shape[0], 0), x.dtype)
    u0 = u - MZ.shape[1]
    n = L.shape[0] if rows is None else rows.shape[0]
    lin = jax.vmap(partial(_linearize, condition, dev_column, on), in_axes=(0, None, 0))
    # the tail is padded with copies of the last point: weight 0 there (never in any sum);
    # S2 is per point (n, 3) or one vector (3,) for all
    per_s2 = S2.ndim == 2
    if V is None:  # computed in the loop (``robust``); a stand-in of no size to chunk
        V = jnp.zeros((n, 0), L.dtype)
    if rows is None:
        (Lc, Vc, Cc, Wc, Gc, Dc, Zc, *S2c), pad = _chunks(
            [L, V, C, W, G, DM, MZ] + ([S2] if per_s2 else []), chunk)
    else:  # the rows' numbers in chunks, the tables' rows taken by them in the loop
        (Lc, Vc, Wc, Gc, *S2c), pad = _chunks([rows, V, W, G] + ([S2] if per_s2 else []), chunk)
        Cc = Dc = Zc = jnp.zeros((Lc.shape[0], 0), bool)  # stand-ins of no size
    S2c = S2c[0] if per_s2 else jnp.zeros((Lc.shape[0], 0), S2.dtype)
    Wc = Wc.reshape(-1).at[Wc.size - pad:].set(0.0).reshape(Wc.shape) if pad else Wc
    if robust is not None:  # F and dF/dl at the observations
        first = jax.vmap(jax.value_and_grad(materialize_trig(condition, on)),
                         in_axes=(0, None, 0))

    def body(carry, ch):
        N, nv, S, sg, tg, wmw, *used = carry
        l, v, c, w8, s2, g, dm, mz = ch
        if rows is not None:  # ``l`` holds the chunk's rows of the tables
            l, c, dm, mz = (t[l] for t in (L, C, DM, MZ))
        s2 = s2 if per_s2 else S2
        live = g >= 0
        gi = jnp.where(live, g, 0)
        dev = jnp.where(live, jnp.sum(dm * U[gi], axis=-1), 0.0)
        c = c.at[:, dev_column].add(dev + mz @ x[u0:])
        if robust is not None:  # residuals at (l, x, c + dev) and the robust rejection there
            F0, b0 = first(l, x[:u0], c)
            m0 = jnp.sum(b0 * b0 * s2, axis=-1)
            ok0 = m0 > 0
            k0 = jnp.where(ok0, -F0 / jnp.where(ok0, m0, 1.0), 0.0)
            v = s2 * b0 * k0[:, None]
            e0 = jnp.abs(k0) * jnp.sqrt(m0) / jnp.sqrt(robust[0])
            w8 = jnp.where((w8 > 0) & (e0 > robust[1]), 0.0, w8)
            in0 = (w8 > 0) & ok0
            used = [used[0] + jnp.sum(in0), used[1] + jnp.sum(jnp.where(in0, k0 * k0 * m0, 0.0))]
        # materialise the linearisation once (a runtime cond, a fusion boundary): F, a, b, e
        # have several consumers each, and XLA would otherwise re-run the derivative in every
        # consumer fusion (3.5x the time of the pass; the same numbers either way)
        F, a, b, e = _materialize(on, lin(l + v, x[:u0], c))
        a = jnp.concatenate([a, e[:, None] * mz], axis=1)
        wm, m, ok, q = point_weights(F, b, v, w8, s2)
        a = jnp.where(ok[:, None], a, 0.0)
        wm0 = jnp.where(ok, wm, 0.0)
        d = jnp.where((ok & live)[:, None], e[:, None] * dm, 0.0)
        add = _point_sums(a, d, q, wm0, jnp.where(live, g, n_cells), n_cells)
        keep = (v, e0, w8) if robust is not None else (
            *(t.astype(STORE_DTYPE) for t in (a, b, d, wm, m)), dev)
        return (*(s + t for s, t in zip((N, nv, S, sg, tg, wmw), add)), *used), keep

    f = x.dtype
    init = (jnp.zeros((u, u), f), jnp.zeros((u,), f), jnp.zeros((n_cells, k, k), f),
            jnp.zeros((n_cells, k, u), f), jnp.zeros((n_cells, k), f), jnp.zeros((), f)) + (
        (jnp.zeros((), f), jnp.zeros((), f)) if robust is not None else ())
    chunks = (Lc, Vc, Cc, Wc, S2c, Gc, Dc, Zc)
    if into is None:
        sums, per_point = lax.scan(body, init, chunks)
    else:
        def body_into(carry, ich):
            sums, bufs = carry
            sums, keep = body(sums, ich[1])
            return (sums, tuple(b_.at[ich[0]].set(k_) for b_, k_ in zip(bufs, keep))), None

        nc = Lc.shape[0]
        bufs = tuple(b_.reshape((nc, chunk) + b_.shape[1:]) for b_ in into)
        (sums, per_point), _ = lax.scan(body_into, (init, bufs), (jnp.arange(nc), chunks))
    per_point = tuple(p.reshape((-1,) + p.shape[2:])[:n] for p in per_point)
    return sums, per_point


def _row_dot(A, B):
    """``sum_j A[..., j] B[..., j]`` written out term by term: one loop fusion with its
    operands' conversions and gathers. ``jnp.sum(A * B, -1)`` is a reduction XLA's CPU
    backend gives its own kernel, with the product (and a gather such as ``dU[g]``) made in
    memory first: 144 MiB per 6.3e6 points for ``d . dU[g]``; ``A @ B`` a float64 copy of a
    float32 ``A`` (900 MB for ``a`` of 1.26e7 points)."""
    out = A[..., 0] * B[..., 0]
    for j in range(1, A.shape[-1]):
        out = out + A[..., j] * B[..., j]
    return out


def _residual_k(a, d, wm, m, dx, dU, groups):
    gi = jnp.where(groups >= 0, groups, 0)
    du_pt = jnp.where(groups >= 0, _row_dot(d, dU[gi]), 0.0)
    return -(_row_dot(a, dx) + du_pt + wm) / jnp.where(m > 0, m, 1.0)


def _final_terms(a, d, wm, m, W, G, DM, U, dx, dU):
    """Per point at the solution, from the last linearisation's terms and step: the
    correction ``k``, its share ``omega = k^2 m`` of ``v^T Sigma^-1 v`` (0 for a point not in
    use) and the surface deviation ``D . u`` of its cell (0 outside every cell)."""
    kk = _residual_k(a, d, wm, m, dx, dU, G)
    ok = (W > 0) & (m > 0)
    omega = jnp.where(ok, kk * kk * jnp.where(m > 0, m, 1.0), 0.0)
    dev = jnp.where(G >= 0, _row_dot(DM, U[jnp.where(G >= 0, G, 0)]), 0.0)
    return kk, omega, dev


def _rejected(kk, m, W, se2, judge, robust_k):
    """The points a step rejects: used ones whose residual ``|k| sqrt(m)`` exceeds ``robust_k``
    noise sigmas (``sqrt(se2)``), where ``judge``."""
    ok = (W > 0) & (m > 0)
    e = jnp.sqrt(jnp.where(ok, kk * kk * m, 0.0) / se2)
    return (e > robust_k) & ok & judge


#: Most points a step's rejections may count for their share of the sums to be taken out at
#: the same linearisation (:func:`_dropped_sums`); more wait for the next pass.
DROP_ROWS = 8192


def _dropped_sums(a, d, wm, m, W, G, idx, n_cells):
    """What the points ``idx`` (-1: none) added to a pass's sums ``(N, nv, S, sg, tg, wMw)``,
    from its stored per-point terms, ``W`` their weights at that pass (as :func:`_pass`: ``a``
    and ``d`` are zero where a point did not enter, ``q = W / m``).

    A rejection after a step changes only the weights: the step at the same linearisation
    without the rejected points comes from the sums minus these, with no pass over the points
    (the normal-equation sums are sums over points)."""
    live = idx >= 0
    i = jnp.where(live, idx, 0)
    a, d, wm, m, w, g = a[i], d[i], wm[i], m[i], W[i], G[i]
    ok = live & (w > 0) & (m > 0)
    q = jnp.where(ok, w / jnp.where(ok, m, 1.0), 0.0)
    return _point_sums(a, d, q, jnp.where(ok, wm, 0.0), jnp.where(ok & (g >= 0), g, n_cells),
                       n_cells)


def _point_sums(a, d, q, wm0, seg, n_cells: int):
    """What points add to a pass's sums ``(N, nv, S, sg, tg, wMw)``: ``N = sum q a a^T``,
    ``nv = sum q a w``, per cell ``S = sum q d d^T``, ``sg = sum q d a^T``, ``tg = sum q d w``,
    and ``wMw = sum q w^2``; ``a``, ``d`` zero and ``q`` 0 where a point does not enter,
    ``seg`` each point's cell (``n_cells``: none). One segment sum of ``[d d^T, d a^T, d w]``
    per point, the points in any order (XLA's CPU scatter takes no less time for points sorted by
    cell: 0.19 s per 6.3e6 points and 9 unknowns either way, which is why the passes take the
    points in the caller's order, not sorted by cell)."""
    k, u = d.shape[1], a.shape[1]
    aq, dq = a * q[:, None], d * q[:, None]
    per = jnp.concatenate([(dq[:, :, None] * d[:, None, :]).reshape(-1, k * k),
                           (dq[:, :, None] * a[:, None, :]).reshape(-1, k * u),
                           dq * wm0[:, None]], axis=1)
    tot = jax.ops.segment_sum(per, seg, n_cells + 1)[:n_cells]
    return (aq.T @ a, aq.T @ wm0, tot[:, : k * k].reshape(n_cells, k, k),
            tot[:, k * k: k * k + k * u].reshape(n_cells, k, u), tot[:, k * k + k * u:],
            jnp.sum(q * wm0 * wm0))


def design_dtype(a):
    """The dtype a design (a cell design, the smooth modes' columns) is kept in: float32 where
    the caller gives it so (half the memory; 6e-8 of rounding), else float64."""
    return np.float32 if np.asarray(a).dtype == np.float32 else np.float64
