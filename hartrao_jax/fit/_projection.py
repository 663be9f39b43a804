"""Observations projected onto a fitted surface: hit points, residuals, outliers.

Each observation ``l = (r, phi, theta)`` moves onto the fitted surface ``model(l, x, c) = 0``
along its weighted least-squares direction (one Gauss-Helmert projection): where its beam met
the reflector (:func:`hit_points`, which gives each point its surface cell), the correction
``v`` itself (:func:`hit_points_and_residuals`, where an adjustment starting at ``x``
linearises), both with the panels they hit (:func:`hit_cells`), and the points that correction
shows to be outliers (:func:`reject_beyond`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._config import by_row_blocks, on_device, row_blocks
from .._programs import cached_jit
from ..geometry._geometry import ring_cells
from ..model._model import ParaboloidModel
from ..solver._kernel import _materialize, materialize_trig


def hit_points(model: ParaboloidModel, l, x, c, sigma_l, kappa_rad) -> jax.Array:
    """Where each beam met the reflector: north-aligned telescope-frame points (m, (n, 3)).

    The raw point is off the surface by its noise, and on an oblique ray the range noise
    (0.8 mm) moves it *across* the surface too: cells assigned from raw points give the
    points near a panel edge to the neighbour panel together with the noise that carried them
    there, an edge pattern of one sign that the panels' random effect turns into a bias of f
    and the pose (f -0.18 mm, 2.2 of its sigmas on average at the paper's 3 mrad resolution).
    Here each observation first moves onto the fitted surface ``model(l, x, c) = 0`` along its
    weighted least-squares direction (one Gauss-Helmert projection,
    ``v = -Sigma b^T F / (b Sigma b^T)``), then into the telescope frame (``Rz(kappa)``).
    """
    # compiled in two stages (projection, then the point), each distinct sin/cos evaluated
    # once, the rotation written out: 0.34 -> 0.24 s per 1e6 points on one core
    return _by_blocks(model, l, x, c, sigma_l, kappa_rad, False)


def hit_points_and_residuals(model: ParaboloidModel, l, x, c, sigma_l, kappa_rad
                             ) -> tuple[jax.Array, jax.Array]:
    """:func:`hit_points` and the residuals ``v`` (n, 3; m, rad, rad) of that projection: the
    observations' corrections onto the surface at ``x`` (a Gauss-Helmert adjustment's
    linearisation point when it starts at ``x``)."""
    return _by_blocks(model, l, x, c, sigma_l, kappa_rad, True)


def hit_cells(model: ParaboloidModel, l, x, c, sigma_l, kappa_rad, ring_edges_m,
              panels_per_ring, *, with_v: bool, with_xy: bool, live: int | None = None
              ) -> tuple[np.ndarray, ...]:
    """The panels the beams hit (:func:`hit_points` into :func:`..geometry.ring_cells`, in one
    program): ``(cell (n,) int32, -1 outside every panel; design (n, 3) float32)``, the design
    ``(1, radial, tangential)`` of a point's panel offset and tilts (m; zeros outside), then,
    ``with_v``, the residuals ``v`` (n, 3) of the projection in float32 and, ``with_xy``, the
    hit points' ``x, y`` (n, 2; m) in float32 (the smooth modes' columns).

    As :func:`hit_points` then :func:`..geometry.panel_cells` and the float32 copies a
    position's random effect keeps of them, without the hit points, the cells' float64 columns
    and their copies in memory: 1.26e7 points 0.9 GB less written and read.

    ``live``: the rows from ``live`` on are a size bucket's padding: where the table is taken
    in blocks (:func:`.._config.by_row_blocks`) they are not computed and are outside every
    cell (cell -1, the rest zero); a table of one call computes them as any row."""
    args = (on_device(sigma_l, np.float64), on_device(kappa_rad, np.float64),
            on_device(True, bool), tuple(map(float, ring_edges_m)),
            tuple(map(int, panels_per_ring)),
            with_v, with_xy)
    out = by_row_blocks(lambda l_, c_: _hit_cells(model, l_, x, c_, *args), (l, c), live=live)
    if live is not None and isinstance(out[0], np.ndarray):  # (taken in blocks: zeros there)
        out[0][live:] = -1
    return out


def _by_blocks(model, l, x, c, sigma_l, kappa_rad, with_v: bool):
    """:func:`_hit_points` by :func:`by_row_blocks`."""
    args = (on_device(sigma_l, np.float64), on_device(kappa_rad, np.float64),
            on_device(True, bool), with_v)
    out = by_row_blocks(lambda l_, c_: _hit_points(model, l_, x, c_, *args), (l, c))
    return out if with_v else out[0]


def _project(model, l, x, c, sigma_l, kappa_rad, on):
    """``(X, v)``: the hit points (north-aligned telescope frame, m) and the residuals of the
    projection of :func:`hit_points`."""
    s2 = jnp.broadcast_to(sigma_l**2, (3,))
    cond = materialize_trig(model, on)
    point = materialize_trig(model.telescope_point, on)
    F, b = jax.vmap(jax.value_and_grad(lambda q, ci: cond(q, x, ci)))(l, c)
    m = jnp.sum(b * b * s2, axis=-1)
    v = _materialize(on, -s2 * b * (F / jnp.where(m > 0, m, 1.0))[:, None])
    P = jax.vmap(lambda q, ci: point(q, x, ci))(l + v, c)
    # Rz(kappa) P, written out (an (n, 3) x (3, 3) product is slower on CPU than its terms)
    ck, sk = jnp.cos(kappa_rad), jnp.sin(kappa_rad)
    X = jnp.stack([ck * P[:, 0] - sk * P[:, 1], sk * P[:, 0] + ck * P[:, 1], P[:, 2]], axis=1)
    return X, v


@cached_jit
def _hit_points(model, l, x, c, sigma_l, kappa_rad, on, with_v: bool):
    X, v = _project(model, l, x, c, sigma_l, kappa_rad, on)
    return (X, v) if with_v else (X,)


@cached_jit
def _hit_cells(model, l, x, c, sigma_l, kappa_rad, on, ring_edges_m: tuple,
               panels_per_ring: tuple, with_v: bool, with_xy: bool):
    X, v = _project(model, l, x, c, sigma_l, kappa_rad, on)
    ids, local = ring_cells(X, ring_edges_m, panels_per_ring, xp=jnp)
    f = jnp.float32
    design = jnp.concatenate([(ids >= 0)[:, None].astype(f), local.astype(f)], axis=1)
    return ((ids.astype(jnp.int32), design) + ((v.astype(f),) if with_v else ())
            + ((X[:, :2].astype(f),) if with_xy else ()))


def reject_beyond(v: np.ndarray, sigma_l, used: np.ndarray, k: float, n_unknowns: int,
                  max_rounds: int = 6) -> np.ndarray:
    """``used`` without the points whose standardized residual ``sqrt(v^T Sigma^-1 v) /
    sigma0`` exceeds ``k`` (residuals ``v`` (n, 3) of a solution, ``sigma_l`` (3,) the a
    priori sigmas): the rule of :func:`..solver.robust_gauss_helmert`, judged at a given
    solution, with ``sigma0`` from the points still used, in rounds until none is rejected."""
    v = np.asarray(v)
    inv_s2 = 1.0 / np.asarray(sigma_l, float) ** 2
    omega = np.empty(len(v))
    for rows in row_blocks(len(v)):  # (a block's temporaries, not whole columns' fresh pages)
        b = v[rows].astype(np.float64)
        b *= b
        np.dot(b, inv_s2, out=omega[rows])
    keep = np.asarray(used, bool).copy()
    for _ in range(max_rounds):
        s0_sq = float(np.sum(omega, where=keep)) / max(int(np.count_nonzero(keep)) - n_unknowns, 1)
        bad = keep & (omega > k * k * s0_sq)
        if not bad.any():
            break
        keep &= ~bad
    return keep
