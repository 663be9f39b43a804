"""Inject known bumps into the real GBT recordings and recover them blind (``real_inject``).

The real counterpart of ``prove``: Gaussian bumps ``a exp(-d^2 / 2 w^2)`` (the catalog's
``local_deformation``) of known centre, amplitude and width are added to the real points of
scan 10 and of the bump-1 strip, displaced along the fitted surface normal (so the real noise,
panel structure and scatter stay), and the local-deformation search of ``diagnose`` is run
without knowing where.

Two levels, both reported:

* **search** (every placement): the start fit of the unmodified recording gives each point's
  residual along the normal; the injected bump adds ``a g`` to it (first order: one local bump
  hardly moves a pose and focal length fitted to 3e4-5e4 points), and
  :func:`hartrao_jax.diagnose._locate.search` runs blind on the sum. Detected = the search's best
  candidate is significant (p < 1e-3 against the reflector's own peaks) and lies within
  ``max(w, 0.5 m)`` of the true centre. Placements without a bump give the false-alarm rate.
* **end to end** (a subset): the displaced points are written as an XYZ export, imported with
  ``hartrao-jax import --telescope gbt`` and ``diagnose`` runs blind; the accepted
  ``local_deformation`` is compared with the truth (position error, amplitude and width within
  their sigmas).

``python benchmarks/real_inject.py [--quick] [--placements N] [--end-to-end K]``; results in
``benchmarks/results/real_inject.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "real" / "gbt-lassi"
OUT = ROOT / "benchmarks" / "results"
FILES = {"scan10": "scan10_random_sample.csv", "bump1": "bump1_high_sample.csv"}


def _normals_and_residuals(camp):
    """Start fit of the recording: per point the residual along the normal (m), its aperture
    position (m), the unit normal towards the focus in the file frame, used mask."""
    from hartrao_jax.diagnose._diagnose import _start_scans
    from hartrao_jax.diagnose._state import DiagnoseConfig, _Context, _evaluate, _Spec
    from hartrao_jax.geometry._geometry import rot_z, scanner_to_telescope

    ctx = _Context(camp, DiagnoseConfig())
    sc = _start_scans(ctx, ("tx", "ty", "tz", "rx", "ry", "f"), None, None)[0]
    _evaluate(ctx, sc, _Spec(start=("tx", "ty", "tz", "rx", "ry", "f")))
    f = sc.value("f")
    X = sc.X_tel
    n_tel = np.column_stack([-X[:, 0] / (2 * f), -X[:, 1] / (2 * f), np.ones(len(X))])
    n_tel /= np.linalg.norm(n_tel, axis=1)[:, None]
    R = np.asarray(scanner_to_telescope(sc.value("rx"), sc.value("ry")))
    K = np.asarray(rot_z(sc.kappa))
    n_file = n_tel @ K @ R  # (K R)^T n for row vectors
    return sc, n_file


def _placements(xy, used, rng, k, w):
    """Centres inside the data: a random used point whose disc of radius w is well covered."""
    from scipy.spatial import cKDTree

    pts = xy[used]
    tree = cKDTree(pts)
    dens = len(pts) / max(1e-6, float(np.ptp(pts[:, 0]) * np.ptp(pts[:, 1])))
    out = []
    for _ in range(200 * k):
        c = pts[rng.integers(len(pts))]
        n = len(tree.query_ball_point(c, w))
        n2 = len(tree.query_ball_point(c, 0.5 * w))
        if n >= 8 and n2 >= 0.25 * n * 0.8 and n >= 0.3 * dens * math.pi * w * w:
            out.append(c)
        if len(out) == k:
            break
    return out


def run(quick: bool, placements: int, end_to_end: int, seed: int = 0) -> dict:
    from hartrao_jax.campaign._import import import_file
    from hartrao_jax.diagnose._locate import search

    amps = [1e-3, 2e-3, -2e-3] if quick else [1e-4, 2e-4, 5e-4, -5e-4, 1e-3, -1e-3, 2e-3, -2e-3]
    widths = [1.0] if quick else [0.3, 0.5, 1.0, 2.0, 3.0]
    rng = np.random.default_rng(seed)
    tmp = Path(tempfile.mkdtemp(prefix="real_inject_"))
    rows, nulls, e2e = [], [], []
    for rec, fname in FILES.items():
        camp = import_file(REAL / fname, "xyz", tmp / rec, telescope="gbt")
        t0 = time.time()
        sc, n_file = _normals_and_residuals(camp)
        u = sc.used
        xy = sc.X_tel[:, :2]
        r0 = sc.mismatch_m
        base = search(xy[u], r0[u])
        c = base.candidate
        nulls.append({"recording": rec, "kind": "unmodified", "significant": bool(c and c.significant),
                      "p_value": c.p_value if c else None,
                      "largest": c.to_json() if c else None})
        print(f"{rec}: start fit + search {time.time() - t0:.1f} s; unmodified: "
              f"p={c.p_value if c else None}", flush=True)
        for w in widths:
            centres = _placements(xy, u, rng, placements, w)
            for k, cxy in enumerate(centres):
                g = np.exp(-np.sum((xy - cxy) ** 2, 1) / (2 * w * w))
                # a placement without a bump: the same search with the field unchanged but a
                # random rotation/shift of nothing is the unmodified run; here a sign-flipped
                # copy of the field (same roughness, no injected structure) is the extra null
                if k < max(1, placements // 4) and w == widths[0]:
                    s0 = search(xy[u], -r0[u])
                    nulls.append({"recording": rec, "kind": "sign-flipped field",
                                  "significant": bool(s0.candidate and s0.candidate.significant),
                                  "p_value": s0.candidate.p_value if s0.candidate else None})
                for a in amps:
                    s = search(xy[u], r0[u] + a * g[u])
                    cc = s.candidate
                    d = math.hypot(cc.x_m - cxy[0], cc.y_m - cxy[1]) if cc else float("inf")
                    det = bool(cc and cc.significant and d < max(w, 0.5))
                    rows.append({"recording": rec, "amplitude_m": a, "width_m": w,
                                 "x_m": float(cxy[0]), "y_m": float(cxy[1]), "detected": det,
                                 "position_error_m": d if det else None,
                                 "amplitude_found_m": cc.amplitude_m if det else None,
                                 "width_found_m": cc.width_m if det else None,
                                 "p_value": cc.p_value if cc else None})
            print(f"{rec} w={w}: {len(centres)} placements done ({time.time() - t0:.0f} s)",
                  flush=True)
        # end to end: displaced points written as an XYZ export, imported and diagnosed blind
        if end_to_end:
            xyz = np.loadtxt(REAL / fname, delimiter=",", skiprows=_header_rows(REAL / fname))
            for j in range(end_to_end):
                a, w = (2e-3, 1.0) if j % 2 == 0 else (-2e-3, 1.0)
                cxy = _placements(xy, u, rng, 1, w)[0]
                e2e.append(_end_to_end(rec, xyz, sc, n_file, cxy, a, w, tmp / f"{rec}_e2e{j}"))
                print(f"{rec} end-to-end {j}: {e2e[-1]}", flush=True)
    return {"rows": rows, "nulls": nulls, "end_to_end": e2e, "amplitudes_m": amps,
            "widths_m": widths, "placements": placements, "quick": quick}


def _header_rows(path) -> int:
    with open(path) as fh:
        first = fh.readline()
    try:
        [float(v) for v in first.replace(",", " ").split()]
        return 0
    except ValueError:
        return 1


def _end_to_end(rec, xyz, sc, n_file, cxy, a, w, out):
    from hartrao_jax.campaign._import import import_file
    from hartrao_jax.diagnose import DiagnoseConfig, diagnose

    # the imported rows keep the file's order: row -> point (only imported rows are moved)
    rows = np.asarray(sc.data.row)
    g = np.exp(-np.sum((sc.X_tel[:, :2] - cxy) ** 2, 1) / (2 * w * w))
    moved = xyz[:, :3].copy()
    moved[rows] += (a * g)[:, None] * n_file
    out.mkdir(parents=True, exist_ok=True)
    f = out / "injected.csv"
    np.savetxt(f, moved, delimiter=",", fmt="%.6f", header="x,y,z", comments="")
    camp = import_file(f, "xyz", out / "camp", telescope="gbt")
    t0 = time.time()
    d = diagnose(camp, "extended", config=DiagnoseConfig(effects=("local_deformation",)))
    doc = d.to_json()
    hit = [x for x in doc["findings"] if x["effect"] == "local_deformation"]
    res = {"recording": rec, "amplitude_m": a, "width_m": w, "x_m": float(cxy[0]),
           "y_m": float(cxy[1]), "time_s": time.time() - t0, "found": bool(hit)}
    if hit:
        e, wh = hit[0]["estimate"], hit[0]["where"]
        res.update(position_error_m=math.hypot(wh["x_m"] - cxy[0], wh["y_m"] - cxy[1]),
                   amplitude=e["amplitude_m"], width=e["width_m"], x=e["x_m"], y=e["y_m"],
                   amplitude_within_2sigma=abs(e["amplitude_m"]["value"] - a)
                   <= 2 * e["amplitude_m"]["sigma"],
                   width_within_2sigma=abs(e["width_m"]["value"] - w) <= 2 * e["width_m"]["sigma"],
                   centre_within_2sigma=math.hypot((e["x_m"]["value"] - cxy[0]) / e["x_m"]["sigma"],
                                                   (e["y_m"]["value"] - cxy[1]) / e["y_m"]["sigma"])
                   <= 2.5)
    else:
        res["statement"] = (doc["local_deformation_search"] or [{}])[0].get("statement")
    return res


def summarize(res: dict) -> str:
    rows = res["rows"]
    lines = ["# Real-data injection: local deformations in the GBT recordings", "",
             f"Placements per (recording, width): {res['placements']}; quick mode: "
             f"{res['quick']}. Detection by the blind search on the start-fit residuals plus "
             "the injected bump (see the script's docstring); a detection must be significant "
             "(p < 1e-3 against the reflector's own largest peaks) and within max(w, 0.5 m) "
             "of the true centre.", ""]
    for rec in FILES:
        lines += [f"## {rec}", "", "| width [m] | amplitude [mm] | detected | median position "
                  "error [m] | median |a_found / a| |", "|---|---|---|---|---|"]
        mins = {}
        for w in res["widths_m"]:
            for a in res["amplitudes_m"]:
                sel = [r for r in rows if r["recording"] == rec and r["width_m"] == w
                       and r["amplitude_m"] == a]
                if not sel:
                    continue
                det = [r for r in sel if r["detected"]]
                rate = len(det) / len(sel)
                pe = np.median([r["position_error_m"] for r in det]) if det else float("nan")
                ar = np.median([r["amplitude_found_m"] / a for r in det]) if det else float("nan")
                lines.append(f"| {w:g} | {1e3 * a:+.1f} | {len(det)}/{len(sel)} ({100 * rate:.0f} %)"
                             f" | {pe:.2f} | {ar:.2f} |")
                if rate >= 0.8 and a > 0:
                    mins[w] = min(mins.get(w, 9.0), a)
        lines += ["", "Smallest positive amplitude detected in at least 80 % of the placements: "
                  + (", ".join(f"w = {w:g} m: {1e3 * mins[w]:.1f} mm" if w in mins else
                               f"w = {w:g} m: none up to {1e3 * max(res['amplitudes_m']):.1f} mm"
                               for w in res["widths_m"])), ""]
    nl = res["nulls"]
    lines += ["## False alarms", "",
              "| recording | null | significant | p-value of the largest structure |",
              "|---|---|---|---|"]
    for r in nl:
        lines.append(f"| {r['recording']} | {r['kind']} | {r['significant']} | "
                     f"{r['p_value'] if r['p_value'] is None else round(r['p_value'], 4)} |")
    if res["end_to_end"]:
        lines += ["", "## End to end (import + diagnose blind)", "",
                  "| recording | a [mm] | w [m] | found | position error [m] | amplitude [mm] "
                  "| width [m] | a within 2 sigma | w within 2 sigma | time [s] |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in res["end_to_end"]:
            if r["found"]:
                lines.append(
                    f"| {r['recording']} | {1e3 * r['amplitude_m']:+.1f} | {r['width_m']:g} | yes | "
                    f"{r['position_error_m']:.2f} | {1e3 * r['amplitude']['value']:+.2f} ± "
                    f"{1e3 * r['amplitude']['sigma']:.2f} | {r['width']['value']:.2f} ± "
                    f"{r['width']['sigma']:.2f} | {r['amplitude_within_2sigma']} | "
                    f"{r['width_within_2sigma']} | {r['time_s']:.0f} |")
            else:
                lines.append(f"| {r['recording']} | {1e3 * r['amplitude_m']:+.1f} | "
                             f"{r['width_m']:g} | no | | | | | | {r['time_s']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--placements", type=int, default=None)
    ap.add_argument("--end-to-end", type=int, default=None)
    ap.add_argument("--out", default=str(OUT))
    a = ap.parse_args(argv)
    placements = a.placements or (6 if a.quick else 20)
    e2e = a.end_to_end if a.end_to_end is not None else (1 if a.quick else 4)
    t0 = time.time()
    res = run(a.quick, placements, e2e)
    res["elapsed_s"] = time.time() - t0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    name = "real_inject_quick" if a.quick else "real_inject"
    (out / f"{name}.json").write_text(json.dumps(res, indent=1, default=float))
    (out / f"{name}.md").write_text(summarize(res))
    print(summarize(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
