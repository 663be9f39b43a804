"""Checks of an accepted explanation before it is modelled: the family's physics signature
(one instrument constant for every scan; a motion that the other cycle does not share), and
the alternatives the data hardly tell apart from it.

Units: statistics are chi-square values (dimensionless), slopes m/m.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ._explain import _Candidate, _Joint, _log_sf, _Test
from ._find import _panel_cells
from ._options import _Option
from ._signature import _signature
from ._state import _num, _Scan


def _signature_check(ctx, S, spec, joint, o: _Option, options: Sequence[_Option] = ()) -> str:
    """The family's physics signature; returns a reason to refuse, or ``""``."""
    cfg = ctx.config
    if o.kind == "catalog" and o.family == "instrument":
        t: _Test = o.payload
        Td, dd = joint.scan_difference(t.cand, t)
        t.T_diff, t.dof_diff = Td, dd
        if dd > 0 and _log_sf(Td, dd) < math.log(cfg.alpha) and Td > cfg.scan_consistency * t.T:
            return (f"not one instrument constant: freeing it per scan adds T={Td:.0f} "
                    f"({dd} dof) to T={t.T:.0f}")
        return ""
    if o.kind == "catalog" and o.family == "motion":
        t = o.payload
        sc = next(s for s in S if s.id == t.cand.scans[0])
        names = t.cand.names
        sig = _signature(ctx, sc, spec, names, t.estimate, window_s=sc.window_s,
                         period_s=sc.period_s)
        t.notes.append("signature")
        o.payload.cand.info["signature"] = sig
        if o.effect == "impulsive_shift" and _at_edge(sc) and any(
                x is not o and x.kind == "catalog" and x.effect == "drift" and x.eligible
                and x.log_p < math.log(cfg.alpha) and sc.id in x.payload.cand.scans
                for x in options):
            return ("a shift window at the start or end of the scan is what a drift leaves "
                    "once the pose takes up its mean: the drift is modelled first")
        others = [s for s in S if s.meta.position == sc.meta.position and s.id != sc.id]
        if not others:
            return ""
        slope, z = _common_slope(ctx, sc, others, sig / sc.s_rho)
        o.payload.cand.info["common_slope"] = (slope, z)
        # the two cycles see a dish point at the same time of their scans: the same motion in
        # both (a significant candidate there too) shows the same pattern in both
        twin = [x for x in options if x is not o and x.kind == "catalog" and x.effect == o.effect
                and x.log_p < math.log(cfg.alpha)
                and set(x.payload.cand.scans) & {s.id for s in others}
                and _same_motion(o.effect, sc, next(s for s in others
                                                   if s.id == x.payload.cand.scans[0]))]
        if twin:  # modelled together (one step), see _apply
            best = {}
            for x in sorted(twin, key=lambda x: x.log_p):
                best.setdefault(x.payload.cand.scans[0], x)
            o.payload.cand.info["twins"] = list(best.values())
            return ""
        if slope > cfg.common_slope and z > 4.0:
            return (f"the other cycle shows the same deviation in the same dish cells "
                    f"(slope {slope:.2f}, z {z:.1f}): a reflector effect, not motion")
    return ""


# below this likelihood ratio between two candidates the data hardly tell them apart (20:
# "strong" evidence on Kass & Raftery's scale starts there)
AMBIGUOUS_LIKELIHOOD_RATIO = 20.0


def _alternatives(joint: _Joint, best: _Option, options: Sequence[_Option]) -> list[dict]:
    """Other significant candidates of the same family that the data hardly tell apart from
    the accepted one (|correlation of the estimates| > 0.9): the choice between them rests on
    a small difference of their statistics (a likelihood ratio below
    :data:`AMBIGUOUS_LIKELIHOOD_RATIO`; a larger one is a clear choice).

    ``likelihood_ratio``: ``exp((T_best - T_alt) / 2)``, how much better the accepted one
    explains the data (score statistics of one dof each, as twice the log-likelihood gain of
    each model over the current one)."""
    if best.kind != "catalog" or best.family != "instrument":
        return []
    cb = best.payload.cand
    out = []
    for o in options:
        if o is best or o.kind != "catalog" or o.family != "instrument" or not o.log_p < 0:
            continue
        lr = math.exp(min(0.5 * (best.T - o.T), 700.0))
        if lr >= AMBIGUOUS_LIKELIHOOD_RATIO:
            continue
        c = o.payload.cand
        pair = _Candidate("pair", "instrument", np.concatenate([cb.idx, c.idx]),
                          np.kron(np.eye(2), np.ones((len(cb.idx), 1))), [cb.effect, c.effect],
                          cb.scans)
        t = joint.test(pair)
        if t.cov is None or t.dof < 2:
            continue
        r = t.cov[0, 1] / math.sqrt(max(t.cov[0, 0] * t.cov[1, 1], 1e-300))
        if abs(r) > 0.9:
            out.append({"effect": c.effect, "statistic": _num(o.T),
                        "correlation": float(r), "joint_statistic": _num(t.T),
                        "likelihood_ratio": _num(lr)})
    return out


def _at_edge(sc: _Scan) -> bool:
    """The scan's shift window (``window_s``) starts in its first or ends in its last time
    bin of the search (``search["edges"]``, s)."""
    edges = (sc.search or {}).get("edges")
    if sc.window_s is None or edges is None or len(edges) < 3:
        return False
    start, dur = sc.window_s
    width = float(edges[1] - edges[0])
    return start - float(edges[0]) <= width or float(edges[-1]) - (start + dur) <= width


def _same_motion(effect: str, a: _Scan, b: _Scan) -> bool:
    """The same motion in two cycles: overlapping windows, or periods within 5 %."""
    if effect == "impulsive_shift":
        (s0, d0), (s1, d1) = a.window_s, b.window_s
        inter = max(0.0, min(s0 + d0, s1 + d1) - max(s0, s1))
        return inter > 0.5 * max(d0, d1)
    if effect == "oscillation":
        return abs(a.period_s / b.period_s - 1.0) < 0.05
    return True


def _common_slope(ctx, sc: _Scan, others: Sequence[_Scan], pred: np.ndarray):
    """Regression slope of the other scans' mismatch on the predicted deviation, per dish cell."""
    cell = _panel_cells(ctx, sc)
    u = sc.used & (cell >= 0)
    nc = ctx.n_panels * ctx.config.panel_cells[0] * ctx.config.panel_cells[1]
    cnt = np.bincount(cell[u], minlength=nc)
    p = np.bincount(cell[u], pred[u], minlength=nc) / np.maximum(cnt, 1)
    pmax = np.max(np.abs(p)) if len(p) else 0.0
    hot = (cnt > 0) & (np.abs(p) > 0.5 * pmax)
    so = np.zeros(nc)
    co = np.zeros(nc)
    ss = 0.0
    n = 0
    for o in others:
        c2 = _panel_cells(ctx, o)
        u2 = o.used & (c2 >= 0)
        so += np.bincount(c2[u2], o.mismatch_m[u2], minlength=nc)
        co += np.bincount(c2[u2], minlength=nc)
        ss += float(np.sum(o.mismatch_m[u2] ** 2))
        n += int(u2.sum())
    hot &= co > 0
    if hot.sum() < 3 or pmax == 0:
        return 0.0, 0.0
    om = so[hot] / co[hot]
    w = co[hot]
    pp = p[hot]
    slope = float(np.sum(w * pp * om) / np.sum(w * pp * pp))
    s2 = ss / max(n, 1)  # per-point variance of the other scans' mismatch
    se = math.sqrt(s2 / float(np.sum(w * pp * pp)))
    return slope, slope / se
