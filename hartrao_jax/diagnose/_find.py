"""Locate: where and when the mismatch lives. Time (change points by box search, periodogram),
covariates (temperature, elevation, intensity, range, ...) and the dish (panel cells)."""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from .._config import each_in_threads
from .._programs import cached_jit
from ._covariates import _sincos_turns, compare
from ._state import (
    DiagnoseConfig,
    _Context,
    _Scan,
    _Spec,
)

COVARIATES = ("theta", "range", "incidence_angle", "intensity", "rho", "psi", "time")


def _time_order(t: np.ndarray) -> np.ndarray | None:
    """The permutation that sorts the times ``t`` (stable), None where they are sorted already
    (a scan is recorded in time order: no sort, no gathers)."""
    return None if bool(np.all(t[1:] >= t[:-1])) else np.argsort(t, kind="stable")


def _time_bins(sc: _Scan, cfg: DiagnoseConfig):
    u = sc.used & (sc.m > 0)
    t = sc.data.time_s
    nb = int(np.clip(u.sum() // cfg.min_points_per_bin, 16, cfg.max_time_bins))
    t0, t1 = float(t[u].min()), float(t[u].max())
    edges = np.linspace(t0, t1 + 1e-9 * max(1.0, abs(t1)), nb + 1)
    b = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, nb - 1)
    q = np.where(u, 1.0 / np.where(sc.m > 0, sc.m, 1.0), 0.0)
    a = sc.probe
    Nb = np.zeros((nb, 5, 5))
    nbv = np.zeros((nb, 5))
    qa = a * q[:, None]
    for i in range(5):
        nbv[:, i] = np.bincount(b, qa[:, i] * sc.F, minlength=nb)
        for j in range(i, 5):
            Nb[:, i, j] = Nb[:, j, i] = np.bincount(b, qa[:, i] * a[:, j], minlength=nb)
    return edges, b, Nb, nbv


def _quadratic_3x3(S: np.ndarray, n: np.ndarray) -> np.ndarray:
    """``n^T S^-1 n`` per row of a stack of 3 x 3 matrices ``S`` (w, 3, 3) and vectors ``n``
    (w, 3), by the adjugate (:func:`_adjugate_form`): ``np.linalg.solve`` calls LAPACK once
    per matrix (the box search's 0.085 s per scan of 1024 bins, 0.05 s so; the statistic
    within 1e-8 relative)."""
    return _adjugate_form([[S[:, r, k] for k in range(3)] for r in range(3)],
                          n[:, 0], n[:, 1], n[:, 2])


def _adjugate_form(S, x, y, z):
    """``n^T S^-1 n`` of a 3 x 3 matrix given as its rows of entries ``S[r][k]`` and the vector
    ``n = (x, y, z)``, each entry an array (elementwise over any shape, NumPy or JAX), by the
    adjugate: ``n^T adj(S) n / det S``."""
    (a, b, c), (d, e, f), (g, h, i) = S
    # rows of the adjugate (the cofactors' transpose)
    c00, c01, c02 = e * i - f * h, c * h - b * i, b * f - c * e
    c10, c11, c12 = f * g - d * i, a * i - c * g, c * d - a * f
    c20, c21, c22 = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * c00 + b * c10 + c * c20
    return (x * (c00 * x + c01 * y + c02 * z) + y * (c10 * x + c11 * y + c12 * z)
            + z * (c20 * x + c21 * y + c22 * z)) / det


#: The six distinct entries of a symmetric 3 x 3 matrix, in the order of :func:`_box_statistic`.
_SYM3 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _box_search(edges, Nb, nbv, cfg: DiagnoseConfig):
    """Best window of a translation (impulsive shift) over the time bins: ``(i, j, T, profile,
    Lmax)``, the window the bins ``i`` to ``j - 1``, ``profile`` per first bin the largest
    statistic of the windows that start there, ``Lmax`` the longest window (bins).

    ``T = n_W^T S_W^-1 n_W`` with ``S_W = N_W - N_W N^-1 N_W`` (the constant translation is
    the object parameters'). Windows up to ``max_window_fraction`` of the scan; of equal
    statistics the shortest, then the earliest, wins.
    """
    B = len(nbv)
    # prefix sums over the bins of the translation block (its distinct entries) and its
    # right-hand side: a window's sums are the difference of two rows
    X = np.concatenate([np.stack([Nb[:, i, j] for i, j in _SYM3], 1), nbv[:, :3]], 1)
    C = np.concatenate([np.zeros((1, 9)), np.cumsum(X, 0)])
    Ntot = C[-1, :6][[[0, 1, 2], [1, 3, 4], [2, 4, 5]]]
    Ninv = np.linalg.pinv(Ntot)
    Lmax = max(1, int(cfg.max_window_fraction * B))
    eps = np.asarray(1e-9 * np.trace(Ntot) / 3)
    # the bins padded to a power of two (the sums of the last bin repeated), so that scans
    # of other sizes reuse the program; the windows past the last real bin or longer than
    # Lmax hold no statistic
    B_pad = max(16, 1 << (B - 1).bit_length())
    C = np.concatenate([C, np.repeat(C[-1:], B_pad - B, 0)])
    rows = max(Lmax, int(cfg.max_window_fraction * B_pad))
    T = np.asarray(_box_statistic(C, 0.5 * (Ninv + Ninv.T), eps, np.asarray(B),
                                  np.asarray(Lmax), rows))[:Lmax, :B]
    profile = np.maximum(T.max(0), 0.0)
    best = int(np.argmax(T))  # (window length - 1, first bin), the first of equal ones
    L, i = divmod(best, B)
    if not T.flat[best] > 0:
        return 0, 1, 0.0, profile, Lmax
    return i, i + L + 1, float(T.flat[best]), profile, Lmax


@cached_jit
def _box_statistic(C, Ninv, eps, n_bins, Lmax, L_rows: int):
    """The statistic of :func:`_box_search` of every window, ``(L_rows, len(C) - 1)``: row
    ``L - 1``, column ``i`` the window of ``L`` bins from bin ``i`` (0 where it runs past bin
    ``n_bins - 1``, is longer than ``Lmax`` bins or holds no points), from the prefix sums
    ``C`` (bins + 1, 9) (the distinct entries of ``N`` (:data:`_SYM3`), then ``n``), ``Ninv``
    (3, 3) the whole scan's ``N^-1`` (symmetric) and the regularisation ``eps`` of the
    diagonal. :func:`_adjugate_form` of ``S_W`` per entry of the symmetric matrices: one
    program instead of a loop over the window lengths (1024 bins, 307 lengths: 3.6 against
    52 ms; the statistic within 1e-8 relative)."""
    B = C.shape[0] - 1
    first = jnp.arange(B)[None, :]
    length = jnp.arange(1, L_rows + 1)[:, None]
    last = first + length
    D = C[jnp.minimum(last, B)] - C[first]  # each window's sums
    n00, n01, n02, n11, n12, n22, x, y, z = (D[..., k] for k in range(9))
    N = ((n00, n01, n02), (n01, n11, n12), (n02, n12, n22))
    R = [[sum(N[i][k] * Ninv[k, j] for k in range(3)) for j in range(3)] for i in range(3)]

    def s(i, j):  # S_W = N_W - N_W N^-1 N_W (+ eps on the diagonal)
        return N[i][j] - sum(R[i][k] * N[k][j] for k in range(3)) + (eps if i == j else 0.0)

    live = (last <= n_bins) & (length <= Lmax) & (n00 + n11 + n22 > 0)
    # each distinct entry once; the windows that hold no statistic take the identity (no
    # division by a zero determinant there)
    a, b, c, e, f, g = (jnp.where(live, s(i, j), float(i == j)) for i, j in _SYM3)
    return jnp.where(live, _adjugate_form([[a, b, c], [b, e, f], [c, f, g]], x, y, z), 0.0)


def _edge_candidates(t: np.ndarray, edges: np.ndarray, k: int, n_cand: int) -> np.ndarray:
    """Candidate window edges within one bin of coarse edge ``k``: positions in the sorted
    times ``t`` (a window edge at position p starts before point p), at most ``n_cand``."""
    lo, hi = edges[max(k - 1, 0)], edges[min(k + 1, len(edges) - 1)]
    idx = np.arange(np.searchsorted(t, lo), np.searchsorted(t, hi, side="right") + 1)
    idx = np.clip(idx, 0, len(t))
    if len(idx) > n_cand:
        idx = idx[np.linspace(0, len(idx) - 1, n_cand).astype(int)]
    return np.unique(idx)


def _refine_window(sc: _Scan, edges, i: int, j: int, Ntot, T0: float, n_cand: int = 48):
    """Window edges at the resolution of the points' times (within one bin of the coarse
    edges), by the same statistic on sums over the time-sorted points (taken up to each
    candidate edge only; no sort where the scan is in time order already)."""
    u = sc.used & (sc.m > 0)
    t = sc.data.time_s[u]
    order = _time_order(t)
    a = sc.probe[u][:, :3]
    q = 1.0 / sc.m[u]
    F = sc.F[u]
    if order is not None:
        t, a, q, F = t[order], a[order], q[order], F[order]
    qa = a * q[:, None]
    Ninv = np.linalg.pinv(Ntot)

    s_idx, e_idx = _edge_candidates(t, edges, i, n_cand), _edge_candidates(t, edges, j, n_cand)
    S0, E0 = np.meshgrid(s_idx, e_idx, indexing="ij")
    ok = E0 > S0
    if not ok.any():
        return (float(edges[i]), float(edges[j] - edges[i])), T0
    S0, E0 = S0[ok], E0[ok]
    # the sums over the points before each candidate edge (prefix sums at those rows only,
    # by segments between consecutive candidates: no cumulative sum over every point)
    P = np.unique(np.concatenate([s_idx, e_idx]))
    m = int(P[-1])
    X = np.concatenate([(qa[:m, :, None] * a[:m, None, :]).reshape(-1, 9),
                        qa[:m] * F[:m, None]], axis=1)
    C = np.zeros((len(P), 12))
    C[0] = X[: P[0]].sum(0)
    if len(P) > 1:
        C[1:] = C[0] + np.cumsum(np.add.reduceat(X, P[:-1], axis=0)[: len(P) - 1], 0)
    at_s, at_e = np.searchsorted(P, S0), np.searchsorted(P, E0)
    NW = (C[at_e, :9] - C[at_s, :9]).reshape(-1, 3, 3)
    nW = C[at_e, 9:] - C[at_s, 9:]
    Sm = NW - NW @ Ninv @ NW + 1e-9 * np.trace(Ntot) / 3 * np.eye(3)
    T = _quadratic_3x3(Sm, nW)
    k = int(np.argmax(T))
    if T[k] <= T0:
        return (float(edges[i]), float(edges[j] - edges[i])), T0
    s0, e0 = int(S0[k]), int(E0[k])
    start = 0.5 * (t[s0 - 1] + t[s0]) if s0 > 0 else t[0] - 1e-9
    end = 0.5 * (t[e0 - 1] + t[e0]) if e0 < len(t) else t[-1] + 1e-9
    return (float(start), float(end - start)), float(T[k])


def _periodogram(edges, Nb, nbv, cfg: DiagnoseConfig):
    """Score statistic of a rotation ``a sin(wt) + b cos(wt)`` about scanner x and y vs period.

    Returns ``(periods, T)``; the constant rotation (object parameters) is eliminated.
    """
    B = len(nbv)
    tb = 0.5 * (edges[:-1] + edges[1:])
    span = edges[-1] - edges[0]
    Nr, nr = Nb[:, 3:, 3:], nbv[:, 3:]
    live = np.trace(Nr, axis1=1, axis2=2) > 0
    tb, Nr, nr = tb[live], Nr[live], nr[live]
    fmin = 2.0 / span
    fmax = 0.25 * B / span  # half the bins' Nyquist frequency
    if fmax <= fmin:
        return np.zeros(0), np.zeros(0)
    nf = int(min(4000, max(50, 4 * (fmax - fmin) * span)))
    freqs = np.linspace(fmin, fmax, nf)
    Ntot = Nr.sum(0)
    Ntot_inv = np.linalg.pinv(Ntot)
    T = np.zeros(nf)
    for lo in range(0, nf, 256):
        f = freqs[lo: lo + 256]
        # single-precision sines after removing the whole turns (_sincos_turns: within 2e-7;
        # NumPy's double sine is not vectorised)
        H = np.stack(_sincos_turns(f[:, None] * tb[None, :]), -1)  # (F, B, 2)
        # sums over the bins as matrix products (einsum's loops took 6x longer):
        # M[f, (p, i), (q, j)] = sum_b H_fbp H_fbq Nr_bij, K[f, (p, i), j], u[f, (p, i)]
        Ht = np.swapaxes(H, 1, 2)  # (F, 2, B)
        HH = (Ht[:, :, None, :] * Ht[:, None, :, :]).reshape(len(f), 4, -1)  # (F, pq, B)
        M = (HH @ Nr.reshape(-1, 4)).reshape(len(f), 2, 2, 2, 2).transpose(
            0, 1, 3, 2, 4).reshape(len(f), 4, 4)
        K = (Ht @ Nr.reshape(-1, 4)).reshape(len(f), 4, 2)
        u = (Ht @ nr).reshape(len(f), 4)
        S = M - K @ Ntot_inv @ np.swapaxes(K, 1, 2)
        S = S + 1e-12 * np.trace(S, axis1=1, axis2=2)[:, None, None] * np.eye(4)
        sol = np.linalg.solve(S, u[..., None])[..., 0]
        T[lo: lo + 256] = np.sum(u * sol, 1)
    return 1.0 / freqs, T


def _periodogram_points(sc: _Scan, freqs: np.ndarray, F: np.ndarray | None = None,
                        chunk: int = 1 << 15) -> np.ndarray:
    """The periodogram statistic at a few frequencies from the points' own times (exact);
    ``F``: misclosures to use instead of the scan's.

    Per frequency the score test of ``(sin, cos) x (rotation x, y)`` against the rotation
    columns ``a``: every sum it needs is ``sum w exp(i k phi)``, ``k`` 0, 1, 2, over five
    weights ``w`` (``q a_x^2, q a_x a_y, q a_y^2, q a_x F, q a_y F``; ``sin^2 = (1 - cos 2
    phi) / 2``, ``sin cos = sin 2 phi / 2``), so all frequencies cost two complex
    exponentials per point (equally spaced frequencies; else one per point and frequency) and
    one product of (frequencies, n) by (n, 5)."""
    u = sc.used & (sc.m > 0)
    t = sc.data.time_s[u]
    a = sc.probe[u][:, 3:]
    q = 1.0 / sc.m[u]
    F = (sc.F if F is None else F)[u]
    qa = a * q[:, None]
    N0 = qa.T @ a
    N0i = np.linalg.pinv(N0)
    W = np.stack([qa[:, 0] * a[:, 0], qa[:, 0] * a[:, 1], qa[:, 1] * a[:, 1],
                  qa[:, 0] * F, qa[:, 1] * F])  # (5, n)
    freqs = np.asarray(freqs, float)
    Z1 = np.zeros((5, len(freqs)), complex)
    Z2 = np.zeros((5, len(freqs)), complex)
    df = np.diff(freqs)
    even = len(freqs) > 2 and np.allclose(df, df[0], rtol=1e-9, atol=0.0)

    def sums(lo):
        tc = t[lo: lo + chunk]
        if even:  # equally spaced: exp(i w_k t) = exp(i w_0 t) exp(i dw t)^k, two exps per
            # point instead of one per point and frequency (15x faster, 1e-14 apart)
            E = np.empty((len(freqs), len(tc)), complex)
            E[0] = np.exp(2j * np.pi * freqs[0] * tc)
            step = np.exp(2j * np.pi * df[0] * tc)
            for k in range(1, len(freqs)):
                np.multiply(E[k - 1], step, out=E[k])
        else:
            E = np.exp(2j * np.pi * freqs[:, None] * tc[None, :])
        Wc = W[:, lo: lo + chunk].T
        return (E @ Wc).T, ((E * E) @ Wc).T

    # the chunks over the cores (NumPy's loops release the GIL), added in their order: the
    # same sums as one thread's
    for z1, z2 in each_in_threads(sums, range(0, len(t), chunk), "periodogram"):
        Z1 += z1
        Z2 += z2
    A0 = W.sum(1)
    pair = ((0, 1), (1, 2))  # index of w for (a_k a_l): xx 0, xy 1, yy 2
    out = np.zeros(len(freqs))
    for k in range(len(freqs)):
        M = np.zeros((4, 4))
        K = np.zeros((4, 2))
        uu = np.zeros(4)
        for i in range(2):
            uu[i] = Z1[3 + i, k].imag  # sin a_i F
            uu[2 + i] = Z1[3 + i, k].real  # cos a_i F
            for j in range(2):
                w = pair[i][j]
                c2, s2 = Z2[w, k].real, Z2[w, k].imag
                M[i, j] = 0.5 * (A0[w] - c2)  # sin sin
                M[2 + i, 2 + j] = 0.5 * (A0[w] + c2)  # cos cos
                M[i, 2 + j] = M[2 + j, i] = 0.5 * s2  # sin cos
                K[i, j] = Z1[w, k].imag
                K[2 + i, j] = Z1[w, k].real
        S = M - K @ N0i @ K.T
        out[k] = float(uu @ np.linalg.solve(S + 1e-12 * np.trace(S) * np.eye(4), uu))
    return out


def _locate_time(sc: _Scan, cfg: DiagnoseConfig) -> None:
    """Window of the strongest box (change points) and the strongest period of one scan."""
    edges, b, Nb, nbv = _time_bins(sc, cfg)
    i, j, T, profile, Lmax = _box_search(edges, Nb, nbv, cfg)
    sc.window_s, sc.window_stat = _refine_window(sc, edges, i, j, Nb[:, :3, :3].sum(0), T)
    periods, P = _periodogram(edges, Nb, nbv, cfg)
    if len(P):
        k = int(np.argmax(P))
        # zoom on the peak with the points' own times
        f0 = 1.0 / periods[k]
        df = abs(1.0 / periods[min(k + 1, len(P) - 1)] - 1.0 / periods[max(k - 1, 0)]) / 2
        fz = f0 + np.linspace(-1.5, 1.5, 31) * df
        Pz = _periodogram_points(sc, fz)
        j = int(np.argmax(Pz))
        fbest = fz[j]
        if 0 < j < len(Pz) - 1:  # parabolic refinement in frequency
            den = Pz[j - 1] - 2 * Pz[j] + Pz[j + 1]
            if den < 0:
                fbest = fz[j] + 0.5 * (Pz[j - 1] - Pz[j + 1]) / den * (fz[1] - fz[0])
        sc.period_s, sc.period_stat = float(1.0 / fbest), float(max(Pz[j], P[k]))
    B = len(nbv)
    sc.search = {
        "edges": edges, "box_profile": profile, "n_windows": B * Lmax,
        "periods": periods, "periodogram": P, "n_periods": max(1, len(P)),
        "translation": _bin_solutions(Nb[:, :3, :3], nbv[:, :3]),
    }


def _bin_solutions(N, n):
    """Per-bin least-squares estimates (regularised), for plots."""
    tr = np.trace(N, axis1=1, axis2=2)[:, None, None]
    reg = 1e-6 * np.where(tr > 0, tr, 1.0) * np.eye(N.shape[-1])
    return -np.linalg.solve(N + reg, n[..., None])[..., 0]


def _covariate_values(sc: _Scan) -> dict[str, np.ndarray]:
    th = np.mod(sc.data.theta_rad, 2 * np.pi)
    return {
        "theta": np.where(th > np.pi, 2 * np.pi - th, th),
        "range": sc.data.range_m,
        "incidence_angle": sc.incidence,
        "intensity": sc.data.intensity.astype(float),
        "rho": sc.rho,
        "psi": sc.psi,
        "time": sc.data.time_s,
        "phi": sc.data.phi_rad,
    }


def _covariate_tests(ctx: _Context, scans: Sequence[_Scan], sigma0: float, names=COVARIATES,
                     skip=frozenset()):
    """Binned structure of the range-equivalent mismatch along each covariate, all scans jointly.

    The alternative is a range error per (scan, face, quantile bin of the covariate). One plane
    per panel (offset and two tilts, common to all scans) is eliminated, so panel-level
    reflector deviations do not show as covariate structure. Returns ``{covariate: dict(T, dof,
    ids (per scan), est (range error per bin, m), se (m), per_scan)}``; the object parameters
    are not eliminated (conservative).
    """
    cfg = ctx.config
    nb = cfg.covariate_bins
    G = ctx.n_panels
    per_scan = 2 * nb
    base = []
    Mgg = np.zeros((G, 3, 3))
    ug = np.zeros((G, 3))
    for k, sc in enumerate(scans):
        u = sc.used & (sc.m > 0)
        q = np.where(u, 1.0 / np.where(sc.m > 0, sc.m, 1.0), 0.0)
        pp = u & (sc.panel >= 0)
        D = _panel_columns(ctx, sc) * sc.s_rho[:, None]  # d condition / d plane parameters
        # the faces binned (enough points in use) and the sums' terms of their points, which
        # no covariate changes (taken out once: the same values as of every point's)
        faces = [(fc, sel) for fc, sel in ((fc, u & (sc.face == fc)) for fc in (1, 2))
                 if sel.sum() >= 4 * nb]
        ok = np.logical_or.reduce([sel for _, sel in faces]) if faces else np.zeros_like(u)
        okp = ok & pp
        qb = q * sc.b0  # (q * b0**2 below, not qb * b0: the products as before, bit for bit)
        terms = ((q * sc.b0**2)[ok], (qb * sc.F)[ok], [(qb * D[:, a])[okp] for a in range(3)],
                 k * per_scan * G + sc.panel[okp])
        base.append((sc, faces, ok, okp, terms, _covariate_values(sc)))
        Dp, F, cell = D[pp], sc.F[pp], sc.panel[pp]
        qD = q[pp][:, None] * Dp
        for a in range(3):
            ug[:, a] += np.bincount(cell, qD[:, a] * F, minlength=G)
            for b in range(3):
                Mgg[:, a, b] += np.bincount(cell, qD[:, a] * Dp[:, b], minlength=G)
    Mi = np.linalg.pinv(Mgg, rcond=1e-10)

    def test(name) -> dict | None:
        """The covariate's test (None: fewer than two bins hold points)."""
        B = per_scan * len(scans)
        Mbb = np.zeros(B)
        ub = np.zeros(B)
        Mbg = np.zeros((B * G, 3))
        ids_all = []
        for k, (sc, faces, ok, okp, (qbb, qbF, qbD, cell0), vals) in enumerate(base):
            v = vals[name]
            ids = np.full(len(v), -1)
            for fc, sel in faces:
                vs = v[sel]
                qs = np.quantile(vs, np.linspace(0, 1, nb + 1)[1:-1])
                ids[sel] = (fc - 1) * nb + np.searchsorted(qs, vs, side="right")
            ids_all.append(ids)
            gid = k * per_scan + ids[ok]
            Mbb += np.bincount(gid, qbb, minlength=B)
            ub += np.bincount(gid, qbF, minlength=B)
            cell = cell0 + ids[okp] * G
            for a in range(3):
                Mbg[:, a] += np.bincount(cell, qbD[a], minlength=B * G)
        live = Mbb > 0
        if live.sum() < 2:
            return None
        Mbg = Mbg.reshape(B, G, 3)
        W = np.einsum("bgi,gij->bgj", Mbg, Mi)
        Sm = np.diag(Mbb) - np.einsum("bgj,cgj->bc", W, Mbg)
        m = ub - np.einsum("bgj,gj->b", W, ug)
        Sm, m = Sm[np.ix_(live, live)], m[live]
        w, V = np.linalg.eigh(0.5 * (Sm + Sm.T))
        # the near-null directions are a common range offset of the bins against the panel
        # planes (x10 against the surface): confounded, left out
        keep = w > 1e-6 * w.max()
        proj = V[:, keep].T @ m
        T = float(np.sum(proj**2 / w[keep])) / sigma0**2
        est = np.zeros(B)
        est[live] = V[:, keep] @ (proj / w[keep])
        planes = np.einsum("gij,gj->gi", Mi, ug - np.einsum("bgi,b->gi", Mbg, est))
        raw = est.copy()
        # a common range offset of all bins is absorbed by the surface (x10 is confounded):
        # report the bins' contrast, per scan and face, with the information of each bin
        for k in range(len(scans)):
            for fc in range(2):
                sl = slice(k * per_scan + fc * nb, k * per_scan + (fc + 1) * nb)
                wl = Mbb[sl]
                if wl.sum() > 0:
                    est[sl] -= np.sum(wl * est[sl]) / wl.sum()
        se = np.where(live, sigma0 / np.sqrt(np.where(live, Mbb, 1.0)), 0.0)
        return {"T": T, "dof": int(keep.sum()), "ids": ids_all, "est": est, "se": se,
                "per_scan": per_scan, "raw": raw, "planes": planes}

    # the covariates over the cores (each alone, NumPy's loops release the GIL), in order
    todo = [n for n in names if n not in skip]
    return {n: t for n, t in zip(todo, each_in_threads(test, todo, "covariate-tests"))
            if t is not None}


def _covariate_cv(S: Sequence[_Scan], spec: _Spec, only=None) -> dict:
    """Cross-validated comparison of the covariates (:func:`._covariates.compare`) on the
    range-equivalent mismatch of the points in use, all scans together."""

    names = [n for n in ("range", "incidence_angle", "intensity", "time", "theta", "phi", "rho",
                         "psi") if n not in spec.no_covariates and (only is None or n in only
                                                                     or n == "phi")]
    vals = {n: [] for n in names}
    res = []
    for sc in S:
        u = sc.used & (sc.m > 0)
        cv = _covariate_values(sc)
        for n in names:
            vals[n].append(np.asarray(cv[n], float)[u])
        res.append(sc.mismatch_range_m[u])
    if not res:
        return {}
    return compare({n: np.concatenate(v) for n, v in vals.items()}, np.concatenate(res))


def _panel_cells(ctx: _Context, sc: _Scan) -> np.ndarray:
    """Sub-cell of each point within its panel (``panel * nr * na + cell``; -1: none)."""
    nr, na = ctx.config.panel_cells
    p = sc.panel
    ok = p >= 0
    k = np.where(ok, p, 0)
    g = ctx.geo
    fr = np.clip((sc.rho - g["rho_in"][k]) / (g["rho_out"][k] - g["rho_in"][k]), 0, 0.999999)
    dpsi = np.mod(sc.psi - g["psi_start"][k], 2 * np.pi)
    fa = np.clip(dpsi / (g["psi_end"][k] - g["psi_start"][k]), 0, 0.999999)
    cell = (fr * nr).astype(int) * na + (fa * na).astype(int)
    return np.where(ok, k * nr * na + cell, -1)


def _panel_columns(ctx: _Context, sc: _Scan, rows: np.ndarray | None = None) -> np.ndarray:
    """Normal-deviation columns of a panel plane (offset, radial tilt, tangential tilt), of
    every point or of the points ``rows`` (a mask or indices: the same values)."""
    rho, psi, panel = (sc.rho, sc.psi, sc.panel) if rows is None else (
        sc.rho[rows], sc.psi[rows], sc.panel[rows])
    k = np.where(panel >= 0, panel, 0)
    g = ctx.geo
    dpsi = np.mod(psi - g["psi_c"][k] + np.pi, 2 * np.pi) - np.pi
    return np.column_stack([np.ones_like(rho), rho - g["rho_c"][k], g["rho_c"][k] * dpsi])


def _panel_points(ctx: _Context, sc: _Scan):
    """The points in use on a panel: ``(mask, w, P, panel)``, their weights along the surface
    normal ``w = s^2 / m`` (m^-2), their panel-plane columns ``P`` (:func:`_panel_columns`)
    and their panels. Taken out once: every product of the callers is then formed over these
    points only (the same values as of every point's, compacted)."""
    u = sc.used & (sc.m > 0) & (sc.panel >= 0)
    s = sc.s_rho[u]
    return u, (1.0 / sc.m[u]) * s * s, _panel_columns(ctx, sc, u), sc.panel[u]


def _add_plane_sums(M: np.ndarray, up: np.ndarray, pid: np.ndarray, w: np.ndarray,
                    P: np.ndarray, r: np.ndarray) -> None:
    """Add points' share of their panels' plane normal equations: ``M[g] += sum w P P^T``,
    ``up[g] += sum w r P`` (``M`` (G, 3, 3), ``up`` (G, 3); ``r`` the normal mismatch, m)."""
    G = len(M)
    wr = w * r
    for a in range(3):
        wP = w * P[:, a]
        up[:, a] += np.bincount(pid, wr * P[:, a], minlength=G)
        for b in range(3):
            M[:, a, b] += np.bincount(pid, wP * P[:, b], minlength=G)


def _dish_test(ctx: _Context, scans: Sequence[_Scan], sigma0: float):
    """Within-panel structure common to all scans: cell offsets after one plane per panel.

    Returns per panel ``(T, dof)``, the per-cell deviation estimates (m) and the cell ids.
    """
    nr, na = ctx.config.panel_cells
    C = nr * na
    G = ctx.n_panels
    # normal-deviation regression: condition change = s * dev, so dev column = -s (F = ... + dev s)
    Mcc = np.zeros(G * C)
    Mcp = np.zeros((G * C, 3))
    Mpp = np.zeros((G, 3, 3))
    uc = np.zeros(G * C)
    up = np.zeros((G, 3))
    cells = []
    for sc in scans:
        cell = _panel_cells(ctx, sc)
        cells.append(cell)
        u, w, P, pi_ = _panel_points(ctx, sc)
        r = -sc.F[u] / sc.s_rho[u]  # mismatch along the normal
        ci = cell[u]
        Mcc += np.bincount(ci, w, minlength=G * C)
        uc += np.bincount(ci, w * r, minlength=G * C)
        for a in range(3):
            Mcp[:, a] += np.bincount(ci, w * P[:, a], minlength=G * C)
        _add_plane_sums(Mpp, up, pi_, w, P, r)
    Tg = np.zeros(G)
    dof = np.zeros(G, int)
    est = np.zeros(G * C)
    for g in range(G):
        sl = slice(g * C, (g + 1) * C)
        live = Mcc[sl] > 0
        if live.sum() <= 3:
            continue
        mcc = Mcc[sl][live]
        mcp = Mcp[sl][live]
        ucg = uc[sl][live]
        # cells (indicators) reduced by the plane: S = diag(mcc) - mcp Mpp^-1 mcp^T
        Pinv = np.linalg.pinv(Mpp[g])
        S = np.diag(mcc) - mcp @ Pinv @ mcp.T
        m = ucg - mcp @ Pinv @ up[g]
        w_, V = np.linalg.eigh(S)
        keep = w_ > 1e-6 * w_.max()
        proj = V[:, keep].T @ m
        Tg[g] = float(np.sum(proj**2 / w_[keep])) / sigma0**2
        dof[g] = int(keep.sum())
        sol = V[:, keep] @ (proj / w_[keep])
        e = np.zeros(C)
        e[live] = sol
        est[sl] = e
    return Tg, dof, est, cells
