"""The command group, one-line errors, the console and the result table every verb shares.

Every command reports bad input as one line ``error: <file>: <field>: <expectation>`` on
stderr with exit status 2 (no traceback unless ``--debug``).
"""

from __future__ import annotations

import functools
import logging
import sys

import click

from .._config import enable_compilation_cache, enable_x64
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


@click.group(cls=OneLineGroup, context_settings={"help_option_names": ["-h", "--help"]})
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
        notes = []
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
        _console().print(pt)
        if extra:
            _console().print(ct)
        for line in dict.fromkeys(notes):
            _console().print(f"not identifiable: {escape(line)}")
        return
    if extra:
        ct = Table(title="calibration (″ = arcsec)", padding=(0, 1))
        ct.add_column("scan", justify="right")
        for n in extra:
            ct.add_column(escape(f"{n} [{_scale_unit(parameter_unit(n))[1]}]"), justify="right")
        for s in cf.scans:
            row = [s.meta.id]
            for n in extra:
                sc, _, dg = _scale_unit(parameter_unit(n))
                if n in s.names:
                    v, sg = s.estimates[n]
                    row.append(_pm(v * sc, sg * sc, dg))
                else:
                    row.append("fixed")
            ct.add_row(*row)
        _console().print(ct)
    pt = Table(title="positions (per-cycle fits: inverse-variance mean of the cycles)",
               padding=(0, 1))
    for c in ("position", "elevation [°]", "f [m]", "σf [mm]"):
        pt.add_column(escape(c), justify="right")
    for p in cf.positions():
        pt.add_row(p["position"], f"{p['elevation_deg']:.2f}", f"{p['f']['value']:.6f}",
                   f"{p['f']['sigma'] * 1e3:.3f}")
    _console().print(pt)


@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False))
@click.option("--d-min", "d_min_m", type=float, default=None, help="Range window minimum (m).")


def _parse_fixes(fixes) -> dict[str, float]:
    """``--fix NAME=VALUE`` items: catalog names, finite values (one-line error otherwise)."""

    return parse_fixes(fixes)
