"""The diagnosis as figures and an HTML page (`diagnose --report DIR`): the engine in
`diagnose/` computes, this module draws and writes."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..diagnose._diagnose import diagnose
from ..diagnose._result import Diagnosis, _json_default
from ..model import format_estimate


def write_report(diag: Diagnosis, out_dir: str | Path) -> Path:
    """Residual maps before and after each accepted step, the evidence of motion findings
    (change points, periodogram) and ``index.html``; returns the HTML path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    hist = diag.history
    images: list[tuple[str, str]] = []
    def maps_figure(before: dict, after: dict, ids: Sequence[str], title: str, name: str):
        vals = np.concatenate([np.abs(before[i][np.isfinite(before[i])]) for i in ids] or [[1e-4]])
        vmax = 1e3 * float(np.percentile(vals, 98)) if vals.size else 0.5
        fig, axes = plt.subplots(len(ids), 2, figsize=(8.5, 4.0 * len(ids)), squeeze=False)
        for r, i in enumerate(ids):
            for c, (lab, mp) in enumerate((("before", before), ("after", after))):
                ax = axes[r, c]
                im = ax.imshow(1e3 * mp[i].T, origin="lower",
                               extent=diag.extents.get(i, [-13.0, 13.0, -13.0, 13.0]),
                               cmap="RdBu_r", vmin=-vmax, vmax=vmax)
                ax.set_title(f"{i}: {lab}", fontsize=9)
                ax.set_xlabel("X [m]")
                if c == 0:
                    ax.set_ylabel("Y [m]")
                ax.set_aspect("equal")
        fig.colorbar(im, ax=axes, shrink=0.6, label="recording - simulation, normal [mm]")
        fig.suptitle(title, fontsize=10)
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        images.append((title, name))

    all_ids = list(hist[0]["maps"]) if hist else []
    for k in range(1, len(hist)):
        ids = [i for i in (hist[k].get("scans") or all_ids) if i in hist[k]["maps"]][:4]
        maps_figure(hist[k - 1]["maps"], hist[k]["maps"], ids,
                    f"step {k}: {hist[k]['label']}", f"step{k}_{hist[k]['label']}_maps.png")
        ev = hist[k].get("evidence")
        if ev and ev.get("kind") == "change_point":
            e = ev["edges"]
            tb = 0.5 * (e[:-1] + e[1:])
            fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
            tr = 1e3 * np.asarray(ev["translation"])
            for j, ax_name in enumerate("xyz"):
                a1.plot(tb, tr[:, j], lw=0.7, label=f"d{ax_name}")
            lo, hi = np.nanpercentile(tr, [2, 98])
            a1.set_ylim(lo - 0.5 * (hi - lo), hi + 0.5 * (hi - lo))  # weak bins clipped
            a1.set_ylabel("translation per time bin [mm]")
            a1.legend(fontsize=8)
            a2.plot(tb, ev["profile"], lw=0.8, color="k")
            a2.set_ylabel("box statistic T (max over lengths)")
            a2.set_xlabel("scan time [s]")
            for ax in (a1, a2):
                w0, dw = ev["window_s"]
                ax.axvspan(w0, w0 + dw, color="orange", alpha=0.3)
            fig.suptitle(f"{ev['scan']}: change-point search (impulsive shift)", fontsize=10)
            name = f"step{k}_change_points.png"
            fig.savefig(out / name, dpi=90)
            plt.close(fig)
            images.append((f"step {k}: change-point search", name))
        elif ev and ev.get("kind") == "periodogram":
            fig, ax = plt.subplots(figsize=(8, 3.5))
            ax.semilogx(ev["periods"], ev["periodogram"], lw=0.8, color="k")
            ax.axvline(ev["period_s"], color="orange")
            ax.set_xlabel("period [s]")
            ax.set_ylabel("score statistic T (4 dof)")
            ax.set_title(f"{ev['scan']}: periodogram of the scanner rotation", fontsize=10)
            fig.tight_layout()
            name = f"step{k}_periodogram.png"
            fig.savefig(out / name, dpi=90)
            plt.close(fig)
            images.append((f"step {k}: periodogram", name))
    if len(hist) > 1:
        ids = all_ids[:4]
        maps_figure(hist[0]["maps"], hist[-1]["maps"], ids, "start model vs final model",
                    "start_vs_final_maps.png")
    rows = "".join(
        f"<tr><td>{i + 1}</td><td>{f.effect}</td><td>{f.family}</td><td>{', '.join(f.scans)}</td>"
        f"<td>{f.statistic:.1f} ({f.dof})</td><td>{1e3 * f.effect_size_m:.4f}</td>"
        f"<td>{f.sigma0_before:.4f} &rarr; {f.sigma0_after:.4f}</td>"
        f"<td>{1e3 * f.rms_before_m:.4f} &rarr; {1e3 * f.rms_after_m:.4f}</td>"
        f"<td>{_html(json.dumps(f.where, default=_json_default))}</td>"
        f"<td>{_html(f.explanation)}</td></tr>" for i, f in enumerate(diag.findings))
    conf = "".join(f"<tr><td>{c['effect']}</td><td>{', '.join(c['with'])}</td>"
                   f"<td>{c['correlation']:.6f}</td></tr>" for c in diag.confounded)

    est = "".join(
        f"<tr><td>{_html(str(p['position']))}</td><td>{p['faces']}</td>"
        + "".join(f"<td>{_estimate_cell(n, e)}</td>" for n, e in p["estimates"].items())
        + "</tr>" for p in diag.positions)
    est_head = ("".join(f"<th>{_html(n)}</th>" for n in diag.positions[0]["estimates"])
                if diag.positions else "")

    images += diagnosis_local_figures(diag, out)
    imgs = "".join(f"<h3>{_html(t)}</h3><img src='{n}' style='max-width:100%'>" for t, n in images)
    skip = "".join(f"<li>{_html(k['search'])}: {_html(k['why'])}</li>" for k in diag.skipped)
    loc = "".join(f"<li>{_html(d.get('statement', ''))}</li>" for d in diag.local_search)
    html = f"""<!doctype html><html><head><meta charset="utf-8"><title>diagnosis</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}} td,th{{border:1px solid #ccc;
padding:3px 6px;font-size:13px;vertical-align:top}} table{{border-collapse:collapse}}</style></head>
<body><h1>Discrepancy diagnosis</h1>
<p>Campaign <code>{_html(diag.campaign)}</code>. Start model {', '.join(diag.start_model)};
final model {', '.join(diag.final_model)}.</p>
<p>sigma0 {diag.sigma0_start:.4f} &rarr; {diag.sigma0_final:.4f}; rms of recording minus simulation
(normal) {1e3 * diag.rms_start_m:.4f} &rarr; {1e3 * diag.rms_final_m:.4f} mm.</p>
<h2>Findings (in the order accepted)</h2>
<table><tr><th>#</th><th>effect</th><th>family</th><th>scans</th><th>T (dof)</th>
<th>effect [mm]</th><th>sigma0</th><th>rms [mm]</th><th>where</th><th>explanation</th></tr>
{rows}</table>
<h2>Final estimates per position</h2>
<p>Both faces adjusted together with the panels' offsets and tilts as a random effect (variances
estimated): these sigmas include the surface. The loop's per-scan white-noise sigmas are in the
JSON as <code>sigma_white</code>.</p>
<table><tr><th>position</th><th>faces</th>{est_head}</tr>{est}</table>
<h2>Confounded with the model (not tested)</h2>
<table><tr><th>effect</th><th>with</th><th>correlation</th></tr>{conf}</table>
<h2>Local deformation search</h2><ul>{loc}</ul>
<h2>Searches skipped (the recording lacks what they need)</h2><ul>{skip}</ul>
<h2>Figures</h2>{imgs}
<p>Notes: {_html('; '.join(diag.notes))}</p></body></html>"""
    p = out / "index.html"
    p.write_text(html, encoding="utf-8")
    return p


def _estimate_cell(name: str, e: dict) -> str:
    """``value ± sigma`` in readable units, or why the data cannot determine it."""
    if e.get("identifiable") is False:
        return f"<i>not identifiable</i>: {_html(e.get('note', ''))}"
    if e.get("value") is None or e.get("sigma") is None:
        return "-"
    return _html(format_estimate(name, e["value"], e["sigma"]))


def _html(s: str) -> str:
    return str(s).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def diagnose_with_report(campaign, start="extended", *, report_dir: str | Path | None = None,
                         **kwargs):
    """:func:`~hartrao_jax.diagnose.diagnose`, then (when ``report_dir`` is given) its figures
    and ``index.html`` written there by :func:`write_report`."""
    diag = diagnose(campaign, start, **kwargs)
    if report_dir is not None:
        write_report(diag, report_dir)
    return diag


def diagnosis_local_figures(diag, out_dir) -> list[tuple[str, str]]:
    """Figures of the local-deformation search of a :class:`~._diagnose.Diagnosis`: for each
    search the residual map before (and after, when the deformation was accepted and modelled)
    and the matched-filter map (roughness-standardised score ``t`` at the candidate's width),
    the candidate outlined by a circle of radius ``2 w`` (solid: accepted; dashed: the largest
    local structure, not distinguishable from the roughness). Returns ``(title, file)`` rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    out = Path(out_dir)
    rows: list[tuple[str, str]] = []
    hist = diag.history
    if not hist or not diag.local_search:
        return rows
    ids = list(hist[0]["maps"])[:2]
    for rec in diag.local_search:
        maps = rec.get("_maps") or []
        if not maps or rec.get("x_m") is None:
            continue
        k = rec.get("search", 1)
        accepted = bool(rec.get("accepted"))
        after = next((h for h in hist if h.get("label") == "local_deformation"
                      and h.get("step", 0) >= k), None) if accepted else None
        m = min(maps, key=lambda mm: abs(mm.width_m - rec["width_m"]))
        x0, y0 = rec["where"]["x_m"] if accepted else rec["x_m"], (
            rec["where"]["y_m"] if accepted else rec["y_m"])
        w = rec["estimate"]["width_m"]["value"] if accepted else rec["width_m"]
        ncol = 3 if after is not None else 2
        fig, axes = plt.subplots(len(ids), ncol, figsize=(4.2 * ncol, 3.9 * len(ids)),
                                 squeeze=False)
        for r_, sid in enumerate(ids):
            ext = diag.extents.get(sid, [-13.0, 13.0, -13.0, 13.0])
            b = hist[0]["maps"][sid]
            fin = np.abs(b[np.isfinite(b)])
            lim = 1e3 * float(np.percentile(fin, 98)) if fin.size else 0.5
            panels = [("residual before [mm]", b)] + (
                [("residual after [mm]", after["maps"][sid])] if after is not None else [])
            for c_, (lab, mp) in enumerate(panels):
                ax = axes[r_, c_]
                im = ax.imshow(1e3 * mp.T, origin="lower", extent=ext, cmap="RdBu_r",
                               vmin=-lim, vmax=lim)
                ax.set_title(f"{sid}: {lab}", fontsize=9)
                fig.colorbar(im, ax=ax, shrink=0.7)
            ax = axes[r_, ncol - 1]
            t = np.where(m.valid, m.t, np.nan)
            e = [m.origin[0], m.origin[0] + m.cell_m * t.shape[0],
                 m.origin[1], m.origin[1] + m.cell_m * t.shape[1]]
            tl = float(np.nanmax(np.abs(t))) if np.isfinite(t).any() else 1.0
            im = ax.imshow(t.T, origin="lower", extent=e, cmap="PuOr_r", vmin=-tl, vmax=tl)
            ax.set_xlim(ext[0], ext[1])
            ax.set_ylim(ext[2], ext[3])
            ax.set_title(f"matched filter t, w = {m.width_m:g} m", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.7)
            for ax in axes[r_]:
                ax.add_patch(Circle((x0, y0), 2 * w, fill=False, lw=1.2, color="k",
                                    ls="-" if accepted else "--"))
                ax.set_aspect("equal")
                ax.set_xlabel("X [m]")
                ax.set_ylabel("Y [m]")
        state = "accepted and modelled" if accepted else "not distinguishable from the roughness"
        fig.suptitle(f"local deformation search {k}: {state}", fontsize=10)
        name = f"local_deformation_{k}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        rows.append((f"local deformation search {k}: {state}", name))
    return rows
