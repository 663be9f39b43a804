"""The pipeline verbs: ``simulate``, ``preprocess``, ``fit`` and ``demo``."""

from __future__ import annotations

import time
from pathlib import Path

import click

from ..campaign._campaign import load_campaign
from ..fit._fit import fit_campaign
from ..fit._joint import fit_joint, write_joint_fit
from ..fit._records import write_fit
from ..physics._catalog import CALIBRATION_OPTION
from ..preprocess import (
    PreprocessConfig,
    preprocess_campaign,
    preprocess_keep,
    preprocess_table,
)
from ..simulate._simulate import parse_effects, simulate_campaign
from ..surface._disturbed import detect_disturbed_campaign, keep_function, without_disturbed
from ._base import (
    UserError,
    _console,
    _names,
    _parse_fixes,
    command,
    disturbed_mode,
    fitting_options,
    main,
    model_option,
    print_fit_table,
)
from ._tables import print_joint_summary


@main.command()
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--preset", default="demo", show_default=True,
              help="Simulation preset (demo, clean, paper, campaign, tour-red).")
@click.option("--effect", "effects", multiple=True, metavar="ID=VALUE",
              help="Add an effect of the physics catalog, e.g. x2=3e-4 or impulsive_shift=0.002; "
                   "sub-parameters as ID.KEY=VALUE.")
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--step", "step_rad", type=float, default=None, help="Angular step (rad).")
@command
def simulate(out, preset, effects, seed, step_rad):
    """Simulate a campaign (scans + truth) into OUT."""

    t0 = time.time()
    camp = simulate_campaign(out, preset=preset, effects=parse_effects(list(effects)), seed=seed,
                             step_rad=step_rad)
    click.echo(f"wrote {len(camp.scans)} scans to {out} ({time.time() - t0:.1f} s)")


@main.command()
@click.argument("campaign", type=click.Path(exists=True))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False))
@click.option("--d-min", "d_min_m", type=float, default=None, help="Range window minimum (m).")
@click.option("--d-max", "d_max_m", type=float, default=None, help="Range window maximum (m).")
@click.option("--patch-size", "patch_size_m", type=float, default=None,
              help="Patch side at the reflector's range (m); default automatic (0.3 m).")
@click.option("--epsilon", "epsilon_m", type=float, default=None,
              help="RANSAC inlier distance (m); default 4.5 sigma + allowance.")
@click.option("--seed", default=0, show_default=True, type=int)
@command
def preprocess(campaign, out_dir, d_min_m, d_max_m, patch_size_m, epsilon_m, seed):
    """Clean every scan: range window, angular patches, RANSAC planes; OUT/preprocess.json."""

    camp = load_campaign(campaign)
    cfg = PreprocessConfig(d_min_m=d_min_m, d_max_m=d_max_m, patch_size_m=patch_size_m,
                           epsilon_m=epsilon_m, seed=seed)
    results = preprocess_campaign(camp, cfg, out_dir=out_dir, progress=True)
    _console().print(preprocess_table(results, f"{camp.telescope.name}: preprocessing"))
    click.echo(f"wrote {Path(out_dir) / 'preprocess.json'}")


@main.command()
@click.argument("campaign", type=click.Path(exists=True))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False))
@model_option()
@click.option("--scans", default=None, help="Comma-separated scan ids (default: all).")
@click.option("--fix", "fixes", multiple=True, metavar="NAME=VALUE",
              help="Hold a parameter at a value (e.g. x10=0.0012).")
@click.option("--robust-k", default=4.0, show_default=True, type=float,
              help="Reject points beyond k a-posteriori sigmas (0: off).")
@click.option("--per-cycle", is_flag=True,
              help="Fit every cycle by itself with white-noise sigmas (the paper's procedure) "
                   "instead of one two-face adjustment per position with the surface as a "
                   "random effect (the default).")
@click.option("--batch/--no-batch", default=False, show_default=True,
              help="With --per-cycle: fit all scans in one compiled call (padded, masked).")
@fitting_options("Clean scans (range window, patches, RANSAC) before fitting.")
@click.option("--joint", is_flag=True,
              help="Calibration shared by the scans of a night (--group) solved by Schur "
                   "complement.")
@click.option("--shared", default=CALIBRATION_OPTION, show_default=True,
              help="With --joint: the calibration parameters shared across scans.")
@click.option("--group", type=click.Choice(["night", "campaign"]), default="night",
              show_default=True, help="With --joint: share per night (tour) or campaign.")
@command
def fit(campaign, out_dir, model, scans, fixes, robust_k, per_cycle, batch, preprocess,
        exclude_disturbed, cut_disturbed, joint, shared, group):
    """Fit every scan of CAMPAIGN; writes OUT/fit.json and OUT/residuals/*.parquet."""

    mode = disturbed_mode(exclude_disturbed, cut_disturbed)
    camp = load_campaign(campaign)
    fixed = _parse_fixes(fixes)
    scan_ids = scans.split(",") if scans else None
    keep = preprocess_keep(preprocess, camp)
    if joint:
        try:
            jf = fit_joint(camp, model, shared=_names(shared), group=group, scans=scan_ids,
                           fixed=fixed, keep=keep, robust_k=robust_k or None, batch=batch,
                           progress=True)
        except ValueError as e:
            raise UserError(str(e)) from None
        p = write_joint_fit(out_dir, jf)
        print_joint_summary(jf, _console())
        click.echo(f"wrote {p}")
        return
    per_cycle = per_cycle or batch
    cf = fit_campaign(camp, model, scans=scan_ids, fixed=fixed, robust_k=robust_k or None,
                      batch=batch, keep=keep, per_cycle=per_cycle)
    if mode is not None:
        # the disturbed-scan checks compare the two cycles of a position: per-cycle fits
        check = cf if per_cycle else fit_campaign(
            camp, model, scans=scan_ids, fixed=fixed, robust_k=robust_k or None, keep=keep,
            per_cycle=True, progress=False)
        reports = detect_disturbed_campaign(check)
        for r in reports:
            click.echo(f"disturbed: scan {r.scan} cycle {r.cycle} from phi {r.phi_deg:.2f} deg "
                       f"to {r.phi_end_deg:.2f} deg (jump {r.jump_m * 1e3:+.2f} mm)")
        if reports:
            ids = [s.meta.id for s in cf.scans]
            if mode == "exclude":
                ids = without_disturbed(ids, reports)
                cf = fit_campaign(camp, model, scans=ids, fixed=fixed,
                                  robust_k=robust_k or None, batch=batch, keep=keep,
                                  per_cycle=per_cycle)
            else:
                cf = fit_campaign(camp, model, scans=ids, fixed=fixed,
                                  robust_k=robust_k or None, batch=batch,
                                  keep=keep_function(reports, base=keep), per_cycle=per_cycle)
    p = write_fit(out_dir, cf)
    print_fit_table(cf, title=f"{camp.telescope.name}: model {model}")
    click.echo(f"wrote {p}")
