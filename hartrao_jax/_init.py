"""Initial values of the object parameters, without hand tuning, at any telescope position.

The pointing (HA/DEC or elevation) gives the gravity vector ``g`` in the telescope frame; the
scanner's z axis hangs along ``g`` (gimbal), which fixes the tilt of the scanner relative to
the paraboloid axis. What the pointing cannot tell is the heading of the scanner on its mount
(its rotation about its own z axis). It is found from the data: for each candidate heading the
scan is rotated into a trial telescope frame and a paraboloid with vertical axis is fitted by
*linear* least squares (translation and focal length), trimmed against scatter; the heading
with the most points near its paraboloid wins. The result is converted to the seed's
parameterisation (``Ry(ry) Rx(rx)``, the frame rotated about Z, see :func:`decompose_zyx`).

NumPy throughout: this is a few thousand points and a grid search, no derivatives needed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._geometry import decompose_zyx, polar_to_cartesian, rot_x, rot_y, rot_z


@dataclass(frozen=True)
class InitialValues:
    """Initial object parameters (fitted frame) and what the search found.

    ``x`` maps ``tx ty tz`` (m), ``rx ry`` (rad), ``f`` (m). ``kappa_rad`` is the rotation of the
    trial frame about Z (the north-alignment angle implied by the found heading), ``heading_rad``
    the scanner heading on its mount, ``inlier_fraction`` the share of sampled points within
    ``tol_m`` of the initial paraboloid.
    """

    x: dict[str, float]
    kappa_rad: float
    heading_rad: float
    inlier_fraction: float
    tol_m: float


def gimbal_rotation(g: np.ndarray) -> np.ndarray:
    """``Ry(ry0) Rx(rx0)`` that maps the scanner z axis onto the unit gravity vector ``g``."""
    g = np.asarray(g, float) / np.linalg.norm(g)
    rx0 = -np.arcsin(np.clip(g[1], -1, 1))
    ry0 = np.arctan2(g[0], g[2])
    return np.asarray(rot_y(ry0) @ rot_x(rx0))


def _vertical_paraboloid_lsq(X: np.ndarray, keep: np.ndarray, f_fixed: float | None = None):
    """Linear LS of ``(X+tx)^2 + (Y+ty)^2 = 4 f (Z+tz)`` on the points ``keep``.

    With ``f_fixed`` the focal length is held (3 unknowns), else estimated (4 unknowns).
    Returns ``(t, f, res)`` with ``res`` the vertical distance (m) of every point.
    """
    q = X[:, 0] ** 2 + X[:, 1] ** 2
    if f_fixed is None:
        A = np.column_stack([X[:, 0], X[:, 1], X[:, 2], np.ones(len(X))])
        p, *_ = np.linalg.lstsq(A[keep], -q[keep], rcond=None)
        tx, ty, f, c = p[0] / 2, p[1] / 2, -p[2] / 4, p[3]
    else:
        f = f_fixed
        A = np.column_stack([X[:, 0], X[:, 1], np.ones(len(X))])
        p, *_ = np.linalg.lstsq(A[keep], (4 * f * X[:, 2] - q)[keep], rcond=None)
        tx, ty, c = p[0] / 2, p[1] / 2, p[2]
    if not np.isfinite(f) or f <= 1e-6:
        return np.zeros(3), np.nan, np.full(len(X), np.inf)
    tz = (tx * tx + ty * ty - c) / (4 * f)
    res = (X[:, 2] + tz) - ((X[:, 0] + tx) ** 2 + (X[:, 1] + ty) ** 2) / (4 * f)
    return np.array([tx, ty, tz]), f, res


def _robust_fit(X: np.ndarray, f0: float, tol_m: float, rounds: int = 4):
    """Robust paraboloid with vertical axis: histogram mode of the height, then trimmed LS.

    The height offset of each point under the nominal paraboloid is ``tz_i = rho^2/4f0 - Z``;
    reflector points agree on it (the mode), scatter does not. Trimmed linear LS with the focal
    length held refines the translation; a last LS frees the focal length.
    """
    tz_i = (X[:, 0] ** 2 + X[:, 1] ** 2) / (4 * f0) - X[:, 2]
    lo, hi = np.nanpercentile(tz_i, [0.5, 99.5])
    nb = int(np.clip((hi - lo) / tol_m, 10, 20000))
    h, e = np.histogram(tz_i, bins=nb, range=(lo, hi))
    mode = 0.5 * (e[np.argmax(h)] + e[np.argmax(h) + 1])
    keep = np.abs(tz_i - mode) < 5 * tol_m
    if keep.sum() < 10:
        return np.zeros(3), np.nan, np.full(len(X), np.inf)
    t, f, res = _vertical_paraboloid_lsq(X, keep, f_fixed=f0)
    for _ in range(rounds):
        a = np.abs(res)
        keep = a <= max(4 * 1.4826 * np.median(a[keep]), tol_m)
        t, f, res = _vertical_paraboloid_lsq(X, keep, f_fixed=f0)
    t, f, res = _vertical_paraboloid_lsq(X, keep)
    return t, f, res


def initial_values(
    r: np.ndarray,
    phi: np.ndarray,
    theta: np.ndarray,
    gravity: np.ndarray,
    *,
    focal_length_m: float,
    n_sample: int = 20000,
    n_headings: int = 120,
    tol_m: float = 0.02,
    seed: int = 0,
) -> InitialValues:
    """Initial values from the pointing (gravity) and the scan itself (heading search).

    Args:
        r, phi, theta: raw observations (m, rad) of the scan (scatter included).
        gravity: unit gravity vector in the telescope frame (from :func:`pointing_gravity`).
        focal_length_m: nominal focal length (m), used to rank headings with nearly equal fits.
        n_sample: points drawn (seeded) for the search.
        n_headings: headings tried on a full turn before a local refinement.
        tol_m: distance defining an inlier of the trial paraboloid.
    """
    rng = np.random.default_rng(seed)
    n = len(r)
    idx = rng.choice(n, size=min(n, n_sample), replace=False) if n > n_sample else np.arange(n)
    xs = np.asarray(polar_to_cartesian(r[idx], phi[idx], theta[idx]))
    Ra = gimbal_rotation(gravity)

    def score(kappa_s: float):
        R = Ra @ np.asarray(rot_z(kappa_s))
        X = xs @ R.T
        t, f, res = _robust_fit(X, focal_length_m, tol_m)
        if not np.isfinite(f) or f <= 0:
            return -np.inf, t, f
        inl = np.mean(np.abs(res) < tol_m)
        # tie-break towards the nominal focal length (symmetric geometries)
        return inl - 1e-3 * abs(f - focal_length_m) / focal_length_m, t, f

    grid = np.linspace(0, 2 * np.pi, n_headings, endpoint=False)
    scores = [score(k)[0] for k in grid]
    best = grid[int(np.argmax(scores))]
    step = grid[1] - grid[0]
    for _ in range(3):  # local refinement
        cand = best + np.linspace(-step, step, 9)
        sc = [score(k)[0] for k in cand]
        best = cand[int(np.argmax(sc))]
        step /= 4
    s, t, f = score(best)
    R_full = Ra @ np.asarray(rot_z(best))
    kappa, ry, rx = (float(a) for a in decompose_zyx(R_full))
    t_fit = np.asarray(rot_z(-kappa)) @ t
    X = xs @ R_full.T
    _, _, res = _robust_fit(X, focal_length_m, tol_m)
    return InitialValues(
        x={"tx": float(t_fit[0]), "ty": float(t_fit[1]), "tz": float(t_fit[2]),
           "rx": rx, "ry": ry, "f": float(f)},
        kappa_rad=kappa,
        heading_rad=float(np.mod(best, 2 * np.pi)),
        inlier_fraction=float(np.mean(np.abs(res) < tol_m)),
        tol_m=tol_m,
    )


def initial_distance(
    r: np.ndarray, phi: np.ndarray, theta: np.ndarray, x: dict[str, float]
) -> np.ndarray:
    """Approximate vertical distance (m) of every raw point from the initial paraboloid.

    Used as the geometry-derived window that removes gross outliers (cone, legs, background)
    before the rigorous adjustment.
    """
    xs = np.asarray(polar_to_cartesian(r, phi, theta))
    R = np.asarray(rot_y(x["ry"]) @ rot_x(x["rx"]))
    X = xs @ R.T + np.array([x["tx"], x["ty"], x["tz"]])
    return X[:, 2] - (X[:, 0] ** 2 + X[:, 1] ** 2) / (4 * x["f"])
