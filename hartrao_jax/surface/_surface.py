"""Surface products: panels, cycle averaging and per-panel deviations (paper sec. 3, end).

From the adjustment of each scan (:class:`._fit.ScanFit`) to the reflector's surface:

1. North alignment. ``ScanFit.X_tel`` already holds the north-aligned telescope-frame
   coordinates (``X_tel = Rz(kappa) X_fit``: X north, Y west at the zenith).
2. Panels. Every point gets the panel id of the campaign's layout (``ring_edges_m``,
   ``panels_per_ring``; :func:`._geometry.panel_ids`); points within ``margin_radial_m`` of a
   ring edge or within ``margin_tangential_m`` (arc length at the point's radius) of a panel's
   side are masked (panel -1): the paper's "edges removed by using a defined mask", so that no
   point can be given to the wrong panel and no average spans a gap between panels.
3. Per-cycle deviations: ``ScanFit.deviation_m``, the signed normal distance from the scan's
   fitted paraboloid, positive towards the focus (``campaign-format.md``).
4. Cycle averaging (paper: "points within a panel are grouped into circles with their nearest
   neighbours where the circle has a radius of about 1 cm; points within one circle are
   averaged"). Points are grouped, panel by panel, into cells of a square lattice in the
   aperture plane (X, Y) of side ``radius_m * sqrt(2)``, so every point of a cell lies within
   ``radius_m`` of the cell's centre (a circle of that radius). The key of a cell includes the
   panel id: two panels are never averaged together. A cell's value is the mean of its cycle-1
   mean and its cycle-2 mean, so both faces weigh the same whatever the point densities and
   the two-face-sensitive errors (opposite sign in the two cycles at the same place) cancel.
   A cell seen by one cycle only (the two cycles' points of one spot can fall on two sides of a
   cell boundary) is paired with the nearest such cell of the other cycle in the same panel
   whose centroid lies within ``radius_m`` (mutual nearest neighbours, ``scipy cKDTree``);
   cells left without a partner are not part of the average (counted as ``n_unpaired``).
5. Per panel: ``deviation_m``, the mean deviation of the panel's averaged points, with
   ``sigma_m`` its standard deviation; a plane ``d = a + t_r (rho - rho_c) + t_t rho_c dpsi``
   (the offset/tilt parametrisation of ``physics.md``'s ``panel_offset``) gives
   ``tilt_rad = hypot(t_r, t_t)``, its radial (outer edge up) and tangential
   (counter-clockwise edge up) parts, and ``offset_m = a`` (the plane at the panel centre, with
   ``offset_sigma_m``); ``rms_m`` is the rms of the panel's deviations, ``rms_plane_m`` about its
   plane, ``n`` the number of averaged points.

Outputs (:func:`write_surface`): ``surface.json`` (schema ``hartrao-surface/1``, see
:func:`surface_json`), ``points/<position>.parquet`` (cycle-averaged points) and
``cycles/<scan>.parquet`` (the masked per-cycle points). Units: m, rad.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..campaign._campaign import load_campaign
from ..campaign._safeio import OutputDir, verify_result_dir
from ..fit._align import mean_heading, scan_heading
from ..fit._fit import fit_campaign, fit_scan
from ..fit._position_record import panel_predictions
from ..fit._records import read_residuals, write_fit
from ..geometry._geometry import column_bounds, face_of, grid_indices, panel_geometry, panel_ids
from ..preprocess._preprocess import preprocess_keep
from ._disturbed import cut_keep, detect_disturbed_campaign, detect_disturbed_residuals

log = logging.getLogger("hartrao_jax")

SURFACE_SCHEMA = "hartrao-surface/1"
PANEL_KEYS = ("deviation_m", "sigma_m", "tilt_rad", "tilt_radial_rad", "tilt_tangential_rad",
              "offset_m", "offset_sigma_m", "rms_m", "rms_plane_m")
"""Per-panel keys of ``surface.json`` besides ``panel``, ``ring`` and ``n`` (m, rad)."""


# --------------------------------------------------------------------------------------------
# Configuration, layout, results
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SurfaceConfig:
    """Parameters of the surface products (m).

    Attributes:
        margin_radial_m: points closer than this to a ring edge are masked.
        margin_tangential_m: points closer than this (arc length) to a panel's side are masked.
        radius_m: radius of the averaging circles; None: the paper's 1 cm, or 0.75 times the
            median point spacing when the scan is coarser (simulated test scans).
        min_points: a panel with fewer averaged points gets no deviation (null in the JSON).
        model: model of the adjustment when :func:`surface_campaign` fits the campaign.
        used_only: only points that entered the adjustment (``ScanFit.used``).
    """

    margin_radial_m: float = 0.02
    margin_tangential_m: float = 0.02
    radius_m: float | None = None
    min_points: int = 3
    model: str = "extended"
    used_only: bool = True

    def __post_init__(self):
        if self.radius_m is not None and self.radius_m <= 0:
            raise ValueError(f"radius_m must be > 0, not {self.radius_m}")
        if self.margin_radial_m < 0 or self.margin_tangential_m < 0:
            raise ValueError("panel margins must be >= 0")
        if self.min_points < 1:
            raise ValueError("min_points must be >= 1")


@dataclass(frozen=True)
class PanelLayout:
    """Rings and panels of a reflector (``campaign-format.md``, "Panels")."""

    ring_edges_m: tuple[float, ...]
    panels_per_ring: tuple[int, ...]

    def __post_init__(self):
        object.__setattr__(self, "ring_edges_m", tuple(float(e) for e in self.ring_edges_m))
        object.__setattr__(self, "panels_per_ring", tuple(int(n) for n in self.panels_per_ring))
        if len(self.ring_edges_m) != len(self.panels_per_ring) + 1:
            raise ValueError("ring_edges_m needs one more entry than panels_per_ring")

    @classmethod
    def from_telescope(cls, telescope) -> PanelLayout | None:
        """The telescope's layout; None without the (optional) panel keys."""
        if not telescope.ring_edges_m or not telescope.panels_per_ring:
            return None
        return cls(tuple(telescope.ring_edges_m), tuple(telescope.panels_per_ring))

    @classmethod
    def default(cls) -> PanelLayout:
        """HartRAO 26-m: 255 panels in 7 rings."""
        return cls((1.6, 3.2, 4.8, 6.4, 8.0, 9.6, 11.2, 12.95), (15, 24, 30, 36, 42, 48, 60))

    @property
    def n_panels(self) -> int:
        return int(sum(self.panels_per_ring))

    def geometry(self) -> dict[str, np.ndarray]:
        return panel_geometry(self.ring_edges_m, self.panels_per_ring)


@dataclass
class CyclePoints:
    """The surface points of one scan (one cycle) after masking (N points, SI units).

    ``panel`` is -1 for points outside every panel or within the edge margins (no layout: 0).
    """

    scan: str
    cycle: int
    X: np.ndarray  # (N, 3) north-aligned telescope frame
    deviation_m: np.ndarray  # (N,) positive towards the focus
    panel: np.ndarray  # (N,) int32
    face: np.ndarray  # (N,) int8
    phi_rad: np.ndarray  # (N,) raw horizontal angle

    def __len__(self):
        return len(self.deviation_m)

    @property
    def inside(self) -> np.ndarray:
        return self.panel >= 0

    @property
    def rms_m(self) -> float:
        d = self.deviation_m[self.inside]
        return float(np.sqrt(np.mean(d * d))) if len(d) else float("nan")


@dataclass
class AveragedPoints:
    """Cycle-averaged points (M groups): centroid, mean deviation, panel, points per cycle."""

    X: np.ndarray  # (M, 3)
    deviation_m: np.ndarray  # (M,)
    panel: np.ndarray  # (M,) int32
    n1: np.ndarray  # (M,) points of the first cycle (cycle 1, or the only one)
    n2: np.ndarray  # (M,) points of cycle 2
    diff_m: np.ndarray  # (M,) mean(cycle 1) - mean(cycle 2) (NaN for single-cycle groups)
    n_unpaired: int = 0

    def __len__(self):
        return len(self.deviation_m)

    @property
    def rms_m(self) -> float:
        d = self.deviation_m
        return float(np.sqrt(np.mean(d * d))) if len(d) else float("nan")


@dataclass
class PanelTable:
    """Per-panel results (arrays of length ``n_panels``; NaN where a panel has too few points)."""

    panel: np.ndarray
    ring: np.ndarray
    deviation_m: np.ndarray
    sigma_m: np.ndarray
    tilt_rad: np.ndarray
    tilt_radial_rad: np.ndarray
    tilt_tangential_rad: np.ndarray
    offset_m: np.ndarray
    offset_sigma_m: np.ndarray
    rms_m: np.ndarray
    rms_plane_m: np.ndarray
    n: np.ndarray

    def records(self) -> list[dict]:
        keys = PANEL_KEYS
        out = []
        for i in range(len(self.panel)):
            r = {"panel": int(self.panel[i]), "ring": int(self.ring[i])}
            r.update({k: _num(getattr(self, k)[i]) for k in keys})
            r["n"] = int(self.n[i])
            out.append(r)
        return out


@dataclass
class PositionSurface:
    """The surface of one telescope position: per-cycle points, their average, panels."""

    position: str
    pointing: dict[str, Any]  # ha_deg, dec_deg / elevation_deg, azimuth_deg (when known)
    cycles: list[CyclePoints]
    averaged: AveragedPoints
    panels: PanelTable | None
    cycle_panels: dict[str, PanelTable | None]
    kind: str  # "cycle average" | "single cycle" | "one face"
    kappa_rad: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    radius_m: float = 0.01  # averaging radius used
    # the position adjustment's panel predictions (random effect, both faces; see
    # ``_fit.panel_predictions``) and how many faces it used
    adjusted_panels: list[dict] = field(default_factory=list)
    faces: int | None = None


@dataclass
class SurfaceResult:
    config: SurfaceConfig
    layout: PanelLayout | None
    positions: list[PositionSurface]
    source: dict[str, Any] = field(default_factory=dict)  # where the fits came from
    disturbed: list[dict] = field(default_factory=list)

    def position(self, name: str) -> PositionSurface:
        for p in self.positions:
            if p.position == name:
                return p
        raise KeyError(name)


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


# --------------------------------------------------------------------------------------------
# Panels and masks
# --------------------------------------------------------------------------------------------


def panel_mask(X: np.ndarray, layout: PanelLayout | None, config: SurfaceConfig | None = None
               ) -> np.ndarray:
    """Panel id of each point (int32), -1 outside the panels or within the edge margins.

    Without a layout every point is in panel 0 (one pseudo panel: no panel products).
    """
    cfg = config or SurfaceConfig()
    X = np.asarray(X, float)
    if layout is None:
        return np.zeros(len(X), np.int32)
    block = 1 << 20
    if len(X) > block:  # bounded temporaries for large scans
        return np.concatenate([panel_mask(X[i:i + block], layout, cfg)
                               for i in range(0, len(X), block)])
    rho = np.hypot(X[:, 0], X[:, 1])
    psi = np.mod(np.arctan2(X[:, 1], X[:, 0]), 2 * np.pi)
    pid = panel_ids(rho, psi, layout.ring_edges_m, layout.panels_per_ring)
    ok = pid >= 0
    g = layout.geometry()
    k = np.where(ok, pid, 0)
    mr, mt = cfg.margin_radial_m, cfg.margin_tangential_m
    ok &= (rho - g["rho_in"][k] >= mr) & (g["rho_out"][k] - rho >= mr)
    ok &= (rho * (psi - g["psi_start"][k]) >= mt) & (rho * (g["psi_end"][k] - psi) >= mt)
    return np.where(ok, pid, -1).astype(np.int32)


def cycle_points(scan: str, cycle: int, X: np.ndarray, deviation_m: np.ndarray,
                 theta_rad: np.ndarray | None, phi_rad: np.ndarray | None,
                 layout: PanelLayout | None, config: SurfaceConfig | None = None,
                 keep: np.ndarray | None = None, face: np.ndarray | None = None) -> CyclePoints:
    """Masked surface points of one scan from its telescope-frame points and deviations.

    ``keep`` selects the points to use (e.g. ``ScanFit.used``); the result holds only those.
    """
    X = np.asarray(X, float)
    dev = np.asarray(deviation_m, float)
    sel = np.isfinite(dev) & np.all(np.isfinite(X), axis=1)
    if keep is not None:
        sel &= np.asarray(keep, bool)
    idx = np.flatnonzero(sel)
    if face is None:
        face = face_of(theta_rad) if theta_rad is not None else np.ones(len(dev), np.int8)
    face = np.asarray(face)[idx].astype(np.int8)
    phi = np.asarray(phi_rad, float)[idx] if phi_rad is not None else np.full(len(idx), np.nan)
    Xs = X[idx]
    return CyclePoints(scan, int(cycle), Xs, dev[idx], panel_mask(Xs, layout, config), face, phi)


# --------------------------------------------------------------------------------------------
# Cycle averaging
# --------------------------------------------------------------------------------------------


def _cell_keys(X: np.ndarray, panel: np.ndarray, side: float, origin: np.ndarray,
               span: int) -> np.ndarray:
    ij = grid_indices(X[:, :2], origin, side)
    return (panel.astype(np.int64) * span + ij[:, 1]) * span + ij[:, 0]


def cycle_average(X1: np.ndarray, d1: np.ndarray, p1: np.ndarray,
                  X2: np.ndarray | None = None, d2: np.ndarray | None = None,
                  p2: np.ndarray | None = None, radius_m: float = 0.01, *,
                  return_groups: bool = False, chunk_points: int = 2_000_000):
    """Average two cycles' deviations, panel by panel, in circles of ``radius_m`` (module doc).

    ``X*`` (n, 3) telescope-frame points, ``d*`` deviations, ``p*`` panel ids (negative ids are
    ignored). With no second cycle the groups are single-cycle means. Returns
    :class:`AveragedPoints`; with ``return_groups`` also the output group of every input point
    of each cycle (``-1``: not averaged). Panels are processed in chunks of about
    ``chunk_points`` points (memory stays bounded whatever the size of the scans).
    """
    X1 = np.asarray(X1, float)
    d1 = np.asarray(d1, float)
    p1 = np.asarray(p1)
    if X2 is None:
        X2, d2, p2 = np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int32)
    X2 = np.asarray(X2, float)
    d2 = np.asarray(d2, float)
    p2 = np.asarray(p2)
    two = len(d1) > 0 and len(d2) > 0
    top = int(max(p1.max(initial=-1), p2.max(initial=-1))) + 1
    cnt = np.bincount(p1[p1 >= 0], minlength=top) + np.bincount(p2[p2 >= 0], minlength=top)
    # panel ranges [lo, hi) of about chunk_points points each
    edges, acc, lo = [], 0, 0
    for k in range(top):
        acc += int(cnt[k])
        if acc >= chunk_points:
            edges.append((lo, k + 1))
            lo, acc = k + 1, 0
    if lo < top:
        edges.append((lo, top))
    # one lattice for all chunks: the cells do not depend on the chunking
    side = radius_m * math.sqrt(2.0)
    ext = [a for a in (X1[:, :2], X2[:, :2]) if len(a)]
    if ext:
        bounds = [column_bounds(a) for a in ext]
        lo_xy = np.min([b[0] for b in bounds], axis=0)
        hi_xy = np.max([b[1] for b in bounds], axis=0)
        origin = np.floor(lo_xy / side) * side - side
        span = int(np.ceil((hi_xy - origin).max() / side)) + 2
        if span * span * (top + 1) >= 2**62:
            raise ValueError("cycle_average: the point cloud is too large for radius_m")
    else:
        origin, span = np.zeros(2), 1
    parts: list[AveragedPoints] = []
    g1 = np.full(len(d1), -1, np.int64) if return_groups else None
    g2 = np.full(len(d2), -1, np.int64) if return_groups else None
    offset = 0
    whole = len(edges) == 1
    for lo, hi in edges:
        s1 = np.flatnonzero((p1 >= lo) & (p1 < hi)) if not whole else np.flatnonzero(p1 >= 0)
        s2 = np.flatnonzero((p2 >= lo) & (p2 < hi)) if not whole else np.flatnonzero(p2 >= 0)
        res, i1, i2 = _average_cells(X1[s1], d1[s1], p1[s1], X2[s2], d2[s2], p2[s2], radius_m,
                                     two, return_groups, origin, span)
        parts.append(res)
        if return_groups:
            g1[s1] = np.where(i1 >= 0, i1 + offset, -1)
            g2[s2] = np.where(i2 >= 0, i2 + offset, -1)
        offset += len(res)
    if parts:
        out = AveragedPoints(
            np.concatenate([r.X for r in parts]), np.concatenate([r.deviation_m for r in parts]),
            np.concatenate([r.panel for r in parts]), np.concatenate([r.n1 for r in parts]),
            np.concatenate([r.n2 for r in parts]), np.concatenate([r.diff_m for r in parts]),
            int(sum(r.n_unpaired for r in parts)))
    else:
        out = _empty_average()
    return (out, g1, g2) if return_groups else out


def _empty_average() -> AveragedPoints:
    return AveragedPoints(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int32),
                          np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))


def _average_cells(X1, d1, p1, X2, d2, p2, radius_m: float, two: bool, groups: bool,
                   origin: np.ndarray, span: int):
    """:func:`cycle_average` of points that all have panel ids >= 0 (one chunk of panels).

    Returns the averaged points and, with ``groups``, the group of every input point."""
    n1_, n2_ = len(d1), len(d2)
    if n1_ + n2_ == 0:
        return _empty_average(), np.zeros(0, np.int64), np.zeros(0, np.int64)
    side = radius_m * math.sqrt(2.0)
    k = np.concatenate([_cell_keys(X1, p1, side, origin, span),
                        _cell_keys(X2, p2, side, origin, span)])
    _, inv = np.unique(k, return_inverse=True)
    del k
    inv = inv.reshape(-1)
    K = int(inv.max()) + 1
    i1, i2 = inv[:n1_], inv[n1_:]

    def means(i, X, d):
        c = np.bincount(i, minlength=K)
        m = [np.bincount(i, weights=w, minlength=K).astype(np.float64, copy=False)
             for w in (d, X[:, 0], X[:, 1], X[:, 2])]  # (empty input: int64 zeros)
        with np.errstate(invalid="ignore", divide="ignore"):
            for a in m:
                a /= c  # in place: NaN where the cycle has no point
        return c, m

    c1, m1 = means(i1, X1, d1)
    c2, m2 = means(i2, X2, d2)
    pan = np.empty(K, np.int32)
    pan[i1] = p1
    pan[i2] = p2
    both = (c1 > 0) & (c2 > 0)
    n_unpaired = 0
    if two:
        o1, o2 = np.flatnonzero((c1 > 0) & (c2 == 0)), np.flatnonzero((c2 > 0) & (c1 == 0))
        partner = np.full(K, -1, np.int64)  # the cycle-2 cell paired with a cycle-1 orphan
        if len(o1) and len(o2):
            pairs = _mutual_nearest(
                np.column_stack([m1[1][o1], m1[2][o1]]), pan[o1],
                np.column_stack([m2[1][o2], m2[2][o2]]), pan[o2], radius_m)
            partner[o1[pairs[:, 0]]] = o2[pairs[:, 1]]
        has = partner >= 0
        n_unpaired = int(c1[o1].sum() + c2[o2].sum() - c1[has].sum() - c2[partner[has]].sum())
        groups1 = np.flatnonzero(both | has)  # the cycle-1 cell of every group
        groups2 = np.where(both[groups1], groups1, partner[groups1])
        del partner, has
        dev = 0.5 * (m1[0][groups1] + m2[0][groups2])
        X = np.empty((len(groups1), 3))
        for j in range(3):
            X[:, j] = 0.5 * (m1[j + 1][groups1] + m2[j + 1][groups2])
        diff = m1[0][groups1] - m2[0][groups2]
        n1, n2 = c1[groups1], c2[groups2]
    else:
        mm, cc = (m1, c1) if n1_ else (m2, c2)
        groups1 = groups2 = np.flatnonzero(cc > 0)
        dev = mm[0][groups1]
        X = np.column_stack([mm[j][groups1] for j in (1, 2, 3)])
        diff = np.full(len(groups1), np.nan)
        z = np.zeros(len(groups1), np.int64)
        n1, n2 = (cc[groups1], z) if n1_ else (z, cc[groups1])
    res = AveragedPoints(X, dev, pan[groups1].astype(np.int32), n1.astype(np.int64),
                         n2.astype(np.int64), diff, n_unpaired)
    if not groups:
        return res, None, None
    out_of_cell = np.full(K, -1, np.int64)
    out_of_cell[groups1] = np.arange(len(groups1))
    out_of_cell[groups2] = np.arange(len(groups1))
    return res, out_of_cell[i1], out_of_cell[i2]


def _mutual_nearest(a: np.ndarray, pa: np.ndarray, b: np.ndarray, pb: np.ndarray,
                    radius: float) -> np.ndarray:
    """Pairs ``(i, j)`` of mutual nearest neighbours of ``a`` and ``b`` within ``radius``, same
    panel (panel ids enter as a third coordinate far larger than any distance)."""
    from scipy.spatial import cKDTree

    sep = 1e3 * (1.0 + np.abs(np.concatenate([a.ravel(), b.ravel()])).max(initial=1.0))
    A = np.column_stack([a, pa * sep])
    B = np.column_stack([b, pb * sep])
    da, ja = cKDTree(B).query(A, k=1, distance_upper_bound=radius)
    db, jb = cKDTree(A).query(B, k=1, distance_upper_bound=radius)
    i = np.flatnonzero(np.isfinite(da))
    j = ja[i]
    ok = jb[j] == i
    return np.column_stack([i[ok], j[ok]])


# --------------------------------------------------------------------------------------------
# Per-panel statistics
# --------------------------------------------------------------------------------------------


def panel_statistics(X: np.ndarray, deviation_m: np.ndarray, panel: np.ndarray,
                     layout: PanelLayout, min_points: int = 3) -> PanelTable:
    """Deviation, tilt, rms and point count of every panel (module doc).

    ``deviation_m`` is the mean deviation of the panel's points and ``sigma_m`` its standard
    deviation from the scatter about the panel's plane; the plane
    ``d = a + t_r (rho - rho_c) + t_t rho_c dpsi`` gives the tilts and ``offset_m = a`` (its
    value at the panel centre, an extrapolation when part of the panel is shadowed).
    """
    g = layout.geometry()
    P = layout.n_panels
    X = np.asarray(X, float)
    d = np.asarray(deviation_m, float)
    p = np.asarray(panel)
    s = (p >= 0) & (p < P) & np.isfinite(d)
    X, d, p = X[s], d[s], p[s].astype(np.int64)
    rho = np.hypot(X[:, 0], X[:, 1])
    psi = np.arctan2(X[:, 1], X[:, 0])
    dr = rho - g["rho_c"][p]
    dt = g["rho_c"][p] * (np.mod(psi - g["psi_c"][p] + np.pi, 2 * np.pi) - np.pi)
    cols = (np.ones_like(d), dr, dt)
    n = np.bincount(p, minlength=P)

    def bs(w):
        return np.bincount(p, weights=w, minlength=P)

    N = np.empty((P, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            N[:, a, b] = N[:, b, a] = bs(cols[a] * cols[b])
    u = np.stack([bs(c * d) for c in cols], 1)
    dd = bs(d * d)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = u[:, 0] / n
        rms = np.sqrt(dd / n)
    sig, off, off_sig = (np.full(P, np.nan) for _ in range(3))
    tr, tt, rmsp = (np.full(P, np.nan) for _ in range(3))
    enough = n >= max(min_points, 1)
    for i in np.flatnonzero(enough):
        var = max(dd[i] / n[i] - mean[i] ** 2, 0.0)
        Ni = N[i]
        if n[i] >= 4 and np.linalg.cond(Ni) < 1e10:
            Q = np.linalg.inv(Ni)
            x = Q @ u[i]
            rss = max(dd[i] - x @ u[i], 0.0)
            s2 = rss / (n[i] - 3)
            off[i], tr[i], tt[i] = x
            off_sig[i] = math.sqrt(s2 * Q[0, 0])
            sig[i] = math.sqrt(s2 / n[i])
            rmsp[i] = math.sqrt(rss / n[i])
        else:  # too few points for a plane: the mean only
            sig[i] = math.sqrt(var / max(n[i] - 1, 1))
            rmsp[i] = math.sqrt(var)
    mean[~enough] = np.nan
    rms[~enough] = np.nan
    return PanelTable(
        panel=np.arange(P), ring=np.asarray(g["ring"], np.int64), deviation_m=mean,
        sigma_m=sig, tilt_rad=np.hypot(tr, tt), tilt_radial_rad=tr, tilt_tangential_rad=tt,
        offset_m=off, offset_sigma_m=off_sig, rms_m=rms, rms_plane_m=rmsp, n=n.astype(np.int64))


# --------------------------------------------------------------------------------------------
# Positions
# --------------------------------------------------------------------------------------------


def point_spacing(X: np.ndarray, max_points: int = 200_000, seed: int = 0) -> float:
    """Median nearest-neighbour distance (m) of points in the aperture plane.

    Measured on a random subsample of ``max_points`` and scaled by ``sqrt(fraction)`` (the
    spacing of a uniform subsample grows as ``1 / sqrt(fraction)``).
    """
    from scipy.spatial import cKDTree

    X = np.asarray(X, float)
    n = len(X)
    if n < 3:
        return float("nan")
    q = min(1.0, max_points / n)
    sub = X if q == 1.0 else X[np.random.default_rng(seed).random(n) < q]
    d, _ = cKDTree(sub[:, :2]).query(sub[:, :2], k=2)
    return float(np.median(d[:, 1]) * math.sqrt(q))


def averaging_radius(cycles: Sequence[CyclePoints], paper_m: float = 0.01) -> float:
    """The paper's 1 cm, or 0.75 x the median point spacing of the scans when that is larger."""
    sp = [point_spacing(c.X[c.inside]) for c in cycles if c.inside.sum() > 2]
    sp = [s for s in sp if np.isfinite(s)]
    return max(paper_m, 0.75 * max(sp)) if sp else paper_m


def position_surface(position: str, cycles: Sequence[CyclePoints], layout: PanelLayout | None,
                     config: SurfaceConfig | None = None, pointing: Mapping | None = None,
                     kappa_rad: Mapping[str, float] | None = None) -> PositionSurface:
    """Average the cycles of one position and compute its panel table.

    Scans of cycle 1 are averaged with those of cycle 2; with only one of them (or one-face
    scans, cycle 0) the groups are single-cycle means and the two-face errors do not cancel.
    """
    cfg = config or SurfaceConfig()
    notes = []
    by = {c: [p for p in cycles if p.cycle == c] for c in (0, 1, 2)}
    a, b = by[1], by[2]
    if a and b:
        kind = "cycle average"
    else:
        a, b = (a or b or by[0]), []
        kind = "one face" if by[0] and not (by[1] or by[2]) else "single cycle"
        notes.append(f"{kind}: no cycle averaging, the two-face-sensitive errors do not cancel")

    def cat(ps):
        if not ps:
            return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int32)
        return (np.concatenate([p.X for p in ps]), np.concatenate([p.deviation_m for p in ps]),
                np.concatenate([p.panel for p in ps]))

    radius = cfg.radius_m or averaging_radius(cycles)
    avg = cycle_average(*cat(a), *cat(b), radius_m=radius)
    if kind == "cycle average" and len(avg):
        paired = int(avg.n1.sum() + avg.n2.sum())
        frac = avg.n_unpaired / max(paired + avg.n_unpaired, 1)
        if frac > 0.2:
            notes.append(f"{frac:.0%} of the points have no partner of the other cycle within "
                         f"{radius * 100:.3g} cm (coarse scan or different grids): "
                         "consider a larger radius_m")
    panels, cyc = None, {}
    if layout is not None:
        panels = panel_statistics(avg.X, avg.deviation_m, avg.panel, layout, cfg.min_points)
        for p in cycles:
            cyc[p.scan] = panel_statistics(p.X, p.deviation_m, p.panel, layout, cfg.min_points)
    return PositionSurface(position, dict(pointing or {}), list(cycles), avg, panels, cyc, kind,
                           dict(kappa_rad or {}), notes, radius)


def _pointing(meta) -> dict[str, Any]:
    out = {}
    for k in ("ha_deg", "dec_deg", "elevation_deg", "azimuth_deg"):
        v = getattr(meta, k, None)
        if v is not None:
            out[k] = float(v)
    return out


def surface_from_fit(campaign_fit, config: SurfaceConfig | None = None, *,
                     keep: Mapping[str, np.ndarray] | None = None,
                     exclude: Iterable[str] = ()) -> SurfaceResult:
    """Surface products of a :class:`._fit.CampaignFit` (every position of it).

    ``keep``: optional extra masks per scan id (True: use the point), e.g. from
    :func:`._disturbed.cut_keep`; ``exclude``: scan ids to leave out.
    """
    cfg = config or SurfaceConfig()
    camp = campaign_fit.campaign
    layout = PanelLayout.from_telescope(camp.telescope)
    exclude = set(exclude)
    groups: dict[str, list] = {}
    for s in campaign_fit.scans:
        if s.meta.id in exclude:
            continue
        groups.setdefault(s.meta.position, []).append(s)
    positions = []
    for pos, fits in groups.items():
        cps, kap = [], {}
        for s in fits:
            m = s.used.copy() if cfg.used_only else np.ones(len(s.deviation_m), bool)
            if keep is not None and s.meta.id in keep:
                m &= np.asarray(keep[s.meta.id], bool)
            cps.append(cycle_points(s.meta.id, s.meta.cycle, s.X_tel, s.deviation_m,
                                    s.data.theta_rad, s.data.phi_rad, layout, cfg, keep=m))
            kap[s.meta.id] = float(s.alignment.kappa_rad)
        ps = position_surface(pos, cps, layout, cfg, _pointing(fits[0].meta), kap)
        ps.pointing.setdefault("elevation_deg", float(fits[0].elevation_deg))
        pf = next((p for p in getattr(campaign_fit, "position_fits", ()) or ()
                   if p.position == pos), None)
        if pf is not None:
            ps.adjusted_panels, ps.faces = panel_predictions(pf), pf.faces
        positions.append(ps)
    return SurfaceResult(cfg, layout, positions,
                         {"model": list(campaign_fit.model_names), "campaign": str(camp.root)})


def layout_for(fit_doc: Mapping | None = None, campaign=None) -> PanelLayout | None:
    """The panel layout of a campaign, or of the campaign a ``fit.json`` names, or the default."""
    if campaign is not None:
        return PanelLayout.from_telescope(campaign.telescope)
    root = (fit_doc or {}).get("campaign")
    if root and (Path(root) / "campaign.toml").exists():
        try:
            return PanelLayout.from_telescope(load_campaign(root).telescope)
        except Exception as e:  # noqa: BLE001
            log.warning("could not read %s (%s): default panel layout", root, e)
    return PanelLayout.default()


def surface_from_fit_dir(fit_dir, config: SurfaceConfig | None = None, *, campaign=None,
                         layout: PanelLayout | None | str = "auto",
                         keep: Mapping[str, np.ndarray] | None = None,
                         exclude: Iterable[str] = ()) -> SurfaceResult:
    """Surface products from a ``fit`` output directory (``fit.json`` + ``residuals/``).

    The layout comes from ``campaign`` (or the campaign ``fit.json`` names, or the default).
    ``keep`` masks are indexed by the residual tables' rows.
    """

    cfg = config or SurfaceConfig()
    fit_dir = Path(fit_dir)
    doc = verify_result_dir(fit_dir, "fit.json")  # a complete fit, or a one-line refusal
    if isinstance(layout, str):
        layout = layout_for(doc, campaign)
    exclude = set(exclude)
    pos_meta = {p["position"]: p for p in doc.get("positions", [])}
    groups: dict[str, list[dict]] = {}
    for s in doc["scans"]:
        if s["id"] not in exclude:
            groups.setdefault(s["position"], []).append(s)
    positions = []
    for pos, scans in groups.items():
        cps, kap = [], {}
        for s in scans:
            path = fit_dir / "residuals" / f"{s['id']}.parquet"
            if not path.exists():
                raise FileNotFoundError(f"{path}: residual table of scan {s['id']} not found "
                                        "(was the fit written with residuals?)")
            r = read_residuals(path, ("used", "face", "phi_rad", "theta_rad", "deviation_m",
                                      "X_m", "Y_m", "Z_m"))
            m = r["used"].astype(bool) if cfg.used_only else np.ones(len(r["used"]), bool)
            if keep is not None and s["id"] in keep:
                m &= np.asarray(keep[s["id"]], bool)
            X = np.column_stack([r["X_m"], r["Y_m"], r["Z_m"]])
            cps.append(cycle_points(s["id"], int(s["cycle"]), X, r["deviation_m"],
                                    r["theta_rad"], r["phi_rad"], layout, cfg, keep=m,
                                    face=r.get("face")))
            kap[s["id"]] = float(s.get("kappa_rad", float("nan")))
        pm = pos_meta.get(pos, {})
        pointing = {k: float(pm[k]) for k in ("ha_deg", "dec_deg", "elevation_deg", "azimuth_deg")
                    if pm.get(k) is not None}
        ps = position_surface(pos, cps, layout, cfg, pointing, kap)
        ps.adjusted_panels, ps.faces = list(pm.get("panels") or []), pm.get("faces")
        positions.append(ps)
    return SurfaceResult(cfg, layout, positions, {"model": doc.get("model"),
                                                  "fit_dir": str(fit_dir),
                                                  "campaign": doc.get("campaign")})


# --------------------------------------------------------------------------------------------
# Campaigns and outputs
# --------------------------------------------------------------------------------------------


def surface_campaign(campaign, config: SurfaceConfig | None = None, out_dir=None, *,
                     fit_dir=None, preprocess: bool = True, disturbed: str | None = None,
                     progress: bool = False, write_fit_dir: bool = True) -> SurfaceResult:
    """Surface products of a campaign, written to ``out_dir`` when given.

    Without ``fit_dir`` the campaign is fitted with ``config.model`` (default: extended) via
    :func:`._fit.fit_campaign` (after preprocessing when available and ``preprocess``), and the
    fit is written to ``out_dir/fit`` (``write_fit_dir``). With ``fit_dir`` its ``fit.json`` and
    residual tables are used. ``disturbed``: None (report only), ``"exclude"`` (leave disturbed
    scans out) or ``"cut"`` (drop their affected phi range; refitted when fitting here).
    """

    cfg = config or SurfaceConfig()
    if disturbed not in (None, "exclude", "cut"):
        raise ValueError(f"disturbed must be None, 'exclude' or 'cut', not {disturbed!r}")
    if fit_dir is not None:
        verify_result_dir(fit_dir, "fit.json")
        reports = detect_disturbed_residuals(fit_dir)
        bad = {r.scan: r for r in reports}
        keep = None
        if disturbed == "cut" and bad:
            keep = {}
            for sid, rep in bad.items():
                r = read_residuals(Path(fit_dir) / "residuals" / f"{sid}.parquet", ("phi_rad",))
                keep[sid] = cut_keep(r["phi_rad"], rep)
        res = surface_from_fit_dir(fit_dir, cfg, campaign=campaign, keep=keep,
                                   exclude=bad if disturbed == "exclude" else ())
    else:
        base = preprocess_keep(preprocess, campaign)
        cf = fit_campaign(campaign, cfg.model, keep=base, progress=progress)
        reports = detect_disturbed_campaign(cf)
        bad = {r.scan: r for r in reports}
        if disturbed == "cut" and bad:
            hint = mean_heading(scan_heading(s) for s in cf.scans)
            for i, s in enumerate(cf.scans):
                if s.meta.id in bad:
                    k = cut_keep(s.data.phi_rad, bad[s.meta.id])
                    if base is not None:
                        k &= base(s.meta, s.data)
                    cf.scans[i] = fit_scan(campaign, s.meta, cfg.model, data=s.data, keep=k,
                                           heading_hint_rad=hint)
        if out_dir is not None and write_fit_dir:
            write_fit(Path(out_dir) / "fit", cf)
        res = surface_from_fit(cf, cfg, exclude=bad if disturbed == "exclude" else ())
        res.source["fit_dir"] = str(Path(out_dir) / "fit") if out_dir and write_fit_dir else None
    res.disturbed = [dict(r.to_json(), action=disturbed or "reported") for r in reports]
    if out_dir is not None:
        write_surface(out_dir, res)
    return res


def surface_json(result: SurfaceResult) -> dict:
    """The ``surface.json`` document (schema ``hartrao-surface/1``)."""
    cfg = result.config
    positions = []
    for p in result.positions:
        cycles = []
        for c in p.cycles:
            rec = {"scan": c.scan, "cycle": c.cycle, "n_points": int(c.inside.sum()),
                   "n_masked": int((~c.inside).sum()), "rms_m": _num(c.rms_m),
                   "kappa_rad": _num(p.kappa_rad.get(c.scan, float("nan"))),
                   "points_file": f"cycles/{c.scan}.parquet"}
            tab = p.cycle_panels.get(c.scan)
            if tab is not None:
                rec["panels"] = tab.records()
            cycles.append(rec)
        a = p.averaged
        rec = {"position": p.position, **p.pointing, "kind": p.kind,
               "scans": [c.scan for c in p.cycles],
               "n_points": len(a), "n_unpaired": int(a.n_unpaired), "rms_m": _num(a.rms_m),
               "radius_m": p.radius_m,
               "face_difference_rms_m": _num(np.sqrt(np.nanmean(a.diff_m ** 2)))
               if np.isfinite(a.diff_m).any() else None,
               "points_file": f"points/{_safe(p.position)}.parquet",
               "panels": p.panels.records() if p.panels is not None else [],
               "cycles": cycles, "notes": p.notes}
        if p.faces is not None:
            rec["faces"] = p.faces
        if p.adjusted_panels:
            # per-panel offsets and tilts predicted by the two-face adjustment (surface random
            # effect, every point of both faces), with their sigmas
            rec["panels_adjusted"] = p.adjusted_panels
        positions.append(rec)
    lay = result.layout
    return {
        "schema": SURFACE_SCHEMA,
        "sign": "deviation_m > 0: towards the focus (above the paraboloid)",
        "frame": "telescope frame, north-aligned (X north, Y west at the zenith)",
        "config": asdict(cfg),
        "layout": ({"ring_edges_m": list(lay.ring_edges_m),
                    "panels_per_ring": list(lay.panels_per_ring)} if lay else None),
        "source": result.source,
        "disturbed": result.disturbed,
        "positions": positions,
    }


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "._-" else "_" for ch in str(name))


def write_surface_json(path, result: SurfaceResult) -> Path:
    """Write ``surface.json`` alone to ``path`` (a file, or a directory to put it in): strict
    JSON, written atomically, with an empty ``"files"`` manifest (no point tables)."""

    p = Path(path)
    if p.suffix != ".json":
        p = p / "surface.json"
    with OutputDir(p.parent, p.name) as od:
        return od.commit(surface_json(result), indent=1)


def write_surface(out_dir, result: SurfaceResult, *, cycles: bool = True) -> Path:
    """``surface.json`` + ``points/<position>.parquet`` (+ ``cycles/<scan>.parquet``).

    Crash-safe (:class:`._safeio.OutputDir`): the tables go to temporary names first,
    ``surface.json`` is written last and lists them with their sizes and SHA-256.
    """
    import pyarrow as pa


    with OutputDir(out_dir, "surface.json") as od:
        for p in result.positions:
            a = p.averaged
            od.write_parquet(f"points/{_safe(p.position)}.parquet", pa.table({
                "X_m": a.X[:, 0], "Y_m": a.X[:, 1], "Z_m": a.X[:, 2],
                "deviation_m": a.deviation_m, "panel": a.panel, "n1": a.n1, "n2": a.n2,
                "diff_m": a.diff_m,
            }))
            if cycles:
                for c in p.cycles:
                    od.write_parquet(f"cycles/{_safe(c.scan)}.parquet", pa.table({
                        "X_m": c.X[:, 0], "Y_m": c.X[:, 1], "Z_m": c.X[:, 2],
                        "deviation_m": c.deviation_m, "panel": c.panel, "face": c.face,
                        "phi_rad": c.phi_rad,
                    }))
        return od.commit(surface_json(result), indent=1)


def read_surface(out_dir) -> SurfaceResult:
    """Load what :func:`write_surface` wrote (``surface.json`` + the Parquet point tables)."""
    import pyarrow.parquet as pq


    out = Path(out_dir)
    doc = verify_result_dir(out, "surface.json")  # complete, or a one-line refusal
    if doc.get("schema") != SURFACE_SCHEMA:
        raise ValueError(f"{out / 'surface.json'}: schema: expected {SURFACE_SCHEMA!r}, found "
                         f"{doc.get('schema')!r}")
    lay = doc.get("layout")
    layout = PanelLayout(lay["ring_edges_m"], lay["panels_per_ring"]) if lay else None
    known = SurfaceConfig.__dataclass_fields__
    cfg = SurfaceConfig(**{k: v for k, v in (doc.get("config") or {}).items() if k in known})

    def table(recs):
        if not recs:
            return None
        cols = {k: np.array([np.nan if r.get(k) is None else r[k] for r in recs], float)
                for k in PANEL_KEYS}
        return PanelTable(panel=np.array([r["panel"] for r in recs]),
                          ring=np.array([r.get("ring", -1) for r in recs]),
                          n=np.array([r["n"] for r in recs]), **cols)

    positions = []
    for p in doc["positions"]:
        cycles, cyc_tabs, kap = [], {}, {}
        for c in p.get("cycles", []):
            f = out / c["points_file"]
            if f.exists():
                tb = pq.read_table(f)
                t = {k: v.to_numpy() for k, v in zip(tb.column_names, tb.columns)}
                cycles.append(CyclePoints(c["scan"], int(c["cycle"]),
                                          np.column_stack([t["X_m"], t["Y_m"], t["Z_m"]]),
                                          t["deviation_m"], t["panel"].astype(np.int32),
                                          t["face"].astype(np.int8), t["phi_rad"]))
            cyc_tabs[c["scan"]] = table(c.get("panels"))
            if c.get("kappa_rad") is not None:
                kap[c["scan"]] = c["kappa_rad"]
        f = out / p["points_file"]
        if f.exists():
            tb = pq.read_table(f)
            t = {k: v.to_numpy() for k, v in zip(tb.column_names, tb.columns)}
            avg = AveragedPoints(np.column_stack([t["X_m"], t["Y_m"], t["Z_m"]]),
                                 t["deviation_m"], t["panel"].astype(np.int32), t["n1"], t["n2"],
                                 t["diff_m"], int(p.get("n_unpaired", 0)))
        else:
            avg = AveragedPoints(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int32),
                                 np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        pointing = {k: p[k] for k in ("ha_deg", "dec_deg", "elevation_deg", "azimuth_deg")
                    if p.get(k) is not None}
        positions.append(PositionSurface(p["position"], pointing, cycles, avg,
                                         table(p.get("panels")), cyc_tabs, p.get("kind", ""),
                                         kap, list(p.get("notes", [])),
                                         float(p.get("radius_m") or 0.01)))
    return SurfaceResult(cfg, layout, positions, dict(doc.get("source") or {}),
                         list(doc.get("disturbed") or []))


__all__ = [
    "SURFACE_SCHEMA", "AveragedPoints", "CyclePoints", "PanelLayout", "PanelTable",
    "PositionSurface", "SurfaceConfig", "SurfaceResult", "cycle_average", "cycle_points",
    "averaging_radius", "layout_for", "panel_mask", "panel_statistics", "point_spacing",
    "position_surface", "read_residuals", "read_surface",
    "surface_campaign", "surface_from_fit", "surface_from_fit_dir", "surface_json",
    "write_surface", "write_surface_json",
]
