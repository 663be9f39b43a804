"""The command group, one-line errors, the console and the result table every verb shares.

Every command reports bad input as one line ``error: <file>: <field>: <expectation>`` on
stderr with exit status 2 (no traceback unless ``--debug``).
"""

from __future__ import annotations

import functools
import importlib
import logging
import os
import sys

import click

from .._config import (
    enable_compilation_cache,
    enable_x64,
    keep_freed_memory,
    set_blas_threads,
)
from ..campaign._campaign import CampaignError
from ..model._model import ModelError, parameter_unit
from ..simulate._simulate import EffectError
from ._checks import OneLineGroup, parse_fixes, validate_command


class UserError(Exception):
    """An error worth one line to the user."""


def _user_errors():
    errs = (CampaignError, ModelError, UserError, FileNotFoundError)

    return errs + (EffectError,)


def command(fn):
    """Wrap a command: JAX set-up, logging, one-line errors."""

    @functools.wraps(fn)
    @click.pass_context
    def wrapper(ctx, *args, **kwargs):
        debug = ctx.obj.get("debug", False) if ctx.obj else False
        enable_x64()
        enable_compilation_cache()
        keep_freed_memory()
        set_blas_threads()
        try:
            validate_command(ctx, kwargs)  # options, paths, inputs: before any work
            return fn(*args, **kwargs)
        except _user_errors() as e:
            if debug:
                raise
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            click.echo(f"error: {msg}", err=True)
            sys.exit(2)

    return wrapper


VERBS: dict[str, tuple[str, str]] = {
    "demo": ("_demo:demo", "Simulate a two-cycle scan, fit it (simplified and extended), "
             "print, plot, report."),
    "diagnose": ("_diagnose:diagnose_command", "Locate the mismatch between CAMPAIGN and the "
                 "model, explain and model it."),
    "fit": ("_pipeline:fit", "Fit every scan of CAMPAIGN; writes OUT/fit.json and "
            "OUT/residuals/*.parquet."),
    "fit-dask": ("_campaign:fit_dask_command", "Fit CAMPAIGN on Dask workers; writes the same "
                 "OUT/fit.json as `fit`."),
    "fit-joint": ("_campaign:fit_joint_command", "Joint adjustment: calibration shared per night "
                  "or campaign (Schur complement)."),
    "fit-stream": ("_campaign:fit_stream", "Adjust full-resolution scans streaming them from disk "
                   "with bounded memory."),
    "gravity": ("_campaign:gravity", "Gravity model over the sky from a fit (RESULTS_DIR with "
                "fit.json and residuals/)."),
    "import": ("_import:import_command", "Import a Leica PTX, XYZ text or E57 export as a "
               "one-face campaign (cycle 0)."),
    "preprocess": ("_pipeline:preprocess", "Clean every scan: range window, angular patches, "
                   "RANSAC planes; OUT/preprocess.json."),
    "prove": ("_diagnose:prove_command", "Prove the diagnosis on simulated campaigns where each "
              "effect is concealed."),
    "report": ("_surface:report", "One self-contained HTML page (figures + tables) for "
               "RESULTS_DIR."),
    "schedule": ("_campaign:schedule", "The measurement plan: four tours, 88 positions, start "
                 "times and temperatures."),
    "sensitivity": ("_campaign:sensitivity", "Implicit derivatives of f, panels and sigma0 w.r.t. "
                    "calibration and scan design."),
    "simulate": ("_pipeline:simulate", "Simulate a campaign (scans + truth) into OUT."),
    "surface": ("_surface:surface", "Surface products of CAMPAIGN: panels, cycle averages, "
                "OUT/surface.json."),
}
"""Verb -> ``("module:attribute", short help)``: the group imports a verb's module (and with it
the engine the verb needs) only when that verb runs or shows its help; ``hartrao-jax --help``
lists the short helps without importing any. ``tests/cli`` checks both against the commands."""


class LazyGroup(OneLineGroup):
    """The verb group: verbs are loaded by name from :data:`VERBS` on first use."""

    def list_commands(self, ctx) -> list[str]:
        return sorted(set(self.commands) | set(VERBS))

    def get_command(self, ctx, name: str):
        if name not in self.commands and name in VERBS:
            module, attr = VERBS[name][0].split(":")
            cmd = getattr(importlib.import_module(f"{__package__}.{module}"), attr)
            self.add_command(cmd, name)
        return self.commands.get(name)

    def format_commands(self, ctx, formatter) -> None:
        """The command list from the short helps of :data:`VERBS` (no verb module imported)."""
        names = self.list_commands(ctx)
        if not names:
            return
        limit = formatter.width - 6 - max(len(n) for n in names)
        rows = [(n, self.commands[n].get_short_help_str(limit) if n in self.commands
                 else click.Command(n, help=VERBS[n][1]).get_short_help_str(limit))
                for n in names]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--debug", is_flag=True, help="Show tracebacks.")
@click.option("-v", "--verbose", is_flag=True, help="More log output.")
@click.version_option(package_name="hartrao-jax")
@click.pass_context
def main(ctx, debug, verbose):
    """hartrao-jax: reflector deformation from terrestrial laser scans (Gauss-Helmert, JAX)."""
    from rich.logging import RichHandler

    ctx.ensure_object(dict)
    ctx.obj["debug"] = debug
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO, format="%(message)s",
        handlers=[RichHandler(show_path=False, show_time=False, console=_console(stderr=True))],
    )
    for noisy in ("jax", "absl", "matplotlib", "distributed", "asyncio"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


#: ``HARTRAO_JAX_FAST_EXIT=0``: :func:`run` ends the process through Python's own shutdown
FAST_EXIT_ENV = "HARTRAO_JAX_FAST_EXIT"


def run() -> None:
    """The ``hartrao-jax`` console command: :data:`main`, then, once its output is flushed,
    the process ends at once (``os._exit``) instead of through Python's shutdown: tearing
    down JAX's runtime and the modules took 0.7 s after a 12-scan ``fit``, with every output
    already written and synced (the kernel's reclaiming of a large position's memory remains
    either way). Every command has closed its files, progress bars and Dask cluster by then.
    In-process callers (tests, notebooks) call :data:`main`, which exits normally."""
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code
    if code is None:
        code = 0
    if not isinstance(code, int) or os.environ.get(FAST_EXIT_ENV, "1") == "0":
        sys.exit(code)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed or gone (a closed pipe): nothing to flush
            pass
    logging.shutdown()
    os._exit(code)


def _console(stderr=False):
    from rich.console import Console

    return Console(stderr=stderr)


def _fmt(v, s, scale=1.0, digits=4):
    return f"{v * scale:.{digits}f} ± {s * scale:.{digits}f}"


def _pm(v: float, s: float, digits: int) -> str:
    return f"{v:.{digits}f}±{s:.{digits}f}"


def _scale_unit(unit: str) -> tuple[float, str, int]:
    """Display scale, unit and decimals: rad in arcsec, m in mm."""
    if unit == "rad":
        return 206264.806, "″", 2
    if unit == "m":
        return 1000.0, "mm", 3
    return 1.0, unit, 6


def print_fit_table(cf, title="fit") -> None:
    """Short tables of a campaign fit on the terminal.

    Scans: f in m with its sigma in mm, sigma0, points, rejections, iterations, kappa. Positions
    (two-face adjustments): f, faces, the variance components and every calibration parameter
    (angles in arcsec, lengths in mm); a parameter the data cannot determine is printed as
    ``held`` and explained in one line below the table.
    """
    import math

    from rich.markup import escape
    from rich.table import Table

    t = Table(title=title, padding=(0, 1))
    for c in ("scan", "f [m]", "σf [mm]", "σ0", "points", "rej", "it", "κ [°]"):
        t.add_column(escape(c), justify="right")
    for s in cf.scans:
        f, sf = s.value("f"), s.sigma_of("f")
        t.add_row(
            s.meta.id, f"{f:.5f}", f"{sf * 1e3:.3f}", f"{s.sigma0:.3f}", f"{s.n_points}",
            f"{s.n_rejected}", f"{s.iterations}{'' if s.converged else '!'}",
            f"{math.degrees(s.alignment.kappa_rad):.1f}",
        )
    _console().print(t)
    extra = [n for n in cf.model_names if n not in ("tx", "ty", "tz", "rx", "ry", "f")]
    if cf.position_fits:
        pt = Table(title="positions (both faces adjusted together; the surface a random effect)",
                   padding=(0, 1))
        for c in ("position", "faces", "elev [°]", "f [m]", "σf [mm]", "σ0", "surface [mm]"):
            pt.add_column(escape(c), justify="right")
        ct = Table(title="calibration per position (″ = arcsec)", padding=(0, 1))
        ct.add_column("position", justify="right")
        for n in extra:
            ct.add_column(escape(f"{n} [{_scale_unit(parameter_unit(n))[1]}]"), justify="right")
        notes, prior = [], []
        for p in cf.position_fits:
            fv, fs = p.estimate("f") if "f" in p.names else (p.scans[0].value("f"), 0.0)
            srf = (f"{math.sqrt(p.surface.variances['offset_m2']) * 1e3:.3f}"
                   if p.surface is not None else "-")
            pt.add_row(p.position, str(p.faces), f"{p.scans[0].elevation_deg:.1f}", f"{fv:.6f}",
                       f"{fs * 1e3:.3f}", f"{p.sigma0:.3f}", srf)
            row = [p.position]
            for n in extra:
                sc, _, dg = _scale_unit(parameter_unit(n))
                if n in p.names:
                    v, sg = p.estimate(n)
                    row.append(_pm(v * sc, sg * sc, dg))
                else:
                    row.append("held" if n in p.held else "fixed")
            ct.add_row(*row)
            notes += [f"{p.position}: {h.note}" for h in p.held.values()]
            prior += [f"{p.position}: {t}" for t in p.notes
                      if t.startswith("smooth modes") or " are not separable from " in t]
        _console().print(pt)
        if extra:
            _console().print(ct)
        for line in dict.fromkeys(notes):
            _console().print(f"not identifiable: {escape(line)}")
        for line in prior:  # modes the data do not determine, or modes not carried at all
            label = ("not separable" if " are not separable from " in line else
                     "surface modes" if "not shown by the data" in line else "prior-dominated")
            _console().print(f"{label}: {escape(line)}")
        return
    if extra:
        ct = Table(title="calibration (″ = arcsec)", padding=(0, 1))
        ct.add_column("scan", justify="right")
        for n in extra:
            ct.add_column(escape(f"{n} [{_scale_unit(parameter_unit(n))[1]}]"), justify="right")
        notes = []
        for s in cf.scans:
            row = [s.meta.id]
            for n in extra:
                sc, _, dg = _scale_unit(parameter_unit(n))
                if n in s.undetermined:
                    row.append("not determined")
                elif n in s.names:
                    v, sg = s.estimates[n]
                    row.append(_pm(v * sc, sg * sc, dg))
                else:
                    row.append("held" if n in s.held else "fixed")
            ct.add_row(*row)
            notes += [f"{s.meta.id}: {h.note}" for h in s.held.values()]
            notes += [f"{s.meta.id}: {t}" for t in dict.fromkeys(s.undetermined.values())]
        _console().print(ct)
        for line in notes:
            _console().print(f"not identifiable: {escape(line)}")
    pt = Table(title="positions (per-cycle fits: inverse-variance mean of the cycles)",
               padding=(0, 1))
    for c in ("position", "elevation [°]", "f [m]", "σf [mm]"):
        pt.add_column(escape(c), justify="right")
    for p in cf.positions():
        pt.add_row(p["position"], f"{p['elevation_deg']:.2f}", f"{p['f']['value']:.6f}",
                   f"{p['f']['sigma'] * 1e3:.3f}")
    _console().print(pt)


def options(*decorators):
    """One decorator applying click options in the order written (as stacked above a verb)."""

    def apply(fn):
        for d in reversed(decorators):
            fn = d(fn)
        return fn

    return apply


def model_option(help: str | None = None):
    """``--model``: the adjustment's model (default extended)."""
    return click.option("--model", default="extended", show_default=True, help=help or (
        "simplified, extended, or comma-separated parameter names of the catalog."))


def fitting_options(preprocess_help: str):
    """``--preprocess/--no-preprocess``, ``--exclude-disturbed``, ``--cut-disturbed``: how the
    verbs that fit (``fit``, ``surface``) clean the scans and treat disturbed ones."""
    return options(
        click.option("--preprocess/--no-preprocess", default=True, show_default=True,
                     help=preprocess_help),
        click.option("--exclude-disturbed", is_flag=True,
                     help="Detect scans disturbed along one phi (brake, settling) and drop them."),
        click.option("--cut-disturbed", is_flag=True,
                     help="Detect disturbed scans and drop only the affected phi range, then "
                          "refit."),
    )


def disturbed_mode(exclude_disturbed: bool, cut_disturbed: bool) -> str | None:
    """``"exclude"``, ``"cut"`` or None from the two flags of :func:`fitting_options`."""
    if exclude_disturbed and cut_disturbed:
        raise UserError("--exclude-disturbed and --cut-disturbed: choose one")
    return "exclude" if exclude_disturbed else "cut" if cut_disturbed else None


def _names(text: str | None) -> tuple[str, ...]:
    """The non-empty items of a comma-separated option value."""
    return tuple(s.strip() for s in (text or "").split(",") if s.strip())


def _parse_fixes(fixes) -> dict[str, float]:
    """``--fix NAME=VALUE`` items: catalog names, finite values (one-line error otherwise)."""

    return parse_fixes(fixes)
