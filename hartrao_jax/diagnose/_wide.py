"""Local deformations as wide as the panels, on a reflector of known panel layout.

The panel-conditional filter of :mod:`._locate` (the panels' offsets free) cannot see a bump
as wide as a panel: that bump *is* its panels' offsets, and those widths are left undefined.
Here they are searched with the windowed filter (``a g + b``, no panel nuisance) and judged
against the panels as what they are in the two-face adjustment: a random effect.

The null: a parametric bootstrap of the panel random effect
-----------------------------------------------------------
The residuals of the points are modelled as ``r_i = P_i u_p(i) + e_i``: per panel an offset
and two tilts along the aperture axes (``P_i = (1, x_i - x_p, y_i - y_p)``), independent
between panels, of variances ``var_offset`` and ``var_tilt`` estimated from the robust spread
(``1.4826 MAD``) of the per-panel plane fits beyond the noise (a bump moves only its own
panels' fits); ``e`` white, of the pooled residual spread of those fits. :data:`REPLICATES`
surfaces of that model are drawn on the filter's grid (the gridded sums of ``P_i u_p`` per
cell, one sparse product for all replicates; the noise per cell ``N(0, noise^2 n_cell)``) and
filtered exactly as the recording. Each width's white scores ``z`` are divided by the null's
own spread at that width (the median over the replicates of their robust spread), for the
recording and the replicates alike (the recording's own spread grows with the bump it is to
find), and the maximum of ``|z| / s`` over every centre and width is taken. The recording's
maximum is judged against the replicates' maxima: a Gumbel distribution fitted by its
moments (the empirical fraction where that is larger, outside the far tail).

Smooth deformation is not in that model (a real reflector's astigmatism, which the
background window only partly removes at 3 m): a candidate must also not be an ordinary peak
of the recording's own field (:func:`._locate.judge`, p below :data:`OWN_FIELD_P` where that
null can be calibrated).

The candidate's sigmas: the filter amplitude's standard deviation under the panel model,
``var(a) = sum_i h_i^2 sigma^2 + sum_p (sum_{i in p} h_i P_i) diag(var) (...)^T`` with ``h``
the filter's weights at the candidate, over its white-noise value gives the factor by which
the refit's white sigmas are multiplied (the role of the roughness factor of the narrow
search).

NumPy/SciPy; units metres.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
from scipy import sparse

from ..geometry._geometry import grid_sum
from ._locate import (
    BackgroundFilter,
    Candidate,
    Search,
    _density,
    _gauss,
    _panel_columns,
    coverage,
    grid_of,
    judge,
    panel_fits,
    roughness_of,
    width_maps,
)

#: Widths (m) searched here on a reflector of known panels (about a panel's size and wider).
WIDE_WIDTHS_M: tuple[float, ...] = (1.5, 2.0, 3.0)
#: Replicate surfaces of the parametric null.
REPLICATES = 120
#: The candidate must be among the largest peaks of the recording's own field at this level.
OWN_FIELD_P = 0.05
_EULER = 0.5772156649015329


def panel_variances(r: np.ndarray, panels) -> tuple[float, float, float]:
    """``(var_offset (m^2), var_tilt (rad^2), noise sd (m))`` of the panel model: the noise
    from the pooled residuals of the per-panel fits (plane, or offset alone for a small
    panel), the panels' variances from the robust spread (``1.4826 MAD``) of their fitted
    offsets and tilts less the noise's share: a bump spread over a few panels moves their
    offsets without widening the null it is judged against."""
    off, tilts, v_o, v_t, rss, dof = [], [], [], [], 0.0, 0
    for (idx, P), (o, Mi, ss) in zip(panels, panel_fits(r, panels)):
        off.append(o[0])
        v_o.append(Mi[0, 0])
        if P.shape[1] == 3:
            tilts += [o[1], o[2]]
            v_t += [Mi[1, 1], Mi[2, 2]]
        rss += ss
        dof += len(idx) - P.shape[1]
    if not off or dof <= 0:
        return 0.0, 0.0, float(np.std(r))
    noise = math.sqrt(rss / dof)

    def robust_var(a):
        a = np.asarray(a)
        return float((1.4826 * np.median(np.abs(a - np.median(a)))) ** 2)

    var_o = max(0.0, robust_var(off) - noise**2 * float(np.median(v_o)))
    var_t = max(0.0, robust_var(tilts) - noise**2 * float(np.median(v_t))) if tilts else 0.0
    return var_o, var_t, noise


def _panel_design(ij_flat: np.ndarray, n_cells: int, panels) -> sparse.csr_matrix:
    """``A`` (cells, 3 panels): the gridded sums of each panel's columns ``(1, dx, dy)``
    (zeros for the tilts of a panel fitted by its offset alone)."""
    rows, cols, vals = [], [], []
    for p, (idx, P) in enumerate(panels):
        for k in range(P.shape[1]):
            rows.append(ij_flat[idx])
            cols.append(np.full(len(idx), 3 * p + k))
            vals.append(P[:, k])
    return sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                     np.concatenate(cols))),
                             shape=(n_cells, 3 * len(panels)))


def _gumbel_p(x: float, maxima: np.ndarray) -> float:
    """P(max >= x) under a Gumbel fitted to ``maxima`` by its moments; the empirical
    fraction (with one added) where that is larger (not in the far tail)."""
    m, s = float(np.mean(maxima)), float(np.std(maxima, ddof=1))
    beta = max(s * math.sqrt(6.0) / math.pi, 1e-12)
    mu = m - _EULER * beta
    p_g = -math.expm1(-math.exp(-(x - mu) / beta))
    p_e = (1 + int(np.sum(maxima >= x))) / (len(maxima) + 1)
    return float(max(p_g, p_e) if p_e > 2.0 / (len(maxima) + 1) else p_g)


def _far_from(centres: np.ndarray, exclude, w: float) -> np.ndarray:
    ok = np.ones(len(centres), bool)
    for ex, ey, ew in exclude:
        ok &= np.hypot(centres[:, 0] - ex, centres[:, 1] - ey) > 2 * max(ew, w)
    return ok


class _Grid:
    """One wide width's grid, filter and panel design."""

    def __init__(self, xy, w, density, panels):
        self.w = w
        self.lo, self.shape, ij, self.h = grid_of(xy, w)
        self.flat = ij[:, 0] * self.shape[1] + ij[:, 1]  # the points' cells (panel design)
        self.C = grid_sum(ij, self.shape)
        covered, _, _ = coverage(self.C, w / self.h, self.h, density)
        self.bf = BackgroundFilter.of(self.C, w / self.h, covered)
        self._panels = panels
        self.cells = np.argwhere(self.bf.valid)  # rows: x index, columns: y index
        self.centres = self.lo + (self.cells + 0.5) * self.h

    @functools.cached_property
    def A(self) -> sparse.csr_matrix:
        """The panels' design on this grid (:func:`_panel_design`; the replicates only)."""
        return _panel_design(self.flat, self.C.size, self._panels)

    def scores(self, U: np.ndarray, sigma: float, noise: float, rng) -> np.ndarray:
        """White scores ``z = a / se(a)`` at the valid centres (valid, B) of the replicates
        (columns of ``U``, the panels' parameters; white noise of sd ``noise``; ``sigma`` the
        recording's robust spread, as its maps are standardised)."""
        B = U.shape[1]
        R = (self.A @ U).reshape(self.shape + (B,))
        R += rng.normal(size=R.shape) * (noise * np.sqrt(self.C))[..., None]
        a = self.bf.amplitude(R)[self.bf.valid]
        return a / (sigma * self.bf.se_unit[self.bf.valid])[:, None]


def amplitude_factor(xy, panels, var_o: float, var_t: float, sigma: float, x0: float,
                     y0: float, w: float, density: float) -> float:
    """sd of the filter's amplitude at ``(x0, y0, w)`` under the panel model (noise sd
    ``sigma``) over its white-noise value (at least 1)."""
    g = _Grid(xy, w, density, panels)
    i = int(np.clip(np.floor((x0 - g.lo[0]) / g.h), 0, g.shape[0] - 1))  # rows: x
    j = int(np.clip(np.floor((y0 - g.lo[1]) / g.h), 0, g.shape[1] - 1))
    # the filter's weight of every grid cell at the centre (i, j): linear in the sums R
    e = np.zeros(g.shape)
    e[i, j] = 1.0
    bf = g.bf
    if not bf.valid[i, j]:
        return 1.0
    h_cells = (bf.S11[i, j] * _gauss(e, bf.s1) - bf.Sg1[i, j] * _gauss(e, bf.sb)) / bf.det[i, j]
    hpt = h_cells.reshape(-1)[g.flat]  # per point (the filter is symmetric)
    white = sigma**2 * float(np.sum(hpt**2))
    var = white
    for idx, P in panels:
        v = hpt[idx] @ P
        var += var_o * v[0] ** 2 + (var_t * float(np.sum(v[1:] ** 2)) if len(v) > 1 else 0.0)
    return max(1.0, math.sqrt(var / white)) if white > 0 else 1.0


def _usable(xy, r, groups):
    xy = np.asarray(xy, float)
    r = np.asarray(r, float)
    groups = np.asarray(groups, np.int64)
    ok = np.all(np.isfinite(xy), 1) & np.isfinite(r) & (groups >= 0)
    return xy[ok], r[ok], groups[ok]


def _panel_model(xy, r, groups, sigma):
    """The panels (:func:`._locate._panel_columns`) and ``(var_offset, var_tilt, noise sd)``
    of the residuals ``r`` centred and clipped as the maps take them."""
    rc = np.clip(r - float(np.median(r)), -5 * sigma, 5 * sigma)
    panels = _panel_columns(xy, groups)
    return panels, *panel_variances(rc, panels)


def panel_factor(xy, r, groups, x0: float, y0: float, w: float) -> float:
    """:func:`amplitude_factor` of a bump at ``(x0, y0)`` of width ``w`` (m) with the panel
    model estimated from the residuals ``r`` (m) at ``xy`` of panels ``groups``: for a bump
    as wide as the panels, by whichever search it was found, its sigmas widen by this."""
    xy, r, groups = _usable(xy, r, groups)
    if len(r) < 16:
        return 1.0
    sigma = float(1.4826 * np.median(np.abs(r - np.median(r)))) or float(np.std(r)) or 1e-4
    panels, var_o, var_t, noise = _panel_model(xy, r, groups, sigma)
    return amplitude_factor(xy, panels, var_o, var_t, noise, x0, y0, w, _density(xy))


def search_wide(xy: np.ndarray, r: np.ndarray, groups: np.ndarray, *, alpha: float,
                min_amplitude_m: float, exclude: Sequence[tuple[float, float, float]] = (),
                widths: Sequence[float] = WIDE_WIDTHS_M, replicates: int = REPLICATES,
                seed: int = 0) -> Search:
    """The windowed matched filter at ``widths`` judged against the panel random effect
    (module docstring). ``groups``: the points' panel ids (points of none, id < 0, left
    out). Returns the maps, the best candidate (``p_value`` of the maximum under the panel
    model, ``roughness`` the amplitude's panel factor) and its significance.

    Each width's white scores are put on one scale by the null's own spread at that width
    (the median over the replicates of their robust spread), for the recording and the
    replicates alike: the recording's own spread would grow with the bump it is to find."""
    xy, r, groups = _usable(xy, r, groups)
    density = _density(xy) if len(r) >= 16 else 0.0  # (fewer: nothing is searched)
    maps, sigma, skipped = width_maps(xy, r, widths, density=density)
    own = judge(maps, sigma, skipped, alpha=alpha, min_amplitude_m=min_amplitude_m,
                exclude=exclude)
    if own.candidate is None or len(r) < 16:
        return own
    panels, var_o, var_t, noise = _panel_model(xy, r, groups, sigma)
    sd = np.repeat([[math.sqrt(var_o), math.sqrt(var_t), math.sqrt(var_t)]], len(panels), 0)
    sd[[P.shape[1] < 3 for _, P in panels], 1:] = 0.0
    rng = np.random.default_rng(seed)
    U = rng.normal(size=(3 * len(panels), replicates)) * sd.reshape(-1)[:, None]
    maxima = np.zeros(replicates)
    best = None  # (|t|, map, cell)
    for m in maps:
        g = _Grid(xy, m.width_m, density, panels)
        if not g.bf.valid.any() or g.shape != m.valid.shape:
            continue
        far = _far_from(g.centres, exclude, m.width_m)
        if not far.any():  # every centre next to a deformation already modelled
            continue
        z_null = g.scores(U, sigma, noise, rng)
        s_null = max(float(np.median(roughness_of(z_null, axis=0))), 1.0)
        maxima = np.maximum(maxima, np.max(np.abs(z_null[far]), axis=0) / s_null)
        z_obs = m.z[m.valid] / s_null
        z_obs = np.where(far, np.abs(z_obs), 0.0)
        k = int(np.argmax(z_obs))
        if best is None or z_obs[k] > best[0]:
            best = (float(z_obs[k]), m, tuple(g.cells[k]), float(m.z[tuple(g.cells[k])]))
    if best is None:
        return own
    t, m, ij, z = best
    x0, y0 = (float(v) for v in m.centre(ij))
    amp = float(m.amplitude[ij])
    p = _gumbel_p(t, maxima)
    factor = amplitude_factor(xy, panels, var_o, var_t, noise, x0, y0, m.width_m, density)
    c = own.candidate
    own_ok = c.p_value is None or (c.p_value < OWN_FIELD_P and math.hypot(
        c.x_m - x0, c.y_m - y0) < 2 * max(c.width_m, m.width_m))
    cand = Candidate(x0, y0, amp, m.width_m, t, z, factor, p, len(maps),
                     {"null": "panel random effect", "replicates": replicates,
                      "panel_offset_sd_m": math.sqrt(var_o),
                      "panel_tilt_sd_rad": math.sqrt(var_t), "noise_sd_m": noise,
                      "null_maxima_median": float(np.median(maxima)),
                      "own_field_p": c.p_value},
                     bool(p < alpha and own_ok and abs(amp) >= min_amplitude_m),
                     "" if own_ok else "not among the largest peaks of the recording's own "
                                       f"field (p = {c.p_value:.2g})")
    return Search(own.maps, cand, own.sigma_m, own.skipped_widths)
