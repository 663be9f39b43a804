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

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..campaign._campaign import Campaign, ScanData, ScanMeta, default_campaign, read_scan
from ..campaign._safeio import OutputDir, write_file_atomic
from ..geometry._geometry import (
    pointing_gravity,
    polar_components,
    polar_to_cartesian,
    scanner_to_telescope,
)
from ._initial import InitialValues, choose_initial_values

log = logging.getLogger("hartrao_jax")

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


# --------------------------------------------------------------------------------------------
# Configuration and result
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# Geometry helpers (NumPy)
# --------------------------------------------------------------------------------------------




# --------------------------------------------------------------------------------------------
# Geometry helpers (NumPy)
# --------------------------------------------------------------------------------------------

CHUNK = 1 << 20
"""Points per block of the per-point NumPy stages. Blocks keep every temporary below glibc's
mmap threshold (32 MiB), so its memory is reused instead of page-faulted afresh for each
operation: on the 2-core test VM a fresh 100-MB temporary cost ~0.5 s, more than the arithmetic.
"""


def _blocks(n: int, size: int = CHUNK):
    for s in range(0, n, size):
        yield s, min(s + size, n)


def _rot(rx: float, ry: float) -> np.ndarray:
    """``Ry(ry) Rx(rx)`` (:func:`..geometry._geometry.scanner_to_telescope`) as NumPy."""
    return np.asarray(scanner_to_telescope(rx, ry))


def _pose(x: Mapping[str, float] | InitialValues) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, f)`` of object parameters (``tx ty tz rx ry f``): ``X = R x_s + t``."""
    x = x.x if isinstance(x, InitialValues) else x
    return _rot(x["rx"], x["ry"]), np.array([x["tx"], x["ty"], x["tz"]]), float(x["f"])


def _cartesian(r: np.ndarray, phi: np.ndarray, theta: np.ndarray):
    """Seed eq. (2) in NumPy as three arrays ``x, y, z`` (the geometry's formula)."""
    return polar_components(r, phi, theta, xp=np)


def _flat_coordinates(xs, x: Mapping[str, float]):
    """Fitted-frame ``X, Y`` and the normal distance ``h`` from the paraboloid of ``x``; ``rho``.

    ``xs`` are the scanner coordinates as three arrays. The vertical distance
    ``Z - rho^2/4f`` (as :func:`._init.initial_distance`) is scaled by
    ``1 / sqrt(1 + (rho/2f)^2)`` into a distance along the paraboloid's normal.
    Returns ``(X, Y, h), rho``.
    """
    R, t, f = _pose(x)
    a, b, c = xs
    X = R[0, 0] * a + R[0, 1] * b + R[0, 2] * c + t[0]
    Y = R[1, 0] * a + R[1, 1] * b + R[1, 2] * c + t[1]
    Z = R[2, 0] * a + R[2, 1] * b + R[2, 2] * c + t[2]
    q = X * X + Y * Y
    Z -= q * (1.0 / (4 * f))
    q *= 1.0 / (4 * f * f)
    q += 1.0
    np.sqrt(q, out=q)
    Z /= q  # normal distance
    rho = np.sqrt((q * q - 1.0) * (4 * f * f))
    return (X, Y, Z), rho


def _normal_distance(xs, p: np.ndarray) -> np.ndarray:
    x = dict(zip(("tx", "ty", "tz", "rx", "ry", "f"), p))
    return _flat_coordinates(xs, x)[0][2]


def refine_pose(xs: np.ndarray, x: Mapping[str, float], *, iterations: int = 8,
                min_tol_m: float = 0.003) -> dict[str, float]:
    """Trimmed Gauss-Newton of ``tx ty tz rx ry f`` on scanner points near the paraboloid.

    The initial values hold the rotation from the gravity vector and a heading found on a grid,
    so ``rx, ry`` can be off by 1e-2 rad, compensated by decimetres in ``tx, ty`` (the surface
    itself stays within a centimetre): good enough for a height window, not for the radius tests
    at the cone and the rim. A few Gauss-Newton steps on a sample of the points inside the
    height window, trimmed at 4 robust sigmas, fix that. NumPy, numerical Jacobian.
    ``xs``: scanner coordinates as three arrays.
    """
    p = np.array([x["tx"], x["ty"], x["tz"], x["rx"], x["ry"], x["f"]], float)
    h = np.array([1e-6, 1e-6, 1e-6, 1e-7, 1e-7, 1e-6])
    for _ in range(iterations):
        r0 = _normal_distance(xs, p)
        a = np.abs(r0)
        keep = a <= max(4 * 1.4826 * np.median(a), min_tol_m)
        if keep.sum() < 50:
            break
        xk, rk = tuple(c[keep] for c in xs), r0[keep]
        J = np.stack([(_normal_distance(xk, p + h[k] * np.eye(6)[k]) - rk) / h[k]
                      for k in range(6)], 1)
        dp, *_ = np.linalg.lstsq(J, -rk, rcond=None)
        if not np.all(np.isfinite(dp)):
            break
        p = p + dp
        if np.all(np.abs(dp[:3]) < 1e-5) and np.all(np.abs(dp[3:5]) < 1e-7):
            break
    return dict(zip(("tx", "ty", "tz", "rx", "ry", "f"), (float(v) for v in p)))


def reflector_distance_range(
    scanner_position: np.ndarray, f: float, rho_min: float, rho_max: float, offset_m: float = 0.0,
    n_rho: int = 129, n_psi: int = 720,
) -> tuple[float, float]:
    """Smallest and largest distance (m) from a point to the annulus of ``Z = rho^2 / 4f``.

    The annulus is ``rho_min <= rho <= rho_max`` about the axis (for an offset reflector,
    ``offset_m > 0``, the aperture circle centred ``offset_m`` off the axis, widened to all
    azimuths). Evaluated on a dense polar grid (the extremes lie on the boundary or at a smooth
    interior extremum; the grid error is far below any sensible margin).
    """
    if offset_m:
        rho_min, rho_max = max(0.0, offset_m - rho_max), offset_m + rho_max
    rho = np.linspace(rho_min, rho_max, n_rho)[:, None]
    psi = np.linspace(0.0, 2 * np.pi, n_psi, endpoint=False)[None, :]
    X = rho * np.cos(psi)
    Y = rho * np.sin(psi)
    Z = np.broadcast_to(rho**2 / (4 * f), X.shape)
    p = np.asarray(scanner_position, float)
    d = np.sqrt((X - p[0]) ** 2 + (Y - p[1]) ** 2 + (Z - p[2]) ** 2)
    return float(d.min()), float(d.max())


def default_range_window(
    campaign: Campaign, pose: Mapping[str, float] | InitialValues | None,
    config: PreprocessConfig | None = None,
) -> tuple[float, float]:
    """``(D_min, D_max)`` (m) from the telescope geometry and the scanner pose (module doc).

    ``pose``: initial values (or refined object parameters); None: nominal geometry, the scanner
    at the focus with ``nominal_range_margin_m``.
    """
    cfg = config or PreprocessConfig()
    tel = campaign.telescope
    if pose is not None:
        _, t, f = _pose(pose)
        margin = cfg.range_margin_m
    else:  # nominal: the scanner hangs at the sub-reflector, near the focus
        t, f = np.array([0.0, 0.0, tel.focal_length_m]), tel.focal_length_m
        margin = cfg.nominal_range_margin_m
    lo, hi = reflector_distance_range(t, f, tel.cone_radius_m, tel.diameter_m / 2, tel.offset_m)
    return max(0.0, lo - margin), hi + margin


class _Bins:
    """Angular discretisation: dense int32 patch key (face, theta band, phi bin) of a point.

    :meth:`subdivide` splits crowded cells into ``a x b`` sub-cells (theta x phi): the
    scanner's grid of constant angular steps puts ``1 / sin(theta)`` times more points per
    square metre near the nadir, so cells there hold many times the typical count.
    """

    def __init__(self, cycle: int, size_m: float, range_m: float):
        self.dth = size_m / range_m
        self.n_band = int(math.ceil(math.pi / self.dth)) + 1
        self.lo, self.span = (0.0, 2 * np.pi) if cycle == 0 else (
            (0.0, np.pi) if cycle == 1 else (np.pi, np.pi))
        centres = (np.arange(self.n_band) + 0.5) * self.dth
        # phi bins per band: patches of about size_m across, also near the nadir
        self.n_phi = np.maximum(1, np.round(self.span * range_m * np.sin(centres) / size_m)
                                ).astype(np.int64)
        self.J = int(self.n_phi.max())
        self.n_cells = 2 * self.n_band * self.J
        if self.n_cells >= 2**31:
            raise ValueError(f"patch size {size_m} m is too small for this scan")
        self.sub_a = self.sub_b = None
        self.n_sub = 1

    @property
    def n_keys(self) -> int:
        return self.n_cells * self.n_sub

    def cell_extent(self) -> tuple[np.ndarray, np.ndarray]:
        """Angular size (theta, phi; rad) of every cell."""
        band = (np.arange(self.n_cells) // self.J) % self.n_band
        return np.full(self.n_cells, self.dth), self.span / self.n_phi[band]

    def grid_step(self, occ: np.ndarray, nominal: float) -> float:
        """The scan's angular step (rad): the campaign's, or coarser if the data say so.

        A fully covered cell of ``dtheta x dphi`` holds ``dtheta dphi / step^2`` points; the
        first quartile over the cells (partly covered ones overestimate) is the estimate.
        """
        dth, dph = self.cell_extent()
        ok = occ >= 4
        if not ok.any():
            return float(nominal)
        est = float(np.quantile(np.sqrt(dth[ok] * dph[ok] / occ[ok]), 0.25))
        return max(float(nominal), est)

    def subdivide(self, occ: np.ndarray, cap: int, step: float, min_lines: int = 4) -> bool:
        """Give every cell with more than ``cap`` points ``a x b >= count / cap`` sub-cells.

        Sub-cells keep at least ``min_lines`` rows and lines of the scan's grid (``step``):
        thinner ones would be (nearly) collinear, and a plane through a line cannot reject
        points off the surface. Counts per angular cell are uniform, so are the sub-cells'.
        """
        dth, dph = self.cell_extent()
        a_max = np.maximum(1, np.floor(dth / (min_lines * step))).astype(np.int64)
        b_max = np.maximum(1, np.floor(dph / (min_lines * step))).astype(np.int64)
        m = np.maximum(1, -(-occ // cap))
        a = np.clip(np.ceil(np.sqrt(m)), 1, a_max).astype(np.int64)
        b = np.clip(-(-m // a), 1, b_max).astype(np.int64)
        a = np.clip(-(-m // b), 1, a_max).astype(np.int64)
        n_sub = int((a * b).max())
        if n_sub == 1 or self.n_cells * n_sub >= 2**31:
            return False
        self.sub_a, self.sub_b, self.n_sub = a, b, n_sub
        return True

    def keys(self, phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
        face2 = theta >= np.pi
        th0 = np.where(face2, 2 * np.pi - theta, theta)
        tb = th0 * (1.0 / self.dth)
        band = np.minimum(tb.astype(np.int64), self.n_band - 1)
        nb = self.n_phi[band]
        u = phi - self.lo
        u = np.where(u < 0, u + 2 * np.pi, u)
        tj = u * (1.0 / self.span) * nb
        j = np.minimum(tj.astype(np.int64), nb - 1)
        cell = (face2 * self.n_band + band) * self.J + j
        if self.sub_a is None:
            return cell.astype(np.int32)
        a, b = self.sub_a[cell], self.sub_b[cell]
        sa = np.clip(((tb - band) * a).astype(np.int64), 0, a - 1)
        sb = np.clip(((tj - j) * b).astype(np.int64), 0, b - 1)
        return (cell * self.n_sub + sa * b + sb).astype(np.int32)

    def merge_sparse(self, keys: np.ndarray, occ: np.ndarray, min_points: int):
        """Move the points of sub-cells with fewer than ``min_points`` (whose cell has enough)
        to the fullest sub-cell of their cell; returns the new keys and counts."""
        if self.n_sub == 1:
            return keys, occ
        o2 = occ.reshape(self.n_cells, self.n_sub)
        cell_total = o2.sum(1)
        tiny = (o2 > 0) & (o2 < min_points) & (cell_total >= min_points)[:, None]
        if not tiny.any():
            return keys, occ
        target = np.arange(self.n_cells)[:, None] * self.n_sub + np.argmax(o2, 1)[:, None]
        remap = np.arange(self.n_keys, dtype=np.int32).reshape(self.n_cells, self.n_sub)
        remap = np.where(tiny, target, remap).astype(np.int32).reshape(-1)
        out = np.empty_like(keys)
        new_occ = np.zeros(self.n_keys, np.int64)
        for s, e in _blocks(len(keys)):
            out[s:e] = remap[keys[s:e]]
            new_occ += np.bincount(out[s:e], minlength=self.n_keys)
        return out, new_occ


def _keys(phi, theta, idx, bins: _Bins) -> tuple[np.ndarray, np.ndarray]:
    """Patch keys of the points ``idx`` and the number of points per key."""
    out = np.empty(len(idx), np.int32)
    occ = np.zeros(bins.n_keys, np.int64)
    for s, e in _blocks(len(idx)):
        out[s:e] = bins.keys(phi[idx[s:e]], theta[idx[s:e]])
        occ += np.bincount(out[s:e], minlength=bins.n_keys)
    return out, occ


# --------------------------------------------------------------------------------------------
# Plane fits (JAX)
# --------------------------------------------------------------------------------------------


def _three_distinct(u: Float[Array, "h 3"], n: Array) -> Array:
    """Three distinct indices in [0, n) per row of uniforms ``u`` (n >= 3)."""
    n = n.astype(jnp.int32)
    nf = n.astype(u.dtype)
    i1 = jnp.minimum((u[:, 0] * nf).astype(jnp.int32), n - 1)
    i2 = (i1 + 1 + jnp.minimum((u[:, 1] * (nf - 1)).astype(jnp.int32), n - 2)) % n
    a, b = jnp.minimum(i1, i2), jnp.maximum(i1, i2)
    k = jnp.minimum((u[:, 2] * (nf - 2)).astype(jnp.int32), n - 3)
    k = k + (k >= a).astype(jnp.int32)
    k = k + (k >= b).astype(jnp.int32)
    return jnp.stack([i1, i2, k], axis=1)


def _adjugate_sym(M: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """Adjugate of a symmetric 3x3 matrix (``det(M) M^-1``, defined for singular ``M`` too)."""
    a, b, c = M[0, 0], M[0, 1], M[0, 2]
    d, e, f = M[1, 1], M[1, 2], M[2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    D = a * f - c * c
    E = b * c - a * e
    F = a * d - b * b
    return jnp.stack([jnp.stack([A, B, C]), jnp.stack([B, D, E]), jnp.stack([C, E, F])])


def _tls_plane(p: Float[Array, "p 3"], w: Float[Array, " p"], n0: Float[Array, "3"]):
    """Total-least-squares plane of the points with 0/1 weights ``w``: ``(n, d)``, ``n.p = d``.

    The normal is the eigenvector of the smallest eigenvalue of the scatter matrix ``M``, found
    by inverse iteration from ``n0`` (the current normal) with the adjugate of ``M`` (no
    division, exact for perfectly planar points): each step shrinks the error by
    ``lambda_min / lambda_mid`` ~ (sigma / patch size)^2 ~ 1e-5, so two steps are exact to
    round-off (a batched ``eigh`` gives the same and compiles much slower).
    """
    sw = jnp.maximum(jnp.sum(w), 1)
    pw = p * w[:, None]
    c = jnp.sum(pw, axis=0) / sw
    # raw moments (one pass over the points); p is centred near the patch's centroid, so
    # subtracting sw c c^T loses nothing that matters even in float32
    M = pw.T @ p - sw * (c[:, None] * c[None, :])
    adj = _adjugate_sym(M)
    u = adj @ (adj @ n0)
    nu = jnp.sqrt(jnp.sum(u * u))
    v = jnp.where(nu > 0, u / jnp.where(nu > 0, nu, 1.0), n0)
    v = jnp.where(v @ n0 < 0, -v, v)
    return v, v @ c


def _patch_fit(pts, n, eps, u, *, n_refine: int, f32: bool, n_score: int):
    """RANSAC (MSAC score) + TLS refinement of one padded patch.

    The hypotheses are scored, and the RANSAC plane refined (``n_refine`` TLS fits of its
    inliers), on ``n_score`` points spread over the patch; a single pass over all the patch's
    points then classifies them (``|distance| <= eps``) and fits the reported plane to the
    inliers (TLS). The refined plane is within ~0.1 mm of the all-points one at the patch edge
    (a few hundred points of 0.8-mm noise over 0.3 m), so only points within that of ``eps``
    could be classified differently; the one full pass keeps the kernel memory-light.

    Args:
        pts: (P, 3) local coordinates (first ``n`` rows valid; any origin within ~metres).
        n: number of valid points (>= 3).
        eps: inlier threshold (m).
        u: (H, 3) uniforms in [0, 1): the minimal samples of the H hypotheses.
        n_score: number of scoring points (all points if the patch is smaller).
        f32: compute in float32 (coordinates relative to the scoring points' centroid, < 1 m:
            a distance is rounded by ~0.1 um, far below the noise), else float64.
    Returns ``(inlier (P,) bool, normal (3,), d, centroid (3,), n_inliers, rms,
    ransac_inliers)``: the TLS plane of the inliers ``normal . (p - centroid) = d``, ``rms``
    the inliers' distances from the classifying plane, ``ransac_inliers`` the RANSAC plane's
    inliers among the scoring points.
    """
    P = pts.shape[0]
    n = n.astype(jnp.int32)
    valid = jnp.arange(P, dtype=jnp.int32) < n
    ct = jnp.float32 if f32 else jnp.float64
    q = pts.astype(ct)
    S = min(P, n_score)
    k = jnp.arange(S, dtype=jnp.int32)
    sub = jnp.where(n > S, (k * n) // S, k)  # spread over the patch when it is larger
    scored = sub < n
    ws = scored.astype(ct)
    qs = q[sub]
    cen = jnp.sum(qs * ws[:, None], axis=0) / jnp.sum(ws)
    qs = qs - cen[None, :]
    e = jnp.asarray(eps, ct)
    idx = _three_distinct(u, n)
    tri = q[idx] - cen[None, None, :]  # (H, 3, 3)
    nrm = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = jnp.sqrt(jnp.sum(nrm * nrm, axis=1))
    scale = jnp.max(jnp.abs(qs) * ws[:, None]) + jnp.asarray(1e-12, ct)
    ok = ln > jnp.asarray(1e-6, ct) * scale * scale
    nh = nrm / jnp.where(ok, ln, 1)[:, None]
    d = jnp.sum(nh * tri[:, 0], axis=1)
    dist = qs @ nh.T - d[None, :]  # (S, H): the one large intermediate
    cost = jnp.sum(jnp.where(scored[:, None], jnp.minimum(dist * dist, e * e), 0), axis=0)
    cost = jnp.where(ok, cost, jnp.inf)
    best = jnp.argmin(cost)
    n_ransac = jnp.sum(scored & (jnp.abs(dist[:, best]) <= e), dtype=jnp.int32)

    def refine(_, nd):  # a loop, not unrolled: one copy of the body to compile
        normal, d0 = nd
        w = (scored & (jnp.abs(qs @ normal - d0) <= e)).astype(ct)
        n_new, d_new = _tls_plane(qs, w, normal)
        enough = jnp.sum(w) >= 3
        return jnp.where(enough, n_new, normal), jnp.where(enough, d_new, d0)

    normal, d0 = nh[best], d[best]
    if n_refine:
        normal, d0 = jax.lax.fori_loop(0, n_refine, refine, (normal, d0))
    # the one pass over all points: classify, then the TLS plane of the inliers
    y = q - cen[None, :]
    r = y @ normal - d0
    inl = valid & (jnp.abs(r) <= e)
    n_in = jnp.sum(inl, dtype=jnp.int32)
    rms = jnp.sqrt(jnp.sum(jnp.where(inl, r * r, 0)) / jnp.maximum(n_in - 3, 1).astype(ct))
    n_f, d_f = _tls_plane(y, inl.astype(ct), normal)
    enough = n_in >= 3
    normal, d0 = jnp.where(enough, n_f, normal), jnp.where(enough, d_f, d0)
    f64 = jnp.float64
    return inl, normal.astype(f64), d0.astype(f64), cen.astype(f64), n_in, rms.astype(f64), n_ransac


@eqx.filter_jit
def _fit_patches(pts, n, eps, u, *, n_refine: int, f32: bool, n_score: int, batch_size: int):
    """Padded patches: ``lax.map`` over chunks of ``batch_size`` vmapped :func:`_patch_fit`."""
    return jax.lax.map(
        lambda a: _patch_fit(*a, n_refine=n_refine, f32=f32, n_score=n_score),
        (pts, n, eps, u), batch_size=batch_size)


def _next_pow2(k: int) -> int:
    return 1 << max(0, int(k - 1).bit_length())


def ransac_uniforms(seed: int, ids: np.ndarray, n_hyp: int) -> np.ndarray:
    """(len(ids), n_hyp, 3) float32 uniforms of the patches ``ids`` (row ``i`` of one stream).

    Drawn with NumPy (``default_rng(seed)``) rather than ``jax.random`` inside the compiled
    kernel: threefry under ``vmap`` took longer to compile (1.3 s) than the kernel itself.
    A patch's samples depend only on the seed and its id, not on the chunking.
    """
    ids = np.asarray(ids, np.int64)
    if len(ids) == 0:
        return np.zeros((0, n_hyp, 3), np.float32)
    U = np.random.default_rng(seed).random((int(ids.max()) + 1, n_hyp, 3), dtype=np.float32)
    return U[ids]


def fit_planes(
    pts: np.ndarray, n: np.ndarray, eps: np.ndarray | float, *, seed: int = 0,
    ransac_iterations: int = 64, refine_iterations: int = 2, ransac_float32: bool = True,
    score_points: int = 256, batch_size: int | None = None, memory_mb: float = 8.0,
    ids: np.ndarray | None = None, max_chunk: int = 1024,
) -> dict[str, np.ndarray]:
    """RANSAC + TLS planes of padded patches (the JAX core, usable on its own).

    Args:
        pts: (n_patches, P, 3) coordinates; the first ``n[i]`` rows of patch ``i`` are valid.
            Any origin within a few metres of the patch (float32 keeps ~0.1 um there).
        n: (n_patches,) valid points per patch (patches with ``n < 3`` give no plane).
        eps: inlier threshold (m), scalar or per patch.
        ids: integer id per patch for its random samples (default ``arange``): the result of a
            patch does not depend on the chunking or on the other patches.
        score_points: points (spread over the patch) that score the hypotheses.
        batch_size: patches per vmapped step of ``lax.map``; None: as many as fit in
            ``memory_mb`` (the patches' working copies and scoring matrices).
        max_chunk: patches per compiled call; calls use power-of-two patch counts up to this,
            so the same few shapes (and compilations) serve every scan.
    Returns a dict of NumPy arrays: ``inlier`` (n_patches, P) bool, ``normal`` (n_patches, 3),
    ``d`` and ``centroid`` (plane ``normal . (p - centroid) = d``, in the coordinates of
    ``pts``), ``n_inliers``, ``rms`` (m), ``ransac_inliers``.
    """
    pts = np.asarray(pts)
    n_p, P = pts.shape[0], pts.shape[1]
    H = int(ransac_iterations)
    S = int(min(P, score_points))
    n = np.asarray(n, np.int64)
    eps = np.broadcast_to(np.asarray(eps, np.float64), (n_p,))
    ids = np.arange(n_p) if ids is None else np.asarray(ids, np.int64)
    if batch_size is None:
        per_patch = P * 3 * 8 * 4 + S * H * (4 if ransac_float32 else 8) * 3
        batch_size = int(max(1, min(1024, memory_mb * 2**20 // per_patch)))
    batch_size = 1 << (int(batch_size).bit_length() - 1)  # power of two: stable shapes
    good = n >= 3
    n_run = np.where(good, np.minimum(n, P), 3).astype(np.int32)  # dummies: 3-point fits
    U = ransac_uniforms(seed, ids, H)
    dt_pts = np.float32 if ransac_float32 else np.float64
    fit = int(max(1, 64 * 2**20 // (P * 3 * 8)))  # patches per call: inputs below 64 MB
    per_call = max(batch_size, _next_pow2(fit + 1) // 2)
    n_call = int(min(max_chunk, per_call, _next_pow2(max(n_p, 1))))
    bs = int(min(batch_size, n_call))
    outs = []
    for s in range(0, n_p, n_call):
        e = min(s + n_call, n_p)
        k = n_call - (e - s)

        def sl(a, fill, s=s, e=e, k=k):
            return a[s:e] if not k else np.concatenate(
                [a[s:e], np.full((k,) + a.shape[1:], fill, a.dtype)])

        out = _fit_patches(
            jnp.asarray(sl(pts, 0), dt_pts), jnp.asarray(sl(n_run, 3)),
            jnp.asarray(sl(eps, 1.0), jnp.float64), jnp.asarray(sl(U, 0.5)),
            n_refine=int(refine_iterations), f32=bool(ransac_float32), n_score=S, batch_size=bs,
        )
        outs.append([np.asarray(a)[: e - s] for a in out])
    if not outs:
        z = np.zeros(0)
        return {"inlier": np.zeros((0, P), bool), "normal": np.zeros((0, 3)), "d": z,
                "centroid": np.zeros((0, 3)), "n_inliers": z.astype(np.int32), "rms": z,
                "ransac_inliers": z.astype(np.int32)}
    inl, normal, d, cen, n_in, rms, n_r = (np.concatenate(c) for c in zip(*outs))
    normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)  # exactly unit in float64
    inl = inl & good[:, None]
    return {"inlier": inl, "normal": np.where(good[:, None], normal, np.nan),
            "d": np.where(good, d, np.nan), "centroid": cen,
            "n_inliers": np.where(good, n_in, 0), "rms": np.where(good, rms, np.nan),
            "ransac_inliers": np.where(good, n_r, 0)}


class PlaneCondition(eqx.Module):
    """Gauss-Helmert condition of a plane in raw observations (for :func:`._ghm.gauss_helmert`).

    ``F(l, x) = n(x) . p(l) - x[2]`` with ``p`` the scanner Cartesian point of ``l = (r, phi,
    theta)`` (eq. 2) and ``n(x) = R0 (x0, x1, 1) / |(x0, x1, 1)|``: ``R0`` rotates z onto a
    starting normal so the parameterisation is regular near the solution. Unknowns
    ``x = (x0, x1, d)`` (-, -, m). Used to check the vmapped refinement against the rigorous
    adjustment; too slow per patch for thousands of patches (module doc).
    """

    R0: Float[Array, "3 3"]

    @staticmethod
    def around(normal) -> PlaneCondition:
        """Condition whose ``x = (0, 0, d)`` is the plane with this normal."""
        z = np.asarray(normal, float) / np.linalg.norm(normal)
        a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(a, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return PlaneCondition(jnp.asarray(np.stack([x, y, z], axis=1)))

    def normal(self, x):
        v = jnp.stack([x[0], x[1], jnp.ones_like(x[0])])
        return self.R0 @ (v / jnp.sqrt(jnp.sum(v * v)))

    def __call__(self, l, x, c):
        return self.normal(x) @ polar_to_cartesian(l[0], l[1], l[2]) - x[2]


# --------------------------------------------------------------------------------------------
# One scan
# --------------------------------------------------------------------------------------------


def _size_buckets(counts: np.ndarray, ids: np.ndarray, min_share: float = 0.2) -> np.ndarray:
    """log2 of the padded size of each patch: powers of two from 32, sparse buckets merged up.

    Each bucket is one compiled shape; a bucket holding fewer than ``min_share`` of the patches
    (at least 16) joins the next larger one, so a scan needs one to three compilations while
    padding stays below ~2x for almost all patches.
    """
    b = np.maximum(5, np.ceil(np.log2(np.maximum(counts, 1))).astype(np.int64))
    if len(ids) == 0:
        return b
    levels = np.unique(b[ids])
    thresh = max(16, min_share * len(ids))
    for lo, hi in zip(levels[:-1], levels[1:]):
        sel = b == lo
        if np.count_nonzero(sel[ids]) < thresh:
            b[sel] = hi
    return b


def _segment(keys: np.ndarray, occ: np.ndarray, max_pp: int):
    """Sort points by patch; cut patches still larger than ``max_pp`` (a memory bound; after
    :meth:`_Bins.subdivide` a rare case) into strips of consecutive rows.

    ``occ``: points per dense key (``bincount(keys)``).

    Returns ``(order, pid, counts, starts)``: ``order`` indexes the input points in patch
    order (stable: file order inside a patch), ``pid`` (int32) the compact patch id of each
    sorted point, ``counts``/``starts`` per patch.
    """
    remap = (np.cumsum(occ > 0) - 1).astype(np.int32)  # dense key -> compact patch id
    order = np.argsort(keys, kind="stable")
    counts = occ[occ > 0]
    pid = np.empty(len(keys), np.int32)
    for s, e in _blocks(len(keys)):
        pid[s:e] = remap[keys[order[s:e]]]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    nsub = -(-counts // max_pp)
    if np.any(nsub > 1):
        base = np.concatenate([[0], np.cumsum(nsub)[:-1]])
        for s, e in _blocks(len(keys)):
            p = pid[s:e].astype(np.int64)
            rank = np.arange(s, e) - starts[p]
            pid[s:e] = base[p] + rank * nsub[p] // counts[p]
        counts = np.bincount(pid, minlength=int(nsub.sum()))
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    return order, pid, counts, starts


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
    r, phi, th = data.range_m, data.phi_rad, data.theta_rad
    reason = np.zeros(n, np.uint8)
    finite = np.empty(n, bool)
    for s, e in _blocks(n):
        finite[s:e] = np.isfinite(r[s:e]) & np.isfinite(phi[s:e]) & np.isfinite(th[s:e])
    reason[~finite] = NON_FINITE
    rng = np.random.default_rng(cfg.seed)

    def sample_rows(mask_fn, size):
        """Up to ``size`` random rows (seeded) for which ``mask_fn(rows)`` holds."""
        m = min(n, 4 * size)
        cand = np.sort(rng.choice(n, size=m, replace=False)) if m < n else np.arange(n)
        return cand[mask_fn(cand)][:size]

    # ---- initial values (pointing + heading search), on a sample
    t0 = time.perf_counter()
    init = None
    if cfg.use_initial_values and finite.sum() >= 100:
        g = pointing_gravity(meta, tel, campaign.site)
        rows = sample_rows(lambda c: finite[c], cfg.init_sample)
        try:
            iv = choose_initial_values(campaign, meta, data.subset(rows), g, seed=cfg.seed)
            if (all(np.isfinite(v) for v in iv.x.values()) and iv.x["f"] > 0
                    and iv.inlier_fraction >= 0.2):
                init = iv
            else:
                notes.append(f"initial values rejected (inlier fraction {iv.inlier_fraction:.2f})"
                             "; nominal geometry used")
        except (np.linalg.LinAlgError, ValueError) as e:  # pragma: no cover - defensive
            notes.append(f"initial values failed ({e}); nominal geometry used")
    timing["initial_values"] = time.perf_counter() - t0

    # ---- pose refinement on a sample inside a generous range window
    t0 = time.perf_counter()
    frame = cfg.frame or ("flat" if init is not None else "scanner")
    if frame == "flat" and init is None:
        notes.append("frame 'flat' needs initial values: using 'scanner'")
        frame = "scanner"
    pose, R_ref = None, None
    if init is not None:
        pose = dict(init.x)
        if cfg.refine_pose:
            lo, hi = default_range_window(campaign, pose, dataclasses.replace(
                cfg, range_margin_m=cfg.range_margin_m + 0.5))
            rows = sample_rows(lambda c: finite[c] & (r[c] >= lo) & (r[c] <= hi),
                               4 * cfg.pose_sample)
            xs = _cartesian(r[rows], phi[rows], th[rows])
            near = np.flatnonzero(np.abs(_flat_coordinates(xs, pose)[0][2])
                                  <= cfg.geometry_window_m)[: cfg.pose_sample]
            if len(near) >= 100:
                pose = refine_pose(tuple(c[near] for c in xs), pose)
                R_ref = float(np.median(r[rows[near]]))
    f_use = pose["f"] if pose is not None else tel.focal_length_m

    # ---- range window (eq. 3), from the (refined) pose
    auto_lo, auto_hi = default_range_window(campaign, pose, cfg)
    d_min = auto_lo if cfg.d_min_m is None else float(cfg.d_min_m)
    d_max = auto_hi if cfg.d_max_m is None else float(cfg.d_max_m)
    if R_ref is None:  # the reflector's typical range sets the angular size of the patches
        rows = sample_rows(lambda c: finite[c] & (r[c] >= d_min) & (r[c] <= d_max), 20000)
        R_ref = float(np.median(r[rows])) if len(rows) else float(tel.focal_length_m)

    # ---- range and geometry windows, block by block; survivors' coordinates for the planes
    rim = tel.diameter_m / 2 + abs(tel.offset_m)
    inner = tel.cone_radius_m - cfg.cone_margin_m if tel.offset_m == 0 else -np.inf
    # patch keys computed here for the survivors, at the requested size or at 0.3 m (the
    # automatic size starts from the points per 0.3-m patch and is 0.3 m on fine scans)
    bins = _Bins(meta.cycle, cfg.patch_size_m or 0.30, R_ref)
    occ_all = np.zeros(bins.n_keys, np.int64)
    idx_parts, coord_parts, key_parts = [], [], []
    for s, e in _blocks(n):
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
        occ_all += np.bincount(key_parts[-1], minlength=bins.n_keys)
    idx = np.concatenate(idx_parts) if idx_parts else np.zeros(0, np.int64)
    coords = [np.concatenate([c[k] for c in coord_parts]) if coord_parts else np.zeros(0)
              for k in range(3)]
    keys = np.concatenate(key_parts) if key_parts else np.zeros(0, np.int32)
    del idx_parts, coord_parts, key_parts
    timing["windows"] = time.perf_counter() - t0

    # ---- patches
    t0 = time.perf_counter()
    typical = None
    if cfg.patch_size_m is None:
        occ0 = occ_all[occ_all > 0]
        typical = float(np.median(occ0)) if len(occ0) else 0.0
        size = 0.30 * (max(1.0, math.sqrt(cfg.target_patch_points / typical)) if typical else 1)
        if size > 0.30:  # a coarse scan: larger patches
            bins = _Bins(meta.cycle, size, R_ref)
            keys, occ_all = _keys(phi, th, idx, bins)
    else:
        size = float(cfg.patch_size_m)
    sigma_n = math.hypot(sc.sigma_range_m, sc.sigma_angle_rad * d_max)
    if cfg.allowance_m is not None:
        allowance = float(cfg.allowance_m)
    elif frame == "flat":
        allowance = 0.0005
    else:
        allowance = (1.3 * size) ** 2 / (12 * f_use)
    eps = cfg.k_sigma * sigma_n + allowance if cfg.epsilon_m is None else float(cfg.epsilon_m)

    occ = occ_all[occ_all >= cfg.min_patch_points]
    cap = cfg.max_patch_points
    if len(occ):  # crowded cells (near the nadir) are subdivided to the common size
        q = float(np.quantile(occ, cfg.split_quantile))
        cap = int(min(cap, max(64, _next_pow2(int(math.ceil(q))))))
        step = bins.grid_step(occ_all, sc.angular_step_rad)
        if bins.subdivide(occ_all, cap, step):
            keys, occ_all = _keys(phi, th, idx, bins)
            keys, occ_all = bins.merge_sparse(keys, occ_all, cfg.min_patch_points)
    order, pid, counts, starts = _segment(keys, occ_all, cfg.max_patch_points)
    del keys
    n_patches = len(counts)
    patch_of = np.full(n, -1, np.int32)
    small = counts < cfg.min_patch_points
    big_ids = np.flatnonzero(~small)
    timing["segmentation"] = time.perf_counter() - t0

    # ---- RANSAC + refinement on the patches large enough, one size bucket at a time
    t0 = time.perf_counter()
    planes = np.full((n_patches, 4), np.nan)
    n_inl = np.zeros(n_patches, np.int64)
    rms = np.full(n_patches, np.nan)
    inlier_sorted = np.zeros(len(order), bool)
    if len(big_ids):
        first = order[starts]
        ref = np.stack([c[first] for c in coords], 1)  # a local origin per patch: its 1st point
        dt_ = np.float32 if cfg.ransac_float32 else np.float64
        bucket = _size_buckets(counts, big_ids)
        bucket[small] = -1
        n_sorted = len(order)
        for b in np.unique(bucket[big_ids]):
            ids_b = big_ids[bucket[big_ids] == b]  # increasing: their points in sorted order
            P = int(2**b)
            lens = counts[ids_b]
            t1 = time.perf_counter()
            # gathers, not scatters: patch i of the bucket is sorted positions
            # starts[i] .. starts[i] + lens[i] - 1, padded with zeros to P
            pad = np.empty((len(ids_b), P, 3), dt_)
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
            t2 = time.perf_counter()
            timing["planes_packing"] = timing.get("planes_packing", 0.0) + t2 - t1
            res = fit_planes(
                pad, lens, eps, seed=cfg.seed,
                ransac_iterations=cfg.ransac_iterations, refine_iterations=cfg.refine_iterations,
                ransac_float32=cfg.ransac_float32, score_points=cfg.score_points,
                batch_size=cfg.batch_size, memory_mb=cfg.memory_mb, ids=ids_b,
            )
            del pad
            t1 = time.perf_counter()
            timing["planes_fit"] = timing.get("planes_fit", 0.0) + t1 - t2
            # row-major boolean extraction walks the patches in sorted order
            inlier_sorted[bucket[pid] == b] = res["inlier"][ar[None, :] < lens[:, None]]
            nrm = res["normal"]
            D = -(res["d"] + np.sum(nrm * (res["centroid"] + ref[ids_b]), axis=1))
            # orientation: towards the scanner (scanner frame) or towards +Z (flat frame)
            flip = (D < 0) if frame == "scanner" else (nrm[:, 2] < 0)
            sgn = np.where(flip, -1.0, 1.0)
            planes[ids_b] = np.column_stack([nrm * sgn[:, None], D * sgn])
            n_inl[ids_b] = res["n_inliers"]
            rms[ids_b] = res["rms"]
    timing["ransac"] = time.perf_counter() - t0

    weak = n_inl < cfg.min_patch_points  # includes the small patches (0 inliers)
    # A scan too sparse for patches of this size (a random subsample of an export, say) would
    # lose most of its points as "small patches": then the patch test cannot judge them, and
    # they are kept for the fitter's robust rejection instead of being thrown away.
    sparse = bool(np.sum(counts[small]) > SPARSE_SHARE * max(int(np.sum(counts)), 1))
    for s, e in _blocks(len(order)):
        rows = idx[order[s:e]]
        p = pid[s:e]
        inl = inlier_sorted[s:e]
        patch_of[rows] = p
        reason[rows[~inl & ~small[p]]] = RANSAC_OUTLIER
        if not sparse:
            reason[rows[small[p] | (weak[p] & inl)]] = SMALL_PATCH
    keep = reason == KEPT

    counts_reason = np.bincount(reason, minlength=len(REASONS))
    removed = {REASONS[k]: int(counts_reason[k]) for k in REASONS if k != KEPT}
    removed["non_finite"] += int(data.n_dropped_nonfinite)
    # rows the reader dropped for a range <= 0 or above the instrument maximum
    removed["invalid_range"] = int(data.n_dropped - data.n_dropped_nonfinite)
    fitted = ~weak
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
        "removed": removed,
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
        "timing_s": timing,
    }
    return PreprocessResult(
        scan_id=meta.id, keep=keep, reason=reason, row=np.asarray(data.row, np.int64),
        patch=patch_of, planes=planes, patch_points=counts, patch_inliers=n_inl,
        patch_rms_m=rms, plane_frame=frame, params=params, stats=stats, init=init, notes=notes,
    )


# --------------------------------------------------------------------------------------------
# Campaigns, outputs
# --------------------------------------------------------------------------------------------


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    return v


def preprocess_json(results: Mapping[str, PreprocessResult],
                    config: PreprocessConfig | None = None,
                    campaign: Campaign | None = None) -> dict:
    """The ``preprocess.json`` document (schema ``hartrao-preprocess/1``)."""
    scans = []
    tot = {"n_rows": 0, "n_kept": 0, "removed": {REASONS[k]: 0 for k in REASONS if k != KEPT}}
    for sid, res in results.items():
        s = res.stats
        scans.append({
            "id": sid, "n_rows": s["n_rows"], "n_kept": s["n_kept"],
            "kept_fraction": s["n_kept"] / max(s["n_rows"], 1), "removed": s["removed"],
            "n_patches": s["n_patches"], "n_patches_fitted": s["n_patches_fitted"],
            "n_patches_small": s["n_patches_small"], "points_per_patch": s["points_per_patch"],
            "plane_rms_median_m": s["plane_rms_median_m"], "params": res.params,
            "timing_s": s["timing_s"], "notes": res.notes,
        })
        tot["n_rows"] += s["n_rows"]
        tot["n_kept"] += s["n_kept"]
        for k, v in s["removed"].items():
            tot["removed"][k] = tot["removed"].get(k, 0) + v  # stages and reading drops
    doc = {
        "schema": PREPROCESS_SCHEMA,
        "reasons": {str(k): v for k, v in REASONS.items()},
        "config": dataclasses.asdict(config) if config is not None else None,
        "scans": scans,
        "totals": tot,
    }
    if campaign is not None:
        doc["campaign"] = str(campaign.root)
    return _jsonable(doc)


def write_preprocess_json(path, results: Mapping[str, PreprocessResult],
                          config: PreprocessConfig | None = None,
                          campaign: Campaign | None = None) -> Path:
    """Write ``preprocess.json`` (schema ``hartrao-preprocess/1``) to ``path`` (file or dir):
    strict JSON, atomically, with an empty ``"files"`` manifest (see
    :func:`write_preprocess_result` for the JSON with its masks)."""
    return write_preprocess_result(path, results, config, campaign, masks=False)


def write_preprocess_result(path, results: Mapping[str, PreprocessResult],
                            config: PreprocessConfig | None = None,
                            campaign: Campaign | None = None, *, masks: bool = True) -> Path:
    """``masks/<scan>.parquet`` and ``preprocess.json`` crash-safely (:class:`._safeio.OutputDir`:
    masks under temporary names first, the JSON last, listing them). ``path``: the directory
    or the JSON file's path. Returns the JSON's path."""
    import pyarrow as pa


    p = Path(path)
    if p.is_dir() or p.suffix == "":
        p = p / "preprocess.json"
    with OutputDir(p.parent, p.name) as od:
        for sid, res in (results.items() if masks else ()):
            od.write_parquet(f"masks/{sid}.parquet", pa.table(
                {"row": res.row, "reason": res.reason, "patch": res.patch}))
        return od.commit(preprocess_json(results, config, campaign), indent=2)


def write_masks(out_dir, results: Mapping[str, PreprocessResult]) -> Path:
    """``out_dir/masks/<scan>.parquet``: ``row`` (file row), ``reason`` (uint8), ``patch``
    (each written to a temporary name and renamed)."""
    import pyarrow as pa
    import pyarrow.parquet as pq


    d = Path(out_dir) / "masks"
    for sid, res in results.items():
        table = pa.table({"row": res.row, "reason": res.reason, "patch": res.patch})
        write_file_atomic(d / f"{sid}.parquet", lambda t, tb=table: pq.write_table(tb, t),
                          durable=False)
    return d


def preprocess_table(results: Mapping[str, PreprocessResult], title: str = "preprocessing"):
    """A rich table: per scan, rows, kept and removed per stage, patches, epsilon, time."""
    from rich.table import Table

    t = Table(title=title)
    for c in ("scan", "rows", "kept", "non-finite", "range", "geometry", "RANSAC", "small patch",
              "patches", "eps mm", "time s"):
        t.add_column(c, justify="left" if c == "scan" else "right")
    for sid, res in results.items():
        s, rm = res.stats, res.stats["removed"]
        kept = f"{s['n_kept']:,} ({s['n_kept'] / max(s['n_rows'], 1):.1%})"
        t.add_row(sid, f"{s['n_rows']:,}", kept,
                  f"{rm['non_finite']:,}", f"{rm['range_window']:,}", f"{rm['geometry_window']:,}",
                  f"{rm['ransac_outlier']:,}", f"{rm['small_patch']:,}",
                  f"{s['n_patches_fitted']:,}/{s['n_patches']:,}",
                  f"{1e3 * res.params['epsilon_m']:.2f}", f"{s['timing_s']['total']:.1f}")
    return t


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
    """``keep(meta, data) -> bool mask`` for ``fit_campaign(keep=...)``.

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
        return preprocess_scan(c, meta, data, cfg).keep

    return keep


__all__ = [
    "PREPROCESS_SCHEMA", "REASONS", "PlaneCondition", "PreprocessConfig", "PreprocessResult",
    "default_range_window", "fit_planes", "keep_mask_fn", "preprocess_campaign",
    "preprocess_json", "preprocess_scan", "preprocess_table", "reflector_distance_range",
    "write_masks", "write_preprocess_json", "write_preprocess_result",
]


def preprocess_keep(preprocess: bool = True, campaign: Campaign | None = None):
    """The default preprocessing's keep mask for ``fit_campaign(keep=...)``, or None when
    ``preprocess`` is off (the one switch the CLI, the Dask tasks and the surface share)."""
    return keep_mask_fn(PreprocessConfig(), campaign) if preprocess else None
