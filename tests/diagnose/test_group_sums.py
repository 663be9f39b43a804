"""The panel nuisance's sums of the local search, all panels at once, against one panel after
the other (the definition)."""

import math

import numpy as np
import pytest
from scipy import ndimage

from hartrao_jax.diagnose import _locate as L
from hartrao_jax.diagnose._locate import _group_sums, _panel_columns, _PanelAlgebra, grid_of


def _one_by_one(ij, r, panels, shape, sw, sigma, tau2):
    """Each panel filtered on its own patch, its sums added into the grid in turn."""
    Q1, Q2 = np.zeros(shape), np.zeros(shape)
    reach = int(4.0 * sw + 0.5) + 1
    for idx, P in panels:
        P = P if tau2 > 0.0 else P[:, :1]
        K = P.T @ P
        if P.shape[1] > 1:
            K[1:, 1:] += np.eye(P.shape[1] - 1) * sigma**2 / tau2
        lo = np.maximum(ij[idx].min(0) - reach, 0)
        hi = np.minimum(ij[idx].max(0) + reach + 1, shape)
        shp = tuple(int(v) for v in hi - lo)
        cell = (ij[idx, 0] - lo[0]) * shp[1] + (ij[idx, 1] - lo[1])
        G = np.stack([ndimage.gaussian_filter(
            np.bincount(cell, P[:, a], minlength=shp[0] * shp[1]).reshape(shp), sw,
            mode="constant", truncate=4.0) * (2 * math.pi * sw * sw)
            for a in range(P.shape[1])], -1)
        GK = G @ np.linalg.inv(K)
        Q1[lo[0]:hi[0], lo[1]:hi[1]] += GK @ (P.T @ r[idx])
        Q2[lo[0]:hi[0], lo[1]:hi[1]] += np.einsum("...a,...a->...", GK, G)
    return Q1, Q2


@pytest.mark.parametrize("chunk", [None, 1, 30_000])
@pytest.mark.parametrize("tau2", [0.0, 1e-8])
def test_all_panels_at_once_are_one_panel_after_the_other(tau2, chunk, monkeypatch):
    """Bit for bit: the same additions in the same order, with and without the tilts, with
    panels of a few points (offset alone) among them and patches cut at the grid's edge; in
    one chunk of panels, one panel a chunk, or a few panels a chunk."""
    if chunk is not None:
        monkeypatch.setattr(L, "PATCH_VALUES", chunk)
    rng = np.random.default_rng(4)
    n = 40_000
    xy = rng.uniform(-6.0, 6.0, (n, 2))
    ids = (np.floor((xy[:, 0] + 6.0) / 2.0) * 6 + np.floor((xy[:, 1] + 6.0) / 2.0)).astype(int)
    few = np.flatnonzero(ids == 7)[:5]  # a panel of five points: its offset alone
    keep = (ids != 7) | np.isin(np.arange(n), few)
    xy, ids = xy[keep], ids[keep]
    r = rng.normal(0.0, 1e-3, len(xy))
    panels = _panel_columns(xy, ids)
    assert any(P.shape[1] == 1 for _, P in panels)
    w, sigma = 0.5, 1e-3
    _, shape, ij, h = grid_of(xy, w)
    # a grid cut close to the points: patches at its edge are clipped
    ij_cut = ij - ij.min(0)
    shape_cut = tuple(int(v) for v in ij_cut.max(0) + 1)
    for grid_ij, grid_shape in ((ij, shape), (ij_cut, shape_cut)):
        got = _group_sums(grid_ij, _PanelAlgebra.of(panels, r, sigma, tau2), grid_shape, w / h)
        want = _one_by_one(grid_ij, r, panels, grid_shape, w / h, sigma, tau2)
        for g, e in zip(got, want):
            assert np.abs(e).max() > 0
            np.testing.assert_array_equal(g, e)
