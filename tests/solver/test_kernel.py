"""The iteration kernel's vectorised float64 sine and cosine, and the materialised trig that
uses it."""

import jax
import jax.numpy as jnp
import numpy as np

from hartrao_jax.solver._kernel import materialize_trig, sincos_f64


def _angles():
    rng = np.random.default_rng(0)
    return np.concatenate([
        rng.uniform(-7.0, 7.0, 200_000), rng.uniform(-1e6, 1e6, 100_000),
        np.arange(-1000, 1001) * (np.pi / 2), np.arange(-1000, 1001) * (np.pi / 4),
        [0.0, -0.0, 1e-300, 5e-324, 1e-8, -3e-5],
        np.nextafter(np.pi / 4, 1.0) * np.arange(1, 40)])


def test_sincos_within_two_units_in_the_last_place_of_numpys():
    """Within 2 ulp of NumPy's (libm's) sine and cosine where the value is at least 1e-12,
    and within 2.3e-16 absolute everywhere, for |x| < 1e6 rad; NaN for inf and NaN."""
    x = _angles()
    s, c = (np.asarray(a) for a in jax.jit(sincos_f64)(x))
    for got, ref in ((s, np.sin(x)), (c, np.cos(x))):
        assert np.abs(got - ref).max() <= 2.3e-16
        big = np.abs(ref) >= 1e-12
        assert np.all(np.abs(got - ref)[big] <= 2 * np.spacing(np.abs(ref[big])))
    zero = [np.asarray(a).tolist() for a in jax.jit(sincos_f64)(np.array([0.0, -0.0]))]
    assert zero == [[0.0, 0.0], [1.0, 1.0]]
    bad = np.asarray(jax.jit(sincos_f64)(np.array([np.inf, -np.inf, np.nan])))
    assert np.isnan(bad).all()


def test_materialised_trig_differentiates_as_sine_and_cosine():
    """A condition's trig goes through the vectorised sincos (a custom derivative: cos and
    -sin, not the polynomials' own): value and gradient equal the analytic ones."""
    def f(x):
        return jnp.sin(x[0]) * jnp.cos(2.0 * x[1]) + jnp.tan(x[0] + x[1])

    on = jnp.asarray(True)
    x = jnp.asarray([0.3, -1.7])
    val, grad = jax.jit(jax.value_and_grad(lambda y, o: materialize_trig(f, o)(y)))(x, on)
    a, b = 0.3, -1.7
    sec2 = 1.0 / np.cos(a + b) ** 2
    np.testing.assert_allclose(float(val), np.sin(a) * np.cos(2 * b) + np.tan(a + b),
                               rtol=1e-15)
    np.testing.assert_allclose(np.asarray(grad),
                               [np.cos(a) * np.cos(2 * b) + sec2,
                                -2 * np.sin(a) * np.sin(2 * b) + sec2], rtol=1e-14)
