"""The model: condition equations assembled from the catalog, exact at the truth, their
Jacobians (autodiff) against finite differences, and the names a model refuses."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import finite_difference, synthetic_scan, truth_vector

from hartrao_jax import ModelError, make_model
from hartrao_jax.physics._catalog import INSTRUMENT, inseparable_pairs
from hartrao_jax.solver._ghm import _linearize


def test_condition_is_exactly_zero_at_truth_without_noise():
    params = {"x4": 1.5e-4, "x6": 3e-5, "x7": -4e-5}
    m = make_model("extended")
    l = synthetic_scan(2000, noise=False, params=params)
    xt = truth_vector(m.free, params=params)
    F = jax.vmap(m, in_axes=(0, None, 0))(jnp.asarray(l), jnp.asarray(xt), jnp.zeros((len(l), 2)))
    assert np.max(np.abs(np.asarray(F))) < 1e-9


def test_jacobians_match_finite_differences():
    m = make_model("x1n,x1z,x2,x3,x4,x5n,x6,x7,x8x,x8y,x10,x11a,x12a")
    l = synthetic_scan(5, noise=False)
    x = truth_vector(m.free) + 1e-4
    c = jnp.zeros(2)
    for i in range(len(l)):
        F, a, b = _linearize(m, jnp.asarray(l[i]), jnp.asarray(x), c)
        a_fd = finite_difference(
            lambda xx: float(m(jnp.asarray(l[i]), jnp.asarray(xx), c)), x, 1e-6)
        b_fd = finite_difference(
            lambda ll: float(m(jnp.asarray(ll), jnp.asarray(x), c)), l[i], 1e-7)
        np.testing.assert_allclose(np.asarray(a), a_fd, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(np.asarray(b), b_fd, rtol=1e-5, atol=1e-7)


def test_inseparable_pairs_found_and_refused():
    pairs = {(a, b) for a, b, _ in inseparable_pairs(list(INSTRUMENT))}
    assert ("x5z", "x7") in pairs or ("x7", "x5z") in pairs
    with pytest.raises(ModelError, match="x5z and x7 cannot be estimated together"):
        make_model("tx,ty,tz,rx,ry,f,x5z,x7")
    # the seed's extended model is separable
    assert inseparable_pairs(["x4", "x6", "x7"]) == []


def test_unknown_parameter_names_are_refused():
    with pytest.raises(ModelError, match="unknown parameter"):
        make_model("x4,x99")


def test_host_values_are_the_params():
    """``values(x)`` on the host (no JAX operation) gives ``params(x)``: the free unknowns
    from ``x``, then the held ones."""
    m = make_model(["tx", "ty", "tz", "rx", "ry", "f", "x2"], fixed={"x4": 1e-5, "x6": -2e-5})
    x = np.linspace(-1.0, 1.0, len(m.free))
    want = {k: float(v) for k, v in m.params(jnp.asarray(x)).items()}
    assert m.values(x) == want
    assert list(m.values(x)) == list(want)
