"""Inject known bumps into the real GBT recordings and recover them blind (``real_inject``).

The real counterpart of ``prove``: Gaussian bumps ``a exp(-d^2 / 2 w^2)`` (the catalog's
``local_deformation``) of known centre, amplitude and width are added to the real points of
scan 10 and of the bump-1 strip, displaced along the fitted surface normal (so the real noise,
panel structure and scatter stay), and the local-deformation search of ``diagnose`` is run
without knowing where.

Two levels, both reported:

* **search** (every placement). ``diagnose`` searches for local deformations first, on the
  start fit's residuals along the normal (:func:`hartrao_jax.diagnose._local.search_points`,
  :func:`~hartrao_jax.diagnose._locate.search` with the diagnosis' own level and minimum
  amplitude), before any other effect, panel offset or random effect is modelled. That step is
  run here exactly, on the unmodified recording's residuals plus the injected ``a g`` (first
  order: one local bump hardly moves a pose and focal length fitted to 3e4-5e4 points; the
  end-to-end runs check it). The robust start fit's rejection is applied to the injected
  residuals as the fit applies it (a point is dropped when its residual exceeds ``robust_k``
  a-posteriori sigmas of that point: ``k sigma0 sqrt(m_i) / s_i`` in metres), and the search
  then takes back the rejected points that agree with their neighbours
  (:func:`~hartrao_jax.diagnose._locate.coherent`: ``|r_i - median of the neighbours| <=
  limit_i``), as ``diagnose`` does: the core of a bump deeper than the limit comes back,
  isolated outliers stay out. ``--no-readmit`` runs the search on the kept points only (the
  search before that rule). Like ``diagnose``, the search runs up to ``MAX_BUMPS`` rounds,
  each after the previous significant candidate's neighbourhood is excluded (here on the same
  maps; ``diagnose`` models the candidate and recomputes them). Detected = a significant
  candidate (p below the diagnosis' level against the reflector's own peaks) within
  ``max(w, 0.5 m)`` of the true centre; a significant candidate on one of the structures the
  unmodified recording itself shows significant is counted as *own*, one anywhere else as a
  false alarm.
* **end to end** (a subset): the displaced points are written as an XYZ export, imported with
  the GBT preset and ``diagnose`` runs blind; the accepted ``local_deformation`` nearest the
  truth is compared with it (position error, amplitude and width within their sigmas).

False alarms without any bump: the unmodified recordings, and parts of them (the points within
a random centre's median distance: half of the recording, a different set of the reflector's
own structures each time).

Per placement the rows also keep the search's ``|t|`` at the true centre and width and the
critical ``|t|`` of its first round's null (what the bump would need), and, for a detection,
the catalog's ``local_deformation`` refitted to the searched residuals near the candidate
(:func:`local_refit`, sigmas times the roughness factor as the diagnosis reports them).

What limits the search on scan 10 (measured, see the results): scan 10's own local
structures. Seen with their cores (the robust start fit rejects every residual above about
3 mm, and before the re-admission the search saw only their rims, ``|t|`` 11.75, 8.8), three
of them stand out from the rest of the surface: a -5.9 mm dent 1.1 m wide at x 29.1, y 0.2 m,
a +4.5 mm bump 0.9 m wide at x 23.3, y 12.7 m and an 18 mm deep dent 0.6 m wide at x 33.1,
y -8.0 m (its rim, x 34.4, y -8.4 m, answers as well). They are real local structures of the
recording (smooth over 1-2 m, 40-50 points each); whether they are the reflector's surface
(a panel corner, an actuator) or something in front of it, one scan cannot say. They take the
first rounds of the search, and with them in the null the critical ``|t|`` of the first round
is about 17 (12.7 when their cores were hidden). On the bump-1 strip (1.5 m wide) the search
skips widths of 0.75 m and more (fewer than 12 independent placements); and its end-to-end
runs refit the strip's pose, which a one-face strip determines poorly (an injected bump can
move the whole strip in the aperture plane, so the position error there says more about the
pose than about the search).

``python benchmarks/real_inject.py [--quick] [--all-amplitudes] [--placements N] [--end-to-end K]
[--regions N] [--amplitudes-mm A,...] [--widths-m W,...] [--recordings scan10,bump1]
[--no-readmit] [--merge A.json,B.json]``; the data are
found through :func:`hartrao_jax._config.real_data_dir` (``$HARTRAO_REAL_DATA``); results in
``benchmarks/results/real_inject{,_quick}{,_kept}.{json,md}``.
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
from scipy.spatial import cKDTree

from hartrao_jax._config import enable_x64, real_data_dir, real_data_missing
from hartrao_jax.campaign._import import import_file
from hartrao_jax.diagnose import DiagnoseConfig, diagnose
from hartrao_jax.diagnose._local import ALPHA_LOCAL, MAX_BUMPS, search_points
from hartrao_jax.diagnose._locate import coherent, judge, width_maps
from hartrao_jax.diagnose._start import _start_scans
from hartrao_jax.diagnose._state import _Context, _evaluate, _Spec
from hartrao_jax.geometry._geometry import rot_z, scanner_to_telescope
from hartrao_jax.physics._catalog import local_deformation

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
FILES = {"scan10": "scan10_random_sample.csv", "bump1": "bump1_high_sample.csv"}
START = ("tx", "ty", "tz", "rx", "ry", "f")
AMPLITUDES = (5e-4, -5e-4, 1e-3, -1e-3, 2e-3, -2e-3)  # 0.1 and 0.2 mm: see ALL_AMPLITUDES
ALL_AMPLITUDES = (1e-4, -1e-4, 2e-4, -2e-4) + AMPLITUDES  # --all-amplitudes
EXTENSION = (3e-3, -3e-3, 4e-3, 5e-3)  # beyond the issue's range: where scan 10 detects, and
# where the robust start fit starts to reject the bump's core (its limit is about 3 mm)
WIDTHS = (0.3, 1.0, 3.0)
E2E = ((5e-3, 1.0), (3e-3, 1.0), (-3e-3, 1.0), (2e-3, 1.0), (2e-3, 3.0))


def _start_fit(camp):
    """The diagnosis' start fit of a one-scan recording: the scan, the unit normal towards the
    focus of every point in the file frame, and every point's rejection threshold (m)."""
    ctx = _Context(camp, DiagnoseConfig())
    sc = _start_scans(ctx, START, None, None)[0]
    _evaluate(ctx, sc, _Spec(start=START))
    f = sc.value("f")
    X = sc.X_tel
    n_tel = np.column_stack([-X[:, 0] / (2 * f), -X[:, 1] / (2 * f), np.ones(len(X))])
    n_tel /= np.linalg.norm(n_tel, axis=1)[:, None]
    R = np.asarray(scanner_to_telescope(sc.value("rx"), sc.value("ry")))
    K = np.asarray(rot_z(sc.kappa))
    n_file = n_tel @ K @ R  # (K R)^T n for row vectors
    k = DiagnoseConfig().robust_k or math.inf
    limit = k * sc.sigma0 * np.sqrt(np.maximum(sc.m, 0.0)) / sc.s_rho
    return sc, n_file, limit


def _normals_and_residuals(camp):
    """(scan, normals in the file frame) of the start fit (used by the real-data tests)."""
    sc, n_file, _ = _start_fit(camp)
    return sc, n_file


def bump_shape(xy, cxy, w) -> np.ndarray:
    """The catalog's ``local_deformation`` of unit amplitude centred at ``cxy`` (width ``w``) at
    the aperture positions ``xy``: what is injected, along the normal."""
    return np.asarray(local_deformation(xy[:, 0], xy[:, 1], float(cxy[0]), float(cxy[1]), 1.0,
                                        float(w)))


def _placements(xy, rng, k, w):
    """``k`` centres inside the data: random kept points whose disc of radius ``w`` holds at
    least 30 % of the points the recording's median density puts there."""
    tree = cKDTree(xy)
    dens = _median_density(xy, tree)
    out = []
    for _ in range(400 * k):
        c = xy[rng.integers(len(xy))]
        if len(tree.query_ball_point(c, w)) >= max(8, 0.3 * dens * math.pi * w * w):
            out.append(c)
        if len(out) == k:
            break
    return out


def _median_density(xy, tree) -> float:
    """Median number of points per m^2 in discs of 1 m around 500 points."""
    idx = np.linspace(0, len(xy) - 1, min(500, len(xy))).astype(int)
    return float(np.median([len(tree.query_ball_point(xy[i], 1.0)) for i in idx])) / math.pi


class Recording:
    """One real recording after the start fit: what the diagnosis' local search sees."""

    def __init__(self, name, camp, readmit: bool = True):
        t0 = time.time()
        self.name = name
        self.sc, self.n_file, self.limit = _start_fit(camp)
        self.fit_s = time.time() - t0
        sc = self.sc
        self.xy_all = sc.X_tel[:, :2]
        self.r0 = sc.mismatch_m
        self.used = sc.used.copy()
        self.window = sc.window & ~sc.cut
        self.readmit = readmit
        self.own: list[tuple[float, float, float]] = []  # significant on the unmodified data
        xy, r = search_points([sc], DiagnoseConfig().robust_k)
        sel, _, _, back = self.points()
        assert readmit is False or len(r) == int(sel.sum())
        self.min_amp = DiagnoseConfig().min_effect_m * 5

    def points(self, bump=None, region=None):
        """What the search sees with ``bump`` (per point, m) added: the mask of the points,
        the residuals (m), how many points the start fit's rejection drops beyond the
        unmodified fit, and the mask of the rejected points re-admitted as coherent."""
        r = self.r0 if bump is None else self.r0 + bump
        win = self.window if region is None else self.window & region
        kept = self.used & win
        if bump is not None:
            kept &= np.abs(r) <= self.limit
        back = np.zeros(len(r), bool)
        if self.readmit:
            back[win] = coherent(self.xy_all[win], r[win], kept[win], self.limit[win])
        return kept | back, r, int((self.used & win & ~kept).sum()), back

    def search(self, bump=None, region=None, rounds: int = MAX_BUMPS):
        """The diagnosis' search on the residuals plus ``bump``, optionally on a subset
        ``region`` of the points: up to ``rounds`` searches, each after the previous
        significant candidate's neighbourhood is excluded (as ``diagnose`` searches again once
        it has modelled one). Returns the searches, the time of the first, the points the
        rejection drops and the points re-admitted."""
        sel, r, dropped, back = self.points(bump, region)
        out, exclude = [], []
        t0 = time.time()
        maps = width_maps(self.xy_all[sel], r[sel])  # a later round: the same maps
        for _ in range(rounds):
            s = judge(*maps, alpha=ALPHA_LOCAL, min_amplitude_m=self.min_amp, exclude=exclude)
            out.append(s)
            c = s.candidate
            if c is None or not c.significant:
                break
            exclude.append((c.x_m, c.y_m, c.width_m))
        self.last = (self.xy_all[sel], r[sel])
        return out, time.time() - t0, dropped, int(back.sum())

    def is_own(self, c) -> bool:
        """Whether candidate ``c`` lies on a structure significant in the unmodified recording."""
        return any(math.hypot(c.x_m - x, c.y_m - y) < max(w, c.width_m, 0.5)
                   for x, y, w in self.own)


def significant(searches) -> list:
    """The significant candidates of a run of searches."""
    return [s.candidate for s in searches if s.candidate is not None and s.candidate.significant]


def critical_t(c, alpha: float = ALPHA_LOCAL) -> float | None:
    """The |t| a candidate needs for ``p < alpha`` against the tail of its search's null."""
    if c is None or not c.tail:
        return None
    p1 = -math.expm1(math.log1p(-alpha) / c.n_peaks)
    return c.tail["threshold"] + c.tail["scale"] * math.log(c.tail["fraction"] / p1)


def at_truth(s, cxy, w) -> dict:
    """The matched filter of width ``w`` at the true centre (None: width skipped or invalid)."""
    for m in s.maps:
        if abs(m.width_m - w) < 1e-9:
            ij = np.floor((np.asarray(cxy) - m.origin) / m.cell_m).astype(int)
            if np.all(ij >= 0) and np.all(ij < m.t.shape) and m.valid[ij[0], ij[1]]:
                return {"t": float(m.t[ij[0], ij[1]]), "z_white": float(m.z[ij[0], ij[1]]),
                        "amplitude_m": float(m.amplitude[ij[0], ij[1]]),
                        "roughness_factor": m.roughness}
    return {"t": None}


def local_refit(xy, r, c) -> dict | None:
    """The catalog's ``local_deformation`` (centre, amplitude, width) plus a constant fitted to
    the kept residuals within ``3 w`` of a candidate, as the diagnosis' refit does with the
    adjustment; sigmas from the Jacobian times the candidate's roughness factor."""
    from scipy.optimize import least_squares

    near = np.hypot(xy[:, 0] - c.x_m, xy[:, 1] - c.y_m) < 3 * c.width_m
    if near.sum() < 12:
        return None
    X, R = xy[near], r[near]

    def f(p):
        return np.asarray(local_deformation(X[:, 0], X[:, 1], p[0], p[1], p[2], p[3])) + p[4] - R

    p0 = np.array([c.x_m, c.y_m, float(np.clip(c.amplitude_m, -0.049, 0.049)), c.width_m, 0.0])
    try:
        sol = least_squares(f, p0, x_scale=np.array([c.width_m, c.width_m, 1e-3, c.width_m,
                                                     1e-3]),
                            bounds=([-np.inf, -np.inf, -0.05, 0.05, -0.05],
                                    [np.inf, np.inf, 0.05, 10.0, 0.05]))
        J = sol.jac
        s0 = math.sqrt(2 * sol.cost / max(1, len(R) - 5))
        cov = np.linalg.inv(J.T @ J) * s0 * s0
    except (np.linalg.LinAlgError, ValueError):
        return None
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0)) * c.roughness
    x, y, a, w = (float(v) for v in sol.x[:4])
    return {"x_m": x, "y_m": y, "amplitude_m": a, "width_m": abs(w), "sigma_x_m": float(sd[0]),
            "sigma_y_m": float(sd[1]), "sigma_amplitude_m": float(sd[2]),
            "sigma_width_m": float(sd[3]), "n_points": int(near.sum())}


def _cand_row(c) -> dict:
    if c is None:
        return {"significant": False, "p_value": None}
    return {"significant": bool(c.significant), "p_value": c.p_value, "t": c.t,
            "x_m": c.x_m, "y_m": c.y_m, "amplitude_m": c.amplitude_m, "width_m": c.width_m,
            "roughness_factor": c.roughness, "n_peaks": c.n_peaks, "critical_t": critical_t(c)}


def _nulls(rec: Recording, rng, n_regions: int) -> list[dict]:
    """The unmodified recording and ``n_regions`` halves of it around random centres. The
    unmodified recording's significant candidates become ``rec.own``: real structures of the
    recording, counted apart from false alarms in the other runs."""
    ss, dt, _, back = rec.search()
    sig = significant(ss)
    rec.own = [(c.x_m, c.y_m, c.width_m) for c in sig]
    out = [{"recording": rec.name, "kind": "unmodified", "time_s": dt, "readmitted": back,
            **_cand_row(ss[0].candidate), "skipped_widths_m": ss[0].skipped_widths,
            "significant_candidates": [_cand_row(c) for c in sig],
            "searches": [_cand_row(s.candidate) for s in ss]}]
    xy = rec.xy_all[rec.used]
    for _ in range(n_regions):
        c = xy[rng.integers(len(xy))]
        d = np.hypot(*(rec.xy_all - c).T)
        region = d <= np.median(d[rec.used])
        ss, dt, _, back = rec.search(region=region)
        sig = significant(ss)
        out.append({"recording": rec.name, "kind": "half around a random centre",
                    "centre_m": [float(c[0]), float(c[1])], "time_s": dt, "readmitted": back,
                    **_cand_row(ss[0].candidate),
                    "n_own": sum(rec.is_own(q) for q in sig),
                    "n_false": sum(not rec.is_own(q) for q in sig)})
    return out


def _inject(rec: Recording, amps, widths, placements, rng, log) -> list[dict]:
    rows = []
    xy = rec.xy_all[rec.used]
    for w in widths:
        t0 = time.time()
        for cxy in _placements(xy, rng, placements, w):
            g = bump_shape(rec.xy_all, cxy, w)
            for a in amps:
                ss, dt, dropped, back = rec.search(a * g)
                sig = significant(ss)
                dist = [math.hypot(c.x_m - cxy[0], c.y_m - cxy[1]) for c in sig]
                hit = [c for c, d in zip(sig, dist) if d < max(w, 0.5)]
                other = [c for c, d in zip(sig, dist) if d >= max(w, 0.5)]
                own = [c for c in other if rec.is_own(c)]
                c = hit[0] if hit else ss[0].candidate
                d = math.hypot(c.x_m - cxy[0], c.y_m - cxy[1]) if c else math.inf
                det = bool(hit)
                row = {"recording": rec.name, "amplitude_m": a, "width_m": w,
                       "x_m": float(cxy[0]), "y_m": float(cxy[1]), "detected": det,
                       "detected_first": bool(det and hit[0] is ss[0].candidate),
                       "false_alarm": len(other) > len(own), "own_structure": len(own),
                       "distance_m": d, "rejected_by_start_fit": dropped, "readmitted": back,
                       "time_s": dt, "found": _cand_row(c),
                       "significant_candidates": [
                           [c.x_m, c.y_m, c.width_m, c.amplitude_m, c.t, c.p_value]
                           for c in sig],
                       "critical_t": critical_t(ss[0].candidate),
                       "at_truth": at_truth(ss[0], cxy, w)}
                if det:
                    e = local_refit(*rec.last, c)
                    if e is not None:
                        row["refit"] = {
                            **e, "position_error_m": math.hypot(e["x_m"] - cxy[0],
                                                                e["y_m"] - cxy[1]),
                            "amplitude_within_2sigma":
                                abs(e["amplitude_m"] - a) <= 2 * e["sigma_amplitude_m"],
                            "width_within_2sigma":
                                abs(e["width_m"] - w) <= 2 * e["sigma_width_m"]}
                rows.append(row)
        log(f"{rec.name} w={w:g}: {placements} placements x {len(amps)} amplitudes "
            f"({time.time() - t0:.0f} s)")
    return rows


def _end_to_end(rec: Recording, xyz, cxy, a, w, out: Path) -> dict:
    """Displace the file's points along the normal, import as an XYZ export, diagnose blind."""
    sc = rec.sc
    rows = np.asarray(sc.data.row)  # imported row -> line of the file
    g = bump_shape(sc.X_tel[:, :2], cxy, w)
    moved = xyz[:, :3].copy()
    moved[rows] += (a * g)[:, None] * rec.n_file
    out.mkdir(parents=True, exist_ok=True)
    f = out / "injected.csv"
    np.savetxt(f, moved, delimiter=",", fmt="%.6f", header="x,y,z", comments="")
    camp = import_file(f, "xyz", out / "camp", telescope="gbt")
    t0 = time.time()
    doc = diagnose(camp, "extended",
                   config=DiagnoseConfig(effects=("local_deformation",))).to_json()
    found = [x for x in doc["findings"] if x["effect"] == "local_deformation"]
    dist = [math.hypot(x["where"]["x_m"] - cxy[0], x["where"]["y_m"] - cxy[1]) for x in found]
    hit = [x for d, x in sorted(zip(dist, found), key=lambda q: q[0]) if d < max(w, 0.5)]
    res = {"recording": rec.name, "amplitude_m": a, "width_m": w, "x_m": float(cxy[0]),
           "y_m": float(cxy[1]), "time_s": time.time() - t0, "timing_s": doc.get("timing_s"),
           "found": bool(hit), "n_local_findings": len(found)}
    if not hit:
        res["statement"] = (doc["local_deformation_search"] or [{}])[0].get("statement")
        return res
    e, wh = hit[0]["estimate"], hit[0]["where"]

    def within(name, truth, k=2.0):
        """|estimate - truth| <= k sigma; None when the parameter was held (no sigma)."""
        sd = e[name]["sigma"]
        return None if sd is None else bool(abs(e[name]["value"] - truth) <= k * sd)

    held = e["x_m"]["sigma"] is None or e["y_m"]["sigma"] is None
    res.update(position_error_m=math.hypot(wh["x_m"] - cxy[0], wh["y_m"] - cxy[1]),
               amplitude=e["amplitude_m"], width=e["width_m"], x=e["x_m"], y=e["y_m"],
               amplitude_within_2sigma=within("amplitude_m", a),
               width_within_2sigma=within("width_m", w),
               centre_within_2sigma=None if held else math.hypot(
                   (e["x_m"]["value"] - cxy[0]) / e["x_m"]["sigma"],
                   (e["y_m"]["value"] - cxy[1]) / e["y_m"]["sigma"]) <= 2.5)
    return res


def _header_rows(path) -> int:
    with open(path) as fh:
        first = fh.readline()
    try:
        [float(v) for v in first.replace(",", " ").split()]
        return 0
    except ValueError:
        return 1


def run(quick: bool, placements: int, end_to_end: int, regions: int, seed: int = 0,
        log=print, all_amplitudes: bool = False, readmit: bool = True, amplitudes=None,
        widths=None, recordings=None, checkpoint: Path | None = None) -> dict:
    real = real_data_dir() / "gbt-lassi"
    amps = tuple(amplitudes) if amplitudes else (
        (2e-3, -2e-3, 3e-3) if quick else
        (ALL_AMPLITUDES if all_amplitudes else AMPLITUDES) + EXTENSION)
    widths = tuple(widths) if widths else ((1.0,) if quick else WIDTHS)
    rng = np.random.default_rng(seed)
    tmp = Path(tempfile.mkdtemp(prefix="real_inject_"))
    rows, nulls, e2e, fits = [], [], [], {}
    for name, fname in FILES.items():
        if recordings and name not in recordings:
            continue
        camp = import_file(real / fname, "xyz", tmp / name, telescope="gbt")
        rec = Recording(name, camp, readmit=readmit)
        fits[name] = {"start_fit_s": rec.fit_s, "n_points": int(len(rec.r0)),
                      "n_kept": int(rec.used.sum()), "sigma0": rec.sc.sigma0}
        nulls += _nulls(rec, rng, regions)
        log(f"{name}: start fit {rec.fit_s:.1f} s; unmodified p={nulls[-regions - 1]['p_value']}")
        rows += _inject(rec, amps, widths, placements, rng, log)
        if checkpoint is not None:  # the injections survive a failure further on
            checkpoint.write_text(json.dumps(_rounded({"rows": rows, "nulls": nulls}),
                                             separators=(",", ":")))
        if end_to_end:
            xyz = np.loadtxt(real / fname, delimiter=",", skiprows=_header_rows(real / fname))
            for j, (a, w) in enumerate(E2E[:end_to_end]):
                cxy = _placements(rec.xy_all[rec.used], rng, 1, w)[0]
                try:
                    e2e.append(_end_to_end(rec, xyz, cxy, a, w, tmp / f"{name}_e2e{j}"))
                except Exception as exc:  # noqa: BLE001 -- one failed run must not lose the rest
                    e2e.append({"recording": name, "amplitude_m": a, "width_m": w,
                                "x_m": float(cxy[0]), "y_m": float(cxy[1]), "found": False,
                                "time_s": 0.0, "error": repr(exc)})
                log(f"{name} end-to-end {j}: found={e2e[-1]['found']} "
                    f"({e2e[-1]['time_s']:.0f} s)")
    return {"rows": rows, "nulls": nulls, "end_to_end": e2e, "start_fits": fits,
            "amplitudes_m": list(amps), "extension_m": [] if quick else list(EXTENSION),
            "widths_m": list(widths), "placements": placements, "quick": quick,
            "readmit": readmit, "rounds": MAX_BUMPS,
            "alpha": ALPHA_LOCAL, "data": str(real)}


# ------------------------------------------------------------------------------------------
# tables
# ------------------------------------------------------------------------------------------


def _med(v) -> float:
    v = [x for x in v if x is not None]
    return float(np.median(v)) if v else float("nan")


def _cell(sel: list[dict], a: float) -> str:
    det = [r for r in sel if r["detected"]]
    fa = sum(r["false_alarm"] for r in sel)
    tt = _med([abs(r["at_truth"]["t"]) if r["at_truth"]["t"] is not None else None for r in sel])
    tc = _med([r.get("critical_t", r["found"].get("critical_t")) for r in sel])
    ref = [r["refit"] for r in det if "refit" in r]
    pe = _med([e["position_error_m"] for e in ref])
    ar = _med([e["amplitude_m"] for e in ref])
    sa = _med([e["sigma_amplitude_m"] for e in ref])
    wf = _med([e["width_m"] for e in ref])
    sw = _med([e["sigma_width_m"] for e in ref])
    ain = sum(e["amplitude_within_2sigma"] for e in ref)
    win = sum(e["width_within_2sigma"] for e in ref)
    fit = (f"{pe:.2f} | {1e3 * ar:+.2f} ± {1e3 * sa:.2f} | {wf:.2f} ± {sw:.2f} | "
           f"{ain}/{len(ref)} | {win}/{len(ref)}") if ref else "| | | |"
    return (f"{len(det)}/{len(sel)} ({100 * len(det) / len(sel):.0f} %) | {fa} | {tt:.1f} | "
            f"{tc:.1f} | {fit}")


def _pm(v: dict, scale: float, fmt: str) -> str:
    """``value ± sigma`` of an estimate (``held`` when it has no sigma)."""
    sd = v.get("sigma")
    return (f"{scale * v['value']:{fmt}} " + ("(held)" if sd is None
                                              else f"± {scale * sd:.2f}"))


def smallest_detected(rows, rec, widths, amps, rate=0.8) -> dict:
    """Per width the smallest |amplitude| detected in at least ``rate`` of the placements with
    both signs (None: none up to the largest)."""
    out = {}
    for w in widths:
        ok = []
        for a in sorted({abs(x) for x in amps}):
            sel = [r for r in rows if r["recording"] == rec and r["width_m"] == w
                   and abs(r["amplitude_m"]) == a]
            if sel and all(np.mean([r["detected"] for r in sel if r["amplitude_m"] == s]) >= rate
                           for s in {r["amplitude_m"] for r in sel}):
                ok.append(a)
        out[w] = min(ok) if ok else None
    return out


def summarize(res: dict) -> str:
    rows = res["rows"]
    lines = [
        "# Real-data injection: local deformations in the GBT recordings", "",
        f"Placements per (recording, width): {res['placements']}; quick mode: {res['quick']}; "
        f"data: `{res['data']}`. Detection by the diagnosis' own local-deformation search "
        "on the start-fit residuals plus the injected bump (the first step of `diagnose`, "
        "before anything else is modelled; the start fit's robust rejection applied to the "
        "sum), see the script's docstring. "
        + ("The search sees the points the start fit keeps and the rejected ones that agree "
           "with their neighbours (re-admitted: the core of a structure deeper than the "
           "rejection limit); " if res.get("readmit", True) else
           "The search sees only the points the start fit keeps (--no-readmit); ")
        + f"it runs up to {res.get('rounds', MAX_BUMPS)} rounds as `diagnose` does (each "
        "after the previous significant candidate's neighbourhood is excluded; the maps are "
        "not recomputed). Detected = a significant candidate "
        f"(p < {res['alpha']:g} against the largest local structures of the same surface) "
        "within max(w, 0.5 m) of the true centre; own = significant on one of the "
        "structures the unmodified recording itself shows significant (not counted as false "
        "alarms); false alarm = significant anywhere else. "
        "|t| at truth: the first round's roughness-standardised matched filter at the true "
        "centre and width; critical: the |t| its null needs for p < alpha (first round, "
        "median over placements). "
        "Position error, amplitude and width of detections: the catalog's local_deformation "
        "refitted to the searched residuals within 3 w of the candidate (sigmas times the "
        "roughness factor, as the diagnosis reports them; medians), and how many are within 2 "
        "sigma of the truth."
        + ("" if res["quick"] or 1e-4 in res["amplitudes_m"] else
           " 0.1 and 0.2 mm were not run (runtime; t at truth is linear in the amplitude, "
           "so they are below the 0.5 mm rows).") + "", ""]
    amps = res["amplitudes_m"]
    for rec in FILES:
        if rec not in res["start_fits"]:
            continue
        fit = res["start_fits"][rec]
        lines += [f"## {rec}", "",
                  f"{fit.get('n_kept')} of {fit.get('n_points')} points kept by the start fit "
                  f"(sigma0 {fit.get('sigma0', float('nan')):.3f}, "
                  f"{fit.get('start_fit_s', 0):.0f} s).", "",
                  "| width [m] | amplitude [mm] | detected | false alarms | abs(t) at truth | "
                  "critical abs(t) | position error [m] | amplitude [mm] | width [m] | "
                  "a within 2 sigma | w within 2 sigma |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for w in res["widths_m"]:
            for a in amps:
                sel = [r for r in rows if r["recording"] == rec and r["width_m"] == w
                       and r["amplitude_m"] == a]
                if sel:
                    lines.append(f"| {w:g} | {1e3 * a:+.1f} | {_cell(sel, a)} |")
        mins = smallest_detected(rows, rec, res["widths_m"], amps)
        lines += ["", "Smallest amplitude detected in at least 80 % of the placements (both "
                  "signs): " + ", ".join(
                      f"w = {w:g} m: {1e3 * a:.1f} mm" if a else
                      f"w = {w:g} m: none up to {1e3 * max(amps):.0f} mm" for w, a in mins.items()),
                  ""]
        skipped = sorted({w for r in res["nulls"] if r["recording"] == rec
                          for w in r.get("skipped_widths_m", [])})
        if skipped:
            lines += [f"Widths the search skips on this recording (fewer than 12 independent "
                      f"placements): {', '.join(f'{w:g}' for w in skipped)} m.", ""]
    lines += ["## False alarms without a bump", "",
              "| recording | null | runs | significant (own structures) | significant "
              "elsewhere | smallest p (first round) | median p |",
              "|---|---|---|---|---|---|---|"]
    for rec in FILES:
        for kind in ("unmodified", "half around a random centre"):
            sel = [r for r in res["nulls"] if r["recording"] == rec and r["kind"] == kind]
            ps = [r["p_value"] for r in sel if r["p_value"] is not None]
            if not sel:
                continue
            if kind == "unmodified":
                own = sum(len(r.get("significant_candidates", [])) for r in sel)
                fa = 0
            else:
                own = sum(r.get("n_own", 0) for r in sel)
                fa = sum(r.get("n_false", 0) for r in sel)
            lines.append(f"| {rec} | {kind} | {len(sel)} | {own} | {fa} | "
                         f"{min(ps) if ps else float('nan'):.2g} | "
                         f"{np.median(ps) if ps else float('nan'):.2g} |")
    fa = [r for r in rows if r["false_alarm"]]
    own = [r for r in rows if r.get("own_structure")]
    lines += ["", f"Placements with a bump where a significant candidate lay elsewhere (not on "
              f"the recording's own significant structures): {len(fa)} of {len(rows)}; with "
              f"one of those own structures significant as well: {len(own)} of {len(rows)}.",
              "",
              "## What the bar is: the recordings' own local structures", "",
              "The unmodified recordings' searches, round by round (a round stops the "
              "sequence when its candidate is not significant).", "",
              "| recording | round | abs(t) | amplitude [mm] | width [m] | x, y [m] | p | "
              "critical abs(t) | local structures in the null |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in res["nulls"]:
        if r["kind"] != "unmodified":
            continue
        for k, q in enumerate(r.get("searches") or [r], 1):
            if q.get("t") is None:
                continue
            ct = q.get("critical_t")
            lines.append(f"| {r['recording']} | {k} | {abs(q['t']):.2f} | "
                         f"{1e3 * q['amplitude_m']:+.2f} | {q['width_m']:g} | {q['x_m']:.1f}, "
                         f"{q['y_m']:.1f} | {q['p_value']:.2g} | "
                         f"{'' if ct is None else f'{ct:.1f}'} | {q['n_peaks']} |")
    lines += ["", "A bump is detected when its abs(t) exceeds the critical value of the round "
              "that reaches it: the recording's own significant structures are taken first "
              "when they are stronger.", ""]
    if res["end_to_end"]:
        lines += ["## End to end (import + diagnose blind)", "",
                  "| recording | a [mm] | w [m] | found | position error [m] | amplitude [mm] "
                  "| width [m] | a within 2 sigma | w within 2 sigma | local findings "
                  "(all) | time [s] |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in res["end_to_end"]:
            head = f"| {r['recording']} | {1e3 * r['amplitude_m']:+.1f} | {r['width_m']:g} |"
            if r["found"]:
                lines.append(
                    f"{head} yes | {r['position_error_m']:.2f} | "
                    f"{_pm(r['amplitude'], 1e3, '+.2f')} | {_pm(r['width'], 1.0, '.2f')} | "
                    f"{r['amplitude_within_2sigma']} | {r['width_within_2sigma']} | "
                    f"{r.get('n_local_findings', '')} | {r['time_s']:.0f} |")
            else:
                lines.append(f"{head} no | | | | | | {r.get('n_local_findings', '')} | "
                             f"{r['time_s']:.0f} |")
    ts = [r["time_s"] for r in rows]
    if ts:
        lines += ["", "## Cost", "",
                  f"One search: median {np.median(ts):.2f} s ({len(ts)} searches); start fits: "
                  + ", ".join(f"{k} {v['start_fit_s']:.0f} s" for k, v in res["start_fits"].items())
                  + (f"; one end-to-end diagnose: median "
                     f"{np.median([r['time_s'] for r in res['end_to_end']]):.0f} s"
                     if res["end_to_end"] else "")
                  + f"; whole run {res.get('elapsed_s', 0) / 60:.0f} min."]
    return "\n".join(lines) + "\n"


def _rounded(x, digits: int = 5):
    """``x`` with every float to ``digits`` significant digits (a compact results file)."""
    if isinstance(x, dict):
        return {k: _rounded(v, digits) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_rounded(v, digits) for v in x]
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return float(f"{x:.{digits}g}") if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def merge(parts) -> dict:
    """One result from the ``.json`` files of several runs (e.g. more amplitudes run later on
    the same recordings and widths): their placements together, amplitudes in the order
    0.1, -0.1, 0.2, ...; nulls and end-to-end runs of every part (an unmodified recording's
    null once), start fits of the first part, run times added."""
    docs = [json.loads(Path(q).read_text()) for q in parts]
    res = dict(docs[0])
    res["rows"] = [r for d in docs for r in d["rows"]]
    amps = {a for d in docs for a in d["amplitudes_m"]}
    res["amplitudes_m"] = sorted(amps, key=lambda a: (abs(a), -a))
    res["extension_m"] = sorted({a for d in docs for a in d.get("extension_m", [])},
                                key=lambda a: (abs(a), -a))
    seen, nulls = set(), []
    for d in docs:
        for r in d["nulls"]:
            key = (r["recording"], r["kind"])
            if r["kind"] == "unmodified" and key in seen:
                continue
            seen.add(key)
            nulls.append(r)
    res["nulls"] = nulls
    res["end_to_end"] = [r for d in docs for r in d["end_to_end"]]
    res["elapsed_s"] = sum(float(d.get("elapsed_s", 0.0)) for d in docs)
    res["parts"] = [str(q) for q in parts]
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--placements", type=int, default=None)
    ap.add_argument("--end-to-end", type=int, default=None)
    ap.add_argument("--regions", type=int, default=None, help="halves searched as nulls")
    ap.add_argument("--all-amplitudes", action="store_true",
                    help="also 0.1 and 0.2 mm (both signs)")
    ap.add_argument("--no-readmit", action="store_true",
                    help="search only the points the robust start fit keeps (the search "
                         "before the coherent re-admission; written as real_inject_kept)")
    ap.add_argument("--amplitudes-mm", default=None,
                    help="comma-separated amplitudes in mm (default: the script's set)")
    ap.add_argument("--widths-m", default=None, help="comma-separated widths in m")
    ap.add_argument("--recordings", default=None, help="comma-separated: scan10,bump1")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--merge", default=None,
                    help="comma-separated result .json files of earlier runs: one table "
                         "(written as real_inject.{json,md} in --out)")
    a = ap.parse_args(argv)
    if a.merge:
        parts = a.merge.split(",")
        bad = [q for q in parts if not Path(q).is_file()]
        if bad:
            print(f"error: --merge: {bad[0]}: no such file", file=sys.stderr)
            return 2
        res = merge(parts)
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "real_inject.json").write_text(json.dumps(_rounded(res), separators=(",", ":")))
        (out / "real_inject.md").write_text(summarize(res))
        print(summarize(res))
        return 0
    missing = real_data_missing()
    if missing:
        print(f"error: {missing}", file=sys.stderr)
        return 2
    if any(v is not None and v < 0 for v in (a.placements, a.end_to_end, a.regions)) or (
            a.placements == 0):
        print("error: --placements must be >= 1, --end-to-end and --regions >= 0",
              file=sys.stderr)
        return 2
    enable_x64()
    placements = a.placements or (4 if a.quick else 20)
    e2e = min(a.end_to_end if a.end_to_end is not None else (1 if a.quick else 4), len(E2E))
    regions = a.regions if a.regions is not None else (2 if a.quick else 20)
    t0 = time.time()
    Path(a.out).mkdir(parents=True, exist_ok=True)
    res = run(a.quick, placements, e2e, regions, log=lambda s: print(s, flush=True),
              all_amplitudes=a.all_amplitudes, readmit=not a.no_readmit,
              amplitudes=[1e-3 * float(v) for v in a.amplitudes_mm.split(",")]
              if a.amplitudes_mm else None,
              widths=[float(v) for v in a.widths_m.split(",")] if a.widths_m else None,
              recordings=a.recordings.split(",") if a.recordings else None,
              checkpoint=Path(a.out) / "real_inject_partial.json")
    res["elapsed_s"] = time.time() - t0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    name = ("real_inject_quick" if a.quick else "real_inject") + (
        "_kept" if a.no_readmit else "")
    (out / f"{name}.json").write_text(json.dumps(_rounded(res), separators=(",", ":")))
    (out / f"{name}.md").write_text(summarize(res))
    print(summarize(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
