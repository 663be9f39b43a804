"""Float64 sine and cosine by vectorised arithmetic: in JAX programs and for NumPy arrays."""

import jax
import numpy as np

from hartrao_jax.geometry._geometry import polar_components
from hartrao_jax.geometry._trig import HOST_BLOCK, host_sincos, sincos_f64


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



def test_host_sincos_of_any_length_and_shape_is_the_programs():
    """NumPy arrays of any length (whole blocks, a padded last one) and shape: the values of
    :func:`sincos_f64`, within 2 ulp of NumPy's; polar coordinates of a whole scan's size
    agree with NumPy's formula to round-off."""
    rng = np.random.default_rng(3)
    for n in (1, HOST_BLOCK - 1, HOST_BLOCK, 2 * HOST_BLOCK + 17):
        x = rng.uniform(-7.0, 7.0, n)
        s, c = host_sincos(x)
        js, jc = (np.asarray(a) for a in jax.jit(sincos_f64)(x))
        assert np.array_equal(s, js) and np.array_equal(c, jc)
        assert np.all(np.abs(s - np.sin(x)) <= 2 * np.spacing(np.abs(np.sin(x))) + 1e-300)
    x = rng.uniform(0.0, 6.3, (300, 70))
    s, c = host_sincos(x)
    assert s.shape == x.shape and np.allclose(c, np.cos(x), rtol=0, atol=2.3e-16)
    r, phi, th = rng.uniform(5, 15, 50_000), rng.uniform(0, 6.3, 50_000), rng.uniform(2, 3, 50_000)
    got = polar_components(r, phi, th, xp=np)
    ref = (r * np.sin(th) * np.sin(phi), r * np.sin(th) * np.cos(phi), r * np.cos(th))
    for g, e in zip(got, ref):
        np.testing.assert_allclose(g, e, rtol=0, atol=1e-14)
