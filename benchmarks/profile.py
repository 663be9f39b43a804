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

    python benchmarks/profile.py                 # 6 positions x 2 cycles at 6 mrad (~2.5e6 rows)
    python benchmarks/profile.py --positions 2 --step 0.01

Results: ``results/profile.md`` and ``.json``. Times include compilation on the first call of
each shape (the persistent compilation cache is on, as in the CLI): run twice to see it warm.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import jax

HERE = Path(__file__).resolve().parent
OUT = HERE / "results"
POSITIONS = [("p1", -35.0, -64.0), ("p2", -60.0, -30.0), ("p3", 40.0, -70.0),
             ("p4", 0.0, 10.0), ("p5", 70.0, -20.0), ("p6", 10.0, -40.0)]


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class Stages:
    """Wall and CPU seconds per stage; nested stages are charged to the innermost one."""

    def __init__(self):
        self.wall = defaultdict(float)
        self.cpu = defaultdict(float)
        self.calls = defaultdict(int)
        self._stack: list[list] = []

    def wrap(self, module, name: str, stage: str):
        fn = getattr(module, name)

        def timed(*a, **k):
            t0, c0 = time.perf_counter(), _cpu()
            self._stack.append([0.0, 0.0])
            try:
                out = fn(*a, **k)
                if hasattr(out, "x"):  # an adjustment result: wait for the device
                    jax.block_until_ready(out.x)
                return out
            finally:
                inner_w, inner_c = self._stack.pop()
                w, c = time.perf_counter() - t0, _cpu() - c0
                self.wall[stage] += w - inner_w
                self.cpu[stage] += c - inner_c
                self.calls[stage] += 1
                if self._stack:
                    self._stack[-1][0] += w
                    self._stack[-1][1] += c

        setattr(module, name, timed)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--positions", type=int, default=6)
    ap.add_argument("--step", type=float, default=0.006, help="angular step of the scans (rad)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    import hartrao_jax  # noqa: F401  (float64)
    from hartrao_jax._config import enable_compilation_cache
    from hartrao_jax.campaign import _campaign
    from hartrao_jax.campaign._campaign import load_campaign
    from hartrao_jax.fit import _fit, _records
    from hartrao_jax.preprocess import preprocess_keep
    from hartrao_jax.simulate._simulate import simulate_campaign

    enable_compilation_cache()
    tmp = Path(tempfile.mkdtemp(prefix="profile-"))
    t0 = time.perf_counter()
    simulate_campaign(tmp / "camp", preset="demo", seed=args.seed,
                      positions=POSITIONS[: args.positions], step_rad=args.step,
                      effects={"gravity_deformation": 1.0})
    t_sim = time.perf_counter() - t0
    camp = load_campaign(tmp / "camp")
    n_rows = sum(_campaign.read_scan(camp, m).range_m.size for m in camp.scans)

    st = Stages()
    st.wrap(_fit, "read_scan", "read")
    st.wrap(_fit, "prepare_scan", "initial values")
    st.wrap(_fit, "robust_gauss_helmert", "gauss-helmert (white)")
    st.wrap(_fit, "gauss_helmert_mixed", "random effect")
    st.wrap(_fit, "finish_scan_fit", "alignment and products")
    keep = preprocess_keep(True, camp)

    def keep_fn(meta, data):
        t, c = time.perf_counter(), _cpu()
        st._stack.append([0.0, 0.0])
        try:
            return keep(meta, data)
        finally:
            iw, ic = st._stack.pop()
            w, cc = time.perf_counter() - t, _cpu() - c
            st.wall["preprocess"] += w - iw
            st.cpu["preprocess"] += cc - ic
            st.calls["preprocess"] += 1
            if st._stack:
                st._stack[-1][0] += w
                st._stack[-1][1] += cc

    runs = []
    for label in ("first (cold compile)", "second (warm)"):
        for d in (st.wall, st.cpu, st.calls):
            d.clear()
        load0 = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), _cpu()
        cf = _fit.fit_campaign(camp, "extended", keep=keep_fn, progress=False)
        t1, c1 = time.perf_counter(), _cpu()
        _records.write_fit(tmp / "out", cf)
        st.wall["write"] += time.perf_counter() - t1
        st.cpu["write"] += _cpu() - c1
        total_w, total_c = time.perf_counter() - t0, _cpu() - c0
        stages = {k: {"wall_s": st.wall[k], "cpu_s": st.cpu[k], "calls": st.calls[k]}
                  for k in ("read", "preprocess", "initial values", "gauss-helmert (white)",
                            "random effect", "alignment and products", "write")}
        other = total_w - sum(v["wall_s"] for v in stages.values())
        runs.append({"run": label, "total_wall_s": total_w, "total_cpu_s": total_c,
                     "other_wall_s": other, "stages": stages,
                     "load_average_1min": [load0, os.getloadavg()[0]]})
        print(label, f"{total_w:.1f} s wall, {total_c:.1f} s CPU", flush=True)
    doc = {"positions": args.positions, "scans": len(camp.scans), "rows": int(n_rows),
           "step_rad": args.step, "simulate_s": t_sim, "cores": os.cpu_count(),
           "load_average": os.getloadavg(), "runs": runs}
    OUT.mkdir(exist_ok=True)
    (OUT / "profile.json").write_text(json.dumps(doc, indent=2))
    lines = ["# Where the time of `fit` goes", "",
             f"{args.positions} positions x 2 cycles, {int(n_rows):,} rows at {args.step} rad, "
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
    lines.append("| load average (1 min) at start, end | " + " | ".join(
        "{:.1f}, {:.1f}".format(*r["load_average_1min"]) for r in runs) + " |")
    (OUT / "profile.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
