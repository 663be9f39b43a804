"""Initial values of the object parameters, without hand tuning, at any telescope position.

The pointing (HA/DEC or elevation) gives the gravity vector ``g`` in the telescope frame; the
scanner's z axis hangs along ``g`` (gimbal), which fixes the tilt of the scanner relative to
the paraboloid axis. What the pointing cannot tell is the heading of the scanner on its mount
(its rotation about its own z axis). It is found from the data: for each candidate heading the
scan is rotated into a trial telescope frame and a paraboloid with vertical axis is fitted by
*linear* least squares (translation and focal length), trimmed against scatter; the heading
with the most points near its paraboloid wins. The result is converted to the seed's
parameterisation (``Ry(ry) Rx(rx)``, the frame rotated about Z, see :func:`decompose_zyx`).

NumPy throughout: this is a few thousand points and a grid search, no derivatives needed. The
candidate headings of one step of the search are evaluated together (arrays ``(K, n)`` over
``K`` headings and ``n`` points): the trial frames share the points' trigonometry (a heading
only mixes two precomputed vectors), every trimmed least-squares round is one weighted sum of
precomputed products per heading, and the robust medians are one partition per round.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from jaxtyping import Array, Float

from .._config import row_blocks
from .._programs import cached_jit
from ..campaign._format import Campaign, ScanData, ScanMeta
from ..geometry._geometry import (
    decompose_zyx,
    polar_components,
    polar_to_cartesian,
    rot_z,
    scanner_to_telescope,
)


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


def scanner_rotation(rx: float, ry: float) -> np.ndarray:
    """``Ry(ry) Rx(rx)`` (rad; :func:`..geometry._geometry.scanner_to_telescope`) in NumPy:
    the pose refinement evaluates it about 60 times per scan, and an eager JAX call on
    scalars costs ~3 ms."""
    return scanner_to_telescope(rx, ry, np)


def gimbal_rotation(g: np.ndarray) -> np.ndarray:
    """``Ry(ry0) Rx(rx0)`` that maps the scanner z axis onto the unit gravity vector ``g``."""
    g = np.asarray(g, float) / np.linalg.norm(g)
    rx0 = -np.arcsin(np.clip(g[1], -1, 1))
    ry0 = np.arctan2(g[0], g[2])
    return scanner_rotation(rx0, ry0)


# --------------------------------------------------------------------------------------------
# Heading search: K trial frames at once, as (K, n) arrays per coordinate
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Basis:
    """A sample's trial frames for any heading: ``Ra Rz(k) x = cos(k) u + sin(k) v + w``.

    ``m``: (3, 3, n), ``m[i] = (u_i, v_i, w_i)`` the ``i``-th components (m) of three vectors per
    point (``Rz(k)`` turns ``(x, y)`` into ``(c x - s y, s x + c y)``, so every heading mixes the
    same three); ``r2``: (n,) the squared range (m^2, unchanged by any rotation); ``valid``:
    (n,) the finite points. The points' rotation is computed once, not once per heading.
    """

    m: np.ndarray
    r2: np.ndarray
    valid: np.ndarray

    @staticmethod
    def of(xs: np.ndarray, Ra: np.ndarray) -> _Basis:
        """The basis of the (n, 3) scanner points ``xs`` (m) under the gimbal rotation ``Ra``;
        non-finite points are zeroed and marked invalid (a NaN times a zero weight is NaN)."""
        valid = np.all(np.isfinite(xs), axis=1)
        xs = np.where(valid[:, None], xs, 0.0)
        x, y, z = xs[:, 0], xs[:, 1], xs[:, 2]
        u = Ra[:, 0:1] * x + Ra[:, 1:2] * y
        v = Ra[:, 1:2] * x - Ra[:, 0:1] * y
        w = Ra[:, 2:3] * z
        return _Basis(np.ascontiguousarray(np.stack([u, v, w], axis=1)), x * x + y * y + z * z,
                      valid)

    def head(self, n: int) -> _Basis:
        """The basis of the first ``n`` points."""
        return _Basis(np.ascontiguousarray(self.m[:, :, :n]), self.r2[:n], self.valid[:n])

    def frames(self, kappa: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(X, Y, Z)``, each (K, n): the points (m) in the trial frames of the headings
        ``kappa`` (K,) (rad); one product ``(cos k, sin k, 1) m[i]`` per coordinate."""
        coef = np.stack([np.cos(kappa), np.sin(kappa), np.ones_like(kappa)], axis=1)
        return tuple(coef @ self.m[i] for i in range(3))


@cached_jit
def _pose_of_heading(Ra: Float[Array, "3 3"], heading: Float[Array, ""],
                     t: Float[Array, " 3"]) -> tuple[Array, Array, Array, Float[Array, " 3"]]:
    """``(kappa, ry, rx, t_fit)`` (rad, m) of the frame ``Ra Rz(heading)`` and its translation
    ``t``: the seed's parameterisation (:func:`decompose_zyx`), ``t`` turned by ``-kappa``
    (one compiled call instead of some 30 eager ones)."""
    kappa, ry, rx = decompose_zyx(Ra @ rot_z(heading))
    return kappa, ry, rx, rot_z(-kappa) @ t


def _rowwise_median(a: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Median of ``a[k][keep[k]]`` for every row ``k`` of (K, n) arrays (NaN for an empty row).

    One sort of the block (float32: the median sets a trimming threshold, 1e-7 relative is far
    below what matters): the excluded entries become ``+inf`` (sorted last) and the two middle
    ranks of every row's own count are averaged (``np.median``'s convention).
    """
    m = np.count_nonzero(keep, axis=1)
    b = np.sort(np.where(keep, a, np.inf).astype(np.float32), axis=1)
    rows = np.arange(len(a))
    lo, hi = np.maximum(m - 1, 0) // 2, np.maximum(m, 1) // 2
    med = 0.5 * (b[rows, lo].astype(float) + b[rows, hi])
    return np.where(m > 0, med, np.nan)


def _row_percentiles(v: np.ndarray, q: tuple[float, ...]) -> list[np.ndarray]:
    """Percentiles ``q`` (%) of every row of ``v`` (K, n), linear interpolation as
    ``np.percentile``'s default, from one partition of the block."""
    n = v.shape[1]
    pos = [p / 100 * (n - 1) for p in q]
    kth = sorted({int(np.floor(x)) for x in pos} | {min(int(np.floor(x)) + 1, n - 1)
                                                    for x in pos})
    part = np.partition(v, kth, axis=1)
    out = []
    for x in pos:
        i = int(np.floor(x))
        j, g = min(i + 1, n - 1), x - i
        out.append(part[:, i] + g * (part[:, j] - part[:, i]))
    return out


def _histogram_mode(v: np.ndarray, valid: np.ndarray, tol_m: float) -> np.ndarray:
    """Per row of (K, n) heights ``v`` (m): the centre of the fullest of the ``tol_m``-wide bins
    (10 to 20000 bins) between the 0.5 and 99.5 % percentiles of the ``valid`` (n,) entries,
    as ``np.histogram`` per row (the first of equal maxima); all rows in one ``bincount``."""
    lo, hi = _row_percentiles(v if valid.all() else v[:, valid], (0.5, 99.5))
    same = ~(hi > lo)  # np.histogram widens an empty range by 0.5 on each side
    lo, hi = np.where(same, lo - 0.5, lo), np.where(same, hi + 0.5, hi)
    nb = np.clip((hi - lo) / tol_m, 10, 20000).astype(np.int64)
    inside = valid & (v >= lo[:, None]) & (v <= hi[:, None])
    u = (v - lo[:, None]) * (nb / (hi - lo))[:, None]
    b = np.minimum(np.where(inside, u, 0).astype(np.int64), nb[:, None] - 1)  # hi: last bin
    width = int(nb.max())  # row k's bins at k * width, the rest of its segment empty
    b += np.arange(len(v))[:, None] * width
    h = np.bincount(b[inside], minlength=len(v) * width).reshape(len(v), width)
    return lo + (np.argmax(h, axis=1) + 0.5) * (hi - lo) / nb


def _weighted_lsq(G: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted linear LS with an intercept for every row at once.

    ``G``: (K, k + 2, n) per row a row of ones, the ``k`` regressors and, last, the
    observations of its points; ``w``: (K, n) 0/1 weights. One batched product ``(G w) G^T``
    gives the count, sums and raw moments; the centred normal equations follow (float64;
    coordinates of metres, centring loses nothing that matters). Solves ``obs ~ p .
    regressors + c``; returns ``(p (K, k), c (K,))``, NaN where a row has fewer than
    ``k + 1`` points or (nearly) collinear regressors.
    """
    k = G.shape[1] - 2
    R = np.matmul(G * w.astype(G.dtype)[:, None, :], G.transpose(0, 2, 1))  # float: 2x faster
    sw = R[:, 0, 0]
    s = np.maximum(sw, 1)
    mean = R[:, 0, 1:] / s[:, None]
    M = R[:, 1:, 1:] / s[:, None, None] - mean[:, :, None] * mean[:, None, :]
    A, b = M[:, :k, :k], M[:, :k, k]
    tr = np.einsum("kii->k", A)
    ok = (sw > k) & (np.linalg.det(A) > 1e-12 * np.maximum(tr, 1e-300) ** k)
    p = np.linalg.solve(np.where(ok[:, None, None], A, np.eye(k)), b[..., None])[..., 0]
    c = mean[:, k] - np.einsum("kf,kf->k", p, mean[:, :k])
    return np.where(ok[:, None], p, np.nan), np.where(ok, c, np.nan)


def _paraboloid_params(p: np.ndarray, c: np.ndarray, f: np.ndarray):
    """``(t (K, 3), f (K,))`` of ``2tx x + 2ty y + c`` fits (``p = (2tx, 2ty, ...)``), with
    ``tz = (tx^2 + ty^2 - c) / 4f``; ``f`` NaN where it is not positive and finite."""
    tx, ty = p[:, 0] / 2, p[:, 1] / 2
    f = np.where(np.isfinite(f) & (f > 1e-6), f, np.nan)
    return np.stack([tx, ty, (tx * tx + ty * ty - c) / (4 * f)], axis=1), f


def _paraboloid_res(X, Y, Z, q, t: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(K, n) vertical distance (m) of the points from ``(X+tx)^2 + (Y+ty)^2 = 4 f (Z+tz)``
    (``q = X^2 + Y^2``); ``inf`` for a row without a valid paraboloid."""
    tx, ty, tz = (t[:, i:i + 1] for i in range(3))
    res = Z + tz - (q + 2 * tx * X + 2 * ty * Y + (tx * tx + ty * ty)) / (4 * f[:, None])
    bad = ~(np.isfinite(f) & np.all(np.isfinite(t), axis=1))
    return np.where(bad[:, None], np.inf, res)


def _held_res(G: np.ndarray, t: np.ndarray, f0: float) -> np.ndarray:
    """:func:`_paraboloid_res` at the focal length ``f0``, as one batched product with
    ``G = (1, X, Y, 4 f0 Z - q)`` (K, 4, n): ``res = tz - (tx^2 + ty^2) / 4f0 - 2tx X / 4f0
    - 2ty Y / 4f0 + G_3 / 4f0``; ``inf`` for a row without a valid translation."""
    tx, ty, tz = t[:, 0], t[:, 1], t[:, 2]
    k = 1 / (4 * f0)
    coef = np.stack([tz - k * (tx * tx + ty * ty), -2 * k * tx, -2 * k * ty,
                     np.full_like(tx, k)], axis=1)
    res = np.matmul(coef[:, None, :], G)[:, 0, :]
    return np.where(np.all(np.isfinite(t), axis=1)[:, None], res, np.inf)


def _robust_fits(X, Y, Z, r2: np.ndarray, valid: np.ndarray, f0: float, tol_m: float,
                 rounds: int = 4):
    """Robust paraboloids with vertical axis ``(X+tx)^2 + (Y+ty)^2 = 4 f (Z+tz)``, one per row
    of the (K, n) trial-frame coordinates (m).

    The height offset of each point under the nominal paraboloid is ``tz_i = rho^2/4f0 - Z``;
    reflector points agree on it (the histogram's mode), scatter does not. Trimmed linear LS
    with the focal length held refines the translation (``rounds`` times, at 4 robust sigmas,
    never below ``tol_m``); a last LS frees the focal length. ``r2``: (n,) squared ranges
    (``rho^2 = r2 - Z^2``); ``valid``: (n,) the points that take part.
    Returns ``(t (K, 3), f (K,), res (K, n))``: ``res`` the vertical distances (m), ``inf`` in
    a row whose fit failed (fewer than 10 points near the mode, or ``f`` not positive).
    """
    q = r2 - Z * Z
    tz_i = q * (1 / (4 * f0)) - Z
    mode = _histogram_mode(tz_i, valid, tol_m)
    keep = valid & (np.abs(tz_i - mode[:, None]) < 5 * tol_m)
    enough = np.count_nonzero(keep, axis=1) >= 10
    one = np.ones_like(X)
    G = np.stack([one, X, Y, -4 * f0 * tz_i], axis=1)  # 4 f0 Z - q = 2tx X + 2ty Y + c
    f_held = np.full(len(X), float(f0))
    t, f = _paraboloid_params(*_weighted_lsq(G, keep), f_held)
    res = _held_res(G, t, f0)
    for _ in range(rounds):
        a = np.abs(res)
        thr = np.fmax(4 * 1.4826 * _rowwise_median(a, keep), tol_m)
        keep = valid & (a <= thr[:, None])
        t, f = _paraboloid_params(*_weighted_lsq(G, keep), f_held)
        res = _held_res(G, t, f0)
    # the focal length free: -q = 2tx X + 2ty Y - 4f Z + c
    p, c = _weighted_lsq(np.stack([one, X, Y, Z, -q], axis=1), keep)
    t, f = _paraboloid_params(p, c, -p[:, 2] / 4)
    f = np.where(enough, f, np.nan)
    return t, f, _paraboloid_res(X, Y, Z, q, t, f)


def _heading_scores(basis: _Basis, kappa: np.ndarray, f0: float, tol_m: float, n_total: int):
    """Score of every trial heading ``kappa`` (K,) (rad): the share of the ``n_total`` sampled
    points within ``tol_m`` (m) of its robust paraboloid, less a tie-break towards the nominal
    focal length ``f0`` (symmetric geometries); ``-inf`` where no paraboloid was found.
    Returns ``(score (K,), t (K, 3), f (K,), inliers (K,))``."""
    n = len(basis.r2)
    out = []
    per = max(1, _BLOCK // max(n, 1))
    for i in range(0, len(kappa), per):  # blocks of headings: the (k, n) arrays stay in cache
        t, f, res = _robust_fits(*basis.frames(kappa[i:i + per]), basis.r2, basis.valid, f0,
                                 tol_m)
        inl = np.count_nonzero(np.abs(res) < tol_m, axis=1) / max(n_total, 1)
        ok = np.isfinite(f) & (f > 0)
        out.append((np.where(ok, inl - 1e-3 * np.abs(f - f0) / f0, -np.inf), t, f, inl))
    return tuple(np.concatenate(a) for a in zip(*out))


_BLOCK = 60000
"""Headings x points per block of :func:`_heading_scores` (arrays of ~0.5 MB: in cache)."""


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

    The full turn is scored on ``n_coarse`` points at ``n_headings`` headings, then three local
    refinements (9 headings each, the spacing shrinking 4x per level: 0.8 mrad at the end at
    the default 120 headings) on the whole sample; each level is one batched evaluation
    (:func:`_heading_scores`) of the headings not scored at the level before. The best
    heading's robust paraboloid gives the translation, the focal length and the inlier
    fraction. (The score is nearly flat within some 10 mrad of the best heading, where a
    heading error is compensated by decimetres of ``tx, ty``: scoring the refinement on fewer
    points moves the heading there, and with it the adjustment's path; it is kept as it was.)

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
    xs = np.stack(polar_components(np.asarray(r, float)[idx], np.asarray(phi, float)[idx],
                                   np.asarray(theta, float)[idx], xp=np), axis=1)
    basis = _Basis.of(xs, gimbal_rotation(gravity))
    if np.count_nonzero(basis.valid) < 10:
        raise ValueError(f"initial values need at least 10 finite points, got "
                         f"{np.count_nonzero(basis.valid)}")
    n_s = len(xs)
    f0 = float(focal_length_m)

    grid = np.linspace(0, 2 * np.pi, n_headings, endpoint=False)
    nc = min(n_coarse, n_s)
    sc = _heading_scores(basis.head(nc), grid, f0, tol_m, nc)[0]
    best = grid[int(np.argmax(sc))]
    step = grid[1] - grid[0]
    done: dict[int, tuple] = {}  # heading (nrad) -> its score, t, f, inliers on the sample
    for _ in range(3):  # local refinement: 9 headings, of which up to 3 were scored before
        cand = best + np.linspace(-step, step, 9)
        keys = [int(k) for k in np.round(cand * 1e9)]
        new = [i for i, k in enumerate(keys) if k not in done]
        for j, row in enumerate(zip(*_heading_scores(basis, cand[new], f0, tol_m, n_s))):
            done[keys[new[j]]] = row
        i = int(np.argmax([done[k][0] for k in keys]))
        best, (_, t, f, inl) = cand[i], done[keys[i]]
        step /= 4
    kappa, ry, rx, t_fit = (np.asarray(a) for a in _pose_of_heading(
        gimbal_rotation(gravity), np.float64(best), np.asarray(t, float)))
    kappa, ry, rx = float(kappa), float(ry), float(rx)
    return InitialValues(
        x={"tx": float(t_fit[0]), "ty": float(t_fit[1]), "tz": float(t_fit[2]),
           "rx": rx, "ry": ry, "f": float(f)},
        kappa_rad=kappa,
        heading_rad=float(np.mod(best, 2 * np.pi)),
        inlier_fraction=float(inl),
        tol_m=tol_m,
    )


def initial_distance(
    r: np.ndarray, phi: np.ndarray, theta: np.ndarray, x: dict[str, float]
) -> np.ndarray:
    """Approximate vertical distance (m) of every raw point from the initial paraboloid.

    Used as the geometry-derived window that removes gross outliers (cone, legs, background)
    before the rigorous adjustment.
    """
    r, phi, theta = (np.asarray(a, float) for a in (r, phi, theta))
    R = scanner_rotation(x["rx"], x["ry"])
    out = np.empty(r.shape)
    for rows in row_blocks(len(out)):  # a block's temporaries reused, not fresh pages
        out[rows] = _distance(R, x, r[rows], phi[rows], theta[rows])
    return out


def _distance(R: np.ndarray, x: dict[str, float], r, phi, theta) -> np.ndarray:
    """:func:`initial_distance` of some points with the scanner's rotation ``R``."""
    a, b, c = polar_components(r, phi, theta, xp=np)
    X = R[0, 0] * a + R[0, 1] * b + R[0, 2] * c + x["tx"]
    Y = R[1, 0] * a + R[1, 1] * b + R[1, 2] * c + x["ty"]
    Z = R[2, 0] * a + R[2, 1] * b + R[2, 2] * c + x["tz"]
    return Z - (X * X + Y * Y) / (4 * x["f"])


POLE_EXCLUSION_RAD = 1e-3
"""Points within this angle of the scanner's pole (``|sin theta|`` below it) are left out of
the adjustment: the collimation and trunnion corrections ``2 x6 / sin(theta)`` and
``x7 / tan(theta)`` are singular there, and a gross outlier's residual of a few 1e-4 rad makes
their linearisation jump between iterations (30 iterations instead of 4 at 6e-4 rad steps)."""


def geometry_window(
    r: np.ndarray, phi: np.ndarray, theta: np.ndarray, x: dict[str, float], window_m: float
) -> np.ndarray:
    """Points to adjust: within ``window_m`` (vertical, m) of the initial paraboloid and not
    within :data:`POLE_EXCLUSION_RAD` of the scanner's pole.

    A block of rows at a time (:func:`.._config.row_blocks`): the fifteen temporaries of whole
    columns were fresh pages each (6.3e6 points: 1.0 s, 0.76 s of it system time)."""
    r, phi, theta = (np.asarray(a, float) for a in (r, phi, theta))
    R = scanner_rotation(x["rx"], x["ry"])
    out = np.empty(r.shape, bool)
    for rows in row_blocks(len(out)):
        th = theta[rows]
        near = np.abs(_distance(R, x, r[rows], phi[rows], th)) < window_m
        out[rows] = near & (np.abs(np.sin(th)) > POLE_EXCLUSION_RAD)
    return out


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
    kappa, ry, rx = (float(v) for v in decompose_zyx(R, np))
    R2 = scanner_rotation(rx, ry)
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
        kappa, ry, rx = (float(x) for x in decompose_zyx(R, np))
        R2 = scanner_rotation(rx, ry)
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
