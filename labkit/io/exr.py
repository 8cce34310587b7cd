"""OpenEXR files: HDR raw mosaics and RGB images (the formats of DESIGN.md).

A **raw image** holds one float32 channel ``raw`` (the Bayer mosaic) and optionally
``variance``; its header carries ``cfa``, ``exposure_s``, ``illumination``,
``wavelength_nm`` (filtered light only) and ``labkit`` (JSON provenance, which also keeps
the exact float64 values of the numeric attributes, since EXR float attributes are
float32).

Spectral images are :mod:`labkit.io.spectral_exr`.

All are written atomically: a crash never leaves a partial file under the final name.
"""

from __future__ import annotations

import errno
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from labkit.cfa import check_layout
from labkit.errors import DataError
from labkit.io.atomic import atomic_path
from labkit.io.tiff import json_default

FORMAT_VERSION = 1


@dataclass
class RawImage:
    """A raw (or HDR raw) mosaic with its metadata.

    Attributes
    ----------
    raw : ndarray (rows, cols) float32
        The mosaic; for HDR images, the fraction of saturation at `exposure_s`.
    cfa : str
        Bayer layout, e.g. ``"GBRG"``.
    exposure_s : float or None
        Exposure the values refer to, s; None when unknown (an image from other software
        that does not record it, see :func:`labkit.io.read_mosaic`).
    illumination : str
        Illumination name (slider position), e.g. ``"unfiltered"`` or ``"550"``; ``""``
        when unknown.
    wavelength_nm : float or None
        Centre wavelength of the bandpass filter, nm (None for unfiltered light).
    variance : ndarray (rows, cols) float32 or None
        Per-pixel variance of `raw`, in `raw` units squared.
    labkit : dict
        Provenance and method-specific facts (JSON).
    """

    raw: np.ndarray
    cfa: str
    exposure_s: float | None
    illumination: str
    wavelength_nm: float | None = None
    variance: np.ndarray | None = None
    labkit: dict[str, Any] = field(default_factory=dict)


def write_raw_exr(path: str | Path, image: RawImage) -> None:
    """Write a :class:`RawImage` as an OpenEXR file, atomically.

    The image's `exposure_s` must be known (a positive number of seconds): labkit's raw
    EXRs always record it.
    """
    import OpenEXR

    raw = checked_plane(path, "raw", image.raw)
    channels = {"raw": raw}
    if image.variance is not None:
        variance = checked_plane(path, "variance", image.variance)
        if variance.shape != raw.shape:
            raise DataError(f"{path}: variance {variance.shape} does not match raw {raw.shape}")
        channels["variance"] = variance
    exposure = math.nan if image.exposure_s is None else float(image.exposure_s)
    if not np.isfinite(exposure) or exposure <= 0:
        raise DataError(
            f"{path}: exposure_s must be a positive number of seconds, got {image.exposure_s}"
        )
    provenance = {
        "format": FORMAT_VERSION,
        "kind": "raw",
        "exposure_s": exposure,
        "wavelength_nm": image.wavelength_nm,
        **image.labkit,
    }
    header: dict[str, Any] = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "cfa": check_layout(image.cfa),
        "exposure_s": exposure,
        "illumination": str(image.illumination),
        "labkit": json.dumps(provenance, default=json_default),
    }
    if image.wavelength_nm is not None:
        header["wavelength_nm"] = float(image.wavelength_nm)
    write_exr(path, header, channels)


def read_raw_exr(path: str | Path) -> RawImage:
    """Read a raw EXR written by :func:`write_raw_exr` (its `exposure_s` is always set).

    EXRs from other software (no ``cfa`` or ``exposure_s`` attribute) and other kinds of
    raw file are read by :func:`labkit.io.read_mosaic`.
    """
    header, channels = read_exr(path)
    if "raw" not in channels:
        raise DataError(
            f"{path}: no 'raw' channel (channels: {sorted(channels)}); "
            "is this a spectral image rather than a raw mosaic?"
        )
    if "cfa" not in header:
        raise DataError(f"{path}: header has no 'cfa' attribute; not a labkit raw EXR")
    provenance = read_provenance(path, header)
    exposure = provenance.get("exposure_s", header.get("exposure_s"))
    if exposure is None:
        raise DataError(f"{path}: header has no 'exposure_s' attribute")
    wavelength = provenance.get("wavelength_nm", header.get("wavelength_nm"))
    return RawImage(
        raw=channels["raw"],
        cfa=check_layout(str(header["cfa"])),
        exposure_s=float(exposure),
        illumination=str(header.get("illumination", "")),
        wavelength_nm=None if wavelength is None else float(wavelength),
        variance=channels.get("variance"),
        labkit=provenance,
    )


def write_rgb_exr(path: str | Path, rgb: np.ndarray, labkit: dict[str, Any] | None = None) -> None:
    """Write a linear (rows, cols, 3) image as an RGB OpenEXR (channels R, G, B), atomically."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise DataError(f"{path}: an RGB image must be (rows, cols, 3), got {rgb.shape}")
    import OpenEXR

    channels = {name: checked_plane(path, name, rgb[:, :, i]) for i, name in enumerate("RGB")}
    provenance = {**(labkit or {}), "format": FORMAT_VERSION, "kind": "rgb"}
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "labkit": json.dumps(provenance, default=json_default),
    }
    write_exr(path, header, channels)


def read_rgb_exr(path: str | Path) -> np.ndarray:
    """Read an RGB EXR (channels R, G, B) in camera colour as (rows, cols, 3) float32.

    A spectral EXR is refused: its R, G, B channels are an sRGB preview of the spectra.
    """
    header, channels = read_exr(path)
    if is_spectral_layout(header, list(channels)):
        raise DataError(
            f"{path} is a spectral EXR, not a colour image (its R, G, B channels are an sRGB "
            "preview, not raw camera colour); give an RGB EXR in raw camera colour, such as "
            "the raw_colour.exr of `labkit reconstruct`"
        )
    if not {"R", "G", "B"} <= set(channels):
        raise DataError(
            f"{path} has channels {sorted(channels)}; expected R, G, B (an RGB EXR in raw "
            "camera colour, such as the raw_colour.exr of `labkit reconstruct`)"
        )
    return np.stack([channels[c] for c in "RGB"], axis=-1)


def is_spectral_layout(header: dict[str, Any], channels: list[str]) -> bool:
    """Whether a header (and its channel names) is in the Fichet et al. (2021) layout for
    spectral images (:mod:`labkit.io.spectral_exr`)."""
    if "spectralLayoutVersion" in header:
        return True
    return any(name.startswith(("S0.", "T.")) and name.endswith(("m", "Hz")) for name in channels)


def checked_plane(path: str | Path, name: str, plane: np.ndarray) -> np.ndarray:
    plane = np.asarray(plane)
    if plane.ndim != 2:
        raise DataError(f"{path}: channel {name!r} must be 2-D, got shape {plane.shape}")
    plane = np.ascontiguousarray(plane, dtype=np.float32)
    bad = int(np.count_nonzero(~np.isfinite(plane)))
    if bad:
        raise DataError(
            f"{path}: channel {name!r} has {bad} NaN/Inf pixels; refusing to write them"
        )
    return plane


def write_exr(path: str | Path, header: dict[str, Any], channels: dict[str, np.ndarray]) -> None:
    import OpenEXR

    with atomic_path(path) as temp:
        try:
            OpenEXR.File(header, channels).write(str(temp))
        except RuntimeError as error:  # the binding reports system errors as bare text
            raise _system_error(error, temp) from None


_SYSTEM_ERROR_TEXTS = {
    "No space left on device": errno.ENOSPC,
    "Disk quota exceeded": errno.EDQUOT,
    "Read-only file system": errno.EROFS,
    "Permission denied": errno.EACCES,
}


def _system_error(error: RuntimeError, path: Path) -> Exception:
    """The OSError behind an OpenEXR RuntimeError's text, so that a full disk reads as one."""
    for text, code in _SYSTEM_ERROR_TEXTS.items():
        if text in str(error):
            return OSError(code, text, str(path))
    return error


def read_exr(path: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header and the float32 channels of an EXR file; :class:`DataError` if unreadable."""
    exr = _open(path, header_only=False)
    try:
        channels = {
            name: np.asarray(channel.pixels, dtype=np.float32)
            for name, channel in exr.channels().items()
        }
    except Exception as error:  # the binding raises bare RuntimeErrors on bad files
        raise DataError(f"{path} is not a readable OpenEXR file ({error})") from None
    return dict(exr.header()), channels


def read_exr_header(path: str | Path) -> dict[str, Any]:
    """The header of an EXR file, pixels not decoded (its ``channels`` entry lists the
    channels); :class:`DataError` if unreadable."""
    return dict(_open(path, header_only=True).header())


def _open(path: str | Path, *, header_only: bool) -> Any:
    import OpenEXR

    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path} is a folder; give an EXR file")
    if not path.is_file():
        raise DataError(f"EXR file {path} does not exist")
    check_exr_file(path)
    try:
        return OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
    except Exception as error:  # the binding raises bare RuntimeErrors on bad files
        raise DataError(f"{path} is not a readable OpenEXR file ({error})") from None


def read_provenance(path: str | Path, header: dict[str, Any]) -> dict[str, Any]:
    text = header.get("labkit")
    if text is None:
        return {}
    try:
        value = json.loads(text)
    except (TypeError, json.JSONDecodeError):
        raise DataError(f"{path}: the 'labkit' header attribute is not valid JSON") from None
    return value if isinstance(value, dict) else {}


# -- a file's first bytes: what it is, and whether it is whole ---------------------------------
EXR_MAGIC = b"\x76\x2f\x31\x01"
_MAGICS = {
    b"II*\x00": "a TIFF file (.tif)",
    b"MM\x00*": "a TIFF file (.tif)",
    b"\x89PNG": "a PNG file (.png)",
    b"\xff\xd8\xff": "a JPEG file (.jpg)",
}
_SINGLE_PART_SCANLINE = 0x200 | 0x800 | 0x1000  # version flags: tiled, deep, multi-part
#: Scanlines per chunk by compression (OpenEXR's compression attribute).
_LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256}


def check_exr_file(path: str | Path) -> None:
    """Raise DataError naming what `path` is, unless it starts like a whole OpenEXR file.

    Checks the magic number, and for single-part scanline files (what labkit writes) that
    the chunk table points inside the file, so that a truncated file is called truncated
    (the library would print its own errors and fail with a vaguer one).
    """
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            head = handle.read(1 << 16)
        size = path.stat().st_size
    except OSError as error:
        raise DataError(f"{path} cannot be read ({error.strerror})") from None
    if not head.startswith(EXR_MAGIC):
        kind = next((k for magic, k in _MAGICS.items() if head.startswith(magic)), None)
        what = f"it is {kind}: give it that suffix" if kind else "it does not start like one"
        raise DataError(f"{path} is not an OpenEXR file ({what})")
    try:
        table = _chunk_table(head)
    except EOFError:
        if len(head) < size:
            return  # a header longer than this check reads
        raise DataError(f"{path} is truncated ({size} bytes: its header is cut short)") from None
    if table is None:
        return  # a layout this check does not read (tiled, deep, multi-part, huge header)
    start, chunks = table
    if start + 8 * chunks > size:
        raise DataError(f"{path} is truncated ({size} bytes, its header promises more)")
    with open(path, "rb") as handle:
        handle.seek(start)
        offsets = np.frombuffer(handle.read(8 * chunks), dtype="<u8")
        last = int(offsets.max()) if offsets.size else 0
        handle.seek(last)
        leader = handle.read(8)  # the last chunk's first row and its size in bytes
    end = last + 8 + int.from_bytes(leader[4:8], "little", signed=True) if len(leader) == 8 else -1
    if offsets.size and (offsets.min() < start + 8 * chunks or not last < end <= size):
        raise DataError(
            f"{path} is truncated or damaged ({size} bytes, but its last chunk ends at byte "
            f"{max(end, last)}); write or copy it again"
        )


def _chunk_table(head: bytes) -> tuple[int, int] | None:
    """(offset, count) of a single-part scanline file's chunk table, from its header; None
    for other layouts; EOFError where `head` ends inside the header."""
    version = int.from_bytes(head[4:8], "little")
    if version & _SINGLE_PART_SCANLINE:
        return None
    at, window, compression = 8, None, None
    while True:
        name_end = head.find(b"\0", at)
        if name_end < 0:
            raise EOFError
        if name_end == at:  # an empty name ends the header
            at += 1
            break
        type_end = head.find(b"\0", name_end + 1)
        if type_end < 0 or type_end + 5 > len(head):
            raise EOFError
        length = int.from_bytes(head[type_end + 1 : type_end + 5], "little", signed=True)
        value = head[type_end + 5 : type_end + 5 + length]
        if length < 0:
            return None
        if len(value) < length:
            raise EOFError
        name = head[at:name_end]
        if name == b"dataWindow" and length == 16:
            window = np.frombuffer(value, dtype="<i4")
        elif name == b"compression" and length == 1:
            compression = value[0]
        at = type_end + 5 + length
    if window is None or compression not in _LINES_PER_CHUNK:
        return None
    rows = int(window[3]) - int(window[1]) + 1
    if rows <= 0:
        return None
    return at, -(-rows // _LINES_PER_CHUNK[compression])
