"""Linearisation kernels for the Gauss-Helmert pass: which one, which precision, which chunk size.

Times ONE pass over the points as the proposed solver does it per iteration (residual update
from the stored a, b, w, m of the previous pass + linearisation at l + v + accumulation of the
normal equations + store), for every kernel variant, interleaved over rounds (best of
``--rounds``; other jobs on the machine make single timings noisy). Also counts the per-point
transcendental ops left in the optimised HLO (``sine``/``cosine``/``tan``), the compile time,
and -- in a subprocess each -- the effect of ``XLA_FLAGS`` values.

    python benchmarks/bench_kernels.py [--n 1e6] [--rounds 5] [--quick] [--no-flags]

Writes ``benchmarks/results/kernels.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402

from _common import (  # noqa: E402
    SIGMA, X0, hand_linearize, machine_info, make_scan, md_table, write_results,
)


def build(args):
    import jax
    import jax.numpy as jnp

    import hartrao_jax  # noqa: F401  (float64)
    from hartrao_jax import make_model
    from _kernels import linearize_fwd, linearize_rev, make_hand_linearize

    model = make_model("extended")
    hand = make_hand_linearize(hand_linearize)
    lins = {"rev": linearize_rev, "fwd": linearize_fwd, "hand": hand}
    f64, f32 = jnp.float64, jnp.float32

    def mixed(lin):
        """F in float64, the Jacobians a, b in float32."""
        def f(cond, l, x, c, on):
            F = lin(cond, l, x, c, on)[0] if lin is hand else _value(cond, l, x, c, on)
            _, a, b = lin(cond, l.astype(f32), x.astype(f32), c.astype(f32), on)
            return F, a.astype(f64), b.astype(f64)
        return f

    def _value(cond, l, x, c, on):
        from _kernels import materialize_trig

        cf = cond if on is None else materialize_trig(cond, on)
        return jax.vmap(cf, in_axes=(0, None, 0))(l, x, c)

    def make_pass(lin, trig, chunk, jac, store):
        """One fused pass as in ``_kernels.gh_one_pass`` (a closed-over copy of its body)."""
        kern = lins[lin] if jac == "f64" else mixed(lins[lin])

        @jax.jit
        def run(cond, L, C, S2, x, dx, st, on):
            u = x.shape[0]
            s2 = S2

            def body(carry, ch):
                N, nv = carry
                lc, cc, (a0, b0, w0, m0) = ch
                k = -((a0.astype(f64) @ dx) + w0) / m0
                v = s2 * b0.astype(f64) * k[:, None]
                F, a, b = kern(cond, lc + v, x, cc, on if trig else None)
                wm = F - jnp.sum(b * v, -1)
                m = jnp.sum(b * b * s2, -1)
                q = 1.0 / m
                aq = a * q[:, None]
                return (N + aq.T @ a, nv + aq.T @ wm), (a.astype(store), b.astype(store), wm, m)

            (N, nv), st = jax.lax.scan(body, (jnp.zeros((u, u)), jnp.zeros(u)), (L, C, st))
            return N, nv, st

        return run

    n = int(float(args.n))
    l = make_scan(n)
    return jax, jnp, model, make_pass, l, n


def count_ops(txt: str) -> dict:
    out = {k: len(re.findall(rf"\b{k}\(", txt)) for k in ("sine", "cosine", "tan", "divide")}
    out["trig"] = out["sine"] + out["cosine"] + out["tan"]
    return out


def run_variants(args, variants):
    jax, jnp, model, make_pass, l, n = build(args)
    rows = []
    compiled = []
    on = jnp.array(True)
    x = jnp.asarray(X0)
    dx = jnp.zeros_like(x)
    S2 = jnp.asarray(SIGMA**2)
    data = {}
    for v in variants:
        chunk = v["chunk"]
        if chunk not in data:
            nc = n // chunk
            L = jnp.asarray(l[: nc * chunk]).reshape(nc, chunk, 3)
            C = jnp.zeros((nc, chunk, 2))
            data[chunk] = (L, C, nc)
        L, C, nc = data[chunk]
        store = jnp.float32 if v["store"] == "f32" else jnp.float64
        st = (jnp.zeros((nc, chunk, 9), store), jnp.zeros((nc, chunk, 3), store),
              jnp.zeros((nc, chunk)), jnp.ones((nc, chunk)))
        fn = make_pass(v["lin"], v["trig"], chunk, v["jac"], store)
        t = time.perf_counter()
        comp = fn.lower(model, L, C, S2, x, dx, st, on).compile()
        tc = time.perf_counter() - t
        ops = count_ops(comp.as_text())
        out = jax.block_until_ready(comp(model, L, C, S2, x, dx, st, on))
        compiled.append((v, comp, (model, L, C, S2, x, dx, st, on), out, tc, ops, nc * chunk))
        del out
    times = {i: [] for i in range(len(compiled))}
    cpu = {i: [] for i in range(len(compiled))}
    for _ in range(args.rounds):
        for i, (v, comp, a, _, _, _, _) in enumerate(compiled):
            t, c = time.perf_counter(), time.process_time()
            jax.block_until_ready(comp(*a))
            times[i].append(time.perf_counter() - t)
            cpu[i].append(time.process_time() - c)
    ref = np.asarray(compiled[0][3][0])
    d = np.sqrt(np.diag(ref))
    for i, (v, comp, a, out, tc, ops, npts) in enumerate(compiled):
        N = np.asarray(out[0])
        best = min(times[i])
        rows.append({**v, "compile_s": tc, "pass_ms": best * 1e3, "median_ms": float(np.median(times[i])) * 1e3,
                     "cpu_ms": min(cpu[i]) * 1e3,
                     "ns_per_point": best / npts * 1e9, "trig_ops": ops["trig"], "divide_ops": ops["divide"],
                     "N_rel_err": float(np.max(np.abs(N - ref) / d[:, None] / d[None, :])),
                     "xla_flags": os.environ.get("XLA_FLAGS", "")})
    return rows


def variant_list(quick: bool):
    V = []
    base = dict(chunk=1 << 16, jac="f64", store="f32")
    for lin in ("rev", "fwd", "hand"):
        for trig in (False, True):
            V.append({**base, "lin": lin, "trig": trig})
    V.append({**base, "lin": "rev", "trig": True, "store": "f64"})
    V.append({**base, "lin": "rev", "trig": True, "jac": "f32"})
    V.append({**base, "lin": "hand", "trig": True, "jac": "f32"})
    if not quick:
        for ch in (1 << 12, 1 << 14, 1 << 18):
            V.append({**base, "lin": "rev", "trig": True, "chunk": ch})
    return V


FLAG_SETS = [
    "--xla_cpu_experimental_ynn_fusion_type=",
    "--xla_cpu_use_thunk_runtime=false",
]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", default="1e6")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-flags", action="store_true", help="skip the XLA_FLAGS subprocesses")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.rounds = "2.5e5", 3

    if args.child:  # subprocess with XLA_FLAGS set: a few variants, JSON on stdout
        V = [v for v in variant_list(True) if v["trig"] and v["jac"] == "f64" and v["store"] == "f32"]
        rows = run_variants(args, V)
        print("JSON:" + json.dumps(rows))
        return 0

    load0 = os.getloadavg()
    rows = run_variants(args, variant_list(args.quick))
    flag_rows, flag_notes = [], []
    if not args.no_flags:
        for flags in FLAG_SETS:
            env = dict(os.environ, XLA_FLAGS=flags)
            p = subprocess.run([sys.executable, __file__, "--child", "1", "--n", args.n,
                                "--rounds", str(args.rounds)], env=env, capture_output=True, text=True)
            line = [s for s in p.stdout.splitlines() if s.startswith("JSON:")]
            if p.returncode == 0 and line:
                flag_rows += json.loads(line[0][5:])
                flag_notes.append(f"`XLA_FLAGS={flags}`: accepted")
            else:
                err = (p.stderr.strip().splitlines() or ["?"])[-1][:200]
                flag_notes.append(f"`XLA_FLAGS={flags}`: rejected or failed ({err})")
    load1 = os.getloadavg()

    cols = [("lin", "kernel", ""), ("trig", "sincos once", ""), ("jac", "Jacobian dtype", ""),
            ("store", "store dtype", ""), ("chunk", "chunk", "d"), ("xla_flags", "XLA_FLAGS", ""),
            ("compile_s", "compile s", ".2f"), ("pass_ms", "pass ms (best)", ".0f"),
            ("median_ms", "median ms", ".0f"), ("cpu_ms", "CPU ms (best)", ".0f"),
            ("ns_per_point", "ns/point", ".0f"),
            ("trig_ops", "sin/cos/tan ops in HLO", "d"), ("N_rel_err", "N rel. err vs first", ".1e")]
    md = ["# Linearisation kernels: one fused GH pass (residual update + linearise + normals + store)\n",
          f"{int(float(args.n)):,} points, extended model (9 unknowns), float64 unless stated. "
          f"Best of {args.rounds} interleaved rounds. Load average before/after: "
          f"{load0[0]:.1f} / {load1[0]:.1f} (the machine is shared: other jobs inflate timings).\n",
          md_table(rows + flag_rows, cols)]
    if flag_notes:
        md.append("\n" + "\n".join(f"- {s}" for s in flag_notes) + "\n")
    md.append("\n```\n" + json.dumps(machine_info(), indent=1) + "\n```\n")
    text = "\n".join(md)
    print(text)
    write_results("kernels", text, {"machine": machine_info(), "n": int(float(args.n)),
                                    "load_before": load0, "load_after": load1,
                                    "rows": rows + flag_rows, "flags": flag_notes})
    return 0


if __name__ == "__main__":
    sys.exit(main())
