"""Streaming Gauss-Helmert adjustment of a full-resolution scan with bounded memory.

A scan at the paper's resolution has about 1.3e7 points; the 88-position campaign (176 scans)
about 2.3e9 -- more than this machine's memory. Here one scan is adjusted without ever holding
it: every iteration streams the scan's chunks from disk (:func:`._campaign.iter_scan_chunks`),
accumulates the normal equations chunk by chunk, and keeps the per-point state (residuals ``v``,
weights, standardized residuals) in memory-mapped ``.npy`` files indexed by the file row.

One read of the file per iteration: the residual pass of iteration ``k`` (which needs ``dx_k``,
known only after all chunks were accumulated) is fused with the normal-equation pass of
iteration ``k + 1`` -- per chunk, the residuals are updated at the old linearisation point and
the normals accumulated at the new one. The arithmetic is that of
:func:`._ghm.gauss_helmert` (same linearisation points, same convergence test, the same final
statistics pass) and of :func:`._ghm.robust_gauss_helmert` (rejection beyond ``k`` a-posteriori
sigmas, rounds until nothing new is rejected), so the result equals the in-memory adjustment to
round-off.

Initial values come from a seeded random sample of the scan (``n_sample`` rows, drawn while
streaming); the geometry window (distance from the initial paraboloid) is applied per chunk.
The RANSAC preprocessing is not applied here (its patches cross chunk boundaries).
"""

from __future__ import annotations

import logging
import math
import tempfile
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._campaign import Campaign, ScanMeta, iter_scan_chunks
from ._fit import _x0, scan_arrays, sigma_vector
from ._geometry import pointing_gravity
from ._ghm import _chunked, _inverse, _pass_normals, _pass_residuals, _solve_normal, _unchunk
from ._init import InitialValues, initial_distance, initial_values
from ._model import make_model

log = logging.getLogger("hartrao_jax")

INNER_CHUNK = 1 << 16  # points per lax.scan step inside one streamed chunk


@eqx.filter_jit
def _fused_pass(model, l, c, w, s2, v, x_old, dx, x_new, do_update, inner):
    """Per streamed chunk: residual update at ``(l + v, x_old)`` with ``dx`` (if ``do_update``),
    then the normal equations at ``(l + v_new, x_new)``. Shapes are fixed (padded chunk)."""
    (L, C, W, S2, V), n = _chunked([l, c, w, s2, v], inner)
    Vn, E, omega = _pass_residuals(model, L, V, C, W, S2, x_old, dx)
    Vn = jnp.where(do_update, Vn, V)
    N, nv = _pass_normals(model, L, Vn, C, W, S2, x_new)
    return _unchunk(Vn, n), _unchunk(E, n), omega, N, nv


@dataclass
class StreamFit:
    """Result of :func:`stream_fit_scan` (SI units). Per-point state under ``store``:
    ``v.npy`` (rows, 3) residuals, ``w.npy`` weights, ``e.npy`` standardized residuals
    (|k| sqrt(m) / sigma0), indexed by the file row."""

    id: str
    names: tuple[str, ...]
    x: np.ndarray
    cov: np.ndarray
    N: np.ndarray
    sigma0: float
    n_rows: int
    n_window: int
    n_points: int
    n_rejected: int
    iterations: int
    rounds: int
    passes: int
    converged: bool
    seconds: float
    store: Path
    init: InitialValues
    timings: dict = field(default_factory=dict)

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def estimates(self) -> dict[str, tuple[float, float]]:
        return {n: (float(self.x[i]), float(self.sigma[i])) for i, n in enumerate(self.names)}


def _count_rows(campaign: Campaign, meta: ScanMeta) -> int:
    path = campaign.root / meta.file
    if path.suffix.lower() == ".parquet":
        import pyarrow.parquet as pq

        return int(pq.ParquetFile(path).metadata.num_rows)
    n = 0
    for ch in iter_scan_chunks(campaign, meta, 1_000_000):
        n = max(n, int(ch.row[-1]) + 1 if len(ch) else n)
    return n


def _sample(campaign, meta, rows_per_chunk: int, n_rows: int, n_sample: int, seed: int):
    rng = np.random.default_rng(seed)
    frac = min(1.0, 1.5 * n_sample / max(n_rows, 1))
    parts = []
    for ch in iter_scan_chunks(campaign, meta, rows_per_chunk):
        pick = rng.random(len(ch)) < frac
        parts.append((ch.range_m[pick], ch.phi_rad[pick], ch.theta_rad[pick]))
    r, phi, th = (np.concatenate([p[i] for p in parts]) for i in range(3))
    return r, phi, th


def stream_fit_scan(
    campaign: Campaign,
    scan: str | ScanMeta,
    model: str | Iterable[str] = "extended",
    *,
    rows_per_chunk: int = 1_000_000,
    store=None,
    fixed: dict[str, float] | None = None,
    init: InitialValues | None = None,
    window_m: float = 0.10,
    robust_k: float | None = 4.0,
    max_rounds: int = 6,
    max_iter: int = 30,
    tol: float = 1e-6,
    n_sample: int = 200_000,
    seed: int = 0,
) -> StreamFit:
    """Adjust one scan streaming it from disk in chunks of ``rows_per_chunk`` file rows.

    ``store``: directory for the memory-mapped per-point state (default: a new temporary
    directory). ``init``: initial values (default: from a random sample of the scan, as
    :func:`._fit.prepare_scan` does from the whole scan). Other arguments as
    :func:`._fit.fit_scan` / :func:`._ghm.robust_gauss_helmert`.
    """
    t_start = time.perf_counter()
    meta = campaign.scan(scan) if isinstance(scan, str) else scan
    fixed = dict(fixed or {})
    mdl = make_model(model, fixed, aperture_radius_m=campaign.telescope.diameter_m / 2)
    names = mdl.free
    u = len(names)
    sig = sigma_vector(campaign)
    s2 = jnp.asarray(sig**2)
    store = Path(store) if store is not None else Path(tempfile.mkdtemp(prefix="hartrao-stream-"))
    store.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    n_rows = _count_rows(campaign, meta)
    g = pointing_gravity(meta, campaign.telescope, campaign.site)
    if init is None:
        r, phi, th = _sample(campaign, meta, rows_per_chunk, n_rows, n_sample, seed)
        init = initial_values(r, phi, th, g, focal_length_m=campaign.telescope.focal_length_m,
                              seed=seed)
    timings["initial_values_s"] = time.perf_counter() - t0

    V = np.lib.format.open_memmap(store / "v.npy", mode="w+", dtype=np.float64, shape=(n_rows, 3))
    Wm = np.lib.format.open_memmap(store / "w.npy", mode="w+", dtype=np.float32, shape=(n_rows,))
    Em = np.lib.format.open_memmap(store / "e.npy", mode="w+", dtype=np.float64, shape=(n_rows,))
    V[:] = 0.0
    Wm[:] = 0.0
    Em[:] = 0.0

    inner = int(min(INNER_CHUNK, max(256, 1 << math.ceil(math.log2(max(rows_per_chunk, 1))))))
    pad_to = int(-(-rows_per_chunk // inner) * inner)
    x = jnp.asarray(_x0(names, init, fixed))
    state = {"first": True, "passes": 0, "n_window": 0, "n_seen": 0}

    def stream_pass(x_old, dx, do_update, *, sigma0_reject: float | None = None):
        """One read of the file: (update with dx at x_old), normals at x_old + dx."""
        N = np.zeros((u, u))
        nv = np.zeros(u)
        omega = 0.0
        x_new = x_old + dx
        for ch in iter_scan_chunks(campaign, meta, rows_per_chunk):
            m = len(ch)
            if m == 0:
                continue
            rows = ch.row
            l, c = scan_arrays(ch)
            if state["first"]:  # window from the initial paraboloid, once
                w = (np.abs(initial_distance(ch.range_m, ch.phi_rad, ch.theta_rad, init.x))
                     < window_m).astype(np.float32)
                Wm[rows] = w
                state["n_window"] += int(m - w.sum())
                state["n_seen"] += m
            w = np.asarray(Wm[rows], dtype=np.float64)
            if sigma0_reject is not None and robust_k is not None:
                bad = (np.asarray(Em[rows], float) > robust_k) & (w > 0)
                if bad.any():
                    w = np.where(bad, 0.0, w)
                    Wm[rows] = w.astype(np.float32)
            v = np.asarray(V[rows])
            pad = pad_to - m
            if pad:
                l = np.concatenate([l, np.repeat(l[-1:], pad, 0)])
                c = np.concatenate([c, np.repeat(c[-1:], pad, 0)])
                w = np.concatenate([w, np.zeros(pad)])
                v = np.concatenate([v, np.zeros((pad, 3))])
            Vn, E, om, Nc, nc = _fused_pass(mdl, jnp.asarray(l), jnp.asarray(c), jnp.asarray(w),
                                            jnp.broadcast_to(s2, l.shape), jnp.asarray(v),
                                            x_old, dx, x_new, jnp.asarray(do_update), inner)
            if do_update:
                V[rows] = np.asarray(Vn)[:m]
                Em[rows] = np.asarray(E)[:m]
            N += np.asarray(Nc)
            nv += np.asarray(nc)
            omega += float(om)
        state["first"] = False
        state["passes"] += 1
        return N, nv, omega

    def solve(N, nv):
        Nj = jnp.asarray(N)
        dx = _solve_normal(Nj, -jnp.asarray(nv))
        d = jnp.diagonal(_inverse(Nj))
        ratio = float(jnp.max(jnp.abs(dx) / jnp.sqrt(jnp.where(d > 0, d, 1.0))))
        return dx, ratio

    zero = jnp.zeros(u)
    total_it = 0
    rounds = 0
    sigma0 = math.nan
    converged = False
    reject_next = False
    t0 = time.perf_counter()
    while True:
        rounds += 1
        # one Gauss-Helmert adjustment from (x, V): passes as described in the module docstring
        N, nv, _ = stream_pass(x, zero, False, sigma0_reject=sigma0 if reject_next else None)
        dx, ratio = solve(N, nv)
        it = 1
        while ratio >= tol and it < max_iter:
            N, nv, _ = stream_pass(x, dx, True)
            x = x + dx
            dx, ratio = solve(N, nv)
            it += 1
        converged = ratio < tol
        # the converged step's residuals, then the final statistics pass
        N, nv, _ = stream_pass(x, dx, True)
        x = x + dx
        dx_f, _ = solve(N, nv)
        _, _, omega = stream_pass(x, dx_f, True)
        x = x + dx_f
        total_it += it
        n_used = int(np.count_nonzero(Wm))
        red = n_used - u
        sigma0 = math.sqrt(omega / max(red, 1))
        # standardized residuals: e / sigma0 (stored in place, chunk by chunk)
        for i0 in range(0, n_rows, rows_per_chunk):
            Em[i0:i0 + rows_per_chunk] /= sigma0
        if robust_k is None or rounds > max_rounds:  # as robust_gauss_helmert: 1 + max_rounds
            break
        n_bad = 0
        for i0 in range(0, n_rows, rows_per_chunk):
            sl = slice(i0, i0 + rows_per_chunk)
            n_bad += int(np.count_nonzero((Em[sl] > robust_k) & (Wm[sl] > 0)))
        if n_bad == 0:
            break
        reject_next = True
    timings["adjustment_s"] = time.perf_counter() - t0
    N_final = N
    cov = sigma0**2 * np.asarray(_inverse(jnp.asarray(N_final)))
    V.flush()
    Wm.flush()
    Em.flush()
    n_window = state["n_window"]
    return StreamFit(meta.id, names, np.asarray(x), cov, N_final, sigma0, n_rows, n_window,
                     n_used, state["n_seen"] - n_window - n_used, total_it, rounds, state["passes"],
                     converged, time.perf_counter() - t_start, store, init, timings)


def peak_rss_gib() -> float:
    """Peak resident memory of this process (GiB), from ``getrusage``."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


__all__ = ["StreamFit", "peak_rss_gib", "stream_fit_scan"]
