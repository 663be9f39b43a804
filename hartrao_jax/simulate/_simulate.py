"""Simulator: ray casting of the scanner's raw angular grid onto the reflector (the test oracle).

The truth of every scan is a :class:`~hartrao_jax.model.ParaboloidModel` with no free unknowns,
built in the *fitted* frame (the telescope frame rotated about Z by ``-kappa``, seed eq. 6). For
every ray of the raw angular grid the raw range ``r`` is solved by Newton's method so that the
model's condition ``F((r, phi, theta), [], (time_s, deviation_m)) = 0``: instrument parameters,
impulsive shift, oscillation and drift act through the very formulas the fitter uses, so a fit
with the right model recovers the truth exactly (to the noise). ``deviation_m`` is the true
normal deviation of the reflector at the hit point (panels + gravity Zernike modes + extras),
re-evaluated between Newton passes. Gaussian noise is added afterwards.

Scene (telescope frame, m): a central truncated cone on the axis, four quadrupod legs from the
reflector surface to an apex beneath the sub-reflector, far terrain behind the rim. Only rays
within ``rim angle + margin_deg`` of the dish axis are cast (the dish axis, not the nadir: the
scanner's z axis follows gravity, so away from the zenith the reflector lies off the nadir);
the rest of the sphere holds the sub-reflector, its support and the sky, which return nothing
useful. The legs stand on the surface (``leg_foot_radius_m``), not at the rim: with the apex
above the scanner, a leg from the rim would hide no reflector point. Every row is labelled with
a class of :data:`CLASSES`.

Scan table order is the scanner's: phi lines at a constant rate (``line_period_s``), theta
through face 1 then face 2 within a line, ``time_s = (line + theta / 2 pi) line_period_s``.

Units: metres, radians, seconds; ``_deg`` names are degrees.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
import pathlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._programs import cached_jit
from ..campaign._campaign import Campaign, ScanData, ScanMeta, default_campaign, write_campaign
from ..campaign._safeio import write_json_atomic, write_table
from ..campaign._schedule import CAMPAIGN_STEP_RAD, PRESET_TOURS, plan_positions
from ..geometry._geometry import (
    decompose_zyx,
    panel_geometry,
    panel_ids,
    pointing_elevation_deg,
    pointing_gravity,
    polar_to_cartesian,
    rot_x,
    rot_y,
    rot_z,
)
from ..model._model import ZERNIKE_PREFIX, ParaboloidModel
from ..physics._catalog import (
    DEFAULT_ZERNIKE_MODES,
    INSTRUMENT,
    gravity_focal_length,
    gravity_zernike_coefficients,
    local_deformation,
    panel_deviation,
    thermal_focal_length,
    zernike_deviation,
)

TRUTH_SCHEMA = "hartrao-truth/1"
EXACT_M = 1e-9  # |condition| (m) every reflector point satisfies at the truth, before noise
CLASSES: dict[str, int] = {"reflector": 0, "cone": 1, "quadrupod": 2, "background": 3,
                           "mixed": 4, "multipath": 5}
"""uint8 class codes of the truth tables: reflector surface, central cone, quadrupod legs, far
background, mixed pixels (rim and leg silhouettes), multipath (reflector range + 3 mm..5 cm)."""

# ------------------------------------------------------------------------------------- effects

_ZPG = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.5e-4, -1.5e-4, 0.0), (0.0, 6e-5, 0.0),
        (6e-5, 0.0, 0.0), (0.0, 0.0, 0.0))  # Zernike m per unit g, modes DEFAULT_ZERNIKE_MODES

EFFECT_DEFAULTS: dict[str, dict[str, Any]] = {
    "impulsive_shift": {"displacement_m": 0.002, "cycle": 1, "phi_deg": 40.0, "duration_s": 1.0,
                        "direction": (0.0, 0.0, 1.0), "scans": None},
    "oscillation": {"amplitude_rad": 2e-5, "period_s": 1.1, "phase_rad": 0.0, "axis": "x",
                    "scans": None},
    "drift": {"rate_m_s": 1e-5, "direction": (1.0, 0.0, 0.0), "rate_rad_s": 0.0, "axis": "z",
              "scans": None},
    "panel_offset": {"rms_m": 1.5e-4, "tilt_rms_rad": None, "fraction": 1.0, "panels": None},
    "gravity_deformation": {"scale": 1.0, "df_dg_m": (5e-4, 1e-3, 2e-3),
                            "zernike_modes": DEFAULT_ZERNIKE_MODES, "zernike_per_g_m": _ZPG},
    "thermal": {"df_dT_m_per_K": 1.3e-4, "reference_c": 15.0},
    "unexplained": {"amplitude_m": 5e-4, "rho_m": 6.0, "psi_deg": 100.0, "width_m": 0.6},
    "local_deformation": {"amplitude_m": 5e-4, "x_m": 4.0, "y_m": 3.0, "width_m": 0.6},
}
"""Non-instrument effects: their keys and defaults; the first key is the main amplitude.

``impulsive_shift``: the scanner is displaced by ``displacement_m`` along ``direction``
(telescope frame) from raw ``phi_deg`` for ``duration_s`` in scans of ``cycle``.
``oscillation``: gimbal swing ``amplitude_rad sin(2 pi t / period_s + phase_rad)`` about scanner
``axis`` x or y. ``drift``: translation ``rate_m_s`` along ``direction`` (telescope frame) and
rotation ``rate_rad_s`` about scanner ``axis``. Motion effects apply to all scans or to ``scans``
(ids). ``panel_offset``: random offsets (``rms_m``) and tilts (``tilt_rms_rad``, default
``rms_m / 2`` per m) of a ``fraction`` of the panels, plus explicit ``panels``
``{id: offset_m | (offset_m, tilt_radial_rad, tilt_tangential_rad)}`` (with ``panels`` the
random part defaults to 0). ``gravity_deformation``: ``f = f0 + scale df_dg_m . g`` (``f0`` such
that the zenith gives the nominal focal length) and Zernike coefficients
``scale zernike_per_g_m @ g`` (rows: ``zernike_modes``). ``thermal``: ``f += df_dT (T - ref)``.
``unexplained``: a Gaussian bump of ``amplitude_m`` at (``rho_m``, ``psi_deg``), no catalog entry.
``local_deformation``: the catalog's bump (:func:`._physics.local_deformation`) of ``amplitude_m``
and ``width_m`` centred at (``x_m``, ``y_m``) of the north-aligned aperture plane.
"""


class EffectError(ValueError):
    """An effect id, key or value that the simulator does not know."""


def _known_ids() -> str:
    return ", ".join([*INSTRUMENT, *EFFECT_DEFAULTS])


def _parse_value(text: str):
    """CLI value: number, ``a,b,c`` list, ``id:value,...`` mapping, or a plain string."""
    def num(s):
        try:
            return float(s)
        except ValueError:
            return s.strip()
    if ":" in text:
        return {int(k): num(v) for k, v in (kv.split(":", 1) for kv in text.split(",") if kv)}
    if "," in text:
        return [num(s) for s in text.split(",") if s.strip()]
    return num(text)


def parse_effects(items: Sequence[str]) -> dict[str, float | dict]:
    """``["x2=3e-4", "impulsive_shift=0.002", "impulsive_shift.phi_deg=40"]`` -> effects dict.

    ``ID=VALUE`` sets an instrument parameter or an effect's main amplitude, ``ID.KEY=VALUE`` one
    of its keys (:data:`EFFECT_DEFAULTS`). Raises :class:`EffectError` naming the bad item.
    """
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise EffectError(f"--effect {item!r}: expected ID=VALUE or ID.KEY=VALUE")
        lhs, text = (s.strip() for s in item.split("=", 1))
        eid, _, key = lhs.partition(".")
        try:
            value = _parse_value(text)
        except ValueError:
            raise EffectError(f"--effect {item!r}: cannot parse the value {text!r}") from None
        if eid in INSTRUMENT:
            if key or not isinstance(value, float):
                raise EffectError(f"--effect {item!r}: instrument parameter {eid} takes one "
                                  "number (ID=VALUE)")
            out[eid] = value
            continue
        if eid not in EFFECT_DEFAULTS:
            raise EffectError(f"--effect {item!r}: unknown effect id {eid!r}; known: "
                              f"{_known_ids()}")
        key = key or next(iter(EFFECT_DEFAULTS[eid]))
        if key not in EFFECT_DEFAULTS[eid]:
            raise EffectError(f"--effect {item!r}: unknown key {key!r} of {eid}; known: "
                              f"{', '.join(EFFECT_DEFAULTS[eid])}")
        out.setdefault(eid, {})[key] = value
    normalize_effects(out)  # validate now, with the CLI's wording
    return out


def normalize_effects(effects: Mapping[str, Any] | None) -> dict[str, Any]:
    """Validate effects and fill in every default: instrument ids -> float, others -> full dict."""
    out: dict[str, Any] = {}
    for eid, v in (effects or {}).items():
        if eid in INSTRUMENT:
            if not isinstance(v, (int, float)) or isinstance(v, bool):
                raise EffectError(f"effect {eid}: expected a number, found {v!r}")
            out[eid] = float(v)
            continue
        if eid not in EFFECT_DEFAULTS:
            raise EffectError(f"unknown effect id {eid!r}; known: {_known_ids()}")
        d = dict(EFFECT_DEFAULTS[eid])
        main = next(iter(d))
        given = dict(v) if isinstance(v, Mapping) else {main: v}
        bad = [k for k in given if k not in d]
        if bad:
            raise EffectError(f"effect {eid}: unknown key(s) {', '.join(map(str, bad))}; known: "
                              f"{', '.join(d)}")
        if eid == "panel_offset" and given.get("panels") and "rms_m" not in given:
            d["rms_m"] = 0.0
        d.update(given)
        for k, x in d.items():
            ref = EFFECT_DEFAULTS[eid][k]
            if isinstance(ref, float) or (k == "cycle"):
                if not isinstance(x, (int, float)) or isinstance(x, bool):
                    raise EffectError(f"effect {eid}.{k}: expected a number, found {x!r}")
                d[k] = int(x) if k == "cycle" else float(x)
        if eid == "impulsive_shift" and d["cycle"] not in (1, 2):
            raise EffectError(f"effect impulsive_shift.cycle: expected 1 or 2, found {d['cycle']}")
        axes = ("x", "y", "z") if eid == "drift" else ("x", "y")
        if eid in ("oscillation", "drift") and d["axis"] not in axes:
            raise EffectError(f"effect {eid}.axis: expected one of {', '.join(axes)} (scanner "
                              f"frame), found {d['axis']!r}")
        for k in ("direction", "df_dg_m"):
            if k in d and np.shape(d[k]) != (3,):
                raise EffectError(f"effect {eid}.{k}: expected 3 numbers, found {d[k]!r}")
        if isinstance(d.get("scans"), str):
            d["scans"] = [d["scans"]]
        out[eid] = d
    return out


# ------------------------------------------------------------------------------------- presets


@dataclass(frozen=True)
class Preset:
    """A named simulation: positions ``(name, ha_deg, dec_deg)``, grid step (rad), effects."""

    name: str
    description: str
    positions: tuple[tuple[str, float, float], ...]
    step_rad: float
    effects: Mapping[str, Any]
    scatter: bool
    plan: tuple[Mapping[str, Any], ...] = ()  # full position dicts (tour, start, temperature)


_DEMO_EFFECTS = {"x4": 1.5e-4, "x6": 3e-5, "x7": -4e-5, "panel_offset": 1.5e-4}
PRESETS: dict[str, Preset] = {
    "demo": Preset("demo", "r23, both cycles, coarse grid, seed instrument errors, panels, scatter",
                   (("r23", -35.0, -64.0),), 0.006, _DEMO_EFFECTS, True),
    "clean": Preset("clean", "demo geometry, reflector points only, no effects (sigma0 tests)",
                    (("r23", -35.0, -64.0),), 0.006, {}, False),
    "paper": Preset("paper", "demo at the paper's resolution (0.63 mrad): benchmarks only",
                    (("r23", -35.0, -64.0),), 0.00063, _DEMO_EFFECTS, True),
}


def _plan_preset(name: str, description: str) -> Preset:
    """A preset on the measurement plan of :mod:`._schedule` (tours, times, temperatures)."""
    plan = tuple(plan_positions(PRESET_TOURS[name]))
    return Preset(name, description,
                  tuple((p["position"], p["ha_deg"], p["dec_deg"]) for p in plan),
                  CAMPAIGN_STEP_RAD, _CAMPAIGN_EFFECTS, True, plan)


_CAMPAIGN_EFFECTS = {**_DEMO_EFFECTS, "gravity_deformation": 1.0, "thermal": 1.3e-4}
PRESETS["campaign"] = _plan_preset(
    "campaign", "the paper's schedule: 4 tours, 88 positions x 2 cycles, start times and night "
    "temperatures; calibration, panels, gravity deformation, thermal; coarse grid (--step)")
PRESETS["tour-red"] = _plan_preset(
    "tour-red", "the red tour of the campaign preset (23 positions x 2 cycles)")


@dataclass(frozen=True)
class SimConfig:
    """Mount, scene, timing and numerics (m, rad, s).

    The scanner hangs ``hang_m`` below a gimbal pivot at ``pivot_m`` (telescope frame), so it sits
    at ``pivot + hang g`` (+ a random ``pose_jitter_m`` per position) unless ``t_tel_m`` fixes it;
    ``kappa_s_rad`` is its heading on the mount. Both cycles of a position share the pose.
    """

    pivot_m: tuple[float, float, float] = (0.005, -0.01, 9.55)
    hang_m: float = 0.25
    t_tel_m: tuple[float, float, float] | None = None
    pose_jitter_m: float = 0.002
    kappa_s_rad: float = 0.4
    gimbal_misalignment_rad: tuple[float, float] = (0.0, 0.0)  # about scanner x, then y
    margin_deg: float = 15.0
    line_period_s: float = 180.0 * 0.00063 / math.pi  # 180 s for the paper's 4987 lines
    duration_s: float | None = None  # overrides line_period_s
    cone_top_radius_m: float = 0.8
    cone_height_m: float = 3.0
    leg_radius_m: float = 0.15
    leg_foot_radius_m: float = 9.0  # legs stand on the surface: they shadow the outer rings
    leg_apex_z_m: float = 10.4
    scatter: bool | None = None  # None: the preset decides
    background_prob: float = 0.3
    background_range_m: tuple[float, float] = (20.0, 80.0)
    mixed_prob: float = 0.8
    multipath_fraction: float = 0.002
    multipath_range_m: tuple[float, float] = (0.003, 0.05)
    intensity_sigma: float = 0.02
    noise: bool = True
    chunk_rays: int = 1 << 16
    block_candidates: int = 2_000_000
    newton_outer: int = 3
    newton_inner: int = 3


# ------------------------------------------------------------------------------------ reflector


@dataclass(frozen=True)
class Reflector:
    """Truth of the reflector, shared by all scans of a campaign (panels per id, m and rad)."""

    f_nominal_m: float
    df_dg_m: np.ndarray
    zernike_modes: tuple[int, ...]
    zernike_per_g_m: np.ndarray
    df_dT_m_per_K: float
    reference_c: float
    offset_m: np.ndarray
    tilt_radial_rad: np.ndarray
    tilt_tangential_rad: np.ndarray
    bump: tuple[float, float, float, float]  # amplitude m, rho m, psi rad, width m
    local: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)  # amplitude, x, y, width m

    def focal_length(self, g: np.ndarray, temperature_c: float | None) -> tuple[float, float]:
        """``(f, f_gravity)``: gravity (zenith gives the nominal), then temperature."""
        f0 = self.f_nominal_m + float(self.df_dg_m[2])
        fg = float(gravity_focal_length(f0, self.df_dg_m, g))
        if temperature_c is None:
            return fg, fg
        return float(thermal_focal_length(fg, self.df_dT_m_per_K, temperature_c,
                                          self.reference_c)), fg

    def zernike(self, g: np.ndarray) -> np.ndarray:
        return np.asarray(gravity_zernike_coefficients(self.zernike_per_g_m, g))


def make_reflector(telescope, effects: Mapping[str, Any], seed: int = 0) -> Reflector:
    """Reflector truth from normalised effects; panels drawn reproducibly from ``seed``."""
    counts = telescope.panels_per_ring or ()
    n = int(sum(counts)) or 1
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
    sel, off, tr, tt = rng.random(n), rng.normal(size=n), rng.normal(size=n), rng.normal(size=n)
    offset, tilt_r, tilt_t = np.zeros(n), np.zeros(n), np.zeros(n)
    if (p := effects.get("panel_offset")) is not None:
        keep = sel < p["fraction"]
        trms = p["rms_m"] / 2 if p["tilt_rms_rad"] is None else p["tilt_rms_rad"]
        offset, tilt_r, tilt_t = (np.where(keep, p["rms_m"] * off, 0.0),
                                  np.where(keep, trms * tr, 0.0), np.where(keep, trms * tt, 0.0))
        for k, v in (p["panels"] or {}).items():
            if not 0 <= int(k) < n:
                raise EffectError(f"effect panel_offset.panels: panel {k} not in 0..{n - 1}")
            vals = (list(v) + [0.0, 0.0])[:3] if isinstance(v, (list, tuple)) else [v, 0.0, 0.0]
            offset[int(k)], tilt_r[int(k)], tilt_t[int(k)] = map(float, vals)
    gd = effects.get("gravity_deformation")
    modes = tuple(int(j) for j in (gd or EFFECT_DEFAULTS["gravity_deformation"])["zernike_modes"])
    s = gd["scale"] if gd else 0.0
    zpg = np.asarray(gd["zernike_per_g_m"] if gd else np.zeros((len(modes), 3)), float)
    if zpg.shape != (len(modes), 3):
        raise EffectError(f"effect gravity_deformation.zernike_per_g_m: expected shape "
                          f"({len(modes)}, 3), found {zpg.shape}")
    th = effects.get("thermal")
    u = effects.get("unexplained")
    bump = ((u["amplitude_m"], u["rho_m"], math.radians(u["psi_deg"]), u["width_m"]) if u
            else (0.0, 0.0, 0.0, 1.0))
    ld = effects.get("local_deformation")
    local = ((ld["amplitude_m"], ld["x_m"], ld["y_m"], ld["width_m"]) if ld
             else (0.0, 0.0, 0.0, 1.0))
    return Reflector(float(telescope.focal_length_m),
                     s * np.asarray(gd["df_dg_m"] if gd else (0.0, 0.0, 0.0), float), modes,
                     s * zpg, th["df_dT_m_per_K"] if th else 0.0, th["reference_c"] if th else 15.0,
                     offset, tilt_r, tilt_t, bump, local)


# ----------------------------------------------------------------------------------------- pose


@dataclass(frozen=True)
class Pose:
    """Truth pose: ``X_tel = R_full x_s + t_tel``; fitted frame ``Ry(ry) Rx(rx)``, ``t_fit``."""

    g: np.ndarray
    t_tel: np.ndarray
    R_full: np.ndarray
    kappa_s: float
    kappa: float
    ry: float
    rx: float
    t_fit: np.ndarray


def scanner_pose(g: np.ndarray, cfg: SimConfig, rng: np.random.Generator | None = None) -> Pose:
    """Scanner z along gravity ``g`` (gimbal), heading ``kappa_s``, decomposed as ``Rz Ry Rx``."""
    g = np.asarray(g, float) / np.linalg.norm(g)
    R_align = np.asarray(rot_y(math.atan2(g[0], g[2])) @ rot_x(-math.asin(g[1])))
    ex, ey = cfg.gimbal_misalignment_rad
    R_full = R_align @ np.asarray(rot_x(ex) @ rot_y(ey) @ rot_z(cfg.kappa_s_rad))
    if cfg.t_tel_m is not None:
        t_tel = np.asarray(cfg.t_tel_m, float)
    else:
        jit = rng.normal(size=3) * cfg.pose_jitter_m if rng is not None else np.zeros(3)
        t_tel = np.asarray(cfg.pivot_m, float) + cfg.hang_m * g + jit
    kappa, ry, rx = (float(a) for a in decompose_zyx(jnp.asarray(R_full)))
    t_fit = np.asarray(rot_z(-kappa)) @ t_tel
    return Pose(g, t_tel, R_full, cfg.kappa_s_rad, kappa, ry, rx, t_fit)


def truth_model(params: Mapping[str, float], *, shift_window_s=(0.0, 0.0), osc_period_s=1.0,
                kappa_rad=0.0, aperture_radius_m=12.95) -> ParaboloidModel:
    """A model with no free unknowns: every parameter (fitted frame) fixed at its truth."""
    names = tuple(sorted(params))
    return ParaboloidModel(
        free=(), fixed_names=names,
        fixed_values=jnp.asarray([float(params[k]) for k in names], dtype=jnp.float64).reshape(-1),
        shift_window_s=jnp.asarray(shift_window_s, dtype=jnp.float64),
        osc_period_s=jnp.asarray(osc_period_s, dtype=jnp.float64),
        kappa_rad=jnp.asarray(kappa_rad, dtype=jnp.float64),
        aperture_radius_m=float(aperture_radius_m))


def model_from_truth(scan_truth: Mapping[str, Any]) -> ParaboloidModel:
    """The truth model of one scan of ``truth.json`` (its ``model_parameters``, without Zernike
    terms: those are part of the per-row ``deviation_m``)."""
    return truth_model(scan_truth["model_parameters"], shift_window_s=scan_truth["shift_window_s"],
                       osc_period_s=scan_truth["osc_period_s"], kappa_rad=scan_truth["kappa_rad"],
                       aperture_radius_m=scan_truth["aperture_radius_m"])


def _motion_parameters(eff, meta: ScanMeta, pose: Pose, grid: _Grid):
    """Model parameters (fitted frame) of the motion effects that apply to this scan."""
    p: dict[str, float] = {}
    window, period = (0.0, 0.0), 1.0
    to_fit = np.asarray(rot_z(-pose.kappa))

    def applies(e):
        return e["scans"] is None or meta.id in e["scans"]

    if (e := eff.get("impulsive_shift")) and applies(e) and meta.cycle == e["cycle"]:
        phi0 = math.radians(e["phi_deg"])
        if not grid.lo <= phi0 < grid.lo + math.pi:
            raise EffectError(f"effect impulsive_shift.phi_deg={e['phi_deg']:g} is not in cycle "
                              f"{meta.cycle}'s phi range [{math.degrees(grid.lo):g}, "
                              f"{math.degrees(grid.lo) + 180:g}) deg")
        window = ((phi0 - grid.lo) / grid.dphi * grid.line_period_s, e["duration_s"])
        u = np.asarray(e["direction"], float)
        d = to_fit @ (e["displacement_m"] * u / np.linalg.norm(u))
        p.update(shift_x=d[0], shift_y=d[1], shift_z=d[2])
    if (e := eff.get("oscillation")) and applies(e):
        a, ph = e["amplitude_rad"], e["phase_rad"]
        p[f"osc_s{e['axis']}"], p[f"osc_c{e['axis']}"] = a * math.cos(ph), a * math.sin(ph)
        period = e["period_s"]
    if (e := eff.get("drift")) and applies(e):
        u = np.asarray(e["direction"], float)
        d = to_fit @ (e["rate_m_s"] * u / np.linalg.norm(u))
        p.update(drift_tx=d[0], drift_ty=d[1], drift_tz=d[2])
        p[f"drift_r{e['axis']}"] = e["rate_rad_s"]
    return {k: float(v) for k, v in p.items()}, window, period


# ----------------------------------------------------------------------------------------- grid


@dataclass(frozen=True)
class _Grid:
    """Raw angular grid of one cycle, offset by half a step from the cycle and face boundaries."""

    cycle: int
    lo: float
    n_phi: int
    dphi: float
    n_theta: int
    dtheta: float
    line_period_s: float

    @classmethod
    def make(cls, cycle: int, step: float, cfg: SimConfig) -> _Grid:
        n_phi, n_th = max(1, round(math.pi / step)), max(2, 2 * round(math.pi / step))
        T = cfg.line_period_s if cfg.duration_s is None else cfg.duration_s / n_phi
        return cls(cycle, 0.0 if cycle == 1 else math.pi, n_phi, math.pi / n_phi, n_th,
                   2 * math.pi / n_th, T)

    def block(self, j0: int, j1: int, R_full: np.ndarray, cos_max: float):
        """Rays of lines ``j0 .. j1-1`` within the cast cone: raw phi, theta, time (time order)."""
        j = np.arange(j0, j1)
        phi = self.lo + (j + 0.5) * self.dphi
        theta = (np.arange(self.n_theta) + 0.5) * self.dtheta
        st, ct = np.sin(theta), np.cos(theta)
        uz = (R_full[2, 0] * np.sin(phi)[:, None] * st + R_full[2, 1] * np.cos(phi)[:, None] * st
              + R_full[2, 2] * ct)
        jj, kk = np.nonzero(-uz >= cos_max)
        t = (j[jj] + theta[kk] / (2 * math.pi)) * self.line_period_s
        return phi[jj], theta[kk], t


# ----------------------------------------------------------------------------- ray solve (JAX)


class _Surface(eqx.Module):
    """True normal deviation (m) of the reflector at a fitted-frame point, and its panel id."""

    kappa: Array
    edges: Array
    counts: Array
    offset: Array
    tilt_r: Array
    tilt_t: Array
    rho_c: Array
    psi_c: Array
    zern: Array
    bump: Array
    aperture: float = eqx.field(static=True)
    modes: tuple[int, ...] = eqx.field(static=True)
    extra: Callable | None = eqx.field(static=True, default=None)

    def __call__(self, X: Array) -> tuple[Array, Array]:
        Xt = rot_z(self.kappa) @ X
        rho = jnp.hypot(Xt[0], Xt[1])
        psi = jnp.mod(jnp.arctan2(Xt[1], Xt[0]), 2 * jnp.pi)
        panel = panel_ids(rho, psi, self.edges, self.counts, xp=jnp).astype(jnp.int32)
        dev = panel_deviation(rho, psi, panel, self.offset, self.tilt_r, self.tilt_t,
                              self.rho_c, self.psi_c)
        if self.modes:
            dev = dev + zernike_deviation(rho / self.aperture, psi, self.zern, self.modes)
        for b in self.bump:  # rows (amplitude, x, y, width): the catalog's local_deformation
            dev = dev + local_deformation(Xt[0], Xt[1], b[1], b[2], b[0], b[3])
        if self.extra is not None:
            dev = dev + self.extra(Xt)
        return dev, panel


def _bumps(refl: Reflector) -> np.ndarray:
    """Rows ``(amplitude, x, y, width)`` (m) of the reflector's local deformations: the
    ``unexplained`` bump (given by rho, psi) and the catalog's ``local_deformation``."""
    a, rho, psi, w = refl.bump
    return np.array([[a, rho * math.cos(psi), rho * math.sin(psi), w], list(refl.local)], float)


def _surface(tel, refl: Reflector, kappa: float, zern: np.ndarray, extra) -> _Surface:
    f64 = lambda a: jnp.asarray(a, dtype=jnp.float64)  # noqa: E731
    if tel.ring_edges_m is None:
        edges, counts, geo = [np.inf, np.inf], [1], {"rho_c": [0.0], "psi_c": [0.0]}
    else:
        edges, counts = tel.ring_edges_m, tel.panels_per_ring
        geo = panel_geometry(edges, counts)
    keep = [i for i, c in enumerate(zern) if c != 0.0]
    return _Surface(f64(kappa), f64(edges), f64(counts), f64(refl.offset_m),
                    f64(refl.tilt_radial_rad), f64(refl.tilt_tangential_rad),
                    f64(geo["rho_c"]), f64(geo["psi_c"]),
                    f64(np.asarray(zern)[keep]), f64(_bumps(refl)), tel.diameter_m / 2,
                    tuple(refl.zernike_modes[i] for i in keep), extra)


@cached_jit
def _solve_rays(model: ParaboloidModel, surface: _Surface, start: Array, phi, theta, time,
                n_outer: int, n_inner: int):
    """Newton on the raw range of every ray so that the truth model's condition is zero.

    ``start = (R (9), t (3), f)`` of the ideal pose gives the initial range (ray-paraboloid
    quadratic). Returns range, deviation, panel, residual, hit point and the points at r = 1
    and r = 11 m (fitted frame), which define the ray for the occluders.
    """
    x = jnp.zeros(0)
    R, o, f = start[:9].reshape(3, 3), start[9:12], start[12]

    def one(ph, th, tt):
        u = R @ polar_to_cartesian(1.0, ph, th)
        a = u[0] ** 2 + u[1] ** 2
        b = 2 * (o[0] * u[0] + o[1] * u[1]) - 4 * f * u[2]
        c = o[0] ** 2 + o[1] ** 2 - 4 * f * o[2]
        r0 = -2 * c / (b + jnp.sqrt(jnp.maximum(b * b - 4 * a * c, 0.0)))
        lc = lambda r, dev: (jnp.stack([r, ph, th]), jnp.stack([tt, dev]))  # noqa: E731

        def F(r, dev):
            obs, c_ = lc(r, dev)
            return model(obs, x, c_)

        vg = jax.value_and_grad(F)

        def newton(_, rd):
            F, dF = vg(*rd)
            return rd[0] - F / dF, rd[1]

        def outer(_, carry):
            r, dev, _ = carry
            obs, c_ = lc(r, dev)
            dev, panel = surface(model.telescope_point(obs, x, c_))
            r, _ = jax.lax.fori_loop(0, n_inner, newton, (r, dev))
            return r, dev, panel

        r, dev, panel = jax.lax.fori_loop(0, n_outer, outer, (r0, jnp.zeros_like(r0),
                                                               jnp.array(-1, jnp.int32)))
        obs, c_ = lc(r, dev)
        A = model.telescope_point(lc(jnp.ones_like(r), dev)[0], x, c_)
        B = model.telescope_point(lc(jnp.full_like(r, 11.0), dev)[0], x, c_)
        return r, dev, panel, model(obs, x, c_), model.telescope_point(obs, x, c_), A, B

    return jax.vmap(one)(phi, theta, time)


def _solve_chunked(model, surface, start, phi, theta, time, cfg: SimConfig):
    """Solve in fixed-size chunks (one compilation, bounded memory); NumPy outputs."""
    n, m = len(phi), cfg.chunk_rays
    if n == 0:  # keep the shapes: solve one dummy ray
        return [a[:0] for a in _solve_chunked(model, surface, start, np.ones(1), np.ones(1),
                                              np.zeros(1), cfg)]
    outs = []
    for i in range(0, n, m):
        sl = [np.pad(a[i:i + m], (0, max(0, i + m - n)), mode="edge") for a in (phi, theta, time)]
        res = _solve_rays(model, surface, start, *(jnp.asarray(a, jnp.float64) for a in sl),
                          cfg.newton_outer, cfg.newton_inner)
        outs.append([np.asarray(a)[: min(m, n - i)] for a in res])
    return [np.concatenate(c) for c in zip(*outs)]


# ------------------------------------------------------------------------- occluders (NumPy)


def _cone_range(A, d, cfg: SimConfig, Rb: float) -> np.ndarray:
    """Raw range at which the line ``A + (r - 1) d`` enters the truncated cone (inf: never)."""
    H, k = cfg.cone_height_m, (cfg.cone_top_radius_m - Rb) / cfg.cone_height_m
    q, qd = Rb + k * A[:, 2], k * d[:, 2]
    a = d[:, 0] ** 2 + d[:, 1] ** 2 - qd**2
    a = np.where(np.abs(a) < 1e-12, 1e-12, a)
    b = 2 * (A[:, 0] * d[:, 0] + A[:, 1] * d[:, 1] - q * qd)
    c = A[:, 0] ** 2 + A[:, 1] ** 2 - q**2
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    best = np.full(len(A), np.inf)
    for s in ((-b - sq) / (2 * a), (-b + sq) / (2 * a)):
        z = A[:, 2] + s * d[:, 2]
        best = np.where((disc >= 0) & (s > 0) & (z >= 0) & (z <= H), np.minimum(best, s), best)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (H - A[:, 2]) / d[:, 2]
    top = np.hypot(A[:, 0] + s * d[:, 0], A[:, 1] + s * d[:, 1]) <= cfg.cone_top_radius_m
    best = np.where(np.isfinite(s) & (s > 0) & top, np.minimum(best, s), best)
    return 1.0 + best


def _leg_ranges(A, d, feet, apex, cfg: SimConfig, step: float):
    """Raw ranges of the first quadrupod hit and of a silhouette graze (inf: none)."""
    R = cfg.leg_radius_m
    hit, sil = np.full(len(A), np.inf), np.full(len(A), np.inf)
    dn = np.linalg.norm(d, axis=1)
    for F in feet:
        e = apex - F
        L = np.linalg.norm(e)
        e = e / L
        w = A - F
        de, we = d @ e, w @ e
        dp, wp = d - de[:, None] * e, w - we[:, None] * e
        a = np.maximum(np.sum(dp * dp, 1), 1e-300)
        b, c = 2 * np.sum(wp * dp, 1), np.sum(wp * wp, 1)
        disc = b * b - 4 * a * (c - R * R)
        s1 = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
        ok = (disc > 0) & (s1 > 0) & (we + s1 * de >= 0) & (we + s1 * de <= L)
        hit = np.where(ok, np.minimum(hit, 1 + s1), hit)
        s2 = -b / (2 * a)
        dmin = np.sqrt(np.maximum(c - b * b / (4 * a), 0.0))
        ax = we + s2 * de
        graze = ((dmin > R) & (dmin < R + 0.5 * step * (1 + s2) * dn) & (s2 > 0) & (ax >= 0)
                 & (ax <= L))
        sil = np.where(graze, np.minimum(sil, 1 + s2), sil)
    return hit, sil


# ---------------------------------------------------------------------------------- one block


def _block(phi, theta, time, ctx) -> dict[str, np.ndarray]:
    """Cast, occlude, scatter and label the rays of one block; rows of returned points only."""
    cfg, tel, rng, scatter, step = ctx["cfg"], ctx["tel"], ctx["rng"], ctx["scatter"], ctx["step"]
    r, dev, panel, F, X, A, B = _solve_chunked(ctx["model"], ctx["surface"], ctx["start"],
                                               phi, theta, time, cfg)
    Rz = np.asarray(rot_z(ctx["kappa"]))
    X, A, B = X @ Rz.T, A @ Rz.T, B @ Rz.T
    d = (B - A) / 10.0  # the ray per metre of raw range
    rho = np.hypot(X[:, 0], X[:, 1])
    R_rim, Rb = tel.diameter_m / 2, tel.cone_radius_m
    ok = np.isfinite(r) & (r > 0)
    n = len(r)
    r_cone = _cone_range(A, d, cfg, Rb)
    r_leg, r_sil = _leg_ranges(A, d, ctx["feet"], ctx["apex"], cfg, step)
    r_dish = np.where(ok & (rho <= R_rim), r, np.inf)
    r_occ = np.minimum(r_cone, r_leg)
    cls = np.full(n, 255, np.uint8)  # 255: no return
    occl = r_occ < r_dish
    exact = np.abs(F) < EXACT_M  # a ray whose Newton solve failed never becomes a truth point
    refl = ok & exact & ~occl & (rho >= Rb) & (rho <= R_rim)
    cls[refl] = CLASSES["reflector"]
    hole = ok & ~occl & (rho < Rb)  # nothing but the cone inside its radius
    rr = np.where(refl, r, np.nan)
    if scatter:
        cls[occl] = np.where(r_cone[occl] <= r_leg[occl], CLASSES["cone"], CLASSES["quadrupod"])
        rr[occl] = r_occ[occl]
        cls[hole], rr[hole] = CLASSES["cone"], r[hole]
        u_bg, u_mix, w = rng.random(n), rng.random(n), rng.uniform(0.1, 0.9, n)
        far = rng.uniform(*cfg.background_range_m, n)
        bg = ~occl & ~refl & ~hole & (u_bg < cfg.background_prob)  # terrain beyond the rim
        cls[bg], rr[bg] = CLASSES["background"], far[bg]
        m_rim = 0.5 * step * np.where(ok, r, 0.0)  # half the footprint spacing at the rim
        rim = ok & ~occl & (np.abs(rho - R_rim) < m_rim) & (u_mix < cfg.mixed_prob)
        cls[rim], rr[rim] = CLASSES["mixed"], (r + w * (far - r))[rim]
        leg_mix = refl & (r_sil < r) & (u_mix < cfg.mixed_prob)
        rs = r_sil[leg_mix]
        cls[leg_mix], rr[leg_mix] = CLASSES["mixed"], rs + w[leg_mix] * (r[leg_mix] - rs)
        mp = (cls == CLASSES["reflector"]) & (rng.random(n) < cfg.multipath_fraction)
        rr[mp] = r[mp] + rng.uniform(*cfg.multipath_range_m, n)[mp]
        cls[mp] = CLASSES["multipath"]
    keep = cls != 255
    surf = keep & ((cls == CLASSES["reflector"]) | (cls == CLASSES["multipath"]))
    P = np.where(surf[:, None], X, A + (np.nan_to_num(rr, nan=1.0) - 1.0)[:, None] * d)
    nrm = np.stack([-X[:, 0] / (2 * ctx["f"]), -X[:, 1] / (2 * ctx["f"]), np.ones(n)], 1)
    cos_inc = np.abs(np.sum(nrm * d, 1)) / (np.linalg.norm(nrm, axis=1) * np.linalg.norm(d, axis=1))
    base = np.select(
        [surf & (cls == 0), cls == 5, cls == 1, cls == 2, cls == 3],
        [0.2 + 0.7 * cos_inc * np.exp(-(r - 5.0) / 60.0), 0.1 + 0.3 * cos_inc, 0.45, 0.35,
         0.05 + 0.2 * rng.random(n)], 0.3)
    inten = np.clip(base + cfg.intensity_sigma * rng.normal(size=n), 0.0, 1.0)
    return {"range_true_m": rr[keep], "phi_true_rad": phi[keep], "theta_true_rad": theta[keep],
            "time_s": time[keep], "intensity": inten[keep].astype(np.float32), "cls": cls[keep],
            "panel": np.where(surf, panel, -1)[keep].astype(np.int16),
            "deviation_m": np.where(surf, dev, np.nan)[keep], "X": P[keep, 0], "Y": P[keep, 1],
            "Z": P[keep, 2], "incidence_rad": np.where(surf, np.arccos(np.clip(cos_inc, 0, 1)),
                                                       np.nan)[keep],
            "condition_m": np.where(refl, F, np.nan)[keep],
            "n_inexact": np.array([np.sum(ok & ~exact & ~occl & (rho >= Rb) & (rho <= R_rim))])}


# ----------------------------------------------------------------------------------- one scan


def _add_noise(lab, cycle: int, scanner, rng, noise: bool):
    """Raw observations = truth + Gaussian noise (campaign sigmas); angles kept in range."""
    n = len(lab["range_true_m"])
    e = rng.normal(size=(3, n)) * np.array([[scanner.sigma_range_m], [scanner.sigma_angle_rad],
                                            [scanner.sigma_angle_rad]]) * noise
    lo = 0.0 if cycle == 1 else math.pi
    phi = np.clip(lab["phi_true_rad"] + e[1], lo, np.nextafter(lo + math.pi, lo))
    th0 = lab["theta_true_rad"]
    f2 = th0 > math.pi
    theta = np.clip(th0 + e[2], np.where(f2, math.pi, 0.0) + 1e-12,
                    np.where(f2, 2 * math.pi, math.pi) - 1e-12)
    return ScanData(lab["range_true_m"] + e[0], phi, theta, lab["intensity"], lab["time_s"],
                    np.arange(n))


def _simulate(meta: ScanMeta, camp: Campaign, refl: Reflector, eff, cfg: SimConfig, scatter: bool,
              step: float, seed: int, scan_index: int, pose: Pose, extra) -> tuple:
    """One scan: truth model, grid blocks cast and labelled, noise; ``(data, labels, truth)``."""
    tel = camp.telescope
    g = pose.g
    f, f_grav = refl.focal_length(g, meta.temperature_c)
    grid = _Grid.make(meta.cycle, step, cfg)
    inst = {k: v for k, v in eff.items() if k in INSTRUMENT}
    motion, window, period = _motion_parameters(eff, meta, pose, grid)
    params = {"tx": pose.t_fit[0], "ty": pose.t_fit[1], "tz": pose.t_fit[2], "rx": pose.rx,
              "ry": pose.ry, "f": f, **inst, **motion}
    model = truth_model(params, shift_window_s=window, osc_period_s=period, kappa_rad=pose.kappa,
                        aperture_radius_m=tel.diameter_m / 2)
    zern = refl.zernike(g)
    R_fit = np.asarray(rot_y(pose.ry) @ rot_x(pose.rx))
    R_rim = tel.diameter_m / 2
    z_rim = R_rim**2 / (4 * tel.focal_length_m)
    alpha = math.atan2(R_rim + math.hypot(*pose.t_tel[:2]), pose.t_tel[2] - z_rim)
    cos_max = math.cos(min(math.pi, alpha + math.radians(cfg.margin_deg)))
    az = np.radians(tel.quadrupod_azimuths_deg or ())
    rf = cfg.leg_foot_radius_m
    ctx = dict(cfg=cfg, tel=tel, scatter=scatter, step=step, model=model, kappa=pose.kappa, f=f,
               surface=_surface(tel, refl, pose.kappa, zern, extra),
               start=jnp.asarray(np.concatenate([R_fit.ravel(), pose.t_fit, [f]]), jnp.float64),
               feet=np.stack([rf * np.cos(az), rf * np.sin(az),
                              np.full(len(az), rf**2 / (4 * tel.focal_length_m))], 1),
               apex=np.array([0.0, 0.0, cfg.leg_apex_z_m]),
               rng=np.random.default_rng(np.random.SeedSequence([seed, 1, scan_index])))
    lines = max(1, cfg.block_candidates // grid.n_theta)
    parts = [_block(*grid.block(j, min(j + lines, grid.n_phi), pose.R_full, cos_max), ctx)
             for j in range(0, grid.n_phi, lines)]
    lab = {k: np.concatenate([p.pop(k) for p in parts]) for k in list(parts[0])}  # frees blocks
    noise_rng = np.random.default_rng(np.random.SeedSequence([seed, 2, scan_index]))
    data = _add_noise(lab, meta.cycle, camp.scanner, noise_rng, cfg.noise)
    lab["row"] = np.arange(len(data))
    cond, n_inexact = lab.pop("condition_m"), int(lab.pop("n_inexact").sum())
    counts = {k: int(np.sum(lab["cls"] == v)) for k, v in CLASSES.items()}
    truth = {
        "id": meta.id, "position": meta.position, "cycle": meta.cycle,
        "temperature_c": meta.temperature_c,
        **{k: float(params[k]) for k in ("tx", "ty", "tz", "rx", "ry", "f")},
        "kappa_rad": pose.kappa, "f_gravity": f_grav,
        "instrument": inst, "motion": motion,
        "zernike": {f"{ZERNIKE_PREFIX}{j}": float(c) for j, c in zip(refl.zernike_modes, zern)},
        "model_parameters": {k: float(v) for k, v in params.items()},
        "shift_window_s": [float(w) for w in window], "osc_period_s": float(period),
        "aperture_radius_m": tel.diameter_m / 2,
        "t_tel": pose.t_tel.tolist(), "kappa_s": pose.kappa_s, "R_full": pose.R_full.tolist(),
        "g": g.tolist(), "step_rad": step, "line_period_s": grid.line_period_s,
        "n_lines": grid.n_phi, "n_rows": len(data), "class_counts": counts,
        "max_abs_condition_m": float(np.nanmax(np.abs(cond), initial=0.0)),
        "n_rays_not_converged": n_inexact,
    }
    return data, lab, truth


# ------------------------------------------------------------------------------- public API


def _preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name]


def _setup(preset: str, effects, step_rad, campaign, config, seed):
    ps = _preset(preset)
    eff = normalize_effects({**ps.effects, **(effects or {})})
    cfg = config or SimConfig()
    camp = campaign or default_campaign()
    step = float(step_rad or (campaign.scanner.angular_step_rad if campaign else ps.step_rad))
    camp = dataclasses.replace(camp, scanner=dataclasses.replace(camp.scanner,
                                                                 angular_step_rad=step))
    scatter = ps.scatter if cfg.scatter is None else cfg.scatter
    return ps, eff, cfg, camp, step, scatter, make_reflector(camp.telescope, eff, seed)


def _position_pose(meta, camp, cfg, seed, index) -> Pose:
    g = pointing_gravity(meta, camp.telescope, camp.site)
    return scanner_pose(g, cfg, np.random.default_rng(np.random.SeedSequence([seed, 3, index])))


def simulate_scan(meta: ScanMeta | None = None, *, campaign: Campaign | None = None,
                  preset: str = "demo", effects: Mapping[str, Any] | None = None, seed: int = 0,
                  step_rad: float | None = None, config: SimConfig | None = None,
                  scan_index: int = 0, position_index: int = 0,
                  extra_deviation: Callable[[Array], Array] | None = None,
                  ) -> tuple[ScanData, dict[str, np.ndarray], dict[str, Any]]:
    """Simulate one scan in memory: ``(ScanData, labels, truth)``.

    ``meta`` defaults to cycle 1 of the preset's first position. ``labels`` holds per-row truth
    (``cls``, ``panel``, ``deviation_m``, telescope-frame ``X Y Z`` and the noiseless
    ``range_true_m phi_true_rad theta_true_rad``); ``truth`` the scan's entry of ``truth.json``.
    ``extra_deviation(X_tel (3,)) -> m`` adds a user-defined normal deviation (JAX function).
    """
    ps, eff, cfg, camp, step, scatter, refl = _setup(preset, effects, step_rad, campaign,
                                                     config, seed)
    if meta is None:
        name, ha, dec = ps.positions[0]
        meta = ScanMeta(f"{name}c1", name, 1, f"scans/{name}c1.parquet", ha, dec)
    pose = _position_pose(meta, camp, cfg, seed, position_index)
    return _simulate(meta, camp, refl, eff, cfg, scatter, step, seed, scan_index, pose,
                     extra_deviation)


def _positions(spec, preset: Preset) -> list[dict[str, Any]]:
    out = []
    for i, p in enumerate(spec if spec is not None else (preset.plan or preset.positions)):
        d = dict(p) if isinstance(p, Mapping) else dict(zip(("position", "ha_deg", "dec_deg"), p))
        d.setdefault("temperature_c", round(18.0 - 0.4 * i, 2))
        d.setdefault("tour", "red")
        out.append(d)
    return out


class _LazyScans(Mapping):
    """Scans simulated when ``write_campaign`` asks for them: one scan in memory at a time."""

    def __init__(self, make: Callable[[str], ScanData], ids: Sequence[str]):
        self.make, self.ids = make, list(ids)

    def __contains__(self, key):
        return key in self.ids

    def __getitem__(self, key):
        if key not in self.ids:
            raise KeyError(key)
        return self.make(key)

    def __iter__(self) -> Iterator[str]:
        return iter(self.ids)

    def __len__(self):
        return len(self.ids)


def _write_truth_table(path: pathlib.Path, lab: Mapping[str, np.ndarray]) -> None:
    import pyarrow as pa

    cols = ["row", "cls", "panel", "deviation_m", "X", "Y", "Z", "range_true_m", "phi_true_rad",
            "theta_true_rad", "time_s", "incidence_rad"]
    write_table(pa.table({c: lab[c] for c in cols}), path)


def simulate_campaign(out_dir, preset: str = "demo", effects: Mapping[str, Any] | None = None,
                      seed: int = 0, positions: Sequence | None = None,
                      step_rad: float | None = None, *, cycles: Sequence[int] = (1, 2),
                      config: SimConfig | None = None, campaign: Campaign | None = None,
                      extra_deviation: Callable[[Array], Array] | None = None) -> Campaign:
    """Simulate a campaign: ``campaign.toml``, ``scans/<id>.parquet``, ``truth.json`` and
    ``truth/<id>.parquet`` under ``out_dir``; returns the written (re-loaded) campaign.

    ``positions``: ``(name, ha_deg, dec_deg)`` tuples or dicts with ``position`` and the
    pointing keys of ``ScanMeta`` (optional ``temperature_c``, ``tour``); default: the
    preset's. ``effects`` update the preset's (see :func:`parse_effects`). Scans are simulated
    one at a time, the ray solve in chunks, so memory is bounded by one scan.
    """
    ps, eff, cfg, camp, step, scatter, refl = _setup(preset, effects, step_rad, campaign,
                                                     config, seed)
    out = pathlib.Path(out_dir)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    t0 = dt.datetime(2024, 4, 8, 18, 0, tzinfo=dt.UTC)
    metas, poses, pos_truth = [], {}, []
    for i, p in enumerate(_positions(positions, ps)):
        keys = {k: p[k] for k in ("ha_deg", "dec_deg", "elevation_deg", "azimuth_deg", "tour",
                                  "temperature_c") if k in p}
        for c in cycles:
            sid = f"{p['position']}c{c}"
            # a plan gives start times and temperatures per cycle: {cycle: value}
            start = (p.get("start") or {}).get(c, t0 + dt.timedelta(minutes=8 * i + 4 * (c - 1)))
            ck = {**keys, "temperature_c": (p.get("temperature") or {}).get(
                c, keys.get("temperature_c"))}
            metas.append(ScanMeta(sid, p["position"], int(c), f"scans/{sid}.parquet",
                                  start=start, **ck))
        pose = _position_pose(metas[-1], camp, cfg, seed, i)
        poses[p["position"]] = pose
        f, fg = refl.focal_length(pose.g, p.get("temperature_c"))
        pos_truth.append({"position": p["position"], **{k: v for k, v in keys.items()},
                          "elevation_deg": pointing_elevation_deg(metas[-1], camp.telescope,
                                                                  camp.site),
                          "g": pose.g.tolist(), "f": f, "f_gravity": fg})
    camp = dataclasses.replace(camp, root=out, scans=tuple(metas))
    truths: dict[str, dict] = {}

    def make(sid: str) -> ScanData:
        k = [m.id for m in metas].index(sid)
        meta = metas[k]
        data, lab, truth = _simulate(meta, camp, refl, eff, cfg, scatter, step, seed, k,
                                     poses[meta.position], extra_deviation)
        _write_truth_table(out / "truth" / f"{sid}.parquet", lab)
        truths[sid] = {**truth, "truth_file": f"truth/{sid}.parquet"}
        return data

    def write_truth():  # before campaign.toml, which write_campaign writes last
        doc = {"schema": TRUTH_SCHEMA, "preset": ps.name, "seed": seed, "step_rad": step,
               "scatter": scatter, "classes": CLASSES, "effects": _jsonable(eff),
               "config": _jsonable(dataclasses.asdict(cfg)),
               "reflector": _jsonable(dataclasses.asdict(refl)),
               "scans": [truths[m.id] for m in metas], "positions": pos_truth}
        write_json_atomic(out / "truth.json", _jsonable(doc), indent=1)

    return write_campaign(out, camp, _LazyScans(make, [m.id for m in metas]),
                          before_toml=write_truth)


def _jsonable(v):
    if isinstance(v, Mapping):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_jsonable(x) for x in (v.tolist() if isinstance(v, np.ndarray) else v)]
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


__all__ = ["CLASSES", "EFFECT_DEFAULTS", "PRESETS", "TRUTH_SCHEMA", "EffectError", "Pose",
           "Preset", "Reflector", "SimConfig", "make_reflector", "model_from_truth",
           "normalize_effects", "parse_effects", "scanner_pose", "simulate_campaign",
           "simulate_scan", "truth_model"]
