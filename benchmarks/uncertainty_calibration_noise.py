"""Where the calibration parameters' two-face errors come from: the noise, or the surface?

x4, x6 and x7 flip sign between the faces; the reflector's surface (panels, smooth modes) is
common to both faces, so in the two-face adjustment it should not move them. This checks that
by measurement, for the cases and seeds of ``uncertainty_calibration.py``:

* **noise-only refit**: the same simulated campaign (same seed, same geometry, same noise
  draws: the simulator's noise generator does not depend on the panels) *without* the panel
  pattern, adjusted with white noise only. If the surface moved x4/x6/x7, their z would differ
  from the stored two-face z of the same seed; the noise-only refits are cheap (no random
  effect), so they also give many more seeds of the noise's own z distribution;
* **influence** (``--influence SEED``): the linearised error of the estimates at the truth,
  ``dx = -N^-1 sum_i a_i w_i / m_i`` from each simulated reflector point's misclosure ``w_i``
  (its noise), split by face and by observation (range, phi, theta), with the effective number of
  points behind it: a few high-leverage points would make the z distribution heavy-tailed, a
  sum over 1e5 points makes it Gaussian with exactly the adjustment's variance.

    python benchmarks/uncertainty_calibration_noise.py --cases panels-0.1mm --seeds 100
    python benchmarks/uncertainty_calibration_noise.py --cases dense --seeds 20 --influence 4
    python benchmarks/uncertainty_calibration_noise.py --merge

Parts are stored in ``results/uncertainty/noise/`` (one per case and seed, plus influence
parts); ``--merge`` writes ``results/uncertainty_noise.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import uncertainty_calibration as uc

NOISE = uc.OUT / "uncertainty" / "noise"
CAL = ("x4", "x6", "x7")


def _simulate(case: str, seed: int, tmp: Path, panels: bool = False):
    from hartrao_jax.campaign._campaign import load_campaign
    from hartrao_jax.simulate._simulate import simulate_campaign

    positions, effects, step = uc.CASES[case]
    eff = dict(effects) if panels else dict(effects, panel_offset=0.0)
    simulate_campaign(tmp / "c", preset="demo", effects=eff, seed=seed + uc.SEED_OFFSET[case],
                      positions=positions, step_rad=step)
    camp = load_campaign(tmp / "c")
    truth = json.loads((tmp / "c" / "truth.json").read_text())
    return camp, {s["id"]: {**s, **s.get("model_parameters", {})} for s in truth["scans"]}


def noise_only(case: str, seed: int) -> dict:
    """White-noise two-face refit of the campaign of (case, seed) without its panel pattern."""
    from hartrao_jax.fit._fit import fit_campaign

    tmp = Path(tempfile.mkdtemp(prefix=f"znoise-{case}-{seed}-"))
    try:
        t0 = time.time()
        camp, ts = _simulate(case, seed, tmp)
        two = fit_campaign(camp, "extended", progress=False, surface=False)
        rows = []
        for p in two.position_fits:
            tr = ts[p.scans[0].meta.id]
            corr = p.cov / np.outer(p.sigma, p.sigma)
            for i, (n, v, sg) in enumerate(zip(p.names, p.x, p.sigma)):
                rows.append({"unit": p.position, "param": n, "sigma": float(sg),
                             "z": uc._z(n, float(v), tr.get(n, 0.0), float(sg)),
                             "corr": [float(q) for q in corr[i]]})
        return {"case": case, "seed": seed, "rows": rows, "seconds": time.time() - t0}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def influence(case: str, seed: int) -> dict:
    """Linearised error at the truth from each reflector point's noise (first position)."""
    import jax
    import jax.numpy as jnp
    import pyarrow.parquet as pq

    from hartrao_jax.campaign._campaign import read_scan
    from hartrao_jax.fit._fit import parse_names, scan_arrays, sigma_vector
    from hartrao_jax.model._model import make_model
    from hartrao_jax.simulate._simulate import CLASSES

    tmp = Path(tempfile.mkdtemp(prefix=f"zinfl-{case}-{seed}-"))
    try:
        camp, ts = _simulate(case, seed, tmp)
        pos = camp.scans[0].position
        metas = [m for m in camp.scans if m.position == pos]
        names = parse_names("extended")
        mdl = make_model(names, {}, aperture_radius_m=camp.telescope.diameter_m / 2,
                         kappa_rad=0.0, check_separable=False)
        tr = ts[metas[0].id]
        xt = jnp.asarray([tr.get(n, 0.0) for n in names])
        L, C, T, face = [], [], [], []
        for k, m in enumerate(metas):
            lab = pq.read_table(tmp / "c" / "truth" / f"{m.id}.parquet")
            sel = lab.column("cls").to_numpy() == CLASSES["reflector"]
            l, c = scan_arrays(read_scan(camp, m))
            L.append(l[sel])
            C.append(c[sel])
            T.append(np.column_stack([lab.column(q).to_numpy() for q in (
                "range_true_m", "phi_true_rad", "theta_true_rad")])[sel])
            face.append(np.full(int(sel.sum()), k))
        l, c, lt, face = (np.concatenate(a) for a in (L, C, T, face))

        def one(li, ci):
            return (mdl(li, xt, ci), jax.grad(lambda x: mdl(li, x, ci))(xt),
                    jax.grad(lambda q: mdl(q, xt, ci))(li))

        F, A, B = (np.asarray(a) for a in jax.jit(jax.vmap(one))(jnp.asarray(l), jnp.asarray(c)))
        m = np.sum(B * B * np.asarray(sigma_vector(camp)) ** 2, 1)
        Q = np.linalg.inv((A / m[:, None]).T @ A)
        G = (A @ Q) / m[:, None]  # dx = -sum_i G_i w_i
        s = np.sqrt(np.diag(Q))
        e = l - lt
        e[:, 1] = (e[:, 1] + np.pi) % (2 * np.pi) - np.pi
        out = {"case": case, "seed": seed, "n_points": int(len(l)),
               "z_linear": dict(zip(names, map(float, -(G * F[:, None]).sum(0) / s))),
               "params": {}}
        for n in CAL:
            j = names.index(n)
            ci = -G[:, j] * F / s[j]  # each point's contribution to z
            vi = G[:, j] ** 2 * m / s[j] ** 2  # its share of z's variance (sums to 1)
            top = np.argsort(-vi)[:1000]
            out["params"][n] = {
                "z": float(ci.sum()), "n_effective": float(1.0 / np.sum(vi**2)),
                "top1000_variance_share": float(vi[top].sum()),
                "top1000_z": float(ci[top].sum()),
                "face_z": [float(ci[face == k].sum()) for k in range(len(metas))],
                "via": {q: float((-G[:, j] * B[:, i] * e[:, i]).sum() / s[j])
                        for i, q in enumerate(("range", "phi", "theta"))}}
        return out
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _std(z) -> float:
    z = np.asarray(z, float)
    return float(np.std(z, ddof=1)) if z.size > 1 else float("nan")


def _p_outside(n: int, lo: float = 0.8, hi: float = 1.25) -> float:
    """Chance that the sample std of n standard-normal z falls outside [lo, hi]."""
    from scipy.stats import chi2

    d = n - 1
    return float(chi2.cdf(d * lo**2, d) + chi2.sf(d * hi**2, d))


def summarize(parts: list[dict], infl: list[dict]) -> dict:
    out: dict = {"cases": {}, "influence": infl}
    for case in dict.fromkeys(p["case"] for p in parts):
        cp = sorted((p for p in parts if p["case"] == case), key=lambda p: p["seed"])
        z = {n: np.array([r["z"] for p in cp for r in p["rows"] if r["param"] == n])
             for n in uc.PARAMS}
        e: dict = {"seeds": len(cp), "noise_only": {
            n: {"std": _std(v), "mean": float(np.mean(v)), "max_abs": float(np.max(np.abs(v)))}
            for n, v in z.items() if v.size}}
        blocks = {}
        for b0 in range(0, max(p["seed"] for p in cp) + 1, 20):
            bz = {n: [r["z"] for p in cp if b0 <= p["seed"] < b0 + 20 for r in p["rows"]
                      if r["param"] == n] for n in CAL}
            if len(bz["x4"]) == 20:
                blocks[f"{b0}-{b0 + 19}"] = {n: _std(v) for n, v in bz.items()}
        e["blocks_of_20"] = blocks
        # the same seeds' stored two-face z (panels and random effect) against the noise-only z
        # (f for contrast: the surface does move it)
        diffs, two = {n: [] for n in CAL + ("f",)}, {n: [] for n in CAL + ("f",)}
        for p in cp:
            f = uc.PARTS / f"{case}-{p['seed']}.json"
            if not f.exists():
                continue
            st = {(r["unit"], r["param"]): r["z"] for r in json.loads(f.read_text())["rows"]
                  if r["mode"] == "two-face"}
            for r in p["rows"]:
                if r["param"] in diffs and (r["unit"], r["param"]) in st:
                    diffs[r["param"]].append(st[(r["unit"], r["param"])] - r["z"])
                    two[r["param"]].append(st[(r["unit"], r["param"])])
        if diffs["x4"]:
            e["two_face_vs_noise_only"] = {
                n: {"n": len(diffs[n]), "max_abs_diff": float(np.max(np.abs(diffs[n]))),
                    "rms_diff": float(np.sqrt(np.mean(np.square(diffs[n])))),
                    "std_two_face": _std(two[n])} for n in diffs if diffs[n]}
        out["cases"][case] = e
    out["p_std_outside_0.8_1.25"] = {n: _p_outside(n) for n in (20, 40, 60, 100)}
    return out


def markdown(s: dict) -> str:
    lines = ["# Two-face calibration parameters: noise or surface?", "",
             "Noise-only refit: the campaign of the same case and seed (same geometry, same noise "
             "draws) without the panel pattern, adjusted with white noise "
             "(`benchmarks/uncertainty_calibration_noise.py`). Two-face: the stored rows of "
             "`uncertainty_calibration.py` (panels, surface random effect).", ""]
    for case, e in s["cases"].items():
        lines += [f"## {case} ({e['seeds']} seeds)", "",
                  "| parameter | std z noise-only | mean z | max abs z |", "|---|---|---|---|"]
        for n, v in e["noise_only"].items():
            lines.append(f"| {n} | {v['std']:.2f} | {v['mean']:+.2f} | {v['max_abs']:.1f} |")
        if "two_face_vs_noise_only" in e:
            lines += ["", "Same seeds, two-face z minus noise-only z: " + "; ".join(
                f"{n} rms {v['rms_diff']:.2f}, max |diff| {v['max_abs_diff']:.2f} over {v['n']} "
                f"(two-face std z "
                f"{v['std_two_face']:.2f})" for n, v in e["two_face_vs_noise_only"].items())]
        if e["blocks_of_20"]:
            lines += ["", "Noise-only std z of x4/x6/x7 per block of 20 seeds: " + "; ".join(
                f"seeds {b}: {v['x4']:.2f}/{v['x6']:.2f}/{v['x7']:.2f}"
                for b, v in e["blocks_of_20"].items())]
        lines.append("")
    p = s["p_std_outside_0.8_1.25"]
    lines += ["Chance that the sample std of n exactly standard-normal z leaves 0.8-1.25: " +
              ", ".join(f"n = {n}: {v:.3f}" for n, v in p.items()) + ".", ""]
    for r in s["influence"]:
        lines += [f"## Influence, {r['case']} seed {r['seed']} ({r['n_points']} reflector "
                  "points)", "", "Linearised error at the truth from the simulated noise alone: "
                  + ", ".join(f"{n} {v:+.2f}" for n, v in r["z_linear"].items()) + ".", "",
                  "| parameter | z | effective points | top 1000 points: variance share | "
                  "their z | z per face | z via range / phi / theta noise |",
                  "|---|---|---|---|---|---|---|"]
        for n, v in r["params"].items():
            lines.append(
                f"| {n} | {v['z']:+.2f} | {v['n_effective']:.0f} | "
                f"{v['top1000_variance_share']:.3f} | {v['top1000_z']:+.2f} | "
                + " / ".join(f"{q:+.2f}" for q in v["face_z"]) + " | "
                + " / ".join(f"{v['via'][q]:+.2f}" for q in ("range", "phi", "theta")) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--cases", default="panels-0.1mm")
    ap.add_argument("--influence", type=int, action="append", default=[],
                    help="also the linearised influence analysis of this seed (first case)")
    ap.add_argument("--merge", action="store_true", help="only merge the stored parts")
    args = ap.parse_args(argv)
    from _common import seeded_parts

    import hartrao_jax  # noqa: F401  (float64)

    cases = [] if args.merge else args.cases.split(",")
    bad = [c for c in cases if c not in uc.CASES]
    if bad:
        print(f"error: --cases: unknown case {bad[0]!r}", file=sys.stderr)
        return 2
    seeded_parts(NOISE, cases, range(args.first_seed, args.first_seed + args.seeds), noise_only,
                 lambda case, seed, r: f"{case} seed {seed}: {r['seconds']:.0f} s")
    parts = seeded_parts(NOISE, [f"influence-{cases[0]}"] if cases else [], args.influence,
                         lambda _, seed: influence(cases[0], seed),
                         lambda case, seed, r: f"{case}-{seed}: linearised influence")
    infl = [p for p in parts if "z_linear" in p]
    s = summarize([p for p in parts if "rows" in p], infl)
    (uc.OUT / "uncertainty_noise.json").write_text(json.dumps(s, indent=1))
    (uc.OUT / "uncertainty_noise.md").write_text(markdown(s))
    print(markdown(s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
