"""THE catalog of physics (``shared/spec/physics.md``): every effect is defined here, once.

The simulator, the fitter and the diagnosis all call these functions; none of them re-states an
effect. Everything is pure ``jax.numpy`` on per-point arrays (any broadcastable shape), so it can
be differentiated, vmapped and jitted.

Units: metres, radians, seconds. Angles are the raw continuous two-face angles (phi in
[0, 2 pi), theta in [0, 2 pi)): every two-face-sensitive term changes sign between faces by
itself, no face flag is needed.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._programs import cached_jit
from ..geometry._geometry import polar_to_cartesian, zernike

# --------------------------------------------------------------------------------------------
# Instrument: calibration parameters (NIST / Muralikrishnan names)
# --------------------------------------------------------------------------------------------

_Term = Callable[[Array, Array, Array, Array], Array]  # (r, phi, theta, value) -> correction


@dataclass(frozen=True)
class InstrumentParameter:
    """One calibration parameter: its corrections to the raw observations.

    ``dr``, ``dphi``, ``dtheta`` map ``(r, phi, theta, value)`` to the additive correction of the
    range (m) and of the angles (rad), or are ``None`` where the parameter has no such term.
    ``phi_at_corrected_theta``: the seed's eq. 9 evaluates the phi term at the corrected theta.
    """

    name: str
    title: str
    unit: str
    dr: _Term | None
    dphi: _Term | None
    dtheta: _Term | None
    two_face: str
    explanation: str
    phi_at_corrected_theta: bool = False
    typical: float = 1e-4  # a typical magnitude, used for scaling and simulation presets


def _z(r, phi, theta, v):
    return jnp.zeros_like(r)


INSTRUMENT: dict[str, InstrumentParameter] = {
    p.name: p
    for p in [
        InstrumentParameter(
            "x1n", "beam offset, normal", "m", None,
            lambda r, ph, th, v: v / r,
            lambda r, ph, th, v: v * jnp.cos(th) / r,
            "theta part yes, phi part no",
            "offset of the beam from the rotation centre, normal to the beam: angular error "
            "falling off as 1/range",
            typical=2e-4,
        ),
        InstrumentParameter(
            "x1z", "beam offset, z", "m", None,
            lambda r, ph, th, v: v / (r * jnp.tan(th)),
            lambda r, ph, th, v: -v * jnp.sin(th) / r,
            "phi part yes",
            "offset of the beam along the standing axis: angular error falling off as 1/range",
            typical=2e-4,
        ),
        InstrumentParameter(
            "x2", "transit offset", "m",
            lambda r, ph, th, v: v * jnp.sin(th),
            None,
            lambda r, ph, th, v: v * jnp.cos(th) / r,
            "yes",
            "two-face-sensitive range error growing with sin(theta): transit offset",
            typical=2e-4,
        ),
        InstrumentParameter(
            "x3", "mirror offset", "m", None,
            lambda r, ph, th, v: v / (r * jnp.sin(th)),
            None,
            "yes",
            "horizontal-angle error falling off as 1/(range sin theta): mirror offset",
            typical=2e-4,
        ),
        InstrumentParameter(
            "x4", "vertical index offset", "rad", None, None,
            lambda r, ph, th, v: v * jnp.ones_like(th),
            "yes",
            "constant vertical-angle error that flips sign between faces: vertical index offset",
            typical=1e-4,
        ),
        InstrumentParameter(
            "x5n", "beam tilt, normal", "rad", None, None,
            lambda r, ph, th, v: v * jnp.cos(th),
            "yes",
            "vertical-angle error growing with cos(theta): beam tilt normal to the mirror",
            typical=5e-5,
        ),
        InstrumentParameter(
            "x5z", "beam tilt, z", "rad", None,
            lambda r, ph, th, v: v / jnp.tan(th),
            lambda r, ph, th, v: -v * jnp.sin(th),
            "phi part yes",
            "beam tilt along the standing axis: horizontal error as 1/tan(theta)",
            typical=5e-5,
        ),
        InstrumentParameter(
            "x6", "mirror tilt", "rad", None,
            lambda r, ph, th, v: 2 * v / jnp.sin(th),
            None,
            "yes",
            "horizontal-angle error as 2/sin(theta) that flips sign between faces: mirror tilt",
            phi_at_corrected_theta=True,
            typical=5e-5,
        ),
        InstrumentParameter(
            "x7", "horizontal (transit) axis error", "rad", None,
            lambda r, ph, th, v: v / jnp.tan(th),
            None,
            "yes",
            "horizontal-angle error as 1/tan(theta): the transit axis is not perpendicular to "
            "the standing axis",
            phi_at_corrected_theta=True,
            typical=5e-5,
        ),
        InstrumentParameter(
            "x8x", "horizontal encoder eccentricity, x", "rad", None,
            lambda r, ph, th, v: v * jnp.sin(ph),
            None,
            "yes",
            "horizontal-angle error varying as sin(phi): eccentric horizontal encoder",
            typical=5e-5,
        ),
        InstrumentParameter(
            "x8y", "horizontal encoder eccentricity, y", "rad", None,
            lambda r, ph, th, v: v * jnp.cos(ph),
            None,
            "yes",
            "horizontal-angle error varying as cos(phi): eccentric horizontal encoder",
            typical=5e-5,
        ),
        InstrumentParameter(
            "x10", "range offset", "m",
            lambda r, ph, th, v: v * jnp.ones_like(r),
            None, None,
            "no",
            "constant range error (additive constant of the rangefinder)",
            typical=1e-3,
        ),
        InstrumentParameter(
            "x11a", "horizontal encoder 2nd order, cos", "rad", None,
            lambda r, ph, th, v: v * jnp.cos(2 * ph),
            None,
            "no",
            "horizontal-angle error varying as cos(2 phi): second-order encoder error",
            typical=3e-5,
        ),
        InstrumentParameter(
            "x11b", "horizontal encoder 2nd order, sin", "rad", None,
            lambda r, ph, th, v: v * jnp.sin(2 * ph),
            None,
            "no",
            "horizontal-angle error varying as sin(2 phi): second-order encoder error",
            typical=3e-5,
        ),
        InstrumentParameter(
            "x12a", "vertical encoder 2nd order, cos", "rad", None, None,
            lambda r, ph, th, v: v * jnp.cos(2 * th),
            "no",
            "vertical-angle error varying as cos(2 theta): second-order encoder error",
            typical=3e-5,
        ),
        InstrumentParameter(
            "x12b", "vertical encoder 2nd order, sin", "rad", None, None,
            lambda r, ph, th, v: v * jnp.sin(2 * th),
            "no",
            "vertical-angle error varying as sin(2 theta): second-order encoder error",
            typical=3e-5,
        ),
        InstrumentParameter(
            "range_scale", "range scale error", "1",
            lambda r, ph, th, v: v * r,
            None, None,
            "no",
            "range error proportional to the range: scale error of the rangefinder",
            typical=1e-5,
        ),
    ]
}

OBJECT_PARAMETERS: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "f")
SIMPLIFIED: tuple[str, ...] = OBJECT_PARAMETERS
#: The instrument calibration the extended model adds: the defaults shared across scans in
#: joint fits, asked about by the sensitivity, and compared with the truth in the demo.
CALIBRATION: tuple[str, ...] = ("x4", "x6", "x7")
#: The calibration as a command-line default (``--shared``, ``--params``).
CALIBRATION_OPTION: str = ",".join(CALIBRATION)
EXTENDED: tuple[str, ...] = OBJECT_PARAMETERS + CALIBRATION

PARAMETER_UNITS: dict[str, str] = {
    "tx": "m", "ty": "m", "tz": "m", "rx": "rad", "ry": "rad", "f": "m",
    **{k: p.unit for k, p in INSTRUMENT.items()},
}


def instrument_corrections(
    r: ArrayLike, phi: ArrayLike, theta: ArrayLike, params: Mapping[str, ArrayLike]
) -> tuple[Array, Array, Array]:
    """Corrections ``(dr, dphi, dtheta)`` of every instrument parameter present in ``params``.

    Seed eq. 9: the corrections are added to the raw observations. The phi terms of ``x6`` and
    ``x7`` are evaluated at the corrected theta; all other terms at the raw observations.
    Parameters not in ``params`` are zero. Keys that are not instrument parameters are ignored.
    """
    r = jnp.asarray(r)
    phi = jnp.asarray(phi)
    theta = jnp.asarray(theta)
    dr = jnp.zeros_like(r)
    dphi = jnp.zeros_like(r)
    dtheta = jnp.zeros_like(r)
    late_phi = []
    for name, p in INSTRUMENT.items():
        if name not in params:
            continue
        v = params[name]
        if p.dr is not None:
            dr = dr + p.dr(r, phi, theta, v)
        if p.dtheta is not None:
            dtheta = dtheta + p.dtheta(r, phi, theta, v)
        if p.dphi is not None:
            if p.phi_at_corrected_theta:
                late_phi.append(p)
            else:
                dphi = dphi + p.dphi(r, phi, theta, v)
    theta_c = theta + dtheta
    for p in late_phi:
        dphi = dphi + p.dphi(r, phi, theta_c, params[p.name])
    return dr, dphi, dtheta


def correct_observations(
    r: ArrayLike, phi: ArrayLike, theta: ArrayLike, params: Mapping[str, ArrayLike]
) -> tuple[Array, Array, Array]:
    """Corrected observations ``(r + dr, phi + dphi, theta + dtheta)`` (seed eq. 9)."""
    dr, dphi, dtheta = instrument_corrections(r, phi, theta, params)
    return r + dr, phi + dphi, theta + dtheta


def face_signatures(names, r: np.ndarray, a: np.ndarray, theta0: np.ndarray):
    """Cartesian displacement (m) of each direction by a unit value of each parameter, split
    into the part that flips between the faces and the part common to both.

    The same direction (azimuth ``a``, nadir angle ``theta0``, range ``r``) is observed in face 1
    as ``(a, theta0)`` and in face 2 as ``(a + pi, 2 pi - theta0)``. Returns ``(odd, even)``,
    each of shape ``(len(names), 3 n)``: ``odd = (d1 - d2) / 2``, ``even = (d1 + d2) / 2``.
    """

    faces = [(a, theta0), (np.mod(a + np.pi, 2 * np.pi), 2 * np.pi - theta0)]
    d = [np.asarray(_displacements(tuple(names), np.asarray(r, float), np.asarray(phi, float),
                                   np.asarray(th, float))) for phi, th in faces]
    return (d[0] - d[1]) / 2, (d[0] + d[1]) / 2


@cached_jit
def _displacements(names: tuple[str, ...], r, phi, theta):
    """Per parameter of ``names``, the Cartesian displacement (m, raveled) of the
    observations ``(r, phi, theta)`` by a unit value, shape ``(len(names), 3 n)``: one program
    for all of them, loaded from disk in later processes (as eager operations, 0.13 s of
    lowering and loading a ``diagnose``)."""
    x0 = polar_to_cartesian(r, phi, theta)
    # linear in the value: a small value and a difference quotient give the column
    h = 1e-7
    return jnp.stack([((polar_to_cartesian(*correct_observations(r, phi, theta, {n: h})) - x0)
                       / h).ravel() for n in names])


def two_face_parameters(names=None) -> tuple[str, ...]:
    """The instrument parameters (among ``names``; None: the whole catalog) whose effect flips
    sign between the faces (``Effect.two_face``): a one-face recording cannot separate them
    from the pose and f."""
    names = INSTRUMENT if names is None else names
    return tuple(n for n in names if n in INSTRUMENT and INSTRUMENT[n].two_face != "no")


def inseparable_pairs(
    names, *, threshold: float = 0.9999, seed: int = 0
) -> list[tuple[str, str, float]]:
    """Pairs of instrument parameters that cannot be estimated together (same column shape).

    Two-face scans separate the instrument from the object through the part of each effect
    that flips between the faces; the part common to both faces is largely absorbed by the
    object parameters. A pair is refused when their face-flipping parts are proportional
    (e.g. ``x5z`` and ``x7``: the same phi term; x5z's theta term is common to both faces),
    or when their whole signatures are, on a generic sample of directions and ranges
    (``|correlation| >= threshold``). Returns ``(a, b, correlation)``.
    """
    inst = [n for n in names if n in INSTRUMENT]
    if len(inst) < 2:
        return []
    rng = np.random.default_rng(seed)
    m = 3000
    a = rng.uniform(0, 2 * np.pi, m)
    theta0 = rng.uniform(0.2, 1.3, m)
    r = rng.uniform(6.0, 15.0, m)
    odd, even = face_signatures(inst, r, a, theta0)
    full = np.concatenate([odd, even], axis=1)

    def corr(u, v):
        nu, nv = np.linalg.norm(u), np.linalg.norm(v)
        if nu < 1e-12 * u.size or nv < 1e-12 * v.size:
            return 0.0
        return float(u @ v / (nu * nv))

    out = []
    for i in range(len(inst)):
        for j in range(i + 1, len(inst)):
            for c in (corr(odd[i], odd[j]), corr(full[i], full[j])):
                if abs(c) >= threshold:
                    out.append((inst[i], inst[j], c))
                    break
    return out


# --------------------------------------------------------------------------------------------
# Motion of the scanner during a scan (pose perturbations as functions of time)
# --------------------------------------------------------------------------------------------
#
# A motion effect returns a small rotation vector ``w`` (rad, scanner frame) and a translation
# ``d`` (m, telescope frame) for every point; the scanner-frame point ``x`` then maps to the
# telescope frame as ``X = R (x + w x x) + t + d``.


def impulsive_shift(
    time_s: ArrayLike, start_s: ArrayLike, duration_s: ArrayLike, displacement_m: ArrayLike
) -> Array:
    """Translation (m, telescope frame) of a scanner displaced during ``[start, start + duration)``.

    The brake was not engaged or the telescope had not settled: a box function in time (the
    scan's time is its phi clock). Returns shape ``time_s.shape + (3,)``.
    """
    t = jnp.asarray(time_s)
    on = ((t >= start_s) & (t < start_s + duration_s)).astype(t.dtype)
    return on[..., None] * jnp.asarray(displacement_m)


def oscillation_sincos(time_s: ArrayLike, frequency_hz: ArrayLike, sin_rad: ArrayLike,
                       cos_rad: ArrayLike) -> Array:
    """Rotation vector (rad, scanner frame) of a gimbal swinging periodically during the scan,
    linear in its amplitudes: ``w(t) = s sin(2 pi f t) + c cos(2 pi f t)`` with ``s``, ``c``
    (3,) the sine and cosine amplitudes about the scanner axes (the model estimates them)."""
    om = 2 * jnp.pi * jnp.asarray(time_s) * frequency_hz
    return (jnp.sin(om)[..., None] * jnp.asarray(sin_rad)
            + jnp.cos(om)[..., None] * jnp.asarray(cos_rad))


def oscillation(
    time_s: ArrayLike, period_s: ArrayLike, amplitude_rad: ArrayLike, phase_rad: ArrayLike,
    axis: ArrayLike,
) -> Array:
    """Rotation vector (rad, scanner frame) of a gimbal swinging periodically during the scan.

    ``w(t) = amplitude sin(2 pi t / period + phase) * axis`` with ``axis`` a unit vector of the
    scanner frame (a gimbal swings about a horizontal axis: x or y); the same swing as
    :func:`oscillation_sincos` with ``s = amplitude cos(phase) axis``,
    ``c = amplitude sin(phase) axis``.
    """
    a = jnp.asarray(axis, dtype=float)
    return oscillation_sincos(time_s, 1.0 / period_s, amplitude_rad * jnp.cos(phase_rad) * a,
                              amplitude_rad * jnp.sin(phase_rad) * a)


def drift(time_s: ArrayLike, rate_m_s: ArrayLike, rate_rad_s: ArrayLike) -> tuple[Array, Array]:
    """Slow steady motion: rotation vector ``rate_rad_s * t`` (scanner frame) and translation
    ``rate_m_s * t`` (telescope frame). Returns ``(w, d)``."""
    t = jnp.asarray(time_s)[..., None]
    return t * jnp.asarray(rate_rad_s, dtype=float), t * jnp.asarray(rate_m_s, dtype=float)


def apply_pose(
    x_s: Array, R: Array, t: Array, w: Array | None = None, d: Array | None = None
) -> Array:
    """Telescope-frame point ``R (x + w x x) + t + d`` of scanner-frame points ``x_s`` (..., 3)."""
    if w is not None:
        x_s = x_s + jnp.cross(w, x_s)
    X = x_s @ R.T + t
    if d is not None:
        X = X + d
    return X


# --------------------------------------------------------------------------------------------
# Reflector: deformations as a normal deviation (m, positive towards the focus)
# --------------------------------------------------------------------------------------------


def panel_deviation(
    rho: ArrayLike, psi: ArrayLike, panel: ArrayLike,
    offset_m: ArrayLike, tilt_radial_rad: ArrayLike, tilt_tangential_rad: ArrayLike,
    rho_c: ArrayLike, psi_c: ArrayLike,
) -> Array:
    """Normal deviation (m) of points on displaced or tilted panels.

    Each panel ``k`` is shifted by ``offset_m[k]`` along the normal and tilted about its centre
    ``(rho_c[k], psi_c[k])``: ``tilt_radial`` raises its outer edge, ``tilt_tangential`` its
    counter-clockwise edge. ``panel`` holds the panel id of each point (-1: no panel).
    """
    panel = jnp.asarray(panel)
    ok = panel >= 0
    k = jnp.where(ok, panel, 0)
    dpsi = jnp.mod(jnp.asarray(psi) - jnp.asarray(psi_c)[k] + jnp.pi, 2 * jnp.pi) - jnp.pi
    dev = (
        jnp.asarray(offset_m)[k]
        + jnp.asarray(tilt_radial_rad)[k] * (rho - jnp.asarray(rho_c)[k])
        + jnp.asarray(tilt_tangential_rad)[k] * jnp.asarray(rho_c)[k] * dpsi
    )
    return jnp.where(ok, dev, 0.0)


DEFAULT_ZERNIKE_MODES: tuple[int, ...] = (4, 5, 6, 7, 8, 11)  # Noll: defocus, astig, coma, sph.


def zernike_deviation(u: ArrayLike, psi: ArrayLike, coefficients_m: ArrayLike,
                      modes: tuple[int, ...] = DEFAULT_ZERNIKE_MODES) -> Array:
    """Normal deviation (m) ``sum_k c_k Z_{j_k}(u, psi)``, ``u = rho / aperture radius``."""
    c = jnp.asarray(coefficients_m)
    out = jnp.zeros_like(jnp.asarray(u, dtype=float))
    for i, j in enumerate(modes):
        out = out + c[i] * zernike(j, u, psi)
    return out


def gravity_focal_length(f0_m: ArrayLike, df_dg_m: ArrayLike, g: ArrayLike) -> Array:
    """Focal length (m) linear in the gravity vector (telescope frame): ``f = f0 + c . g``.

    ``df_dg_m`` (3,) is the change of focal length per unit gravity component. ``f0`` is the
    focal length without gravity load; at the zenith ``g = (0, 0, -1)`` and ``f = f0 - c_z``
    (the simulator sets ``f0 = nominal + c_z`` so that the zenith gives the nominal value).
    """
    return f0_m + jnp.dot(jnp.asarray(df_dg_m), jnp.asarray(g))


def gravity_zernike_coefficients(coeff_per_g_m: ArrayLike, g: ArrayLike) -> Array:
    """Zernike coefficients (m) linear in gravity: ``c_k = C[k] . g`` with ``C`` shape (K, 3)."""
    return jnp.asarray(coeff_per_g_m) @ jnp.asarray(g)


def thermal_focal_length(f0_m: ArrayLike, df_dT_m_per_K: ArrayLike, temperature_c: ArrayLike,
                         reference_c: float = 15.0) -> Array:
    """Focal length (m) linear in temperature: ``f = f0 + df/dT (T - T_ref)``."""
    return f0_m + df_dT_m_per_K * (temperature_c - reference_c)


LOCAL_DEFORMATION_PARAMETERS: tuple[str, ...] = ("x_m", "y_m", "amplitude_m", "width_m")


def local_deformation(x: ArrayLike, y: ArrayLike, x0_m: ArrayLike, y0_m: ArrayLike,
                      amplitude_m: ArrayLike, width_m: ArrayLike) -> Array:
    """Normal deviation (m, positive towards the focus) of a smooth local bump or dent.

    ``a exp(-d^2 / (2 w^2))`` with ``d`` the distance of the aperture-plane point ``(x, y)``
    (reflector frame, m) from the centre ``(x0_m, y0_m)``; ``amplitude_m`` is ``a`` (+ towards
    the focus: a bump; - a dent), ``width_m`` is ``w`` (the Gaussian's standard deviation, m).
    Actuators pushed, a damaged or loose panel, a load. The simulator builds it into the
    surface, the fitter models it (``bump_*`` parameters of :mod:`hartrao_jax.model`) and the
    diagnosis searches for it, all through this function.
    """
    dx = jnp.asarray(x) - x0_m
    dy = jnp.asarray(y) - y0_m
    return amplitude_m * jnp.exp(-(dx * dx + dy * dy) / (2.0 * width_m * width_m))


def paraboloid_condition(X: Array, f: ArrayLike, deviation_m: ArrayLike = 0.0) -> Array:
    """Seed eq. 5 with an optional modelled deviation: ``(X^2+Y^2)/4f - Z + dev * s(rho)``.

    Zero on the (deformed) surface; positive below it (away from the focus).
    """
    rho2 = X[..., 0] ** 2 + X[..., 1] ** 2
    F = rho2 / (4.0 * f) - X[..., 2]
    return F + deviation_m * jnp.sqrt(1.0 + rho2 / (4.0 * f * f))


# --------------------------------------------------------------------------------------------
# The catalog of effects (ids of physics.md): what the diagnosis names and the prover simulates
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Effect:
    id: str
    family: str  # instrument | motion | reflector | generic
    title: str
    explanation: str
    signature: str  # how it shows: "two-face", "time", "common to both cycles", ...


EFFECTS: dict[str, Effect] = {
    **{
        k: Effect(k, "instrument", p.title, p.explanation,
                  "flips sign between faces" if p.two_face != "no" else "same in both faces")
        for k, p in INSTRUMENT.items()
    },
    "impulsive_shift": Effect(
        "impulsive_shift", "motion", "impulsive shift",
        "the scanner was displaced for a short time (brake not engaged or telescope not settled): "
        "a jump of the residuals along one horizontal angle", "time (one phi range)"),
    "oscillation": Effect(
        "oscillation", "motion", "oscillation",
        "the gimbal swung periodically during the scan: residuals periodic in time",
        "time (periodic)"),
    "drift": Effect(
        "drift", "motion", "drift",
        "slow steady motion of the scanner during the scan: residuals growing linearly in time",
        "time (linear)"),
    "panel_offset": Effect(
        "panel_offset", "reflector", "panel offsets and tilts",
        "individual panels displaced or tilted: residuals constant per panel and common to both "
        "cycles", "common to both cycles, per panel"),
    "gravity_deformation": Effect(
        "gravity_deformation", "reflector", "gravity deformation",
        "elastic sag linear in the gravity vector: focal length and low-order surface modes "
        "change with the pointing", "across positions, with g"),
    "local_deformation": Effect(
        "local_deformation", "reflector", "local deformation",
        "a smooth local bump or dent of the surface (actuators pushed, a damaged or loose panel, "
        "a load): a Gaussian normal deviation a exp(-d^2 / 2 w^2) around a centre in the "
        "aperture plane", "common to both cycles, compact on the dish"),
    "thermal": Effect(
        "thermal", "reflector", "thermal expansion",
        "focal length changing linearly with temperature", "across scans, with temperature"),
    "unexplained": Effect(
        "unexplained", "generic", "unexplained structure",
        "significant residual structure that no catalog entry explains", "anywhere"),
}
