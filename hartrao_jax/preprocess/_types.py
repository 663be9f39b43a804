"""Configuration, result and reason codes of the preprocessing (SI units: m, rad), and the
block size of its per-point NumPy passes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._config import row_blocks
from ._initial import InitialValues

PREPROCESS_SCHEMA = "hartrao-preprocess/1"

KEPT, NON_FINITE, RANGE_WINDOW, GEOMETRY_WINDOW, RANSAC_OUTLIER, SMALL_PATCH = range(6)
SPARSE_SHARE = 0.2  # share of points in too-small patches above which a scan counts as sparse
REASONS: dict[int, str] = {
    KEPT: "kept",
    NON_FINITE: "non_finite",
    RANGE_WINDOW: "range_window",
    GEOMETRY_WINDOW: "geometry_window",
    RANSAC_OUTLIER: "ransac_outlier",
    SMALL_PATCH: "small_patch",
}
"""uint8 reason codes of :attr:`PreprocessResult.reason` (0: kept)."""

@dataclass(frozen=True)
class PreprocessConfig:
    """Parameters of the preprocessing (m, rad). ``None`` means "derive from the campaign".

    Attributes:
        d_min_m, d_max_m: range window (paper eq. 3); None: from the geometry (module doc).
        range_margin_m: margin of the automatic range window with initial values.
        nominal_range_margin_m: margin without initial values (scanner height unknown).
        patch_size_m: side of a patch at the reflector's range; None: automatic (module doc).
        target_patch_points: typical points per patch the automatic patch size aims at.
        epsilon_m: RANSAC inlier threshold (paper eq. 4); None: ``k_sigma`` sigmas + allowance.
        k_sigma: sigmas of the automatic ``epsilon``.
        allowance_m: added to the automatic ``epsilon``; None: frame-dependent (module doc).
        ransac_iterations: minimal samples (hypotheses) per patch.
        score_points: hypotheses are scored on this many points spread over the patch (all
            points when the patch is smaller) and the RANSAC plane refined on them; the
            classification (and the reported plane) use every point.
        refine_iterations: total-least-squares refinements after RANSAC.
        min_patch_points: smaller patches (and planes with fewer inliers) are removed.
        max_patch_points: hard size limit: larger patches are cut into strips of consecutive
            rows (a memory bound; the subdivision below normally keeps patches smaller).
        split_quantile: patches above the power of two covering this quantile of the patch
            sizes are subdivided: with the median, almost every patch lands in one padded
            size (one compilation, at most 2x padding).
        seed: seeds the RANSAC samples and the initial-value search: same seed, same result.
        use_initial_values: derive the windows and the "flat" frame from the initial values.
        geometry_window_m: half-width of the window about the initial paraboloid (vertical).
        rim_margin_m, cone_margin_m: tolerances of the annulus test at the rim and at the
            cone (the spec: no reflector data inside ``cone_radius_m``; the simulator puts the
            cone's hole exactly on the paraboloid there, so only the radius separates them).
        init_sample: random finite rows the initial-value search runs on.
        refine_pose: refine the initial pose (trimmed Gauss-Newton on ``pose_sample`` points
            inside the height window, :func:`refine_pose`) before the radius tests.
        frame: "flat", "scanner" or None (flat when initial values exist, else scanner).
        batch_size: patches per vmapped chunk of ``lax.map``; None: from ``memory_mb``.
        memory_mb: working set of one vmapped step (its patches' copies and scoring
            matrices). Small is fast: a cache-sized step (8 MB) ran 3x faster than 64 MB.
        ransac_float32: fit the planes in float32 (coordinates relative to the patch
            centroid, distances rounded to ~0.1 um); False: float64.
    """

    d_min_m: float | None = None
    d_max_m: float | None = None
    range_margin_m: float = 0.3
    nominal_range_margin_m: float = 2.5
    patch_size_m: float | None = None
    target_patch_points: int = 40
    epsilon_m: float | None = None
    k_sigma: float = 4.5
    allowance_m: float | None = None
    ransac_iterations: int = 64
    score_points: int = 256
    refine_iterations: int = 2
    min_patch_points: int = 10
    max_patch_points: int = 4096
    split_quantile: float = 0.5
    seed: int = 0
    use_initial_values: bool = True
    geometry_window_m: float = 0.05
    rim_margin_m: float = 0.05
    cone_margin_m: float = 0.01
    init_sample: int = 20000
    refine_pose: bool = True
    pose_sample: int = 20000
    frame: str | None = None
    batch_size: int | None = None
    memory_mb: float = 8.0
    ransac_float32: bool = True

    def __post_init__(self):
        if self.frame not in (None, "flat", "scanner"):
            raise ValueError(f"frame must be 'flat', 'scanner' or None, not {self.frame!r}")
        if self.min_patch_points < 3:
            raise ValueError("min_patch_points must be >= 3 (a plane needs 3 points)")
        if self.max_patch_points < max(self.min_patch_points, 8):
            raise ValueError("max_patch_points must be >= min_patch_points and >= 8")
        if self.ransac_iterations < 1:
            raise ValueError("ransac_iterations must be >= 1")


@dataclass
class PreprocessResult:
    """Outcome of preprocessing one scan (NumPy; SI units).

    Attributes:
        scan_id: the scan.
        keep: bool (n,) over the rows of the ``ScanData`` given (True: reflector point kept).
        reason: uint8 (n,) code of :data:`REASONS` (0 kept, else the stage that removed it).
        row: int64 (n,) original row index in the scan file (``ScanData.row``).
        patch: int32 (n,) patch index of each row (-1: not in a patch).
        planes: (n_patches, 4) ``A, B, C, D`` of each patch's plane ``A x + B y + C z + D = 0``
            (unit normal, m) in ``plane_frame``; NaN for patches that were not fitted.
        patch_points, patch_inliers: points per patch and the refined plane's inliers.
        patch_rms_m: rms distance (m) of the inliers from their plane.
        plane_frame: "flat" or "scanner" (module doc).
        params: the parameters actually used (windows, patch size, epsilon, ...).
        stats: counts per stage and timings (what ``preprocess.json`` holds per scan).
        init: the initial values the windows came from (None if not used or failed).
    """

    scan_id: str
    keep: np.ndarray
    reason: np.ndarray
    row: np.ndarray
    patch: np.ndarray
    planes: np.ndarray
    patch_points: np.ndarray
    patch_inliers: np.ndarray
    patch_rms_m: np.ndarray
    plane_frame: str
    params: dict[str, Any]
    stats: dict[str, Any]
    init: InitialValues | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def kept_rows(self) -> np.ndarray:
        """Original row indices (file rows) of the kept points."""
        return self.row[self.keep]

    def removed(self) -> dict[str, int]:
        """Rows of the given ScanData removed per stage (``non_finite`` without dropped rows)."""
        counts = np.bincount(self.reason, minlength=len(REASONS))
        return {REASONS[k]: int(counts[k]) for k in REASONS if k != KEPT}


class KeepMask(np.ndarray):
    """The keep mask of one scan (bool, like :attr:`PreprocessResult.keep`) carrying the
    preprocessing's initial values as ``init`` (or None): the fitter starts from them instead
    of searching the heading again (the same estimator on a seeded sample of the same scan).

    Anything computed from the mask (reductions, ``mask & other``) is a plain ndarray or
    scalar; only the mask itself and its views carry ``init``.
    """

    init: InitialValues | None = None

    def __array_finalize__(self, obj):
        self.init = getattr(obj, "init", None)

    def __array_wrap__(self, arr, context=None, return_scalar=False):
        arr = np.asarray(arr)
        return arr[()] if return_scalar else arr

    @classmethod
    def of(cls, result: PreprocessResult) -> KeepMask:
        m = np.asarray(result.keep, bool).view(cls)
        m.init = result.init
        return m


CHUNK = 1 << 20
"""Points per block of the per-point NumPy stages. Blocks keep every temporary below glibc's
mmap threshold (32 MiB), so its memory is reused instead of page-faulted afresh for each
operation: on the 2-core test VM a fresh 100-MB temporary cost ~0.5 s, more than the arithmetic.
"""


def _blocks(n: int, size: int = CHUNK):
    """``(start, stop)`` of the blocks of :func:`.._config.row_blocks` (of ``size`` rows)."""
    return ((rows.start, rows.stop) for rows in row_blocks(n, size))

