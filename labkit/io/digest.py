"""Checksums of stored files: sha256 of a file, and reading a file checked against its record."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from labkit.errors import DataError

_BLOCK = 1 << 22


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes (hex), read in 4 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(_BLOCK):
            digest.update(chunk)
    return digest.hexdigest()


def read_verified(path: str | Path, *, sha256: str, size: int | None, name: str) -> bytes:
    """A file's bytes, read once and checked against its recorded size and checksum.

    Parameters
    ----------
    path : str or Path
        The file.
    sha256 : str
        Its recorded sha256 (hex).
    size : int or None
        Its recorded size in bytes, if known (checked before reading).
    name : str
        How messages name the file (e.g. ``"frame disks/450/10ms/r001 (…)"``).

    Raises
    ------
    DataError
        The file is missing, or its size or checksum is not the recorded one.
    """
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            actual = os.fstat(handle.fileno()).st_size
            if size is not None and actual != size:
                raise DataError(
                    f"{name} is {actual} bytes but {size} were recorded: the file was changed "
                    "or replaced after capture"
                )
            data = handle.read()
    except FileNotFoundError:
        raise DataError(f"{name} is missing") from None
    except IsADirectoryError:
        raise DataError(f"{name} is a folder, not a file") from None
    if hashlib.sha256(data).hexdigest() != sha256:
        raise DataError(
            f"{name} does not match its recorded sha256: the file was changed or replaced "
            "after capture"
        )
    return data
