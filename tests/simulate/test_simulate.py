"""Simulator: exactness against the truth model, grid and faces, occluders, scatter, noise,
determinism, effects, CLI parsing and the written campaign (coarse grids: fast)."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pyarrow.parquet as pq
import pytest

from hartrao_jax.campaign._campaign import ScanMeta, load_campaign, read_scan
from hartrao_jax.geometry._geometry import panel_ids, rot_x, rot_y, rot_z
from hartrao_jax.simulate._simulate import (
    CLASSES,
    TRUTH_SCHEMA,
    EffectError,
    SimConfig,
    model_from_truth,
    normalize_effects,
    parse_effects,
    simulate_campaign,
    simulate_scan,
    truth_model,
)

STEP = 0.02
SIG_R, SIG_A = 0.0008, 2e-5
ALL_EFFECTS = {
    "x1n": 2e-4, "x1z": -1e-4, "x2": 3e-4, "x3": 1e-4, "x4": 1.5e-4, "x5n": 2e-5, "x5z": 1e-5,
    "x6": 3e-5, "x7": -4e-5, "x8x": 1e-5, "x8y": -2e-5, "x10": 1e-3, "x11a": 1e-5, "x11b": 2e-5,
    "x12a": -1e-5, "x12b": 1e-5, "range_scale": 2e-5,
    "impulsive_shift": {"displacement_m": 0.003, "phi_deg": 60.0, "duration_s": 0.5},
    "oscillation": {"amplitude_rad": 3e-5, "period_s": 0.4, "phase_rad": 0.3, "axis": "y"},
    "drift": {"rate_m_s": 2e-4, "rate_rad_s": 1e-6, "axis": "x"},
    "panel_offset": 3e-4, "gravity_deformation": 1.0, "thermal": 1.3e-4, "unexplained": 1e-3,
}


def meta(cycle=1, temperature_c=None, pos=("r23", -35.0, -64.0)):
    name, ha, dec = pos
    return ScanMeta(f"{name}c{cycle}", name, cycle, f"scans/{name}c{cycle}.parquet", ha, dec,
                    temperature_c=temperature_c)


def sim(cycle=1, preset="clean", **kw):
    kw.setdefault("step_rad", STEP)
    return simulate_scan(meta(cycle, kw.pop("temperature_c", None)), preset=preset, **kw)


def condition(model, lab, rows, dtheta=0.0):
    obs = np.stack([lab["range_true_m"], lab["phi_true_rad"], lab["theta_true_rad"] + dtheta], 1)
    c = np.stack([lab["time_s"], lab["deviation_m"]], 1)
    f = jax.jit(jax.vmap(lambda ll, cc: model(ll, jnp.zeros(0), cc)))
    return np.asarray(f(jnp.asarray(obs[rows]), jnp.asarray(c[rows])))


@pytest.fixture(scope="module")
def demo_c1():
    return sim(1, preset="demo")


@pytest.fixture(scope="module")
def demo_c2():
    return sim(2, preset="demo")


# ----------------------------------------------------------------------------- exactness


@pytest.mark.parametrize("cycle", [1, 2])
def test_reflector_points_satisfy_truth_model(cycle):
    eff = dict(ALL_EFFECTS)
    if cycle == 2:
        eff["impulsive_shift"] = {**eff["impulsive_shift"], "cycle": 2, "phi_deg": 250.0}
    data, lab, truth = sim(cycle, effects=eff, temperature_c=22.0)
    refl = lab["cls"] == CLASSES["reflector"]
    F = condition(model_from_truth(truth), lab, refl)
    assert refl.sum() > 10000
    assert np.max(np.abs(F)) < 1e-9
    assert truth["max_abs_condition_m"] < 1e-9 and truth["n_rays_not_converged"] == 0
    # every effect is really in the model
    mp = truth["model_parameters"]
    assert {"shift_x", "osc_sy", "osc_cy", "drift_tx", "drift_rx", "x1n", "range_scale"} <= set(mp)
    assert truth["shift_window_s"][1] == 0.5 and truth["osc_period_s"] == 0.4
    assert any(abs(v) > 0 for v in truth["zernike"].values())


def test_truth_pose_is_the_fitted_frame():
    _, _, truth = sim(1)
    R = np.asarray(truth["R_full"])
    g = np.asarray(truth["g"])
    np.testing.assert_allclose(R[:, 2], g, atol=1e-12)  # scanner z along gravity
    M = np.asarray(rot_z(truth["kappa_rad"]) @ rot_y(truth["ry"]) @ rot_x(truth["rx"]))
    np.testing.assert_allclose(M, R, atol=1e-12)
    t_fit = np.asarray(rot_z(-truth["kappa_rad"])) @ np.asarray(truth["t_tel"])
    np.testing.assert_allclose([truth["tx"], truth["ty"], truth["tz"]], t_fit, atol=1e-12)
    assert truth["f"] == pytest.approx(10.9816)


def test_gimbal_misalignment_and_fixed_position():
    cfg = SimConfig(t_tel_m=(0.0, 0.0, 9.3), gimbal_misalignment_rad=(1e-3, -2e-3),
                    kappa_s_rad=1.0)
    _, lab, truth = sim(1, config=cfg)
    assert truth["t_tel"] == [0.0, 0.0, 9.3]
    assert not np.allclose(np.asarray(truth["R_full"])[:, 2], truth["g"], atol=1e-4)
    F = condition(model_from_truth(truth), lab, lab["cls"] == 0)
    assert np.max(np.abs(F)) < 1e-9


def test_extra_deviation_enters_the_truth():
    bump = lambda X: 2e-4 * jnp.cos(X[0] / 3.0)  # noqa: E731  (telescope frame, m)
    _, l0, _ = sim(1)
    _, l1, t1 = sim(1, extra_deviation=bump)
    s = l1["cls"] == 0
    np.testing.assert_allclose(l1["deviation_m"][s], 2e-4 * np.cos(l1["X"][s] / 3.0), atol=1e-12)
    assert np.max(np.abs(condition(model_from_truth(t1), l1, s))) < 1e-9
    assert not np.array_equal(l0["range_true_m"][:100], l1["range_true_m"][:100])


def test_fit_recovers_truth(demo_c1):
    """The fitter's extended model on the simulator's output: unbiased to a few sigma."""
    from hartrao_jax.model._model import make_model
    from hartrao_jax.solver._ghm import gauss_helmert

    data, lab, truth = demo_c1
    refl = lab["cls"] == 0
    model = make_model("extended", kappa_rad=truth["kappa_rad"])
    x_true = np.array([truth["model_parameters"][n] for n in model.free])
    obs = np.stack([data.range_m, data.phi_rad, data.theta_rad], 1)[refl]
    c = np.stack([data.time_s, lab["deviation_m"]], 1)[refl]
    x0 = x_true + np.array([0.01, -0.01, 0.01, 1e-3, -1e-3, 0.005, 0.0, 0.0, 0.0])
    res = gauss_helmert(model, obs, x0, np.array([SIG_R, SIG_A, SIG_A]), c)
    z = (np.asarray(res.x) - x_true) / np.asarray(res.sigma)
    assert bool(res.converged)
    assert np.all(np.abs(z) < 4), dict(zip(model.free, z))
    assert float(res.sigma0) == pytest.approx(1.0, abs=0.03)


# ----------------------------------------------------------------------------- grid


@pytest.mark.parametrize("cycle", [1, 2])
def test_raw_angles_faces_and_time_order(cycle):
    data, lab, truth = sim(cycle, preset="demo")
    lo = 0.0 if cycle == 1 else math.pi
    for phi in (data.phi_rad, lab["phi_true_rad"]):
        assert phi.min() >= lo and phi.max() < lo + math.pi
    assert data.theta_rad.min() > 0 and data.theta_rad.max() < 2 * math.pi
    face2 = data.theta_rad > math.pi
    refl = lab["cls"] == 0
    assert (refl & face2).sum() > 1000 and (refl & ~face2).sum() > 1000
    assert np.all(np.diff(data.time_s) >= 0)
    assert data.time_s[-1] == pytest.approx(truth["n_lines"] * truth["line_period_s"], rel=0.02)
    assert data.intensity.dtype == np.float32
    assert 0 <= data.intensity.min() and data.intensity.max() <= 1
    assert lab["cls"].dtype == np.uint8 and lab["panel"].dtype == np.int16
    np.testing.assert_array_equal(lab["row"], np.arange(len(data)))


def test_cycles_cover_the_dish_with_swapped_faces(demo_c1, demo_c2):
    def panels(d, lab, face2):
        s = (lab["cls"] == 0) & ((d.theta_rad > math.pi) == face2)
        return set(np.unique(lab["panel"][s]))

    c1f1, c1f2 = panels(*demo_c1[:2], False), panels(*demo_c1[:2], True)
    c2f1, c2f2 = panels(*demo_c2[:2], False), panels(*demo_c2[:2], True)
    # each cycle sees the whole dish but panels hidden behind the quadrupod legs
    assert len(c1f1 | c1f2) >= 245 and len(c2f1 | c2f2) >= 245
    jac = lambda a, b: len(a & b) / len(a | b)  # noqa: E731
    # cycle 2 sees in face 2 what cycle 1 sees in face 1, and vice versa
    assert jac(c1f1, c2f2) > 0.9 and jac(c1f2, c2f1) > 0.9
    assert jac(c1f1, c2f1) < 0.3 and jac(c1f2, c2f2) < 0.3


# ----------------------------------------------------------------------------- occluders


def test_no_reflector_inside_cone_and_leg_shadows(demo_c1):
    data, lab, truth = demo_c1
    refl = lab["cls"] == 0
    rho = np.hypot(lab["X"], lab["Y"])
    psi = np.degrees(np.arctan2(lab["Y"], lab["X"])) % 360
    assert rho[refl].min() >= 1.6
    assert (lab["cls"] == CLASSES["cone"]).sum() > 0
    assert (lab["cls"] == CLASSES["quadrupod"]).sum() > 0
    outer = refl & (rho > 10.5) & (rho < 12.9)
    for az in (45.0, 135.0, 225.0, 315.0):
        dpsi = (psi - az + 180) % 360 - 180
        near = np.histogram(dpsi[outer], bins=6, range=(-6, 6))[0]
        assert near.min() == 0, (az, near)  # a gap behind the leg (parallax: off-centre)
        assert (outer & (np.abs(dpsi - 20) < 2.0)).sum() > 10
    assert rho[refl].max() <= 12.95
    assert rho[refl].max() > 12.8


def test_scatter_classes_in_configured_fractions():
    cfg = SimConfig(multipath_fraction=0.05, background_prob=1.0)
    _, lab, _ = sim(1, preset="demo", config=cfg)
    n = {k: int((lab["cls"] == v).sum()) for k, v in CLASSES.items()}
    assert all(v > 0 for v in n.values()), n
    frac = n["multipath"] / (n["multipath"] + n["reflector"])
    assert frac == pytest.approx(0.05, abs=0.01)
    bg = lab["range_true_m"][lab["cls"] == CLASSES["background"]]
    assert bg.min() >= 20 and bg.max() <= 80
    _, lab3, _ = sim(1, preset="demo", config=SimConfig(background_prob=0.3))
    n3 = int((lab3["cls"] == CLASSES["background"]).sum())
    assert n3 / n["background"] == pytest.approx(0.3, abs=0.05)
    # clean: reflector only
    _, labc, _ = sim(1, preset="clean")
    assert set(np.unique(labc["cls"])) == {0}


def test_multipath_and_mixed_ranges(demo_c1):
    data, lab, truth = demo_c1
    _, lab0, _ = sim(1, preset="demo", config=SimConfig(multipath_fraction=0.0, mixed_prob=0.0))
    mp = lab["cls"] == CLASSES["multipath"]
    # the same rays without multipath: the surface range
    ia, i0 = common_rows(lab, lab0)
    idx = i0[mp[ia]]
    mp = ia[mp[ia]]
    surf = lab0["range_true_m"][idx]
    excess = lab["range_true_m"][mp] - surf
    assert excess.min() >= 0.003 - 1e-9 and excess.max() <= 0.05 + 1e-9
    assert (lab["cls"] == CLASSES["mixed"]).sum() > 0


# ----------------------------------------------------------------------------- noise


def test_noise_matches_sigmas(demo_c1):
    data, lab, _ = demo_c1
    s = lab["cls"] == 0
    for obs, true, sig in ((data.range_m, lab["range_true_m"], SIG_R),
                           (data.phi_rad, lab["phi_true_rad"], SIG_A),
                           (data.theta_rad, lab["theta_true_rad"], SIG_A)):
        e = (obs - true)[s]
        assert np.std(e) == pytest.approx(sig, rel=0.05)
        assert abs(np.mean(e)) < 4 * sig / math.sqrt(s.sum())


def test_determinism():
    a, la, ta = sim(1, preset="demo", seed=3)
    b, lb, tb = sim(1, preset="demo", seed=3)
    c, _, tc = sim(1, preset="demo", seed=4)
    for k in ("range_m", "phi_rad", "theta_rad", "intensity", "time_s"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    np.testing.assert_array_equal(la["cls"], lb["cls"])
    assert ta == tb
    assert len(a) != len(c) or not np.array_equal(a.range_m, c.range_m)
    assert ta["tx"] != tc["tx"]  # the pose jitter follows the seed


# ----------------------------------------------------------------------------- effects


def common_rows(la, lb):
    """Indices of the rays (same raw grid angles) present in both label tables."""
    key = lambda d: np.round(d["phi_true_rad"] * 1e6) * 1e7 + np.round(d["theta_true_rad"] * 1e6)  # noqa: E731
    _, ia, ib = np.intersect1d(key(la), key(lb), return_indices=True)
    return ia, ib


def test_x4_acts_through_the_model_only():
    _, l0, t0 = sim(1)
    _, l4, t4 = sim(1, effects={"x4": 2e-4})
    # same raw grid, same pose; only the raw ranges change (a few rim rays come and go)
    i0, i4 = common_rows(l0, l4)
    assert len(i0) > 0.99 * len(l0["cls"])
    np.testing.assert_array_equal(l0["theta_true_rad"][i0], l4["theta_true_rad"][i4])
    assert t0["tx"] == t4["tx"] and t4["model_parameters"]["x4"] == 2e-4
    assert np.max(np.abs(l4["range_true_m"][i4] - l0["range_true_m"][i0])) > 1e-4
    refl = l4["cls"] == 0
    no_x4 = model_from_truth(t0)  # the same truth without x4 ...
    assert np.max(np.abs(condition(no_x4, l4, refl))) > 1e-5
    # ... holds once theta is corrected by x4 (seed eq. 9)
    assert np.max(np.abs(condition(no_x4, l4, refl, dtheta=2e-4))) < 1e-9


def test_impulsive_shift_only_inside_its_window():
    eff = {"impulsive_shift": {"displacement_m": 0.004, "phi_deg": 90.0, "duration_s": 1.0}}
    _, l0, t0 = sim(1)
    _, l1, t1 = sim(1, effects=eff)
    start, dur = t1["shift_window_s"]
    assert start == pytest.approx(math.pi / 2 / (math.pi / t1["n_lines"]) * t1["line_period_s"])
    assert np.hypot(*[t1["model_parameters"][k] for k in ("shift_x", "shift_y")]) < 1e-12
    i0, i1 = common_rows(l0, l1)
    inside = (l1["time_s"][i1] >= start) & (l1["time_s"][i1] < start + dur)
    d = l1["range_true_m"][i1] - l0["range_true_m"][i0]
    assert inside.sum() > 50
    assert np.max(np.abs(d[~inside])) < 1e-11
    assert np.min(np.abs(d[inside])) > 5e-4
    # cycle 2 is not affected by a cycle-1 shift
    _, _, t2 = sim(2, effects=eff)
    assert "shift_z" not in t2["model_parameters"]


def test_panel_offset_explicit_panels_and_ids():
    eff = {"panel_offset": {"panels": {20: 1e-3, 100: (-5e-4, 1e-4, 0.0)}}}
    _, lab, _ = sim(1, effects=eff)
    s = lab["cls"] == 0
    dev, panel = lab["deviation_m"][s], lab["panel"][s]
    assert set(np.unique(panel[dev != 0])) == {20, 100}
    np.testing.assert_allclose(dev[panel == 20], 1e-3, atol=1e-15)
    X, Y = lab["X"][s], lab["Y"][s]
    ids = panel_ids(np.hypot(X, Y), np.mod(np.arctan2(Y, X), 2 * np.pi),
                    (1.6, 3.2, 4.8, 6.4, 8.0, 9.6, 11.2, 12.95), (15, 24, 30, 36, 42, 48, 60))
    assert np.mean(ids == panel) > 0.9999


def test_gravity_and_thermal_focal_length():
    _, _, t0 = sim(1)
    _, _, tg = sim(1, effects={"gravity_deformation": 1.0})
    g = np.asarray(tg["g"])
    expected = 10.9816 + 2e-3 + np.dot([5e-4, 1e-3, 2e-3], g)
    assert tg["f"] == pytest.approx(expected, abs=1e-12)
    assert tg["f"] != t0["f"]
    _, _, tt = sim(1, effects={"thermal": 1e-4}, temperature_c=25.0)
    assert tt["f"] == pytest.approx(10.9816 + 1e-4 * 10.0, abs=1e-12)


def test_truth_model_has_no_unknowns():
    m = truth_model({"tx": 0.0, "ty": 0.0, "tz": 9.3, "rx": 0.0, "ry": math.pi, "f": 10.0})
    assert m.free == ()
    # straight down from 9.3 m: the vertex, 9.3 m away
    assert float(m(jnp.array([9.3, 0.0, 1e-9]), jnp.zeros(0), jnp.zeros(2))) == pytest.approx(
        0.0, abs=1e-12)


# ----------------------------------------------------------------------------- parsing


def test_parse_effects():
    eff = parse_effects(["x2=3e-4", "impulsive_shift=0.002", "impulsive_shift.phi_deg=40",
                         "impulsive_shift.direction=0,0,1", "oscillation.axis=y",
                         "panel_offset.panels=17:1e-3,18:-5e-4", "drift.scans=r23c1"])
    assert eff["x2"] == 3e-4
    assert eff["impulsive_shift"] == {"displacement_m": 0.002, "phi_deg": 40.0,
                                      "direction": [0.0, 0.0, 1.0]}
    assert eff["panel_offset"] == {"panels": {17: 1e-3, 18: -5e-4}}
    full = normalize_effects(eff)
    assert full["impulsive_shift"]["cycle"] == 1 and full["oscillation"]["axis"] == "y"
    assert full["panel_offset"]["rms_m"] == 0.0 and full["drift"]["scans"] == ["r23c1"]


@pytest.mark.parametrize("items, match", [
    (["foo=1"], "unknown effect id 'foo'"),
    (["x2"], "expected ID=VALUE"),
    (["x2=abc"], "takes one number"),
    (["x2.k=1"], "takes one number"),
    (["impulsive_shift.when=3"], "unknown key 'when'"),
    (["oscillation.axis=q"], "axis"),
    (["impulsive_shift.cycle=3"], "cycle"),
    (["impulsive_shift.direction=1,2"], "3 numbers"),
    (["panel_offset.panels=a:1"], "cannot parse"),
])
def test_parse_effects_errors(items, match):
    with pytest.raises(EffectError, match=match):
        parse_effects(items)


def test_bad_phi_for_cycle_and_unknown_preset():
    with pytest.raises(EffectError, match="not in cycle 2"):
        sim(2, effects={"impulsive_shift": {"cycle": 2, "phi_deg": 40.0}})
    with pytest.raises(ValueError, match="unknown preset"):
        simulate_scan(preset="nope")


# ----------------------------------------------------------------------------- campaign


def test_simulate_campaign_writes_format_and_truth(tmp_path):
    camp = simulate_campaign(tmp_path / "c", preset="demo", step_rad=0.03, seed=1,
                             positions=[("r23", -35.0, -64.0), ("z1", 0.0, -25.8897)],
                             effects={"thermal": 1e-4})
    assert [s.id for s in camp.scans] == ["r23c1", "r23c2", "z1c1", "z1c2"]
    camp = load_campaign(tmp_path / "c")
    assert camp.scanner.angular_step_rad == 0.03
    truth = json.loads((tmp_path / "c" / "truth.json").read_text())
    assert truth["schema"] == TRUTH_SCHEMA and truth["classes"] == CLASSES
    assert [p["position"] for p in truth["positions"]] == ["r23", "z1"]
    z1 = truth["positions"][1]
    assert z1["elevation_deg"] == pytest.approx(90.0, abs=1e-6)
    for st, meta in zip(truth["scans"], camp.scans):
        data = read_scan(camp, meta)
        tab = pq.read_table(tmp_path / "c" / st["truth_file"]).to_pydict()
        assert len(tab["row"]) == len(data) == st["n_rows"]
        for k in ("tx", "ty", "tz", "rx", "ry", "f", "kappa_rad"):
            assert isinstance(st[k], float)
        assert st["max_abs_condition_m"] < 1e-9
        assert st["temperature_c"] == meta.temperature_c
    # both cycles of a position share the pose; positions differ
    s = truth["scans"]
    assert s[0]["t_tel"] == s[1]["t_tel"] and s[0]["t_tel"] != s[2]["t_tel"]
    assert s[0]["f"] != s[2]["f"]  # thermal: the positions have different temperatures
