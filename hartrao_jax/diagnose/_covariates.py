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

from .._config import each_in_threads

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


def _sincos_turns(turns):
    """``(sin 2 pi t, cos 2 pi t)`` of phases ``t`` in turns, as float64 arrays, evaluated in
    single precision after removing the whole turns in double: absolute error below 2e-7 at
    a sixth of the time (NumPy's float32 sine is vectorised, its float64 sine is not: 0.4
    against 16 ns per value here). For the period searches only: the sinusoid of the chosen
    period is fitted in double."""
    frac = turns - np.rint(turns)
    ph = (frac * (2 * np.pi)).astype(np.float32)
    return np.sin(ph).astype(float), np.cos(ph).astype(float)


def _periodogram_folds(v, r, fold, periods, n_folds: int = FOLDS):
    """Residual sum of squares of a constant plus one sinusoid at each period, fitted to the
    training points of every fold (all points but the fold's): ``(n_folds, len(periods))``.

    The sines and cosines are evaluated once for all folds: each fold's training sums are the
    totals minus the fold's own (vectorised normal equations, the constant eliminated by
    centring on the training mean)."""
    order = np.argsort(np.asarray(fold), kind="stable")  # the folds as contiguous blocks
    v = np.asarray(v, float)[order]
    r = np.asarray(r, float)[order]
    counts = np.bincount(np.asarray(fold)[order], minlength=n_folds)[:n_folds]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    live = counts > 0

    def train(a):  # (k, n) per-point rows -> (folds, k) sums over each fold's training points
        own = np.zeros((a.shape[0], n_folds))
        own[:, live] = np.add.reduceat(a, starts[live], axis=1)
        return (a.sum(1)[:, None] - own).T

    n = train(np.ones((1, len(v))))[:, 0]
    m = np.maximum(n, 1.0)[:, None]
    sr0, rr0 = train(r[None])[:, 0], train((r * r)[None])[:, 0]
    rss = rr0 - sr0 * sr0 / m[:, 0]  # of the constant alone
    out = np.empty((n_folds, len(periods)))
    for lo in range(0, len(periods), 64):
        P = np.asarray(periods[lo: lo + 64])
        S, C = _sincos_turns((1.0 / P)[:, None] * v[None, :])  # (periods, points)
        s1, c1 = train(S), train(C)
        ss = train(S * S) - s1 * s1 / m
        cc = train(C * C) - c1 * c1 / m
        sc = train(S * C) - s1 * c1 / m
        sr = train(S * r[None]) - s1 * sr0[:, None] / m
        cr = train(C * r[None]) - c1 * sr0[:, None] / m
        det = ss * cc - sc * sc
        det = np.where(det > 1e-12 * (n * n)[:, None], det, np.inf)
        expl = (cc * sr * sr - 2 * sc * sr * cr + ss * cr * cr) / det
        out[:, lo: lo + 64] = rss[:, None] - expl
    return out


def _fold_periods(v, rr, fo, periods):
    """Per fold, the period of the sinusoid that fits its training points best: a coarse
    search over ``periods`` on about 4,000 points, then +-3 % around it on about 8,000 (each
    search evaluated once for all folds)."""
    coarse = np.arange(len(v))[:: max(1, len(v) // 4000)]
    ps = _periodogram_folds(v[coarse], rr[coarse], fo[coarse], periods)
    P0 = periods[np.argmin(ps, axis=1)]
    fine_idx = np.arange(len(v))[:: max(1, len(v) // 8000)]
    out = np.empty(FOLDS)
    for p0 in np.unique(P0):  # folds usually agree: one fine search for all of them
        fine = p0 * np.linspace(0.97, 1.03, 25)
        pf = _periodogram_folds(v[fine_idx], rr[fine_idx], fo[fine_idx], fine)
        for k in np.flatnonzero(P0 == p0):
            out[k] = fine[int(np.argmin(pf[k]))]
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

    def rows_of(name, v_all) -> list[dict]:
        """The covariate's rows (none where it cannot be compared)."""
        v = np.asarray(v_all, float)[idx]
        rr = r[idx]
        ok = np.isfinite(v) & np.isfinite(rr)
        if ok.sum() < 10 * BINS or np.ptp(v[ok]) <= 0:
            return []
        v, rr, fo = v[ok], rr[ok], fold[ok]
        span = float(np.ptp(v))
        periods = np.geomspace(span / 100.0, span / 1.5, N_PERIODS)
        sse = {"bins": 0.0, "periodic": 0.0}
        sst = 0.0
        chosen = []
        fold_P = _fold_periods(v, rr, fo, periods)  # from each fold's training points only
        for k in range(FOLDS):
            tr, te = fo != k, fo == k
            if te.sum() < 5 or tr.sum() < 10 * BINS:
                continue
            mu = rr[tr].mean()
            sst += float(np.sum((rr[te] - mu) ** 2))
            sse["bins"] += float(np.sum((rr[te] - _bins_predict(v[tr], rr[tr], v[te])) ** 2))
            P = fold_P[k]
            ph = 2 * np.pi * v / P
            A = np.column_stack([np.sin(ph), np.cos(ph), np.ones_like(v)])
            coef, *_ = np.linalg.lstsq(A[tr], rr[tr], rcond=None)
            sse["periodic"] += float(np.sum((rr[te] - A[te] @ coef) ** 2))
            chosen.append((P, float(np.hypot(coef[0], coef[1]))))
        if sst <= 0:
            return []
        rows = []
        for model in ("bins", "periodic"):
            row = {"covariate": name, "model": model, "cv_explained": 1.0 - sse[model] / sst}
            if model == "periodic" and chosen:
                Ps = np.array([c[0] for c in chosen])
                row["period"] = float(np.median(Ps))
                row["period_spread"] = float(np.ptp(Ps))
                row["amplitude_m"] = float(np.median([c[1] for c in chosen]))
            rows.append(row)
        return rows

    # the covariates over the cores (each alone, NumPy's loops release the GIL), in order
    rows = [row for part in each_in_threads(rows_of, list(values.items()), "covariates")
            for row in part]
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
