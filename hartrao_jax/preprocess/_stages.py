"""The stages of :func:`._preprocess.preprocess_scan`, one small function each: finite rows,
seeded samples, initial values, pose refinement, range and geometry windows (m), patch size,
``epsilon`` (m), subdivision, padded packing, plane fits and the classification of rows."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..campaign._campaign import Campaign, ScanData, ScanMeta
from ..geometry._geometry import (
    pointing_gravity,
)
from ._frames import _cartesian, _flat_coordinates, default_range_window, refine_pose
from ._initial import choose_initial_values
from ._patches import _Bins, _keys, _next_pow2, _size_buckets, _split_keys
from ._planes import fit_planes
from ._types import (
    CHUNK,
    GEOMETRY_WINDOW,
    KEPT,
    RANGE_WINDOW,
    RANSAC_OUTLIER,
    REASONS,
    SMALL_PATCH,
    PreprocessConfig,
    _blocks,
)


@dataclass
class _Windowed:
    """The rows that pass the range and geometry windows, with their patch keys.

    ``idx``: row indices into the scan; ``coords``: their coordinates (m) in the plane-fitting
    frame as three arrays; ``keys``/``occ``: patch key of each row and rows per key of ``bins``.
    """

    idx: np.ndarray
    coords: list[np.ndarray]
    keys: np.ndarray
    occ: np.ndarray
    bins: _Bins


@dataclass
class _Planes:
    """Plane fits per patch: ``planes`` (n, 4) ``A, B, C, D`` (unit normal, m), inliers per
    patch, inliers' rms (m), and the inlier flag of every row in patch order."""

    planes: np.ndarray
    n_inliers: np.ndarray
    rms: np.ndarray
    inlier_sorted: np.ndarray


def _finite_rows(r: np.ndarray, phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Rows whose three observations are finite (block by block)."""
    finite = np.empty(len(r), bool)
    for s, e in _blocks(len(r)):
        finite[s:e] = np.isfinite(r[s:e]) & np.isfinite(phi[s:e]) & np.isfinite(theta[s:e])
    return finite


def _sample_rows(rng: np.random.Generator, n: int, mask_fn, size: int) -> np.ndarray:
    """Up to ``size`` random rows of ``n`` (drawn from ``rng``) for which ``mask_fn(rows)``
    holds, in increasing order."""
    m = min(n, 4 * size)
    cand = np.sort(rng.choice(n, size=m, replace=False)) if m < n else np.arange(n)
    return cand[mask_fn(cand)][:size]


def _initial_stage(campaign: Campaign, meta: ScanMeta, data: ScanData, finite: np.ndarray,
                   rng: np.random.Generator, cfg: PreprocessConfig, notes: list[str]):
    """Initial values from the pointing and a heading search on a sample, or None (with a
    note) when they are off or do not fit the data."""
    if not (cfg.use_initial_values and finite.sum() >= 100):
        return None
    g = pointing_gravity(meta, campaign.telescope, campaign.site)
    rows = _sample_rows(rng, len(finite), lambda c: finite[c], cfg.init_sample)
    try:
        iv = choose_initial_values(campaign, meta, data.subset(rows), g, seed=cfg.seed)
    except (np.linalg.LinAlgError, ValueError) as e:  # pragma: no cover - defensive
        notes.append(f"initial values failed ({e}); nominal geometry used")
        return None
    if all(np.isfinite(v) for v in iv.x.values()) and iv.x["f"] > 0 and iv.inlier_fraction >= 0.2:
        return iv
    notes.append(f"initial values rejected (inlier fraction {iv.inlier_fraction:.2f})"
                 "; nominal geometry used")
    return None


def _plane_frame(cfg: PreprocessConfig, init, notes: list[str]) -> str:
    """``"flat"`` or ``"scanner"``: the configured frame, flat needing initial values."""
    frame = cfg.frame or ("flat" if init is not None else "scanner")
    if frame == "flat" and init is None:
        notes.append("frame 'flat' needs initial values: using 'scanner'")
        frame = "scanner"
    return frame


def _refined_pose(campaign: Campaign, data: ScanData, finite: np.ndarray, init,
                  rng: np.random.Generator, cfg: PreprocessConfig):
    """``(pose, R_ref)``: the initial pose refined on a sample near the paraboloid
    (:func:`refine_pose`), and the sample's median range (m; None without a refinement)."""
    if init is None:
        return None, None
    pose = dict(init.x)
    if not cfg.refine_pose:
        return pose, None
    r, phi, th = data.range_m, data.phi_rad, data.theta_rad
    lo, hi = default_range_window(campaign, pose, dataclasses.replace(
        cfg, range_margin_m=cfg.range_margin_m + 0.5))
    rows = _sample_rows(rng, len(r), lambda c: finite[c] & (r[c] >= lo) & (r[c] <= hi),
                        4 * cfg.pose_sample)
    xs = _cartesian(r[rows], phi[rows], th[rows])
    near = np.flatnonzero(np.abs(_flat_coordinates(xs, pose)[0][2])
                          <= cfg.geometry_window_m)[: cfg.pose_sample]
    if len(near) < 100:
        return pose, None
    return refine_pose(tuple(c[near] for c in xs), pose), float(np.median(r[rows[near]]))


def _windows(campaign: Campaign, data: ScanData, finite: np.ndarray, reason: np.ndarray,
             pose, frame: str, d_min: float, d_max: float, f_use: float, bins: _Bins,
             cfg: PreprocessConfig) -> _Windowed:
    """Range window (eq. 3) and, with a pose, the geometry window (height about the
    paraboloid and annulus), block by block; marks the removed rows in ``reason`` and
    returns the survivors with their fitting-frame coordinates and patch keys."""
    tel = campaign.telescope
    r, phi, th = data.range_m, data.phi_rad, data.theta_rad
    rim = tel.diameter_m / 2 + abs(tel.offset_m)
    inner = tel.cone_radius_m - cfg.cone_margin_m if tel.offset_m == 0 else -np.inf
    occ = np.zeros(bins.n_keys, np.int64)
    idx_parts, coord_parts, key_parts = [], [], []
    for s, e in _blocks(len(r)):
        alive = finite[s:e] & (r[s:e] >= d_min) & (r[s:e] <= d_max)
        reason[s:e][finite[s:e] & ~alive] = RANGE_WINDOW
        ia = np.flatnonzero(alive)
        xs = _cartesian(r[s:e][ia], phi[s:e][ia], th[s:e][ia])
        if pose is not None:
            Xf, rho = _flat_coordinates(xs, pose)
            hv = Xf[2] * np.sqrt(1.0 + rho**2 / (4 * f_use * f_use))  # vertical distance
            good = ((np.abs(hv) <= cfg.geometry_window_m) & (rho >= inner)
                    & (rho <= rim + cfg.rim_margin_m))
            reason[s + ia[~good]] = GEOMETRY_WINDOW
            ia = ia[good]
            xs = tuple(c[good] for c in (Xf if frame == "flat" else xs))
        idx_parts.append((s + ia).astype(np.int64))
        coord_parts.append(xs)
        key_parts.append(bins.keys(phi[s + ia], th[s + ia]))
        occ += np.bincount(key_parts[-1], minlength=bins.n_keys)
    idx = np.concatenate(idx_parts) if idx_parts else np.zeros(0, np.int64)
    coords = [np.concatenate([c[k] for c in coord_parts]) if coord_parts else np.zeros(0)
              for k in range(3)]
    keys = np.concatenate(key_parts) if key_parts else np.zeros(0, np.int32)
    return _Windowed(idx, coords, keys, occ, bins)


def _patch_size(w: _Windowed, data: ScanData, cycle: int, R_ref: float,
                cfg: PreprocessConfig) -> tuple[float, float | None]:
    """``(size_m, typical)``: the patch side (m) and the median points per 0.3-m patch
    (None with a configured size). A coarse scan gets larger patches: ``w`` is re-keyed."""
    if cfg.patch_size_m is not None:
        return float(cfg.patch_size_m), None
    occ0 = w.occ[w.occ > 0]
    typical = float(np.median(occ0)) if len(occ0) else 0.0
    size = 0.30 * (max(1.0, math.sqrt(cfg.target_patch_points / typical)) if typical else 1)
    if size > 0.30:
        w.bins = _Bins(cycle, size, R_ref)
        w.keys, w.occ = _keys(data.phi_rad, data.theta_rad, w.idx, w.bins)
    return size, typical


def _epsilon(cfg: PreprocessConfig, sigma_n: float, frame: str, size: float,
             f_use: float) -> tuple[float, float]:
    """``(epsilon, allowance)`` (m): the RANSAC threshold, ``k_sigma`` sigmas of a point's
    distance plus the frame's allowance (module doc), unless configured."""
    if cfg.allowance_m is not None:
        allowance = float(cfg.allowance_m)
    elif frame == "flat":
        allowance = 0.0005
    else:
        allowance = (1.3 * size) ** 2 / (12 * f_use)
    eps = cfg.k_sigma * sigma_n + allowance if cfg.epsilon_m is None else float(cfg.epsilon_m)
    return eps, allowance


def _subdivide_crowded(w: _Windowed, data: ScanData, angular_step: float,
                       cfg: PreprocessConfig) -> int:
    """Subdivide the crowded cells (near the nadir) to the common padded size; returns that
    cap (points)."""
    occ = w.occ[w.occ >= cfg.min_patch_points]
    cap = cfg.max_patch_points
    if len(occ):
        q = float(np.quantile(occ, cfg.split_quantile))
        cap = int(min(cap, max(64, _next_pow2(int(math.ceil(q))))))
        step = w.bins.grid_step(w.occ, angular_step)
        if w.bins.subdivide(w.occ, cap, step):  # only the split cells' points are re-keyed
            w.keys, w.occ = _split_keys(data.phi_rad, data.theta_rad, w.idx, w.keys, w.bins)
            w.keys, w.occ = w.bins.merge_sparse(w.keys, w.occ, cfg.min_patch_points)
    return cap


def _pack_bucket(coords, ref, order, starts, counts, ids_b, P: int, dtype) -> np.ndarray:
    """(len(ids_b), P, 3) coordinates of the patches ``ids_b`` relative to ``ref``, zero
    padded: patch ``i`` is sorted positions ``starts[i] .. starts[i] + counts[i] - 1``."""
    n_sorted = len(order)
    pad = np.empty((len(ids_b), P, 3), dtype)
    ar = np.arange(P)
    step = max(1, CHUNK // P)
    for s in range(0, len(ids_b), step):
        ib = ids_b[s:s + step]
        m = ar[None, :] < counts[ib][:, None]
        src = order[np.minimum(starts[ib][:, None] + ar[None, :], n_sorted - 1)]
        for k in range(3):
            v = coords[k][src]
            v -= ref[ib, k][:, None]
            v[~m] = 0.0
            pad[s:s + len(ib), :, k] = v
    return pad


def _fit_patch_planes(coords, order, pid, counts, starts, small, frame: str, eps: float,
                      cfg: PreprocessConfig, timing: dict[str, float]) -> _Planes:
    """RANSAC + refinement on the patches large enough, one padded size bucket at a time."""
    n_patches = len(counts)
    planes = np.full((n_patches, 4), np.nan)
    n_inl = np.zeros(n_patches, np.int64)
    rms = np.full(n_patches, np.nan)
    inlier_sorted = np.zeros(len(order), bool)
    big_ids = np.flatnonzero(~small)
    if not len(big_ids):
        return _Planes(planes, n_inl, rms, inlier_sorted)
    ref = np.stack([c[order[starts]] for c in coords], 1)  # a local origin per patch
    dt_ = np.float32 if cfg.ransac_float32 else np.float64
    bucket = _size_buckets(counts, big_ids)
    bucket[small] = -1
    for b in np.unique(bucket[big_ids]):
        ids_b = big_ids[bucket[big_ids] == b]  # increasing: their points in sorted order
        P = int(2**b)
        lens = counts[ids_b]
        t1 = time.perf_counter()
        pad = _pack_bucket(coords, ref, order, starts, counts, ids_b, P, dt_)
        t2 = time.perf_counter()
        timing["planes_packing"] = timing.get("planes_packing", 0.0) + t2 - t1
        res = fit_planes(
            pad, lens, eps, seed=cfg.seed,
            ransac_iterations=cfg.ransac_iterations, refine_iterations=cfg.refine_iterations,
            ransac_float32=cfg.ransac_float32, score_points=cfg.score_points,
            batch_size=cfg.batch_size, memory_mb=cfg.memory_mb, ids=ids_b,
        )
        del pad
        timing["planes_fit"] = timing.get("planes_fit", 0.0) + time.perf_counter() - t2
        # row-major boolean extraction walks the patches in sorted order
        inlier_sorted[bucket[pid] == b] = res["inlier"][np.arange(P)[None, :] < lens[:, None]]
        nrm = res["normal"]
        D = -(res["d"] + np.sum(nrm * (res["centroid"] + ref[ids_b]), axis=1))
        # orientation: towards the scanner (scanner frame) or towards +Z (flat frame)
        flip = (D < 0) if frame == "scanner" else (nrm[:, 2] < 0)
        sgn = np.where(flip, -1.0, 1.0)
        planes[ids_b] = np.column_stack([nrm * sgn[:, None], D * sgn])
        n_inl[ids_b] = res["n_inliers"]
        rms[ids_b] = res["rms"]
    return _Planes(planes, n_inl, rms, inlier_sorted)


def _classify(reason: np.ndarray, idx, order, pid, inlier_sorted, small, weak,
              sparse: bool) -> np.ndarray:
    """Mark RANSAC outliers and (unless the scan is sparse) the points of small or weak
    patches in ``reason``; returns the patch of every row (-1: none)."""
    patch_of = np.full(len(reason), -1, np.int32)
    for s, e in _blocks(len(order)):
        rows = idx[order[s:e]]
        p = pid[s:e]
        inl = inlier_sorted[s:e]
        patch_of[rows] = p
        reason[rows[~inl & ~small[p]]] = RANSAC_OUTLIER
        if not sparse:
            reason[rows[small[p] | (weak[p] & inl)]] = SMALL_PATCH
    return patch_of


def _removed(reason: np.ndarray, data: ScanData) -> dict[str, int]:
    """Rows removed per stage, with the rows the reader dropped (non-finite, invalid range)."""
    counts = np.bincount(reason, minlength=len(REASONS))
    removed = {REASONS[k]: int(counts[k]) for k in REASONS if k != KEPT}
    removed["non_finite"] += int(data.n_dropped_nonfinite)
    # rows the reader dropped for a range <= 0 or above the instrument maximum
    removed["invalid_range"] = int(data.n_dropped - data.n_dropped_nonfinite)
    return removed


def _patch_stats(counts: np.ndarray, small, weak, rms) -> dict[str, Any]:
    """Patch counts and sizes, and the median plane rms (m) of the fitted patches."""
    n_patches = len(counts)
    fitted = ~weak
    return {
        "n_patches": int(n_patches),
        "n_patches_fitted": int(fitted.sum()),
        "n_patches_small": int(small.sum()),
        "n_patches_weak": int((weak & ~small).sum()),
        "points_per_patch": {
            "min": int(counts.min()) if n_patches else 0,
            "median": float(np.median(counts)) if n_patches else 0.0,
            "max": int(counts.max()) if n_patches else 0,
        },
        "plane_rms_median_m": float(np.nanmedian(rms[fitted])) if fitted.any() else None,
    }
