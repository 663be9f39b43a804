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

from ..campaign._format import Campaign, ScanData, ScanMeta
from ..geometry._geometry import decompose_zyx, polar_to_cartesian, rot_x, rot_y, rot_z


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
    n_coarse: int = 2500,
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
        n_coarse: points of the sample that score the full turn (the inlier fraction of a
            heading to about 1 %); the local refinement uses the whole sample.
        tol_m: distance defining an inlier of the trial paraboloid.
    """
    rng = np.random.default_rng(seed)
    n = len(r)
    idx = rng.choice(n, size=min(n, n_sample), replace=False) if n > n_sample else np.arange(n)
    xs = np.asarray(polar_to_cartesian(r[idx], phi[idx], theta[idx]))
    Ra = gimbal_rotation(gravity)

    def score(kappa_s: float, pts: np.ndarray = xs):
        R = Ra @ np.asarray(rot_z(kappa_s))
        X = pts @ R.T
        t, f, res = _robust_fit(X, focal_length_m, tol_m)
        if not np.isfinite(f) or f <= 0:
            return -np.inf, t, f
        inl = np.mean(np.abs(res) < tol_m)
        # tie-break towards the nominal focal length (symmetric geometries)
        return inl - 1e-3 * abs(f - focal_length_m) / focal_length_m, t, f

    grid = np.linspace(0, 2 * np.pi, n_headings, endpoint=False)
    scores = [score(k, xs[:n_coarse])[0] for k in grid]
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


POLE_EXCLUSION_RAD = 1e-3
"""Points within this angle of the scanner's pole (``|sin theta|`` below it) are left out of
the adjustment: the collimation and trunnion corrections ``2 x6 / sin(theta)`` and
``x7 / tan(theta)`` are singular there, and a gross outlier's residual of a few 1e-4 rad makes
their linearisation jump between iterations (30 iterations instead of 4 at 6e-4 rad steps)."""


def geometry_window(
    r: np.ndarray, phi: np.ndarray, theta: np.ndarray, x: dict[str, float], window_m: float
) -> np.ndarray:
    """Points to adjust: within ``window_m`` (vertical, m) of the initial paraboloid and not
    within :data:`POLE_EXCLUSION_RAD` of the scanner's pole."""
    near = np.abs(initial_distance(r, phi, theta, x)) < window_m
    return near & (np.abs(np.sin(np.asarray(theta, float))) > POLE_EXCLUSION_RAD)


# --------------------------------------------------------------------------------------------
# Any pose: algebraic quadric fit (no pointing, offset reflectors, any scanner orientation)
# --------------------------------------------------------------------------------------------


def _quadric_design(P: np.ndarray) -> np.ndarray:
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    return np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z,
                            np.ones(len(P))])


def _paraboloid_from_quadric(q: np.ndarray):
    """Axis ``a`` (towards the focus side), vertex ``V`` and focal length from quadric coefficients.

    ``x^T Q x + p . x + c = 0`` with ``Q = k (I - a a^T)`` for a paraboloid of revolution:
    ``a`` is the eigenvector of the smallest |eigenvalue|; ``f = -(a . p) / (4 k)``.
    """
    Q = np.array([[q[0], q[3], q[4]], [q[3], q[1], q[5]], [q[4], q[5], q[2]]])
    p, c = q[6:9], q[9]
    w, E = np.linalg.eigh(Q)
    i = int(np.argmin(np.abs(w)))
    a = E[:, i]
    k = float(np.mean(np.delete(w, i)))
    f = -float(a @ p) / (4 * k)
    if f < 0:
        a, f = -a, -f
    Pp = np.eye(3) - np.outer(a, a)
    V_perp = -0.5 * Pp @ (p / k)  # (I - a a^T) V
    # along the axis: the vertex satisfies the quadric: V = V_perp + s a
    #   V^T Q V + p.V + c = 0 -> k |V_perp|^2 + p.V_perp + s (p.a) + c = 0
    s = -(k * V_perp @ V_perp + p @ V_perp + c) / (p @ a)
    return a, V_perp + s * a, f


def _paraboloid_distance(P: np.ndarray, a: np.ndarray, V: np.ndarray, f: float) -> np.ndarray:
    """Approximate signed distance (m) of points from the paraboloid (axis a, vertex V, f)."""
    D = P - V
    h = D @ a
    rho2 = np.sum(D * D, axis=1) - h * h
    return (h - rho2 / (4 * f)) / np.sqrt(1 + rho2 / (4 * f * f))


def _locally_planar(P: np.ndarray, k: int = 12, ratio: float = 0.05) -> np.ndarray:
    """Points whose ``k`` nearest neighbours lie close to a plane (a surface, not scatter).

    ``ratio``: largest allowed share of the smallest eigenvalue of the neighbourhood covariance;
    isolated returns (background, scatter in mid-air) have round neighbourhoods and fail it.
    """
    from scipy.spatial import cKDTree

    if len(P) <= k:
        return np.ones(len(P), bool)
    _, nb = cKDTree(P).query(P, k=k)
    Q = P[nb] - P[nb].mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", Q, Q)
    w = np.linalg.eigvalsh(C)
    share = w[:, 0] / np.maximum(w.sum(axis=1), 1e-30)
    keep = share < ratio
    return keep if keep.sum() > 0.2 * len(P) else np.ones(len(P), bool)


def quadric_initial_values(
    r: np.ndarray, phi: np.ndarray, theta: np.ndarray, *, n_sample: int = 20000,
    tol_m: float = 0.05, rounds: int = 6, seed: int = 0,
) -> InitialValues:
    """Initial values for any pose from an algebraic quadric fit of the points (scanner frame).

    Works without pointing metadata, for any scanner orientation and for offset reflectors
    whose vertex lies far outside the data. The fit is trimmed against non-reflector returns
    (it keeps the points nearest to the current paraboloid, then tightens). The paraboloid axis
    ``a`` (towards the focus) fixes ``rx, ry`` (third row of ``Ry Rx`` equals ``a``) and the vertex
    fixes the translation.
    """
    rng = np.random.default_rng(seed)
    n = len(r)
    idx = rng.choice(n, size=min(n, n_sample), replace=False) if n > n_sample else np.arange(n)
    P = np.asarray(polar_to_cartesian(r[idx], phi[idx], theta[idx]))
    keep = _locally_planar(P)
    mu = np.median(P[keep], axis=0)
    scale = float(np.median(np.linalg.norm(P[keep] - mu, axis=1))) or 1.0
    Pn = (P - mu) / scale

    def model(sel):
        _, _, Vt = np.linalg.svd(_quadric_design(Pn[sel]), full_matrices=False)
        a, Vn, fn = _paraboloid_from_quadric(Vt[-1])
        return a, mu + Vn * scale, fn * scale

    # RANSAC over small random subsets (a few far returns ruin an algebraic fit), then trimming
    cand = np.flatnonzero(keep)
    best, best_score = None, np.inf
    for _ in range(40):
        sel = rng.choice(cand, size=min(len(cand), 40), replace=False)
        a, V, f = model(sel)
        if not (np.isfinite(f) and f > 0 and np.all(np.isfinite(V))):
            continue
        score = np.median(np.abs(_paraboloid_distance(P[keep], a, V, f)))
        if score < best_score:
            best, best_score = (a, V, f), score
    if best is None:
        best = model(keep)
    a, V, f = best
    for _ in range(rounds):
        d = np.abs(_paraboloid_distance(P, a, V, f))
        sel = keep & (d <= max(4 * 1.4826 * np.median(d[keep]), tol_m))
        if sel.sum() < 10:
            break
        a, V, f = model(sel)
    R = _rotation_axis_to_z(a)
    kappa, ry, rx = (float(v) for v in decompose_zyx(R))
    R2 = np.asarray(rot_y(ry) @ rot_x(rx))
    t = -R2 @ V
    d = np.abs(_paraboloid_distance(P, a, V, f))
    return InitialValues(
        x={"tx": float(t[0]), "ty": float(t[1]), "tz": float(t[2]), "rx": rx, "ry": ry,
           "f": float(f)},
        kappa_rad=0.0, heading_rad=0.0, inlier_fraction=float(np.mean(d < tol_m)), tol_m=tol_m,
    )


def _rotation_axis_to_z(a: np.ndarray) -> np.ndarray:
    """A rotation whose third row is ``a`` (maps the axis ``a`` onto +Z)."""
    a = a / np.linalg.norm(a)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(helper, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    return np.stack([e1, e2, a])


def patch_initial_values(
    r: np.ndarray, phi: np.ndarray, theta: np.ndarray, *, focal_length_m: float,
    n_sample: int = 20000, tol_m: float = 0.02, seed: int = 0,
) -> list[InitialValues]:
    """Initial values from a small region of a reflector of known focal length.

    A region much smaller than the aperture does not determine a quadric, but its curvature
    does determine where it sits on a paraboloid of known ``f``: at radius ``rho`` the sagittal
    curvature is ``1 / (2 f sqrt(1 + s^2))`` with ``s = rho / 2f``, and the meridional (smaller)
    curvature direction points along the radius. The axis is the surface normal tilted by
    ``atan(s)`` within the meridional plane; the sign of that tilt is ambiguous, so both
    candidates are returned, best first (by the share of points within ``tol_m``).
    """
    rng = np.random.default_rng(seed)
    n = len(r)
    idx = rng.choice(n, size=min(n, n_sample), replace=False) if n > n_sample else np.arange(n)
    P = np.asarray(polar_to_cartesian(r[idx], phi[idx], theta[idx]))
    keep = np.ones(len(P), bool)
    for _ in range(4):  # trimmed local quadratic height field
        c = np.mean(P[keep], axis=0)
        _, _, Vt = np.linalg.svd(P[keep] - c, full_matrices=False)
        e1, e2, nrm = Vt
        if nrm @ (-c) < 0:  # normal towards the scanner (the focus side of the reflector)
            nrm, e2 = -nrm, -e2
        D = P - c
        u, v, h = D @ e1, D @ e2, D @ nrm
        A = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
        coef, *_ = np.linalg.lstsq(A[keep], h[keep], rcond=None)
        res = h - A @ coef
        keep = np.abs(res) < max(4 * 1.4826 * np.median(np.abs(res[keep])), 1e-3)
    H = np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]])
    w, E = np.linalg.eigh(H)
    i_m = int(np.argmin(np.abs(w)))
    k_s = float(np.abs(w[1 - i_m]))
    f = focal_length_m
    s2 = max(1.0 / (4 * f * f * k_s * k_s) - 1.0, 0.0)
    s = np.sqrt(s2)
    rho = 2 * f * s
    # the surface at the centroid of the patch: offset and slope of the height field there
    p0 = c + coef[0] * nrm
    n0 = nrm - coef[1] * e1 - coef[2] * e2
    n0 /= np.linalg.norm(n0)
    t_m = E[0, i_m] * e1 + E[1, i_m] * e2  # meridional direction (sign unknown)
    t_m = t_m - (t_m @ n0) * n0
    t_m /= np.linalg.norm(t_m)
    alpha = np.arctan(s)
    out = []
    for sign in (1.0, -1.0):
        t = sign * t_m
        a = np.cos(alpha) * n0 + np.sin(alpha) * t  # axis direction, towards the focus side
        r_hat = t - (t @ a) * a
        r_hat /= np.linalg.norm(r_hat)
        V = p0 - rho * r_hat - (rho * rho / (4 * f)) * a
        R = _rotation_axis_to_z(a)
        kappa, ry, rx = (float(x) for x in decompose_zyx(R))
        R2 = np.asarray(rot_y(ry) @ rot_x(rx))
        tt = -R2 @ V
        d = np.abs(_paraboloid_distance(P, a, V, f))
        out.append(InitialValues(
            x={"tx": float(tt[0]), "ty": float(tt[1]), "tz": float(tt[2]), "rx": rx, "ry": ry,
               "f": f},
            kappa_rad=0.0, heading_rad=0.0, inlier_fraction=float(np.mean(d < tol_m)), tol_m=tol_m,
        ))
    return sorted(out, key=lambda c: -c.inlier_fraction)


def choose_initial_values(campaign: Campaign, meta: ScanMeta, data: ScanData, g, *, seed=0):
    """Pointing-based initial values (scanner hanging on its gimbal) when they fit the data,
    else the pose-free quadric fit (one-face exports, other scanner set-ups, offset reflectors).
    """
    tel = campaign.telescope
    cands = []
    if meta.cycle != 0 and tel.offset_m == 0:
        cands.append(initial_values(data.range_m, data.phi_rad, data.theta_rad, g,
                                    focal_length_m=tel.focal_length_m, seed=seed))
        if cands[-1].inlier_fraction >= 0.5:
            return cands[-1]
    q = quadric_initial_values(data.range_m, data.phi_rad, data.theta_rad, seed=seed)
    cands.append(q)
    if q.inlier_fraction < 0.5:  # a region too small for a quadric: use its curvature
        cands.extend(patch_initial_values(data.range_m, data.phi_rad, data.theta_rad,
                                          focal_length_m=tel.focal_length_m, seed=seed))
    return max(cands, key=lambda c: c.inlier_fraction)
