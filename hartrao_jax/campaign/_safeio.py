"""Crash-safe, strict outputs: one policy for every file the project writes.

Conventions (``shared/spec/outputs.md``, issue 13):

* **Strict JSON.** Every JSON document goes through :func:`strict_json`: NaN and +-Infinity
  become ``null`` (the path of each replaced value is recorded, and the writers put a note in
  the document under ``"nonfinite"``), NumPy scalars and arrays become plain numbers and
  lists, tuples become lists, mapping keys become strings. It is then serialised with
  ``allow_nan=False``, so a bare ``NaN`` can never reach a file.
* **Atomic files.** A file is written to a temporary name in its own directory
  (``.<name>.tmp-<pid>-<token>``), flushed to disk and renamed over the final name
  (:func:`write_bytes_atomic`, :func:`write_json_atomic`). A reader sees the old file or the
  new one, never a part of one.
* **Result directories.** A verb that writes several files (``fit``: ``fit.json`` +
  ``residuals/*.parquet``; ``surface``; ``gravity`` ...) uses an :class:`OutputDir`
  transaction: every file goes to a temporary name first; :meth:`OutputDir.commit` then
  removes the previous main JSON, renames the files into place and writes the verb's main
  JSON **last**. That JSON is the commit point: its ``"files"`` key lists every file of the
  result, ``{relpath: {"bytes": n, "sha256": hex}}`` (paths relative to the main JSON's
  directory, ``/``-separated). Files the previous main JSON listed and the new one does not
  are removed after the commit; nothing else in the directory is touched.
* **Readers verify.** :func:`verify_result_dir` raises the project's one-line user error
  (:class:`~hartrao_jax.campaign.CampaignError`, printed as ``error: <file>: <field>: ...``
  with exit status 2) when the main JSON is missing, not strict JSON, has no manifest, or a
  listed file is missing or differs in size or SHA-256: an interrupted write or a directory
  mixing two results is refused, never read.

A kill at any moment therefore leaves either the previous complete result (kill before the
commit), the new complete result (kill after it), or, within the few renames of the commit
itself, a directory without a valid main JSON that every reader refuses in one line. Stale
temporary files of dead writers are removed by the next transaction on the same directory.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
import math
import os
import pathlib
import re
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np

from .._files import FileDigest, HashingFile
from .._files import fsync_dir as _fsync_dir
from .._files import fsync_file as _fsync_file
from .._files import tmp_name as _tmp_name
from .._files import unlink as _unlink
from .._files import write_via_temp as _write_via_temp
from ._format import CampaignError

#: Fault-injection hook of the crash tests: with ``HARTRAO_JAX_SAFEIO_PAUSE_S=<seconds>`` in
#: the environment an :class:`OutputDir` pauses after each file it writes and after each step
#: of its commit, so that a test can kill the process inside every phase. Unset in normal use.
PAUSE_ENV = "HARTRAO_JAX_SAFEIO_PAUSE_S"

_TMP_RE = re.compile(r"^\.(?P<name>.+)\.tmp-(?P<pid>\d+)-[0-9a-f]{8}$")
_CHUNK = 1 << 20
#: Keyword arguments of every Parquet table the package writes (:func:`write_table`): no
#: dictionary encoding. Columns of measurements and residuals (float64) never repeat a value,
#: and pyarrow's attempt to dictionary-encode each one took 5/6 of the write (12 residual tables
#: of 2.1e5 rows, 318 MB: 2.02 s with it, 0.33 s without, the same size within 1 %). Any Parquet
#: reader reads both. The codec is chosen per column (:func:`parquet_codecs`).
PARQUET_WRITE_OPTIONS: dict[str, Any] = {"use_dictionary": False}


def parquet_codecs(schema) -> dict[str, str]:
    """Parquet codec per column of a pyarrow ``schema``: Snappy for integer and boolean columns
    (row numbers, flags, faces: 2-20x smaller), none for floating-point ones.

    Measured floats (angles, ranges, times, residuals) have random low bits, which Snappy
    cannot shorten: on a 6.5e6-row residual table it made 11 of its 13 float columns 0.01 %
    *larger* and the other two 5-12 % smaller (the whole file 2.1 % smaller), for 0.2-0.25 s of
    a 1.6-s write (``benchmarks/results/profile.md``). Every Parquet reader reads both."""
    import pyarrow.types as pt

    return {f.name: ("none" if pt.is_floating(f.type) else "snappy") for f in schema}


def _parquet_options(schema, kwargs: Mapping[str, Any]) -> dict[str, Any]:
    """:data:`PARQUET_WRITE_OPTIONS` and :func:`parquet_codecs` for ``schema``, ``kwargs``
    (further ``pyarrow.parquet`` writer arguments) winning."""
    return {**PARQUET_WRITE_OPTIONS, "compression": parquet_codecs(schema), **kwargs}


def required_fields(table):
    """``table`` with every column that holds no null declared required (``nullable=False``):
    Parquet then stores no definition level per value. Encoding those levels took 0.31 of the
    0.72 s a 6.5e6-row residual table took to write (0.41 s without; the same file size within
    0.01 %, the same values read back). A column with nulls stays optional."""
    import pyarrow as pa

    schema = pa.schema([f.with_nullable(False) if f.nullable and c.null_count == 0 else f
                        for f, c in zip(table.schema, table.columns)],
                       metadata=table.schema.metadata)
    return table if schema.equals(table.schema) else table.cast(schema)


def write_table(table, path, **kwargs) -> None:
    """Write a pyarrow table as Parquet with the package's options (:data:`PARQUET_WRITE_OPTIONS`,
    :func:`parquet_codecs`, columns without nulls required: :func:`required_fields`;
    ``kwargs``: further ``pyarrow.parquet.write_table`` arguments, which win)."""
    import pyarrow.parquet as pq

    table = required_fields(table)
    pq.write_table(table, path, **_parquet_options(table.schema, kwargs))


#: Rows per row group of :func:`write_columns`. A quarter of pyarrow's default for
#: ``write_table``: a writer holds about a row group's table and its encoding, 33 MiB instead of
#: 141 MiB for a 16-column residual table (two written at once at the end of a large
#: position), in the same time (0.76-1.13 s for 6.3e6 rows either way) and the same size.
ROW_GROUP_ROWS = 1 << 18


def write_columns(columns: Mapping[str, np.ndarray], path, *,
                  row_group_rows: int = ROW_GROUP_ROWS) -> FileDigest:
    """Write equal-length NumPy columns as Parquet, one row group at a time; returns the
    file's manifest entry, taken as it was written (:class:`.._files.HashingFile`: an
    :class:`OutputDir` does not read it again).

    The file :func:`write_table` would write from ``pa.table(columns)``, but a strided column
    (``v[:, 0]`` of an ``(n, 3)`` array) is copied one row group at a time instead of whole:
    a 6.3e6-row residual table with six such columns holds 50 MB of copies instead of 300 MB.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    n = len(next(iter(columns.values()))) if columns else 0
    # NumPy columns hold no nulls: every one required, as :func:`required_fields` would make
    # them, but declared so from the start (its cast loads ``pyarrow.compute``: 0.03 s of a
    # ``fit`` command)
    schema = pa.schema([pa.field(k, pa.from_numpy_dtype(np.asarray(v).dtype), nullable=False)
                        for k, v in columns.items()])
    with HashingFile(path) as sink:
        with pq.ParquetWriter(sink, schema, **_parquet_options(schema, {})) as w:
            for a in range(0, max(n, 1), row_group_rows):
                w.write_table(pa.table({k: np.ascontiguousarray(v[a:min(n, a + row_group_rows)])
                                        for k, v in columns.items()}, schema=schema),
                              row_group_size=row_group_rows)
    return sink.digest


# ----------------------------------------------------------------------------- strict JSON


def strict_json(obj: Any, replaced: list[str] | None = None, *,
                default: Callable[[Any], Any] | None = None, _path: str = "") -> Any:
    """``obj`` as plain, strictly JSON-serialisable Python (recursively).

    Non-finite floats (Python or NumPy) become ``None`` and their paths (``a.b[2].value``)
    are appended to ``replaced`` when given. NumPy arrays become (nested) lists, NumPy scalars
    Python numbers, NumPy booleans ``bool``, tuples and sets lists, mapping keys strings,
    ``pathlib`` paths and date-times strings. Anything else goes through ``default`` (which
    must return something this function accepts) or raises ``TypeError``.
    """
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        if math.isfinite(v):
            return v
        if replaced is not None:
            replaced.append(_path or "$")
        return None
    if isinstance(obj, np.ndarray):
        obj = obj.tolist()
    if isinstance(obj, Mapping):
        return {str(k): strict_json(v, replaced, default=default,
                                    _path=f"{_path}.{k}" if _path else str(k))
                for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        items = sorted(obj, key=repr) if isinstance(obj, (set, frozenset)) else obj
        return [strict_json(v, replaced, default=default, _path=f"{_path}[{i}]")
                for i, v in enumerate(items)]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (dt.datetime, dt.date, dt.time)):
        return obj.isoformat()
    if isinstance(obj, complex):
        return strict_json([obj.real, obj.imag], replaced, default=default, _path=_path)
    if default is not None:
        return strict_json(default(obj), replaced, default=None, _path=_path)
    raise TypeError(f"{_path or 'value'}: {type(obj).__name__} is not JSON serialisable")


NONFINITE_NOTE = ("values that were not finite numbers (NaN or infinity) are written as null; "
                  "`paths` lists them")


def strict_document(doc: Any, *, default: Callable[[Any], Any] | None = None) -> Any:
    """:func:`strict_json` of a document; a mapping gets a ``"nonfinite"`` note listing the
    paths of the values replaced by null (no key when there were none)."""
    replaced: list[str] = []
    out = strict_json(doc, replaced, default=default)
    if replaced and isinstance(out, dict):
        out["nonfinite"] = {"note": NONFINITE_NOTE, "paths": replaced[:1000],
                            "count": len(replaced)}
    return out


def dumps_strict(doc: Any, *, indent: int | None = 1,
                 default: Callable[[Any], Any] | None = None) -> str:
    """Strict JSON text of ``doc`` (see :func:`strict_document`); never NaN or Infinity."""
    return json.dumps(strict_document(doc, default=default), indent=indent, allow_nan=False) + "\n"


def _reject_constant(name: str):
    raise ValueError(f"{name} is not strict JSON")


def loads_strict(text: str | bytes) -> Any:
    """Parse strict JSON (``NaN``, ``Infinity`` refused with ``ValueError``)."""
    return json.loads(text, parse_constant=_reject_constant)


# ----------------------------------------------------------------------------- atomic files


def _pause() -> None:
    t = os.environ.get(PAUSE_ENV)
    if t:

        time.sleep(float(t))


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(directory: str | os.PathLike) -> int:
    """Remove temporary files (``.<name>.tmp-<pid>-<token>``) of writers that no longer run
    from ``directory`` (not recursive); returns how many were removed."""
    n = 0
    d = pathlib.Path(directory)
    if not d.is_dir():
        return 0
    for p in d.iterdir():
        m = _TMP_RE.match(p.name)
        if m and not _pid_alive(int(m["pid"])) and p.is_file():
            _unlink(p)
            n += 1
    return n


def write_file_atomic(path: str | os.PathLike, writer: Callable[[pathlib.Path], Any], *,
                      durable: bool = True) -> pathlib.Path:
    """Call ``writer(temporary_path)`` and rename its file to ``path`` (parents created); the
    temporary file is removed if the writer fails."""
    return _write_via_temp(pathlib.Path(path), writer, durable=durable)


def write_bytes_atomic(path: str | os.PathLike, data: bytes, *, durable: bool = True
                       ) -> pathlib.Path:
    """Write ``data`` to ``path`` through a temporary file and a rename (parents created)."""
    return _write_via_temp(pathlib.Path(path), lambda t: t.write_bytes(data), durable=durable)


def write_text_atomic(path: str | os.PathLike, text: str, *, durable: bool = True
                      ) -> pathlib.Path:
    """UTF-8 text to ``path`` through a temporary file and a rename."""
    return write_bytes_atomic(path, text.encode("utf-8"), durable=durable)


def write_json_atomic(path: str | os.PathLike, obj: Any, *, indent: int | None = 1,
                      default: Callable[[Any], Any] | None = None, durable: bool = True
                      ) -> pathlib.Path:
    """Strict JSON (:func:`dumps_strict`) to ``path`` through a temporary file and a rename."""
    return write_text_atomic(path, dumps_strict(obj, indent=indent, default=default),
                             durable=durable)


def file_digest(path: str | os.PathLike) -> dict[str, Any]:
    """``{"bytes": size, "sha256": hex digest}`` of a file (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    n = 0
    with open(path, "rb") as f:
        while block := f.read(_CHUNK):
            h.update(block)
            n += len(block)
    return FileDigest(n, h.hexdigest()).entry()


# ----------------------------------------------------------------------------- result dirs


def _relpath(rel: str | os.PathLike) -> str:
    p = pathlib.PurePosixPath(pathlib.PurePath(rel).as_posix())
    if p.is_absolute() or ".." in p.parts or not p.parts or str(p) == ".":
        raise ValueError(f"result file {str(rel)!r}: expected a relative path inside the "
                         "result directory")
    return str(p)


class OutputDir:
    """One crash-safe write of a result directory (see the module docstring).

    Usage::

        with OutputDir(out, "fit.json") as od:
            od.write_parquet("residuals/r23c1.parquet", table)
            od.savefig("figures/f.png", fig)
            od.commit({"schema": "hartrao-fit/1", ...})   # main JSON last, with "files"

    Every ``write_*`` goes to a temporary name beside the final one; nothing visible changes
    before :meth:`commit`. Leaving the ``with`` block without a commit (an exception) removes
    the temporary files and leaves the directory as it was. ``durable`` (default) flushes
    files and directories to disk before the renames.
    """

    def __init__(self, root: str | os.PathLike, main_json: str = "result.json", *,
                 durable: bool = True):
        self.root = pathlib.Path(root)
        self.main_json = _relpath(main_json)
        self.durable = durable
        self._pending: dict[str, pathlib.Path] = {}
        self._sealed: dict[str, dict[str, Any]] = {}  # rel -> digest of a finished file
        self._adopted: set[str] = set()
        self._committed = False

    # -- context manager
    def __enter__(self) -> OutputDir:
        self.root.mkdir(parents=True, exist_ok=True)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self._committed:
            self.abort()

    def abort(self) -> None:
        """Remove the temporary files written so far (the directory is left as it was)."""
        for tmp in self._pending.values():
            _unlink(tmp)
        self._pending.clear()

    # -- writing
    def final_path(self, rel: str) -> pathlib.Path:
        """Where ``rel`` will be after the commit."""
        return self.root / _relpath(rel)

    def temp_path(self, rel: str) -> pathlib.Path:
        """A fresh temporary path for the file ``rel`` (its directory created); the file the
        caller writes there becomes ``rel`` at the commit."""
        if self._committed:
            raise RuntimeError("OutputDir: already committed")
        rel = _relpath(rel)
        if rel == self.main_json:
            raise ValueError(f"{rel}: the main JSON is written by commit()")
        final = self.root / rel
        final.parent.mkdir(parents=True, exist_ok=True)
        if rel in self._pending:
            _unlink(self._pending[rel])
            self._sealed.pop(rel, None)
        else:
            remove_stale_temporaries(final.parent)
        tmp = _tmp_name(final)
        self._pending[rel] = tmp
        return tmp

    def write_with(self, rel: str, writer: Callable[[pathlib.Path], Any]) -> pathlib.Path:
        """Call ``writer(temporary_path)`` to write the file ``rel``; returns the final path."""
        return self.write_each([(rel, writer)])[0]

    def write_each(self, items: Iterable[tuple[str, Callable[[pathlib.Path], Any]]], *,
                   threads: int = 1) -> list[pathlib.Path]:
        """:meth:`write_with` for every ``(rel, writer)`` of ``items``, ``threads`` at a time;
        each file is flushed (``durable``) and hashed for the manifest by the thread that
        wrote it, while it is still in the page cache, or, where its writer returns the
        :class:`.._files.FileDigest` it took while writing (:func:`write_columns`), that one.
        Returns the final paths in order.

        For writers that release the GIL (Parquet encoding and compression; ``savefig`` does
        not): the two 6.3e6-row residual tables of a full-resolution position are written in
        2.6-2.7 s instead of 3.8-4.6 s on two threads. If a writer fails, the others finish,
        every file of the call is removed and the error is raised.
        """
        items = [(_relpath(rel), writer) for rel, writer in items]
        tmps = [self.temp_path(rel) for rel, _ in items]

        def one(k: int) -> dict[str, Any]:
            rel, writer = items[k]
            got = writer(tmps[k])
            if not tmps[k].is_file():
                raise RuntimeError(f"{rel}: the writer wrote no file")
            return self._seal(tmps[k], got if isinstance(got, FileDigest) else None)

        try:
            if threads <= 1 or len(items) <= 1:
                sealed = [one(k) for k in range(len(items))]
            else:
                from concurrent.futures import ThreadPoolExecutor

                with ThreadPoolExecutor(min(threads, len(items))) as ex:
                    futures = [ex.submit(one, k) for k in range(len(items))]
                sealed = [f.result() for f in futures]  # all finished: the first error
        except BaseException:
            for (rel, _), tmp in zip(items, tmps):
                _unlink(tmp)
                self._pending.pop(rel, None)
            raise
        for (rel, _), digest in zip(items, sealed):
            self._sealed[rel] = digest
            _pause()
        return [self.final_path(rel) for rel, _ in items]

    def _seal(self, path: pathlib.Path, digest: FileDigest | None = None) -> dict[str, Any]:
        """Flush a finished file to disk (``durable``) and return its manifest entry: the
        ``digest`` its writer took as it wrote it (:class:`.._files.HashingFile`), where
        given and of the file's size, else read from the file."""
        if self.durable:
            _fsync_file(path)
        if digest is not None and digest.bytes == path.stat().st_size:
            return digest.entry()
        return file_digest(path)

    def write_bytes(self, rel: str, data: bytes) -> pathlib.Path:
        return self.write_with(rel, lambda t: t.write_bytes(data))

    def write_text(self, rel: str, text: str) -> pathlib.Path:
        return self.write_bytes(rel, text.encode("utf-8"))

    def write_json(self, rel: str, obj: Any, *, indent: int | None = 1,
                   default: Callable[[Any], Any] | None = None) -> pathlib.Path:
        """A secondary JSON file of the result (strict, listed in the manifest)."""
        return self.write_text(rel, dumps_strict(obj, indent=indent, default=default))

    def write_parquet(self, rel: str, table, **kwargs) -> pathlib.Path:
        """A pyarrow table as Parquet (:func:`write_table`; ``pyarrow.parquet.write_table``
        keyword arguments)."""
        return self.write_with(rel, lambda t: write_table(table, t, **kwargs))

    def savefig(self, rel: str, fig, **kwargs) -> pathlib.Path:
        """A Matplotlib figure (format from ``rel``'s suffix unless given)."""
        kwargs.setdefault("format", pathlib.PurePath(rel).suffix.lstrip(".") or "png")
        return self.write_with(rel, lambda t: fig.savefig(t, **kwargs))

    def invalidate(self) -> None:
        """Remove the previous main JSON now: for writers that cannot stage their files (other
        processes write them in place, see :meth:`adopt`), the directory then holds no
        result until :meth:`commit` instead of a mixed one."""
        _unlink(self.root / self.main_json)

    def adopt(self, rel: str) -> pathlib.Path:
        """List a file another writer already put at its final place (atomically) in the
        manifest; call :meth:`invalidate` before such files are written."""
        rel = _relpath(rel)
        if not (self.root / rel).is_file():
            raise FileNotFoundError(f"{self.root / rel}: result file not found")
        self._adopted.add(rel)
        return self.root / rel

    @property
    def files(self) -> tuple[str, ...]:
        """Relative paths of the files written so far (not yet committed)."""
        return tuple(sorted({*self._pending, *self._adopted}))

    # -- commit
    def commit(self, doc: Mapping[str, Any], *, indent: int | None = 2,
               default: Callable[[Any], Any] | None = None) -> pathlib.Path:
        """Make the result visible; ``doc`` (the main JSON, a mapping) is written last with
        its ``"files"`` manifest. Returns the main JSON's path."""
        if self._committed:
            raise RuntimeError("OutputDir: already committed")
        manifest = {}
        for rel in self.files:
            sealed = self._sealed.get(rel)
            manifest[rel] = sealed or self._seal(self._pending.get(rel, self.root / rel))
        body = strict_document({**dict(doc), "files": manifest}, default=default)
        text = json.dumps(body, indent=indent, allow_nan=False) + "\n"
        main = self.root / self.main_json
        main.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(main.parent)
        main_tmp = _tmp_name(main)
        try:
            main_tmp.write_bytes(text.encode("utf-8"))
            if self.durable:
                _fsync_file(main_tmp)
        except BaseException:
            _unlink(main_tmp)
            raise
        old = _old_manifest(main)
        _pause()
        # the commit: no valid main JSON while the files move, the new one last
        _unlink(main)
        dirs = {main.parent}
        for rel, tmp in self._pending.items():
            final = self.root / rel
            os.replace(tmp, final)
            dirs.add(final.parent)
            _pause()
        if self.durable:
            for d in dirs:
                _fsync_dir(d)
        os.replace(main_tmp, main)
        if self.durable:
            _fsync_dir(main.parent)
        self._committed = True
        self._pending.clear()
        for rel in old:  # files of the previous result that this one does not have
            if rel not in manifest and rel != self.main_json:
                with contextlib.suppress(ValueError, OSError):
                    _unlink(self.root / _relpath(rel))
        return main


def _old_manifest(main: pathlib.Path) -> Iterable[str]:
    try:
        doc = loads_strict(main.read_bytes())
    except (OSError, ValueError):
        return ()
    files = doc.get("files") if isinstance(doc, dict) else None
    return list(files) if isinstance(files, dict) else ()


def _rerun(main_json: str) -> str:
    return (f"expected the complete result {main_json} describes (an interrupted write or "
            "files of two different runs?): write the result again")


def read_main_json(directory: str | os.PathLike, main_json: str) -> dict:
    """The main JSON of a result directory, parsed strictly; ``CampaignError`` if it is
    missing, unreadable, not strict JSON or not an object. No manifest check."""
    d = pathlib.Path(directory)
    main = d / _relpath(main_json)
    if not d.is_dir():
        raise CampaignError(d, "directory", "expected a results directory, not found or not a "
                            "directory")
    if not main.is_file():
        raise CampaignError(main, "file", f"not found, expected the {main_json} of a complete "
                            "result (none here, or a write was interrupted: write it again)")
    try:
        doc = loads_strict(main.read_bytes())
    except OSError as e:
        raise CampaignError(main, "file", f"not readable ({e.strerror or e}), expected a "
                            "readable file") from None
    except (ValueError, UnicodeDecodeError) as e:
        msg = str(e).splitlines()[0][:120] if str(e) else type(e).__name__
        raise CampaignError(main, "json", f"not strict JSON ({msg}), expected a complete "
                            f"{main_json} (truncated or edited?)") from None
    if not isinstance(doc, dict):
        raise CampaignError(main, "json", f"found a JSON {type(doc).__name__}, expected an "
                            "object")
    return doc


def verify_result_dir(directory: str | os.PathLike, main_json: str, *,
                      hashes: bool = True) -> dict:
    """Check that ``directory`` holds one complete result; return its parsed main JSON.

    Raises :class:`~hartrao_jax.campaign.CampaignError` (one line) when the main JSON is
    missing or not strict JSON, has no ``"files"`` manifest, or a listed file is missing or
    differs in size (or, with ``hashes``, in SHA-256) from what the manifest says.
    """
    d = pathlib.Path(directory)
    doc = read_main_json(d, main_json)
    main = d / _relpath(main_json)
    files = doc.get("files")
    if not isinstance(files, dict):
        raise CampaignError(main, "files", "no manifest of the result's files, expected the "
                            f"\"files\" key every {main_json} of this version carries "
                            "(written by an older version or by hand? write it again)")
    for rel, meta in files.items():
        try:
            path = d / _relpath(rel)
        except ValueError:
            raise CampaignError(main, "files", f"entry {rel!r}: expected a relative path "
                                "inside the directory") from None
        if not isinstance(meta, dict) or not isinstance(meta.get("bytes"), int):
            raise CampaignError(main, f"files.{rel}", "expected {\"bytes\": n, \"sha256\": hex}")
        if not path.is_file():
            raise CampaignError(path, "file", f"missing, {_rerun(main_json)}")
        size = path.stat().st_size
        if size != meta["bytes"]:
            raise CampaignError(path, "bytes", f"{size} bytes where {main_json} lists "
                                f"{meta['bytes']}, {_rerun(main_json)}")
        if hashes and meta.get("sha256") is not None:
            if file_digest(path)["sha256"] != meta["sha256"]:
                raise CampaignError(path, "sha256", f"content differs from {main_json}'s "
                                    f"manifest, {_rerun(main_json)}")
    return doc


# ----------------------------------------------------------------------------- output paths


def check_output_path(path: str | os.PathLike, option: str, *, kind: str = "dir") -> None:
    """Refuse, before any work, an output path that cannot be created.

    ``kind="dir"``: ``path`` must be a directory or creatable as one; ``kind="file"``: a
    file (not a directory) in a creatable directory. Raises ``CampaignError`` naming
    ``option`` (e.g. ``--out``): a regular file on the way, a directory where a file is
    wanted, or a directory that cannot be written to.
    """
    p = pathlib.Path(path)
    if kind not in ("dir", "file"):
        raise ValueError(f"kind must be 'dir' or 'file', not {kind!r}")
    if p.exists():
        if kind == "dir" and not p.is_dir():
            raise CampaignError(option, str(p), "is a regular file, expected a directory (or "
                                "a path where one can be created)")
        if kind == "file" and p.is_dir():
            raise CampaignError(option, str(p), "is a directory, expected a file name")
    # the nearest existing ancestor must be a writable directory
    anc = p if (kind == "dir" and p.exists()) else p.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise CampaignError(option, str(p), f"{str(anc)!r} on its path is a regular file, "
                            "expected a directory (or a path where one can be created)")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise CampaignError(option, str(p), f"directory {str(anc)!r} is not writable, "
                            "expected a writable place for the output")


__all__ = ["NONFINITE_NOTE", "OutputDir", "check_output_path", "dumps_strict", "file_digest",
           "loads_strict", "read_main_json", "remove_stale_temporaries", "strict_document",
           "strict_json", "verify_result_dir", "write_bytes_atomic", "write_file_atomic",
           "write_json_atomic",
           "write_text_atomic"]
