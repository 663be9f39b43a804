"""Streaming Gauss-Helmert adjustment of a full-resolution scan with bounded memory.

A scan at the paper's resolution has about 1.3e7 points; the 88-position campaign (176 scans)
about 2.3e9 -- more than this machine's memory. Here one scan is adjusted without ever holding
it: every iteration streams the scan's chunks from disk (:func:`._campaign.iter_scan_chunks`)
and runs the package's one-pass kernel (:func:`._kernel.make_pass`, the pass of
:func:`._kernel.gh_one_pass`) on each chunk: per point ONE linearisation per iteration, the
residual update of the previous iteration fused into the normal-equation pass of this one.

The kernel's per-point store (``a``, ``b`` in float32, ``w``, ``m`` in float64: 64 bytes per
point for the extended model), the weights and a copy of the decoded observations (range,
angles, time: 32 bytes per row, written by the first pass; the later passes read it instead
of decoding the scan file again) live in flat files under ``store``, one slot block per
streamed chunk, read and written with ``pread``/``pwrite`` chunk by chunk (not
memory-mapped, so the page cache of these files never counts towards the process's resident
memory). Memory is bounded by a few chunk buffers whatever the number of rows.

One read of the observations per iteration, and everything else from the same pass:

* the normals ``N``, ``n`` and ``w^T M^-1 w`` at the new linearisation point, so the weighted
  square sum after the step follows without another pass:
  ``omega = sum q (a.dx + w)^2 = w^T M^-1 w + dx.n`` (for ``dx = -N^-1 n``);
* the residuals ``v`` and standardized residuals of the previous solution (from the stored
  ``a, b, w, m`` and the previous step, as the kernel's final sweep computes them).

The robust rejection is that of :func:`._ghm.robust_gauss_helmert`, inside the iteration: once
a step was below one sigma of the unknowns, each pass first judges the previous solution's
residuals (from the store and the previous step) against ``robust_k`` a-posteriori sigmas of
that solution (``sigma0`` from the previous pass's sums), gives the points beyond weight 0 for
good, then accumulates the normals; the iteration ends when a step is below ``tol`` and its
pass rejected nothing. The residuals of the solution come from the store at the end (no read
of the file). Passes over the observations = iterations (the scan file itself is decoded
once). The arithmetic is that of the in-memory
kernel (same linearisation points, same rejections, same convergence test), so the result
equals the in-memory adjustment to round-off. (Until 2026-11 each robust round was iterated
to convergence, one more pass confirmed it, and a round stalled at full resolution by gross
outliers near the scanner's pole, where x6/x7 are singular, was checked early: 18 passes in
5 rounds; rejected at the first sub-sigma step they no longer stall the iteration.)

Outputs under ``store`` (indexed by the file row, rows dropped as non-finite are zero):
``v.npy`` (rows, 3) residuals, ``w.npy`` weights (0: outside the window or rejected),
``e.npy`` standardized residuals ``|k| sqrt(m) / sigma0``.

Initial values come from a seeded random sample of the scan (``n_sample`` rows, drawn while
streaming); the geometry window (distance from the initial paraboloid) is applied per chunk.
The RANSAC preprocessing is not applied here (its patches cross chunk boundaries).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import resource
import tempfile
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._programs import cached_jit
from ..campaign._campaign import Campaign, ScanMeta, iter_scan_chunks
from ..campaign._campaign import _concat as concat_scans
from ..campaign._format import CampaignError
from ..geometry._geometry import pointing_gravity
from ..model._model import N_CONSTS, make_model, parameter_unit
from ..preprocess._initial import InitialValues, choose_initial_values, geometry_window
from ..solver._kernel import (
    REJECT_BELOW,
    chunk_for,
    linearize_rev,
    make_pass,
    next_rate,
    part_chunk,
    pass_threads,
    remaining_error,
    solve_scaled,
    step_sigmas,
    thread_pool,
)
from ._distributed import worker_campaign
from ._fit import _progress, _x0, parse_names, sigma_vector
from ._identify import one_face_holds
from ._results import Estimates

log = logging.getLogger("hartrao_jax")

INNER_CHUNK = 8192  # points per step of the kernel's loop (its ``chunk``)
BLOCK = 1 << 18  # points per compiled call (a streamed chunk is split into blocks)
STORE_DTYPE = np.float32  # a, b as the in-memory kernel stores them


def _chunk_pass_impl(model, obs, c, w, sig, a, b, wm, m, x, dx_prev, reject, sigma0, k_rob, on):
    """One compute block (padded to a multiple of the kernel chunk, padding with weight 0).

    1. residuals of the previous solution from the stored ``a, b, wm, m`` and ``dx_prev``:
       ``k``, ``v = Sigma b k``, ``e = |k| sqrt(m) / sigma0``; if ``reject``, points with
       ``e > k_rob`` get weight 0 (as :func:`._ghm.robust_gauss_helmert`);
    2. the kernel's pass (:func:`._kernel.make_pass`) at ``x`` with the new weights: ``N``,
       ``n`` and the new store; ``wMw = sum q wm^2`` from that store.
    """
    f = obs.dtype
    nc, C = wm.shape
    s2 = sig**2
    k = -(jnp.einsum("icu,u->ic", a.astype(f), dx_prev) + wm) / m
    e = jnp.abs(k) * jnp.sqrt(m) / sigma0
    v = s2 * b.astype(f) * k[..., None]
    w2 = w.reshape(nc, C)
    bad = reject & (w2 > 0) & (e > k_rob)
    w_new = jnp.where(bad, 0.0, w2)
    one_pass, _, _, _ = make_pass(model, obs, c, w_new.reshape(-1), sig, on, lin=linearize_rev,
                                  chunk=C, store_dtype=a.dtype)
    N, nv, (a2, b2, wm2, m2) = one_pass(x, dx_prev, (a, b, wm, m))
    wmw = jnp.sum(jnp.where(w_new > 0, w_new * wm2 * wm2 / m2, 0.0))
    return (N, nv, wmw, jnp.sum(bad), jnp.sum(w_new > 0), a2, b2, wm2, m2,
            v.reshape(-1, 3), e.reshape(-1), w_new.reshape(-1))


# every array argument but the model is a fresh buffer per call: donated, so the new store
# is written in place of the old one (no copy of the chunk's store)
_chunk_pass = cached_jit(_chunk_pass_impl, donate="all-except-first")


@cached_jit
def _chunk_residuals(sig, a, b, wm, m, dx, sigma0):
    """Residuals ``v`` and ``e = |k| sqrt(m) / sigma0`` from a stored chunk (no linearisation)."""
    f = wm.dtype
    k = -(jnp.einsum("icu,u->ic", a.astype(f), dx) + wm) / m
    v = sig**2 * b.astype(f) * k[..., None]
    return v.reshape(-1, 3), (jnp.abs(k) * jnp.sqrt(m) / sigma0).reshape(-1)


class _SlotFile:
    """A flat binary file of per-slot records, read and written by chunk (pread/pwrite)."""

    def __init__(self, path: Path, dtype, tail: tuple[int, ...] = ()):
        self.path = path
        self.dtype = np.dtype(dtype)
        self.tail = tail
        self.rec = self.dtype.itemsize * int(np.prod(tail, dtype=int))
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)

    def read(self, start: int, n: int) -> np.ndarray:
        buf = np.empty((n, *self.tail), self.dtype)
        got = os.preadv(self.fd, [memoryview(buf).cast("B")], start * self.rec)
        if got != buf.nbytes:
            raise OSError(f"{self.path}: short read ({got} of {buf.nbytes} bytes)")
        return buf

    def write(self, start: int, arr) -> None:
        self._write_at(start * self.rec, arr)

    def _write_at(self, off: int, arr) -> None:
        arr = np.ascontiguousarray(arr, self.dtype)
        mv = memoryview(arr).cast("B")
        while len(mv):
            k = os.pwrite(self.fd, mv, off)
            mv, off = mv[k:], off + k

    def close(self, remove: bool = False) -> None:
        os.close(self.fd)
        if remove:
            self.path.unlink(missing_ok=True)


class _NpyRows(_SlotFile):
    """A ``.npy`` file of ``n_rows`` records indexed by the file row, written by row blocks."""

    def __init__(self, path: Path, dtype, n_rows: int, tail: tuple[int, ...] = ()):
        mm = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=(n_rows, *tail))
        del mm  # header written, data zero-filled (sparse)
        self.path = path
        self.dtype = np.dtype(dtype)
        self.tail = tail
        self.rec = self.dtype.itemsize * int(np.prod(tail, dtype=int))
        self.fd = os.open(path, os.O_RDWR)
        self.header = os.fstat(self.fd).st_size - n_rows * self.rec

    def write_rows(self, rows: np.ndarray, values) -> None:
        """``values`` at the file rows ``rows`` (increasing; gaps, if any, are written as 0)."""
        if len(rows) == 0:
            return
        r0, r1 = int(rows[0]), int(rows[-1]) + 1
        if r1 - r0 != len(rows):
            block = np.zeros((r1 - r0, *self.tail), self.dtype)
            block[rows - r0] = values
            values = block
        self._write_at(self.header + r0 * self.rec, values)


@dataclass
class StreamFit(Estimates):
    """Result of :func:`stream_fit_scan` (SI units). Per-point results under ``store``:
    ``v.npy`` (rows, 3) residuals, ``w.npy`` weights, ``e.npy`` standardized residuals
    (|k| sqrt(m) / sigma0), indexed by the file row.

    ``iterations``: kernel passes (one linearisation per point); ``passes``: reads of the scan
    file by the adjustment (= iterations; the residuals of the solution come from the store);
    ``rounds``: 1 + the passes that rejected points, ``round_iterations`` the iterations
    between them; ``ratios``: the convergence measure ``max |dx_j| / sigma_j`` of each
    iteration (converged when :func:`.solver._kernel.remaining_error` is below ``tol``);
    ``stalled_rounds``: always empty (kept for the record's shape: the rejection inside the
    iteration does not stall)."""

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
    round_iterations: list = field(default_factory=list)
    ratios: list = field(default_factory=list)
    stalled_rounds: list = field(default_factory=list)
    held: dict = field(default_factory=dict)  # name -> Held: two-face ones of a one-face scan


class _Cached:
    """A streamed chunk read back from the store's copy of its observations (the columns the
    adjustment uses; ``row``: the file rows)."""

    def __init__(self, obs: np.ndarray, row: np.ndarray):
        self.range_m, self.phi_rad, self.theta_rad, self.time_s = obs.T
        self.row = row

    def __len__(self) -> int:
        return len(self.row)


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
    """A random sample of about ``1.5 n_sample`` of the scan's rows (one read of the file)."""
    rng = np.random.default_rng(seed)
    frac = min(1.0, 1.5 * n_sample / max(n_rows, 1))
    return concat_scans([ch.subset(np.flatnonzero(rng.random(len(ch)) < frac))
                         for ch in iter_scan_chunks(campaign, meta, rows_per_chunk)])


@cached_jit
def _solve_step(N, nv, wmw):
    """``dx = -N^-1 n`` (as :func:`._kernel.gh_one_pass`), ``N^-1``, the convergence measure
    ``max |dx_j| / sqrt((N^-1)_jj)`` and the weighted square sum after the step."""
    dx, Ninv = solve_scaled(N, -nv)
    return dx, Ninv, step_sigmas(dx, Ninv), wmw + dx @ nv


def _blocks(m: int, B: int, G: int) -> list[tuple[int, int, int]]:
    """``(start, rows, padded size)`` of the compute blocks of a chunk of ``m`` rows: blocks of
    ``B`` rows, the last one padded to a multiple of ``G`` (few distinct compiled shapes)."""
    out = []
    for s0 in range(0, m, B):
        n = min(B, m - s0)
        out.append((s0, n, min(B, -(-n // G) * G)))
    return out


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
    prefetch: bool = False,
    stall: bool = True,
    threads: int | None = None,
) -> StreamFit:
    """Adjust one scan streaming it from disk in chunks of ``rows_per_chunk`` file rows.

    ``store``: directory for the per-point results (default: a new temporary directory); the
    kernel's working files there are removed at the end. ``init``: initial values (default:
    from a random sample of the scan, as :func:`._fit.prepare_scan` does from the whole scan).
    ``prefetch``: read the next chunk (file and store) in a thread while this one is computed
    (no gain measured on 2 busy cores, and glibc's per-thread arena keeps about 1 GiB more).
    ``stall``: ignored (the rounds it shortened are gone: the rejection is inside the
    iteration, as in :func:`._ghm.robust_gauss_helmert`).
    ``threads``: compute blocks of a chunk run at a time, one thread each (None:
    :func:`~.solver._kernel.pass_threads` of the chunk's rows); the sums are added in block
    order, so the result does not depend on it.
    Other arguments as :func:`._fit.fit_scan` / :func:`._ghm.robust_gauss_helmert`.
    """
    t_start = time.perf_counter()
    meta = campaign.scan(scan) if isinstance(scan, str) else scan
    fixed = dict(fixed or {})
    held = one_face_holds(parse_names(model), fixed) if meta.cycle == 0 else {}
    fixed.update({n: h.value for n, h in held.items()})
    mdl = make_model(model, fixed, aperture_radius_m=campaign.telescope.diameter_m / 2)
    names = mdl.free
    u = len(names)
    sig = sigma_vector(campaign)
    store = Path(store) if store is not None else Path(tempfile.mkdtemp(prefix="hartrao-stream-"))
    store.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {"read_s": 0.0, "wait_s": 0.0, "compute_s": 0.0, "write_s": 0.0}

    t0 = time.perf_counter()
    n_rows = _count_rows(campaign, meta)
    g = pointing_gravity(meta, campaign.telescope, campaign.site)
    if init is None:
        # as the in-memory fit chooses them: from the pointing, or pose-free (one-face
        # exports, offset reflectors)
        init = choose_initial_values(
            campaign, meta, _sample(campaign, meta, rows_per_chunk, n_rows, n_sample, seed), g,
            seed=seed)
    timings["initial_values_s"] = time.perf_counter() - t0

    threads = pass_threads(min(rows_per_chunk, n_rows)) if threads is None else int(threads)
    # (blocks at once, or a Dask worker's one thread: each block's loop on one core)
    inner = chunk_for(rows_per_chunk, part_chunk(INNER_CHUNK, threads))
    B = min(BLOCK, -(-rows_per_chunk // inner) * inner)  # rows per compiled call
    G = max(inner, B // 4 // inner * inner)  # granularity of a chunk's last block
    P = -(-rows_per_chunk // B) * B  # store slots per streamed chunk
    files = {"a": _SlotFile(store / "_a.bin", STORE_DTYPE, (u,)),
             "b": _SlotFile(store / "_b.bin", STORE_DTYPE, (3,)),
             "wm": _SlotFile(store / "_wm.bin", np.float64),
             "m": _SlotFile(store / "_m.bin", np.float64),
             "w": _SlotFile(store / "_w.bin", np.float32),
             # the decoded observations (range, phi, theta, time): the later passes read
             # these instead of decoding the scan file again (2-3 s per pass at 1.3e7 rows)
             "obs": _SlotFile(store / "_obs.bin", np.float64, (4,))}
    out_v = _NpyRows(store / "v.npy", np.float64, n_rows, (3,))
    out_w = _NpyRows(store / "w.npy", np.float32, n_rows)
    out_e = _NpyRows(store / "e.npy", np.float64, n_rows)
    chunk_rows: list[np.ndarray | tuple[int, int]] = []  # file rows of each streamed chunk
    x = _x0(names, init, fixed)
    dx_prev = np.zeros(u)
    state = {"first": True, "passes": 0, "n_window": 0, "n_seen": 0}
    k_rob = np.inf if robust_k is None else float(robust_k)

    def rows_of(j):
        r = chunk_rows[j]
        return np.arange(r[0], r[0] + r[1]) if isinstance(r, tuple) else r

    def read_store(slot, n):
        ni = n // inner
        return (files["a"].read(slot, n).reshape(ni, inner, u),
                files["b"].read(slot, n).reshape(ni, inner, 3),
                files["wm"].read(slot, n).reshape(ni, inner),
                files["m"].read(slot, n).reshape(ni, inner))

    def load(item):
        """Read side of one streamed chunk (in the prefetch thread): per compute block the
        observations, constants and weights padded to the block's size (repeating the last
        row, weight 0), and the block's kernel store."""
        j, ch = item
        m = len(ch)
        if m > P:
            raise ValueError(f"chunk of {m} rows > rows_per_chunk {rows_per_chunk}")
        if state["first"]:
            w_all = geometry_window(ch.range_m, ch.phi_rad, ch.theta_rad, init.x,
                                    window_m).astype(np.float32)
            files["obs"].write(j * P, np.column_stack([ch.range_m, ch.phi_rad, ch.theta_rad,
                                                        ch.time_s]))
        else:
            w_all = files["w"].read(j * P, m)
        blocks = []
        for s0, n, size in _blocks(m, B, G):
            obs = np.empty((size, 3))
            c = np.zeros((size, N_CONSTS))
            for col, arr in enumerate((ch.range_m, ch.phi_rad, ch.theta_rad)):
                obs[:n, col] = arr[s0:s0 + n]
            c[:n, 0] = ch.time_s[s0:s0 + n]
            obs[n:] = obs[n - 1]
            c[n:] = c[n - 1]
            w = np.zeros(size, np.float32)
            w[:n] = w_all[s0:s0 + n]
            ni = size // inner
            if state["first"]:  # the kernel's start store: v = 0
                st = (np.zeros((ni, inner, u), STORE_DTYPE), np.zeros((ni, inner, 3), STORE_DTYPE),
                      np.full((ni, inner), -1.0), np.ones((ni, inner)))
            else:
                st = read_store(j * P + s0, size)
            blocks.append((s0, n, obs, c, w, st))
        return j, ch.row, m, blocks

    def stream_pass(x, dx_prev, *, reject: bool, sigma0: float):
        """One read of the observations: (rejection and) residuals of the previous solution,
        normals at ``x`` (the residuals of the solution are written by ``final_sweep``)."""
        N = np.zeros((u, u))
        nv = np.zeros(u)
        wmw = 0.0
        n_bad = n_used = 0
        src = enumerate(iter_scan_chunks(campaign, meta, rows_per_chunk) if state["first"]
                        else (_Cached(files["obs"].read(j_ * P, len(rows_of(j_))), rows_of(j_))
                              for j_ in range(len(chunk_rows))))

        def fetch():  # the file and store reads of the next chunk
            t = time.perf_counter()
            item = next(src, None)
            out = None if item is None else load(item)
            return out, time.perf_counter() - t

        pool = ThreadPoolExecutor(1) if prefetch else None
        try:
            nxt = pool.submit(fetch) if pool else None
            while True:
                tq = time.perf_counter()
                item, t_read = nxt.result() if pool else fetch()
                timings["wait_s"] += time.perf_counter() - tq
                timings["read_s"] += t_read
                if item is None:
                    break
                if pool:
                    nxt = pool.submit(fetch)
                j, rows, m, blocks = item
                if state["first"]:
                    contiguous = m and int(rows[-1]) - int(rows[0]) + 1 == m
                    chunk_rows.append((int(rows[0]), m) if contiguous else np.asarray(rows))
                    state["n_seen"] += m
                def compute(block):
                    _, _, obs, c, w, st = block
                    outs = _chunk_pass(mdl, obs, c, w, sig, *st, x, dx_prev, np.asarray(reject),
                                       np.asarray(sigma0), np.asarray(k_rob), np.ones((), bool))
                    return tuple(np.asarray(o) for o in outs)

                # the chunk's blocks computed in `threads` threads at a time (one jitted call
                # runs on one core; concurrent calls run concurrently), used in block order
                futs = [cpool.submit(compute, b) for b in blocks] if cpool else None
                for i_b, (s0, n, obs, c, w, st) in enumerate(blocks):
                    tc = time.perf_counter()
                    Nc, nc_, wc, bad, used, a2, b2, wm2, m2, v, e, w2 = (
                        futs[i_b].result() if futs else compute(blocks[i_b]))
                    timings["compute_s"] += time.perf_counter() - tc
                    tw = time.perf_counter()
                    N += Nc
                    nv += nc_
                    wmw += float(wc)
                    n_bad += int(bad)
                    n_used += int(used)
                    slot = j * P + s0
                    if state["first"]:
                        state["n_window"] += int(n - np.count_nonzero(w[:n]))
                    if state["first"] or bad:
                        files["w"].write(slot, w2[:n])
                    for key, arr in zip(("a", "b", "wm", "m"), (a2, b2, wm2, m2)):
                        files[key].write(slot, arr.reshape((-1, *files[key].tail)))
                    timings["write_s"] += time.perf_counter() - tw
        finally:
            if pool:
                pool.shutdown(wait=True, cancel_futures=True)
        state["first"] = False
        state["passes"] += 1
        return N, nv, wmw, n_bad, n_used

    def final_sweep(dx, sigma0):
        """Residuals of the solution from the store alone (no read of the file)."""
        for j in range(len(chunk_rows)):
            rows = rows_of(j)
            w_all = files["w"].read(j * P, len(rows))
            for s0, n, size in _blocks(len(rows), B, G):
                v, e = (np.asarray(o) for o in _chunk_residuals(
                    sig, *read_store(j * P + s0, size), dx, np.asarray(sigma0)))
                r = rows[s0:s0 + n]
                out_v.write_rows(r, v[:n])
                out_e.write_rows(r, e[:n])
                out_w.write_rows(r, w_all[s0:s0 + n])

    cpool = thread_pool(threads) if threads > 1 else None
    t0 = time.perf_counter()
    try:
        # the iteration of :func:`._kernel.gh_one_pass` with its rejection inside the
        # iteration (:func:`._ghm.robust_gauss_helmert`): each pass judges the previous
        # solution's residuals (from the store) against robust_k a-posteriori sigmas of that
        # solution (sigma0 from the previous pass's sums: omega = w^T M^-1 w + dx.n), once a
        # step was below one sigma; rejected points stay out
        rounds, it_round, total_it, rejecting = 1, 0, 0, 0
        round_its: list[int] = []
        ratios: list[float] = []
        sigma0, ratio = 1.0, math.inf
        rate = 1.0  # the steps' contraction, as in gh_one_pass
        converged = False
        N = Ninv = None
        n_used = 0
        while True:
            judge = (robust_k is not None and total_it >= 1 and ratio < REJECT_BELOW
                     and rejecting < max_rounds)
            judged = judge or robust_k is None or rejecting >= max_rounds
            N, nv, wmw, n_bad, n_used = stream_pass(x, dx_prev, reject=judge, sigma0=sigma0)
            if n_bad:
                log.info("stream %s: iteration %d rejects %d points", meta.id, total_it + 1,
                         n_bad)
                round_its.append(it_round)
                rounds += 1
                rejecting += 1
                it_round = 0
            dx, Ninv, r, omega = (np.asarray(o) for o in _solve_step(N, nv, wmw))
            rate = float(next_rate(rate, ratio, float(r), n_bad > 0))
            ratio, omega = float(r), float(omega)
            it_round += 1
            total_it += 1
            ratios.append(ratio)
            log.debug("stream %s: iteration %d ratio %.3g", meta.id, total_it, ratio)
            x = x + dx
            dx_prev = dx
            sigma0 = math.sqrt(max(omega, 0.0) / max(n_used - u, 1))
            converged = float(remaining_error(ratio, rate)) < tol and judged and not n_bad
            if converged or total_it >= max_iter:
                final_sweep(dx_prev, sigma0)
                break
        round_its.append(it_round)
    finally:
        for f_ in files.values():
            f_.close(remove=True)
        for f_ in (out_v, out_w, out_e):
            f_.close()
    if n_used <= u or not math.isfinite(sigma0):  # never a NaN estimate passed on
        raise CampaignError(
            f"{meta.id}: {n_used:,} of {n_rows:,} rows are within the window of the paraboloid "
            f"after {total_it} iterations (initial f {init.x.get('f', math.nan):.4g} m, "
            f"{100 * init.inlier_fraction:.0f} % of the sample near it): too few for {u} "
            "unknowns; expected a scan of the reflector that its initial values find")
    timings["adjustment_s"] = time.perf_counter() - t0
    timings["s_per_pass"] = timings["adjustment_s"] / max(state["passes"], 1)
    cov = sigma0**2 * Ninv
    n_window = state["n_window"]
    return StreamFit(meta.id, names, np.asarray(x), cov, N, sigma0, n_rows, n_window,
                     n_used, state["n_seen"] - n_window - n_used, total_it, rounds,
                     state["passes"], converged, time.perf_counter() - t_start, store, init,
                     timings, round_its, ratios, [], held)


def peak_rss_gib() -> float:
    """Peak resident memory of this process (GiB), from ``getrusage``."""

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def stream_document(r: StreamFit) -> dict:
    """The JSON record of one streamed scan (``"schema": "hartrao-stream/1"``; SI units)."""

    return {"schema": "hartrao-stream/1", "scan": r.id, "model": list(r.names),
            "estimates": {**{n: {"value": v, "sigma": s, "unit": parameter_unit(n)}
                             for n, (v, s) in r.estimates.items()},
                          **{n: {"value": h.value, "sigma": None, "identifiable": False,
                                 "note": h.note, "unit": parameter_unit(n)}
                             for n, h in r.held.items()}},
            "sigma0": r.sigma0, "n_rows": r.n_rows, "n_points": r.n_points,
            "n_rejected": r.n_rejected, "n_outside_window": r.n_window,
            "iterations": r.iterations, "rounds": r.rounds, "passes": r.passes,
            "converged": r.converged, "seconds": r.seconds, "peak_rss_gib": peak_rss_gib(),
            "store": str(r.store), "timings": r.timings}


def stream_scan_document(campaign: Campaign, scan_id: str, model, store: str | None,
                         rows_per_chunk: int, robust_k: float | None) -> dict:
    """One scan streamed (:func:`stream_fit_scan`), its JSON record (:func:`stream_document`);
    the per-point results stay in ``store`` (None: not kept, ``"store": null``)."""
    with kept_store(store) as st:
        doc = stream_document(stream_fit_scan(campaign, scan_id, model,
                                              rows_per_chunk=rows_per_chunk, store=st,
                                              robust_k=robust_k))
    if store is None:
        doc["store"] = None
    return doc


def _stream_task(root: str, scan_id: str, model, store: str | None, rows_per_chunk: int,
                 robust_k: float | None) -> dict:
    """One scan streamed where this runs (in-process or on a Dask worker): its small record;
    the per-point results stay in ``store`` (on the worker's disk; None: not kept)."""
    camp = worker_campaign(root)  # on a Dask worker: float64, the compilation cache
    return stream_scan_document(camp, scan_id, model, store, rows_per_chunk, robust_k)


@contextlib.contextmanager
def kept_store(store: str | None):
    """The directory of a streamed fit's per-point results: ``store`` itself, or (None) a
    temporary one removed on exit, so a command run without ``--store`` leaves nothing behind
    (at full resolution a scan's results take about 36 B per row: 0.5 GB at 1.3e7 rows)."""
    if store is not None:
        yield Path(store)
        return
    with tempfile.TemporaryDirectory(prefix="hartrao-stream-") as tmp:
        yield Path(tmp)


def stream_fit_campaign(
    campaign: Campaign,
    scans: Iterable[str] | None = None,
    model: str | Iterable[str] = "extended",
    *,
    store=None,
    rows_per_chunk: int = 1_000_000,
    robust_k: float | None = 4.0,
    client=None,
    progress: bool = False,
) -> dict:
    """Stream every scan of a campaign (a full-resolution campaign larger than memory).

    Each scan is adjusted by :func:`stream_fit_scan` with bounded memory, one after the other
    in this process, or as independent tasks on a Dask ``client`` (one scan per worker core at
    a time; only the small records travel back). ``store``: a directory receiving one
    sub-directory of per-point results per scan (default: temporary ones). Returns
    ``{"schema": "hartrao-stream-campaign/1", "scans": [record, ...], "seconds": ...}`` in the
    campaign's scan order.
    """
    t0 = time.perf_counter()
    ids = [m.id for m in campaign.scans] if scans is None else list(scans)
    for sid in ids:
        campaign.scan(sid)  # unknown ids: the campaign's own error, before any work
    root = str(campaign.root)
    stores = [None if store is None else str(Path(store) / sid) for sid in ids]
    if client is None:
        recs = []
        with _progress(not progress) as prog:
            task = prog.add_task("streaming scans", total=len(ids))
            for sid, st in zip(ids, stores):
                prog.update(task, description=f"streaming {sid}")
                recs.append(_stream_task(root, sid, model, st, rows_per_chunk, robust_k))
                prog.advance(task)
    else:
        futs = [client.submit(_stream_task, root, sid, model, st, rows_per_chunk, robust_k,
                              key=f"stream-{sid}", pure=False) for sid, st in zip(ids, stores)]
        recs = client.gather(futs)
    return {"schema": "hartrao-stream-campaign/1", "campaign": root, "scans": recs,
            "seconds": time.perf_counter() - t0, "rows_per_chunk": rows_per_chunk,
            "workers": None if client is None else len(client.scheduler_info()["workers"])}


__all__ = ["StreamFit", "peak_rss_gib", "stream_document", "stream_fit_campaign",
           "stream_fit_scan"]
