"""Streaming adjustment (bounded memory) and the Dask scale-out, against the in-process fit."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

import hartrao_jax  # noqa: F401  (float64)
from hartrao_jax._config import enable_compilation_cache
from hartrao_jax.campaign._campaign import load_campaign, read_scan
from hartrao_jax.campaign._schedule import find_position
from hartrao_jax.fit._fit import RESUMED_NOTE, fit_campaign, fit_scan, prepare_scan
from hartrao_jax.fit._records import fit_json
from hartrao_jax.fit._stream import peak_rss_gib, stream_fit_scan
from hartrao_jax.simulate._simulate import simulate_campaign

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
    # one read of the file per iteration, the rejection inside it: the in-memory iteration
    assert st.passes == st.iterations == ref.iterations and st.converged and st.rounds > 1
    assert st.iterations == sum(st.round_iterations) and len(st.round_iterations) == st.rounds
    assert st.stalled_rounds == []
    v = np.load(tmp_path / "store" / "v.npy", mmap_mode="r")
    w = np.load(tmp_path / "store" / "w.npy", mmap_mode="r")
    e = np.load(tmp_path / "store" / "e.npy", mmap_mode="r")
    np.testing.assert_allclose(v[data.row][ref.used], ref.v[ref.used], atol=1e-10)
    np.testing.assert_array_equal(w[data.row] > 0, ref.used)
    np.testing.assert_allclose(e[data.row], ref.normalized, rtol=1e-6, atol=1e-8)
    assert sorted(p.name for p in (tmp_path / "store").iterdir()) == ["e.npy", "v.npy", "w.npy"]
    assert peak_rss_gib() > 0


def test_stream_without_rejection(scatter_campaign, tmp_path):
    """robust_k=None: one adjustment; the residuals come from the kernel's store (no extra
    read of the file), passes = iterations."""
    camp = scatter_campaign
    meta = camp.scan("r23c1")
    data = read_scan(camp, meta)
    _, _, init, _ = prepare_scan(camp, meta, data)
    ref = fit_scan(camp, meta, "extended", data=data, robust_k=None)
    st = stream_fit_scan(camp, meta, "extended", rows_per_chunk=len(data) // 3, init=init,
                         robust_k=None, store=tmp_path / "s")
    np.testing.assert_allclose((st.x - ref.x) / ref.sigma, 0.0, atol=1e-6)
    assert st.sigma0 == pytest.approx(ref.sigma0, rel=1e-9)
    assert st.rounds == 1 and st.passes == st.iterations == ref.iterations and st.converged
    v = np.load(tmp_path / "s" / "v.npy")
    e = np.load(tmp_path / "s" / "e.npy")
    np.testing.assert_allclose(v[data.row], ref.v, atol=1e-10)
    np.testing.assert_allclose(e[data.row], ref.normalized, rtol=1e-6, atol=1e-8)


def test_stream_to_max_iter_equals_in_memory(scatter_campaign, tmp_path):
    """A tolerance below round-off: the in-memory and the streamed robust iteration both run to
    max_iter, rejecting inside the iteration, with the same rejections and estimates (no
    robust rounds, so no round stalls: formerly a stalled round was checked early here)."""
    from hartrao_jax.fit._fit import _x0, scan_arrays, sigma_vector
    from hartrao_jax.model._model import make_model
    from hartrao_jax.solver._ghm import robust_gauss_helmert

    camp = scatter_campaign
    meta = camp.scan("r23c1")
    data = read_scan(camp, meta)
    _, _, init, window = prepare_scan(camp, meta, data)
    mdl = make_model("extended", aperture_radius_m=camp.telescope.diameter_m / 2)
    obs, c = scan_arrays(data)
    w = window.astype(float)
    kw = dict(max_iter=8, tol=1e-30)
    res = robust_gauss_helmert(mdl, obs, _x0(mdl.free, init, {}), sigma_vector(camp), c, w,
                               k=4.0, **kw)
    assert int(res.iterations) == 8 and not bool(res.converged)
    st = stream_fit_scan(camp, meta, "extended", rows_per_chunk=len(data) // 2, init=init,
                         store=tmp_path / "s", **kw)
    assert st.iterations == 8 and not st.converged and st.rounds > 1
    assert st.stalled_rounds == []
    assert st.n_points == int(np.sum(np.asarray(res.weights) > 0))
    sig = np.sqrt(np.diag(np.asarray(res.cov)))
    np.testing.assert_allclose((st.x - np.asarray(res.x)) / sig, 0.0, atol=1e-6)
    assert st.sigma0 == pytest.approx(float(res.sigma0), rel=1e-9)


def test_stream_blocks_in_threads_equal_one_thread(scatter_campaign, tmp_path, monkeypatch):
    """A chunk's compute blocks run in two threads: the same sums added in the same order."""
    from hartrao_jax.fit import _stream
    from hartrao_jax.solver._kernel import PART_CHUNK

    # the kernel's chunk of blocks in threads (at most PART_CHUNK) for one thread as well
    monkeypatch.setattr(_stream, "INNER_CHUNK", PART_CHUNK)
    monkeypatch.setattr(_stream, "BLOCK", _stream.INNER_CHUNK)  # several blocks per chunk
    camp = scatter_campaign
    meta = camp.scan("r23c1")
    _, _, init, _ = prepare_scan(camp, meta)
    kw = dict(rows_per_chunk=4 * _stream.INNER_CHUNK, init=init)
    one = stream_fit_scan(camp, meta, "extended", threads=1, store=tmp_path / "a", **kw)
    two = stream_fit_scan(camp, meta, "extended", threads=2, store=tmp_path / "b", **kw)
    np.testing.assert_array_equal(two.x, one.x)
    assert (two.sigma0, two.iterations, two.n_points) == (one.sigma0, one.iterations,
                                                          one.n_points)
    np.testing.assert_array_equal(np.load(tmp_path / "b" / "v.npy"),
                                  np.load(tmp_path / "a" / "v.npy"))


def test_stream_with_its_own_initial_values(scatter_campaign, tmp_path):
    camp = scatter_campaign
    ref = fit_scan(camp, camp.scan("r23c2"), "extended")
    st = stream_fit_scan(camp, "r23c2", "extended", rows_per_chunk=7000, store=tmp_path / "s")
    np.testing.assert_allclose((st.x - ref.x) / ref.sigma, 0.0, atol=0.05)


def test_padded_fit_equals_fit_scan(scatter_campaign):
    """The padded fit (rows padded to a bucket size: one compiled program per campaign, not
    per scan) gives the unpadded results, rejected points included, on the scan's own rows."""
    from hartrao_jax.fit._joint import bucket_size

    camp = scatter_campaign
    meta = camp.scan("r23c1")
    data = read_scan(camp, meta)
    assert bucket_size(len(data)) > len(data)
    ref = fit_scan(camp, meta, "extended", data=data, pad=False)
    pad = fit_scan(camp, meta, "extended", data=data)
    assert ref.n_rejected > 0
    np.testing.assert_allclose((pad.x - ref.x) / ref.sigma, 0.0, atol=1e-6)
    np.testing.assert_allclose(pad.sigma, ref.sigma, rtol=1e-8)
    assert pad.sigma0 == pytest.approx(ref.sigma0, rel=1e-10)
    assert (pad.n_points, pad.n_rejected, pad.n_window, pad.iterations) == (
        ref.n_points, ref.n_rejected, ref.n_window, ref.iterations)
    assert pad.data is data
    for k in ("used", "v", "normalized", "deviation_m", "X_tel"):
        assert len(getattr(pad, k)) == len(data), k
    np.testing.assert_array_equal(pad.used, ref.used)
    np.testing.assert_allclose(pad.deviation_m, ref.deviation_m, atol=1e-12)
    assert pad.alignment.kappa_rad == pytest.approx(ref.alignment.kappa_rad, abs=1e-12)


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
            if e["sigma"] is None:  # not identifiable here: held, or (per cycle) not reported
                mine = sa["estimates"][n]
                assert mine["sigma"] is None and mine["note"] == e["note"], n
                assert mine["value"] == (None if e["value"] is None
                                         else pytest.approx(e["value"], rel=rtol)), n
                continue
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
    from hartrao_jax.fit._distributed import (
        MALLOC_VAR,
        close_client,
        fit_dask,
        fit_document,
        start_client,
    )
    from hartrao_jax.fit._joint import fit_joint, joint_json

    # the joint adjustment starts from per-cycle fits, on the workers as in-process
    local = fit_campaign(camp, "extended", progress=False, per_cycle=True)
    two_face = fit_campaign(camp, "extended", progress=False)
    client, cluster = start_client(n_workers=2)
    try:
        # Dask's default MALLOC_TRIM_THRESHOLD_ tripled the workers' CPU time per scan
        envs = client.run(lambda: __import__("os").environ.get(MALLOC_VAR))
        assert set(envs.values()) == {None}, envs
        res = fit_dask(camp, "extended", client=client, preprocess=False, joint=True,
                       group="campaign", out_dir=tmp_path / "dask")
        # the default: one task per position, both faces adjusted together
        pos = fit_dask(camp, "extended", client=client, preprocess=False,
                       out_dir=tmp_path / "dask2")
    finally:
        close_client(client, cluster)
    written = json.loads((tmp_path / "dask2" / "fit.json").read_text())
    written.pop("files", None)  # the manifest of the crash-safe output directory
    _compare_docs(written, fit_json(two_face))
    assert all(s.worker.startswith("tcp://") for s in pos.summaries)
    assert res.n_workers == 2
    assert all(s.worker.startswith("tcp://") for s in res.summaries)  # fitted on workers
    _compare_docs(fit_document(camp, local.model_names, res.summaries), fit_json(local))
    jd = joint_json(fit_joint(camp, start=local, group="campaign"))
    on_disk = json.loads((tmp_path / "dask" / "fit.json").read_text())
    on_disk.pop("files", None)  # the manifest of the crash-safe output directory
    assert on_disk["schema"] == "hartrao-fit/1"
    _compare_docs(on_disk, jd, rtol=1e-9)
    for n in ("x4", "x6", "x7"):
        assert on_disk["shared"][n]["value"] == pytest.approx(jd["shared"][n]["value"], rel=1e-9)
        assert on_disk["shared"][n]["sigma"] == pytest.approx(jd["shared"][n]["sigma"], rel=1e-9)
    assert on_disk["joint"]["iterations"] == jd["joint"]["iterations"]
    assert (tmp_path / "dask" / "residuals" / "r23c1.parquet").is_file()


def test_cli_fit_stream(scatter_campaign, tmp_path):
    from click.testing import CliRunner

    import hartrao_jax.cli._campaign  # noqa: F401  (registers the commands)
    from hartrao_jax.cli import main

    r = CliRunner().invoke(main, ["fit-stream", str(scatter_campaign.root), "--scan", "r23c1",
                                  "--rows-per-chunk", "5000", "--store", str(tmp_path / "s"),
                                  "--json", str(tmp_path / "st.json"), "--per-cycle"])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "st.json").read_text())
    assert doc["schema"] == "hartrao-stream/1" and doc["converged"]
    assert doc["n_points"] > 0 and doc["peak_rss_gib"] > 0
    assert (tmp_path / "s" / "v.npy").is_file()


@pytest.mark.slow  # a worker compiling its own programs: about 20 s with an empty cache
def test_cli_fit_stream_on_dask_equals_in_process(scatter_campaign, tmp_path):
    """``fit-stream --dask`` (its workers keeping freed memory from their start) gives the
    in-process streamed position's estimates, and leaves this process's environment as it
    was."""
    pytest.importorskip("distributed")
    from click.testing import CliRunner

    import hartrao_jax.cli._campaign  # noqa: F401  (registers the commands)
    from hartrao_jax._config import keep_freed_environment
    from hartrao_jax.cli import main

    kept = keep_freed_environment()
    assert kept
    before = {k: os.environ.get(k) for k in kept}
    docs = []
    for extra in ([], ["--dask", "--workers", "1"]):
        out = tmp_path / f"st{len(extra)}.json"
        r = CliRunner().invoke(main, ["fit-stream", str(scatter_campaign.root), "--rows-per-chunk",
                                      "5000", "--json", str(out), *extra])
        assert r.exit_code == 0, r.output
        docs.append(json.loads(out.read_text()))
    assert {k: os.environ.get(k) for k in kept} == before
    (local,), (remote,) = docs[0]["positions"], docs[1]["positions"]
    assert remote["n_points"] == local["n_points"] > 0
    estimates = [n for n, e in local.items() if isinstance(e, dict) and "sigma" in e]
    assert {"f", "tx", "x4"} <= set(estimates)
    for n in estimates:
        e = local[n]
        assert remote[n]["value"] == pytest.approx(e["value"], rel=1e-10, abs=1e-8 * e["sigma"])


def test_stream_campaign_in_process_and_on_dask(scatter_campaign, tmp_path):
    """Every scan streamed (the full-resolution campaign path): in-process one after the other
    and one task per scan on a 2-worker LocalCluster give the single-scan results; the
    workers keep freed memory (as ``fit-stream --dask`` starts them) from their start on,
    and this process's environment is left as it was."""
    pytest.importorskip("distributed")
    from hartrao_jax._config import keep_freed_environment
    from hartrao_jax.fit._distributed import close_client, start_client
    from hartrao_jax.fit._stream import stream_document, stream_fit_campaign, stream_fit_scan

    camp = scatter_campaign
    ids = [m.id for m in camp.scans]
    assert len(ids) == 2
    one = stream_document(stream_fit_scan(camp, ids[1], "extended", rows_per_chunk=5000,
                                          store=tmp_path / "one"))
    local = stream_fit_campaign(camp, None, "extended", rows_per_chunk=5000,
                                store=tmp_path / "local")
    assert local["schema"] == "hartrao-stream-campaign/1" and local["workers"] is None
    assert [r["scan"] for r in local["scans"]] == ids
    assert (tmp_path / "local" / ids[0] / "v.npy").is_file()
    kept = keep_freed_environment()
    assert kept
    before = {k: os.environ.get(k) for k in kept}
    client, cluster = start_client(n_workers=2, keep_freed=True)
    try:
        assert {k: os.environ.get(k) for k in kept} == before
        seen = client.run(lambda: {k: os.environ.get(k) for k in kept})
        assert list(seen.values()) == [kept] * 2
        remote = stream_fit_campaign(camp, ids, "extended", rows_per_chunk=5000, client=client,
                                     store=tmp_path / "dask")
    finally:
        close_client(client, cluster)
    assert remote["workers"] == 2
    for a, b in zip(local["scans"], remote["scans"]):
        assert a["scan"] == b["scan"] and a["n_points"] == b["n_points"]
        for n, e in a["estimates"].items():
            assert b["estimates"][n]["value"] == pytest.approx(e["value"], rel=1e-10,
                                                               abs=1e-8 * e["sigma"])
    for n, e in one["estimates"].items():
        assert local["scans"][1]["estimates"][n]["value"] == pytest.approx(
            e["value"], rel=1e-10, abs=1e-8 * e["sigma"])


def test_cli_fit_stream_every_scan(scatter_campaign, tmp_path, monkeypatch):
    """Without ``--store`` the per-point results are not kept: nothing is left in the
    temporary directory (a full-resolution scan's results take about 0.5 GB)."""
    import tempfile

    from click.testing import CliRunner

    import hartrao_jax.cli._campaign  # noqa: F401  (registers the commands)
    from hartrao_jax.cli import main

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    r = CliRunner().invoke(main, ["fit-stream", str(scatter_campaign.root), "--rows-per-chunk",
                                  "5000", "--json", str(tmp_path / "st.json"), "--per-cycle"])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "st.json").read_text())
    assert doc["schema"] == "hartrao-stream-campaign/1" and len(doc["scans"]) == 2
    assert all(s["converged"] for s in doc["scans"])
    assert "streamed 2 scans" in r.output
    # the default: one two-face adjustment of the position
    r = CliRunner().invoke(main, ["fit-stream", str(scatter_campaign.root), "--rows-per-chunk",
                                  "5000", "--json", str(tmp_path / "pos.json")])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "pos.json").read_text())
    (p,) = doc["positions"]
    assert p["faces"] == 2 and p["converged"] and p["f"]["sigma"] > 0
    assert [s["scan"] for s in doc["scans"]] == ["r23c1", "r23c2"]
    assert "streamed 1 positions (2 scans)" in r.output
    assert p["store"] is None and all(s["store"] is None for s in doc["scans"])
    assert list(tmp.iterdir()) == []
    r = CliRunner().invoke(main, ["fit-stream", str(scatter_campaign.root), "--scan", "nope"])
    assert r.exit_code == 2 and "nope" in r.output


def test_dask_campaign_prior_resumes_on_the_worker_that_holds_it(tmp_path):
    """fit-dask with a position whose pose takes up coma (r23 under gravity, with g1 and g2
    showing the modes): its adjustment with the campaign's variance runs on the worker that
    kept its continuation, and every position equals the in-process fit; nothing stays held
    on the workers afterwards."""
    pytest.importorskip("distributed")
    from hartrao_jax.fit._distributed import (
        close_client,
        fit_dask,
        held_resume_points,
        start_client,
    )

    camp = load_campaign(simulate_campaign(
        tmp_path / "g", preset="demo", seed=0, step_rad=0.012,
        effects={"x4": 1.5e-4, "x6": 3e-5, "x7": -4e-5, "panel_offset": 1.5e-4,
                 "gravity_deformation": 1.0},
        positions=[("r23", -35.0, -64.0), ("g1", -60.0, -30.0), ("g2", 40.0, -70.0)]).root)
    ref = {p["position"]: p for p in fit_json(fit_campaign(camp, "extended",
                                                           progress=False))["positions"]}
    client, cluster = start_client(n_workers=2)
    try:
        fit_dask(camp, "extended", client=client, preprocess=False, out_dir=tmp_path / "out")
        assert set(client.run(held_resume_points).values()) == {0}
    finally:
        close_client(client, cluster)
    got = {p["position"]: p for p in json.loads(
        (tmp_path / "out" / "fit.json").read_text())["positions"]}
    assert any("carried with the campaign's variance" in n for n in got["r23"]["notes"])
    assert RESUMED_NOTE in got["r23"]["notes"] and RESUMED_NOTE in ref["r23"]["notes"]
    for pos, p in ref.items():
        for n in ("tx", "ty", "tz", "rx", "ry", "f", "x4", "x6", "x7"):
            assert got[pos][n]["value"] == pytest.approx(p[n]["value"], abs=1e-6 * p[n]["sigma"])
            assert got[pos][n]["sigma"] == pytest.approx(p[n]["sigma"], rel=1e-6)


def test_a_worker_adds_its_xla_options_to_the_packages(monkeypatch):
    """A remote worker imports the package (which adds its XLA options) before its setup
    runs: the setup adds the worker's own options beside them instead of leaving them out,
    and a variable the worker was started with keeps its values."""
    import hartrao_jax.fit._distributed as dist

    for name in ("set_blas_threads", "enable_x64", "enable_compilation_cache"):
        monkeypatch.setattr(dist, name, lambda: None)
    for k in dist.WORKER_ENV:
        monkeypatch.delenv(k, raising=False)
    ynn = "--xla_cpu_experimental_ynn_fusion_type="
    monkeypatch.setenv("XLA_FLAGS", ynn)
    dist.worker_setup()
    assert os.environ["XLA_FLAGS"].split() == [ynn, dist.WORKER_ENV["XLA_FLAGS"]]
    assert os.environ["OMP_NUM_THREADS"] == "1"
    monkeypatch.setenv("XLA_FLAGS", f"{ynn} --xla_cpu_multi_thread_eigen=true")
    dist.worker_setup()
    assert os.environ["XLA_FLAGS"] == f"{ynn} --xla_cpu_multi_thread_eigen=true"
