"""RANSAC planes of padded patches (JAX, vmapped): minimal samples, MSAC scoring, total
least-squares refinement; distances in m. :class:`PlaneCondition` is the rigorous
Gauss-Helmert plane the refinement is checked against."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._programs import cached_jit
from ..geometry._geometry import (
    polar_to_cartesian,
)
from ._patches import _next_pow2


def _three_distinct(u: Float[Array, "h 3"], n: Array) -> Array:
    """Three distinct indices in [0, n) per row of uniforms ``u`` (n >= 3)."""
    n = n.astype(jnp.int32)
    nf = n.astype(u.dtype)
    i1 = jnp.minimum((u[:, 0] * nf).astype(jnp.int32), n - 1)
    i2 = (i1 + 1 + jnp.minimum((u[:, 1] * (nf - 1)).astype(jnp.int32), n - 2)) % n
    a, b = jnp.minimum(i1, i2), jnp.maximum(i1, i2)
    k = jnp.minimum((u[:, 2] * (nf - 2)).astype(jnp.int32), n - 3)
    k = k + (k >= a).astype(jnp.int32)
    k = k + (k >= b).astype(jnp.int32)
    return jnp.stack([i1, i2, k], axis=1)


def _adjugate_sym(M: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """Adjugate of a symmetric 3x3 matrix (``det(M) M^-1``, defined for singular ``M`` too)."""
    a, b, c = M[0, 0], M[0, 1], M[0, 2]
    d, e, f = M[1, 1], M[1, 2], M[2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    D = a * f - c * c
    E = b * c - a * e
    F = a * d - b * b
    return jnp.stack([jnp.stack([A, B, C]), jnp.stack([B, D, E]), jnp.stack([C, E, F])])


def _tls_plane(p: Float[Array, "p 3"], w: Float[Array, " p"], n0: Float[Array, " 3"]):
    """Total-least-squares plane of the points with 0/1 weights ``w``: ``(n, d)``, ``n.p = d``.

    The normal is the eigenvector of the smallest eigenvalue of the scatter matrix ``M``, found
    by inverse iteration from ``n0`` (the current normal) with the adjugate of ``M`` (no
    division, exact for perfectly planar points): each step shrinks the error by
    ``lambda_min / lambda_mid`` ~ (sigma / patch size)^2 ~ 1e-5, so two steps are exact to
    round-off (a batched ``eigh`` gives the same and compiles much slower).
    """
    sw = jnp.maximum(jnp.sum(w), 1)
    pw = p * w[:, None]
    c = jnp.sum(pw, axis=0) / sw
    # raw moments (one pass over the points); p is centred near the patch's centroid, so
    # subtracting sw c c^T loses nothing that matters even in float32
    M = pw.T @ p - sw * (c[:, None] * c[None, :])
    adj = _adjugate_sym(M)
    u = adj @ (adj @ n0)
    nu = jnp.sqrt(jnp.sum(u * u))
    v = jnp.where(nu > 0, u / jnp.where(nu > 0, nu, 1.0), n0)
    v = jnp.where(v @ n0 < 0, -v, v)
    return v, v @ c


def _patch_fit(pts, n, eps, u, *, n_refine: int, f32: bool, n_score: int):
    """RANSAC (MSAC score) + TLS refinement of one padded patch.

    The hypotheses are scored, and the RANSAC plane refined (``n_refine`` TLS fits of its
    inliers), on ``n_score`` points spread over the patch; a single pass over all the patch's
    points then classifies them (``|distance| <= eps``) and fits the reported plane to the
    inliers (TLS). The refined plane is within ~0.1 mm of the all-points one at the patch edge
    (a few hundred points of 0.8-mm noise over 0.3 m), so only points within that of ``eps``
    could be classified differently; the one full pass keeps the kernel memory-light.

    Args:
        pts: (P, 3) local coordinates (first ``n`` rows valid; any origin within ~metres).
        n: number of valid points (>= 3).
        eps: inlier threshold (m).
        u: (H, 3) uniforms in [0, 1): the minimal samples of the H hypotheses.
        n_score: number of scoring points (all points if the patch is smaller).
        f32: compute in float32 (coordinates relative to the scoring points' centroid, < 1 m:
            a distance is rounded by ~0.1 um, far below the noise), else float64.
    Returns ``(inlier (P,) bool, normal (3,), d, centroid (3,), n_inliers, rms,
    ransac_inliers)``: the TLS plane of the inliers ``normal . (p - centroid) = d``, ``rms``
    the inliers' distances from the classifying plane, ``ransac_inliers`` the RANSAC plane's
    inliers among the scoring points.
    """
    P = pts.shape[0]
    n = n.astype(jnp.int32)
    valid = jnp.arange(P, dtype=jnp.int32) < n
    ct = jnp.float32 if f32 else jnp.float64
    q = pts.astype(ct)
    S = min(P, n_score)
    k = jnp.arange(S, dtype=jnp.int32)
    sub = jnp.where(n > S, (k * n) // S, k)  # spread over the patch when it is larger
    scored = sub < n
    ws = scored.astype(ct)
    qs = q[sub]
    cen = jnp.sum(qs * ws[:, None], axis=0) / jnp.sum(ws)
    qs = qs - cen[None, :]
    e = jnp.asarray(eps, ct)
    idx = _three_distinct(u, n)
    tri = q[idx] - cen[None, None, :]  # (H, 3, 3)
    nrm = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = jnp.sqrt(jnp.sum(nrm * nrm, axis=1))
    scale = jnp.max(jnp.abs(qs) * ws[:, None]) + jnp.asarray(1e-12, ct)
    ok = ln > jnp.asarray(1e-6, ct) * scale * scale
    nh = nrm / jnp.where(ok, ln, 1)[:, None]
    d = jnp.sum(nh * tri[:, 0], axis=1)
    dist = qs @ nh.T - d[None, :]  # (S, H): the one large intermediate
    cost = jnp.sum(jnp.where(scored[:, None], jnp.minimum(dist * dist, e * e), 0), axis=0)
    cost = jnp.where(ok, cost, jnp.inf)
    best = jnp.argmin(cost)
    n_ransac = jnp.sum(scored & (jnp.abs(dist[:, best]) <= e), dtype=jnp.int32)

    def refine(_, nd):  # a loop, not unrolled: one copy of the body to compile
        normal, d0 = nd
        w = (scored & (jnp.abs(qs @ normal - d0) <= e)).astype(ct)
        n_new, d_new = _tls_plane(qs, w, normal)
        enough = jnp.sum(w) >= 3
        return jnp.where(enough, n_new, normal), jnp.where(enough, d_new, d0)

    normal, d0 = nh[best], d[best]
    if n_refine:
        normal, d0 = jax.lax.fori_loop(0, n_refine, refine, (normal, d0))
    # the one pass over all points: classify, then the TLS plane of the inliers
    y = q - cen[None, :]
    r = y @ normal - d0
    inl = valid & (jnp.abs(r) <= e)
    n_in = jnp.sum(inl, dtype=jnp.int32)
    rms = jnp.sqrt(jnp.sum(jnp.where(inl, r * r, 0)) / jnp.maximum(n_in - 3, 1).astype(ct))
    n_f, d_f = _tls_plane(y, inl.astype(ct), normal)
    enough = n_in >= 3
    normal, d0 = jnp.where(enough, n_f, normal), jnp.where(enough, d_f, d0)
    f64 = jnp.float64
    return inl, normal.astype(f64), d0.astype(f64), cen.astype(f64), n_in, rms.astype(f64), n_ransac


@cached_jit
def _fit_patches(pts, n, eps, u, *, n_refine: int, f32: bool, n_score: int, batch_size: int):
    """Padded patches: ``lax.map`` over chunks of ``batch_size`` vmapped :func:`_patch_fit`."""
    return jax.lax.map(
        lambda a: _patch_fit(*a, n_refine=n_refine, f32=f32, n_score=n_score),
        (pts, n, eps, u), batch_size=batch_size)


def ransac_uniforms(seed: int, ids: np.ndarray, n_hyp: int) -> np.ndarray:
    """(len(ids), n_hyp, 3) float32 uniforms of the patches ``ids`` (row ``i`` of one stream).

    Drawn with NumPy (``default_rng(seed)``) rather than ``jax.random`` inside the compiled
    kernel: threefry under ``vmap`` took longer to compile (1.3 s) than the kernel itself.
    A patch's samples depend only on the seed and its id, not on the chunking.
    """
    ids = np.asarray(ids, np.int64)
    if len(ids) == 0:
        return np.zeros((0, n_hyp, 3), np.float32)
    U = np.random.default_rng(seed).random((int(ids.max()) + 1, n_hyp, 3), dtype=np.float32)
    return U[ids]


def fit_planes(
    pts: np.ndarray, n: np.ndarray, eps: np.ndarray | float, *, seed: int = 0,
    ransac_iterations: int = 64, refine_iterations: int = 2, ransac_float32: bool = True,
    score_points: int = 256, batch_size: int | None = None, memory_mb: float = 8.0,
    ids: np.ndarray | None = None, max_chunk: int = 1024,
) -> dict[str, np.ndarray]:
    """RANSAC + TLS planes of padded patches (the JAX core, usable on its own).

    Args:
        pts: (n_patches, P, 3) coordinates; the first ``n[i]`` rows of patch ``i`` are valid.
            Any origin within a few metres of the patch (float32 keeps ~0.1 um there).
        n: (n_patches,) valid points per patch (patches with ``n < 3`` give no plane).
        eps: inlier threshold (m), scalar or per patch.
        ids: integer id per patch for its random samples (default ``arange``): the result of a
            patch does not depend on the chunking or on the other patches.
        score_points: points (spread over the patch) that score the hypotheses.
        batch_size: patches per vmapped step of ``lax.map``; None: as many as fit in
            ``memory_mb`` (the patches' working copies and scoring matrices).
        max_chunk: patches per compiled call; calls use power-of-two patch counts up to this,
            so the same few shapes (and compilations) serve every scan.
    Returns a dict of NumPy arrays: ``inlier`` (n_patches, P) bool, ``normal`` (n_patches, 3),
    ``d`` and ``centroid`` (plane ``normal . (p - centroid) = d``, in the coordinates of
    ``pts``), ``n_inliers``, ``rms`` (m), ``ransac_inliers``.
    """
    pts = np.asarray(pts)
    n_p, P = pts.shape[0], pts.shape[1]
    H = int(ransac_iterations)
    S = int(min(P, score_points))
    n = np.asarray(n, np.int64)
    eps = np.broadcast_to(np.asarray(eps, np.float64), (n_p,))
    ids = np.arange(n_p) if ids is None else np.asarray(ids, np.int64)
    if batch_size is None:
        per_patch = P * 3 * 8 * 4 + S * H * (4 if ransac_float32 else 8) * 3
        batch_size = int(max(1, min(1024, memory_mb * 2**20 // per_patch)))
    batch_size = 1 << (int(batch_size).bit_length() - 1)  # power of two: stable shapes
    good = n >= 3
    n_run = np.where(good, np.minimum(n, P), 3).astype(np.int32)  # dummies: 3-point fits
    U = ransac_uniforms(seed, ids, H)
    dt_pts = np.float32 if ransac_float32 else np.float64
    fit = int(max(1, 64 * 2**20 // (P * 3 * 8)))  # patches per call: inputs below 64 MB
    per_call = max(batch_size, _next_pow2(fit + 1) // 2)
    n_call = int(min(max_chunk, per_call, _next_pow2(max(n_p, 1))))
    bs = int(min(batch_size, n_call))
    outs = []
    for s in range(0, n_p, n_call):
        e = min(s + n_call, n_p)
        k = n_call - (e - s)

        def sl(a, fill, s=s, e=e, k=k):
            return a[s:e] if not k else np.concatenate(
                [a[s:e], np.full((k,) + a.shape[1:], fill, a.dtype)])

        out = _fit_patches(
            jnp.asarray(sl(pts, 0), dt_pts), jnp.asarray(sl(n_run, 3)),
            jnp.asarray(sl(eps, 1.0), jnp.float64), jnp.asarray(sl(U, 0.5)),
            n_refine=int(refine_iterations), f32=bool(ransac_float32), n_score=S, batch_size=bs,
        )
        outs.append([np.asarray(a)[: e - s] for a in out])
    if not outs:
        z = np.zeros(0)
        return {"inlier": np.zeros((0, P), bool), "normal": np.zeros((0, 3)), "d": z,
                "centroid": np.zeros((0, 3)), "n_inliers": z.astype(np.int32), "rms": z,
                "ransac_inliers": z.astype(np.int32)}
    inl, normal, d, cen, n_in, rms, n_r = (np.concatenate(c) for c in zip(*outs))
    normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)  # exactly unit in float64
    inl = inl & good[:, None]
    return {"inlier": inl, "normal": np.where(good[:, None], normal, np.nan),
            "d": np.where(good, d, np.nan), "centroid": cen,
            "n_inliers": np.where(good, n_in, 0), "rms": np.where(good, rms, np.nan),
            "ransac_inliers": np.where(good, n_r, 0)}


class PlaneCondition(eqx.Module):
    """Gauss-Helmert condition of a plane in raw observations (for :func:`._ghm.gauss_helmert`).

    ``F(l, x) = n(x) . p(l) - x[2]`` with ``p`` the scanner Cartesian point of ``l = (r, phi,
    theta)`` (eq. 2) and ``n(x) = R0 (x0, x1, 1) / |(x0, x1, 1)|``: ``R0`` rotates z onto a
    starting normal so the parameterisation is regular near the solution. Unknowns
    ``x = (x0, x1, d)`` (-, -, m). Used to check the vmapped refinement against the rigorous
    adjustment; too slow per patch for thousands of patches (module doc).
    """

    R0: Float[Array, "3 3"]

    @staticmethod
    def around(normal) -> PlaneCondition:
        """Condition whose ``x = (0, 0, d)`` is the plane with this normal."""
        z = np.asarray(normal, float) / np.linalg.norm(normal)
        a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(a, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return PlaneCondition(jnp.asarray(np.stack([x, y, z], axis=1)))

    def normal(self, x):
        v = jnp.stack([x[0], x[1], jnp.ones_like(x[0])])
        return self.R0 @ (v / jnp.sqrt(jnp.sum(v * v)))

    def __call__(self, obs, x, c):
        return self.normal(x) @ polar_to_cartesian(obs[0], obs[1], obs[2]) - x[2]


