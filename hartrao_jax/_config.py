"""Process-wide settings: float64, the XLA compilation cache, the threads work may use, where the
real recordings are."""

from __future__ import annotations

import ctypes
import os
import sys
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import numpy as np

from ._programs import clear_programs, set_program_dir

#: Threads this process's work may use (default: the cores it may run on).
THREADS_ENV = "HARTRAO_JAX_THREADS"
_POOLS: dict[tuple[str, int], ThreadPoolExecutor] = {}


#: Rows of a block of per-point work on a large table (NumPy's or a compiled program's): a
#: block's temporaries (2 MiB a float64 column) are reused from the heap by the next block,
#: where whole columns of 1e7 points would each take fresh pages from the kernel (on a VM,
#: about 0.3 s per GB in 4 KiB pages and up to 2.4 s per GB in NumPy's huge pages, measured).
BLOCK_ROWS = 1 << 18


def row_blocks(n: int, rows: int = BLOCK_ROWS) -> list[slice]:
    """The rows ``0..n`` cut into consecutive slices of ``rows`` (the last one shorter)."""
    return [slice(s, min(s + rows, n)) for s in range(0, n, rows)]


def by_row_blocks(fn, rows: tuple, block: int = BLOCK_ROWS, live: int | None = None) -> tuple:
    """``fn(*rows)`` for a per-point ``fn`` (row ``i`` of each output depends on row ``i`` of
    each input alone) of arrays ``rows`` with a common first axis: a table of more than
    ``block`` rows a block at a time into NumPy arrays (every block of that size, the last
    one ending at the table's end, so that it is one program; two blocks at a time, one's
    copies while the other computes); a smaller one in one call. A tuple of the outputs
    (aligned for the device where blocked: :func:`lendable_empty`).

    With :data:`BLOCK_ROWS` rows a block, a program's temporaries (150 B per point for
    :func:`.fit._projection.hit_points`) take a block's memory, reused by the next block,
    instead of new pages for the whole table (1.26e7 points: 1.9 GB, 630,000 page faults).

    ``live``: the rows from ``live`` on are padding (a size bucket's), whose outputs nobody
    reads: a table of more than ``block`` live rows computes only those (the blocks keep
    their size, so no new program); the padding's outputs of a table taken in blocks are
    zero (a large position's table of 1.30e7 rows in a bucket of 1.47e7: 12 % of the work). A
    table of at most one block is one call over every row, as before (a program per bucket,
    not per live size)."""
    n = rows[0].shape[0]
    m = live if live is not None and block < live < n else n  # the rows computed
    if m <= block:
        return tuple(fn(*rows))
    rows = tuple(np.asarray(r) for r in rows)
    out: list[np.ndarray] = []

    def one(start):
        s = min(start, m - block)
        got = fn(*(r[s:s + block] for r in rows))
        for o, g in zip(out, got):
            o[s:s + block] = np.asarray(g)  # (nothing returned: the block's arrays let go)

    first = fn(*(r[:block] for r in rows))
    out.extend(lendable_empty((n,) + g.shape[1:], g.dtype) for g in first)
    for o, g in zip(out, first):
        o[:block] = np.asarray(g)
    list(thread_pool(2, "row_blocks").map(one, range(block, m, block)))
    if live is not None:  # the padding zero, computed or not
        for o in out:
            o[live:] = 0
    return tuple(out)


def small_key_order(keys: np.ndarray, n_keys: int) -> np.ndarray:
    """Indices sorting ``keys`` (integers in ``0 .. n_keys - 1``), stable. Where they fit 16
    bits NumPy's stable sort is a radix sort: 5-10x a merge sort of wider keys (1.26e7
    shuffled keys 0.87 -> 0.08 s), the same order."""
    keys = np.asarray(keys)
    return np.argsort(keys.astype(np.uint16) if n_keys <= 1 << 16 else keys, kind="stable")


#: Byte alignment of a host array that ``jax.device_put`` lends to the CPU device instead of
#: copying (XLA's CPU buffers; glibc's ``malloc`` aligns NumPy's data to 16 bytes only).
DEVICE_ALIGN = 64


def lendable_empty(shape: tuple[int, ...], dtype) -> np.ndarray:
    """An uninitialised NumPy array whose data start on a :data:`DEVICE_ALIGN` boundary:
    ``jax.device_put`` of it (whole) makes no copy. For large arrays built on the host for the
    device (a copy of 1.2 GB of a random effect's points took their memory twice)."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    raw = np.empty(nbytes + DEVICE_ALIGN, np.uint8)
    start = -raw.ctypes.data % DEVICE_ALIGN
    return raw[start:start + nbytes].view(dtype).reshape(shape)


def on_device(v, dtype=None) -> jax.Array:
    """``jnp.asarray(v, dtype)`` of a host value by a transfer: the same array (a Python
    scalar weakly typed, as there), without the conversion program that ``jnp.asarray`` of a
    host value lowers and loads per shape and dtype in every process (7-10 ms each)."""
    if dtype is None and isinstance(v, (bool, int, float, complex)):
        return jax.device_put(v)
    return jax.device_put(np.asarray(v, dtype))


def lend_to_device(a, dtype=None) -> jax.Array:
    """``a`` (as ``dtype``) on the CPU device, sharing the host array's memory where it can
    (C-contiguous, of that dtype, on a :data:`DEVICE_ALIGN` boundary: :func:`lendable_empty`);
    else copied once, into a lendable array. The host array must not be written to while the
    device array is in use."""
    a = np.asarray(a)
    dtype = a.dtype if dtype is None else np.dtype(dtype)
    if not (a.dtype == dtype and a.flags.c_contiguous and a.ctypes.data % DEVICE_ALIGN == 0):
        b = lendable_empty(a.shape, dtype)
        b[...] = a
        a = b
    return jax.device_put(a)


def machine_cores() -> int:
    """The cores this process may run on (its CPU affinity on Linux; elsewhere the core
    count): those XLA's own threads span."""
    affinity = getattr(os, "sched_getaffinity", None)
    return max(1, len(affinity(0)) if affinity else os.cpu_count() or 1)


def usable_cores() -> int:
    """The threads this process's work may use: ``$HARTRAO_JAX_THREADS`` (a Dask worker's
    one, other processes using the other cores), else :func:`machine_cores`."""
    env = os.environ.get(THREADS_ENV)
    return max(1, int(env)) if env else machine_cores()


def thread_pool(threads: int, name: str) -> ThreadPoolExecutor:
    """The process's pool of ``threads`` threads for the parts of ``name``'s work (threads
    ``hartrao-<name>_<i>``). A task of a pool must never wait for another task of the same
    pool (each user has its own name)."""
    key = (name, threads)
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(threads, thread_name_prefix=f"hartrao-{name}")
    return _POOLS[key]


def threads_for(items: int) -> int:
    """The threads :func:`each_in_threads` runs ``items`` items in: the usable cores, at most
    one per item."""
    return min(usable_cores(), items)


def each_in_threads(fn, items: Sequence, name: str) -> list:
    """``[fn(*item) for item in items]`` (an item that is not a tuple is one argument) with
    the items over the usable cores (:func:`usable_cores`; the pool of ``name``, see
    :func:`thread_pool`), in their order: for work whose NumPy or SciPy loops release the
    GIL, each item's result the same as in one thread."""
    args = [it if isinstance(it, tuple) else (it,) for it in items]
    threads = threads_for(len(args))
    if threads < 2:
        return [fn(*a) for a in args]
    return list(thread_pool(threads, name).map(lambda a: fn(*a), args))


def enable_x64() -> None:
    """The adjustment needs float64 (focal length to 1e-7 relative, angles to 1e-8 rad)."""
    jax.config.update("jax_enable_x64", True)


#: XLA options the package adds to ``$XLA_FLAGS`` (:func:`set_xla_flags`). YNNPACK fusions
#: off: XLA:CPU (jaxlib 0.10) hands every ``dot`` and some element-wise and reduction
#: fusions to YNNPACK, whose float64 kernels ran the per-point 3 x 3 rotations of the
#: condition and their derivatives, ``(n, 3) x (3, 3)`` products, at 5-16 % of a command's
#: CPU; XLA's own loops do them in less. Measured (``benchmarks/ab.py``, 5 alternated pairs
#: each, ``benchmarks/results/profile.md``): the 1.30e7-row position's ``fit`` 1.3 s faster
#: (median), the 12-scan ``fit`` 0.5 s, ``diagnose`` 0.6 s; results equal to 4e-8 relative
#: (the order of float64 sums).
XLA_FLAGS = ("--xla_cpu_experimental_ynn_fusion_type=",)


def set_xla_flags(flags: Sequence[str] = XLA_FLAGS) -> str:
    """Add ``flags`` (``--name=value``) to ``$XLA_FLAGS``, each unless that variable already
    names its option (a user's own setting wins); returns the variable's value.

    XLA reads the variable when JAX starts its first backend: importing the package does this
    before any computation of its own, but not after a program that ran JAX first."""
    have = os.environ.get("XLA_FLAGS", "").split()
    named = {f.split("=", 1)[0] for f in have}
    add = [f for f in flags if f.split("=", 1)[0] not in named]
    if add:
        os.environ["XLA_FLAGS"] = " ".join(have + add)
    return os.environ.get("XLA_FLAGS", "")


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Persistent XLA compilation cache, so a second CLI run does not compile again; its
    ``programs`` folder keeps :func:`._programs.cached_jit`'s programs, so that it does not
    trace them again either.

    Default location ``$HARTRAO_JAX_CACHE`` or ``~/.cache/hartrao-jax/xla``; every compiled
    program is cached (minimum compile time 0 s). Unbounded: JAX's bounded (LRU) cache scans
    every entry before each write (0.23 s per write at 12,000 entries), which made the test
    suite minutes slower. Concurrent processes may read an entry while another writes it; the
    compressed entry is then incomplete, JAX warns and compiles again.
    """
    p = Path(path or os.environ.get("HARTRAO_JAX_CACHE")
             or Path.home() / ".cache" / "hartrao-jax" / "xla")
    p.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(p))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    set_program_dir(p / "programs")  # and the traced programs themselves (._programs)
    return p


#: ``$HARTRAO_JAX_KEEP_FREED_MEMORY=0`` turns :func:`keep_freed_memory` (and
#: :func:`keep_freed_environment`) off.
KEEP_FREED_MEMORY_ENV = "HARTRAO_JAX_KEEP_FREED_MEMORY"
#: glibc's malloc settings of :func:`keep_freed_memory`: ``(mallopt parameter of <malloc.h>,
#: the environment variable glibc reads when a process starts, value)``: no memory maps for
#: large blocks, the heap's top kept up to 2 GiB, one heap for every thread.
MALLOC_SETTINGS = ((-4, "MALLOC_MMAP_MAX_", 0), (-1, "MALLOC_TRIM_THRESHOLD_", 2**31 - 1),
                   (-8, "MALLOC_ARENA_MAX", 1))


def keep_freed_wanted() -> bool:
    """False where ``$HARTRAO_JAX_KEEP_FREED_MEMORY=0`` turns keeping freed memory off."""
    return os.environ.get(KEEP_FREED_MEMORY_ENV, "1") != "0"


def keep_freed_environment() -> dict[str, str]:
    """:func:`keep_freed_memory`'s settings (and Arrow's system pool) as the environment of a
    process about to start, for processes whose threads exist before any code of the package
    runs (glibc and Arrow read them at the start; ``mallopt`` would come too late for those
    threads); empty where turned off."""
    if not keep_freed_wanted():
        return {}
    return {name: str(v) for _, name, v in MALLOC_SETTINGS} | {
        "ARROW_DEFAULT_MEMORY_POOL": "system"}


def _glibc() -> ctypes.CDLL | None:
    """The C library where it is glibc on Linux (``mallopt``, ``malloc_trim``), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc
        return None


def keep_freed_memory() -> bool:
    """Keep freed memory in the process for reuse (glibc ``mallopt``: large blocks from the
    heap instead of their own memory maps, the heap's top not given back below 2 GiB, and one
    heap for every thread; Arrow's buffers from that heap too); True if set. The CLI does it
    (off with ``$HARTRAO_JAX_KEEP_FREED_MEMORY=0``).

    Why, measured on a two-face position of 1.26e7 points:

    * Each large array (a column of 1e7 points is 80 MB) otherwise gets fresh pages from the
      kernel, which faults every 4 KiB page in on first touch (18-22 % of the CPU time of a
      full-resolution fit was system time); reused, it is already there. Whole ``fit`` 38.1
      -> 30.9 s warm, peak resident 9.3 -> 10.3 GB.
    * One heap (``M_ARENA_MAX`` 1): a thread's own heap holds at most 64 MiB, so glibc gives
      the larger blocks of a worker thread (the random effect's passes run in two) their own
      memory maps whatever ``M_MMAP_MAX`` says, and each pass faulted 1.5 GB in again
      (381,000 faults); with one heap none. Random effect 12.7 -> 6.9 s warm.
    * Arrow (reading and writing Parquet) allocates through its system pool instead of
      mimalloc, which hands freed memory back to the kernel: a 611 MiB residual table written
      after that fit in 1.6-2.2 s, now 0.7-1.4 s.

    Freed memory is no longer returned to the kernel, so not for long-lived processes: a Dask
    worker whose resident memory stays above 80 % of its limit after a large position is
    paused by its nanny. ``fit-dask`` workers keep glibc's default; those of
    ``fit-stream --dask``'s local cluster, whose footprint is bounded, get the same settings
    from their environment at their start (:func:`keep_freed_environment`)."""
    libc = _glibc() if keep_freed_wanted() else None
    if libc is None:
        return False
    ok = all(bool(libc.mallopt(param, value)) for param, _, value in MALLOC_SETTINGS)
    if ok:
        import pyarrow as pa

        pa.set_memory_pool(pa.system_memory_pool())
    return ok


def return_free_heap() -> bool:
    """Give the pages of the heap's free blocks back to the kernel (glibc ``malloc_trim(0)``);
    True where done. With :func:`keep_freed_memory` freed memory otherwise stays resident for
    reuse, and the free blocks the random effect's passes leave between them (a pass's
    per-point store freed, the next one's blocks of the same size placed elsewhere in the
    heap) added 1.1 and 0.5 GiB of resident memory at its second and third pass over a
    1.26e7-point position. Called before each pass over many points: the pass faults its store
    in again either way (measured: 221,184 faults per thread without it), so it costs no
    time, and the peak resident of that position's ``fit`` fell from 8.79-8.81 to 7.47-8.01 GB.
    """
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True


#: The variable an OpenBLAS library reads for its threads when it loads: the number
#: :func:`set_blas_threads` gives the loaded libraries by default where it is set (the user's
#: choice).
BLAS_THREADS_ENV = "OPENBLAS_NUM_THREADS"
#: Names of OpenBLAS's thread-count setter in its builds: plain, and NumPy's and SciPy's own
#: copies (``scipy_`` prefix; 64-bit integers with the ``64_`` suffix).
_BLAS_SETTERS = tuple(f"{p}openblas_set_num_threads{s}" for p in ("", "scipy_")
                      for s in ("", "64_"))


def blas_libraries() -> list[str]:
    """Paths of the OpenBLAS libraries this process has loaded (NumPy and SciPy each bring
    their own copy), from ``/proc/self/maps``; empty where ``/proc`` does not tell."""
    try:
        with open("/proc/self/maps") as fh:
            paths = {line.split()[-1] for line in fh if "openblas" in line.lower()}
    except OSError:
        return []
    return sorted(p for p in paths if p.startswith("/"))


def set_blas_threads(threads: int | None = None) -> int:
    """``threads`` (default ``$OPENBLAS_NUM_THREADS`` where set, else one) for every OpenBLAS
    library loaded in this process (:func:`blas_libraries`); returns how many it set. The CLI
    calls it at the start of each command, a Dask worker at its set-up; a library loaded
    later keeps its own number (read from the environment as it loads).

    Why: the package's NumPy and SciPy calls into BLAS are small (least squares of samples,
    3 x 3 systems, products of an ``(n, 3)`` table with a vector), and OpenBLAS's worker
    threads keep spinning after each call on the cores XLA's threads and the package's own
    compute on (``blas_thread_server`` 3 % of a large position's CPU samples under ``perf``).
    Measured on 2 cores (``benchmarks/ab.py``, 4 alternated runs each, medians):
    ``diagnose`` 12.16 -> 11.55 s (user CPU 18.6 -> 16.1 s), the 12-scan ``fit`` 8.82 -> 8.47
    s, the large position's 13.56 -> 13.29 s."""
    if threads is None:
        try:
            threads = int(os.environ.get(BLAS_THREADS_ENV) or 1)
        except ValueError:  # not a number: OpenBLAS itself took its default
            return 0
    threads = max(1, int(threads))
    done = 0
    for path in blas_libraries():
        try:
            lib = ctypes.CDLL(path)  # already loaded: the same library, not a second copy
        except OSError:
            continue
        name = next((n for n in _BLAS_SETTERS if hasattr(lib, n)), None)
        if name is not None:
            setter = getattr(lib, name)
            setter.argtypes = [ctypes.c_int64 if name.endswith("64_") else ctypes.c_int]
            setter.restype = None
            setter(threads)
            done += 1
    return done


#: Share of the kernel's memory-map limit above which :func:`release_compiled_programs` drops
#: JAX's in-memory compiled programs.
MAPS_FRACTION = 0.5


def memory_maps() -> tuple[int, int] | None:
    """``(memory maps of this process, the kernel's limit vm.max_map_count)``; None where
    ``/proc`` does not tell."""
    try:
        with open("/proc/self/maps", "rb") as fh:
            n = sum(1 for _ in fh)
        with open("/proc/sys/vm/max_map_count") as fh:
            return n, int(fh.read())
    except (OSError, ValueError):
        return None


def release_compiled_programs(fraction: float = MAPS_FRACTION) -> bool:
    """Drop JAX's in-memory compiled programs when this process holds more than ``fraction``
    of the kernel's memory-map limit; returns True when it dropped them.

    Every compiled XLA program keeps some memory maps of its own (about 2,000 for the programs
    of one demo ``fit``), and a process that meets many point counts (a campaign, ``prove``,
    a worker, the test suite) compiles thousands. At ``vm.max_map_count`` (65,530 by default)
    LLVM can no longer map code: the process dies inside XLA (an abort or a segmentation
    fault while compiling or loading a program; the test suite reached 44,000 maps at 78 %).
    Called between positions, cases and tasks; programs used again come back from the
    persistent compilation cache.
    """
    m = memory_maps()
    if m is None or m[0] <= fraction * m[1]:
        return False
    jax.clear_caches()
    clear_programs()
    return True


REAL_DATA_ENV = "HARTRAO_REAL_DATA"
REAL_DATA_DEFAULT = "../shared/real"
REAL_DATA_SOURCE = (
    "the public repository GreenBankObservatory/lassi-analysis, folder data/ "
    "(https://github.com/GreenBankObservatory/lassi-analysis)")


def repository_root() -> Path:
    """The directory holding ``pyproject.toml`` above the package (a checkout or editable
    install); the current directory when the package is installed elsewhere."""
    root = Path(__file__).resolve().parents[1]
    return root if (root / "pyproject.toml").is_file() else Path.cwd()


def real_data_dir() -> Path:
    """Directory of the real recordings (not part of the repository: their source publishes
    no licence): ``$HARTRAO_REAL_DATA``, default ``../shared/real``; a relative path is taken
    from the repository root (:func:`repository_root`). The Green Bank scans are expected in
    its ``gbt-lassi/`` folder (files from :data:`REAL_DATA_SOURCE`, names in the README).
    The directory may not exist; callers decide what to do then.
    """
    p = Path(os.environ.get(REAL_DATA_ENV) or REAL_DATA_DEFAULT).expanduser()
    return p if p.is_absolute() else (repository_root() / p).resolve()


def real_data_missing(sub: str = "gbt-lassi") -> str | None:
    """None when ``real_data_dir() / sub`` exists, else the reason to give (where to get it)."""
    d = real_data_dir() / sub
    if d.is_dir():
        return None
    return (f"real recordings not found at {d} (${REAL_DATA_ENV}, default {REAL_DATA_DEFAULT} "
            f"from the repository root): get them from {REAL_DATA_SOURCE} and put them under "
            f"${REAL_DATA_ENV}/{sub}/ (file names: see README, 'Real recordings')")
