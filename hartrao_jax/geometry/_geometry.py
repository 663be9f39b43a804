"""Geometry: rotations, pointing, scanner polar coordinates, dish coordinates, panels, Zernike.

Conventions (binding, from ``shared/spec/campaign-format.md``):

* Scanner frame, seed eq. (2): ``x = r sin(theta) sin(phi)``, ``y = r sin(theta) cos(phi)``,
  ``z = r cos(theta)``; the scanner hangs upside down, its z axis points to the nadir.
* Telescope frame: origin at the paraboloid vertex, Z along the boresight, X north and Y west
  when the telescope points at the zenith.
* All angles in radians unless a name ends in ``_deg``; lengths in metres.

Everything differentiable is written in ``jax.numpy``; panel bookkeeping is NumPy.
"""

from __future__ import annotations

from functools import lru_cache
from math import factorial

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._config import BLOCK_ROWS, by_row_blocks, lend_to_device
from .._programs import cached_jit
from ..campaign._format import cartesian_to_raw  # noqa: F401  (the recording's face rule)
from ._trig import host_sincos

# --------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------


def rot_x(a: ArrayLike, xp=jnp) -> Float[Array, "3 3"]:
    """Right-handed rotation by ``a`` (rad) about the x axis; ``xp``: ``jax.numpy``
    (default) or ``numpy`` (host-side bookkeeping: no JAX operation)."""
    c, s = xp.cos(a), xp.sin(a)
    o, z = xp.ones_like(c), xp.zeros_like(c)
    return xp.stack([xp.stack([o, z, z]), xp.stack([z, c, -s]), xp.stack([z, s, c])])


def rot_y(a: ArrayLike, xp=jnp) -> Float[Array, "3 3"]:
    """Right-handed rotation by ``a`` (rad) about the y axis; ``xp``: ``jax.numpy``
    (default) or ``numpy`` (host-side bookkeeping: no JAX operation)."""
    c, s = xp.cos(a), xp.sin(a)
    o, z = xp.ones_like(c), xp.zeros_like(c)
    return xp.stack([xp.stack([c, z, s]), xp.stack([z, o, z]), xp.stack([-s, z, c])])


def rot_z(a: ArrayLike, xp=jnp) -> Float[Array, "3 3"]:
    """Right-handed rotation by ``a`` (rad) about the z axis; ``xp``: ``jax.numpy``
    (default) or ``numpy`` (host-side bookkeeping: no JAX operation)."""
    c, s = xp.cos(a), xp.sin(a)
    o, z = xp.ones_like(c), xp.zeros_like(c)
    return xp.stack([xp.stack([c, -s, z]), xp.stack([s, c, z]), xp.stack([z, z, o])])


def rot_axis(axis: ArrayLike, angle: ArrayLike) -> Float[Array, "3 3"]:
    """Right-handed rotation by ``angle`` (rad) about the unit vector ``axis`` (Rodrigues)."""
    k = jnp.asarray(axis, dtype=float)
    k = k / jnp.linalg.norm(k)
    kx = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return jnp.eye(3) + jnp.sin(angle) * kx + (1.0 - jnp.cos(angle)) * (kx @ kx)


def rotation_from_vector(w: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    """Rotation matrix of the rotation vector ``w`` (axis times angle, rad); exact, safe at 0."""
    theta2 = jnp.sum(w * w)
    small = theta2 < 1e-16
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / (theta * theta))
    kx = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    return jnp.eye(3) + a * kx + b * (kx @ kx)


def scanner_to_telescope(rx: ArrayLike, ry: ArrayLike, xp=jnp) -> Float[Array, "3 3"]:
    """Seed eq. (6) rotation ``Ry(ry) . Rx(rx)`` from the scanner to the (fitted) telescope
    frame; ``xp`` as in :func:`rot_x`."""
    return rot_y(ry, xp) @ rot_x(rx, xp)


def decompose_zyx(R: Float[Array, "3 3"], xp=jnp) -> tuple[Array, Array, Array]:
    """Angles ``(kappa, ry, rx)`` with ``R = Rz(kappa) . Ry(ry) . Rx(rx)``; ``xp`` as in
    :func:`rot_x`.

    The branch is chosen with ``cos(ry) < 0`` (scanner upside down, ``ry`` near pi), the
    attitude of a scanner hanging towards the reflector, so that the initial values and
    the simulator's truth agree with what the fit converges to.
    """
    # Third row of Rz Ry Rx is (-sin ry, cos ry sin rx, cos ry cos rx): independent of kappa.
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    rx = xp.arctan2(-r21, -r22)
    ry = xp.arctan2(-r20, -xp.sqrt(r21**2 + r22**2))
    M = rot_y(ry, xp) @ rot_x(rx, xp)
    # R = Rz(kappa) M  ->  Rz(kappa) = R M^T
    Rz = R @ M.T
    kappa = xp.arctan2(Rz[1, 0], Rz[0, 0])
    return kappa, ry, rx


# --------------------------------------------------------------------------------------------
# Pointing
# --------------------------------------------------------------------------------------------

_E = np.array([1.0, 0.0, 0.0])
_N = np.array([0.0, 1.0, 0.0])
_U = np.array([0.0, 0.0, 1.0])
_BASE = np.stack([_N, -_E, _U], axis=1)  # columns X_t, Y_t, Z_t at the zenith, in ENU


def telescope_axes_hadec(ha_rad: ArrayLike, dec_rad: ArrayLike, lat_rad: ArrayLike) -> Array:
    """Telescope axes of an HA-DEC mount as the columns of ``F`` (ENU components).

    ``F(h, d) = R(P, -h) . R(E, lat - d) . [N, -E, U]`` with ``P = (0, cos lat, sin lat)``.
    """
    P = jnp.array([0.0, jnp.cos(lat_rad), jnp.sin(lat_rad)])
    return rot_axis(P, -ha_rad) @ rot_axis(_E, lat_rad - dec_rad) @ _BASE


def telescope_axes_altaz(elevation_rad: ArrayLike, azimuth_rad: ArrayLike) -> Array:
    """Telescope axes of an alt-az mount (azimuth from north towards east), columns in ENU.

    ``F = R(U, -az) . R(E, el - pi/2) . [N, -E, U]``: at the zenith this equals the HA-DEC
    definition; at elevation 0 and azimuth 0 the boresight points to the northern horizon.
    """
    return rot_axis(_U, -azimuth_rad) @ rot_axis(_E, elevation_rad - jnp.pi / 2) @ _BASE


def gravity_in_telescope(F: Float[Array, "3 3"]) -> Float[Array, " 3"]:
    """Unit gravity vector in the telescope frame, ``g = F^T (0, 0, -1)``."""
    return F.T @ jnp.array([0.0, 0.0, -1.0])


def elevation_of(F: Float[Array, "3 3"]) -> Array:
    """Elevation of the boresight (rad): ``asin(F[2, 2])``."""
    return jnp.arcsin(jnp.clip(F[2, 2], -1.0, 1.0))


@lru_cache(maxsize=4096)
def _pointing(mount: str, a: float, b: float, lat: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Axes, gravity vector and elevation (deg) of one pointing, computed once: the eager JAX
    rotations take ~15 ms a call, and every scan asks for its pointing several times
    (preprocessing, initial values, fit, alignment) with the same values. The arrays are
    read-only; the public functions return copies."""
    F, g, el = (np.asarray(v) for v in _pointing_program(  # (the angles traced: one program)
        mount, np.float64(a), np.float64(b), np.float64(lat)))
    el = float(np.degrees(el))
    F.setflags(write=False)
    g.setflags(write=False)
    return F, g, el


@cached_jit
def _pointing_program(mount: str, a, b, lat):
    """Axes, gravity vector and elevation (rad) of a pointing as one compiled program: each
    eager operation was a program of its own to lower and load in every process (25, 0.1 s)."""
    F = telescope_axes_altaz(a, b) if mount == "alt-az" else telescope_axes_hadec(a, b, lat)
    return F, gravity_in_telescope(F), elevation_of(F)


def _pointing_key(meta, telescope, site) -> tuple[str, float, float, float]:
    if telescope.mount == "alt-az":
        return ("alt-az", float(np.radians(meta.elevation_deg)),
                float(np.radians(meta.azimuth_deg or 0.0)), 0.0)
    return ("ha-dec", float(np.radians(meta.ha_deg)), float(np.radians(meta.dec_deg)),
            float(np.radians(site.latitude_deg)))


def pointing_axes(meta, telescope, site) -> np.ndarray:
    """Telescope axes ``F`` (3x3 NumPy, columns in ENU) of a scan from its campaign metadata."""
    return _pointing(*_pointing_key(meta, telescope, site))[0].copy()


def pointing_gravity(meta, telescope, site) -> np.ndarray:
    """Unit gravity vector (telescope frame) of a scan, from HA/DEC or elevation/azimuth."""
    return _pointing(*_pointing_key(meta, telescope, site))[1].copy()


def pointing_elevation_deg(meta, telescope, site) -> float:
    """Elevation of the boresight (deg) of a scan."""
    return _pointing(*_pointing_key(meta, telescope, site))[2]


# --------------------------------------------------------------------------------------------
# Scanner polar coordinates
# --------------------------------------------------------------------------------------------


#: NumPy arrays of at least this many angles take their sines and cosines from
#: :func:`._trig.host_sincos` (a compiled program), smaller ones from NumPy.
HOST_TRIG_MIN = 4096


def polar_components(r: ArrayLike, phi: ArrayLike, theta: ArrayLike, xp=jnp):
    """Seed eq. (2) as three arrays ``x, y, z`` = ``r sin(theta) sin(phi)``, ``r sin(theta)
    cos(phi)``, ``r cos(theta)``; ``xp`` is ``jax.numpy`` (default) or ``numpy``
    (preprocessing of whole scans), one formula for both. NumPy arrays of
    :data:`HOST_TRIG_MIN` angles or more: the trigonometry by :func:`._trig.host_sincos`
    (within 2 ulp of NumPy's, 4x faster)."""
    if xp is np and np.size(theta) >= HOST_TRIG_MIN and np.size(phi) >= HOST_TRIG_MIN:
        (st, ct), (sp, cp) = host_sincos(theta), host_sincos(phi)
        return r * st * sp, r * st * cp, r * ct
    st = xp.sin(theta)
    return r * st * xp.sin(phi), r * st * xp.cos(phi), r * xp.cos(theta)


def polar_to_cartesian(r: ArrayLike, phi: ArrayLike, theta: ArrayLike, xp=jnp) -> Array:
    """Seed eq. (2): ``(r sin(theta) sin(phi), r sin(theta) cos(phi), r cos(theta))``, last
    axis 3; ``xp`` as in :func:`polar_components`."""
    return xp.stack(polar_components(r, phi, theta, xp), axis=-1)


def face_of(theta: ArrayLike) -> np.ndarray:
    """Face (1 or 2) of raw vertical angles: face 1 in (0, pi), face 2 in (pi, 2 pi)."""
    return np.where(np.mod(np.asarray(theta), 2 * np.pi) < np.pi, 1, 2)


# --------------------------------------------------------------------------------------------
# Dish coordinates, paraboloid, panels
# --------------------------------------------------------------------------------------------


def dish_coordinates(X: Float[Array, "... 3"]) -> tuple[Array, Array]:
    """Dish radius ``rho = hypot(X, Y)`` (m) and azimuth ``psi = atan2(Y, X)`` in [0, 2 pi)."""
    rho = jnp.hypot(X[..., 0], X[..., 1])
    psi = jnp.mod(jnp.arctan2(X[..., 1], X[..., 0]), 2 * jnp.pi)
    return rho, psi


def paraboloid_normal_scale(rho: ArrayLike, f: ArrayLike, xp=jnp) -> Array:
    """``sqrt(1 + (rho / 2f)^2)``: converts a normal deviation into a change of Z at radius rho;
    ``xp``: ``jax.numpy`` (default) or ``numpy``."""
    return xp.sqrt(1.0 + (rho / (2.0 * f)) ** 2)


def paraboloid_deviation(X: Float[Array, "... 3"], f: ArrayLike, newton_steps: int = 3) -> Array:
    """Signed distance (m) of points from the paraboloid ``Z = rho^2 / 4f``, along its normal.

    Positive towards the focus (above the surface), as ``campaign-format.md`` defines the surface
    deviation. Exact to round-off: the foot point is found by Newton's method in the meridian
    plane, starting from the first-order estimate.
    """
    rho = jnp.hypot(X[..., 0], X[..., 1])
    Z = X[..., 2]
    # minimise (rho - s)^2 + (Z - s^2/4f)^2 over s
    s = rho
    for _ in range(newton_steps):
        q = s * s / (4 * f)
        g = (s - rho) + (q - Z) * s / (2 * f)
        h = 1.0 + (s / (2 * f)) ** 2 + (q - Z) / (2 * f)
        s = s - g / h
    d = jnp.sqrt((rho - s) ** 2 + (Z - s * s / (4 * f)) ** 2)
    return jnp.where(Z >= rho * rho / (4 * f), d, -d)


def panel_ids(
    rho: np.ndarray,
    psi: np.ndarray,
    ring_edges_m,
    panels_per_ring,
    *,
    xp=np,
) -> np.ndarray:
    """Panel id of each point, -1 outside the panelled annulus (``xp``: ``numpy`` -> int64, or
    ``jax.numpy`` inside traced code: the simulator's ray casting uses the same rule).

    Rings are numbered from 0 (innermost) outwards; within ring k the panels are numbered from
    ``psi = 0`` counter-clockwise, each spanning ``2 pi / panels_per_ring[k]``.
    """
    edges = xp.asarray(ring_edges_m, dtype=float)
    counts = xp.asarray(panels_per_ring)
    nr = counts.shape[0]
    first = xp.concatenate([xp.zeros(1, counts.dtype), xp.cumsum(counts)[:-1]])
    ring = xp.searchsorted(edges, xp.asarray(rho, dtype=float), side="right") - 1
    inside = (ring >= 0) & (ring < nr)
    rc = xp.clip(ring, 0, nr - 1)
    n = counts[rc]
    k = xp.floor(xp.mod(xp.asarray(psi, dtype=float), 2 * np.pi) / (2 * np.pi) * n)
    k = xp.minimum(k.astype(counts.dtype), n - 1)
    return xp.where(inside, first[rc] + k, -1)


#: Side (m) of the square cells that stand in for panels on a reflector with no panel layout.
DEFAULT_CELL_M = 2.0


def panel_cells(
    X: np.ndarray,
    ring_edges_m=None,
    panels_per_ring=None,
    *,
    cell_m: float = DEFAULT_CELL_M,
    keys: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int, str]:
    """Surface cells of points for the surface random effect, and each point's local coordinates.

    ``X``: (n, 3) points in the north-aligned telescope frame (m). With a ring layout
    (``ring_edges_m``, ``panels_per_ring``) the cells are the panels of :func:`panel_ids` and
    the local coordinates ``(rho - rho_c, rho_c * dpsi)`` are those of the panel tilts of
    :func:`._physics.panel_deviation` (radial, tangential; m). Without one, the aperture plane
    is cut into squares of ``cell_m`` (a stated regular grid, never another telescope's panel
    numbers) with local coordinates ``(x - x_c, y - y_c)``; ``keys`` fixes those squares (see
    :func:`square_cells`).

    Returns ``(cell (n,) int64 compact ids, -1 outside any cell; local (n, 2) m; n_cells;
    description)``.
    """
    X = np.asarray(X, float)
    if ring_edges_m is not None and panels_per_ring is not None:
        edges, counts = tuple(map(float, ring_edges_m)), tuple(map(int, panels_per_ring))
        if len(X) > BLOCK_ROWS:
            # compiled, a block of rows at a time on each core (one program: every block of
            # BLOCK_ROWS rows): 1.26e7 points 0.26-0.34 s in a process of its own, 0.39-0.58 s
            # in the command (fresh pages for its 350 MB of outputs), NumPy's 0.52 s there
            ids, local = by_row_blocks(lambda X_: _ring_cells_compiled(X_, edges, counts), (X,),
                                       block=BLOCK_ROWS)
        else:
            ids, local = ring_cells(X, edges, counts)
        return (ids.astype(np.int64, copy=False), local) + panel_layout(counts)
    cell, local, keys = square_cells(X, cell_m, keys)
    return cell, local, int(len(keys)), f"square cells of {cell_m:g} m (no panel layout)"


def panel_layout(panels_per_ring) -> tuple[int, str]:
    """``(number of panels, description)`` of a ring layout, as :func:`panel_cells` gives
    them."""
    n = int(sum(panels_per_ring))
    return n, f"panels ({n} in {len(panels_per_ring)} rings)"


def ring_cells(X, ring_edges_m, panels_per_ring, xp=np):
    """Panel ids and local ``(radial, tangential)`` coordinates (m) of points ``X`` (n, 3)
    (``xp``: NumPy, or ``jax.numpy`` inside a compiled program)."""
    geo = panel_geometry(ring_edges_m, panels_per_ring)
    rho = xp.hypot(X[:, 0], X[:, 1])
    psi = xp.mod(xp.arctan2(X[:, 1], X[:, 0]), 2 * np.pi)
    ids = panel_ids(rho, psi, ring_edges_m, panels_per_ring, xp=xp)
    inside = ids >= 0
    k = xp.where(inside, ids, 0)
    rho_c, psi_c = xp.asarray(geo["rho_c"])[k], xp.asarray(geo["psi_c"])[k]
    dpsi = xp.mod(psi - psi_c + np.pi, 2 * np.pi) - np.pi
    local = xp.stack([rho - rho_c, rho_c * dpsi], 1)
    return ids, xp.where(inside[:, None], local, 0.0)


@cached_jit
def _ring_cells_compiled(X, ring_edges_m: tuple, panels_per_ring: tuple):
    """:func:`ring_cells` of a block of points, compiled (int32 ids)."""
    ids, local = ring_cells(X, ring_edges_m, panels_per_ring, xp=jnp)
    return ids.astype(jnp.int32), local


def column_bounds(a: Float[np.ndarray, "n k"]) -> tuple[Float[np.ndarray, " k"],
                                                      Float[np.ndarray, " k"]]:
    """``(a.min(0), a.max(0))``, the least and the greatest value of each column of ``a``,
    taken column by column: NumPy reduces a tall array of few columns along its rows one row
    at a time (5.2e5 rows of two: 13 ms for ``a.min(0)``, 0.35 ms per column)."""
    cols = [a[:, k] for k in range(a.shape[1])]
    return np.array([c.min() for c in cols]), np.array([c.max() for c in cols])


def grid_indices(xy: Float[np.ndarray, "n k"], lo: Float[np.ndarray, " k"],
                 h: float) -> Int[np.ndarray, "n k"]:
    """The cells ``floor((xy - lo) / h)`` (int64) of a grid of spacing ``h`` from ``lo``,
    column by column (as :func:`column_bounds`: 5.2e5 points of two coordinates 17 -> 3 ms);
    the same values."""
    ij = np.empty(np.shape(xy), np.int64)
    for k in range(ij.shape[1]):
        ij[:, k] = np.floor((xy[:, k] - lo[k]) / h)
    return ij


def cell_code(ij: Int[np.ndarray, "n 2"]) -> Int[np.ndarray, " n"]:
    """One int64 per grid index pair (each index within +-2^30), ordered as the pairs are
    lexicographically: sorting or counting the codes is that of the pairs, without
    ``np.unique(axis=0)``'s row views (10x the time)."""
    ij = np.asarray(ij, np.int64)
    return (ij[:, 0] + (1 << 30)) * (1 << 31) + (ij[:, 1] + (1 << 30))


def _cell_pairs(code: np.ndarray) -> np.ndarray:
    """The grid index pairs (g, 2) of :func:`cell_code` values."""
    return np.column_stack([code // (1 << 31) - (1 << 30), code % (1 << 31) - (1 << 30)])


def grid_sum(ij: Int[np.ndarray, "n 2"], shape: tuple[int, int],
             weights: np.ndarray | None = None) -> np.ndarray:
    """Per cell of a grid of ``shape``, the sum of ``weights`` (default 1) of the points in it
    (``ij`` their cells, inside the grid): ``np.add.at`` by ``bincount``, the same sums in the
    same order."""
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    return np.bincount(flat, weights, minlength=shape[0] * shape[1]).astype(float).reshape(
        shape)


def square_cells(
    X: np.ndarray, cell_m: float = DEFAULT_CELL_M, keys: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Square cells of ``cell_m`` (m) in the aperture plane: ``(cell (n,), local (n, 2) m,
    keys (g, 2))``. ``keys``: the grid indices of the cells (sorted, as returned before): points
    of other squares get cell -1 (so chunks of one recording share one numbering); default: the
    squares that ``X`` occupies."""
    X = np.asarray(X, float)
    ij = grid_indices(X[:, :2], np.zeros(2), cell_m)  # (x - 0 is x: the same cells)
    if keys is None:
        codes, cell = np.unique(cell_code(ij), return_inverse=True)
        keys, cell = _cell_pairs(codes), cell.reshape(-1).astype(np.int64)
    else:
        keys = np.asarray(keys, np.int64).reshape(-1, 2)
        codes, want = cell_code(keys), cell_code(ij)
        cell = np.full(len(ij), -1, np.int64)
        if len(codes):
            pos = np.clip(np.searchsorted(codes, want), 0, len(codes) - 1)
            cell = np.where(codes[pos] == want, pos, -1).astype(np.int64)
    centre = (keys + 0.5) * cell_m
    local = np.where((cell >= 0)[:, None], X[:, :2] - centre[np.maximum(cell, 0)], 0.0)
    return cell, local, keys


def panel_geometry(ring_edges_m, panels_per_ring) -> dict[str, np.ndarray]:
    """Per-panel ring, inner/outer radius (m), azimuth start/end and centre (rad)."""
    edges = np.asarray(ring_edges_m, dtype=float)
    out = {k: [] for k in ("ring", "rho_in", "rho_out", "psi_start", "psi_end", "rho_c", "psi_c")}
    for ring, n in enumerate(panels_per_ring):
        w = 2 * np.pi / n
        for k in range(n):
            out["ring"].append(ring)
            out["rho_in"].append(edges[ring])
            out["rho_out"].append(edges[ring + 1])
            out["psi_start"].append(k * w)
            out["psi_end"].append((k + 1) * w)
            out["rho_c"].append(0.5 * (edges[ring] + edges[ring + 1]))
            out["psi_c"].append((k + 0.5) * w)
    return {k: np.asarray(v) for k, v in out.items()}


# --------------------------------------------------------------------------------------------
# Zernike polynomials over the aperture (Noll ordering, unit-rms normalisation)
# --------------------------------------------------------------------------------------------


def noll_to_nm(j: int) -> tuple[int, int]:
    """Radial order ``n`` and signed azimuthal frequency ``m`` of Noll index ``j`` (1-based).

    ``m > 0`` is a cosine term (even ``j``), ``m < 0`` a sine term (odd ``j``).
    """
    if j < 1:
        raise ValueError(f"Noll index must be >= 1, got {j}")
    n, j1 = 0, j - 1
    while j1 > n:
        n += 1
        j1 -= n
    m = (-1) ** j * ((n % 2) + 2 * ((j1 + ((n + 1) % 2)) // 2))
    return n, m


def zernike(j: int, u: ArrayLike, psi: ArrayLike, xp=jnp) -> Array:
    """Noll-indexed Zernike polynomial ``Z_j`` at normalised radius ``u`` in [0, 1] and azimuth psi.

    Normalised to unit rms over the unit disk (``Z_1 = 1``). ``xp`` is the array namespace:
    ``jax.numpy`` (default) or ``numpy`` (the gravity model's grids), one formula for both.
    """
    n, m = noll_to_nm(j)
    ma = abs(m)
    u = xp.asarray(u, dtype=float)
    R = xp.zeros_like(u)
    for s in range((n - ma) // 2 + 1):
        c = (-1) ** s * factorial(n - s) / (
            factorial(s) * factorial((n + ma) // 2 - s) * factorial((n - ma) // 2 - s))
        R = R + c * u ** (n - 2 * s)
    if m == 0:
        return np.sqrt(n + 1.0) * R
    ang = xp.cos(ma * psi) if m > 0 else xp.sin(ma * psi)
    return np.sqrt(2.0 * (n + 1.0)) * R * ang


def zernike_columns(X: Float[ArrayLike, "n d"], modes, aperture_radius_m: float,
                    dtype=np.float64) -> Float[np.ndarray, "n r"]:
    """The Zernike terms ``Z_j`` (Noll ``j`` of ``modes``, unit coefficient) at the aperture
    coordinates of points ``X`` (m; columns x, y of the telescope frame, any further ones
    ignored): ``u = rho / aperture_radius_m``, azimuth from the x axis. NumPy, one column per
    mode: the design of a Zernike fit or of the smooth modes of a random effect.

    Evaluated by one compiled program per mode set (:func:`zernike`'s formula in ``jax.numpy``:
    integer powers as products, one fusion; 0.09 s per 1e6 points and 7 modes against 0.21 s
    in NumPy). ``dtype``: of the columns (evaluated in float64 either way; float32 halves a
    large design's memory, 6e-8 of rounding on values within +-sqrt(2 (n + 1)))."""
    X = np.asarray(X)
    modes = tuple(int(j) for j in modes)
    if not len(X) or not modes:
        return np.zeros((len(X), len(modes)), dtype)
    # x, y as float64 in one copy the device shares (not a float64 copy of every column,
    # then another of two of them: 200 MB of the 1.26e7 float32 hit points of a large position)
    return np.asarray(_zernike_columns(lend_to_device(X[:, :2], np.float64), modes,
                                       jnp.asarray(aperture_radius_m, float), np.dtype(dtype)))


@cached_jit
def _zernike_columns(xy, modes: tuple[int, ...], aperture_radius_m, dtype):
    u = jnp.hypot(xy[:, 0], xy[:, 1]) / aperture_radius_m
    psi = jnp.arctan2(xy[:, 1], xy[:, 0])
    return jnp.stack([zernike(j, u, psi).astype(dtype) for j in modes], axis=1)
