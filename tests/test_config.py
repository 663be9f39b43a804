"""Process-wide settings: a process drops its in-memory compiled programs before it runs out
of memory maps."""

from __future__ import annotations

import jax
import pytest


def test_compiled_programs_are_dropped_near_the_memory_map_limit():
    """Past the share of vm.max_map_count the in-memory programs go (and their maps with
    them); below it nothing happens."""
    from hartrao_jax._config import memory_maps, release_compiled_programs

    m = memory_maps()
    if m is None:
        return  # no /proc here: nothing to measure
    f = jax.jit(lambda x: x * 2.0)
    f(1.0)
    assert not release_compiled_programs(fraction=1.0)
    assert f._cache_size() == 1
    assert release_compiled_programs(fraction=0.0)
    assert f._cache_size() == 0


def test_freed_memory_is_kept_unless_switched_off(monkeypatch):
    """The CLI keeps freed memory for reuse (glibc mallopt, Linux; Arrow's system pool); the
    environment switch turns it off before anything is changed."""
    import sys

    from hartrao_jax._config import KEEP_FREED_MEMORY_ENV, keep_freed_memory

    monkeypatch.setenv(KEEP_FREED_MEMORY_ENV, "0")
    assert keep_freed_memory() is False
    monkeypatch.delenv(KEEP_FREED_MEMORY_ENV)
    try:
        import ctypes

        ctypes.CDLL("libc.so.6")
        glibc = sys.platform.startswith("linux")
    except OSError:
        glibc = False
    assert keep_freed_memory() is glibc
    if glibc:  # Arrow's buffers from the same heap
        import pyarrow as pa

        assert pa.default_memory_pool().backend_name == "system"


def test_freed_memory_environment_for_new_processes(monkeypatch):
    """The same settings as the environment of a process about to start (Dask workers of
    ``fit-stream --dask``), and nothing where the switch turns keeping off."""
    from hartrao_jax._config import KEEP_FREED_MEMORY_ENV, keep_freed_environment

    monkeypatch.setenv(KEEP_FREED_MEMORY_ENV, "0")
    assert keep_freed_environment() == {}
    monkeypatch.delenv(KEEP_FREED_MEMORY_ENV)
    assert keep_freed_environment() == {
        "MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(2**31 - 1),
        "MALLOC_ARENA_MAX": "1", "ARROW_DEFAULT_MEMORY_POOL": "system"}


def test_blas_libraries_run_one_thread_unless_told_otherwise():
    """Every OpenBLAS library a process has loaded (NumPy's and SciPy's copies) runs one
    thread after :func:`set_blas_threads`, the user's ``$OPENBLAS_NUM_THREADS`` where set,
    or the number given (fresh processes: a library reads the variable as it loads)."""
    import json
    import os
    import subprocess
    import sys

    code = """
import ctypes, json
import numpy, scipy.special
from hartrao_jax._config import blas_libraries, set_blas_threads
def threads():
    out = []
    for path in blas_libraries():
        lib = ctypes.CDLL(path)
        for name in ("openblas_get_num_threads", "openblas_get_num_threads64_",
                     "scipy_openblas_get_num_threads", "scipy_openblas_get_num_threads64_"):
            if hasattr(lib, name):
                out.append(getattr(lib, name)())
                break
    return out
done = set_blas_threads()
first = threads()
print(json.dumps([done, first, set_blas_threads(3), threads()]))
"""
    if not sys.platform.startswith("linux"):
        return

    def run(**extra):
        env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"} | extra
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             check=True, env=env).stdout
        return json.loads(out.splitlines()[-1])

    done, threads, done3, threads3 = run()
    if not threads:
        pytest.skip("NumPy and SciPy brought no OpenBLAS here (another BLAS)")
    n = len(threads)
    assert (done, threads, done3, threads3) == (n, [1] * n, n, [3] * n)
    done, threads, _, _ = run(OPENBLAS_NUM_THREADS="2")
    assert (done, threads) == (n, [2] * n)

def test_free_heap_goes_back_to_the_kernel():
    """With freed memory kept (a new process, as the CLI sets it), 512 MiB freed stay resident
    until :func:`return_free_heap` gives the free blocks' pages back."""
    import subprocess
    import sys

    code = """
import ctypes, sys
try:
    ctypes.CDLL("libc.so.6")
except OSError:
    print("skip"); sys.exit(0)
import numpy as np
from hartrao_jax._config import keep_freed_memory, return_free_heap
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
assert keep_freed_memory()
keep = np.ones(2**20)  # something live above the freed block: the heap's top is not free
a = np.ones(2**26); tail = np.ones(2**16); del a
before = rss()
assert return_free_heap()
print(before - rss())
"""
    if not sys.platform.startswith("linux"):
        return
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()[-1]
    if out != "skip":
        assert float(out) > 400.0, out  # MiB given back of the 512 freed


def test_lendable_arrays_go_to_the_device_without_a_copy():
    """``lendable_empty``'s data start on a 64-byte boundary, so ``device_put`` lends them to
    the CPU device (the same memory); a NumPy array at glibc's 16-byte alignment is copied."""
    import numpy as np

    from hartrao_jax._config import DEVICE_ALIGN, lendable_empty

    for shape, dtype in (((1000, 3), np.float64), ((4097,), np.float32), ((7, 2), np.int32)):
        a = lendable_empty(shape, dtype)
        assert a.shape == shape and a.dtype == dtype and a.flags.c_contiguous
        assert a.ctypes.data % DEVICE_ALIGN == 0
        a[...] = 1
        d = jax.device_put(a)
        assert d.unsafe_buffer_pointer() == a.ctypes.data
        np.testing.assert_array_equal(np.asarray(d), a)


def test_arrays_are_lent_where_they_can_be_and_copied_once_where_not():
    """``lend_to_device``: an aligned array of the asked dtype is shared; a misaligned one, a
    strided one or one of another dtype is copied (once), with the same values."""
    import numpy as np

    from hartrao_jax._config import lend_to_device, lendable_empty

    a = lendable_empty((500, 3), np.float64)
    a[...] = np.arange(1500).reshape(500, 3)
    assert lend_to_device(a).unsafe_buffer_pointer() == a.ctypes.data
    for b, dtype in ((a[1:], None), (a[:, 1], None), (a, np.float32)):
        d = lend_to_device(b, dtype)
        assert d.dtype == (b.dtype if dtype is None else dtype)
        np.testing.assert_array_equal(np.asarray(d), b.astype(d.dtype))
        assert d.unsafe_buffer_pointer() != a.ctypes.data


def test_each_in_threads_keeps_the_order_and_runs_alone_on_one_core(monkeypatch):
    """The items' results in the items' order over the cores (tuples spread as arguments),
    and in the calling thread where one core is usable."""
    import threading

    from hartrao_jax._config import THREADS_ENV, each_in_threads

    monkeypatch.setenv(THREADS_ENV, "2")
    assert each_in_threads(lambda a, b: a * b, [(i, 3) for i in range(50)], "test") == [
        3 * i for i in range(50)]
    assert each_in_threads(lambda a: -a, range(5), "test") == [0, -1, -2, -3, -4]
    monkeypatch.setenv(THREADS_ENV, "1")
    main = threading.get_ident()
    assert each_in_threads(lambda a: threading.get_ident(), range(3), "test") == [main] * 3


def test_on_device_is_jnp_asarray_without_a_program():
    """A host value put on the device by a transfer is the array ``jnp.asarray`` makes (dtype,
    shape, value, weak type of a Python scalar), and lowers no conversion program."""
    import logging

    import jax.numpy as jnp
    import numpy as np

    from hartrao_jax._config import on_device

    cases = [(1.0, None), (np.inf, None), (3, None), (True, bool), (0.25, np.float64),
             ((1e-8, 2e-8, 3e-8), None), ([0.5, 1.5], float), (np.zeros((0,), np.int32), None),
             (np.arange(6.0).reshape(2, 3), np.float64)]
    seen: list[str] = []

    class Catch(logging.Handler):
        def emit(self, rec):
            seen.append(rec.getMessage())

    h = Catch()
    logger = logging.getLogger("jax._src.interpreters.pxla")
    old = logger.level
    logger.addHandler(h)
    logger.setLevel(logging.DEBUG)
    try:
        with jax.log_compiles(True):
            got = [on_device(v, d) for v, d in cases]
    finally:
        logger.removeHandler(h)
        logger.setLevel(old)
    assert not [m for m in seen if m.startswith("Compiling")]
    for (v, d), a in zip(cases, got):
        want = jnp.asarray(v, d)
        assert isinstance(a, jax.Array)
        assert (a.dtype, a.shape, a.weak_type) == (want.dtype, want.shape, want.weak_type)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(want))


def test_xla_flags_are_added_unless_the_environment_names_them(monkeypatch):
    """The package's XLA options join ``$XLA_FLAGS``; an option the variable already sets
    (to any value) is left as the user set it, and the other options are kept."""
    from hartrao_jax._config import set_xla_flags

    ynn = "--xla_cpu_experimental_ynn_fusion_type"
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert set_xla_flags((f"{ynn}=",)) == f"{ynn}="
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    assert set_xla_flags((f"{ynn}=",)).split() == ["--xla_cpu_multi_thread_eigen=false",
                                                    f"{ynn}="]
    monkeypatch.setenv("XLA_FLAGS", f"{ynn}=dot --xla_cpu_multi_thread_eigen=false")
    assert set_xla_flags((f"{ynn}=",)) == f"{ynn}=dot --xla_cpu_multi_thread_eigen=false"


def test_importing_the_package_turns_ynnpack_fusions_off():
    """In a fresh process, ``import hartrao_jax`` sets the option before JAX starts: a
    compiled ``(n, 3) x (3, 3)`` product holds no YNNPACK fusion; the user's own
    ``$XLA_FLAGS`` naming the option is left as it was."""
    import os
    import subprocess
    import sys

    code = ("import os, hartrao_jax, jax, jax.numpy as jnp\n"
            "f = jax.jit(lambda a, b: a @ b)\n"
            "print('ynn' in f.lower(jnp.ones((4096, 3)), jnp.ones((3, 3))).compile()"
            ".as_text().lower(), os.environ['XLA_FLAGS'])\n")
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert got == ["False", "--xla_cpu_experimental_ynn_fusion_type="]
    env["XLA_FLAGS"] = "--xla_cpu_experimental_ynn_fusion_type=dot"
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert got[1:] == ["--xla_cpu_experimental_ynn_fusion_type=dot"]
