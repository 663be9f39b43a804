"""Cycle averaging at the paper's density: two cycles of up to 1.3e7 points each.

Synthetic points (no simulator, no fit): cycle 1 uniform in area over the panelled annulus
(rho 1.6 .. 12.95 m) of the paraboloid, deviations = panel offsets + noise; cycle 2 the same
spots displaced by 3 mm (what two cycles of one position look like after the adjustment) and
shuffled, with the two-face error of opposite sign. 1.3e7 points per cycle is the paper's
0.63 mrad grid (6.3 mm at 10 m) over the reflector.

Timed stages of :mod:`hartrao_jax.surface._surface` (each size in its own subprocess, so that
peak memory is its own):

* ``panel_mask``: panel ids and the 2 cm edge masks of both cycles;
* ``cycle_average``: cells of the 1 cm circles keyed by panel, per-cycle means, cross-cycle
  pairing of the leftover cells with cKDTree;
* ``panel_statistics``: per-panel mean, plane (tilt), rms of the averaged points.

Memory: resident set after the inputs exist, and the peak above it during each stage
(``ru_maxrss``), plus the peak of NumPy allocations inside ``cycle_average`` (tracemalloc).
A baseline for comparison: the direct circle search (cKDTree ``query_ball_point`` of every
cycle-1 point among the cycle-2 points of its panel, the obvious transcription of the paper),
at the smaller sizes only.

    python benchmarks/bench_surface.py [--sizes 1e6,4e6,1.3e7] [--baseline 1e6,4e6]

Writes ``benchmarks/results/surface.md`` and ``.json``.
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


def _rss_mib() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class PeakRSS:
    """Peak resident set size (MiB) while the ``with`` block runs (sampled every 2 ms)."""

    def __enter__(self):
        import threading

        self.peak = _rss_mib()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self):
        while not self._stop.wait(0.002):
            self.peak = max(self.peak, _rss_mib())

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, _rss_mib())


def make_cycles(n: int, seed: int = 0, block: int = 1 << 21):
    """Two cycles of ``n`` points: (X1, d1, X2, d2), built in blocks (few temporaries)."""
    from hartrao_jax.surface._surface import PanelLayout

    lay = PanelLayout.default()
    rng = np.random.default_rng(seed)
    offsets = rng.normal(scale=3e-4, size=lay.n_panels)
    X1 = np.empty((n, 3))
    d1 = np.empty(n)
    for s in range(0, n, block):
        m = min(block, n - s)
        rho = np.sqrt(rng.uniform(1.6**2, 12.95**2, m))
        psi = rng.uniform(0, 2 * np.pi, m)
        X1[s:s + m, 0] = rho * np.cos(psi)
        X1[s:s + m, 1] = rho * np.sin(psi)
        X1[s:s + m, 2] = rho * rho / (4 * 10.9816)
        from hartrao_jax.geometry._geometry import panel_ids

        pid = panel_ids(rho, psi, lay.ring_edges_m, lay.panels_per_ring)
        d1[s:s + m] = offsets[pid] + rng.normal(scale=8e-4, size=m)
    perm = rng.permutation(n)
    X2 = X1[perm]
    X2 += rng.normal(scale=3e-3, size=(n, 3))
    d2 = d1[perm]  # the same surface ...
    for s in range(0, n, block):  # ... with its own noise: replace cycle 1's noise term
        m = min(block, n - s)
        d2[s:s + m] += rng.normal(scale=8e-4, size=m) - (d1[perm[s:s + m]] - _truth(
            X1[perm[s:s + m]], offsets, lay))
    two_face = 3e-4 * np.sign(X1[:, 0])
    d1 += two_face
    d2 -= two_face[perm]
    del perm, two_face
    return X1, d1, X2, d2


def _truth(X: np.ndarray, offsets: np.ndarray, lay) -> np.ndarray:
    from hartrao_jax.geometry._geometry import panel_ids

    rho = np.hypot(X[:, 0], X[:, 1])
    psi = np.mod(np.arctan2(X[:, 1], X[:, 0]), 2 * np.pi)
    return offsets[panel_ids(rho, psi, lay.ring_edges_m, lay.panels_per_ring)]


def run_one(n: int, baseline: bool) -> dict:
    """One size, in this process: the stages' times and memory."""
    import tracemalloc

    from hartrao_jax.surface._surface import (
        PanelLayout,
        SurfaceConfig,
        cycle_average,
        panel_mask,
        panel_statistics,
    )

    lay = PanelLayout.default()
    cfg = SurfaceConfig()
    t = time.perf_counter()
    X1, d1, X2, d2 = make_cycles(n)
    out = {"n_per_cycle": n, "make_s": time.perf_counter() - t}
    out["input_MiB"] = (X1.nbytes + d1.nbytes + X2.nbytes + d2.nbytes) / 2**20
    out["rss_inputs_MiB"] = _rss_mib()

    base = _rss_mib()
    t = time.perf_counter()
    with PeakRSS() as pk:
        p1, p2 = panel_mask(X1, lay, cfg), panel_mask(X2, lay, cfg)
    out["panel_mask_s"] = time.perf_counter() - t
    out["panel_mask_peak_above_MiB"] = pk.peak - base

    base = _rss_mib()
    t = time.perf_counter()
    with PeakRSS() as pk:
        avg = cycle_average(X1, d1, p1, X2, d2, p2, radius_m=0.01)
    out["cycle_average_s"] = time.perf_counter() - t
    out["cycle_average_peak_above_MiB"] = pk.peak - base
    out["n_groups"] = len(avg)
    out["n_unpaired"] = int(avg.n_unpaired)
    out["paired_fraction"] = 1.0 - avg.n_unpaired / (2.0 * n)
    out["rms_cycle1_mm"] = 1e3 * float(np.sqrt(np.mean(d1[p1 >= 0] ** 2)))
    out["rms_averaged_mm"] = 1e3 * avg.rms_m

    t = time.perf_counter()
    tab = panel_statistics(avg.X, avg.deviation_m, avg.panel, lay)
    out["panel_statistics_s"] = time.perf_counter() - t
    out["panels_with_data"] = int(np.isfinite(tab.deviation_m).sum())
    del avg, tab

    # NumPy allocations of cycle_average alone (tracemalloc: slower, measured separately)
    tracemalloc.start()
    cycle_average(X1, d1, p1, X2, d2, p2, radius_m=0.01)
    out["cycle_average_tracemalloc_peak_MiB"] = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()

    if baseline:
        out.update(_baseline(X1, d1, p1, X2, d2, p2, 0.01))
    out["peak_rss_MiB"] = _peak_mib()
    return out


def _baseline(X1, d1, p1, X2, d2, p2, r) -> dict:
    """The direct circle search: every cycle-1 point with the cycle-2 points of its panel
    within r (cKDTree.query_ball_point, all cores), averaged."""
    from scipy.spatial import cKDTree

    base = _rss_mib()
    t = time.perf_counter()
    with PeakRSS() as pk:
        s1, s2 = p1 >= 0, p2 >= 0
        big = 1e3
        tree = cKDTree(np.column_stack([X2[s2, :2], p2[s2] * big]))
        lists = tree.query_ball_point(np.column_stack([X1[s1, :2], p1[s1] * big]), r, workers=-1)
        cnt = np.fromiter((len(x) for x in lists), np.int64, len(lists))
        idx = np.concatenate([np.asarray(x, np.int64) for x in lists if x])
        owner = np.repeat(np.arange(len(lists)), cnt)
        m2 = np.bincount(owner, weights=d2[s2][idx], minlength=len(lists))
        with np.errstate(invalid="ignore"):
            dev = 0.5 * (d1[s1] + m2 / cnt)
        ok = cnt > 0
    return {"baseline_s": time.perf_counter() - t,
            "baseline_peak_above_MiB": pk.peak - base,
            "baseline_paired_fraction": float(ok.mean()),
            "baseline_rms_averaged_mm": 1e3 * float(np.sqrt(np.mean(dev[ok] ** 2)))}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1e6,4e6,1.3e7")
    ap.add_argument("--baseline", default="1e6,4e6",
                    help="sizes at which the direct cKDTree circle search runs too")
    ap.add_argument("--one", type=float, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--with-baseline", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one is not None:
        print(json.dumps(run_one(int(args.one), args.with_baseline)))
        return
    from _common import machine_info, md_table, write_results

    sizes = [int(float(s)) for s in args.sizes.split(",") if s]
    base_sizes = {int(float(s)) for s in args.baseline.split(",") if s}
    load0 = os.getloadavg()[0]
    rows = []
    for n in sizes:
        cmd = [sys.executable, __file__, "--one", str(n)]
        if n in base_sizes:
            cmd.append("--with-baseline")
        print(f"n = {n:,} per cycle ...", flush=True)
        r = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if r.returncode != 0:
            print(r.stderr[-3000:], file=sys.stderr)
            raise SystemExit(f"size {n} failed")
        row = json.loads(r.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(json.dumps(row, indent=1), flush=True)
    load1 = os.getloadavg()[0]
    info = machine_info()
    cols = [("n_per_cycle", "points per cycle", ",d"), ("panel_mask_s", "panel mask s", ".2f"),
            ("cycle_average_s", "cycle average s", ".2f"),
            ("panel_statistics_s", "panel stats s", ".2f"),
            ("rss_inputs_MiB", "RSS with inputs MiB", ".0f"),
            ("cycle_average_peak_above_MiB", "average: peak above MiB", ".0f"),
            ("cycle_average_tracemalloc_peak_MiB", "average: NumPy peak MiB", ".0f"),
            ("paired_fraction", "paired", ".4f"), ("n_groups", "groups", ",d"),
            ("rms_cycle1_mm", "rms cycle 1 mm", ".3f"),
            ("rms_averaged_mm", "rms averaged mm", ".3f")]
    bcols = [("n_per_cycle", "points per cycle", ",d"),
             ("cycle_average_s", "cells + pairing s", ".2f"),
             ("baseline_s", "cKDTree ball search s", ".2f"),
             ("cycle_average_peak_above_MiB", "cells: peak above MiB", ".0f"),
             ("baseline_peak_above_MiB", "ball search: peak above MiB", ".0f"),
             ("paired_fraction", "cells: paired", ".4f"),
             ("baseline_paired_fraction", "ball search: paired", ".4f"),
             ("rms_averaged_mm", "cells: rms mm", ".3f"),
             ("baseline_rms_averaged_mm", "ball search: rms mm", ".3f")]
    md = ["# Cycle averaging (surface products)", "",
          "Two synthetic cycles per size (uniform over the panelled annulus; cycle 2 = the same "
          "spots moved by 3 mm, shuffled; panel offsets 0.3 mm rms, noise 0.8 mm, a +-0.3 mm "
          "two-face error of opposite sign in the two cycles), 1 cm circles, 2 cm panel edge "
          "masks, one subprocess per size. 1.3e7 points per cycle is the paper's 0.63 mrad "
          "grid. `peak above` = peak RSS during the stage (sampled every 2 ms) minus the RSS "
          "before it (the inputs: 32 bytes per point); `NumPy peak` = tracemalloc peak of the "
          "NumPy allocations of `cycle_average` alone.", "",
          f"Load average before/after: {load0:.1f} / {load1:.1f} (the machine is shared: "
          "other jobs inflate timings).", "",
          md_table(rows, cols)]
    if any("baseline_s" in r for r in rows):
        md += ["", "## Against the direct circle search", "",
               "The obvious transcription of the paper: for every cycle-1 point, the cycle-2 "
               "points of its panel within 1 cm (`cKDTree.query_ball_point`, all cores), "
               "averaged with it. It gives one (overlapping) group per cycle-1 point and "
               "weighs the cycles unequally where the densities differ.", "",
               md_table([r for r in rows if "baseline_s" in r], bcols)]
    md += ["", "```", json.dumps(info, indent=1), "```", ""]
    p_md, _ = write_results("surface", "\n".join(md), {"machine": info, "rows": rows,
                                                       "load": [load0, load1]})
    print(f"wrote {p_md}")


if __name__ == "__main__":
    main()
