"""Linearisation kernels for the Gauss-Helmert iteration: which kernel, precision, chunk, flags.

Times the work of ONE iteration over all points, for

* ``pkg two-pass``: what ``hartrao_jax.solver._ghm`` does now (``_pass_normals`` +
  ``_pass_residuals``, i.e. two linearisations per point and iteration);
* ``one-pass``: the fused pass of ``_kernels.make_pass`` (residual update of iteration k-1 from
  the stored ``a, b, w, m`` + ONE linearisation + normal equations + in-place store), with
  kernel ``rev`` (``value_and_grad`` under ``vmap``), ``fwd`` (``jacfwd`` over ``(x, l)``) or
  ``hand`` (hand-derived derivatives), with/without ``sincos`` computed once
  (:func:`_kernels.materialize_trig`), with/without the linearisation materialised once
  (``_kernels._materialize``), float32/float64 store, several chunk sizes;

and, each in a subprocess, the effect of ``XLA_FLAGS`` values. Variants are interleaved over
rounds and the best is kept (the machine is shared: other jobs make single timings noisy); both
wall and process CPU time are reported. Also counts the transcendental ops left in the optimised
HLO.

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
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    SIGMA,
    X0,
    hand_linearize,
    machine_info,
    make_scan,
    md_table,
    write_results,
)


def count_ops(txt: str) -> dict:
    out = {k: len(re.findall(rf"\b{k}\(", txt)) for k in ("sine", "cosine", "tan", "divide")}
    out["trig"] = out["sine"] + out["cosine"] + out["tan"]
    out["ynn_fusions"] = len(re.findall(r"kind=kCustom", txt))
    return out


def run_variants(n: int, rounds: int, variants: list[dict]) -> list[dict]:
    import _kernels as K
    import jax
    import jax.numpy as jnp

    import hartrao_jax  # noqa: F401  (float64)
    from hartrao_jax import make_model
    from hartrao_jax.solver import _ghm

    model = make_model("extended")
    hand = K.make_hand_linearize(hand_linearize)
    lins = {"rev": K.linearize_rev, "fwd": K.linearize_fwd, "hand": hand}
    l = jnp.asarray(make_scan(n))
    C = jnp.zeros((n, 2))
    W = jnp.ones(n)
    on = jnp.ones((), bool)
    x = jnp.asarray(X0)
    dx = jnp.full(9, 1e-9)
    sig = jnp.asarray(SIGMA)

    def build(v):
        if v["method"] == "pkg two-pass":
            chunk = v["chunk"]

            def it(cond, l, C, W, x, dx, on):
                (L, Cc, Wc, S2, V0), nn = _ghm._chunked(
                    [l, C, W, jnp.broadcast_to(sig**2, l.shape), jnp.zeros_like(l)], chunk)
                Wc = Wc.reshape(-1).at[nn:].set(0.0).reshape(Wc.shape)  # as _gauss_helmert
                N, nv = _ghm._pass_normals(cond, L, V0, Cc, Wc, S2, x)
                Vn, _, om = _ghm._pass_residuals(cond, L, V0, Cc, Wc, S2, x, dx)
                return N, nv, om
            return jax.jit(it)
        lin = lins[v["lin"]]
        store = jnp.float32 if v["store"] == "f32" else jnp.float64

        def it(cond, l, C, W, x, dx, on):
            one_pass, _, store0, _ = K.make_pass(cond, l, C, W, sig, on, lin=lin, chunk=v["chunk"],
                                                 trig=v["trig"], store_dtype=store, mat=v["mat"])
            N, nv, st = one_pass(x, dx, store0(9))
            return N, nv, st[2][0, 0]
        return jax.jit(it)

    args = (model, l, C, W, x, dx, on)
    compiled = []
    for v in variants:
        t = time.perf_counter()
        comp = build(v).lower(*args).compile()
        tc = time.perf_counter() - t
        ops = count_ops(comp.as_text())
        out = jax.block_until_ready(comp(*args))
        compiled.append((v, comp, np.asarray(out[0]), tc, ops))
    wall = {i: [] for i in range(len(compiled))}
    cpu = {i: [] for i in range(len(compiled))}
    for _ in range(rounds):
        for i, (v, comp, *_rest) in enumerate(compiled):
            t, c = time.perf_counter(), time.process_time()
            jax.block_until_ready(comp(*args))
            wall[i].append(time.perf_counter() - t)
            cpu[i].append(time.process_time() - c)
    ref = compiled[0][2]
    d = np.sqrt(np.diag(ref))
    rows = []
    for i, (v, comp, N, tc, ops) in enumerate(compiled):
        rows.append({**v, "compile_s": tc, "wall_ms": min(wall[i]) * 1e3,
                     "median_ms": float(np.median(wall[i])) * 1e3, "cpu_ms": min(cpu[i]) * 1e3,
                     "ns_per_point": min(min(wall[i]), min(cpu[i])) / n * 1e9,
                     "trig_ops": ops["trig"], "ynn_fusions": ops["ynn_fusions"],
                     "N_rel_err": float(np.max(np.abs(N - ref) / d[:, None] / d[None, :])),
                     "xla_flags": os.environ.get("XLA_FLAGS", "")})
    return rows


def variant_list(quick: bool, flags_child: bool = False) -> list[dict]:
    one = dict(method="one-pass", chunk=1 << 16, store="f32", trig=True, mat=True)
    if flags_child:
        return [dict(method="pkg two-pass", lin="rev", chunk=1 << 16, store="", trig=False,
                     mat=False),
                {**one, "lin": "rev"}, {**one, "lin": "hand"}]
    V = [dict(method="pkg two-pass", lin="rev", chunk=1 << 16, store="", trig=False, mat=False)]
    for lin in ("rev", "fwd", "hand"):
        V.append({**one, "lin": lin, "trig": False, "mat": False})
        V.append({**one, "lin": lin, "trig": True, "mat": False})
        V.append({**one, "lin": lin})
    V.append({**one, "lin": "rev", "store": "f64"})
    if not quick:
        for ch in (1 << 12, 1 << 14, 1 << 18):
            V.append({**one, "lin": "rev", "chunk": ch})
            V.append({**one, "lin": "hand", "chunk": ch})
    return V


FLAG_SETS = [
    "--xla_cpu_experimental_ynn_fusion_type=",
    "--xla_cpu_experimental_ynn_fusion_type=dot,eltwise,reduce",
]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", default="1e6")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-flags", action="store_true", help="skip the XLA_FLAGS subprocesses")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.rounds = "2.5e5", 3
    n = int(float(args.n))

    if args.child:  # subprocess with XLA_FLAGS set: a few variants, JSON on stdout
        rows = run_variants(n, args.rounds, variant_list(True, flags_child=True))
        print("JSON:" + json.dumps(rows))
        return 0

    load0 = os.getloadavg()
    rows = run_variants(n, args.rounds, variant_list(args.quick))
    flag_rows, flag_notes = [], []
    if not args.no_flags:
        for flags in [""] + FLAG_SETS:
            env = dict(os.environ)
            env.pop("XLA_FLAGS", None)
            if flags:
                env["XLA_FLAGS"] = flags
            p = subprocess.run([sys.executable, __file__, "--child", "--n", args.n,
                                "--rounds", str(args.rounds)],
                               env=env, capture_output=True, text=True)
            line = [s for s in p.stdout.splitlines() if s.startswith("JSON:")]
            label = f"`XLA_FLAGS={flags}`" if flags else "no XLA_FLAGS (default)"
            if p.returncode == 0 and line:
                flag_rows += json.loads(line[0][5:])
                flag_notes.append(f"{label}: accepted")
            else:
                err = (p.stderr.strip().splitlines() or ["?"])
                err = next((e for e in err if "Illegal" in e or "rror" in e), err[-1])[:200]
                flag_notes.append(f"{label}: rejected or failed ({err})")
    load1 = os.getloadavg()

    cols = [("method", "method", ""), ("lin", "kernel", ""), ("trig", "sincos once", ""),
            ("mat", "lin. materialised", ""), ("store", "store", ""), ("chunk", "chunk", "d"),
            ("compile_s", "compile s", ".2f"), ("wall_ms", "wall ms (best)", ".0f"),
            ("median_ms", "wall ms (median)", ".0f"), ("cpu_ms", "CPU ms (best)", ".0f"),
            ("ns_per_point", "ns/point", ".0f"), ("trig_ops", "sin/cos/tan in HLO", "d"),
            ("N_rel_err", "N rel. err", ".1e")]
    fcols = [("xla_flags", "XLA_FLAGS", ""), ("method", "method", ""), ("lin", "kernel", ""),
             ("compile_s", "compile s", ".2f"), ("wall_ms", "wall ms (best)", ".0f"),
             ("cpu_ms", "CPU ms (best)", ".0f"), ("ynn_fusions", "YNN fusions in HLO", "d")]
    md = ["# Linearisation kernels: the work of one GH iteration over all points\n",
          f"{n:,} points, extended model (9 unknowns), float64. `pkg two-pass` = the current "
          "`_ghm` iteration (normals pass + residual pass, two linearisations per point); "
          "`one-pass` = `_kernels.make_pass` (one linearisation per point and iteration). "
          f"Best of {args.rounds} interleaved rounds; ns/point uses the smaller of wall and CPU. "
          f"Load average before/after: {load0[0]:.1f} / {load1[0]:.1f} on {os.cpu_count()} cores "
          "(the machine is shared: other jobs inflate timings).\n",
          md_table(rows, cols)]
    if flag_rows or flag_notes:
        md += ["\n## XLA_FLAGS (each in a fresh process)\n", md_table(flag_rows, fcols),
               "\n" + "\n".join(f"- {s}" for s in flag_notes) + "\n"]
    md.append("\n```\n" + json.dumps(machine_info(), indent=1) + "\n```\n")
    text = "\n".join(md)
    print(text)
    write_results("kernels", text, {"machine": machine_info(), "n": n, "load_before": load0,
                                    "load_after": load1, "rows": rows, "flag_rows": flag_rows,
                                    "flags": flag_notes})
    return 0


if __name__ == "__main__":
    sys.exit(main())
