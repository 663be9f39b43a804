"""One command of the CLI under two versions of the package, alternated: wall, CPU and peak.

    python benchmarks/ab.py --before ae8eb1a [--after DIR] [--runs 3] [--json FILE] \
        -- fit /path/campaign --out {out}

``--before`` is a git revision of this repository, checked out into a temporary worktree
(removed at the end); ``--after`` the package root to compare it with (default: this
checkout, with its uncommitted changes). ``--env-before`` / ``--env-after KEY=VALUE`` set an
environment variable for one side only: ``--before HEAD --env-after NUMPY_MADVISE_HUGEPAGE=0``
compares a setting on the same code. Each version's bytecode is written first
(:func:`compile_package`). Each run is a fresh ``python -m hartrao_jax.cli`` process with
``PYTHONPATH`` the version's root and its working directory an empty temporary directory,
and the module actually imported is checked before the runs: from the repository's
root, ``python -m`` and ``python -c`` put the working directory first on ``sys.path``, so the
checkout there shadows ``PYTHONPATH`` and "before" silently runs the new code (two comparisons
of 2026-11-27 were made that way). ``{out}`` in the arguments becomes a new temporary
directory per run, removed after it. The versions alternate (before, after, before, ...), so a
machine that slows down during the comparison slows both.

Measured per run from the child's resource usage (``os.wait4``): wall seconds, user and system
CPU seconds, peak resident set (GiB). The paired differences (after - before, run by run)
cancel most of a drift of the machine's speed; ``benchmarks/machine_probe.py`` runs before the
first and after the last run, so the machine's state is recorded with the comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "benchmarks"))
from machine_probe import fresh as _probe  # noqa: E402
from machine_probe import line as _probe_line  # noqa: E402


def _module_root(root: Path, cwd: str, env: dict[str, str]) -> Path:
    """The directory the package is imported from with this environment and directory."""
    code = "import hartrao_jax; print(hartrao_jax.__file__)"
    out = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True,
                         text=True, check=True)
    return Path(out.stdout.strip()).resolve().parent.parent


def compile_package(root: Path) -> None:
    """Write the bytecode of the package at ``root`` (``compileall``), as ``make demo`` and
    ``make test`` do: with ``$PYTHONDONTWRITEBYTECODE`` set (as on the machines here) a
    process would otherwise compile the package's source again at every start, 0.22-0.37 s
    of each ``diagnose``, and a side with bytecode would be compared with one without."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(root / "hartrao_jax")],
                   check=True, capture_output=True)


def child_env(root: Path, extra_env: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of a command of the package at ``root``: this one, ``extra_env`` and
    ``PYTHONPATH`` the root."""
    return {**os.environ, **(extra_env or {}), "PYTHONPATH": str(root)}


def run_command(root: Path, args: list[str], cwd: str,
                extra_env: dict[str, str] | None = None) -> dict[str, float]:
    """One ``hartrao-jax`` command (``args``; ``{out}`` a new directory, removed after it) in
    a fresh process importing the package from ``root``, started in ``cwd`` (an empty
    directory: see the module doc) with ``extra_env`` added: its wall, user and system
    seconds and peak resident GiB; a failed command ends the benchmark with its last lines."""
    env = child_env(root, extra_env)
    out = tempfile.mkdtemp(prefix="ab-out-")
    shutil.rmtree(out)  # the command makes it
    argv = [a.replace("{out}", out) for a in args]
    # stderr to a file, read after the exit: a pipe read only then would block a child that
    # writes more than the pipe holds (progress bars, logs), and wait4 would wait forever
    with tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "hartrao_jax.cli", *argv], cwd=cwd,
                                env=env, stdout=subprocess.DEVNULL, stderr=err)
        _, status, ru = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        code = os.waitstatus_to_exitcode(status)
        err.seek(0)
        tail = err.read().decode(errors="replace").strip()[-400:]
    shutil.rmtree(out, ignore_errors=True)
    if code != 0:
        raise SystemExit(f"error: {root}: exit {code}: {tail}")
    return {"wall_s": wall, "user_s": ru.ru_utime, "sys_s": ru.ru_stime,
            "peak_gib": ru.ru_maxrss / 2**20}


def _span(xs: list[float], fmt: str) -> str:
    lo, hi, mid = (fmt.format(v) for v in (min(xs), max(xs), statistics.median(xs)))
    return f"{lo}-{hi} (median {mid})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="git revision of this repository")
    ap.add_argument("--after", default=str(REPO), help="package root (default: this checkout)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json", default=None, help="write the runs here as well")
    ap.add_argument("--env-before", action="append", default=[], metavar="KEY=VALUE",
                    help="an environment variable of the before runs only (repeatable)")
    ap.add_argument("--env-after", action="append", default=[], metavar="KEY=VALUE",
                    help="an environment variable of the after runs only (repeatable; with "
                         "--before HEAD and a clean checkout: one setting against another)")
    ap.add_argument("args", nargs=argparse.REMAINDER, help="-- then the command's arguments")
    a = ap.parse_args()
    args = a.args[1:] if a.args[:1] == ["--"] else a.args
    envs = {}
    for label, pairs in (("before", a.env_before), ("after", a.env_after)):
        bad = [p for p in pairs if "=" not in p or not p.split("=", 1)[0]]
        if bad:
            raise SystemExit(f"error: --env-{label}: expected KEY=VALUE, found {bad[0]!r}")
        envs[label] = dict(p.split("=", 1) for p in pairs)
    if not args:
        raise SystemExit("error: no command given (after --)")
    tree = Path(tempfile.mkdtemp(prefix="ab-before-"))
    cwd = tempfile.mkdtemp(prefix="ab-cwd-")
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(tree), a.before],
                   check=True, capture_output=True)
    try:
        roots = {"before": tree, "after": Path(a.after).resolve()}
        for label, root in roots.items():
            compile_package(root)
            got = _module_root(root, cwd, child_env(root, envs[label]))
            if got != root:
                raise SystemExit(f"error: {label}: the package comes from {got}, not {root}")
        runs: dict[str, list[dict]] = {"before": [], "after": []}
        probes = [_probe()]
        print("machine before:", _probe_line(probes[0]), flush=True)
        for i in range(a.runs):
            for label, root in roots.items():
                r = run_command(root, args, cwd, envs[label])
                runs[label].append(r)
                print(f"{label} {i + 1}: {r['wall_s']:.2f} s wall, {r['user_s']:.2f} user, "
                      f"{r['sys_s']:.2f} sys, {r['peak_gib']:.2f} GiB", flush=True)
        probes.append(_probe())
        print("machine after:", _probe_line(probes[1]), flush=True)
    finally:
        subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)],
                       capture_output=True)
        shutil.rmtree(cwd, ignore_errors=True)
    print(f"\n`hartrao-jax {' '.join(args)}`, {a.runs} runs each, alternated\n")
    print("| | wall s | user s | sys s | peak GiB |\n|---|---|---|---|---|")
    for label, rs in runs.items():
        name = (a.before if label == "before" else a.after) + "".join(
            f", {k}={v}" for k, v in envs[label].items())
        print(f"| {label} ({name}) | " + " | ".join(
            _span([r[k] for r in rs], f) for k, f in (("wall_s", "{:.2f}"), ("user_s", "{:.1f}"),
                                                      ("sys_s", "{:.1f}"),
                                                      ("peak_gib", "{:.2f}"))) + " |")
    paired = [q["wall_s"] - p["wall_s"] for p, q in zip(runs["before"], runs["after"])]
    print(f"\npaired differences (after - before), wall s: {min(paired):+.2f} to "
          f"{max(paired):+.2f} (median {statistics.median(paired):+.2f})")
    if a.json:
        Path(a.json).write_text(json.dumps({"before": a.before, "after": a.after,
                                            "args": args, "env": envs, "runs": runs,
                                            "paired_wall_s": paired,
                                            "machine_probe": probes}, indent=1))


if __name__ == "__main__":
    main()
