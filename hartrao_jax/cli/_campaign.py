"""Campaign-scale commands (imported by :mod:`.cli`): ``schedule``, ``fit-joint``, ``gravity``,
``sensitivity``, ``fit-dask`` and ``fit-stream``."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np

from ..campaign._campaign import load_campaign
from ..campaign._safeio import strict_json, write_json_atomic
from ..campaign._schedule import TOURS, campaign_plan, check_plan, plan_table
from ..fit._distributed import close_client, fit_dask, start_client
from ..fit._fit import fit_campaign
from ..fit._joint import fit_joint, write_joint_fit
from ..fit._stream import stream_fit_campaign, stream_scan_document
from ..fit._stream_position import stream_fit_positions
from ..physics._catalog import CALIBRATION_OPTION
from ..preprocess import preprocess_keep
from ..sensitivity._sensitivity import finite_difference, sensitivity_table, write_sensitivity
from ..sensitivity._sensitivity import sensitivity as run
from ..surface._gravity import write_gravity
from ._base import UserError, _console, _names, _parse_fixes, command, main
from ._tables import print_gravity_summary, print_joint_summary


@main.command()
@click.option("--tour", "tours", multiple=True,
              type=click.Choice(["red", "green", "blue", "magenta"]),
              help="Only these tours (default: all four).")
@click.option("--json", "json_file", type=click.Path(dir_okay=False), default=None,
              help="Also write the plan as JSON.")
@command
def schedule(tours, json_file):
    """The measurement plan: four tours, 88 positions, start times and temperatures."""

    plan = campaign_plan(tours or TOURS)
    click.echo(plan_table(plan))
    problems = check_plan(plan) if not tours else []
    for p in problems:
        click.echo(f"warning: {p}", err=True)
    if json_file:
        write_json_atomic(json_file, {"schema": "hartrao-schedule/1",
                                      "positions": [p.as_dict() for p in plan]}, indent=1)
        click.echo(f"wrote {json_file}")


@main.command("fit-joint")
@click.argument("campaign", type=click.Path(exists=True))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False))
@click.option("--model", default="extended", show_default=True)
@click.option("--shared", default=CALIBRATION_OPTION, show_default=True,
              help="Calibration parameters estimated once per group.")
@click.option("--group", type=click.Choice(["night", "campaign"]), default="night",
              show_default=True, help="Share per night (tour) or over the whole campaign.")
@click.option("--scans", default=None, help="Comma-separated scan ids (default: all).")
@click.option("--fix", "fixes", multiple=True, metavar="NAME=VALUE")
@click.option("--robust-k", default=4.0, show_default=True, type=float)
@click.option("--batch/--no-batch", default=False, show_default=True)
@click.option("--preprocess/--no-preprocess", default=True, show_default=True)
@command
def fit_joint_command(campaign, out_dir, model, shared, group, scans, fixes, robust_k, batch,
                      preprocess):
    """Joint adjustment: calibration shared per night or campaign (Schur complement)."""

    camp = load_campaign(campaign)
    t0 = time.time()
    try:
        jf = fit_joint(camp, model, shared=_names(shared), group=group,
                       scans=scans.split(",") if scans else None, fixed=_parse_fixes(fixes),
                       keep=preprocess_keep(preprocess, camp), robust_k=robust_k or None,
                       batch=batch, progress=True)
    except ValueError as e:
        raise UserError(str(e)) from None
    p = write_joint_fit(out_dir, jf)
    print_joint_summary(jf, _console())
    click.echo(f"wrote {p} ({time.time() - t0:.1f} s)")


@main.command()
@click.argument("results_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--out", "out_dir", default=None, type=click.Path(file_okay=False),
              help="Output directory (default: RESULTS_DIR).")
@click.option("--modes", default="4,5,6,7,8,11", show_default=True,
              help="Zernike modes (Noll) of the surface model; empty for none.")
@click.option("--temperature/--no-temperature", default=False, show_default=True,
              help="Add df/dT (T - 15 C) to the focal-length model.")
@click.option("--grid-step", "step_deg", default=2.0, show_default=True, type=float,
              help="HA/DEC step of the sky map (deg).")
@click.option("--figures/--no-figures", default=True, show_default=True)
@command
def gravity(results_dir, out_dir, modes, temperature, step_deg, figures):
    """Gravity model over the sky from a fit (RESULTS_DIR with fit.json and residuals/)."""

    try:
        p, gm = write_gravity(results_dir, out_dir, modes=[int(m) for m in _names(modes)],
                              temperature=temperature, step_deg=step_deg, figures=figures)
    except ValueError as e:
        raise UserError(f"{results_dir}: {e}") from None
    print_gravity_summary(gm, _console())
    click.echo(f"wrote {p}")


@main.command()
@click.argument("campaign", type=click.Path(exists=True))
@click.option("--json", "json_file", required=True, type=click.Path(dir_okay=False))
@click.option("--model", default="extended", show_default=True,
              help="Model of the fit the derivatives are taken at.")
@click.option("--params", default=CALIBRATION_OPTION, show_default=True,
              help="Calibration parameters held fixed (at their estimates, or --fix values).")
@click.option("--fix", "fixes", multiple=True, metavar="NAME=VALUE")
@click.option("--scans", default=None, help="Comma-separated scan ids (default: all).")
@click.option("--joint/--no-joint", default=False, show_default=True,
              help="Hold the parameters at their joint (campaign) estimates.")
@click.option("--batch/--no-batch", default=False, show_default=True)
@click.option("--preprocess/--no-preprocess", default=True, show_default=True)
@click.option("--validate", "n_validate", default=0, show_default=True, type=int,
              help="Check the first N scans against finite differences (refits).")
@command
def sensitivity(campaign, json_file, model, params, fixes, scans, joint, batch, preprocess,
                n_validate):
    """Implicit derivatives of f, panels and sigma0 w.r.t. calibration and scan design."""
    camp = load_campaign(campaign)
    t0 = time.time()
    # implicit derivatives of the per-scan adjustment
    picked = scans.split(",") if scans else None
    if joint and all(camp.scan(s).cycle == 0 for s in picked or [m.id for m in camp.scans]):
        raise UserError("--joint: every scan is one face (cycle 0), whose two-face calibration "
                        "parameters are held, not estimated: there is no joint estimate to hold "
                        "them at; expected two-face scans, or no --joint")
    keep = preprocess_keep(preprocess, camp)
    start = fit_campaign(camp, model, scans=picked, fixed=_parse_fixes(fixes), keep=keep,
                         batch=batch, per_cycle=True)
    # the two-face adjustments (surface random effect): what of sigma(f) a finer step cannot buy
    two = fit_campaign(camp, model, scans=picked, fixed=_parse_fixes(fixes), keep=keep)
    if joint:
        start = fit_joint(camp, model, shared=[p for p in _names(params) if p in start.model_names],
                          group="campaign", start=start).campaign_fit()
    cs = run(camp, start, _names(params), positions=two.position_fits)
    validation = None
    if n_validate:
        rows = []
        for s, ss in list(zip(start.scans, cs.scans))[:n_validate]:
            fd = finite_difference(camp, s, cs.params)
            err = float(np.max(np.abs(fd["dxdp"] - ss.dxdp)) / np.max(np.abs(ss.dxdp)))
            rows.append({"scan": s.meta.id, "max_relative_difference": err,
                         "df_dp_implicit": ss.df_dp.tolist(),
                         "df_dp_finite_difference": fd["dxdp"][ss.names.index("f")].tolist()})
        validation = {"method": "central differences, refit with p +- 1 arcsec", "scans": rows}
    p = write_sensitivity(json_file, cs, figures_dir=Path(json_file).parent, validation=validation)
    click.echo(sensitivity_table(cs))
    click.echo(f"wrote {p} ({time.time() - t0:.1f} s)")


@main.command("fit-dask")
@click.argument("campaign", type=click.Path(exists=True))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False))
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="An existing Dask scheduler (default: a LocalCluster).")
@click.option("--workers", "n_workers", default=2, show_default=True, type=int,
              help="Worker processes of the LocalCluster (one thread each).")
@click.option("--model", default="extended", show_default=True)
@click.option("--scans", default=None, help="Comma-separated scan ids (default: all).")
@click.option("--fix", "fixes", multiple=True, metavar="NAME=VALUE")
@click.option("--robust-k", default=4.0, show_default=True, type=float)
@click.option("--preprocess/--no-preprocess", default=True, show_default=True)
@click.option("--joint/--no-joint", default=False, show_default=True,
              help="Joint adjustment with shared calibration (Schur complement on the workers).")
@click.option("--shared", default=CALIBRATION_OPTION, show_default=True)
@click.option("--group", type=click.Choice(["night", "campaign"]), default="night",
              show_default=True)
@click.option("--per-cycle", is_flag=True,
              help="One task per scan, each cycle alone (default: one task per position, both "
                   "faces adjusted together with the surface as a random effect).")
@command
def fit_dask_command(campaign, out_dir, scheduler, n_workers, model, scans, fixes, robust_k,
                     preprocess, joint, shared, group, per_cycle):
    """Fit CAMPAIGN on Dask workers; writes the same OUT/fit.json as `fit`."""

    camp = load_campaign(campaign)
    try:
        res = fit_dask(camp, model, scheduler=scheduler, n_workers=n_workers,
                       scans=scans.split(",") if scans else None, fixed=_parse_fixes(fixes),
                       robust_k=robust_k or None, preprocess=preprocess, out_dir=out_dir,
                       joint=joint, shared=_names(shared), group=group, per_cycle=per_cycle)
    except ValueError as e:
        raise UserError(str(e)) from None
    n = len(res.summaries)
    rate = 60 * n / max(res.seconds, 1e-9)
    click.echo(f"fitted {n} scans on {res.n_workers} workers in {res.seconds:.1f} s "
               f"({rate:.1f} scans/min); wrote {Path(out_dir) / 'fit.json'}")


@main.command("fit-stream")
@click.argument("campaign", type=click.Path(exists=True))
@click.option("--scan", "scan_ids", multiple=True,
              help="Scan id (repeatable, or comma-separated; default: every scan).")
@click.option("--model", default="extended", show_default=True)
@click.option("--rows-per-chunk", default=1_000_000, show_default=True, type=int)
@click.option("--store", default=None, type=click.Path(file_okay=False),
              help="Directory of the per-point results (v, weights, standardized residuals; "
                   "one sub-directory per scan for several scans; default: not kept, a temporary "
                   "directory removed at the end).")
@click.option("--json", "json_file", default=None, type=click.Path(dir_okay=False))
@click.option("--robust-k", default=4.0, show_default=True, type=float)
@click.option("--dask/--no-dask", "use_dask", default=False, show_default=True,
              help="One task per position (per scan with --per-cycle) on Dask workers.")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="With --dask: an existing scheduler (default: a LocalCluster).")
@click.option("--workers", default=2, show_default=True, type=int,
              help="With --dask: worker processes of the LocalCluster (one thread each).")
@click.option("--per-cycle", is_flag=True, default=False,
              help="Each scan by itself, white noise (the paper's procedure) instead of one "
                   "two-face adjustment per position with the surface a random effect.")
@command
def fit_stream(campaign, scan_ids, model, rows_per_chunk, store, json_file, robust_k, use_dask,
               scheduler, workers, per_cycle):
    """Adjust full-resolution scans streaming them from disk with bounded memory.

    Default: one adjustment per position from both faces (the scans selected), the surface a
    random effect, started from a sample of each face and refined from every row; writes a
    ``hartrao-stream-campaign/1`` document with ``positions[]`` (as fit.json's) and
    ``scans[]``. ``--per-cycle``: one scan (``--scan ID``) writes a ``hartrao-stream/1`` record,
    several a ``hartrao-stream-campaign/1`` document with one record per scan. ``--dask``: one
    task per position (per scan with ``--per-cycle``) on Dask workers.
    """

    camp = load_campaign(campaign)
    ids = [s.strip() for v in scan_ids for s in v.split(",") if s.strip()]
    if not per_cycle:
        _fit_stream_positions(camp, ids, model, rows_per_chunk, store, json_file, robust_k,
                              use_dask, scheduler, workers)
        return
    if len(ids) == 1 and not use_dask:
        doc = stream_scan_document(camp, ids[0], model, store, rows_per_chunk,
                                   robust_k or None)
        if json_file:
            write_json_atomic(json_file, doc, indent=1)
        click.echo(json.dumps(strict_json({k: doc[k] for k in (
            "scan", "sigma0", "n_points", "iterations", "passes", "seconds", "peak_rss_gib")}),
            allow_nan=False))
        f = doc["estimates"]["f"]
        click.echo(f"f = {f['value']:.6f} ± {f['sigma']:.6f} m")
        return
    doc = _streamed(stream_fit_campaign, camp, ids, model, rows_per_chunk, store, json_file,
                    robust_k, use_dask, scheduler, workers)
    for rec in doc["scans"]:
        f = rec["estimates"]["f"]
        click.echo(f"{rec['scan']}: f = {f['value']:.6f} ± {f['sigma']:.6f} m, sigma0 "
                   f"{rec['sigma0']:.3f}, {rec['n_points']:,} points, {rec['passes']} passes, "
                   f"{rec['seconds']:.1f} s, peak {rec['peak_rss_gib']:.2f} GiB")
    click.echo(f"streamed {len(doc['scans'])} scans in {doc['seconds']:.1f} s")


def _streamed(run, camp, ids, model, rows_per_chunk, store, json_file, robust_k, use_dask,
              scheduler, workers) -> dict:
    """``run(camp, ids, model, ...)`` (a streamed fit of scans or positions), on Dask workers
    with ``use_dask``; its document is written to ``json_file`` when given and returned."""
    client = cluster = None
    if use_dask:
        client, cluster = start_client(scheduler, n_workers=workers, keep_freed=True)
    try:
        doc = run(camp, ids or None, model, store=store, rows_per_chunk=rows_per_chunk,
                  robust_k=robust_k or None, client=client, progress=True)
    finally:
        if client is not None:
            close_client(client, cluster)
    if json_file:
        write_json_atomic(json_file, doc, indent=1)
    return doc


def _fit_stream_positions(camp, ids, model, rows_per_chunk, store, json_file, robust_k, use_dask,
                          scheduler, workers):
    """``fit-stream`` without ``--per-cycle``: one streamed two-face adjustment per position."""
    doc = _streamed(stream_fit_positions, camp, ids, model, rows_per_chunk, store, json_file,
                    robust_k, use_dask, scheduler, workers)
    for rec in doc["positions"]:
        f = rec["f"]
        click.echo(f"{rec['position']}: {rec['faces']} face(s), f = {f['value']:.6f} ± "
                   f"{f['sigma']:.6f} m, sigma0 {rec['sigma0']:.3f}, {rec['n_points']:,} of "
                   f"{rec['n_rows']:,} rows, {rec['passes']} passes, {rec['seconds']:.1f} s, "
                   f"peak {rec['peak_rss_gib']:.2f} GiB")
        for n, e in rec.items():
            if isinstance(e, dict) and e.get("identifiable") is False:
                click.echo(f"  not identifiable: {e['note']}")
    click.echo(f"streamed {len(doc['positions'])} positions ({len(doc['scans'])} scans) in "
               f"{doc['seconds']:.1f} s")
