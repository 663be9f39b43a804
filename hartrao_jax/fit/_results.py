"""The results of the fits: a scan's (:class:`ScanFit`), a position's two-face adjustment
(:class:`PositionFit`, with its surface random effect :class:`SurfaceEffect` and where it
ended, :class:`MixedState`) and a campaign's (:class:`CampaignFit`). Plain dataclasses of
NumPy arrays; units SI (m, rad), sigmas at the fit's sigma0.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..campaign._campaign import Campaign, ScanData, ScanMeta
from ..model._model import ParaboloidModel
from ..preprocess._initial import InitialValues
from ._align import Alignment
from ._identify import Held
from ._position_record import position_record
from ._surface_effect import takes_campaign_prior


def _faces(metas: Sequence[ScanMeta]) -> int:
    return 2 if {1, 2} <= {m.cycle for m in metas} else 1


class Estimates:
    """``sigma`` and ``estimates`` of a fit with ``names``, ``x`` and ``cov`` (scan, stream)."""

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def estimates(self) -> dict[str, tuple[float, float]]:
        return {n: (float(self.x[i]), float(self.sigma[i])) for i, n in enumerate(self.names)}


@dataclass
class ScanFit(Estimates):
    """The adjustment of one scan (NumPy; SI units).

    ``used`` marks the points of ``data`` that entered the final adjustment; ``deviation_m`` is
    the signed normal distance of every point of ``data`` from the fitted paraboloid (positive
    towards the focus), ``X_tel`` its north-aligned telescope-frame coordinates (m).
    """

    meta: ScanMeta
    model: ParaboloidModel
    names: tuple[str, ...]
    x: np.ndarray
    cov: np.ndarray
    sigma0: float
    iterations: int
    converged: bool
    n_points: int
    n_rejected: int
    n_window: int
    alignment: Alignment
    init: InitialValues
    data: ScanData
    used: np.ndarray
    v: np.ndarray
    normalized: np.ndarray
    deviation_m: np.ndarray
    X_tel: np.ndarray
    gravity: np.ndarray
    elevation_deg: float
    notes: list[str] = field(default_factory=list)
    #: parameters of the model the scan cannot determine (two-face ones on a one-face scan),
    #: held at their fixed/prior value instead of estimated
    held: dict[str, Held] = field(default_factory=dict)
    #: parameters a per-cycle fit estimated freely but cannot determine (x6/x7 near the
    #: zenith), with their notes: reported as not identifiable, not as estimates
    undetermined: dict[str, str] = field(default_factory=dict)

    def value(self, name: str) -> float:
        """Estimated or fixed value of a parameter (0 for a parameter not in the model)."""
        if name in self.names:
            return float(self.x[self.names.index(name)])
        fixed = dict(zip(self.model.fixed_names, np.asarray(self.model.fixed_values)))
        return float(fixed.get(name, 0.0))

    def sigma_of(self, name: str) -> float:
        """Standard deviation of an estimate (0 for a fixed parameter)."""
        return float(self.sigma[self.names.index(name)]) if name in self.names else 0.0

    @property
    def correlation(self) -> np.ndarray:
        s = self.sigma
        return self.cov / np.outer(s, s)


@dataclass
class SurfaceEffect:
    """The surface random effect of a position adjustment (``shared/spec/physics.md``).

    ``cells``: description of the cells (panels, or square cells where the telescope has no
    panel layout); ``u`` (g, 3) the cells' predicted offset (m, positive towards the focus) and
    tilts (rad: radial/tangential, or x/y for square cells) with prediction-error covariances
    ``u_cov`` (g, 3, 3); ``n`` points per cell. ``variances``: the estimated components
    (``noise``: factor on the a priori variances; ``offset_m2``, ``tilt_rad2``, ``modes_m2``)
    and their redundancy shares. ``modes``: the smooth modes carried, ``{name: (value m,
    sigma m)}``; ``mode_tests``: per group of modes, the test that decided whether it is carried
    (``chi2``, ``dof``, ``p``, ``carried``). ``mode_prior`` (:func:`mode_prior`): how far the
    data determine each mode (``determined``) and how much of each other unknown's variance is
    the modes' (``share``). ``mode_confounding`` (:func:`mode_confounding`): where the modes are
    not carried, those the other unknowns take up (coma, by the pose) and their response.
    """

    cells: str
    u: np.ndarray
    u_cov: np.ndarray
    n: np.ndarray
    variances: dict[str, float]
    redundancy: dict[str, float]
    modes: dict[str, tuple[float, float]] = field(default_factory=dict)
    mode_tests: dict[str, dict] = field(default_factory=dict)
    mode_prior: dict[str, dict[str, float]] = field(default_factory=dict)
    mode_confounding: dict = field(default_factory=dict)


@dataclass
class MixedState:
    """Where a position's random-effect adjustment ended, to refine it from more points (the
    streamed full-resolution refinement of :mod:`._stream_position`).

    ``model``: the condition with the surface modes; ``x``: all its unknowns (modes included);
    ``u`` (g, 3): the cells' predictions; ``var``: ``(noise factor, cell variances (3,), mode
    variances (r,))`` and ``var0`` their start values; ``ridge``: the modes' indices in ``x``;
    ``kappa_rad``: the north alignment; ``cell_m`` and ``cell_keys``: the square cells (no
    panel layout; None with one); ``inits``: each scan's initial values (its geometry window).
    ``condition``: ``model`` without the modes, which enter through their Zernike columns
    (Noll ``modes``, aperture radius ``aperture_m``) at the points' hit positions, as
    ``mode_design`` of :func:`..solver.gauss_helmert_mixed` (``model`` itself when none).
    """

    model: ParaboloidModel
    x: np.ndarray
    u: np.ndarray
    var: tuple
    var0: tuple
    ridge: dict | None
    kappa_rad: float
    cell_m: float
    cell_keys: np.ndarray | None
    inits: list[InitialValues]
    condition: ParaboloidModel
    modes: tuple[int, ...] = ()
    aperture_m: float = 1.0
    #: the variances were held (the modes carried at a campaign's variance), not estimated
    variances_held: bool = False
    #: the contraction of its iteration (``MixedResult.contraction``), for an adjustment of
    #: the same problem that starts here
    contraction: float = 1.0


@dataclass
class PositionFit:
    """One telescope position adjusted from both faces at once (or from its one usable face).

    One pose, one f and one set of calibration parameters (``names``, ``x``, ``cov``) for all
    of ``scans``; ``cov`` includes the surface random effect. ``held``: parameters not
    identifiable from these data, held at their fixed/prior value. ``faces``: 2 when both
    cycles entered the adjustment, 1 otherwise (never called a cycle average).
    ``response`` (g, len(names), 3): ``d estimate / d (offset, tilt, tilt)`` of each surface
    cell (the solver's ``x_response``): the surface's share of ``cov`` is ``sum_g R_g
    diag(surface variances) R_g^T``; positions that see the same panels share those errors
    (``gravity`` uses it). ``sigma_white``: the rest of each sigma, the noise's (what more
    points shrink). Both None without the surface effect.
    """

    position: str
    scans: list[ScanFit]
    names: tuple[str, ...]
    x: np.ndarray
    cov: np.ndarray
    held: dict[str, Held]
    faces: int
    sigma0: float
    surface: SurfaceEffect | None
    iterations: int
    converged: bool
    n_points: int
    notes: list[str] = field(default_factory=list)
    mixed: MixedState | None = None
    sigma_white: np.ndarray | None = None
    response: np.ndarray | None = None
    #: ``fit_position(keep_resume=True)``: the adjustment again with a campaign's mode variance
    resume: Callable[[float], PositionFit] | None = field(default=None, repr=False,
                                                          compare=False)

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    def estimate(self, name: str) -> tuple[float, float]:
        i = self.names.index(name)
        return float(self.x[i]), float(self.sigma[i])

    @property
    def takes_campaign_prior(self) -> bool:
        """Whether a campaign's mode variance changes this adjustment
        (:func:`._surface_effect.takes_campaign_prior` of its surface effect)."""
        return self.surface is not None and takes_campaign_prior(self.surface.mode_confounding,
                                                                 self.surface.modes)


@dataclass
class CampaignFit:
    """The fitted scans of a campaign. ``shared``: parameters estimated jointly by all scans of
    a group (a joint adjustment's calibration; empty for scan-by-scan fits). ``position_fits``:
    the two-face adjustments the scans come from (empty for per-cycle fits)."""

    campaign: Campaign
    model_names: tuple[str, ...]
    scans: list[ScanFit]
    shared: tuple[str, ...] = ()
    position_fits: list[PositionFit] = field(default_factory=list)

    def positions(self) -> list[dict]:
        """Per position: its adjustment's estimates (two-face fits), or the inverse-variance mean
        focal length of its scans (per-cycle fits)."""
        if self.position_fits:
            return [position_record(p) for p in self.position_fits]
        out: dict[str, list[ScanFit]] = {}
        for s in self.scans:
            out.setdefault(s.meta.position, []).append(s)
        rows = []
        for pos, fits in out.items():
            v = np.array([s.value("f") for s in fits])
            sg = np.array([s.sigma_of("f") for s in fits])
            if np.all(sg > 0):
                w = 1.0 / sg**2
                mean = float(np.sum(w * v) / np.sum(w))
                sig = float(1.0 / math.sqrt(np.sum(w)))
            else:  # focal length held fixed
                w = np.ones_like(v)
                mean, sig = float(np.mean(v)), 0.0
            m = fits[0].meta
            row = {"position": pos}
            if m.ha_deg is not None:
                row.update(ha_deg=m.ha_deg, dec_deg=m.dec_deg)
            if m.azimuth_deg is not None or m.elevation_deg is not None:
                row.update(azimuth_deg=m.azimuth_deg)
            faces = _faces([s.meta for s in fits])
            row.update(elevation_deg=fits[0].elevation_deg, faces=faces,
                       kind=("inverse-variance mean of per-cycle fits" if len(fits) > 1
                             else "one cycle" if faces == 2 or fits[0].meta.cycle else "one face"),
                       f={"value": mean, "sigma": sig},
                       gravity=[float(a) for a in fits[0].gravity],
                       scans=[s.meta.id for s in fits])
            if len(fits) > 1 and sig > 0:
                chi2 = float(np.sum(w * (v - mean) ** 2))
                row["f_consistency_chi2"] = chi2
            rows.append(row)
        return rows
