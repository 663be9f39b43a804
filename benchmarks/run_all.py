"""Run every benchmark script ``benchmarks/bench_*.py`` in sequence (one process each).

    python benchmarks/run_all.py [--quick] [--only ghm,kernels] [--skip surface] [--list]

``--quick`` is passed to the scripts that accept it (their source mentions ``--quick``); the
others run with their defaults. Each script writes its own ``benchmarks/results/<name>.md`` and
``.json``; this runner prints a summary (exit code, duration) and exits non-zero if any failed.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def scripts() -> list[Path]:
    return sorted(HERE.glob("bench_*.py"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short runs where supported")
    ap.add_argument("--only", default="", help="comma-separated names (bench_<name>.py)")
    ap.add_argument("--skip", default="", help="comma-separated names to leave out")
    ap.add_argument("--list", action="store_true", help="list the scripts and exit")
    args = ap.parse_args(argv)

    only = {s.strip() for s in args.only.split(",") if s.strip()}
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    todo = [p for p in scripts()
            if (not only or p.stem[6:] in only) and p.stem[6:] not in skip]
    if args.list:
        print("\n".join(p.name for p in todo))
        return 0

    summary = []
    for p in todo:
        cmd = [sys.executable, str(p)]
        if args.quick and "--quick" in p.read_text():
            cmd.append("--quick")
        print(f"\n=== {p.name} ({' '.join(cmd[2:]) or 'defaults'}) ===", flush=True)
        t = time.perf_counter()
        rc = subprocess.call(cmd, cwd=HERE.parent)
        dt = time.perf_counter() - t
        summary.append((p.name, rc, dt))
        print(f"=== {p.name}: exit {rc} after {dt:.0f} s ===", flush=True)

    print("\nsummary:")
    for name, rc, dt in summary:
        print(f"  {name:28s} {'ok' if rc == 0 else f'FAILED (exit {rc})':16s} {dt:8.0f} s")
    return 0 if all(rc == 0 for _, rc, _ in summary) else 1


if __name__ == "__main__":
    sys.exit(main())
