"""Shared test helpers: synthetic scans without the simulator, finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from hartrao_jax._config import real_data_dir, real_data_missing
from hartrao_jax.geometry._geometry import cartesian_to_raw, scanner_to_telescope

F_TRUE = 10.9816
POSE = {"tx": 0.01, "ty": -0.02, "tz": 9.3, "rx": 0.3, "ry": np.pi - 0.5}
SIGMA = np.array([0.0008, 2e-5, 2e-5])

# Real GBT recordings, outside the repository: $HARTRAO_REAL_DATA/gbt-lassi (default
# ../shared/real from the repository root). Absent: skipped, saying where to get them.
REAL_GBT = real_data_dir() / "gbt-lassi"
needs_real_gbt = pytest.mark.skipif(real_data_missing() is not None,
                                    reason=real_data_missing() or "")


def real_gbt_file(name: str):
    """A file of the real GBT recordings: skip when the folder is absent; when the folder is
    there, the file must be too (never a silent skip)."""
    reason = real_data_missing()
    if reason is not None:
        pytest.skip(reason)
    p = REAL_GBT / name
    assert p.is_file(), f"{p}: missing from the real recordings in {REAL_GBT}"
    return p


def paraboloid_points(n: int, f: float = F_TRUE, seed: int = 0, rho=(1.6, 12.95)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r = np.sqrt(rng.uniform(rho[0] ** 2, rho[1] ** 2, n))
    psi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([r * np.cos(psi), r * np.sin(psi), r**2 / (4 * f)], 1)


def synthetic_scan(n=20000, *, cycle=1, seed=0, noise=True, pose=None, f=F_TRUE, model=None,
                   params=None):
    """Raw observations (n, 3) of a paraboloid seen from ``pose``; exact under ``model``.

    With a model and instrument ``params``, the raw angles are solved by fixed-point iteration so
    that ``model(l, x_true, 0) == 0`` (before noise).
    """
    pose = dict(POSE if pose is None else pose)
    X = paraboloid_points(n, f, seed)
    R = np.asarray(scanner_to_telescope(pose["rx"], pose["ry"]))
    t = np.array([pose["tx"], pose["ty"], pose["tz"]])
    xs = (X - t) @ R
    r, phi, th = cartesian_to_raw(xs, cycle)
    l = np.stack([r, phi, th], 1)
    if params:
        from hartrao_jax.physics._catalog import instrument_corrections

        target = l.copy()
        for _ in range(20):  # raw + correction(raw) = target
            dr, dphi, dth = (np.asarray(a)
                             for a in instrument_corrections(l[:, 0], l[:, 1], l[:, 2], params))
            l = target - np.stack([dr, dphi, dth], 1)
    if noise:
        rng = np.random.default_rng(seed + 1000)
        l = l + rng.normal(size=l.shape) * SIGMA
    return l


def truth_vector(names, pose=None, f=F_TRUE, params=None):
    pose = dict(POSE if pose is None else pose)
    vals = {**pose, "f": f, **(params or {})}
    return np.array([vals.get(n, 0.0) for n in names])


def finite_difference(fn, x, eps=1e-6):
    x = np.asarray(x, float)
    out = []
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = eps * max(1.0, abs(x[i]))
        out.append((fn(x + e) - fn(x - e)) / (2 * e[i]))
    return np.asarray(out)


def temporaries(out) -> list:
    """The temporary files (``.<name>.tmp-<pid>-<token>``) left under a result directory."""
    return [p for p in out.rglob(".*.tmp-*")] if out.exists() else []
