"""The machine-readable records of a fit and the files they go to (``shared/spec/outputs.md``).

``fit.json`` (schema ``hartrao-fit/1``): ``scans[]`` per scan (:func:`scan_record`) and
``positions[]`` per position (:meth:`._fit.CampaignFit.positions`, the two-face records by
:func:`._position_record.position_record`); ``residuals/<scan>.parquet`` per scan
(:func:`write_residuals`). Every directory is written as one transaction
(:class:`..campaign._safeio.OutputDir`). Units: SI (m, rad), as named in each field.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .._config import row_blocks, usable_cores
from .._files import FileDigest
from ..campaign._safeio import OutputDir, write_columns, write_file_atomic
from ..geometry._geometry import face_of
from ..model._model import parameter_unit
from ._identify import Held
from ._results import CampaignFit, ScanFit

FIT_SCHEMA = "hartrao-fit/1"


def scan_record(s: ScanFit, held: dict[str, Held] | None = None) -> dict:
    """The ``scans[]`` entry of ``fit.json`` for one scan (``held``: the parameters its
    position adjustment could not determine, listed with ``identifiable: false``)."""
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
            **{n: ({"value": v, "sigma": sg, "unit": parameter_unit(n)}
                   if n not in s.undetermined else  # not an estimate: what the fit used
                   {"value": None, "sigma": None, "identifiable": False,
                    "note": s.undetermined[n], "value_in_fit": v, "unit": parameter_unit(n)})
               for n, (v, sg) in s.estimates.items()},
            **{n: {"value": h.value, "sigma": None, "identifiable": False, "note": h.note,
                   "unit": parameter_unit(n)} for n, h in {**s.held, **(held or {})}.items()},
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
    """``fit.json`` (schema ``hartrao-fit/1``, ``shared/spec/outputs.md``).

    Two-face fits: ``positions[]`` carry the shared estimates (f, pose, every calibration
    parameter, each ``{value, sigma}``; not identifiable ones ``{value, sigma: null,
    identifiable: false, note}``) and the variance components; ``scans[]`` repeat them under
    ``estimates`` and keep their own sigma0, counts and convergence.
    """
    held = {s.meta.id: p.held for p in cf.position_fits for s in p.scans}
    scans = [scan_record(s, held.get(s.meta.id)) for s in cf.scans]
    return {
        "schema": FIT_SCHEMA,
        "model": list(cf.model_names),
        "adjustment": "two-face, surface random effect" if cf.position_fits else "per cycle",
        "campaign": str(cf.campaign.root),
        "scans": scans,
        "positions": cf.positions(),
    }


def write_residuals(path: Path, s: ScanFit) -> None:
    """Per-point residuals of one scan as Parquet (every row of the scan, ``used`` flags).

    Written to a temporary name and renamed (never a half-written table at ``path``).
    """
    write_file_atomic(path, lambda t: write_residual_table(t, s), durable=False)


def write_residual_table(path: Path, s: ScanFit) -> FileDigest:
    """The table of :func:`write_residuals` written at ``path`` itself (a temporary name
    given by the caller: :class:`..campaign._safeio.OutputDir`); its manifest entry."""
    d = s.data
    face = np.empty(len(d), np.int8)  # a block at a time (no int64 and float64 columns made)
    for rows in row_blocks(len(d)):
        face[rows] = face_of(d.theta_rad[rows])
    columns = {
        "row": d.row.astype(np.int64, copy=False),
        "used": s.used,
        "face": face,
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
    }
    return write_columns(columns, path)


def write_fit(out_dir: str | Path, cf: CampaignFit, *, residuals: bool = True) -> Path:
    """Write ``fit.json`` and ``residuals/<scan>.parquet``; returns the JSON path.

    Crash-safe (:class:`._safeio.OutputDir`): the residual tables go to temporary names,
    ``fit.json`` is written last and lists them (``"files"``: bytes, SHA-256); the JSON is
    strict (non-finite numbers null, listed under ``"nonfinite"``). Each scan record gets
    ``n_dropped``: the rows dropped while reading, per reason.
    """

    doc = fit_json(cf)
    for rec, s in zip(doc.get("scans", []), cf.scans):
        if getattr(s, "data", None) is not None and "n_dropped" not in rec:
            rec["n_dropped"] = dict(s.data.dropped)
    return write_fit_dir(out_dir, doc, cf.scans if residuals else ())


def write_fit_dir(out_dir, doc: dict, scans: Sequence[ScanFit] = ()) -> Path:
    """``residuals/<scan>.parquet`` of ``scans`` under temporary names, then ``fit.json``
    (``doc``, strict, with the ``"files"`` manifest) last: the one commit of every fit."""
    with OutputDir(out_dir, "fit.json") as od:
        od.write_each([(f"residuals/{s.meta.id}.parquet",
                        lambda t, s=s: write_residual_table(t, s)) for s in scans],
                      threads=usable_cores())
        return od.commit(doc)


def read_residuals(path, columns: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """A ``residuals/<scan>.parquet`` table of ``write_fit`` as NumPy columns (all or those
    named)."""
    import pyarrow.parquet as pq

    t = pq.read_table(path, columns=list(columns) if columns is not None else None)
    return {c: t.column(c).to_numpy() for c in t.column_names}
