"""diagnose on the real GBT recordings: every imported campaign runs, lists what it skips,
never estimates two-face parameters from one face, never prints HartRAO panel ids on the GBT,
and finds a bump injected into the real points (along the fitted normal) at the right place."""

import math
import os
from pathlib import Path

import numpy as np
import pytest

from hartrao_jax.campaign._import import import_file
from hartrao_jax.diagnose import DiagnoseConfig, diagnose
from hartrao_jax.diagnose._recording import two_face_parameters

REAL = Path(os.environ.get("HARTRAO_REAL_DATA",
                           Path(__file__).resolve().parents[3] / "shared" / "real")) / "gbt-lassi"
needs_real = pytest.mark.skipif(not REAL.exists(), reason="real GBT data not present")


def _check_one_face(doc):
    tf = set(two_face_parameters())
    assert not tf & set(doc["start_model"])
    assert not tf & {f["effect"] for f in doc["findings"]}
    for s in doc["scans"].values():
        assert not tf & set(s["estimates"])
    assert {d["parameter"] for d in doc["not_identifiable"]} >= {"x4", "x6", "x7"}
    searches = {k["search"] for k in doc["skipped"]}
    assert {"impulsive_shift", "oscillation", "drift", "covariate:intensity",
            "two-face instrument parameters"} <= searches
    for f in doc["findings"]:  # grid cells, not HartRAO panel numbers
        assert "panels" not in f["where"]
    assert doc["local_deformation_search"]


@needs_real
@pytest.mark.parametrize("name", ["bump1_high_sample.csv", "scan10_random_sample.csv"])
def test_diagnose_runs_on_imported_real_recordings(tmp_path, name):
    camp = import_file(REAL / name, "xyz", tmp_path / "c", telescope="gbt")
    doc = diagnose(camp, "extended").to_json()
    _check_one_face(doc)
    assert math.isfinite(doc["sigma0_start"]) and doc["sigma0_final"] <= doc["sigma0_start"]
    s = doc["local_deformation_search"][0]
    assert len(s["centre_scan_m"]) == 3
    if not s["accepted"]:
        assert "not distinguishable from the reflector's panel-scale roughness" in s["statement"]


@needs_real
@pytest.mark.slow
def test_bump_injected_into_scan10_is_found_at_its_place(tmp_path):
    """A 5 mm, 1 m wide bump added to the real scan-10 points along the fitted normal (the
    injection benchmark: 1-2 mm at 1 m do not stand out from scan 10's own structure)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from real_inject import _normals_and_residuals

    csv = REAL / "scan10_random_sample.csv"
    camp = import_file(csv, "xyz", tmp_path / "c", telescope="gbt")
    sc, n_file = _normals_and_residuals(camp)
    c, a, w = np.array([60.0, -10.0]), 5e-3, 1.0
    xyz = np.loadtxt(csv, delimiter=",")
    g = np.exp(-np.sum((sc.X_tel[:, :2] - c) ** 2, 1) / (2 * w * w))
    xyz[np.asarray(sc.data.row)] += (a * g)[:, None] * n_file
    f = tmp_path / "inj.csv"
    np.savetxt(f, xyz, delimiter=",", fmt="%.6f")
    doc = diagnose(import_file(f, "xyz", tmp_path / "i", telescope="gbt"), "extended",
                   config=DiagnoseConfig(effects=("local_deformation",))).to_json()
    hit = [x for x in doc["findings"] if x["effect"] == "local_deformation"]
    assert hit, doc["local_deformation_search"]
    e, wh = hit[0]["estimate"], hit[0]["where"]
    assert math.hypot(wh["x_m"] - c[0], wh["y_m"] - c[1]) < 0.5
    assert abs(e["amplitude_m"]["value"] - a) < 3 * e["amplitude_m"]["sigma"]
    assert abs(e["width_m"]["value"] - w) < 3 * e["width_m"]["sigma"]
