"""Figures and the self-contained HTML report (``hartrao-jax report RESULTS_DIR``).

Figures are drawn headless with matplotlib's Agg canvas (no pyplot, no display, no global
backend switch). Deviations are shown in millimetres with the sign convention of
``campaign-format.md`` in every colour bar: positive towards the focus (above the paraboloid),
negative away from it (a sagging panel is blue). Dish maps are in the north-aligned telescope
frame seen from the focus: X (north) up, Y (west) to the left.

* :func:`fig_cycle_maps`: residuals of every cycle of a position with the face boundary (paper
  Figs. 6, 7), the boundary computed from the data (:func:`face_boundary`);
* :func:`fig_average_map`: the cycle-averaged residuals with the panel outlines (Fig. 8);
* :func:`fig_panel_map`: panels coloured by their deviation, with ids and values;
* :func:`fig_focal_sky`: focal length per position on an HA/DEC plot and against elevation;
* :func:`fig_residual_distribution`: histogram and normal Q-Q plot of the residuals;
* :func:`fig_disturbed`: line medians of disturbed scans against phi;
* :func:`write_report`: all of them plus the result tables in one HTML page (PNG images
  embedded as base64), from a results directory with ``fit.json`` / ``surface.json`` /
  ``preprocess.json`` or from sub-directories holding them (``simplified/``, ``extended/``).
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import io
import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..campaign._campaign import CampaignError, load_campaign
from ..campaign._safeio import verify_result_dir, write_bytes_atomic, write_text_atomic
from ..surface._disturbed import detect_disturbed_residuals
from ..surface._surface import (
    PanelLayout,
    PositionSurface,
    SurfaceResult,
    point_spacing,
    read_residuals,
    read_surface,
    surface_from_fit_dir,
)

log = logging.getLogger("hartrao_jax")

DPI = 110
CMAP = "RdBu_r"
SIGN_LABEL = "deviation [mm]\n+ towards focus (above) / \u2212 away (below, sag)"
MAX_MAP_POINTS = 300_000


# --------------------------------------------------------------------------------------------
# Matplotlib helpers (object-oriented, Agg canvas)
# --------------------------------------------------------------------------------------------


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
    ij = np.floor(X / cell_m).astype(np.int64)
    key = ij[:, 0] * 1_000_003 + ij[:, 1]
    u, inv = np.unique(key, return_inverse=True)
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
    ij = np.floor(sub[:, :2] / cell_m).astype(np.int64)
    area = len(np.unique(ij[:, 0] * 1_000_003 + ij[:, 1])) * cell_m**2
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


# --------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------


def fig_cycle_maps(pos: PositionSurface, layout: PanelLayout | None = None, title: str = ""):
    """Per-cycle residual maps of one position with the face boundary (paper Figs. 6, 7)."""
    cycles = [c for c in pos.cycles if len(c)]
    n = max(1, len(cycles))
    w = 5.2 * n + 1.2
    fig = _figure(w, 5.6)
    axs = fig.subplots(1, n, squeeze=False)[0]
    R = _dish_radius(layout, *[c.X for c in cycles])
    imgs = [raster(c.X[c.inside], c.deviation_m[c.inside], R) for c in cycles]
    lim = colour_limit_mm([1e-3 * im[np.isfinite(im)] for im, _ in imgs])
    sc = None
    for ax, c, (img, half) in zip(axs, cycles, imgs):
        sc = _map(ax, img, half, lim)
        _draw_outlines(ax, layout, lw=0.25, alpha=0.4)
        fb = face_boundary(c.X, c.face)
        if fb is not None:
            ax.plot(fb[:, 1], fb[:, 0], color="red", lw=1.8, zorder=4, label="face 1 | face 2")
            ax.legend(loc="lower right", fontsize=8, framealpha=0.8)
        rms = 1e3 * c.rms_m
        _dish_axes(ax, R, f"{c.scan} (cycle {c.cycle}): rms {rms:.2f} mm")
    if sc is not None:
        cb = fig.colorbar(sc, ax=list(axs), shrink=0.85, extend="both")
        cb.set_label(SIGN_LABEL, fontsize=9)
    fig.suptitle(title or f"Residuals per cycle, position {pos.position}", fontsize=11)
    return fig


def fig_average_map(pos: PositionSurface, layout: PanelLayout | None = None, title: str = ""):
    """The cycle-averaged residuals of one position with panel outlines (paper Fig. 8)."""
    a = pos.averaged
    fig = _figure(7.0, 6.0)
    ax = fig.subplots()
    R = _dish_radius(layout, a.X)
    if len(a):
        img, half = raster(a.X, a.deviation_m, R)
        lim = colour_limit_mm([1e-3 * img[np.isfinite(img)]])
        sc = _map(ax, img, half, lim)
        cb = fig.colorbar(sc, ax=ax, shrink=0.85, extend="both")
        cb.set_label(SIGN_LABEL, fontsize=9)
    _draw_outlines(ax, layout)
    _dish_axes(ax, R, title or f"{pos.position}: {pos.kind}, rms {1e3 * a.rms_m:.2f} mm "
               f"({len(a):,} points, radius {100 * pos.radius_m:.2g} cm)")
    return fig


def _panel_polygons(layout: PanelLayout, n_arc: int = 8) -> list[np.ndarray]:
    g = layout.geometry()
    polys = []
    for i in range(layout.n_panels):
        t = np.linspace(g["psi_start"][i], g["psi_end"][i], n_arc)
        ri, ro = g["rho_in"][i], g["rho_out"][i]
        pts = np.concatenate([np.column_stack([ri * np.sin(t), ri * np.cos(t)]),
                              np.column_stack([ro * np.sin(t[::-1]), ro * np.cos(t[::-1])])])
        polys.append(pts)
    return polys


def fig_panel_map(pos: PositionSurface, layout: PanelLayout, title: str = ""):
    """Panels coloured by their deviation (mm), each labelled with its id and value."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import Normalize

    tab = pos.panels
    fig = _figure(10.0, 9.0)
    ax = fig.subplots()
    R = float(layout.ring_edges_m[-1])
    dev = tab.deviation_m if tab is not None else np.full(layout.n_panels, np.nan)
    lim = colour_limit_mm([dev[np.isfinite(dev)]], q=100)
    norm = Normalize(-lim, lim)
    cmap = colormaps[CMAP]
    colours = [cmap(norm(1e3 * d)) if np.isfinite(d) else (0.85, 0.85, 0.85, 1.0) for d in dev]
    ax.add_collection(PolyCollection(_panel_polygons(layout), facecolors=colours,
                                     edgecolors="0.25", linewidths=0.5))
    g = layout.geometry()
    for i in range(layout.n_panels):
        y, x = g["rho_c"][i] * np.sin(g["psi_c"][i]), g["rho_c"][i] * np.cos(g["psi_c"][i])
        v = dev[i]
        txt = f"{i}\n{1e3 * v:+.2f}" if np.isfinite(v) else f"{i}\n\u2013"
        dark = np.isfinite(v) and abs(norm(1e3 * v) - 0.5) > 0.33
        ax.text(y, x, txt, ha="center", va="center", fontsize=5.2, linespacing=0.95,
                color="white" if dark else "black")
    cb = fig.colorbar(ScalarMappable(norm, cmap), ax=ax, shrink=0.8, extend="both")
    cb.set_label("panel " + SIGN_LABEL, fontsize=9)
    _dish_axes(ax, R, title or f"{pos.position}: panel deviations (id, mm); grey: too few points")
    return fig


def fig_focal_sky(fits: Sequence[tuple[str, dict]], nominal_m: float | None = None):
    """Focal length per position: HA/DEC sky plot colour-coded (annotated f - f0 +- sigma) and
    f against elevation with error bars, for every fit given as ``(label, fit.json)``."""
    fig = _figure(12.0, 5.2)
    ax1, ax2 = fig.subplots(1, 2, width_ratios=[1.15, 1])
    main_label, main = fits[-1]
    pos = main.get("positions", [])
    f0 = nominal_m
    if f0 is None:
        vals = [p["f"]["value"] for p in pos]
        f0 = float(np.median(vals)) if vals else 0.0
    ref_txt = f"f\u2080 = {f0:.4f} m"
    has_hadec = pos and all(p.get("ha_deg") is not None for p in pos)
    if pos:
        xk, yk, xl, yl = (("ha_deg", "dec_deg", "hour angle [deg]", "declination [deg]")
                          if has_hadec else
                          ("azimuth_deg", "elevation_deg", "azimuth [deg]", "elevation [deg]"))
        x = np.array([p.get(xk) or 0.0 for p in pos], float)
        y = np.array([p.get(yk) or 0.0 for p in pos], float)
        df = np.array([1e3 * (p["f"]["value"] - f0) for p in pos])
        sg = np.array([1e3 * p["f"]["sigma"] for p in pos])
        lim = _nice(float(np.max(np.abs(df))) if len(df) else 1.0)
        sc = ax1.scatter(x, y, c=df, cmap=CMAP, vmin=-lim, vmax=lim, s=110, edgecolors="k",
                         linewidths=0.6, zorder=3)
        for xi, yi, d, s, p in zip(x, y, df, sg, pos):
            ax1.annotate(f"{p['position']}\n{d:+.2f}\u00b1{s:.2f}", (xi, yi), xytext=(0, 9),
                         textcoords="offset points", ha="center", va="bottom", fontsize=7)
        cb = fig.colorbar(sc, ax=ax1, shrink=0.9)
        cb.set_label("f \u2212 f\u2080 [mm]", fontsize=9)
        ax1.set_xlabel(xl)
        ax1.set_ylabel(yl)
        pad_x = max(10.0, 0.1 * np.ptp(x))
        pad_y = max(10.0, 0.15 * np.ptp(y))
        ax1.set_xlim(x.min() - pad_x, x.max() + pad_x)
        ax1.set_ylim(y.min() - pad_y, y.max() + 2 * pad_y)
        ax1.grid(alpha=0.3)
    ax1.set_title(f"Focal length per position ({main_label}, {ref_txt}); labels: "
                  "f \u2212 f\u2080 \u00b1 \u03c3 [mm]", fontsize=10)
    for k, (label, doc) in enumerate(fits):
        ps = doc.get("positions", [])
        if not ps:
            continue
        el = np.array([p.get("elevation_deg", np.nan) for p in ps], float)
        df = np.array([1e3 * (p["f"]["value"] - f0) for p in ps])
        sg = np.array([1e3 * p["f"]["sigma"] for p in ps])
        ax2.errorbar(el + 0.3 * (k - (len(fits) - 1) / 2), df, yerr=sg, fmt="o", ms=5,
                     capsize=3, label=label)
    ax2.axhline(0, color="0.5", lw=0.8)
    lo, hi = ax2.get_xlim()
    if hi - lo < 10:
        mid = 0.5 * (lo + hi)
        ax2.set_xlim(mid - 5, mid + 5)
    ax2.set_xlabel("elevation [deg]")
    ax2.set_ylabel(f"f \u2212 f\u2080 [mm]  ({ref_txt})")
    ax2.set_title("Focal length against elevation (error bars: 1 \u03c3)", fontsize=10)
    ax2.grid(alpha=0.3)
    if len(fits) > 1:
        ax2.legend(fontsize=8)
    return fig


def fig_residual_distribution(samples: Sequence[tuple[str, np.ndarray]]):
    """Histogram (with the normal density of the same mean and sigma) and normal Q-Q plot of
    residuals (deviations, m) of one or more fits given as ``(label, values)``."""
    from scipy import stats

    fig = _figure(12.0, 4.8)
    ax1, ax2 = fig.subplots(1, 2)
    lim = 0.0
    for _, v in samples:
        v = np.asarray(v, float)
        v = v[np.isfinite(v)]
        if len(v):
            lim = max(lim, 1e3 * float(np.percentile(np.abs(v), 99.8)))
    lim = _nice(lim) if lim > 0 else 1.0
    bins = np.linspace(-lim, lim, 121)
    p = np.linspace(0.0005, 0.9995, 1500)
    zq = stats.norm.ppf(p)
    for label, v in samples:
        v = 1e3 * np.asarray(v, float)
        v = v[np.isfinite(v)]
        if not len(v):
            continue
        mu, sd = float(v.mean()), float(v.std())
        rs = 1.4826 * float(np.median(np.abs(v - np.median(v))))
        h = ax1.hist(v, bins=bins, density=True, histtype="step", lw=1.4,
                     label=f"{label}: rms {math.sqrt(mu * mu + sd * sd):.3f} mm, robust \u03c3 "
                           f"{rs:.3f} mm (n = {len(v):,})")
        col = h[2][0].get_edgecolor()
        xx = np.linspace(-lim, lim, 400)
        ax1.plot(xx, stats.norm.pdf(xx, mu, sd), color=col, lw=0.9, ls="--")
        q = np.quantile(v, p)
        ax2.plot(zq, (q - mu) / sd, ".", ms=2.5, color=col, label=label)
    ax1.set_yscale("log")
    ax1.set_ylim(bottom=1e-4)
    ax1.set_xlabel("residual (normal deviation) [mm]; + towards the focus")
    ax1.set_ylabel("density (log)")
    ax1.set_title("Residual histogram (dashed: normal density, same mean and \u03c3)",
                  fontsize=10)
    ax1.legend(fontsize=7.5, loc="upper left")
    ax1.grid(alpha=0.3)
    z = np.array([-4, 4])
    ax2.plot(z, z, color="0.3", lw=1, label="normal")
    ax2.set_xlabel("normal quantile")
    ax2.set_ylabel("standardised residual quantile")
    ax2.set_title("Normal Q-Q plot", fontsize=10)
    ax2.set_xlim(-4, 4)
    ax2.set_ylim(-6, 6)
    ax2.legend(fontsize=8, loc="upper left")
    ax2.grid(alpha=0.3)
    return fig


def fig_disturbed(reports: Sequence):
    """Line medians (face 1 and face 2 halves) against raw phi for disturbed scans, with the
    detected range shaded; the face boundary is at the ends of the phi range."""
    reps = [r for r in reports if getattr(r, "series", None)]
    n = max(1, len(reps))
    fig = _figure(11.0, 2.9 * n + 0.6)
    axs = fig.subplots(n, 1, squeeze=False)[:, 0]
    for ax, r in zip(axs, reps):
        ph = r.series["phi_deg"]
        S = 1e3 * r.series["series_m"]
        for k, lab in ((0, "face 1 half-lines"), (1, "face 2 half-lines")):
            ax.plot(ph, S[k], ".-", ms=2.5, lw=0.7, label=lab)
        a, b = sorted((r.phi_deg, r.phi_end_deg))
        ax.axvspan(a, b, color="orange", alpha=0.3, label=f"disturbed {a:.1f}\u2013{b:.1f} deg")
        ax.axhline(0, color="0.5", lw=0.7)
        ref = f" minus {r.reference} (same dish lines)" if r.reference else ""
        ax.set_title(f"{r.scan} (cycle {r.cycle}): median residual per phi line{ref}; jump "
                     f"{1e3 * r.jump_m:+.2f} mm, statistic {r.statistic:.1f} "
                     f"(threshold {r.threshold:g})", fontsize=9)
        ax.set_xlabel("raw horizontal angle phi [deg]")
        ax.set_ylabel("median [mm]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7.5, loc="lower right")
        finite = S[np.isfinite(S)]
        if len(finite):
            lo, hi = np.percentile(finite, [0.5, 99.5])
            pad = 0.3 * (hi - lo + 1e-3)
            ax.set_ylim(min(lo, 1e3 * r.jump_m) - pad, max(hi, 1e3 * r.jump_m) + pad)
    return fig


def fig_panel_truth(est_m: np.ndarray, truth_m: np.ndarray, title: str = ""):
    """Estimated against simulated panel offsets (mm) with the 1:1 line and the correlation."""
    fig = _figure(5.5, 5.0)
    ax = fig.subplots()
    ok = np.isfinite(est_m) & np.isfinite(truth_m)
    e, t = 1e3 * est_m[ok], 1e3 * truth_m[ok]
    ax.scatter(t, e, s=12, alpha=0.8)
    lim = _nice(float(np.max(np.abs(np.concatenate([e, t])))) if len(e) else 1.0)
    ax.plot([-lim, lim], [-lim, lim], color="0.4", lw=1)
    r = float(np.corrcoef(e, t)[0, 1]) if len(e) > 2 else float("nan")
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_aspect("equal")
    ax.set_xlabel("simulated panel offset [mm]")
    ax.set_ylabel("estimated panel deviation [mm]")
    ax.set_title(title or f"Panels against the simulator's truth: r = {r:.3f}", fontsize=10)
    ax.grid(alpha=0.3)
    return fig


def pixel_std(png: bytes) -> float:
    """Standard deviation of the grey levels of a PNG (0: a blank image)."""
    from matplotlib import image

    a = image.imread(io.BytesIO(png), format="png")
    return float(np.asarray(a[..., :3], float).mean(-1).std())


# --------------------------------------------------------------------------------------------
# Collecting results
# --------------------------------------------------------------------------------------------

_MODEL_ORDER = {"simplified": 0, "extended": 1}


@dataclass
class ReportInputs:
    root: Path
    fits: list[tuple[str, Path, dict]] = field(default_factory=list)
    surfaces: list[tuple[str, SurfaceResult]] = field(default_factory=list)
    preprocess: list[tuple[str, dict]] = field(default_factory=list)
    disturbed: list = field(default_factory=list)  # DisturbedReport objects or dicts
    campaign: Any = None
    truth: dict | None = None


def _label(root: Path, d: Path) -> str:
    rel = d.relative_to(root)
    return str(rel) if str(rel) != "." else "results"


def _find(root: Path, name: str) -> list[Path]:
    out = [root / name] if (root / name).is_file() else []
    for pat in (f"*/{name}", f"*/*/{name}"):
        out += sorted(root.glob(pat))
    return out


def collect(results_dir, campaign=None) -> ReportInputs:
    """Find fits, surfaces, preprocessing and disturbed-scan results under ``results_dir``."""
    root = Path(results_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: results directory not found")
    inp = ReportInputs(root)

    for p in _find(root, "fit.json"):
        # an incomplete or mixed fit directory is refused (one-line CampaignError)
        doc = verify_result_dir(p.parent, "fit.json")
        if str(doc.get("schema", "")).startswith("hartrao-fit/"):
            inp.fits.append((_label(root, p.parent), p.parent, doc))
    inp.fits.sort(key=lambda t: (_MODEL_ORDER.get(Path(t[0]).name, 5), t[0]))
    if campaign is None:
        for _, _, doc in inp.fits:
            c = doc.get("campaign")
            if c and (Path(c) / "campaign.toml").exists():
                try:
                    campaign = load_campaign(c)
                    break
                except Exception as e:  # noqa: BLE001
                    log.warning("campaign %s not readable: %s", c, e)
    inp.campaign = campaign
    if campaign is not None and (Path(campaign.root) / "truth.json").exists():
        try:
            inp.truth = json.loads((Path(campaign.root) / "truth.json").read_text())
        except (OSError, ValueError):
            pass
    for p in _find(root, "surface.json"):
        try:
            verify_result_dir(p.parent, "surface.json")  # refused when incomplete or mixed
            inp.surfaces.append((_label(root, p.parent), read_surface(p.parent)))
        except Exception as e:  # noqa: BLE001
            if isinstance(e, CampaignError):
                raise
            log.warning("%s: not readable (%s), skipped", p, e)
    inp.surfaces.sort(key=lambda t: (_MODEL_ORDER.get(Path(t[0]).name, 5), t[0]))  # as fits
    if not inp.surfaces:
        for label, d, _ in inp.fits:
            if (d / "residuals").is_dir():
                try:
                    inp.surfaces.append((label, surface_from_fit_dir(d, campaign=campaign)))
                except Exception as e:  # noqa: BLE001
                    log.warning("surface products of %s failed: %s", d, e)
    for p in _find(root, "preprocess.json"):
        try:
            inp.preprocess.append((_label(root, p.parent), json.loads(p.read_text())))
        except (OSError, ValueError):
            pass
    main = _main_fit(inp)
    if main is not None and (main[1] / "residuals").is_dir():
        try:
            inp.disturbed = detect_disturbed_residuals(main[1])
        except Exception as e:  # noqa: BLE001
            log.warning("disturbed-scan search failed: %s", e)
    else:
        for _, s in inp.surfaces:
            inp.disturbed += list(s.disturbed)
    if not inp.disturbed:
        for p in _find(root, "disturbed.json"):
            try:
                inp.disturbed += list(json.loads(p.read_text()).get("disturbed", []))
            except (OSError, ValueError):
                pass
    return inp


def _main_fit(inp: ReportInputs):
    return inp.fits[-1] if inp.fits else None


# --------------------------------------------------------------------------------------------
# HTML
# --------------------------------------------------------------------------------------------

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:2em auto;
max-width:1250px;color:#222;line-height:1.4;padding:0 1em}
h1{font-size:1.6em}h2{border-bottom:2px solid #ddd;padding-bottom:.2em;margin-top:2em}
h3{margin-top:1.5em}table{border-collapse:collapse;margin:.6em 0;font-size:.85em}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:right}th{background:#f2f2f2}
td:first-child,th:first-child{text-align:left}figure{margin:1em 0}
figure img{max-width:100%;border:1px solid #eee}figcaption{font-size:.85em;color:#555}
.note{color:#8a5300}.small{font-size:.85em;color:#555}details{margin:.5em 0}
nav ul{columns:2}code{background:#f5f5f5;padding:0 3px}
"""


def _esc(x) -> str:
    return html.escape(str(x))


def _table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    h = "".join(f"<th>{_esc(c)}</th>" for c in headers)
    body = "".join("<tr>" + "".join(f"<td>{_esc(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>"


def _f(v, fmt="{:.4f}", scale=1.0, none="\u2013"):
    if v is None:
        return none
    try:
        v = float(v)
    except (TypeError, ValueError):
        return str(v)
    return fmt.format(v * scale) if math.isfinite(v) else none


class _Doc:
    def __init__(self, fig_dir: Path | None):
        self.parts: list[str] = []
        self.toc: list[tuple[str, str]] = []
        self.fig_dir = fig_dir
        self.n_fig = 0
        self.figures: list[Path] = []

    def h2(self, title: str, anchor: str):
        self.toc.append((anchor, title))
        self.parts.append(f'<h2 id="{anchor}">{_esc(title)}</h2>')

    def add(self, s: str):
        self.parts.append(s)

    def figure(self, fig, caption: str, name: str):
        png = png_bytes(fig)
        self.n_fig += 1
        if self.fig_dir is not None:
            p = self.fig_dir / f"{self.n_fig:02d}_{name}.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(png)
            self.figures.append(p)
        b64 = base64.b64encode(png).decode("ascii")
        self.parts.append(f'<figure><img alt="{_esc(name)}" src="data:image/png;base64,{b64}">'
                          f"<figcaption>Figure {self.n_fig}. {_esc(caption)}</figcaption></figure>")


def _fit_section(doc: _Doc, inp: ReportInputs):
    if not inp.fits:
        return
    doc.h2("Adjustment (fit.json)", "fit")
    for label, d, fj in inp.fits:
        model = fj.get("model", [])
        doc.add(f"<h3>{_esc(label)}: model {_esc(', '.join(model))}</h3>")
        extra = [n for n in model if n not in ("tx", "ty", "tz", "rx", "ry", "f")]
        heads = ["scan", "position", "cycle", "f [m]", "\u03c3 f [mm]", "\u03c30", "points",
                 "rejected", "iter", "\u03ba [deg]"]
        unit_of = {}
        for n in extra:
            u = None
            for s in fj.get("scans", []):
                u = s.get("estimates", {}).get(n, {}).get("unit")
                if u:
                    break
            unit_of[n] = u or ""
            heads.append(f"{n} [{'arcsec' if u == 'rad' else 'mm' if u == 'm' else u or ''}]")
        rows = []
        for s in fj.get("scans", []):
            est = s.get("estimates", {})
            f = est.get("f", {})
            row = [s.get("id"), s.get("position"), s.get("cycle"), _f(f.get("value"), "{:.5f}"),
                   _f(f.get("sigma"), "{:.3f}", 1e3), _f(s.get("sigma0"), "{:.3f}"),
                   s.get("n_points"), s.get("n_rejected"),
                   f"{s.get('iterations')}{'' if s.get('converged', True) else ' (!)'}",
                   _f(s.get("kappa_rad"), "{:.3f}", 180 / math.pi)]
            for n in extra:
                e = est.get(n, {})
                sc = 206264.806 if unit_of[n] == "rad" else 1e3 if unit_of[n] == "m" else 1.0
                v, sg = e.get("value"), e.get("sigma")
                row.append(f"{_f(v, '{:.2f}', sc)} \u00b1 {_f(sg, '{:.2f}', sc)}")
            rows.append(row)
        doc.add(_table(heads, rows))
        notes = [(s["id"], n) for s in fj.get("scans", []) for n in s.get("notes", [])]
        if notes:
            doc.add("<ul class='note'>" + "".join(f"<li>{_esc(i)}: {_esc(n)}</li>"
                                                   for i, n in notes) + "</ul>")
        prow = []
        for p in fj.get("positions", []):
            fp = p.get("f") or {}
            prow.append([p.get("position"), _position_kind(p), _f(p.get("ha_deg"), "{:.1f}"),
                         _f(p.get("dec_deg"), "{:.1f}"), _f(p.get("elevation_deg"), "{:.2f}"),
                         _f(fp.get("value"), "{:.6f}"), _f(fp.get("sigma"), "{:.4f}", 1e3),
                         ", ".join(p.get("scans", []))])
        doc.add("<p class='small'>Positions: both faces adjusted together, or a position with "
                "one usable cycle (labelled so: no cycle average, the two-face-sensitive errors "
                "do not cancel).</p>")
        doc.add(_table(["position", "faces", "HA [deg]", "DEC [deg]", "elevation [deg]",
                        "f [m]", "\u03c3 f [mm]", "scans"], prow))


def _position_kind(p: dict) -> str:
    """How a fit.json position was formed: two faces, or one usable cycle (never called a
    cycle average)."""
    faces = p.get("faces")
    if faces == 1 or (faces is None and len(p.get("scans", [])) < 2):
        return "one usable cycle"
    return str(p.get("kind") or ("two faces" if faces == 2 else "mean of the cycles"))


def _focal_section(doc: _Doc, inp: ReportInputs):
    if not inp.fits:
        return
    nominal = inp.campaign.telescope.focal_length_m if inp.campaign is not None else None
    doc.h2("Focal length across positions", "focal")
    fig = fig_focal_sky([(label, fj) for label, _, fj in inp.fits], nominal)
    doc.figure(fig, "Left: focal length of each position on the sky (hour angle, declination), "
               "colour and label f \u2212 f\u2080 \u00b1 \u03c3 in mm, f\u2080 the nominal focal "
               "length; right: against elevation for every fit.", "focal_length")


def _residual_section(doc: _Doc, inp: ReportInputs):
    samples = []
    rng = np.random.default_rng(0)
    for label, d, fj in inp.fits:
        vals = []
        scans = fj.get("scans", [])
        per_scan = max(20_000, 2_000_000 // max(len(scans), 1))  # a sample is enough
        for s in scans:
            p = d / "residuals" / f"{s['id']}.parquet"
            if p.exists():
                r = read_residuals(p, ("deviation_m", "used"))
                v = r["deviation_m"][r["used"].astype(bool)]
                if len(v) > per_scan:
                    v = v[rng.choice(len(v), per_scan, replace=False)]
                vals.append(v)
        if vals:
            samples.append((label, np.concatenate(vals)))
    if not samples:
        return
    doc.h2("Residual distribution", "residuals")
    doc.figure(fig_residual_distribution(samples),
               "Residuals (normal deviation of the points used in the adjustment) of every fit: "
               "histogram with the normal density of the same mean and standard deviation, and "
               "normal Q-Q plot of the standardised residuals. Heavy tails or a skew show "
               "unmodelled structure (panels, instrument errors) or leftover outliers.",
               "residual_distribution")


def _surface_section(doc: _Doc, inp: ReportInputs, max_positions: int):
    if not inp.surfaces:
        return
    doc.h2("Surface deviations", "surface")
    doc.add("<p class='small'>Maps: north-aligned telescope frame seen from the focus, X "
            "(north) up, Y (west) to the left; colour = normal deviation in mm, positive "
            "towards the focus (above the paraboloid), negative away from it (sag). Panel "
            "edges are masked; cycles are averaged panel by panel, never across two "
            "panels.</p>")
    main_label = inp.surfaces[-1][0]
    for label, res in inp.surfaces:
        doc.add(f"<h3>{_esc(label)}</h3>")
        rows = []
        for p in res.positions:
            cyc = "; ".join(f"{c.scan}: {1e3 * c.rms_m:.3f}" for c in p.cycles)
            rows.append([p.position, p.kind, cyc, _f(p.averaged.rms_m, "{:.3f}", 1e3),
                         f"{len(p.averaged):,}", f"{p.averaged.n_unpaired:,}",
                         _f(p.radius_m, "{:.2g}", 100), "; ".join(p.notes)])
        doc.add(_table(["position", "kind", "rms per cycle [mm]", "rms averaged [mm]",
                        "averaged points", "unpaired points", "radius [cm]", "notes"], rows))
        shown = res.positions[:max_positions]
        if len(res.positions) > len(shown):
            doc.add(f"<p class='note'>Maps of the first {len(shown)} of "
                    f"{len(res.positions)} positions.</p>")
        for p in shown:
            if any(len(c) for c in p.cycles):
                doc.figure(fig_cycle_maps(p, res.layout, f"{label}: residuals per cycle, "
                                          f"position {p.position}"),
                           f"{label}, {p.position}: residuals of each cycle; red: the face "
                           "boundary (from the data: where face-1 and face-2 points meet). "
                           "Two-face-sensitive errors change sign across it and between the "
                           "cycles (paper Figs. 6 and 7).", f"cycles_{label}_{p.position}")
            if len(p.averaged):
                doc.figure(fig_average_map(p, res.layout, f"{label}, {p.position}: "
                                           f"{p.kind}, rms {1e3 * p.averaged.rms_m:.2f} mm"),
                           f"{label}, {p.position}: cycle-averaged residuals (paper Fig. 8): "
                           "points of cycles 1 and 2 within the averaging radius, one panel at "
                           "a time; the two-face-sensitive errors cancel.",
                           f"average_{label}_{p.position}")
            if label == main_label and res.layout is not None and p.panels is not None:
                doc.figure(fig_panel_map(p, res.layout),
                           f"{label}, {p.position}: per-panel deviation (mean of the panel's "
                           "cycle-averaged points), panel id and value in mm; grey: too few "
                           "points.",
                           f"panels_{label}_{p.position}")
                _panel_table(doc, p)
                _truth_panels(doc, inp, p)


def _panel_table(doc: _Doc, p: PositionSurface):
    t = p.panels
    order = np.argsort(-np.nan_to_num(np.abs(t.deviation_m), nan=-1))
    rows = []
    for i in order:
        rows.append([int(t.panel[i]), int(t.ring[i]), _f(t.deviation_m[i], "{:+.3f}", 1e3),
                     _f(t.sigma_m[i], "{:.3f}", 1e3), _f(t.tilt_rad[i], "{:.3f}", 1e3),
                     _f(t.tilt_radial_rad[i], "{:+.3f}", 1e3),
                     _f(t.tilt_tangential_rad[i], "{:+.3f}", 1e3), _f(t.rms_m[i], "{:.3f}", 1e3),
                     _f(t.rms_plane_m[i], "{:.3f}", 1e3), int(t.n[i])])
    heads = ["panel", "ring", "deviation [mm]", "\u03c3 [mm]", "tilt [mrad]", "radial [mrad]",
             "tangential [mrad]", "rms [mm]", "rms about plane [mm]", "n"]
    doc.add(f"<p class='small'>Panels of {_esc(p.position)} with the largest |deviation|:</p>")
    doc.add(_table(heads, rows[:12]))
    doc.add(f"<details><summary>all {len(rows)} panels</summary>{_table(heads, rows)}"
            "</details>")


def _truth_panels(doc: _Doc, inp: ReportInputs, p: PositionSurface):
    t = inp.truth
    if not t or "reflector" not in t:
        return
    off = np.asarray(t["reflector"].get("offset_m") or [], float)
    if len(off) != len(p.panels.deviation_m) or not np.any(off):
        return
    doc.figure(fig_panel_truth(p.panels.deviation_m, off),
               f"{p.position}: estimated panel deviations against the simulator's panel "
               "offsets (truth.json); the fitted paraboloid absorbs their mean and its "
               "focal-length-like part, so the cloud may be shifted slightly from the 1:1 line.",
               f"truth_panels_{p.position}")


def _preprocess_section(doc: _Doc, inp: ReportInputs):
    if not inp.preprocess:
        return
    doc.h2("Preprocessing (preprocess.json)", "preprocess")
    for label, pj in inp.preprocess:
        doc.add(f"<h3>{_esc(label)}</h3>")
        rows, stages = [], []
        for s in pj.get("scans", []):
            rm = s.get("removed", {})
            stages = stages or list(rm)
            rows.append([s.get("id"), f"{s.get('n_rows', 0):,}", f"{s.get('n_kept', 0):,}",
                         _f(s.get("kept_fraction"), "{:.1%}")]
                        + [f"{rm.get(k, 0):,}" for k in stages]
                        + [s.get("n_patches_fitted", ""),
                           _f(s.get("plane_rms_median_m"), "{:.3f}", 1e3)])
        doc.add(_table(["scan", "rows", "kept", "kept %"] + [f"removed: {k}" for k in stages]
                       + ["patches", "plane rms [mm]"], rows))


def _disturbed_section(doc: _Doc, inp: ReportInputs):
    doc.h2("Disturbed scans", "disturbed")
    reps = inp.disturbed
    if not reps:
        doc.add("<p>No scan shows a jump of its residuals along one horizontal angle (the "
                "paper's brake / settling disturbance).</p>")
        return
    rows = []
    for r in reps:
        j = r.to_json() if hasattr(r, "to_json") else r
        a, b = j.get("phi_range_deg", [j.get("phi_deg"), j.get("phi_end_deg")])
        rows.append([j["scan"], j["cycle"], _f(j["phi_deg"], "{:.2f}"), f"{a:.2f} \u2013 {b:.2f}",
                     _f(j["jump_m"], "{:+.3f}", 1e3), _f(j["statistic"], "{:.1f}"),
                     j.get("kind", ""), j.get("reference") or "\u2013"])
    doc.add(_table(["scan", "cycle", "phi [deg]", "phi range [deg]", "jump [mm]", "statistic",
                    "kind", "reference"], rows))
    doc.add("<p class='small'>Exclude them with <code>--exclude-disturbed</code> or cut the "
            "range with <code>--cut-disturbed</code>.</p>")
    if any(getattr(r, "series", None) for r in reps):
        doc.figure(fig_disturbed(reps), "Median residual of every phi line (its face-1 and "
                   "face-2 halves, theta structure removed, minus the other cycle's same dish "
                   "lines when available) against phi, with the detected range.", "disturbed")


def write_report(results_dir, campaign=None, out: str | Path | None = None, *,
                 max_positions: int = 4, figures_dir: bool = True) -> Path:
    """Write one self-contained HTML page for a results directory; returns its path.

    ``results_dir`` holds ``fit.json`` (+ ``residuals/``), ``surface.json`` and/or
    ``preprocess.json``, or sub-directories that do (the ``demo`` layout ``simplified/``,
    ``extended/``). Without ``surface.json`` the surface products are computed from the
    residual tables. ``campaign`` (optional) gives the panel layout, the nominal focal length
    and, for simulated campaigns, the truth. The page goes to ``out`` (default
    ``results_dir/report.html``); the PNGs also to ``results_dir/figures/``.
    """
    inp = collect(results_dir, campaign)
    root = inp.root
    if not (inp.fits or inp.surfaces or inp.preprocess):
        raise FileNotFoundError(f"{root}: no fit.json, surface.json or preprocess.json found "
                                "(in the directory or its sub-directories)")
    doc = _Doc(root / "figures" if figures_dir else None)
    _fit_section(doc, inp)
    _focal_section(doc, inp)
    _residual_section(doc, inp)
    _surface_section(doc, inp, max_positions)
    _disturbed_section(doc, inp)
    _preprocess_section(doc, inp)
    camp = inp.campaign
    title = f"hartrao-jax report: {camp.telescope.name}" if camp is not None else \
        "hartrao-jax report"
    toc = "".join(f'<li><a href="#{a}">{_esc(t)}</a></li>' for a, t in doc.toc)
    meta = [f"results: <code>{_esc(root.resolve())}</code>",
            f"generated {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC"]
    if camp is not None:
        meta.append(f"campaign: <code>{_esc(camp.root)}</code> ({len(camp.scans)} scans)")
    page = (f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{_esc(title)}"
            f"</title><style>{_CSS}</style></head><body><h1>{_esc(title)}</h1>"
            f"<p class='small'>{' &middot; '.join(meta)}</p><nav><ul>{toc}</ul></nav>"
            + "\n".join(doc.parts) + "</body></html>")

    return write_text_atomic(Path(out) if out is not None else root / "report.html", page)


__all__ = [
    "CMAP", "SIGN_LABEL", "colour_limit_mm", "collect", "face_boundary", "fig_average_map",
    "fig_cycle_maps", "fig_disturbed", "fig_focal_sky", "fig_panel_map", "fig_panel_truth",
    "fig_residual_distribution", "pixel_std", "png_bytes", "save_png", "write_report",
]


# --------------------------------------------------------------------------------------------
# diagnosis: local deformation figures (residual maps before/after, matched-filter map)
# --------------------------------------------------------------------------------------------


def diagnosis_local_figures(diag, out_dir) -> list[tuple[str, str]]:
    """Figures of the local-deformation search of a :class:`~._diagnose.Diagnosis`: for each
    search the residual map before (and after, when the deformation was accepted and modelled)
    and the matched-filter map (roughness-standardised score ``t`` at the candidate's width),
    the candidate outlined by a circle of radius ``2 w`` (solid: accepted; dashed: the largest
    local structure, not distinguishable from the roughness). Returns ``(title, file)`` rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    out = Path(out_dir)
    rows: list[tuple[str, str]] = []
    hist = diag.history
    if not hist or not diag.local_search:
        return rows
    ids = list(hist[0]["maps"])[:2]
    for rec in diag.local_search:
        maps = rec.get("_maps") or []
        if not maps or rec.get("x_m") is None:
            continue
        k = rec.get("search", 1)
        accepted = bool(rec.get("accepted"))
        after = next((h for h in hist if h.get("label") == "local_deformation"
                      and h.get("step", 0) >= k), None) if accepted else None
        m = min(maps, key=lambda mm: abs(mm.width_m - rec["width_m"]))
        x0, y0 = rec["where"]["x_m"] if accepted else rec["x_m"], (
            rec["where"]["y_m"] if accepted else rec["y_m"])
        w = rec["estimate"]["width_m"]["value"] if accepted else rec["width_m"]
        ncol = 3 if after is not None else 2
        fig, axes = plt.subplots(len(ids), ncol, figsize=(4.2 * ncol, 3.9 * len(ids)),
                                 squeeze=False)
        for r_, sid in enumerate(ids):
            ext = diag.extents.get(sid, [-13.0, 13.0, -13.0, 13.0])
            b = hist[0]["maps"][sid]
            fin = np.abs(b[np.isfinite(b)])
            lim = 1e3 * float(np.percentile(fin, 98)) if fin.size else 0.5
            panels = [("residual before [mm]", b)] + (
                [("residual after [mm]", after["maps"][sid])] if after is not None else [])
            for c_, (lab, mp) in enumerate(panels):
                ax = axes[r_, c_]
                im = ax.imshow(1e3 * mp.T, origin="lower", extent=ext, cmap="RdBu_r",
                               vmin=-lim, vmax=lim)
                ax.set_title(f"{sid}: {lab}", fontsize=9)
                fig.colorbar(im, ax=ax, shrink=0.7)
            ax = axes[r_, ncol - 1]
            t = np.where(m.valid, m.t, np.nan)
            e = [m.origin[0], m.origin[0] + m.cell_m * t.shape[0],
                 m.origin[1], m.origin[1] + m.cell_m * t.shape[1]]
            tl = float(np.nanmax(np.abs(t))) if np.isfinite(t).any() else 1.0
            im = ax.imshow(t.T, origin="lower", extent=e, cmap="PuOr_r", vmin=-tl, vmax=tl)
            ax.set_xlim(ext[0], ext[1])
            ax.set_ylim(ext[2], ext[3])
            ax.set_title(f"matched filter t, w = {m.width_m:g} m", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.7)
            for ax in axes[r_]:
                ax.add_patch(Circle((x0, y0), 2 * w, fill=False, lw=1.2, color="k",
                                    ls="-" if accepted else "--"))
                ax.set_aspect("equal")
                ax.set_xlabel("X [m]")
                ax.set_ylabel("Y [m]")
        state = "accepted and modelled" if accepted else "not distinguishable from the roughness"
        fig.suptitle(f"local deformation search {k}: {state}", fontsize=10)
        name = f"local_deformation_{k}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        rows.append((f"local deformation search {k}: {state}", name))
    return rows
