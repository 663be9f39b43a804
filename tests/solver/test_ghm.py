"""The Gauss-Helmert solver: recovery, sigma0, invariance, derivatives, batch, peer agreement."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import SIGMA, synthetic_scan, truth_vector

from hartrao_jax import gauss_helmert, gauss_helmert_batch, make_model, robust_gauss_helmert


def _start(x):
    return x + np.array([0.02, -0.01, -0.1, 0.01, -0.01, -0.2] + [0.0] * (len(x) - 6))


@pytest.mark.parametrize("model", ["simplified", "extended"])
def test_recovers_parameters_within_three_sigma_and_sigma0_near_one(model):
    params = {"x4": 1.5e-4, "x6": 3e-5, "x7": -4e-5} if model == "extended" else None
    m = make_model(model)
    l = synthetic_scan(40000, seed=1, model=m, params=params)
    xt = truth_vector(m.free, params=params)
    res = gauss_helmert(m, l, _start(xt), SIGMA, np.zeros((len(l), 2)))
    assert bool(res.converged)
    z = (np.asarray(res.x) - xt) / np.asarray(res.sigma)
    assert np.all(np.abs(z) < 3.5), dict(zip(m.free, z))
    assert 0.95 < float(res.sigma0) < 1.05




def test_invariant_under_rotation_of_the_cloud_about_the_scanner_axis():
    """Rotating the cloud about the scanner's z axis only shifts phi: f and sigma0 unchanged."""
    m = make_model("tx,ty,tz,rx,ry,f,x4")
    l = synthetic_scan(20000, cycle=0, seed=3)
    xt = truth_vector(m.free)
    c = np.zeros((len(l), 2))
    r1 = gauss_helmert(m, l, _start(xt), SIGMA, c, tol=1e-10)
    l2 = l.copy()
    l2[:, 1] = np.mod(l2[:, 1] + 1.234, 2 * np.pi)
    r2 = gauss_helmert(m, l2, _start(xt), SIGMA, c, tol=1e-10)
    i = m.free.index("f")
    assert abs(float(r1.x[i] - r2.x[i])) < 1e-9 * float(r1.x[i])
    assert abs(float(r1.sigma0 - r2.sigma0)) < 1e-8


def test_invariant_under_rigid_motion_of_noiseless_cloud():
    """A rigid motion of the scanner (any pose) is absorbed by tx..ry: f is the same."""
    m = make_model("simplified")
    fs = []
    for pose in [
        {"tx": 0.01, "ty": -0.02, "tz": 9.3, "rx": 0.3, "ry": np.pi - 0.5},
        {"tx": -0.2, "ty": 0.15, "tz": 8.7, "rx": -0.6, "ry": np.pi + 0.2},
    ]:
        l = synthetic_scan(5000, seed=4, noise=False, pose=pose)
        xt = truth_vector(m.free, pose=pose)
        res = gauss_helmert(m, l, _start(xt), SIGMA, np.zeros((len(l), 2)), tol=1e-10)
        fs.append(float(res.x[5]))
    assert abs(fs[0] - fs[1]) < 1e-9
    assert abs(fs[0] - 10.9816) < 1e-9


def test_residuals_satisfy_condition_and_sigma0_matches_definition():
    m = make_model("simplified")
    l = synthetic_scan(5000, seed=5)
    xt = truth_vector(m.free)
    res = gauss_helmert(m, l, _start(xt), SIGMA, np.zeros((len(l), 2)), tol=1e-12)
    F = jax.vmap(m, in_axes=(0, None, 0))(jnp.asarray(l) + res.v, res.x, jnp.zeros((len(l), 2)))
    assert np.max(np.abs(np.asarray(F))) < 1e-9  # adjusted observations lie on the surface
    omega = np.sum((np.asarray(res.v) / SIGMA) ** 2)
    assert abs(np.sqrt(omega / (len(l) - 6)) - float(res.sigma0)) < 1e-6


def test_covariance_is_statistically_right():
    """Spread of estimates over noise realisations matches the reported sigma (within 25 %)."""
    m = make_model("simplified")
    xt = truth_vector(m.free)
    est, sig = [], []
    for seed in range(12):
        l = synthetic_scan(3000, seed=100 + seed)
        res = gauss_helmert(m, l, xt, SIGMA, np.zeros((len(l), 2)))
        est.append(np.asarray(res.x))
        sig.append(np.asarray(res.sigma))
    z = (np.array(est) - xt) / np.array(sig)
    # chi-square of all z: mean of z^2 ~ 1 (72 values)
    assert 0.55 < float(np.mean(z**2)) < 1.6


def test_batch_equals_one_by_one():
    m = make_model("extended")
    params = {"x4": 1e-4}
    ls = [synthetic_scan(3000, seed=s, params=params) for s in (7, 8)]
    ls[1] = ls[1][:2500]
    xt = truth_vector(m.free, params=params)
    n = 3000
    L = np.zeros((2, n, 3))
    W = np.zeros((2, n))
    for b, l in enumerate(ls):
        L[b, : len(l)] = l
        L[b, len(l):] = l[0]
        W[b, : len(l)] = 1
    rb = gauss_helmert_batch(m, L, np.stack([_start(xt)] * 2), SIGMA, np.zeros((2, n, 2)), W)
    for b, l in enumerate(ls):
        r1 = gauss_helmert(m, l, _start(xt), SIGMA, np.zeros((len(l), 2)))
        np.testing.assert_allclose(np.asarray(rb.x[b]), np.asarray(r1.x), rtol=1e-10, atol=1e-12)
        assert abs(float(rb.sigma0[b] - r1.sigma0)) < 1e-9


def test_robust_option_rejects_gross_errors_and_keeps_good_points():
    m = make_model("simplified")
    l = synthetic_scan(10000, seed=9)
    rng = np.random.default_rng(0)
    bad = rng.choice(len(l), 100, replace=False)
    l[bad, 0] -= rng.uniform(0.01, 0.2, 100)  # returns 1-20 cm short (multipath/scatter)
    xt = truth_vector(m.free)
    res = robust_gauss_helmert(m, l, _start(xt), SIGMA, np.zeros((len(l), 2)), k=4.0)
    w = np.asarray(res.weights)
    assert np.all(w[bad] == 0)
    assert np.mean(w == 0) < 0.0115  # at most ~15 good points lost
    assert 0.95 < float(res.sigma0) < 1.05
    assert abs(float(res.x[5]) - xt[5]) < 3.5 * float(res.sigma[5])


def test_agrees_with_odrpack_implicit_odr():
    """Independent peer: ODRPACK95's implicit ODR on the same observations and weights."""
    odrpack = pytest.importorskip("odrpack")
    m = make_model("simplified")
    l = synthetic_scan(400, seed=11)
    xt = truth_vector(m.free)
    res = gauss_helmert(m, l, xt, SIGMA, np.zeros((len(l), 2)), tol=1e-12)
    fm = jax.jit(jax.vmap(lambda ll, b: m(ll, b, jnp.zeros(2)), in_axes=(0, None)))

    def f(x, beta):
        return np.asarray(fm(jnp.asarray(x.T), jnp.asarray(beta)))

    out = odrpack.odr_fit(
        f, l.T, np.zeros(len(l)), xt, weight_x=1.0 / SIGMA**2, task="implicit-ODR",
        diff_scheme="central", sstol=1e-14, partol=1e-14, maxit=200,
    )
    f_odr = out.beta[5]
    assert abs(f_odr - float(res.x[5])) < 1e-6 * float(res.x[5])
