"""Commands of the discrepancy engine: ``hartrao-jax diagnose`` and ``hartrao-jax prove``.

Imported by :mod:`hartrao_jax.cli` (the commands register themselves on its group).
"""

from __future__ import annotations

import time

import click

from ..diagnose import DiagnoseConfig, write_json
from ..model import format_estimate
from ..physics._catalog import EFFECTS, INSTRUMENT
from ..preprocess import preprocess_keep
from ..prove._prove import CASES, run_prove
from ..prove._prove import detectability as mda
from ..report._diagnosis import diagnose_with_report
from ._base import UserError, _console, _names, command, main


def print_diagnosis(diag) -> None:
    """Findings and confounded parameters as tables on the terminal."""
    from rich.table import Table

    t = Table(title=f"diagnosis: sigma0 {diag.sigma0_start:.4f} -> {diag.sigma0_final:.4f}, "
                    f"rms {1e3 * diag.rms_start_m:.4f} -> {1e3 * diag.rms_final_m:.4f} mm")
    for c in ("#", "effect", "family", "scans", "T (dof)", "effect [mm]", "sigma0", "explanation"):
        t.add_column(c, overflow="fold")
    for i, f in enumerate(diag.findings):
        t.add_row(str(i + 1), f.effect, f.family, ",".join(f.scans), f"{f.statistic:.1f} ({f.dof})",
                  f"{1e3 * f.effect_size_m:.4f}", f"{f.sigma0_before:.3f} -> {f.sigma0_after:.3f}",
                  f.explanation)
    _console().print(t)
    if diag.positions:
        _console().print(_positions_table(diag.positions))
    if diag.confounded:
        c = Table(title="confounded with the model (never reported as findings)")
        for col in ("effect", "with", "correlation"):
            c.add_column(col)
        for row in diag.confounded:
            c.add_row(row["effect"], ", ".join(row["with"]), f"{row['correlation']:.6f}")
        _console().print(c)


def _positions_table(positions: list[dict]):
    """The final model's estimates per position (both faces, the surface a random effect)."""
    from rich.table import Table

    t = Table(title="final estimates per position (faces together, surface as a random effect)")
    for c in ("position", "faces", "f (m)", "calibration", "not identifiable"):
        t.add_column(c, overflow="fold")
    for p in positions:
        est = p["estimates"]
        f = est.get("f", {})
        cal = [f"{n} = {format_estimate(n, e['value'], e['sigma'])}" for n, e in est.items()
               if n in INSTRUMENT and e.get("value") is not None]
        held = [n for n, e in est.items() if e.get("identifiable") is False]
        t.add_row(p["position"], str(p["faces"]),
                  f"{f['value']:.5f} ± {1e3 * f['sigma']:.3f} mm" if f.get("value") else "-",
                  "; ".join(cal), ", ".join(held) or "-")
    return t


@main.command("diagnose")
@click.argument("campaign", type=click.Path(exists=True))
@click.option("--json", "json_path", required=True, type=click.Path(dir_okay=False),
              help="Write the hartrao-diagnosis/1 document here.")
@click.option("--from", "start", type=click.Choice(["simplified", "extended"]),
              default="extended", show_default=True, help="Start model.")
@click.option("--report", "report_dir", default=None, type=click.Path(file_okay=False),
              help="Write residual maps, evidence plots and index.html here.")
@click.option("--scans", default=None, help="Comma-separated scan ids (default: all, jointly).")
@click.option("--effects", default=None,
              help="Comma-separated effect ids to test (default: the whole catalog).")
@click.option("--alpha", default=1e-6, show_default=True, type=float,
              help="False-alarm probability of one step (Bonferroni over the candidates).")
@click.option("--min-effect-mm", default=0.01, show_default=True, type=float,
              help="Practical effect size: predicted rms change of the fit a finding must reach.")
@click.option("--max-steps", default=10, show_default=True, type=int)
@click.option("--preprocess/--no-preprocess", default=False, show_default=True,
              help="Clean scans (range window, patches, RANSAC) first.")
@command
def diagnose_command(campaign, json_path, start, report_dir, scans, effects, alpha,
                     min_effect_mm, max_steps, preprocess):
    """Locate the mismatch between CAMPAIGN and the model, explain and model it."""

    eff = _names(effects) or None
    bad = [e for e in eff or () if e not in EFFECTS]
    if bad:
        raise UserError(f"--effects: unknown effect id(s) {', '.join(bad)}; known: "
                        f"{', '.join(EFFECTS)}")
    cfg = DiagnoseConfig(alpha=alpha, min_effect_m=min_effect_mm * 1e-3, max_steps=max_steps,
                         effects=eff)
    t0 = time.time()
    diag = diagnose_with_report(campaign, start, config=cfg,
                                scans=scans.split(",") if scans else None,
                                keep=preprocess_keep(preprocess), report_dir=report_dir)
    p = write_json(diag, json_path)
    print_diagnosis(diag)
    click.echo(f"wrote {p} ({time.time() - t0:.1f} s)")
    if report_dir:
        click.echo(f"report: {report_dir}/index.html")


@main.command("prove")
@click.option("--out", "out_dir", default="prove-output", show_default=True,
              type=click.Path(file_okay=False))
@click.option("--seeds", default=3, show_default=True, type=int, help="Seeds per case.")
@click.option("--cases", default=None,
              help="Comma-separated case names (default: all; see --list).")
@click.option("--step", "step_rad", default=0.01, show_default=True, type=float,
              help="Angular step of the simulated scans (rad).")
@click.option("--list", "list_cases", is_flag=True, help="List the cases and exit.")
@click.option("--keep-campaigns", is_flag=True, help="Keep the simulated campaigns.")
@click.option("--detectability", is_flag=True,
              help="Only the minimal detectable amplitudes on a clean campaign.")
@command
def prove_command(out_dir, seeds, cases, step_rad, list_cases, keep_campaigns, detectability):
    """Prove the diagnosis on simulated campaigns where each effect is concealed."""
    from pathlib import Path


    if detectability:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        rows = mda(out_dir, step_rad=step_rad)
        for r in rows:
            click.echo(f"{r['effect']:16s} {r['parameter']:12s} {r['minimal_detectable']:10.3g} "
                       f"{r['unit']:5s} {r['relative_to_range_noise']:7.3f} x noise "
                       f"({r['limited_by']})")
        click.echo(f"wrote {out_dir}/detectability-{step_rad:g}.md")
        return
    if list_cases:
        for c in CASES:
            click.echo(f"{c.name:22s} {c.description}")
        return
    names = [c.strip() for c in cases.split(",")] if cases else None
    known = {c.name for c in CASES}
    bad = [n for n in names or () if n not in known]
    if bad:
        raise UserError(f"--cases: unknown case(s) {', '.join(bad)}; known: {', '.join(known)}")
    res = run_prove(out_dir, seeds=seeds, cases=names, step_rad=step_rad,
                    keep_campaigns=keep_campaigns, progress=True)
    print_table(res)
    click.echo(f"wrote {res['paths']['json']} and {res['paths']['table']}")


def print_table(res: dict) -> None:
    """The prove table (one row per concealed case)."""
    from rich.table import Table

    t = Table(title="diagnosis on concealed data")
    for c in ("case", "amplitude/noise", "found", "located", "estimate", "improved",
              "false alarms", "time [s]"):
        t.add_column(c, justify="right")
    for r in res["table"]:
        t.add_row(r["case"], f"{r['amplitude_rel_noise']:.3f}", r["found"], r["located"],
                  r["estimate"], r["improved"],
                  r["false_alarms"] + (f" ({','.join(r['false_effects'])})"
                                       if r["false_effects"] else ""),
                  f"{r['mean_time_s']:.1f}")
    _console().print(t)
