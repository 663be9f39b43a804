"""Wall time of one ``diagnose`` of a two-cycle scan (position r23), by stage.

The campaign is simulated once per size (panel offsets 0.15 mm rms, a transit offset x2 and an
impulsive shift in cycle 1, so the loop accepts three findings and then proves that nothing is
left). Each size runs in a fresh process twice: cold (empty compilation cache) and warm (the
persistent cache filled by the first run), so both the first use and the usual use are timed.

    python benchmarks/bench_diagnose.py [--steps 0.005,0.0036] [--quick]

``--quick``: one small size (0.01 rad, 1.3e5 points). Writes
``benchmarks/results/diagnose.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

EFFECTS = {"panel_offset": {"rms_m": 1.5e-4}, "x2": 1e-4,
           "impulsive_shift": {"displacement_m": 8e-4, "phi_deg": 40.0, "duration_s": 0.6}}


def _child(camp: str, cache: str) -> None:
    os.environ["HARTRAO_JAX_CACHE"] = cache
    import hartrao_jax  # noqa: F401
    from hartrao_jax._config import enable_compilation_cache
    from hartrao_jax.diagnose._diagnose import diagnose

    enable_compilation_cache()
    t = time.perf_counter()
    c0 = time.process_time()
    d = diagnose(camp)
    wall = time.perf_counter() - t
    cpu = time.process_time() - c0
    n = sum(c["n_points"] for c in d.comparison)
    print(json.dumps({"wall_s": wall, "cpu_s": cpu, "load_1min": os.getloadavg()[0],
                      "timing_s": d.timing_s, "n_points": n,
                      "findings": [f.effect for f in d.findings],
                      "sigma0": [d.sigma0_start, d.sigma0_final]}))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", default="0.005", help="angular steps (rad), comma-separated")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _child(*args.child)
        return 0
    from _common import machine_info, md_table, write_results

    import hartrao_jax  # noqa: F401
    from hartrao_jax.simulate._simulate import simulate_campaign

    steps = [0.01] if args.quick else [float(s) for s in args.steps.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for step in steps:
            camp = Path(tmp) / f"camp-{step}"
            t = time.perf_counter()
            simulate_campaign(camp, preset="clean", effects=EFFECTS, seed=1, step_rad=step)
            t_sim = time.perf_counter() - t
            cache = str(Path(tmp) / f"cache-{step}")
            for run in ("cold", "warm"):
                out = subprocess.run([sys.executable, __file__, "--child", str(camp), cache],
                                     capture_output=True, text=True, check=True)
                res = json.loads(out.stdout.strip().splitlines()[-1])
                rows.append({"step_rad": step, "run": run, "n_points": res["n_points"],
                             "wall_s": res["wall_s"], "cpu_s": res["cpu_s"],
                             "load_1min": res["load_1min"],
                             "start_fit_s": res["timing_s"]["start_fit"],
                             "loop_s": res["timing_s"]["loop"],
                             "findings": ",".join(res["findings"]),
                             "simulate_s": t_sim})
                print(rows[-1], flush=True)
    md = ("# diagnose: wall time of one two-cycle scan\n\nOn a 2-core machine, wall time "
          "lies between CPU time / 2 and CPU time when the machine is otherwise idle; a load "
          "above 2 means other jobs shared the cores.\n\n") + md_table(rows, [
        ("step_rad", "step [rad]", "g"), ("run", "run", ""), ("n_points", "points", "d"),
        ("wall_s", "wall [s]", ".1f"), ("cpu_s", "process CPU [s]", ".1f"),
        ("load_1min", "load (1 min) at end", ".1f"), ("start_fit_s", "start fit [s]", ".1f"),
        ("loop_s", "loop [s]", ".1f"), ("findings", "findings", "")])
    write_results("diagnose", md, {"rows": rows, "machine": machine_info(), "effects": EFFECTS})
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
