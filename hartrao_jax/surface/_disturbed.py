"""Disturbed scans: an abrupt jump of the residuals along one horizontal angle (paper sec. 4.2).

The paper found 4 of 46 scans, always in cycle 1, with "an abnormal line along one random
horizontal angle": the scanner moved for a moment (brake not engaged, telescope not settled),
so every point recorded meanwhile is shifted. Such scans should be excluded, or the affected
part cut out. The simulator's ``impulsive_shift`` effect produces them.

Detection (per scan, on the residuals of the adjustment):

1. The scan sweeps phi at a constant rate, so a short disturbance covers a band of phi lines.
   Points are binned into the scanner's vertical lines (bin width: the angular step, measured
   on the data) and, within each line, into its face-1 and face-2 halves (the half-lines at dish
   azimuths ``phi`` and ``phi + pi``). Per half-line the median normal deviation is taken
   (medians: robust to the scatter left in the data).
2. The dish's own structure is common to both cycles: line ``j`` of cycle 2 covers the same two
   half-lines as line ``j`` of cycle 1, with the faces swapped. With the other cycle of the
   position as reference, its series is subtracted (face 1 of one cycle minus face 2 of the
   other), which leaves noise and whatever happened during one of the two scans.
3. A moving-sum (MOSUM) two-sample statistic compares the mean of the ``w`` lines after each
   line boundary with the ``w`` lines before, in units of its noise (sigma of one line from the
   median absolute difference of neighbouring lines). The two halves give a 2-dof statistic
   ``T = sqrt(T1^2 + T2^2)``. The face boundary lies at the ends of the cycle's phi range
   (phi = cycle start / end): boundaries within ``edge_deg`` of them are not tested, nor is
   anything the smooth two-face-sensitive errors do (they change slowly with phi).
4. A change is significant when ``T > threshold`` and the jump exceeds ``min_jump_m`` (a
   practical effect size: with millions of points everything is "significant"). Around the
   strongest change a one-change and a two-change (box) piecewise-constant model are fitted by
   least squares; the box is taken when it explains significantly more. The disturbed range is
   the box, or for one change the side that departs from the scan's median level (usually the
   shorter one, "the first or the last quarter of the scan").
5. With a reference, a change is given to the scan whose own series jumps more there (a
   disturbance of the reference shows in the difference too).

:func:`detect_disturbed` returns a :class:`DisturbedReport` (scan, cycle, phi range in deg,
jump, statistic) or None; :func:`cut_keep` and :func:`keep_function` build the masks for
``--cut-disturbed``; :func:`without_disturbed` the scan list for ``--exclude-disturbed``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..fit._records import read_residuals

DISTURBED_SCHEMA = "hartrao-disturbed/1"


@dataclass(frozen=True)
class DisturbedConfig:
    """Parameters of the detection (deg, m).

    Attributes:
        window_deg: half-width of the moving windows (at least ``min_window_lines`` lines).
        min_window_lines: smallest window in lines.
        threshold: MOSUM statistic (noise sigmas, 2 dof) that makes a change significant.
        min_jump_m: smallest jump of the line medians worth reporting (effect size).
        edge_deg: no change is tested within this of the ends of the phi range (face boundary).
        max_abs_m: points with larger |deviation| are ignored (scatter).
        min_line_points: half-lines with fewer points are gaps.
        band_deg: width of the vertical-angle bands whose medians are removed first.
        line_width_deg: width of the phi bins; None: the angular step measured on the data.
        cut_margin_deg: the cut (``cut_keep``) extends the disturbed range by this on each side.
    """

    window_deg: float = 2.0
    min_window_lines: int = 3
    threshold: float = 8.0
    min_jump_m: float = 3e-4
    edge_deg: float = 2.0
    max_abs_m: float = 0.02
    min_line_points: int = 5
    band_deg: float = 2.0
    line_width_deg: float | None = None
    cut_margin_deg: float = 0.5


@dataclass
class DisturbedReport:
    """A disturbed scan: where (phi, deg), by how much, and how sure."""

    scan: str
    position: str
    cycle: int
    phi_deg: float  # where the disturbance starts (raw phi)
    phi_end_deg: float  # where it ends (raw phi)
    jump_m: float  # level of the disturbed lines minus the rest (median of the two faces)
    jump_faces_m: tuple[float, float]
    statistic: float
    threshold: float
    sigma_line_m: float
    n_lines: int
    line_width_deg: float
    reference: str | None = None
    kind: str = "box"  # "box" (two changes) or "step" (one change, to the end of the range)
    series: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def to_json(self) -> dict[str, Any]:
        return {
            "scan": self.scan, "position": self.position, "cycle": self.cycle,
            "phi_deg": self.phi_deg, "phi_end_deg": self.phi_end_deg,
            "phi_range_deg": [min(self.phi_deg, self.phi_end_deg),
                              max(self.phi_deg, self.phi_end_deg)],
            "jump_m": self.jump_m, "jump_faces_m": list(self.jump_faces_m),
            "statistic": self.statistic, "threshold": self.threshold,
            "sigma_line_m": self.sigma_line_m, "n_lines": self.n_lines,
            "line_width_deg": self.line_width_deg, "reference": self.reference, "kind": self.kind,
        }


# --------------------------------------------------------------------------------------------
# Line series
# --------------------------------------------------------------------------------------------


def _phi_start(cycle: int) -> tuple[float, float]:
    return (math.pi, math.pi) if cycle == 2 else (0.0, math.pi if cycle == 1 else 2 * math.pi)


def line_width(phi: np.ndarray, default_rad: float = math.radians(0.1)) -> float:
    """The angular step between vertical lines (rad), measured on raw phi values.

    Sorted phi values are cut into lines where the gap exceeds 1e-4 rad (far above the angle
    noise, far below any scanner's step); the step is the median spacing of the lines' medians.
    """
    p = np.sort(np.asarray(phi, float))
    if len(p) < 20:
        return default_rad
    cut = np.flatnonzero(np.diff(p) > 1e-4) + 1
    if len(cut) < 10:
        return default_rad
    bounds = np.concatenate([[0], cut, [len(p)]])
    centres = np.array([p[(a + b - 1) // 2] for a, b in zip(bounds[:-1], bounds[1:])])
    return float(np.median(np.diff(centres)))


def _grouped_median(idx: np.ndarray, val: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Median of ``val`` per group ``idx`` in ``0..n-1`` (NaN for empty groups) and counts."""
    order = np.lexsort((val, idx))
    i, v = idx[order], val[order]
    cnt = np.bincount(i, minlength=n)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    med = np.full(n, np.nan)
    ok = cnt > 0
    lo = start[ok] + (cnt[ok] - 1) // 2
    hi = start[ok] + cnt[ok] // 2
    med[ok] = 0.5 * (v[lo] + v[hi])
    return med, cnt


@dataclass
class LineSeries:
    """Median deviation per phi line and face half (``med[face-1, line]``), with bookkeeping."""

    cycle: int
    lo_rad: float
    width_rad: float
    med: np.ndarray  # (2, L)
    count: np.ndarray  # (2, L)

    @property
    def n_lines(self) -> int:
        return self.med.shape[1]

    def phi_rad(self, k) -> np.ndarray:
        """Raw phi of line boundary ``k`` (start of line k)."""
        return self.lo_rad + np.asarray(k, float) * self.width_rad


def line_series(phi: np.ndarray, theta: np.ndarray, deviation_m: np.ndarray, cycle: int,
                valid: np.ndarray | None = None, config: DisturbedConfig | None = None,
                width_rad: float | None = None) -> LineSeries:
    """Per-line, per-face median deviation of one scan (module doc, step 1).

    Before the medians, each point's deviation is reduced by the median of its face and its
    band of vertical angle (``band_deg`` wide) over the whole scan: what depends on theta (the
    radius on the dish, and every two-face-sensitive error) is then the same for every line, so
    a line that misses part of its points (quadrupod shadows) keeps its level.
    """
    cfg = config or DisturbedConfig()
    phi = np.asarray(phi, float)
    theta = np.asarray(theta, float)
    dev = np.asarray(deviation_m, float)
    ok = np.isfinite(dev) & (np.abs(dev) < cfg.max_abs_m) & np.isfinite(theta)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    lo, span = _phi_start(cycle)
    if width_rad is None:
        width_rad = (math.radians(cfg.line_width_deg) if cfg.line_width_deg
                     else line_width(phi[ok]))
    L = max(1, int(math.ceil(span / width_rad - 1e-9)))
    j = np.clip(np.floor((phi[ok] - lo) / width_rad).astype(np.int64), 0, L - 1)
    th = np.mod(theta[ok], 2 * math.pi)
    f = (th >= math.pi).astype(np.int64)
    th0 = np.where(f == 1, 2 * math.pi - th, th)
    nb = int(math.ceil(180.0 / cfg.band_deg))
    band = np.clip((np.degrees(th0) / cfg.band_deg).astype(np.int64), 0, nb - 1)
    d = dev[ok]
    base, _ = _grouped_median(f * nb + band, d, 2 * nb)
    d = d - base[f * nb + band]
    med, cnt = _grouped_median(f * L + j, d, 2 * L)
    med, cnt = med.reshape(2, L), cnt.reshape(2, L)
    med[cnt < cfg.min_line_points] = np.nan
    return LineSeries(cycle, lo, width_rad, med, cnt)


def noise_scale(med: np.ndarray, cnt: np.ndarray) -> np.ndarray:
    """Per face, ``c`` with ``var(median of line j) = c / n_j``, from neighbouring lines.

    The normalised differences ``(m_j - m_j-1) / sqrt(1/n_j + 1/n_j-1)`` have variance ``c``
    (noise plus whatever structure changes from one line to the next); ``c`` is their squared
    robust (MAD) scale.
    """
    out = np.full(len(med), np.nan)
    for i, (m, n) in enumerate(zip(med, cnt)):
        ok = np.isfinite(m) & (n > 0)
        mm, nn = m[ok], n[ok].astype(float)
        if len(mm) < 6:
            continue
        z = np.diff(mm) / np.sqrt(1 / nn[1:] + 1 / nn[:-1])
        out[i] = (1.4826 * np.median(np.abs(z - np.median(z)))) ** 2
    return out


def _cums(S: np.ndarray, W: np.ndarray):
    Wv = np.where(np.isfinite(S), W, 0.0)
    Sv = np.where(np.isfinite(S), S, 0.0)
    z = np.zeros((len(S), 1))
    cw = np.concatenate([z, np.cumsum(Wv, 1)], 1)
    cs = np.concatenate([z, np.cumsum(Wv * Sv, 1)], 1)
    cq = np.concatenate([z, np.cumsum(Wv * Sv * Sv, 1)], 1)
    return cw, cs, cq


def _mosum(S: np.ndarray, W: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Per line boundary k: the 2-dof statistic and the jumps per face (weighted mean of the
    ``w`` lines after k minus the ``w`` lines before; weights = inverse variances ``W``)."""
    L = S.shape[1]
    cw, cs, _ = _cums(S, W)
    k = np.arange(L + 1)
    a0, b1 = np.clip(k - w, 0, L), np.clip(k + w, 0, L)
    wl, wr = cw[:, k] - cw[:, a0], cw[:, b1] - cw[:, k]
    with np.errstate(invalid="ignore", divide="ignore"):
        D = (cs[:, b1] - cs[:, k]) / wr - (cs[:, k] - cs[:, a0]) / wl
        T = D / np.sqrt(1 / wl + 1 / wr)
    bad = ~np.isfinite(T)
    T2 = np.where(bad, 0.0, T * T).sum(0)
    T2[bad.all(0)] = np.nan
    return np.sqrt(T2), np.where(bad, np.nan, D)


def _chi2(cums, bounds: Sequence[int]) -> float:
    """Weighted residual sum of squares (summed over faces) of a piecewise-constant model
    with the given segment boundaries (0 and L included), from prefix sums."""
    cw, cs, cq = cums
    tot = 0.0
    for i, j in zip(bounds[:-1], bounds[1:]):
        ww, ss, qq = cw[:, j] - cw[:, i], cs[:, j] - cs[:, i], cq[:, j] - cq[:, i]
        with np.errstate(invalid="ignore", divide="ignore"):
            tot += float(np.where(ww > 0, qq - ss * ss / np.where(ww > 0, ww, 1.0), 0.0).sum())
    return tot


def _peaks(T: np.ndarray, D: np.ndarray, cand: np.ndarray, w: int) -> list[int]:
    """Candidate boundaries that are the largest within +-w among those whose jump has the
    same sign (the two edges of a short box are both kept)."""
    sign = np.sign(np.nansum(np.where(np.isfinite(D), D, 0.0), axis=0))
    out: list[int] = []
    for k in np.flatnonzero(cand)[np.argsort(-T[cand], kind="stable")]:
        if all(abs(k - j) > w or sign[k] != sign[j] for j in out):
            out.append(int(k))
    return out


def _refine(cums, bounds: list[int], w: int, L: int) -> list[int]:
    """Move each inner boundary within +-w to the least chi-square, the others held."""
    b = list(bounds)
    for _ in range(2):
        for i in range(1, len(b) - 1):
            lo, hi = max(b[i - 1] + 1, b[i] - w), min(b[i + 1] - 1, b[i] + w)
            best = min(range(lo, hi + 1), key=lambda k: _chi2(cums, b[:i] + [k] + b[i + 1:]))
            b[i] = best
    return b


def _wmean(S: np.ndarray, W: np.ndarray, sel: np.ndarray) -> np.ndarray:
    ok = np.isfinite(S) & sel[None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, W * S, 0.0).sum(1) / np.where(ok, W, 0.0).sum(1)


def detect_series(S: np.ndarray, W: np.ndarray, width_rad: float, lo_rad: float,
                  config: DisturbedConfig | None = None, span_rad: float = math.pi
                  ) -> dict[str, Any] | None:
    """Change search on line series ``S`` (faces x lines) with inverse variances ``W``.

    Returns the disturbed range in lines (``start``, ``end``) and raw phi (deg), its jump per
    face, the statistic, or None when nothing significant and large enough is found.
    """
    cfg = config or DisturbedConfig()
    L = S.shape[1]
    w = max(cfg.min_window_lines, int(round(math.radians(cfg.window_deg) / width_rad)))
    e = int(math.ceil(math.radians(cfg.edge_deg) / width_rad))
    if L < 2 * (w + e) + 2:
        return None
    T, D = _mosum(S, W, w)
    k = np.arange(L + 1)
    T = np.where((k >= w + e) & (k <= L - w - e) & np.isfinite(T), T, 0.0)
    big = np.max(np.where(np.isfinite(D), np.abs(D), 0.0), axis=0)
    cand = (T > cfg.threshold) & (big > cfg.min_jump_m)
    if not cand.any():
        return None
    peaks = _peaks(T, D, cand, w)
    k0 = peaks[0]
    cums = _cums(S, W)
    step = _refine(cums, [0, k0, L], w, L)
    chi_step = _chi2(cums, step)
    box, chi_box = None, np.inf
    for kj in peaks[1:]:
        bb = _refine(cums, [0, min(k0, kj), max(k0, kj), L], w, L)
        c = _chi2(cums, bb)
        if c < chi_box:
            box, chi_box = bb, c
    lines = np.arange(L)
    if box is not None and chi_step - chi_box > cfg.threshold**2 / 2:
        kind, i0, i1 = "box", box[1], box[2]
        start, end = i0, i1
    else:
        kind, c1 = "step", step[1]
        with np.errstate(invalid="ignore"):
            base = np.nanmedian(S, axis=1)
        before, after = _wmean(S, W, lines < c1), _wmean(S, W, lines >= c1)
        if np.nanmean(np.abs(after - base)) >= np.nanmean(np.abs(before - base)):
            i0, i1, start, end = c1, L, c1, L
        else:
            i0, i1, start, end = 0, c1, c1, 0
    inside = (lines >= i0) & (lines < i1)
    jump_faces = _wmean(S, W, inside) - _wmean(S, W, ~inside)
    jump = float(np.nanmean(jump_faces))
    if abs(jump) < cfg.min_jump_m and np.nanmax(np.abs(jump_faces)) < cfg.min_jump_m:
        return None
    return {"start": int(start), "end": int(end), "i0": int(i0), "i1": int(i1), "kind": kind,
            "statistic": float(T[k0]), "jump_m": jump,
            "jump_faces_m": tuple(float(x) for x in jump_faces), "window_lines": w,
            "phi_deg": math.degrees(lo_rad + min(start * width_rad, span_rad)),
            "phi_end_deg": math.degrees(lo_rad + min(end * width_rad, span_rad))}


# --------------------------------------------------------------------------------------------
# Scans
# --------------------------------------------------------------------------------------------


def _valid(deviation_m: np.ndarray, used: np.ndarray | None, cfg: DisturbedConfig) -> np.ndarray:
    """Points for the line medians: within a few sigmas of the surface, used or not (a large
    jump can make the adjustment reject the disturbed points)."""
    d = np.asarray(deviation_m, float)
    ref = d[used] if used is not None and used.any() else d[np.isfinite(d)]
    ref = ref[np.abs(ref) < cfg.max_abs_m]
    s = 1.4826 * np.median(np.abs(ref - np.median(ref))) if len(ref) else cfg.max_abs_m
    clip = min(cfg.max_abs_m, max(8 * s, 0.004))
    return np.isfinite(d) & (np.abs(d) < clip)


def _series_of(phi, theta, dev, cycle, used, cfg, width=None) -> LineSeries:
    return line_series(phi, theta, dev, cycle, _valid(dev, used, cfg), cfg, width)


def detect_disturbed_arrays(scan: str, position: str, cycle: int, phi: np.ndarray,
                            theta: np.ndarray, deviation_m: np.ndarray,
                            used: np.ndarray | None = None, *, reference: Mapping | None = None,
                            config: DisturbedConfig | None = None) -> DisturbedReport | None:
    """:func:`detect_disturbed` on plain arrays (raw ``phi``, ``theta`` in rad). ``reference``:
    the other cycle of the position as a mapping with ``scan, cycle, phi, theta, deviation_m,
    used``."""
    cfg = config or DisturbedConfig()
    if cycle not in (0, 1, 2):
        return None
    own = _series_of(phi, theta, deviation_m, cycle, used, cfg)
    c_own = noise_scale(own.med, own.count)
    with np.errstate(divide="ignore"):
        var = c_own[:, None] / own.count
    S, ref_id, rs = own.med, None, None
    if reference is not None and {cycle, int(reference["cycle"])} == {1, 2}:
        rs = _series_of(reference["phi"], reference["theta"], reference["deviation_m"],
                        int(reference["cycle"]), reference.get("used"), cfg, width=own.width_rad)
        if rs.n_lines == own.n_lines:
            # the same dish half-lines: face 1 of this cycle <-> face 2 of the other, by line
            rmed, rcnt = rs.med[::-1], rs.count[::-1]
            c_ref = noise_scale(rmed, rcnt)
            with np.errstate(divide="ignore"):
                var = var + c_ref[:, None] / rcnt
            S = own.med - rmed
            ref_id = str(reference["scan"])
        else:
            rs = None
    with np.errstate(divide="ignore", invalid="ignore"):
        W = np.where(np.isfinite(var) & (var > 0), 1.0 / var, 0.0)
    r = detect_series(S, W, own.width_rad, own.lo_rad, cfg, _phi_start(cycle)[1])
    if r is None:
        return None
    if rs is not None:
        # attribution: the scan whose own line medians jump more over the range
        sel = (np.arange(own.n_lines) >= r["i0"]) & (np.arange(own.n_lines) < r["i1"])
        with np.errstate(divide="ignore"):
            Wo = np.where(own.count > 0, own.count / c_own[:, None], 0.0)
            Wr = np.where(rs.count[::-1] > 0, rs.count[::-1] / c_ref[:, None], 0.0)
        jo = np.nanmean(np.abs(_wmean(own.med, Wo, sel) - _wmean(own.med, Wo, ~sel)))
        jr = np.nanmean(np.abs(_wmean(rs.med[::-1], Wr, sel) - _wmean(rs.med[::-1], Wr, ~sel)))
        if jr > jo:
            return None
    phi_lines = np.degrees(own.phi_rad(np.arange(own.n_lines) + 0.5))
    with np.errstate(divide="ignore", invalid="ignore"):
        sig = float(np.sqrt(np.nanmedian(np.where(W > 0, 1 / W, np.nan))))
    return DisturbedReport(
        scan=scan, position=position, cycle=cycle, phi_deg=r["phi_deg"],
        phi_end_deg=r["phi_end_deg"], jump_m=r["jump_m"], jump_faces_m=r["jump_faces_m"],
        statistic=r["statistic"], threshold=cfg.threshold, sigma_line_m=sig,
        n_lines=own.n_lines, line_width_deg=math.degrees(own.width_rad), reference=ref_id,
        kind=r["kind"], series={"phi_deg": phi_lines, "series_m": S, "own_m": own.med})


def _arrays_of_fit(s) -> dict[str, Any]:
    return {"scan": s.meta.id, "cycle": s.meta.cycle, "phi": s.data.phi_rad,
            "theta": s.data.theta_rad, "deviation_m": s.deviation_m, "used": s.used}


def detect_disturbed(scan_fit, reference=None, config: DisturbedConfig | None = None, *,
                     keep: np.ndarray | None = None) -> DisturbedReport | None:
    """Is this scan disturbed along one horizontal angle? (module doc)

    ``scan_fit``: a :class:`._fit.ScanFit`; ``reference``: optionally the ScanFit of the other
    cycle of the same position (removes the dish's own structure). Points near the surface are
    used whether the adjustment kept them or not (a large jump gets the disturbed points
    rejected); ``keep`` restricts them (e.g. to what preprocessing or a cut kept). Returns None
    for a clean scan.
    """
    a = _arrays_of_fit(scan_fit)
    ref = _arrays_of_fit(reference) if reference is not None else None
    dev = a["deviation_m"]
    if keep is not None:
        dev = np.where(np.asarray(keep, bool), dev, np.nan)
    return detect_disturbed_arrays(a["scan"], scan_fit.meta.position, a["cycle"], a["phi"],
                                   a["theta"], dev, a["used"], reference=ref, config=config)


def _pair(items: Sequence, position, cycle) -> dict:
    """For every item, the first item of the same position and the other cycle (or None)."""
    out = {}
    for i, x in enumerate(items):
        others = [y for y in items if position(y) == position(x) and
                  {cycle(x), cycle(y)} == {1, 2}]
        out[i] = others[0] if others else None
    return out


def detect_disturbed_campaign(campaign_fit, config: DisturbedConfig | None = None
                              ) -> list[DisturbedReport]:
    """Every disturbed scan of a :class:`._fit.CampaignFit` (the other cycle as reference)."""
    scans = list(campaign_fit.scans)
    ref = _pair(scans, lambda s: s.meta.position, lambda s: s.meta.cycle)
    out = []
    for i, s in enumerate(scans):
        r = detect_disturbed(s, ref[i], config)
        if r is not None:
            out.append(r)
    return out


def detect_disturbed_residuals(fit_dir, config: DisturbedConfig | None = None
                               ) -> list[DisturbedReport]:
    """Every disturbed scan of a ``fit`` output directory (``fit.json`` + ``residuals/``)."""

    fit_dir = Path(fit_dir)
    doc = json.loads((fit_dir / "fit.json").read_text())
    arrays = []
    for s in doc["scans"]:
        p = fit_dir / "residuals" / f"{s['id']}.parquet"
        if not p.exists():
            continue
        r = read_residuals(p, ("phi_rad", "theta_rad", "deviation_m", "used"))
        arrays.append({"scan": s["id"], "position": s["position"], "cycle": int(s["cycle"]),
                       "phi": r["phi_rad"], "theta": r["theta_rad"],
                       "deviation_m": r["deviation_m"], "used": r["used"].astype(bool)})
    ref = _pair(arrays, lambda a: a["position"], lambda a: a["cycle"])
    out = []
    for i, a in enumerate(arrays):
        r = detect_disturbed_arrays(a["scan"], a["position"], a["cycle"], a["phi"], a["theta"],
                                    a["deviation_m"], a["used"], reference=ref[i], config=config)
        if r is not None:
            out.append(r)
    return out


# --------------------------------------------------------------------------------------------
# Masks for --exclude-disturbed / --cut-disturbed
# --------------------------------------------------------------------------------------------


def cut_keep(phi_rad: np.ndarray, report: DisturbedReport | Mapping,
             margin_deg: float | None = None) -> np.ndarray:
    """Keep mask (True: keep) dropping the report's phi range plus ``margin_deg`` each side."""
    rep = report.to_json() if isinstance(report, DisturbedReport) else dict(report)
    m = DisturbedConfig().cut_margin_deg if margin_deg is None else margin_deg
    a, b = rep["phi_range_deg"] if "phi_range_deg" in rep else sorted(
        (rep["phi_deg"], rep["phi_end_deg"]))
    ph = np.degrees(np.asarray(phi_rad, float))
    return ~((ph >= a - m) & (ph <= b + m))


def keep_function(reports: Iterable[DisturbedReport], base: Callable | None = None,
                  margin_deg: float | None = None) -> Callable:
    """``keep(meta, data) -> mask`` for ``fit_campaign(keep=...)`` (``--cut-disturbed``):
    the disturbed phi range of each reported scan is dropped, combined with ``base`` (e.g. the
    preprocessing's keep function) when given."""
    by = {r.scan: r for r in reports}

    def keep(meta, data, *args):
        k = np.ones(len(data), bool) if base is None else np.asarray(base(meta, data, *args), bool)
        if meta.id in by:
            k &= cut_keep(data.phi_rad, by[meta.id], margin_deg)
        return k

    return keep


def without_disturbed(scan_ids: Iterable[str], reports: Iterable[DisturbedReport]) -> list[str]:
    """The scan ids minus the disturbed ones (``--exclude-disturbed``)."""
    bad = {r.scan for r in reports}
    return [s for s in scan_ids if s not in bad]


def disturbed_json(reports: Iterable[DisturbedReport], config: DisturbedConfig | None = None
                   ) -> dict:
    """``disturbed.json`` (schema ``hartrao-disturbed/1``)."""
    from dataclasses import asdict

    return {"schema": DISTURBED_SCHEMA, "config": asdict(config or DisturbedConfig()),
            "disturbed": [r.to_json() for r in reports]}


__all__ = [
    "DISTURBED_SCHEMA", "DisturbedConfig", "DisturbedReport", "LineSeries", "cut_keep",
    "detect_disturbed", "detect_disturbed_arrays", "detect_disturbed_campaign",
    "detect_disturbed_residuals", "detect_series", "disturbed_json", "keep_function",
    "line_series", "without_disturbed",
]
