"""Initial values converge over the whole working range; kappa from gravity and from the legs."""

import numpy as np
import pytest
from helpers import SIGMA, paraboloid_points

from hartrao_jax import gauss_helmert, make_model
from hartrao_jax.fit._align import kappa_from_heading, mount_heading, north_alignment
from hartrao_jax.geometry._geometry import (
    cartesian_to_raw,
    decompose_zyx,
    gravity_in_telescope,
    rot_z,
    telescope_axes_hadec,
)
from hartrao_jax.preprocess._initial import gimbal_rotation, initial_values

LAT = np.radians(-25.8897)
F = 10.9816
T_TEL = np.array([0.01, -0.02, 9.3])
LEGS = [45.0, 135.0, 225.0, 315.0]


def _scan(ha_deg, dec_deg, heading, n=30000, seed=0, scatter=0.15, legs=False):
    g = np.asarray(gravity_in_telescope(
        telescope_axes_hadec(np.radians(ha_deg), np.radians(dec_deg), LAT)))
    R = gimbal_rotation(g) @ np.asarray(rot_z(heading))
    X = paraboloid_points(n, F, seed)
    if legs:
        psi = np.degrees(np.arctan2(X[:, 1], X[:, 0])) % 360
        shadow = np.zeros(n, bool)
        for L in LEGS:
            shadow |= (np.abs((psi - L + 180) % 360 - 180) < 1.5) & (np.hypot(X[:, 0], X[:, 1]) > 3)
        X = X[~shadow]
    xs = (X - T_TEL) @ R
    rng = np.random.default_rng(seed + 1)
    if scatter:
        k = int(scatter * len(xs))
        xs = np.concatenate([xs, rng.normal(size=(k, 3)) * 4 + [0, 0, 3]])
    r, phi, th = cartesian_to_raw(xs, 1)
    l = np.stack([r, phi, th], 1) + rng.normal(size=(len(r), 3)) * SIGMA
    kappa, ry, rx = (float(a) for a in decompose_zyx(R))
    return l, g, kappa, R


@pytest.mark.parametrize("ha,dec", [(-88, -89), (-35, -64), (0, -25.8897), (45, 10), (88, 45),
                                    (-60, 30), (20, -80)])
def test_initial_values_converge_across_working_range(ha, dec):
    l, g, kappa, R = _scan(ha, dec, heading=0.7, seed=ha + 100)
    iv = initial_values(l[:, 0], l[:, 1], l[:, 2], g, focal_length_m=F)
    m = make_model("extended")
    x0 = np.array([iv.x.get(k, 0.0) for k in m.free])
    # geometry window as the fit pipeline does it
    from hartrao_jax.preprocess._initial import initial_distance

    w = (np.abs(initial_distance(l[:, 0], l[:, 1], l[:, 2], iv.x)) < 0.1).astype(float)
    res = gauss_helmert(m, l, x0, SIGMA, np.zeros((len(l), 2)), w)
    assert bool(res.converged)
    assert abs(float(res.x[5]) - F) < 4 * float(res.sigma[5])
    tz = float(res.x[2])
    assert abs(tz - 9.3) < 1e-3


def test_kappa_from_gravity_away_from_zenith():
    l, g, kappa, R = _scan(-35, -64, heading=0.7, scatter=0.0)
    _, ry, rx = decompose_zyx(R)
    al = north_alignment(float(rx), float(ry), g)
    assert al.source == "gravity"
    assert abs(al.kappa_rad - kappa) < 1e-9
    # the mount heading is recovered and predicts kappa elsewhere
    h = mount_heading(al.kappa_rad, float(rx), float(ry), g)
    assert abs(h - 0.7) < 1e-9
    _, g2, kappa2, _ = _scan(40, 20, heading=0.7, n=10, scatter=0.0)
    assert abs(kappa_from_heading(h, g2) - kappa2) < 1e-9


def test_kappa_at_zenith_from_quadrupod_shadows():
    l, g, kappa, R = _scan(0, -25.8897, heading=0.7, scatter=0.0, legs=True, n=60000)
    _, ry, rx = decompose_zyx(R)
    from hartrao_jax.geometry._geometry import polar_to_cartesian, rot_x, rot_y

    X_fit = np.asarray(polar_to_cartesian(l[:, 0], l[:, 1], l[:, 2])) @ np.asarray(
        rot_y(ry) @ rot_x(rx)).T + np.asarray(rot_z(-kappa)) @ T_TEL
    al = north_alignment(float(rx), float(ry), g, X_fit, leg_azimuths_deg=LEGS,
                         heading_hint_rad=0.7)
    assert al.source == "quadrupod+heading"
    assert abs((al.kappa_rad - kappa + np.pi) % (2 * np.pi) - np.pi) < np.radians(0.2)
    # without a hint: right modulo the legs' 90-degree symmetry, and the ambiguity is reported
    al2 = north_alignment(float(rx), float(ry), g, X_fit, leg_azimuths_deg=LEGS)
    d = (al2.kappa_rad - kappa) % (np.pi / 2)
    assert min(d, np.pi / 2 - d) < np.radians(0.2)
    assert abs(al2.ambiguity_rad - np.pi / 2) < 1e-9
    # the points to look at as a mask: the same as those points given alone
    used = np.random.default_rng(1).random(len(X_fit)) < 0.7
    a, b = (north_alignment(float(rx), float(ry), g, X, used=u, leg_azimuths_deg=LEGS,
                            heading_hint_rad=0.7) for X, u in ((X_fit, used), (X_fit[used], None)))
    assert a == b


def test_geometry_window_leaves_out_the_scanners_pole():
    """Points within 1e-3 rad of the pole (x6/sin(theta), x7/tan(theta) singular) are not
    adjusted, on both faces; all others inside the window are."""
    from hartrao_jax.preprocess._initial import (
        POLE_EXCLUSION_RAD,
        geometry_window,
        initial_distance,
    )

    x = {"tx": 0.0, "ty": 0.0, "tz": 0.0, "rx": 0.0, "ry": 0.0, "f": 10.9816}
    theta = np.array([2e-4, 9e-4, 1.1e-3, 0.5, np.pi - 5e-4, np.pi + 5e-4, 2 * np.pi - 2e-4,
                      2 * np.pi - 0.5])
    phi = np.full_like(theta, 0.3)
    # ranges that put every point on the paraboloid (or far from it for the pole points)
    r = np.full_like(theta, 3.0)
    near = np.abs(initial_distance(r, phi, theta, x)) < 1e9  # window wide open
    w = geometry_window(r, phi, theta, x, 1e9)
    assert near.all()
    assert w.tolist() == [False, False, True, True, False, False, False, True]
    assert np.all(np.abs(np.sin(theta[~w])) <= POLE_EXCLUSION_RAD)
