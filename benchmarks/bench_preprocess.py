"""Preprocessing throughput: the JAX pipeline against NumPy RANSAC and open3d per patch.

One simulated scan (demo scene: reflector, cone, quadrupod, background, mixed pixels, multipath)
per size, cached as ``.npz``. Every method runs the *same* pipeline
(:func:`hartrao_jax.preprocess.preprocess_scan`: initial values, range and geometry windows,
angular patches) and differs only in the plane stage, swapped in for ``fit_planes`` where the
pipeline calls it (``_stages``):

* ``jax``: the package (RANSAC vmapped over padded patches, ``lax.map`` chunks, float32,
  hypotheses scored on up to 256 points per patch, TLS refinement on all points), first call
  (with compilation: cold, and with the persistent compilation cache the CLI enables) and warm
  calls;
* ``numpy``: the same algorithm with NumPy on chunks of padded patches (same samples: it must
  agree with ``jax`` to round-off);
* ``open3d``: ``PointCloud.segment_plane`` called once per patch (a Python loop, open3d's own
  RANSAC, same threshold and number of hypotheses), the usual way of doing this step.

Each method runs in its own subprocess, so its peak memory (``ru_maxrss``) is its own; the
baseline (Python + JAX + the scan in memory) is reported separately.

    python benchmarks/bench_preprocess.py [--sizes 1e6,1.3e7] [--methods jax,numpy,open3d]

Writes ``benchmarks/results/preprocess.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import math
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

CACHE = Path(os.environ.get("HARTRAO_BENCH_CACHE", "/tmp/hartrao-bench-cache"))
ROWS_AT_6MRAD = 211_722  # rows of the demo r23c1 scan at 0.006 rad (grid step -> size)


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


def step_for(n_rows: float) -> float:
    return 0.006 * math.sqrt(ROWS_AT_6MRAD / n_rows)


def scan_file(n_rows: float) -> Path:
    return CACHE / f"scan_{int(n_rows):d}.npz"


def make_scan(n_rows: float) -> Path:
    p = scan_file(n_rows)
    if p.exists():
        return p
    import hartrao_jax  # noqa: F401
    from hartrao_jax.simulate._simulate import simulate_scan

    CACHE.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    data, lab, truth = simulate_scan(step_rad=step_for(n_rows), seed=0)
    print(f"simulated {len(data):,} rows in {time.perf_counter() - t:.0f} s", flush=True)
    np.savez(p, range_m=data.range_m, phi_rad=data.phi_rad, theta_rad=data.theta_rad,
             intensity=data.intensity, time_s=data.time_s, row=data.row, cls=lab["cls"],
             step=step_for(n_rows))
    return p


def load_scan(n_rows: float):
    from hartrao_jax.campaign._campaign import ScanData

    z = np.load(scan_file(n_rows))
    data = ScanData(z["range_m"], z["phi_rad"], z["theta_rad"], z["intensity"], z["time_s"],
                    z["row"])
    return data, z["cls"], float(z["step"])


# --------------------------------------------------------------------------------------------
# Peers of the plane stage (same signature and outputs as _planes.fit_planes)
# --------------------------------------------------------------------------------------------


def _three_distinct_np(u, n):
    n = n[:, None]
    i1 = np.minimum((u[..., 0] * n).astype(np.int64), n - 1)
    i2 = (i1 + 1 + np.minimum((u[..., 1] * (n - 1)).astype(np.int64), n - 2)) % n
    a, b = np.minimum(i1, i2), np.maximum(i1, i2)
    k = np.minimum((u[..., 2] * (n - 2)).astype(np.int64), n - 3)
    k = k + (k >= a)
    k = k + (k >= b)
    return np.stack([i1, i2, k], axis=-1)


def numpy_fit_planes(pts, n, eps, *, seed=0, ransac_iterations=64, refine_iterations=2,
                     ransac_float32=True, score_points=256, memory_mb=64.0, ids=None, **_):
    """The package's algorithm in NumPy, chunk by chunk of padded patches."""
    from hartrao_jax.preprocess._planes import ransac_uniforms

    pts = np.asarray(pts)
    n_p, P = pts.shape[:2]
    H = int(ransac_iterations)
    n = np.asarray(n, np.int64)
    eps = np.broadcast_to(np.asarray(eps, float), (n_p,))
    ids = np.arange(n_p) if ids is None else np.asarray(ids)
    U = ransac_uniforms(seed, ids, H)
    good = n >= 3
    nr = np.where(good, np.minimum(n, P), 3)
    ct = np.float32 if ransac_float32 else np.float64
    S = min(P, score_points)
    isz = np.dtype(ct).itemsize
    chunk = int(max(1, memory_mb * 2**20 // (P * 3 * isz * 4 + S * H * isz * 3)))
    inl_all = np.zeros((n_p, P), bool)
    normal_all, d_all, cen_all = np.zeros((n_p, 3)), np.zeros(n_p), np.zeros((n_p, 3))
    nin_all, rms_all, nr_all = np.zeros(n_p, np.int32), np.zeros(n_p), np.zeros(n_p, np.int32)
    ar = np.arange(P)
    for s in range(0, n_p, chunk):
        e = min(s + chunk, n_p)
        B = e - s
        k = nr[s:e]
        valid = ar[None, :] < k[:, None]
        q = pts[s:e].astype(ct)
        cen = np.sum(np.where(valid[..., None], q, 0), axis=1) / k[:, None].astype(ct)
        q -= cen[:, None, :]
        idx = _three_distinct_np(U[s:e], k)  # (B, H, 3)
        tri = np.take_along_axis(q, idx.reshape(B, H * 3)[..., None], axis=1).reshape(B, H, 3, 3)
        nrm = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
        ln = np.sqrt(np.sum(nrm * nrm, -1))
        scale = np.abs(np.where(valid[..., None], q, 0)).max(axis=(1, 2))[:, None] + ct(1e-12)
        ok = ln > ct(1e-6) * scale * scale
        nh = nrm / np.where(ok, ln, 1)[..., None]
        d = np.sum(nh * tri[:, :, 0], -1)
        kk = np.arange(S)[None, :]
        sub = np.where(k[:, None] > S, (kk * k[:, None]) // S, kk)  # (B, S)
        scored = sub < k[:, None]
        qs = np.take_along_axis(q, sub[..., None], axis=1)
        dist = qs @ nh.transpose(0, 2, 1) - d[:, None, :]  # (B, S, H)
        ee = eps[s:e].astype(ct)[:, None, None]
        cost = np.sum(np.where(scored[..., None], np.minimum(dist * dist, ee * ee), 0), axis=1)
        cost = np.where(ok, cost, np.inf)
        best = np.argmin(cost, axis=1)
        db = np.take_along_axis(dist, best[:, None, None], axis=2)[..., 0]
        nr_all[s:e] = np.sum(scored & (np.abs(db) <= ee[:, :, 0]), axis=1)
        normal = nh[np.arange(B), best]
        d0 = d[np.arange(B), best]
        ep = eps[s:e].astype(ct)[:, None]
        for _ in range(refine_iterations):
            r = np.einsum("bpk,bk->bp", q, normal) - d0[:, None]
            w = (valid & (np.abs(r) <= ep)).astype(ct)
            sw = np.maximum(w.sum(1), 1)
            pw = q * w[..., None]
            c = pw.sum(1) / sw[:, None]
            M = pw.transpose(0, 2, 1) @ q - sw[:, None, None] * (c[:, :, None] * c[:, None, :])
            a_, b_, c_ = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
            d_, e_, f_ = M[:, 1, 1], M[:, 1, 2], M[:, 2, 2]
            A, B_, C = d_ * f_ - e_ * e_, c_ * e_ - b_ * f_, b_ * e_ - c_ * d_
            D, E, F = a_ * f_ - c_ * c_, b_ * c_ - a_ * e_, a_ * d_ - b_ * b_
            adj = np.stack([np.stack([A, B_, C], -1), np.stack([B_, D, E], -1),
                            np.stack([C, E, F], -1)], 1)
            u = np.einsum("bij,bj->bi", adj, np.einsum("bij,bj->bi", adj, normal))
            nu = np.linalg.norm(u, axis=1)
            v = np.where((nu > 0)[:, None], u / np.where(nu > 0, nu, 1)[:, None], normal)
            v = np.where((np.sum(v * normal, 1) < 0)[:, None], -v, v)
            enough = w.sum(1) >= 3
            normal = np.where(enough[:, None], v, normal)
            d0 = np.where(enough, np.sum(v * c, 1), d0)
        r = np.einsum("bpk,bk->bp", q, normal) - d0[:, None]
        inl = valid & (np.abs(r) <= ep)
        nin = inl.sum(1)
        inl_all[s:e], nin_all[s:e] = inl, nin
        normal_all[s:e] = normal / np.linalg.norm(normal.astype(float), axis=1, keepdims=True)
        d_all[s:e], cen_all[s:e] = d0, cen
        rms_all[s:e] = np.sqrt(np.sum(np.where(inl, r * r, 0), 1) / np.maximum(nin - 3, 1))
    inl_all &= good[:, None]
    return {"inlier": inl_all, "normal": np.where(good[:, None], normal_all, np.nan),
            "d": np.where(good, d_all, np.nan), "centroid": cen_all,
            "n_inliers": np.where(good, nin_all, 0), "rms": np.where(good, rms_all, np.nan),
            "ransac_inliers": np.where(good, nr_all, 0)}


def open3d_fit_planes(pts, n, eps, *, seed=0, ransac_iterations=64, **_):
    """``open3d.geometry.PointCloud.segment_plane`` once per patch (no refinement)."""
    import open3d as o3d

    o3d.utility.random.seed(int(seed))
    pts = np.asarray(pts)
    n_p, P = pts.shape[:2]
    n = np.asarray(n, np.int64)
    eps = np.broadcast_to(np.asarray(eps, float), (n_p,))
    inl_all = np.zeros((n_p, P), bool)
    normal_all, d_all = np.full((n_p, 3), np.nan), np.full(n_p, np.nan)
    nin_all, rms_all = np.zeros(n_p, np.int64), np.full(n_p, np.nan)
    for i in range(n_p):
        k = int(n[i])
        if k < 3:
            continue
        q = pts[i, :k].astype(np.float64)
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(q))
        model, inl = pc.segment_plane(distance_threshold=float(eps[i]), ransac_n=3,
                                      num_iterations=int(ransac_iterations))
        m = np.asarray(model, float)
        nn = np.linalg.norm(m[:3])
        nrm, dd = m[:3] / nn, -m[3] / nn
        idx = np.asarray(inl, np.int64)
        inl_all[i, idx] = True
        r = q[idx] @ nrm - dd
        normal_all[i], d_all[i], nin_all[i] = nrm, dd, len(idx)
        rms_all[i] = np.sqrt(np.sum(r * r) / max(len(idx) - 3, 1))
    return {"inlier": inl_all, "normal": normal_all, "d": d_all, "centroid": np.zeros((n_p, 3)),
            "n_inliers": nin_all, "rms": rms_all, "ransac_inliers": nin_all}


# --------------------------------------------------------------------------------------------
# The refinement alternative: the generic Gauss-Helmert solver on every patch (batched)
# --------------------------------------------------------------------------------------------


def gh_comparison(n_rows: float, n_patches: int) -> dict:
    """Rigorous GH plane per patch (``gauss_helmert_batch``) vs the TLS kernel, same patches.

    Patches of the scanner-frame preprocessing of the scan; the GH condition is
    ``_preprocess.PlaneCondition`` with its rotation passed per patch as constants.
    """
    import dataclasses

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import hartrao_jax  # noqa: F401
    from hartrao_jax import preprocess as pp
    from hartrao_jax.campaign._campaign import ScanMeta, default_campaign
    from hartrao_jax.geometry._geometry import polar_to_cartesian
    from hartrao_jax.solver._ghm import gauss_helmert_batch

    class PlaneC(eqx.Module):
        def __call__(self, obs, x, c):
            v = jnp.stack([x[0], x[1], jnp.ones_like(x[0])])
            nrm = c[:9].reshape(3, 3) @ (v / jnp.sqrt(jnp.sum(v * v)))
            return nrm @ polar_to_cartesian(obs[0], obs[1], obs[2]) - x[2]

    data, cls, step = load_scan(n_rows)
    camp = default_campaign()
    camp = dataclasses.replace(camp, scanner=dataclasses.replace(camp.scanner,
                                                                 angular_step_rad=step))
    meta = ScanMeta("r23c1", "r23", 1, "", ha_deg=-35.0, dec_deg=-64.0)
    res = pp.preprocess_scan(camp, meta, data, pp.PreprocessConfig(frame="scanner"))
    cand = np.flatnonzero(res.patch_inliers >= 20)
    ids = np.sort(np.random.default_rng(0).choice(cand, min(n_patches, len(cand)), replace=False))
    rows = [np.flatnonzero((res.patch == i) & res.keep) for i in ids]
    P = max(len(r) for r in rows)
    L = np.zeros((len(ids), P, 3))
    W = np.zeros((len(ids), P))
    X = np.zeros((len(ids), P, 3))
    C = np.zeros((len(ids), P, 9))
    X0 = np.zeros((len(ids), 3))
    for b, (i, rr) in enumerate(zip(ids, rows)):
        obs = np.stack([data.range_m[rr], data.phi_rad[rr], data.theta_rad[rr]], 1)
        L[b, : len(rr)], L[b, len(rr):] = obs, obs[0]
        W[b, : len(rr)] = 1.0
        A, B, Cc, D = res.planes[i]
        cond = pp.PlaneCondition.around([A, B, Cc])
        C[b] = np.asarray(cond.R0).ravel()
        X0[b] = [0.0, 0.0, -D]
        xs = np.asarray(polar_to_cartesian(obs[:, 0], obs[:, 1], obs[:, 2]))
        X[b, : len(rr)] = xs - xs.mean(0)
    sig = np.array([camp.scanner.sigma_range_m, camp.scanner.sigma_angle_rad,
                    camp.scanner.sigma_angle_rad])
    out = {"n_patches": len(ids), "padded_points": P}
    for tag in ("first", "warm"):
        t = time.perf_counter()
        gh = gauss_helmert_batch(PlaneC(), L, X0, sig, C, W)
        jax.block_until_ready(gh.x)
        out[f"gh_{tag}_s"] = time.perf_counter() - t
    n_valid = W.sum(1).astype(int)
    for tag in ("first", "warm"):
        t = time.perf_counter()
        tls = pp.fit_planes(X.astype(np.float32), n_valid, 1.0, refine_iterations=2)
        out[f"tls_{tag}_s"] = time.perf_counter() - t
    # the TLS normal in the GH parameters (x0, x1); Mahalanobis distance with the GH covariance
    R0 = C[:, 0].reshape(-1, 3, 3)
    v = np.einsum("bji,bj->bi", R0, tls["normal"])  # R0^T n
    v = v / v[:, 2:3]
    dx = v[:, :2] - np.asarray(gh.x)[:, :2]
    cov = np.asarray(gh.cov)[:, :2, :2]
    z = np.sqrt(np.einsum("bi,bij,bj->b", dx, np.linalg.inv(cov), dx))
    out["mahalanobis_median"] = float(np.median(z))
    out["mahalanobis_p95"] = float(np.percentile(z, 95))
    out["mahalanobis_max"] = float(np.max(z))
    out["gh_converged"] = float(np.mean(np.asarray(gh.converged)))
    return out


# --------------------------------------------------------------------------------------------
# Worker: one method on one scan, in its own process
# --------------------------------------------------------------------------------------------


def _plane_stage_modules() -> list:
    """The pipeline modules that call ``fit_planes`` by their global name (the stages module
    since the preprocessing was split into stages; ``_preprocess`` before)."""
    import importlib

    mods = []
    for name in ("hartrao_jax.preprocess._stages", "hartrao_jax.preprocess._preprocess"):
        try:
            m = importlib.import_module(name)
        except ImportError:
            continue
        if hasattr(m, "fit_planes"):
            mods.append(m)
    return mods


def worker(method: str, n_rows: float, calls: int = 3, xla_cache: str | None = None) -> dict:
    import jax

    import hartrao_jax  # noqa: F401
    from hartrao_jax.campaign._campaign import ScanMeta, default_campaign
    from hartrao_jax.preprocess import _preprocess as pp

    data, cls, step = load_scan(n_rows)
    import dataclasses

    camp = default_campaign()
    camp = dataclasses.replace(camp, scanner=dataclasses.replace(camp.scanner,
                                                                 angular_step_rad=step))
    meta = ScanMeta("r23c1", "r23", 1, "", ha_deg=-35.0, dec_deg=-64.0)
    base = peak_mib()
    if method == "jax" and xla_cache:
        from hartrao_jax._config import enable_compilation_cache

        out_cache = any(Path(xla_cache).glob("*")) if Path(xla_cache).exists() else False
        enable_compilation_cache(xla_cache)
    peer = {"numpy": numpy_fit_planes, "open3d": open3d_fit_planes}.get(method)
    if peer is not None:  # swap the plane stage where the pipeline looks it up
        for mod in _plane_stage_modules():
            mod.fit_planes = peer
    cfg = pp.PreprocessConfig()
    out = {"method": method, "n_rows": len(data), "step_rad": step, "baseline_mib": base}
    if method == "jax" and xla_cache:
        out["xla_cache_was_warm"] = out_cache
    t, c = time.perf_counter(), time.process_time()
    res = pp.preprocess_scan(camp, meta, data, cfg)
    out["first_s"] = time.perf_counter() - t
    out["first_cpu_s"] = time.process_time() - c
    out["first_plane_s"] = res.stats["timing_s"]["ransac"]
    warm, cpu, plane, stages = [], [], [], []
    for _ in range(calls - 1):  # warm calls (jax: compiled shapes reused); best of
        t, c = time.perf_counter(), time.process_time()
        res = pp.preprocess_scan(camp, meta, data, cfg)
        warm.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        plane.append(res.stats["timing_s"]["ransac"])
        stages.append(res.stats["timing_s"])
    if warm:
        out["warm_s"], out["warm_plane_s"], out["cpu_s"] = min(warm), min(plane), min(cpu)
        out["timing_s"] = {k: min(st[k] for st in stages) for k in stages[0]}
    else:
        out["timing_s"] = res.stats["timing_s"]
    for k, key in (("init_s", "initial_values"), ("windows_s", "windows"),
                   ("segmentation_s", "segmentation")):
        out[k] = out["timing_s"].get(key)
    out["peak_mib"] = peak_mib()
    out["n_patches"] = res.stats["n_patches_fitted"]
    out["points_per_patch"] = res.stats["points_per_patch"]
    out["patch_size_m"] = res.params["patch_size_m"]
    out["epsilon_m"] = res.params["epsilon_m"]
    refl = cls == 0
    scatter = cls != 0
    out["reflector_kept"] = float(res.keep[refl].mean())
    out["scatter_removed"] = float(1 - res.keep[scatter].mean())
    np.save(CACHE / f"keep_{method}_{int(n_rows)}.npy", res.keep)
    out["jax_devices"] = str(jax.devices())
    return out


# --------------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------------


def run_worker(method: str, n_rows: float, timeout: float, calls: int) -> dict:
    cmd = [sys.executable, __file__, "--worker", method, "--size", repr(n_rows),
           "--calls", str(calls), "--xla-cache", str(CACHE / "xla")]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"method": method, "error": f"timeout after {timeout:.0f} s"}
    if p.returncode != 0:
        tail = (p.stderr or p.stdout).strip().splitlines()[-3:]
        return {"method": method, "error": " | ".join(tail)}
    return json.loads(p.stdout.strip().splitlines()[-1])


def _gh_md(gh: dict | None) -> str:
    if not gh:
        return ""
    if "error" in gh:
        return f"## Refinement: generic Gauss-Helmert per patch\n\nfailed: {gh['error']}\n\n"
    return (
        "## Refinement: generic Gauss-Helmert per patch vs the vmapped TLS kernel\n\n"
        f"{gh['n_patches']} patches of the smallest scan (scanner frame, kept points, padded to "
        f"{gh['padded_points']}): `gauss_helmert_batch` with the plane condition in raw "
        f"observations (`PlaneCondition`) took {gh['gh_first_s']:.2f} s first call, "
        f"{gh['gh_warm_s']:.2f} s warm; the TLS kernel (`fit_planes`, RANSAC included) "
        f"{gh['tls_first_s']:.2f} s / {gh['tls_warm_s']:.3f} s. The TLS normal lies "
        f"{gh['mahalanobis_median']:.3f} (median), {gh['mahalanobis_p95']:.3f} (95 %), "
        f"{gh['mahalanobis_max']:.3f} (max) standard deviations (Mahalanobis, GH covariance) "
        f"from the GH normal; GH converged on {100 * gh['gh_converged']:.0f} % of the patches. "
        "Patches drawn at random among those with at least 20 kept points; the largest "
        "differences come from elongated patches (near the scanner's nadir) whose tilt across "
        "is barely determined: GH then also trades that tilt against the anisotropy of the "
        "noise, which TLS ignores; the classification is unaffected.\n\n"
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="1e6,1.3e7")
    ap.add_argument("--methods", default="jax,numpy,open3d")
    ap.add_argument("--timeout", type=float, default=3600.0)
    ap.add_argument("--calls", type=int, default=3,
                    help="calls per worker: the first, then warm ones (best of)")
    ap.add_argument("--rounds", type=int, default=2,
                    help="workers per method and size, interleaved (best of: shared machine)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--xla-cache", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--gh-patches", type=int, default=500,
                    help="patches of the 1e6 scan for the GH-vs-TLS refinement comparison "
                         "(0: skip)")
    ap.add_argument("--size", type=float, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker == "gh":
        print(json.dumps(gh_comparison(args.size, args.gh_patches), default=float))
        return
    if args.worker:
        print(json.dumps(worker(args.worker, args.size, args.calls, args.xla_cache),
                         default=float))
        return
    from _common import machine_info, md_table, write_results

    load_start = os.getloadavg()
    import shutil

    sizes = [float(s) for s in args.sizes.split(",")]
    methods = args.methods.split(",")
    rows = []
    for n in sizes:
        make_scan(n)
        shutil.rmtree(CACHE / "xla", ignore_errors=True)  # round 1 compiles cold, then hits
        best: dict[str, dict] = {}
        for rnd in range(args.rounds):
            for m in methods:
                print(f"size {n:.3g}: {m} (round {rnd + 1}) ...", flush=True)
                r = run_worker(m, n, args.timeout, args.calls)
                print(json.dumps(r, default=float), flush=True)
                if "error" in r:
                    best.setdefault(m, r)
                    continue
                r["plane_s"] = r.get("warm_plane_s", r["first_plane_s"])
                r["total_s"] = r.get("warm_s", r["first_s"])
                if r.get("xla_cache_was_warm"):
                    r["first_cached_s"] = r["first_s"]
                    r["first_s"] = None
                b = best.get(m)
                if b is None or "error" in b:
                    best[m] = r
                else:  # best of rounds, per column
                    for k in ("plane_s", "total_s", "cpu_s", "first_s", "first_cached_s",
                              "first_plane_s", "peak_mib", "init_s", "windows_s",
                              "segmentation_s"):
                        v = [x for x in (b.get(k), r.get(k)) if x is not None]
                        b[k] = min(v) if v else None
        for m in methods:
            r = best[m]
            r["size"] = n
            if "error" not in r:
                ref = CACHE / f"keep_jax_{int(n)}.npy"
                mine = CACHE / f"keep_{m}_{int(n)}.npy"
                if ref.exists() and mine.exists():
                    r["agree_with_jax"] = float(np.mean(np.load(ref) == np.load(mine)))
                r["throughput_Mpts_s"] = r["n_rows"] / r["total_s"] / 1e6
            rows.append(r)
    gh = None
    if args.gh_patches:
        print("GH vs TLS refinement ...", flush=True)
        cmd = [sys.executable, __file__, "--worker", "gh", "--size", repr(min(sizes)),
               "--gh-patches", str(args.gh_patches)]
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
        gh = (json.loads(p.stdout.strip().splitlines()[-1]) if p.returncode == 0 else
              {"error": " | ".join((p.stderr or p.stdout).strip().splitlines()[-3:])})
        print(json.dumps(gh), flush=True)
    info = machine_info()
    info["loadavg_start"] = [round(v, 1) for v in load_start]
    info["loadavg_end"] = [round(v, 1) for v in os.getloadavg()]
    try:
        import open3d

        info["open3d"] = open3d.__version__
    except Exception as e:  # pragma: no cover
        info["open3d"] = f"not available ({type(e).__name__}: {e})"
    cols = [("n_rows", "rows", ",d"), ("method", "plane stage", ""),
            ("n_patches", "patches", ",d"), ("patch_size_m", "patch m", ".2f"),
            ("init_s", "initial values s", ".2f"), ("windows_s", "windows s", ".2f"),
            ("segmentation_s", "segmentation s", ".2f"),
            ("plane_s", "plane stage s", ".2f"), ("first_plane_s", "plane 1st call s", ".2f"),
            ("total_s", "total s", ".2f"), ("cpu_s", "total CPU s", ".2f"),
            ("first_s", "first call s", ".2f"),
            ("first_cached_s", "first call, XLA cache s", ".2f"),
            ("throughput_Mpts_s", "Mpts/s", ".2f"),
            ("baseline_mib", "baseline MiB", ".0f"), ("peak_mib", "peak MiB", ".0f"),
            ("reflector_kept", "reflector kept", ".4f"),
            ("scatter_removed", "scatter removed", ".4f"),
            ("agree_with_jax", "same mask as jax", ".6f"), ("error", "error", "")]
    full = [r for r in rows if r.get("size") == max(sizes) and "error" not in r]
    jx = next((r for r in full if r["method"] == "jax"), None)
    o3 = next((r for r in full if r["method"] == "open3d"), None)
    verdict = []
    if jx:
        first = max(v for v in (jx.get("first_s"), jx.get("first_cached_s"), jx["total_s"])
                    if v is not None)
        verdict.append(f"- full-resolution scan ({jx['n_rows']:,} rows): whole preprocessing "
                       f"{jx['total_s']:.1f} s warm, {first:.1f} s at worst (first call, cold "
                       f"compilation) (target < 60 s: {'met' if first < 60 else 'NOT met'})")
    if jx and o3:
        verdict.append(f"- plane stage: JAX {jx['plane_s']:.2f} s vs open3d per patch "
                       f"{o3['plane_s']:.2f} s ({o3['plane_s'] / jx['plane_s']:.1f}x); whole "
                       f"pipeline {jx['total_s']:.1f} s vs {o3['total_s']:.1f} s")
    md = (
        "# Preprocessing throughput\n\n"
        "`python benchmarks/bench_preprocess.py` -- one simulated demo scan per size (reflector, "
        "cone, quadrupod, background, mixed pixels, multipath), the same pipeline "
        "(initial values, range and geometry windows, angular patches) for every method; "
        "only the plane stage differs. *plane stage*: RANSAC + refinement of all patches; "
        "*total*: `preprocess_scan` end to end, best of the warm calls (for jax the "
        "compiled shapes are reused; *total CPU*: process time of that call, all threads); "
        "*first call* includes compilation and every method's first-use overheads (for jax "
        "with an empty persistent compilation cache; *XLA cache*: a new process with the "
        "cache the CLI enables already filled). Best of `--rounds` interleaved workers per "
        "method: the machine is shared, single timings are noisy. Peak memory is the worker "
        "process's `ru_maxrss`; *baseline* is its peak after loading the scan (Python, JAX, "
        "the scan's columns). *same mask as jax*: fraction of rows with the same keep flag.\n\n"
        + md_table(rows, cols) + "\n" + "\n".join(verdict) + "\n\n"
        + _gh_md(gh)
        + "Machine: " + ", ".join(f"{k}={v}" for k, v in info.items()) + "\n"
    )
    p_md, _ = write_results("preprocess", md, {"machine": info, "rows": rows})
    print(md)
    print(f"wrote {p_md}")


if __name__ == "__main__":
    main()
