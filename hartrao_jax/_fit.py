"""Fit campaigns: per scan initial values, cleaning, rigorous GH adjustment, north alignment.

Everything here is bookkeeping (NumPy) around the differentiable core (:mod:`._ghm`,
:mod:`._model`). Results are plain dataclasses of NumPy arrays, written to ``fit.json``
(schema ``hartrao-fit/1``, ``shared/spec/outputs.md``) and to per-scan residual tables.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ._align import Alignment, mount_heading, north_alignment
from ._campaign import Campaign, ScanData, ScanMeta, read_scan
from ._geometry import face_of, paraboloid_deviation, pointing_elevation_deg, pointing_gravity, rot_z
from ._ghm import GHResult, gauss_helmert_batch, robust_gauss_helmert
from ._init import (
    InitialValues,
    geometry_window,
    initial_values,
    patch_initial_values,
    quadric_initial_values,
)
from ._model import N_CONSTS, ParaboloidModel, make_model, parameter_unit
from ._physics import INSTRUMENT

log = logging.getLogger("hartrao_jax")

FIT_SCHEMA = "hartrao-fit/1"


@dataclass
class ScanFit:
    """The adjustment of one scan (NumPy; SI units).

    ``used`` marks the points of ``data`` that entered the final adjustment; ``deviation_m`` is
    the signed normal distance of every point of ``data`` from the fitted paraboloid (positive
    towards the focus), ``X_tel`` its north-aligned telescope-frame coordinates (m).
    """

    meta: ScanMeta
    model: ParaboloidModel
    names: tuple[str, ...]
    x: np.ndarray
    cov: np.ndarray
    sigma0: float
    iterations: int
    converged: bool
    n_points: int
    n_rejected: int
    n_window: int
    alignment: Alignment
    init: InitialValues
    data: ScanData
    used: np.ndarray
    v: np.ndarray
    normalized: np.ndarray
    deviation_m: np.ndarray
    X_tel: np.ndarray
    gravity: np.ndarray
    elevation_deg: float
    notes: list[str] = field(default_factory=list)

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def estimates(self) -> dict[str, tuple[float, float]]:
        return {n: (float(self.x[i]), float(self.sigma[i])) for i, n in enumerate(self.names)}

    def value(self, name: str) -> float:
        """Estimated or fixed value of a parameter (0 for a parameter not in the model)."""
        if name in self.names:
            return float(self.x[self.names.index(name)])
        fixed = dict(zip(self.model.fixed_names, np.asarray(self.model.fixed_values)))
        return float(fixed.get(name, 0.0))

    def sigma_of(self, name: str) -> float:
        """Standard deviation of an estimate (0 for a fixed parameter)."""
        return float(self.sigma[self.names.index(name)]) if name in self.names else 0.0

    @property
    def correlation(self) -> np.ndarray:
        s = self.sigma
        return self.cov / np.outer(s, s)


@dataclass
class CampaignFit:
    """The fitted scans of a campaign. ``shared``: parameters estimated jointly by all scans of
    a group (a joint adjustment's calibration; empty for scan-by-scan fits)."""

    campaign: Campaign
    model_names: tuple[str, ...]
    scans: list[ScanFit]
    shared: tuple[str, ...] = ()

    def positions(self) -> list[dict]:
        """Per position: inverse-variance mean focal length of its scans (m)."""
        out: dict[str, list[ScanFit]] = {}
        for s in self.scans:
            out.setdefault(s.meta.position, []).append(s)
        rows = []
        for pos, fits in out.items():
            v = np.array([s.value("f") for s in fits])
            sg = np.array([s.sigma_of("f") for s in fits])
            if np.all(sg > 0):
                w = 1.0 / sg**2
                mean = float(np.sum(w * v) / np.sum(w))
                sig = float(1.0 / math.sqrt(np.sum(w)))
            else:  # focal length held fixed
                w = np.ones_like(v)
                mean, sig = float(np.mean(v)), 0.0
            m = fits[0].meta
            row = {"position": pos}
            if m.ha_deg is not None:
                row.update(ha_deg=m.ha_deg, dec_deg=m.dec_deg)
            if m.azimuth_deg is not None or m.elevation_deg is not None:
                row.update(azimuth_deg=m.azimuth_deg)
            row.update(elevation_deg=fits[0].elevation_deg,
                       f={"value": mean, "sigma": sig},
                       gravity=[float(a) for a in fits[0].gravity],
                       scans=[s.meta.id for s in fits])
            if len(fits) > 1 and sig > 0:
                chi2 = float(np.sum(w * (v - mean) ** 2))
                row["f_consistency_chi2"] = chi2
            rows.append(row)
        return rows


# --------------------------------------------------------------------------------------------


def scan_arrays(data: ScanData) -> tuple[np.ndarray, np.ndarray]:
    """Observations ``l = (r, phi, theta)`` (n, 3) and constants ``c = (time_s, 0)`` (n, 2)."""
    l = np.column_stack([data.range_m, data.phi_rad, data.theta_rad])
    c = np.zeros((len(data), N_CONSTS))
    c[:, 0] = data.time_s
    return l, c


def sigma_vector(campaign: Campaign) -> np.ndarray:
    s = campaign.scanner
    return np.array([s.sigma_range_m, s.sigma_angle_rad, s.sigma_angle_rad])


def _x0(names: Sequence[str], init: InitialValues, fixed: dict[str, float]) -> np.ndarray:
    return np.array([init.x.get(n, fixed.get(n, 0.0)) for n in names], dtype=float)


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


def prepare_scan(
    campaign: Campaign, meta: ScanMeta, data: ScanData | None = None, *, window_m: float = 0.10,
    keep: np.ndarray | None = None, seed: int = 0,
):
    """Read a scan, find initial values and the points inside the geometry window.

    Returns ``(data, gravity, init, window)`` where ``window`` marks points within
    ``window_m`` (vertical) of the initial paraboloid (and inside ``keep`` if given).
    """
    data = read_scan(campaign, meta) if data is None else data
    g = pointing_gravity(meta, campaign.telescope, campaign.site)
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
    from ._joint import bucket_size

    fixed = dict(fixed or {})
    data, g, init, window = prepare_scan(campaign, meta, data, window_m=window_m, keep=keep)
    mdl = make_model(model, fixed, aperture_radius_m=campaign.telescope.diameter_m / 2)
    n = len(data)
    n_pad = bucket_size(n) if pad else n
    pdata = data.subset(np.concatenate([np.arange(n), np.zeros(n_pad - n, np.int64)])) \
        if n_pad > n else data
    l, c = scan_arrays(pdata)
    c[n:] = 0.0
    wpad = np.zeros(n_pad, bool)
    wpad[:n] = window
    w = wpad.astype(float)
    x0 = _x0(mdl.free, init, fixed)
    sig = sigma_vector(campaign)
    if robust_k is None:
        from ._ghm import gauss_helmert

        res = gauss_helmert(mdl, l, x0, sig, c, w, v0=np.zeros_like(l), max_iter=max_iter)
    else:
        res = robust_gauss_helmert(mdl, l, x0, sig, c, w, k=robust_k, max_iter=max_iter)
    fit = finish_scan_fit(campaign, meta, mdl, pdata, res, g, init, wpad,
                          heading_hint_rad=heading_hint_rad)
    if n_pad == n:
        return fit
    # back to the scan's own rows (the padding rows are unused and outside the window)
    fit.data = data
    for k in ("used", "v", "normalized", "deviation_m", "X_tel"):
        setattr(fit, k, np.asarray(getattr(fit, k))[:n])
    fit.n_window -= n_pad - n
    return fit


def finish_scan_fit(
    campaign: Campaign, meta: ScanMeta, mdl: ParaboloidModel, data: ScanData, res: GHResult,
    g: np.ndarray, init: InitialValues, window: np.ndarray, *, heading_hint_rad: float | None = None,
) -> ScanFit:
    """Turn a GH result into a :class:`ScanFit`: alignment, deviations, bookkeeping."""
    import jax

    x = np.asarray(res.x)
    names = mdl.free
    used = np.asarray(res.weights) > 0
    l, c = scan_arrays(data)
    X_fit = np.asarray(jax.vmap(mdl.telescope_point, in_axes=(0, None, 0))(l, res.x, c))
    p = {k: float(v) for k, v in mdl.params(res.x).items()}
    f = p["f"]
    dev = np.asarray(paraboloid_deviation(jnp.asarray(X_fit), f))
    tel = campaign.telescope
    rim = tel.diameter_m / 2
    align = north_alignment(
        p["rx"], p["ry"], g, X_fit[used], leg_azimuths_deg=tel.quadrupod_azimuths_deg,
        rho_range_m=(max(tel.cone_radius_m, 0.25 * rim) , 0.92 * rim),
        heading_hint_rad=heading_hint_rad,
    )
    X_tel = X_fit @ np.asarray(rot_z(align.kappa_rad)).T
    notes = []
    if not bool(res.converged):
        notes.append(f"not converged after {int(res.iterations)} iterations")
    if meta.cycle == 0:
        two_face = [n for n in names if n in INSTRUMENT and INSTRUMENT[n].two_face != "no"]
        if two_face:
            notes.append("one-face scan: " + ", ".join(two_face) + " are not separable from the "
                         "object parameters without a second face")
    return ScanFit(
        meta=meta, model=mdl, names=names, x=x, cov=np.asarray(res.cov),
        sigma0=float(res.sigma0), iterations=int(res.iterations), converged=bool(res.converged),
        n_points=int(used.sum()), n_rejected=int(window.sum() - used.sum()),
        n_window=int(len(data) - window.sum()), alignment=align, init=init, data=data, used=used,
        v=np.asarray(res.v), normalized=np.asarray(res.normalized), deviation_m=dev, X_tel=X_tel,
        gravity=np.asarray(g), elevation_deg=pointing_elevation_deg(meta, tel, campaign.site),
        notes=notes,
    )


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
) -> CampaignFit:
    """Fit every scan (or those named) of a campaign with one model.

    Scans away from the zenith are fitted first; their mount heading then resolves the
    quadrupod symmetry of zenith scans' north alignment. ``batch=True`` fits all scans in one
    compiled call (padded and masked), with the same results as one by one.
    """
    metas = [campaign.scan(s) for s in scans] if scans else list(campaign.scans)
    tel, site = campaign.telescope, campaign.site
    tilt = {m.id: np.arccos(np.clip(-pointing_gravity(m, tel, site)[2], -1, 1)) for m in metas}
    order = sorted(metas, key=lambda m: -tilt[m.id])
    if batch:
        fits = _fit_batch(campaign, order, model, fixed=fixed, robust_k=robust_k, keep=keep,
                          progress=progress)
    else:
        fits = {}
        headings = []
        with _progress(not progress) as prog:
            task = prog.add_task("fitting scans", total=len(order))
            for m in order:
                prog.update(task, description=f"fitting {m.id}")
                data = read_scan(campaign, m)
                k = keep(m, data) if keep is not None else None
                hint = float(np.angle(np.mean(np.exp(1j * np.array(headings))))) if headings else None
                fit = fit_scan(campaign, m, model, data=data, keep=k, fixed=fixed, robust_k=robust_k,
                               heading_hint_rad=hint)
                if fit.alignment.source == "gravity":
                    headings.append(mount_heading(fit.alignment.kappa_rad, fit.value("rx"),
                                                  fit.value("ry"), fit.gravity))
                fits[m.id] = fit
                prog.advance(task)
    names = parse_names(model)
    return CampaignFit(campaign, names, [fits[m.id] for m in metas])


def parse_names(model) -> tuple[str, ...]:
    from ._model import parse_model

    return parse_model(model)


def _fit_batch(campaign, metas, model, *, fixed, robust_k, keep, progress) -> dict[str, ScanFit]:
    """All scans padded to one shape and adjusted in one compiled call (vmap)."""
    fixed = dict(fixed or {})
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
        hint = float(np.angle(np.mean(np.exp(1j * np.array(headings))))) if headings else None
        fit = finish_scan_fit(campaign, m, mdl, data, rb, g, init, window, heading_hint_rad=hint)
        if fit.alignment.source == "gravity":
            headings.append(mount_heading(fit.alignment.kappa_rad, fit.value("rx"), fit.value("ry"),
                                          fit.gravity))
        out[m.id] = fit
    return out


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------


def _num(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def scan_record(s: ScanFit) -> dict:
    """The ``scans[]`` entry of ``fit.json`` for one scan."""
    corr = s.correlation
    high = []
    for i in range(len(s.names)):
        for j in range(i + 1, len(s.names)):
            if abs(corr[i, j]) > 0.95:
                high.append({"a": s.names[i], "b": s.names[j], "correlation": float(corr[i, j])})
    return {
        "id": s.meta.id,
        "position": s.meta.position,
        "cycle": s.meta.cycle,
        "estimates": {
            n: {"value": v, "sigma": sg, "unit": parameter_unit(n)} for n, (v, sg) in s.estimates.items()
        },
        "sigma0": s.sigma0,
        "n_points": s.n_points,
        "n_rejected": s.n_rejected,
        "n_outside_window": s.n_window,
        "n_dropped_nonfinite": int(s.data.n_dropped_nonfinite),
        "iterations": s.iterations,
        "converged": s.converged,
        "kappa_rad": s.alignment.kappa_rad,
        "kappa_source": s.alignment.source,
        "kappa_ambiguity_rad": s.alignment.ambiguity_rad,
        "elevation_deg": s.elevation_deg,
        "gravity": [float(a) for a in s.gravity],
        "rms_deviation_m": float(np.sqrt(np.mean(s.deviation_m[s.used] ** 2))),
        "high_correlations": high,
        "notes": s.notes,
    }


def fit_json(cf: CampaignFit) -> dict:
    return {
        "schema": FIT_SCHEMA,
        "model": list(cf.model_names),
        "campaign": str(cf.campaign.root),
        "scans": [scan_record(s) for s in cf.scans],
        "positions": cf.positions(),
    }


def write_residuals(path: Path, s: ScanFit) -> None:
    """Per-point residuals of one scan as Parquet (every row of the scan, ``used`` flags).

    Written to a temporary name and renamed (never a half-written table at ``path``).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from ._safeio import write_file_atomic

    d = s.data
    table = pa.table({
        "row": d.row.astype(np.int64),
        "used": s.used,
        "face": face_of(d.theta_rad).astype(np.int8),
        "phi_rad": d.phi_rad,
        "theta_rad": d.theta_rad,
        "range_m": d.range_m,
        "time_s": d.time_s,
        "intensity": d.intensity,
        "v_range_m": s.v[:, 0],
        "v_phi_rad": s.v[:, 1],
        "v_theta_rad": s.v[:, 2],
        "normalized": s.normalized,
        "deviation_m": s.deviation_m,
        "X_m": s.X_tel[:, 0],
        "Y_m": s.X_tel[:, 1],
        "Z_m": s.X_tel[:, 2],
    })
    write_file_atomic(path, lambda t: pq.write_table(table, t), durable=False)


def write_fit(out_dir: str | Path, cf: CampaignFit, *, residuals: bool = True) -> Path:
    """Write ``fit.json`` and ``residuals/<scan>.parquet``; returns the JSON path.

    Crash-safe (:class:`._safeio.OutputDir`): the residual tables go to temporary names,
    ``fit.json`` is written last and lists them (``"files"``: bytes, SHA-256); the JSON is
    strict (non-finite numbers null, listed under ``"nonfinite"``). Each scan record gets
    ``n_dropped``: the rows dropped while reading, per reason.
    """
    from ._safeio import OutputDir

    doc = fit_json(cf)
    for rec, s in zip(doc.get("scans", []), cf.scans):
        if getattr(s, "data", None) is not None and "n_dropped" not in rec:
            rec["n_dropped"] = dict(s.data.dropped)
    with OutputDir(out_dir, "fit.json") as od:
        if residuals:
            for s in cf.scans:
                od.write_with(f"residuals/{s.meta.id}.parquet",
                              lambda t, s=s: write_residuals(t, s))
        return od.commit(doc)
