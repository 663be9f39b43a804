"""Summaries of the scans for the result: extents and binned maps of the mismatch (figures),
the recording-against-simulation comparison, and grid cells in place of panel ids on a
telescope without a panel layout.

Units: metres (telescope frame).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..geometry._geometry import column_bounds
from ._state import Finding, _Context, _num, _Scan


def _extent(sc: _Scan | _Moment) -> list[float]:
    """Square ``[x0, x1, y0, y1]`` (m, telescope frame) around the scan's points in the window."""
    w = sc.window & np.all(np.isfinite(sc.X_tel[:, :2]), 1)
    if not w.any():
        return [-1.0, 1.0, -1.0, 1.0]
    lo, hi = column_bounds(sc.X_tel[w, :2])
    c, h = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) * 1.02 + 1e-3
    return [float(c[0] - h), float(c[0] + h), float(c[1] - h), float(c[1] + h)]


def _cells_not_panels(ctx: _Context, f: Finding) -> None:
    """Grid cells instead of panel ids for a telescope without a panel layout: centres (m)."""
    g = ctx.geo
    if "panels" in f.where:
        ids = f.where.pop("panels")
        f.where["cells"] = [{"cell": int(k), "x_m": float(g["rho_c"][k] * np.cos(g["psi_c"][k])),
                             "y_m": float(g["rho_c"][k] * np.sin(g["psi_c"][k]))} for k in ids]
        f.where["grid"] = ctx.layout_note
    if f.effect == "panel_offset":
        f.explanation = f.explanation.replace(" panels, offsets", " grid cells (no panel layout), "
                                              "offsets")
    for k in [k for k in f.estimate if k.startswith("panel_") and k.endswith("_offset_m")]:
        f.estimate[k.replace("panel_", "cell_", 1)] = f.estimate.pop(k)


def _dish_map(sc: _Scan | _Moment, values: np.ndarray, n: int = 96):
    """Binned mean of ``values`` on an ``n x n`` grid of telescope X, Y over the scan's extent
    (for figures), over its points in use."""
    u = sc.used & np.all(np.isfinite(sc.X_tel[:, :2]), 1)
    x0, x1, y0, y1 = _extent(sc)
    X, Y = sc.X_tel[u, 0], sc.X_tel[u, 1]
    i = np.clip(((X - x0) / (x1 - x0) * n).astype(int), 0, n - 1)
    j = np.clip(((Y - y0) / (y1 - y0) * n).astype(int), 0, n - 1)
    k = i * n + j
    s = np.bincount(k, values[u], minlength=n * n)
    c = np.bincount(k, minlength=n * n)
    out = np.full(n * n, np.nan)
    out[c > 0] = s[c > 0] / c[c > 0]
    return out.reshape(n, n)


@dataclass(frozen=True)
class _Moment:
    """What a mismatch map needs of a scan at one moment: its telescope coordinates and
    window (never changed during a diagnosis: shared, not copied) and its points in use then
    (a copy)."""

    X_tel: np.ndarray
    window: np.ndarray
    used: np.ndarray


class _Maps(Mapping[str, np.ndarray]):
    """Binned mismatch maps (m, float32) of the scans as they were when it was made, by scan
    id, for the history figures. It keeps each scan's mismatch of that moment (a fresh
    array) and its points in use (:class:`_Moment`, not the scan: a diagnosis kept does not
    keep its scans) and bins them when a map is first read: a diagnosis without a report
    (the command without ``--report``) never bins them (0.05 s a snapshot of two 2.6e5-point
    scans)."""

    def __init__(self, scans: Sequence[_Scan]):
        self._of = {sc.id: (_Moment(sc.X_tel, sc.window, sc.used.copy()), sc.mismatch_m)
                    for sc in scans}
        self._maps: dict[str, np.ndarray] = {}

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in self._maps:
            moment, d = self._of[key]
            self._maps[key] = _dish_map(moment, d).astype(np.float32)
        return self._maps[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._of)

    def __len__(self) -> int:
        return len(self._of)


def _snapshot(scans: Sequence[_Scan]) -> _Maps:
    """Binned mismatch maps (m, float32) of every scan at this moment, for the history
    figures (binned when read)."""
    return _Maps(scans)


def _compare(sc: _Scan) -> dict:
    """Recording minus simulation of one scan, summarised (m)."""
    u = sc.used
    d = sc.mismatch_m
    rr = sc.mismatch_range_m
    row = {"scan": sc.id, "position": sc.meta.position, "cycle": sc.meta.cycle,
           "n_points": int(u.sum()), "sigma0": _num(sc.sigma0),
           "rms_deviation_m": _num(np.sqrt(np.mean(d[u] ** 2))),
           "rms_range_m": _num(np.sqrt(np.mean(rr[u] ** 2))), "faces": {}}
    for fc in (1, 2):
        s = u & (sc.face == fc)
        if s.any():
            row["faces"][str(fc)] = {"n_points": int(s.sum()),
                                     "mean_deviation_m": _num(np.mean(d[s])),
                                     "rms_deviation_m": _num(np.sqrt(np.mean(d[s] ** 2)))}
    return row
