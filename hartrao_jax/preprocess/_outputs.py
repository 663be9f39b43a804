"""What preprocessing writes and shows: ``preprocess.json`` (schema ``hartrao-preprocess/1``),
the masks ``masks/<scan>.parquet`` and the summary table."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..campaign._campaign import Campaign
from ..campaign._safeio import OutputDir, write_file_atomic, write_table
from ._types import KEPT, PREPROCESS_SCHEMA, REASONS, PreprocessConfig, PreprocessResult


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    return v


def preprocess_json(results: Mapping[str, PreprocessResult],
                    config: PreprocessConfig | None = None,
                    campaign: Campaign | None = None) -> dict:
    """The ``preprocess.json`` document (schema ``hartrao-preprocess/1``)."""
    scans = []
    tot = {"n_rows": 0, "n_kept": 0, "removed": {REASONS[k]: 0 for k in REASONS if k != KEPT}}
    for sid, res in results.items():
        s = res.stats
        scans.append({
            "id": sid, "n_rows": s["n_rows"], "n_kept": s["n_kept"],
            "kept_fraction": s["n_kept"] / max(s["n_rows"], 1), "removed": s["removed"],
            "n_patches": s["n_patches"], "n_patches_fitted": s["n_patches_fitted"],
            "n_patches_small": s["n_patches_small"], "points_per_patch": s["points_per_patch"],
            "plane_rms_median_m": s["plane_rms_median_m"], "params": res.params,
            "timing_s": s["timing_s"], "notes": res.notes,
        })
        tot["n_rows"] += s["n_rows"]
        tot["n_kept"] += s["n_kept"]
        for k, v in s["removed"].items():
            tot["removed"][k] = tot["removed"].get(k, 0) + v  # stages and reading drops
    doc = {
        "schema": PREPROCESS_SCHEMA,
        "reasons": {str(k): v for k, v in REASONS.items()},
        "config": dataclasses.asdict(config) if config is not None else None,
        "scans": scans,
        "totals": tot,
    }
    if campaign is not None:
        doc["campaign"] = str(campaign.root)
    return _jsonable(doc)


def write_preprocess_json(path, results: Mapping[str, PreprocessResult],
                          config: PreprocessConfig | None = None,
                          campaign: Campaign | None = None) -> Path:
    """Write ``preprocess.json`` (schema ``hartrao-preprocess/1``) to ``path`` (file or dir):
    strict JSON, atomically, with an empty ``"files"`` manifest (see
    :func:`write_preprocess_result` for the JSON with its masks)."""
    return write_preprocess_result(path, results, config, campaign, masks=False)


def write_preprocess_result(path, results: Mapping[str, PreprocessResult],
                            config: PreprocessConfig | None = None,
                            campaign: Campaign | None = None, *, masks: bool = True) -> Path:
    """``masks/<scan>.parquet`` and ``preprocess.json`` crash-safely (:class:`._safeio.OutputDir`:
    masks under temporary names first, the JSON last, listing them). ``path``: the directory
    or the JSON file's path. Returns the JSON's path."""
    import pyarrow as pa


    p = Path(path)
    if p.is_dir() or p.suffix == "":
        p = p / "preprocess.json"
    with OutputDir(p.parent, p.name) as od:
        for sid, res in (results.items() if masks else ()):
            od.write_parquet(f"masks/{sid}.parquet", pa.table(
                {"row": res.row, "reason": res.reason, "patch": res.patch}))
        return od.commit(preprocess_json(results, config, campaign), indent=2)


def write_masks(out_dir, results: Mapping[str, PreprocessResult]) -> Path:
    """``out_dir/masks/<scan>.parquet``: ``row`` (file row), ``reason`` (uint8), ``patch``
    (each written to a temporary name and renamed)."""
    import pyarrow as pa


    d = Path(out_dir) / "masks"
    for sid, res in results.items():
        table = pa.table({"row": res.row, "reason": res.reason, "patch": res.patch})
        write_file_atomic(d / f"{sid}.parquet", lambda t, tb=table: write_table(tb, t),
                          durable=False)
    return d


def preprocess_table(results: Mapping[str, PreprocessResult], title: str = "preprocessing"):
    """A rich table: per scan, rows, kept and removed per stage, patches, epsilon, time."""
    from rich.table import Table

    t = Table(title=title)
    for c in ("scan", "rows", "kept", "non-finite", "range", "geometry", "RANSAC", "small patch",
              "patches", "eps mm", "time s"):
        t.add_column(c, justify="left" if c == "scan" else "right")
    for sid, res in results.items():
        s, rm = res.stats, res.stats["removed"]
        kept = f"{s['n_kept']:,} ({s['n_kept'] / max(s['n_rows'], 1):.1%})"
        t.add_row(sid, f"{s['n_rows']:,}", kept,
                  f"{rm['non_finite']:,}", f"{rm['range_window']:,}", f"{rm['geometry_window']:,}",
                  f"{rm['ransac_outlier']:,}", f"{rm['small_patch']:,}",
                  f"{s['n_patches_fitted']:,}/{s['n_patches']:,}",
                  f"{1e3 * res.params['epsilon_m']:.2f}", f"{s['timing_s']['total']:.1f}")
    return t


