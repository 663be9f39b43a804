"""The diagnosis state and its refits: configuration, per-scan state (`_Scan`), the grown
model (`_Spec`: parameters, fixed values, bumps, shared instrument parameters), findings,
and the weighted refit of one or all scans that every search and step relies on."""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._config import each_in_threads, on_device
from .._programs import cached_jit
from ..campaign._campaign import Campaign, ScanData, ScanMeta
from ..fit._fit import side_by_side
from ..geometry._geometry import panel_geometry
from ..model._model import (
    OSCILLATION,
    SHIFT,
    ZERNIKE_PREFIX,
    ParaboloidModel,
    is_bump_parameter,
    make_model,
)
from ..solver._ghm import GHResult, gauss_helmert, robust_gauss_helmert
from ..solver._kernel import materialize_trig

ZERNIKE_TESTED: tuple[int, ...] = (5, 6, 7, 8, 9, 10, 11)  # Noll; defocus (4) is the focal length


PROBE = ("shift_x", "shift_y", "shift_z", "osc_cx", "osc_cy")  # translation (3), rotation x, y


GRID_CELL_M = 2.0  # cell of the stated regular grid of telescopes without a panel layout


@dataclass(frozen=True)
class DiagnoseConfig:
    """Decision thresholds and search settings of :func:`diagnose`.

    Attributes:
        alpha: family-wise false-alarm probability of one step; divided among the candidates
            (and the windows and periods searched for motion) by Bonferroni.
        min_effect_m: practical effect size: the predicted rms change of the fit (m) a finding
            must reach, however significant.
        confounded_correlation: multiple correlation with the model above which a parameter is
            inseparable (reported under ``confounded``, never tested).
        max_steps: at most this many findings are accepted.
        robust_k: rejection threshold of the refits (a-posteriori sigmas; None: off).
        max_time_bins / min_points_per_bin: time bins of the motion search.
        max_window_fraction: longest impulsive-shift window searched (fraction of the scan).
        covariate_bins: quantile bins per covariate and face.
        panel_cells: sub-cells per panel (radial, azimuthal) of the within-panel search.
        scan_consistency: a shared (instrument) candidate is refused when freeing it per scan
            improves the fit by more than this fraction of its own statistic (and
            significantly): its structure then belongs to one scan, not to the instrument.
        common_slope: a motion candidate is refused when the other cycle shows the same
            deviation in the same dish cells (regression slope above this and significant).
        effects: effect ids to test (None: all of the catalog).
    """

    alpha: float = 1e-6
    min_effect_m: float = 1.0e-5
    confounded_correlation: float = 0.9995
    max_steps: int = 10
    robust_k: float | None = 4.0
    max_time_bins: int = 1024
    min_points_per_bin: int = 120
    max_window_fraction: float = 0.3
    covariate_bins: int = 16
    panel_cells: tuple[int, int] = (3, 3)
    scan_consistency: float = 0.3
    common_slope: float = 0.5
    effects: tuple[str, ...] | None = None


@dataclass
class _Scan:
    """One scan under diagnosis: fixed geometry from the start fit and the current solution."""

    meta: ScanMeta
    data: ScanData
    g: np.ndarray
    init_x: dict[str, float]
    window: np.ndarray  # points inside the geometry window (and the preprocessing mask)
    l: np.ndarray
    kappa: float
    elevation_deg: float
    X_tel: np.ndarray
    rho: np.ndarray
    psi: np.ndarray
    panel: np.ndarray  # panel id (-1: none), from the start fit
    local: np.ndarray  # (n, 2) m: the point in its panel (radial, tangential; panel_cells)
    s_rho: np.ndarray  # sqrt(1 + rho^2/4f^2): d condition / d normal offset
    face: np.ndarray
    incidence: np.ndarray
    known: np.ndarray  # modelled normal deviation (m): panels and empirical maps
    extra_known: np.ndarray  # the empirical (unexplained) part of it
    cut: np.ndarray  # points cut from the adjustment (bool)
    # current solution
    names: tuple[str, ...] = ()
    x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    sigma0: float = float("nan")
    omega: float = 0.0
    redundancy: int = 0
    v: np.ndarray | None = None
    used: np.ndarray | None = None
    F: np.ndarray | None = None  # misclosure at the observations (m, condition units)
    m: np.ndarray | None = None  # b Sigma b^T
    b0: np.ndarray | None = None  # dF/dr
    probe: np.ndarray | None = None  # dF/d(translation x y z, rotation x y), (n, 5)
    converged: bool = True
    window_s: tuple[float, float] | None = None  # shift window found by the search (s)
    window_stat: float = 0.0
    period_s: float | None = None  # oscillation period found by the periodogram (s)
    period_stat: float = 0.0
    search: dict = field(default_factory=dict)  # curves of the searches (for figures)

    @property
    def id(self) -> str:
        return self.meta.id

    def value(self, name: str) -> float:
        return float(self.x[self.names.index(name)])

    @property
    def mismatch_m(self) -> np.ndarray:
        """Recording minus simulation as normal surface deviation (m, towards the focus)."""
        return -self.F / self.s_rho

    @property
    def mismatch_range_m(self) -> np.ndarray:
        """Recording minus simulation in observation space: the range error (m)."""
        b0 = np.where(np.abs(self.b0) > 1e-12, self.b0, 1e-12)
        return self.F / b0

    def consts(self) -> np.ndarray:
        return np.column_stack([self.data.time_s, self.known, self.s_rho])


@dataclass
class _Spec:
    """The functional model being grown (what is common to all scans and what is per scan)."""

    start: tuple[str, ...]
    shared: dict[str, float] = field(default_factory=dict)  # accepted instrument parameters
    shared_sigma: dict[str, float] = field(default_factory=dict)
    zern_C: np.ndarray | None = None  # (K, 3) gravity Zernike coefficients, modes ZERNIKE_TESTED
    motion: dict[str, dict] = field(default_factory=dict)  # scan id -> names, window_s, period_s
    panels: dict[str, np.ndarray] | None = None  # offset, tilt_r, tilt_t per panel
    accepted: list[str] = field(default_factory=list)
    skip: set[str] = field(default_factory=set)  # found confounded: not tested again
    modelled: set[str] = field(default_factory=set)  # covariates modelled by a map
    times: bool = True  # recorded scan times (else no motion search)
    no_covariates: set[str] = field(default_factory=set)  # covariates the recording lacks
    # modelled local deformations: {"names": bump_* names, "values": {name: value},
    # "scans": ids of the scans where they are free (the others hold them fixed), "free":
    # optional subset of the names that are free there (the rest held at "values")}
    bumps: list[dict] = field(default_factory=list)

    def names(self) -> list[str]:
        out = list(self.start) + list(self.shared)
        for m in self.motion.values():
            out += [n for n in m["names"] if n not in out]
        if self.zern_C is not None:
            out += [f"{ZERNIKE_PREFIX}{j}" for j in ZERNIKE_TESTED]
        if self.panels is not None:
            out.append("panel_offset")
        for a in self.accepted:
            if a.startswith("unexplained") and "unexplained" not in out:
                out.append("unexplained")
        for b in self.bumps:
            out += list(b["names"])
        return out


def _fixed(sc: _Scan, spec: _Spec) -> dict[str, float]:
    fixed = dict(spec.shared)
    for b in spec.bumps:
        fixed.update(b["values"])
    if spec.zern_C is not None:
        for k, j in enumerate(ZERNIKE_TESTED):
            fixed[f"{ZERNIKE_PREFIX}{j}"] = float(spec.zern_C[k] @ sc.g)
    return fixed


def _scan_model(sc: _Scan, spec: _Spec, aperture: float, extra: Sequence[str] = (),
                window_s=None, period_s=None, canonical: bool = False):
    """The scan's model: the start parameters, its motions and bumps, then ``extra``.
    ``canonical``: the parameters after the start's in name order, so that the same set
    gives the same model (and the same compiled programs) whatever the order they joined in
    (the joint systems of successive steps)."""
    mot = spec.motion.get(sc.id, {})
    names = list(spec.start) + [n for n in mot.get("names", ()) if n not in spec.start]
    for b in spec.bumps:  # free where they are seen; "free": the subset the fit may move
        if sc.id in b["scans"]:
            names += [n for n in b["names"] if n in b.get("free", b["names"])]
    names += [n for n in extra if n not in names]
    if canonical:
        names = list(spec.start) + sorted(n for n in names if n not in spec.start)
    window = mot.get("window_s") or window_s or (0.0, 0.0)
    period = mot.get("period_s") or period_s or 1.0
    fixed = {k: v for k, v in _fixed(sc, spec).items() if k not in names}  # free wins here
    return make_model(names, fixed, shift_window_s=window, osc_period_s=period,
                      kappa_rad=sc.kappa, aperture_radius_m=aperture, check_separable=False)


@cached_jit
def _pointwise(model, probe, l, x, xp, c, s2, on):
    """Per point: the misclosure ``F``, ``m = b Sigma b^T``, ``dF/dr`` and the probe derivatives
    (translation, rotation); one program and one pass over the points for all four. ``on``: a
    runtime True, so that each distinct sine and cosine is evaluated once
    (:func:`..solver._kernel.materialize_trig`: 0.15 -> 0.06 s for 2.6e5 points, the same
    values to 2e-13 relative)."""
    k = len(PROBE)
    cond, prb = materialize_trig(model, on), materialize_trig(probe, on)

    def one(args):
        ll, cc = args
        F, b = jax.value_and_grad(lambda l0: cond(l0, x, cc))(ll)
        m = jnp.sum(b * b * s2)
        ap = jax.jacfwd(lambda p: prb(ll, jnp.concatenate([xp, p]), cc))(jnp.zeros(k, ll.dtype))
        return F, m, b[0], ap

    return jax.lax.map(one, (l, c), batch_size=8192)


class _Context:
    """Campaign-level constants of one diagnosis."""

    def __init__(self, campaign: Campaign, config: DiagnoseConfig):
        self.campaign = campaign
        self.config = config
        self.sums_memo: dict[str, object] = {}  # scans' joint-system sums (._explain._cell_sums)
        tel = campaign.telescope
        self.aperture = tel.diameter_m / 2
        s = campaign.scanner
        self.sigma = np.array([s.sigma_range_m, s.sigma_angle_rad, s.sigma_angle_rad])
        self.has_layout = bool(tel.ring_edges_m and tel.panels_per_ring)
        if self.has_layout:
            self.edges, self.counts = list(tel.ring_edges_m), list(tel.panels_per_ring)
            self.layout_note = f"panels of the {tel.name} layout"
        else:
            # no panel layout (e.g. the GBT): a stated regular grid of cells of about
            # GRID_CELL_M in the aperture plane (rings of that width, arcs of that length),
            # over the radii the reflector spans (an offset reflector: offset +- D/2)
            off = float(getattr(tel, "offset_m", 0.0) or 0.0)
            r0 = max(float(tel.cone_radius_m or 0.0), off - self.aperture)
            r1 = off + self.aperture
            nr = max(1, round((r1 - r0) / GRID_CELL_M))
            self.edges = list(np.linspace(r0, r1, nr + 1))
            self.counts = [max(6, round(2 * np.pi * 0.5 * (a + b) / GRID_CELL_M))
                           for a, b in zip(self.edges[:-1], self.edges[1:])]
            self.layout_note = (f"{tel.name} has no panel layout: grid cells of about "
                                f"{GRID_CELL_M:g} m x {GRID_CELL_M:g} m in the aperture plane "
                                f"(rings of {GRID_CELL_M:g} m, arcs of {GRID_CELL_M:g} m), "
                                "ids are grid cells, not panels")
        self.geo = panel_geometry(self.edges, self.counts)
        self.n_panels = int(sum(self.counts))
        self.supersets = _Supersets()


def _held_outside(model, names) -> tuple[str, ...]:
    """The names ``model`` holds at a value that are not among ``names`` (sorted, as
    :func:`..model.make_model` orders them)."""
    return tuple(sorted(n for n in model.fixed_names if n not in names))


def _covers(big, model) -> bool:
    """Whether ``big``'s names can stand in for ``model``'s: every free name of ``model`` free
    in ``big``, the same names held outside them, the same aperture, and no parameter of a
    bump free in ``big`` alone (a zero width is not "no bump"; every other parameter of the
    catalog at zero leaves the condition as it is)."""
    if big.aperture_radius_m != model.aperture_radius_m or not set(model.free) <= set(big.free):
        return False
    if big.fixed_names != _held_outside(model, big.free):
        return False
    named = set(model.free) | set(model.fixed_names)
    return not any(is_bump_parameter(n) for n in set(big.free) - named)


class _Supersets:
    """Per scan, the widest sets of names evaluated on it so far, each to stand in for the
    narrower ones it covers (:func:`_covers`). The free names are static in a model, so every
    candidate set would otherwise be a program of its own to trace, lower and load (0.1-0.3 s
    each); the wider set gives the same values with the names it adds at zero (the sums equal
    the narrower model's to 1e-9 relative, ``tests/diagnose/test_supersets.py``; the diagnosis
    document within 1.2e-7, the same findings). Where a term of an added name is not finite at
    some point (zero times an infinite column), :func:`._explain._cell_sums` falls back to the
    narrower model."""

    def __init__(self):
        self._by_scan: dict[str, list] = {}

    def of(self, scan_id: str, model, x) -> tuple[ParaboloidModel, np.ndarray, np.ndarray]:
        """``(wide, x_wide, idx)``: ``model`` with the names of a wider set seen before (its
        own the first time, or where none covers it), the unknowns at ``model``'s values for
        ``x`` (its held values where it holds them, else zero), and the positions of
        ``model.free`` in ``wide.free``. Shift window, period, frame and held values are
        ``model``'s."""
        known = self._by_scan.setdefault(scan_id, [])
        big = next((b for b in known if _covers(b, model)), None)
        if big is None:
            known.append(model)
            return model, np.asarray(x, float), np.arange(len(model.free))
        values = model.values(x)
        wide = ParaboloidModel(
            free=big.free, fixed_names=big.fixed_names,
            fixed_values=on_device([values[n] for n in big.fixed_names], float),
            shift_window_s=model.shift_window_s, osc_period_s=model.osc_period_s,
            kappa_rad=model.kappa_rad, aperture_radius_m=model.aperture_radius_m)
        x_wide = np.array([values.get(n, 0.0) for n in big.free])
        return wide, x_wide, np.array([big.free.index(n) for n in model.free], int)


_BUCKET = 1 << 15  # point arrays are padded to a multiple: scans of similar size share programs


def _npad(n: int) -> int:
    return max(_BUCKET, -(-n // _BUCKET) * _BUCKET)


def _pad(a: np.ndarray, npad: int, fill=None) -> np.ndarray:
    """Rows padded to ``npad``: repeating the last row (``fill=None``) or with ``fill``."""
    a = np.asarray(a)
    n = a.shape[0]
    if n == npad:
        return a
    tail = (np.repeat(a[-1:], npad - n, 0) if fill is None
            else np.full((npad - n,) + a.shape[1:], fill, a.dtype))
    return np.concatenate([a, tail])


def _adjust(ctx: _Context, model, l, x0, c, w, v0=None):
    """Robust GH on padded arrays; returns the result cut back to the points."""

    n = len(l)
    npad = _npad(n)
    lp, cp, wp = _pad(l, npad), _pad(c, npad), _pad(w, npad, 0.0)
    k = ctx.config.robust_k
    if k is None:
        res = gauss_helmert(model, lp, x0, ctx.sigma, cp, wp)
    else:
        res = robust_gauss_helmert(model, lp, x0, ctx.sigma, cp, wp, k=k)
    # the padding cut off on the host (a slice of a device array is a program per shape)
    return GHResult(x=res.x, cov=res.cov, N=res.N, sigma0=res.sigma0, v=np.asarray(res.v)[:n],
                    misclosure=np.asarray(res.misclosure)[:n],
                    normalized=np.asarray(res.normalized)[:n],
                    weights=np.asarray(res.weights)[:n], redundancy=res.redundancy,
                    iterations=res.iterations, converged=res.converged)


def _refit(ctx: _Context, sc: _Scan, spec: _Spec, x_hint: dict[str, float] | None = None,
           from_used: bool = False) -> None:
    """Adjust one scan with the current model (rigorous GH with robust rejection).

    Rejection starts from the whole window (points rejected because of an effect that is now
    modelled come back), or from the points used so far (``from_used``: global, small changes).
    """
    model = _scan_model(sc, spec, ctx.aperture)
    prev = dict(zip(sc.names, sc.x))
    hint = x_hint or {}
    x0 = np.array([hint.get(n, prev.get(n, sc.init_x.get(n, 0.0))) for n in model.free])
    w = ((sc.used if from_used and sc.used is not None else sc.window) & ~sc.cut).astype(float)
    res = _adjust(ctx, model, sc.l, x0, sc.consts(), w)
    sc.names = model.free
    sc.x, sc.cov, sc.sigma0 = np.asarray(res.x), np.asarray(res.cov), float(res.sigma0)
    sc.v, sc.used = np.asarray(res.v), np.asarray(res.weights) > 0
    sc.converged = bool(res.converged)
    _evaluate(ctx, sc, spec, model)


def _evaluate(ctx: _Context, sc: _Scan, spec: _Spec, model=None) -> None:
    """Misclosures, ``m``, ``dF/dr`` and probe derivatives at the current solution."""
    model = model or _scan_model(sc, spec, ctx.aperture)
    n = len(sc.l)
    npad = _npad(n)
    c = _pad(sc.consts(), npad)
    lp = _pad(sc.l, npad)
    x = np.asarray(sc.x, float)
    base = [n for n in model.free if n not in SHIFT + OSCILLATION]
    fixed = {k: v for k, v in _fixed(sc, spec).items() if k not in base}
    probe = make_model(base + list(PROBE), fixed, shift_window_s=(-1e9, 1e18),
                       osc_period_s=1e18, kappa_rad=sc.kappa, aperture_radius_m=ctx.aperture,
                       check_separable=False)
    xp = np.array([sc.value(n) for n in probe.free[: len(probe.free) - len(PROBE)]])
    F, m, b0, ap = _pointwise(model, probe, lp, x, xp, c, np.asarray(ctx.sigma, float)**2,
                              on_device(True, bool))
    sc.F, sc.m = np.asarray(F)[:n], np.asarray(m)[:n]
    sc.b0, sc.probe = np.asarray(b0)[:n], np.asarray(ap)[:n]
    u = sc.used
    sc.omega = float(np.sum(sc.F[u] ** 2 / sc.m[u]))
    sc.redundancy = int(u.sum() - len(sc.x))


def _global_sigma0(scans: Sequence[_Scan]) -> float:
    return math.sqrt(sum(s.omega for s in scans) / max(1, sum(s.redundancy for s in scans)))


def _rms(scans: Sequence[_Scan]) -> float:
    v = np.concatenate([s.mismatch_m[s.used] for s in scans])
    return float(np.sqrt(np.mean(v**2)))


@dataclass
class Finding:
    """One accepted effect (a ``findings[]`` entry of ``hartrao-diagnosis/1``)."""

    effect: str
    family: str
    scans: list[str]
    where: dict[str, Any]
    estimate: dict[str, dict[str, float]]
    statistic: float
    dof: int
    p_value: float
    sigma0_before: float
    sigma0_after: float
    rms_before_m: float
    rms_after_m: float
    explanation: str
    effect_size_m: float = 0.0
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        d = {
            "effect": self.effect, "family": self.family, "scans": self.scans,
            "where": self.where, "estimate": self.estimate,
            "statistic": _num(self.statistic), "dof": int(self.dof),
            "p_value": _num(self.p_value),
            "sigma0_before": _num(self.sigma0_before), "sigma0_after": _num(self.sigma0_after),
            "rms_before_m": _num(self.rms_before_m), "rms_after_m": _num(self.rms_after_m),
            "explanation": self.explanation, "effect_size_m": _num(self.effect_size_m),
        }
        d.update(self.extra)
        return d


def _num(v):
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _panel_known(ctx: _Context, sc: _Scan, panels: dict[str, np.ndarray] | None) -> np.ndarray:
    if panels is None:
        return np.zeros(len(sc.rho))
    k = np.where(sc.panel >= 0, sc.panel, 0)
    return np.where(sc.panel >= 0, panels["offset"][k], 0.0)


def _set_known(ctx: _Context, sc: _Scan, spec: _Spec) -> None:
    sc.known = _panel_known(ctx, sc, spec.panels) + sc.extra_known


_STATE = ("names", "x", "cov", "sigma0", "omega", "redundancy", "v", "used", "F", "m", "b0",
          "probe", "converged", "known", "extra_known", "cut")


def _save(S: Sequence[_Scan], spec: _Spec):
    """The scans' fit state and a copy of the spec (for :func:`_restore`)."""
    return [{k: getattr(sc, k) for k in _STATE} for sc in S], copy.deepcopy(spec)


def _restore(S: Sequence[_Scan], saved) -> _Spec:
    states, spec = saved
    for sc, st in zip(S, states):
        for k, v in st.items():
            setattr(sc, k, v)
    return spec


def _refit_all(ctx, S, spec, only: Sequence[_Scan] | None = None, hints=None,
               from_used: bool = True, others: bool = False):
    """Refit the scans ``only`` (default all) from the window or from their points in use;
    ``others``: the remaining scans too, from their points in use (the panel offsets or the
    shared parameters moved). The scans in threads: each refit reads the context and the
    spec and writes its own scan only; the parts of its passes go to the solver's pool, and
    one scan's host bookkeeping and evaluation overlap the other's passes."""
    todo = [(sc, only is None or sc in only) for sc in S]
    todo = [(sc, mine) for sc, mine in todo if mine or others]

    def refit(sc, mine):
        _set_known(ctx, sc, spec)
        _refit(ctx, sc, spec, (hints or {}).get(sc.id), from_used=from_used or not mine)

    if side_by_side(ctx.campaign, [sc.meta for sc, _ in todo]):
        each_in_threads(refit, todo, "refits")
    else:  # scans too large for two adjustments' stores at once (as ``fit``'s faces)
        for sc, mine in todo:
            refit(sc, mine)
