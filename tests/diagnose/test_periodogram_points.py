"""The periodogram at the points' own times (all frequencies from one complex exponential per
point and frequency) equals the per-frequency score test it replaces."""

from __future__ import annotations

import types

import numpy as np

from hartrao_jax.diagnose._find import _periodogram_points


def _direct(sc, freqs):
    """Per frequency: the (sin, cos) x (rotation x, y) columns against the rotation columns."""
    u = sc.used & (sc.m > 0)
    t, a, q, F = sc.data.time_s[u], sc.probe[u][:, 3:], 1.0 / sc.m[u], sc.F[u]
    N0i = np.linalg.pinv((a * q[:, None]).T @ a)
    out = np.zeros(len(freqs))
    for k, f in enumerate(freqs):
        h = np.stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)], 1)
        C = (h[:, :, None] * a[:, None, :]).reshape(len(t), 4)
        qC = C * q[:, None]
        M, K, uu = qC.T @ C, qC.T @ a, qC.T @ F
        S = M - K @ N0i @ K.T
        out[k] = float(uu @ np.linalg.solve(S + 1e-12 * np.trace(S) * np.eye(4), uu))
    return out


def test_periodogram_points_equals_the_per_frequency_test():
    rng = np.random.default_rng(0)
    n = 40000
    t = np.sort(rng.uniform(0.0, 11.0, n))
    sc = types.SimpleNamespace(
        used=rng.uniform(size=n) > 0.02, m=rng.uniform(0.5, 2.0, n) * 1e-6,
        data=types.SimpleNamespace(time_s=t), probe=rng.normal(size=(n, 5)) * [1, 1, 1, 10, 10],
        F=rng.normal(size=n) * 1e-3 + 3e-4 * np.sin(2 * np.pi * t / 1.1))
    freqs = 1 / 1.1 + np.linspace(-1.5, 1.5, 31) * 0.01
    ref = _direct(sc, freqs)
    got = _periodogram_points(sc, freqs, chunk=4096)  # several chunks
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9 * ref.max())
    assert np.argmax(got) == np.argmax(ref)
