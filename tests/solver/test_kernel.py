"""The iteration kernel's materialised trig (the vectorised float64 sine and cosine of
:mod:`hartrao_jax.geometry._trig`)."""

import jax
import jax.numpy as jnp
import numpy as np

from hartrao_jax.solver._kernel import materialize_trig


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
