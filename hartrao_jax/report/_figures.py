"""The report's figures, one function each; deviations in mm with the sign convention of
``campaign-format.md`` (+ towards the focus)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..surface._surface import (
    PanelLayout,
    PositionSurface,
)
from ._draw import (
    CMAP,
    SIGN_LABEL,
    _dish_axes,
    _dish_radius,
    _draw_outlines,
    _figure,
    _map,
    _nice,
    colour_limit_mm,
    face_boundary,
    raster,
)


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
