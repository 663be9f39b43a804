"""The ``demo`` verb: simulate the demo campaign, fit it with both models, average the cycles,
print the comparison with the truth and write the report (a few MB; ``--full`` keeps the
per-point tables)."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import click

from ..campaign._campaign import load_campaign
from ..fit._fit import fit_campaign
from ..fit._records import write_fit
from ..physics._catalog import CALIBRATION
from ..preprocess import preprocess_keep
from ..report import write_report
from ..simulate._simulate import simulate_campaign
from ..surface._surface import (
    SurfaceConfig,
    point_spacing,
    surface_from_fit_dir,
    write_surface,
    write_surface_json,
)
from ._base import _console, command, main, print_fit_table


@main.command()
@click.option("--out", "out_dir", default="demo-output", show_default=True,
              type=click.Path(file_okay=False))
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--full", is_flag=True,
              help="Also keep the per-point tables: the simulated campaign (scans, truth "
                   "labels), residuals/ and the surface points/ and cycles/ of both models "
                   "(about 200 MB). Default: fit.json, surface.json, figures and the report "
                   "(a few MB).")
@command
def demo(out_dir, seed, full):
    """Simulate a two-cycle scan, fit it (simplified and extended), print, plot, report."""
    out = Path(out_dir)
    t0 = time.time()
    camp_dir = out / "campaign"
    simulated = not (camp_dir / "campaign.toml").exists()
    if simulated:
        click.echo("simulating the demo campaign (position r23, two cycles) ...")
        simulate_campaign(camp_dir, preset="demo", seed=seed)
    camp = load_campaign(camp_dir)
    keep = preprocess_keep(True, camp)
    fits, surfaces = {}, {}
    for model in ("simplified", "extended"):
        cf = fit_campaign(camp, model, keep=keep)
        write_fit(out / model, cf)
        print_fit_table(cf, title=f"demo: model {model}")
        fits[model] = cf
    truth = camp.root / "truth.json"
    if truth.exists():
        _print_truth_comparison(cf, json.loads(truth.read_text()))
    # cycle averaging in the paper's 1 cm circles, unless the two cycles' points miss each
    # other at 1 cm (a coarse scan on different grids): then the automatic radius
    for cfg in (SurfaceConfig(radius_m=_PAPER_RADIUS_M), None):
        surfaces = {m: surface_from_fit_dir(out / m, cfg, campaign=camp) for m in fits}
        if _paired_fraction(surfaces["extended"].positions) >= 0.8:
            break
    for model, surf in surfaces.items():
        write_surface(out / model, surf)
    _print_demo_averaging(surfaces["extended"], camp)

    # the report and its figures are made from the per-point tables, before they are dropped
    html = write_report(out, campaign=camp)
    click.echo(f"report: {html}")
    if not full:
        before = _dir_bytes(out)
        for model in fits:  # the same documents without their tables (manifests updated)
            write_fit(out / model, fits[model], residuals=False)
            write_surface_json(out / model / "surface.json", surfaces[model])
            for sub in ("residuals", "points", "cycles"):
                shutil.rmtree(out / model / sub, ignore_errors=True)
        if simulated:  # this run's simulation: its truth is kept, its scans are not
            if truth.exists():
                shutil.copyfile(truth, out / "truth.json")
            shutil.rmtree(camp_dir)
        click.echo(f"per-point tables not kept ({(before - _dir_bytes(out)) / 1e6:.0f} MB: "
                   "residuals, surface points"
                   + (", the simulated campaign; its truth in truth.json" if simulated else "")
                   + "); `hartrao-jax demo --full` keeps them")
    click.echo(f"demo done in {time.time() - t0:.1f} s; outputs in {out}/ "
               f"({_dir_bytes(out) / 1e6:.1f} MB)")


def _dir_bytes(path: Path) -> int:
    """Total size of the files under ``path``."""
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


_PAPER_RADIUS_M = 0.01  # the paper's averaging circles


def _paired_fraction(positions) -> float:
    """Fraction of the cycle-averaged positions' points that found a partner of the other cycle."""
    n = u = 0
    for p in positions:
        if p.kind == "cycle average":
            n += int(p.averaged.n1.sum() + p.averaged.n2.sum())
            u += int(p.averaged.n_unpaired)
    return n / (n + u) if n + u else 1.0


def _print_demo_averaging(surf, camp) -> None:
    """The demo's cycle-averaging radius against the paper's 1 cm, with the pairs it made."""

    step = getattr(camp.scanner, "angular_step_rad", None)
    for p in surf.positions:
        if p.kind != "cycle average":
            continue
        a = p.averaged
        n = int(a.n1.sum() + a.n2.sum())
        spacing = max(point_spacing(c.X[c.inside]) for c in p.cycles)
        grid = (f"{1e3 * step:.2g} mrad grid, " if step else "grid, ") + \
            f"{100 * spacing:.2g} cm between points on the dish"
        pairs = (f"{len(a):,} circles with points of both cycles, {n:,} points averaged, "
                 f"{int(a.n_unpaired):,} ({1 - _paired_fraction([p]):.1%}) without a partner")
        if p.radius_m <= _PAPER_RADIUS_M * (1 + 1e-9):
            click.echo(f"cycle averaging {p.position}: circles of 1 cm as in the paper ({pairs}). "
                       f"The demo's scan is coarser than the paper's ({grid}; the paper: "
                       "6.3 mm at 10 m), but both cycles sample the same directions, so 1 cm "
                       f"circles still pair them ({n / max(len(a), 1) / 2:.1f} points of each "
                       "cycle per circle on average).")
        else:
            click.echo(f"cycle averaging {p.position}: circles of {100 * p.radius_m:.2g} cm, not "
                       f"the paper's 1 cm: at 1 cm fewer than 80 % of the points found a partner "
                       f"of the other cycle on this coarse scan ({grid}; the paper: 6.3 mm at "
                       f"10 m), so the radius is 0.75 x the point spacing ({pairs}).")


def _print_truth_comparison(cf, truth: dict) -> None:
    """Estimates against the simulator's truth, in units of their own sigma."""
    from rich.table import Table

    t = Table(title="fit against the simulator's truth",
              caption="The simulated reflector carries panel deviations (0.15 mm rms) that no "
                      "paraboloid contains; the surface random effect carries them in the sigmas.")
    for c in ("position", "parameter", "truth", "estimate", "sigma", "(est-truth)/sigma"):
        t.add_column(c, justify="right")
    scans = {s["id"]: s for s in truth.get("scans", [])}
    units = [(p.position, p.scans[0].meta.id, list(zip(p.names, p.x, p.sigma)))
             for p in cf.position_fits] or [
        (s.meta.id, s.meta.id, [(n, v, sg) for n, (v, sg) in s.estimates.items()])
        for s in cf.scans]
    for unit, sid, est in units:
        tr = dict(scans.get(sid, {}))
        tr.update(tr.get("model_parameters", {}))
        for n, v, sg in est:
            tv = tr.get(n, 0.0 if n in CALIBRATION else None)
            if isinstance(tv, (int, float)):
                t.add_row(unit, n, f"{tv:.7g}", f"{v:.7g}", f"{sg:.2g}", f"{(v - tv) / sg:+.2f}")
    _console().print(t)
