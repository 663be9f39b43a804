"""Figures (matplotlib, Agg) and self-contained HTML: the surface report and the diagnosis report.

* ``_draw``: drawing primitives (PNG bytes, colour limits, dish axes, face boundary, rasters)
* ``_figures``: one function per figure of the surface report
* ``_inputs``: collecting ``fit.json`` / ``surface.json`` / ``preprocess.json`` of a results dir
* ``_html``: HTML building blocks and the page under construction
* ``_sections``: the sections of the surface report
* ``_report``: :func:`write_report`, the surface report's page
* ``_diagnosis``: the diagnosis report (``diagnose --report``)
"""

from ._diagnosis import diagnose_with_report
from ._diagnosis import write_report as write_diagnosis_report
from ._draw import CMAP, SIGN_LABEL, colour_limit_mm, face_boundary, pixel_std, png_bytes, save_png
from ._figures import (
    fig_average_map,
    fig_cycle_maps,
    fig_disturbed,
    fig_focal_sky,
    fig_panel_map,
    fig_panel_truth,
    fig_residual_distribution,
)
from ._inputs import collect
from ._report import write_report

__all__ = [
    "CMAP", "SIGN_LABEL", "collect", "colour_limit_mm", "diagnose_with_report", "face_boundary",
    "fig_average_map", "fig_cycle_maps", "fig_disturbed", "fig_focal_sky", "fig_panel_map",
    "fig_panel_truth", "fig_residual_distribution", "pixel_std", "png_bytes", "save_png",
    "write_diagnosis_report", "write_report",
]
