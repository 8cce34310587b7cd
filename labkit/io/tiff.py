"""Raw frames as lossless 16-bit TIFF with labkit metadata in the ImageDescription tag."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import tifffile

from labkit.errors import DataError
from labkit.io.atomic import atomic_path


def encode_raw_tiff(image: np.ndarray, metadata: dict[str, Any] | None = None) -> bytes:
    """A Bayer mosaic (rows, cols) uint8/uint16 as the bytes of an uncompressed TIFF.

    `metadata` (JSON-serialisable) is stored in the ImageDescription tag as
    ``{"shape": [rows, cols], "labkit": metadata}`` (the leading ``shape`` keeps the
    tag a valid tifffile JSON description whatever keys `metadata` holds).
    """
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise DataError(
            f"a raw frame must be a 2-D uint8/uint16 mosaic, got {image.dtype} {image.shape}"
        )
    description = json.dumps(
        {"shape": list(image.shape), "labkit": metadata or {}}, default=json_default
    )
    buffer = io.BytesIO()
    tifffile.imwrite(
        buffer, image, photometric="minisblack", description=description, metadata=None
    )
    return buffer.getvalue()


def write_raw_tiff(
    path: str | Path, image: np.ndarray, metadata: dict[str, Any] | None = None
) -> None:
    """Write a Bayer mosaic (rows, cols) uint8/uint16 as an uncompressed TIFF, atomically.

    `metadata` (JSON-serialisable) is stored in the ImageDescription tag.
    """
    try:
        data = encode_raw_tiff(image, metadata)
    except DataError as error:
        raise DataError(f"raw TIFF {path}: {error}") from None
    with atomic_path(path) as temp:
        temp.write_bytes(data)


def read_raw_tiff(
    path: str | Path, *, data: bytes | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Read a raw TIFF written by :func:`write_raw_tiff` (or any 2-D grey TIFF).

    Returns the image and the labkit metadata ({} if absent). With `data`, the file's
    bytes already read (and checked, :func:`labkit.io.digest.read_verified`) are decoded
    instead of reading `path`, which then only names the file in messages.
    """
    path = Path(path)
    try:
        with tifffile.TiffFile(path if data is None else io.BytesIO(data)) as tif:
            image = tif.asarray()
            description = tif.pages.first.description or ""
    except FileNotFoundError:
        raise DataError(f"raw frame {path} does not exist") from None
    except Exception as error:  # tifffile raises many types on corrupt files
        raise DataError(f"raw frame {path} is not a readable TIFF ({error})") from None
    if image.ndim != 2:
        raise DataError(f"raw frame {path}: expected a 2-D mosaic, got shape {image.shape}")
    return image, description_metadata(description)


def description_metadata(description: str) -> dict[str, Any]:
    """The labkit metadata of a TIFF ImageDescription ({} for other software's text)."""
    try:
        metadata = json.loads(description).get("labkit", {})
    except (json.JSONDecodeError, AttributeError):
        return {}
    return metadata if isinstance(metadata, dict) else {}


def json_default(value: Any) -> Any:
    """``json.dumps`` fallback: numpy scalars and arrays as Python values, others as text."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
