"""Localised deformations: find and measure bumps and dents in the surface deviations.

A deformation the catalog does not name (an actuator pushed into the surface, a dented panel,
a hail strike) shows as a compact blob in the map of surface deviations. The search smooths the
deviations at several scales with a band-pass (a Gaussian at the scale minus one at four times
the scale, so a smooth misfit of the whole surface does not count), divides by the standard
error of the smoothed mean, and takes the most significant peak. A 2-D Gaussian bump
``A exp(-d^2 / 2 w^2)`` on a local plane is then fitted to the points around it by least
squares, which gives the centre, the amplitude with its sigma and the width. Found bumps are
masked and the search repeats.

NumPy/SciPy bookkeeping on a grid; units metres.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..geometry._geometry import column_bounds, grid_indices, grid_sum


@dataclass(frozen=True)
class LocalDeformation:
    """One localised deformation (surface coordinates in the frame of the points given).

    ``amplitude_m`` is positive for a bump towards the focus, negative for a dent;
    ``z`` is the significance of the band-passed peak (in standard errors).
    """

    x_m: float
    y_m: float
    amplitude_m: float
    sigma_amplitude_m: float
    width_m: float
    z: float
    n_points: int
    scale_m: float

    def asdict(self) -> dict:
        return {k: float(v) if not isinstance(v, int) else v for k, v in asdict(self).items()}


def _bandpass_z(xy, dev, sigma_dev, scale, cell, origin, shape):
    from scipy import ndimage  # (here: about 0.1 s of every command importing the surface)

    ij = grid_indices(xy, origin, cell)
    S, C = grid_sum(ij, shape, dev), grid_sum(ij, shape)
    s = scale / cell

    def smooth(a, sg):
        return ndimage.gaussian_filter(a, sg, mode="constant", truncate=3.0)

    cs = smooth(C, s)
    mean_s = np.where(cs > 1e-9, smooth(S, s) / np.where(cs > 1e-9, cs, 1), 0.0)
    cb = smooth(C, 4 * s)
    mean_b = np.where(cb > 1e-9, smooth(S, 4 * s) / np.where(cb > 1e-9, cb, 1), 0.0)
    # variance of the small-scale mean: sigma^2 sum K^2 / (sum K)^2, K^2 ~ Gaussian(s / sqrt 2);
    # n_eff = (sum K)^2 / sum K^2 is the effective number of points behind the mean
    k2 = smooth(C, s / np.sqrt(2)) / (4 * np.pi * s * s)
    ok = (k2 > 1e-12) & (cs > 1e-9)
    n_eff = np.where(ok, cs * cs / np.where(ok, k2, 1.0), 0.0)
    ok &= n_eff > 30
    # only where the data are: the peak's own neighbourhood (half the scale) must hold points
    ok &= smooth(C, max(s / 2, 0.5)) * 2 * np.pi * max(s / 2, 0.5) ** 2 > 3
    se = sigma_dev * np.sqrt(np.where(ok, k2, 1.0)) / np.where(ok, cs, 1.0)
    z = np.where(ok, (mean_s - mean_b) / se, 0.0)
    return z, ij


def _bump(params, x, y):
    A, x0, y0, lw, b0, bx, by = params
    w = np.exp(lw)
    return (A * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * w * w))
            + b0 + bx * (x - x0) + by * (y - y0))


def _coverage(xy: np.ndarray, x0: float, y0: float, w: float, n: int = 15) -> float:
    """Share of a grid over the disc of radius ``w`` at (x0, y0) that has a data point nearby."""
    from scipy.spatial import cKDTree

    g = np.linspace(-w, w, n)
    gx, gy = np.meshgrid(g, g)
    inside = gx**2 + gy**2 <= w * w
    pts = np.column_stack([x0 + gx[inside], y0 + gy[inside]])
    d, _ = cKDTree(xy).query(pts)
    return float(np.mean(d < 2 * w / n + 1e-9))


def fit_bump(xy: np.ndarray, dev: np.ndarray, x0: float, y0: float, w0: float, sigma_dev: float):
    """Least-squares 2-D Gaussian bump on a plane around ``(x0, y0)``; returns (params, sigmas)."""
    sel = np.hypot(xy[:, 0] - x0, xy[:, 1] - y0) < 4 * w0
    x, y, d = xy[sel, 0], xy[sel, 1], dev[sel]
    near = np.hypot(x - x0, y - y0) < w0
    if near.sum() < 5 or len(d) < 20:
        return None, None, int(sel.sum())
    p0 = np.array([np.median(d[near]) - np.median(d), x0, y0, np.log(w0), np.median(d), 0.0, 0.0])
    from scipy import optimize  # here: importing it takes 0.15 s, which `fit` never needs

    res = optimize.least_squares(lambda p: (_bump(p, x, y) - d) / sigma_dev, p0, method="lm")
    J = res.jac
    dof = max(len(d) - len(p0), 1)
    s0 = float(np.sqrt(np.sum(res.fun**2) / dof))
    try:
        cov = np.linalg.inv(J.T @ J) * s0 * s0
        sig = np.sqrt(np.diag(cov))
    except np.linalg.LinAlgError:
        sig = np.full(len(p0), np.nan)
    return res.x, sig, int(sel.sum())


def find_local_deformations(
    xy: np.ndarray,
    dev: np.ndarray,
    sigma_dev_m: float,
    *,
    scales_m=(0.25, 0.5, 1.0, 2.0),
    z_min: float = 8.0,
    min_amplitude_m: float = 0.0,
    max_count: int = 3,
    min_coverage: float = 0.7,
    max_tries: int = 12,
) -> list[LocalDeformation]:
    """Localised deformations in deviations ``dev`` (m) at surface coordinates ``xy`` (m).

    ``sigma_dev_m``: noise of one point's deviation (m); ``z_min``: significance needed;
    ``min_amplitude_m``: practical size needed (|A|); ``min_coverage``: share of the disc of
    radius ``width`` around a candidate that must hold data (else it is an edge effect).
    Returns the deformations, strongest first.
    """
    xy = np.asarray(xy, float)
    dev = np.asarray(dev, float)
    # narrow features (panel gaps, mixed pixels) must not pass for a bump: clip them
    med = np.median(dev)
    mad = 1.4826 * np.median(np.abs(dev - med)) or sigma_dev_m
    keep = np.abs(dev - med) < 4 * mad
    xy, dev = xy[keep], dev[keep]
    out: list[LocalDeformation] = []
    mask = np.ones(len(dev), bool)
    cell = min(scales_m) / 2
    lo, hi = column_bounds(xy)
    origin = lo - 8 * max(scales_m)
    shape = tuple(np.ceil((hi + 8 * max(scales_m) - origin) / cell).astype(int) + 1)
    for _ in range(max_tries):
        if len(out) >= max_count:
            break
        best = None
        for sc in scales_m:
            z, ij = _bandpass_z(xy[mask], dev[mask], sigma_dev_m, sc, cell, origin, shape)
            k = np.unravel_index(np.argmax(np.abs(z)), z.shape)
            if best is None or abs(z[k]) > abs(best[0]):
                best = (z[k], k, sc)
        zmax, (i, j), sc = best
        if abs(zmax) < z_min:
            break
        cx, cy = origin + (np.array([i, j]) + 0.5) * cell
        p, sg, n = fit_bump(xy[mask], dev[mask], cx, cy, sc, sigma_dev_m)
        if p is None:
            mask &= np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) > 2 * sc
            continue
        A, x0, y0, lw = p[:4]
        w = float(np.exp(lw))
        if not np.isfinite(A) or abs(A) < min_amplitude_m or w > 20 * max(scales_m):
            break
        if _coverage(xy[mask], x0, y0, w) < min_coverage:
            # a blob at the border of the data is an edge effect of the fit, not a bump
            mask &= np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) > 2 * sc
            continue
        out.append(LocalDeformation(float(x0), float(y0), float(A), float(sg[0]), w, float(zmax),
                                    n, float(sc)))
        mask &= np.hypot(xy[:, 0] - x0, xy[:, 1] - y0) > 2.5 * w
    return out
