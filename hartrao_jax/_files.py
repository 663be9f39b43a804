"""Files written whole or not at all: a temporary name in the same folder, then a rename;
and files hashed as they are written (their manifest entries, :class:`HashingFile`).

The base of :mod:`.campaign._safeio` (every output of the package) and of :mod:`._programs`
(compiled programs kept on disk), which both sit on it; nothing of the package below it.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import mmap
import os
import pathlib
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

try:
    import fcntl
except ImportError:  # not a Unix: no direct writes either
    fcntl = None


def tmp_name(final: pathlib.Path) -> pathlib.Path:
    """A temporary name beside ``final`` (hidden, of this process, random)."""
    return final.with_name(f".{final.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")


def fsync_file(path: pathlib.Path) -> None:
    """Flush ``path``'s data to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(path: pathlib.Path) -> None:
    """Flush the folder ``path`` (its renames) to the disk, where the file system allows."""
    with contextlib.suppress(OSError):  # not every file system lets a directory be synced
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def unlink(path: pathlib.Path, ignore: tuple[type[OSError], ...] = (FileNotFoundError,)) -> None:
    """Remove ``path``; the errors ``ignore`` (default: it is not there) are not raised."""
    with contextlib.suppress(*ignore):
        path.unlink()


def write_via_temp(final: pathlib.Path, write: Callable[[pathlib.Path], Any], *,
                   durable: bool = True) -> pathlib.Path:
    """``write(temporary path)`` and rename it to ``final`` (parents created); the temporary
    file is removed if anything fails (and the error raised). ``durable``: file and folder
    flushed to the disk."""
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = tmp_name(final)
    try:
        write(tmp)
        if durable:
            fsync_file(tmp)
        os.replace(tmp, final)
    except BaseException:
        unlink(tmp)
        raise
    if durable:
        fsync_dir(final.parent)
    return final


@dataclass(frozen=True)
class FileDigest:
    """A file's manifest entry: its size (bytes) and SHA-256 (hex)."""

    bytes: int
    sha256: str

    def entry(self) -> dict[str, Any]:
        """``{"bytes": n, "sha256": hex}``, as result manifests list it."""
        return {"bytes": self.bytes, "sha256": self.sha256}


#: Bytes a :class:`HashingFile` writes between two hand-overs of its pages to the kernel's
#: writeback (where it cannot write around the page cache).
WRITEBACK_BYTES = 64 << 20
#: Bytes of a :class:`HashingFile`'s aligned buffer for writes around the page cache; a
#: multiple of every block size direct writes may need.
DIRECT_BYTES = 8 << 20
#: ``$HARTRAO_JAX_DIRECT_WRITES=0``: every file through the page cache.
DIRECT_WRITES_ENV = "HARTRAO_JAX_DIRECT_WRITES"


def _open_new(path: str | os.PathLike) -> tuple[int, bool]:
    """``(descriptor, direct)``: ``path`` created (or truncated) for writing, with
    ``O_DIRECT`` where the system and the file system take it (Linux's ext4, xfs, btrfs;
    tmpfs since Linux 6.6, as here; an older one refuses it at the open), unless
    :data:`DIRECT_WRITES_ENV` is ``0``."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0)
    direct = getattr(os, "O_DIRECT", 0)
    if direct and fcntl is not None and os.environ.get(DIRECT_WRITES_ENV, "1") != "0":
        try:
            return os.open(path, flags | direct, 0o666), True
        except OSError as e:
            if e.errno != errno.EINVAL:
                raise
    return os.open(path, flags, 0o666), False


class HashingFile:
    """A new file written front to back (a file object for writers such as pyarrow's), whose
    size and SHA-256 are taken as its bytes pass, so that its manifest entry needs no second
    read (:attr:`digest` once closed).

    Where the file system allows, the bytes go to the disk around the page cache
    (``O_DIRECT``) from a page-aligned buffer of :data:`DIRECT_BYTES`, its last part of less
    than a block written through the page cache. The kernel then neither copies them into
    new page-cache pages (which a VM backs as slowly as fresh memory) nor writes them back
    later: the thread writing a 680-MB residual table 1.4-1.9 -> 1.0 CPU-s, measured
    (``benchmarks/results/profile.md``). Elsewhere every :data:`WRITEBACK_BYTES` the written
    pages are handed to the kernel's writeback (``posix_fadvise(DONTNEED)`` where there is
    one), so that a later ``fsync`` waits for the rest only.
    """

    def __init__(self, path: str | os.PathLike):
        self._fd, self._direct = _open_new(path)
        self._buf = mmap.mmap(-1, DIRECT_BYTES) if self._direct else None
        self._fill = 0  # bytes waiting in the buffer
        self._hash = hashlib.sha256()
        self._n = 0
        self._handed = 0
        self._closed = False
        self.digest: FileDigest | None = None

    def _write_all(self, view: memoryview) -> None:
        done = 0
        while done < len(view):
            try:
                done += os.write(self._fd, view[done:])
            except OSError as e:  # a file system that opens O_DIRECT but will not write so
                if not (self._direct and e.errno == errno.EINVAL):
                    raise
                self._through_page_cache()

    def _through_page_cache(self) -> None:
        fcntl.fcntl(self._fd, fcntl.F_SETFL, fcntl.fcntl(self._fd, fcntl.F_GETFL) & ~os.O_DIRECT)
        self._direct = False

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        self._hash.update(view)
        n = len(view)
        if self._buf is None:
            self._write_all(view)
        else:
            done = 0
            while done < n:  # through the aligned buffer, a whole buffer per direct write
                take = min(n - done, DIRECT_BYTES - self._fill)
                self._buf[self._fill:self._fill + take] = view[done:done + take]
                self._fill += take
                done += take
                if self._fill == DIRECT_BYTES:
                    self._write_all(memoryview(self._buf))
                    self._fill = 0
        self._n += n
        if (self._buf is None and self._n - self._handed >= WRITEBACK_BYTES
                and hasattr(os, "posix_fadvise")):
            os.posix_fadvise(self._fd, self._handed, self._n - self._handed,
                             os.POSIX_FADV_DONTNEED)
            self._handed = self._n
        return n

    def _finish_direct(self) -> None:
        """The buffer's rest: whole blocks directly, the last bytes through the page cache."""
        whole = self._fill - self._fill % 4096
        with memoryview(self._buf) as buf:
            self._write_all(buf[:whole])
            if self._fill > whole:
                if self._direct:
                    self._through_page_cache()
                self._write_all(buf[whole:self._fill])
        self._fill = 0

    def tell(self) -> int:
        return self._n

    def flush(self) -> None:
        pass

    def writable(self) -> bool:
        return True

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            if self._buf is not None:
                self._finish_direct()
                self._buf.close()
        finally:
            os.close(self._fd)
        self.digest = FileDigest(self._n, self._hash.hexdigest())

    def __enter__(self) -> HashingFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
