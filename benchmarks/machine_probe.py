"""How fast this machine is right now: a few seconds of fixed work, so that timings taken at
different hours or on different machines can be told apart from changes of the code.

    python benchmarks/machine_probe.py [--json]

Measured in this process (start it fresh: its first touch of memory is one of the probes):

* ``python_loop_s``: 3e6 iterations of an interpreted loop (one core, the GIL's pace);
* ``numpy_sin_s``: ``np.sin`` of 1e7 float64 values into an existing array (one core);
* ``numpy_sin_2threads_s``: the same in two threads at once, 1e7 values each (both cores:
  NumPy releases the GIL in its loops). Twice ``numpy_sin_s``'s work in about its time on two
  free cores; a host that slows the second core, or both when both run, shows here and not
  in the one-core figures (2026-11-28: every command 15-25 % slower within an hour, the
  one-core probes unchanged);
* ``first_touch_s_per_gib``: writing 1 GiB of memory this process never had (in NumPy's huge
  pages where the kernel gives them; 4 KiB pages took 0.40-0.44 s per GiB on the machine
  where huge pages took 1.8-1.9 s, `results/profile.md`). On a virtual
  machine whose host backs guest memory lazily, or takes freed memory back, this cost grows
  by an order of magnitude (0.12 s per GiB to 3.5 s per GiB measured on one machine within an
  hour, 2026-11-28), and every command that allocates fresh arrays pays it;
* ``retouch_s_per_gib``: the same 1 GiB written again (the memory is the process's now);
* ``read_gb_s``: summing 1 GiB already in memory.

``benchmarks/ab.py`` runs it before and after its comparisons.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

GIB = 1 << 30


def _sin_into(a: np.ndarray, out: np.ndarray) -> None:
    np.sin(a, out=out)


def probe() -> dict[str, float]:
    """The probes of the module docstring (seconds; GB/s for ``read_gb_s``)."""
    out = {}
    t = time.perf_counter()
    k = 0
    for i in range(3_000_000):
        k += i
    out["python_loop_s"] = time.perf_counter() - t
    x = np.random.default_rng(0).random(10**7)
    y = np.empty_like(x)
    np.sin(x, out=y)
    t = time.perf_counter()
    np.sin(x, out=y)
    out["numpy_sin_s"] = time.perf_counter() - t
    xs, ys = (x, x[::-1].copy()), (y, np.empty_like(x))
    with ThreadPoolExecutor(2) as ex:
        list(ex.map(_sin_into, xs, ys))  # (the threads started)
        t = time.perf_counter()
        list(ex.map(_sin_into, xs, ys))
        out["numpy_sin_2threads_s"] = time.perf_counter() - t
    del x, y, xs, ys
    b = np.empty(GIB // 8)
    t = time.perf_counter()
    b[...] = 1.0
    out["first_touch_s_per_gib"] = time.perf_counter() - t
    t = time.perf_counter()
    b[...] = 2.0
    out["retouch_s_per_gib"] = time.perf_counter() - t
    t = time.perf_counter()
    b.sum()
    out["read_gb_s"] = GIB / (time.perf_counter() - t) / 1e9
    return out


def fresh() -> dict[str, float]:
    """:func:`probe` in a process of its own (its first touch is then of fresh memory)."""
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--json"],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def line(p: dict[str, float]) -> str:
    """One line of a probe's figures."""
    two = p.get("numpy_sin_2threads_s")  # (not in the probes of earlier JSON files)
    return (f"python loop {p['python_loop_s']:.3f} s, sin 1e7 {p['numpy_sin_s']:.3f} s"
            + (f" (two threads {two:.3f} s), " if two is not None else ", ") +
            f"first touch {p['first_touch_s_per_gib']:.2f} s/GiB, again "
            f"{p['retouch_s_per_gib']:.2f} s/GiB, read {p['read_gb_s']:.1f} GB/s")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    a = ap.parse_args(argv)
    p = probe()
    print(json.dumps(p) if a.json else line(p))


if __name__ == "__main__":
    main()
