"""Drawing primitives: Agg figures and their PNG bytes, colour limits, dish axes, panel
outlines, the face boundary and rasters of deviations (given in m, shown in mm)."""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..campaign._safeio import write_bytes_atomic
from ..geometry._geometry import cell_code, grid_indices
from ..surface._surface import (
    PanelLayout,
    point_spacing,
)

DPI = 110
CMAP = "RdBu_r"
SIGN_LABEL = "deviation [mm]\n+ towards focus (above) / \u2212 away (below, sag)"
MAX_MAP_POINTS = 300_000

def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def png_bytes(fig) -> bytes:
    """The figure as PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, facecolor="white")
    return buf.getvalue()


def save_png(fig, path) -> Path:
    """The figure as PNG at ``path`` (temporary name + rename)."""

    return write_bytes_atomic(path, png_bytes(fig), durable=False)


def pixel_std(png: bytes) -> float:
    """Standard deviation of the grey levels of a PNG (0: a blank image)."""
    from matplotlib import image

    a = image.imread(io.BytesIO(png), format="png")
    return float(np.asarray(a[..., :3], float).mean(-1).std())


def _nice(v: float) -> float:
    """A round number >= v (1, 1.5, 2, 2.5, 3, 4, 5, 6, 8 x 10^k)."""
    if not np.isfinite(v) or v <= 0:
        return 1.0
    e = 10 ** math.floor(math.log10(v))
    for m in (1, 1.5, 2, 2.5, 3, 4, 5, 6, 8, 10):
        if m * e >= v * (1 - 1e-9):
            return m * e
    return 10 * e


def colour_limit_mm(values_m: Sequence[np.ndarray], q: float = 99.0) -> float:
    """Symmetric colour limit (mm): a round number above the ``q``-th percentile of |dev|."""
    v = np.concatenate([np.abs(np.asarray(x, float)) for x in values_m if len(x)] or [np.ones(1)])
    v = v[np.isfinite(v)]
    return _nice(1e3 * float(np.percentile(v, q))) if len(v) else 1.0


def _subsample(n: int, k: int = MAX_MAP_POINTS, seed: int = 0) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def _dish_axes(ax, R: float, title: str | None = None):
    """Dish map axes: horizontal Y (west to the left), vertical X (north up), equal scale."""
    ax.set_aspect("equal")
    ax.set_xlim(1.04 * R, -1.04 * R)  # inverted: +Y (west) on the left
    ax.set_ylim(-1.04 * R, 1.04 * R)
    ax.set_xlabel("Y [m]  (west \u2190)")
    ax.set_ylabel("X [m]  (north \u2191)")
    ax.tick_params(labelsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    ax.annotate("N", xy=(0.04, 0.97), xycoords="axes fraction", ha="center", va="top",
                fontsize=9, fontweight="bold")
    ax.annotate("", xy=(0.04, 0.93), xytext=(0.04, 0.83), xycoords="axes fraction",
                arrowprops=dict(arrowstyle="->", lw=1.2))


def _outline_segments(layout: PanelLayout, n_arc: int = 240) -> list[np.ndarray]:
    """Panel outlines (ring circles and radial panel sides) as (k, 2) arrays of (Y, X)."""
    segs = []
    t = np.linspace(0, 2 * np.pi, n_arc + 1)
    for r in layout.ring_edges_m:
        segs.append(np.column_stack([r * np.sin(t), r * np.cos(t)]))
    e = layout.ring_edges_m
    for k, n in enumerate(layout.panels_per_ring):
        for j in range(n):
            psi = 2 * np.pi * j / n
            segs.append(np.array([[e[k] * np.sin(psi), e[k] * np.cos(psi)],
                                  [e[k + 1] * np.sin(psi), e[k + 1] * np.cos(psi)]]))
    return segs


def _draw_outlines(ax, layout: PanelLayout | None, color="0.35", lw=0.4, alpha=0.7):
    if layout is None:
        return
    from matplotlib.collections import LineCollection

    ax.add_collection(LineCollection(_outline_segments(layout), colors=color, linewidths=lw,
                                     alpha=alpha, zorder=3))


def face_boundary(X: np.ndarray, face: np.ndarray, cell_m: float | None = None
                  ) -> np.ndarray | None:
    """The line on the dish where the scanner's face changes, from the data: ``(k, 2)`` (X, Y).

    Cells of a grid (about three point spacings) that hold points of both faces mark the
    boundary; a quadratic curve (the boundary is a plane through the scanner cut with the
    paraboloid: a circle of large radius in projection) is fitted through their centres
    along their principal direction, with outliers removed. None when one face is missing.
    """
    X = np.asarray(X, float)
    face = np.asarray(face)
    if len(X) < 10 or (face == 1).sum() < 5 or (face == 2).sum() < 5:
        return None
    idx = _subsample(len(X), 400_000, seed=1)
    X, face = X[idx, :2], face[idx]
    if cell_m is None:
        sp = point_spacing(X)
        cell_m = 3.0 * (sp if np.isfinite(sp) else 0.1)
    u, inv = np.unique(cell_code(grid_indices(X, (0.0, 0.0), cell_m)), return_inverse=True)
    inv = inv.reshape(-1)
    f1 = np.bincount(inv, weights=(face == 1), minlength=len(u))
    f2 = np.bincount(inv, weights=(face == 2), minlength=len(u))
    both = (f1 > 0) & (f2 > 0)
    if both.sum() < 3:
        return None
    cnt = np.bincount(inv, minlength=len(u))
    C = np.column_stack([np.bincount(inv, weights=X[:, j], minlength=len(u)) / cnt
                         for j in (0, 1)])[both]
    keep = np.ones(len(C), bool)
    for _ in range(4):
        m = C[keep].mean(0)
        _, _, vt = np.linalg.svd(C[keep] - m, full_matrices=False)
        d = vt[0]
        t = (C - m) @ d
        n = (C - m) @ np.array([-d[1], d[0]])
        deg = 2 if keep.sum() >= 6 else 1
        coef = np.polyfit(t[keep], n[keep], deg)
        res = n - np.polyval(coef, t)
        s = max(1.4826 * np.median(np.abs(res[keep])), cell_m)
        new = np.abs(res) < 3 * s
        if new.sum() < 3 or (new == keep).all():
            break
        keep = new
    tt = np.linspace(t[keep].min(), t[keep].max(), 100)
    nn = np.polyval(coef, tt)
    return m + np.outer(tt, d) + np.outer(nn, np.array([-d[1], d[0]]))


def _dish_radius(layout: PanelLayout | None, *Xs: np.ndarray) -> float:
    if layout is not None:
        return float(layout.ring_edges_m[-1])
    r = [np.nanmax(np.hypot(X[:, 0], X[:, 1])) for X in Xs if len(X)]
    return float(max(r)) if r else 13.0


def mean_spacing(X: np.ndarray, cell_m: float = 0.25) -> float:
    """Mean point spacing (m): sqrt(area covered / points), the area from occupied cells."""
    X = np.asarray(X, float)
    if len(X) < 3:
        return 0.1
    sub = X[_subsample(len(X), 1_000_000, seed=2)]
    area = len(np.unique(cell_code(grid_indices(sub[:, :2], (0.0, 0.0), cell_m)))) * cell_m**2
    return float(math.sqrt(area / len(X)))


def raster(X: np.ndarray, dev_m: np.ndarray, R: float, pixel_m: float | None = None,
           max_pixels: int = 520, points_per_pixel: float = 4.0) -> tuple[np.ndarray, float]:
    """Mean deviation (mm) per square pixel of the aperture plane: image rows along X (north),
    columns along Y, covering ``[-1.05 R, 1.05 R]`` in both; NaN where there is no point.

    The pixel is at least ``2.1 R / max_pixels`` and holds about ``points_per_pixel`` points
    on average (the noise of single points would hide the panels on coarse scans).
    """
    X = np.asarray(X, float)
    if pixel_m is None:
        pixel_m = max(2.1 * R / max_pixels, math.sqrt(points_per_pixel) * mean_spacing(X))
    n = int(math.ceil(2.1 * R / pixel_m))
    half = 0.5 * n * pixel_m
    iy = np.floor((X[:, 0] + half) / pixel_m).astype(np.int64)
    ix = np.floor((X[:, 1] + half) / pixel_m).astype(np.int64)
    ok = (ix >= 0) & (ix < n) & (iy >= 0) & (iy < n) & np.isfinite(dev_m)
    k = iy[ok] * n + ix[ok]
    c = np.bincount(k, minlength=n * n)
    v = np.bincount(k, weights=1e3 * np.asarray(dev_m, float)[ok], minlength=n * n)
    with np.errstate(invalid="ignore", divide="ignore"):
        img = (v / c).reshape(n, n)
    return img, half


def _map(ax, img: np.ndarray, half: float, lim_mm: float):
    from matplotlib import colormaps

    cmap = colormaps[CMAP].with_extremes(bad=(1, 1, 1, 0))
    return ax.imshow(img, origin="lower", extent=(-half, half, -half, half), cmap=cmap,
                     vmin=-lim_mm, vmax=lim_mm, interpolation="nearest", zorder=2)

