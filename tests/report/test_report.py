"""Figures and the HTML report: written, readable (not blank), the demo layout and a surface
directory both handled, the face boundary from the data, the CLI."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest

from hartrao_jax.fit._fit import fit_campaign
from hartrao_jax.fit._records import write_fit
from hartrao_jax.geometry._geometry import face_of
from hartrao_jax.report import (
    face_boundary,
    fig_average_map,
    fig_cycle_maps,
    fig_focal_sky,
    fig_panel_map,
    fig_residual_distribution,
    pixel_std,
    png_bytes,
    write_report,
)
from hartrao_jax.simulate._simulate import simulate_campaign
from hartrao_jax.surface._surface import surface_from_fit, write_surface

MIN_STD = 0.03  # grey-level standard deviation of a figure with content (blank: 0)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The ``demo`` command's layout: OUT/campaign, OUT/simplified, OUT/extended."""
    out = tmp_path_factory.mktemp("demo")
    camp = simulate_campaign(out / "campaign", preset="clean",
                             effects={"x4": 2e-4, "x7": -4e-5, "panel_offset": 3e-4}, seed=7,
                             step_rad=0.012)
    fits = {}
    for model in ("simplified", "extended"):
        fits[model] = fit_campaign(camp, model, progress=False)
        write_fit(out / model, fits[model])
    return out, camp, fits


def _images(html: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r'src="data:image/png;base64,([^"]+)"', html)]


def test_demo_layout_report(demo):
    out, camp, _ = demo
    p = write_report(out, campaign=camp)
    assert p == out / "report.html" and p.exists()
    html = p.read_text()
    text = re.sub(r"base64,[A-Za-z0-9+/=]+", "base64,", html)
    assert "<script" not in text and "http" not in text  # self-contained: nothing to fetch
    imgs = _images(html)
    # focal length, residuals, 2 x (cycle maps + average map), panel map, truth comparison
    assert len(imgs) >= 7
    for png in imgs:
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        assert pixel_std(png) > MIN_STD
    for word in ("simplified", "extended", "r23c1", "Disturbed scans", "towards", "fit.json"):
        assert word in html
    figs = sorted((out / "figures").glob("*.png"))
    assert len(figs) == len(imgs)


def test_report_of_a_surface_directory(demo, tmp_path):
    out, camp, fits = demo
    res = surface_from_fit(fits["extended"])
    write_surface(tmp_path / "surf", res)
    p = write_report(tmp_path / "surf", campaign=camp, out=tmp_path / "r.html")
    imgs = _images(p.read_text())
    assert len(imgs) >= 3  # cycle maps, average map, panel map
    assert all(pixel_std(png) > MIN_STD for png in imgs)


def test_report_errors_on_empty_directory(tmp_path):
    with pytest.raises(FileNotFoundError, match="no fit.json"):
        write_report(tmp_path)


def test_figures_not_blank(demo):
    out, camp, fits = demo
    res = surface_from_fit(fits["extended"])
    pos = res.positions[0]
    docs = [(m, json.loads((out / m / "fit.json").read_text())) for m in ("simplified", "extended")]
    figs = {
        "cycles": fig_cycle_maps(pos, res.layout),
        "average": fig_average_map(pos, res.layout),
        "panels": fig_panel_map(pos, res.layout),
        "focal": fig_focal_sky(docs, camp.telescope.focal_length_m),
        "residuals": fig_residual_distribution(
            [(m, np.concatenate([s.deviation_m[s.used] for s in cf.scans]))
             for m, cf in fits.items()]),
    }
    for name, fig in figs.items():
        assert pixel_std(png_bytes(fig)) > MIN_STD, name
    from hartrao_jax.report._draw import _figure

    assert pixel_std(png_bytes(_figure(2, 2))) == 0  # a blank figure fails the check


def test_face_boundary_separates_the_faces(demo):
    """Points on either side of the boundary drawn on the maps belong to one face each."""
    _, _, fits = demo
    for s in fits["extended"].scans:
        X = s.X_tel[s.used]
        face = face_of(s.data.theta_rad[s.used])
        line = face_boundary(X, face)
        assert line is not None and len(line) > 10
        # side of each point: sign of the cross product with the nearest boundary segment
        P = X[:, :2]
        seg0, seg1 = line[:-1], line[1:]
        d = ((P[:, None, :] - 0.5 * (seg0 + seg1)[None]) ** 2).sum(-1)
        j = d.argmin(1)
        t = seg1[j] - seg0[j]
        side = np.sign(t[:, 0] * (P[:, 1] - seg0[j, 1]) - t[:, 1] * (P[:, 0] - seg0[j, 0]))
        agree = max(np.mean((side > 0) == (face == 1)), np.mean((side > 0) == (face == 2)))
        assert agree > 0.97, (s.meta.id, agree)


def test_report_cli(demo, tmp_path):
    from click.testing import CliRunner

    import hartrao_jax.cli._surface  # noqa: F401  (registers the commands)
    from hartrao_jax.cli import main

    out, camp, _ = demo
    target = tmp_path / "page.html"
    r = CliRunner().invoke(main, ["report", str(out), "--campaign", str(camp.root), "--out",
                                  str(target), "--max-positions", "1"])
    assert r.exit_code == 0, r.output
    assert target.exists() and len(_images(target.read_text())) >= 7
    r = CliRunner().invoke(main, ["report", str(tmp_path / "nothing")])
    assert r.exit_code == 2
