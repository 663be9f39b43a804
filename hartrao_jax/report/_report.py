"""Figures and the self-contained HTML report (``hartrao-jax report RESULTS_DIR``).

Figures are drawn headless with matplotlib's Agg canvas (no pyplot, no display, no global
backend switch). Deviations are shown in millimetres with the sign convention of
``campaign-format.md`` in every colour bar: positive towards the focus (above the paraboloid),
negative away from it (a sagging panel is blue). Dish maps are in the north-aligned telescope
frame seen from the focus: X (north) up, Y (west) to the left.

* :func:`fig_cycle_maps`: residuals of every cycle of a position with the face boundary (paper
  Figs. 6, 7), the boundary computed from the data (:func:`face_boundary`);
* :func:`fig_average_map`: the cycle-averaged residuals with the panel outlines (Fig. 8);
* :func:`fig_panel_map`: panels coloured by their deviation, with ids and values;
* :func:`fig_focal_sky`: focal length per position on an HA/DEC plot and against elevation;
* :func:`fig_residual_distribution`: histogram and normal Q-Q plot of the residuals;
* :func:`fig_disturbed`: line medians of disturbed scans against phi;
* :func:`write_report`: all of them plus the result tables in one HTML page (PNG images
  embedded as base64), from a results directory with ``fit.json`` / ``surface.json`` /
  ``preprocess.json`` or from sub-directories holding them (``simplified/``, ``extended/``).
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

from ..campaign._safeio import write_text_atomic
from ._html import _CSS, _Doc, _esc
from ._inputs import collect
from ._sections import (
    _disturbed_section,
    _fit_section,
    _focal_section,
    _preprocess_section,
    _residual_section,
    _surface_section,
)


def write_report(results_dir, campaign=None, out: str | Path | None = None, *,
                 max_positions: int = 4, figures_dir: bool = True) -> Path:
    """Write one self-contained HTML page for a results directory; returns its path.

    ``results_dir`` holds ``fit.json`` (+ ``residuals/``), ``surface.json`` and/or
    ``preprocess.json``, or sub-directories that do (the ``demo`` layout ``simplified/``,
    ``extended/``). Without ``surface.json`` the surface products are computed from the
    residual tables. ``campaign`` (optional) gives the panel layout, the nominal focal length
    and, for simulated campaigns, the truth. The page goes to ``out`` (default
    ``results_dir/report.html``); the PNGs also to ``results_dir/figures/``.
    """
    inp = collect(results_dir, campaign)
    root = inp.root
    if not (inp.fits or inp.surfaces or inp.preprocess):
        raise FileNotFoundError(f"{root}: no fit.json, surface.json or preprocess.json found "
                                "(in the directory or its sub-directories)")
    doc = _Doc(root / "figures" if figures_dir else None)
    _fit_section(doc, inp)
    _focal_section(doc, inp)
    _residual_section(doc, inp)
    _surface_section(doc, inp, max_positions)
    _disturbed_section(doc, inp)
    _preprocess_section(doc, inp)
    camp = inp.campaign
    title = f"hartrao-jax report: {camp.telescope.name}" if camp is not None else \
        "hartrao-jax report"
    toc = "".join(f'<li><a href="#{a}">{_esc(t)}</a></li>' for a, t in doc.toc)
    meta = [f"results: <code>{_esc(root.resolve())}</code>",
            f"generated {dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC"]
    if camp is not None:
        meta.append(f"campaign: <code>{_esc(camp.root)}</code> ({len(camp.scans)} scans)")
    page = (f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{_esc(title)}"
            f"</title><style>{_CSS}</style></head><body><h1>{_esc(title)}</h1>"
            f"<p class='small'>{' &middot; '.join(meta)}</p><nav><ul>{toc}</ul></nav>"
            + "\n".join(doc.parts) + "</body></html>")

    return write_text_atomic(Path(out) if out is not None else root / "report.html", page)


