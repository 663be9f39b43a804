"""The sections of the surface report: each a function ``(doc, inputs)`` that appends its
heading, tables and figures to the page."""

from __future__ import annotations

import math

import numpy as np

from ..surface._surface import (
    PositionSurface,
    read_residuals,
)
from ._figures import (
    fig_average_map,
    fig_cycle_maps,
    fig_disturbed,
    fig_focal_sky,
    fig_panel_map,
    fig_panel_truth,
    fig_residual_distribution,
)
from ._html import _Doc, _esc, _f, _table
from ._inputs import ReportInputs


def _fit_section(doc: _Doc, inp: ReportInputs):
    if not inp.fits:
        return
    doc.h2("Adjustment (fit.json)", "fit")
    for label, d, fj in inp.fits:
        model = fj.get("model", [])
        doc.add(f"<h3>{_esc(label)}: model {_esc(', '.join(model))}</h3>")
        extra = [n for n in model if n not in ("tx", "ty", "tz", "rx", "ry", "f")]
        heads = ["scan", "position", "cycle", "f [m]", "\u03c3 f [mm]", "\u03c30", "points",
                 "rejected", "iter", "\u03ba [deg]"]
        unit_of = {}
        for n in extra:
            u = None
            for s in fj.get("scans", []):
                u = s.get("estimates", {}).get(n, {}).get("unit")
                if u:
                    break
            unit_of[n] = u or ""
            heads.append(f"{n} [{'arcsec' if u == 'rad' else 'mm' if u == 'm' else u or ''}]")
        rows = []
        for s in fj.get("scans", []):
            est = s.get("estimates", {})
            f = est.get("f", {})
            row = [s.get("id"), s.get("position"), s.get("cycle"), _f(f.get("value"), "{:.5f}"),
                   _f(f.get("sigma"), "{:.3f}", 1e3), _f(s.get("sigma0"), "{:.3f}"),
                   s.get("n_points"), s.get("n_rejected"),
                   f"{s.get('iterations')}{'' if s.get('converged', True) else ' (!)'}",
                   _f(s.get("kappa_rad"), "{:.3f}", 180 / math.pi)]
            for n in extra:
                e = est.get(n, {})
                sc = 206264.806 if unit_of[n] == "rad" else 1e3 if unit_of[n] == "m" else 1.0
                v, sg = e.get("value"), e.get("sigma")
                row.append(f"{_f(v, '{:.2f}', sc)} \u00b1 {_f(sg, '{:.2f}', sc)}")
            rows.append(row)
        doc.add(_table(heads, rows))
        notes = [(s["id"], n) for s in fj.get("scans", []) for n in s.get("notes", [])]
        if notes:
            doc.add("<ul class='note'>" + "".join(f"<li>{_esc(i)}: {_esc(n)}</li>"
                                                   for i, n in notes) + "</ul>")
        prow = []
        for p in fj.get("positions", []):
            fp = p.get("f") or {}
            prow.append([p.get("position"), _position_kind(p), _f(p.get("ha_deg"), "{:.1f}"),
                         _f(p.get("dec_deg"), "{:.1f}"), _f(p.get("elevation_deg"), "{:.2f}"),
                         _f(fp.get("value"), "{:.6f}"), _f(fp.get("sigma"), "{:.4f}", 1e3),
                         ", ".join(p.get("scans", []))])
        doc.add("<p class='small'>Positions: both faces adjusted together, or a position with "
                "one usable cycle (labelled so: no cycle average, the two-face-sensitive errors "
                "do not cancel).</p>")
        doc.add(_table(["position", "faces", "HA [deg]", "DEC [deg]", "elevation [deg]",
                        "f [m]", "\u03c3 f [mm]", "scans"], prow))


def _position_kind(p: dict) -> str:
    """How a fit.json position was formed: two faces, or one usable cycle (never called a
    cycle average)."""
    faces = p.get("faces")
    if faces == 1 or (faces is None and len(p.get("scans", [])) < 2):
        return "one usable cycle"
    return str(p.get("kind") or ("two faces" if faces == 2 else "mean of the cycles"))


def _focal_section(doc: _Doc, inp: ReportInputs):
    if not inp.fits:
        return
    nominal = inp.campaign.telescope.focal_length_m if inp.campaign is not None else None
    doc.h2("Focal length across positions", "focal")
    fig = fig_focal_sky([(label, fj) for label, _, fj in inp.fits], nominal)
    doc.figure(fig, "Left: focal length of each position on the sky (hour angle, declination), "
               "colour and label f \u2212 f\u2080 \u00b1 \u03c3 in mm, f\u2080 the nominal focal "
               "length; right: against elevation for every fit.", "focal_length")


def _residual_section(doc: _Doc, inp: ReportInputs):
    samples = []
    rng = np.random.default_rng(0)
    for label, d, fj in inp.fits:
        vals = []
        scans = fj.get("scans", [])
        per_scan = max(20_000, 2_000_000 // max(len(scans), 1))  # a sample is enough
        for s in scans:
            p = d / "residuals" / f"{s['id']}.parquet"
            if p.exists():
                r = read_residuals(p, ("deviation_m", "used"))
                v = r["deviation_m"][r["used"].astype(bool)]
                if len(v) > per_scan:
                    v = v[rng.choice(len(v), per_scan, replace=False)]
                vals.append(v)
        if vals:
            samples.append((label, np.concatenate(vals)))
    if not samples:
        return
    doc.h2("Residual distribution", "residuals")
    doc.figure(fig_residual_distribution(samples),
               "Residuals (normal deviation of the points used in the adjustment) of every fit: "
               "histogram with the normal density of the same mean and standard deviation, and "
               "normal Q-Q plot of the standardised residuals. Heavy tails or a skew show "
               "unmodelled structure (panels, instrument errors) or leftover outliers.",
               "residual_distribution")


def _surface_section(doc: _Doc, inp: ReportInputs, max_positions: int):
    if not inp.surfaces:
        return
    doc.h2("Surface deviations", "surface")
    doc.add("<p class='small'>Maps: north-aligned telescope frame seen from the focus, X "
            "(north) up, Y (west) to the left; colour = normal deviation in mm, positive "
            "towards the focus (above the paraboloid), negative away from it (sag). Panel "
            "edges are masked; cycles are averaged panel by panel, never across two "
            "panels.</p>")
    main_label = inp.surfaces[-1][0]
    for label, res in inp.surfaces:
        doc.add(f"<h3>{_esc(label)}</h3>")
        rows = []
        for p in res.positions:
            cyc = "; ".join(f"{c.scan}: {1e3 * c.rms_m:.3f}" for c in p.cycles)
            rows.append([p.position, p.kind, cyc, _f(p.averaged.rms_m, "{:.3f}", 1e3),
                         f"{len(p.averaged):,}", f"{p.averaged.n_unpaired:,}",
                         _f(p.radius_m, "{:.2g}", 100), "; ".join(p.notes)])
        doc.add(_table(["position", "kind", "rms per cycle [mm]", "rms averaged [mm]",
                        "averaged points", "unpaired points", "radius [cm]", "notes"], rows))
        shown = res.positions[:max_positions]
        if len(res.positions) > len(shown):
            doc.add(f"<p class='note'>Maps of the first {len(shown)} of "
                    f"{len(res.positions)} positions.</p>")
        for p in shown:
            if any(len(c) for c in p.cycles):
                doc.figure(fig_cycle_maps(p, res.layout, f"{label}: residuals per cycle, "
                                          f"position {p.position}"),
                           f"{label}, {p.position}: residuals of each cycle; red: the face "
                           "boundary (from the data: where face-1 and face-2 points meet). "
                           "Two-face-sensitive errors change sign across it and between the "
                           "cycles (paper Figs. 6 and 7).", f"cycles_{label}_{p.position}")
            if len(p.averaged):
                doc.figure(fig_average_map(p, res.layout, f"{label}, {p.position}: "
                                           f"{p.kind}, rms {1e3 * p.averaged.rms_m:.2f} mm"),
                           f"{label}, {p.position}: cycle-averaged residuals (paper Fig. 8): "
                           "points of cycles 1 and 2 within the averaging radius, one panel at "
                           "a time; the two-face-sensitive errors cancel.",
                           f"average_{label}_{p.position}")
            if label == main_label and res.layout is not None and p.panels is not None:
                doc.figure(fig_panel_map(p, res.layout),
                           f"{label}, {p.position}: per-panel deviation (mean of the panel's "
                           "cycle-averaged points), panel id and value in mm; grey: too few "
                           "points.",
                           f"panels_{label}_{p.position}")
                _panel_table(doc, p)
                _truth_panels(doc, inp, p)


def _panel_table(doc: _Doc, p: PositionSurface):
    t = p.panels
    order = np.argsort(-np.nan_to_num(np.abs(t.deviation_m), nan=-1))
    rows = []
    for i in order:
        rows.append([int(t.panel[i]), int(t.ring[i]), _f(t.deviation_m[i], "{:+.3f}", 1e3),
                     _f(t.sigma_m[i], "{:.3f}", 1e3), _f(t.tilt_rad[i], "{:.3f}", 1e3),
                     _f(t.tilt_radial_rad[i], "{:+.3f}", 1e3),
                     _f(t.tilt_tangential_rad[i], "{:+.3f}", 1e3), _f(t.rms_m[i], "{:.3f}", 1e3),
                     _f(t.rms_plane_m[i], "{:.3f}", 1e3), int(t.n[i])])
    heads = ["panel", "ring", "deviation [mm]", "\u03c3 [mm]", "tilt [mrad]", "radial [mrad]",
             "tangential [mrad]", "rms [mm]", "rms about plane [mm]", "n"]
    doc.add(f"<p class='small'>Panels of {_esc(p.position)} with the largest |deviation|:</p>")
    doc.add(_table(heads, rows[:12]))
    doc.add(f"<details><summary>all {len(rows)} panels</summary>{_table(heads, rows)}"
            "</details>")


def _truth_panels(doc: _Doc, inp: ReportInputs, p: PositionSurface):
    t = inp.truth
    if not t or "reflector" not in t:
        return
    off = np.asarray(t["reflector"].get("offset_m") or [], float)
    if len(off) != len(p.panels.deviation_m) or not np.any(off):
        return
    doc.figure(fig_panel_truth(p.panels.deviation_m, off),
               f"{p.position}: estimated panel deviations against the simulator's panel "
               "offsets (truth.json); the fitted paraboloid absorbs their mean and its "
               "focal-length-like part, so the cloud may be shifted slightly from the 1:1 line.",
               f"truth_panels_{p.position}")


def _preprocess_section(doc: _Doc, inp: ReportInputs):
    if not inp.preprocess:
        return
    doc.h2("Preprocessing (preprocess.json)", "preprocess")
    for label, pj in inp.preprocess:
        doc.add(f"<h3>{_esc(label)}</h3>")
        rows, stages = [], []
        for s in pj.get("scans", []):
            rm = s.get("removed", {})
            stages = stages or list(rm)
            rows.append([s.get("id"), f"{s.get('n_rows', 0):,}", f"{s.get('n_kept', 0):,}",
                         _f(s.get("kept_fraction"), "{:.1%}")]
                        + [f"{rm.get(k, 0):,}" for k in stages]
                        + [s.get("n_patches_fitted", ""),
                           _f(s.get("plane_rms_median_m"), "{:.3f}", 1e3)])
        doc.add(_table(["scan", "rows", "kept", "kept %"] + [f"removed: {k}" for k in stages]
                       + ["patches", "plane rms [mm]"], rows))


def _disturbed_section(doc: _Doc, inp: ReportInputs):
    doc.h2("Disturbed scans", "disturbed")
    reps = inp.disturbed
    if not reps:
        doc.add("<p>No scan shows a jump of its residuals along one horizontal angle (the "
                "paper's brake / settling disturbance).</p>")
        return
    rows = []
    for r in reps:
        j = r.to_json() if hasattr(r, "to_json") else r
        a, b = j.get("phi_range_deg", [j.get("phi_deg"), j.get("phi_end_deg")])
        rows.append([j["scan"], j["cycle"], _f(j["phi_deg"], "{:.2f}"), f"{a:.2f} \u2013 {b:.2f}",
                     _f(j["jump_m"], "{:+.3f}", 1e3), _f(j["statistic"], "{:.1f}"),
                     j.get("kind", ""), j.get("reference") or "\u2013"])
    doc.add(_table(["scan", "cycle", "phi [deg]", "phi range [deg]", "jump [mm]", "statistic",
                    "kind", "reference"], rows))
    doc.add("<p class='small'>Exclude them with <code>--exclude-disturbed</code> or cut the "
            "range with <code>--cut-disturbed</code>.</p>")
    if any(getattr(r, "series", None) for r in reps):
        doc.figure(fig_disturbed(reps), "Median residual of every phi line (its face-1 and "
                   "face-2 halves, theta structure removed, minus the other cycle's same dish "
                   "lines when available) against phi, with the detected range.", "disturbed")

