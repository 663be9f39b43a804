"""Batch and joint adjustment of a small simulated campaign (two tours, three positions)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import hartrao_jax  # noqa: F401  (float64)
from hartrao_jax._config import enable_compilation_cache
from hartrao_jax.campaign._schedule import find_position
from hartrao_jax.fit._fit import fit_campaign
from hartrao_jax.fit._joint import (
    LocalBackend,
    ScanProblem,
    bucket_size,
    fit_joint,
    group_of,
    joint_json,
    problems_from_fits,
    residual_update,
    schur_iterate,
    write_joint_fit,
)
from hartrao_jax.fit._results import CampaignFit
from hartrao_jax.simulate._simulate import simulate_campaign

enable_compilation_cache()

TRUTH = {"x4": 1.0e-4, "x6": 3.0e-5, "x7": -4.0e-5}
POSITIONS = ("r23", "r5", "g7")


def _position(name):
    p = find_position(name).simulator_position()
    return {k: p[k] for k in ("position", "ha_deg", "dec_deg", "tour", "temperature_c")}


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    out = tmp_path_factory.mktemp("joint")
    return simulate_campaign(out / "camp", preset="clean", effects=dict(TRUTH),
                             positions=[_position(n) for n in POSITIONS], step_rad=0.03, seed=3)


@pytest.fixture(scope="module")
def start(campaign):
    return fit_campaign(campaign, "extended", progress=False, per_cycle=True)


def test_batch_equals_loop(campaign, start):
    batch = fit_campaign(campaign, "extended", progress=False, batch=True)
    for a, b in zip(start.scans, batch.scans):
        assert a.meta.id == b.meta.id
        np.testing.assert_allclose((a.x - b.x) / a.sigma, 0.0, atol=1e-6)
        np.testing.assert_allclose(a.sigma, b.sigma, rtol=1e-8)
        assert abs(a.sigma0 - b.sigma0) < 1e-9
        assert a.n_points == b.n_points and a.n_rejected == b.n_rejected
        assert abs(a.alignment.kappa_rad - b.alignment.kappa_rad) < 1e-9


def test_one_scan_joint_is_the_per_scan_fit(campaign, start):
    one = CampaignFit(campaign, start.model_names, start.scans[:1])
    s = start.scans[0]
    for shared in ((), ("x4", "x6", "x7")):
        jf = fit_joint(campaign, start=one, shared=shared, group="campaign")
        j = jf.scans[0]
        np.testing.assert_allclose((j.x - s.x) / s.sigma, 0.0, atol=1e-6)
        np.testing.assert_allclose(j.sigma, s.sigma, rtol=1e-7)
        assert abs(jf.sigma0 - s.sigma0) < 1e-9


def test_residual_update_is_the_solver_pass(campaign, start):
    s = start.scans[0]
    prob = problems_from_fits(campaign, [s])[0]
    # at the solution a zero step leaves the residuals where the solver put them
    v, e, omega = residual_update(s.model, prob.l, s.x, prob.sigma_l, prob.c, prob.w, prob.v,
                                  np.zeros(len(s.x)))
    np.testing.assert_allclose(np.asarray(v)[: prob.n][s.used], s.v[s.used], atol=1e-12)
    red = s.n_points - len(s.x)
    assert abs(np.sqrt(float(omega) / red) - s.sigma0) < 1e-8
    np.testing.assert_allclose(np.asarray(e)[: prob.n][s.used] / s.sigma0,
                               s.normalized[s.used], rtol=1e-6, atol=1e-9)


def test_schur_complement_equals_the_dense_joint_matrix(campaign, start):
    fits = start.scans
    backend = LocalBackend(problems_from_fits(campaign, fits))
    names = fits[0].names
    sol = schur_iterate(backend, names, ("x4", "x6", "x7"), ["campaign"] * len(fits),
                        [s.x for s in fits])
    o, c = sol.o_idx, sol.c_idx
    uo, k = len(o), len(c)
    S = len(fits)
    D = np.zeros((S * uo + k, S * uo + k))
    for s, N in enumerate(sol.N):
        sl = slice(s * uo, (s + 1) * uo)
        D[sl, sl] = N[np.ix_(o, o)]
        D[sl, S * uo:] = N[np.ix_(o, c)]
        D[S * uo:, sl] = N[np.ix_(c, o)]
        D[S * uo:, S * uo:] += N[np.ix_(c, c)]
    d = 1 / np.sqrt(np.diag(D))
    Q = np.linalg.inv(D * d[:, None] * d[None, :]) * d[:, None] * d[None, :]
    np.testing.assert_allclose(sol.Q_cc["campaign"], Q[S * uo:, S * uo:], rtol=1e-7)
    for s in range(S):
        sl = slice(s * uo, (s + 1) * uo)
        np.testing.assert_allclose(sol.Q_oo[s], Q[sl, sl], rtol=1e-6,
                                   atol=1e-9 * np.max(np.abs(Q[sl, sl])))
        np.testing.assert_allclose(sol.Q_oc[s], Q[sl, S * uo:], rtol=1e-6,
                                   atol=1e-9 * np.max(np.abs(Q[sl, S * uo:])))
    assert sol.converged


def test_joint_is_consistent_and_more_precise(campaign, start):
    jf = fit_joint(campaign, start=start, group="campaign")
    assert jf.solution.converged
    est = jf.shared_estimates()["campaign"]
    per = {s.meta.id: s for s in start.scans}
    for n in ("x4", "x6", "x7"):
        v, sj = est[n]
        assert abs(v - TRUTH[n]) < 4 * sj, (n, v, sj)
        for s in start.scans:
            vs, ss = s.estimates[n]
            assert sj < ss
            assert abs(vs - v) < 4 * np.sqrt(ss**2 - sj**2), (s.meta.id, n)
    gain = jf.precision_gain()
    for n in ("x4", "x6", "x7"):
        assert gain["shared"][n]["campaign"]["gain"] < 0.8
    assert gain["f"]["gain_median"] < 1.0
    for s in jf.scans:
        assert s.estimates["f"][1] <= per[s.meta.id].estimates["f"][1] * (1 + 1e-9)
    corr = jf.correlation_drop()["max_abs_corr_f_calibration"]
    assert corr["joint"]["median"] < corr["per_scan"]["median"]
    # focal lengths agree with the per-scan ones within the combined sigma
    for s in jf.scans:
        p = per[s.meta.id]
        d = s.value("f") - p.value("f")
        assert abs(d) < 4 * np.sqrt(max(p.estimates["f"][1] ** 2 - s.estimates["f"][1] ** 2,
                                        1e-14))


def test_night_groups_and_fit_json(campaign, start, tmp_path):
    jf = fit_joint(campaign, start=start, group="night")
    assert set(jf.groups) == {"red", "green"}
    assert group_of(campaign.scan("g7c1"), "night") == "green"
    p = write_joint_fit(tmp_path / "joint", jf)
    doc = json.loads(p.read_text())
    assert doc["schema"] == "hartrao-fit/1"
    assert set(doc["shared"]) == {"x4", "x6", "x7"}
    for n, e in doc["shared"].items():
        assert {"value", "sigma", "unit", "by_group"} <= set(e)
        assert set(e["by_group"]) == {"red", "green"}
        assert e["by_group"]["red"]["gain"] < 1.0
    for rec in doc["scans"]:
        assert "x4" not in rec["estimates"] and "f" in rec["estimates"]
        assert rec["shared_group"] in ("red", "green")
    assert (tmp_path / "joint" / "residuals" / "r23c1.parquet").is_file()
    j = doc["joint"]
    assert j["correlation"]["joint"]["median"] < j["correlation"]["per_scan"]["median"]
    assert joint_json(jf)["shared"]["x4"]["value"] == pytest.approx(doc["shared"]["x4"]["value"])


def test_bad_shared_parameters(campaign, start):
    with pytest.raises(ValueError, match="object parameters"):
        fit_joint(campaign, start=start, shared=("f",))
    with pytest.raises(ValueError, match="not in the model"):
        fit_joint(campaign, start=start, shared=("x2",))
    with pytest.raises(ValueError, match="group"):
        fit_joint(campaign, start=start, group="week")


def test_bucket_size():
    for n in (1, 100, 4096, 4097, 10_000, 123_457, 13_000_000):
        b = bucket_size(n)
        assert b >= n and b - n <= max(4096, b // 8)
    assert bucket_size(10_100) == bucket_size(10_500)  # similar scans share one shape


def test_scan_problem_padding(start, campaign):
    s = start.scans[0]
    pr = ScanProblem.from_fit(s, np.array([8e-4, 2e-5, 2e-5]), len(s.data) + 100)
    assert len(pr.l) == len(s.data) + 100 and pr.n == len(s.data)
    assert np.all(pr.w[pr.n:] == 0) and pr.n_used == s.n_points
