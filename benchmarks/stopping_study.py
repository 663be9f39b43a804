"""How much a change of the iterations' stopping rule moves the two-face estimates and sigmas.

Runs the two-face fits of stored (case, seed) parts of ``uncertainty_calibration.py`` with the
package found first on ``sys.path`` (``PYTHONPATH=<worktree of another revision>`` for the
other side) and writes their rows as JSON lines; ``--compare A B`` then gives, over the
estimates both hold, the largest shift in sigmas, the largest relative change of a sigma and
the standard deviation of z against the truth on either side.

    PYTHONPATH=/tmp/base python benchmarks/stopping_study.py --out before.jsonl --seeds 12
    python benchmarks/stopping_study.py --out after.jsonl --seeds 12
    python benchmarks/stopping_study.py --compare before.jsonl after.jsonl

``--sample``: positions of more than 6e4 points start from a sample of 2.5e4
(``fit._fit.SAMPLE_START_POINTS``, ``SAMPLE_POINTS``), so that the simulated positions take
the path of a full-resolution one (its start's contraction judging the first step).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import uncertainty_calibration as ucal  # noqa: E402


def run(out: Path, cases: list[str], seeds: int, sample: bool) -> None:
    """The two-face rows of every (case, seed) into ``out`` (JSON lines)."""
    if sample:
        import hartrao_jax.fit._fit as fit_module

        fit_module.SAMPLE_START_POINTS, fit_module.SAMPLE_POINTS = 60_000, 25_000
    with out.open("w") as f:
        for case in cases:
            for seed in range(seeds):
                part = json.loads((ucal.PARTS / f"{case}-{seed}.json").read_text())
                t0 = time.time()
                res = ucal.run_one(case, seed, previous=part)
                rows = [r for r in res["rows"]
                        if r["mode"] == "two-face" and r["param"] != "_surface"]
                f.write(json.dumps({"case": case, "seed": seed, "rows": rows}) + "\n")
                f.flush()
                print(f"{case} seed {seed}: {time.time() - t0:.1f} s", file=sys.stderr)


def _rows(path: Path) -> dict:
    out = {}
    for line in path.read_text().splitlines():
        r = json.loads(line)
        for row in r["rows"]:
            out[(r["case"], r["seed"], row["unit"], row["param"])] = row
    return out


def compare(a_path: Path, b_path: Path) -> dict:
    """Shifts of B's estimates from A's (in A's sigmas), B's sigmas against A's, z on each."""
    a, b = _rows(a_path), _rows(b_path)
    keys = sorted(set(a) & set(b))
    dz = np.array([(b[k]["value"] - a[k]["value"]) / a[k]["sigma"] for k in keys])
    ds = np.array([b[k]["sigma"] / a[k]["sigma"] - 1.0 for k in keys])
    per_case = defaultdict(lambda: [0.0, 0.0])
    for k, z, s in zip(keys, dz, ds):
        per_case[k[0]] = [max(per_case[k[0]][0], abs(z)), max(per_case[k[0]][1], abs(s))]
    return {"estimates": len(keys), "max_abs_shift_sigma": float(np.abs(dz).max()),
            "max_abs_sigma_change": float(np.abs(ds).max()),
            "std_z": [float(np.std([a[k]["z"] for k in keys])),
                      float(np.std([b[k]["z"] for k in keys]))],
            "per_case": {c: {"max_abs_shift_sigma": v[0], "max_abs_sigma_change": v[1]}
                         for c, v in per_case.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--cases", default="demo,gravity,gravity-coma-campaign")
    ap.add_argument("--seeds", type=int, default=12)
    ap.add_argument("--sample", action="store_true")
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"))
    args = ap.parse_args(argv)
    if args.compare:
        print(json.dumps(compare(*args.compare), indent=2))
        return 0
    if args.out is None:
        print("error: --out: a file for the rows expected (or --compare A B)", file=sys.stderr)
        return 2
    run(args.out, args.cases.split(","), args.seeds, args.sample)
    return 0


if __name__ == "__main__":
    sys.exit(main())
