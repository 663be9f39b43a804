"""The joint systems of the diagnosis through the widest model seen on a scan
(`_state._Supersets`): the same sums as the narrower model's own, one compiled program."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from helpers import F_TRUE, POSE, SIGMA, paraboloid_points, synthetic_scan

from hartrao_jax.diagnose._state import _covers, _Supersets
from hartrao_jax.geometry._geometry import panel_cells
from hartrao_jax.model._model import make_model
from hartrao_jax.solver._mixed_stream import mixed_chunk

EDGES = (1.6, 3.2, 4.8, 6.4, 8.0, 9.6, 11.2, 12.95)
COUNTS = (15, 24, 30, 36, 42, 48, 60)
WIDE = ("tx", "ty", "tz", "rx", "ry", "f", "x2", "x4", "x6", "x7", "range_scale", "shift_x",
        "shift_y", "shift_z", "osc_sx", "osc_cx", "drift_tx", "zern_7")


def _sums(model, x, l, c, cell, design, n_cells):
    s, _ = mixed_chunk(model, jnp.asarray(l), jnp.asarray(c), jnp.ones(len(l)),
                       jnp.asarray(SIGMA**2), jnp.asarray(cell), jnp.asarray(design),
                       jnp.asarray(x, float), jnp.zeros((n_cells, 3)), jnp.asarray(1.0),
                       jnp.asarray(np.inf), dev_column=1)
    return s


def test_wide_model_gives_the_narrow_models_sums():
    """A narrow model (held x2, its own shift window and period) through the names of a wider
    one seen before: its rows and columns of the wide sums equal its own sums to 1e-9, and the
    wide model has the static names of the first (the same program)."""
    n = 4096
    l = synthetic_scan(n, seed=3)
    X = paraboloid_points(n, F_TRUE, 3)
    cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    design = np.column_stack([np.ones(n), local]) * (cell >= 0)[:, None]
    c = np.column_stack([np.linspace(0.0, 600.0, n), np.zeros(n)])
    sets = _Supersets()
    first = make_model(WIDE, shift_window_s=(10.0, 5.0), osc_period_s=3.0, kappa_rad=0.2,
                       check_separable=False)
    got, _, idx = sets.of("s1", first, np.zeros(len(first.free)))
    assert got is first and list(idx) == list(range(len(first.free)))
    narrow = make_model(("tx", "ty", "tz", "rx", "ry", "f", "x4", "shift_x", "shift_y"),
                        {"x2": 3e-4}, shift_window_s=(100.0, 200.0), osc_period_s=7.0,
                        kappa_rad=0.2, check_separable=False)
    truth = {**POSE, "f": F_TRUE, "x4": 1e-4, "shift_x": 2e-4, "shift_y": -1e-4}
    x = np.array([truth[k] for k in narrow.free])
    wide, x_wide, idx = sets.of("s1", narrow, x)
    assert wide.free == first.free and wide.fixed_names == first.fixed_names
    assert float(wide.shift_window_s[0]) == 100.0 and float(wide.osc_period_s) == 7.0
    assert x_wide[wide.free.index("x2")] == 3e-4 and x_wide[wide.free.index("x6")] == 0.0
    own = _sums(narrow, x, l, c, cell, design, n_cells)
    big = _sums(wide, x_wide, l, c, cell, design, n_cells)
    N, N_own = np.asarray(big.N)[np.ix_(idx, idx)], np.asarray(own.N)
    assert np.allclose(N, N_own, rtol=1e-9, atol=1e-9 * np.abs(N_own).max())
    assert np.allclose(np.asarray(big.nv)[idx], own.nv, rtol=1e-9,
                       atol=1e-9 * np.abs(own.nv).max())
    assert np.allclose(np.asarray(big.sg)[:, :, idx], own.sg, rtol=1e-9,
                       atol=1e-9 * np.abs(own.sg).max())
    for name in ("S", "tg", "wMw", "n_used", "omega"):
        a, b = np.asarray(getattr(big, name)), np.asarray(getattr(own, name))
        assert np.allclose(a, b, rtol=1e-9, atol=1e-12), name
    # another scan keeps its own models
    other, _, _ = sets.of("s2", narrow, x)
    assert other is narrow


def test_covers_refuses_what_would_change_the_condition():
    wide = make_model(WIDE, check_separable=False)
    assert _covers(wide, make_model(("tx", "ty", "tz", "rx", "ry", "f", "x6")))
    # a name the narrow model holds at a value but the wide one neither frees nor holds
    held = make_model(("tx", "ty", "tz", "rx", "ry", "f"), {"x12a": 1e-4})
    assert not _covers(wide, held)
    # a name the narrow model frees that the wide one lacks
    assert not _covers(wide, make_model(("tx", "ty", "tz", "rx", "ry", "f", "x3")))
    # a bump free in the wide model alone: a zero width is not "no bump"
    bump = make_model(WIDE + ("bump_x_m", "bump_y_m", "bump_amp_m", "bump_width_m"),
                      check_separable=False)
    assert not _covers(bump, make_model(("tx", "ty", "tz", "rx", "ry", "f")))
    # another aperture
    assert not _covers(wide, make_model(("tx", "ty", "tz", "rx", "ry", "f"),
                                        aperture_radius_m=50.0))
