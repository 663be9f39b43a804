"""Local deformations as wide as the panels: the windowed filter judged against a parametric
bootstrap of the panels' random effect (``diagnose/_wide.py``)."""

from __future__ import annotations

import numpy as np

from hartrao_jax.diagnose._locate import _panel_columns
from hartrao_jax.diagnose._wide import panel_factor, panel_variances, search_wide
from hartrao_jax.geometry._geometry import panel_cells
from hartrao_jax.physics._catalog import local_deformation

EDGES = (1.6, 3.2, 4.8, 6.4, 8.0, 9.6, 11.2, 12.95)
COUNTS = (15, 24, 30, 36, 42, 48, 60)
OFFSET_SD, TILT_SD, NOISE = 1.5e-4, 7.5e-5, 8e-4


def surface(seed: int, n: int = 60000, bump=None):
    """Points over the aperture (m) and their residuals: iid panel offsets and tilts, white
    noise, and optionally a bump ``(amplitude, x, y, width)`` (m)."""
    rng = np.random.default_rng(seed)
    rho = 12.9 * np.sqrt(rng.random(n))
    psi = rng.uniform(0, 2 * np.pi, n)
    xy = np.column_stack([rho * np.cos(psi), rho * np.sin(psi)])
    X = np.column_stack([xy, rho**2 / (4 * 10.9816)])
    cell, _, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    off, tx, ty = (rng.normal(0, s, n_cells) for s in (OFFSET_SD, TILT_SD, TILT_SD))
    centre = np.array([xy[cell == k].mean(0) if np.any(cell == k) else (0.0, 0.0)
                       for k in range(n_cells)])
    d = xy - centre[np.maximum(cell, 0)]
    r = off[cell] + tx[cell] * d[:, 0] + ty[cell] * d[:, 1] + rng.normal(0, NOISE, n)
    if bump is not None:
        a, x0, y0, w = bump
        r = r + np.asarray(local_deformation(xy[:, 0], xy[:, 1], x0, y0, a, w))
    return xy, r, cell


def test_panel_variances_recover_the_simulated_ones():
    xy, r, cell = surface(0)
    var_o, var_t, noise = panel_variances(r, _panel_columns(xy, cell))
    assert abs(np.sqrt(var_o) / OFFSET_SD - 1) < 0.25
    assert abs(np.sqrt(var_t) / TILT_SD - 1) < 0.35
    assert abs(noise / NOISE - 1) < 0.02


def test_panels_alone_are_no_finding_and_a_wide_bump_is():
    """Clean surfaces: not significant, p spread (not pushed to 0); a 2 mm bump 2.5 m wide:
    significant, at its place, with a panel factor that widens its sigmas."""
    ps = []
    for seed in range(4):
        xy, r, cell = surface(seed)
        c = search_wide(xy, r, cell, alpha=1e-3, min_amplitude_m=1e-5, replicates=60,
                        seed=seed).candidate
        assert c is not None and not c.significant
        ps.append(c.p_value)
    assert max(ps) > 0.1, ps
    xy, r, cell = surface(7, bump=(2e-3, -6.0, 3.0, 2.5))
    c = search_wide(xy, r, cell, alpha=1e-3, min_amplitude_m=1e-5, replicates=60).candidate
    assert c.significant and c.p_value < 1e-3
    assert np.hypot(c.x_m + 6.0, c.y_m - 3.0) < 1.0 and c.width_m >= 1.5
    assert c.roughness > 2.0  # the panels' random effect blurs the amplitude
    assert panel_factor(xy, r, cell, -6.0, 3.0, 2.5) > 2.0


def test_a_partial_recording_and_an_excluded_neighbourhood_never_fail():
    """A strip of the aperture, and a search whose every centre lies next to a modelled
    deformation: a candidate or none, never an exception."""
    xy, r, cell = surface(3, n=20000)
    strip = np.abs(xy[:, 1]) < 1.0
    s = search_wide(xy[strip], r[strip], cell[strip], alpha=1e-3, min_amplitude_m=1e-5,
                    replicates=20)
    assert s.candidate is None or not s.candidate.significant
    s = search_wide(xy, r, cell, alpha=1e-3, min_amplitude_m=1e-5, replicates=20,
                    exclude=[(0.0, 0.0, 40.0)])
    assert s.candidate is None or not s.candidate.significant
    assert search_wide(xy[:5], r[:5], cell[:5], alpha=1e-3, min_amplitude_m=1e-5).candidate \
        is None
