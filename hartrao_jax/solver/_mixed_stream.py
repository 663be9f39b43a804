"""The random-effect adjustment of :mod:`._mixed` streamed: sums per chunk of points, the step
from the sums (constant memory per chunk; ``fit-stream`` and the diagnosis' joint systems).

The same model and arithmetic as :func:`._mixed.gauss_helmert_mixed`: :func:`mixed_chunk`
linearises one chunk and returns its :class:`MixedSums`; the sums of every chunk added give the
step and the variance components by :func:`mixed_step`.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._config import on_device
from .._programs import cached_jit
from ._kernel import part_chunk, step_sigmas
from ._mixed import _Linearization, _ridge_args, _update, _vce
from ._mixed_pass import _pass


class MixedSums(eqx.Module):
    """Normal-equation sums of a set of points (add them over chunks), see :func:`mixed_chunk`.

    ``N`` (u, u), ``nv`` (u,), per cell ``S`` (g, k, k), ``sg`` (g, k, u), ``tg`` (g, k),
    ``wMw`` the weighted misclosure square sum, ``n_used`` the points in the sums,
    ``omega`` the points' ``v^T Sigma^-1 v`` at the linearisation point (for sigma0).
    """

    N: Float[Array, "u u"]
    nv: Float[Array, " u"]
    S: Float[Array, "g k k"]
    sg: Float[Array, "g k u"]
    tg: Float[Array, "g k"]
    wMw: Float[Array, ""]
    n_used: Float[Array, ""]
    omega: Float[Array, ""]

    def __add__(self, other: MixedSums) -> MixedSums:
        return jax.tree.map(jnp.add, self, other)


class MixedChunk(eqx.Module):
    """Per point of a chunk (the caller's order): residuals ``v`` (n, 3) at the solution the
    chunk was linearised at, standardized residuals ``e`` (``|k| sqrt(m) / s_e``) and the
    weights after the robust rejection."""

    v: Float[Array, "n 3"]
    e: Float[Array, " n"]
    weights: Float[Array, " n"]


def mixed_chunk(
    condition,
    l: Float[Array, "n 3"],
    consts: Float[Array, "n c"],
    weights: Float[Array, " n"],
    s2: Float[Array, "n 3"] | Float[Array, " 3"],
    groups: Int[Array, " n"],
    design: Float[Array, "n k"],
    x: Float[Array, " u"],
    U: Float[Array, "g k"],
    noise_var: Float[Array, ""],
    robust_k: Float[Array, ""],
    *,
    dev_column: int = 1,
    chunk: int = 8192,
    threads: int = 1,
    mode_design: Float[Array, "n r"] | None = None,
) -> tuple[MixedSums, MixedChunk]:
    """One chunk of points of a streamed :func:`gauss_helmert_mixed` (constant memory per chunk).

    1. Residuals at ``(x, U)``, first-order Gauss-Helmert at the observations:
       ``k = -F(l, x, c + dev) / m``, ``v = Sigma b k``; points with ``|k| sqrt(m) / s_e`` above
       ``robust_k`` get weight 0 (at every pass from the current solution: a point is out
       exactly when its residual is beyond the limit there).
    2. The linearisation at ``(l + v, x, c + dev)`` and its sums (as one pass of the in-memory
       solver). The sums of all chunks give the step by :func:`mixed_step`.

    ``mode_design`` (n, r): the last ``r`` unknowns of ``x`` enter the deviation through these
    per-point columns (as ``mode_design`` of :func:`gauss_helmert_mixed`); ``condition`` then
    takes the first ``u - r``. ``s2``: the observations' variances per point (n, 3), or one
    vector (3,) for all.

    Steps 1 and 2 run in one loop over blocks of ``chunk`` points (the residuals of a block
    are linearised while its rows are in cache: 0.61 -> 0.46 s per 1e6 points on one core);
    ``threads``: calls made at once (in threads), which, as in a Dask worker of one thread,
    keep their blocks small enough to take one core each (:func:`._kernel.part_chunk`).
    """
    MZ = (on_device(np.zeros((l.shape[0], 0), x.dtype)) if mode_design is None
          else jnp.asarray(mode_design, x.dtype))
    # ``on`` enters the compiled program as an argument: a constant True would let XLA fold
    # the materialising cond of the pass away and recompute the derivatives in every consumer
    # (10x the time with the 30 unknowns of the diagnosis' candidates: 2.1 s for 2.6e5 points)
    return _mixed_chunk(condition, l, consts, weights, s2, groups, design, x, U, noise_var,
                        robust_k, on_device(True, bool), MZ, dev_column=dev_column,
                        chunk=part_chunk(chunk, threads))


@cached_jit
def _mixed_chunk(condition, l, consts, weights, s2, groups, design, x, U, noise_var, robust_k,
                 on, MZ, *, dev_column, chunk):
    (N, nv, S, sg, tg, wmw, n_used, omega), (V, e, W) = _pass(
        condition, dev_column, on, U.shape[0], chunk, l, None, consts, weights, s2, groups,
        design, x, U, MZ, robust=(noise_var, robust_k))
    sums = MixedSums(N, nv, S, sg, tg, wmw, n_used.astype(l.dtype), omega)
    return sums, MixedChunk(V, e, W)


class MixedStep(eqx.Module):
    """The step of a streamed mixed adjustment: new ``x``, ``U``, variance components
    ``var = (s_e^2, cell variances (k,), ridge variances (r,))``, ``Qxx``, ``Quu``, the
    redundancy shares and the convergence measure ``max |dx_j| / sigma_j``."""

    x: Array
    U: Array
    var: tuple
    Qxx: Array
    Quu: Array
    redundancy_noise: Array
    redundancy_cells: Array
    redundancy_ridge: Array
    ratio: Array


@cached_jit
def mixed_step(
    sums: MixedSums, var: tuple, var0: tuple, x: Float[Array, " u"], U: Float[Array, "g k"],
    ridge_idx: Int[Array, " r"], ridge_group: Int[Array, " r"], n_ridge_groups: int,
    estimate_variances: bool = True,
) -> MixedStep:
    """Variance components at these sums (Foerstner's fixed point), then the step: the same
    arithmetic as one iteration of :func:`gauss_helmert_mixed`, from sums added over chunks."""
    upd = partial(_update, var0=var0, **_ridge_args(ridge_idx, ridge_group, n_ridge_groups))
    lin = _Linearization(sums.N, sums.nv, sums.S, sums.sg, sums.tg, sums.wMw,
                         None, None, None, None, None)
    if estimate_variances:
        var = _vce(upd, lin, var, var0, x, U, sums.n_used)
    up = upd(lin, var, x=x, U=U, n_used=sums.n_used)
    return MixedStep(x + up.dx, U + up.dU, var, up.Qxx, up.Quu, up.r_e, up.r_cells, up.r_ridge,
                     step_sigmas(up.dx, up.Qxx))
