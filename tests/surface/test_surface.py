"""Surface products: panel masks, cycle averaging (never across panels, cancels two-face errors),
panel deviations against the simulator's truth, north alignment and panel ids at several
positions, surface.json, CLI (coarse simulated grids: fast)."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from hartrao_jax.campaign._campaign import load_campaign
from hartrao_jax.fit._fit import fit_campaign
from hartrao_jax.fit._records import write_fit
from hartrao_jax.geometry._geometry import panel_ids
from hartrao_jax.simulate._simulate import SimConfig, simulate_campaign
from hartrao_jax.surface._surface import (
    SURFACE_SCHEMA,
    PanelLayout,
    SurfaceConfig,
    cycle_average,
    panel_mask,
    panel_statistics,
    read_surface,
    surface_campaign,
    surface_from_fit,
    surface_from_fit_dir,
    write_surface,
)

STEP = 0.01
LAYOUT = PanelLayout.default()
DENT = (100, -6e-4)  # panel id, offset (m)


# ------------------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module")
def two_face(tmp_path_factory):
    """x4 only, no noise, simplified fit: the residuals are the two-face error the simplified
    model leaves (plus nothing else)."""
    d = tmp_path_factory.mktemp("twoface")
    camp = simulate_campaign(d / "camp", preset="clean", effects={"x4": 2e-4}, seed=3,
                             step_rad=STEP, config=SimConfig(noise=False))
    return camp, fit_campaign(camp, "simplified", progress=False)


@pytest.fixture(scope="module")
def panels(tmp_path_factory):
    """Displaced and tilted panels plus one 0.6 mm dent, seed instrument errors, noise;
    extended fit written to disk."""
    d = tmp_path_factory.mktemp("panels")
    eff = {"x4": 1.5e-4, "x6": 3e-5, "x7": -4e-5,
           "panel_offset": {"rms_m": 3e-4, "panels": {DENT[0]: DENT[1]}}}
    camp = simulate_campaign(d / "camp", preset="clean", effects=eff, seed=5, step_rad=STEP)
    cf = fit_campaign(camp, "extended", progress=False)
    write_fit(d / "fit", cf)
    return camp, cf, d


# ------------------------------------------------------------------------------ units


def test_panel_mask_margins_and_ids():
    rng = np.random.default_rng(0)
    rho = np.sqrt(rng.uniform(1.0, 13.5**2, 200_000))
    psi = rng.uniform(0, 2 * np.pi, rho.size)
    X = np.column_stack([rho * np.cos(psi), rho * np.sin(psi), rho**2 / 43.9])
    ids = panel_ids(rho, psi, LAYOUT.ring_edges_m, LAYOUT.panels_per_ring)
    assert panel_mask(X, LAYOUT, SurfaceConfig(margin_radial_m=0, margin_tangential_m=0)).tolist() \
        == ids.tolist()
    m = panel_mask(X, LAYOUT, SurfaceConfig(margin_radial_m=0.05, margin_tangential_m=0.03))
    kept = m >= 0
    assert (m[kept] == ids[kept]).all()
    g = LAYOUT.geometry()
    k = m[kept]
    assert (rho[kept] - g["rho_in"][k] >= 0.05).all()
    assert (g["rho_out"][k] - rho[kept] >= 0.05).all()
    assert (rho[kept] * (psi[kept] - g["psi_start"][k]) >= 0.03).all()
    assert (rho[kept] * (g["psi_end"][k] - psi[kept]) >= 0.03).all()
    # a point 1 cm inside a ring edge is masked, 6 cm inside is kept
    e = LAYOUT.ring_edges_m[3]
    P = np.array([[e + 0.01, 0.0, 0.0], [e + 0.06, 0.0, 0.0]])
    c, s = np.cos(0.05), np.sin(0.05)
    P = P @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    assert panel_mask(P, LAYOUT, SurfaceConfig(margin_radial_m=0.05))[0] == -1
    cfg = SurfaceConfig(margin_radial_m=0.05, margin_tangential_m=0.02)
    assert panel_mask(P, LAYOUT, cfg)[1] >= 0


def test_cycle_average_never_mixes_panels():
    """Two panels with +1 / -1 mm, points up to their common edge, the two cycles offset by a few
    mm: every group holds points of one panel only and keeps its panel's value exactly."""
    rng = np.random.default_rng(1)
    e = LAYOUT.ring_edges_m[2]  # boundary between rings 1 and 2 (panels 15..38 | 39..68)
    n = 40_000
    r = rng.uniform(e - 0.3, e + 0.3, n)
    psi = rng.uniform(0.01, 0.5, n)  # panels 15, 16 | 39, 40, 41
    X1 = np.column_stack([r * np.cos(psi), r * np.sin(psi), np.zeros(n)])
    X2 = X1 + rng.normal(scale=0.004, size=X1.shape)
    cfg = SurfaceConfig(margin_radial_m=0.0, margin_tangential_m=0.0)
    p1, p2 = panel_mask(X1, LAYOUT, cfg), panel_mask(X2, LAYOUT, cfg)
    assert set(np.unique(p1)) == {15, 16, 39, 40, 41}
    d1 = np.where(p1 < 39, 1e-3, -1e-3)
    d2 = np.where(p2 < 39, 1e-3, -1e-3)
    avg, g1, g2 = cycle_average(X1, d1, p1, X2, d2, p2, radius_m=0.01, return_groups=True)
    assert len(avg) > 1000
    for g, p in ((g1, p1), (g2, p2)):
        ok = g >= 0
        assert (avg.panel[g[ok]] == p[ok]).all()  # every point sits in a group of its panel
    assert np.allclose(np.abs(avg.deviation_m), 1e-3)
    assert np.allclose(avg.deviation_m, np.where(avg.panel < 39, 1e-3, -1e-3))
    assert (avg.n1 > 0).all() and (avg.n2 > 0).all()
    # most points are paired despite the offsets (cells + nearest-neighbour pairing)
    assert avg.n_unpaired < 0.05 * 2 * n
    # processing the panels in chunks changes nothing
    small = cycle_average(X1, d1, p1, X2, d2, p2, radius_m=0.01, chunk_points=5_000)
    np.testing.assert_array_equal(small.deviation_m, avg.deviation_m)
    np.testing.assert_array_equal(small.X, avg.X)


def test_cycle_average_equal_weights_per_cycle():
    """A cell's value is the mean of the two cycles' means, whatever their point counts."""
    X1 = np.array([[5.0, 0.001, 0.0]] * 5)
    X2 = np.array([[5.0, 0.002, 0.0]])
    p = np.array([0] * 5)
    avg = cycle_average(X1, np.full(5, 2e-3), p, X2, np.array([0.0]), np.array([0]), radius_m=0.01)
    assert len(avg) == 1 and avg.n1[0] == 5 and avg.n2[0] == 1
    assert avg.deviation_m[0] == pytest.approx(1e-3)
    assert avg.diff_m[0] == pytest.approx(2e-3)


def test_panel_statistics_recovers_offset_and_tilt():
    rng = np.random.default_rng(2)
    g = LAYOUT.geometry()
    k = 120
    n = 3000
    rho = rng.uniform(g["rho_in"][k] + 0.05, g["rho_out"][k] - 0.05, n)
    psi = rng.uniform(g["psi_start"][k] + 0.01, g["psi_end"][k] - 0.01, n)
    X = np.column_stack([rho * np.cos(psi), rho * np.sin(psi), np.zeros(n)])
    off, tr, tt = 4e-4, 2e-4, -1e-4
    dev = off + tr * (rho - g["rho_c"][k]) + tt * g["rho_c"][k] * (psi - g["psi_c"][k])
    dev = dev + rng.normal(scale=2e-4, size=n)
    t = panel_statistics(X, dev, np.full(n, k), LAYOUT)
    assert t.n[k] == n and t.n.sum() == n
    assert t.offset_m[k] == pytest.approx(off, abs=4 * t.offset_sigma_m[k])
    assert t.deviation_m[k] == pytest.approx(dev.mean())
    assert t.sigma_m[k] == pytest.approx(2e-4 / math.sqrt(n), rel=0.1)
    assert t.tilt_radial_rad[k] == pytest.approx(tr, abs=3e-5)
    assert t.tilt_tangential_rad[k] == pytest.approx(tt, abs=3e-5)
    assert t.tilt_rad[k] == pytest.approx(math.hypot(tr, tt), abs=4e-5)
    assert t.rms_plane_m[k] == pytest.approx(2e-4, rel=0.05)
    assert np.isnan(t.deviation_m[k + 1]) and t.n[k + 1] == 0


# ------------------------------------------------------------------------------ simulated


def test_cycle_average_cancels_two_face_errors(two_face):
    camp, cf = two_face
    res = surface_from_fit(cf)
    pos = res.positions[0]
    assert pos.kind == "cycle average"
    per_cycle = [c.rms_m for c in pos.cycles]
    assert min(per_cycle) > 3e-4  # the simplified model leaves the two-face error of x4
    assert pos.averaged.rms_m < 0.25 * min(per_cycle)  # averaged: (much) better than halved
    # the face difference (cycle 1 - cycle 2 at the same place) carries the error instead
    assert np.sqrt(np.nanmean(pos.averaged.diff_m**2)) > min(per_cycle)
    # nothing is averaged across panels, on the real geometry either
    c1, c2 = pos.cycles
    avg, g1, g2 = cycle_average(c1.X, c1.deviation_m, c1.panel, c2.X, c2.deviation_m, c2.panel,
                                radius_m=pos.radius_m, return_groups=True)
    for g, c in ((g1, c1), (g2, c2)):
        ok = g >= 0
        assert (avg.panel[g[ok]] == c.panel[ok]).all()
    assert avg.n_unpaired < 0.3 * (len(c1) + len(c2))


def test_panel_deviations_recovered(panels):
    camp, cf, _ = panels
    res = surface_from_fit(cf)
    truth = json.loads((camp.root / "truth.json").read_text())["reflector"]
    off = np.asarray(truth["offset_m"])
    tab = res.positions[0].panels
    ok = np.isfinite(tab.deviation_m)
    assert ok.sum() >= 240  # a few panels are hidden by the quadrupod legs
    r = np.corrcoef(tab.deviation_m[ok], off[ok])[0, 1]
    assert r > 0.95
    k, dent = DENT
    assert tab.deviation_m[k] == pytest.approx(dent, abs=1.5e-4)
    assert tab.deviation_m[k] < -4e-4
    assert tab.sigma_m[k] < 1e-4
    # per cycle too, but the average is closer to the truth
    cyc = [res.positions[0].cycle_panels[c.scan] for c in res.positions[0].cycles]
    err_avg = np.nanstd(tab.deviation_m - off)
    for t in cyc:
        assert np.nanstd(t.deviation_m - off) > err_avg


def test_kappa_and_panel_ids_at_several_positions(tmp_path):
    """North alignment and panel ids against the simulator's truth at tilted positions and at
    the zenith (where kappa comes from the quadrupod shadows, resolved by the mount heading)."""
    step = 0.015
    positions = [("p1", -60.0, -20.0), ("p2", 45.0, 10.0), ("zen", 0.0, -25.8897),
                 ("p4", 30.0, -75.0)]
    camp = simulate_campaign(tmp_path / "camp", preset="clean", seed=11, step_rad=step,
                             positions=positions, cycles=(1,))
    cf = fit_campaign(camp, "simplified", progress=False)
    res = surface_from_fit(cf)
    truth = {s["id"]: s for s in json.loads((camp.root / "truth.json").read_text())["scans"]}
    for s, pos in zip(cf.scans, res.positions):
        zenith = s.meta.position == "zen"
        k_true = truth[s.meta.id]["kappa_rad"]
        dk = math.remainder(s.alignment.kappa_rad - k_true, 2 * math.pi)
        # away from the zenith gravity fixes kappa; at the zenith the leg shadows do (the gaps'
        # middles over many rings: a fraction of the step; what is left is the shadows' own
        # offset from the leg azimuths, ~1 mrad for a scanner 1 cm off the axis)
        assert abs(dk) < (3e-3 if zenith else 1e-3), (s.meta.id, s.alignment, k_true)
        t = pq.read_table(camp.root / "truth" / f"{s.meta.id}.parquet").to_pydict()
        tp = np.asarray(t["panel"])[s.data.row]
        # panel ids of the (masked) surface points against the simulator's panel column
        mine = pos.cycles[0].panel
        sel = (mine >= 0) & (tp[s.used] >= 0)
        assert sel.sum() > 0.8 * s.used.sum()
        agree = np.mean(mine[sel] == tp[s.used][sel])
        print(s.meta.id, s.alignment.source, f"dkappa {dk:+.2e} rad, panel ids agree {agree:.4f}")
        assert agree > (0.995 if zenith else 0.999), (s.meta.id, agree)
        assert pos.kind == "single cycle"
        assert pos.kappa_rad[s.meta.id] == s.alignment.kappa_rad


def test_surface_json_roundtrip_and_schema(panels, tmp_path):
    camp, cf, _ = panels
    res = surface_from_fit(cf)
    p = write_surface(tmp_path / "out", res)
    doc = json.loads(p.read_text())
    assert doc["schema"] == SURFACE_SCHEMA
    pos = doc["positions"][0]
    assert pos["position"] == "r23" and pos["kind"] == "cycle average"
    assert len(pos["panels"]) == 255
    rec = pos["panels"][DENT[0]]
    for key in ("panel", "deviation_m", "sigma_m", "tilt_rad", "rms_m", "n"):
        assert key in rec
    assert rec["panel"] == DENT[0] and rec["n"] > 0
    assert (tmp_path / "out" / pos["points_file"]).exists()
    for c in pos["cycles"]:
        assert (tmp_path / "out" / c["points_file"]).exists()
    back = read_surface(tmp_path / "out")
    np.testing.assert_allclose(back.positions[0].panels.deviation_m,
                               res.positions[0].panels.deviation_m, equal_nan=True)
    assert len(back.positions[0].averaged) == len(res.positions[0].averaged)
    assert [c.scan for c in back.positions[0].cycles] == ["r23c1", "r23c2"]


def test_surface_from_fit_dir_matches_fit(panels):
    camp, cf, d = panels
    a = surface_from_fit(cf).positions[0].panels.deviation_m
    b = surface_from_fit_dir(d / "fit", campaign=camp).positions[0].panels.deviation_m
    np.testing.assert_allclose(a, b, equal_nan=True, atol=1e-12)


def test_surface_cli(panels, tmp_path):
    from click.testing import CliRunner

    import hartrao_jax.cli._surface  # noqa: F401  (registers the commands)
    from hartrao_jax.cli import main

    camp, _, d = panels
    out = tmp_path / "surf"
    r = CliRunner().invoke(main, ["surface", str(camp.root), "--out", str(out), "--fit",
                                  str(d / "fit"), "--margin", "0.03"])
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "surface.json").read_text())
    assert doc["config"]["margin_radial_m"] == 0.03
    assert doc["disturbed"] == []
    r = CliRunner().invoke(main, ["surface", str(camp.root), "--out", str(out), "--fit",
                                  str(d / "fit"), "--exclude-disturbed", "--cut-disturbed"])
    assert r.exit_code == 2 and "choose one" in r.output


def test_surface_campaign_fits_when_no_fit_dir(tmp_path):
    camp = simulate_campaign(tmp_path / "camp", preset="clean", seed=2, step_rad=0.02)
    res = surface_campaign(load_campaign(camp.root), SurfaceConfig(model="simplified"),
                           tmp_path / "out", preprocess=False)
    assert (tmp_path / "out" / "surface.json").exists()
    assert (tmp_path / "out" / "fit" / "fit.json").exists()
    assert res.positions[0].kind == "cycle average"
    assert res.source["model"] == ["tx", "ty", "tz", "rx", "ry", "f"]
