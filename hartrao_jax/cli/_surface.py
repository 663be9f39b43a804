"""Commands ``hartrao-jax surface`` and ``hartrao-jax report`` (imported by :mod:`.cli`)."""

from __future__ import annotations

import time
from pathlib import Path

import click

from ..campaign._campaign import load_campaign
from ..report import write_report
from ..surface._surface import SurfaceConfig, surface_campaign
from ._base import UserError, command, disturbed_mode, fitting_options, main, model_option


@main.command()
@click.argument("campaign", type=click.Path(exists=True))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output directory: surface.json, points/, cycles/ (and fit/ when fitting).")
@click.option("--fit", "fit_dir", type=click.Path(exists=True, file_okay=False), default=None,
              help="Use this fit output (fit.json + residuals/) instead of fitting.")
@model_option("Model of the adjustment when fitting here.")
@click.option("--margin", "margin_m", type=float, default=0.02, show_default=True,
              help="Panel edge mask, radial and tangential (m).")
@click.option("--margin-radial", type=float, default=None, help="Radial edge mask (m).")
@click.option("--margin-tangential", type=float, default=None, help="Tangential edge mask (m).")
@click.option("--radius", "radius_m", type=float, default=None,
              help="Cycle-averaging radius (m); default 1 cm, more on coarse scans.")
@fitting_options("Clean scans before fitting (when fitting here).")
@click.option("--report/--no-report", "with_report", default=False, show_default=True,
              help="Also write OUT/report.html.")
@command
def surface(campaign, out_dir, fit_dir, model, margin_m, margin_radial, margin_tangential,
            radius_m, preprocess, exclude_disturbed, cut_disturbed, with_report):
    """Surface products of CAMPAIGN: panels, cycle averages, OUT/surface.json."""

    mode = disturbed_mode(exclude_disturbed, cut_disturbed)
    try:
        cfg = SurfaceConfig(
            margin_radial_m=margin_m if margin_radial is None else margin_radial,
            margin_tangential_m=margin_m if margin_tangential is None else margin_tangential,
            radius_m=radius_m, model=model)
    except ValueError as e:
        raise UserError(f"surface: {e}") from None
    t0 = time.time()
    camp = load_campaign(campaign)
    if camp.telescope.ring_edges_m is None or camp.telescope.panels_per_ring is None:
        click.echo("note: the campaign has no panel layout: no panel products, points only",
                   err=True)
    res = surface_campaign(camp, cfg, out_dir, fit_dir=fit_dir, preprocess=preprocess,
                           disturbed=mode, progress=True)
    _print_summary(res)
    if with_report:
        click.echo(f"report: {write_report(out_dir, campaign=camp)}")
    click.echo(f"wrote {Path(out_dir) / 'surface.json'} ({time.time() - t0:.1f} s)")


def _print_summary(res) -> None:
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    t = Table(title="surface (deviations in mm, + towards the focus)")
    for c in ("position", "kind", "rms per cycle", "rms averaged", "points", "worst panels"):
        t.add_column(c, justify="right")
    for p in res.positions:
        worst = ""
        if p.panels is not None:
            d = p.panels.deviation_m
            order = np.argsort(-np.nan_to_num(np.abs(d), nan=-1))[:3]
            worst = ", ".join(f"{int(i)}: {1e3 * d[i]:+.2f}" for i in order if np.isfinite(d[i]))
        t.add_row(p.position, p.kind, " ".join(f"{1e3 * c.rms_m:.3f}" for c in p.cycles),
                  f"{1e3 * p.averaged.rms_m:.3f}", f"{len(p.averaged):,}", worst)
    con = Console(markup=False, highlight=False)
    con.print(t)
    for d in res.disturbed:
        a, b = d["phi_range_deg"]
        con.print(f"disturbed: {d['scan']} (cycle {d['cycle']}) phi {a:.1f}..{b:.1f} deg, jump "
                  f"{1e3 * d['jump_m']:+.2f} mm, statistic {d['statistic']:.1f} "
                  f"[{d.get('action', 'reported')}]")


@main.command()
@click.argument("results_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--campaign", "campaign_dir", type=click.Path(exists=True), default=None,
              help="The campaign (panel layout, nominal focal length, truth of simulations); "
                   "default: the one fit.json names.")
@click.option("--out", "out_file", type=click.Path(dir_okay=False), default=None,
              help="HTML file (default RESULTS_DIR/report.html).")
@click.option("--max-positions", default=4, show_default=True, type=int,
              help="Dish maps for at most this many positions.")
@command
def report(results_dir, campaign_dir, out_file, max_positions):
    """One self-contained HTML page (figures + tables) for RESULTS_DIR."""

    camp = None
    if campaign_dir:
        camp = load_campaign(campaign_dir)
    t0 = time.time()
    p = write_report(results_dir, campaign=camp, out=out_file, max_positions=max_positions)
    click.echo(f"wrote {p} ({time.time() - t0:.1f} s)")
