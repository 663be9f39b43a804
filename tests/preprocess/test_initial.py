"""The batched heading search of the initial values against the one-heading-at-a-time algorithm
it replaced (NumPy ``lstsq``, ``np.histogram``, ``np.median``), and its NumPy rotations against
the geometry's JAX ones."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import SIGMA, paraboloid_points

from hartrao_jax.geometry._geometry import (
    cartesian_to_raw,
    gravity_in_telescope,
    polar_to_cartesian,
    rot_x,
    rot_y,
    rot_z,
    scanner_to_telescope,
    telescope_axes_hadec,
)
from hartrao_jax.preprocess._initial import (
    _Basis,
    _histogram_mode,
    _robust_fits,
    _rowwise_median,
    _weighted_lsq,
    gimbal_rotation,
    initial_distance,
    initial_values,
    scanner_rotation,
)

F = 10.9816
LAT = np.radians(-25.8897)


# ------------------------------------------------------- the per-heading reference (the old code)


def _lsq_one(X, keep, f_fixed=None):
    q = X[:, 0] ** 2 + X[:, 1] ** 2
    if f_fixed is None:
        A = np.column_stack([X[:, 0], X[:, 1], X[:, 2], np.ones(len(X))])
        p, *_ = np.linalg.lstsq(A[keep], -q[keep], rcond=None)
        tx, ty, f, c = p[0] / 2, p[1] / 2, -p[2] / 4, p[3]
    else:
        f = f_fixed
        A = np.column_stack([X[:, 0], X[:, 1], np.ones(len(X))])
        p, *_ = np.linalg.lstsq(A[keep], (4 * f * X[:, 2] - q)[keep], rcond=None)
        tx, ty, c = p[0] / 2, p[1] / 2, p[2]
    tz = (tx * tx + ty * ty - c) / (4 * f)
    res = (X[:, 2] + tz) - ((X[:, 0] + tx) ** 2 + (X[:, 1] + ty) ** 2) / (4 * f)
    return np.array([tx, ty, tz]), f, res


def _robust_one(X, f0, tol, rounds=4):
    tz_i = (X[:, 0] ** 2 + X[:, 1] ** 2) / (4 * f0) - X[:, 2]
    lo, hi = np.percentile(tz_i, [0.5, 99.5])
    nb = int(np.clip((hi - lo) / tol, 10, 20000))
    h, e = np.histogram(tz_i, bins=nb, range=(lo, hi))
    mode = 0.5 * (e[np.argmax(h)] + e[np.argmax(h) + 1])
    keep = np.abs(tz_i - mode) < 5 * tol
    t, f, res = _lsq_one(X, keep, f_fixed=f0)
    for _ in range(rounds):
        a = np.abs(res)
        keep = a <= max(4 * 1.4826 * np.median(a[keep]), tol)
        t, f, res = _lsq_one(X, keep, f_fixed=f0)
    return _lsq_one(X, keep)


def _scan_points(heading=0.7, n=4000, seed=0, scatter=0.15):
    """Scanner points of a paraboloid hung on its gimbal at HA -35, DEC -64, with scatter."""
    g = np.asarray(gravity_in_telescope(telescope_axes_hadec(np.radians(-35.0),
                                                             np.radians(-64.0), LAT)))
    R = gimbal_rotation(g) @ np.asarray(rot_z(heading))
    X = paraboloid_points(n, F, seed)
    xs = (X - np.array([0.01, -0.02, 9.3])) @ R
    rng = np.random.default_rng(seed + 1)
    k = int(scatter * n)
    xs = np.concatenate([xs + rng.normal(size=xs.shape) * 4e-4,
                         rng.normal(size=(k, 3)) * 4 + [0, 0, 3]])
    return xs[rng.permutation(len(xs))], g


# ------------------------------------------------------------------------------ the pieces


def test_numpy_rotations_equal_the_geometry():
    for rx, ry in [(0.3, 2.9), (-1.1, -2.8), (0.0, 0.0), (0.7, np.pi)]:
        np.testing.assert_allclose(scanner_rotation(rx, ry),
                                   np.asarray(scanner_to_telescope(rx, ry)), atol=1e-15)
    g = np.array([0.3, -0.4, -0.8])
    g /= np.linalg.norm(g)
    np.testing.assert_allclose(gimbal_rotation(g) @ np.array([0.0, 0.0, 1.0]), g, atol=1e-15)


def test_initial_distance_equals_the_jax_formula():
    rng = np.random.default_rng(3)
    r, phi, th = rng.uniform(5, 15, 500), rng.uniform(0, 2 * np.pi, 500), rng.uniform(0.1, 3, 500)
    x = {"tx": 0.1, "ty": -0.2, "tz": 9.3, "rx": 0.4, "ry": 2.8, "f": F}
    xs = np.asarray(polar_to_cartesian(r, phi, th))
    X = xs @ np.asarray(rot_y(x["ry"]) @ rot_x(x["rx"])).T + np.array([0.1, -0.2, 9.3])
    ref = X[:, 2] - (X[:, 0] ** 2 + X[:, 1] ** 2) / (4 * F)
    np.testing.assert_allclose(initial_distance(r, phi, th, x), ref, atol=1e-12)


def test_rowwise_median_and_histogram_mode_match_numpy():
    rng = np.random.default_rng(0)
    a = np.abs(rng.normal(size=(7, 301)))
    keep = rng.random(a.shape) < 0.6
    keep[3] = False
    med = _rowwise_median(a, keep)
    for k in range(len(a)):
        if keep[k].any():
            assert med[k] == pytest.approx(np.median(a[k][keep[k]]), rel=1e-6)
        else:
            assert np.isnan(med[k])
    v = np.concatenate([rng.normal(0.3, 0.005, (5, 800)), rng.normal(0, 3, (5, 200))], axis=1)
    valid = np.ones(v.shape[1], bool)
    mode = _histogram_mode(v, valid, 0.02)
    for k in range(len(v)):
        lo, hi = np.percentile(v[k], [0.5, 99.5])
        h, e = np.histogram(v[k], bins=int(np.clip((hi - lo) / 0.02, 10, 20000)), range=(lo, hi))
        assert mode[k] == pytest.approx(0.5 * (e[np.argmax(h)] + e[np.argmax(h) + 1]), abs=1e-9)


def test_weighted_lsq_matches_lstsq_and_flags_degenerate_rows():
    rng = np.random.default_rng(1)
    G = rng.normal(size=(4, 4, 50)) * [[[0.0], [10.0], [10.0], [100.0]]]
    G[:, 0] = 1.0
    w = rng.random((4, 50)) < 0.7
    w[2] = False
    w[2, :2] = True  # two points: too few for two regressors and an intercept
    p, c = _weighted_lsq(G, w)
    for k in (0, 1, 3):
        A = np.column_stack([G[k, 1], G[k, 2], np.ones(50)])[w[k]]
        ref, *_ = np.linalg.lstsq(A, G[k, 3][w[k]], rcond=None)
        np.testing.assert_allclose(np.r_[p[k], c[k]], ref, rtol=1e-9, atol=1e-9)
    assert np.all(np.isnan(p[2])) and np.isnan(c[2])


# --------------------------------------------------------------------- the whole robust fit


def test_batched_robust_fits_equal_the_per_heading_algorithm():
    xs, g = _scan_points()
    basis = _Basis.of(xs, gimbal_rotation(g))
    kappa = np.array([0.0, 0.5, 0.7, 0.72, 2.0, 4.0])
    X, Y, Z = basis.frames(kappa)
    t, f, res = _robust_fits(X, Y, Z, basis.r2, basis.valid, F, 0.02)
    for k, kap in enumerate(kappa):
        Xk = xs @ (gimbal_rotation(g) @ np.asarray(rot_z(kap))).T
        np.testing.assert_allclose(np.stack([X[k], Y[k], Z[k]], 1), Xk, atol=1e-12)
        t1, f1, res1 = _robust_one(Xk, F, 0.02)
        np.testing.assert_allclose(t[k], t1, atol=1e-8)
        assert f[k] == pytest.approx(f1, abs=1e-8)
        assert np.count_nonzero(np.abs(res[k]) < 0.02) == np.count_nonzero(np.abs(res1) < 0.02)


def test_initial_values_find_the_heading_and_skip_non_finite_points():
    xs, g = _scan_points(heading=0.7, n=20000)
    r, phi, th = cartesian_to_raw(xs, 1)
    rng = np.random.default_rng(2)
    r = r + rng.normal(size=len(r)) * SIGMA[0]
    iv = initial_values(r, phi, th, g, focal_length_m=F)
    assert iv.heading_rad == pytest.approx(0.7, abs=0.02)
    assert iv.x["tz"] == pytest.approx(9.3, abs=0.01)
    assert iv.x["f"] == pytest.approx(F, abs=0.01)
    assert iv.inlier_fraction > 0.8
    r2 = r.copy()
    r2[::50] = np.nan
    iv2 = initial_values(r2, phi, th, g, focal_length_m=F)
    assert iv2.heading_rad == pytest.approx(0.7, abs=0.02)
    assert iv2.inlier_fraction == pytest.approx(iv.inlier_fraction * 0.98, abs=0.01)
    with pytest.raises(ValueError, match="finite"):
        initial_values(np.full(100, np.nan), phi[:100], th[:100], g, focal_length_m=F)
