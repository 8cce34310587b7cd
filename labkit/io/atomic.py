"""Crash-safe file writing: temporary file in the same folder, fsync, rename, fsync folder."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


@contextlib.contextmanager
def atomic_path(path: str | Path, *, suffix: str = ".part") -> Iterator[Path]:
    """Yield a temporary path that replaces `path` only when the block succeeds.

    Write the file at the yielded path (any library, any number of opens). Its name is
    hidden (a leading dot) and ends in `suffix`; libraries that pick a format from the
    name need one such as ``".part.exr"``. On success it
    is fsynced and renamed over `path`, and the folder entry is fsynced; a crash or
    exception leaves the old file or none — never a partial file under the final name.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, temp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix, dir=target.parent)
    os.close(fd)
    temp = Path(temp_name)
    try:
        yield temp
        os.chmod(temp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the usual mode
        fd = os.open(temp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(temp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            temp.unlink()
        raise
    fsync_directory(target.parent)


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a file handle whose content replaces `path` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as temp, open(temp, mode) as handle:
        yield handle


def _read_umask() -> int:
    """The process umask (read once at import: setting it is not thread-safe)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def process_umask() -> int:
    """The process umask as read at import (for giving files and folders the usual mode)."""
    return _UMASK


def fsync_directory(folder: str | Path) -> None:
    """Make a rename or new entry in `folder` durable."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write a UTF-8 text file atomically."""
    with atomic_write(path, "w") as handle:
        handle.write(text)
