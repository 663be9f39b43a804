"""``hartrao-jax import``: a Leica PTX, XYZ text or E57 export as a one-face campaign."""

from __future__ import annotations

import pathlib
import sys

import click

from ..campaign import CampaignError
from ..campaign._import import FORMATS, LINE_PERIOD_S, XYZ_DT_S, import_file
from ._checks import OneLineCommand, validate_command


@click.command("import", cls=OneLineCommand)
@click.argument("file", type=click.Path(dir_okay=False, path_type=pathlib.Path))
@click.option("--format", "fmt", type=click.Choice(FORMATS), default=None,
              help="Input format (default: from the suffix; .ptx, .e57, else xyz).")
@click.option("--out", "out", required=True, type=click.Path(file_okay=False,
                                                             path_type=pathlib.Path),
              help="Campaign directory to write.")
@click.option("--telescope", default="gbt", show_default=True,
              help="Preset (gbt, hartrao) or a TOML file with a [telescope] table.")
@click.option("--elevation-deg", type=float, default=None,
              help="Elevation of the telescope (default 90, flagged as assumed).")
@click.option("--azimuth-deg", type=float, default=None, help="Azimuth (from north to east).")
@click.option("--ha-deg", type=float, default=None, help="Hour angle (HA-DEC telescopes).")
@click.option("--dec-deg", type=float, default=None, help="Declination (HA-DEC telescopes).")
@click.option("--position", default="p1", show_default=True, help="Position name of the scans.")
@click.option("--line-period-s", type=float, default=LINE_PERIOD_S, show_default=True,
              help="Nominal time of one PTX column.")
@click.option("--dt-s", type=float, default=XYZ_DT_S, show_default=True,
              help="Nominal time between XYZ points.")
@click.option("--allow-truncated", is_flag=True, help="Keep the points of a truncated PTX file.")
@click.option("--overwrite", is_flag=True, help="Replace an existing campaign.toml.")
def import_command(file, fmt, out, telescope, elevation_deg, azimuth_deg, ha_deg, dec_deg,
                   position, line_period_s, dt_s, allow_truncated, overwrite):
    """Import a Leica PTX, XYZ text or E57 export as a one-face campaign (cycle 0)."""

    ctx = click.get_current_context()
    try:
        validate_command(ctx, {k: v for k, v in ctx.params.items() if k != "file"})
        c = import_file(file, fmt, out, telescope=telescope, elevation_deg=elevation_deg,
                        azimuth_deg=azimuth_deg, position=position, ha_deg=ha_deg,
                        dec_deg=dec_deg, line_period_s=line_period_s, dt_s=dt_s,
                        allow_truncated=allow_truncated, overwrite=overwrite)
    except (CampaignError, ValueError, OSError) as e:
        root = ctx.find_root()
        if (root.obj or {}).get("debug"):
            raise
        click.echo(f"error: {(str(e).splitlines() or [type(e).__name__])[0]}", err=True)
        sys.exit(2)
    for s in c.scans:
        click.echo(f"{s.id}: {s.extra.get('n_points', '?')} points -> {c.root / s.file}")
    click.echo(f"wrote {c.root / 'campaign.toml'} ({c.telescope.name}, {len(c.scans)} scan"
               f"{'s' if len(c.scans) != 1 else ''}, angular step "
               f"{c.scanner.angular_step_rad:.3g} rad)")

