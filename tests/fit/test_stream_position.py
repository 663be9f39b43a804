"""Streamed two-face position adjustment: equals the in-memory one, holds what it holds."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hartrao_jax.campaign._campaign import load_campaign
from hartrao_jax.fit._fit import fit_campaign
from hartrao_jax.fit._stream_position import stream_fit_position, stream_fit_positions
from hartrao_jax.geometry import square_cells
from hartrao_jax.simulate._simulate import simulate_campaign

EFFECTS = {"x4": 1.5e-4, "x6": 3e-5, "x7": -4e-5, "panel_offset": 1.5e-4}


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    root = tmp_path_factory.mktemp("sp")
    c = simulate_campaign(root / "c", preset="demo", effects=EFFECTS, seed=5, step_rad=0.03,
                          positions=[("r23", -35.0, -64.0)])
    return load_campaign(c.root)


def test_streamed_position_equals_in_memory(campaign, tmp_path):
    """Started from a 40 % sample per face, refined from every row in 4 chunks per face: the
    estimates, sigmas and variance components of the in-memory two-face adjustment."""
    ref = fit_campaign(campaign, "extended", progress=False).position_fits[0]
    ids = [m.id for m in campaign.scans]
    rec = stream_fit_position(campaign, ids, "extended", rows_per_chunk=4000, n_sample=6000,
                              store=tmp_path / "st")
    assert rec["faces"] == 2 and rec["converged"]
    for name, v, s in zip(ref.names, ref.x, ref.sigma):
        assert abs(rec[name]["value"] - v) < 0.05 * s, name
        assert rec[name]["sigma"] == pytest.approx(s, rel=0.05), name
    for name, sw in zip(ref.names, ref.sigma_white):  # the same split into noise and surface
        assert rec[name]["sigma_white"] == pytest.approx(sw, rel=0.05), name
    assert rec["variance_components"]["surface_m"] == pytest.approx(
        np.sqrt(ref.surface.variances["offset_m2"]), rel=0.05)
    assert abs(rec["n_points"] - ref.n_points) <= 0.001 * ref.n_points
    for s in rec["scans"]:
        w = np.load(tmp_path / "st" / s["scan"] / "w.npy")
        assert len(w) == s["n_rows"] and int(np.sum(w > 0)) == s["n_points"]
        assert 0.8 < s["sigma0"] < 1.25
    json.dumps(rec, allow_nan=False)
    # without a store: no per-point results, no final pass, the same answer
    bare = stream_fit_position(campaign, ids, "extended", rows_per_chunk=4000, n_sample=6000)
    assert bare["passes"] == rec["passes"] - 1 and bare["store"] is None
    assert all(s["store"] is None for s in bare["scans"])
    for name, s in zip(ref.names, ref.sigma):
        assert abs(bare[name]["value"] - rec[name]["value"]) < 0.01 * s, name
        assert bare[name]["sigma"] == pytest.approx(rec[name]["sigma"], rel=0.01), name
    assert bare["sigma0"] == pytest.approx(rec["sigma0"], rel=1e-3)


def test_streamed_one_face_holds_the_two_face_parameters(campaign, tmp_path):
    doc = stream_fit_positions(campaign, ["r23c1"], "extended", rows_per_chunk=5000,
                               store=tmp_path / "one")
    (rec,) = doc["positions"]
    assert rec["faces"] == 1 and rec["kind"] == "one face"
    assert rec["x6"]["identifiable"] is False and rec["x6"]["sigma"] is None
    assert [s["scan"] for s in doc["scans"]] == ["r23c1"]


def test_square_cells_with_fixed_keys_keep_the_numbering():
    rng = np.random.default_rng(0)
    X = rng.uniform(-10, 10, (500, 3))
    cell, local, keys = square_cells(X, 2.0)
    part = X[::3]
    c2, l2, k2 = square_cells(part, 2.0, keys)
    assert np.array_equal(c2, cell[::3]) and np.allclose(l2, local[::3]) and k2 is not None
    far = np.array([[100.0, 100.0, 0.0]])
    assert square_cells(far, 2.0, keys)[0][0] == -1


def test_streamed_position_with_smooth_modes_converges_to_the_in_memory_one(tmp_path):
    """Gravity's astigmatism and coma carried as random effects (the modes' path through
    per-point Zernike columns and the cached chunk geometry): the streamed refinement
    converges in a few passes (recomputing cells and columns from the current solution made it
    oscillate at 0.03-0.06 sigma up to max_iter) to the in-memory estimates."""
    c = simulate_campaign(tmp_path / "g", preset="demo", effects={
        **EFFECTS, "gravity_deformation": 3.0}, seed=2, step_rad=0.015,
        positions=[("g2", 40.0, -70.0)])
    camp = load_campaign(c.root)
    ref = fit_campaign(camp, "extended", progress=False).position_fits[0]
    assert ref.surface.mode_tests["modes"]["carried"] and ref.mixed.modes
    rec = stream_fit_position(camp, [m.id for m in camp.scans], "extended",
                              rows_per_chunk=20_000, n_sample=20_000)
    assert rec["converged"] and rec["passes"] <= 4
    for name, v, s in zip(ref.names, ref.x, ref.sigma):
        assert abs(rec[name]["value"] - v) < 0.25 * s, name  # measured: at most 0.13
        assert rec[name]["sigma"] == pytest.approx(s, rel=0.01), name  # 0.15 %


def test_remaining_error_from_contracting_steps():
    """The error left after the last step: the step itself, or the geometric rest of steps
    that contract fast (the full-resolution position's 3.1, 0.082 sigma -> 0.0022)."""
    import pytest

    from hartrao_jax.fit._stream_position import _remaining

    assert _remaining([0.5]) == 0.5
    assert _remaining([3.119, 0.08194]) == pytest.approx(0.08194 * 0.02627 / 0.97373, rel=1e-3)
    assert _remaining([0.1, 0.06]) == 0.06  # contracting slowly: the step itself
    assert _remaining([0.0, 0.0]) == 0.0


def test_a_streamed_campaign_streams_a_position_taking_the_campaign_prior_once(tmp_path,
                                                                               monkeypatch):
    """r23 under gravity shows no smooth mode but its pose takes up coma: its start (the
    sample's adjustment) says so, so the campaign defers it and streams it once, after g1 and
    g2 gave their mode variance, with the modes carried at the median of theirs; g1 and g2
    are streamed once each, as without a deferral."""
    import hartrao_jax.fit._stream_position as SP

    camp = load_campaign(simulate_campaign(
        tmp_path / "g", preset="demo", seed=0, step_rad=0.012,
        effects={**EFFECTS, "gravity_deformation": 1.0},
        positions=[("r23", -35.0, -64.0), ("g1", -60.0, -30.0), ("g2", 40.0, -70.0)]).root)
    calls, inner = [], SP.stream_fit_position

    def counted(*a, **k):
        rec = inner(*a, **k)
        calls.append((rec["position"], bool(rec.get("deferred")), k.get("mode_prior_m2")))
        return rec

    monkeypatch.setattr(SP, "stream_fit_position", counted)
    doc = stream_fit_positions(camp, None, "extended", rows_per_chunk=50_000)
    by = {p["position"]: p for p in doc["positions"]}
    others = [by[q]["variance_components"]["modes_m"] for q in ("g1", "g2")]
    prior = float(np.median(np.square(others)))
    assert sorted(calls) == sorted([("r23", True, None), ("g1", False, None),
                                    ("g2", False, None), ("r23", False, prior)])
    p = by["r23"]
    assert "deferred" not in p and "zern_7" in p["surface_modes"]
    assert any("carried with the campaign's variance" in n for n in p["notes"])
    assert p["variance_components"]["modes_m"] == pytest.approx(np.sqrt(prior), rel=1e-6)
    for n in ("tx", "ty", "rx", "ry"):
        assert p[n]["mode_prior_share"] > 0.5
    assert [s["scan"] for s in doc["scans"]] == [m.id for m in camp.scans]
