"""Gauss-Helmert fit of one scan, extended model (tx ty tz rx ry f x4 x6 x7): speed and memory.

Methods (each (method, size) runs in its own subprocess, so compile time and peak memory are
clean):

* ``pkg``          -- ``hartrao_jax.gauss_helmert`` as it is now (two linearisations per point
                      and iteration + a final statistics pass);
* ``onepass-rev``  -- the proposed drop-in (``_kernels.gh_one_pass``): one linearisation per
                      point and iteration, autodiff (reverse mode under vmap) of the package's
                      model, sin/cos computed once, linearisation materialised once, a/b stored
                      in float32, chunks of 4096 points;
* ``onepass-rev-noynn`` -- the same with ``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=``;
* ``onepass-hand`` -- the same loop with hand-derived derivatives (the floor an autodiff engine
                      can reach);
* ``numpy-hand``   -- the same algorithm vectorised in NumPy with hand-derived derivatives;
* ``odrpack``      -- odrpack 0.7 implicit ODR (``task='implicit-ODR'``) on the raw
                      observations (r, phi, theta) with weights 1/sigma^2 and analytic
                      Jacobians: the same least-squares problem (sizes <= 1e6), run with
                      ``partol=1e-7`` so that it reaches the GH solution (to ~1e-6 sigma);
* ``odrpack-default`` -- the same with odrpack's default tolerances, which stop ~0.1 sigma
                      short of the solution (sizes <= 1e5 by default).

Plus the streaming memory bandwidth (NumPy copy) and the time one pass over the points would
take at that bandwidth.

    python benchmarks/bench_ghm.py [--sizes 1e5,1e6,1.3e7] [--quick] [--methods a,b] [--odr-max 1e6]

Writes ``benchmarks/results/ghm.md`` and ``ghm.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    NAMES,
    SIGMA,
    TRUTH,
    X0,
    hand_linearize,
    machine_info,
    make_scan,
    md_table,
    peak_rss_mib,
    rss_mib,
    stream_bandwidth,
    write_results,
)

NOYNN = "--xla_cpu_experimental_ynn_fusion_type="
METHODS = ["pkg", "onepass-rev", "onepass-rev-noynn", "onepass-hand", "numpy-hand", "odrpack",
           "odrpack-default"]
TOL = 1e-6
CHUNK = 4096  # points per chunk of the one-pass solver (bench_kernels: 2048-8192 best)
# bytes per point of one pass: observations (3 f64) + constants (2 f64) + weight (f64)
BYTES_MIN = 3 * 8 + 2 * 8 + 8
# the one-pass iteration also reads and rewrites its store: a (9 f32), b (3 f32), w, m (f64)
BYTES_STORE = 9 * 4 + 3 * 4 + 8 + 8
BYTES_ONEPASS = BYTES_MIN + 2 * BYTES_STORE


# --------------------------------------------------------------------------------------------
# workers (run in subprocesses)
# --------------------------------------------------------------------------------------------


def _result(x, t_first, t_run, iterations, n, passes, extra=None):
    x = np.asarray(x, float)
    out = {"x": x.tolist(), "f": float(x[5]), "t_first_s": t_first, "t_run_s": t_run,
           "compile_s": max(t_first - t_run, 0.0) if t_first is not None else None,
           "iterations": int(iterations), "passes": passes, "n": n,
           "t_iter_s": t_run / max(int(iterations), 1)}
    out.update(extra or {})
    return out


def work_jax(method: str, l: np.ndarray, repeat: int):
    """Compile time by ahead-of-time lowering + compilation (independent of run-time noise),
    then ``repeat`` timed fits (best kept)."""
    import _kernels as K
    import jax
    import jax.numpy as jnp

    import hartrao_jax
    from hartrao_jax import make_model
    from hartrao_jax.solver import _ghm

    n = l.shape[0]
    model = make_model("extended")
    consts = np.zeros((n, 2))
    rss0 = rss_mib()
    if method == "pkg":
        def run():
            r = hartrao_jax.gauss_helmert(model, l, X0, SIGMA, consts, tol=TOL)
            jax.block_until_ready(r)
            return r.x, r.iterations, r.sigma0, r.sigma
        passes = "2 per iteration + 2 final"
        t = time.perf_counter()
        try:  # the package's private entry point, called as gauss_helmert calls it
            lj = jnp.asarray(l)
            chunk = int(min(1 << 16, max(256, 1 << int(np.ceil(np.log2(max(n, 1)))))))
            _ghm._gauss_helmert.lower(model, lj, jnp.asarray(X0), jnp.asarray(SIGMA),
                                      jnp.asarray(consts), jnp.ones((n,)), jnp.zeros_like(lj),
                                      float(TOL), max_iter=30, chunk_size=chunk).compile()
            t_compile = time.perf_counter() - t
            del lj
        except Exception:  # signature changed: fall back to first call minus a timed call
            t_compile = None
        t = time.perf_counter()
        run()  # warm-up (compiles again through the package's own cache)
        t_first = time.perf_counter() - t
    else:
        lin = K.make_hand_linearize(hand_linearize) if method == "onepass-hand" else K.linearize_rev
        lj = jnp.asarray(l)
        fargs = (model, lj, jnp.asarray(X0), jnp.asarray(SIGMA), jnp.asarray(consts),
                 jnp.ones((n,)), None, jnp.ones((), bool), TOL)
        def comp(*a):  # eqx.filter_jit: compiled on the first call, cached after
            return K.gh_one_pass(*a, lin=lin, chunk=min(CHUNK, n))

        t_compile = None
        t = time.perf_counter()
        jax.block_until_ready(comp(*fargs))
        t_first = time.perf_counter() - t

        def run():
            x, N, Ninv, V, Kk, M, F0, omega, it, done, _ = jax.block_until_ready(comp(*fargs))
            s0 = jnp.sqrt(omega / (n - x.shape[0]))
            return x, it, s0, jnp.sqrt(jnp.diagonal(Ninv)) * s0
        passes = "1 per iteration + 1 store sweep"
    best = None
    for _ in range(repeat):
        t = time.perf_counter()
        c = time.process_time()
        x, it, s0, sig = run()
        dt, dc = time.perf_counter() - t, time.process_time() - c
        if best is None or dt < best[0]:
            best = (dt, dc)
    out = _result(x, t_first, best[0], it, n, passes,
                  {"cpu_s": best[1], "sigma0": float(s0), "sigma": np.asarray(sig).tolist(),
                   "rss_before_fit_mib": rss0})
    if t_compile is not None:
        out["compile_s"] = t_compile
    return out


def numpy_gh(l, x0, sigma, tol=TOL, chunk=1 << 16, max_iter=30):
    """The one-pass GH algorithm in vectorised NumPy with hand-derived derivatives."""
    n, u = l.shape[0], x0.shape[0]
    s2 = np.asarray(sigma) ** 2
    A = np.zeros((n, u), np.float32)
    B = np.zeros((n, 3), np.float32)
    Wm = np.zeros(n)
    M = np.ones(n)
    x = np.array(x0, float)
    dx = np.zeros(u)
    it = 0
    for it in range(1, max_iter + 1):
        N = np.zeros((u, u))
        nv = np.zeros(u)
        for s in range(0, n, chunk):
            e = min(s + chunk, n)
            k = -(A[s:e] @ dx.astype(np.float32) + Wm[s:e]) / M[s:e] if it > 1 else np.zeros(e - s)
            v = s2 * B[s:e] * k[:, None]
            lv = l[s:e] + v
            F, a, b = hand_linearize(np, lv[:, 0], lv[:, 1], lv[:, 2], x)
            a = np.stack([np.broadcast_to(ai, F.shape) for ai in a], axis=1)
            b = np.stack(b, axis=1)
            wm = F - np.einsum("ij,ij->i", b, v)
            m = (b * b) @ s2
            aq = a / m[:, None]
            N += aq.T @ a
            nv += aq.T @ wm
            A[s:e], B[s:e], Wm[s:e], M[s:e] = a, b, wm, m
        dx = -np.linalg.solve(N, nv)
        Ninv = np.linalg.inv(N)
        x = x + dx
        if np.max(np.abs(dx) / np.sqrt(np.diag(Ninv))) < tol:
            break
    omega = 0.0
    for s in range(0, n, chunk):
        e = min(s + chunk, n)
        k = -(A[s:e] @ dx.astype(np.float32) + Wm[s:e]) / M[s:e]
        omega += float(np.sum(k * k * M[s:e]))
    s0 = np.sqrt(omega / (n - u))
    return x, it, s0, np.sqrt(np.diag(Ninv)) * s0


def work_numpy(l, repeat):
    rss0 = rss_mib()
    best = None
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        x, it, s0, sig = numpy_gh(l, X0, SIGMA)
        dt, dc = time.perf_counter() - t, time.process_time() - c
        if best is None or dt < best[0]:
            best = (dt, dc)
    return _result(x, None, best[0], it, l.shape[0], "1 per iteration + 1 store sweep",
                   {"cpu_s": best[1], "sigma0": float(s0), "sigma": sig.tolist(),
                    "rss_before_fit_mib": rss0})


def work_odr(l, partol):
    from odrpack import odr_fit

    n = l.shape[0]
    cb = [0.0]

    def f(x, beta):
        t = time.perf_counter()
        r = hand_linearize(np, x[0], x[1], x[2], beta)[0]
        cb[0] += time.perf_counter() - t
        return r

    def jac_beta(x, beta):
        t = time.perf_counter()
        F, a, _ = hand_linearize(np, x[0], x[1], x[2], beta)
        r = np.stack([np.broadcast_to(ai, F.shape) for ai in a])
        cb[0] += time.perf_counter() - t
        return r

    def jac_x(x, beta):
        t = time.perf_counter()
        r = np.stack(hand_linearize(np, x[0], x[1], x[2], beta)[2])
        cb[0] += time.perf_counter() - t
        return r

    xdata = np.ascontiguousarray(l.T)
    rss0 = rss_mib()
    t, c = time.perf_counter(), time.process_time()
    r = odr_fit(f, xdata, np.zeros(n), X0, weight_x=1.0 / SIGMA**2, task="implicit-ODR",
                jac_beta=jac_beta, jac_x=jac_x, partol=partol, maxit=1000)
    dt, dc = time.perf_counter() - t, time.process_time() - c
    return _result(r.beta, None, dt, r.niter, n, "ODRPACK iterations",
                   {"cpu_s": dc, "callbacks_s": cb[0], "nfev": int(r.nfev), "njev": int(r.njev),
                    "stopreason": r.stopreason, "partol": partol,
                    "sigma": list(map(float, r.sd_beta)),
                    "rss_before_fit_mib": rss0})


def worker(args):
    if args.worker == "bandwidth":
        out = stream_bandwidth(1 << 29, 7)
    elif args.worker == "data":
        l = make_scan(args.n)
        np.save(args.data, l)
        out = {"n": args.n}
    else:
        l = np.load(args.data)
        if args.worker in ("pkg", "onepass-rev", "onepass-rev-noynn", "onepass-hand"):
            out = work_jax(args.worker, l, args.repeat)
        elif args.worker == "numpy-hand":
            out = work_numpy(l, args.repeat)
        elif args.worker == "odrpack":
            out = work_odr(l, args.partol)
        elif args.worker == "odrpack-default":
            out = work_odr(l, None)
        else:
            raise SystemExit(f"unknown worker {args.worker}")
        out["peak_rss_mib"] = peak_rss_mib()
    print("JSON:" + json.dumps(out))


def spawn(worker_name, n=0, data="", repeat=1, partol=1e-7, env_extra=None, timeout=None):
    env = dict(os.environ)
    env.update(env_extra or {})
    cmd = [sys.executable, __file__, "--worker", worker_name, "--n", str(n), "--data", data,
           "--repeat", str(repeat), "--partol", str(partol)]
    t = time.perf_counter()
    try:
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timeout after {timeout} s"}
    line = [s for s in p.stdout.splitlines() if s.startswith("JSON:")]
    if p.returncode != 0 or not line:
        err = [s for s in p.stderr.strip().splitlines() if "Warning" not in s]
        return {"error": (err[-1] if err else f"exit {p.returncode}")[:300]}
    out = json.loads(line[0][5:])
    out["wall_process_s"] = time.perf_counter() - t
    return out


# --------------------------------------------------------------------------------------------
# driver
# --------------------------------------------------------------------------------------------


def fmt_n(n: int) -> str:
    return f"{n:.1e}".replace("e+0", "e")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1e5,1e6,1.3e7")
    ap.add_argument("--quick", action="store_true", help="1e5 points only, one repeat")
    ap.add_argument("--methods", default=None,
                    help=f"comma-separated, default all: {','.join(METHODS)}")
    ap.add_argument("--odr-max", type=float, default=1e6, help="largest size odrpack is run at")
    ap.add_argument("--odr-default-max", type=float, default=1e5,
                    help="largest size odrpack with default tolerances is run at")
    ap.add_argument("--partol", type=float, default=1e-7,
                    help="odrpack partol (its default 6e-6 stops ~0.1 sigma short of the solution)")
    ap.add_argument("--repeat", type=int, default=0, help="timed repeats (default 2, 1 above 2e6)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=lambda s: int(float(s)), default=0, help=argparse.SUPPRESS)
    ap.add_argument("--data", default="", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args)
    if args.quick:
        args.sizes = "1e5"
    sizes = [int(float(s)) for s in args.sizes.split(",") if s]
    if args.methods is None:  # --quick leaves out odrpack (a minute or more even at 1e5)
        methods = [m for m in METHODS if not (args.quick and m.startswith("odrpack"))]
    else:
        methods = [m for m in args.methods.split(",") if m]

    load0 = os.getloadavg()
    t_start = time.perf_counter()
    bw = spawn("bandwidth")
    print(f"bandwidth: {bw}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="hartrao_bench_") as tmp:
        for n in sizes:
            path = os.path.join(tmp, f"l_{n}.npy")
            d = spawn("data", n=n, data=path)
            if "error" in d:
                print(f"data {n}: {d['error']}", flush=True)
                continue
            repeat = args.repeat or (1 if n > 2_000_000 or args.quick else 2)
            for m in methods:
                if (m == "odrpack" and n > args.odr_max) or (
                        m == "odrpack-default" and n > args.odr_default_max):
                    continue
                env = {"XLA_FLAGS": NOYNN} if m == "onepass-rev-noynn" else {}
                worker_name = "onepass-rev" if m == "onepass-rev-noynn" else m
                r = spawn(worker_name, n=n, data=path, repeat=repeat, partol=args.partol,
                          env_extra=env)
                r.update({"method": m, "n": n})
                rows.append(r)
                msg = r.get("error") or (f"{r['t_run_s']:.2f}s it={r['iterations']} "
                                         f"f={r['f']:.9f} peak={r['peak_rss_mib']:.0f}MiB")
                print(f"{m:18s} n={n:>9,d}: {msg}", flush=True)
    load1 = os.getloadavg()

    # derived columns
    bw_copy = bw.get("copy_GBps", float("nan")) * 1e9
    by = {(r["method"], r["n"]): r for r in rows if "error" not in r}
    for r in rows:
        if "error" in r:
            continue
        n = r["n"]
        ref = by.get(("pkg", n)) or by.get(("onepass-rev", n))
        if ref is not None:
            r["df_ref_m"] = abs(r["f"] - ref["f"])
            sig = np.asarray(ref["sigma"])
            dx = np.abs(np.asarray(r["x"]) - np.asarray(ref["x"]))
            r["dx_ref_sigma"] = float(np.max(dx / sig))
        r["points_per_s"] = n / r["t_run_s"]
        r["points_per_s_iter"] = n / r["t_iter_s"]
        r["bw_bound_ms"] = BYTES_MIN * n / bw_copy * 1e3
        r["iter_over_bw"] = r["t_iter_s"] * 1e3 / r["bw_bound_ms"]
        ours = by.get(("onepass-rev", n))
        hand = by.get(("onepass-hand", n))
        if r["method"].startswith("odrpack") and ours:
            r["odr_over_ours"] = r["t_run_s"] / ours["t_run_s"]
            r["odr_over_ours_cpu"] = r["cpu_s"] / ours["cpu_s"]
            pkg = by.get(("pkg", n))
            if pkg:
                r["odr_over_pkg"] = r["t_run_s"] / pkg["t_run_s"]
        if hand and not r["method"].startswith("odrpack"):
            r["iter_over_hand"] = r["t_iter_s"] / hand["t_iter_s"]
        r["size"] = fmt_n(n)
        r["peak_gib"] = r["peak_rss_mib"] / 1024
        r["fit_gib"] = (r["peak_rss_mib"] - r.get("rss_before_fit_mib", 0.0)) / 1024

    cols = [("size", "points", ""), ("method", "method", ""), ("compile_s", "compile s", ".2f"),
            ("t_iter_s", "s / iteration", ".3f"), ("iterations", "iterations", "d"),
            ("t_run_s", "s to convergence", ".2f"), ("cpu_s", "CPU s", ".2f"),
            ("points_per_s", "points/s (fit)", ".3g"),
            ("points_per_s_iter", "points/s (iteration)", ".3g"),
            ("peak_gib", "peak RSS GiB", ".2f"),
            ("fit_gib", "RSS added by fit GiB", ".2f"), ("df_ref_m", "abs(f - f_ref) m", ".1e"),
            ("dx_ref_sigma", "max abs(x - x_ref)/sigma", ".1e"),
            ("odr_over_ours", "odrpack / onepass-rev", ".1f"),
            ("odr_over_ours_cpu", "same, CPU time", ".1f"),
            ("odr_over_pkg", "odrpack / pkg", ".1f"),
            ("iter_over_hand", "iteration / hand-JAX", ".2f"),
            ("iter_over_bw", "iteration / bandwidth bound", ".0f")]
    errs = [f"- {r['method']} at {fmt_n(r['n'])}: {r['error']}" for r in rows if "error" in r]
    mi = machine_info()
    md = [
        "# Gauss-Helmert fit of one scan: extended model (9 unknowns)\n",
        "Synthetic scan (paraboloid f = 10.9816 m, rho 1.6-12.95 m, pose (0.01, -0.02, 9.3) m, "
        "rx 0.3, ry pi-0.5, x4/x6/x7 applied, noise 0.8 mm / 20 urad / 20 urad), x0 off by cm/mrad "
        f"with the calibration at zero; convergence when every step < {TOL:g} of its sigma. "
        "float64 throughout. `f_ref`/`x_ref`: the `pkg` solution at the same size.\n",
        "Columns: compile = ahead-of-time lower + compile of the jitted solver; "
        "s / iteration = time to convergence / iterations (pkg: each iteration is "
        "2 linearisation passes, plus 2 final passes in the total; onepass: 1 pass, "
        "plus a store sweep); peak RSS of the worker process (data + JAX runtime "
        "included; the next column subtracts the RSS before the fit); bandwidth bound = one pass "
        f"reading the observations, constants and weights ({BYTES_MIN} B/point) at the measured "
        f"copy bandwidth (the one-pass iteration moves {BYTES_ONEPASS} B/point with its store).\n",
        md_table(rows and [r for r in rows if "error" not in r], cols),
    ]
    if errs:
        md.append("\nFailed runs:\n" + "\n".join(errs) + "\n")
    md.append(
        f"\nStreaming bandwidth (NumPy, 1 GiB, single thread): read (sum) "
        f"{bw.get('read_GBps', float('nan')):.1f} GB/s, copy (read+write) "
        f"{bw.get('copy_GBps', float('nan')):.1f} GB/s.\n"
        f"Load average before/after: {load0[0]:.1f} / {load1[0]:.1f} on {os.cpu_count()} cores "
        "(the machine is shared with other jobs; wall times are inflated by them). "
        f"Total benchmark time {time.perf_counter() - t_start:.0f} s.\n")
    md.append("\n```\n" + json.dumps(mi, indent=1) + "\n```\n")
    text = "\n".join(md)
    print(text)
    write_results("ghm", text, {"machine": mi, "bandwidth": bw, "bytes_min": BYTES_MIN,
                                "bytes_onepass": BYTES_ONEPASS, "load_before": load0,
                                "load_after": load1, "tol": TOL, "names": NAMES,
                                "truth": TRUTH.tolist(), "x0": X0.tolist(), "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
