"""The proof of the discrepancy engine on concealed data, as a script (same as
``hartrao-jax prove``).

    python benchmarks/prove.py [--out DIR] [--seeds N] [--cases a,b] [--step RAD]

For every case of :data:`hartrao_jax.prove._prove.CASES` (one effect class concealed below the
noise, absorbed by the model, masked by panel deviations or confined to a small part of one scan;
plus clean controls) it simulates ``--seeds`` campaigns, diagnoses them blind and scores the
findings against the truth. Prints the table and writes ``DIR/prove.json``, ``prove.md``,
``prove.png``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results/prove")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    ap.add_argument("--step", type=float, default=0.01, help="angular step (rad)")
    ap.add_argument("--seed0", type=int, default=1, help="first seed")
    ap.add_argument("--keep-campaigns", action="store_true")
    ap.add_argument("--merge", default=None,
                    help="comma-separated result directories of earlier runs: one table")
    ap.add_argument("--detectability", action="store_true",
                    help="only the minimal detectable amplitudes on a clean campaign")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger("hartrao_jax").setLevel(logging.INFO)
    import hartrao_jax  # noqa: F401
    from hartrao_jax.cli._diagnose import print_table
    from hartrao_jax.prove._prove import detectability, merge_results, run_prove

    if args.merge:
        res = merge_results(args.out, args.merge.split(","))
        print_table(res)
        return 0

    if args.detectability:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        for r in detectability(args.out, step_rad=args.step, seed=args.seed0):
            print(f"{r['effect']:16s} {r['parameter']:12s} {r['minimal_detectable']:10.3g} "
                  f"{r['unit']:5s} {r['relative_to_range_noise']:7.3f} x noise ({r['limited_by']})")
        return 0

    res = run_prove(args.out, seeds=args.seeds,
                    cases=args.cases.split(",") if args.cases else None, step_rad=args.step,
                    keep_campaigns=args.keep_campaigns, progress=True, seed0=args.seed0)
    print_table(res)
    print(f"wrote {res['paths']['json']} and {res['paths']['table']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
