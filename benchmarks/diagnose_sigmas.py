"""Calibration of the sigmas `diagnose` reports for its final model: z over seeded campaigns.

For every case and seed a campaign with known truth is simulated and diagnosed blind; z =
(estimate - truth) / sigma is collected for the pose, f and every calibration parameter of the
diagnosis JSON: per position (``positions[]``: both faces together, the surface a random
effect), per scan (``scans``: each scan's own unknowns with the same random effect) and, for
comparison, per scan against the loop's white-noise sigma (``sigma_white``). Target as for
``fit``: std(z) 0.8-1.25, no |z| > 4.

    python benchmarks/diagnose_sigmas.py                      # all cases, 20 seeds
    python benchmarks/diagnose_sigmas.py --cases x2 --seeds 3
    python benchmarks/diagnose_sigmas.py --merge              # tables from parts/*.json

Each (case, seed) is stored in ``results/diagnose_sigmas/parts/`` as soon as it is done.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "results"
PARTS = OUT / "diagnose_sigmas" / "parts"

PANELS = {"x4": 1.5e-4, "x6": 3e-5, "x7": -4e-5, "panel_offset": 1.5e-4}
# name: (positions or None (the preset's), effects, step_rad)
CASES = {
    "panels": (None, PANELS, 0.01),
    "x2": (None, {**PANELS, "x2": 3e-4}, 0.01),
    "gravity": ([("g1", -60.0, -30.0), ("g2", 40.0, -70.0), ("g3", 0.0, 10.0)],
                {**PANELS, "gravity_deformation": 1.0}, 0.015),
}
SEED_OFFSET = {"panels": 60_000, "x2": 70_000, "gravity": 80_000}
PARAMS = ("tx", "ty", "tz", "rx", "ry", "f", "x2", "x4", "x6", "x7")


def _z(name: str, value: float, truth: float, sigma: float) -> float:
    d = value - truth
    if name in ("rx", "ry"):
        d = (d + np.pi) % (2 * np.pi) - np.pi
    return float(d / sigma)


def run_one(case: str, seed: int) -> dict:
    from hartrao_jax.diagnose import diagnose
    from hartrao_jax.simulate._simulate import simulate_campaign

    positions, effects, step = CASES[case]
    tmp = Path(tempfile.mkdtemp(prefix=f"dsig-{case}-{seed}-"))
    try:
        simulate_campaign(tmp / "c", preset="demo", effects=effects,
                          seed=seed + SEED_OFFSET[case], positions=positions, step_rad=step)
        truth = json.loads((tmp / "c" / "truth.json").read_text())
        ts = {s["id"]: {**s, **s.get("model_parameters", {})} for s in truth["scans"]}
        tp = {s["position"]: ts[s["id"]] for s in truth["scans"]}
        t0 = time.time()
        doc = diagnose(tmp / "c").to_json()
        rows, held = [], []
        for p in doc["positions"]:
            for n, e in p["estimates"].items():
                if n not in PARAMS:
                    continue
                if e.get("identifiable") is False:
                    held.append({"position": p["position"], "param": n, "note": e["note"]})
                    continue
                rows.append({"mode": "position", "unit": p["position"], "param": n,
                             "z": _z(n, e["value"], tp[p["position"]].get(n, 0.0), e["sigma"])})
        for n, e in doc["shared_estimates"].items():
            if n in PARAMS:
                rows.append({"mode": "position", "unit": "shared", "param": n,
                             "z": _z(n, e["value"], effects.get(n, 0.0), e["sigma"])})
        for sid, s in doc["scans"].items():
            for n, e in s["estimates"].items():
                if n not in PARAMS:
                    continue
                tr = ts[sid].get(n, 0.0)
                rows.append({"mode": "scan", "unit": sid, "param": n,
                             "z": _z(n, e["value"], tr, e["sigma"])})
                rows.append({"mode": "scan, white sigma", "unit": sid, "param": n,
                             "z": _z(n, e["value"], tr, e["sigma_white"])})
        return {"case": case, "seed": seed, "rows": rows, "held": held,
                "findings": [f["effect"] for f in doc["findings"]],
                "seconds": time.time() - t0, "timing_s": doc["timing_s"]}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def summarize(parts: list[dict]) -> str:
    modes = ("position", "scan", "scan, white sigma")
    lines = ["# Calibration of the sigmas of `diagnose`'s final model", "",
             "z = (estimate - truth) / sigma over seeded simulated campaigns, diagnosed blind "
             "(`benchmarks/diagnose_sigmas.py`). `position`: both faces together, the surface "
             "(panel offsets and tilts) a random effect with variances estimated "
             "(`positions[]` and `shared_estimates` of the diagnosis JSON); `scan`: each "
             "scan's own unknowns with the same random effect (`scans`); `scan, white sigma`: "
             "the same values judged with the loop's white-noise sigma (`sigma_white`). "
             "Target: std(z) 0.8-1.25, no |z| > 4. The std of 20 standard-normal z scatters "
             "by about 0.16.", ""]
    for case in dict.fromkeys(p["case"] for p in parts):
        ps = [p for p in parts if p["case"] == case]
        fnd: dict[str, int] = {}
        for p in ps:
            for f in p["findings"]:
                fnd[f] = fnd.get(f, 0) + 1
        lines += [f"## {case} ({len(ps)} seeds)", "",
                  "findings: " + ", ".join(f"{k} {v}/{len(ps)}" for k, v in fnd.items())
                  + f"; median time {np.median([p['seconds'] for p in ps]):.0f} s", ""]
        params = [n for n in PARAMS if any(r["param"] == n for p in ps for r in p["rows"])]
        lines += ["| mode | n per parameter | " + " | ".join(f"std z {n}" for n in params)
                  + " | max abs z |", "|---" * (len(params) + 3) + "|"]
        for m in modes:
            zs = {n: np.array([r["z"] for p in ps for r in p["rows"]
                               if r["mode"] == m and r["param"] == n]) for n in params}
            allz = np.concatenate([z for z in zs.values() if z.size]) if zs else np.zeros(0)
            if not allz.size:
                continue
            cells = [f"{np.std(z, ddof=1):.2f}" if z.size > 1 else "-" for z in zs.values()]
            lines.append(f"| {m} | {max(z.size for z in zs.values())} | " + " | ".join(cells)
                         + f" | {np.max(np.abs(allz)):.1f} |")
        held = [h for p in ps for h in p["held"]]
        lines += ["", f"not identifiable (not scored): {len(held)}"
                  + (f", e.g. {held[0]['param']}: {held[0]['note']}" if held else ""), ""]
    pos = np.array([r["z"] for p in parts for r in p["rows"] if r["mode"] == "position"])
    white = np.array([r["z"] for p in parts for r in p["rows"]
                      if r["mode"] == "scan, white sigma"])
    lines += ["## All cases", "",
              f"position: {pos.size} estimates, std z {np.std(pos, ddof=1):.2f}, "
              f"{int(np.sum(np.abs(pos) > 4))} with |z| > 4 (largest {np.max(np.abs(pos)):.1f}); "
              f"per scan against the white sigma: {white.size} estimates, std z "
              f"{np.std(white, ddof=1):.2f}, {int(np.sum(np.abs(white) > 4))} with |z| > 4.", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--merge", action="store_true", help="Only the tables from stored parts.")
    a = ap.parse_args(argv)
    logging.disable(logging.WARNING)
    from _common import seeded_parts

    if not a.merge:
        from hartrao_jax._config import enable_compilation_cache

        enable_compilation_cache()
    parts = seeded_parts(
        PARTS, [] if a.merge else a.cases.split(","), range(a.first, a.first + a.seeds), run_one,
        lambda case, seed, r: f"{case} seed {seed}: {r['findings']} {r['seconds']:.0f} s")
    text = summarize(parts)
    (OUT / "diagnose_sigmas.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
