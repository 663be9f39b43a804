"""Campaign scale: the simulated 88-position campaign, in-process and on Dask; one streamed
full-resolution scan; a projection of the full-resolution campaign on N workers.

Stages (each timed in its own process, so that start-up, compilation and peak memory are its
own):

1. ``simulate``: ``hartrao-jax simulate --preset campaign`` (88 positions x 2 cycles, the
   paper's schedule, step 0.02 rad by default).
2. ``fit-local``: in-process ``fit`` end to end (read, preprocess, adjust, north alignment,
   residual tables, fit.json), one scan after the other; then the joint adjustment (shared
   calibration per night, Schur complement) and the gravity model.
3. ``fit-dask``: the same fit on a ``LocalCluster(n_workers=2, threads_per_worker=1,
   processes=True)``; its fit.json is compared with the in-process one.
4. ``simulate-full`` / ``stream``: one scan at the paper's resolution (0.63 mrad, ~1.3e7
   rows) streamed from disk in chunks (per-point state in files); wall time and peak RSS.
5. A projection of the full-resolution campaign (176 scans) on N Dask workers from the measured
   per-scan cost.

    python benchmarks/bench_campaign.py [--quick] [--step 0.02] [--work DIR] [--workers 2]

Writes ``benchmarks/results/campaign.md`` and ``.json``. ``--quick``: the red tour's first 6
positions, a 0.0016 rad "full-resolution" scan.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

PY = sys.executable


def _peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _emit(doc: dict) -> None:
    print("@@RESULT@@" + json.dumps(doc))


def _run_stage(args: list[str], timeout: float = 7200) -> dict:
    t0 = time.perf_counter()
    p = subprocess.run([PY, str(Path(__file__).resolve()), *args], capture_output=True,
                       text=True, timeout=timeout, env={**os.environ})
    wall = time.perf_counter() - t0
    res = None
    for line in p.stdout.splitlines():
        if line.startswith("@@RESULT@@"):
            res = json.loads(line[len("@@RESULT@@"):])
    if p.returncode != 0 or res is None:
        sys.stderr.write(p.stdout[-4000:] + p.stderr[-4000:])
        raise RuntimeError(f"stage {args[:2]} failed ({p.returncode})")
    res["process_wall_s"] = wall
    return res


# --------------------------------------------------------------------------------------------
# stages (run in a subprocess)
# --------------------------------------------------------------------------------------------


def stage_simulate(a) -> None:
    from hartrao_jax.simulate._simulate import simulate_campaign

    t0 = time.perf_counter()
    kw = {}
    if a.positions:
        from hartrao_jax.campaign._schedule import plan_positions

        kw["positions"] = plan_positions(["red"])[: a.positions]
    camp = simulate_campaign(a.camp, preset="campaign", step_rad=a.step, seed=0, **kw)
    from hartrao_jax.campaign._campaign import read_scan

    n = [len(read_scan(camp, m)) for m in camp.scans[:4]]
    _emit({"seconds": time.perf_counter() - t0, "scans": len(camp.scans),
           "positions": len(camp.positions()), "rows_per_scan_sample": n,
           "peak_rss_gib": _peak_gib()})


def _keep(camp, preprocess: bool):
    """The preprocessing mask per scan -- and, as fit_campaign calls it once per scan, the place
    to drop JAX's in-memory compilation caches now and then (176 scans of 176 sizes compile
    some thousand programs: without this the process runs out of memory maps, see
    ``_config.release_compiled_programs``)."""
    from hartrao_jax._config import release_compiled_programs

    k = None
    if preprocess:
        from hartrao_jax.preprocess._preprocess import PreprocessConfig, keep_mask_fn

        k = keep_mask_fn(PreprocessConfig(), camp)

    def keep(meta, data):
        release_compiled_programs()
        return k(meta, data) if k is not None else np.ones(len(data), bool)

    return keep


def stage_fit_local(a) -> None:
    from hartrao_jax._config import enable_compilation_cache
    from hartrao_jax.campaign._campaign import load_campaign
    from hartrao_jax.fit._fit import fit_campaign
    from hartrao_jax.fit._records import write_fit

    enable_compilation_cache()
    camp = load_campaign(a.camp)
    out = Path(a.out)
    times = {}
    t0 = time.perf_counter()
    cf = fit_campaign(camp, "extended", keep=_keep(camp, a.preprocess), progress=False)
    times["fit_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    write_fit(out / "fit", cf)
    times["write_s"] = time.perf_counter() - t1
    times["end_to_end_s"] = time.perf_counter() - t0
    if cf.position_fits:
        # the gravity model from the default two-face fit (f with the positions' covariance)
        from hartrao_jax.surface._gravity import write_gravity

        t1 = time.perf_counter()
        temps = all(m.temperature_c is not None for m in camp.scans)
        _, gm = write_gravity(out / "fit", out / "gravity-two-face", temperature=temps)
        times["gravity_two_face_s"] = time.perf_counter() - t1
        times["gravity_two_face"] = {
            "names": list(gm.focal.names), "beta": gm.focal.beta.tolist(),
            "sigma_scaled": gm.focal.sigma_scaled.tolist(), "variance_factor": gm.focal.scale,
            "dof": int(gm.focal.dof), "chi2": float(gm.focal.chi2),
            "corrected_modes": list(gm.corrected_modes)}
    n_rows = sum(len(s.data) for s in cf.scans)
    n_pts = sum(s.n_points for s in cf.scans)
    res = {"scans": len(cf.scans), "positions": len({s.meta.position for s in cf.scans}),
           "rows": n_rows, "points_used": n_pts, **times,
           "converged": sum(s.converged for s in cf.scans),
           "sigma0_median": float(sorted(s.sigma0 for s in cf.scans)[len(cf.scans) // 2])}
    if a.joint:
        from hartrao_jax.fit._joint import fit_joint, write_joint_fit

        t1 = time.perf_counter()
        # from per-cycle fits of the same preprocessed points (the joint adjustment's start)
        jf = fit_joint(camp, group="night", keep=_keep(camp, a.preprocess))
        res["joint_s"] = time.perf_counter() - t1
        res["joint_iterations"] = jf.solution.iterations
        write_joint_fit(out / "joint", jf)
        g = jf.precision_gain()
        c = jf.correlation_drop()["max_abs_corr_f_calibration"]
        est = jf.shared_estimates()
        res["joint"] = {"shared": {gr: {n: list(v) for n, v in e.items()} for gr, e in est.items()},
                        "gain": {n: {gr: d["gain"] for gr, d in g["shared"][n].items()}
                                 for n in g["shared"]},
                        "f_gain_median": g["f"]["gain_median"], "corr": c}
        from hartrao_jax.surface._gravity import write_gravity

        t1 = time.perf_counter()
        temps = all(m.temperature_c is not None for m in camp.scans)
        _, gm = write_gravity(out / "joint", out / "gravity", temperature=temps)
        res["gravity_s"] = time.perf_counter() - t1
        res["gravity"] = {"df_dg_m": gm.c.tolist(), "sigma_scaled": gm.focal.sigma_scaled.tolist(),
                          "names": list(gm.focal.names), "beta": gm.focal.beta.tolist(),
                          "p_value_F": gm.test["p_value_F"], "F": gm.test["F"],
                          "C": gm.C.tolist(), "modes": list(gm.modes),
                          "variance_factor": gm.focal.scale,
                          "corrected_modes": list(gm.corrected_modes)}
        # the old regression of f alone (the modes' take-up by f not corrected), for comparison
        from hartrao_jax.surface._gravity import gravity_model

        raw = gravity_model(out / "joint", temperature=temps, correct_leakage=False)
        res["gravity_raw"] = {"names": list(raw.focal.names), "beta": raw.focal.beta.tolist(),
                              "sigma_scaled": raw.focal.sigma_scaled.tolist(),
                              "variance_factor": raw.focal.scale}
        truth = camp.root / "truth.json"
        if truth.is_file():
            t = json.loads(truth.read_text())
            res["truth"] = {"df_dg_m": t["reflector"]["df_dg_m"],
                            "zernike_per_g_m": t["reflector"]["zernike_per_g_m"],
                            "df_dT_m_per_K": t["reflector"]["df_dT_m_per_K"],
                            "instrument": t["scans"][0]["instrument"]}
    res["peak_rss_gib"] = _peak_gib()
    _emit(res)


def _on_local_cluster(a, run, keep_freed: bool = False):
    """``run(campaign, client)`` on a LocalCluster of ``a.workers`` workers (the campaign of
    ``a.camp``, compilation cache on; ``keep_freed`` as ``fit-stream --dask`` starts them);
    returns its result, the start time (perf_counter) and the cluster's start-up seconds."""
    from hartrao_jax._config import enable_compilation_cache
    from hartrao_jax.campaign._campaign import load_campaign
    from hartrao_jax.fit._distributed import close_client, start_client

    enable_compilation_cache()
    camp = load_campaign(a.camp)
    t0 = time.perf_counter()
    client, cluster = start_client(n_workers=a.workers, keep_freed=keep_freed)
    t_start = time.perf_counter() - t0
    try:
        return run(camp, client), t0, t_start
    finally:
        close_client(client, cluster)


def stage_fit_dask(a) -> None:
    from hartrao_jax.fit._distributed import fit_dask

    res, t0, t_start = _on_local_cluster(a, lambda camp, client: fit_dask(
        camp, "extended", client=client, preprocess=a.preprocess,
        out_dir=Path(a.out) / "fit-dask"))
    per = [s.seconds for s in res.summaries]
    _emit({"scans": len(res.summaries), "cluster_start_s": t_start, "fit_s": res.seconds,
           "end_to_end_s": time.perf_counter() - t0, "workers": res.n_workers,
           "per_scan_s_median": sorted(per)[len(per) // 2], "per_scan_s_sum": sum(per),
           "per_scan_s_max": max(per), "peak_rss_client_gib": _peak_gib()})


def stage_simulate_full(a) -> None:
    from hartrao_jax.simulate._simulate import simulate_campaign

    t0 = time.perf_counter()
    camp = simulate_campaign(a.camp, preset="paper", step_rad=a.step, seed=0, cycles=(1,))
    import pyarrow.parquet as pq

    rows = pq.ParquetFile(camp.root / camp.scans[0].file).metadata.num_rows
    _emit({"seconds": time.perf_counter() - t0, "rows": rows, "peak_rss_gib": _peak_gib(),
           "file_gib": (camp.root / camp.scans[0].file).stat().st_size / 2**30})


def stage_stream(a) -> None:
    from hartrao_jax._config import enable_compilation_cache
    from hartrao_jax.campaign._campaign import load_campaign
    from hartrao_jax.fit._stream import stream_fit_scan

    enable_compilation_cache()
    camp = load_campaign(a.camp)
    base = _peak_gib()
    t0 = time.perf_counter()
    r = stream_fit_scan(camp, camp.scans[0], "extended", rows_per_chunk=a.rows_per_chunk,
                        store=Path(a.out) / "store")
    wall = time.perf_counter() - t0
    _emit({"seconds": wall, "rows": r.n_rows, "points": r.n_points, "rejected": r.n_rejected,
           "outside_window": r.n_window, "iterations": r.iterations, "rounds": r.rounds,
           "passes": r.passes, "round_iterations": r.round_iterations,
           "stalled_rounds": r.stalled_rounds, "converged": r.converged, "sigma0": r.sigma0,
           "f": r.estimates["f"], "x4": r.estimates["x4"], "timings": r.timings,
           "rows_per_chunk": a.rows_per_chunk, "peak_rss_gib": _peak_gib(),
           "peak_rss_before_gib": base,
           "file_gib": (camp.root / camp.scans[0].file).stat().st_size / 2**30,
           "s_per_pass": r.timings["adjustment_s"] / max(r.passes, 1),
           "store_gib": sum(p.stat().st_size for p in (Path(a.out) / "store").glob("*.npy"))
           / 2**30})


def stage_stream_dask(a) -> None:
    """Every position of ``--camp`` streamed as one two-face adjustment per position (the
    full-resolution path: ``fit-stream --dask``), one Dask task per position on ``--workers``
    worker processes of one thread; the per-point results are not kept."""
    from hartrao_jax.fit._stream_position import stream_fit_positions

    doc, t0, t_start = _on_local_cluster(a, lambda camp, client: stream_fit_positions(
        camp, None, "extended", rows_per_chunk=a.rows_per_chunk, client=client),
        keep_freed=True)
    recs = doc["positions"]
    _emit({"positions": len(recs), "scans": len(doc["scans"]), "cluster_start_s": t_start,
           "fit_s": doc["seconds"], "end_to_end_s": time.perf_counter() - t0,
           "workers": doc["workers"], "rows": sum(r["n_rows"] for r in recs),
           "per_position": [{k: r[k] for k in ("position", "n_rows", "n_points", "passes",
                                                 "seconds", "peak_rss_gib", "sigma0")}
                            | {"f": r["f"], "converged": r["converged"],
                               "campaign_prior": any("campaign's variance" in n
                                                     for n in r.get("notes", []))}
                            for r in recs]})


# --------------------------------------------------------------------------------------------
# orchestration
# --------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", default=None)
    ap.add_argument("--camp", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--step", type=float, default=0.02)
    ap.add_argument("--full-step", type=float, default=0.00063)
    ap.add_argument("--positions", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rows-per-chunk", type=int, default=1_000_000)
    ap.add_argument("--work", default="/tmp/hartrao-bench-campaign")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-preprocess", dest="preprocess", action="store_false")
    ap.add_argument("--no-joint", dest="joint", action="store_false")
    ap.add_argument("--skip", default="", help="comma-separated: local,dask,full")
    ap.add_argument("--stem", default="campaign",
                    help="results file stem under benchmarks/results/ (default campaign)")
    a = ap.parse_args(argv)
    if a.stage:
        {"simulate": stage_simulate, "fit-local": stage_fit_local, "fit-dask": stage_fit_dask,
         "simulate-full": stage_simulate_full, "stream": stage_stream,
         "stream-dask": stage_stream_dask}[a.stage](a)
        return 0

    from _common import machine_info, write_results

    if a.quick:
        a.positions = a.positions or 6
        a.full_step = max(a.full_step, 0.0016)
    skip = {s.strip() for s in a.skip.split(",") if s.strip()}
    work = Path(a.work)
    camp = work / (f"campaign-{a.step:g}" + (f"-{a.positions}" if a.positions else ""))
    full = work / f"full-{a.full_step:g}"
    common = ["--step", str(a.step)] + ([] if a.preprocess else ["--no-preprocess"])
    data: dict = {"machine": machine_info(), "step_rad": a.step, "full_step_rad": a.full_step,
                  "workers": a.workers, "preprocess": a.preprocess,
                  "load_average_start": list(os.getloadavg())}
    if not (camp / "campaign.toml").is_file():
        print(f"simulating {camp} ...", flush=True)
        data["simulate"] = _run_stage(["--stage", "simulate", "--camp", str(camp),
                                       "--positions", str(a.positions), *common])
    if "local" not in skip:
        print("in-process fit ...", flush=True)
        data["local"] = _run_stage(["--stage", "fit-local", "--camp", str(camp), "--out",
                                    str(work / "out"), *common]
                                   + ([] if a.joint else ["--no-joint"]))
    if "dask" not in skip:
        print("Dask fit ...", flush=True)
        data["dask"] = _run_stage(["--stage", "fit-dask", "--camp", str(camp), "--out",
                                   str(work / "out"), "--workers", str(a.workers), *common])
        a_doc = json.loads((work / "out" / "fit-dask" / "fit.json").read_text())
        if (work / "out" / "fit" / "fit.json").is_file():
            b_doc = json.loads((work / "out" / "fit" / "fit.json").read_text())
            diffs = []
            for sa, sb in zip(a_doc["scans"], b_doc["scans"]):
                for n, e in sb["estimates"].items():
                    if e.get("sigma"):  # None: held, not estimated
                        diffs.append(abs(sa["estimates"][n]["value"] - e["value"]) / e["sigma"])
            data["dask"]["max_abs_difference_over_sigma"] = max(diffs) if diffs else None
    if "full" not in skip:
        if not (full / "campaign.toml").is_file():
            print(f"simulating one scan at {a.full_step} rad ...", flush=True)
            data["simulate_full"] = _run_stage(["--stage", "simulate-full", "--camp", str(full),
                                                "--step", str(a.full_step)])
        print("streaming it ...", flush=True)
        data["stream"] = _run_stage(["--stage", "stream", "--camp", str(full), "--out",
                                     str(work / "stream"), "--rows-per-chunk",
                                     str(a.rows_per_chunk)])
    data["load_average_end"] = list(os.getloadavg())
    md = report(data)
    p_md, _ = write_results(a.stem, md, data)
    print(md)
    print(f"wrote {p_md}")
    return 0


def _fmt_s(s):
    return "" if s is None else (f"{s / 60:.1f} min" if s >= 120 else f"{s:.1f} s")


def report(d: dict) -> str:
    m = d["machine"]
    L = ["# Campaign scale", "",
         f"Machine: {m.get('cpu', '?')}, {m.get('cores')} cores, {m.get('mem_GiB', '?')} GiB; "
         f"jax {m.get('jax', '?')}. Reduced resolution: step {d['step_rad']} rad; "
         f"preprocessing {'on' if d['preprocess'] else 'off'}. Load average at start / end "
         f"{d['load_average_start'][1]:.1f} / {d['load_average_end'][1]:.1f} (5 min)"
         + (": the machine was shared with other jobs, so the times are upper bounds."
            if max(d["load_average_start"][1], d["load_average_end"][1]) > 2.5 else
            ": no other job ran."), ""]
    if "simulate" in d:
        s = d["simulate"]
        L += [f"Simulation: {s['scans']} scans ({s['positions']} positions) in "
              f"{_fmt_s(s['seconds'])}; rows per scan (first four): {s['rows_per_scan_sample']}.",
              ""]
    rows = []
    if "local" in d:
        lo = d["local"]
        rows.append({"run": "in-process, one scan after the other", "scans": lo["scans"],
                     "positions": lo["positions"], "wall": _fmt_s(lo["end_to_end_s"]),
                     "ppm": 60 * lo["positions"] / lo["end_to_end_s"],
                     "proc": _fmt_s(lo["process_wall_s"])})
    if "dask" in d:
        da = d["dask"]
        pos = d.get("local", {}).get("positions", da["scans"] / 2)
        rows.append({"run": f"Dask LocalCluster, {da['workers']} workers x 1 thread",
                     "scans": da["scans"], "positions": pos,
                     "wall": _fmt_s(da["end_to_end_s"]), "ppm": 60 * pos / da["end_to_end_s"],
                     "proc": _fmt_s(da["process_wall_s"])})
    if rows:
        L += ["## The reduced-resolution campaign, end to end", "",
              "| run | scans | positions | wall (fit incl. I/O) | positions / min | process |",
              "|---|---:|---:|---:|---:|---:|"]
        for r in rows:
            L.append(f"| {r['run']} | {r['scans']} | {r['positions']} | {r['wall']} | "
                     f"{r['ppm']:.2f} | {r['proc']} |")
        L.append("")
        if "dask" in d:
            da = d["dask"]
            lo = d.get("local")
            local = (f" (in-process: {lo['fit_s'] / lo['scans']:.1f} s per scan, read, "
                     "preprocessing and adjustment)" if lo else "")
            L += [f"Dask: cluster start {da['cluster_start_s']:.1f} s; per-scan task time median "
                  f"{da['per_scan_s_median']:.1f} s{local}, longest "
                  f"{da.get('per_scan_s_max', float('nan')):.1f} s (a worker's first scans "
                  f"compile), sum {_fmt_s(da['per_scan_s_sum'])}; largest difference to the "
                  f"in-process estimates "
                  f"{da.get('max_abs_difference_over_sigma', float('nan')):.2g} sigma.", ""]
    if "local" in d and "joint_s" in d["local"]:
        lo = d["local"]
        j = lo["joint"]
        L += ["## Joint adjustment and gravity model", "",
              f"Joint (calibration shared per night, Schur complement): {lo['joint_s']:.1f} s, "
              f"{lo['joint_iterations']} iterations. max |corr(f, calibration)| median per scan "
              f"{j['corr']['per_scan']['median']:.3f} -> joint {j['corr']['joint']['median']:.3f};"
              f" sigma(f) joint / per scan (median) {j['f_gain_median']:.3f}.", "",
              "| night | x4 [arcsec] | x6 [arcsec] | x7 [arcsec] | sigma ratio x4 / x6 / x7 |",
              "|---|---:|---:|---:|---:|"]
        rad = 206264.806
        for gname, e in j["shared"].items():
            cells = [f"{e[n][0] * rad:.3f} ± {e[n][1] * rad:.3f}" for n in ("x4", "x6", "x7")]
            gains = " / ".join(f"{j['gain'][n][gname]:.3f}" for n in ("x4", "x6", "x7"))
            L.append(f"| {gname} | " + " | ".join(cells) + f" | {gains} |")
        if "truth" in lo:
            t = lo["truth"]["instrument"]
            L.append(f"| truth | {t.get('x4', 0) * rad:.3f} | {t.get('x6', 0) * rad:.3f} | "
                     f"{t.get('x7', 0) * rad:.3f} | |")
        g = lo["gravity"]
        L += ["", f"Gravity model ({_fmt_s(lo['gravity_s'])}): "
              + ", ".join(f"{n} = {b * 1e3:.3f} ± {s * 1e3:.3f} mm" for n, b, s in
                          zip(g["names"], g["beta"], g["sigma_scaled"]))
              + f"; transverse terms F = {g['F']:.1f}, p = {g['p_value_F']:.2g}; chi2/dof "
              f"{g.get('variance_factor', float('nan')):.2f}; take-up of modes "
              f"{g.get('corrected_modes', [])} by f corrected."]
        if "gravity_raw" in lo:
            r = lo["gravity_raw"]
            L.append("Without that correction (f alone regressed on g): "
                     + ", ".join(f"{n} = {b * 1e3:.3f} ± {s * 1e3:.3f} mm" for n, b, s in
                                 zip(r["names"], r["beta"], r["sigma_scaled"]))
                     + f"; chi2/dof {r['variance_factor']:.2f}.")
        if "gravity_two_face" in lo:
            r = lo["gravity_two_face"]
            L.append("From the default two-face fit (f per position, the positions' full "
                     "covariance): "
                     + ", ".join(f"{n} = {b * 1e3:.3f} ± {s * 1e3:.3f} mm" for n, b, s in
                                 zip(r["names"], r["beta"], r["sigma_scaled"]))
                     + f"; chi2/dof {r['variance_factor']:.2f} on {r['dof']} dof.")
        if "truth" in lo:
            L.append(f"Truth: df/dg = {[round(v * 1e3, 3) for v in lo['truth']['df_dg_m']]} mm, "
                     f"df/dT = {lo['truth']['df_dT_m_per_K'] * 1e3:.3f} mm/K.")
        L.append("")
    if "stream" in d:
        st = d["stream"]
        sf = d.get("simulate_full", {})
        L += ["## One full-resolution scan, streamed", "",
              f"Step {d['full_step_rad']} rad: {st['rows']:,} rows ({st['points']:,} used, "
              f"{st['rejected']:,} rejected, {st['outside_window']:,} outside the window)"
              + (f"; file {sf['file_gib']:.2f} GiB, simulated in {_fmt_s(sf['seconds'])}"
                 if sf else "") + ".", "",
              "| quantity | value |", "|---|---:|",
              f"| wall time (initial values + adjustment) | {_fmt_s(st['seconds'])} |",
              f"| initial values (sampling pass) | {st['timings']['initial_values_s']:.1f} s |",
              f"| passes over the file / iterations / robust rounds | {st['passes']} / "
              f"{st['iterations']} / {st['rounds']} |",
              f"| time per pass | {st['s_per_pass']:.1f} s |",
              f"| rows per chunk | {st['rows_per_chunk']:,} |",
              f"| peak RSS of the process | {st['peak_rss_gib']:.2f} GiB |",
              "| per-point state left on disk (v, weights, residuals) | "
              f"{st['store_gib']:.2f} GiB |",
              f"| sigma0 | {st['sigma0']:.4f} |",
              f"| f | {st['f'][0]:.6f} ± {st['f'][1]:.6f} m |", ""]
        # projection
        t1 = st["seconds"]
        n_scans = 176
        rows_full = st["rows"] * (d["full_step_rad"] / 0.00063) ** 2
        scale = rows_full / st["rows"]
        t_scan = t1 * scale
        mem = st["peak_rss_gib"] + (scale - 1) * st["store_gib"]
        L += ["## Projection: the full-resolution campaign (176 scans, ~2.3e9 points)", "",
              f"Per scan {_fmt_s(t_scan)} for {rows_full:.3g} rows"
              + ("" if scale == 1 else f" (measured {_fmt_s(t1)} for {st['rows']:,} rows, "
                 "scaled linearly)")
              + f"; one scan per worker at a time, each worker one core and about {mem:.1f} GiB "
              "(the chunk buffers do not grow with the scan; the per-point state lives in "
              "files on disk, read and written chunk by chunk). The scans are independent, "
              "so the wall time divides by the number of workers until the disks saturate "
              "(one pass reads the scan file once: "
              f"{st['passes']} passes x "
              f"{sf.get('file_gib', st.get('file_gib', float('nan'))) * scale:.2f} GiB per "
              "scan). The joint adjustment adds one pass per Schur iteration over the "
              "worker-resident scans (about one GH iteration per scan).", "",
              "| workers (1 core each) | wall | positions / hour |", "|---:|---:|---:|"]
        for n in (1, 2, 8, 32, 88, 176):
            w = t_scan * -(-n_scans // n)
            L.append(f"| {n} | {_fmt_s(w)} | {88 / (w / 3600):.1f} |")
        L.append("")
    return "\n".join(L)


if __name__ == "__main__":
    sys.exit(main())
