"""The surface as a random effect: honest sigmas judged by z-scores over seeds, variance
components, identifiability."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import F_TRUE, POSE, SIGMA, paraboloid_points

from hartrao_jax.fit._projection import hit_points
from hartrao_jax.geometry._geometry import (
    cartesian_to_raw,
    panel_cells,
    scanner_to_telescope,
    zernike,
    zernike_columns,
)
from hartrao_jax.model._model import make_model
from hartrao_jax.solver._ghm import gauss_helmert
from hartrao_jax.solver._mixed import MIXED_TOL, gauss_helmert_mixed, ridge_chi2

EDGES = (1.6, 3.2, 4.8, 6.4, 8.0, 9.6, 11.2, 12.95)
COUNTS = (15, 24, 30, 36, 42, 48, 60)
TAU = 1.5e-4  # panel offsets, m


def two_face_scan(seed: int, n: int = 12000, tau: float = TAU, noise: bool = True,
                  extra: dict[int, float] | None = None, modes: dict[int, float] | None = None):
    """Both faces of one set-up looking at a paraboloid whose panels are offset by N(0, tau^2)
    along the normal (plus ``extra`` {cell: offset m} and smooth ``modes`` {Noll j: m} over the
    aperture ``EDGES[-1]``): raw observations (2n, 3), telescope-frame points."""
    rng = np.random.default_rng(seed)
    X = paraboloid_points(2 * n, F_TRUE, seed)
    cell, _, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    offsets = rng.normal(0.0, tau, n_cells)
    for k, d in (extra or {}).items():
        offsets[k] += d
    rho = np.hypot(X[:, 0], X[:, 1])
    normal = np.column_stack([-X[:, 0] / (2 * F_TRUE), -X[:, 1] / (2 * F_TRUE),
                              np.ones(len(X))]) / np.sqrt(1 + (rho / (2 * F_TRUE)) ** 2)[:, None]
    dev = np.where(cell >= 0, offsets[np.clip(cell, 0, None)], 0.0)
    psi = np.arctan2(X[:, 1], X[:, 0])
    for j, a in (modes or {}).items():
        dev = dev + a * np.asarray(zernike(j, rho / EDGES[-1], psi, xp=np))
    Xd = X + dev[:, None] * normal
    R = np.asarray(scanner_to_telescope(POSE["rx"], POSE["ry"]))
    t = np.array([POSE["tx"], POSE["ty"], POSE["tz"]])
    xs = (Xd - t) @ R
    parts = []
    for face, sl in ((1, slice(0, n)), (2, slice(n, 2 * n))):
        r, phi, th = cartesian_to_raw(xs[sl], face)
        parts.append(np.stack([r, phi, th], 1))
    lobs = np.concatenate(parts)
    if noise:
        lobs = lobs + np.random.default_rng(seed + 7).normal(size=lobs.shape) * SIGMA
    return lobs, X


def _fit_mixed(lobs, X, names=("tx", "ty", "tz", "rx", "ry", "f")):
    model = make_model(list(names))
    x_true = np.array([{**POSE, "f": F_TRUE}.get(k, 0.0) for k in model.free])
    cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    design = np.column_stack([np.ones(len(X)), local]) * (cell >= 0)[:, None]
    c = np.zeros((len(lobs), 2))
    res = gauss_helmert_mixed(model, lobs, x_true, SIGMA, c, np.ones(len(lobs)), cell, design,
                              n_cells, cell_var0=np.array([1e-8, 1e-8, 1e-8]))
    return res, x_true, model


def test_mixed_sigmas_are_honest_over_seeds():
    """z = (estimate - truth) / sigma over 12 seeds of a panelled reflector: std near 1 with the
    random effect; the white-noise adjustment of the same data is overconfident."""
    z_mixed, z_white, tau_hat = [], [], []
    for seed in range(12):
        lobs, X = two_face_scan(seed)
        res, x_true, model = _fit_mixed(lobs, X)
        assert bool(res.converged)
        z_mixed.append((np.asarray(res.x) - x_true) / np.asarray(res.sigma))
        tau_hat.append(float(np.sqrt(res.cell_var[0])))
        white = gauss_helmert(model, lobs, x_true, SIGMA, np.zeros((len(lobs), 2)))
        z_white.append((np.asarray(white.x) - x_true) / np.asarray(white.sigma))
    z_mixed, z_white = np.concatenate(z_mixed), np.concatenate(z_white)
    assert 0.7 < np.std(z_mixed) < 1.35, np.std(z_mixed)
    assert np.max(np.abs(z_mixed)) < 4.5
    assert np.std(z_white) > 2.0  # the panel pattern seen as white noise
    assert np.median(tau_hat) == pytest.approx(TAU, rel=0.15)


def test_mixed_without_surface_is_white_noise_adjustment():
    """No panel pattern: the offsets' variance goes to ~0, sigma0 ~ 1 and the estimates equal
    the white-noise Gauss-Helmert ones."""
    lobs, X = two_face_scan(3, tau=0.0)
    res, x_true, model = _fit_mixed(lobs, X)
    white = gauss_helmert(model, lobs, x_true, SIGMA, np.zeros((len(lobs), 2)))
    assert float(res.noise_var) == pytest.approx(1.0, abs=0.05)
    assert float(np.sqrt(res.cell_var[0])) < 8e-5  # half the panel rms of the other tests
    d = np.abs(np.asarray(res.x) - np.asarray(white.x)) / np.asarray(res.sigma)
    assert np.all(d < 1.5), d  # tau is estimated: a few 1e-5 m of noise-driven spread
    assert np.all(np.asarray(res.sigma) >= 0.99 * np.asarray(white.sigma))


def test_mixed_blups_predict_panel_offsets():
    """The cells' predictions follow the simulated offsets within their prediction sigmas."""
    seed = 5
    lobs, X = two_face_scan(seed, n=20000)
    res, *_ = _fit_mixed(lobs, X)
    rng = np.random.default_rng(seed)
    cell, _, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    truth = rng.normal(0.0, TAU, n_cells)
    u = np.asarray(res.u)[:, 0]
    su = np.sqrt(np.asarray(res.u_cov)[:, 0, 0])
    # the panel offsets are known up to what the pose/f absorb (a global paraboloid change);
    # remove the mean before comparing
    d = (u - truth) - np.mean(u - truth)
    z = d / su
    assert np.std(z) < 1.6
    assert np.corrcoef(u, truth)[0, 1] > 0.8  # ~160 points of 0.8 mm noise per panel


def test_x_response_is_the_estimates_derivative_by_a_cell():
    """``x_response[g]``: a known extra offset of one panel moves the estimates by
    ``R_g @ (offset, 0, 0)`` (refit at the same variances); the surface's share of the
    covariance, ``sum_g R_g G R_g^T``, is most of sigma(f)^2 and never more than all of it."""
    model = make_model(["tx", "ty", "tz", "rx", "ry", "f"])
    x_true = np.array([{**POSE, "f": F_TRUE}[k] for k in model.free])
    fits = []
    for extra in (None, {40: 2e-4}):
        lobs, X = two_face_scan(2, n=8000, noise=False, extra=extra)
        cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
        design = np.column_stack([np.ones(len(X)), local]) * (cell >= 0)[:, None]
        fits.append(gauss_helmert_mixed(
            model, lobs, x_true, SIGMA, np.zeros((len(lobs), 2)), np.ones(len(lobs)), cell,
            design, n_cells, cell_var0=np.array([TAU**2, 1e-8, 1e-8]), estimate_variances=False,
            robust_k=None))
    R = np.asarray(fits[0].x_response)
    dx = np.asarray(fits[1].x) - np.asarray(fits[0].x)
    np.testing.assert_allclose(dx, R[40] @ np.array([2e-4, 0.0, 0.0]), rtol=0.02,
                               atol=1e-3 * np.max(np.abs(dx)))
    G = np.diag(np.asarray(fits[0].cell_var))
    surf = np.einsum("gik,kl,gjl->ij", R, G, R) * 1.0
    tot = np.asarray(fits[0].cov)
    i_f = model.free.index("f")
    assert np.all(np.diag(surf) <= np.diag(tot) * (1 + 1e-9))
    assert np.diag(surf)[i_f] > 0.5 * tot[i_f, i_f]


def test_mode_groups_are_carried_only_where_the_data_show_them():
    """``ridge_chi2``: smooth modes estimated as fixed effects (cells still random) against
    zero. Without smooth modes the p-values are spread over (0, 1) (no group rejected at 1 % in
    6 seeds x 3 groups, allowing one); 0.4 mm of astigmatism is shown at p < 1e-6, and the
    coma and trefoil groups of the same data stay consistent with zero."""
    groups = {"astig": (5, 6), "coma": (7, 8), "trefoil": (9, 10)}
    names = ("tx", "ty", "tz", "rx", "ry", "f") + tuple(f"zern_{j}" for g in groups.values()
                                                        for j in g)
    model = make_model(list(names), aperture_radius_m=EDGES[-1])
    ridge = {k: [model.free.index(f"zern_{j}") for j in g] for k, g in groups.items()}

    def tests(seed, modes=None):
        lobs, X = two_face_scan(seed, n=8000, modes=modes)
        x0 = np.array([{**POSE, "f": F_TRUE}.get(k, 0.0) for k in model.free])
        cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
        design = np.column_stack([np.ones(len(X)), local]) * (cell >= 0)[:, None]
        res = gauss_helmert_mixed(model, lobs, x0, SIGMA, np.zeros((len(lobs), 2)),
                                  np.ones(len(lobs)), cell, design, n_cells,
                                  cell_var0=np.array([1e-8, 1e-8, 1e-8]), ridge=ridge)
        return ridge_chi2(res, ridge)

    p_null = [t[2] for s in range(6) for t in tests(s).values()]
    assert sum(p < 0.01 for p in p_null) <= 1, p_null
    assert np.max(p_null) > 0.3  # not all pushed to zero
    shown = tests(11, modes={6: 4e-4})
    assert shown["astig"][2] < 1e-6 and shown["astig"][1] == 2
    assert shown["coma"][2] > 1e-3 and shown["trefoil"][2] > 1e-3


def test_mode_design_equals_modes_inside_the_condition():
    """Smooth modes given as per-point columns (``mode_design``: the Zernike terms at each
    observation's hit point on the fitted surface, as ``fit`` gives them) and the same modes
    differentiated inside the condition give the same adjustment: estimates within 0.02 sigma,
    sigmas and variance components within 0.5 %. (At the points' true positions instead,
    0.05 sigma: the range noise moves an observation across the surface by up to 15 mm, and
    the condition sees the modes where the observation is.)"""
    lobs, X = two_face_scan(3, n=4000, modes={6: 3e-4, 8: 1e-4})
    js = (5, 6, 7, 8, 11)
    names = ["tx", "ty", "tz", "rx", "ry", "f"] + [f"zern_{j}" for j in js]
    full = make_model(names, aperture_radius_m=EDGES[-1])
    core = make_model(names[:6], aperture_radius_m=EDGES[-1])
    ridge = {"modes": [full.free.index(f"zern_{j}") for j in js]}
    x0 = np.array([{**POSE, "f": F_TRUE}.get(k, 0.0) for k in full.free])
    cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    design = np.column_stack([np.ones(len(X)), local]) * (cell >= 0)[:, None]
    kw = dict(cell_var0=np.array([1e-8, 1e-8, 1e-8]), ridge=ridge)
    c = np.zeros((len(lobs), 2))
    w = np.ones(len(lobs))
    a = gauss_helmert_mixed(full, lobs, x0, SIGMA, c, w, cell, design, n_cells, **kw)
    H = np.asarray(hit_points(full, lobs, a.x, c, SIGMA, 0.0))
    Z = zernike_columns(H, js, EDGES[-1])
    b = gauss_helmert_mixed(core, lobs, x0, SIGMA, c, w, cell, design, n_cells,
                            mode_design=Z, **kw)
    assert bool(a.converged) and bool(b.converged)
    sa, sb = np.asarray(a.sigma), np.asarray(b.sigma)
    assert np.max(np.abs(np.asarray(a.x) - np.asarray(b.x)) / sa) < 0.02
    np.testing.assert_allclose(sb, sa, rtol=5e-3)
    np.testing.assert_allclose(np.asarray(b.cell_var), np.asarray(a.cell_var), rtol=5e-3)
    np.testing.assert_allclose(np.asarray(b.ridge_var), np.asarray(a.ridge_var), rtol=5e-3)


@pytest.mark.parametrize("threads", [1, 2])
def test_a_start_from_a_sample_solution_saves_passes_with_the_same_answer(threads):
    """Started from a random-effect solution of a quarter of the points (its cells ``u0``, its
    contraction ``rate0``), the adjustment of every point judges outliers from its first step
    and stops on the predicted rest: fewer passes than from the white start, the same
    estimates (1e-3 sigma), sigmas, variance components and rejected points; with the start's
    residuals, one pass (the estimates within :data:`MIXED_TOL` of their sigmas)."""
    lobs, X = two_face_scan(3, n=8000)
    bad = np.arange(0, len(lobs), 997)
    lobs[bad, 0] += 0.02  # 2 cm range outliers, far beyond the noise
    model = make_model(["tx", "ty", "tz", "rx", "ry", "f"])
    x_true = np.array([{**POSE, "f": F_TRUE}.get(k, 0.0) for k in model.free])
    cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    design = np.column_stack([np.ones(len(X)), local]) * (cell >= 0)[:, None]
    c, w, v0 = np.zeros((len(lobs), 2)), np.ones(len(lobs)), np.ones(3) * 1e-8

    def run(idx, **kw):
        return gauss_helmert_mixed(model, lobs[idx], kw.pop("x0", x_true), SIGMA, c[idx],
                                   w[idx], cell[idx], design[idx], n_cells,
                                   cell_var0=kw.pop("cell_var0", v0), robust_k=4.0,
                                   threads=threads, **kw)

    every = np.arange(len(lobs))
    ref = run(every)
    s = run(every[::4])
    warm = run(every, x0=np.asarray(s.x), u0=np.asarray(s.u), cell_var0=np.asarray(s.cell_var),
               noise_var0=float(s.noise_var), rate0=float(s.contraction))
    sd = np.sqrt(np.diag(np.asarray(ref.cov)))
    assert np.max(np.abs(np.asarray(warm.x) - np.asarray(ref.x)) / sd) < 1e-3
    assert np.allclose(np.sqrt(np.diag(np.asarray(warm.cov))), sd, rtol=1e-3)
    assert np.allclose(np.asarray(warm.cell_var), np.asarray(ref.cell_var), rtol=1e-2)
    assert np.array_equal(np.asarray(warm.weights) > 0, np.asarray(ref.weights) > 0)
    assert not np.any(np.asarray(warm.weights)[bad] > 0)
    # the white start here is the truth itself; since a step's rejections leave the sums at
    # once (_dropped_sums) it needs 3 passes, as the sample's start does (5 and 4 before)
    assert bool(warm.converged) and int(warm.iterations) <= int(ref.iterations)
    assert 0.0 < float(warm.contraction) < 0.5
    # with the white adjustment's residuals as well (a large position's start, fit._fit), the
    # first step is judged by the sample's contraction: one pass, the same answer within tol
    white = gauss_helmert(model, lobs, x_true, SIGMA, c, weights=w)
    one = run(every, x0=np.asarray(s.x), u0=np.asarray(s.u), cell_var0=np.asarray(s.cell_var),
              noise_var0=float(s.noise_var), rate0=float(s.contraction),
              v0=np.asarray(white.v))
    assert bool(one.converged) and int(one.iterations) == 1
    assert np.max(np.abs(np.asarray(one.x) - np.asarray(ref.x)) / sd) < MIXED_TOL
    assert np.allclose(np.sqrt(np.diag(np.asarray(one.cov))), sd, rtol=1e-3)
    assert np.array_equal(np.asarray(one.weights) > 0, np.asarray(ref.weights) > 0)


def test_chi2_sf_equals_scipys_chi_square_survival():
    """The mode tests' chi-square survival (:func:`chi2_sf`, closed form for integer degrees of
    freedom) equals ``scipy.special.chdtrc`` to 1e-12 relative from p = 1 down to 1e-290, for
    1 to 40 degrees of freedom and a few large ones; 1 at and below 0, 0 at infinity, NaN
    for NaN; a non-positive number of degrees of freedom is refused."""
    from scipy.special import chdtrc

    from hartrao_jax.solver._mixed import chi2_sf

    for k in [*range(1, 41), 63, 253, 1000]:
        for t in np.concatenate([[1e-12, 1e-6], np.geomspace(1e-3, 3000.0, 120)]):
            want = float(chdtrc(k, t))
            if want > 1e-290:
                assert abs(chi2_sf(k, t) - want) <= 1e-12 * want, (k, t)
    assert chi2_sf(3, 0.0) == chi2_sf(2, -1.0) == 1.0
    assert chi2_sf(5, np.inf) == 0.0 and np.isnan(chi2_sf(1, np.nan))
    with pytest.raises(ValueError, match="degrees of freedom"):
        chi2_sf(0, 1.0)
