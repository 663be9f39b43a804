"""Which unknowns the data cannot determine, from an adjustment's covariance matrix: strong
pairwise or multiple correlation, or a sigma beyond the unknown's plausible size. Pure NumPy;
used by every adjustment of a position (:mod:`..fit._identify`)."""

from __future__ import annotations

import numpy as np


def unidentifiable(
    cov: np.ndarray, names, candidates, *, threshold: float = 0.99,
    typical: dict[str, float] | None = None,
) -> list[tuple[tuple[str, ...], tuple[str, ...], float, str]]:
    """Parameters the data cannot determine, from the covariance (or cofactor) matrix.

    A candidate (a calibration parameter; object parameters are never held) is not identifiable

    * when its correlation with another unknown exceeds ``threshold`` in absolute value,
    * when its multiple correlation with all the others does (``1 - 1/VIF > threshold^2``, VIF
      the diagonal of the inverse correlation matrix: a near rank deficiency shared by three or
      more unknowns), or
    * when its sigma exceeds its ``typical`` magnitude (the data say less about it than its
      plausible size: e.g. x6 and x7 near the zenith, where they act as a rotation about the
      reflector's axis of symmetry, which no reflector of revolution can show).

    Candidates confounded with each other are returned together. Returns ``[(held names,
    confounded with, max |correlation|, reason)]`` with reason ``"correlation"`` or ``"sigma"``.
    """
    names = list(names)
    typical = typical or {}
    C = np.asarray(cov, float)
    s = np.sqrt(np.clip(np.diag(C), 1e-300, None))
    R = C / np.outer(s, s)
    np.fill_diagonal(R, 0.0)
    try:
        vif = np.diag(np.linalg.inv(R + np.eye(len(s))))
        multiple = 1.0 - 1.0 / np.clip(vif, 1.0, None)
    except np.linalg.LinAlgError:
        multiple = np.ones(len(names))
    corr_bad = {i for i, n in enumerate(names) if n in set(candidates)
                and (np.max(np.abs(R[i])) > threshold or multiple[i] > threshold**2)}
    sigma_bad = {i for i, n in enumerate(names) if n in set(candidates) and n in typical
                 and s[i] > typical[n]}
    bad = sorted(corr_bad | sigma_bad)
    out, seen = [], set()
    for i in sorted(bad, key=lambda i: -multiple[i]):
        if i in seen:
            continue
        group = [i] + [j for j in bad if j != i and j not in seen and abs(R[i, j]) > 0.9]
        seen.update(group)
        partners = [j for j in range(len(names)) if j not in group
                    and max(abs(R[g, j]) for g in group) > 0.9]
        corr = float(max(np.max(np.abs(R[g])) for g in group))
        reason = "correlation" if any(g in corr_bad for g in group) else "sigma"
        out.append((tuple(names[g] for g in group), tuple(names[j] for j in partners),
                    max(corr, float(np.sqrt(max(multiple[i], 0.0)))), reason))
    return out
