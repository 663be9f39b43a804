"""Measurement plan, gravity model over the sky (regression, test, sky map, Ruze)."""

from __future__ import annotations

import datetime as dt
import json
import math

import numpy as np
import pytest

import hartrao_jax  # noqa: F401  (float64)
from hartrao_jax._config import enable_compilation_cache
from hartrao_jax.campaign._schedule import (
    LATITUDE_DEG,
    TOURS,
    campaign_plan,
    check_plan,
    elevation_deg,
    find_position,
    plan_positions,
    tour_plan,
    within_limits,
)
from hartrao_jax.geometry._geometry import gravity_in_telescope, telescope_axes_hadec, zernike
from hartrao_jax.physics._catalog import DEFAULT_ZERNIKE_MODES
from hartrao_jax.surface._gravity import (
    ScanSample,
    gravity_grid,
    gravity_model,
    ruze_gain,
    samples_from_fit,
    weighted_lsq,
    write_gravity,
    zernike_np,
    zernike_projection,
)

enable_compilation_cache()


# --------------------------------------------------------------------------------------------
# the measurement plan
# --------------------------------------------------------------------------------------------


def test_plan_follows_the_paper():
    plan = campaign_plan()
    assert len(plan) == 88
    assert check_plan(plan) == []
    for tour in TOURS:
        ps = tour_plan(tour)
        assert 19 <= len(ps) <= 24
        assert sum(p.zenith for p in ps) == 2
        assert [p.position for p in ps] == [f"{tour[0]}{i}" for i in range(1, len(ps) + 1)]
        # 18:00-23:00 local (UTC+2), one night per tour, temperatures falling
        assert ps[0].start_c1 >= dt.datetime.combine(ps[0].start_c1.date(), dt.time(16),
                                                     tzinfo=dt.UTC)
        assert ps[-1].start_c2 + dt.timedelta(minutes=3) <= dt.datetime.combine(
            ps[0].start_c1.date(), dt.time(21), tzinfo=dt.UTC)
        assert all(a.start_c2 > a.start_c1 for a in ps)
        assert all(b.start_c1 > a.start_c2 for a, b in zip(ps, ps[1:]))
        temps = [p.temperature_c1 for p in ps]
        assert temps == sorted(temps, reverse=True) and 11 <= temps[-1] < temps[0] <= 21
    assert len({p.start_c1.date() for p in plan}) == 4
    assert (find_position("r23").ha_deg, find_position("r23").dec_deg) == (-35.0, -64.0)
    assert (find_position("r5").ha_deg, find_position("r5").dec_deg) == (35.0, -25.8897)
    for p in plan:
        assert abs(p.ha_deg) <= 88 and -89 <= p.dec_deg <= 45 and within_limits(p.ha_deg,
                                                                                 p.dec_deg)
        assert p.zenith == (p.ha_deg == 0 and p.dec_deg == LATITUDE_DEG)
    # the sky is covered: elevations from near the horizon to the zenith, both sides
    el = np.array([p.elevation_deg for p in plan])
    assert el.min() < 20 and el.max() == pytest.approx(90.0)
    assert min(p.ha_deg for p in plan) <= -85 and max(p.ha_deg for p in plan) >= 85


def test_elevation_formula_matches_the_geometry():
    from hartrao_jax.geometry._geometry import elevation_of

    for h, d in ((0, LATITUDE_DEG), (35, -25.8897), (-35, -64), (80, -10), (0, 45), (60, -89)):
        F = telescope_axes_hadec(math.radians(h), math.radians(d), math.radians(LATITUDE_DEG))
        assert elevation_deg(h, d) == pytest.approx(math.degrees(float(elevation_of(F))),
                                                    abs=1e-5)  # asin near 90 deg


def test_presets_use_the_plan(tmp_path):
    from hartrao_jax.simulate._simulate import PRESETS, simulate_campaign

    assert len(PRESETS["campaign"].positions) == 88
    assert len(PRESETS["tour-red"].positions) == 23
    assert PRESETS["campaign"].step_rad == pytest.approx(0.02)
    pos = plan_positions(["red"])[4:5]  # r5: start times and temperatures per cycle
    camp = simulate_campaign(tmp_path / "c", preset="tour-red", positions=pos, step_rad=0.1)
    m1, m2 = camp.scan("r5c1"), camp.scan("r5c2")
    p = find_position("r5")
    assert (m1.start, m2.start) == (p.start_c1, p.start_c2)
    assert (m1.temperature_c, m2.temperature_c) == (p.temperature_c1, p.temperature_c2)
    assert m1.tour == "red"


# --------------------------------------------------------------------------------------------
# building blocks
# --------------------------------------------------------------------------------------------


def test_gravity_grid_and_zernike_match_the_jax_versions():
    ha, dec = np.array([-80.0, 0.0, 35.0]), np.array([-89.0, LATITUDE_DEG, 45.0])
    G, el = gravity_grid(ha, dec, LATITUDE_DEG)
    for i, d in enumerate(dec):
        for k, h in enumerate(ha):
            F = telescope_axes_hadec(math.radians(h), math.radians(d), math.radians(LATITUDE_DEG))
            np.testing.assert_allclose(G[i, k], np.asarray(gravity_in_telescope(F)), atol=1e-12)
    rng = np.random.default_rng(0)
    u, psi = rng.random(50), rng.uniform(0, 2 * np.pi, 50)
    for j in range(1, 16):
        np.testing.assert_allclose(zernike_np(j, u, psi), np.asarray(zernike(j, u, psi)),
                                   atol=1e-12)


def test_zernike_projection_recovers_modes_on_the_annulus():
    rng = np.random.default_rng(1)
    n = 40000
    rho = np.sqrt(rng.uniform(1.6**2, 12.95**2, n))
    psi = rng.uniform(0, 2 * np.pi, n)
    X = np.column_stack([rho * np.cos(psi), rho * np.sin(psi), rho**2 / 43.9])
    a = {5: 4e-5, 6: -1e-4, 8: 2e-5, 11: 3e-5}
    dev = 1e-4 + 2e-5 * zernike_np(2, rho / 12.95, psi)  # piston, tilt: nuisance
    for j, v in a.items():
        dev = dev + v * zernike_np(j, rho / 12.95, psi)
    dev = dev + rng.normal(size=n) * 1e-4
    modes = (4, 5, 6, 7, 8, 11)
    coef, sig, rms = zernike_projection(X, dev, 12.95, modes)
    truth = np.array([a.get(j, 0.0) for j in modes])
    assert np.all(np.abs(coef - truth) < 5 * sig)
    assert rms == pytest.approx(1e-4, rel=0.05)


def _samples(c, zern_C=None, noise=2e-5, seed=0, positions=None):
    """Synthetic per-scan samples on plan positions: f = f0 + c . g (+ noise)."""
    rng = np.random.default_rng(seed)
    plan = positions or campaign_plan()
    out = []
    for p in plan:
        F = telescope_axes_hadec(math.radians(p.ha_deg), math.radians(p.dec_deg),
                                 math.radians(LATITUDE_DEG))
        g = np.asarray(gravity_in_telescope(F))
        f = 10.9816 + float(np.dot(c, g)) + rng.normal() * noise
        out.append(ScanSample(p.position + "c1", p.position, g, f, noise, p.ha_deg, p.dec_deg,
                              p.elevation_deg, p.temperature_c1))
    return out


def test_regression_and_the_transverse_test():
    c = np.array([5e-4, 1e-3, 2e-3])
    gm = gravity_model(_samples(c), modes=())
    np.testing.assert_allclose(gm.c, c, atol=5 * gm.focal.sigma[1:].max())
    assert gm.test["p_value_F"] < 1e-6 and gm.test["p_value_chi2"] < 1e-6
    assert 0.5 < gm.focal.scale < 1.6  # the sigmas are right
    # g_z only: the nested test does not reject
    gz = gravity_model(_samples(np.array([0.0, 0.0, 2e-3]), seed=4), modes=())
    assert gz.test["p_value_F"] > 1e-3
    assert abs(gz.focal_gz.beta[1] - 2e-3) < 5 * gz.focal_gz.sigma[1]
    # prediction and sky map
    g0 = np.array([0.0, 0.0, -1.0])
    assert gm.predict_f(g0) == pytest.approx(gm.f0 - gm.c[2])
    sky = gm.sky_map(step_deg=10.0)
    assert sky["f_m"].shape == (len(sky["dec_deg"]), len(sky["ha_deg"]))
    below = sky["elevation_deg"] < 0
    assert below.any() and np.all(np.isnan(sky["f_m"][below]))
    assert np.all(np.isfinite(sky["f_m"][~below]))


def test_ruze():
    lam = 0.013
    assert ruze_gain(lam / (4 * np.pi), lam) == pytest.approx(math.exp(-1))
    assert ruze_gain(0.0, lam) == 1.0
    assert ruze_gain(3e-4, 0.013) < ruze_gain(3e-4, 0.025) < 1


# --------------------------------------------------------------------------------------------
# recovery on a simulated multi-position campaign (joint calibration)
# --------------------------------------------------------------------------------------------

DF_DG = (5e-4, 1e-3, 2e-3)
# modes (4, 5, 6, 7, 8, 11): astigmatism only (coma is taken up by the pose, defocus by f)
ZPG = ((0, 0, 0), (0, 1e-4, 0), (1.5e-4, -1.5e-4, 0), (0, 0, 0), (0, 0, 0), (0, 0, 0))
NAMES = ("r1", "r5", "r10", "r23", "g5", "b9", "m5")


@pytest.fixture(scope="module")
def gravity_fit(tmp_path_factory):
    from hartrao_jax.fit._fit import fit_campaign
    from hartrao_jax.fit._joint import fit_joint, write_joint_fit
    from hartrao_jax.simulate._simulate import simulate_campaign

    out = tmp_path_factory.mktemp("gravity")
    pos = []
    for n in NAMES:
        p = find_position(n).simulator_position()
        pos.append({k: p[k] for k in ("position", "ha_deg", "dec_deg", "tour")})
    camp = simulate_campaign(
        out / "camp", preset="clean", positions=pos, step_rad=0.03, seed=5,
        effects={"x4": 1e-4, "x6": 3e-5, "x7": -4e-5,
                 "gravity_deformation": {"df_dg_m": DF_DG, "zernike_per_g_m": ZPG}})
    start = fit_campaign(camp, "extended", progress=False, batch=True)
    jf = fit_joint(camp, start=start, group="campaign")
    write_joint_fit(out / "joint", jf)
    return camp, start, jf, out / "joint"


def test_mode_response_explains_the_focal_length_errors(gravity_fit):
    """The scans' f take up the gravity-dependent astigmatism (far beyond their sigmas, by an
    amount that depends on the scan's geometry); mode_response predicts by how much."""
    camp, start, jf, _ = gravity_fit
    truth = {s["id"]: s for s in json.loads((camp.root / "truth.json").read_text())["scans"]}
    modes = DEFAULT_ZERNIKE_MODES
    for src, raw_min in ((start, 3.0), (jf, 1.5)):  # per-scan calibration, shared calibration
        ss = samples_from_fit(src, modes=modes)
        err = np.array([s.f - truth[s.id]["f"] for s in ss])
        sig = np.array([s.sigma_f for s in ss])
        a = np.array([[truth[s.id]["zernike"].get(f"zern_{j}", 0.0) for j in modes] for s in ss])
        pred = np.array([s.leak @ ak for s, ak in zip(ss, a)])
        rms = lambda z: float(np.sqrt(np.mean(z * z)))  # noqa: E731
        assert rms(err / sig) > raw_min  # the effect is real ...
        assert rms((err - pred) / sig) < 1.6  # ... and explained
        k6 = modes.index(6)
        assert np.median([s.retention[k6, k6] for s in ss]) > 0.2  # astigmatism is visible


def test_gravity_coefficients_recovered(gravity_fit):
    """df/dg within 3 sigma and a variance factor near 1, from the joint fit and from the
    per-scan fits. Without the mode take-up (the old regression of f alone) the per-scan fits
    gave chi2/dof 35 and the joint one 8 (df/dg_x 4 sigma low): both fail here."""
    camp, start, jf, _ = gravity_fit
    truth = np.array(DF_DG)
    for src in (jf, start):
        gm = gravity_model(src)
        assert set(gm.corrected_modes) >= {5, 6}
        sig = gm.focal.sigma_scaled[1:4]
        assert np.all(np.abs(gm.c - truth) < 3 * sig), (gm.c, truth, sig)
        assert gm.focal.scale < 3.0, gm.focal.scale
    raw = gravity_model(jf, correct_leakage=False)
    assert raw.corrected_modes == () and raw.focal.scale > 4.0  # the bias the test guards
    # the joint fit's campaign_fit() carries the shared calibration: the same model
    via_cf = gravity_model(jf.campaign_fit())
    assert via_cf.corrected_modes == gravity_model(jf).corrected_modes
    np.testing.assert_allclose(via_cf.c, gravity_model(jf).c, rtol=1e-10)
    gm = gravity_model(jf)
    assert gm.test["p_value_F"] < 0.05  # the transverse terms are there
    C = gm.C
    k5, k6 = gm.modes.index(5), gm.modes.index(6)
    zs = np.array([z.sigma_scaled[1:4] for z in gm.zernike])
    np.testing.assert_allclose(C[k6], ZPG[2], atol=float(4 * zs[k6].max() + 1.5e-5))
    np.testing.assert_allclose(C[k5], ZPG[1], atol=float(4 * zs[k5].max() + 1.5e-5))
    eff = gm.effect_parameters()
    assert eff["zernike_modes"] == list(gm.modes) and len(eff["df_dg_m"]) == 3


def test_gravity_json_and_figures(gravity_fit):
    _, _, _, results = gravity_fit
    p, gm = write_gravity(results, step_deg=6.0)
    doc = json.loads(p.read_text())
    assert doc["schema"] == "hartrao-gravity/1"
    assert doc["n_positions"] == len(NAMES)
    assert set(doc["focal_length"]["coefficients"]) == {"f0", "gx", "gy", "gz"}
    t = doc["test_transverse"]
    assert 0.0 <= t["p_value_F"] <= 1.0 and t["F_dof"] == [2, len(NAMES) - 4]
    sky = doc["sky_map"]
    assert "ruze_gain_2.5cm" in sky and "ruze_gain_1.3cm" in sky
    assert sky["ruze_gain_1.3cm_range"]["min"] <= sky["ruze_gain_2.5cm_range"]["min"] <= 1.0
    for f in doc["figures"]:
        assert (results / f).is_file()
    # the same model from the directory as from memory
    np.testing.assert_allclose(gm.c, np.array(list(doc["focal_length"]["df_dg_m"].values())))


def test_cli_schedule_and_gravity(gravity_fit, tmp_path):
    from click.testing import CliRunner

    import hartrao_jax.cli._campaign  # noqa: F401  (registers the commands)
    from hartrao_jax.cli import main

    r = CliRunner().invoke(main, ["schedule", "--json", str(tmp_path / "plan.json")])
    assert r.exit_code == 0, r.output
    assert "| r23 | red | -35.0 | -64.00 |" in r.output
    plan = json.loads((tmp_path / "plan.json").read_text())
    assert len(plan["positions"]) == 88
    _, _, _, results = gravity_fit
    r = CliRunner().invoke(main, ["gravity", str(results), "--out", str(tmp_path / "g"),
                                  "--grid-step", "10", "--no-figures"])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "g" / "gravity.json").read_text())
    assert doc["schema"] == "hartrao-gravity/1"
    r = CliRunner().invoke(main, ["gravity", str(results), "--out", str(tmp_path / "g2"),
                                  "--temperature", "--no-figures", "--grid-step", "10"])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "g2" / "gravity.json").read_text())
    assert "dT" in doc["focal_length"]["coefficients"]
    (tmp_path / "empty").mkdir()
    r = CliRunner().invoke(main, ["gravity", str(tmp_path / "empty")])
    assert r.exit_code == 2 and "fit.json" in r.output


def test_weighted_lsq_with_shared_errors_is_the_generalised_lsq():
    """Positions that see the same panels share the surface's errors: with ``cov_y`` the fit is
    the generalised LS (estimates, covariance, chi2); an error common to all rows moves only
    the intercept and leaves chi2 unchanged."""
    rng = np.random.default_rng(0)
    n = 9
    A = np.column_stack([np.ones(n), rng.normal(size=(n, 3))])
    y = rng.normal(size=n)
    sw, s = rng.uniform(0.5, 1.5, n), rng.uniform(0.5, 2.0, n)
    C = np.diag(sw**2) + np.outer(s, s)
    Ci = np.linalg.inv(C)
    N = A.T @ Ci @ A
    beta = np.linalg.solve(N, A.T @ Ci @ y)
    r = y - A @ beta
    names = ("f0", "gx", "gy", "gz")
    fit = weighted_lsq(A, y, np.sqrt(np.diag(C)), names, C)
    np.testing.assert_allclose(fit.beta, beta, rtol=1e-10)
    np.testing.assert_allclose(fit.cov, np.linalg.inv(N), rtol=1e-10)
    assert fit.chi2 == pytest.approx(float(r @ Ci @ r), rel=1e-10)
    C1 = np.eye(n) + 4.0
    same = weighted_lsq(A, y + 3.0, np.full(n, np.sqrt(5.0)), names, C1)
    base = weighted_lsq(A, y, np.full(n, np.sqrt(5.0)), names, C1)
    np.testing.assert_allclose(same.beta[1:], base.beta[1:], atol=1e-12)
    assert same.chi2 == pytest.approx(base.chi2)
