"""The local-deformation search sees what the robust fit rejected when the surface confirms it:
the core of a bump deeper than the rejection limit comes back (it agrees with its neighbours),
isolated outliers stay out (they depart from a neighbourhood near zero), and the search on the
re-admitted points finds the bump with its core."""

from __future__ import annotations

import numpy as np
import pytest

from hartrao_jax.diagnose._locate import coherent, local_level, search
from hartrao_jax.physics._catalog import local_deformation

LIMIT = 3.0e-3  # rejection limit (m): 4 a-posteriori sigmas of 0.75 mm


def _surface(seed=0, n=12000, half=10.0, bump=None, outliers=40):
    """Points of a 20 m x 20 m patch (uniform), white residuals of 0.75 mm, an optional
    ``bump = (x, y, a, w)`` (m) and ``outliers`` isolated gross outliers of 5-50 mm (either
    sign). Returns positions, residuals, what a fit with rejection at ``LIMIT`` keeps, the
    outliers' indices and the bump's shape at the points."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-half, half, (n, 2))
    r = rng.normal(0.0, 0.75e-3, n)
    g = np.zeros(n)
    if bump is not None:
        x0, y0, a, w = bump
        g = np.asarray(local_deformation(xy[:, 0], xy[:, 1], x0, y0, 1.0, w))
        r += a * g
    far = np.flatnonzero(g < 1e-3)
    out = rng.choice(far, outliers, replace=False)
    r[out] += rng.choice([-1.0, 1.0], outliers) * rng.uniform(5e-3, 50e-3, outliers)
    return xy, r, np.abs(r) <= LIMIT, out, g


def test_local_level_is_the_median_of_the_neighbours_without_the_point():
    xy = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.1], [-0.1, 0.0], [0.0, -0.1], [5.0, 5.0]])
    r = np.array([9.0, 1.0, 2.0, 3.0, 4.0, 100.0])
    level, n = local_level(xy, r, np.array([0]), radius=0.3, k_min=3, radius_max=1.0)
    assert n[0] == 4 and level[0] == pytest.approx(2.5)  # itself and the far point excluded
    # sparse data: the k nearest within radius_max when the radius holds too few
    level, n = local_level(xy, r, np.array([0]), radius=0.05, k_min=3, radius_max=1.0)
    assert n[0] == 3
    level, n = local_level(xy, r, np.array([5]), radius=0.3, k_min=3, radius_max=1.0)
    assert n[0] == 0 and np.isnan(level[0])


def test_core_of_a_deep_bump_comes_back_and_isolated_outliers_stay_out():
    xy, r, kept, out, g = _surface(bump=(2.0, -1.0, 5e-3, 1.0))
    core = ~kept & (g > 0.8)
    assert core.sum() > 25  # the fit rejects the bump's core
    back = coherent(xy, r, kept, np.full(len(r), LIMIT))
    assert not back[kept].any()  # only rejected points are re-admitted
    assert back[core].mean() > 0.95
    assert not back[out].any()  # no isolated outlier comes back


def test_search_finds_the_bump_with_its_core_and_no_outlier_becomes_a_finding():
    bump = (2.0, -1.0, 5e-3, 1.0)
    xy, r, kept, _, _ = _surface(bump=bump)
    back = coherent(xy, r, kept, np.full(len(r), LIMIT))
    rim = search(xy[kept], r[kept]).candidate
    full = search(xy[kept | back], r[kept | back]).candidate
    assert full.significant
    assert np.hypot(full.x_m - bump[0], full.y_m - bump[1]) < 0.3
    assert abs(full.width_m - bump[3]) <= 0.5
    # with its core the bump answers more strongly than its rim alone
    assert abs(full.t) > abs(rim.t)
    # clean surface with outliers: no outlier comes back (at most a noise point just beyond
    # the limit whose neighbours lean its way), nothing stands out
    xy, r, kept, out, _ = _surface(seed=1)
    back = coherent(xy, r, kept, np.full(len(r), LIMIT))
    assert not back[out].any() and back.sum() <= 3
    assert np.all(np.abs(r[back]) < 1.5 * LIMIT)
    c = search(xy[kept | back], r[kept | back]).candidate
    assert not c.significant
