"""Joint adjustment of a campaign: calibration shared by scans, object parameters per scan.

The paper fits every scan (one cycle at one position) by itself: each cycle estimates its own
scanner calibration (``x4 x6 x7``), and the per-cycle calibration absorbs part of the panel
pattern and correlates with the focal length. The scanner is the same all night (all campaign),
so its calibration can be *shared*: one set per night (``group="night"``, the tour) or for the
whole campaign (``group="campaign"``), while the pose and the focal length stay per scan.

The joint Gauss-Helmert adjustment is solved from the per-scan normal equations by Schur
complement -- never one dense matrix over all points, never one over all scans' unknowns:

* per scan ``s``, linearise at ``(l + v_s, x_s, c_g)`` (:func:`._ghm.normal_equations` of the
  scan's model, whose free parameters are the object ones ``o`` and the shared ones ``c``) and
  partition ``N_s`` into the blocks ``oo``, ``oc``, ``cc`` (and ``n_s`` into ``o``, ``c``);
* reduce per group: ``Nr = sum_s (N_cc - N_co N_oo^-1 N_oc)``,
  ``nr = sum_s (n_c - N_co N_oo^-1 n_o)``;
* solve ``dc = -Nr^-1 nr``; back-substitute ``do_s = -N_oo^-1 (n_o + N_oc dc)`` per scan;
* update every scan's residuals with the Gauss-Helmert residual pass (``v = Sigma b k``,
  ``k = -(a . dx + w) / m``), iterate to convergence.

Cofactors: ``Q_cc = Nr^-1``, ``Q_oc = -N_oo^-1 N_oc Q_cc``, ``Q_oo = N_oo^-1 + N_oo^-1 N_oc Q_cc
N_co N_oo^-1``; one ``sigma0^2 = sum v^T Sigma^-1 v / (sum n - sum u_o - k * groups)``.

The per-scan work (normal equations, residual pass) goes through a small *backend* interface, so
the same iteration runs in-process (:class:`LocalBackend`) or on Dask workers
(:mod:`._distributed`), where only the small normal matrices travel.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import jax.numpy as jnp
import numpy as np

from .._programs import cached_jit
from ..campaign._campaign import Campaign, ScanMeta
from ..model._model import parameter_unit
from ..physics._catalog import CALIBRATION, OBJECT_PARAMETERS, two_face_parameters
from ..solver._ghm import (
    _chunked,
    _pass_residuals,
    _unchunk,
    bucket_size,
    chunk_for,
    normal_equations,
)
from ._align import mean_heading, scan_heading
from ._fit import finish_scan_fit, fit_campaign, scan_arrays, scan_result, sigma_vector
from ._identify import Held
from ._records import fit_json, write_fit_dir
from ._results import CampaignFit, ScanFit

log = logging.getLogger("hartrao_jax")

DEFAULT_SHARED = CALIBRATION
GROUPS = ("night", "campaign")


# --------------------------------------------------------------------------------------------
# The residual pass of the Gauss-Helmert iteration as a function (candidate for _ghm)
# --------------------------------------------------------------------------------------------


@cached_jit
def _residual_pass(condition, l, x, s2, consts, weights, v, dx, chunk_size):
    n_pts = l.shape[0]
    (L, C, W, S2, V), n = _chunked([l, consts, weights, s2, v], chunk_size)
    W = W.reshape(-1).at[n_pts:].set(0.0).reshape(W.shape)
    Vn, E, omega = _pass_residuals(condition, L, V, C, W, S2, x, dx)
    return _unchunk(Vn, n), _unchunk(E, n), omega


def residual_update(condition, l, x, sigma_l, consts, weights, v, dx, *, chunk_size: int = 1 << 16):
    """New residuals after a step ``dx`` taken from the linearisation at ``(l + v, x)``.

    The second pass of the Gauss-Helmert iteration (:func:`._ghm._pass_residuals`):
    ``k_i = -(a_i . dx + w_i) / m_i``, ``v_i = Sigma_i b_i k_i``. Returns ``(v_new (n, 3),
    e (n,), omega)``: ``e_i = |k_i| sqrt(m_i)`` (the standardized residual times sigma0) and
    ``omega = sum w_i k_i^2 m_i = v^T Sigma^-1 v`` over the weighted points.
    """
    l = jnp.asarray(l, jnp.float64)
    n = l.shape[0]
    consts = jnp.zeros((n, 0), l.dtype) if consts is None else jnp.asarray(consts, l.dtype)
    weights = jnp.ones((n,), l.dtype) if weights is None else jnp.asarray(weights, l.dtype)
    v = jnp.zeros_like(l) if v is None else jnp.asarray(v, l.dtype)
    s2 = jnp.broadcast_to(jnp.asarray(sigma_l, l.dtype) ** 2, l.shape)
    chunk = chunk_for(n, chunk_size)
    return _residual_pass(condition, l, jnp.asarray(x, l.dtype), s2, consts, weights, v,
                          jnp.asarray(dx, l.dtype), chunk)


# --------------------------------------------------------------------------------------------
# Per-scan problems and the backend interface
# --------------------------------------------------------------------------------------------


@dataclass
class ScanProblem:
    """One scan's arrays for the joint iteration, padded to ``len(l)`` (weights 0 on the pad).

    ``n`` is the number of real rows; ``v`` the current residuals; ``e`` the last standardized
    residuals times sigma0 (``|k| sqrt(m)``).
    """

    id: str
    model: object
    l: np.ndarray
    c: np.ndarray
    w: np.ndarray
    v: np.ndarray
    n: int
    sigma_l: np.ndarray
    e: np.ndarray | None = None

    @classmethod
    def from_fit(cls, s: ScanFit, sigma_l: np.ndarray, n_pad: int | None = None) -> ScanProblem:
        l, c = scan_arrays(s.data)
        n = len(l)
        n_pad = max(n, n_pad or n)
        pad = n_pad - n
        w = s.used.astype(float)
        v = np.asarray(s.v, float)
        if pad:
            l = np.concatenate([l, np.repeat(l[-1:], pad, 0)])
            c = np.concatenate([c, np.repeat(c[-1:], pad, 0)])
            w = np.concatenate([w, np.zeros(pad)])
            v = np.concatenate([v, np.zeros((pad, 3))])
        return cls(s.meta.id, s.model, l, c, w, v, n, np.asarray(sigma_l, float))

    @property
    def n_used(self) -> int:
        return int(np.sum(self.w > 0))

    def normals(self, x: np.ndarray):
        """``(N, n, wMw, n_used)`` at ``(l + v, x)`` (NumPy)."""
        ne = normal_equations(self.model, self.l, x, self.sigma_l, self.c, self.w, self.v,
                              chunk_size=chunk_for(len(self.l)))
        return np.asarray(ne.N), np.asarray(ne.n), float(ne.wMw), self.n_used

    def update(self, x: np.ndarray, dx: np.ndarray) -> ScanProblem:
        """A new problem with the residuals after the step ``dx`` (arrays shared, ``v`` new)."""
        v, e, omega = residual_update(self.model, self.l, x, self.sigma_l, self.c, self.w,
                                      self.v, dx, chunk_size=chunk_for(len(self.l)))
        out = dataclasses.replace(self, v=np.asarray(v), e=np.asarray(e))
        out._omega = float(omega)  # type: ignore[attr-defined]
        return out

    @property
    def omega(self) -> float:
        return float(getattr(self, "_omega", np.nan))


class JointBackend(Protocol):
    """Where the per-scan work runs. ``normals`` returns the small per-scan normal equations;
    ``update`` applies a step to every scan's residuals and returns ``omega`` per scan."""

    def normals(self, xs: Sequence[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray, float, int]]:
        ...

    def update(self, xs: Sequence[np.ndarray], dxs: Sequence[np.ndarray]) -> list[float]:
        ...


class LocalBackend:
    """In-process backend: the scans' arrays in memory, one padded shape (one compilation)."""

    def __init__(self, problems: Sequence[ScanProblem]):
        self.problems = list(problems)

    def normals(self, xs):
        return [p.normals(x) for p, x in zip(self.problems, xs)]

    def update(self, xs, dxs):
        self.problems = [p.update(x, dx) for p, x, dx in zip(self.problems, xs, dxs)]
        return [p.omega for p in self.problems]

    def residuals(self) -> list[tuple[np.ndarray, np.ndarray]]:
        return [(p.v[: p.n], p.e[: p.n]) for p in self.problems]


# --------------------------------------------------------------------------------------------
# The Schur-complement iteration (backend-agnostic, NumPy on small matrices)
# --------------------------------------------------------------------------------------------


def _scaled_inverse(N: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix with Jacobi scaling (Cholesky)."""
    if N.size == 0:
        return np.zeros_like(N)
    d = np.diag(N)
    d = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
    Ns = N * d[:, None] * d[None, :]
    try:
        L = np.linalg.cholesky(Ns)
        Li = np.linalg.inv(L)
        inv = Li.T @ Li
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(Ns, hermitian=True)
    return inv * d[:, None] * d[None, :]


def condition_number(N: np.ndarray) -> float:
    """Condition number of ``N`` after Jacobi scaling (unit diagonal)."""
    d = np.diag(N)
    d = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
    w = np.linalg.eigvalsh(N * d[:, None] * d[None, :])
    return float(w[-1] / w[0]) if w[0] > 0 else math.inf


@dataclass
class SchurSolution:
    """Result of :func:`schur_iterate` (cofactors: multiply by ``sigma0**2``)."""

    xs: list[np.ndarray]
    groups: list[str]
    shared_value: dict[str, np.ndarray]
    Q_cc: dict[str, np.ndarray]
    Q_oo: list[np.ndarray]
    Q_oc: list[np.ndarray]
    N: list[np.ndarray]
    omega: list[float]
    n_used: list[int]
    sigma0: float
    redundancy: int
    iterations: int
    converged: bool
    o_idx: np.ndarray
    c_idx: np.ndarray
    history: list[float] = field(default_factory=list)

    def cov(self, s: int) -> np.ndarray:
        """Full covariance (model order) of scan ``s``'s unknowns, shared ones included."""
        u = len(self.xs[s])
        Q = np.zeros((u, u))
        o, c = self.o_idx, self.c_idx
        g = self.groups[s]
        Q[np.ix_(o, o)] = self.Q_oo[s]
        Q[np.ix_(o, c)] = self.Q_oc[s]
        Q[np.ix_(c, o)] = self.Q_oc[s].T
        Q[np.ix_(c, c)] = self.Q_cc[g]
        return self.sigma0**2 * Q


def _reduce(N, nvec, o, c):
    Noo = N[np.ix_(o, o)]
    Noc = N[np.ix_(o, c)]
    Ncc = N[np.ix_(c, c)]
    Noo_inv = _scaled_inverse(Noo)
    T = Noo_inv @ Noc
    return Noo_inv, T, Ncc - Noc.T @ T, nvec[c] - T.T @ nvec[o]


def schur_iterate(
    backend: JointBackend,
    names: Sequence[str],
    shared: Sequence[str],
    groups: Sequence[str],
    x0s: Sequence[np.ndarray],
    *,
    max_iter: int = 30,
    tol: float = 1e-6,
) -> SchurSolution:
    """Joint Gauss-Helmert iteration of the scans behind ``backend`` (see the module docstring).

    ``x0s``: per-scan starting unknowns in ``names`` order; the shared entries of scans of one
    group are replaced by their mean. ``tol``: convergence when every step is below ``tol``
    times its a priori standard deviation (as :func:`._ghm.gauss_helmert`).
    """
    names = list(names)
    c = np.array([names.index(s) for s in shared], dtype=int)
    o = np.array([i for i in range(len(names)) if i not in set(c.tolist())], dtype=int)
    gnames = list(dict.fromkeys(groups))
    xs = [np.asarray(x, float).copy() for x in x0s]
    for g in gnames:
        members = [i for i, gg in enumerate(groups) if gg == g]
        mean = np.mean([xs[i][c] for i in members], axis=0)
        for i in members:
            xs[i][c] = mean

    def solve(normals):
        red = {g: [np.zeros((len(c), len(c))), np.zeros(len(c))] for g in gnames}
        parts = []
        for s, (N, nvec, _, _) in enumerate(normals):
            Noo_inv, T, Nr, nr = _reduce(N, nvec, o, c)
            red[groups[s]][0] += Nr
            red[groups[s]][1] += nr
            parts.append((Noo_inv, T, nvec[o]))
        Q_cc = {g: _scaled_inverse(red[g][0]) for g in gnames}
        dc = {g: -Q_cc[g] @ red[g][1] for g in gnames}
        dxs, Q_oo, Q_oc, ratio = [], [], [], 0.0
        for s, (Noo_inv, T, n_o) in enumerate(parts):
            g = groups[s]
            # do = -Noo^-1 (n_o + N_oc dc) = -Noo^-1 n_o - T dc
            do = -Noo_inv @ n_o - T @ dc[g]
            dx = np.zeros(len(names))
            dx[o], dx[c] = do, dc[g]
            dxs.append(dx)
            qoc = -T @ Q_cc[g]
            qoo = Noo_inv + T @ Q_cc[g] @ T.T
            Q_oo.append(qoo)
            Q_oc.append(qoc)
            sd = np.sqrt(np.maximum(np.diag(qoo), 1e-300))
            ratio = max(ratio, float(np.max(np.abs(do) / sd)))
        for g in gnames:
            if len(c):
                ratio = max(ratio, float(np.max(np.abs(dc[g]) /
                                                np.sqrt(np.maximum(np.diag(Q_cc[g]), 1e-300)))))
        return dxs, Q_cc, Q_oo, Q_oc, ratio

    history = []
    it, converged = 0, False
    while it < max_iter and not converged:
        normals = backend.normals(xs)
        dxs, *_, ratio = solve(normals)
        backend.update(xs, dxs)
        xs = [x + dx for x, dx in zip(xs, dxs)]
        it += 1
        history.append(ratio)
        converged = ratio < tol
        log.debug("joint iteration %d: max |dx|/sigma = %.3g", it, ratio)
    # final statistics at the solution: one more linearisation (dx ~ 0), as _ghm does
    normals = backend.normals(xs)
    dxs, Q_cc, Q_oo, Q_oc, _ = solve(normals)
    omega = backend.update(xs, dxs)
    xs = [x + dx for x, dx in zip(xs, dxs)]
    n_used = [nu for (_, _, _, nu) in normals]
    red = int(sum(n_used) - len(xs) * len(o) - len(gnames) * len(c))
    sigma0 = math.sqrt(sum(omega) / max(red, 1))
    shared_value = {g: xs[groups.index(g)][c].copy() for g in gnames}
    return SchurSolution(xs, list(groups), shared_value, Q_cc, Q_oo, Q_oc,
                         [N for (N, _, _, _) in normals], list(omega), n_used, sigma0, red, it,
                         converged, o, c, history)


# --------------------------------------------------------------------------------------------
# Campaign level
# --------------------------------------------------------------------------------------------


def group_of(meta: ScanMeta, group: str) -> str:
    """The group a scan belongs to: its tour (night) or the whole campaign."""
    if group == "campaign":
        return "campaign"
    if group in ("night", "tour"):
        if meta.tour:
            return str(meta.tour)
        if meta.start is not None:  # a night spans midnight: shift by 12 h
            return (meta.start - dt.timedelta(hours=12)).date().isoformat()
        return "campaign"
    raise ValueError(f"group: expected one of {', '.join(GROUPS)}, found {group!r}")


def check_shared(names: Sequence[str], shared: Sequence[str]) -> tuple[str, ...]:
    shared = tuple(dict.fromkeys(shared))
    bad = [s for s in shared if s in OBJECT_PARAMETERS]
    if bad:
        raise ValueError(f"--shared: {', '.join(bad)} are object parameters (per scan); only "
                         "calibration parameters can be shared")
    missing = [s for s in shared if s not in names]
    if missing:
        raise ValueError(f"--shared: {', '.join(missing)} not in the model "
                         f"({', '.join(names)})")
    return shared


@dataclass
class JointFit:
    """A joint adjustment: per-scan fits with the shared parameters estimated once per group.

    ``scans`` are :class:`ScanFit` objects of the joint solution (their ``cov`` is the joint
    covariance of the scan's unknowns, shared ones included); ``per_scan`` the independent fits
    it started from (for comparison).
    """

    campaign: Campaign
    model_names: tuple[str, ...]
    shared: tuple[str, ...]
    group: str
    groups: dict[str, list[str]]
    scans: list[ScanFit]
    per_scan: CampaignFit
    solution: SchurSolution
    #: shared parameters asked for that the scans cannot determine (two-face ones on one-face
    #: scans), held at their fixed/prior value
    held: dict[str, Held] = field(default_factory=dict)

    @property
    def sigma0(self) -> float:
        return self.solution.sigma0

    def shared_estimates(self) -> dict[str, dict[str, tuple[float, float]]]:
        """group -> name -> (value, sigma)."""
        sol = self.solution
        out = {}
        for g, val in sol.shared_value.items():
            sig = sol.sigma0 * np.sqrt(np.diag(sol.Q_cc[g]))
            out[g] = {n: (float(val[i]), float(sig[i])) for i, n in enumerate(self.shared)}
        return out

    def campaign_fit(self) -> CampaignFit:
        return CampaignFit(self.campaign, self.model_names, self.scans, tuple(self.shared))

    def precision_gain(self) -> dict:
        """``sigma_joint / sigma_per_scan`` of each shared parameter (median over the group's
        scans) and of the focal length (median over scans)."""
        per = {s.meta.id: s for s in self.per_scan.scans}
        out: dict = {"shared": {}, "f": None}
        est = self.shared_estimates()
        for g, members in self.groups.items():
            for n in self.shared:
                s_per = np.array([per[i].estimates[n][1] for i in members])
                out["shared"].setdefault(n, {})[g] = {
                    "sigma_joint": est[g][n][1],
                    "sigma_per_scan_median": float(np.median(s_per)),
                    "gain": float(est[g][n][1] / np.median(s_per)),
                    "ideal_gain": float(1.0 / math.sqrt(len(members))),
                    "n_scans": len(members),
                }
        ratios = [s.estimates["f"][1] / per[s.meta.id].estimates["f"][1] for s in self.scans]
        out["f"] = {"gain_median": float(np.median(ratios)), "gain_min": float(np.min(ratios)),
                    "gain_max": float(np.max(ratios))}
        return out

    def correlation_drop(self) -> dict:
        """Max |corr(f, calibration)| per scan, per-scan fit vs joint fit."""
        per = {s.meta.id: s for s in self.per_scan.scans}
        rows = []
        for s in self.scans:
            p = per[s.meta.id]

            def maxcorr(fit):
                C = fit.correlation
                i = fit.names.index("f")
                return float(max(abs(C[i, fit.names.index(n)]) for n in self.shared))

            rows.append({"scan": s.meta.id, "per_scan": maxcorr(p), "joint": maxcorr(s)})
        a = np.array([r["per_scan"] for r in rows])
        b = np.array([r["joint"] for r in rows])
        return {"max_abs_corr_f_calibration": {
            "per_scan": {"median": float(np.median(a)), "max": float(np.max(a))},
            "joint": {"median": float(np.median(b)), "max": float(np.max(b))}},
            "scans": rows}

    def consistency(self) -> dict:
        """Per-scan calibration estimates against the joint ones: normalized differences
        ``(x_s - x_joint) / sqrt(sigma_s^2 - sigma_joint^2)`` (the joint estimate contains the
        scan) and their chi-square per group and parameter."""
        per = {s.meta.id: s for s in self.per_scan.scans}
        est = self.shared_estimates()
        out = {}
        for g, members in self.groups.items():
            for n in self.shared:
                vj, sj = est[g][n]
                z = []
                for i in members:
                    v, s = per[i].estimates[n]
                    z.append((v - vj) / math.sqrt(max(s * s - sj * sj, 1e-300)))
                z = np.array(z)
                out.setdefault(n, {})[g] = {"chi2": float(np.sum(z**2)), "dof": len(z) - 1,
                                            "max_abs_z": float(np.max(np.abs(z)))}
        return out


def _heading_hint(fits: Iterable[ScanFit]) -> float | None:
    return mean_heading(scan_heading(s) for s in fits)


def problems_from_fits(campaign: Campaign, fits: Sequence[ScanFit], *, common_shape: bool = True
                       ) -> list[ScanProblem]:
    sig = sigma_vector(campaign)
    sizes = [bucket_size(len(s.data)) for s in fits]
    if common_shape:
        sizes = [max(sizes)] * len(fits)
    return [ScanProblem.from_fit(s, sig, n) for s, n in zip(fits, sizes)]


def fit_joint(
    campaign: Campaign,
    model: str | Iterable[str] = "extended",
    *,
    shared: Sequence[str] = DEFAULT_SHARED,
    group: str = "night",
    start: CampaignFit | None = None,
    scans: Sequence[str] | None = None,
    fixed: dict[str, float] | None = None,
    keep=None,
    robust_k: float | None = 4.0,
    batch: bool = False,
    max_iter: int = 30,
    tol: float = 1e-6,
    backend: JointBackend | None = None,
    progress: bool = False,
) -> JointFit:
    """Joint adjustment: ``shared`` calibration parameters per ``group`` (``"night"``: the tour,
    else the night of the start time; ``"campaign"``: all scans), object parameters per scan.

    ``start``: independent per-scan fits to start from (default: :func:`fit_campaign` with the
    same model, ``fixed``, ``keep``, ``robust_k``; its rejections are kept). Returns a
    :class:`JointFit`; :func:`joint_json` gives its ``fit.json``.
    """
    if group not in GROUPS and group != "tour":
        raise ValueError(f"group: expected one of {', '.join(GROUPS)}, found {group!r}")
    shared = _shareable(campaign, scans, shared)
    if start is None or start.position_fits:  # the joint adjustment starts from single cycles
        start = fit_campaign(campaign, model, scans=scans, fixed=fixed, robust_k=robust_k,
                             keep=keep, batch=batch, progress=progress, per_cycle=True)
    elif scans:
        start = CampaignFit(start.campaign, start.model_names,
                            [s for s in start.scans if s.meta.id in set(scans)])
    fits = list(start.scans)
    names = tuple(fits[0].names)
    held = {n: h for n, h in fits[0].held.items() if n in shared}  # two-face, one-face scans
    shared = check_shared(names, [n for n in shared if n not in held])
    groups = [group_of(s.meta, group) for s in fits]
    if backend is None:
        backend = LocalBackend(problems_from_fits(campaign, fits))
    sol = schur_iterate(backend, names, shared, groups, [s.x for s in fits], max_iter=max_iter,
                        tol=tol)
    residuals = backend.residuals() if hasattr(backend, "residuals") else None
    scans_out = joint_scan_fits(campaign, fits, sol, residuals)
    gmap: dict[str, list[str]] = {}
    for s, g in zip(fits, groups):
        gmap.setdefault(g, []).append(s.meta.id)
    return JointFit(campaign, names, shared, group, gmap, scans_out, start, sol, held)


def _shareable(campaign: Campaign, scans: Sequence[str] | None, shared: Sequence[str]
               ) -> tuple[str, ...]:
    """``shared``, checked before any work against the faces of the scans: one-face scans
    (cycle 0) hold the two-face parameters (:func:`._fit.one_face_holds`), so a joint
    adjustment of them has nothing to share if only those are asked for, and one-face and
    two-face scans cannot share them."""
    metas = [campaign.scan(s) for s in scans] if scans else list(campaign.scans)
    one = [m.id for m in metas if m.cycle == 0]
    two_face = two_face_parameters(shared)
    if not one or not two_face:
        return tuple(shared)
    if len(one) < len(metas):
        raise ValueError(f"--shared: {', '.join(two_face)} flip sign between the faces; the "
                         f"one-face scans ({', '.join(one[:3])}{', ...' if len(one) > 3 else ''}"
                         ") cannot share them with two-face scans: expected scans of one kind "
                         "(--scans)")
    if set(two_face) == set(shared):
        raise ValueError(f"--shared: {', '.join(shared)} flip sign between the faces and every "
                         "scan is one face (cycle 0), so they are not estimable: nothing to "
                         "share; expected a parameter one face determines, or two-face scans")
    return tuple(shared)


def joint_scan_fit(campaign: Campaign, s: ScanFit, x: np.ndarray, cov: np.ndarray, N: np.ndarray,
                   sigma0: float, v: np.ndarray, e: np.ndarray, n_used: int, omega: float,
                   u_object: int, iterations: int, converged: bool,
                   heading_hint_rad: float | None) -> ScanFit:
    """The :class:`ScanFit` of one scan of a joint solution (alignment, deviations redone)."""
    res = scan_result(x=x, cov=cov, N=N, sigma0=sigma0, v=v,
                      normalized=np.asarray(e) / sigma0, weights=s.used,
                      redundancy=n_used - u_object, iterations=iterations, converged=converged)
    f = finish_scan_fit(campaign, s.meta, s.model, s.data, res, s.gravity, s.init, s.used,
                        heading_hint_rad=None if s.alignment.source == "gravity"
                        else heading_hint_rad)
    scan_sigma0 = math.sqrt(omega / max(n_used - u_object, 1))
    return dataclasses.replace(
        f, n_rejected=s.n_rejected, n_window=s.n_window, sigma0=sigma0, held=s.held,
        notes=list(s.notes) + [f"joint adjustment; sigma0 of this scan's residuals "
                               f"{scan_sigma0:.4f}"])


def joint_scan_fits(campaign: Campaign, fits: Sequence[ScanFit], sol: SchurSolution,
                    residuals: Sequence[tuple[np.ndarray, np.ndarray]] | None) -> list[ScanFit]:
    """ScanFit objects of the joint solution (alignment and deviations recomputed)."""
    hint = _heading_hint(fits)
    out = []
    for i, s in enumerate(fits):
        if residuals is not None:
            v, e = residuals[i]
        else:  # residuals stayed elsewhere: keep the per-scan ones for the deviations
            v, e = s.v, s.normalized * s.sigma0
        out.append(joint_scan_fit(campaign, s, sol.xs[i], sol.cov(i), sol.N[i], sol.sigma0, v, e,
                                  sol.n_used[i], sol.omega[i], len(sol.o_idx), sol.iterations,
                                  sol.converged, hint))
    return out


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------


def joint_json(jf: JointFit, *, base: dict | None = None) -> dict:
    """``fit.json`` of a joint adjustment (schema ``hartrao-fit/1``).

    The scans' ``estimates`` hold the per-scan (object) parameters; the shared ones appear once
    under ``"shared"``: ``{name: {value, sigma, unit, ...}}``. With one group (``campaign``)
    ``value``/``sigma`` are its estimate; with several (``night``) they are the inverse-variance
    combination of the groups, whose own estimates are under ``by_group``. ``"joint"`` holds the
    precision gain (sigma_joint / sigma_per_scan), the drop of the correlation between the focal
    length and the calibration, and the consistency of the per-scan estimates. ``base``: the
    ``fit.json`` of the joint scans when they were finished elsewhere (Dask workers).
    """
    doc = fit_json(jf.campaign_fit()) if base is None else base
    for rec in doc["scans"]:
        for n in jf.shared:
            rec["estimates"].pop(n, None)
        rec["shared_group"] = group_of(jf.campaign.scan(rec["id"]), jf.group)
    est = jf.shared_estimates()
    gain = jf.precision_gain()
    cons = jf.consistency()
    shared = {}
    for n in jf.shared:
        vals = np.array([est[g][n][0] for g in est])
        sigs = np.array([est[g][n][1] for g in est])
        w = 1.0 / sigs**2
        mean = float(np.sum(w * vals) / np.sum(w))
        entry = {"value": mean, "sigma": float(1.0 / math.sqrt(np.sum(w))),
                 "unit": parameter_unit(n), "group": jf.group,
                 "by_group": {g: {"value": est[g][n][0], "sigma": est[g][n][1],
                                  "scans": jf.groups[g], **gain["shared"][n][g],
                                  "consistency": cons[n][g]} for g in est}}
        if len(est) > 1:
            entry["groups_chi2"] = float(np.sum(w * (vals - mean) ** 2))
            entry["groups_dof"] = len(vals) - 1
        shared[n] = entry
    for n, h in jf.held.items():
        shared[n] = {"value": h.value, "sigma": None, "identifiable": False, "note": h.note,
                     "unit": parameter_unit(n), "group": jf.group}
    doc["shared"] = shared
    sol = jf.solution
    doc["joint"] = {
        "group": jf.group, "shared": list(jf.shared), "sigma0": sol.sigma0,
        "redundancy": sol.redundancy, "iterations": sol.iterations, "converged": sol.converged,
        "step_history": sol.history,
        "precision_gain": gain,
        "correlation": jf.correlation_drop()["max_abs_corr_f_calibration"],
        "correlation_per_scan": jf.correlation_drop()["scans"],
    }
    return doc


def write_joint_fit(out_dir, jf: JointFit, *, residuals: bool = True) -> Path:
    """Write ``fit.json`` (with ``shared``) and ``residuals/<scan>.parquet`` of a joint fit.

    Crash-safe like :func:`._records.write_fit`: tables first under temporary names, ``fit.json``
    last, strict, with the ``"files"`` manifest.
    """

    return write_fit_dir(out_dir, joint_json(jf), jf.scans if residuals else ())


__all__ = [
    "DEFAULT_SHARED", "JointBackend", "JointFit", "LocalBackend", "ScanProblem", "SchurSolution",
    "bucket_size", "check_shared", "condition_number", "fit_joint", "group_of", "joint_json",
    "joint_scan_fit", "joint_scan_fits", "problems_from_fits",
    "residual_update",
    "schur_iterate", "write_joint_fit",
]
