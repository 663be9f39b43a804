"""Search of the residual surface for a local deformation, judged against the reflector's own
roughness (the ``local_deformation`` search of ``hartrao-jax diagnose``).

Matched filter
--------------
For every width ``w`` of :data:`WIDTHS_M` and every centre ``c`` of a grid of the aperture
plane (cells of ``w / 4``), the residual normal deviations ``r_i`` of the points near ``c`` are
fitted by ``a g_i + b`` with ``g_i = exp(-|p_i - c|^2 / 2 w^2)`` (the catalog's
:func:`~hartrao_jax.physics.local_deformation` of unit amplitude) and a local constant ``b``,
by least squares weighted with a broad Gaussian window of ``3 w``: a smooth misfit of the whole
surface does not count, only what is compact at the scale ``w``. All sums are Gaussian
convolutions of the binned counts and residuals, so one width costs a few image filters.
``z = a / se_white(a)`` is the white-noise score of the amplitude.

Panels: the offsets free, the tilts a random effect
----------------------------------------------------
On a reflector of known panel layout the panels are the dominant structure at the scale of a
bump, and a local constant does not model them: a panel's offset steps at its edges, its tilt
ramps across it. There (``groups``: the points' panel ids) the filter fits ``a g_i`` with the
panels as nuisance instead of the windowed constant: per panel an offset (free) and two tilts
along the aperture axes (a random effect of variance ``tau^2``, estimated from the moments of
the per-panel plane fits beyond the noise, :func:`tilt_variance`). This is the generalised
least squares of ``a`` under the covariance ``sigma^2 I + Z tau^2 Z^T``: by Woodbury, per
centre, ``a = (sum g r - sum_p G_p^T K_p^-1 u_p) / (sum g^2 - sum_p G_p^T K_p^-1 G_p)`` with
``G_p = sum_{i in p} g_i P_i``, ``u_p = sum_{i in p} r_i P_i``, ``P_i = (1, x_i - x_p, y_i -
y_p)`` and ``K_p = sum P P^T + diag(0, sigma^2/tau^2, sigma^2/tau^2)``; the denominator is
``1 / var(a)`` in units of ``sigma^2``. The panel that holds a bump cannot absorb it into its
offset (the amplitude is estimated from the bump's shape within the panels, whatever their
offsets), and the tilts' ramps no longer count as roughness. Free tilts (fixed effects) would
take most of a bump narrower than a panel with them; no tilts leave their ramps in the null
(roughness 1.2-1.5 on simulated 0.15 mm panels, against 1.0-1.1 with them as a random effect).
Centres where the bump's within-panel part carries less than :data:`MIN_WITHIN_PANEL` of its
``sum g^2`` are not searched (a bump as wide as the panels is their offsets). A regular grid
of cells on a reflector without a layout is no physical structure: there the windowed local
constant stays.

The null: a calibrated maximum from the same reflector
-----------------------------------------------------
On a real reflector the residuals are not white: panel offsets and tilts, gaps and scanner
columns make them correlated over 0.1-2 m, and ``z`` is inflated everywhere (a permutation of
the points, or a shift of the residuals against the positions, destroys that correlation and
declares everything significant). The question is whether the strongest candidate stands out
from what *this* surface produces anywhere else. So:

1. each width's ``z`` map is divided by its own robust spread over all valid centres
   (``1.4826 MAD``): the *roughness factor* ``s_w`` (1 for white noise, 2-5 on real panels)
   carries the correlated structure at that scale into the statistic ``t = z / s_w``. A
   width whose valid centres cover fewer than :data:`MIN_PLACEMENTS` discs of radius ``w``
   is skipped (listed): its spread would come from one or two placements (on a 1.5 m strip a
   1 m wide bump fills the map and its own ``s_w``), and such maps gave the largest,
   meaningless peaks;
2. the local maxima of ``|t|`` (one per neighbourhood of radius ``w``) over the whole surface
   are the placements the reflector offers; their heights, pooled over the widths and without
   the candidate's own neighbourhood, give the null distribution of one placement's peak, whose
   upper tail is fitted by an exponential above its 80th percentile (the median with fewer
   than 100 peaks; heavier than the Gaussian tail of a smooth random field: conservative);
3. the candidate's p-value is that of the *maximum* of the ``N`` peaks:
   ``p = 1 - (1 - P_tail(t))^N``.

This is the distribution of the matched-filter maximum over the placements of the residual
field itself: whatever structure the surface has (panel gaps, notches, column stripes, edge
effects) produces peaks of the same kind in the null, so a candidate is significant only when
it exceeds the largest peaks the reflector's roughness produces elsewhere. Too few peaks for a
tail (a small patch) and the search reports the candidate without a significance.

A candidate that does not stand out is reported as the largest local structure, with its
size, as "not distinguishable from the reflector's panel-scale roughness". An accepted one is
modelled by the ``bump_*`` parameters of the model and refitted by the diagnosis.

Which points: what the robust fit rejected but the surface confirms
-------------------------------------------------------------------
The robust fit drops every point whose residual exceeds ``k`` a-posteriori sigmas (about 3 mm
on the GBT recordings), so without help the search would see only the rim of any structure
deeper than that: the deformation it is meant to find hidden by the fit. A rejected point is
given back to the search (:func:`coherent`) when it agrees with its own neighbourhood: when
its residual lies within its rejection limit of the *median residual of its neighbours*
(:func:`local_level`; all points of the window within :data:`COHERENCE_RADIUS_M`, the
smallest search width, or the :data:`COHERENCE_NEIGHBOURS` nearest when fewer lie there, up
to :data:`COHERENCE_MAX_RADIUS_M`; rejected ones included, the point itself not). That is the
fit's own test, ``|r_i - level| <= limit_i``, made against the local surface instead of the
global model: an isolated outlier (a mixed pixel, a return from the feed arm among surface
points) departs from a neighbourhood that sits near zero and stays out; the core of a
deformation sits among neighbours that deviate with it and comes back. A structure narrower
than the neighbourhood (a panel gap one or two centimetres wide) does not move the median and
stays out too. The null is computed from the same point set (the search is run once, on it),
so the reflector's own deep structures enter the null with their cores as well.

NumPy/SciPy on grids; units metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .._config import each_in_threads, usable_cores
from ..geometry._geometry import cell_code, column_bounds, grid_indices, grid_sum

WIDTHS_M: tuple[float, ...] = (0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
BACKGROUND = 3.0  # background window (Gaussian sigma) in units of the width
TAIL_QUANTILE = 0.8  # 0.5 when there are fewer than 100 peaks (a strip, a small patch)
MIN_PEAKS = 16  # fewer peaks: no calibrated significance
MIN_PLACEMENTS = 12.0  # valid area of a width in discs of radius w: fewer, the width is skipped
MIN_WITHIN_PANEL = 0.1  # panel nuisance: the bump's within-panel share of sum g^2, at least
COHERENCE_RADIUS_M = 0.3  # neighbourhood of a rejected point (m): the smallest search width
COHERENCE_NEIGHBOURS = 6  # at least this many neighbours (nearest ones where the data are sparse)
COHERENCE_MAX_RADIUS_M = 1.0  # ... but none farther than this (m)
NOT_DISTINGUISHABLE = "not distinguishable from the reflector's panel-scale roughness"


@dataclass
class WidthMap:
    """The matched-filter maps of one width (grid of ``cell`` m from ``origin``)."""

    width_m: float
    cell_m: float
    origin: np.ndarray
    amplitude: np.ndarray  # a (m)
    z: np.ndarray  # white score
    t: np.ndarray  # z / roughness factor (0 where invalid)
    valid: np.ndarray
    roughness: float  # s_w
    peaks: np.ndarray  # (k, 2) grid indices of the local maxima of |t|

    def centre(self, ij) -> np.ndarray:
        return self.origin + (np.asarray(ij, float) + 0.5) * self.cell_m


@dataclass
class Candidate:
    """The strongest local structure and its significance against the reflector's own peaks."""

    x_m: float
    y_m: float
    amplitude_m: float
    width_m: float
    t: float  # roughness-standardised score
    z_white: float
    roughness: float  # s_w at its width
    p_value: float | None  # of the maximum over the reflector's placements (None: no null)
    n_peaks: int
    tail: dict = field(default_factory=dict)
    significant: bool = False
    note: str = ""

    def to_json(self) -> dict:
        return {"x_m": self.x_m, "y_m": self.y_m, "amplitude_m": self.amplitude_m,
                "width_m": self.width_m, "t": self.t, "z_white": self.z_white,
                "roughness_factor": self.roughness, "p_value": self.p_value,
                "n_peaks": self.n_peaks, "tail": self.tail, "significant": self.significant,
                "note": self.note}


@dataclass
class Search:
    maps: list[WidthMap]
    candidate: Candidate | None
    sigma_m: float
    skipped_widths: list[float]


def _gauss(a: np.ndarray, s_cells: float, lead: int = 0) -> np.ndarray:
    """Unnormalised Gaussian convolution ``sum_k a_k exp(-d^2 / 2 s^2)`` (d in cells) over the
    grid's two axes, the ones after the first ``lead`` (a stack of grids: not filtered)."""
    sig = [0.0] * lead + [s_cells, s_cells] + [0.0] * (a.ndim - lead - 2)
    return ndimage.gaussian_filter(a, sig, mode="constant", truncate=4.0) * (
        2 * math.pi * s_cells * s_cells)


def _density(xy: np.ndarray) -> float:
    """Median point density (1/m^2) over occupied cells of about 30 points."""
    lo, hi = column_bounds(xy)
    span = hi - lo
    area0 = max(float(span[0] * span[1]), 1e-6)
    h = max(math.sqrt(30.0 * area0 / len(xy)), 1e-3)
    ij = grid_indices(xy, lo, h)
    _, cnt = np.unique(cell_code(ij), return_counts=True)
    return float(np.median(cnt)) / (h * h)


def _panel_columns(xy: np.ndarray, groups: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per panel (group id): the indices of its points and their nuisance columns ``(1, x -
    x_p, y - y_p)`` (aperture plane, m; the offset alone for a panel of fewer than 12 points
    or a degenerate one)."""
    order = np.argsort(groups, kind="stable")
    out = []
    for idx in np.split(order, np.flatnonzero(np.diff(groups[order])) + 1):
        if len(idx) == 0:
            continue
        d = xy[idx] - xy[idx].mean(0)
        P = np.column_stack([np.ones(len(idx)), d])
        if len(idx) < 12 or np.linalg.cond(P.T @ P) > 1e10:
            P = P[:, :1]
        out.append((idx, P))
    return out


def panel_fits(r: np.ndarray, panels) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Per panel of :func:`_panel_columns` (in their order), the least-squares fit of its
    columns ``P`` to the residuals ``r`` (m): ``(coefficients (k,), M^-1 = (P^T P)^-1 (k, k),
    residual sum of squares (m^2))``, ``k`` the panel's columns (3: offset m, tilts m/m; 1: the
    offset alone)."""
    out = []
    for idx, P in panels:
        Mi = np.linalg.inv(P.T @ P)
        coef = Mi @ (P.T @ r[idx])
        out.append((coef, Mi, float(np.sum((r[idx] - P @ coef) ** 2))))
    return out


def tilt_variance(r: np.ndarray, panels, sigma: float) -> float:
    """The variance of the panels' tilts (m/m per aperture axis) beyond the noise: moments of
    the per-panel plane fits (:func:`panel_fits`; ``mean(t^2) - sigma^2 mean(M^-1_tt)``, at
    least 0)."""
    t2, nv = [], []
    for t, Mi, _ in panel_fits(r, [(idx, P) for idx, P in panels if P.shape[1] == 3]):
        t2 += [t[1] ** 2, t[2] ** 2]
        nv += [Mi[1, 1], Mi[2, 2]]
    if not t2:
        return 0.0
    return max(0.0, float(np.mean(t2) - sigma**2 * np.mean(nv)))


@dataclass(frozen=True)
class _PanelAlgebra:
    """What the panel nuisance of the maps needs of the panels whatever the width: per panel
    ``K^-1`` and ``u = P^T r`` (:func:`_group_sums`), and the panels' points one panel after
    the other with their nuisance columns (``k`` of them: zero where a panel has fewer)."""

    rows: np.ndarray  # (n,) the points, panel after panel
    pid: np.ndarray  # (n,) their panel, 0 .. n_p - 1
    starts: np.ndarray  # (n_p,) first entry of each panel in ``rows``
    cols: np.ndarray  # (n, k) nuisance columns
    Ki: np.ndarray  # (n_p, k, k)
    u: np.ndarray  # (n_p, k)

    @classmethod
    def of(cls, panels, r: np.ndarray, sigma: float, tau2: float) -> _PanelAlgebra:
        """From :func:`_panel_columns`' panels, the residuals ``r`` (m), their sd ``sigma``
        and the tilts' variance ``tau2`` (none when 0)."""
        k = 3 if tau2 > 0.0 else 1
        n_p = len(panels)
        sizes = np.array([len(idx) for idx, _ in panels], np.int64)
        cols = np.zeros((int(sizes.sum()), k))
        Ki = np.zeros((n_p, k, k))
        u = np.zeros((n_p, k))
        at = 0
        for p, (idx, P) in enumerate(panels):
            P = P[:, :k]
            kp = P.shape[1]
            K = P.T @ P
            if kp > 1:
                K[1:, 1:] += np.eye(kp - 1) * sigma**2 / tau2
            Ki[p, :kp, :kp] = np.linalg.inv(K)
            u[p, :kp] = P.T @ r[idx]
            cols[at: at + len(idx), :kp] = P
            at += len(idx)
        rows = (np.concatenate([idx for idx, _ in panels]) if panels
                else np.zeros(0, np.int64))
        return cls(rows, np.repeat(np.arange(n_p), sizes), np.cumsum(sizes) - sizes, cols, Ki,
                   u)


#: Values of a chunk of stacked panel patches in :func:`_group_sums` (panels x cells x columns;
#: 32 MB per array): a reflector of thousands of panels or grid cells is taken in chunks.
PATCH_VALUES = 1 << 22


def _group_sums(ij: np.ndarray, alg: _PanelAlgebra, shape, sw: float):
    """Per centre, the panels' share of the bump's sums: ``sum_p G_p^T K_p^-1 u_p`` and
    ``sum_p G_p^T K_p^-1 G_p`` with a panel's nuisance columns ``P`` (:func:`_panel_columns`),
    ``G_p = sum g P`` (Gaussian sums of width ``sw`` cells over the panel's points), ``u_p =
    sum r P`` and ``K_p = P^T P + diag(0, sigma^2/tau2, sigma^2/tau2)``: the offset free, the
    tilts a random effect of variance ``tau2`` (generalised least squares by Woodbury; no tilt
    when ``tau2`` is 0; :class:`_PanelAlgebra`). Each panel is filtered on its own patch (its
    points' cells plus the filter's reach): the cost is that of the points, not of the panels
    times the grid.

    The panels at once, in chunks of at most :data:`PATCH_VALUES`: their patches stacked,
    each at the corner of a patch of the largest size (the filter's zeros beyond a patch are
    those of its ``mode="constant"``). The sums are added into the grid in the panels' order
    (a chunk's after the grid's values so far), so every cell receives the same additions, in
    the same order, as from one panel after the other: bit-identical to the per-panel loop of
    2026-11-28, whose ~1e4 small NumPy calls a search held the GIL."""
    Q1, Q2 = np.zeros(shape), np.zeros(shape)
    n_p, k = alg.u.shape
    if n_p == 0:
        return Q1, Q2
    reach = int(4.0 * sw + 0.5) + 1  # gaussian_filter's truncate=4 radius, and one cell
    at = ij[alg.rows]
    lo = np.maximum(np.minimum.reduceat(at, alg.starts) - reach, 0)
    shp = np.minimum(np.maximum.reduceat(at, alg.starts) + reach + 1, shape) - lo
    n = shape[0] * shape[1]
    every = np.arange(n)
    per = max(1, PATCH_VALUES // (int(np.prod(shp.max(0))) * k))
    ends = np.append(alg.starts[1:], len(alg.rows))
    for p0 in range(0, n_p, per):
        p1 = min(p0 + per, n_p)
        rows = slice(int(alg.starts[p0]), int(ends[p1 - 1]))
        pid, a_pt = alg.pid[rows] - p0, at[rows]
        lo_c, shp_c = lo[p0:p1], shp[p0:p1]
        H, W = (int(v) for v in shp_c.max(0))
        # every point's cell in its panel's patch, the patches one after the other
        cell = (pid * H + (a_pt[:, 0] - lo_c[pid, 0])) * W + (a_pt[:, 1] - lo_c[pid, 1])
        G = np.empty((p1 - p0, H, W, k))
        for a in range(k):
            Ca = np.bincount(cell, alg.cols[rows, a],
                             minlength=(p1 - p0) * H * W).reshape(p1 - p0, H, W)
            G[..., a] = _gauss(Ca, sw, lead=1)
        GK = G @ alg.Ki[p0:p1, None]  # (panels, H, W, k)
        q1 = (GK @ alg.u[p0:p1, None, :, None])[..., 0]
        q2 = np.einsum("...a,...a->...", GK, G)
        # the cells of each panel's own patch in the grid, panel after panel, after the
        # grid's values so far
        a_, b_ = np.ogrid[:H, :W]
        inside = (a_[None] < shp_c[:, 0, None, None]) & (b_[None] < shp_c[:, 1, None, None])
        to = (lo_c[:, 0, None, None] + a_[None]) * shape[1] + (lo_c[:, 1, None, None] + b_[None])
        to = np.concatenate([every, np.broadcast_to(to, inside.shape)[inside]])
        Q1 = np.bincount(to, np.concatenate([Q1.reshape(-1), q1[inside]]),
                         minlength=n).reshape(shape)
        Q2 = np.bincount(to, np.concatenate([Q2.reshape(-1), q2[inside]]),
                         minlength=n).reshape(shape)
    return Q1, Q2


def grid_of(xy: np.ndarray, w: float) -> tuple[np.ndarray, tuple[int, int], np.ndarray, float]:
    """The filter's grid for width ``w``: ``(origin, shape, ij (n, 2) cell of every point,
    cell size h = w / 4)``; shape ``(0, 0)`` when it would exceed 2.5e7 cells."""
    h = w / 4.0
    pad = 4 * BACKGROUND * w
    lo, hi = column_bounds(xy)
    lo = lo - pad
    shape = tuple(int(v) for v in np.ceil((hi + pad - lo) / h).astype(int) + 1)
    if shape[0] * shape[1] > 2.5e7:
        return lo, (0, 0), np.zeros((0, 2), np.int64), h
    return lo, shape, grid_indices(xy, lo, h), h


def coverage(C: np.ndarray, sw: float, h: float, density: float, min_coverage: float = 0.7,
             min_points: float = 8.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(covered, ng, disc)``: centres whose bump (width ``sw`` cells) holds enough points,
    whose disc of radius w is covered and whose core holds points; ``ng`` the unweighted
    sum of ``g^2`` per centre; ``disc`` the footprint of radius w (cells)."""
    ng = _gauss(C, sw / math.sqrt(2.0))
    yy, xx = np.mgrid[-4:5, -4:5]
    disc = (xx * xx + yy * yy <= 16).astype(float)
    n_disc = ndimage.convolve(C, disc, mode="constant")
    expect = density * disc.sum() * h * h
    # the core (radius w / 2) must hold points too: a ring of points around a hole is no bump
    core = (xx * xx + yy * yy <= 4).astype(float)
    n_core = ndimage.convolve(C, core, mode="constant")
    expect_core = density * core.sum() * h * h
    covered = (ng >= min_points) & (n_disc >= min_coverage * expect) & (
        n_core >= max(1.0, 0.6 * expect_core))
    return covered, ng, disc


@dataclass
class BackgroundFilter:
    """The matched filter ``a g + b`` under the background window (Gaussian of BACKGROUND w)
    on one grid: everything that depends on the points' positions only. ``a = (S11 Sgr - Sg1
    S1r) / det`` with ``Sgr``, ``S1r`` the residual sums filtered at ``s1``, ``sb`` cells."""

    S11: np.ndarray
    Sg1: np.ndarray
    det: np.ndarray
    valid: np.ndarray
    se_unit: np.ndarray  # se(a) / sigma
    s1: float
    sb: float

    @classmethod
    def of(cls, C: np.ndarray, sw: float, covered: np.ndarray) -> BackgroundFilter:
        sb = BACKGROUND * sw
        s1 = 1.0 / math.sqrt(1.0 / sb**2 + 1.0 / sw**2)  # W g
        s2 = 1.0 / math.sqrt(1.0 / sb**2 + 2.0 / sw**2)  # W g^2
        S11, Sg1, Sgg = _gauss(C, sb), _gauss(C, s1), _gauss(C, s2)
        det = S11 * Sgg - Sg1 * Sg1
        valid = covered & (det > 1e-9 * np.maximum(S11 * Sgg, 1e-300)) & (S11 > 3.0 * Sgg)
        detv = np.where(valid, det, 1.0)
        return cls(S11, Sg1, detv, valid,
                   np.sqrt(np.where(valid, np.maximum(S11, 0.0) / detv, 1.0)), s1, sb)

    def amplitude(self, R: np.ndarray) -> np.ndarray:
        """``a`` per centre from the gridded residual sums ``R`` (the grid on its first two
        axes; further axes are replicates, not filtered)."""
        def g(a, s):
            return _filter_grids(a, s) * (2 * math.pi * s * s)
        ex = (slice(None),) * 2 + (None,) * (R.ndim - 2)
        a = (self.S11[ex] * g(R, self.s1) - self.Sg1[ex] * g(R, self.sb)) / self.det[ex]
        return np.where(self.valid[ex], a, 0.0)


#: Grid values (cells x replicates) from which :func:`_filter_grids` splits the replicates
#: over the cores (a search's 167 x 167 x 120 replicate grids: 0.227 -> 0.10-0.12 s per
#: filter).
SPLIT_FILTER_VALUES = 1_000_000


def _filter_grids(a: np.ndarray, s: float) -> np.ndarray:
    """The Gaussian filter of sigma ``s`` cells (truncated at 4 sigma, zero outside) over the
    first two axes of ``a``, each replicate (the further axes) alone; many replicates are
    split over the cores (``scipy.ndimage`` releases the GIL): the same values."""
    sig = [s, s] + [0.0] * (a.ndim - 2)
    if a.ndim < 3 or a.size < SPLIT_FILTER_VALUES or a.shape[2] < 2:
        return ndimage.gaussian_filter(a, sig, mode="constant", truncate=4.0)
    out = np.empty_like(a)  # (ndimage's output: the input's dtype)

    def one(part: slice) -> None:
        ndimage.gaussian_filter(a[:, :, part], sig, mode="constant", truncate=4.0,
                                output=out[:, :, part])
    cuts = np.linspace(0, a.shape[2], min(usable_cores(), a.shape[2]) + 1).astype(int)
    each_in_threads(one, [slice(lo, hi) for lo, hi in zip(cuts[:-1], cuts[1:])], "grid-filter")
    return out


def width_map(xy: np.ndarray, r: np.ndarray, w: float, sigma: float, density: float,
              min_coverage: float = 0.7, min_points: float = 8.0,
              panels: _PanelAlgebra | None = None) -> WidthMap | None:
    """Matched-filter maps of width ``w`` (see the module docstring); ``panels``: the points'
    panels as their :class:`_PanelAlgebra` (for these ``r`` and ``sigma``), whose offsets (and
    tilts) are then the filter's nuisance instead of the local background (the module
    docstring, "Panels")."""
    lo, shape, ij, h = grid_of(xy, w)
    if shape == (0, 0):
        return None
    C, R = grid_sum(ij, shape), grid_sum(ij, shape, r)
    sw = w / h
    # points under the bump (unweighted sum of g^2) and coverage of the disc of radius w
    covered, ng, disc = coverage(C, sw, h, density, min_coverage, min_points)
    if panels is None:  # a g + b under the background window W (Gaussian of BACKGROUND w)
        bf = BackgroundFilter.of(C, sw, covered)
        valid = bf.valid
        a = bf.amplitude(R)
        se = sigma * bf.se_unit
    else:  # a g + one offset per panel, unwindowed: sums over the bump's own points
        Q1, Q2 = _group_sums(ij, panels, shape, sw)
        den = ng - Q2  # sum of the bump's within-panel part squared
        valid = covered & (den > MIN_WITHIN_PANEL * ng)
        denv = np.where(valid, den, 1.0)
        a = np.where(valid, (_gauss(R, sw) - Q1) / denv, 0.0)
        se = sigma / np.sqrt(denv)
    z = np.where(valid, a / se, 0.0)
    if valid.sum() * h * h < MIN_PLACEMENTS * math.pi * w * w:
        return None  # too few independent placements to measure the roughness at this width
    if valid.sum() < 16:
        return WidthMap(w, h, lo, a, z, np.zeros_like(z), valid, float("nan"),
                        np.zeros((0, 2), int))
    s_w = roughness_of(z[valid])
    t = np.where(valid, z / s_w, 0.0)
    at = np.abs(t)
    mx = ndimage.maximum_filter(at, footprint=disc.astype(bool), mode="constant")
    pk = np.argwhere(valid & (at == mx) & (at > 0))
    return WidthMap(w, h, lo, a, z, t, valid, s_w, pk)


def roughness_of(z: np.ndarray, axis=None) -> np.ndarray | float:
    """The roughness factor ``s_w``: the robust spread (``1.4826 MAD``) of the white scores
    ``z`` over the valid centres, never below 1 (white noise)."""
    med = np.median(z, axis=axis, keepdims=axis is not None)
    s = 1.4826 * np.median(np.abs(z - med), axis=axis)
    return np.maximum(s, 1.0) if axis is not None else max(float(s), 1.0)


def _distinct_peaks(maps: Sequence[WidthMap], exclude=()) -> np.ndarray:
    """Local maxima of ``|t|`` over all widths, one per feature: rows ``(|t|, map, i, j)``,
    strongest first. A feature answers at several widths and at neighbouring centres; a
    peak is kept only if no stronger kept peak lies within ``1.5 max(w, w')`` (otherwise
    one structure would weigh several times in the null). Peaks within ``2 w`` of a modelled
    deformation in ``exclude`` are left out."""
    rows = []
    for k, m in enumerate(maps):
        if len(m.peaks):
            c = m.centre(m.peaks)
            far = np.ones(len(c), bool)
            for ex, ey, ew in exclude:
                far &= np.hypot(c[:, 0] - ex, c[:, 1] - ey) > 2 * max(ew, m.width_m)
            t = np.abs(m.t[m.peaks[:, 0], m.peaks[:, 1]])
            rows.append(np.column_stack([t, np.full(len(t), k), m.peaks, c,
                                         np.full(len(t), m.width_m)])[far])
    P = np.concatenate(rows) if rows else np.zeros((0, 7))
    if not len(P):  # no peak, or every one next to a deformation already modelled
        return np.zeros((0, 4))
    P = P[np.argsort(-P[:, 0])]
    from scipy.spatial import cKDTree

    wmax = float(P[:, 6].max())
    tree = cKDTree(P[:, 4:6])
    kept = np.zeros(len(P), bool)
    for n in range(len(P)):
        near = tree.query_ball_point(P[n, 4:6], 1.5 * wmax)
        if not any(kept[q] and math.hypot(*(P[q, 4:6] - P[n, 4:6])) < 1.5 * max(P[q, 6], P[n, 6])
                   for q in near):
            kept[n] = True
    return P[kept][:, :4]


def _tail(heights: np.ndarray) -> dict | None:
    if len(heights) < MIN_PEAKS:
        return None
    u = float(np.quantile(heights, TAIL_QUANTILE if len(heights) >= 100 else 0.5))
    exc = heights[heights > u] - u
    if len(exc) < 8:
        return None
    return {"threshold": u, "scale": float(np.mean(exc)), "fraction": len(exc) / len(heights),
            "n": int(len(heights))}


def _p_tail(t: float, tail: dict) -> float:
    if t <= tail["threshold"]:
        return 1.0
    return tail["fraction"] * math.exp(-(t - tail["threshold"]) / tail["scale"])


def width_maps(xy: np.ndarray, r: np.ndarray, widths: Sequence[float] = WIDTHS_M,
               groups: np.ndarray | None = None, density: float | None = None):
    """The matched-filter maps of residuals ``r`` (m, normal) at aperture positions ``xy`` (m)
    for every width: ``(maps, sigma, skipped widths)``; ``sigma`` is the residuals' robust
    spread (m). Residuals are taken about their median and clipped to 5 sigma (no single
    point, a mixed pixel or the deep core of a structure, weighs more than that). ``groups``:
    the points' panel ids (one offset per panel is then the filter's nuisance; points of no
    panel, id < 0, are left out). ``density``: the points' median density (1/m^2) when the
    caller has it (default: measured here)."""
    xy = np.asarray(xy, float)
    r = np.asarray(r, float)
    ok = np.all(np.isfinite(xy), 1) & np.isfinite(r)
    if groups is not None:
        groups = np.asarray(groups, np.int64)
        ok &= groups >= 0
        groups = groups[ok]
    xy, r = xy[ok], r[ok]
    if len(r) < 16:  # nothing to search (every point rejected, or an empty recording)
        return [], float("nan"), [float(w) for w in widths]
    med = float(np.median(r))
    sigma = float(1.4826 * np.median(np.abs(r - med))) or float(np.std(r)) or 1e-4
    r = np.clip(r - med, -5 * sigma, 5 * sigma)
    dens = _density(xy) if density is None else density
    panels = _panel_columns(xy, groups) if groups is not None else None
    tau2 = tilt_variance(r, panels, sigma) if panels is not None else 0.0
    alg = _PanelAlgebra.of(panels, r, sigma, tau2) if panels is not None else None
    maps, skipped = [], []
    # the widths over the cores (each map alone; its grid work releases the GIL), in order
    done = each_in_threads(lambda w: width_map(xy, r, w, sigma, dens, panels=alg),
                           list(widths), "width-maps")
    for w, m in zip(widths, done):
        if m is None or not np.isfinite(m.roughness) or len(m.peaks) == 0:
            skipped.append(float(w))
            continue
        maps.append(m)
    return maps, sigma, skipped


def judge(maps: Sequence[WidthMap], sigma: float, skipped: Sequence[float], *,
          alpha: float = 1e-3, min_amplitude_m: float = 5e-5,
          exclude: Sequence[tuple[float, float, float]] = ()) -> Search:
    """The best candidate of the maps and its p-value against the other distinct peaks (the
    reflector's own; see the module docstring), peaks near ``exclude`` left out."""
    maps, skipped = list(maps), list(skipped)
    if not maps:
        return Search(maps, None, sigma, skipped)
    peaks = _distinct_peaks(maps, exclude)
    if not len(peaks):
        return Search(maps, None, sigma, skipped)
    # candidate: the largest |t| over widths and places; the null: every other distinct peak
    v, k, i, j = peaks[0][0], int(peaks[0][1]), int(peaks[0][2]), int(peaks[0][3])
    m = maps[k]
    c = m.centre((i, j))
    hts = peaks[1:, 0]
    tail = _tail(hts)
    cand = Candidate(float(c[0]), float(c[1]), float(m.amplitude[i, j]), m.width_m,
                     float(m.t[i, j]), float(m.z[i, j]), m.roughness, None, int(len(hts) + 1))
    if tail is None:
        cand.note = (f"{len(hts)} peaks of the reflector's own matched-filter field: too few "
                     "to calibrate the maximum; no significance")
    else:
        p1 = _p_tail(v, tail)
        cand.p_value = float(-math.expm1(cand.n_peaks * math.log1p(-min(p1, 1 - 1e-16))))
        cand.tail = tail
        cand.significant = bool(cand.p_value < alpha and abs(cand.amplitude_m) >= min_amplitude_m)
    return Search(maps, cand, sigma, skipped)


def search(xy: np.ndarray, r: np.ndarray, *, widths: Sequence[float] = WIDTHS_M,
           alpha: float = 1e-3, min_amplitude_m: float = 5e-5,
           exclude: Sequence[tuple[float, float, float]] = (),
           groups: np.ndarray | None = None) -> Search:
    """Matched-filter search of residuals ``r`` (m, normal) at aperture positions ``xy`` (m):
    :func:`width_maps` then :func:`judge`.

    ``exclude``: centres ``(x, y, w)`` of deformations already modelled (their neighbourhood
    of ``2 w`` is no candidate). Returns the maps, the best candidate with its p-value against
    the reflector's own peaks and whether it is significant (``p < alpha`` and ``|a| >=
    min_amplitude_m``). ``groups``: the points' panel ids, whose offsets are then the
    filter's nuisance (see the module docstring).
    """
    return judge(*width_maps(xy, r, widths, groups), alpha=alpha, min_amplitude_m=min_amplitude_m,
                 exclude=exclude)


def local_level(xy: np.ndarray, r: np.ndarray, at: np.ndarray, *,
                radius: float = COHERENCE_RADIUS_M, k_min: int = COHERENCE_NEIGHBOURS,
                radius_max: float = COHERENCE_MAX_RADIUS_M) -> tuple[np.ndarray, np.ndarray]:
    """Median residual (m) of the neighbours of the points ``at`` (indices into ``xy``, ``r``).

    Neighbours of point ``i``: every other point within ``radius`` (m) of it in the aperture
    plane, or, where fewer than ``k_min`` lie there, its ``k_min`` nearest ones within
    ``radius_max``. Returns ``(level, n)``: the median (NaN without neighbours) and how many
    neighbours it was taken over.
    """
    from scipy.spatial import cKDTree

    at = np.asarray(at, np.int64)
    level = np.full(len(at), np.nan)
    n = np.zeros(len(at), np.int64)
    if len(at) == 0 or len(r) < 2:
        return level, n
    # a tree without the balanced splits and compacted nodes: built in a third of the time
    # (5.2e5 points 0.29 -> 0.09 s), the same neighbours found
    tree = cKDTree(xy, balanced_tree=False, compact_nodes=False)
    k = min(k_min + 1, len(r))
    dk, jk = tree.query(xy[at], k=k, distance_upper_bound=radius_max)
    dk, jk = dk.reshape(len(at), k), jk.reshape(len(at), k)
    balls = tree.query_ball_point(xy[at], radius)
    for q, i in enumerate(at):
        nb = [j for j in balls[q] if j != i]
        if len(nb) < k_min:
            nb = [int(j) for j, d in zip(jk[q], dk[q]) if np.isfinite(d) and j != i]
        if nb:
            level[q] = float(np.median(r[nb]))
            n[q] = len(nb)
    return level, n


def coherent(xy: np.ndarray, r: np.ndarray, kept: np.ndarray, limit: np.ndarray, *,
             min_neighbours: int = 3, **kw) -> np.ndarray:
    """The rejected points (``~kept``) that agree with their neighbourhood (bool mask).

    ``xy``: aperture positions (m) of all points of the window, ``r`` their residual normal
    deviations (m), ``kept`` what the robust fit kept, ``limit`` each point's rejection limit
    in the same units as ``r`` (``k`` a-posteriori sigmas). A rejected point comes back when it
    has at least ``min_neighbours`` neighbours and ``|r_i - level_i| <= limit_i``, ``level_i``
    the median residual of its neighbours (:func:`local_level`, keywords passed on; rejected
    neighbours count): it is part of a structure the surface shows around it, not an outlier
    (see the module docstring).
    """
    kept = np.asarray(kept, bool)
    out = np.zeros(len(r), bool)
    rej = np.flatnonzero(~kept & np.isfinite(r))
    if len(rej) == 0:
        return out
    ok = np.all(np.isfinite(xy), 1) & np.isfinite(r)
    idx = np.flatnonzero(ok)
    pos = np.searchsorted(idx, rej)
    level, n = local_level(xy[idx], r[idx], pos, **kw)
    out[rej] = (n >= min_neighbours) & (np.abs(r[rej] - level) <= np.asarray(limit)[rej])
    return out


def covered_ids(xy: np.ndarray, ids: np.ndarray, x0: float, y0: float, radius: float,
                limit: int = 12) -> list[int]:
    """Ids (panels or cells) of the points within ``radius`` of ``(x0, y0)``, most points first."""
    near = (np.hypot(xy[:, 0] - x0, xy[:, 1] - y0) < radius) & (ids >= 0)
    u, c = np.unique(ids[near], return_counts=True)
    return [int(v) for v in u[np.argsort(-c)][:limit]]


def scan_point(xy: np.ndarray, xs: np.ndarray, x0: float, y0: float,
               w: float) -> list[float] | None:
    """The surface point above ``(x0, y0)`` in the scan's own Cartesian frame: a plane of the
    recorded coordinates ``xs`` (n, 3) against the aperture positions ``xy`` of the points
    within ``w`` (at least 6), evaluated at the centre."""
    for rad in (w, 2 * w, 4 * w):
        near = np.hypot(xy[:, 0] - x0, xy[:, 1] - y0) < rad
        if near.sum() >= 6:
            A = np.column_stack([np.ones(near.sum()), xy[near, 0] - x0, xy[near, 1] - y0])
            coef = np.linalg.lstsq(A, xs[near], rcond=None)[0]
            return [float(v) for v in coef[0]]
    return None
