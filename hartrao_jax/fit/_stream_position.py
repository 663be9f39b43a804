"""Two-face position adjustment of full-resolution scans, streamed with bounded memory.

The default adjustment of a position (:func:`._fit.fit_position`: both faces together, the
surface a random effect with estimated variances) holds every point in memory. At the paper's
resolution a position has 2.6e7 points; here it is adjusted without holding them:

1. **Start** from :func:`._fit.fit_position` on a seeded random sample of each face
   (``n_sample`` rows per scan, drawn while streaming): initial values, geometry window,
   identifiability (the parameters it holds stay held), north alignment, cells, and the
   random effect's predictions and variance components. With the surface a random effect the
   sigmas of f, pose and calibration are set by the surface, not by the number of points, so
   this start is already close (and its sigmas close) to the full-resolution answer.
2. **Refine** from every row of both scans: each iteration reads the scans chunk by chunk
   and adds up the normal-equation sums of :func:`.solver.mixed_chunk` (residuals at the
   current solution, robust rejection at ``robust_k`` noise sigmas from there, linearisation
   at ``l + v``); :func:`.solver.mixed_step` re-estimates the variance components from the
   sums and takes the Gauss-Newton step of ``x`` and the cells. Iterations stop when the
   error left in the new solution is below ``tol`` of its sigma: the last step, or, once the
   steps contract fast (ratio ``c`` of the last two below 0.5) and the variance components
   have settled, the rest of their geometric series ``step c / (1 - c)``
   (:func:`.solver._mixed.iteration_converged`; at full resolution the steps went 3.1,
   0.082, then 4.5e-5 sigma: the third pass only confirmed the second). With a ``store``, one
   more pass writes the per-point results (without, the statistics are the last step's: one
   read of every row fewer).

Memory: a chunk of ``rows_per_chunk`` rows and the per-cell sums (g x 3 x u); nothing per point
is kept between passes (the residuals are recomputed at each pass from the solution).
Per-point outputs under ``store/<scan id>/``: ``v.npy`` (rows, 3) residuals (m, rad, rad),
``w.npy`` weights (0: outside the window or rejected), ``e.npy`` standardized residuals,
``dev.npy`` the surface random effect's deviation at the point (m), indexed by the file row.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ..campaign._campaign import Campaign, ScanMeta, iter_scan_chunks
from ..campaign._campaign import _concat as concat_scans
from ..geometry._geometry import panel_cells, square_cells, zernike_columns
from ..model._model import ZERNIKE_PREFIX
from ..preprocess._initial import geometry_window
from ..solver._ghm import bucket_size
from ..solver._kernel import next_rate, remaining_error
from ..solver._mixed import MIXED_TOL, iteration_converged, mixed_response, ridge_indices
from ..solver._mixed_stream import MixedSums, mixed_chunk, mixed_step
from ._distributed import worker_campaign
from ._fit import fit_position, scan_arrays, sigma_vector
from ._identify import mode_prior
from ._position_record import position_record
from ._projection import hit_points
from ._results import PositionFit, SurfaceEffect
from ._stream import _count_rows, _NpyRows, _progress, _SlotFile, peak_rss_gib
from ._surface_effect import (
    mode_variance_parts,
    pooled_mode_variance,
    record_mode_variance,
    surface_components,
    white_sigmas,
)


def _sample_rows(campaign: Campaign, meta: ScanMeta, rows_per_chunk: int, n_sample: int,
                 seed: int):
    """A seeded random sample of about ``n_sample`` rows of one scan (read by chunks)."""
    n_rows = _count_rows(campaign, meta)
    frac = min(1.0, n_sample / max(n_rows, 1))
    rng = np.random.default_rng(seed)
    parts = [ch.subset(rng.random(len(ch)) < frac)
             for ch in iter_scan_chunks(campaign, meta, rows_per_chunk)]
    return concat_scans(parts), n_rows


def _cells(st, tel, X_tel):
    """Cell and design ``(1, local coordinates)`` of each point, numbered as the start's."""
    if st.cell_keys is None:
        cell, local, _, _ = panel_cells(X_tel, tel.ring_edges_m, tel.panels_per_ring)
    else:
        cell, local, _ = square_cells(X_tel, st.cell_m, st.cell_keys)
    return cell, np.column_stack([np.ones(len(cell)), local]) * (cell >= 0)[:, None]


def _padded_obs(ch) -> tuple[np.ndarray, np.ndarray]:
    """Observations and constants of one chunk, padded to a size bucket with copies of the
    first row (weight 0 and in no cell: see :func:`_chunk_geometry`): few compiled shapes."""
    n = len(ch)
    l, c = scan_arrays(ch)
    size = bucket_size(n)
    if size > n:
        pad = np.r_[np.arange(n), np.zeros(size - n, np.int64)]
        l, c = l[pad], c[pad]
    return l, c


def _chunk_geometry(campaign, st, ch, init, window_m, x, l, c) -> tuple[np.ndarray, ...]:
    """Window weights (float32), cells (int32), cell design ``(1, local coordinates)`` and
    smooth-mode columns (float32) of one chunk, padded as :func:`_padded_obs` (``l, c``) with
    weight 0 and cell -1, where ``x`` puts the beams (their hit points)."""
    n = len(ch)
    w = geometry_window(ch.range_m, ch.phi_rad, ch.theta_rad, init.x, window_m)
    u0 = len(st.condition.free)
    X_hit = np.asarray(hit_points(st.condition, l[:n], x[:u0], c[:n], sigma_vector(campaign),
                                  st.kappa_rad))
    cell, design = _cells(st, campaign.telescope, X_hit)
    mz = zernike_columns(X_hit, st.modes, st.aperture_m)
    size = len(l)
    out = (np.zeros(size, np.float32), np.full(size, -1, np.int32),
           np.zeros((size, design.shape[1]), np.float32), np.zeros((size, mz.shape[1]),
                                                                   np.float32))
    for a, v in zip(out, (w, cell, design, mz)):
        a[:n] = v
    return out


class _GeometryCache:
    """Each chunk's :func:`_chunk_geometry`, computed at the first pass and read back at the
    later ones from flat files in a temporary directory (44 B per row and smooth mode count
    below 7; removed by :meth:`close`): the cells and columns are the same at every pass, and
    the hit points, cells and Zernike terms took as long as the adjustment's own chunk (0.9 of
    2.0 s per 1e6 rows)."""

    def __init__(self, k: int, r: int, where=None):
        self._dir = tempfile.TemporaryDirectory(prefix="hartrao-geometry-", dir=where)
        d = Path(self._dir.name)
        self.files = (_SlotFile(d / "w.bin", np.float32), _SlotFile(d / "cell.bin", np.int32),
                      _SlotFile(d / "design.bin", np.float32, (k,)),
                      _SlotFile(d / "mz.bin", np.float32, (r,)) if r else None)
        self.slots: dict[tuple[int, int], tuple[int, int]] = {}
        self.end = 0

    def get(self, key: tuple[int, int], compute) -> tuple[np.ndarray, ...]:
        if key in self.slots:
            start, size = self.slots[key]
            return tuple(np.zeros((size, 0), np.float32) if f is None else f.read(start, size)
                         for f in self.files)
        arrays = compute()
        self.slots[key] = (self.end, len(arrays[0]))
        for f, a in zip(self.files, arrays):
            if f is not None:
                f.write(self.end, a)
        self.end += len(arrays[0])
        return arrays

    def close(self) -> None:
        for f in self.files:
            if f is not None:
                f.close()
        self._dir.cleanup()


def stream_fit_position(
    campaign: Campaign,
    scans: Sequence[str | ScanMeta],
    model: str | Iterable[str] = "extended",
    *,
    rows_per_chunk: int = 1_000_000,
    n_sample: int = 300_000,
    store=None,
    fixed: dict[str, float] | None = None,
    window_m: float = 0.10,
    robust_k: float | None = 4.0,
    max_iter: int = 10,
    tol: float = MIXED_TOL,
    seed: int = 0,
    progress: bool = False,
    mode_prior_m2: float | None = None,
    defer_campaign_prior: bool = False,
) -> dict:
    """Adjust the scans of one position (both faces, or one) streaming them from disk.

    Returns the position's record (as ``fit.json``'s ``positions[]``, see
    :func:`._position_record.position_record`) with the streaming figures added (``n_rows``,
    ``passes``, ``seconds``, ``peak_rss_gib``, ``start``: the sample adjustment's f and sigma0) and
    ``scans[]``: per scan its rows, points, rejections, sigma0 and the ``store`` of its
    per-point results (``store`` None: none are written, and the final pass that writes them
    is saved).

    ``defer_campaign_prior``: when the start shows that the position would take a campaign's
    mode variance (:func:`._surface_effect.takes_campaign_prior`), stop there and return only
    ``{"position", "deferred": True, "surface_mode_confounding", "seconds"}``: a campaign
    streams such a position once, with the variance, after the others instead of twice.
    """
    t_start = time.perf_counter()
    metas = [campaign.scan(s) if isinstance(s, str) else s for s in scans]
    if len({m.position for m in metas}) != 1:
        raise ValueError("stream_fit_position: scans of one position expected, found "
                         + ", ".join(sorted({m.position for m in metas})))
    store = None if store is None else Path(store)
    timings = {}
    t0 = time.perf_counter()
    samples, n_rows = [], []
    for i, m in enumerate(metas):
        d, n = _sample_rows(campaign, m, rows_per_chunk, n_sample, seed + i)
        samples.append(d)
        n_rows.append(n)
    timings["sample_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    start = fit_position(campaign, metas, model, datas=samples, fixed=fixed, robust_k=robust_k,
                         window_m=window_m, mode_prior_m2=mode_prior_m2)
    timings["start_fit_s"] = time.perf_counter() - t0
    if defer_campaign_prior and start.takes_campaign_prior:
        return {"position": metas[0].position, "deferred": True,
                "surface_mode_confounding": start.surface.mode_confounding,
                "seconds": time.perf_counter() - t_start, "timings": timings}
    st = start.mixed
    if st is None:
        raise ValueError(f"position {metas[0].position}: the start adjustment has no surface "
                         "random effect to refine")
    sig = sigma_vector(campaign)
    k_rob = np.asarray(np.inf if robust_k is None else float(robust_k))
    ridge_idx, ridge_group, n_groups = ridge_indices(st.ridge)
    var0 = tuple(jnp.asarray(v, jnp.float64) for v in st.var0)
    var = tuple(jnp.asarray(v, jnp.float64) for v in st.var)
    x, U = jnp.asarray(st.x), jnp.asarray(st.u)
    u0 = len(st.condition.free)  # the unknowns before the smooth modes
    outs = {}

    def stream_pass(x, U, var, write: bool):
        """One read of every scan of the position: the sums at ``(x, U)`` (and, if ``write``,
        the per-point results there). Returns the sums and per scan (omega, n_used)."""
        total, per_scan = None, []
        for i, m in enumerate(metas):
            om = nu = 0.0
            for j, ch in enumerate(iter_scan_chunks(campaign, m, rows_per_chunk)):
                n = len(ch)
                l, c = _padded_obs(ch)
                # cells and mode columns where the start solution puts the beams (as the
                # in-memory adjustment keeps its white fit's): the same at every pass
                w, cell, design, mz = geometry.get((i, j), lambda: _chunk_geometry(
                    campaign, st, ch, st.inits[i], window_m, st.x, l, c))
                sums, pc = mixed_chunk(st.condition, l, c, w, sig**2,
                                       cell, design, x, U, var[0], k_rob, mode_design=mz)
                total = sums if total is None else total + sums
                om += float(sums.omega)
                nu += float(sums.n_used)
                if write:  # the surface's deviation at each point: cells and modes
                    dev = np.where(cell[:n] >= 0, np.sum(design[:n] * np.asarray(U)[
                        np.maximum(cell[:n], 0)], axis=1), 0.0) + mz[:n] @ np.asarray(x)[u0:]
                    for key, val in (("v", pc.v), ("w", pc.weights), ("e", pc.e), ("dev", dev)):
                        outs[m.id][key].write_rows(ch.row, np.asarray(val)[:n])
            per_scan.append((om, nu))
        return total, per_scan

    if store is not None:  # the per-point results asked for
        for m, nr in zip(metas, n_rows):
            d = store / m.id
            d.mkdir(parents=True, exist_ok=True)
            outs[m.id] = {"v": _NpyRows(d / "v.npy", np.float64, nr, (3,)),
                          "w": _NpyRows(d / "w.npy", np.float32, nr),
                          "e": _NpyRows(d / "e.npy", np.float64, nr),
                          "dev": _NpyRows(d / "dev.npy", np.float64, nr)}
    t0 = time.perf_counter()
    ratios, passes, converged = [], 0, False
    geometry = _GeometryCache(3, len(st.modes))
    try:
        with _progress(not progress) as prog:
            task = prog.add_task(f"streaming position {metas[0].position}", total=max_iter + 1)
            for _ in range(max_iter):
                sums, per_scan = stream_pass(x, U, var, write=False)
                passes += 1
                final = mixed_step(sums, var, var0, x, U, ridge_idx, ridge_group, n_groups,
                                   estimate_variances=not st.variances_held)
                var_prev = var
                x, U, var = final.x, final.U, final.var
                ratios.append(float(final.ratio))
                prog.advance(task)
                if bool(iteration_converged(ratios[-1], _rate(ratios), tol, var, var_prev,
                                            var0)):
                    converged = True
                    break
            if store is not None:  # per-point results (and the statistics) at the solution
                sums, per_scan = stream_pass(x, U, var, write=True)
                passes += 1
                final = mixed_step(sums, var, var0, x, U, ridge_idx, ridge_group, n_groups,
                                   estimate_variances=False)
            # else: the statistics of the last step's linearisation (its step below tol
            # sigma), as the in-memory adjustment: one read of every row fewer
            prog.advance(task)
    finally:
        geometry.close()
        for o in outs.values():
            for f_ in o.values():
                f_.close()
    timings["refine_s"] = time.perf_counter() - t0
    rec = _record(start, st, x, final, var, sums, per_scan, converged, passes)
    rec.update(n_rows=int(sum(n_rows)), n_sample=[len(d) for d in samples], passes=passes,
               ratios=ratios, remaining_ratio=_remaining(ratios) if ratios else None,
               seconds=time.perf_counter() - t_start,
               peak_rss_gib=peak_rss_gib(), timings=timings,
               store=None if store is None else str(store),
               start={"f": {"value": start.estimate("f")[0], "sigma": start.estimate("f")[1],
                            "unit": "m"}, "sigma0": start.sigma0, "n_points": start.n_points})
    r_e = float(final.redundancy_noise)
    rec["scans"] = [
        {"scan": m.id, "n_rows": nr, "n_points": int(nu),
         "sigma0": _sigma0(om, nu, r_e, sums),
         "store": None if store is None else str(store / m.id)}
        for m, nr, (om, nu) in zip(metas, n_rows, per_scan)]
    return rec


def _rate(ratios: Sequence[float]) -> float:
    """The contraction of the last two of these steps (sigmas each; the streamed passes
    reject afresh at every pass, so no step restarts the series)."""
    return float(next_rate(1.0, ratios[-2] if len(ratios) > 1 else 0.0, ratios[-1], False))


def _remaining(ratios: Sequence[float]) -> float:
    """The error left in the solution after the last of these steps (sigmas, largest over the
    unknowns): :func:`.solver._kernel.remaining_error` at their contraction."""
    return float(remaining_error(ratios[-1], _rate(ratios)))


def _sigma0(omega: float, n_used: float, redundancy: float, sums: MixedSums) -> float:
    """A scan's sigma0: its share of ``v^T Sigma^-1 v`` over its share of the redundancy."""
    r = redundancy * n_used / max(float(sums.n_used), 1.0)
    return math.sqrt(omega / max(r, 1.0))


def _record(start: PositionFit, st, x, final, var, sums, per_scan, converged, passes) -> dict:
    """The ``positions[]`` record of the refined adjustment."""
    names = st.model.free
    xs = np.asarray(x)
    cov = float(var[0]) * np.asarray(final.Qxx)
    keep = [i for i, n in enumerate(names) if not n.startswith(ZERNIKE_PREFIX)]
    cov_keep = cov[np.ix_(keep, keep)]
    response = np.asarray(mixed_response(sums, var, final.Qxx))[:, keep, :]
    modes = [i for i, n in enumerate(names) if n.startswith(ZERNIKE_PREFIX)]
    s = start.surface
    variances, shares = surface_components(
        var, (final.redundancy_noise, final.redundancy_cells, final.redundancy_ridge), st.ridge)
    surf = SurfaceEffect(
        cells=s.cells, u=np.asarray(final.U), u_cov=float(var[0]) * np.asarray(final.Quu),
        n=s.n, variances=variances, redundancy=shares,
        modes={names[i]: (float(xs[i]), math.sqrt(cov[i, i])) for i in modes},
        mode_prior=mode_prior(cov, names, st.ridge, var[2]),
        mode_confounding=s.mode_confounding)
    n_used = float(sums.n_used)
    sigma0 = math.sqrt(float(sums.omega) / max(n_used - len(names), 1.0))
    pf = dataclasses.replace(
        start, names=tuple(names[i] for i in keep), x=xs[keep], cov=cov_keep,
        sigma0=sigma0, surface=surf, iterations=passes, converged=converged,
        n_points=int(n_used), mixed=None, response=response,
        sigma_white=white_sigmas(response, var[1], cov_keep,
                                 mode_variance_parts(surf.mode_prior, names, keep, cov_keep)),
        notes=[*start.notes, "streamed: started from a sample of each face, refined from "
               "every row"])
    rec = position_record(pf)
    rec.pop("panels", None)  # the cells' point counts are the sample's: not written
    return rec


def _position_task(root: str, scan_ids: list[str], model, store: str | None,
                   rows_per_chunk: int, robust_k: float | None,
                   mode_prior_m2: float | None = None, defer: bool = False) -> dict:
    """One position streamed where this runs (in-process or on a Dask worker); the per-point
    results stay in ``store`` (None: not written); ``defer``: as
    :func:`stream_fit_position`'s ``defer_campaign_prior``."""
    camp = worker_campaign(root)  # on a Dask worker: float64, the compilation cache
    return stream_fit_position(camp, scan_ids, model, rows_per_chunk=rows_per_chunk,
                               store=store, robust_k=robust_k, mode_prior_m2=mode_prior_m2,
                               defer_campaign_prior=defer)


def stream_fit_positions(
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
    """Stream every position of a campaign (or of the scans named): one two-face adjustment
    per position (:func:`stream_fit_position`), in this process one after the other or as one
    Dask task per position. ``store``: a directory receiving ``<scan id>/`` per scan.

    Returns ``{"schema": "hartrao-stream-campaign/1", "positions": [record, ...], "scans":
    [...], "seconds": ...}``.
    """
    t0 = time.perf_counter()
    ids = [m.id for m in campaign.scans] if scans is None else list(scans)
    metas = [campaign.scan(s) for s in ids]  # unknown ids: the campaign's error, before work
    groups: dict[str, list[str]] = {}
    for m in metas:
        groups.setdefault(m.position, []).append(m.id)
    root = str(campaign.root)
    st = None if store is None else str(store)

    def run(todo: dict[str, list[str]], prior=None, tag="", defer=False) -> dict[str, dict]:
        if client is None:
            out = {}
            with _progress(not progress) as prog:
                task = prog.add_task("streaming positions" + tag, total=len(todo))
                for pos, sids in todo.items():
                    prog.update(task, description=f"streaming {pos}{tag}")
                    out[pos] = _position_task(root, sids, model, st, rows_per_chunk, robust_k,
                                              prior, defer)
                    prog.advance(task)
            return out
        futs = [client.submit(_position_task, root, sids, model, st, rows_per_chunk, robust_k,
                              prior, defer, key=f"stream-{pos}{tag.replace(' ', '-')}",
                              pure=False)
                for pos, sids in todo.items()]
        return dict(zip(todo, client.gather(futs)))

    # as fit, the positions whose pose takes up coma are adjusted with the campaign's mode
    # variance; their starts (from the sample) show it, so they are streamed once, after the
    # others have given the variance, instead of streamed twice
    done = run(groups, defer=True)
    deferred = [p for p in groups if done[p].get("deferred")]
    prior = pooled_mode_variance([record_mode_variance(done[p]) for p in groups])
    if deferred:
        done.update(run({p: groups[p] for p in deferred}, prior,
                        " (coma prior)" if prior is not None else " (deferred)"))
    recs = [done[p] for p in groups]
    return {"schema": "hartrao-stream-campaign/1", "campaign": root, "positions": recs,
            "scans": [s for r in recs for s in r["scans"]],
            "seconds": time.perf_counter() - t0, "rows_per_chunk": rows_per_chunk,
            "workers": None if client is None else len(client.scheduler_info()["workers"])}


__all__ = ["stream_fit_position", "stream_fit_positions"]
