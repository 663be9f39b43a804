"""Streaming adjustment (bounded memory) and the Dask scale-out, against the in-process fit."""

from __future__ import annotations

import json

import numpy as np
import pytest

import hartrao_jax  # noqa: F401  (float64)
from hartrao_jax._campaign import read_scan
from hartrao_jax._config import enable_compilation_cache
from hartrao_jax._fit import fit_campaign, fit_json, fit_scan, prepare_scan
from hartrao_jax._schedule import find_position
from hartrao_jax._simulate import simulate_campaign
from hartrao_jax._stream import peak_rss_gib, stream_fit_scan

enable_compilation_cache()


def _pos(*names):
    out = []
    for n in names:
        p = find_position(n).simulator_position()
        out.append({k: p[k] for k in ("position", "ha_deg", "dec_deg", "tour")})
    return out


@pytest.fixture(scope="module")
def scatter_campaign(tmp_path_factory):
    """Demo effects with scatter: the robust rounds reject points."""
    out = tmp_path_factory.mktemp("stream")
    return simulate_campaign(out / "camp", preset="demo", positions=_pos("r23"), step_rad=0.03,
                             seed=1)


def test_stream_equals_in_memory(scatter_campaign, tmp_path):
    camp = scatter_campaign
    meta = camp.scan("r23c1")
    data = read_scan(camp, meta)
    _, _, init, window = prepare_scan(camp, meta, data)
    ref = fit_scan(camp, meta, "extended", data=data)  # robust, no preprocessing
    assert ref.n_rejected > 0
    rows = max(1000, len(data) // 5)  # several chunks, a short last one
    st = stream_fit_scan(camp, meta, "extended", rows_per_chunk=rows, init=init,
                         store=tmp_path / "store")
    np.testing.assert_allclose((st.x - ref.x) / ref.sigma, 0.0, atol=1e-6)
    np.testing.assert_allclose(st.sigma, ref.sigma, rtol=1e-6)
    assert st.sigma0 == pytest.approx(ref.sigma0, rel=1e-9)
    assert (st.n_points, st.n_rejected, st.n_window) == (ref.n_points, ref.n_rejected,
                                                         ref.n_window)
    assert st.passes >= st.iterations + 2 and st.converged
    v = np.load(tmp_path / "store" / "v.npy", mmap_mode="r")
    w = np.load(tmp_path / "store" / "w.npy", mmap_mode="r")
    np.testing.assert_allclose(v[data.row][ref.used], ref.v[ref.used], atol=1e-10)
    np.testing.assert_array_equal(w[data.row] > 0, ref.used)
    assert peak_rss_gib() > 0


def test_stream_with_its_own_initial_values(scatter_campaign, tmp_path):
    camp = scatter_campaign
    ref = fit_scan(camp, camp.scan("r23c2"), "extended")
    st = stream_fit_scan(camp, "r23c2", "extended", rows_per_chunk=7000, store=tmp_path / "s")
    np.testing.assert_allclose((st.x - ref.x) / ref.sigma, 0.0, atol=0.05)


def _small(tmp_path_factory, *names):
    out = tmp_path_factory.mktemp("dask")
    return simulate_campaign(out / "camp", preset="clean", positions=_pos(*names),
                             step_rad=0.03, seed=4,
                             effects={"x4": 1e-4, "x6": 3e-5, "x7": -4e-5})


@pytest.fixture(scope="module")
def small_campaign(tmp_path_factory):
    return _small(tmp_path_factory, "r23")


@pytest.fixture(scope="module")
def zenith_campaign(tmp_path_factory):
    """A tilted position and the zenith: the zenith's north alignment needs the heading from
    the tilted one (two phases on the workers)."""
    return _small(tmp_path_factory, "r23", "r1")


def _compare_docs(a, b, rtol=1e-9):
    assert a.keys() == b.keys()
    assert [s["id"] for s in a["scans"]] == [s["id"] for s in b["scans"]]
    for sa, sb in zip(a["scans"], b["scans"]):
        assert sa.keys() == sb.keys()
        for n, e in sb["estimates"].items():
            assert sa["estimates"][n]["value"] == pytest.approx(
                e["value"], rel=rtol, abs=1e-6 * e["sigma"])
            assert sa["estimates"][n]["sigma"] == pytest.approx(e["sigma"], rel=1e-6)
        for k in ("sigma0", "n_points", "n_rejected", "kappa_rad", "rms_deviation_m"):
            assert sa[k] == pytest.approx(sb[k], rel=1e-8, abs=1e-12), k
    for pa, pb in zip(a["positions"], b["positions"]):
        assert pa["position"] == pb["position"]
        assert pa["f"]["value"] == pytest.approx(pb["f"]["value"], rel=1e-12)


def test_dask_local_cluster_equals_in_process(small_campaign, tmp_path):
    """Per-scan fits on 2 workers, then the joint adjustment over the worker-resident scans
    (only normal matrices travel): both equal to the in-process results."""
    _dask_equals_in_process(small_campaign, tmp_path)


@pytest.mark.slow
def test_dask_with_the_zenith_equals_in_process(zenith_campaign, tmp_path):
    _dask_equals_in_process(zenith_campaign, tmp_path)


def _dask_equals_in_process(camp, tmp_path):
    pytest.importorskip("distributed")
    from hartrao_jax._distributed import fit_dask, fit_document
    from hartrao_jax._joint import fit_joint, joint_json

    local = fit_campaign(camp, "extended", progress=False)
    res = fit_dask(camp, "extended", n_workers=2, preprocess=False, joint=True,
                   group="campaign", out_dir=tmp_path / "dask")
    assert res.n_workers == 2
    assert all(s.worker.startswith("tcp://") for s in res.summaries)  # fitted on workers
    _compare_docs(fit_document(camp, local.model_names, res.summaries), fit_json(local))
    jd = joint_json(fit_joint(camp, start=local, group="campaign"))
    on_disk = json.loads((tmp_path / "dask" / "fit.json").read_text())
    assert on_disk["schema"] == "hartrao-fit/1"
    _compare_docs(on_disk, jd, rtol=1e-9)
    for n in ("x4", "x6", "x7"):
        assert on_disk["shared"][n]["value"] == pytest.approx(jd["shared"][n]["value"], rel=1e-9)
        assert on_disk["shared"][n]["sigma"] == pytest.approx(jd["shared"][n]["sigma"], rel=1e-9)
    assert on_disk["joint"]["iterations"] == jd["joint"]["iterations"]
    assert (tmp_path / "dask" / "residuals" / "r23c1.parquet").is_file()


def test_cli_fit_stream(scatter_campaign, tmp_path):
    from click.testing import CliRunner

    import hartrao_jax._cli_campaign  # noqa: F401  (registers the commands)
    from hartrao_jax.cli import main

    r = CliRunner().invoke(main, ["fit-stream", str(scatter_campaign.root), "--scan", "r23c1",
                                  "--rows-per-chunk", "5000", "--store", str(tmp_path / "s"),
                                  "--json", str(tmp_path / "st.json")])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "st.json").read_text())
    assert doc["schema"] == "hartrao-stream/1" and doc["converged"]
    assert doc["n_points"] > 0 and doc["peak_rss_gib"] > 0
    assert (tmp_path / "s" / "v.npy").is_file()
