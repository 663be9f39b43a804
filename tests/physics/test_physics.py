"""The catalog: sign conventions, two-face behaviour, separability, motion, reflector."""

import numpy as np
import pytest

from hartrao_jax.geometry._geometry import polar_to_cartesian
from hartrao_jax.physics._catalog import (
    EFFECTS,
    INSTRUMENT,
    correct_observations,
    impulsive_shift,
    instrument_corrections,
    oscillation,
    oscillation_sincos,
    panel_deviation,
    paraboloid_condition,
)


def _both_faces(a_deg=30.0, th0=0.6, r=10.0):
    """The same direction observed in face 1 and in face 2 (raw angles)."""
    a = np.radians(a_deg)
    return (np.array([r, r]), np.array([a, a + np.pi]), np.array([th0, 2 * np.pi - th0]))


@pytest.mark.parametrize("name", sorted(INSTRUMENT))
def test_two_face_flag_matches_behaviour(name):
    """Two-face-sensitive parameters move the point differently in the two faces."""
    r, phi, th = _both_faces()
    p = INSTRUMENT[name]
    v = 1e-4
    x0 = np.asarray(polar_to_cartesian(r, phi, th))
    x1 = np.asarray(polar_to_cartesian(*correct_observations(r, phi, th, {name: v})))
    d = x1 - x0
    same = np.allclose(d[0], d[1], atol=1e-12)
    if name == "x12a":
        # physics.md lists x12a as not two-face sensitive, but cos(2 theta) of the raw continuous
        # theta is the same number in both faces, so it moves the beam in opposite directions
        # there (like x4): it is two-face sensitive. Assert the physics.
        assert not same
        return
    if p.two_face == "no":
        assert same, name
    else:
        assert not same, name


def test_x6_x7_phi_terms_use_corrected_theta():
    r, phi, th = (np.array([10.0]), np.array([0.3]), np.array([0.5]))
    dr, dphi, dth = instrument_corrections(r, phi, th, {"x4": 1e-3, "x7": 1e-4})
    assert abs(float(dphi[0]) - 1e-4 / np.tan(0.5 + 1e-3)) < 1e-15
    dr, dphi, dth = instrument_corrections(r, phi, th, {"x5n": 1e-3, "x3": 1e-4})
    assert abs(float(dphi[0]) - 1e-4 / (10 * np.sin(0.5))) < 1e-15




def test_motion_effects():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    d = np.asarray(impulsive_shift(t, 1.0, 1.5, [0, 0, 0.002]))
    np.testing.assert_allclose(d[:, 2], [0, 0.002, 0.002, 0])
    w = np.asarray(oscillation(t, 4.0, 1e-5, 0.0, [1, 0, 0]))
    np.testing.assert_allclose(w[:, 0], 1e-5 * np.sin(2 * np.pi * t / 4), atol=1e-20)


def test_panel_deviation_offset_and_tilt():
    rho_c, psi_c = np.array([5.0]), np.array([0.5])
    dev = panel_deviation(np.array([5.0, 5.5]), np.array([0.5, 0.5]), np.array([0, 0]),
                          np.array([1e-3]), np.array([2e-3]), np.array([0.0]), rho_c, psi_c)
    np.testing.assert_allclose(np.asarray(dev), [1e-3, 1e-3 + 2e-3 * 0.5])
    assert float(panel_deviation(np.array([5.0]), np.array([0.5]), np.array([-1]), np.array([1.0]),
                                 np.array([0.0]), np.array([0.0]), rho_c, psi_c)[0]) == 0.0


def test_positive_deviation_is_towards_focus():
    # a point raised 1 mm along the normal: on the surface deviated by +1 mm, above (condition
    # negative: towards the focus) the undeformed one
    n = np.array([-5.0 / 20.0, 0.0, 1.0]) / np.sqrt(1 + (5.0 / 20.0) ** 2)
    X = np.array([5.0, 0.0, 25.0 / 40.0]) + 0.001 * n
    assert abs(float(paraboloid_condition(X, 10.0, 0.001))) < 1e-7
    assert float(paraboloid_condition(X, 10.0, 0.0)) < -0.9e-3


def test_oscillation_forms_agree():
    t = np.linspace(0.0, 3.0, 7)
    w = np.asarray(oscillation(t, 1.1, 2e-5, 0.7, [0, 1, 0]))
    s, c = 2e-5 * np.cos(0.7), 2e-5 * np.sin(0.7)
    w2 = np.asarray(oscillation_sincos(t, 1 / 1.1, [0, s, 0], [0, c, 0]))
    np.testing.assert_allclose(w, w2, atol=1e-20)


def test_catalog_has_every_effect_of_the_spec():
    spec = {"x1n", "x1z", "x2", "x3", "x4", "x5n", "x5z", "x6", "x7", "x8x", "x8y", "x10", "x11a",
            "x11b", "x12a", "x12b", "range_scale", "impulsive_shift", "oscillation", "drift",
            "panel_offset", "gravity_deformation", "thermal", "unexplained"}
    assert spec <= set(EFFECTS)
