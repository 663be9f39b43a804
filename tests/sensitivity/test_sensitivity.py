"""Implicit sensitivities against finite differences (refits with the parameter perturbed)."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hartrao_jax  # noqa: F401  (float64)
from hartrao_jax._config import enable_compilation_cache
from hartrao_jax.campaign._schedule import find_position
from hartrao_jax.fit._fit import fit_campaign, scan_arrays
from hartrao_jax.geometry._geometry import panel_ids, paraboloid_deviation
from hartrao_jax.model._model import make_model
from hartrao_jax.sensitivity._sensitivity import (
    ARCSEC,
    finite_difference,
    refit_with,
    sensitivity,
    sensitivity_table,
    solve_columns,
    write_sensitivity,
)
from hartrao_jax.simulate._simulate import simulate_campaign

enable_compilation_cache()
PARAMS = ("x4", "x6", "x7")


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    out = tmp_path_factory.mktemp("sens")
    pos = []
    for n in ("r23", "r5"):
        p = find_position(n).simulator_position()
        pos.append({k: p[k] for k in ("position", "ha_deg", "dec_deg", "tour")})
    camp = simulate_campaign(out / "camp", preset="clean", positions=pos, step_rad=0.03, seed=2,
                             effects={"x4": 1e-4, "x6": 3e-5, "x7": -4e-5,
                                      "panel_offset": 1e-4})
    start = fit_campaign(camp, "extended", progress=False, batch=True)
    cs = sensitivity(camp, start, PARAMS)
    return camp, start, cs


def test_solve_columns():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    A = A @ A.T + 6 * np.eye(6)
    A = A * np.outer([1, 1e3, 1e-3, 1, 1e2, 1], [1, 1e3, 1e-3, 1, 1e2, 1])
    B = rng.normal(size=(6, 3))
    np.testing.assert_allclose(solve_columns(A, B), np.linalg.solve(A, B), rtol=1e-8)


def test_implicit_derivatives_match_finite_differences(fitted):
    camp, start, cs = fitted
    for s, ss in zip(start.scans, cs.scans):
        fd = finite_difference(camp, s, PARAMS, step=ARCSEC)
        assert fd["names"] == ss.names
        scale = np.max(np.abs(ss.dxdp), axis=1, keepdims=True)
        np.testing.assert_allclose(ss.dxdp / scale, fd["dxdp"] / scale, atol=5e-3)
        i = ss.names.index("f")
        np.testing.assert_allclose(ss.df_dp, fd["dxdp"][i], rtol=1e-2,
                                   atol=1e-3 * np.max(np.abs(ss.df_dp)))
        # sigma0 after a 1 arcsec error: second-order prediction against the refit
        for j in range(len(PARAMS)):
            dp = np.zeros(len(PARAMS))
            dp[j] = ARCSEC
            pred = ss.sigma0_after(dp)
            assert pred == pytest.approx(fd["sigma0_pm"][j][0], rel=1e-6)
            assert pred >= ss.sigma0 - 1e-12  # p sits at its estimate: any error costs
        np.testing.assert_allclose(ss.n_p, 0.0, atol=1e-6 * np.sqrt(np.diag(ss.N)[-3:]).max())


def test_panel_derivatives_match_finite_differences(fitted):
    camp, start, cs = fitted
    s, ss = start.scans[0], cs.scans[0]
    tel = camp.telescope
    l, c = scan_arrays(s.data)
    used = s.used
    X = s.X_tel[used]
    pid = panel_ids(np.hypot(X[:, 0], X[:, 1]), np.mod(np.arctan2(X[:, 1], X[:, 0]), 2 * np.pi),
                    tel.ring_edges_m, tel.panels_per_ring)
    n_panels = int(sum(tel.panels_per_ring))
    ok = pid >= 0
    cnt = np.bincount(pid[ok], minlength=n_panels)

    def panel_means(names, x, p):
        fixed = {k: v for k, v in zip(s.model.fixed_names, np.asarray(s.model.fixed_values))}
        fixed.update(dict(zip(PARAMS, p)))
        m = make_model(names, fixed, aperture_radius_m=tel.diameter_m / 2)
        Xf = jax.vmap(m.telescope_point, in_axes=(0, None, 0))(jnp.asarray(l[used]),
                                                                 jnp.asarray(x),
                                                                 jnp.asarray(c[used]))
        d = np.asarray(paraboloid_deviation(Xf, x[names.index("f")]))
        tot = np.bincount(pid[ok], weights=d[ok], minlength=n_panels)
        return np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)

    j = 0  # x4
    h = ARCSEC
    names, xp, _ = refit_with(camp, s, PARAMS, ss.p + h * np.eye(3)[j])
    _, xm, _ = refit_with(camp, s, PARAMS, ss.p - h * np.eye(3)[j])
    fd = (panel_means(names, xp, ss.p + h * np.eye(3)[j])
          - panel_means(names, xm, ss.p - h * np.eye(3)[j])) / (2 * h)
    live = cnt > 20
    scale = np.nanmax(np.abs(ss.panel_dp[live, j]))
    np.testing.assert_allclose(ss.panel_dp[live, j] / scale, fd[live] / scale, atol=2e-2)


def test_design_one_face_against_two(fitted):
    _, _, cs = fitted
    for s in cs.scans:
        two, one = s.design["two_faces"], s.design["one_face"]
        assert one["n_points"] < two["n_points"]
        # calibration with one face: (much) worse conditioned, f much less precise
        assert one["calibrated"]["condition_number"] > 2 * two["calibrated"]["condition_number"]
        assert one["calibrated"]["sigma_f_m"] > 1.5 * two["calibrated"]["sigma_f_m"]
        assert two["fixed"]["sigma_f_m"] < two["calibrated"]["sigma_f_m"]
    d = cs.design()
    steps = {r["step_rad"]: r["sigma_f_m"] for r in d["step"]["table"]}
    assert steps[0.006] == pytest.approx(2 * steps[0.003])
    assert d["step"]["sigma_f_m_at_reference"] == pytest.approx(
        steps[float(cs.campaign.scanner.angular_step_rad)])


def test_json_table_and_figure(fitted, tmp_path):
    _, _, cs = fitted
    p = write_sensitivity(tmp_path / "sens.json", cs, figures_dir=tmp_path)
    doc = json.loads(p.read_text())
    assert doc["schema"] == "hartrao-sensitivity/1"
    assert doc["params"] == list(PARAMS)
    assert len(doc["scans"]) == 4 and len(doc["positions"]) == 2
    rec = doc["scans"][0]
    assert set(rec["dx_dp"]) == set(PARAMS) and "f" in rec["dx_dp"]["x4"]
    names = rec["correlation_with_params"]["names"]
    C = np.array(rec["correlation_with_params"]["matrix"])
    np.testing.assert_allclose(np.diag(C), 1.0, atol=1e-9)
    assert names[-3:] == list(PARAMS)
    tab = doc["table_per_error"]
    assert tab[0]["x4"]["error_unit"] == "arcsec"
    assert tab[0]["x4"]["delta_f_m"] == pytest.approx(
        doc["positions"][0]["df_dp_m_per_unit"]["x4"] * ARCSEC)
    assert len(doc["positions"][0]["panel_dp_m_per_unit"]["x4"]) == 255
    assert (tmp_path / "sensitivity_f.png").is_file()
    assert "arcsec of x4" in sensitivity_table(cs)


def test_design_splits_sigma_f_into_white_and_surface(fitted):
    """With the two-face fits, sigma(f) = white (+) surface per position, and a finer step
    shrinks only the white part: the step table's two-face sigma falls slower than 1/step."""
    camp, start, _ = fitted
    two = fit_campaign(camp, "extended", progress=False)
    cs = sensitivity(camp, start, PARAMS, panels=False, positions=two.position_fits)
    lim = cs.surface_limited_f()
    assert [r["position"] for r in lim] == [p.position for p in two.position_fits]
    for r, p in zip(lim, two.position_fits):
        assert r["sigma_f_m"] == pytest.approx(float(p.sigma[list(p.names).index("f")]))
        assert 0 < r["sigma_f_white_m"] < r["sigma_f_m"]
        assert r["sigma_f_surface_m"] > 0  # the panels (0.1 mm rms) blur f
        assert r["sigma_f_m"] ** 2 == pytest.approx(
            r["sigma_f_white_m"] ** 2 + r["sigma_f_surface_m"] ** 2)
    rows = {r["step_rad"]: r for r in cs.design()["step"]["table"]}
    assert rows[0.006]["sigma_f_m"] == pytest.approx(2 * rows[0.003]["sigma_f_m"])
    ratio = rows[0.003]["sigma_f_two_face_m"] / rows[0.006]["sigma_f_two_face_m"]
    assert 0.5 < ratio < 1.0
    assert "surface" in sensitivity_table(cs)


def test_two_face_derivatives_match_refits_of_the_position(fitted, tmp_path):
    """The positions' derivatives are those of the two-face adjustment with the surface random
    effect (the estimates ``fit`` reports): central differences of refits with p +- 1 arcsec
    (same points and cells, variance components held) agree, and sensitivity.json says so."""
    from hartrao_jax.sensitivity._sensitivity import position_sensitivity, refit_position_with

    camp, start, _ = fitted
    two = fit_campaign(camp, "extended", progress=False)
    pf = two.position_fits[0]
    ps = position_sensitivity(camp, pf, PARAMS)
    assert ps.names == tuple(n for n in pf.mixed.model.free if n not in PARAMS)
    cols = []
    for j in range(len(PARAMS)):
        e = np.zeros(len(PARAMS))
        e[j] = ARCSEC
        names, xp = refit_position_with(camp, pf, PARAMS, ps.p + e)
        _, xm = refit_position_with(camp, pf, PARAMS, ps.p - e)
        cols.append((xp - xm) / (2 * ARCSEC))
    assert names == ps.names
    fd = np.array(cols).T
    np.testing.assert_allclose(ps.dxdp, fd, atol=0.005 * np.max(np.abs(fd)))
    i_f = ps.names.index("f")
    np.testing.assert_allclose(ps.df_dp, fd[i_f], atol=0.005 * np.max(np.abs(fd[i_f])))
    assert np.all(np.isfinite(ps.panel_dp[pf.surface.n > 0]))
    cs = sensitivity(camp, start, PARAMS, panels=False, design=False,
                     positions=two.position_fits)
    doc = json.loads(write_sensitivity(tmp_path / "s.json", cs).read_text())
    row = next(r for r in doc["positions"] if r["position"] == pf.position)
    assert row["method"].startswith("two-face adjustment")
    assert row["df_dp_m_per_unit"]["x4"] == pytest.approx(float(ps.df_dp[0]))
    assert "df_dp_per_cycle_m_per_unit" in row
