"""Preprocessing: scatter removal against the simulator's truth, RANSAC planes, bookkeeping."""

from __future__ import annotations

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pyarrow.parquet as pq
import pytest

from hartrao_jax.campaign._campaign import ScanData, ScanMeta, default_campaign
from hartrao_jax.geometry._geometry import cartesian_to_raw, face_of, polar_to_cartesian
from hartrao_jax.preprocess import (
    PREPROCESS_SCHEMA,
    REASONS,
    PlaneCondition,
    PreprocessConfig,
    default_range_window,
    fit_planes,
    keep_mask_fn,
    preprocess_campaign,
    preprocess_scan,
)
from hartrao_jax.simulate._simulate import CLASSES, SimConfig, simulate_campaign, simulate_scan
from hartrao_jax.solver._ghm import gauss_helmert

STEP = 0.015  # rad: coarse, fast
SCATTER = ("cone", "quadrupod", "background", "mixed")


@pytest.fixture(scope="module")
def scene():
    """One simulated scan (demo preset: scatter, panels, instrument errors), more multipath."""
    data, lab, truth = simulate_scan(step_rad=STEP, seed=0,
                                     config=SimConfig(multipath_fraction=0.03))
    camp = dataclasses.replace(default_campaign(), scanner=dataclasses.replace(
        default_campaign().scanner, angular_step_rad=STEP))
    meta = ScanMeta("r23c1", "r23", 1, "", ha_deg=-35.0, dec_deg=-64.0)
    return camp, meta, data, lab, truth


@pytest.fixture(scope="module")
def result(scene):
    camp, meta, data, _, _ = scene
    return preprocess_scan(camp, meta, data, PreprocessConfig())


def _normal_offset(lab, truth):
    """True distance (m) of every surface-class point from the reflector along its normal."""
    X = np.stack([lab["X"], lab["Y"], lab["Z"]], 1)
    excess = lab["range_true_m"] - np.linalg.norm(X - np.asarray(truth["t_tel"]), axis=1)
    return excess * np.cos(lab["incidence_rad"])


# ------------------------------------------------------------------- against the simulator


@pytest.mark.parametrize("frame", ["flat", "scanner"])
def test_keeps_reflector_and_removes_scatter(scene, result, frame):
    camp, meta, data, lab, _ = scene
    res = result if frame == "flat" else preprocess_scan(camp, meta, data,
                                                         PreprocessConfig(frame=frame))
    assert res.plane_frame == frame
    cls = lab["cls"]
    refl = cls == CLASSES["reflector"]
    assert res.keep[refl].mean() >= 0.98, res.stats
    for name in SCATTER:
        m = cls == CLASSES[name]
        assert m.sum() > 20, name
        assert 1 - res.keep[m].mean() >= 0.95, (name, np.bincount(res.reason[m], minlength=6))
    scatter = np.isin(cls, [CLASSES[k] for k in (*SCATTER, "multipath")])
    assert 1 - res.keep[scatter].mean() >= 0.95


def test_multipath_beyond_epsilon_plus_three_sigma_is_removed(scene, result):
    _, _, _, lab, truth = scene
    mp = lab["cls"] == CLASSES["multipath"]
    off = _normal_offset(lab, truth)
    far = mp & (off > result.params["epsilon_m"] + 3 * result.params["sigma_distance_m"])
    assert far.sum() > 100
    assert not result.keep[far].any()
    # and the near ones that survive are within epsilon + noise of the surface
    kept_mp = mp & result.keep
    assert np.all(off[kept_mp] < result.params["epsilon_m"] + 3 * result.params["sigma_distance_m"])


def test_default_range_window_contains_every_reflector_point(scene, result):
    camp, meta, data, lab, _ = scene
    surf = np.isin(lab["cls"], [CLASSES["reflector"], CLASSES["multipath"]])
    r = data.range_m[surf]
    p = result.params
    assert p["d_min_m"] <= r.min() and r.max() <= p["d_max_m"]
    assert not np.any(result.reason[surf] == REASONS_CODE["range_window"])
    # the window is tight: it removes the near quadrupod and the far background
    assert p["d_max_m"] - p["d_min_m"] < 1.3 * (r.max() - r.min()) + 1.0
    # nominal geometry (no initial values) is wider and still contains them
    lo, hi = default_range_window(camp, None)
    assert lo <= r.min() and r.max() <= hi


REASONS_CODE = {v: k for k, v in REASONS.items()}


def _angle(a, b) -> float:
    """Angle (rad) between two lines (sign of the vectors ignored), accurate near 0."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), abs(a @ b)))


def test_without_initial_values_falls_back_to_scanner_planes(scene):
    camp, meta, data, lab, _ = scene
    res = preprocess_scan(camp, meta, data, PreprocessConfig(use_initial_values=False))
    assert res.plane_frame == "scanner" and res.init is None
    assert res.params["geometry_window_m"] is None
    refl = lab["cls"] == CLASSES["reflector"]
    assert res.keep[refl].mean() >= 0.98
    assert 1 - res.keep[lab["cls"] == CLASSES["background"]].mean() >= 0.95


# ----------------------------------------------------------------------------- RANSAC core


def _plane_patch(n_pts, n_out, normal, d, noise, seed=0, size=0.3):
    rng = np.random.default_rng(seed)
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    uv = rng.uniform(-size / 2, size / 2, (n_pts, 2))
    off = rng.normal(size=n_pts) * noise
    out = np.zeros(n_pts, bool)
    out[rng.choice(n_pts, n_out, replace=False)] = True
    off[out] = rng.choice([-1, 1], n_out) * rng.uniform(0.01, 0.08, n_out)
    P = d * normal + uv[:, :1] * a + uv[:, 1:] * b + off[:, None] * normal
    return P, out, normal


@pytest.mark.parametrize("f32", [True, False])
def test_ransac_recovers_exact_plane_despite_outliers(f32):
    normal, d = np.array([0.2, -0.5, 0.8]), 1.7
    P, out, nrm = _plane_patch(300, 120, normal, d, noise=0.0)
    cen = P.mean(0)
    res = fit_planes((P - cen)[None].astype(np.float32 if f32 else np.float64), [300], 0.004,
                     ransac_float32=f32)
    n_hat = res["normal"][0]
    d_hat = res["d"][0] + n_hat @ (res["centroid"][0] + cen)
    s = np.sign(n_hat @ nrm)
    assert _angle(n_hat, nrm) < 1e-6
    assert abs(s * d_hat - d) < 1e-6
    np.testing.assert_array_equal(res["inlier"][0, :300], ~out)
    assert res["n_inliers"][0] == 180 and res["rms"][0] < 1e-6


def test_ransac_plane_with_noise_is_within_its_uncertainty():
    noise = 0.0008
    normal, d = np.array([0.0, 0.3, 1.0]), -10.2
    P, out, nrm = _plane_patch(1000, 300, normal, d, noise=noise, seed=4)
    cen = P.mean(0)
    res = fit_planes((P - cen)[None].astype(np.float32), [1000], 4.5 * noise)
    n_hat = res["normal"][0]
    tilt_sigma = noise / (0.3 / np.sqrt(12)) / np.sqrt(700)
    assert _angle(n_hat, nrm) < 5 * tilt_sigma
    inl = res["inlier"][0, :1000]
    assert not np.any(inl & out)  # all gross outliers (>= 1 cm) removed
    assert inl[~out].mean() > 0.999
    assert abs(res["rms"][0] / noise - 1) < 0.1


def test_patches_are_independent_of_batching_and_deterministic():
    Ps, ns = [], []
    for k in range(37):
        P, _, _ = _plane_patch(50 + k, 10, [0.1 * k, 1.0, 2.0], 0.0, 0.001, seed=k)
        pad = np.zeros((128, 3), np.float32)
        pad[: len(P)] = P - P.mean(0)
        Ps.append(pad)
        ns.append(len(P))
    Ps = np.stack(Ps)
    a = fit_planes(Ps, ns, 0.004, seed=3)
    b = fit_planes(Ps, ns, 0.004, seed=3, batch_size=4, max_chunk=8)
    c = fit_planes(Ps[5:13], ns[5:13], 0.004, seed=3, ids=np.arange(5, 13), batch_size=4,
                   max_chunk=8)  # a patch's samples follow its id, not its position
    for k in ("inlier", "n_inliers"):  # same samples, same decisions
        np.testing.assert_array_equal(a[k], b[k])
        np.testing.assert_array_equal(a[k][5:13], c[k])
    for k in ("normal", "d"):  # float32 sums: the order may differ with the batch width
        np.testing.assert_allclose(a[k], b[k], rtol=0, atol=1e-7)
        np.testing.assert_allclose(a[k][5:13], c[k], rtol=0, atol=1e-7)
    again = fit_planes(Ps, ns, 0.004, seed=3)
    for k in a:
        np.testing.assert_array_equal(a[k], again[k])


def test_refinement_equals_gauss_helmert_plane_in_raw_observations():
    """The vmapped TLS refinement gives the rigorous GH plane (condition in r, phi, theta)."""
    rng = np.random.default_rng(3)
    P, _, nrm = _plane_patch(400, 0, [0.3, -0.2, 1.0], 0.0, 0.0, seed=3)
    P = P + np.array([4.0, 3.0, 10.5])  # ~12 m from the scanner
    r, phi, th = cartesian_to_raw(P, 1)
    sig = np.array([0.0008, 2e-5, 2e-5])
    obs = np.stack([r, phi, th], 1) + rng.normal(size=(len(r), 3)) * sig
    xs = np.asarray(polar_to_cartesian(obs[:, 0], obs[:, 1], obs[:, 2]))
    cen = xs.mean(0)
    res = fit_planes((xs - cen)[None], [len(xs)], 0.004, ransac_float32=False)
    n_tls = res["normal"][0]
    d_tls = res["d"][0] + n_tls @ (res["centroid"][0] + cen)
    cond = PlaneCondition.around(n_tls)
    gh = gauss_helmert(cond, obs, np.array([0.0, 0.0, d_tls]), sig)
    assert bool(gh.converged) and 0.9 < float(gh.sigma0) < 1.1
    n_gh = np.asarray(cond.normal(jnp.asarray(gh.x)))
    angle = _angle(n_gh, n_tls)
    assert angle < 0.25 * float(np.min(np.asarray(gh.sigma)[:2]))
    # offsets compared at the centroid (d itself is correlated with the tilt 12 m away)
    assert abs((n_gh @ cen - float(gh.x[2])) - (n_tls @ cen - d_tls)) < 0.25 * 0.0008 / np.sqrt(
        len(xs))


# --------------------------------------------------------------------------- bookkeeping


def test_kept_rows_keep_their_original_indices(scene):
    camp, meta, data, lab, _ = scene
    rng = np.random.default_rng(0)
    sel = np.sort(rng.choice(len(data), size=len(data) * 2 // 3, replace=False))
    sub = data.subset(sel)  # rows are now a non-trivial subset of the file rows
    res = preprocess_scan(camp, meta, sub, PreprocessConfig())
    np.testing.assert_array_equal(res.row, sel)
    np.testing.assert_array_equal(res.kept_rows, sel[res.keep])
    # kept rows point back to reflector points of the full scan
    assert np.mean(lab["cls"][res.kept_rows] == CLASSES["reflector"]) > 0.99


def test_stats_add_up_with_non_finite_rows(scene):
    camp, meta, data, _, _ = scene
    d = dataclasses.replace(data.subset(np.arange(len(data))), n_dropped_nonfinite=7)
    bad = np.arange(0, len(d), 97)
    d.range_m = d.range_m.copy()
    d.range_m[bad[::2]] = np.nan
    d.theta_rad = d.theta_rad.copy()
    d.theta_rad[bad[1::2]] = np.inf
    res = preprocess_scan(camp, meta, d, PreprocessConfig())
    s = res.stats
    assert s["n_rows"] == len(d) + 7 and s["n_input"] == len(d)
    assert s["n_kept"] + sum(s["removed"].values()) == s["n_rows"]
    assert s["removed"]["non_finite"] == len(bad) + 7
    assert s["n_kept"] == int(res.keep.sum()) == int(np.sum(res.reason == 0))
    assert res.removed()["non_finite"] == len(bad)
    assert np.all(res.reason[bad] == REASONS_CODE["non_finite"])
    assert np.array_equal(res.keep, res.reason == 0)
    assert res.reason.dtype == np.uint8 and set(np.unique(res.reason)) <= set(REASONS)
    for stage in ("range_window", "geometry_window", "ransac_outlier", "small_patch"):
        assert s["removed"][stage] > 0, stage


def test_same_seed_same_result(scene, result):
    camp, meta, data, _, _ = scene
    again = preprocess_scan(camp, meta, data, PreprocessConfig())
    np.testing.assert_array_equal(again.reason, result.reason)
    np.testing.assert_array_equal(again.planes, result.planes)
    assert again.stats["removed"] == result.stats["removed"]


def test_patches_never_mix_faces_and_have_the_requested_size(scene, result):
    _, _, data, lab, _ = scene
    inp = result.patch >= 0
    face = face_of(data.theta_rad)
    assert set(np.unique(face[inp])) == {1, 2}  # the scan has both faces in patches
    per_patch = np.zeros((result.patch.max() + 1, 2), int)
    np.add.at(per_patch, (result.patch[inp], face[inp] - 1), 1)
    assert not np.any((per_patch[:, 0] > 0) & (per_patch[:, 1] > 0))
    # patch extent on the reflector is about patch_size_m (from the truth coordinates)
    s = result.params["patch_size_m"]
    ext = []
    for p in np.flatnonzero(result.patch_points >= 20)[:200]:
        X = np.stack([lab["X"], lab["Y"]], 1)[result.patch == p]
        ext.append(np.sqrt(np.prod(X.max(0) - X.min(0))))
    assert 0.5 * s < np.median(ext) < 1.6 * s
    med = result.stats["points_per_patch"]["median"]
    assert 10 <= med <= 200


def test_keep_mask_fn_gives_a_mask_over_the_scan_rows(scene, result):
    camp, meta, data, _, _ = scene
    keep = keep_mask_fn(PreprocessConfig(), campaign=camp)(meta, data)
    assert keep.dtype == bool and keep.shape == (len(data),)
    np.testing.assert_array_equal(keep, result.keep)


def test_campaign_writes_preprocess_json_and_masks(tmp_path):
    camp = simulate_campaign(tmp_path / "camp", preset="demo", step_rad=0.02, seed=1)
    out = tmp_path / "pre"
    results = preprocess_campaign(camp, PreprocessConfig(), out_dir=out, progress=False)
    assert set(results) == {m.id for m in camp.scans}
    doc = json.loads((out / "preprocess.json").read_text())
    assert doc["schema"] == PREPROCESS_SCHEMA == "hartrao-preprocess/1"
    assert [s["id"] for s in doc["scans"]] == [m.id for m in camp.scans]
    for s in doc["scans"]:
        assert s["n_kept"] + sum(s["removed"].values()) == s["n_rows"]
        assert s["params"]["epsilon_m"] > 0 and s["params"]["d_min_m"] < s["params"]["d_max_m"]
        mask = pq.read_table(out / "masks" / f"{s['id']}.parquet")
        reason = mask.column("reason").to_numpy()
        assert int(np.sum(reason == 0)) == s["n_kept"]
        truth = pq.read_table(tmp_path / "camp" / "truth" / f"{s['id']}.parquet")
        cls = truth.column("cls").to_numpy()
        rows = mask.column("row").to_numpy()
        assert np.mean(reason[cls[rows] == CLASSES["reflector"]] == 0) >= 0.98
    assert doc["totals"]["n_kept"] == sum(s["n_kept"] for s in doc["scans"])


def test_config_validation():
    with pytest.raises(ValueError, match="frame"):
        PreprocessConfig(frame="telescope")
    with pytest.raises(ValueError, match="min_patch_points"):
        PreprocessConfig(min_patch_points=2)


def test_scan_without_points_in_the_window_is_all_removed():
    camp = default_campaign()
    meta = ScanMeta("x", "x", 1, "", ha_deg=0.0, dec_deg=-25.8897)
    n = 500
    rng = np.random.default_rng(0)
    d = ScanData(rng.uniform(40, 60, n), rng.uniform(0, np.pi, n), rng.uniform(0.1, 3, n),
                 np.zeros(n, np.float32), np.arange(n) * 1e-3, np.arange(n))
    res = preprocess_scan(camp, meta, d, PreprocessConfig(use_initial_values=False))
    assert not res.keep.any() and res.stats["removed"]["range_window"] == n
