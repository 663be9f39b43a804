"""Scale-out on Dask distributed: per-scan work on workers, small normal matrices back.

Every scan is read, preprocessed and adjusted on a worker (:func:`fit_dask`); what travels back
to the client is a summary of a few kilobytes (estimates, covariance, the ``fit.json`` record) --
the points and residuals stay on the worker, which writes the residual table itself when the
output directory is shared. The joint adjustment (:mod:`._joint`) runs its Schur-complement
iteration on the client over the same worker-resident scans (:class:`DaskBackend`): per
iteration the workers return their normal equations (9 x 9) and apply the step to their
residuals.

Workers import JAX themselves and switch on float64 and the persistent compilation cache
(``JaxWorkerPlugin``, built on first use: ``distributed`` loads only for the Dask commands); a
:class:`~distributed.LocalCluster` is started with one thread per worker process and XLA
limited to one intra-op thread, so ``n`` workers use ``n`` cores.

Two things made a worker 3.5 times slower per scan than the in-process fit, both fixed here:

* every scan has its own number of rows, so every scan compiled its own Gauss-Helmert program
  (two: with and without start residuals), ~4 s of a ~5 s scan; a worker now pads each scan to
  a bucket size (:func:`._fit.fit_scan` pads): one compilation per worker for a campaign;
* Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_`` set, which switches off glibc's
  dynamic mmap threshold: every large NumPy/JAX buffer became a fresh ``mmap`` with its page
  faults, tripling the CPU time of the preprocessing and bookkeeping (:func:`_pre_spawn_environ`).

North alignment of zenith scans needs the mount heading from the tilted scans: as in
:func:`._fit.fit_campaign`, tilted scans are fitted first (in parallel), then the near-zenith
ones with the heading hint. The result equals the in-process fit.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._config import (
    enable_compilation_cache,
    enable_x64,
    keep_freed_environment,
    release_compiled_programs,
    set_blas_threads,
    set_xla_flags,
)
from ..campaign._campaign import load_campaign, read_scan
from ..campaign._safeio import OutputDir
from ..geometry._geometry import pointing_gravity
from ..model._model import parse_model
from ..preprocess._preprocess import preprocess_keep
from ._align import MIN_TILT_RAD, Alignment, mean_heading, scan_heading
from ._fit import fit_position, fit_scan, fits_resume_budget, sigma_vector
from ._joint import (
    DEFAULT_SHARED,
    JointFit,
    ScanProblem,
    bucket_size,
    check_shared,
    group_of,
    joint_json,
    joint_scan_fit,
    schur_iterate,
)
from ._position_record import position_record
from ._records import FIT_SCHEMA, scan_record, write_residuals
from ._results import CampaignFit, ScanFit
from ._surface_effect import (
    positions_for_campaign_prior,
    record_mode_variance,
    takes_campaign_prior,
)

log = logging.getLogger("hartrao_jax")

WORKER_ENV = {
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false",
    "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
    "JAX_ENABLE_X64": "1", "JAX_PLATFORMS": "cpu",
    # one part per pass in the random-effect adjustment (solver.mixed_threads): a worker is
    # one core, the workers together use the machine
    "HARTRAO_JAX_THREADS": "1",
}
MALLOC_VAR = "MALLOC_TRIM_THRESHOLD_"  # see _pre_spawn_environ


# --------------------------------------------------------------------------------------------
# Cluster
# --------------------------------------------------------------------------------------------


def worker_setup() -> None:
    """Runs in every worker: float64, the persistent compilation cache and one BLAS thread
    (the worker's libraries are loaded before this runs: their number is set, not only the
    environment's). ``$XLA_FLAGS`` gets the worker's options it does not name yet: importing
    the package to run this has already added its own there (:func:`.._config.set_xla_flags`)."""
    for k, v in WORKER_ENV.items():
        if k == "XLA_FLAGS":
            set_xla_flags(v.split())
        else:
            os.environ.setdefault(k, v)

    set_blas_threads()
    enable_x64()
    try:
        enable_compilation_cache()
    except OSError:  # read-only home on a remote worker: compile every time
        pass


def worker_campaign(root: str):
    """On a worker (or in-process): :func:`worker_setup`, then the campaign at ``root``."""
    worker_setup()
    return load_campaign(root)


def _plugin_class():
    """The worker plugin class, built on first use: ``distributed`` (optional, heavy) is
    imported only when a Dask command runs, never by ``import hartrao_jax``."""
    global _JaxWorkerPlugin
    if _JaxWorkerPlugin is None:
        from distributed.diagnostics.plugin import WorkerPlugin

        class JaxWorkerPlugin(WorkerPlugin):  # type: ignore[misc]
            """Imports hartrao_jax in each worker (float64, compilation cache) before any task."""

            name = "hartrao-jax"

            def setup(self, worker):  # noqa: D401
                worker_setup()

        JaxWorkerPlugin.__module__ = __name__
        JaxWorkerPlugin.__qualname__ = "JaxWorkerPlugin"  # pickled by reference (__getattr__)
        _JaxWorkerPlugin = JaxWorkerPlugin
    return _JaxWorkerPlugin


_JaxWorkerPlugin = None


def __getattr__(name: str):
    if name == "JaxWorkerPlugin":
        return _plugin_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def start_client(scheduler: str | None = None, *, n_workers: int = 2, threads_per_worker: int = 1,
                 memory_limit: str | float | None = "auto", keep_freed: bool = False):
    """A Dask client: to ``scheduler`` (address) or to a new local cluster of processes.

    ``keep_freed``: the local cluster's workers keep freed memory for reuse from their start
    (:func:`.._config.keep_freed_environment`; ``$HARTRAO_JAX_KEEP_FREED_MEMORY=0`` turns it
    off). A worker's task thread otherwise has its own glibc heap of at most 64 MiB, so every
    larger block of a streamed position's chunks is a fresh memory map, faulted in page by
    page on every chunk. For streamed work only: its footprint is bounded (1.6 GiB for a
    full-resolution position), so the memory a worker keeps is too, where an in-memory
    position's peak would stay with it. Returns ``(client, cluster)``; ``cluster`` is None
    for an existing scheduler. Close both when done (:func:`close_client`).
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError as e:  # pragma: no cover
        raise ImportError("the Dask commands need dask[distributed]: pip install "
                          "'hartrao-jax[dask]'") from e
    _quiet()
    cluster = None
    if scheduler:
        client = Client(scheduler)
    else:
        import dask

        pre = _pre_spawn_environ()
        if keep_freed:
            # glibc reads them when the process starts: only the nanny's pre-spawn environment
            # (set in this process's environment before each spawn) comes early enough
            pre.update(keep_freed_environment())
        saved = {k: os.environ.get(k) for k in pre}
        try:
            with dask.config.set({"distributed.nanny.pre-spawn-environ": pre}):
                cluster = LocalCluster(n_workers=n_workers, threads_per_worker=threads_per_worker,
                                       processes=True, env=dict(WORKER_ENV),
                                       dashboard_address=None, memory_limit=memory_limit,
                                       silence_logs=logging.ERROR)
        finally:  # this process's own environment as it was
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        client = Client(cluster)
    client.register_plugin(_plugin_class()())
    return client, cluster


def _pre_spawn_environ() -> dict:
    """Dask's pre-spawn environment of worker processes without ``MALLOC_TRIM_THRESHOLD_``.

    Dask's nanny sets ``MALLOC_TRIM_THRESHOLD_=65536`` in every worker process (and in the
    process that starts them, before each spawn). Setting any glibc malloc tunable switches
    off glibc's dynamic mmap threshold: every array above 128 KiB is then a fresh ``mmap``
    and its pages are faulted in again on every allocation. The preprocessing and the
    per-scan bookkeeping allocate many such arrays (NumPy and JAX host buffers): measured on
    a 20k-row scan, 1.5 s CPU per scan in-process against 4.8 s in a worker, 2.7 s of it
    system time. Without the variable the workers allocate like the
    in-process fit. A leftover value from an earlier cluster in this process (the nanny
    writes it into ``os.environ``) is removed as well, as the workers inherit it.
    """
    import dask

    pre = dict(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    trim = pre.pop(MALLOC_VAR, None)
    if trim is not None and os.environ.get(MALLOC_VAR) == str(trim):
        del os.environ[MALLOC_VAR]
    return pre


def _quiet() -> None:
    """Dask's own INFO messages (scheduler start/stop) are not the user's business."""
    for name in list(logging.root.manager.loggerDict):
        if name.startswith("distributed"):
            logging.getLogger(name).setLevel(logging.WARNING)
    logging.getLogger("distributed").setLevel(logging.WARNING)


def close_client(client, cluster) -> None:
    client.close()
    if cluster is not None:
        cluster.close()


# --------------------------------------------------------------------------------------------
# Worker tasks (module-level functions: pickled by reference)
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _campaign(root: str):
    return load_campaign(root)


@dataclass
class ScanSummary:
    """What a worker sends back after fitting a scan (small)."""

    id: str
    names: tuple[str, ...]
    x: np.ndarray
    cov: np.ndarray
    sigma0: float
    record: dict
    alignment_source: str
    heading_rad: float | None
    gravity: np.ndarray
    elevation_deg: float
    n_points: int
    seconds: float
    worker: str = ""
    extra: dict = field(default_factory=dict)


def task_fit_scan(root: str, scan_id: str, model, fixed: dict | None, robust_k: float | None,
                  preprocess: bool, heading_hint_rad: float | None):
    """Worker: read, preprocess and fit one scan; the :class:`ScanFit` stays on the worker."""

    worker_setup()

    release_compiled_programs()  # every scan's point count compiles programs of its own
    t0 = time.perf_counter()
    camp = _campaign(root)
    meta = camp.scan(scan_id)
    data = read_scan(camp, meta)
    keep_fn = preprocess_keep(preprocess, camp)
    keep = keep_fn(meta, data) if keep_fn is not None else None
    fit = fit_scan(camp, meta, model, data=data, keep=keep, fixed=fixed,
                   robust_k=robust_k, heading_hint_rad=heading_hint_rad)  # padded rows
    fit.notes = list(fit.notes)
    fit._seconds = time.perf_counter() - t0  # type: ignore[attr-defined]
    return fit


#: Continuations of positions that take the campaign's mode variance, kept by the worker
#: that adjusted them (``fit_position(keep_resume=True)``), by (campaign root, position).
_RESUMES: dict[tuple[str, str], tuple] = {}


def held_resume_points() -> int:
    """Points whose arrays this process holds for :func:`task_fit_position`'s continuations."""
    return sum(n for _, n in _RESUMES.values())


def drop_resumes() -> int:
    """Worker: forget every held continuation (after a campaign's second round); returns how
    many there were."""
    n = len(_RESUMES)
    _RESUMES.clear()
    return n


def task_fit_position(root: str, scan_ids: Sequence[str], model, fixed: dict | None,
                      robust_k: float | None, preprocess: bool, heading_hint_rad: float | None,
                      out_dir: str | None, mode_prior_m2: float | None = None,
                      resume: bool = False):
    """Worker: read, preprocess and adjust the scans of one position together (two faces, the
    surface a random effect; ``mode_prior_m2`` as :func:`._fit.fit_position`); returns the
    scans' summaries and the position's record.

    A position that would take the campaign's mode variance keeps its continuation here
    (:func:`._fit.fits_resume_budget`, per worker), and ``resume=True`` (with
    ``mode_prior_m2``) adjusts it from there instead of from its points; where this worker
    holds none (another worker ran it, or it restarted), from its points."""

    worker_setup()

    release_compiled_programs()  # every scan's point count compiles programs of its own
    t0 = time.perf_counter()
    camp = _campaign(root)
    metas = [camp.scan(i) for i in scan_ids]
    held = _RESUMES.pop((root, metas[0].position), None) if resume else None
    if held is not None:
        pf = held[0](mode_prior_m2)
    else:
        pf = fit_position(camp, metas, model, keep=preprocess_keep(preprocess, camp),
                          fixed=fixed, robust_k=robust_k, heading_hint_rad=heading_hint_rad,
                          mode_prior_m2=mode_prior_m2, keep_resume=mode_prior_m2 is None)
        if fits_resume_budget(held_resume_points(), pf):
            _RESUMES[(root, metas[0].position)] = (pf.resume, pf.n_points)
        pf.resume = None
    seconds = time.perf_counter() - t0
    out = []
    for s in pf.scans:
        s._seconds = seconds / len(pf.scans)  # type: ignore[attr-defined]
        out.append(task_summary(s, out_dir, held=pf.held))
    return out, position_record(pf)


def task_summary(fit, out_dir: str | None = None, held=None) -> ScanSummary:
    """Worker: the small summary of a fitted scan (and its residual table, if ``out_dir``)."""
    from distributed import get_worker


    if out_dir:
        (Path(out_dir) / "residuals").mkdir(parents=True, exist_ok=True)
        write_residuals(Path(out_dir) / "residuals" / f"{fit.meta.id}.parquet", fit)
    heading = scan_heading(fit)
    try:
        wname = get_worker().address
    except ValueError:
        wname = "local"
    return ScanSummary(fit.meta.id, tuple(fit.names), np.asarray(fit.x), np.asarray(fit.cov),
                       float(fit.sigma0), scan_record(fit, held), fit.alignment.source, heading,
                       np.asarray(fit.gravity), float(fit.elevation_deg), int(fit.n_points),
                       float(getattr(fit, "_seconds", math.nan)), wname)


def task_problem(fit, sigma_l, n_pad: int | None):
    """Worker: the joint-iteration arrays of a fitted scan (stay on the worker)."""

    worker_setup()
    return ScanProblem.from_fit(fit, sigma_l, n_pad or bucket_size(len(fit.data)))


def task_normals(problem, x):
    return problem.normals(np.asarray(x))


def task_update(problem, x, dx):
    return problem.update(np.asarray(x), np.asarray(dx))


def task_omega(problem) -> float:
    return problem.omega


def task_finish_joint(root, fit, problem, x, cov, N, sigma0, n_used, omega, u_object, iterations,
                      converged, hint, out_dir):
    """Worker: the joint ScanFit of one scan, its fit.json record and residual table."""

    camp = _campaign(root)
    jf = joint_scan_fit(camp, fit, x, cov, N, sigma0, problem.v[: problem.n],
                        problem.e[: problem.n], n_used, omega, u_object, iterations, converged,
                        hint)
    jf._seconds = 0.0  # type: ignore[attr-defined]
    return task_summary(jf, out_dir)


# --------------------------------------------------------------------------------------------
# Client side
# --------------------------------------------------------------------------------------------


def thin_scan_fit(summary: ScanSummary, meta):
    """A ScanFit without point arrays (enough for positions, precision and correlations)."""

    e = np.zeros(0)
    return ScanFit(meta=meta, model=None, names=summary.names, x=summary.x, cov=summary.cov,
                   sigma0=summary.sigma0, iterations=summary.record.get("iterations", 0),
                   converged=summary.record.get("converged", True), n_points=summary.n_points,
                   n_rejected=summary.record.get("n_rejected", 0),
                   n_window=summary.record.get("n_outside_window", 0),
                   alignment=Alignment(summary.record.get("kappa_rad", 0.0),
                                       summary.alignment_source),
                   init=None, data=None, used=e.astype(bool), v=e, normalized=e, deviation_m=e,
                   X_tel=np.zeros((0, 3)), gravity=summary.gravity,
                   elevation_deg=summary.elevation_deg)


def fit_document(campaign, names, summaries: Sequence[ScanSummary],
                 positions: Sequence[dict] | None = None) -> dict:
    """``fit.json`` from worker summaries, in the form :func:`._records.fit_json` gives
    (``positions``: the records of two-face position adjustments; None: per-cycle fits)."""

    thin = [thin_scan_fit(s, campaign.scan(s.id)) for s in summaries]
    doc = {"schema": FIT_SCHEMA, "model": list(names),
           "adjustment": "per cycle" if positions is None else "two-face, surface random effect"}
    doc.update({"campaign": str(campaign.root), "scans": [s.record for s in summaries],
                "positions": list(positions) if positions is not None
                else CampaignFit(campaign, tuple(names), thin).positions()})
    return doc


@dataclass
class DaskFit:
    """Result of :func:`fit_dask`: the ``fit.json`` document and the worker summaries."""

    document: dict
    summaries: list[ScanSummary]
    seconds: float
    n_workers: int
    joint: object | None = None  # a JointFit with thin scans when joint=True
    fit_futures: list | None = None


class DaskBackend:
    """:class:`._joint.JointBackend` over worker-resident scan problems (futures)."""

    def __init__(self, client, problem_futures):
        self.client = client
        self.futures = list(problem_futures)

    def normals(self, xs):
        futs = self.client.map(task_normals, self.futures, [np.asarray(x) for x in xs], pure=False)
        return self.client.gather(futs)

    def update(self, xs, dxs):
        new = self.client.map(task_update, self.futures, [np.asarray(x) for x in xs],
                              [np.asarray(d) for d in dxs], pure=False)
        self.futures = new
        return self.client.gather(self.client.map(task_omega, new, pure=False))


def _tilt(meta, campaign) -> float:
    g = pointing_gravity(meta, campaign.telescope, campaign.site)
    return float(np.arccos(np.clip(-g[2], -1, 1)))


def fit_dask(
    campaign,
    model="extended",
    *,
    client=None,
    scheduler: str | None = None,
    n_workers: int = 2,
    scans: Sequence[str] | None = None,
    fixed: dict | None = None,
    robust_k: float | None = 4.0,
    preprocess: bool = True,
    out_dir=None,
    joint: bool = False,
    shared: Sequence[str] = DEFAULT_SHARED,
    group: str = "night",
    keep_futures: bool = False,
    per_cycle: bool = False,
) -> DaskFit:
    """Fit the scans of ``campaign`` on Dask workers; with ``out_dir`` write ``fit.json`` (and
    the workers write ``residuals/``) as ``hartrao-jax fit`` does.

    ``client``: an existing client; else one to ``scheduler`` or to a new
    ``LocalCluster(n_workers, threads_per_worker=1, processes=True)`` (closed at the end).
    ``joint=True``: then the joint adjustment (shared calibration per ``group``) with the
    Schur-complement iteration over the worker-resident scans. Default: one task per position,
    both faces adjusted together with the surface as a random effect (as ``fit``);
    ``per_cycle=True``: one task per scan, each cycle alone.
    """


    t0 = time.perf_counter()
    own = client is None
    cluster = None
    if own:
        client, cluster = start_client(scheduler, n_workers=n_workers)
    try:
        root = str(Path(campaign.root).resolve())
        metas = [campaign.scan(s) for s in scans] if scans else list(campaign.scans)
        order = sorted(metas, key=lambda m: -_tilt(m, campaign))
        tilted = [m for m in order if _tilt(m, campaign) >= MIN_TILT_RAD]
        flat = [m for m in order if _tilt(m, campaign) < MIN_TILT_RAD]
        outd = str(Path(out_dir).resolve()) if out_dir and not joint else None
        od = None
        if out_dir:
            # workers write the residual tables in place (each atomically): no fit.json
            # until the new one lists them
            od = OutputDir(out_dir, "fit.json")
            od.invalidate()
        fits: dict[str, object] = {}
        summaries: dict[str, ScanSummary] = {}
        if not joint and not per_cycle:  # one task per position: both faces together
            groups: dict[str, list] = {}
            for m in order:
                groups.setdefault(m.position, []).append(m)
            records: dict[str, dict] = {}

            def run_positions(names_, hint, prior=None):
                # with the prior: on the worker that holds the position's continuation
                fut = [client.submit(
                    task_fit_position, root, [m.id for m in groups[p]], model, fixed,
                    robust_k, preprocess, hint, outd, prior, prior is not None, pure=False,
                    **({"workers": [summaries[groups[p][0].id].worker],
                        "allow_other_workers": True} if prior is not None else {}))
                    for p in names_]
                for p, (summ, rec) in zip(names_, client.gather(fut)):
                    records[p] = rec
                    for s in summ:
                        summaries[s.id] = s

            first = [p for p in groups if _tilt(groups[p][0], campaign) >= MIN_TILT_RAD]
            run_positions(first, None)
            hs = [summaries[m.id].heading_rad for p in first for m in groups[p][:1]
                  if summaries[m.id].alignment_source == "gravity"]
            hint = mean_heading(hs)
            rest = [p for p in groups if p not in first]
            if rest:
                run_positions(rest, hint)
            # as fit_campaign: the positions whose pose takes up coma, with the modes carried
            # at the variance of the positions that show them
            prior, redo = positions_for_campaign_prior(
                {p: record_mode_variance(records[p]) for p in groups},
                {p: takes_campaign_prior(records[p].get("surface_mode_confounding"),
                                         records[p].get("surface_modes")) for p in groups})
            for part, h in (([p for p in redo if p in first], None),
                            ([p for p in redo if p not in first], hint)):
                if part:  # each with the heading hint of its first adjustment
                    run_positions(part, h, prior)
            client.run(drop_resumes)  # the continuations not needed
            ordered = [summaries[m.id] for m in metas]
            pos_order = list(dict.fromkeys(m.position for m in metas))
            return _finish(client, od, out_dir, metas, ordered,
                           fit_document(campaign, parse_model(model), ordered,
                                        [records[p] for p in pos_order]), t0, None, None)

        def run(batch, hint):
            fut = client.map(task_fit_scan, [root] * len(batch), [m.id for m in batch],
                             [model] * len(batch), [fixed] * len(batch),
                             [robust_k] * len(batch), [preprocess] * len(batch),
                             [hint] * len(batch), pure=False)
            summ = client.gather(client.map(task_summary, fut, [outd] * len(batch), pure=False))
            for m, f, s in zip(batch, fut, summ):
                fits[m.id], summaries[m.id] = f, s

        run(tilted, None)
        hs = [summaries[m.id].heading_rad for m in tilted
              if summaries[m.id].alignment_source == "gravity"]
        hint = mean_heading(hs)
        if flat:
            run(flat, hint)
        names = parse_model(model)
        ordered = [summaries[m.id] for m in metas]
        doc = fit_document(campaign, names, ordered)
        jf = None
        if joint:
            jf, doc = _joint_on_workers(client, root, campaign, metas, fits, ordered, names,
                                        shared, group, sigma_vector(campaign), hint, out_dir)
        return _finish(client, od, out_dir, metas, ordered, doc, t0, jf,
                       [fits[m.id] for m in metas] if keep_futures else None)
    finally:
        if own:
            close_client(client, cluster)


def _finish(client, od, out_dir, metas, ordered, doc, t0, jf, futures) -> DaskFit:
    """Commit the output directory (the residual tables the workers wrote, ``fit.json`` last)
    and the :class:`DaskFit`."""

    if od is not None:
        for m in metas:
            if (Path(out_dir) / "residuals" / f"{m.id}.parquet").is_file():
                od.adopt(f"residuals/{m.id}.parquet")
        od.commit(doc)
    n_w = len(client.scheduler_info().get("workers", {}))
    return DaskFit(doc, ordered, time.perf_counter() - t0, n_w, jf, futures)


def _joint_on_workers(client, root, campaign, metas, fits, summaries, names, shared, group, sigma_l,
                      hint, out_dir):
    shared = check_shared(names, shared)
    # rows of each scan = used + rejected + outside the window: one padded shape for all
    n_pad = max(bucket_size(s.n_points + s.record.get("n_rejected", 0)
                            + s.record.get("n_outside_window", 0)) for s in summaries)
    futs = [fits[m.id] for m in metas]
    probs = client.map(task_problem, futs, [sigma_l] * len(futs), [n_pad] * len(futs), pure=False)
    backend = DaskBackend(client, probs)
    groups = [group_of(m, group) for m in metas]
    sol = schur_iterate(backend, names, shared, groups, [s.x for s in summaries])
    outd = str(Path(out_dir).resolve()) if out_dir else None
    jsum = client.gather(client.map(
        task_finish_joint, [root] * len(futs), futs, backend.futures, sol.xs,
        [sol.cov(i) for i in range(len(futs))],
        sol.N, [sol.sigma0] * len(futs), sol.n_used, sol.omega, [len(sol.o_idx)] * len(futs),
        [sol.iterations] * len(futs), [sol.converged] * len(futs), [hint] * len(futs),
        [outd] * len(futs), pure=False))
    thin_joint = [thin_scan_fit(s, m) for s, m in zip(jsum, metas)]
    thin_start = [thin_scan_fit(s, m) for s, m in zip(summaries, metas)]
    gmap: dict[str, list[str]] = {}
    for m, g in zip(metas, groups):
        gmap.setdefault(g, []).append(m.id)
    jf = JointFit(campaign, tuple(names), shared, group, gmap, thin_joint,
                  CampaignFit(campaign, tuple(names), thin_start), sol)
    doc = joint_json(jf, base=fit_document(campaign, names, jsum))
    return jf, doc


__all__ = ["DaskBackend", "DaskFit", "ScanSummary", "WORKER_ENV",
           "close_client", "fit_dask", "fit_document", "start_client",
           "thin_scan_fit", "worker_campaign", "worker_setup"]
