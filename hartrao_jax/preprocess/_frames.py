"""Geometry of the windows (NumPy): scanner -> telescope frame of a pose, the "flat" frame
(paraboloid sag removed, heights as normal distances, m), the pose refinement and the
range window (m) from the reflector annulus."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..campaign._campaign import Campaign
from ..geometry._geometry import polar_components
from ._initial import InitialValues, scanner_rotation
from ._types import PreprocessConfig


def _rot(rx: float, ry: float) -> np.ndarray:
    """``Ry(ry) Rx(rx)`` (:func:`..geometry._geometry.scanner_to_telescope`) as NumPy."""
    return scanner_rotation(rx, ry)


def _pose(x: Mapping[str, float] | InitialValues) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, f)`` of object parameters (``tx ty tz rx ry f``): ``X = R x_s + t``."""
    x = x.x if isinstance(x, InitialValues) else x
    return _rot(x["rx"], x["ry"]), np.array([x["tx"], x["ty"], x["tz"]]), float(x["f"])


def _cartesian(r: np.ndarray, phi: np.ndarray, theta: np.ndarray):
    """Seed eq. (2) in NumPy as three arrays ``x, y, z`` (the geometry's formula)."""
    return polar_components(r, phi, theta, xp=np)


def _flat_coordinates(xs, x: Mapping[str, float]):
    """Fitted-frame ``X, Y`` and the normal distance ``h`` from the paraboloid of ``x``; ``rho``.

    ``xs`` are the scanner coordinates as three arrays. The vertical distance
    ``Z - rho^2/4f`` (as :func:`._init.initial_distance`) is scaled by
    ``1 / sqrt(1 + (rho/2f)^2)`` into a distance along the paraboloid's normal.
    Returns ``(X, Y, h), rho``.
    """
    R, t, f = _pose(x)
    a, b, c = xs
    X = R[0, 0] * a + R[0, 1] * b + R[0, 2] * c + t[0]
    Y = R[1, 0] * a + R[1, 1] * b + R[1, 2] * c + t[1]
    Z = R[2, 0] * a + R[2, 1] * b + R[2, 2] * c + t[2]
    q = X * X + Y * Y
    Z -= q * (1.0 / (4 * f))
    q *= 1.0 / (4 * f * f)
    q += 1.0
    np.sqrt(q, out=q)
    Z /= q  # normal distance
    rho = np.sqrt((q * q - 1.0) * (4 * f * f))
    return (X, Y, Z), rho


def _normal_distance(xs, p: np.ndarray) -> np.ndarray:
    x = dict(zip(("tx", "ty", "tz", "rx", "ry", "f"), p))
    return _flat_coordinates(xs, x)[0][2]


def _least_squares(J: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``argmin |J p - b|`` of a tall ``J`` (n, k): normal equations of the column-scaled ``J``
    (a k x k solve, ~10x faster than ``lstsq``'s SVD on 20000 x 6), ``lstsq`` when they are
    ill-conditioned (condition number above 1e10, i.e. ``J``'s above 1e5)."""
    s = np.sqrt(np.einsum("ij,ij->j", J, J))
    s = np.where(s > 0, s, 1.0)
    Js = J / s
    N = Js.T @ Js
    if not np.linalg.cond(N) < 1e10:
        return np.linalg.lstsq(J, b, rcond=None)[0]
    return np.linalg.solve(N, Js.T @ b) / s


def refine_pose(xs: np.ndarray, x: Mapping[str, float], *, iterations: int = 8,
                min_tol_m: float = 0.003) -> dict[str, float]:
    """Trimmed Gauss-Newton of ``tx ty tz rx ry f`` on scanner points near the paraboloid.

    The initial values hold the rotation from the gravity vector and a heading found on a grid,
    so ``rx, ry`` can be off by 1e-2 rad, compensated by decimetres in ``tx, ty`` (the surface
    itself stays within a centimetre): good enough for a height window, not for the radius tests
    at the cone and the rim. A few Gauss-Newton steps on a sample of the points inside the
    height window, trimmed at 4 robust sigmas, fix that. NumPy, numerical Jacobian.
    ``xs``: scanner coordinates as three arrays.
    """
    p = np.array([x["tx"], x["ty"], x["tz"], x["rx"], x["ry"], x["f"]], float)
    h = np.array([1e-6, 1e-6, 1e-6, 1e-7, 1e-7, 1e-6])
    for _ in range(iterations):
        r0 = _normal_distance(xs, p)
        a = np.abs(r0)
        keep = a <= max(4 * 1.4826 * np.median(a), min_tol_m)
        if keep.sum() < 50:
            break
        xk, rk = tuple(c[keep] for c in xs), r0[keep]
        J = np.stack([(_normal_distance(xk, p + h[k] * np.eye(6)[k]) - rk) / h[k]
                      for k in range(6)], 1)
        dp = _least_squares(J, -rk)
        if not np.all(np.isfinite(dp)):
            break
        p = p + dp
        if np.all(np.abs(dp[:3]) < 1e-5) and np.all(np.abs(dp[3:5]) < 1e-7):
            break
    return dict(zip(("tx", "ty", "tz", "rx", "ry", "f"), (float(v) for v in p)))


def reflector_distance_range(
    scanner_position: np.ndarray, f: float, rho_min: float, rho_max: float, offset_m: float = 0.0,
    n_rho: int = 129, n_psi: int = 720,
) -> tuple[float, float]:
    """Smallest and largest distance (m) from a point to the annulus of ``Z = rho^2 / 4f``.

    The annulus is ``rho_min <= rho <= rho_max`` about the axis (for an offset reflector,
    ``offset_m > 0``, the aperture circle centred ``offset_m`` off the axis, widened to all
    azimuths). Evaluated on a dense polar grid (the extremes lie on the boundary or at a smooth
    interior extremum; the grid error is far below any sensible margin).
    """
    if offset_m:
        rho_min, rho_max = max(0.0, offset_m - rho_max), offset_m + rho_max
    rho = np.linspace(rho_min, rho_max, n_rho)[:, None]
    psi = np.linspace(0.0, 2 * np.pi, n_psi, endpoint=False)[None, :]
    X = rho * np.cos(psi)
    Y = rho * np.sin(psi)
    Z = np.broadcast_to(rho**2 / (4 * f), X.shape)
    p = np.asarray(scanner_position, float)
    d = np.sqrt((X - p[0]) ** 2 + (Y - p[1]) ** 2 + (Z - p[2]) ** 2)
    return float(d.min()), float(d.max())


def default_range_window(
    campaign: Campaign, pose: Mapping[str, float] | InitialValues | None,
    config: PreprocessConfig | None = None,
) -> tuple[float, float]:
    """``(D_min, D_max)`` (m) from the telescope geometry and the scanner pose (module doc).

    ``pose``: initial values (or refined object parameters); None: nominal geometry, the scanner
    at the focus with ``nominal_range_margin_m``.
    """
    cfg = config or PreprocessConfig()
    tel = campaign.telescope
    if pose is not None:
        _, t, f = _pose(pose)
        margin = cfg.range_margin_m
    else:  # nominal: the scanner hangs at the sub-reflector, near the focus
        t, f = np.array([0.0, 0.0, tel.focal_length_m]), tel.focal_length_m
        margin = cfg.nominal_range_margin_m
    lo, hi = reflector_distance_range(t, f, tel.cone_radius_m, tel.diameter_m / 2, tel.offset_m)
    return max(0.0, lo - margin), hi + margin

