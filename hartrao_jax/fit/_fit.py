"""Fit campaigns: per scan initial values, cleaning, rigorous GH adjustment, north alignment.

Everything here is bookkeeping (NumPy) around the differentiable core (:mod:`._ghm`,
:mod:`._model`). Results are plain dataclasses of NumPy arrays; a position's ``positions[]``
record is :func:`._position_record.position_record`, the surface random effect's modes and
variances are in :mod:`._surface_effect`, the files (``fit.json``, schema ``hartrao-fit/1``,
``shared/spec/outputs.md``, and the per-scan residual tables) are written by :mod:`._records`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from .._config import (
    BLOCK_ROWS,
    by_row_blocks,
    lendable_empty,
    on_device,
    release_compiled_programs,
    row_blocks,
    thread_pool,
    usable_cores,
)
from .._programs import cached_jit
from ..campaign._campaign import Campaign, ScanData, ScanMeta, read_scan
from ..campaign._campaign import _concat as concat_scans
from ..geometry._geometry import (
    panel_cells,
    panel_layout,
    paraboloid_deviation,
    pointing_elevation_deg,
    pointing_gravity,
    rot_z,
    square_cells,
    zernike_columns,
)
from ..model._model import (
    N_CONSTS,
    ZERNIKE_PREFIX,
    ParaboloidModel,
    make_model,
    parse_model,
)
from ..preprocess._initial import (
    InitialValues,
    choose_initial_values,
    geometry_window,
)
from ..preprocess._types import KeepMask
from ..solver._ghm import (
    GHResult,
    bucket_size,
    gauss_helmert,
    gauss_helmert_batch,
    host_result,
    robust_gauss_helmert,
)
from ..solver._kernel import materialize_trig
from ..solver._mixed import gauss_helmert_mixed
from ._align import MIN_TILT_RAD, mean_heading, north_alignment, scan_heading
from ._identify import (
    PER_CYCLE_UNDETERMINED,
    Held,
    confounding_note,
    hold_parameters,
    mode_confounding,
    mode_prior,
    mode_prior_note,
    one_face_holds,
    undetermined_parameters,
    unidentifiable_calibration,
)
from ._projection import hit_cells, hit_points, hit_points_and_residuals, reject_beyond
from ._results import (
    CampaignFit,
    MixedState,
    PositionFit,
    ScanFit,
    SurfaceEffect,
    _faces,
)
from ._surface_effect import (
    _CELL_VAR0,
    _MODE_VAR0,
    SURFACE_MODE_GROUPS,
    _absent_modes,
    mode_variance_parts,
    positions_for_campaign_prior,
    surface_components,
    white_sigmas,
)

log = logging.getLogger("hartrao_jax")



# --------------------------------------------------------------------------------------------


def scan_arrays(*datas: ScanData, n_pad: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Observations ``l = (r, phi, theta)`` (n, 3) and constants ``c = (time_s, 0)`` (n, 2) of
    the rows of ``datas`` one after the other; up to ``n_pad`` rows (the padding of a size
    bucket, given weight 0 by the caller) follow as copies of the first row's observations
    with constants 0. Filled in place: no concatenated or padded table is made on the way;
    aligned for the device (``lendable_empty``: the random effect reads them without a copy)."""
    n = sum(len(d) for d in datas)
    n_pad = max(n, n_pad or 0)
    l = lendable_empty((n_pad, 3), np.float64)
    c = lendable_empty((n_pad, N_CONSTS), np.float64)
    c[:] = 0.0
    at = 0
    for d in datas:
        _put_rows(l, c, slice(at, at + len(d)), d.range_m, d.phi_rad, d.theta_rad, d.time_s)
        at += len(d)
    l[n:] = l[0] if n else 0.0
    return l, c


def _put_rows(l, c, rows, range_m, phi_rad, theta_rad, time_s) -> None:
    """Rows ``rows`` of the tables ``l`` and ``c`` (constants other than the time left as they
    are) from a scan's columns: the layout of :func:`scan_arrays`."""
    for j, col in enumerate((range_m, phi_rad, theta_rad)):
        l[rows, j] = col
    c[rows, 0] = time_s


def columns_in(datas: Sequence[ScanData], l: np.ndarray, c: np.ndarray) -> list[ScanData]:
    """``datas`` with their observation and time columns the rows of :func:`scan_arrays`'
    ``l`` and ``c`` (views: the same values, not a second copy of them; 32 B per point). The
    tables must not be written to while the scans are in use."""
    out, at = [], 0
    for d in datas:
        rows = slice(at, at + len(d))
        at += len(d)
        out.append(dataclasses.replace(d, range_m=l[rows, 0], phi_rad=l[rows, 1],
                                       theta_rad=l[rows, 2], time_s=c[rows, 0]))
    return out


def sigma_vector(campaign: Campaign) -> np.ndarray:
    s = campaign.scanner
    return np.array([s.sigma_range_m, s.sigma_angle_rad, s.sigma_angle_rad])


def _x0(names: Sequence[str], init: InitialValues, fixed: dict[str, float]) -> np.ndarray:
    return np.array([init.x.get(n, fixed.get(n, 0.0)) for n in names], dtype=float)


def prepare_scan(
    campaign: Campaign, meta: ScanMeta, data: ScanData | None = None, *, window_m: float = 0.10,
    keep: np.ndarray | None = None, seed: int = 0,
):
    """Read a scan, find initial values and the points inside the geometry window.

    Returns ``(data, gravity, init, window)`` where ``window`` marks points within
    ``window_m`` (vertical) of the initial paraboloid (and inside ``keep`` if given). A
    ``keep`` mask from the preprocessing (``preprocess.KeepMask``) brings its initial values
    (the same estimator on a sample of the same scan): they are used instead of a new search.
    """
    data = read_scan(campaign, meta) if data is None else data
    g = pointing_gravity(meta, campaign.telescope, campaign.site)
    init = getattr(keep, "init", None)
    if init is None:
        init = choose_initial_values(campaign, meta, data, g, seed=seed)
    window = geometry_window(data.range_m, data.phi_rad, data.theta_rad, init.x, window_m)
    if keep is not None:
        window &= keep
    return data, g, init, window


def fit_scan(
    campaign: Campaign,
    meta: ScanMeta,
    model: str | Iterable[str] = "extended",
    *,
    data: ScanData | None = None,
    keep: np.ndarray | None = None,
    fixed: dict[str, float] | None = None,
    robust_k: float | None = 4.0,
    window_m: float = 0.10,
    heading_hint_rad: float | None = None,
    max_iter: int = 30,
    pad: bool = True,
) -> ScanFit:
    """Adjust one scan with the given model (names, ``"simplified"`` or ``"extended"``).

    ``keep``: optional boolean mask of points to consider (e.g. from preprocessing).
    ``robust_k``: reject points beyond ``k`` a posteriori sigmas (None: no rejection).
    ``pad``: run the adjustment on the rows padded to :func:`._joint.bucket_size` (copies of
    the first row at weight 0, which enter no sum): scans of similar size then share one
    compiled program instead of compiling one each (compilation was most of the time per scan
    of a campaign). The estimates equal the unpadded ones to round-off.
    """

    fixed = dict(fixed or {})
    held = one_face_holds(parse_names(model), fixed) if meta.cycle == 0 else {}
    fixed.update({n: h.value for n, h in held.items()})
    data, g, init, window = prepare_scan(campaign, meta, data, window_m=window_m, keep=keep)
    mdl = make_model(model, fixed, aperture_radius_m=campaign.telescope.diameter_m / 2)
    n = len(data)
    n_pad = bucket_size(n) if pad else n
    pdata = data.padded(n_pad)  # one size bucket, one compiled program
    l, c = scan_arrays(data, n_pad=n_pad)
    wpad = np.zeros(n_pad, bool)
    wpad[:n] = window
    w = wpad.astype(float)
    x0 = _x0(mdl.free, init, fixed)
    sig = sigma_vector(campaign)
    if robust_k is None:
        res = gauss_helmert(mdl, l, x0, sig, c, w, v0=np.zeros_like(l), max_iter=max_iter)
    else:
        res = robust_gauss_helmert(mdl, l, x0, sig, c, w, k=robust_k, max_iter=max_iter)
    fit = finish_scan_fit(campaign, meta, mdl, pdata, res, g, init, wpad,
                          heading_hint_rad=heading_hint_rad)
    fit.held = held
    fit.undetermined = undetermined_parameters(fit.cov, fit.names, fit.elevation_deg,
                                             then=PER_CYCLE_UNDETERMINED)
    if n_pad == n:
        return fit
    # back to the scan's own rows (the padding rows are unused and outside the window)
    fit.data = data
    for k in ("used", "v", "normalized", "deviation_m", "X_tel"):
        setattr(fit, k, np.asarray(getattr(fit, k))[:n])
    fit.n_window -= n_pad - n
    return fit


@cached_jit
def _fitted_points_jit(mdl: ParaboloidModel, l, x, c, f, on):
    # each distinct sin/cos evaluated once (materialize_trig): 6.3e6 points 0.34 -> 0.20 s
    point = materialize_trig(mdl.telescope_point, on)
    X = jax.vmap(lambda q, ci: point(q, x, ci))(l, c)
    return X, paraboloid_deviation(X, f)


def _fitted_points(mdl: ParaboloidModel, data: ScanData, x, f: float):
    """The observations of ``data`` in the fitted paraboloid's frame (m) and their normal
    deviations from it (m): one compiled program per size bucket (:func:`bucket_size`;
    eagerly, each of the model's operations was a pass of its own over the points, 2.4x the
    time). The observations are made at the bucket's size (:func:`scan_arrays`), not copied
    with a padding on the way to the device: a 6.3e6-point scan 0.51 -> 0.33 s at the first
    call in a process (fresh pages), 0.35 -> 0.33 s after. A scan of more than
    :data:`BLOCK_ROWS` points is taken a block at a time (:func:`by_row_blocks`), each block's
    observations made from the scan's columns (not a copy of the whole scan's: 240 MiB per
    6.3e6 points)."""
    n = len(data)
    x, f, on = jnp.asarray(x), on_device(f, np.float64), on_device(True, bool)
    if n <= BLOCK_ROWS:
        l, c = scan_arrays(data, n_pad=bucket_size(n))
        X, dev = _fitted_points_jit(mdl, l, x, c, f, on)
        return np.asarray(X)[:n], np.asarray(dev)[:n]

    def block(*cols):  # a block's l and c (as scan_arrays'), not the whole scan's
        l, c = np.empty((len(cols[0]), 3)), np.zeros((len(cols[0]), N_CONSTS))
        _put_rows(l, c, slice(None), *cols)
        return _fitted_points_jit(mdl, l, x, c, f, on)

    return by_row_blocks(block, (data.range_m, data.phi_rad, data.theta_rad, data.time_s))


def scan_result(*, x, cov, N, sigma0, v, normalized, weights, redundancy, iterations,
                converged) -> GHResult:
    """One scan's share of a larger adjustment (a position's, a joint one) as a
    :class:`GHResult` for :func:`finish_scan_fit`; its misclosures are not kept (zero). The
    small fields are put on the device by :func:`..solver._ghm.host_result` (``jnp.asarray``
    and ``jnp.zeros`` compiled a program for every new length: 10-25 ms each, 36 per 12-scan
    fit of a new recording); the per-point arrays stay the host's (NumPy, which is all
    :func:`finish_scan_fit` reads): a device copy of each took 240 MiB per 6.3e6-point scan
    at the end of a large position, beside the originals."""
    return host_result(x=x, cov=cov, N=N, sigma0=sigma0, v=v,
                       misclosure=np.broadcast_to(0.0, (len(v),)), normalized=normalized,
                       weights=np.asarray(weights, float), redundancy=redundancy,
                       iterations=iterations, converged=converged,
                       keep_host=("v", "misclosure", "normalized", "weights"))


def finish_scan_fit(
    campaign: Campaign, meta: ScanMeta, mdl: ParaboloidModel, data: ScanData, res: GHResult,
    g: np.ndarray, init: InitialValues, window: np.ndarray, *,
    heading_hint_rad: float | None = None,
) -> ScanFit:
    """Turn a GH result into a :class:`ScanFit`: alignment, deviations, bookkeeping."""

    x = np.asarray(res.x)
    names = mdl.free
    used = np.asarray(res.weights) > 0
    p = mdl.values(x)
    X_fit, dev = _fitted_points(mdl, data, res.x, p["f"])
    tel = campaign.telescope
    rim = tel.diameter_m / 2
    align = north_alignment(
        p["rx"], p["ry"], g, X_fit, used=used, leg_azimuths_deg=tel.quadrupod_azimuths_deg,
        rho_range_m=(max(tel.cone_radius_m, 0.25 * rim) , 0.92 * rim),
        heading_hint_rad=heading_hint_rad,
    )
    # north-aligned in place where X_fit is the host's own, a block at a time (no second
    # (n, 3) table: 144 MiB per 6.3e6-point scan)
    X_tel = X_fit if X_fit.flags.writeable else np.array(X_fit)
    R = rot_z(align.kappa_rad, np).T
    for rows in row_blocks(len(X_tel)):
        X_tel[rows] = X_tel[rows] @ R
    notes = []
    if not bool(res.converged):
        notes.append(f"not converged after {int(res.iterations)} iterations")
    return ScanFit(
        meta=meta, model=mdl, names=names, x=x, cov=np.asarray(res.cov),
        sigma0=float(res.sigma0), iterations=int(res.iterations), converged=bool(res.converged),
        n_points=int(used.sum()), n_rejected=int(window.sum() - used.sum()),
        n_window=int(len(data) - window.sum()), alignment=align, init=init, data=data, used=used,
        v=np.asarray(res.v), normalized=np.asarray(res.normalized), deviation_m=dev, X_tel=X_tel,
        gravity=np.asarray(g), elevation_deg=pointing_elevation_deg(meta, tel, campaign.site),
        notes=notes,
    )


# --------------------------------------------------------------------------------------------
# Two-face position adjustment with the surface as a random effect
# --------------------------------------------------------------------------------------------

#: Positions with more points than this (both faces, inside the geometry window) start from a
#: seeded sample of :data:`SAMPLE_POINTS`: see :func:`_sample_start`.
SAMPLE_START_POINTS = 4_000_000
#: How the answer depends on the sample (a position of 1.26e7 points, four seeds per size): the
#: seeds' estimates spread by up to 0.084 of their sigmas with 1e6 points, 0.081 with 5e5 and
#: 0.054 with 2.5e5 (panels: medians 0.022, 0.030 and 0.025 of theirs), and the sizes' means
#: differ by 0.041 and 0.054 sigma, within that spread: the start decides the cells'
#: alignment and the rejections at a few hundredths of a sigma whatever its size (a variance
#: of 0.7 % of the sigmas' squares at most). 5e5 points: 0.7 s less than 1e6 (12.3 -> 11.6 s; the
#: streamed position starts from 3e5 per face, :mod:`._stream_position`).
SAMPLE_POINTS = 500_000
#: The most points of positions a process keeps in memory for their adjustment with a
#: campaign's mode variance (``fit_position(keep_resume=True)``; 0.25 kB of arrays per point,
#: measured on a position of 3.6e5 points); beyond, such a position is adjusted again from its
#: points. See :func:`fits_resume_budget`.
RESUME_POINTS = 4_000_000
#: The note of a position adjusted from its continuation (``PositionFit.resume``).
RESUMED_NOTE = ("adjusted with the campaign's mode variance from where its first adjustment "
                "ended (the same points, cells and variances), not from its points again")
#: Scan files of a position (bytes, all faces) up to which its faces are read and preprocessed
#: in parallel threads (about 2.2e7 rows of Parquet; above, one face at a time holds less):
#: the 12-scan profile campaign 10.2 -> 9.1 s; a position of 1.26e7 rows (1.2 GB) 22.5 ->
#: 20.6 s in a fresh process (three runs each), peak resident 9.3-9.6 GiB either way (with
#: one heap for every thread, ``_config.keep_freed_memory``; before it, nothing was gained).
PARALLEL_FACES_BYTES = 2 * 2**30
#: A tilted position of at most this many bytes of scan files is fitted in a thread while the
#: position before it is (``fit_campaign``: two small positions use the cores better than one).
AHEAD_POSITION_BYTES = 256 * 2**20


def file_bytes(campaign: Campaign, metas: Sequence[ScanMeta]) -> int:
    """The size of the scans' files (bytes); larger than any limit where one is unreadable
    (reading it says what is wrong)."""
    try:
        return sum((campaign.root / m.file).stat().st_size for m in metas)
    except OSError:
        return 2**62


def side_by_side(campaign: Campaign, metas: Sequence[ScanMeta]) -> bool:
    """Whether the scans ``metas`` are small enough to be read, prepared and adjusted in
    threads at once (:data:`PARALLEL_FACES_BYTES` of files: a position's faces, a diagnosis'
    scans)."""
    return file_bytes(campaign, metas) <= PARALLEL_FACES_BYTES


def fits_resume_budget(held_points: int, pf: PositionFit) -> bool:
    """Whether ``pf``'s continuation may be kept with ``held_points`` points already held
    (:data:`RESUME_POINTS`): the one rule of ``fit`` and of a ``fit-dask`` worker."""
    return pf.resume is not None and held_points + pf.n_points <= RESUME_POINTS


def _sample_start(campaign: Campaign, metas: Sequence[ScanMeta], model, prepared, *, fixed,
                  robust_k, window_m, heading_hint_rad, max_iter, seed: int = 0
                  ) -> PositionFit | None:
    """The two-face adjustment of a seeded sample of a large position's points, as the start
    of the adjustment of all of them (None: the sample has no surface random effect).

    Why: with the surface a random effect, the sigmas of f, pose and calibration are set by
    the surface, not by the number of points, so :data:`SAMPLE_POINTS` already give the pose,
    the north alignment, the cells, the smooth modes the data show and the variance components
    close to their full-data values. The adjustment of every point then starts there and
    needs two or three passes, and the white robust adjustment of every point (which only
    provides that start) is not made. The same start as the streamed position
    (:mod:`._stream_position`); the sample is drawn among each face's points inside the
    geometry window and the preprocessing's mask, in proportion to their numbers."""
    inside = [np.flatnonzero(p[3]) for p in prepared]
    total = sum(len(i) for i in inside)
    rng = np.random.default_rng(seed)
    datas, masks = [], {}
    for m, p, idx in zip(metas, prepared, inside):
        take = min(len(idx), int(round(SAMPLE_POINTS * len(idx) / max(total, 1))))
        pick = np.sort(rng.choice(idx, size=take, replace=False))
        datas.append(p[0].subset(pick))
        mask = np.ones(take, bool).view(KeepMask)
        mask.init = p[2]  # the full scan's initial values: no new search
        masks[m.id] = mask
    start = fit_position(campaign, metas, model, datas=datas, keep=lambda m, d: masks[m.id],
                         fixed=fixed, robust_k=robust_k, window_m=window_m,
                         heading_hint_rad=heading_hint_rad, max_iter=max_iter, as_start=True)
    return start if start.mixed is not None else None


def _carried_mode_variance(p: PositionFit) -> float | None:
    if p.surface is None or not p.surface.modes:
        return None
    return p.surface.variances.get("modes_m2")


def fit_position(
    campaign: Campaign,
    metas: Sequence[ScanMeta],
    model: str | Iterable[str] = "extended",
    *,
    datas: Sequence[ScanData] | None = None,
    keep: Callable[[ScanMeta, ScanData], np.ndarray] | None = None,
    fixed: dict[str, float] | None = None,
    robust_k: float | None = 4.0,
    window_m: float = 0.10,
    heading_hint_rad: float | None = None,
    surface: bool = True,
    max_iter: int = 30,
    mode_prior_m2: float | None = None,
    keep_resume: bool = False,
    as_start: bool = False,
) -> PositionFit:
    """Adjust the scans of one position together: one pose, one f, one set of calibration.

    1. Initial values and the geometry window per scan; the best-fitting scan's initial values
       start the joint adjustment (both cycles share the scanner set-up).
    2. A robust Gauss-Helmert adjustment of all points (white noise) rejects outliers and gives
       the pose for the north alignment, hence each point's panel (surface cell). A position
       of more than :data:`SAMPLE_START_POINTS` points takes all of that, and the start of
       step 3, from the two-face adjustment of a seeded sample instead (:func:`_sample_start`;
       outliers rejected at that solution by the same rule, :func:`reject_beyond`).
    3. The adjustment with the surface as a random effect (:mod:`._mixed`): panel offsets and
       tilts (and, on a centred reflector, the smooth modes of :data:`SURFACE_MODES` where the
       data show them: :func:`_absent_modes`) with variances estimated from the data; sigmas
       include the surface's blur.
    4. Identifiability: two-face parameters are held on a one-face position; any calibration
       parameter the normal matrix cannot separate (``|correlation| > 0.99``, e.g. x6/x7 near
       the zenith) is held at its fixed/prior value with a note, and the position refitted.

    ``mode_prior_m2``: where the data show none of the smooth modes but the other unknowns take
    one up (coma by the pose, :func:`mode_confounding`), the modes are carried all the same with
    this variance (m^2; the campaign's, :func:`pooled_mode_variance`), so that the sigmas of
    the pose include coma of that size instead of assuming none. ``keep_resume``: a position
    that would take such a variance (none given) keeps ``resume(mode_prior_m2)``, the same
    adjustment with it from where this one ended (its arrays held until then), so that a
    campaign does not adjust it from its points twice.

    ``as_start``: this adjustment is only the start of the adjustment of more points of the
    same position (it adjusts a sample of them, :func:`_sample_start`). Its loop over the
    smooth modes ends at their first verdict: the groups the data do not show are marked not
    carried (``surface.mode_tests``, what the fixed effects take up without them in
    ``surface.mode_confounding``) but are not adjusted away here; the larger adjustment starts
    without them.
    """

    metas = list(metas)
    fixed = dict(fixed or {})
    tel = campaign.telescope
    faces = _faces(metas)
    names = tuple(n for n in parse_names(model) if n not in fixed)
    held: dict[str, Held] = {}
    if faces == 1:
        held.update(one_face_holds(names, fixed))

    def prepare(i):
        m = metas[i]
        data = datas[i] if datas is not None else read_scan(campaign, m)
        k = keep(m, data) if keep is not None else None
        return prepare_scan(campaign, m, data, window_m=window_m, keep=k)

    # the faces read and preprocessed each in its own thread (NumPy releases the GIL in its
    # array loops; the same results in the same order), where they are small enough; a pool
    # of this call's own, whose threads end with it: the process's persistent pool
    # (_config.each_in_threads) kept something of that work while its threads lived, the
    # large position's peak 3.72-3.81 -> 4.10-4.22 GiB (benchmarks/results/profile.md)
    together = datas is not None or side_by_side(campaign, metas)
    workers = min(len(metas), usable_cores()) if together else 1
    with ThreadPoolExecutor(max(1, workers)) as ex:
        prepared = list(ex.map(prepare, range(len(metas))))
    init = max((p[2] for p in prepared), key=lambda c: c.inlier_fraction)
    g = prepared[0][1]
    elevation = pointing_elevation_deg(metas[0], tel, campaign.site)
    sizes = [len(p[0]) for p in prepared]
    n = int(sum(sizes))
    n_pad = bucket_size(n)
    l, c = scan_arrays(*(p[0] for p in prepared), n_pad=n_pad)  # both faces, one table
    # the faces' columns from then on the table's rows (the read ones let go: 32 B per point)
    prepared = [(d,) + p[1:] for d, p in zip(columns_in([p[0] for p in prepared], l, c),
                                              prepared)]
    w = np.concatenate([p[3] for p in prepared] + [np.zeros(n_pad - n, bool)]).astype(float)
    sig = sigma_vector(campaign)
    aperture = tel.diameter_m / 2

    def free_of(extra=()):
        return tuple(n_ for n_ in names if n_ not in held) + tuple(extra)

    def model_of(free, kappa=0.0):
        fx = {**fixed, **{k_: h.value for k_, h in held.items()}}
        return make_model(free, fx, aperture_radius_m=aperture, kappa_rad=kappa,
                          check_separable=False)

    def assemble(notes, *, free, x_pos, cov_pos, weights, v, omega_pt, r_e, sigma0,
                 iterations, converged, normalized, mdl_final, surf, mixed, sigma_white,
                 response) -> PositionFit:
        """4. The position's result and its per-scan views: the shared estimates, each scan's
        own residuals and statistics."""
        n_used = int(np.sum(weights > 0))
        scans, start = [], 0
        for (data, gg, init_s, window), m, size in zip(prepared, metas, sizes):
            sl = slice(start, start + size)
            start += size
            ws = weights[sl]
            n_s = int(np.sum(ws > 0))
            r_s = max(r_e * n_s / max(n_used, 1), 1.0)
            s0 = math.sqrt(float(np.sum(np.where(ws > 0, omega_pt[sl], 0.0))) / r_s)
            gh = scan_result(x=x_pos, cov=cov_pos, N=np.linalg.pinv(cov_pos), sigma0=s0,
                             v=v[sl], normalized=normalized[sl], weights=ws, redundancy=n_s,
                             iterations=iterations, converged=converged)
            sf = finish_scan_fit(campaign, m, mdl_final, data, gh, gg, init_s, window,
                                 heading_hint_rad=heading_hint_rad)
            sf.notes.append("two-face position adjustment" if faces == 2 else
                            "one usable face: adjusted alone")
            scans.append(sf)
        notes = list(notes)
        for h in held.values():
            if h.note not in notes:
                notes.append(h.note)
        return PositionFit(
            position=metas[0].position, scans=scans, names=tuple(free), x=x_pos, cov=cov_pos,
            held=held, faces=faces, sigma0=sigma0, surface=surf, iterations=iterations,
            converged=converged, n_points=n_used, notes=notes, mixed=mixed,
            sigma_white=sigma_white, response=response)
    notes: list[str] = []
    start = (_sample_start(campaign, metas, model, prepared, fixed=fixed, robust_k=robust_k,
                           window_m=window_m, heading_hint_rad=heading_hint_rad,
                           max_iter=max_iter)
             if surface and n > SAMPLE_START_POINTS else None)
    if start is not None:
        # 2'. a large position: the white adjustment of a sample stands in for that of every
        # point (held parameters, north alignment, cells, smooth modes carried and the random
        # effect's start come from the sample's own two-face adjustment)
        held.update(start.held)
        mdl = model_of(free_of())
        st = start.mixed
        kappa = st.kappa_rad
        x_white = np.array([dict(zip(st.model.free, st.x))[n_] for n_ in mdl.free])
        used = w > 0
        notes.append(f"started from a seeded sample of {start.n_points:,} of the {n:,} points "
                     f"(more than {SAMPLE_START_POINTS:,}): its adjustment gave the north "
                     "alignment, the cells and the start of the random effect")
    else:
        # 2. white-noise robust adjustment, with identifiability on its normal matrix
        for _ in range(4):
            mdl = model_of(free_of())
            x0 = _x0(mdl.free, init, fixed)
            if robust_k is None:
                res = gauss_helmert(mdl, l, x0, sig, c, w, v0=np.zeros_like(l),
                                    max_iter=max_iter)
            else:
                res = robust_gauss_helmert(mdl, l, x0, sig, c, w, k=robust_k, max_iter=max_iter)
            bad = unidentifiable_calibration(res.cov, mdl.free)
            if not bad:
                break
            hold_parameters(held, fixed, bad, res.cov, mdl.free, elevation)
        used = np.asarray(res.weights) > 0
        pdata = concat_scans([p[0] for p in prepared]).padded(n_pad)
        fit1 = finish_scan_fit(campaign, metas[0], mdl, pdata, res, g, init, used,
                               heading_hint_rad=heading_hint_rad)
        kappa = fit1.alignment.kappa_rad
        x_white = np.asarray(res.x)
    if surface:
        del w  # (the random effect's weights are ``used``'s; 8 B per point less at its peak)
        cell_m = float(tel.extra.get("panel_cell_m", 2.0)) if tel.extra else 2.0
        if start is None:
            groups = dict(SURFACE_MODE_GROUPS) if tel.offset_m == 0 else {}
            mode_tests: dict[str, tuple] = {}
            confounding: dict = {}
            x_start = {n_: float(v_) for n_, v_ in zip(mdl.free, x_white)}
            warm: dict = {"v0": np.asarray(res.v), "cell_var0": np.asarray(_CELL_VAR0)}
            ridge_var0 = np.full(len(groups), _MODE_VAR0)
        else:  # the sample's verdicts on the modes and its random effect as the start
            # (the groups the sample shows: :func:`_sample_start` leaves the others in its
            # result, marked not carried, instead of adjusting it again without them)
            groups = {k_: SURFACE_MODE_GROUPS[k_] for k_ in (st.ridge or {})
                      if start.surface.mode_tests.get(k_, {"carried": True})["carried"]}
            mode_tests = dict(start.surface.mode_tests)
            confounding = dict(start.surface.mode_confounding)
            x_start = {n_: float(v_) for n_, v_ in zip(st.model.free, st.x)}
            warm = {"u0": np.asarray(st.u), "noise_var0": float(st.var[0]),
                    "cell_var0": np.maximum(np.asarray(st.var[1]), np.asarray(_CELL_VAR0)),
                    "rate0": st.contraction}
            ridge_var0 = np.maximum(np.array([v_ for k_, v_ in zip(st.ridge or {}, np.asarray(
                st.var[2], float)) if k_ in groups]), _MODE_VAR0)
        # each point's cell (its panel) where its beam hit the reflector, and its local
        # coordinates there, as the random effect's design: held in float32 (0.1 um of
        # rounding on a panel's local coordinates; the solver takes its rows in float64), 12 B
        # per point less at its peak. The hit points are held only for the smooth modes'
        # columns, as their x and y in float32 (1e-6 m of rounding; the columns are float32
        # themselves): 16 B per point less at the peak where modes are carried; where none
        # is, not at all (made again if a later adjustment carries them: a campaign's mode
        # variance, ``finish``). A large position also takes the start's residuals, where the
        # random effect linearises first (in float32: a start, 1e-10 m of rounding)
        if tel.ring_edges_m is not None and tel.panels_per_ring is not None:
            cell, design, *rest = hit_cells(
                mdl, l, x_white, c, sig, kappa, tel.ring_edges_m, tel.panels_per_ring,
                with_v=start is not None, with_xy=bool(groups), live=n)
            v_start = rest.pop(0) if start is not None else None
            X_hit = rest.pop(0) if groups else None
            n_cells, desc = panel_layout(tel.panels_per_ring)
            keys = None
        else:  # square cells: those the used points occupy, or the start's
            X_hit, *rest = (np.asarray(a) for a in (
                hit_points_and_residuals(mdl, l, x_white, c, sig, kappa) if start is not None
                else (hit_points(mdl, l, x_white, c, sig, kappa),)))
            v_start = rest[0].astype(np.float32) if start is not None else None
            keys = (start.mixed.cell_keys if start is not None
                    else square_cells(X_hit[used], cell_m)[2])
            cell, local, n_cells, desc = panel_cells(X_hit, cell_m=cell_m, keys=keys)
            cell = cell.astype(np.int32)  # (the ids fit: 4 B per point less at the peak)
            design = lendable_empty((n_pad, 1 + local.shape[1]), np.float32)
            design[:, 0] = cell >= 0
            np.multiply(local, design[:, :1], out=design[:, 1:], casting="same_kind")
            del local, rest
            X_hit = X_hit[:, :2].astype(np.float32) if groups else None
        if start is not None:
            if robust_k is not None:
                # the outliers the white robust adjustment would have rejected, judged there
                used = reject_beyond(v_start, sig, used, robust_k, len(mdl.free))
            warm["v0"] = v_start
        w_mixed = used  # (bool: taken as 0/1 weights, 7 B per point less than float)

        def hit_points_now():
            return X_hit if X_hit is not None else np.asarray(
                hit_points(mdl, l, x_white, c, sig, kappa))

        def adjust(groups, x_start, w_, ridge_var0, warm, estimate_variances=True):
            """The random-effect adjustment carrying the smooth modes of ``groups`` (the
            parameters held so far held), from ``x_start`` (by name) and ``warm``."""
            modes = [j for g_ in groups.values() for j in g_]
            mdl2 = model_of(free_of(tuple(f"{ZERNIKE_PREFIX}{j}" for j in modes)), kappa)
            ridge = {k_: [mdl2.free.index(f"{ZERNIKE_PREFIX}{j}") for j in g_]
                     for k_, g_ in groups.items()} or None
            # the modes (last in mdl2.free) enter through their columns at the hit points
            cond, mz = ((model_of(free_of(), kappa),
                         zernike_columns(hit_points_now(), modes, aperture, np.float32))
                        if modes else (mdl2, None))
            rm = gauss_helmert_mixed(
                cond, l, np.array([x_start.get(n_, 0.0) for n_ in mdl2.free]), sig, c, w_,
                cell, design, n_cells, robust_k=robust_k, ridge=ridge, ridge_var0=ridge_var0,
                max_iter=60, mode_design=mz, estimate_variances=estimate_variances, **warm)
            return modes, mdl2, ridge, cond, mz, rm

        def resumed(rm):
            """Where ``rm`` ended, by name, and its state as the next adjustment's start."""
            return ({n_: float(v_) for n_, v_ in zip(mdl2.free, np.asarray(rm.x))},
                    {"v0": np.asarray(rm.v), "u0": np.asarray(rm.u),
                     "cell_var0": np.asarray(rm.cell_var), "noise_var0": float(rm.noise_var),
                     "rate0": float(rm.contraction)})

        for _ in range(3 + len(groups)):
            modes, mdl2, ridge, cond, mz, rm = adjust(groups, x_start, w_mixed, ridge_var0, warm)
            bad = unidentifiable_calibration(rm.cov, mdl2.free)
            if bad:
                hold_parameters(held, fixed, bad, rm.cov, mdl2.free, elevation)
                continue
            absent = _absent_modes(rm, ridge, mode_tests)
            if not absent:
                break
            if not confounding:  # what the fixed effects take up once the modes are dropped
                confounding = mode_confounding(np.asarray(rm.Qxx), mdl2.free, ridge,
                                               np.asarray(rm.ridge_var), float(rm.noise_var))
            if as_start:  # the verdicts are in; the larger adjustment starts without them
                break
            ridge_var0 = np.array([v_ for k_, v_ in zip(groups, np.asarray(rm.ridge_var))
                                   if k_ not in absent])
            for k_ in absent:  # the data do not show them: not carried (see _absent_modes)
                groups.pop(k_)
            # refit without them from where this one ended (same points, cells, variances)
            x_start, warm = resumed(rm)
            warm["cell_var0"] = np.maximum(warm["cell_var0"], np.asarray(_CELL_VAR0))
            w_mixed = np.asarray(rm.weights)

        def finish(mode_prior_m2, notes, rm, groups, modes, mdl2, ridge, cond, mz,
                   confounding) -> PositionFit:
            """The position's result from where the loop over the modes ended (its adjustment
            ``rm`` and what it carried); with ``mode_prior_m2``, a position whose pose takes
            up modes it does not carry adjusted once more with them at that variance."""
            notes = list(notes)
            pooled = bool(mode_prior_m2 and mode_prior_m2 > 0 and confounding and not groups
                          and tel.offset_m == 0)
            if pooled:
                # carried with the campaign's variance (held: this position cannot estimate it),
                # from where the adjustment without them ended, its own variances held as well
                x_start, warm = resumed(rm)
                groups = dict(SURFACE_MODE_GROUPS)
                modes, mdl2, ridge, cond, mz, rm = adjust(
                    groups, x_start, np.asarray(rm.weights), float(mode_prior_m2), warm,
                    estimate_variances=False)
                confounding = {}
            absent = [k_ for k_, t in mode_tests.items() if not t["carried"]]
            if absent:
                notes.append("smooth modes not shown by the data, not carried as a random effect ("
                             + ", ".join(f"{k_} p = {mode_tests[k_]['p']:.2f}" for k_ in absent)
                             + "): the panels' random effect covers those the data can determine"
                             if not pooled else
                             "smooth modes not shown by the data ("
                             + ", ".join(f"{k_} p = {mode_tests[k_]['p']:.2f}" for k_ in absent)
                             + ") but taken up by the pose: carried with the campaign's variance "
                             f"({1e6 * math.sqrt(mode_prior_m2):.0f} um rms per mode, from the "
                             "positions that show them), the position's own variance components "
                             "held")
            keep_idx = [i for i, n_ in enumerate(mdl2.free) if not n_.startswith(ZERNIKE_PREFIX)]
            mode_idx = [i for i, n_ in enumerate(mdl2.free) if n_.startswith(ZERNIKE_PREFIX)]
            xs = np.asarray(rm.x)
            cov = np.asarray(rm.cov)
            weights = np.asarray(rm.weights)
            counts = sum(  # a block at a time (a whole int64 copy of the cells was 96 MiB)
                np.bincount(cell[r][(cell[r] >= 0) & (weights[r] > 0)], minlength=n_cells)
                for r in row_blocks(len(cell)))
            variances, shares = surface_components(
                (rm.noise_var, rm.cell_var, rm.ridge_var),
                (rm.redundancy_noise, rm.redundancy_cells, rm.redundancy_ridge), ridge)
            surf = SurfaceEffect(
                cells=desc, u=np.asarray(rm.u), u_cov=np.asarray(rm.u_cov), n=counts,
                variances=variances, redundancy=shares,
                modes={mdl2.free[i]: (float(xs[i]), float(np.sqrt(cov[i, i]))) for i in mode_idx},
                mode_tests=mode_tests, mode_prior=mode_prior(cov, mdl2.free, ridge, rm.ridge_var),
                mode_confounding=confounding if not ridge or as_start else {})
            line = mode_prior_note(surf.mode_prior, surf.modes,
                                   math.sqrt(variances.get("modes_m2", 0.0)))
            if line:
                notes.append(line)
            mixed = MixedState(mdl2, xs, np.asarray(rm.u), (float(rm.noise_var), np.asarray(
                rm.cell_var), np.asarray(rm.ridge_var)), (1.0, np.asarray(_CELL_VAR0), np.full(
                    len(ridge or ()), _MODE_VAR0)), ridge, kappa, cell_m, keys,
                [p[2] for p in prepared], cond, tuple(modes), aperture, variances_held=pooled,
                contraction=float(rm.contraction))
            free = tuple(mdl2.free[i] for i in keep_idx)
            x_pos, cov_pos = xs[keep_idx], cov[np.ix_(keep_idx, keep_idx)]
            iterations, converged = int(rm.iterations), bool(rm.converged)
            if not converged:
                notes.append(f"surface random effect: not converged after {iterations} "
                             "iterations")
            response = np.asarray(rm.x_response)[:, keep_idx, :]
            sigma_white = white_sigmas(response, rm.cell_var, cov_pos, mode_variance_parts(
                surf.mode_prior, mdl2.free, keep_idx, cov_pos))
            line = confounding_note(surf.mode_confounding, free, np.sqrt(np.diag(cov_pos)),
                                    "the smooth modes the data can determine are absent")
            if line:
                notes.append(line)
            return assemble(
                notes, free=free, x_pos=x_pos, cov_pos=cov_pos, weights=np.asarray(rm.weights),
                v=np.asarray(rm.v), omega_pt=np.asarray(rm.omega_point),
                r_e=float(rm.redundancy_noise), sigma0=float(rm.sigma0), iterations=iterations,
                converged=converged, normalized=np.asarray(rm.normalized),
                mdl_final=model_of(free, kappa), surf=surf, mixed=mixed,
                sigma_white=sigma_white, response=response)

        # what no further adjustment of these points needs let go before the per-scan results
        # are made (a further one starts from where this one ended, ``resumed``; only one
        # with the campaign's mode variance adjusts them again): 24 B per point less at the
        # end of a large position
        warm = v_start = None
        if mode_prior_m2 is None and not keep_resume:
            design = None
        result = finish(mode_prior_m2, notes, rm, groups, modes, mdl2, ridge, cond, mz,
                        confounding)
        if mode_prior_m2 is None and keep_resume and result.takes_campaign_prior:
            # what fit_campaign needs to adjust it again with the campaign's mode variance
            # from here (not from its points again); holds this position's arrays until then
            loop_end = (notes, rm, groups, modes, mdl2, ridge, cond, mz, confounding)

            def resume(prior: float) -> PositionFit:
                again = finish(prior, *loop_end)
                again.notes.append(RESUMED_NOTE)
                return again

            result.resume = resume
        return result
    k_ = np.asarray(res.normalized) * float(res.sigma0)
    return assemble(
        notes, free=mdl.free, x_pos=np.asarray(res.x), cov_pos=np.asarray(res.cov),
        weights=np.asarray(res.weights), v=np.asarray(res.v), omega_pt=k_ * k_,
        r_e=float(res.redundancy), sigma0=float(res.sigma0), iterations=int(res.iterations),
        converged=bool(res.converged), normalized=np.asarray(res.normalized), mdl_final=mdl,
        surf=None, mixed=None, sigma_white=None, response=None)  # white: every sigma the noise's


def _progress(disable: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), disable=disable, transient=False,
    )


def fit_campaign(
    campaign: Campaign,
    model: str | Iterable[str] = "extended",
    *,
    scans: Sequence[str] | None = None,
    fixed: dict[str, float] | None = None,
    robust_k: float | None = 4.0,
    keep: Callable[[ScanMeta, ScanData], np.ndarray] | None = None,
    batch: bool = False,
    progress: bool = True,
    per_cycle: bool = False,
    surface: bool = True,
) -> CampaignFit:
    """Fit a campaign (or the scans named) with one model.

    Default: one adjustment per position from both faces together, the surface a random effect
    (:func:`fit_position`); a position with one usable cycle is adjusted alone and says so.
    ``per_cycle=True``: every scan by itself, white noise (the paper's procedure; the
    disturbed-scan checks need it); ``batch=True`` fits the scans that way in one compiled call.
    Positions away from the zenith are fitted first; their mount heading then resolves the
    quadrupod symmetry of zenith positions' north alignment.
    """
    metas = [campaign.scan(s) for s in scans] if scans else list(campaign.scans)
    tel, site = campaign.telescope, campaign.site
    tilt = {m.id: np.arccos(np.clip(-pointing_gravity(m, tel, site)[2], -1, 1)) for m in metas}
    names = parse_names(model)
    if not per_cycle and not batch:
        groups: dict[str, list[ScanMeta]] = {}
        for m in metas:
            groups.setdefault(m.position, []).append(m)
        order = sorted(groups, key=lambda p: -tilt[groups[p][0].id])
        pfits: dict[str, PositionFit] = {}
        held_points = 0
        headings: list[float] = []
        hints: dict[str, float | None] = {}

        def fit_one(pos, hint):
            return fit_position(campaign, groups[pos], model, keep=keep, fixed=fixed,
                                robust_k=robust_k, heading_hint_rad=hint, surface=surface,
                                keep_resume=True)

        # small tilted positions fitted in threads, the next one while this one is: gravity
        # fixes their north alignment, so they need no heading from the positions before
        # them (checked on the result; the same fits, taken in the same order)
        ahead = {p: tilt[groups[p][0].id] >= MIN_TILT_RAD and file_bytes(campaign, groups[p])
                 <= AHEAD_POSITION_BYTES for p in order} if usable_cores() > 1 else {}
        pending: dict = {}
        with _progress(not progress) as prog:
            task = prog.add_task("fitting positions", total=len(order))
            for i, pos in enumerate(order):
                prog.update(task, description=f"fitting {pos}")
                hints[pos] = mean_heading(headings)
                for p in order[i: i + 2]:
                    if ahead.get(p) and p not in pending:
                        pending[p] = thread_pool(2, "positions").submit(fit_one, p, None)
                pf = pending.pop(pos).result() if pos in pending else None
                if pf is None or any(s.alignment.source != "gravity" for s in pf.scans):
                    pf = fit_one(pos, hints[pos])
                if fits_resume_budget(held_points, pf):  # its arrays held for the prior
                    held_points += pf.n_points
                else:
                    pf.resume = None  # adjusted again from its points, if at all
                headings.append(scan_heading(pf.scans[0]))
                pfits[pos] = pf
                release_compiled_programs()
                prog.advance(task)
            # positions whose pose takes up a coma they cannot determine: again, with the
            # smooth modes carried at the variance of the positions that show them
            prior, redo = positions_for_campaign_prior(
                {p: _carried_mode_variance(pfits[p]) for p in order},
                {p: pfits[p].takes_campaign_prior for p in order})
            if redo:
                task = prog.add_task("coma prior from the campaign", total=len(redo))
            for pos in redo:
                again = pfits[pos].resume
                pfits[pos] = (again(prior) if again is not None else fit_position(
                    campaign, groups[pos], model, keep=keep, fixed=fixed, robust_k=robust_k,
                    heading_hint_rad=hints[pos], surface=surface, mode_prior_m2=prior))
                release_compiled_programs()
                prog.advance(task)
            for pf in pfits.values():
                pf.resume = None  # the held arrays go
        by_id = {s.meta.id: s for pf in pfits.values() for s in pf.scans}
        plist = [pfits[p] for p in groups]
        return CampaignFit(campaign, names, [by_id[m.id] for m in metas], position_fits=plist)
    order = sorted(metas, key=lambda m: -tilt[m.id])
    if batch:  # one compiled call per kind: one-face scans hold the two-face parameters
        fits = {}
        for kind in ([m for m in order if m.cycle == 0], [m for m in order if m.cycle != 0]):
            if kind:
                fits.update(_fit_batch(campaign, kind, model, fixed=fixed, robust_k=robust_k,
                                       keep=keep, progress=progress))
    else:
        fits = {}
        headings = []
        with _progress(not progress) as prog:
            task = prog.add_task("fitting scans", total=len(order))
            for m in order:
                prog.update(task, description=f"fitting {m.id}")
                data = read_scan(campaign, m)
                k = keep(m, data) if keep is not None else None
                fit = fit_scan(campaign, m, model, data=data, keep=k, fixed=fixed,
                               robust_k=robust_k, heading_hint_rad=mean_heading(headings))
                headings.append(scan_heading(fit))
                fits[m.id] = fit
                prog.advance(task)
    return CampaignFit(campaign, names, [fits[m.id] for m in metas])


def parse_names(model) -> tuple[str, ...]:
    return parse_model(model)


def _fit_batch(campaign, metas, model, *, fixed, robust_k, keep, progress) -> dict[str, ScanFit]:
    """All scans padded to one shape and adjusted in one compiled call (vmap); one-face scans
    (all of ``metas`` or none) hold the two-face parameters, as :func:`fit_scan`."""
    fixed = dict(fixed or {})
    held = one_face_holds(parse_names(model), fixed) if metas[0].cycle == 0 else {}
    fixed.update({n: h.value for n, h in held.items()})
    mdl = make_model(model, fixed, aperture_radius_m=campaign.telescope.diameter_m / 2)
    prepared = []
    with _progress(not progress) as prog:
        task = prog.add_task("reading and initial values", total=len(metas))
        for m in metas:
            data = read_scan(campaign, m)
            k = keep(m, data) if keep is not None else None
            prepared.append((m,) + prepare_scan(campaign, m, data, keep=k))
            prog.advance(task)
    n = max(len(p[1]) for p in prepared)
    B = len(prepared)
    L = np.zeros((B, n, 3))
    C = np.zeros((B, n, N_CONSTS))
    W = np.zeros((B, n))
    X0 = np.zeros((B, len(mdl.free)))
    for b, (m, data, g, init, window) in enumerate(prepared):
        l, c = scan_arrays(data)
        L[b, : len(l)] = l
        L[b, len(l):] = l[0]  # harmless padding (weight 0)
        C[b, : len(c)] = c
        W[b, : len(l)] = window
        X0[b] = _x0(mdl.free, init, fixed)
    sig = sigma_vector(campaign)
    res = gauss_helmert_batch(mdl, L, X0, sig, C, W)
    for _ in range(6 if robust_k is not None else 0):
        bad = (np.asarray(res.normalized) > robust_k) & (W > 0)
        if not bad.any():
            break
        W = np.where(bad, 0.0, W)
        res = gauss_helmert_batch(mdl, L, np.asarray(res.x), sig, C, W)
    out = {}
    headings = []
    for b, (m, data, g, init, window) in enumerate(prepared):
        nb = len(data)
        rb = GHResult(
            x=res.x[b], cov=res.cov[b], N=res.N[b], sigma0=res.sigma0[b], v=res.v[b, :nb],
            misclosure=res.misclosure[b, :nb], normalized=res.normalized[b, :nb],
            weights=res.weights[b, :nb], redundancy=res.redundancy[b],
            iterations=res.iterations[b], converged=res.converged[b],
        )
        fit = finish_scan_fit(campaign, m, mdl, data, rb, g, init, window,
                              heading_hint_rad=mean_heading(headings))
        fit.held = held
        fit.undetermined = undetermined_parameters(fit.cov, fit.names, fit.elevation_deg,
                                                   then=PER_CYCLE_UNDETERMINED)
        headings.append(scan_heading(fit))
        out[m.id] = fit
    return out
