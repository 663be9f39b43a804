"""Which covariate carries off-catalog structure: compared on held-out points.

Residual structure that no catalog effect explains is reported with the covariate it follows
(range, incidence angle, intensity, time, theta, phi, rho, psi). On a paraboloid several of them
are correlated (range and incidence angle, theta and rho), so a covariate that merely correlates
with the true one also "explains" part of the structure when it is fitted and scored on the
same points. Here every covariate gets two predictors fitted on training points and scored on
held-out points (``FOLDS``-fold cross-validation, explained fraction of the held-out variance):

* bins: the mean per quantile bin (``BINS`` bins);
* periodic: a constant plus ``a sin(2 pi v / P) + b cos(2 pi v / P)``, the period ``P`` chosen
  on the training points from a periodogram over ``N_PERIODS`` log-spaced periods between
  ``span / 100`` and ``span / 1.5`` of the covariate (a short period in range is the cyclic
  error of a phase-comparison rangefinder, invisible to coarse bins).

The best covariate is the one with the largest held-out explained fraction; the runners-up are
reported with their scores. Known signatures are named (:data:`PHYSICS`), the structure stays
``unexplained`` when the catalog lacks it.

NumPy; units of each covariate (range m, angles rad, time s, intensity 0..1).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

FOLDS = 4
BINS = 16
N_PERIODS = 150
MAX_POINTS = 30_000

PHYSICS = {
    ("range", "periodic"): "a range error periodic in range is the cyclic error of a "
                           "phase-comparison rangefinder (non-linearity of the phase "
                           "measurement), not in the catalog",
    ("intensity", "bins"): "a range error following the intensity is a range walk of the "
                           "signal strength (not in the catalog)",
    ("incidence_angle", "bins"): "a range error following the incidence angle is a beam "
                                 "footprint / surface penetration effect (not in the catalog)",
}


def _bins_predict(vt, rt, vv):
    qs = np.quantile(vt, np.linspace(0, 1, BINS + 1)[1:-1])
    it = np.searchsorted(qs, vt, side="right")
    s = np.bincount(it, rt, minlength=BINS)
    c = np.bincount(it, minlength=BINS)
    mean = np.where(c > 0, s / np.maximum(c, 1), 0.0)
    return mean[np.searchsorted(qs, vv, side="right")]


def _periodogram(v, r, periods):
    """Residual sum of squares of a sinusoid plus a constant at each period (vectorised
    normal equations)."""
    v = np.asarray(v, float)
    r = np.asarray(r, float) - np.mean(r)
    n = len(v)
    out = np.empty(len(periods))
    for lo in range(0, len(periods), 64):
        P = np.asarray(periods[lo: lo + 64])
        ph = 2 * np.pi * v[:, None] / P[None, :]
        S, C = np.sin(ph), np.cos(ph)
        # centre the columns (the constant is eliminated)
        S -= S.mean(0)
        C -= C.mean(0)
        ss, cc, sc = np.sum(S * S, 0), np.sum(C * C, 0), np.sum(S * C, 0)
        sr, cr = r @ S, r @ C
        det = ss * cc - sc * sc
        det = np.where(det > 1e-12 * n * n, det, np.inf)
        expl = (cc * sr * sr - 2 * sc * sr * cr + ss * cr * cr) / det
        out[lo: lo + 64] = float(r @ r) - expl
    return out


def compare(values: Mapping[str, np.ndarray], r: np.ndarray, *, seed: int = 0) -> dict:
    """Cross-validated comparison of covariates for residuals ``r``.

    ``values``: covariate name -> per-point values (finite where usable). Returns
    ``{"ranking": [{covariate, model, cv_explained, period?, amplitude_m?}...], "best": row,
    "physics": str | None}`` with the ranking best first (one row per covariate: its better
    model).
    """
    r = np.asarray(r, float)
    rng = np.random.default_rng(seed)
    n = len(r)
    idx = rng.permutation(n)[:MAX_POINTS]
    fold = np.arange(len(idx)) % FOLDS
    rows = []
    for name, v_all in values.items():
        v = np.asarray(v_all, float)[idx]
        rr = r[idx]
        ok = np.isfinite(v) & np.isfinite(rr)
        if ok.sum() < 10 * BINS or np.ptp(v[ok]) <= 0:
            continue
        v, rr, fo = v[ok], rr[ok], fold[ok]
        span = float(np.ptp(v))
        periods = np.geomspace(span / 100.0, span / 1.5, N_PERIODS)
        sse = {"bins": 0.0, "periodic": 0.0}
        sst = 0.0
        chosen = []
        for k in range(FOLDS):
            tr, te = fo != k, fo == k
            if te.sum() < 5 or tr.sum() < 10 * BINS:
                continue
            mu = rr[tr].mean()
            sst += float(np.sum((rr[te] - mu) ** 2))
            sse["bins"] += float(np.sum((rr[te] - _bins_predict(v[tr], rr[tr], v[te])) ** 2))
            # the period from the training points only (coarse then fine)
            sub = np.flatnonzero(tr)[:: max(1, int(tr.sum()) // 3000)]
            ps = _periodogram(v[sub], rr[sub], periods)
            P0 = periods[int(np.argmin(ps))]
            fine = P0 * np.linspace(0.97, 1.03, 25)
            sub = np.flatnonzero(tr)[:: max(1, int(tr.sum()) // 12000)]
            P = fine[int(np.argmin(_periodogram(v[sub], rr[sub], fine)))]
            ph = 2 * np.pi * v / P
            A = np.column_stack([np.sin(ph), np.cos(ph), np.ones_like(v)])
            coef, *_ = np.linalg.lstsq(A[tr], rr[tr], rcond=None)
            sse["periodic"] += float(np.sum((rr[te] - A[te] @ coef) ** 2))
            chosen.append((P, float(np.hypot(coef[0], coef[1]))))
        if sst <= 0:
            continue
        for model in ("bins", "periodic"):
            row = {"covariate": name, "model": model, "cv_explained": 1.0 - sse[model] / sst}
            if model == "periodic" and chosen:
                Ps = np.array([c[0] for c in chosen])
                row["period"] = float(np.median(Ps))
                row["period_spread"] = float(np.ptp(Ps))
                row["amplitude_m"] = float(np.median([c[1] for c in chosen]))
            rows.append(row)
    best_per = {}
    for row in rows:
        b = best_per.get(row["covariate"])
        if b is None or row["cv_explained"] > b["cv_explained"]:
            best_per[row["covariate"]] = row
    ranking = sorted(best_per.values(), key=lambda x: -x["cv_explained"])
    out = {"method": f"{FOLDS}-fold cross-validated explained fraction of held-out residual "
                     f"variance; bins ({BINS} quantile bins) or one sinusoid with the period "
                     "chosen on the training folds (periodogram)",
           "ranking": ranking, "all": rows, "best": ranking[0] if ranking else None,
           "physics": None}
    if ranking:
        b = ranking[0]
        # a periodic model is named only if its period is stable across the folds
        if b["model"] == "periodic" and b.get("period_spread", 1e9) > 0.05 * b["period"]:
            out["note"] = "period not stable across the folds"
        out["physics"] = PHYSICS.get((b["covariate"], b["model"]))
    return out
