"""A step's robust rejections leave the random-effect adjustment's normal-equation sums at the
same linearisation (``solver._mixed_pass._dropped_sums``): no pass over the points of their own."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import F_TRUE, POSE, SIGMA
from test_mixed import COUNTS, EDGES, two_face_scan

from hartrao_jax.geometry._geometry import panel_cells
from hartrao_jax.model._model import make_model
from hartrao_jax.solver._mixed import gauss_helmert_mixed
from hartrao_jax.solver._mixed_pass import _dropped_sums, _pass

NAMES = ["tx", "ty", "tz", "rx", "ry", "f"]


def _scan(seed, n=8000):
    lobs, X = two_face_scan(seed, n=n)
    bad = np.arange(0, len(lobs), 499)
    lobs[bad, 0] += np.linspace(0.01, 0.05, len(bad))  # range outliers, 1-5 cm
    cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    design = np.column_stack([np.ones(len(X)), local]) * (cell >= 0)[:, None]
    model = make_model(NAMES)
    x0 = np.array([{**POSE, "f": F_TRUE}.get(k, 0.0) for k in model.free])
    return model, lobs, x0, cell, design, n_cells, bad


def test_dropped_sums_are_the_points_share_of_a_pass():
    """The sums of a pass minus those of some of its points equal the pass without them: the
    points' share from the pass's stored terms (float32, ``STORE_DTYPE``: to a few 1e-7 of
    that share) is the difference of the two passes' sums (made in float64)."""
    model, lobs, x0, cell, design, n_cells, _ = _scan(1, n=3000)
    order = np.argsort(np.where(cell >= 0, cell, n_cells), kind="stable")
    L, G, D = (jnp.asarray(a[order]) for a in (lobs, cell.astype(np.int32), design))
    n = len(order)
    C, V, MZ = jnp.zeros((n, 2)), jnp.zeros((n, 3)), jnp.zeros((n, 0))
    W = jnp.asarray(np.where(np.arange(n) % 5 == 0, 0.5, 1.0))  # unequal weights
    U = jnp.asarray(np.random.default_rng(2).normal(0, 1e-4, (n_cells, 3)))
    S2 = jnp.asarray(SIGMA) ** 2
    on = jnp.ones((), bool)
    x = jnp.asarray(x0 + 1e-4)

    pass_ = eqx.filter_jit(_pass)  # one program for both calls

    def sums(w):
        return pass_(model, 1, on, n_cells, 1024, L, V, C, w, S2, G, D, x, U, MZ)

    full, (a, b, d, wm, m, _) = sums(W)
    idx = np.array([0, 7, 8, 1999, n - 1, -1, -1])  # the first, a cell-less tail, padding
    out = sums(W.at[idx[idx >= 0]].set(0.0))[0]
    drop = _dropped_sums(a, d, wm, m, W, G, jnp.asarray(idx), n_cells)
    for s, t, o in zip(full, drop, out):
        s, t, o = np.asarray(s), np.asarray(t), np.asarray(o)
        np.testing.assert_allclose(t, s - o, rtol=1e-6, atol=1e-12 * np.max(np.abs(s)))
    assert np.any(np.asarray(drop[0]) != 0)


@pytest.mark.parametrize("threads", [1, 2])
def test_robust_adjustment_is_the_adjustment_of_the_points_it_kept(threads):
    """The robust adjustment (rejection inside the iteration, the rejected points' share out of
    the sums at once) equals the adjustment of the points it kept, their weights held: the
    same estimates (1e-3 sigma), sigmas, variance components; and 3 passes, where the robust
    adjustment took 5 before the rejections left the sums at once."""
    model, lobs, x0, cell, design, n_cells, bad = _scan(4)
    c = np.zeros((len(lobs), 2))

    def run(w, k, **kw):
        return gauss_helmert_mixed(model, lobs, x0, SIGMA, c, w, cell, design, n_cells,
                                   cell_var0=np.full(3, 1e-8), robust_k=k, threads=threads,
                                   **kw)

    robust = run(np.ones(len(lobs)), 4.0)
    kept = np.asarray(robust.weights)
    held = run(kept, None)
    assert not np.any(kept[bad] > 0) and np.sum(kept == 0) < 2 * len(bad)
    assert bool(robust.converged) and bool(held.converged)
    sd = np.sqrt(np.diag(np.asarray(held.cov)))
    assert np.max(np.abs(np.asarray(robust.x) - np.asarray(held.x)) / sd) < 1e-3
    np.testing.assert_allclose(np.sqrt(np.diag(np.asarray(robust.cov))), sd, rtol=1e-3)
    # the variance components are fixed points found to their settling tolerance (0.5 % per
    # step): a poorly determined tilt variance settles up to 3 % apart by the two paths (so
    # before this change too); well inside their own standard error, s^2 sqrt(2 / r)
    cv, cv_held = np.asarray(robust.cell_var), np.asarray(held.cell_var)
    se = cv_held * np.sqrt(2.0 / np.asarray(held.redundancy_cells))
    assert np.all(np.abs(cv - cv_held) < 0.25 * se)
    assert float(robust.sigma0) == pytest.approx(float(held.sigma0), rel=1e-4)
    # the points rejected at the second step restart it: at most one pass more than the
    # adjustment of the kept points (3 and 2 passes here); where both iterate to 1e-3 sigma,
    # no more passes (3 and 3)
    assert int(robust.iterations) <= min(3, int(held.iterations) + 1)
    tight = run(np.ones(len(lobs)), 4.0, tol=1e-3)
    assert int(tight.iterations) <= int(run(np.asarray(tight.weights), None, tol=1e-3).iterations)
