"""Explain: which catalog effects account for the mismatch. The joint system of all scans
augmented by candidate columns, score tests with their p-values, separability of candidates."""

from __future__ import annotations

import functools
import hashlib
import logging
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import jax
import numpy as np

from .._config import each_in_threads, on_device, threads_for
from .._programs import Uncacheable, spec
from ..model._model import (
    DRIFT,
    OSCILLATION,
    SHIFT,
    ZERNIKE_PREFIX,
)
from ..physics._catalog import INSTRUMENT, inseparable_pairs
from ..solver._mixed import chi2_sf
from ..solver._mixed_stream import MixedSums, mixed_chunk, mixed_step
from ._state import (
    ZERNIKE_TESTED,
    _Context,
    _fixed,
    _npad,
    _pad,
    _Scan,
    _scan_model,
    _Spec,
)

log = logging.getLogger("hartrao_jax")


MOTION: dict[str, tuple[str, ...]] = {
    # a steady rotation of the scanner about x or y moves the far points like a translation:
    # within one scan the drift rotations are inseparable from the drift translations
    "impulsive_shift": SHIFT, "oscillation": OSCILLATION, "drift": DRIFT[:3],
}


@dataclass
class _Candidate:
    """A catalog effect (or a group of parameters) to test, in joint indices."""

    effect: str
    family: str
    idx: np.ndarray  # joint indices of its (local) parameters
    H: np.ndarray  # (len(idx), q): the tested parameters -> local columns
    names: list[str]  # names of the tested parameters
    scans: list[str]
    penalty: float = 1.0  # Bonferroni factor of searches (windows, periods)
    info: dict = field(default_factory=dict)
    per_scan: np.ndarray | None = None  # H of the per-scan alternative (shared candidates)


@dataclass
class _Test:
    cand: _Candidate
    T: float
    dof: int
    p: float
    z: float
    effect_m: float
    estimate: np.ndarray
    sigma: np.ndarray
    correlation: float
    with_: list[str]
    corr_with: list[float]
    confounded: bool
    T_diff: float = 0.0
    dof_diff: int = 0
    notes: list[str] = field(default_factory=list)
    S: np.ndarray | None = None  # Schur complement of the tested parameters (x, panels out)
    Draw: np.ndarray | None = None  # their normal matrix alone
    cov: np.ndarray | None = None  # covariance of the one-step estimate


def _z_of(T: float, dof: int) -> float:
    """Equivalent standard-normal score of a chi-square value (Wilson-Hilferty)."""
    if dof <= 0:
        return 0.0
    k = float(dof)
    return ((max(T, 0.0) / k) ** (1 / 3) - (1 - 2 / (9 * k))) / math.sqrt(2 / (9 * k))


def _p_of(T: float, dof: int) -> float:
    return chi2_sf(max(dof, 1), max(T, 0.0))


K_CELL = 3  # per surface cell: offset (m) and two tilts (rad) about its centre
_CELL_VAR0 = (1e-8, 1e-8, 1e-8)  # start of the cells' variances: 0.1 mm, 1e-4 rad


def _cell_sums(ctx: _Context, sc: _Scan, model, x: np.ndarray, w: np.ndarray,
               U: np.ndarray, threads: int = 1) -> MixedSums:
    """Normal-equation sums of one scan at its current solution, with the columns of its
    surface cells (its panels, or the stated grid, with the local coordinates of
    :func:`..geometry.panel_cells` frozen at the start; per cell its
    offset and radial and tangential tilt, entering as normal deviation), as the two-face
    adjustment forms them (:func:`..solver.mixed_chunk`). ``w``: weights of the points; ``U``
    (cells, 3): the cells' current values (the modelled panel offsets), taken out of the
    points' known deviation so that the random effect carries the whole surface.
    ``threads``: scans whose sums are made at once (:func:`..solver.mixed_chunk`)."""
    n = len(w)
    cell = np.where(sc.panel >= 0, sc.panel, -1)
    design = np.column_stack([np.ones(n), sc.local]) * (cell >= 0)[:, None]
    consts = sc.consts().copy()
    consts[:, 1] -= np.where(cell >= 0, np.sum(design * U[np.maximum(cell, 0)], axis=1), 0.0)
    npad = _npad(n)
    # NumPy arrays into the program (each jnp.asarray of a NumPy array is a program of its own
    # to lower and load per shape in every process)
    args = (_pad(sc.l, npad), _pad(consts, npad), _pad(w, npad, 0.0),
            np.ascontiguousarray(np.broadcast_to(ctx.sigma**2, (npad, 3))),
            _pad(cell, npad, -1), _pad(design, npad, 0.0))

    def sums_of(m, x_m):
        # the same scan, model, solution and cells as a joint system before (the last step's
        # and the final estimates' first, 0.2 s a scan): its sums again
        key = _sums_key(m, x_m, args, U)
        with _MEMO_LOCK:  # the scans' sums are made in threads
            if key is not None and key in ctx.sums_memo:
                return ctx.sums_memo[key]
        s, _ = mixed_chunk(m, *args, np.asarray(x_m, float), np.asarray(U, float),
                           on_device(1.0), on_device(np.inf), dev_column=1, threads=threads)
        s = jax.tree.map(np.asarray, s)
        if key is not None:
            with _MEMO_LOCK:
                while len(ctx.sums_memo) >= SUMS_MEMO:
                    ctx.sums_memo.pop(next(iter(ctx.sums_memo)))
                ctx.sums_memo[key] = s
        return s

    # by the widest model of the scan that gives the same values (one program for the
    # successive joint systems, :class:`._state._Supersets`), its rows of ``model``'s unknowns
    wide, x_wide, idx = ctx.supersets.of(sc.id, model, x)
    sums = sums_of(wide, x_wide)
    if wide is not model:
        if not all(np.isfinite(a).all() for a in jax.tree.leaves(sums)):
            return sums_of(model, x)
        sums = MixedSums(N=sums.N[np.ix_(idx, idx)], nv=sums.nv[idx], S=sums.S,
                         sg=sums.sg[:, :, idx], tg=sums.tg, wMw=sums.wMw, n_used=sums.n_used,
                         omega=sums.omega)
    return sums


#: Joint systems' sums of one scan kept for reuse (:func:`_cell_sums`; a scan's are a few MB).
SUMS_MEMO = 8
_MEMO_LOCK = threading.Lock()


def _sums_key(model, x, args, U) -> str | None:
    """A digest of everything :func:`._explain._cell_sums`' sums of a scan depend on: the
    model's static fields and every array (its own, the unknowns, the points' rows, the
    cells' values); None where the model cannot be stated (:func:`.._programs.spec`)."""
    try:
        h = hashlib.sha1(repr(spec(model)).encode())
    except Uncacheable:
        return None
    for a in (*jax.tree.leaves(model), x, *args, U):
        a = np.ascontiguousarray(np.asarray(a))
        h.update(repr((a.shape, a.dtype.str)).encode())
        h.update(a.data)
    return h.hexdigest()


def _jacobi_scale(K: np.ndarray) -> np.ndarray:
    """``1 / sqrt(diag K)`` (1 where the diagonal is not positive)."""
    return 1.0 / np.sqrt(np.where(np.diag(K) > 0, np.diag(K), 1.0))


def _scaled_pinv(K: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
    """Pseudo-inverse of a symmetric normal matrix after Jacobi scaling (by ``d``, default
    :func:`_jacobi_scale` of ``K``)."""
    d = _jacobi_scale(K) if d is None else d
    return np.linalg.pinv(K * d[:, None] * d[None, :], rcond=1e-13) * d[:, None] * d[None, :]


@dataclass
class _SurfaceNull:
    """The joint system with the surface as a random effect, the null of the score tests
    (``physics.md``, Statistics: ``M`` and ``N`` include the surface random effect).

    Each surface cell (a panel, common to every scan) carries an offset (m) and two tilts
    (rad) with variances ``cell_var`` estimated with the noise variance ``noise_var`` (the
    factor on the a priori sigmas) at this linearisation, by the two-face adjustment's
    variance-component estimation (:func:`..solver.mixed_step`, Foerstner). The cells are then
    eliminated (Schur complement): the tilts with their prior, the offsets free, as fixed
    nuisance, so that the null carries the reflector's shape at every scale above a cell
    (smooth deformation of millimetres on a real reflector, which the offsets' variance does
    not describe) as well as the structure within the cells. ``N``, ``n``: the reduced system
    over all joint unknowns; ``K_inv``: inverse of its null block;
    ``sigma0 = sqrt(noise_var)``."""

    N: np.ndarray
    n: np.ndarray
    K_inv: np.ndarray
    sigma0: float
    noise_var: float
    cell_var: np.ndarray
    note: str = ""

    @classmethod
    def of(cls, joint: _Joint) -> _SurfaceNull:
        I0 = joint.I0
        S3, sg3, tg3, U = joint.cells
        sums = MixedSums(
            joint.N_raw[np.ix_(I0, I0)], joint.n_raw[I0], np.asarray(S3, float),
            sg3[:, :, I0], np.asarray(tg3, float), on_device(joint.wMw_raw),
            on_device(float(joint.n_used)), on_device(0.0))
        var0 = (on_device(1.0), on_device(_CELL_VAR0), on_device(np.zeros((0,))))
        none = on_device(np.zeros((0,), np.int32))
        st = mixed_step(sums, var0, var0, np.zeros(len(I0)), np.asarray(U, float), none, none,
                        0)
        se2, cv = float(st.var[0]), np.asarray(st.var[1], float)
        if not (np.isfinite(se2) and se2 > 0 and np.all(np.isfinite(cv))):
            # the null block is singular for the random-effect solve: the white system
            return cls(joint.N, joint.n, joint.K_inv, joint.sigma0, joint.sigma0**2,
                       np.zeros(K_CELL), "surface variances not estimable: panel offsets "
                       "eliminated as fixed, white noise")
        # the offsets free (no prior): they take up the reflector's shape at every scale
        # above a cell, which the tilts' random effect alone does not describe (on a real
        # reflector, smooth deformation of millimetres); the tilts with their prior
        N, n = eliminate_cells(joint, se2, cv, offsets_random=False)
        return cls(N, n, _scaled_pinv(N[np.ix_(I0, I0)]), math.sqrt(se2), se2, cv)

    def to_json(self) -> dict:
        return {"noise_variance": self.noise_var, "sigma0": self.sigma0,
                "cell_sd": {"offset_m": float(np.sqrt(self.cell_var[0])),
                            "tilt_radial_rad": float(np.sqrt(self.cell_var[1])),
                            "tilt_tangential_rad": float(np.sqrt(self.cell_var[2]))},
                **({"note": self.note} if self.note else {})}


def eliminate_cells(joint: _Joint, noise_var: float, cell_var: np.ndarray, *,
                    offsets_random: bool) -> tuple[np.ndarray, np.ndarray]:
    """The joint normal system ``(N, n)`` over all joint unknowns with the surface cells
    eliminated (Schur complement, one 3 x 3 block per cell): the tilts (rad) with their prior
    ``noise_var / cell_var[1:]``, the offsets (m) with theirs when ``offsets_random`` and free
    otherwise. The cells' prior mean is zero for their whole value: the current ones ``U`` (the
    modelled panel offsets) enter as a start."""
    S3, sg3, tg3, U = joint.cells
    lam = np.zeros((len(S3), K_CELL))
    lam[:, 1:] = noise_var / cell_var[1:]  # the tilts' prior
    if offsets_random:
        lam[:, 0] = noise_var / cell_var[0]
    lam[S3[:, 0, 0] <= 0, 0] = 1.0  # a cell without points: its offset is arbitrary
    Dinv = np.linalg.inv(S3 + lam[:, :, None] * np.eye(K_CELL)[None])
    N = joint.N_raw - np.einsum("gki,gkl,glj->ij", sg3, Dinv, sg3)
    n = joint.n_raw - np.einsum("gki,gkl,gl->i", sg3, Dinv, tg3 + lam * U)
    return N, n


SURFACE_CELLS = "the surface cells (offsets and tilts)"


def _named_correlation(joint: _Joint, cand: _Candidate) -> float:
    """Multiple correlation of a one-parameter candidate with the model's named unknowns
    alone (the surface cells left out)."""
    J, H = cand.idx, cand.H
    B = joint.N_raw[np.ix_(joint.I0, J)] @ H
    D = float((H.T @ joint.N_raw[np.ix_(J, J)] @ H)[0, 0])
    S = D - float((B.T @ joint.Kr_inv @ B)[0, 0])
    return math.sqrt(min(max(1.0 - S / D, 0.0), 1.0)) if D > 0 else 0.0


class _Joint:
    """The scans' normal equations summed into one system: panel offsets eliminated as fixed
    nuisance (the panel test and the model step), and the score tests' null with the surface
    (:class:`_SurfaceNull`, ``surface``)."""

    def __init__(self, ctx: _Context, scans: Sequence[_Scan], spec: _Spec, candidates_local):
        self.ctx = ctx
        self.scans = scans
        cfg = ctx.config
        G = ctx.n_panels
        # ---- joint layout: x blocks per scan, accepted shared, then per-scan candidate slots
        self.labels: list[str] = []
        self.xidx: dict[str, np.ndarray] = {}
        maps = []
        self.local_names = {}
        for sc in scans:
            model = _scan_model(sc, spec, ctx.aperture)
            x_names = list(model.free)
            self.xidx[sc.id] = np.arange(len(self.labels), len(self.labels) + len(x_names))
            self.labels += [f"{n}@{sc.id}" for n in x_names]
            maps.append(x_names)
        # accepted shared parameters (instrument; Zernike through gravity)
        self.shared_names = list(spec.shared)
        zern_acc = spec.zern_C is not None
        self.sidx = np.arange(len(self.labels), len(self.labels) + len(self.shared_names)
                              + (3 * len(ZERNIKE_TESTED) if zern_acc else 0))
        self.labels += self.shared_names
        if zern_acc:
            self.labels += [f"C{j}{a}" for j in ZERNIKE_TESTED for a in "xyz"]
        # candidate slots: per scan
        self.cidx: dict[tuple[str, str], int] = {}
        for sc in scans:
            for n in candidates_local[sc.id]:
                self.cidx[(sc.id, n)] = len(self.labels)
                self.labels.append(f"{n}@{sc.id}")
        D = len(self.labels)
        self.D = D
        N = np.zeros((D, D))
        n = np.zeros(D)
        wMw = 0.0
        U = np.zeros((G, K_CELL))  # the cells' current values: the modelled panel offsets
        if spec.panels is not None:
            U[:, 0] = spec.panels["offset"]
        S3 = np.zeros((G, K_CELL, K_CELL))
        sg3 = np.zeros((G, K_CELL, D))
        tg3 = np.zeros((G, K_CELL))
        self.n_used = 0
        self.sum_q = 0.0
        t0 = time.time()

        threads = threads_for(len(scans))  # scans whose sums are made at once (each_in_threads)

        def scan_sums(sc, x_names):
            """One scan's sums at its solution and its columns' place in the joint system
            (``P``: its model's unknowns -> joint unknowns)."""
            cands = candidates_local[sc.id]
            extra = list(self.shared_names) + (
                [f"{ZERNIKE_PREFIX}{j}" for j in ZERNIKE_TESTED] if zern_acc else [])
            extra += [c for c in cands if c not in extra]
            mot = spec.motion.get(sc.id, {})
            model = _scan_model(sc, spec, ctx.aperture, extra=extra,
                                window_s=None if mot.get("window_s") else sc.window_s,
                                period_s=None if mot.get("period_s") else sc.period_s,
                                canonical=True)
            fixed = _fixed(sc, spec)
            prev = dict(zip(sc.names, sc.x))
            x = np.array([prev.get(k, fixed.get(k, 0.0)) for k in model.free])
            P = np.zeros((len(model.free), D))
            for i, name in enumerate(model.free):
                if name in x_names:
                    P[i, self.xidx[sc.id][x_names.index(name)]] = 1.0
                elif name in self.shared_names:
                    P[i, self.sidx[self.shared_names.index(name)]] = 1.0
                elif zern_acc and name.startswith(ZERNIKE_PREFIX) and int(
                        name[len(ZERNIKE_PREFIX):]) in ZERNIKE_TESTED:
                    k = ZERNIKE_TESTED.index(int(name[len(ZERNIKE_PREFIX):]))
                    base = self.sidx[len(self.shared_names) + 3 * k]
                    P[i, base: base + 3] = sc.g
                else:
                    P[i, self.cidx[(sc.id, name)]] = 1.0
            w = (sc.used & (sc.m > 0)).astype(float)
            return _cell_sums(ctx, sc, model, x, w, U, threads), P, w

        # the scans' sums in threads (their programs overlap), added in the scans' order
        for sc, (ne, P, w) in zip(scans, each_in_threads(scan_sums, list(zip(scans, maps)),
                                                        "joint-sums")):
            N += P.T @ np.asarray(ne.N) @ P
            n += P.T @ np.asarray(ne.nv)
            wMw += float(ne.wMw)
            S3 += np.asarray(ne.S)
            sg3 += np.asarray(ne.sg) @ P
            tg3 += np.asarray(ne.tg)
            self.n_used += int(w.sum())
            self.sum_q += float(np.sum(w / np.where(sc.m > 0, sc.m, 1.0)))
        log.debug("joint normal equations: %d unknowns, %.1f s", D, time.time() - t0)
        self.N_raw, self.n_raw, self.wMw_raw = N, n, wMw
        # the panel offsets alone, as fixed nuisance (the panel test and the model step)
        S, sg, tg = S3[:, 0, 0], sg3[:, 0, :], tg3[:, 0]
        live = S > 0
        Si = np.where(live, 1.0 / np.where(live, S, 1.0), 0.0)
        self.G_live = int(live.sum())
        self.N = N - (sg.T * Si) @ sg
        self.n = n - sg.T @ (Si * tg)
        self.wMw = wMw - float(np.sum(Si * tg**2))
        self.group = (S, sg, tg)
        self.group_count = np.zeros(G)
        for sc in scans:
            ok = sc.used & (sc.panel >= 0)
            self.group_count += np.bincount(sc.panel[ok], minlength=G)
        # ---- null system: x blocks and accepted shared
        self.I0 = np.concatenate([*self.xidx.values(), self.sidx]).astype(int)
        K = self.N[np.ix_(self.I0, self.I0)]
        scale = _jacobi_scale(K)
        self.K_inv = _scaled_pinv(K, scale)
        n0 = self.n[self.I0]
        self.omega0 = self.wMw - float(n0 @ self.K_inv @ n0)
        self.dof0 = self.n_used - len(self.I0) - self.G_live
        self.sigma0 = math.sqrt(max(self.omega0, 1e-300) / max(self.dof0, 1))
        # null without panel elimination (for the panel test)
        self.Kr_inv = _scaled_pinv(self.N_raw[np.ix_(self.I0, self.I0)], scale)  # no cells
        n0r = self.n_raw[self.I0]
        self.omega0_raw = self.wMw_raw - float(n0r @ self.Kr_inv @ n0r)
        self.cfg = cfg
        # ---- the score tests' null: the surface as a random effect (physics.md, Statistics)
        self.cells = (S3, sg3, tg3, U)  # per cell: normal block, coupling, right side, value
        self.surface = _SurfaceNull.of(self)
        log.debug("score-test null: %s", self.surface.to_json())

    # ----------------------------------------------------------------------------------
    def null_step(self) -> np.ndarray:
        """Increment of all null unknowns (x blocks, accepted shared) with panels eliminated."""
        d = np.zeros(self.D)
        d[self.I0] = -self.K_inv @ self.n[self.I0]
        return d

    def panel_step(self, dz: np.ndarray) -> np.ndarray:
        """Panel offsets (m, normal) of the joint solution given the other increments ``dz``."""
        S, sg, tg = self.group
        live = S > 0
        return np.where(live, -(tg + sg @ dz) / np.where(live, S, 1.0), 0.0)

    def test(self, cand: _Candidate, sigma0: float | None = None) -> _Test:
        """Score statistic, one-step estimate, effect size and correlation of a candidate."""
        cfg = self.cfg
        sf = self.surface
        s0 = sigma0 or sf.sigma0
        H = cand.H
        J = cand.idx
        B = sf.N[np.ix_(self.I0, J)] @ H
        Z = sf.K_inv @ B
        S = H.T @ sf.N[np.ix_(J, J)] @ H - B.T @ Z
        m = H.T @ sf.n[J] - Z.T @ sf.n[self.I0]
        Draw = H.T @ self.N_raw[np.ix_(J, J)] @ H
        S = 0.5 * (S + S.T)
        # canonical directions: S v = lam Draw v; lam = 1 - rho^2
        d = np.sqrt(np.where(np.diag(Draw) > 0, np.diag(Draw), 1.0))
        Dn = Draw / np.outer(d, d)
        Sn = S / np.outer(d, d)
        L = np.linalg.cholesky(Dn + 1e-14 * np.eye(len(Dn)))
        Li = np.linalg.inv(L)
        lam, V = np.linalg.eigh(Li @ Sn @ Li.T)
        U = (Li.T @ V) / d[:, None]  # directions in parameter space with U^T Draw U = I
        lam = np.clip(lam, 0.0, 1.0)
        thr = 1.0 - cfg.confounded_correlation**2
        # one parameter: confounded beyond the threshold is not tested; several (motion,
        # gravity): every numerically identifiable direction is kept (large variances show the
        # weak ones), so estimates and covariances stay comparable with any truth
        keep = lam > (thr if len(lam) == 1 else 1e-10)
        rho = float(math.sqrt(max(0.0, 1.0 - lam.min()))) if len(lam) else 0.0
        proj = U[:, keep].T @ m
        T = float(np.sum(proj**2 / lam[keep])) / s0**2 if keep.any() else 0.0
        dof = int(keep.sum())
        delta = -U[:, keep] @ (proj / lam[keep]) if keep.any() else np.zeros(len(m))
        cov = ((U[:, keep] / lam[keep]) @ U[:, keep].T * s0**2 if keep.any()
               else np.zeros((len(m),) * 2))
        sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
        effect = math.sqrt(max(T - dof, 0.0) * s0**2 / max(self.sum_q, 1e-300))
        # correlation of each tested parameter with the null unknowns (for "with")
        with_, cw = [], []
        if len(m) == 1:
            # corr(e, x_i) = -Z_i / sqrt(S (K^-1)_ii + Z_i^2)  (inverse of the bordered matrix)
            kd = np.maximum(np.diag(sf.K_inv), 0.0)
            Sv = max(float(S[0, 0]), 0.0)
            corr = -Z[:, 0] / np.sqrt(Sv * kd + Z[:, 0] ** 2 + 1e-300)
            order = np.argsort(-np.abs(corr))
            for i in order:
                name = self.labels[self.I0[i]].split("@")[0]
                if name in with_:
                    continue
                if (abs(corr[i]) >= 0.5 and len(with_) < 3) or not with_:
                    with_.append(name)
                    cw.append(float(corr[i]))
            if rho > cfg.confounded_correlation and _named_correlation(self, cand) < \
                    cfg.confounded_correlation:  # the cells, not the named unknowns, take it
                with_.append(SURFACE_CELLS)
                cw.append(rho)
        p = _p_of(T, dof)
        return _Test(cand, T, dof, p, _z_of(T, dof), effect, delta, sig, rho, with_, cw,
                     confounded=dof < len(m) if len(m) == 1 else dof == 0, S=S, Draw=Draw,
                     cov=cov)

    def scan_difference(self, cand: _Candidate, test: _Test) -> tuple[float, int]:
        """``T`` of freeing a shared candidate per scan, beyond the shared value."""
        if cand.per_scan is None or cand.per_scan.shape[1] <= cand.H.shape[1]:
            return 0.0, 0
        alt = _Candidate(cand.effect, cand.family, cand.idx, cand.per_scan, cand.names, cand.scans)
        t = self.test(alt)
        return max(0.0, t.T - test.T), t.dof - test.dof


@functools.lru_cache(maxsize=1)
def _inseparable_table() -> dict[frozenset, float]:
    """Every pair of instrument parameters with the same correction shape (computed once)."""
    return {frozenset((a, b)): c for a, b, c in inseparable_pairs(list(INSTRUMENT))}


def _inseparable(names: tuple[str, ...]) -> tuple:
    """The inseparable pairs among ``names`` (as :func:`inseparable_pairs`)."""
    tab = _inseparable_table()
    inst = [n for n in names if n in INSTRUMENT]
    return tuple((a, b, tab[frozenset((a, b))]) for i, a in enumerate(inst) for b in inst[i + 1:]
                 if frozenset((a, b)) in tab)


def _local_candidates(ctx: _Context, scans: Sequence[_Scan], spec: _Spec) -> dict[str, list[str]]:
    """Per scan: the catalog parameters not in the model, free at value 0 in the test."""
    cfg = ctx.config
    wanted = set(cfg.effects) if cfg.effects else None
    in_model = set(spec.start) | set(spec.shared)
    inst = []
    for k in INSTRUMENT:
        if k in in_model or (wanted is not None and k not in wanted) or k in spec.skip:
            continue
        if _inseparable(tuple(sorted(in_model)) + (k,)):
            continue  # same shape as a model parameter: reported as confounded elsewhere
        inst.append(k)
    positions = {sc.meta.position for sc in scans}
    gs = np.array([sc.g for sc in scans])
    grav = (len(positions) >= 2 and spec.zern_C is None and np.linalg.matrix_rank(
        gs - gs.mean(0), tol=1e-3) >= 1 and (wanted is None or "gravity_deformation" in wanted))
    out = {}
    for sc in scans:
        mot = spec.motion.get(sc.id, {})
        names = list(inst)
        if grav:
            names += [f"{ZERNIKE_PREFIX}{j}" for j in ZERNIKE_TESTED]
        if spec.times:  # motion lives in time: no recorded times, no motion candidates
            if "window_s" not in mot and sc.window_s and _want(wanted, "impulsive_shift"):
                names += list(SHIFT)
            if "period_s" not in mot and sc.period_s and _want(wanted, "oscillation"):
                names += list(OSCILLATION)
            if not any(n in DRIFT for n in mot.get("names", ())) and _want(wanted, "drift"):
                names += list(MOTION["drift"])
        out[sc.id] = names
    return out


def _want(wanted, eid):
    return wanted is None or eid in wanted


def _candidates(joint: _Joint, scans: Sequence[_Scan], local: dict[str, list[str]]):
    """The candidates of the joint system: shared instrument, per-scan motion, gravity."""
    out: list[_Candidate] = []
    ids = [sc.id for sc in scans]
    first = local[ids[0]]
    for k in INSTRUMENT:
        if k not in first:
            continue
        idx = np.array([joint.cidx[(s, k)] for s in ids])
        out.append(_Candidate(k, "instrument", idx, np.ones((len(ids), 1)), [k], ids,
                              per_scan=np.eye(len(ids))))
    for sc in scans:
        for eff, pnames in MOTION.items():
            present = [n for n in pnames if n in local[sc.id]]
            if not present:
                continue
            idx = np.array([joint.cidx[(sc.id, n)] for n in present])
            penalty = 1.0
            info = {}
            if eff == "impulsive_shift":
                penalty = float(sc.search.get("n_windows", 1))
                info = {"window_s": sc.window_s, "search_T": sc.window_stat}
            elif eff == "oscillation":
                penalty = float(sc.search.get("n_periods", 1))
                info = {"period_s": sc.period_s, "search_T": sc.period_stat}
            out.append(_Candidate(eff, "motion", idx, np.eye(len(idx)), present, [sc.id],
                                  penalty=penalty, info=info))
    zern = [f"{ZERNIKE_PREFIX}{j}" for j in ZERNIKE_TESTED]
    if all(z in first for z in zern):
        idx, rows = [], []
        for sc in scans:
            for z in zern:
                idx.append(joint.cidx[(sc.id, z)])
                k = zern.index(z)
                row = np.zeros(3 * len(zern))
                row[3 * k: 3 * k + 3] = sc.g
                rows.append(row)
        out.append(_Candidate("gravity_deformation", "reflector", np.array(idx), np.array(rows),
                              [f"C{j}{a}" for j in ZERNIKE_TESTED for a in "xyz"], ids))
    return out


def _log_sf(T: float, dof: int) -> float:
    """Natural log of the chi-square survival function, accurate far in the tail."""
    T = max(float(T), 0.0)
    k = max(int(dof), 1)
    p = chi2_sf(k, T)
    if p > 1e-300:
        return math.log(p)
    a, x = k / 2.0, T / 2.0  # asymptotic upper incomplete gamma: x^(a-1) e^-x / Gamma(a)
    return (a - 1) * math.log(x) - x - math.lgamma(a) + math.log1p((a - 1) / x)
