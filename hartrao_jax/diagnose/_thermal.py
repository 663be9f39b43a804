"""The ``thermal`` effect: the scans' focal lengths against temperature (no mismatch in the
points: the focal length is estimated per scan).

Units: metres, kelvin (degrees Celsius for the temperatures reported).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from ..physics._catalog import EFFECTS
from ..solver._mixed import chi2_sf
from ._state import Finding, _Context, _global_sigma0, _rms, _Scan

log = logging.getLogger("hartrao_jax")

THERMAL_REFERENCE_C = 15.0
THERMAL_MIN_POSITIONS = 10  # with 7 the temperature term took up 0.4 mm/K of pointing effects


def _thermal(ctx: _Context, S: Sequence[_Scan], m_tests: int):
    """Focal length against temperature across the scans (catalog effect ``thermal``).

    The focal length is estimated per scan, so a thermal change of f leaves no mismatch in the
    points: it shows in the scans' focal lengths. They are regressed (weights ``1/sigma_f^2``)
    on a constant, the gravity vector (when the positions span it, so that a gravity change of
    f is not taken for a thermal one: at least :data:`THERMAL_MIN_POSITIONS` positions then)
    and ``T - 15 C``; the statistic of the
    temperature term is scaled by the variance factor of the regression (scatter of f beyond
    its formal sigma, e.g. from unmodelled surface modes). Returns ``("finding", Finding)``,
    ``("confounded", dict)`` when temperature and gravity cannot be told apart (fewer
    positions), or None (too few scans or temperatures, not significant).
    """
    rows = [sc for sc in S if sc.meta.temperature_c is not None and "f" in sc.names
            and sc.converged]
    if len(rows) < 4:
        return None
    T = np.array([sc.meta.temperature_c for sc in rows], float) - THERMAL_REFERENCE_C
    if np.ptp(T) < 1.0:
        return None
    j = [sc.names.index("f") for sc in rows]
    f = np.array([sc.x[k] for sc, k in zip(rows, j)])
    sf = np.array([math.sqrt(max(sc.cov[k, k], 0.0)) for sc, k in zip(rows, j)])
    if np.any(sf <= 0):
        return None
    G = np.array([sc.g for sc in rows], float)
    n_pos = len({sc.meta.position for sc in rows})
    with_g = float(np.ptp(G, axis=0).max()) > 0.05
    if with_g and n_pos < THERMAL_MIN_POSITIONS:
        # f also follows the pointing (gravity, and surface modes the fit of f takes up):
        # with few positions a temperature drift over the night is indistinguishable from it
        r = max(abs(float(np.corrcoef(T, G[:, a])[0, 1])) for a in range(3)
                if np.ptp(G[:, a]) > 1e-6)
        return "confounded", {"effect": "thermal", "with": ["gravity"], "correlation": r,
                              "reason": f"{n_pos} positions: f against temperature needs at "
                                        f"least {THERMAL_MIN_POSITIONS} to be told apart from "
                                        f"f against gravity"}
    base = [np.ones(len(rows))] + ([G[:, a] for a in range(3)] if with_g else [])
    w = 1.0 / sf**2

    def wls(cols):
        X = np.column_stack(cols)
        N = X.T @ (X * w[:, None])
        c = np.linalg.solve(N, X.T @ (w * f))
        r = f - X @ c
        return c, np.linalg.inv(N), float(np.sum(w * r * r)), r

    p1 = len(base) + 1
    dof = len(rows) - p1
    if dof < 1:
        return None
    _, _, chi0, r0 = wls(base)
    c1, Q1, chi1, r1 = wls(base + [T])
    vf = max(1.0, chi1 / dof)
    stat = (chi0 - chi1) / vf
    p = chi2_sf(1, stat)
    b, sb = float(c1[-1]), float(math.sqrt(Q1[-1, -1] * vf))
    size = abs(b) * float(np.ptp(T))
    cfg = ctx.config
    log.info("thermal: df/dT %.4f +- %.4f mm/K over %.1f K, statistic %.1f (variance factor "
             "%.2f, %d scans, gravity terms %s)", 1e3 * b, 1e3 * sb, np.ptp(T), stat, vf,
             len(rows), with_g)
    if not (p * max(m_tests, 1) < cfg.alpha and size > cfg.min_effect_m):
        return None
    s0 = _global_sigma0(S)
    rms = _rms(S)
    rms_f = (float(np.sqrt(np.mean(r0**2))), float(np.sqrt(np.mean(r1**2))))
    expl = (f"{EFFECTS['thermal'].explanation}; "
            f"df/dT = {1e3 * b:.3f} ± {1e3 * sb:.3f} mm/K over {np.ptp(T):.1f} K "
            f"({len(rows)} scans, {n_pos} positions{', gravity terms estimated' if with_g else ''})"
            f"; the points' fit is unchanged (f is estimated per scan): the focal lengths "
            f"scatter {1e3 * rms_f[0]:.3f} -> {1e3 * rms_f[1]:.3f} mm about the model")
    return "finding", Finding(
        "thermal", "reflector", [sc.id for sc in rows],
        {"covariate": "temperature", "temperature_c": [float(T.min() + THERMAL_REFERENCE_C),
                                                       float(T.max() + THERMAL_REFERENCE_C)],
         "positions": sorted({sc.meta.position for sc in rows})},
        {"df_dT_m_per_K": {"value": b, "sigma": sb}}, stat, 1, p, s0, s0, rms, rms, expl,
        effect_size_m=size,
        extra={"reference_c": THERMAL_REFERENCE_C, "gravity_terms": with_g,
               "variance_factor": vf, "focal_rms_before_m": rms_f[0],
               "focal_rms_after_m": rms_f[1]})
