"""Discrepancy engine: concealed effects are found, located and modelled, the fit improves;
clean data (with panel deviations) give no instrument or motion finding; confounded parameters
never appear among the findings; the loop is deterministic for a seed.

Coarse grids (0.02 rad, ~16k points per cycle) keep this fast; the amplitudes are scaled to the
smaller number of points (the proof in ``_prove.py`` uses 0.01 rad and smaller amplitudes).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hartrao_jax._config import enable_compilation_cache
from hartrao_jax.diagnose._explain import _log_sf
from hartrao_jax.diagnose._find import _box_search, _periodogram
from hartrao_jax.diagnose._result import DIAGNOSIS_SCHEMA, write_json
from hartrao_jax.diagnose._state import DiagnoseConfig, _Context
from hartrao_jax.diagnose._thermal import _thermal
from hartrao_jax.prove._prove import (
    MULTI_POSITIONS,
    PANELS,
    Case,
    _intensity_range_error,
    score,
)
from hartrao_jax.report._diagnosis import diagnose_with_report as diagnose  # report_dir
from hartrao_jax.simulate._simulate import simulate_campaign

STEP = 0.02


@pytest.fixture(scope="module", autouse=True)
def _cache():
    enable_compilation_cache()


def _campaign(tmp_path_factory, name, effects, seed=3, positions=None, post=None):
    out = tmp_path_factory.mktemp(name)
    simulate_campaign(out, preset="clean", effects={**PANELS, **effects}, seed=seed,
                      step_rad=STEPS.get(name, STEP), positions=positions)
    if post is not None:
        post(out, seed)
    return out


def _run(out, **kw):
    diag = diagnose(out, **kw)
    doc = diag.to_json()
    truth = json.loads((out / "truth.json").read_text())
    return diag, doc, truth


# ------------------------------------------------------------------------------ statistics


def test_log_sf_matches_scipy_and_extends_the_tail():
    from scipy import stats

    for T, k in [(3.0, 1), (40.0, 3), (300.0, 32), (700.0, 4)]:
        assert _log_sf(T, k) == pytest.approx(stats.chi2.logsf(T, k), rel=1e-6, abs=1e-9)
    far = [_log_sf(T, 3) for T in (2000.0, 5000.0, 1e5)]
    assert all(np.isfinite(far)) and far[0] > far[1] > far[2]
    assert _log_sf(5000.0, 3) == pytest.approx(-2500.0 + 0.5 * math.log(2500.0)
                                               - math.lgamma(1.5), rel=1e-3)


def _bins(rng, B=200, q=5):
    """Per-bin normal equations of random probe columns (translation 3, rotation 2)."""
    A = rng.normal(size=(B, 40, q))
    N = np.einsum("bki,bkj->bij", A, A)
    return A, N


def test_box_search_finds_a_planted_window():
    rng = np.random.default_rng(0)
    A, N = _bins(rng)
    d = np.zeros((200, 5))
    d[120:135, :3] = [0.0, 0.0, 0.4]  # a jump of the translation in bins 120..134
    w = np.einsum("bki,bi->bk", A, d) + rng.normal(size=(200, 40))  # misclosures
    n = np.einsum("bki,bk->bi", A, w)
    edges = np.linspace(0.0, 20.0, 201)
    i, j, T, profile, _ = _box_search(edges, N, n, DiagnoseConfig())
    assert (i, j) == (120, 135)
    assert T > 50  # the planted energy is 15 bins x 40 points x 0.4^2 = 96


def test_box_search_statistic_of_every_window_equals_its_solve():
    """Each window's statistic (the profile, the best window and its value) as the score test
    written with the window's own sums and a solve: ``S_W = N_W - N_W N^-1 N_W``."""
    rng = np.random.default_rng(3)
    B = 60
    A, N = _bins(rng, B=B)
    N[17:19] = 0.0  # bins without points: windows of those alone hold no statistic
    n = np.einsum("bki,bk->bi", A, rng.normal(size=(B, 40)))
    n[17:19] = 0.0
    cfg = DiagnoseConfig()
    i, j, T, profile, Lmax = _box_search(np.linspace(0.0, 6.0, B + 1), N, n, cfg)
    assert Lmax == int(cfg.max_window_fraction * B)
    Ninv = np.linalg.pinv(N[:, :3, :3].sum(0))
    eye = 1e-9 * np.trace(N[:, :3, :3].sum(0)) / 3 * np.eye(3)
    want = np.zeros((Lmax, B))
    for L in range(1, Lmax + 1):
        for k in range(B - L + 1):
            NW, nW = N[k:k + L, :3, :3].sum(0), n[k:k + L, :3].sum(0)
            if np.trace(NW) > 0:
                want[L - 1, k] = nW @ np.linalg.solve(NW - NW @ Ninv @ NW + eye, nW)
    np.testing.assert_allclose(profile, want.max(0), rtol=1e-9, atol=1e-12)
    L, k = divmod(int(np.argmax(want)), B)
    assert (i, j) == (k, k + L + 1)
    assert T == pytest.approx(want.max(), rel=1e-9)


def test_periodogram_finds_a_planted_period():
    rng = np.random.default_rng(1)
    A, N = _bins(rng, B=400)
    edges = np.linspace(0.0, 40.0, 401)
    t = 0.5 * (edges[:-1] + edges[1:])
    d = np.zeros((400, 5))
    d[:, 3] = 0.3 * np.sin(2 * np.pi * t / 2.5 + 0.4)
    w = np.einsum("bki,bi->bk", A, d) + rng.normal(size=(400, 40))
    n = np.einsum("bki,bk->bi", A, w)
    periods, T = _periodogram(edges, N, n, DiagnoseConfig())
    assert periods[np.argmax(T)] == pytest.approx(2.5, rel=0.02)


# ------------------------------------------------------------------------ concealed effects

# the default suite: x2, impulsive shift, oscillation, panel offsets, one unexplained
FAST = {
    # with x10 and range_scale, which are inseparable from the object parameters
    "x2": Case("x2", "x2", {"x2": 3e-4, "x10": 1.5e-3, "range_scale": 5e-5}, 3e-4,
               "transit offset 0.3 mm"),
    "impulsive_shift": Case(
        "impulsive_shift", "impulsive_shift",
        {"impulsive_shift": {"displacement_m": 1.2e-3, "phi_deg": 40.0, "duration_s": 1.0}},
        1.2e-3, "1.2 mm jump for 1 s in cycle 1"),
    "oscillation": Case("oscillation", "oscillation",
                        {"oscillation": {"amplitude_rad": 8e-5, "period_s": 1.1}}, 8e-4,
                        "gimbal swing 16 arcsec"),
    "panel_offset": Case("panel_offset", "panel_offset", {"panel_offset": {"rms_m": 2e-4}},
                         2e-4, "panel offsets 0.2 mm rms"),
    "unexplained_intensity": Case(
        "unexplained_intensity", "unexplained", {}, 5e-4, "range walk with intensity",
        post=lambda out, seed: _intensity_range_error(out, seed, 1e-3)),
}
SLOW = {
    "x1n": Case("x1n", "x1n", {"x1n": 8e-4}, 4e-4, ""),
    "x1z": Case("x1z", "x1z", {"x1z": 5e-3}, 2e-3, ""),
    "x3": Case("x3", "x3", {"x3": 5e-3}, 1.5e-3, ""),
    "x5n": Case("x5n", "x5n", {"x5n": 8e-5}, 8e-4, ""),
    "x8x": Case("x8x", "x8x", {"x8x": 1.2e-4}, 1.2e-3, ""),
    "drift": Case("drift", "drift", {"drift": {"rate_m_s": 4e-4,
                                                "direction": (0.3, 0.5, 1.0)}}, 2.2e-3, ""),
    "gravity_deformation": Case("gravity_deformation", "gravity_deformation",
                                {"gravity_deformation": {"scale": 3.0}}, 4.5e-4, "",
                                MULTI_POSITIONS),
    # a local bump needs points: at 0.02 rad its core is a few points, rejected as outliers
    "unexplained_bump": Case("unexplained_bump", "unexplained",
                             {"unexplained": {"amplitude_m": 3e-3, "width_m": 0.3}}, 3e-3, ""),
}
# a local bump needs points: at 0.02 rad (3.2e4 points in both cycles) a 1.5 mm bump 0.6 m wide
# under 0.15 mm panels has |t| about 7 against a bar of about 8.5 (p < 1e-3 of the maximum over
# some 500 local structures): found in a third of the seeds. At 0.01 rad (1.3e5 points, the
# proof's resolution) its |t| is about 14.
STEPS = {"unexplained_bump": 0.01, "bump0.0015": 0.01}
PARAMS = [pytest.param(c, id=k) for k, c in FAST.items()] + [
    pytest.param(c, id=k, marks=pytest.mark.slow) for k, c in SLOW.items()]


@pytest.fixture(scope="module")
def x2_run(tmp_path_factory):
    """x2 concealed among x10 and range_scale (confounded), with a report."""
    case = FAST["x2"]
    out = _campaign(tmp_path_factory, case.name, case.effects)
    report = tmp_path_factory.mktemp("report")
    return (*_run(out, report_dir=report), report)


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    out = _campaign(tmp_path_factory, "clean", {}, seed=5)
    return (out, *_run(out))


@pytest.mark.parametrize("case", PARAMS)
def test_concealed_effect_is_found_located_and_improves_the_fit(tmp_path_factory, request, case):
    if case.name == "x2":
        diag, doc, truth, _ = request.getfixturevalue("x2_run")
    else:
        out = _campaign(tmp_path_factory, case.name, case.effects, positions=case.positions,
                        post=case.post)
        diag, doc, truth = _run(out)
    sc = score(case, doc, truth, seed=3, time_s=0.0)
    assert sc.found, [f["effect"] for f in doc["findings"]]
    assert sc.located in (True, None), sc.detail
    assert sc.improved, doc["findings"]
    if sc.estimate_ok is not None:
        assert sc.estimate_ok, sc.detail
    assert not sc.false, sc.false
    assert doc["sigma0_final"] < doc["sigma0_start"]
    # every finding: one plain sentence and the schema's keys
    for f in doc["findings"]:
        assert f["explanation"] and "\n" not in f["explanation"]
        for k in ("effect", "family", "scans", "where", "estimate", "statistic", "dof",
                  "p_value", "sigma0_before", "sigma0_after", "rms_before_m", "rms_after_m"):
            assert k in f


def test_clean_data_with_panels_have_no_instrument_or_motion_finding(clean_run):
    out, diag, doc, truth = clean_run
    fams = {f["family"] for f in doc["findings"]}
    assert not fams & {"instrument", "motion"}, doc["findings"]
    assert [f["effect"] for f in doc["findings"]] == ["panel_offset"]
    assert doc["schema"] == DIAGNOSIS_SCHEMA
    assert doc["final_model"][-1] == "panel_offset"


def test_confounded_parameters_are_never_findings(x2_run, tmp_path):
    diag, doc, truth, report = x2_run
    found = {f["effect"] for f in doc["findings"]}
    conf = {c["effect"]: c for c in doc["confounded"]}
    assert {"x10", "range_scale"} <= set(conf)
    assert not found & set(conf)
    assert "x2" in found
    assert conf["range_scale"]["correlation"] > 0.9995
    assert {"tz"} & set(conf["x10"]["with"]) and {"f", "tz"} & set(conf["range_scale"]["with"])
    # the written document and the report
    p = write_json(diag, tmp_path / "d.json")
    back = json.loads(p.read_text())
    assert back["schema"] == DIAGNOSIS_SCHEMA and back["findings"][0]["effect"]
    assert (report / "index.html").exists()
    assert list(report.glob("step1_*_maps.png"))


def test_the_loop_is_deterministic(clean_run):
    out, diag, a, truth = clean_run
    b = diagnose(out).to_json()
    a = {k: v for k, v in a.items() if k != "timing_s"}
    b.pop("timing_s")
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _fake_scans(n_pos, df_dT, seed=0, sigma_f=5e-5):
    """Per-scan focal lengths of a campaign: f = f0 + c.g + df_dT (T - 15) + noise."""
    from types import SimpleNamespace

    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_pos):
        el = rng.uniform(0.3, 1.5)
        az = rng.uniform(0, 2 * np.pi)
        g = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
        T = 18.0 - 0.4 * i + rng.normal(0, 0.3)
        for cyc in (1, 2):
            f = 10.9816 + np.array([5e-4, 1e-3, 2e-3]) @ g + df_dT * (T - 15.0) \
                + rng.normal(0, sigma_f)
            out.append(SimpleNamespace(
                id=f"p{i}c{cyc}", meta=SimpleNamespace(temperature_c=T, position=f"p{i}"),
                names=("tx", "f"), x=np.array([0.0, f]), cov=np.diag([1e-8, sigma_f**2]),
                converged=True, g=g, omega=100.0, redundancy=100, used=np.ones(4, bool),
                mismatch_m=np.full(4, 1e-4)))
    return out


def test_thermal_from_the_focal_lengths_across_positions():
    """f against temperature with the gravity terms estimated: found with its estimate on 23
    positions, nothing without it, and confounded with gravity on a few positions."""
    ctx = _Context.__new__(_Context)
    ctx.config = DiagnoseConfig()
    kind, f = _thermal(ctx, _fake_scans(23, 1.3e-4), 40)
    assert kind == "finding" and f.effect == "thermal"
    est = f.estimate["df_dT_m_per_K"]
    assert abs(est["value"] - 1.3e-4) < 3 * est["sigma"]
    assert f.where["covariate"] == "temperature" and f.extra["gravity_terms"]
    for seed in range(5):
        assert _thermal(ctx, _fake_scans(23, 0.0, seed=seed), 40) is None
    kind, c = _thermal(ctx, _fake_scans(4, 1.3e-4), 40)
    assert kind == "confounded" and c["with"] == ["gravity"]


# ------------------------------------------------------- local deformation, covariates, one face


def _cyclic_range_error(out, seed, amp=3e-4, period=1.2):
    """A phase rangefinder's cyclic error: ``amp sin(2 pi r / period)`` added to the ranges."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    for f in sorted((out / "scans").glob("*.parquet")):
        t = pq.read_table(f)
        cols = {n: t.column(n).to_numpy() for n in t.column_names}
        cols["range_m"] = cols["range_m"] + amp * np.sin(2 * np.pi * cols["range_m"] / period
                                                         + 0.3)
        pq.write_table(pa.table(cols, schema=t.schema), f)


@pytest.mark.slow
def test_cyclic_range_error_is_located_on_range_not_incidence_or_intensity(tmp_path_factory):
    """0.3 mm cyclic error of 1.2 m period under 0.8 mm noise: the covariate that carries it
    is range (held-out explained variance, with its period), not the correlated incidence
    angle or intensity; it stays unexplained and the cyclic error is named."""
    out = _campaign(tmp_path_factory, "cyclic", {}, post=_cyclic_range_error)
    diag, doc, truth = _run(out, config=DiagnoseConfig(effects=("unexplained",)))
    cmp_ = doc["covariate_comparison"]
    best = cmp_["best"]
    assert best["covariate"] == "range", cmp_["ranking"][:3]
    assert best["model"] == "periodic" and abs(best["period"] - 1.2) < 0.05
    assert abs(best["amplitude_m"] - 3e-4) < 1e-4
    assert "cyclic error" in cmp_["physics"]
    runners = {r["covariate"]: r["cv_explained"] for r in cmp_["ranking"][1:]}
    # incidence angle is nearly a function of range on this geometry: it comes second,
    # reported with its (lower) held-out score; intensity explains next to nothing
    assert runners["incidence_angle"] < best["cv_explained"]
    assert runners["intensity"] < 0.5 * best["cv_explained"]
    for f in doc["findings"]:
        if f["effect"] == "unexplained" and "covariate" in f["where"]:
            assert f["where"]["covariate"] in ("range", "panel"), f["where"]


def test_local_deformation_is_one_function_for_simulator_and_model():
    """The catalog's bump: the simulator's surface and the model's deviation agree."""
    import jax.numpy as jnp

    from hartrao_jax.model._model import make_model
    from hartrao_jax.physics._catalog import EFFECTS, local_deformation

    assert EFFECTS["local_deformation"].family == "reflector"
    v = float(local_deformation(1.0, 2.0, 1.0, 2.0, 1e-3, 0.5))
    assert v == pytest.approx(1e-3)
    assert float(local_deformation(1.5, 2.0, 1.0, 2.0, 1e-3, 0.5)) == pytest.approx(
        1e-3 * math.exp(-0.5))
    m = make_model(["tx", "ty", "tz", "rx", "ry", "f", "bump_x_m", "bump_y_m", "bump_amp_m",
                    "bump_width_m"], kappa_rad=0.3)
    X = jnp.array([3.0, 4.0, 25.0 / 44.0])
    Xt = np.asarray([[math.cos(0.3), -math.sin(0.3)], [math.sin(0.3), math.cos(0.3)]]) @ X[:2]
    p = {"bump_x_m": Xt[0], "bump_y_m": Xt[1], "bump_amp_m": 2e-3, "bump_width_m": 0.4}
    assert float(m.deviation(X, p, jnp.zeros(3))) == pytest.approx(2e-3)


@pytest.mark.slow
@pytest.mark.parametrize("amplitude_m", [1.5e-3, 5e-3])
def test_local_deformation_under_panels_is_found_located_and_modelled(tmp_path_factory,
                                                                      amplitude_m):
    """1.5 mm (at 0.01 rad, see STEPS: fewer points do not show it reliably): below the robust
    fit's rejection limit (about 4 x 0.8 mm); 5 mm: the start fit rejects the bump's core, the
    search takes it back (it agrees with its neighbours) and the refit sees it. The panels are
    the search's nuisance, so the panel the bump sits in does not take it: the amplitude comes
    out whole (within 3 sigma), and it is the only local finding."""
    out = _campaign(tmp_path_factory, f"bump{amplitude_m:g}", {"local_deformation": {
        "amplitude_m": amplitude_m, "x_m": 4.0, "y_m": 3.0, "width_m": 0.6}})
    diag, doc, truth = _run(out)
    f = [f for f in doc["findings"] if f["effect"] == "local_deformation"]
    assert len(f) == 1, doc["local_deformation_search"]
    e, w = f[0]["estimate"], f[0]["where"]
    assert math.hypot(w["x_m"] - 4.0, w["y_m"] - 3.0) < 3 * max(e["x_m"]["sigma"], 0.05)
    assert abs(e["amplitude_m"]["value"] - amplitude_m) < 3 * e["amplitude_m"]["sigma"]
    assert f[0]["rms_after_m"] < f[0]["rms_before_m"] and len(f[0]["centre_scan_m"]) == 3
    if amplitude_m > 4e-3:
        assert doc["local_deformation_search"][0]["readmitted_points"] > 0


# ------------------------------------------------------------------ the score tests' null


def _dz(name: str, value: float, truth: float) -> float:
    """Estimate minus truth; angles of the pose on the same turn."""
    d = value - truth
    return (d + math.pi) % (2 * math.pi) - math.pi if name in ("rx", "ry") else d


@pytest.fixture(scope="module")
def clean_seeds(tmp_path_factory):
    """Diagnoses of six clean campaigns (panels 0.15 mm rms and their tilts, noise): the
    catalog candidates' statistics of the last step, instrument parameters (1 dof each)."""
    T, nulls, z = [], [], {"position": [], "scan": [], "white": []}
    for seed in range(20, 26):
        out = tmp_path_factory.mktemp(f"null{seed}")
        simulate_campaign(out, preset="clean", effects=PANELS, seed=seed, step_rad=0.03)
        doc = diagnose(out).to_json()
        assert [f["effect"] for f in doc["findings"]] in ([], ["panel_offset"]), doc["findings"]
        T += [r["statistic"] for r in doc["last_candidates"]
              if r["family"] == "instrument" and r["dof"] == 1]
        nulls.append(doc["score_test_null"]["surface_random_effect"])
        truth = json.loads((out / "truth.json").read_text())["scans"]
        tr = {s["id"]: {**s, **s["model_parameters"]} for s in truth}
        for p in doc["positions"]:
            t = tr[p["scans"][0]]
            z["position"] += [_dz(n, e["value"], t.get(n, 0.0)) / e["sigma"]
                              for n, e in p["estimates"].items() if e["sigma"]]
        for sid, sc in doc["scans"].items():
            for n, e in sc["estimates"].items():
                z["scan"].append(_dz(n, e["value"], tr[sid].get(n, 0.0)) / e["sigma"])
                z["white"].append(_dz(n, e["value"], tr[sid].get(n, 0.0)) / e["sigma_white"])
    return np.array(T), nulls, {k: np.array(v) for k, v in z.items()}


def test_score_statistics_on_clean_data_follow_their_chi_square(clean_seeds):
    """Under the null (no effect) the score statistic of a 1-dof candidate is chi2(1): mean 1,
    P(T > 6.63) = 1 %. Judged against white noise after one offset per panel (the panels' tilts
    left in the noise) it was not: over 16 clean campaigns at 0.02 rad its mean was 1.78, 3.4 %
    of the values exceeded 10.83 (0.1 % expected) and the encoder term x12b averaged 7.8. With
    the panels' tilts as a random effect (20 campaigns): mean 0.82, none above 6.63 in 220."""
    T, _, _ = clean_seeds
    assert len(T) >= 50
    assert 0.6 < T.mean() < 1.4, T
    assert np.mean(T > 6.63) < 0.04, np.sort(T)[-5:]
    assert T.max() < 15.0, np.sort(T)[-5:]


def test_score_null_estimates_the_panel_spread(clean_seeds):
    """The null's cell variances come from the data: the simulated panels are 0.15 mm rms."""
    _, nulls, _ = clean_seeds
    off = np.array([n["cell_sd"]["offset_m"] for n in nulls])
    assert np.all(np.abs(off / 1.5e-4 - 1) < 0.25), off
    assert all(0.9 < n["sigma0"] < 1.1 for n in nulls), nulls


def test_final_estimates_carry_the_surface_in_their_sigmas(clean_seeds):
    """The final model's estimates (pose, f, x4/x6/x7) per position, both faces together with
    the panels as a random effect, have z = (estimate - truth) / sigma of std near 1 over six
    clean campaigns (54 values; on 23 demo campaigns at 0.01 rad std 0.79-1.20 per parameter,
    ``benchmarks/diagnose_sigmas.py``); the loop's white-noise sigmas of the same per-scan
    values are too small (std 3-5.6 at 0.01 rad)."""
    _, _, z = clean_seeds
    assert z["position"].size == 6 * 9
    assert 0.7 < np.std(z["position"]) < 1.35, z["position"]
    assert np.max(np.abs(z["position"])) < 4.0
    assert 0.7 < np.std(z["scan"]) < 1.35
    assert np.std(z["white"]) > 1.3 * np.std(z["scan"])
