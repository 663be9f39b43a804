"""The local-deformation search on a reflector of known panels: the panels' offsets (free) and
tilts (a random effect) are the matched filter's nuisance, so a bump inside a panel keeps its
amplitude (its panel's offset cannot take it), per-panel constants change nothing, and the
panel pattern alone gives no significant candidate."""

from __future__ import annotations

import numpy as np
import pytest

from hartrao_jax.diagnose._locate import (
    _panel_columns,
    _PanelAlgebra,
    search,
    tilt_variance,
    width_map,
)
from hartrao_jax.physics._catalog import local_deformation

PANEL_M = 2.0  # square panels of a 24 m x 24 m patch


def _surface(seed=0, n=60000, half=12.0, offset_rms=1.5e-4, tilt_rms=7.5e-5, bump=None):
    """Uniform points, white residuals of 0.75 mm, square panels with random offsets and tilts
    (m, m/m) and an optional ``bump = (x, y, a, w)``; returns positions, residuals, panel ids."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-half, half, (n, 2))
    ij = np.floor((xy + half) / PANEL_M).astype(int)
    k = int(round(2 * half / PANEL_M))
    ids = ij[:, 0] * k + ij[:, 1]
    off = rng.normal(0.0, offset_rms, k * k)
    tilt = rng.normal(0.0, tilt_rms, (k * k, 2))
    centre = (ij + 0.5) * PANEL_M - half
    r = rng.normal(0.0, 0.75e-3, n) + off[ids] + np.sum(tilt[ids] * (xy - centre), 1)
    if bump is not None:
        x0, y0, a, w = bump
        r += np.asarray(local_deformation(xy[:, 0], xy[:, 1], x0, y0, a, w))
    return xy, r, ids


def test_tilt_variance_is_estimated_beyond_the_noise():
    xy, r, ids = _surface(tilt_rms=2e-4)
    tau2 = tilt_variance(r, _panel_columns(xy, ids), 0.75e-3)
    assert np.sqrt(tau2) == pytest.approx(2e-4, rel=0.25)
    xy, r, ids = _surface(tilt_rms=0.0)
    assert np.sqrt(tilt_variance(r, _panel_columns(xy, ids), 0.75e-3)) < 5e-5


def test_per_panel_constants_do_not_change_the_panel_filter():
    xy, r, ids = _surface(bump=(1.3, -2.4, 1e-3, 0.5))
    shift = np.random.default_rng(1).normal(0.0, 1e-3, ids.max() + 1)[ids]
    panels = _panel_columns(xy, ids)
    sigma, tau2 = 0.75e-3, 1e-8
    m0, m1 = (width_map(xy, r_, 0.5, sigma, 100.0,
                        panels=_PanelAlgebra.of(panels, r_, sigma, tau2)) for r_ in (r, r + shift))
    assert m0.valid.sum() > 1000 and np.array_equal(m0.valid, m1.valid)
    np.testing.assert_allclose(m1.amplitude[m0.valid], m0.amplitude[m0.valid], atol=1e-9)


def test_a_bump_inside_a_panel_keeps_its_amplitude_with_the_panels_as_nuisance():
    bump = (1.3, -2.4, 2e-3, 0.5)  # inside the panel [0, 2] x [-4, -2]
    xy, r, ids = _surface(bump=bump)
    c = search(xy, r, groups=ids).candidate
    assert c.significant and np.hypot(c.x_m - 1.3, c.y_m + 2.4) < 0.2
    assert c.amplitude_m == pytest.approx(2e-3, rel=0.15)
    assert c.roughness < 1.15  # the tilts' ramps are not roughness any more
    plain = search(xy, r).candidate  # the windowed local constant: the panels are roughness
    assert plain.roughness > c.roughness


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_panels_alone_give_no_significant_candidate(seed):
    xy, r, ids = _surface(seed=seed)
    s = search(xy, r, groups=ids)
    assert s.candidate is not None and not s.candidate.significant
