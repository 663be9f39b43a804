"""Validation of every command's options and paths before any work starts (issue 13).

One rule for every verb: a bad option, output path or input is refused in one line
``error: <file or option>: <what is wrong>, expected <what>`` with exit status 2, before data
is loaded and before a progress bar is drawn. :func:`validate_command` runs at the start of
each command (from :func:`hartrao_jax.cli.command`); the checks are keyed by the parameter
names the commands share, so a new command gets them by naming its options the same way:

* every float option must be finite (click accepts ``nan`` and ``inf``);
* range rules of :data:`RULES` (``--robust-k >= 0`` with 0 = off, ``--step > 0``,
  ``--rows-per-chunk >= 1`` ...);
* output paths (:data:`OUTPUT_DIRS`, :data:`OUTPUT_FILES`) must be creatable
  (:func:`._safeio.check_output_path`);
* ``--fix NAME=VALUE``: a catalog parameter and a finite number; ``--model``/``--shared``:
  catalog names; ``--preset``: a simulator preset; ``--scans``/``--scan``: ids of the campaign;
* ``fit`` and ``diagnose``: a scan named with ``--scans`` (or every scan, for ``diagnose``)
  with fewer rows than :func:`._campaign.minimum_points` is refused by name.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from typing import Any

import click

from ..campaign._campaign import CampaignError, load_campaign, minimum_points
from ..campaign._safeio import check_output_path, verify_result_dir
from ..model._model import known_parameter, parse_model
from ..simulate._simulate import PRESETS


class OptionError(CampaignError):
    """A bad option: ``<option>: <what is wrong>, expected <what>`` (one line)."""

    def __init__(self, option: str, message: str):
        self.file, self.field, self.message = option, "", message
        Exception.__init__(self, f"{option}: {message}")


def _ge(lo):
    return lambda v: v >= lo


def _gt(lo):
    return lambda v: v > lo


#: parameter name -> (test, expectation) for numeric options (None values are skipped).
RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "robust_k": (_ge(0), "a number >= 0 (0: no rejection)"),
    "step_rad": (_gt(0), "a positive angular step in rad"),
    "rows_per_chunk": (_ge(1), "an integer >= 1"),
    "d_min_m": (_ge(0), "a range >= 0 m"),
    "d_max_m": (_gt(0), "a positive range in m"),
    "patch_size_m": (_gt(0), "a positive length in m"),
    "epsilon_m": (_gt(0), "a positive distance in m"),
    "margin_m": (_ge(0), "a length >= 0 m"),
    "margin_radial": (_ge(0), "a length >= 0 m"),
    "margin_tangential": (_ge(0), "a length >= 0 m"),
    "radius_m": (_gt(0), "a positive radius in m"),
    "step_deg": (_gt(0), "a positive step in degrees"),
    "alpha": (lambda v: 0 < v < 1, "a probability in (0, 1)"),
    "min_effect_mm": (_ge(0), "a size >= 0 mm"),
    "max_steps": (_ge(1), "an integer >= 1"),
    "seeds": (_ge(1), "an integer >= 1"),
    "seed": (_ge(0), "an integer >= 0"),
    "n_workers": (_ge(1), "an integer >= 1"),
    "workers": (_ge(1), "an integer >= 1"),
    "max_positions": (_ge(0), "an integer >= 0"),
    "n_validate": (_ge(0), "an integer >= 0"),
    "line_period_s": (_gt(0), "a positive time in s"),
    "dt_s": (_gt(0), "a positive time in s"),
    "elevation_deg": (lambda v: -90 <= v <= 90, "an elevation in [-90, 90] degrees"),
    "dec_deg": (lambda v: -90 <= v <= 90, "a declination in [-90, 90] degrees"),
    "ha_deg": (lambda v: -720 <= v <= 720, "an hour angle in [-720, 720] degrees"),
    "azimuth_deg": (lambda v: -720 <= v <= 720, "an azimuth in [-720, 720] degrees"),
}

#: Inside a campaign (no ``--scans``), a scan with fewer rows than
#: :func:`._campaign.minimum_points` is refused by name before the fit while this is True. Set
#: it to False once the fitting core leaves such scans out of every average with a note
#: (it then owns the rule; a scan named with ``--scans`` is refused either way).
REFUSE_SMALL_SCANS_IN_CAMPAIGN = True

#: Peak resident memory of an in-memory ``fit`` per row of the position it adjusts (bytes):
#: the whole process peaked at 12.0 GiB for one scan of 12,947,001 rows (0.99 kB per row,
#: benchmarks/results/profile.md); the random effect alone adds 1.2 kB per point on 4.6e5
#: points (campaign.md): the larger figure is used. A position that needs more than the
#: machine has available is refused before any work (the kernel would otherwise kill the
#: process part-way).
FIT_BYTES_PER_ROW = 1200
#: Overrides the memory the check assumes available (GiB; default: MemAvailable of
#: /proc/meminfo; the check is skipped where that cannot be read).
MEMORY_ENV = "HARTRAO_JAX_MEMORY_GIB"

#: parameters naming an output directory / an output file
OUTPUT_DIRS = ("out_dir", "out", "store", "report_dir")
OUTPUT_FILES = ("json_file", "json_path", "out_file")


def _option_name(ctx: click.Context | None, name: str) -> str:
    if ctx is not None:
        for p in ctx.command.params:
            if p.name == name:
                if isinstance(p, click.Option) and p.opts:
                    return max(p.opts, key=len)
                return (p.metavar or p.name or name).upper()
    return "--" + name.replace("_", "-")


def parse_fixes(fixes) -> dict[str, float]:
    """``--fix NAME=VALUE`` items -> {name: value}; refuses unknown names and non-finite
    values."""

    out = {}
    for f in fixes or ():
        if "=" not in f:
            raise OptionError("--fix", f"{f!r} has no '=', expected NAME=VALUE (e.g. x4=0.0002)")
        k, v = (x.strip() for x in f.split("=", 1))
        if not known_parameter(k):
            raise OptionError("--fix", f"{k!r} is not a parameter of the catalog, expected a "
                              "name such as x4, x6, zern_5 (see physics.md)")
        try:
            val = float(v)
        except ValueError:
            raise OptionError("--fix", f"{k}={v!r} is not a number, expected a finite "
                              "number") from None
        if not math.isfinite(val):
            raise OptionError("--fix", f"{k}={v} is not finite, expected a finite number")
        out[k] = val
    return out


def _names(text) -> list[str]:
    return [s.strip() for s in (text or "").split(",") if s.strip()]


def _check_numbers(ctx, kwargs: Mapping[str, Any]) -> None:
    for name, v in kwargs.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        opt = _option_name(ctx, name)
        if isinstance(v, float) and not math.isfinite(v):
            rule = RULES.get(name)
            raise OptionError(opt, f"{v} is not finite, expected "
                              f"{rule[1] if rule else 'a finite number'}")
        rule = RULES.get(name)
        if rule is not None and not rule[0](v):
            raise OptionError(opt, f"{v:g} is out of range, expected {rule[1]}")
    lo, hi = kwargs.get("d_min_m"), kwargs.get("d_max_m")
    if lo is not None and hi is not None and not hi > lo:
        raise OptionError("--d-max", f"{hi:g} is not above --d-min {lo:g}, expected a range "
                          "window with d-min < d-max")


def _check_paths(ctx, kwargs: Mapping[str, Any]) -> None:
    for name in OUTPUT_DIRS:
        if kwargs.get(name) is not None:
            check_output_path(kwargs[name], _option_name(ctx, name), kind="dir")
    for name in OUTPUT_FILES:
        if kwargs.get(name) is not None:
            check_output_path(kwargs[name], _option_name(ctx, name), kind="file")


def _check_names(ctx, kwargs: Mapping[str, Any]) -> None:
    if "fixes" in kwargs:
        parse_fixes(kwargs["fixes"])
    if isinstance(kwargs.get("model"), str) and "campaign" in kwargs:
        parse_model(kwargs["model"])
    if isinstance(kwargs.get("shared"), str):
        bad = [n for n in _names(kwargs["shared"]) if not known_parameter(n)]
        if bad:
            raise OptionError("--shared", f"unknown parameter(s) {', '.join(bad)}, expected "
                              "catalog names such as x4,x6,x7")
    if "preset" in kwargs and kwargs["preset"] is not None:
        if kwargs["preset"] not in PRESETS:
            raise OptionError("--preset", f"unknown preset {kwargs['preset']!r}, expected one "
                              f"of {', '.join(PRESETS)}")
    if isinstance(kwargs.get("modes"), str):
        for m in _names(kwargs["modes"]):
            if not (m.isdigit() and int(m) >= 1):
                raise OptionError("--modes", f"{m!r} is not a Noll index, expected "
                                  "comma-separated integers >= 1 (e.g. 4,5,6)")


def _selected_scans(kwargs) -> list[str] | None:
    if isinstance(kwargs.get("scans"), str):
        return _names(kwargs["scans"])
    if kwargs.get("scan_ids"):
        return [s for v in kwargs["scan_ids"] for s in _names(v)]
    return None


def _parquet_rows(path) -> int | None:
    """Rows of a Parquet scan from its footer (None if it cannot be read: the reader says why
    later)."""
    try:
        import pyarrow.parquet as pq

        return pq.ParquetFile(path).metadata.num_rows
    except Exception:  # noqa: BLE001 - reported by the reader with its own message
        return None


def _check_campaign(ctx, kwargs: Mapping[str, Any]) -> None:
    """Campaign-level checks that need only campaign.toml and the Parquet footers."""
    if kwargs.get("campaign") is None or ctx is None:
        return

    camp = load_campaign(kwargs["campaign"])
    ids = _selected_scans(kwargs)
    for sid in ids or ():
        camp.scan(sid)
    cmd = ctx.command.name
    if cmd not in ("fit", "diagnose", "fit-joint", "fit-dask", "fit-stream", "sensitivity"):
        return

    model = kwargs.get("model") or (kwargs.get("start") if cmd == "diagnose" else None) \
        or "extended"
    try:
        names = parse_model(model)
    except Exception:  # noqa: BLE001 - reported by the command
        return
    fixed = parse_fixes(kwargs.get("fixes"))
    n_free = len([n for n in names if n not in fixed])
    need = minimum_points(n_free)
    metas = [camp.scan(s) for s in ids] if ids else list(camp.scans)
    # rows from the Parquet footers (None: another format, sizes unknown before reading)
    rows = {m.id: _parquet_rows(camp.root / m.file) if m.file.lower().endswith(".parquet")
            else None for m in metas}
    small = []
    for m in metas:
        n = rows[m.id]
        if m.file.lower().endswith(".parquet"):
            if n == 0:
                raise CampaignError(camp.root / m.file, "rows", f"scan {m.id!r}: the scan table "
                                    "has no rows, expected at least one observation")
            if n is not None and n < need:
                small.append((m, n))
    # a scan the user named, or any scan of a joint diagnosis, or a campaign without one
    # scan that is large enough: refused by name. Other small scans of a campaign: see
    # REFUSE_SMALL_SCANS_IN_CAMPAIGN.
    if small and (ids or cmd in ("diagnose", "fit-stream") or len(small) == len(metas)
                  or REFUSE_SMALL_SCANS_IN_CAMPAIGN):
        m, n = small[0]
        raise CampaignError(camp.root / m.file, "points",
                            f"scan {m.id!r} has {n} rows, expected at least {need} for model "
                            f"{model!r} ({n_free} free parameters, 50 points each)")
    if cmd == "fit":
        _check_memory(camp, metas, rows, bool(kwargs.get("per_cycle") or kwargs.get("batch")))
    elif cmd == "fit-dask" and not kwargs.get("scheduler"):
        # a LocalCluster on this machine: its workers share the memory, one position each
        _check_memory(camp, metas, rows, bool(kwargs.get("per_cycle")),
                      workers=max(1, int(kwargs.get("n_workers") or 1)))


def available_memory_gib() -> float | None:
    """Memory available to a new allocation (GiB): ``$HARTRAO_JAX_MEMORY_GIB``, else
    MemAvailable of ``/proc/meminfo``; None where neither can be read."""
    env = os.environ.get(MEMORY_ENV)
    if env:
        try:
            return float(env)
        except ValueError:
            return None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 2**20
    except (OSError, ValueError, IndexError):
        return None
    return None


def _check_memory(camp, metas, rows: Mapping[str, int | None], per_cycle: bool,
                  workers: int = 1) -> None:
    """Refuse an in-memory fit whose largest adjustment (a position's scans together, or the
    largest scan with ``--per-cycle``) needs more memory than is available (to each of
    ``workers`` local Dask workers, which adjust one position each at a time); ``rows``: each
    scan's row count (None: unknown)."""
    avail = available_memory_gib()
    if avail is None:
        return
    avail = avail / workers
    groups: dict[str, list] = {}
    for m in metas:
        groups.setdefault(m.id if per_cycle else m.position, []).append(m)
    for key, ms in groups.items():
        counts = [rows[m.id] for m in ms]
        if any(r is None for r in counts):
            continue  # E57/PTX/XYZ sizes are not known before reading: not checked
        n = sum(counts)
        need = n * FIT_BYTES_PER_ROW / 2**30
        if need > avail:
            what = (f"scan {key!r} holds {n:,} rows" if per_cycle else
                    f"position {key!r}: its {len(ms)} scan(s) hold {n:,} rows")
            share = f" to each of {workers} local workers" if workers > 1 else ""
            raise CampaignError(camp.root / "campaign.toml", "size",
                                f"{what}; an in-memory fit needs about {need:.1f} GiB "
                                f"({FIT_BYTES_PER_ROW} bytes per row), {avail:.1f} GiB are "
                                f"available{share}: use `hartrao-jax fit-stream` (bounded "
                                "memory)" + (" or fewer --workers" if workers > 1 else "")
                                + ("" if per_cycle else " or `--per-cycle`"))


def _check_results(ctx, kwargs: Mapping[str, Any]) -> None:
    """Result directories read by a command hold one complete result (verified manifest)."""

    if kwargs.get("fit_dir") is not None:
        verify_result_dir(kwargs["fit_dir"], "fit.json")
    if ctx is not None and ctx.command.name == "gravity" and kwargs.get("results_dir"):
        verify_result_dir(kwargs["results_dir"], "fit.json")


def validate_command(ctx: click.Context | None, kwargs: Mapping[str, Any]) -> None:
    """All checks of the module for one command invocation (raises a one-line error)."""
    _check_numbers(ctx, kwargs)
    _check_names(ctx, kwargs)
    _check_paths(ctx, kwargs)
    _check_results(ctx, kwargs)
    _check_campaign(ctx, kwargs)


# ----------------------------------------------------------------------------- click errors


_TYPE_EXPECTED = {"float": "a number", "integer": "an integer", "boolean": "true or false",
                  "text": "a text", "path": "an existing path", "file": "an existing file",
                  "directory": "an existing directory"}


def click_error_line(e: click.ClickException) -> str:
    """One line ``<option>: <what is wrong>, expected <what>`` for click's own usage errors."""
    msg = " ".join(e.format_message().split())
    if isinstance(e, click.MissingParameter):
        q = e.param
        name = (max(q.opts, key=len) if isinstance(q, click.Option) and q.opts else
                (q.human_readable_name or q.name or "?")) if q is not None else "?"
        kind = "option" if isinstance(q, click.Option) else "argument"
        return f"{name}: missing {kind}, expected it on the command line (see --help)"
    if isinstance(e, click.BadParameter) and e.param is not None:
        p = e.param
        name = max(p.opts, key=len) if isinstance(p, click.Option) and p.opts else \
            (p.human_readable_name or p.name or "?")
        kind = getattr(p.type, "name", "")
        inner = e.message if isinstance(e.message, str) else msg
        inner = " ".join(inner.split()).rstrip(".")
        expected = _TYPE_EXPECTED.get(kind)
        if isinstance(p.type, click.Path):
            what = ("file or directory" if p.type.file_okay and p.type.dir_okay else
                    "file" if p.type.file_okay else "directory")
            expected = f"an existing {what}" if p.type.exists else f"a {what} path"
        if isinstance(p.type, click.Choice):
            expected = "one of " + ", ".join(map(str, p.type.choices))
        tail = f", expected {expected}" if expected and "expected" not in inner else ""
        return f"{name}: {inner}{tail}"
    if isinstance(e, click.NoSuchOption):
        hint = f" (did you mean {', '.join(e.possibilities)}?)" if e.possibilities else ""
        return f"{e.option_name}: no such option{hint}, expected an option of the command " \
               "(see --help)"
    return msg.rstrip(".")


class _OneLineMain:
    """``main`` of a click command or group: click's usage errors become one line
    ``error: ...`` with exit status 2 (``--debug`` on the command line: click's own output)."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        import sys

        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode, **extra)
        argv = list(sys.argv[1:] if args is None else args)
        try:
            rv = super().main(argv, prog_name, complete_var, False, **extra)
        except click.ClickException as e:
            help_error = getattr(click.exceptions, "NoArgsIsHelpError", ())
            if "--debug" in argv or isinstance(e, help_error):  # no arguments: the help
                e.show()
                sys.exit(e.exit_code)
            click.echo(f"error: {click_error_line(e)}", err=True)
            sys.exit(2)
        except click.Abort:
            click.echo("error: aborted", err=True)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)


class OneLineGroup(_OneLineMain, click.Group):
    """A click group whose usage errors are one line ``error: ...`` with exit status 2."""


class OneLineCommand(_OneLineMain, click.Command):
    """A click command (run by itself) whose usage errors are one line, exit status 2."""


__all__ = ["OUTPUT_DIRS", "OUTPUT_FILES", "OneLineCommand", "OneLineGroup", "OptionError",
           "REFUSE_SMALL_SCANS_IN_CAMPAIGN", "RULES", "click_error_line", "parse_fixes",
           "validate_command"]
