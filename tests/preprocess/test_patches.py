"""Patch keys: re-keying only the split cells' points gives the keys of a full re-keying, and
the keys follow their definition (face, theta band, phi bin, sub-cell)."""

from __future__ import annotations

import numpy as np
import pytest

from hartrao_jax.preprocess._patches import _Bins, _keys, _split_keys


def _angles(cycle: int, n: int = 200_000, seed: int = 0, grid: float = 0.003):
    """Raw angles (rad) of one face (cycle 1, 2) or both (0): half on a scanner-like grid."""
    rng = np.random.default_rng(seed)
    lo, hi = {1: (0.01, np.pi - 0.01), 2: (np.pi + 0.01, 2 * np.pi - 0.01),
              0: (0.01, 2 * np.pi - 0.01)}[cycle]
    th, phi = rng.uniform(lo, hi, n), rng.uniform(0, 2 * np.pi, n)
    h = n // 2
    th[:h], phi[:h] = np.round(th[:h] / grid) * grid, np.round(phi[:h] / grid) * grid
    return phi, np.clip(th, lo, hi)


@pytest.mark.parametrize("cycle", [0, 1, 2])
def test_split_keys_equal_a_full_rekeying(cycle):
    phi, th = _angles(cycle)
    bins = _Bins(cycle, 0.3, 12.0)
    idx = np.arange(len(phi))
    cells, occ = _keys(phi, th, idx, bins)
    assert bins.subdivide(occ, 64, 0.003)
    full, occ_full = _keys(phi, th, idx, bins)
    split, occ_split = _split_keys(phi, th, idx, cells, bins)
    np.testing.assert_array_equal(split, full)
    np.testing.assert_array_equal(occ_split, occ_full)
    assert full.dtype == np.int32 and full.min() >= 0 and full.max() < bins.n_keys


def test_keys_follow_their_definition():
    phi, th = _angles(1, n=20_000, seed=1)
    bins = _Bins(1, 0.3, 12.0)
    k = bins.keys(phi, th)
    band = np.minimum((th / bins.dth).astype(np.int64), bins.n_band - 1)
    nb = bins.n_phi[band]
    j = np.minimum((phi * (1.0 / np.pi) * nb).astype(np.int64), nb - 1)
    np.testing.assert_array_equal(k, band * bins.J + j)
