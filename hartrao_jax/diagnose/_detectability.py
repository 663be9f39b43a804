"""Minimal detectable amplitudes (Baarda) of every candidate at the final solution.

Units: minimal detectable amplitudes in the parameters' own units, rms effects in
metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import special

from ..model._model import SHIFT
from ._explain import _Joint, _Test
from ._state import _Context, _Scan

POWER = 0.8  # of the minimal detectable amplitude (Baarda's beta = 0.2)


def _noncentrality(alpha: float, dof: int, power: float = POWER) -> float:
    """The noncentrality at which a chi-square test of ``dof`` degrees of freedom at level
    ``alpha`` rejects with probability ``power`` (scipy.special's chi-square functions: the
    same numbers as scipy.stats to 1e-15, without its 0.4 s import; the noncentral
    distribution's inverse in its noncentrality, within 4e-16 of a root search on its CDF,
    without scipy.optimize's 0.1 s import)."""
    return float(special.chndtrinc(special.chdtri(dof, alpha), dof, 1.0 - power))


def _detectability(ctx: _Context, joint: _Joint, tests: Sequence[_Test],
                   m_tests: int, S: Sequence[_Scan] = ()) -> list[dict]:
    """Minimal detectable amplitude of every candidate at the final solution (Baarda).

    The noncentrality ``lam`` gives 80 % power at the Bonferroni-adjusted level of a step; the
    amplitude of parameter j alone is ``sigma0 sqrt(lam / S_jj)`` (S: the Schur complement of
    the candidate with the model and the panel offsets eliminated), or what reaches
    ``min_effect_m``, whichever is larger. ``rms_effect_m`` is the rms change of the points'
    condition at that amplitude before the model absorbs part of it;
    ``relative_to_range_noise`` divides it by ``sigma_range_m``.
    """
    cfg = ctx.config
    out = []
    s0 = joint.sigma0
    sq = joint.sum_q
    for t in tests:
        if t.S is None or t.dof == 0 or t.confounded or t.cand.effect == "impulsive_shift":
            continue
        q = t.dof
        a = cfg.alpha / max(m_tests, 1) / t.cand.penalty
        lam = _noncentrality(a, q)
        for j, name in enumerate(t.cand.names):
            if t.S[j, j] <= 0:
                continue
            # a bias of this parameter alone: noncentrality d^2 S_jj / sigma0^2
            mdb_stat = s0 * math.sqrt(lam / t.S[j, j])
            mdb_eff = cfg.min_effect_m * math.sqrt(sq / t.S[j, j])
            mdb = max(mdb_stat, mdb_eff)
            raw = mdb * math.sqrt(max(t.Draw[j, j], 0.0) / sq)
            out.append({"effect": t.cand.effect, "parameter": name, "scans": t.cand.scans,
                        "minimal_detectable": mdb,
                        "limited_by": "statistic" if mdb_stat >= mdb_eff else "effect_size",
                        "rms_effect_m": raw,
                        "relative_to_range_noise": raw / float(ctx.sigma[0]),
                        "correlation_with_model": t.correlation})
    # an impulsive shift: for a reference window (the middle 5 % of the first scan's time),
    # from the translation derivatives of the points (the windows found in noise are arbitrary)
    for sc in S[:1]:
        u = sc.used & (sc.m > 0)
        t_ = sc.data.time_s[u]
        a = sc.probe[u][:, :3]
        q_ = 1.0 / sc.m[u]
        lo, hi = np.quantile(t_, [0.475, 0.525])
        w = (t_ >= lo) & (t_ < hi)
        Ntot = (a * q_[:, None]).T @ a
        NW = (a[w] * q_[w, None]).T @ a[w]
        SW = NW - NW @ np.linalg.pinv(Ntot) @ NW
        pen = float(sc.search.get("n_windows", 1))
        lam = _noncentrality(cfg.alpha / max(m_tests, 1) / pen, 3)
        for j, name in enumerate(SHIFT):
            mdb_stat = s0 * math.sqrt(lam / max(SW[j, j], 1e-300))
            mdb_eff = cfg.min_effect_m * math.sqrt(sq / max(SW[j, j], 1e-300))
            mdb = max(mdb_stat, mdb_eff)
            raw = mdb * math.sqrt(NW[j, j] / float(np.sum(q_[w])))  # rms inside the window
            out.append({"effect": "impulsive_shift", "parameter": name, "scans": [sc.id],
                        "minimal_detectable": mdb,
                        "limited_by": "statistic" if mdb_stat >= mdb_eff else "effect_size",
                        "rms_effect_m": raw, "relative_to_range_noise": raw / float(ctx.sigma[0]),
                        "window": "middle 5 % of the scan (rms effect inside the window)",
                        "correlation_with_model": None})
    return out
