"""Files written whole or not at all: a temporary name in the same folder, then a rename.

The base of :mod:`.campaign._safeio` (every output of the package) and of :mod:`._programs`
(compiled programs kept on disk), which both sit on it; nothing of the package below it.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import secrets
from collections.abc import Callable
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
