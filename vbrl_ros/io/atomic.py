"""Crash-safe file replacement: write a temporary file beside the target, then rename.

A reader (or a robot restarting after a crash mid-save) sees either the last
complete file or the new complete file, never a half-written one: rename is
atomic within one filesystem on POSIX. A writer killed mid-write (kill -9, power
cut) leaves its temporary file behind; the writer holds an exclusive ``flock`` on
it while writing, which the kernel releases when the process dies, so
:func:`remove_stale_temporaries` tells such leftovers from a write in progress.
"""

from __future__ import annotations

import errno
import fcntl
import glob
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> Path:
    """Call ``write(file)`` on a temporary file and atomically move it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)  # released on close, or when the process dies
        except OSError:  # a filesystem without locks: the write goes on, unmarked
            pass
        # mkstemp creates 0600; give the file the permissions open() would have
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())  # data on disk before the rename makes it visible
            os.replace(tmp_name, path)  # still locked: no cleaner takes a file being renamed
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return path


def check_writable(path: str | os.PathLike) -> None:
    """Raise ``OSError`` (with ``strerror`` and ``filename``) unless :func:`atomic_write` can write ``path``.

    Creates the missing folders, as the first write would, and a temporary file
    there (removed at once): a read-only filesystem or missing permission shows now.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "a folder, not a file", str(path))
    blocking = next((folder for folder in path.parents if folder.exists() and not folder.is_dir()), None)
    if blocking is not None:
        raise NotADirectoryError(errno.ENOTDIR, "a file where a folder should be", str(blocking))
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryFile(dir=path.parent):
        pass


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files that writers of ``path`` killed mid-write left beside it.

    A write in progress (its flock held) keeps its file. Returns the removed files.
    """
    path = Path(path)
    removed = []
    for candidate in sorted(path.parent.glob(f".{glob.escape(path.name)}.*.tmp")):
        try:
            fd = os.open(candidate, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:  # renamed or removed meanwhile, or not ours to open
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            continue  # a live writer holds it
        else:
            candidate.unlink(missing_ok=True)
            removed.append(candidate)
        finally:
            os.close(fd)
    return removed


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
