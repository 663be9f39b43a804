"""Where the time of a whole ``fit`` goes, stage by stage (wall and process CPU seconds).

The stages of the default command (two-face position adjustments with the surface as a random
effect, preprocessing on) are timed by wrapping the functions that carry them out:

* read: reading and decoding the scan tables (``read_scan``)
* preprocess: range window, patch segmentation, RANSAC (the keep mask)
* initial values: pointing / quadric initial values and the geometry window (``prepare_scan``)
* gauss-helmert (white): the robust white-noise adjustment that rejects outliers
* random effect: the adjustment with the surface as a random effect (variance components)
* alignment and products: north alignment, deviations, per-scan views (``finish_scan_fit``)
* write: ``fit.json`` and the residual tables

Then the peer of issue 15 on the same scans: a plain vectorised NumPy Gauss-Helmert
(:func:`numpy_peer`, written without the package: pyarrow columns, forward-difference
derivatives, 7 iterations, no preprocessing, no surface random effect); the ratio of its time to
the warm ``fit`` is the end-to-end target (5x).

    python benchmarks/profile.py                 # 6 positions x 2 cycles at 6 mrad (~2.5e6 rows)
    python benchmarks/profile.py --positions 2 --step 0.01

Results: ``results/profile.md`` and ``.json``. Times include compilation on the first call of
each shape (the persistent compilation cache is on, as in the CLI): run twice to see it warm.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import resource
import shutil
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import jax
import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "results"
POSITIONS = [("p1", -35.0, -64.0), ("p2", -60.0, -30.0), ("p3", 40.0, -70.0),
             ("p4", 0.0, 10.0), ("p5", 70.0, -20.0), ("p6", 10.0, -40.0)]


def _peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class Stages:
    """Wall and CPU seconds per stage; nested stages are charged to the innermost one (per
    thread: the faces of a position are read and preprocessed in two threads, so those stages'
    seconds are summed over the threads, and the process CPU seconds of each include the other
    thread's; their sum can exceed the wall time they took, and "other" is then too small)."""

    def __init__(self):
        self.wall = defaultdict(float)
        self.cpu = defaultdict(float)
        self.calls = defaultdict(int)
        self.iterations = defaultdict(list)  # per adjustment: its passes over the points
        self.peak = defaultdict(float)  # the process's peak resident GiB after the stage's calls
        self.grew = defaultdict(float)  # GiB the peak grew by during the stage's calls
        self._local = threading.local()

    @property
    def _stack(self) -> list[list]:
        if not hasattr(self._local, "stack"):
            self._local.stack = []
        return self._local.stack

    def wrap(self, module, name: str, stage: str):
        fn = getattr(module, name)

        def timed(*a, **k):
            t0, c0, p0 = time.perf_counter(), _cpu(), _peak_gib()
            self._stack.append([0.0, 0.0])
            try:
                out = fn(*a, **k)
                if hasattr(out, "x"):  # an adjustment result: wait for the device
                    jax.block_until_ready(out.x)
                    self.iterations[stage].append(int(out.iterations))
                return out
            finally:
                inner_w, inner_c = self._stack.pop()
                w, c = time.perf_counter() - t0, _cpu() - c0
                self.wall[stage] += w - inner_w
                self.cpu[stage] += c - inner_c
                self.calls[stage] += 1
                self.peak[stage] = max(self.peak[stage], _peak_gib())
                self.grew[stage] += _peak_gib() - p0
                if self._stack:
                    self._stack[-1][0] += w
                    self._stack[-1][1] += c

        setattr(module, name, timed)


# --------------------------------------------------------------------------------------------
# The peer: a plain vectorised NumPy Gauss-Helmert, written independently of the package
# --------------------------------------------------------------------------------------------

PEER_ITERATIONS = 7


def _peer_condition(r, phi, theta, x):
    """Paraboloid condition of raw observations (extended model: tx ty tz rx ry f x4 x6 x7),
    plain NumPy: point = Ry(ry) Rx(rx) polar(r, phi + (2 x6 + x7 cos th) / sin th, th) + t,
    th = theta + x4; F = rho^2 / 4f - Z."""
    cx, sx, cy, sy = np.cos(x[3]), np.sin(x[3]), np.cos(x[4]), np.sin(x[4])
    R = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]) @ np.array(
        [[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    th = theta + x[6]
    s, c = np.sin(th), np.cos(th)
    ph = phi + (2.0 * x[7] + x[8] * c) / s
    p = np.stack([r * s * np.sin(ph), r * s * np.cos(ph), r * c])
    X = R @ p + np.asarray(x[:3])[:, None]
    return (X[0] ** 2 + X[1] ** 2) / (4.0 * x[5]) - X[2]


def numpy_peer_fit(l, x0, sigma, iterations=PEER_ITERATIONS, chunk=1 << 16):
    """Gauss-Helmert with numerical (forward-difference) derivatives, ``iterations`` steps,
    every point weighted by ``1 / (b Sigma b^T)``; returns ``(x, sigma0)``."""
    n, u = len(l), len(x0)
    s2 = np.asarray(sigma, float) ** 2
    hx = np.array([1e-6, 1e-6, 1e-6, 1e-7, 1e-7, 1e-6, 1e-8, 1e-8, 1e-8])
    hl = np.array([1e-6, 1e-8, 1e-8])
    x = np.array(x0, float)
    V = np.zeros_like(l)
    omega = 0.0
    for _ in range(iterations):
        N, nv, parts = np.zeros((u, u)), np.zeros(u), []
        for s in range(0, n, chunk):
            lv = l[s:s + chunk] + V[s:s + chunk]
            F = _peer_condition(lv[:, 0], lv[:, 1], lv[:, 2], x)
            a = np.empty((len(F), u))
            for j in range(u):
                e = np.zeros(u)
                e[j] = hx[j]
                a[:, j] = (_peer_condition(lv[:, 0], lv[:, 1], lv[:, 2], x + e) - F) / hx[j]
            b = np.empty((len(F), 3))
            for j in range(3):
                d = np.zeros(3)
                d[j] = hl[j]
                b[:, j] = (_peer_condition(*(lv + d).T, x) - F) / hl[j]
            w = F - np.sum(b * V[s:s + chunk], axis=1)
            m = (b * b) @ s2
            aq = a / m[:, None]
            N += aq.T @ a
            nv += aq.T @ w
            parts.append((a, b, w, m))
        dx = -np.linalg.solve(N, nv)
        x = x + dx
        omega = 0.0
        for i, (a, b, w, m) in enumerate(parts):
            k = -(a @ dx + w) / m
            V[i * chunk:(i + 1) * chunk] = s2 * b * k[:, None]
            omega += float(np.sum(k * k * m))
    return x, float(np.sqrt(omega / max(n - u, 1)))


def numpy_peer(camp_dir: Path) -> dict:
    """The peer on every scan of the campaign: Parquet columns read with pyarrow, the points
    within 0.1 m (height) of the paraboloid of a first guess (the simulator's truth off by
    cm/mrad, calibration at zero: what initial values give), then ``PEER_ITERATIONS`` steps.
    No preprocessing, no robust rejection, no surface random effect."""
    import tomllib

    import pyarrow.parquet as pq

    toml = tomllib.loads((camp_dir / "campaign.toml").read_text())
    sc = toml["scanner"]
    sigma = np.array([sc["sigma_range_m"], sc["sigma_angle_rad"], sc["sigma_angle_rad"]])
    truth = {s["id"]: s["model_parameters"] for s in
             json.loads((camp_dir / "truth.json").read_text())["scans"]}
    names = ("tx", "ty", "tz", "rx", "ry", "f", "x4", "x6", "x7")
    offset = np.array([0.02, -0.015, 0.03, 2e-3, -1.5e-3, 0.02, 0.0, 0.0, 0.0])
    t0, c0 = time.perf_counter(), _cpu()
    points, out = 0, {}
    for scan in toml["scan"]:
        tab = pq.read_table(camp_dir / scan["file"], columns=["range_m", "phi_rad", "theta_rad"])
        l = np.column_stack([tab.column(k).to_numpy() for k in ("range_m", "phi_rad",
                                                                 "theta_rad")])
        l = l[np.all(np.isfinite(l), axis=1)]
        x0 = np.array([truth[scan["id"]][k] for k in names]) + offset
        x0[6:] = 0.0
        near = np.abs(_peer_condition(l[:, 0], l[:, 1], l[:, 2], x0)) < 0.1
        x, s0 = numpy_peer_fit(l[near], x0, sigma)
        points += int(near.sum())
        out[scan["id"]] = {"f": float(x[5]), "sigma0": s0}
    return {"wall_s": time.perf_counter() - t0, "cpu_s": _cpu() - c0, "points": points,
            "iterations": PEER_ITERATIONS, "scans": out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--positions", type=int, default=6)
    ap.add_argument("--step", type=float, default=0.006, help="angular step of the scans (rad)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-peer", dest="peer", action="store_false",
                    help="skip the plain NumPy Gauss-Helmert peer on the same scans")
    ap.add_argument("--camp", type=Path, default=None,
                    help="an existing campaign (with truth.json) instead of simulating one")
    ap.add_argument("--no-keep-memory", dest="keep_memory", action="store_false",
                    help="return freed memory to the kernel (the CLI keeps it for reuse: "
                         "hartrao_jax._config.keep_freed_memory)")
    ap.add_argument("--runs", type=int, default=2,
                    help="fits in the process (the first compiles, the later ones are warm)")
    ap.add_argument("--out", type=Path, default=OUT / "profile",
                    help="results path without suffix (.json and .md are written)")
    args = ap.parse_args(argv)

    import hartrao_jax  # noqa: F401  (float64)
    from hartrao_jax._config import enable_compilation_cache, keep_freed_memory, set_blas_threads
    from hartrao_jax.campaign import _campaign
    from hartrao_jax.campaign._campaign import load_campaign
    from hartrao_jax.fit import _fit, _records
    from hartrao_jax.preprocess import preprocess_keep
    from hartrao_jax.simulate._simulate import simulate_campaign

    enable_compilation_cache()
    # as the CLI. One BLAS thread for the peer as well: its wall time is the same with its
    # default two (10.79-11.31 against 10.87-10.96 s), at twice the CPU seconds (the second spun)
    if args.keep_memory:
        keep_freed_memory()
        set_blas_threads()
    tmp = Path(tempfile.mkdtemp(prefix="profile-"))  # the outputs (and the campaign it made)
    atexit.register(shutil.rmtree, tmp, True)  # 1.2 GB per run of a full-resolution position
    t0 = time.perf_counter()
    camp_dir = args.camp or tmp / "camp"
    if args.camp is None:
        simulate_campaign(camp_dir, preset="demo", seed=args.seed,
                          positions=POSITIONS[: args.positions], step_rad=args.step,
                          effects={"gravity_deformation": 1.0})
    t_sim = time.perf_counter() - t0
    camp = load_campaign(camp_dir)
    n_rows = sum(_campaign.read_scan(camp, m).range_m.size for m in camp.scans)

    st = Stages()
    st.wrap(_fit, "read_scan", "read")
    st.wrap(_fit, "prepare_scan", "initial values")
    st.wrap(_fit, "robust_gauss_helmert", "gauss-helmert (white)")
    st.wrap(_fit, "gauss_helmert_mixed", "random effect")
    st.wrap(_fit, "finish_scan_fit", "alignment and products")
    keep = preprocess_keep(True, camp)

    def keep_fn(meta, data):
        t, c, p0 = time.perf_counter(), _cpu(), _peak_gib()
        st._stack.append([0.0, 0.0])
        try:
            return keep(meta, data)
        finally:
            iw, ic = st._stack.pop()
            w, cc = time.perf_counter() - t, _cpu() - c
            st.wall["preprocess"] += w - iw
            st.cpu["preprocess"] += cc - ic
            st.calls["preprocess"] += 1
            st.grew["preprocess"] += _peak_gib() - p0
            if st._stack:
                st._stack[-1][0] += w
                st._stack[-1][1] += cc

    runs = []
    labels = ["first (cold compile)", "second (warm)"] + [f"run {i + 3} (warm)" for i in
                                                       range(max(args.runs - 2, 0))]
    for label in labels[: args.runs]:
        for d in (st.wall, st.cpu, st.calls, st.iterations, st.peak, st.grew):
            d.clear()
        load0 = os.getloadavg()[0]
        t0, c0, p_start = time.perf_counter(), _cpu(), _peak_gib()
        cf = _fit.fit_campaign(camp, "extended", keep=keep_fn, progress=False)
        t1, c1, p1 = time.perf_counter(), _cpu(), _peak_gib()
        _records.write_fit(tmp / "out", cf)
        st.wall["write"] += time.perf_counter() - t1
        st.cpu["write"] += _cpu() - c1
        st.grew["write"] += _peak_gib() - p1
        del cf
        total_w, total_c = time.perf_counter() - t0, _cpu() - c0
        stages = {k: {"wall_s": st.wall[k], "cpu_s": st.cpu[k], "calls": st.calls[k],
                      "iterations": list(st.iterations.get(k, [])),
                      "peak_rss_gib_after": st.peak.get(k), "peak_rss_growth_gib": st.grew.get(k)}
                  for k in ("read", "preprocess", "initial values", "gauss-helmert (white)",
                            "random effect", "alignment and products", "write")}
        other = total_w - sum(v["wall_s"] for v in stages.values())
        other_growth = _peak_gib() - p_start - sum(st.grew.values())
        runs.append({"run": label, "total_wall_s": total_w, "total_cpu_s": total_c,
                     "other_wall_s": other, "other_peak_rss_growth_gib": other_growth,
                     "stages": stages,
                     "load_average_1min": [load0, os.getloadavg()[0]],
                     "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20})
        print(label, f"{total_w:.1f} s wall, {total_c:.1f} s CPU", flush=True)
    peer = None
    if args.peer:
        load0 = os.getloadavg()[0]
        peer = numpy_peer(camp_dir)
        peer["load_average_1min"] = [load0, os.getloadavg()[0]]
        print(f"peer {peer['wall_s']:.1f} s wall, {peer['cpu_s']:.1f} s CPU", flush=True)
    doc = {"positions": args.positions, "scans": len(camp.scans), "rows": int(n_rows),
           "step_rad": args.step, "simulate_s": t_sim, "cores": os.cpu_count(),
           "load_average": os.getloadavg(), "runs": runs, "peer": peer}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(doc, indent=2))
    lines = ["# Where the time of `fit` goes", "",
             (f"{args.positions} positions x 2 cycles, {int(n_rows):,} rows at {args.step} rad, "
              if args.camp is None else
              f"campaign {args.camp} ({len(camp.scans)} scans, {int(n_rows):,} rows), ") +
             f"default `fit` (two-face, surface random effect, preprocessing on); "
             f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the end "
             "(`benchmarks/profile.py`).", "",
             "| stage | " + " | ".join(f"{r['run']}: wall s (CPU s)" for r in runs) + " |",
             "|---|" + "---|" * len(runs)]
    for k in runs[0]["stages"]:
        lines.append(f"| {k} | " + " | ".join(
            f"{r['stages'][k]['wall_s']:.1f} ({r['stages'][k]['cpu_s']:.1f})" for r in runs) + " |")
    lines.append("| other (bookkeeping) | " + " | ".join(f"{r['other_wall_s']:.1f}" for r in runs)
                 + " |")
    lines.append("| **total** | " + " | ".join(
        f"**{r['total_wall_s']:.1f}** ({r['total_cpu_s']:.1f})" for r in runs) + " |")
    for k in ("gauss-helmert (white)", "random effect"):
        lines.append(f"| iterations per adjustment, {k} | " + " | ".join(
            ", ".join(map(str, r["stages"][k]["iterations"])) for r in runs) + " |")
    lines.append("| stages where the peak resident grew (GiB) | " + " | ".join(
        ", ".join(f"{k} +{v['peak_rss_growth_gib']:.1f}" for k, v in r["stages"].items()
                  if (v.get("peak_rss_growth_gib") or 0) > 0.05)
        + f", other +{r['other_peak_rss_growth_gib']:.1f}" for r in runs) + " |")
    lines.append("| peak resident (process, GiB) | " + " | ".join(
        f"{r['peak_rss_gib']:.1f}" for r in runs) + " |")
    lines.append("| load average (1 min) at start, end | " + " | ".join(
        "{:.1f}, {:.1f}".format(*r["load_average_1min"]) for r in runs) + " |")
    if peer is not None:
        warm = runs[-1]
        lines += ["", f"Peer (plain NumPy Gauss-Helmert, forward-difference derivatives, "
                  f"{peer['iterations']} iterations, no preprocessing, {peer['points']:,} points "
                  f"within 0.1 m of a first guess): {peer['wall_s']:.1f} s wall "
                  f"({peer['cpu_s']:.1f} CPU s), load {peer['load_average_1min'][0]:.1f}, "
                  f"{peer['load_average_1min'][1]:.1f}; warm `fit` / peer: "
                  f"{peer['wall_s'] / warm['total_wall_s']:.2f}x wall, "
                  f"{peer['cpu_s'] / warm['total_cpu_s']:.2f}x CPU (target 5x)."]
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
