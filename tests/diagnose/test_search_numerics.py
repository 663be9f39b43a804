"""The searches' fast numerics equal what they replace: single-precision sines after removing
whole turns (period searches), scipy.special's chi-square functions (detectability), the box
search's 3 x 3 quadratic forms by the adjugate, the shift window refined from sums up to the
candidate edges, the replicate grids filtered over the cores."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import optimize, stats

from hartrao_jax.diagnose._covariates import _fold_periods, _periodogram_folds, _sincos_turns
from hartrao_jax.diagnose._detectability import _noncentrality
from hartrao_jax.diagnose._find import _edge_candidates, _quadratic_3x3, _refine_window
from hartrao_jax.diagnose._locate import _filter_grids


def test_sincos_turns_within_2e7_of_double_at_any_phase():
    rng = np.random.default_rng(0)
    turns = np.concatenate([rng.uniform(-1e4, 1e4, 200_000), [0.0, 0.25, 0.5, -0.75, 1e6 + 0.125]])
    s, c = _sincos_turns(turns)
    assert s.dtype == c.dtype == np.float64
    assert np.max(np.abs(s - np.sin(2 * np.pi * turns))) < 2e-7
    assert np.max(np.abs(c - np.cos(2 * np.pi * turns))) < 2e-7


def _folds_double(v, r, fold, periods, n_folds=4):
    """The training-fold residual sums of a constant plus one sinusoid, by plain least
    squares per fold and period (double precision throughout)."""
    out = np.empty((n_folds, len(periods)))
    for k in range(n_folds):
        tr = fold != k
        for j, P in enumerate(periods):
            A = np.column_stack([np.sin(2 * np.pi * v[tr] / P), np.cos(2 * np.pi * v[tr] / P),
                                 np.ones(tr.sum())])
            res = r[tr] - A @ np.linalg.lstsq(A, r[tr], rcond=None)[0]
            out[k, j] = res @ res
    return out


def test_fold_periodogram_equals_least_squares_and_finds_the_period():
    """A 1.3 m cyclic range error on 3,000 points of 20-60 m: the fold periodograms equal
    per-fold least squares to 1e-6 of the total and every fold picks the true period."""
    rng = np.random.default_rng(1)
    n = 3000
    v = rng.uniform(20.0, 60.0, n)
    r = 2e-4 * np.sin(2 * np.pi * v / 1.3 + 0.7) + 1e-4 * rng.normal(size=n)
    fold = np.arange(n) % 4
    periods = np.geomspace(0.4, 26.0, 40)
    got = _periodogram_folds(v, r, fold, periods)
    ref = _folds_double(v, r, fold, periods)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6 * float(np.sum(r * r)))
    coarse = np.geomspace(40.0 / 100, 40.0 / 1.5, 150)  # as compare() spans them
    assert np.all(np.abs(_fold_periods(v, r, fold, coarse) / 1.3 - 1) < 0.005)


@pytest.mark.parametrize("dof", [1, 3, 12])
@pytest.mark.parametrize("alpha", [1e-3, 5e-8, 1e-12])
def test_noncentrality_equals_scipy_stats(dof, alpha):
    crit = stats.chi2.isf(alpha, dof)
    ref = optimize.brentq(lambda L: stats.ncx2.sf(crit, dof, L) - 0.8, 1e-6, 1e6)
    assert _noncentrality(alpha, dof) == pytest.approx(ref, rel=1e-12)


def test_quadratic_3x3_equals_the_solve():
    """``n^T S^-1 n`` by the adjugate equals LAPACK's solve, well and badly conditioned (the
    box search's Schur complements, a 1e-9 ridge on their trace)."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(2000, 3, 3))
    S = A @ A.transpose(0, 2, 1) + np.logspace(-9, 0, 2000)[:, None, None] * np.eye(3)
    n = rng.normal(size=(2000, 3))
    ref = np.einsum("wi,wi->w", n, np.linalg.solve(S, n[..., None])[..., 0])
    cond = np.linalg.cond(S)
    got = _quadratic_3x3(S, n)
    assert np.all(np.abs(got - ref) <= 1e-13 * cond * np.abs(ref) + 1e-300)


def _window_by_cumsum(t, a, q, F, edges, i, j, Ntot, n_cand=48):
    """The refined window's statistic from cumulative sums over every time-sorted point (as
    :func:`_refine_window` computed it before)."""
    o = np.argsort(t, kind="stable")
    t, a, q, F = t[o], a[o], q[o], F[o]
    qa = a * q[:, None]
    CN = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(qa[:, :, None] * a[:, None, :], 0)])
    Cn = np.concatenate([np.zeros((1, 3)), np.cumsum(qa * F[:, None], 0)])
    S0, E0 = np.meshgrid(_edge_candidates(t, edges, i, n_cand),
                         _edge_candidates(t, edges, j, n_cand), indexing="ij")
    S0, E0 = S0[E0 > S0], E0[E0 > S0]
    NW, nW = CN[E0] - CN[S0], Cn[E0] - Cn[S0]
    Sm = NW - NW @ np.linalg.pinv(Ntot) @ NW + 1e-9 * np.trace(Ntot) / 3 * np.eye(3)
    return float(np.max(np.sum(nW * np.linalg.solve(Sm, nW[..., None])[..., 0], 1)))


@pytest.mark.parametrize("shuffled", [False, True])
def test_refined_window_equals_the_cumulative_sums(shuffled):
    """The window refined from the sums up to each candidate edge (no sort where the times are
    in order) has the statistic of cumulative sums over every time-sorted point, and finds a
    planted shift of 10.0-10.9 s to the points' resolution, whatever the rows' order."""
    import types

    rng = np.random.default_rng(3)
    n = 60_000
    t = np.sort(rng.uniform(0.0, 22.0, n))
    if shuffled:
        t = rng.permutation(t)
    probe, m = rng.normal(size=(n, 5)), rng.uniform(0.5, 2.0, n)
    F = rng.normal(size=n) + 0.5 * ((t > 10.0) & (t < 10.9)) * probe[:, 2]
    used = rng.uniform(size=n) > 0.02
    sc = types.SimpleNamespace(used=used, m=m, probe=probe, F=F,
                               data=types.SimpleNamespace(time_s=t))
    edges = np.linspace(0.0, 22.0, 221)
    i, j = 99, 109  # the coarse window's bins around 10.0-10.9 s
    u = used & (m > 0)
    a, q = probe[u][:, :3], 1.0 / m[u]
    Ntot = (a * q[:, None]).T @ a
    (start, width), T = _refine_window(sc, edges, i, j, Ntot, 0.0)
    assert T == pytest.approx(_window_by_cumsum(t[u], a, q, F[u], edges, i, j, Ntot), rel=1e-10)
    assert abs(start - 10.0) < 0.01 and abs(start + width - 10.9) < 0.01


def test_replicate_grids_filtered_over_the_cores_equal_one_filter():
    """The replicates split over threads give ndimage's filter of the whole stack exactly, in
    its dtype; a single grid is filtered as it was."""
    from scipy import ndimage

    rng = np.random.default_rng(0)
    for shape, dtype in [((120, 110, 90), np.float64), ((100, 100, 101), np.float32),
                         ((80, 80), np.float64)]:
        R = rng.normal(size=shape).astype(dtype)
        for s in (3.79, 12.0):
            want = ndimage.gaussian_filter(R, [s, s] + [0.0] * (R.ndim - 2), mode="constant",
                                           truncate=4.0)
            got = _filter_grids(R, s)
            assert got.dtype == want.dtype and np.array_equal(got, want)
