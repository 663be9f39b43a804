"""HTML building blocks: escaping, tables, number formatting and the page under construction
(:class:`_Doc`; figures embedded as base64 PNG)."""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ._draw import png_bytes

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:2em auto;
max-width:1250px;color:#222;line-height:1.4;padding:0 1em}
h1{font-size:1.6em}h2{border-bottom:2px solid #ddd;padding-bottom:.2em;margin-top:2em}
h3{margin-top:1.5em}table{border-collapse:collapse;margin:.6em 0;font-size:.85em}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:right}th{background:#f2f2f2}
td:first-child,th:first-child{text-align:left}figure{margin:1em 0}
figure img{max-width:100%;border:1px solid #eee}figcaption{font-size:.85em;color:#555}
.note{color:#8a5300}.small{font-size:.85em;color:#555}details{margin:.5em 0}
nav ul{columns:2}code{background:#f5f5f5;padding:0 3px}
"""


def _esc(x) -> str:
    return html.escape(str(x))


def _table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    h = "".join(f"<th>{_esc(c)}</th>" for c in headers)
    body = "".join("<tr>" + "".join(f"<td>{_esc(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>"


def _f(v, fmt="{:.4f}", scale=1.0, none="\u2013"):
    if v is None:
        return none
    try:
        v = float(v)
    except (TypeError, ValueError):
        return str(v)
    return fmt.format(v * scale) if math.isfinite(v) else none


class _Doc:
    def __init__(self, fig_dir: Path | None):
        self.parts: list[str] = []
        self.toc: list[tuple[str, str]] = []
        self.fig_dir = fig_dir
        self.n_fig = 0
        self.figures: list[Path] = []

    def h2(self, title: str, anchor: str):
        self.toc.append((anchor, title))
        self.parts.append(f'<h2 id="{anchor}">{_esc(title)}</h2>')

    def add(self, s: str):
        self.parts.append(s)

    def figure(self, fig, caption: str, name: str):
        png = png_bytes(fig)
        self.n_fig += 1
        if self.fig_dir is not None:
            p = self.fig_dir / f"{self.n_fig:02d}_{name}.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(png)
            self.figures.append(p)
        b64 = base64.b64encode(png).decode("ascii")
        self.parts.append(f'<figure><img alt="{_esc(name)}" src="data:image/png;base64,{b64}">'
                          f"<figcaption>Figure {self.n_fig}. {_esc(caption)}</figcaption></figure>")

