"""What an explanation predicts: the change of every point's condition by given parameter
values (:func:`_signature`) and where that change lives on the recording (faces, phi, panels,
the covariate it follows).

Units: metres (condition and deviation), degrees (``phi_deg``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from .._config import on_device
from .._programs import cached_jit
from ..solver._kernel import materialize_trig
from ._find import COVARIATES, _covariate_values
from ._state import _Context, _fixed, _npad, _pad, _Scan, _scan_model, _Spec


@cached_jit
def _columns(model, l, x, c, idx, on):
    """Per point derivatives of the condition w.r.t. the free parameters ``idx``; ``on`` a
    runtime True (each distinct sine and cosine evaluated once, :func:`materialize_trig`)."""
    cond = materialize_trig(model, on)

    def one(args):
        ll, cc = args
        return jax.grad(lambda xx: cond(ll, xx, cc))(x)[idx]

    return jax.lax.map(one, (l, c), batch_size=8192)


def _signature(ctx: _Context, sc: _Scan, spec: _Spec, names: Sequence[str], values: np.ndarray,
               window_s=None, period_s=None) -> np.ndarray:
    """Predicted change of the condition of every point (m) by ``names = values``."""
    model = _scan_model(sc, spec, ctx.aperture, extra=list(names), window_s=window_s,
                        period_s=period_s)
    fixed = _fixed(sc, spec)
    prev = dict(zip(sc.names, sc.x))
    x = np.array([prev.get(k, fixed.get(k, 0.0)) for k in model.free])
    idx = np.array([model.free.index(n) for n in names])
    npad = _npad(len(sc.l))
    A = np.asarray(_columns(model, _pad(sc.l, npad), x, _pad(sc.consts(), npad), idx,
                            on_device(True, bool)))[: len(sc.l)]
    return A @ np.asarray(values, float)


def _where_of_signature(ctx: _Context, sc: _Scan, sig: np.ndarray, motion: bool) -> dict:
    """Where a predicted signature lives: faces, phi range, panels, the covariate it follows."""
    u = sc.used
    dev = -sig / sc.s_rho
    out: dict[str, Any] = {}
    rms_face = {fc: float(np.sqrt(np.mean(dev[u & (sc.face == fc)] ** 2)))
                if np.any(u & (sc.face == fc)) else 0.0 for fc in (1, 2)}
    big = max(rms_face.values())
    faces = [fc for fc in (1, 2) if rms_face[fc] > 0.25 * big]
    if len(faces) == 1:
        out["face"] = faces[0]
    if motion:
        out["cycle"] = sc.meta.cycle
        amax = np.max(np.abs(dev[u])) if u.any() else 0.0
        hit = u & (np.abs(dev) > 0.3 * amax)
        if hit.any():
            ph = np.degrees(sc.data.phi_rad[hit])
            out["phi_deg"] = [float(ph.min()), float(ph.max())]
            pn, cnt = np.unique(sc.panel[hit & (sc.panel >= 0)], return_counts=True)
            out["panels"] = [int(p) for p in pn[np.argsort(-cnt)][:40]]
    # covariate: the one whose binned means (per face) explain most of the signature variance
    # left after the face means (the face flip of two-face effects is reported as face_split)
    vals = _covariate_values(sc)
    best, frac = None, -1.0
    fc = sc.face[u]
    d = dev[u].copy()
    tot0 = float(np.sum(d**2)) or 1.0
    for f in (1, 2):
        if np.any(fc == f):
            d[fc == f] -= d[fc == f].mean()
    out["face_split"] = float(1.0 - np.sum(d**2) / tot0)
    tot = float(np.sum(d**2)) or 1.0
    for name in COVARIATES:
        v = vals[name][u]
        expl = 0.0
        for f in (1, 2):
            s = fc == f
            if s.sum() < 64:
                continue
            qs = np.quantile(v[s], np.linspace(0, 1, 33)[1:-1])
            ids = np.searchsorted(qs, v[s], side="right")
            sums = np.bincount(ids, d[s], minlength=32)
            cnt = np.bincount(ids, minlength=32)
            expl += float(np.sum(sums[cnt > 0] ** 2 / cnt[cnt > 0]))
        if expl / tot > frac:
            best, frac = name, expl / tot
    if best is not None:
        out["covariate"] = best
    return out
