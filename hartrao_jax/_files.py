"""Files written whole or not at all: a temporary name in the same folder, then a rename;
and files hashed as they are written (their manifest entries, :class:`HashingFile`).

The base of :mod:`.campaign._safeio` (every output of the package) and of :mod:`._programs`
(compiled programs kept on disk), which both sit on it; nothing of the package below it.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pathlib
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


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
#: writeback.
WRITEBACK_BYTES = 64 << 20


class HashingFile:
    """A new file written front to back (a file object for writers such as pyarrow's), whose
    size and SHA-256 are taken as its bytes pass, so that its manifest entry needs no second
    read (:attr:`digest` once closed); every :data:`WRITEBACK_BYTES` its written pages are
    handed to the kernel's writeback (``posix_fadvise(DONTNEED)`` where there is one), so that
    a later ``fsync`` waits for the rest only.

    The two 6.3e6-row residual tables of a position of 1.26e7 points, written at once: 1.30 s
    with the flush and a second read for the hash, 1.04 s so (``benchmarks/results/profile.md``).
    """

    def __init__(self, path: str | os.PathLike):
        self._f = open(path, "wb", buffering=0)  # noqa: SIM115 (closed by close())
        self._hash = hashlib.sha256()
        self._n = 0
        self._handed = 0
        self.digest: FileDigest | None = None

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        self._hash.update(view)
        done = 0
        while done < len(view):
            done += self._f.write(view[done:])
        self._n += len(view)
        if self._n - self._handed >= WRITEBACK_BYTES and hasattr(os, "posix_fadvise"):
            os.posix_fadvise(self._f.fileno(), self._handed, self._n - self._handed,
                             os.POSIX_FADV_DONTNEED)
            self._handed = self._n
        return len(view)

    def tell(self) -> int:
        return self._n

    def flush(self) -> None:
        pass

    def writable(self) -> bool:
        return True

    @property
    def closed(self) -> bool:
        return self._f.closed

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()
            self.digest = FileDigest(self._n, self._hash.hexdigest())

    def __enter__(self) -> HashingFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
