"""Functional models: a list of catalog names (+ fixed values) -> the condition of one point.

A model is data (an ``eqx.Module``) and callable as the Gauss-Helmert condition
``F(l, x, c)`` with ``l = (r, phi, theta)`` raw observations, ``x`` the free unknowns in the
order of ``model.free`` and ``c = (time_s, known_deviation_m)`` per-point constants.

The condition chains the catalog of :mod:`hartrao_jax.physics`: instrument corrections (seed
eq. 9), polar to Cartesian (eq. 2), motion of the scanner, scanner to telescope frame (eq. 6)
and the paraboloid with modelled deviations (eq. 5).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._config import on_device
from ..geometry._geometry import polar_to_cartesian, rot_z, scanner_to_telescope
from ..physics._catalog import (
    EXTENDED,
    INSTRUMENT,
    OBJECT_PARAMETERS,
    PARAMETER_UNITS,
    SIMPLIFIED,
    apply_pose,
    correct_observations,
    drift,
    impulsive_shift,
    inseparable_pairs,
    local_deformation,
    oscillation_sincos,
    paraboloid_condition,
    zernike_deviation,
)

SHIFT = ("shift_x", "shift_y", "shift_z")  # m, telescope frame, during the shift window
OSCILLATION = ("osc_sx", "osc_cx", "osc_sy", "osc_cy")  # rad: sin/cos amplitudes about x, y
OSC_FREQUENCY = "osc_df_hz"  # Hz: correction to the modelled oscillation frequency 1/period
DRIFT = ("drift_tx", "drift_ty", "drift_tz", "drift_rx", "drift_ry", "drift_rz")  # m/s, rad/s
ZERNIKE_PREFIX = "zern_"  # zern_<noll j>: normal deviation coefficient (m)
# local_deformation (physics.md): centre x, y (telescope frame, aperture plane), amplitude,
# width (m); a second bump is ``bump2_x_m`` ... (prefix ``bump<k>_``)
BUMP = ("bump_x_m", "bump_y_m", "bump_amp_m", "bump_width_m")


def bump_names(k: int = 1) -> tuple[str, ...]:
    """Parameter names of the ``k``-th modelled local deformation (1: ``bump_x_m`` ...)."""
    return BUMP if k == 1 else tuple(n.replace("bump_", f"bump{k}_", 1) for n in BUMP)


def _bump_key(name: str):
    """``(k, field)`` of a bump parameter name, else None."""
    head, _, field = name.partition("_")
    k = head[4:]
    if not head.startswith("bump") or f"bump_{field}" not in BUMP or not (k == "" or k.isdigit()):
        return None
    return (int(k) if k else 1), field

EXTRA_UNITS = {
    **{k: "m" for k in SHIFT}, **{k: "rad" for k in OSCILLATION}, OSC_FREQUENCY: "Hz",
    "drift_tx": "m/s", "drift_ty": "m/s", "drift_tz": "m/s",
    "drift_rx": "rad/s", "drift_ry": "rad/s", "drift_rz": "rad/s",
}

N_CONSTS = 2  # per-point constants: time_s, known deviation (m)
DEV_COLUMN = 1  # the column of the known normal deviation of the surface (m)


class ModelError(ValueError):
    """A model that cannot be built (unknown or inseparable parameters)."""


def is_bump_parameter(name: str) -> bool:
    """Whether ``name`` is a parameter of a local deformation (``bump_amp_m``, ``bump2_x_m``...)."""
    return _bump_key(name) is not None


def known_parameter(name: str) -> bool:
    return (
        name in OBJECT_PARAMETERS or name in INSTRUMENT or name in SHIFT or name in OSCILLATION
        or name == OSC_FREQUENCY
        or name in DRIFT
        or (name.startswith(ZERNIKE_PREFIX) and name[len(ZERNIKE_PREFIX):].isdigit())
        or is_bump_parameter(name)
    )


def parse_model(spec: str | Iterable[str]) -> tuple[str, ...]:
    """``"simplified"``, ``"extended"`` or comma-separated catalog names -> parameter names.

    Object parameters (``tx ty tz rx ry f``) are always estimated and put first.
    """
    if isinstance(spec, str):
        s = spec.strip().lower()
        if s == "simplified":
            return SIMPLIFIED
        if s == "extended":
            return EXTENDED
        names = [n.strip() for n in spec.split(",") if n.strip()]
    else:
        names = list(spec)
    unknown = [n for n in names if not known_parameter(n)]
    if unknown:
        raise ModelError(
            f"--model: unknown parameter(s) {', '.join(unknown)}; expected 'simplified', "
            f"'extended' or names from: {', '.join(OBJECT_PARAMETERS + tuple(INSTRUMENT))}"
        )
    rest = [n for n in dict.fromkeys(names) if n not in OBJECT_PARAMETERS]
    return OBJECT_PARAMETERS + tuple(rest)


def _floats(v) -> Array:
    """``v`` (a value or a list of values) as a float64 device array: host values by a
    transfer (:func:`.._config.on_device`), JAX arrays and tracers by ``jnp.asarray``."""
    if any(isinstance(a, jax.Array) for a in (v if isinstance(v, (list, tuple)) else [v])):
        return jnp.asarray(v, dtype=float)
    return on_device(v, float)


def _unstack(v: Float[Array, " p"]) -> list[Array]:
    """The entries of a vector as scalars (none for an empty one)."""
    return list(jnp.unstack(v)) if v.shape[0] else []


class ParaboloidModel(eqx.Module):
    """Condition of one point on a paraboloid of revolution seen by a (mis-)calibrated scanner.

    Attributes:
        free: names of the estimated unknowns, in the order of ``x``.
        fixed_names / fixed_values: parameters held at given values (instrument parameters,
            or motion/deformation terms) -- everything not named is zero.
        shift_window_s: (start, duration) of the impulsive-shift box in scan time (s).
        osc_period_s: period of the modelled oscillation (s); ``osc_df_hz``, when estimated,
            corrects its frequency (phase ``2 pi t (1/period + df)``, t in scan time).
        kappa_rad: rotation fitted frame -> telescope frame about the axis (for Zernike azimuth).
        aperture_radius_m: radius normalising the Zernike terms.
    """

    free: tuple[str, ...] = eqx.field(static=True)
    fixed_names: tuple[str, ...] = eqx.field(static=True)
    fixed_values: Float[Array, " p"]
    shift_window_s: Float[Array, " 2"]
    osc_period_s: Float[Array, ""]
    kappa_rad: Float[Array, ""]
    aperture_radius_m: float = eqx.field(static=True, default=12.95)

    def values(self, x: ArrayLike) -> dict[str, float]:
        """:meth:`params` on the host, as floats (no JAX operation)."""
        p = dict(zip(self.fixed_names, np.asarray(self.fixed_values, float).tolist(),
                     strict=True))
        p.update(zip(self.free, np.asarray(x, float).reshape(-1).tolist(), strict=True))
        return p

    def params(self, x: Float[Array, " u"]) -> dict[str, Array]:
        """All named parameter values: free ones from ``x``, then the fixed ones."""
        # one unstack per vector: indexing ``x[i]`` once per name costs 5x the tracing
        p = dict(zip(self.fixed_names, _unstack(self.fixed_values), strict=True))
        p.update(zip(self.free, _unstack(x), strict=True))
        return p

    def telescope_point(self, l: Float[Array, " 3"], x: Float[Array, " u"], c: Float[Array, " k"]):
        """Telescope-frame (fitted frame) coordinates of one observation (m)."""
        p = self.params(x)
        r, phi, theta = correct_observations(l[0], l[1], l[2], p)
        xs = polar_to_cartesian(r, phi, theta)
        t_s = c[0]
        R = scanner_to_telescope(p["rx"], p["ry"])
        t = jnp.stack([p["tx"], p["ty"], p["tz"]])
        w = jnp.zeros(3)
        d = jnp.zeros(3)
        if any(n in p for n in SHIFT):
            disp = jnp.stack([p.get(n, 0.0) for n in SHIFT])
            d = d + impulsive_shift(t_s, self.shift_window_s[0], self.shift_window_s[1], disp)
        if any(n in p for n in OSCILLATION):
            zero = jnp.zeros(())
            w = w + oscillation_sincos(
                t_s, 1.0 / self.osc_period_s + p.get(OSC_FREQUENCY, 0.0),
                jnp.stack([p.get("osc_sx", zero), p.get("osc_sy", zero), zero]),
                jnp.stack([p.get("osc_cx", zero), p.get("osc_cy", zero), zero]))
        if any(n in p for n in DRIFT):
            dw, dd = drift(
                t_s,
                jnp.stack([p.get(n, 0.0) for n in DRIFT[:3]]),
                jnp.stack([p.get(n, 0.0) for n in DRIFT[3:]]),
            )
            w, d = w + dw, d + dd
        return apply_pose(xs, R, t, w, d)

    def deviation(self, X: Float[Array, " 3"], p: Mapping[str, Array], c) -> Array:
        """Modelled normal deviation (m) of the reflector at ``X``: known part + Zernike terms."""
        dev = c[DEV_COLUMN]
        zs = [(int(n[len(ZERNIKE_PREFIX):]), v)
              for n, v in p.items() if n.startswith(ZERNIKE_PREFIX)]
        if zs:
            Xt = rot_z(self.kappa_rad) @ X
            u = jnp.hypot(Xt[0], Xt[1]) / self.aperture_radius_m
            psi = jnp.arctan2(Xt[1], Xt[0])
            dev = dev + zernike_deviation(u, psi, jnp.stack([v for _, v in zs]),
                                          tuple(j for j, _ in zs))
        bumps: dict[int, dict[str, Array]] = {}
        for n, v in p.items():
            key = _bump_key(n)
            if key is not None:
                bumps.setdefault(key[0], {})[key[1]] = v
        if bumps:  # local_deformation: centre in the north-aligned aperture plane
            Xt = rot_z(self.kappa_rad) @ X
            for b in bumps.values():
                dev = dev + local_deformation(Xt[0], Xt[1], b.get("x_m", 0.0), b.get("y_m", 0.0),
                                              b.get("amp_m", 0.0), b.get("width_m", 1.0))
        return dev

    def __call__(
        self, l: Float[Array, " 3"], x: Float[Array, " u"], c: Float[Array, " k"]
    ) -> Array:
        p = self.params(x)
        X = self.telescope_point(l, x, c)
        return paraboloid_condition(X, p["f"], self.deviation(X, p, c))

    def with_free(self, free: Iterable[str]) -> ParaboloidModel:
        return make_model(free, fixed=dict(zip(self.fixed_names, np.asarray(self.fixed_values))),
                          shift_window_s=self.shift_window_s, osc_period_s=self.osc_period_s,
                          kappa_rad=self.kappa_rad, aperture_radius_m=self.aperture_radius_m)


def make_model(
    free: str | Iterable[str],
    fixed: Mapping[str, float] | None = None,
    *,
    shift_window_s=(0.0, 0.0),
    osc_period_s: float = 1.0,
    kappa_rad: float = 0.0,
    aperture_radius_m: float = 12.95,
    check_separable: bool = True,
) -> ParaboloidModel:
    """Build a model from parameter names (or ``"simplified"``/``"extended"``) and fixed values.

    Object parameters are estimated unless given a fixed value (e.g. ``fixed={"f": 60.0}``).

    Raises :class:`ModelError` for unknown names and for pairs that cannot be separated
    (same column shape, e.g. ``x5z`` with ``x7``).
    """
    fixed = {k: float(v) for k, v in (fixed or {}).items()}
    names = tuple(n for n in parse_model(free) if n not in fixed)  # a fixed value wins
    bad = [k for k in fixed if not known_parameter(k)]
    if bad:
        raise ModelError(f"fixed parameter(s) not in the catalog: {', '.join(bad)}")
    if check_separable:
        pairs = inseparable_pairs(names)
        if pairs:
            a, b, c = pairs[0]
            raise ModelError(
                f"--model: {a} and {b} cannot be estimated together: their corrections have the "
                f"same shape (correlation {c:+.6f}); keep one of them"
            )
    fixed_names = tuple(sorted(fixed))
    return ParaboloidModel(
        free=names,
        fixed_names=fixed_names,
        fixed_values=_floats([fixed[k] for k in fixed_names]),
        shift_window_s=_floats(shift_window_s),
        osc_period_s=_floats(osc_period_s),
        kappa_rad=_floats(kappa_rad),
        aperture_radius_m=float(aperture_radius_m),
    )


def parameter_unit(name: str) -> str:
    if name in PARAMETER_UNITS:
        return PARAMETER_UNITS[name]
    if name in EXTRA_UNITS:
        return EXTRA_UNITS[name]
    return "m" if name.startswith(ZERNIKE_PREFIX) or _bump_key(name) is not None else ""


def format_estimate(name: str, value: float, sigma: float) -> str:
    """``value ± sigma`` of parameter ``name`` in readable units (arcsec for rad, mm for m)."""
    unit = parameter_unit(name)
    if unit == "rad":
        return f"{value * 206264.806:.2f} ± {sigma * 206264.806:.2f} arcsec"
    if unit == "m":
        return f"{value * 1e3:.4f} ± {sigma * 1e3:.4f} mm"
    return f"{value:.4g} ± {sigma:.2g} {unit}".strip()
