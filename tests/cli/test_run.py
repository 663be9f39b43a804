"""The console command (``cli.run``): it ends the process without Python's shutdown, so its
output must be flushed, its files complete and its exit status the command's own."""

from __future__ import annotations

import json
import os
import subprocess
import sys

_CLI = [sys.executable, "-m", "hartrao_jax.cli"]


def _run(*args, fast: bool = True, **kw):
    env = {**os.environ, "HARTRAO_JAX_FAST_EXIT": "1" if fast else "0"}
    return subprocess.run([*_CLI, *args], capture_output=True, text=True, env=env, **kw)


def test_output_through_a_pipe_and_files_complete(tmp_path):
    """stdout is a pipe (block-buffered): the whole table arrives; the JSON is complete; the
    same bytes as through Python's normal shutdown."""
    outs = {}
    for fast in (True, False):
        (tmp_path / str(fast)).mkdir()
        r = _run("schedule", "--json", "plan.json", fast=fast, cwd=tmp_path / str(fast))
        assert r.returncode == 0, r.stderr
        outs[fast] = (r.stdout, (tmp_path / str(fast) / "plan.json").read_text())
    assert outs[True] == outs[False]
    rows = [ln for ln in outs[True][0].splitlines() if ln.startswith("| ")]
    assert len(rows) == 1 + 88  # the header and 88 positions
    assert outs[True][0].endswith("wrote plan.json\n")
    assert len(json.loads(outs[True][1])["positions"]) == 88


def test_bad_input_keeps_its_one_line_and_status(tmp_path):
    r = _run("fit", str(tmp_path / "missing"), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert r.stdout == ""
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("error: "), r.stderr
    assert not (tmp_path / "out").exists()


def test_version_exits_zero():
    r = _run("--version")
    assert r.returncode == 0 and "version" in r.stdout
