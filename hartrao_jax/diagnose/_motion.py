"""Period of a modelled oscillation: refined from the periodogram once the panel offsets no
longer hold part of it, and estimated with the amplitudes (free frequency).

Units: seconds (periods), hertz (frequency correction).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..model._model import OSC_FREQUENCY, OSCILLATION
from ._find import _periodogram_points
from ._signature import _signature
from ._state import _adjust, _Context, _refit, _scan_model, _set_known, _Spec

log = logging.getLogger("hartrao_jax")


def _refine_periods(ctx: _Context, spec: _Spec, refit) -> None:
    """Period of a modelled oscillation from the periodogram of the misclosures without it,
    now that the panel offsets no longer hold part of it; refit when it moved."""
    for sc, names in refit:
        mot = spec.motion[sc.id]
        vals = np.array([sc.value(n) for n in names])
        sig = _signature(ctx, sc, spec, names, vals)
        f0 = 1.0 / mot["period_s"]
        fz = f0 * (1.0 + np.linspace(-0.01, 0.01, 41))
        Pz = _periodogram_points(sc, fz, sc.F - sig)
        j = int(np.argmax(Pz))
        fbest = fz[j]
        if 0 < j < len(Pz) - 1:
            den = Pz[j - 1] - 2 * Pz[j] + Pz[j + 1]
            if den < 0:
                fbest = fz[j] + 0.5 * (Pz[j - 1] - Pz[j + 1]) / den * (fz[1] - fz[0])
        if abs(fbest / f0 - 1.0) > 2e-4:
            log.debug("period of %s refined: %.5f -> %.5f s", sc.id, 1 / f0, 1 / fbest)
            mot["period_s"] = sc.period_s = float(1.0 / fbest)
            _set_known(ctx, sc, spec)
            _refit(ctx, sc, spec, from_used=True)


def _free_frequency(ctx: _Context, spec: _Spec, refit) -> dict[str, dict]:
    """Estimate the oscillation frequency with the amplitudes (one more GH adjustment per scan).

    The amplitudes of a fixed period are conditional on it: a period off by 0.1 % turns the
    phase by 0.07 rad over an 11 s scan, many sigma of the amplitudes. With the frequency
    correction ``osc_df_hz`` free the period is corrected and the amplitude covariance grows
    by ``C_free - C_fixed`` (the part the period's uncertainty adds); the scan is then refitted
    at the corrected period. Returns per scan id the added covariance over its oscillation
    names, the period and its sigma (s).
    """
    out = {}
    for sc, names in refit:
        mot = spec.motion[sc.id]
        osc = [n for n in names if n in OSCILLATION]
        if not osc:
            continue
        model = _scan_model(sc, spec, ctx.aperture, extra=(OSC_FREQUENCY,))
        x0 = np.array([sc.value(n) if n in sc.names else 0.0 for n in model.free])
        w = (sc.used & ~sc.cut).astype(float)
        res = _adjust(ctx, model, sc.l, x0, sc.consts(), w)
        free = list(model.free)
        j = free.index(OSC_FREQUENCY)
        C = np.asarray(res.cov)
        if not res.converged or not np.isfinite(C[j, j]) or C[j, j] <= 0:
            continue
        f0 = 1.0 / mot["period_s"]
        df = float(res.x[j])
        a = [free.index(n) for n in osc]
        b = [sc.names.index(n) for n in osc]
        D = C[np.ix_(a, a)] - sc.cov[np.ix_(b, b)]
        w_, V = np.linalg.eigh(0.5 * (D + D.T))
        D = (V * np.maximum(w_, 0.0)) @ V.T
        period = 1.0 / (f0 + df)
        mot["period_s"] = sc.period_s = float(period)
        _refit(ctx, sc, spec, from_used=True)
        out[sc.id] = {"names": osc, "added_cov": D, "period_s": float(period),
                      "period_sigma_s": float(math.sqrt(C[j, j]) * period**2)}
    return out
