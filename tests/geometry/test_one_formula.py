"""Geometry written once: the NumPy evaluations equal the JAX ones (no twins to drift apart)."""

import jax.numpy as jnp
import numpy as np

from hartrao_jax.geometry._geometry import polar_components, polar_to_cartesian, zernike
from hartrao_jax.preprocess._frames import _cartesian
from hartrao_jax.surface._gravity import zernike_np


def test_zernike_numpy_equals_jax():
    rng = np.random.default_rng(1)
    u, psi = rng.uniform(0, 1, 500), rng.uniform(0, 2 * np.pi, 500)
    for j in range(1, 23):
        np.testing.assert_allclose(zernike_np(j, u, psi), np.asarray(zernike(j, u, psi)),
                                   rtol=1e-12, atol=1e-13)
        assert isinstance(zernike(j, u, psi, xp=np), np.ndarray)


def test_polar_numpy_equals_jax():
    rng = np.random.default_rng(2)
    r, phi, th = rng.uniform(1, 60, 400), rng.uniform(0, 2 * np.pi, 400), rng.uniform(0, np.pi, 400)
    xyz = np.stack(_cartesian(r, phi, th), axis=-1)
    np.testing.assert_allclose(xyz, np.asarray(polar_to_cartesian(r, phi, th)), rtol=1e-13,
                               atol=1e-12)
    assert all(isinstance(a, np.ndarray) for a in polar_components(r, phi, th, xp=np))
    assert all(isinstance(a, jnp.ndarray) for a in polar_components(r, phi, th))
