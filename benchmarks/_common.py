"""Shared pieces of the benchmarks: synthetic scans, hand-derived kernels, timing and memory.

Nothing here imports the simulator: a scan is built directly from the physics catalog's geometry
(points on the paraboloid, scanner pose, two-face raw observations, inverted calibration), so the
benchmarks keep working while the simulator changes.

Import order matters for the XLA flags: set ``XLA_FLAGS`` in the environment *before* importing
this module (it imports JAX).
"""

from __future__ import annotations

import gc
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# --------------------------------------------------------------------------------------------
# The test problem: one scan, extended model (tx ty tz rx ry f x4 x6 x7)
# --------------------------------------------------------------------------------------------

NAMES = ("tx", "ty", "tz", "rx", "ry", "f", "x4", "x6", "x7")
TRUTH = np.array([0.01, -0.02, 9.3, 0.3, np.pi - 0.5, 10.9816, 1.2e-4, 6.0e-5, -4.0e-5])
# initial values as a real first guess would be: cm / mrad off, calibration at zero
X0 = TRUTH + np.array([0.02, -0.015, 0.03, 2e-3, -1.5e-3, 0.02, 0.0, 0.0, 0.0])
X0[6:] = 0.0
SIGMA = np.array([0.0008, 2e-5, 2e-5])  # range m, phi rad, theta rad
RHO_MIN, RHO_MAX = 1.6, 12.95


def _rot(rx: float, ry: float) -> np.ndarray:
    """``Ry(ry) Rx(rx)`` (scanner -> telescope), same as ``_geometry.scanner_to_telescope``."""
    cx, sx, cy, sy = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    return Ry @ Rx


def _cartesian_to_raw(xs: np.ndarray):
    try:  # the package's face rule when available (it is the spec's)
        from hartrao_jax.geometry._geometry import cartesian_to_raw

        return cartesian_to_raw(xs, cycle=1)
    except Exception:  # pragma: no cover - fallback identical to the spec's face rule, cycle 1
        x, y, z = xs[:, 0], xs[:, 1], xs[:, 2]
        r = np.sqrt(x * x + y * y + z * z)
        a = np.mod(np.arctan2(x, y), 2 * np.pi)
        th0 = np.arccos(np.clip(z / r, -1, 1))
        f1 = a < np.pi
        return r, np.where(f1, a, a - np.pi), np.where(f1, th0, 2 * np.pi - th0)


def make_scan(n: int, seed: int = 0, truth: np.ndarray = TRUTH, noise: bool = True,
              block: int = 1 << 20) -> np.ndarray:
    """Raw two-face observations ``(n, 3)`` = (r, phi, theta) of ``n`` points of one scan.

    Points are uniform in area on the paraboloid (rho in [1.6, 12.95] m), transformed into the
    scanner frame of the pose ``truth[:5]``, recorded with the cycle-1 face rule, then the
    calibration ``x4, x6, x7`` is inverted exactly (the phi terms are evaluated at the corrected
    theta, which is known), so ``make_model('extended')(l_true, truth, 0) == 0`` to round-off.
    Built in blocks of ``block`` points so a 1.3e7-point scan needs no large temporaries.
    """
    tx, ty, tz, rx, ry, f, x4, x6, x7 = truth
    R = _rot(rx, ry)
    t = np.array([tx, ty, tz])
    out = np.empty((n, 3))
    rng = np.random.default_rng(seed)
    for s in range(0, n, block):
        m = min(block, n - s)
        rho = np.sqrt(rng.uniform(RHO_MIN**2, RHO_MAX**2, m))
        psi = rng.uniform(0, 2 * np.pi, m)
        X = np.stack([rho * np.cos(psi), rho * np.sin(psi), rho * rho / (4 * f)], axis=1)
        xs = (X - t) @ R  # R^T (X - t)
        r, ph_c, th_c = _cartesian_to_raw(xs)
        theta = th_c - x4
        phi = ph_c - (2 * x6 / np.sin(th_c) + x7 * np.cos(th_c) / np.sin(th_c))
        blk = np.stack([r, phi, theta], axis=1)
        if noise:
            blk += rng.standard_normal((m, 3)) * SIGMA
        out[s:s + m] = blk
        del rho, psi, X, xs, r, ph_c, th_c, theta, phi, blk
    return out


# --------------------------------------------------------------------------------------------
# Hand-derived condition and derivatives (extended model, known deviation 0)
# --------------------------------------------------------------------------------------------


def _pose_mats(xp, x):
    """R, dR/drx, dR/dry for R = Ry(ry) Rx(rx) (3x3 arrays of module ``xp``)."""
    cx, sx, cy, sy = xp.cos(x[3]), xp.sin(x[3]), xp.cos(x[4]), xp.sin(x[4])
    o, z = xp.ones_like(cx), xp.zeros_like(cx)
    Rx = xp.stack([xp.stack([o, z, z]), xp.stack([z, cx, -sx]), xp.stack([z, sx, cx])])
    dRx = xp.stack([xp.stack([z, z, z]), xp.stack([z, -sx, -cx]), xp.stack([z, cx, -sx])])
    Ry = xp.stack([xp.stack([cy, z, sy]), xp.stack([z, o, z]), xp.stack([-sy, z, cy])])
    dRy = xp.stack([xp.stack([-sy, z, cy]), xp.stack([z, z, z]), xp.stack([-cy, z, -sy])])
    return Ry @ Rx, Ry @ dRx, dRy @ Rx


def hand_linearize(xp, r, phi, theta, x):
    """Condition ``F`` and its gradients for arrays of points (any array module ``xp``).

    Returns ``F (n,)``, ``a`` as a list of 9 arrays (dF/dx), ``b`` as a list of 3 (dF/dl).
    4 transcendental ops per point (sin/cos of theta and phi) + 1 reciprocal.
    """
    R, Rrx, Rry = _pose_mats(xp, x)
    f, x4, x6, x7 = x[5], x[6], x[7], x[8]
    th = theta + x4
    s, c = xp.sin(th), xp.cos(th)
    inv_s = 1.0 / s
    g = (2.0 * x6 + x7 * c) * inv_s  # phi correction at the corrected theta
    dg = -(2.0 * x6 * c + x7) * inv_s * inv_s
    ph = phi + g
    sp, cp = xp.sin(ph), xp.cos(ph)
    u0, u1, u2 = s * sp, s * cp, c  # unit direction (scanner frame)
    xs0, xs1, xs2 = r * u0, r * u1, r * u2
    X0 = R[0, 0] * xs0 + R[0, 1] * xs1 + R[0, 2] * xs2 + x[0]
    X1 = R[1, 0] * xs0 + R[1, 1] * xs1 + R[1, 2] * xs2 + x[1]
    X2 = R[2, 0] * xs0 + R[2, 1] * xs1 + R[2, 2] * xs2 + x[2]
    i4f = 1.0 / (4.0 * f)
    rho2 = X0 * X0 + X1 * X1
    F = rho2 * i4f - X2
    g0, g1 = X0 * (2.0 * i4f), X1 * (2.0 * i4f)  # dF/dX = (g0, g1, -1)
    # gradient in the scanner frame: R^T gX
    h0 = R[0, 0] * g0 + R[1, 0] * g1 - R[2, 0]
    h1 = R[0, 1] * g0 + R[1, 1] * g1 - R[2, 1]
    h2 = R[0, 2] * g0 + R[1, 2] * g1 - R[2, 2]
    dFr = h0 * u0 + h1 * u1 + h2 * u2
    dFth = r * (c * (h0 * sp + h1 * cp) - s * h2)
    dFph = r * s * (h0 * cp - h1 * sp)
    dFtheta = dFth + dFph * dg

    def rot_grad(M):
        return (g0 * (M[0, 0] * xs0 + M[0, 1] * xs1 + M[0, 2] * xs2)
                + g1 * (M[1, 0] * xs0 + M[1, 1] * xs1 + M[1, 2] * xs2)
                - (M[2, 0] * xs0 + M[2, 1] * xs1 + M[2, 2] * xs2))

    a = [g0, g1, -xp.ones_like(F), rot_grad(Rrx), rot_grad(Rry), -rho2 * i4f / f,
         dFtheta, dFph * 2.0 * inv_s, dFph * c * inv_s]
    b = [dFr, dFph, dFtheta]
    return F, a, b


# --------------------------------------------------------------------------------------------
# Measuring
# --------------------------------------------------------------------------------------------


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far (MiB; Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rss_mib() -> float:
    try:
        import psutil

        return psutil.Process().memory_info().rss / 2**20
    except Exception:  # pragma: no cover
        return float("nan")


def timed(fn, *args, repeat: int = 1, **kw):
    """(best seconds, result) of ``fn(*args)`` over ``repeat`` calls (result blocked on)."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn(*args, **kw)
        out = _block(out)
        best = min(best, time.perf_counter() - t)
    return best, out


def _block(out):
    try:
        import jax

        return jax.block_until_ready(out)
    except Exception:
        return out


def stream_bandwidth(n_bytes: int = 1 << 30, repeat: int = 5) -> dict[str, float]:
    """Streaming memory bandwidth (GB/s) measured with NumPy: read (sum) and copy (read+write).

    ``np.add.reduce`` on a float64 array reads ``n`` bytes; ``np.copyto`` reads and writes
    ``n`` bytes (counted as 2n). Best of ``repeat``. Single-threaded (NumPy's elementwise code).
    """
    t_sum, t_copy = _stream_times(n_bytes, repeat)
    gc.collect()  # the arrays went out of scope with _stream_times
    return {"read_GBps": n_bytes / t_sum / 1e9, "copy_GBps": 2 * n_bytes / t_copy / 1e9}


def _stream_times(n_bytes: int, repeat: int) -> tuple[float, float]:
    """Best seconds of ``a.sum()`` and ``np.copyto(b, a)`` on ``n_bytes`` float64 arrays."""
    a = np.ones(n_bytes // 8)
    b = np.empty_like(a)
    t_sum = min(_t(lambda: a.sum()) for _ in range(repeat))
    t_copy = min(_t(lambda: np.copyto(b, a)) for _ in range(repeat))
    return t_sum, t_copy


def _t(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def machine_info() -> dict:
    info = {"python": platform.python_version(), "machine": platform.machine(),
            "cores": os.cpu_count()}
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        import jax
        import jaxlib

        info["jax"] = jax.__version__
        info["jaxlib"] = jaxlib.__version__
    except Exception:
        pass
    info["numpy"] = np.__version__
    for k in ("XLA_FLAGS", "OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE"):
        if os.environ.get(k):
            info[k] = os.environ[k]
    try:
        import psutil

        info["mem_GiB"] = round(psutil.virtual_memory().total / 2**30, 1)
    except Exception:
        pass
    return info


def write_results(stem: str, md: str, data: dict) -> tuple[Path, Path]:
    RESULTS.mkdir(parents=True, exist_ok=True)
    p_md, p_js = RESULTS / f"{stem}.md", RESULTS / f"{stem}.json"
    p_md.write_text(md)
    p_js.write_text(json.dumps(data, indent=2, default=float) + "\n")
    return p_md, p_js


def md_table(rows: list[dict], cols: list[tuple[str, str, str]]) -> str:
    """Markdown table of ``rows``; ``cols`` = (key, header, format)."""
    head = "| " + " | ".join(h for _, h, _ in cols) + " |"
    sep = "|" + "|".join("---" for _ in cols) + "|"
    lines = [head, sep]
    for r in rows:
        cells = []
        for k, _, fmt in cols:
            v = r.get(k)
            if v is None or (isinstance(v, float) and not np.isfinite(v)):
                cells.append("")
            elif fmt:
                cells.append(format(v, fmt))
            else:
                cells.append(str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def seeded_parts(directory: Path, cases, seeds, run, describe) -> list[dict]:
    """Run ``run(case, seed)`` for every (case, seed) whose part ``directory/<case>-<seed>.json``
    is not stored yet, store each result as soon as it is done (temporary name, then rename),
    print ``describe(case, seed, result)``; return every stored part of ``directory`` (a run
    can be split over processes or sessions and merged)."""
    directory.mkdir(parents=True, exist_ok=True)
    for case in cases:
        for seed in seeds:
            part = directory / f"{case}-{seed}.json"
            if part.exists():
                continue
            res = run(case, seed)
            tmp = part.with_suffix(".tmp")
            tmp.write_text(json.dumps(res))
            tmp.replace(part)
            print(describe(case, seed, res), file=sys.stderr, flush=True)
    return [json.loads(q.read_text()) for q in sorted(directory.glob("*.json"))]
