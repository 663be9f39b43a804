"""Disturbed scans: the simulator's impulsive shift found at its phi, clean scans left alone,
attribution with the other cycle, masks for --exclude-disturbed / --cut-disturbed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hartrao_jax.fit._fit import fit_campaign, fit_scan
from hartrao_jax.fit._records import write_fit
from hartrao_jax.simulate._simulate import simulate_campaign
from hartrao_jax.surface._disturbed import (
    DisturbedConfig,
    cut_keep,
    detect_disturbed,
    detect_disturbed_arrays,
    detect_disturbed_campaign,
    detect_disturbed_residuals,
    disturbed_json,
    keep_function,
    line_width,
    without_disturbed,
)

PHI0 = 123.4  # deg, where the simulated disturbance starts (cycle 1 of position "a")
STEP = 0.012


@pytest.fixture(scope="module")
def campaign_fit(tmp_path_factory):
    d = tmp_path_factory.mktemp("disturbed")
    eff = {"x4": 1.5e-4, "panel_offset": 2e-4,
           "impulsive_shift": {"phi_deg": PHI0, "duration_s": 0.3, "displacement_m": 0.002,
                               "cycle": 1, "scans": ["ac1"]}}
    camp = simulate_campaign(d / "camp", preset="clean", effects=eff, seed=4, step_rad=STEP,
                             positions=[("a", -35.0, -64.0), ("b", 40.0, -10.0)])
    cf = fit_campaign(camp, "extended", progress=False)
    write_fit(d / "fit", cf)
    return camp, cf, d


def _scan(cf, sid):
    return next(s for s in cf.scans if s.meta.id == sid)


# ------------------------------------------------------------------------------ simulated


def test_disturbed_scan_found_at_its_phi(campaign_fit):
    camp, cf, _ = campaign_fit
    s = _scan(cf, "ac1")
    for ref in (None, _scan(cf, "ac2")):
        rep = detect_disturbed(s, ref)
        assert rep is not None
        assert rep.scan == "ac1" and rep.cycle == 1 and rep.position == "a"
        assert abs(rep.phi_deg - PHI0) < 1.0
        # 0.3 s at the simulator's line period: the disturbed range ends about 4.8 deg later
        n_lines = 0.3 / 0.0361
        width = math.degrees(math.pi / round(math.pi / STEP))
        assert abs(rep.phi_end_deg - (PHI0 + n_lines * width)) < 1.5 * width
        assert rep.kind == "box"
        assert rep.jump_m < -1e-3  # the scanner moved towards +Z: points appear lower
        assert rep.statistic > rep.threshold
        assert rep.reference == (None if ref is None else "ac2")


def test_clean_scans_are_not_reported(campaign_fit):
    camp, cf, _ = campaign_fit
    for sid, other in (("ac2", "ac1"), ("bc1", "bc2"), ("bc2", "bc1")):
        assert detect_disturbed(_scan(cf, sid)) is None, sid
        # with the reference: a disturbance of the *other* scan is not given to this one
        assert detect_disturbed(_scan(cf, sid), _scan(cf, other)) is None, sid
    reps = detect_disturbed_campaign(cf)
    assert [r.scan for r in reps] == ["ac1"]


def test_detection_from_residual_files(campaign_fit):
    _, cf, d = campaign_fit
    reps = detect_disturbed_residuals(d / "fit")
    assert [r.scan for r in reps] == ["ac1"]
    assert abs(reps[0].phi_deg - PHI0) < 1.0
    doc = disturbed_json(reps)
    assert doc["schema"] == "hartrao-disturbed/1"
    j = doc["disturbed"][0]
    assert j["phi_range_deg"][0] < j["phi_range_deg"][1]


def test_cut_and_exclude_masks(campaign_fit):
    camp, cf, _ = campaign_fit
    s = _scan(cf, "ac1")
    rep = detect_disturbed(s, _scan(cf, "ac2"))
    keep = cut_keep(s.data.phi_rad, rep)
    ph = np.degrees(s.data.phi_rad)
    a, b = sorted((rep.phi_deg, rep.phi_end_deg))
    assert not keep[(ph > a) & (ph < b)].any()
    assert keep[(ph < a - 1) | (ph > b + 1)].all()
    assert 0.9 < keep.mean() < 0.99
    kf = keep_function([rep])
    assert (kf(s.meta, s.data) == keep).all()
    other = _scan(cf, "bc1")
    assert kf(other.meta, other.data).all()
    assert without_disturbed([m.id for m in camp.scans], [rep]) == ["ac2", "bc1", "bc2"]
    # refitting without the cut range: the scan is clean
    refit = fit_scan(camp, s.meta, "extended", data=s.data, keep=keep)
    assert detect_disturbed(refit, keep=keep) is None
    assert refit.sigma0 <= s.sigma0


# ------------------------------------------------------------------------------ synthetic


def _synthetic(cycle=1, seed=0, box=None, step=None, n_lines=314, per_line=160):
    """Raw angles of a two-face scan with smooth, theta-dependent structure and noise; a
    disturbance ``box = (phi_start_deg, phi_end_deg, jump_m)`` added to its lines."""
    rng = np.random.default_rng(seed)
    lo = 0.0 if cycle == 1 else math.pi
    w = math.pi / n_lines
    phi = lo + (np.repeat(np.arange(n_lines), per_line) + 0.5) * w
    th0 = rng.uniform(0.05, 1.2, phi.size)
    face2 = rng.random(phi.size) < 0.5
    theta = np.where(face2, 2 * math.pi - th0, th0)
    dev = (4e-4 * np.sin(3 * th0) + np.where(face2, 3e-4, -3e-4) * th0
           + 1e-4 * np.sin(2 * phi) + rng.normal(scale=8e-4, size=phi.size))
    phi = phi + rng.normal(scale=2e-5, size=phi.size)
    if box is not None:
        a, b, j = box
        pd = np.degrees(phi)
        dev = dev + np.where((pd >= a) & (pd < b), j, 0.0)
    return phi, theta, dev


def test_line_width_measured():
    phi, _, _ = _synthetic()
    assert line_width(phi) == pytest.approx(math.pi / 314, rel=1e-3)


@pytest.mark.parametrize("cycle,box", [(1, (30.0, 32.0, 1.5e-3)), (2, (300.0, 318.0, -1e-3)),
                                       (1, (150.0, 180.0, 1e-3))])
def test_synthetic_disturbance_found(cycle, box):
    phi, theta, dev = _synthetic(cycle, seed=1, box=box)
    rep = detect_disturbed_arrays("s", "p", cycle, phi, theta, dev)
    assert rep is not None
    a, b = sorted((rep.phi_deg, rep.phi_end_deg))
    assert abs(a - box[0]) < 1.0 and abs(b - box[1]) < 1.0
    assert rep.jump_m == pytest.approx(box[2], abs=2e-4)
    if box[1] == 180.0:  # lasts to the end of the cycle: one change, not a box
        assert rep.kind == "step" and rep.phi_deg == pytest.approx(box[0], abs=1.0)


def test_no_false_alarms_on_smooth_structure():
    hits = 0
    for seed in range(20):
        for cycle in (1, 2):
            phi, theta, dev = _synthetic(cycle, seed=100 + seed)
            hits += detect_disturbed_arrays("s", "p", cycle, phi, theta, dev) is not None
    assert hits == 0


def test_small_jump_below_effect_size_not_reported():
    phi, theta, dev = _synthetic(1, seed=3, box=(60.0, 70.0, 1.5e-4))
    cfg = DisturbedConfig(threshold=5.0)
    assert detect_disturbed_arrays("s", "p", 1, phi, theta, dev, config=cfg) is None
