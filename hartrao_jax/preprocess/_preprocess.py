"""Preprocessing (paper section 2.3): range window, angular patches, RANSAC planes per patch.

Stages, applied in this order to the rows of one scan; each removed row gets the code of the
first stage that removed it (:data:`REASONS`):

1. ``non_finite``: a NaN/inf observation (rows dropped while reading are counted too).
2. ``range_window``: paper eq. (3), ``D_min <= r <= D_max``. By default ``D_min``/``D_max`` are
   the smallest/largest distance from the scanner to the reflector annulus
   ``cone_radius_m <= rho <= diameter_m / 2`` of the paraboloid, plus ``range_margin_m``. The
   scanner position comes from the initial values (:func:`._init.initial_values`, i.e. the
   pointing's gravity plus a heading search on the scan, refined as in stage 3); without
   them from the nominal geometry (scanner at the focus, a wider margin).
3. ``geometry_window``: the quadrupod legs are locally planar too, so RANSAC alone cannot remove
   them. Points further than ``geometry_window_m`` (vertically, as
   :func:`._init.initial_distance`) from the paraboloid of the initial values, or outside the
   annulus ``[cone_radius_m - cone_margin_m, diameter_m / 2 + rim_margin_m]``, are removed: legs
   and cone stand decimetres to metres in front of the surface, the background and the rim's
   mixed pixels lie beyond the rim. The initial pose is first refined (:func:`refine_pose`: a
   trimmed 6-parameter Gauss-Newton on a sample inside the height window) because the initial
   values' ``tx, ty`` can be decimetres off (compensated by ``rx, ry``), which matters for the
   radius tests, not for the height window.
4. Segmentation (NumPy): the raw angles are discretised into patches of about
   ``patch_size_m`` x ``patch_size_m`` at the reflector's range: ``dtheta = s / R`` and, per
   theta band, ``dphi = s / (R sin theta)`` (so patches near the nadir are not slivers). Faces
   are keyed separately, so a patch never mixes face 1 (theta < pi) and face 2. Patches with
   more points than the power of two above the median patch (and than ``max_patch_points``),
   that is the cells near the nadir, where the scanner's constant angular steps crowd the
   points, are subdivided in theta and phi into sub-patches of at least 4 x 4 grid lines (so
   one padded size serves almost every patch, and no patch is a line); patches with fewer
   than ``min_patch_points`` are removed (``small_patch``; a sparse sub-patch joins its
   fullest sibling instead).
5. RANSAC (JAX, vmapped over all patches of a scan, chunked with ``lax.map(batch_size=...)``):
   ``ransac_iterations`` minimal samples (3 distinct points) per patch, scored by the MSAC cost
   ``sum min(d^2, eps^2)`` over up to ``score_points`` points spread over the patch, the
   best plane refined on those points (see below), then one pass over all the patch's points
   classifies them and fits the reported plane to the inliers. Points beyond ``epsilon`` from
   the refined plane are removed (paper eq. 4, ``ransac_outlier``); a patch whose plane holds
   fewer than ``min_patch_points`` inliers is removed as a whole (``small_patch``).

Planes are fitted in one of two frames (``PreprocessConfig.frame``):

* ``"flat"`` (default when initial values exist): telescope-frame coordinates of the initial
  pose with the initial paraboloid's sag removed and the height scaled to a normal distance,
  ``(X, Y, (Z - rho^2/4f) / sqrt(1 + (rho/2f)^2))``. The reflector is then locally planar to far
  below the noise whatever the patch size, so ``epsilon`` needs no curvature allowance and
  coarse scans can use large patches. A plane in this frame is "paraboloid + local tilt and
  offset"; its distances are normal distances from the reflector (to first order).
* ``"scanner"`` (the paper's choice; the fallback without initial values): planes in the
  scanner's Cartesian frame (eq. 2); ``epsilon`` then includes the curvature allowance
  ``(1.3 s)^2 / (12 f)``: the largest distance of a paraboloid patch of side ``1.3 s`` (the
  patch's extent on the surface at incidence up to ~40 deg) from its least-squares plane, with
  the principal curvatures bounded by ``1 / 2f``.

Plane refinement: the rigorous Gauss-Helmert plane adjustment in the raw observations
(condition ``n . p(r, phi, theta) - d = 0``, see :class:`PlaneCondition`) minimises
``sum (n . p_i - d)^2 / m_i`` with ``m_i = b_i Sigma_l b_i^T`` the variance of point ``i``'s
distance from the plane. Inside one patch (0.3 m seen from ~12 m: ray directions within
+-0.7 deg, ranges within +-1 %) ``m_i`` varies by ~1 %, so the GH solution is, to a small
fraction of its standard deviation, the total-least-squares plane of the inliers (smallest
eigenvector of their scatter matrix), iterated with the inlier set. That is what runs here
(iterated on the scoring points, then once on all inliers of the patch),
vmapped over thousands of patches in one compiled call. The generic GH solver
(``gauss_helmert_batch`` with :class:`PlaneCondition`) took 3.1 s per 500 patches (about a
minute per scan) against 0.02 s, and its normals differ from these by 0.05 sigma (median;
95 % below 0.16 sigma; ``benchmarks/results/preprocess.md``); the test suite checks the
agreement on one patch.

The default ``epsilon`` is ``k_sigma * sqrt(sigma_range^2 + (sigma_angle * D_max)^2)`` (an upper
bound of the standard deviation of a point's distance from the surface, whatever the incidence)
plus the allowance: ``allowance_m`` (default: 0.5 mm for panel steps and the curvature left by
the initial focal length in the ``"flat"`` frame; the curvature bound above in the
``"scanner"`` frame).

Patch size: ``patch_size_m=None`` chooses the paper's "about 30 cm^2", read as patches of
0.3 m x 0.3 m (about 5800 cells on the 26-m dish, ~7700 patches once the crowded cells near
the nadir are subdivided; 700-2000 points per patch at the paper's 0.63 mrad step, measured
at 0.77 mrad: median 1400), enlarged on coarser scans so that a typical patch holds about
``target_patch_points`` points (measured on the data, whatever the row order): 0.3 m up to
~3 mrad, ~0.6 m at 10 mrad, ~1.2 m at 20 mrad.

The per-point NumPy stages run in blocks of :data:`CHUNK` points; the survivors are sorted by
patch once, packed into padded arrays by size bucket (powers of two) and handed to
:func:`fit_planes` (the JAX core, usable on its own).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..campaign._campaign import Campaign, ScanData, ScanMeta, default_campaign, read_scan
from ._frames import default_range_window
from ._outputs import write_preprocess_result
from ._patches import _Bins, _segment
from ._stages import (
    _classify,
    _epsilon,
    _finite_rows,
    _fit_patch_planes,
    _initial_stage,
    _patch_size,
    _patch_stats,
    _plane_frame,
    _refined_pose,
    _removed,
    _sample_rows,
    _subdivide_crowded,
    _windows,
)
from ._types import (
    KEPT,
    NON_FINITE,
    SPARSE_SHARE,
    KeepMask,
    PreprocessConfig,
    PreprocessResult,
)

log = logging.getLogger("hartrao_jax")


def preprocess_scan(
    campaign: Campaign, meta: ScanMeta, data: ScanData, config: PreprocessConfig | None = None,
) -> PreprocessResult:
    """Clean one scan: range window, geometry window, patches, RANSAC planes (module doc).

    Returns a :class:`PreprocessResult` whose ``keep`` mask and ``reason`` codes run over the
    rows of ``data`` (``data.row`` gives their file rows).
    """
    cfg = config or PreprocessConfig()
    tel, sc = campaign.telescope, campaign.scanner
    t_start = time.perf_counter()
    timing: dict[str, float] = {}
    notes: list[str] = []
    n = len(data)
    r = data.range_m
    finite = _finite_rows(r, data.phi_rad, data.theta_rad)
    reason = np.where(finite, KEPT, NON_FINITE).astype(np.uint8)
    rng = np.random.default_rng(cfg.seed)  # one stream: the samples below draw in turn

    t0 = time.perf_counter()
    init = _initial_stage(campaign, meta, data, finite, rng, cfg, notes)
    timing["initial_values"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    frame = _plane_frame(cfg, init, notes)
    pose, R_ref = _refined_pose(campaign, data, finite, init, rng, cfg)
    f_use = pose["f"] if pose is not None else tel.focal_length_m
    auto_lo, auto_hi = default_range_window(campaign, pose, cfg)
    d_min = auto_lo if cfg.d_min_m is None else float(cfg.d_min_m)
    d_max = auto_hi if cfg.d_max_m is None else float(cfg.d_max_m)
    if R_ref is None:  # the reflector's typical range sets the angular size of the patches
        rows = _sample_rows(rng, n, lambda c: finite[c] & (r[c] >= d_min) & (r[c] <= d_max),
                            20000)
        R_ref = float(np.median(r[rows])) if len(rows) else float(tel.focal_length_m)
    # patch keys at the requested size or at 0.3 m (the automatic size starts from the points
    # per 0.3-m patch and is 0.3 m on fine scans)
    bins = _Bins(meta.cycle, cfg.patch_size_m or 0.30, R_ref)
    w = _windows(campaign, data, finite, reason, pose, frame, d_min, d_max, f_use, bins, cfg)
    timing["windows"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    size, typical = _patch_size(w, data, meta.cycle, R_ref, cfg)
    sigma_n = math.hypot(sc.sigma_range_m, sc.sigma_angle_rad * d_max)
    eps, allowance = _epsilon(cfg, sigma_n, frame, size, f_use)
    cap = _subdivide_crowded(w, data, sc.angular_step_rad, cfg)
    order, pid, counts, starts = _segment(w.keys, w.occ, cfg.max_patch_points)
    small = counts < cfg.min_patch_points
    timing["segmentation"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    fits = _fit_patch_planes(w.coords, order, pid, counts, starts, small, frame, eps, cfg,
                             timing)
    timing["ransac"] = time.perf_counter() - t0

    weak = fits.n_inliers < cfg.min_patch_points  # includes the small patches (0 inliers)
    # A scan too sparse for patches of this size (a random subsample of an export, say) would
    # lose most of its points as "small patches": then the patch test cannot judge them, and
    # they are kept for the fitter's robust rejection instead of being thrown away.
    sparse = bool(np.sum(counts[small]) > SPARSE_SHARE * max(int(np.sum(counts)), 1))
    patch_of = _classify(reason, w.idx, order, pid, fits.inlier_sorted, small, weak, sparse)
    keep = reason == KEPT
    params = {
        "d_min_m": d_min, "d_max_m": d_max, "d_min_auto_m": auto_lo, "d_max_auto_m": auto_hi,
        "patch_size_m": size, "typical_points_per_0.3m_patch": typical,
        "reference_range_m": R_ref, "epsilon_m": eps, "epsilon_allowance_m": allowance,
        "sigma_distance_m": sigma_n, "k_sigma": cfg.k_sigma, "frame": frame,
        "geometry_window_m": cfg.geometry_window_m if pose is not None else None,
        "rim_margin_m": cfg.rim_margin_m, "cone_margin_m": cfg.cone_margin_m,
        "ransac_iterations": cfg.ransac_iterations, "score_points": cfg.score_points,
        "refine_iterations": cfg.refine_iterations, "min_patch_points": cfg.min_patch_points,
        "max_patch_points": cfg.max_patch_points, "patch_points_cap": cap, "seed": cfg.seed,
        "initial_values": None if init is None else {
            **{k: float(v) for k, v in init.x.items()}, "kappa_rad": init.kappa_rad,
            "inlier_fraction": init.inlier_fraction},
        "pose": pose,
    }
    timing["total"] = time.perf_counter() - t_start
    stats = {
        "n_rows": n + int(data.n_dropped),
        "n_input": n,
        "n_kept": int(keep.sum()),
        "removed": _removed(reason, data),
        **_patch_stats(counts, small, weak, fits.rms),
        "timing_s": timing,
    }
    return PreprocessResult(
        scan_id=meta.id, keep=keep, reason=reason, row=np.asarray(data.row, np.int64),
        patch=patch_of, planes=fits.planes, patch_points=counts, patch_inliers=fits.n_inliers,
        patch_rms_m=fits.rms, plane_frame=frame, params=params, stats=stats, init=init,
        notes=notes,
    )


def preprocess_campaign(
    campaign: Campaign, config: PreprocessConfig | None = None, out_dir=None,
    progress: bool = True, *, scans=None, masks: bool = True,
) -> dict[str, PreprocessResult]:
    """Preprocess every scan (or those named); with ``out_dir`` write ``preprocess.json``
    (and ``masks/<scan>.parquet``) there. :func:`preprocess_table` is the summary table (the
    CLI prints it)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    cfg = config or PreprocessConfig()
    metas = [campaign.scan(s) for s in scans] if scans else list(campaign.scans)
    results: dict[str, PreprocessResult] = {}
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), disable=not progress) as prog:
        task = prog.add_task("preprocessing", total=len(metas))
        for m in metas:
            prog.update(task, description=f"preprocessing {m.id}")
            data = read_scan(campaign, m)
            results[m.id] = preprocess_scan(campaign, m, data, cfg)
            prog.advance(task)
    if out_dir is not None:
        write_preprocess_result(Path(out_dir) / "preprocess.json", results, cfg, campaign,
                                masks=masks)
    return results


def keep_mask_fn(
    config: PreprocessConfig | None = None, campaign: Campaign | None = None,
) -> Callable[[ScanMeta, ScanData], np.ndarray] | Callable[..., np.ndarray]:
    """``keep(meta, data) -> bool mask`` for ``fit_campaign(keep=...)``; the mask is a
    :class:`KeepMask` carrying the preprocessing's initial values, which the fitter reuses.

    The preprocessing needs the campaign (telescope geometry, scanner sigmas): pass it here.
    Without it the callable accepts ``keep(meta, data, campaign)`` or falls back to the HartRAO
    defaults of :func:`._campaign.default_campaign` (with a warning).
    """
    cfg = config or PreprocessConfig()

    def keep(meta: ScanMeta, data: ScanData, camp: Campaign | None = None) -> np.ndarray:
        c = camp or campaign
        if c is None:
            log.warning("keep_mask_fn: no campaign given, using the HartRAO defaults")
            c = default_campaign()
        return KeepMask.of(preprocess_scan(c, meta, data, cfg))

    return keep


def preprocess_keep(preprocess: bool = True, campaign: Campaign | None = None):
    """The default preprocessing's keep mask for ``fit_campaign(keep=...)``, or None when
    ``preprocess`` is off (the one switch the CLI, the Dask tasks and the surface share)."""
    return keep_mask_fn(PreprocessConfig(), campaign) if preprocess else None
