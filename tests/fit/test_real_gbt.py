"""Real recordings: the Green Bank Telescope scans of $HARTRAO_REAL_DATA (default ../shared/real),
and any reflector pose."""

import numpy as np
import pytest
from helpers import needs_real_gbt as needs_real
from helpers import paraboloid_points, real_gbt_file

from hartrao_jax import gauss_helmert, make_model
from hartrao_jax.campaign._import import import_file
from hartrao_jax.fit._fit import fit_scan
from hartrao_jax.geometry._geometry import cartesian_to_raw, rot_x, rot_y, rot_z
from hartrao_jax.preprocess._initial import patch_initial_values, quadric_initial_values
from hartrao_jax.surface._local import find_local_deformations


def _offset_section(n, f=60.0, seed=0):
    """Points of an off-axis section of a paraboloid: aperture centre 54 m off the axis."""
    rng = np.random.default_rng(seed)
    c = np.array([54.0, 0.0])
    r = 35 * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * np.pi, n)
    x, y = c[0] + r * np.cos(a), c[1] + r * np.sin(a)
    return np.stack([x, y, (x * x + y * y) / (4 * f)], 1)


def test_offset_paraboloid_from_arbitrary_pose_without_initial_values():
    X = _offset_section(30000)
    R = np.asarray(rot_z(0.7) @ rot_y(2.2) @ rot_x(-0.4))  # any orientation of the scanner
    t = np.array([20.0, -5.0, 45.0])
    xs = (X - t) @ R  # scanner frame
    rng = np.random.default_rng(1)
    xs = np.concatenate([xs, rng.normal(size=(1500, 3)) * 20])  # 5 % non-reflector returns
    r, phi, th = cartesian_to_raw(xs, 0)
    sig = np.array([0.0008, 1.5e-5, 1.5e-5])
    l = np.stack([r, phi, th], 1) + rng.normal(size=(len(r), 3)) * sig
    iv = quadric_initial_values(l[:, 0], l[:, 1], l[:, 2])
    assert abs(iv.x["f"] - 60.0) < 1.0
    m = make_model("simplified")
    from hartrao_jax.preprocess._initial import initial_distance

    w = (np.abs(initial_distance(l[:, 0], l[:, 1], l[:, 2], iv.x)) < 0.1).astype(float)
    res = gauss_helmert(m, l, np.array([iv.x[k] for k in m.free]), sig, np.zeros((len(l), 2)), w)
    assert bool(res.converged)
    assert abs(float(res.x[5]) - 60.0) < 3.5 * float(res.sigma[5])
    assert 0.95 < float(res.sigma0) < 1.05


def test_small_region_of_known_focal_length_gets_initial_values_from_its_curvature():
    X = paraboloid_points(20000, f=60.0, rho=(20, 40))
    psi = np.arctan2(X[:, 1], X[:, 0])
    X = X[np.abs(psi) < 0.15]  # a patch ~20 m x 9 m at 20-40 m from the axis
    R = np.asarray(rot_y(3.0) @ rot_x(0.1))
    xs = (X - np.array([0.0, 0.0, 50.0])) @ R
    r, phi, th = cartesian_to_raw(xs, 0)
    cands = patch_initial_values(r, phi, th, focal_length_m=60.0)
    assert cands[0].inlier_fraction > 0.9


@pytest.fixture(scope="module")
def scan10(tmp_path_factory):
    out = tmp_path_factory.mktemp("gbt") / "scan10"
    return import_file(real_gbt_file("scan10_random_sample.csv"), "xyz", out, telescope="gbt")


@needs_real
def test_real_gbt_scan_focal_length_and_stability(scan10):
    meta = scan10.scans[0]
    fits = [fit_scan(scan10, meta, "simplified", robust_k=k, window_m=w)
            for k, w in [(4.0, 0.1), (3.0, 0.1), (5.0, 0.3), (3.5, 0.05)]]
    fs = np.array([s.value("f") for s in fits])
    assert np.all(np.abs(fs - 60.0) < 0.05)  # within a few cm of the 60 m design
    assert np.ptp(fs) < 1e-3  # stable to 1 mm across cleaning settings
    s = fits[0]
    assert 0.7 < s.sigma0 < 1.3  # realistic a priori sigmas of a Leica export
    removed = 1 - s.n_points / len(s.data)
    assert removed < 0.1
    assert s.sigma_of("f") < 1e-3


@needs_real
def test_real_gbt_bump_region_is_located(tmp_path):
    camp = import_file(real_gbt_file("bump1_high_sample.csv"), "xyz", tmp_path / "bump",
                       telescope="gbt")
    meta = camp.scans[0]
    found = []
    for fixed in ({"f": 60.0}, None):
        s = fit_scan(camp, meta, "simplified", fixed=fixed)
        P = s.X_tel[s.used]
        c = P.mean(axis=0)
        _, _, Vt = np.linalg.svd(P - c, full_matrices=False)
        xy = (P - c) @ Vt[:2].T
        dev = s.deviation_m[s.used]
        bumps = find_local_deformations(xy, dev, float(np.std(dev)))
        assert bumps, "no localised deformation found"
        b = bumps[0]
        assert abs(b.amplitude_m) > 3 * b.sigma_amplitude_m
        assert abs(b.amplitude_m) > 3e-4
        # location in the scanner frame (independent of the fitted frame)
        sel = np.hypot(xy[:, 0] - b.x_m, xy[:, 1] - b.y_m) < b.width_m
        found.append(np.asarray(s.data.subset(s.used).range_m)[sel].mean())
        found[-1] = np.median(P[sel] @ np.eye(3), axis=0) if False else found[-1]
    assert abs(found[0] - found[1]) < 0.5  # the same place whatever the focal-length choice


@needs_real
def test_real_gbt_one_face_per_cycle_fit_holds_the_two_face_parameters(scan10):
    """A one-face recording (cycle 0) never estimates x4/x6/x7, per cycle or jointly: with
    them estimated the extended model put f 15 mm from the independent 60.0355 m."""
    from hartrao_jax.fit._joint import fit_joint
    from hartrao_jax.fit._records import scan_record

    s = fit_scan(scan10, scan10.scans[0], "extended")
    assert set(s.held) == {"x4", "x6", "x7"} and not set(s.held) & set(s.names)
    rec = scan_record(s)["estimates"]
    for n in ("x4", "x6", "x7"):
        assert rec[n]["identifiable"] is False and rec[n]["sigma"] is None
        assert rec[n]["value"] == 0.0 and "one-face" in rec[n]["note"]
    assert abs(s.value("f") - 60.0355) < 3e-3
    from hartrao_jax.fit._fit import fit_campaign

    (b,) = fit_campaign(scan10, "extended", per_cycle=True, batch=True, progress=False).scans
    assert set(b.held) == {"x4", "x6", "x7"} and not set(b.held) & set(b.names)
    assert abs(b.value("f") - 60.0355) < 3e-3
    with pytest.raises(ValueError, match="every scan is one face"):
        fit_joint(scan10, "extended", shared=("x4", "x6", "x7"), group="campaign")


@needs_real
def test_real_gbt_streamed_per_cycle_starts_like_the_in_memory_fit(scan10, tmp_path):
    """fit-stream --per-cycle on a one-face export of an offset reflector: initial values from
    the pose-free quadric as in memory (from the pointing it kept 0 points and printed
    f = nan), the two-face parameters held."""
    from hartrao_jax.fit._stream import stream_document, stream_fit_scan

    doc = stream_document(stream_fit_scan(scan10, scan10.scans[0], "extended",
                                          rows_per_chunk=20_000, store=tmp_path / "s"))
    assert doc["n_points"] > 0.9 * doc["n_rows"] and doc["converged"]
    assert abs(doc["estimates"]["f"]["value"] - 60.0355) < 3e-3
    assert doc["estimates"]["x6"]["identifiable"] is False
