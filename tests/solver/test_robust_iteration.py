"""The robust white adjustment rejects inside the iteration: the same rejections and estimates
as the repeated solves it replaced (adjust to convergence, reject beyond k a-posteriori sigmas,
adjust again from that solution, until nothing more is rejected), in fewer passes."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import SIGMA, synthetic_scan, truth_vector

from hartrao_jax import gauss_helmert, make_model, robust_gauss_helmert


def _start(x):
    return x + np.array([0.02, -0.01, -0.1, 0.01, -0.01, -0.2] + [0.0] * (len(x) - 6))


def _rounds(m, l, x0, c, k=4.0, max_rounds=6):
    """The former robust_gauss_helmert: one full adjustment per round."""
    w = np.ones(len(l))
    res = gauss_helmert(m, l, x0, SIGMA, c, w, v0=np.zeros_like(l))
    its = [int(res.iterations)]
    for _ in range(max_rounds):
        bad = (np.asarray(res.normalized) > k) & (w > 0)
        if not bad.any():
            break
        w = np.where(bad, 0.0, w)
        res = gauss_helmert(m, l, res.x, SIGMA, c, w, v0=res.v)
        its.append(int(res.iterations))
    return res, its


@pytest.mark.parametrize("model", ["simplified", "extended"])
def test_rejection_inside_the_iteration_equals_the_rounds(model):
    m = make_model(model)
    l = synthetic_scan(20000, seed=3)
    rng = np.random.default_rng(1)
    bad = rng.choice(len(l), 200, replace=False)
    l[bad, 0] -= rng.uniform(0.003, 0.2, 200)  # short returns, 4-250 sigma
    xt = truth_vector(m.free)
    c = np.zeros((len(l), 2))
    ref, its = _rounds(m, l, _start(xt), c)
    res = robust_gauss_helmert(m, l, _start(xt), SIGMA, c, k=4.0)
    assert len(its) >= 2  # the rounds did reject
    assert bool(res.converged)
    np.testing.assert_array_equal(np.asarray(res.weights) > 0, np.asarray(ref.weights) > 0)
    sig = np.asarray(ref.sigma)
    np.testing.assert_allclose((np.asarray(res.x) - np.asarray(ref.x)) / sig, 0.0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(res.sigma), sig, rtol=1e-8)
    assert float(res.sigma0) == pytest.approx(float(ref.sigma0), rel=1e-9)
    used = np.asarray(res.weights) > 0
    np.testing.assert_allclose(np.asarray(res.normalized)[used],
                               np.asarray(ref.normalized)[used], rtol=1e-6, atol=1e-8)
    assert not np.any(np.asarray(res.normalized)[used] > 4.0)  # no used point beyond the limit
    assert int(res.iterations) < sum(its)  # fewer passes over the points


def test_max_rounds_bounds_the_rejecting_passes():
    m = make_model("simplified")
    l = synthetic_scan(5000, seed=4)
    l[::50, 0] -= 0.05
    xt = truth_vector(m.free)
    c = np.zeros((len(l), 2))
    none = robust_gauss_helmert(m, l, _start(xt), SIGMA, c, k=4.0, max_rounds=0)
    assert np.all(np.asarray(none.weights) == 1.0)
    one = robust_gauss_helmert(m, l, _start(xt), SIGMA, c, k=4.0, max_rounds=1)
    assert np.sum(np.asarray(one.weights) == 0) >= 100


@pytest.mark.parametrize("threads", [2, 3])
@pytest.mark.parametrize("robust", [True, False])
def test_passes_split_over_threads_equal_one_loop(threads, robust):
    """Each pass split into parts (one thread each, the normal equations added) gives the
    single jitted loop's adjustment: same iterations and rejections, x and sigmas to 1e-9."""
    m = make_model("extended")
    l = synthetic_scan(30001, seed=5)  # parts of whole chunks, a short last one
    l[::97, 0] -= 0.02
    xt = truth_vector(m.free)
    c = np.zeros((len(l), 2))
    w = np.ones(len(l))
    w[-50:] = 0.0  # padding-like rows
    sig = np.broadcast_to(SIGMA, l.shape) * np.where(np.arange(len(l)) % 2, 1.0, 1.2)[:, None]
    kw = dict(k=4.0) if robust else {}
    fit = robust_gauss_helmert if robust else gauss_helmert
    one = fit(m, l, _start(xt), sig, c, w, threads=1, **kw)
    split = fit(m, l, _start(xt), sig, c, w, threads=threads, **kw)
    assert int(split.iterations) == int(one.iterations) and bool(split.converged)
    np.testing.assert_array_equal(np.asarray(split.weights), np.asarray(one.weights))
    s = np.asarray(one.sigma)
    np.testing.assert_allclose((np.asarray(split.x) - np.asarray(one.x)) / s, 0.0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(split.sigma), s, rtol=1e-9)
    assert float(split.sigma0) == pytest.approx(float(one.sigma0), rel=1e-10)
    used = np.asarray(one.weights) > 0
    np.testing.assert_allclose(np.asarray(split.v)[used], np.asarray(one.v)[used], atol=1e-12)
    np.testing.assert_allclose(np.asarray(split.normalized), np.asarray(one.normalized),
                               rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(np.asarray(split.misclosure), np.asarray(one.misclosure),
                               atol=1e-12)
