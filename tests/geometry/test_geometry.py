"""Pointing, frames, eq. 2, faces, panels, Zernike, paraboloid distance."""

import numpy as np
import pytest

from hartrao_jax.geometry._geometry import (
    cartesian_to_raw,
    decompose_zyx,
    elevation_of,
    gravity_in_telescope,
    noll_to_nm,
    panel_geometry,
    panel_ids,
    paraboloid_deviation,
    polar_to_cartesian,
    rot_x,
    rot_y,
    rot_z,
    telescope_axes_altaz,
    telescope_axes_hadec,
    zernike,
)

LAT = np.radians(-25.8897)
EDGES = [1.6, 3.2, 4.8, 6.4, 8.0, 9.6, 11.2, 12.95]
PANELS = [15, 24, 30, 36, 42, 48, 60]


def test_zenith_pointing_is_north_west_up():
    F = np.asarray(telescope_axes_hadec(0.0, LAT, LAT))
    np.testing.assert_allclose(F, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(np.asarray(gravity_in_telescope(F)), [0, 0, -1], atol=1e-15)
    assert abs(float(elevation_of(F)) - np.pi / 2) < 1e-12


def test_pointing_south_tilts_boresight_south_and_meridian_elevation():
    dec = np.radians(-64.0)
    F = np.asarray(telescope_axes_hadec(0.0, dec, LAT))
    # on the meridian, elevation = 90 - |lat - dec|
    assert abs(np.degrees(float(elevation_of(F))) - (90 - abs(-25.8897 + 64.0))) < 1e-9
    assert F[1, 2] < 0  # boresight has a southern component
    np.testing.assert_allclose(F.T @ F, np.eye(3), atol=1e-14)
    assert abs(np.linalg.det(F) - 1) < 1e-14


def test_hour_angle_west_moves_boresight_west():
    F = np.asarray(telescope_axes_hadec(np.radians(30.0), LAT, LAT))
    assert F[0, 2] < 0  # east component negative: pointing west


def test_altaz_matches_hadec_at_zenith_and_horizon_north():
    np.testing.assert_allclose(np.asarray(telescope_axes_altaz(np.pi / 2, 0.0)),
                               np.asarray(telescope_axes_hadec(0.0, LAT, LAT)), atol=1e-15)
    F = np.asarray(telescope_axes_altaz(0.0, 0.0))
    np.testing.assert_allclose(F[:, 2], [0, 1, 0], atol=1e-15)


@pytest.mark.parametrize("cycle", [0, 1, 2])
def test_raw_angles_invert_eq2_and_follow_face_rule(cycle):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(5000, 3)) * 5
    r, phi, th = cartesian_to_raw(xyz, cycle)
    np.testing.assert_allclose(np.asarray(polar_to_cartesian(r, phi, th)), xyz, atol=1e-12)
    if cycle == 0:
        assert np.all((phi >= 0) & (phi < 2 * np.pi) & (th > 0) & (th < np.pi))
    else:
        lo = 0 if cycle == 1 else np.pi
        assert np.all((phi >= lo) & (phi < lo + np.pi))
        a = np.mod(np.arctan2(xyz[:, 0], xyz[:, 1]), 2 * np.pi)
        face1 = (a >= lo) & (a < lo + np.pi)
        assert np.all((th < np.pi) == face1)


def test_decompose_zyx_roundtrip_upside_down_branch():
    for k, ry, rx in [(0.4, np.pi - 0.3, 0.2), (-2.0, 2.5, -0.7), (1.0, -np.pi + 0.1, 0.0)]:
        R = rot_z(k) @ rot_y(ry) @ rot_x(rx)
        k2, ry2, rx2 = decompose_zyx(R)
        np.testing.assert_allclose(np.asarray(rot_z(k2) @ rot_y(ry2) @ rot_x(rx2)), np.asarray(R),
                                   atol=1e-12)
        assert np.cos(float(ry2)) < 0


def test_panel_ids_numbering_and_count():
    geo = panel_geometry(EDGES, PANELS)
    assert len(geo["ring"]) == 255
    ids = panel_ids(geo["rho_c"], geo["psi_c"], EDGES, PANELS)
    np.testing.assert_array_equal(ids, np.arange(255))
    outside = panel_ids(np.array([1.0, 13.0]), np.array([0.0, 0.0]), EDGES, PANELS)
    assert outside.tolist() == [-1, -1]
    # ring 0, first panel counter-clockwise from psi = 0
    assert panel_ids(np.array([2.0]), np.array([0.01]), EDGES, PANELS)[0] == 0
    assert panel_ids(np.array([2.0]), np.array([2 * np.pi - 0.01]), EDGES, PANELS)[0] == 14
    assert panel_ids(np.array([12.0]), np.array([0.01]), EDGES, PANELS)[0] == 255 - 60


def test_panel_cells_compiled_by_blocks_equal_numpy(monkeypatch):
    """Above ``BLOCK_ROWS`` points the panel cells are compiled and taken a block at a time
    (the last block overlapping): the same panels as NumPy's one call, local coordinates
    within 1e-12 m; points outside the panelled annulus get -1 and zeros either way."""
    import hartrao_jax.geometry._geometry as G

    rng = np.random.default_rng(4)
    n = 5000
    rho = rng.uniform(0.0, 13.5, n)
    psi = rng.uniform(-np.pi, np.pi, n)
    X = np.stack([rho * np.cos(psi), rho * np.sin(psi), rng.normal(size=n)], 1)
    ref_ids, ref_local, nc, _ = G.panel_cells(X, EDGES, PANELS)
    monkeypatch.setattr(G, "BLOCK_ROWS", 1024)
    ids, local, nc2, _ = G.panel_cells(X, EDGES, PANELS)
    np.testing.assert_array_equal(ids, ref_ids)
    np.testing.assert_allclose(local, ref_local, atol=1e-12)
    assert nc == nc2 == 255 and ids.dtype == np.int64
    assert np.all(local[ids < 0] == 0.0) and np.any(ids < 0)


def test_paraboloid_deviation_exact_and_signed():
    f = 10.9816
    rng = np.random.default_rng(1)
    rho = rng.uniform(0, 13, 200)
    psi = rng.uniform(0, 2 * np.pi, 200)
    d = rng.uniform(-0.05, 0.05, 200)
    # point at normal distance d from the surface (towards the focus for d > 0)
    z0 = rho**2 / (4 * f)
    n = np.stack([-rho / (2 * f), np.ones_like(rho)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    R = rho + d * n[:, 0]
    Z = z0 + d * n[:, 1]
    X = np.stack([R * np.cos(psi), R * np.sin(psi), Z], 1)
    np.testing.assert_allclose(np.asarray(paraboloid_deviation(X, f)), d, atol=1e-12)


def test_zernike_orthonormal_on_unit_disk():
    assert [noll_to_nm(j) for j in (1, 2, 3, 4, 5, 6, 11)] == [
        (0, 0), (1, 1), (1, -1), (2, 0), (2, -2), (2, 2), (4, 0)]
    u = np.sqrt(np.linspace(0, 1, 400)[1:])
    psi = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    U, P = np.meshgrid(u, psi)
    Z = np.stack([np.asarray(zernike(j, U, P)).ravel() for j in range(1, 12)])
    G = Z @ Z.T / Z.shape[1]
    np.testing.assert_allclose(G, np.eye(11), atol=2e-2)


def test_grid_sum_and_cell_codes_equal_add_at_and_unique_rows():
    """``grid_sum`` is ``np.add.at`` (the same sums in the same order, bit for bit);
    ``cell_code`` sorts and counts as the rows of ``np.unique(axis=0)``, negative indices
    included; ``square_cells`` gives the same cells as before."""
    from hartrao_jax.geometry._geometry import cell_code, grid_sum, square_cells

    rng = np.random.default_rng(3)
    X = rng.normal(size=(50_000, 3)) * 8.0
    ij = np.floor(X[:, :2] / 0.7).astype(np.int64)
    keys, inv, cnt = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    codes, inv2, cnt2 = np.unique(cell_code(ij), return_inverse=True, return_counts=True)
    assert np.array_equal(np.argsort(cell_code(keys)), np.arange(len(keys)))
    assert np.array_equal(inv.reshape(-1), inv2) and np.array_equal(cnt, cnt2)
    cell, _, k = square_cells(X, 0.7)
    assert np.array_equal(k, keys) and np.array_equal(cell, inv.reshape(-1))
    g = ij - ij.min(0)
    shape = tuple(int(v) for v in g.max(0) + 1)
    ref = np.zeros(shape)
    np.add.at(ref, (g[:, 0], g[:, 1]), X[:, 2])
    assert np.array_equal(grid_sum(g, shape, X[:, 2]), ref)
    ones = np.zeros(shape)
    np.add.at(ones, (g[:, 0], g[:, 1]), 1.0)
    assert np.array_equal(grid_sum(g, shape), ones)


def test_column_bounds_and_grid_indices_equal_numpys_row_reductions():
    """``column_bounds`` is ``(a.min(0), a.max(0))`` and ``grid_indices`` is
    ``floor((xy - lo) / h)`` as int64, value for value, on a strided view as well."""
    from hartrao_jax.geometry._geometry import column_bounds, grid_indices

    rng = np.random.default_rng(4)
    X = rng.normal(size=(20_001, 3)) * 9.0
    for a in (X, X[:, :2], X[::3, 1:]):
        lo, hi = column_bounds(a)
        assert np.array_equal(lo, a.min(0)) and np.array_equal(hi, a.max(0))
        start = lo - 0.37
        assert np.array_equal(grid_indices(a, start, 0.05),
                              np.floor((a - start) / 0.05).astype(np.int64))
