"""hartrao_jax._programs: compiled programs kept on disk and loaded by a later process without
tracing; the key states every argument by value or nothing is kept."""

from __future__ import annotations

import functools
import json
import os
import pickle
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hartrao_jax import _programs as P
from hartrao_jax._programs import Uncacheable, cached_jit, spec

jax.config.update("jax_enable_x64", True)
ROOT = Path(__file__).resolve().parents[1]


class _Scale(eqx.Module):
    a: jax.Array
    names: tuple[str, ...] = eqx.field(static=True)
    power: int = eqx.field(static=True, default=1)


TRACES: list[int] = []


def _body(m, x, y, *, k=2):
    TRACES.append(1)
    return {"s": (jnp.sin(x) * m.a) ** m.power * k + y, "names": m.names}, (jnp.sum(x),)


_f = cached_jit(_body, donate="all-except-first")


@cached_jit
def _apply(fn, x):
    return fn(x)


def _square(x):
    return x * x


@pytest.fixture
def programs(tmp_path, monkeypatch):
    """A fresh program directory, nothing held in memory."""
    monkeypatch.setitem(P._state, "dir", tmp_path)
    monkeypatch.delenv(P.PROGRAMS_ENV, raising=False)
    P.clear_programs()
    yield tmp_path
    P.clear_programs()


def _args(power=1, n=5):
    return (_Scale(jnp.asarray(2.0), ("a", "b"), power), jnp.arange(float(n)), jnp.ones(n))


def _same(a, b):
    la, ta = jax.tree.flatten(a)
    lb, tb = jax.tree.flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_same_results_and_donations_as_filter_jit(programs):
    ref = eqx.filter_jit(_body, donate="all-except-first")
    a, b = _args(), _args()
    _same(_f(*a, k=3), ref(*b, k=3))
    # the same arguments given up (donated) and the first kept
    assert [x.is_deleted() for x in a[1:]] == [x.is_deleted() for x in b[1:]]
    assert not a[0].a.is_deleted()


def test_written_once_then_loaded_without_tracing(programs):
    first = _f(*_args(), k=3)
    assert len(list(programs.glob("*.bin"))) == 1
    P.clear_programs()  # as a new process: nothing in memory
    n, loaded = len(TRACES), P.program_counts()["loaded"]
    _same(_f(*_args(), k=3), first)
    assert len(TRACES) == n and P.program_counts()["loaded"] == loaded + 1


def test_every_static_value_and_shape_is_a_program_of_its_own(programs):
    _f(*_args(), k=3)
    _f(*_args(), k=3)
    assert len(list(programs.glob("*.bin"))) == 1
    _f(*_args(power=2), k=3)  # a static field
    _f(*_args(), k=4)  # a static keyword
    _f(*_args(n=6), k=3)  # a shape
    assert len(list(programs.glob("*.bin"))) == 4


def test_a_closure_is_traced_as_filter_jit_and_not_kept(programs):
    c = 3.0
    x = jnp.arange(4.0)
    np.testing.assert_array_equal(_apply(lambda v: v * c, x), x * 3.0)
    assert not list(programs.glob("*.bin"))
    np.testing.assert_array_equal(_apply(_square, x), x * x)  # module level: kept
    assert len(list(programs.glob("*.bin"))) == 1


def test_a_damaged_or_foreign_file_is_compiled_again(programs):
    first = _f(*_args(), k=3)
    (path,) = programs.glob("*.bin")
    path.write_bytes(b"not a program")
    P.clear_programs()
    counts = P.program_counts()
    _same(_f(*_args(), k=3), first)
    assert P.program_counts()["compiled"] == counts["compiled"] + 1
    kept = pickle.loads(zlib.decompress(path.read_bytes()))  # written again, whole
    kept["key"] = kept["key"].replace("'names'", "'other'")
    path.write_bytes(zlib.compress(pickle.dumps(kept)))
    P.clear_programs()
    _same(_f(*_args(), k=3), first)  # a file written for another key is not used
    assert P.program_counts()["compiled"] == counts["compiled"] + 2


def test_a_file_whose_first_run_never_ended_is_condemned(programs):
    """The marker a loaded program keeps until its first run has ended: one left behind (a
    process that died inside XLA) makes the next process compile and write it again."""
    first = _f(*_args(), k=3)
    (path,) = programs.glob("*.bin")
    P.clear_programs()
    counts = P.program_counts()
    _same(_f(*_args(), k=3), first)  # loaded, run: no marker left
    assert P.program_counts()["loaded"] == counts["loaded"] + 1
    assert not list(programs.glob("*.trying"))
    path.with_name(path.name + ".trying").write_bytes(b"")  # as if that run had crashed
    P.clear_programs()
    _same(_f(*_args(), k=3), first)
    assert P.program_counts()["compiled"] == counts["compiled"] + 1
    assert path.exists() and not list(programs.glob("*.trying"))


def test_off_by_environment(programs, monkeypatch):
    monkeypatch.setenv(P.PROGRAMS_ENV, "0")
    _f(*_args(), k=3)
    assert not list(programs.glob("*.bin"))


def test_spec_states_values_exactly():
    assert spec(0.1) != spec(float(np.nextafter(0.1, 1.0)))  # one ulp
    assert spec(1) != spec(1.0) != spec(True)
    assert spec((1, 2)) != spec([1, 2])
    assert spec(np.float32) == ("ref", "numpy", "float32", "")
    assert spec(functools.partial(_square)) == ("partial", spec(_square), ("tuple",), ("dict",))
    assert spec(_Scale(jnp.ones(2), ("a",))) != spec(_Scale(jnp.ones(2), ("b",)))
    for bad in (lambda v: v, object(), _Scale(jnp.ones(2), (np.ones(2),))):
        with pytest.raises(Uncacheable):
            spec(bad)


SCRIPT = textwrap.dedent("""
    import json, sys
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    from hartrao_jax._config import enable_compilation_cache
    from hartrao_jax import _programs
    enable_compilation_cache(sys.argv[1])
    _programs.set_program_dir(sys.argv[2])
    from hartrao_jax.solver._kernel import newton_step
    N = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
    dx, Ninv, r = newton_step(N, np.array([1.0, -2.0, 0.5]))
    print(json.dumps({"dx": np.asarray(dx).tolist(), "r": float(r),
                      **_programs.program_counts()}))
""")


def test_a_later_process_loads_linear_algebra_programs(tmp_path):
    """LAPACK's kernels registered before a loaded program calls them (it crashed), and a
    program JAX's compilation cache had is compiled here before it is written (a copy of it
    failed: "Function ... not found")."""
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop(P.PROGRAMS_ENV, None)

    def run(programs: str) -> dict:
        out = subprocess.run([sys.executable, str(script), str(tmp_path / "xla"),
                              str(tmp_path / programs)], env=env, capture_output=True,
                             text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    runs = [run("a"), run("a"), run("b"), run("b")]
    assert [(r["compiled"], r["loaded"], r["written"]) for r in runs] == [
        (1, 0, 1), (0, 1, 0), (1, 0, 1), (0, 1, 0)]
    for r in runs[1:]:
        assert r["dx"] == runs[0]["dx"] and r["r"] == runs[0]["r"]


def test_a_whole_fit_from_loaded_programs_is_the_same(programs, tmp_path):
    """A two-face position adjusted with its programs compiled (and written), then again from
    the written programs alone (nothing traced): the same fit.json."""
    from hartrao_jax.campaign._campaign import load_campaign
    from hartrao_jax.fit._fit import fit_campaign
    from hartrao_jax.fit._records import fit_json
    from hartrao_jax.simulate._simulate import simulate_campaign

    camp = load_campaign(simulate_campaign(
        tmp_path / "camp", preset="demo", effects={"x4": 1.5e-4, "panel_offset": 1.5e-4},
        seed=5, step_rad=0.03, positions=[("r23", -35.0, -64.0)]).root)
    first = fit_json(fit_campaign(camp, "extended", progress=False))
    assert P.program_counts()["written"] > 0
    P.clear_programs()
    jax.clear_caches()
    counts = P.program_counts()
    again = fit_json(fit_campaign(camp, "extended", progress=False))
    assert P.program_counts()["compiled"] == counts["compiled"]  # every program loaded
    assert P.program_counts()["loaded"] > counts["loaded"]
    assert json.dumps(again, sort_keys=True) == json.dumps(first, sort_keys=True)
