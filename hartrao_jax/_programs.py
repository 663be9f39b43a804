"""Compiled programs kept on disk and loaded by later processes without tracing: :func:`cached_jit`.

``eqx.filter_jit`` traces, lowers and compiles a program in every process that calls it; JAX's
persistent compilation cache saves only the last of the three. Tracing and lowering took 2.2 s of
a full-resolution position's ``fit`` and 2.5-3.4 s of the 12-scan campaign's and of
``diagnose``'s (measured, ``benchmarks/results/profile.md``). :func:`cached_jit` is
``filter_jit`` (arrays traced, every other argument static, the same donation) whose compiled
programs are also written to ``<compilation cache>/programs`` (:func:`set_program_dir`) and
loaded from there by a later process (``jax.experimental.serialize_executable``).

A program on disk is found by a key of everything that shapes it, and is used only when the key
it was written with equals the key of the call (not only its digest):

* the function (module and qualified name) and the digest of the whole package's source;
* every argument: an array by its shape, dtype and weak type; anything else by value (numbers,
  strings, tuples, lists, dicts, dtypes, enums, dataclasses such as ``eqx.Module`` field by
  field, functions and classes defined at module level by their qualified name and, outside
  the package and the libraries, the digest of their module's file; ``functools.partial``);
* the versions of Python, jax, jaxlib, equinox and NumPy; JAX's configuration (but for its
  logging, caches and tracebacks: :data:`QUIET_OPTIONS`); the backend's platform, its version
  and the CPU's model and features; the environment variables of the package, of XLA and of
  JAX; the cores the process may use.

The package's module constants are part of its source. A test that rebinds one (or replaces a
function) changes what a program computes without changing its key, so the test suite keeps no
programs on disk (``tests/conftest.py`` sets ``$HARTRAO_JAX_PROGRAMS=0``;
``tests/test_programs.py`` turns it on for itself).

A call the key cannot state exactly (a closure, an object that is neither a dataclass nor a plain
value, an array held in a static field, a call from inside another trace) is an ordinary
``filter_jit`` call: nothing of it is read from or written to disk. So only functions whose
programs depend on their arguments and the package's source alone are given to
:func:`cached_jit`; a program that cannot be serialised (closed-over constants) stays in memory.
``$HARTRAO_JAX_PROGRAMS=0`` turns the disk off.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import inspect
import os
import pickle
import platform
import sys
import threading
import types
import warnings
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import equinox as eqx
import jax
import numpy as np
from jax.experimental.serialize_executable import deserialize_and_load, serialize

from ._files import unlink, write_via_temp

#: ``$HARTRAO_JAX_PROGRAMS=0``: compiled programs are neither read from nor written to disk.
PROGRAMS_ENV = "HARTRAO_JAX_PROGRAMS"
#: The format of a program file (part of its key).
FORMAT = 1
#: Prefixes of the environment variables that are part of every key.
ENV_PREFIXES = ("HARTRAO", "XLA", "JAX", "TF_", "OMP_", "MKL_", "OPENBLAS")

#: JAX options left out of the key (words of their names): logging, caches, tracebacks; they do
#: not change what a program computes (``jax_log_compiles`` would otherwise compile every
#: program again for a process that only wants to see its compilations).
QUIET_OPTIONS = ("log", "cache", "traceback", "explain")

_PACKAGE = __name__.rsplit(".", 1)[0]
_state: dict[str, Any] = {"dir": None, "process": None}
_counts = {"loaded": 0, "compiled": 0, "written": 0}
_lock = threading.RLock()
_instances: list[CachedJit] = []


class Uncacheable(Exception):
    """An argument whose value the key cannot state exactly."""


def set_program_dir(path: str | os.PathLike | None) -> None:
    """Where compiled programs are kept (None: nowhere, memory only). Set by
    :func:`hartrao_jax._config.enable_compilation_cache` to its directory's ``programs``."""
    _state["dir"] = None if path is None else Path(path)


def program_dir() -> Path | None:
    """The directory of compiled programs, None where off (unset or ``$HARTRAO_JAX_PROGRAMS=0``)."""
    if os.environ.get(PROGRAMS_ENV, "1") == "0":
        return None
    return _state["dir"]


def program_counts() -> dict[str, int]:
    """How many programs this process has loaded from disk, compiled (traced) and written."""
    return dict(_counts)


def clear_programs() -> None:
    """Drop the compiled programs held in memory by every :func:`cached_jit` function (with
    ``jax.clear_caches``: each holds memory maps of its own)."""
    with _lock:
        for c in _instances:
            c._memory.clear()
            c._locks.clear()


# --------------------------------------------------------------------------------------------
# the key
# --------------------------------------------------------------------------------------------

_PLAIN = (type(None), bool, int, str, bytes)


#: Libraries whose code is part of every key by their versions (:func:`_process_key`; the
#: standard library's by Python's); any other module's functions by their file's digest.
LIBRARIES = ("builtins", "jax", "jaxlib", "equinox", "numpy", "math", "operator", "functools")
_file_digests: dict[str, str] = {}


def _source_digest(module: str) -> str:
    """The digest of the source file of ``module`` where the key does not already hold it (the
    package's source and the libraries' versions do): a function of a test or a script."""
    top = module.split(".", 1)[0]
    if top == _PACKAGE or top in LIBRARIES:
        return ""
    if module not in _file_digests:
        file = getattr(sys.modules.get(module), "__file__", None)
        if not file:
            raise Uncacheable(f"module {module} has no source file")
        _file_digests[module] = hashlib.sha256(Path(file).read_bytes()).hexdigest()
    return _file_digests[module]


def _module_level(obj) -> tuple[str, str, str]:
    """``(module, qualified name, source digest)`` of a function or class reachable by that
    name, else :class:`Uncacheable` (a closure, a lambda, a function defined inside another)."""
    mod, qual = getattr(obj, "__module__", None), getattr(obj, "__qualname__", None)
    if not mod or not qual or "<" in qual:
        raise Uncacheable(f"{obj!r} is not defined at module level")
    found = sys.modules.get(mod)
    for part in qual.split("."):
        found = getattr(found, part, None)
    if found is not obj:
        raise Uncacheable(f"{obj!r} is not what {mod}.{qual} names")
    return mod, qual, _source_digest(mod)


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray, np.generic))


def spec(obj, static: bool = False) -> Any:
    """The value of a (static part of an) argument as nested tuples of plain values; arrays
    (traced) as ``("A",)``, their shapes and dtypes being in the avals. ``static``: inside a
    field held static, where an array would be part of the program: :class:`Uncacheable`."""
    t = type(obj)
    if t in _PLAIN:
        return (t.__name__, obj)
    if t is float or t is complex:
        return (t.__name__, repr(obj))
    if _is_array(obj):
        if static:
            raise Uncacheable("an array held static")
        return ("A",)
    if t is tuple or t is list:
        return (t.__name__,) + tuple(spec(x, static) for x in obj)
    if t is dict:
        return ("dict",) + tuple((spec(k, True), spec(v, static)) for k, v in obj.items())
    if isinstance(obj, np.dtype):
        return ("dtype", obj.str)
    if isinstance(obj, enum.Enum):
        return ("enum",) + _module_level(t) + (obj.name,)
    if isinstance(obj, functools.partial):
        return ("partial", spec(obj.func, static), spec(obj.args, static),
                spec(obj.keywords, static))
    if isinstance(obj, types.MethodType):
        return ("method", spec(obj.__self__, static), obj.__func__.__qualname__)
    if isinstance(obj, type) or callable(obj) and not dataclasses.is_dataclass(obj):
        if getattr(obj, "__closure__", None):
            raise Uncacheable(f"{obj!r} is a closure")
        return ("ref",) + _module_level(obj)
    if dataclasses.is_dataclass(obj):
        fields = tuple(
            (f.name, spec(getattr(obj, f.name), static or bool(f.metadata.get("static"))))
            for f in dataclasses.fields(obj))
        if set(vars(obj)) - {f.name for f in dataclasses.fields(obj)}:
            raise Uncacheable(f"{t.__name__} holds attributes that are not its fields")
        return ("obj",) + _module_level(t) + fields
    if isinstance(obj, tuple) and hasattr(t, "_fields"):  # a NamedTuple
        return ("obj",) + _module_level(t) + tuple(spec(x, static) for x in obj)
    raise Uncacheable(f"an argument of type {t.__name__}")


def _aval(x) -> tuple:
    if isinstance(x, jax.Array):
        return (x.shape, x.dtype.str, bool(getattr(x, "weak_type", False)))
    x = np.asarray(x)
    return (x.shape, x.dtype.str, False)


def _package_digest() -> str:
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


#: The digest of the package's source, read when this module is loaded (with the package: the
#: source a program is traced from is the source read then, even if a file changes later).
_SOURCE = _package_digest()


def _cpu() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            lines = [ln for ln in fh if ln.startswith(("model name", "flags"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.processor()


def _process_key() -> str:
    """What shapes every program of this process and does not change while it runs."""
    if _state["process"] is None:
        import jaxlib

        dev = jax.devices()[0]
        _state["process"] = repr((
            FORMAT, _SOURCE, sys.version, jax.__version__, jaxlib.__version__,
            eqx.__version__ if hasattr(eqx, "__version__") else "", np.__version__,
            platform.machine(), dev.platform, dev.client.platform_version, dev.device_kind,
            jax.device_count(), _cpu()))
    return _state["process"]


def _now_key() -> str:
    """What shapes programs and may change while a process runs: JAX's configuration, the
    environment and the usable cores."""
    cfg = sorted((k, v) for k, v in jax.config.values.items()
                 if isinstance(v, (bool, int, float, str, type(None)))
                 and not any(w in k for w in QUIET_OPTIONS))
    env = sorted((k, v) for k, v in os.environ.items() if k.startswith(ENV_PREFIXES))
    affinity = getattr(os, "sched_getaffinity", None)
    cores = len(affinity(0)) if affinity else os.cpu_count()
    return repr((cfg, env, cores))


# --------------------------------------------------------------------------------------------
# the programs
# --------------------------------------------------------------------------------------------


class _Slot:
    """Where the i-th array of a program's outputs goes in its output structure."""

    __slots__ = ("i",)

    def __init__(self, i: int):
        self.i = i

    def __eq__(self, other):
        return isinstance(other, _Slot) and other.i == self.i

    def __hash__(self):
        return hash(("slot", self.i))

    def __reduce__(self):
        return (_Slot, (self.i,))


@dataclasses.dataclass(frozen=True)
class _Program:
    """A compiled program and how its flat outputs become the function's."""

    compiled: Any
    out_tree: Any
    out_leaves: tuple  # a _Slot for each array output, the value of every other leaf
    trying: list = dataclasses.field(default_factory=list)  # a loaded one's marker until it ran

    def __call__(self, dyn):
        outs = self.compiled(*dyn)
        if self.trying:  # its first run from a file has ended: the file is good
            jax.block_until_ready(outs)
            try:
                _unlink(self.trying.pop())
            except IndexError:  # (another thread's run of it removed the marker)
                pass
        return jax.tree.unflatten(self.out_tree, [outs[x.i] if isinstance(x, _Slot) else x
                                                 for x in self.out_leaves])


def _unlink(path: Path) -> None:
    """Remove ``path`` if it can be (another process may have removed it first, the folder
    may be read-only)."""
    unlink(path, ignore=(OSError,))


def _skeleton(out_tree, out_leaves):
    """The function's output with each array's place (a :class:`_Slot`) instead of the array."""
    return jax.tree.unflatten(out_tree, list(out_leaves))


class CachedJit:
    """:func:`cached_jit`'s wrapper of one function."""

    def __init__(self, fn: Callable, donate: str, keep_unused: bool):
        functools.update_wrapper(self, fn)
        self._fn = fn
        if "<" in fn.__qualname__:
            raise ValueError(f"cached_jit: {fn.__qualname__} is not defined at module level")
        self._name = f"{fn.__module__}.{fn.__qualname__}"
        self._signature = inspect.signature(fn)
        self._donate = donate
        self._keep_unused = keep_unused
        self._jit = eqx.filter_jit(fn, donate=donate, keep_unused=keep_unused)
        self._memory: dict = {}
        self._locks: dict = {}
        with _lock:
            _instances.append(self)

    def __call__(self, *args, **kwargs):
        bound = self._signature.bind(*args, **kwargs)
        args, kwargs = bound.args, bound.kwargs
        leaves, treedef = jax.tree.flatten((args, kwargs))
        dyn = [x for x in leaves if _is_array(x)]
        if any(isinstance(x, jax.core.Tracer) for x in dyn):
            return self._jit(*args, **kwargs)  # inside another trace: part of that program
        try:
            key = (spec((args, kwargs)), tuple(_aval(x) for x in dyn))
            prog = self._memory.get(key)
        except (Uncacheable, TypeError):
            return self._jit(*args, **kwargs)
        if prog is None:
            # one lock per program: threads wanting the same one wait for its compilation,
            # threads wanting different ones compile at the same time (the parts of a pass)
            with _lock:
                lock = self._locks.setdefault(key, threading.Lock())
            with lock:
                prog = self._memory.get(key)
                if prog is None:
                    prog = self._memory[key] = self._program(key, args, leaves, treedef, dyn)
        return prog(dyn)

    def _program(self, key, args, leaves, treedef, dyn) -> _Program:
        directory, path, digest = program_dir(), None, ""
        try:
            if directory is not None:
                full = repr((self._name, _source_digest(self._fn.__module__), key,
                             _process_key(), _now_key()))
                digest = hashlib.sha256(full.encode()).hexdigest()[:40]
                path = directory / f"{self._name}-{digest}.bin"
        except Uncacheable:
            path = None
        if path is not None:
            # a marker beside the file until the loaded program has run once: one left behind
            # by a process that died loading or running it (a crash inside XLA) condemns the
            # file, which is then compiled and written again
            trying = path.with_name(f"{path.name}.trying")
            if trying.exists():
                _unlink(path)
                _unlink(trying)
            elif path.exists():
                _write(trying, b"")
                prog = _load(path, full)
                if prog is not None:
                    _counts["loaded"] += 1
                    prog.trying.append(trying)
                    return prog
                _unlink(trying)
        _counts["compiled"] += 1
        is_dyn = [_is_array(x) for x in leaves]
        n_first = sum(_is_array(x) for x in jax.tree.leaves(args[:1]))
        donate = tuple(range(n_first if self._donate == "all-except-first" else 0, len(dyn))
                       if self._donate in ("all", "all-except-first") else ())
        traced: dict = {}
        fn = self._fn

        def flat(*d):
            it = iter(d)
            a, k = jax.tree.unflatten(treedef, [next(it) if f else x
                                                for f, x in zip(is_dyn, leaves)])
            out = fn(*a, **k)
            o_leaves, o_tree = jax.tree.flatten(out)
            arrays = [x for x in o_leaves if _is_array(x)]
            i = iter(range(len(arrays)))
            traced["tree"] = o_tree
            traced["leaves"] = tuple(_Slot(next(i)) if _is_array(x) else x for x in o_leaves)
            return tuple(arrays)

        def compile_as(name: str):
            flat.__name__ = flat.__qualname__ = name
            with warnings.catch_warnings():  # (as filter_jit: an unused donation is no fault)
                warnings.filterwarnings("ignore", message="Some donated buffers were not usable")
                hits = _cache_hits()
                compiled = jax.jit(flat, donate_argnums=donate,
                                   keep_unused=self._keep_unused).lower(*dyn).compile()
                return compiled, _cache_hits() > hits

        if path is None:
            compiled, _ = compile_as(self._fn.__name__)
            return _Program(compiled, traced["tree"], traced["leaves"])
        # a program to write must be compiled here: one loaded from JAX's compilation cache
        # writes a damaged copy (measured: "Function ... not found" when the copy is run), so
        # its name is that of its key (a new key misses JAX's cache), and if JAX's cache had
        # it all the same (the program file lost), it is compiled again under another name
        compiled, hit = compile_as(f"{self._fn.__name__}_{digest[:12]}")
        prog = _Program(compiled, traced["tree"], traced["leaves"])
        blob = _blob(full, prog)
        if blob is not None and hit:  # (one that cannot be kept is not compiled again)
            compiled, hit = compile_as(f"{self._fn.__name__}_{digest[:12]}_{os.urandom(6).hex()}")
            prog = _Program(compiled, traced["tree"], traced["leaves"])
            blob = None if hit else _blob(full, prog)
        if blob is not None:
            _write(path, blob)
        return prog


_hits = threading.local()


def _count_hit(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _hits.n = getattr(_hits, "n", 0) + 1


def _cache_hits() -> int:
    """Programs this thread has loaded from JAX's compilation cache so far."""
    if not _state.get("listening"):
        with _lock:
            if not _state.get("listening"):
                jax.monitoring.register_event_listener(_count_hit)
                _state["listening"] = True
    return getattr(_hits, "n", 0)


def _ensure_handlers() -> None:
    """Register the CPU's LAPACK kernels with XLA, as lowering a linear-algebra operation does
    (JAX registers them lazily; a loaded program calling them before would crash, as
    ``jax.export`` notes for its own loaded programs)."""
    if not _state.get("handlers"):
        from jax._src.lax.linalg import initialize_lapack

        initialize_lapack()
        _state["handlers"] = True


def _load(path: Path, full: str) -> _Program | None:
    """The program kept at ``path`` if it was written with the key ``full``; None where there is
    none, it was written with another key or cannot be read (then it is written again)."""
    try:
        _ensure_handlers()
        with open(path, "rb") as fh:
            kept = pickle.loads(zlib.decompress(fh.read()))
        if kept["key"] != full:
            return None
        compiled = deserialize_and_load(kept["exe"], kept["in_tree"], kept["out_tree"])
        leaves, tree = jax.tree.flatten(kept["skeleton"], is_leaf=lambda x: isinstance(x, _Slot))
        return _Program(compiled, tree, tuple(leaves))
    except Exception:  # noqa: BLE001  (a damaged, foreign or vanished file: compiled again)
        return None


def _blob(full: str, prog: _Program) -> bytes | None:
    """``prog`` as the bytes of its file, None where it cannot be kept: it calls back into
    Python or has effects, cannot be serialised, or its output structure does not come back
    from the file as it is."""
    try:
        unloaded = prog.compiled._executable._unloaded_executable
        if (unloaded.host_callbacks or unloaded.keepalive or unloaded.ordered_effects
                or unloaded.unordered_effects):
            return None  # (Python callbacks and effects belong to this process)
        exe, in_tree, out_tree = serialize(prog.compiled)
        skeleton = _skeleton(prog.out_tree, prog.out_leaves)
        back = pickle.loads(pickle.dumps(skeleton))
        leaves, tree = jax.tree.flatten(back, is_leaf=lambda x: isinstance(x, _Slot))
        if tree != prog.out_tree or tuple(leaves) != prog.out_leaves:
            return None
        return zlib.compress(pickle.dumps({"key": full, "exe": exe, "in_tree": in_tree,
                                           "out_tree": out_tree, "skeleton": skeleton}), 1)
    except Exception:  # noqa: BLE001  (not serialisable: kept in memory only)
        return None


def _write(path: Path, blob: bytes) -> None:
    """Write ``blob`` to ``path``, whole or not at all (:func:`._files.write_via_temp`, not
    flushed to the disk: a lost program is compiled again); a folder that cannot be written
    keeps none."""
    try:
        write_via_temp(path, lambda t: t.write_bytes(blob), durable=False)
    except OSError:
        return
    _counts["written"] += blob != b""


def cached_jit(fn: Callable | None = None, *,
               donate: Literal["none", "all", "all-except-first"] = "none",
               keep_unused: bool = False):
    """``eqx.filter_jit`` whose compiled programs later processes load from disk instead of
    tracing, lowering and compiling them again (module doc). For functions defined at module
    level whose programs depend on their arguments and the package's source alone."""
    if fn is None:
        return functools.partial(cached_jit, donate=donate, keep_unused=keep_unused)
    return CachedJit(fn, donate, keep_unused)
