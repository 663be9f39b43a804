"""Issue 15's targets in one run: each command in fresh processes, with the machine's state.

    python benchmarks/targets.py [--work /tmp/hartrao-targets] [--runs 3] [--skip stream]

The data are simulated once into ``--work`` and reused by later runs:

* ``diagnose``: preset ``clean`` with :mod:`bench_diagnose`'s effects (panel offsets, x2, an
  impulsive shift), seed 1, 0.005 rad (two cycles, 5.2e5 points);
* ``p12``: :mod:`profile`'s campaign (6 positions x 2 cycles, 0.006 rad, gravity, seed 0);
* ``large``: preset ``paper``, one position (HA -35, DEC -64), both faces at 0.00108 rad
  (1.30e7 rows).

Each command runs ``--runs`` times after one run that fills the compilation cache (left
out): ``diagnose``, ``fit`` of the 12 scans, ``fit`` of the large position, ``fit-stream``
of the large position. Then ``profile.py --camp p12`` gives the 12-scan ``fit`` in one process
against the NumPy peer (the 5x target). :mod:`machine_probe` runs before and after.
The 88-position projection needs 20 GB of scans and 10 minutes:
``bench_campaign.py --stage stream-dask`` (``results/campaign.md``).

Writes ``--out`` (default ``results/targets``) ``.json`` and ``.md``: wall seconds and peak
resident memory of every run, and each target's verdict on this machine.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from ab import compile_package, run_command  # noqa: E402
from machine_probe import fresh as _probe  # noqa: E402
from machine_probe import line as probe_line  # noqa: E402

#: (name, command after ``hartrao-jax``, data set, target wall s or None, target GiB or None)
COMMANDS = (
    ("diagnose", ["diagnose", "{camp}", "--json", "{out}/d.json"], "diagnose", 10.0, None),
    ("12-scan fit", ["fit", "{camp}", "--out", "{out}"], "p12", None, None),
    ("large position fit", ["fit", "{camp}", "--out", "{out}"], "large", 10.0, 4.0),
    ("large position fit-stream", ["fit-stream", "{camp}", "--json", "{out}/s.json"], "large",
     30.0, None),
)

_SIMULATE = {
    "diagnose": "from bench_diagnose import EFFECTS\n"
                "simulate_campaign(out, preset='clean', effects=EFFECTS, seed=1, "
                "step_rad=0.005)",
    "p12": "from profile import POSITIONS\n"
           "simulate_campaign(out, preset='demo', seed=0, positions=POSITIONS[:6], "
           "step_rad=0.006, effects={'gravity_deformation': 1.0})",
    "large": "simulate_campaign(out, preset='paper', seed=0, positions=[('p1', -35.0, -64.0)], "
             "step_rad=0.00108)",
}


def _simulate(name: str, out: Path) -> None:
    """The data set ``name`` into ``out`` (in a process of its own), unless it is there."""
    if (out / "campaign.toml").is_file():
        return
    print(f"simulating {name} into {out} ...", flush=True)
    code = (f"import sys; sys.path.insert(0, {str(HERE)!r})\n"
            "from hartrao_jax.simulate._simulate import simulate_campaign\n"
            f"out = {str(out)!r}\n{_SIMULATE[name]}\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def _verdict(value: float, target: float | None) -> str:
    return "" if target is None else ("met" if value < target else "not met")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/hartrao-targets"))
    ap.add_argument("--runs", type=int, default=3, help="warm runs per command")
    ap.add_argument("--skip", default="", help="comma-separated: diagnose, p12, large, stream, "
                                               "peer")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "targets")
    a = ap.parse_args(argv)
    skip = {s.strip() for s in a.skip.split(",") if s.strip()}
    a.work.mkdir(parents=True, exist_ok=True)
    compile_package(HERE.parent)
    cwd = tempfile.mkdtemp(prefix="targets-cwd-")  # empty: no checkout shadows the package
    atexit.register(shutil.rmtree, cwd, True)
    doc: dict = {"runs_per_command": a.runs, "probe_before": _probe(), "commands": {}}
    print("machine before:", probe_line(doc["probe_before"]), flush=True)
    for name, args, data, t_wall, t_gib in COMMANDS:
        if data in skip or ("stream" in skip and "stream" in name):
            continue
        camp = a.work / data
        _simulate(data, camp)
        argv = [x.replace("{camp}", str(camp)) for x in args]
        run_command(HERE.parent, argv, cwd)  # fills the compilation cache (left out)
        runs = [run_command(HERE.parent, argv, cwd) for _ in range(a.runs)]
        wall = statistics.median(r["wall_s"] for r in runs)
        peak = max(r["peak_gib"] for r in runs)
        doc["commands"][name] = {"argv": argv, "runs": runs, "median_wall_s": wall,
                                 "max_peak_gib": peak, "target_wall_s": t_wall,
                                 "target_peak_gib": t_gib}
        print(f"{name}: " + ", ".join(f"{r['wall_s']:.2f} s" for r in runs)
              + f" (median {wall:.2f} s), peak {peak:.2f} GiB", flush=True)
    if "peer" not in skip and "p12" not in skip:
        prof = a.work / "profile"
        subprocess.run([sys.executable, str(HERE / "profile.py"), "--camp", str(a.work / "p12"),
                        "--runs", "2", "--out", str(prof)], check=True, capture_output=True)
        p = json.loads(prof.with_suffix(".json").read_text())
        warm = p["runs"][-1]["total_wall_s"]
        doc["peer"] = {"fit_in_process_warm_s": warm, "peer_s": p["peer"]["wall_s"],
                       "ratio": p["peer"]["wall_s"] / warm}
        print(f"12-scan fit in one process {warm:.2f} s, peer {p['peer']['wall_s']:.2f} s: "
              f"{doc['peer']['ratio']:.2f}x", flush=True)
    doc["probe_after"] = _probe()
    print("machine after:", probe_line(doc["probe_after"]), flush=True)

    doc["date_utc"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    lines = ["# Issue 15's targets on this machine (`benchmarks/targets.py`)", "",
             f"{doc['date_utc']}, {os.cpu_count()} cores. Each command {a.runs} times in fresh "
             "processes, caches warm (after one run that compiles). The data sets are the "
             "module docstring's. Machine before: "
             f"{probe_line(doc['probe_before'])}; after: {probe_line(doc['probe_after'])}. "
             "The 88-position projection: `results/campaign.md`.",
             "", "| command | wall s (runs) | median | peak GiB | target | verdict |",
             "|---|---|---|---|---|---|"]
    for name, c in doc["commands"].items():
        target = " and ".join(t for t in (
            f"< {c['target_wall_s']:g} s" if c["target_wall_s"] else "",
            f"< {c['target_peak_gib']:g} GiB" if c["target_peak_gib"] else "") if t) or "-"
        verdict = " and ".join(v for v in (_verdict(c["median_wall_s"], c["target_wall_s"]),
                                           _verdict(c["max_peak_gib"], c["target_peak_gib"]))
                               if v) or "-"
        lines.append(f"| {name} | "
                     + ", ".join(f"{r['wall_s']:.2f}" for r in c["runs"])
                     + f" | {c['median_wall_s']:.2f} | {c['max_peak_gib']:.2f} | {target} | "
                       f"{verdict} |")
    if "peer" in doc:
        pr = doc["peer"]
        lines.append(f"| 12-scan `fit` in one process against the NumPy peer | "
                     f"{pr['fit_in_process_warm_s']:.2f} against {pr['peer_s']:.2f} | | | 5x | "
                     f"{pr['ratio']:.2f}x: {'met' if pr['ratio'] >= 5.0 else 'not met'} |")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(doc, indent=1))
    a.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
