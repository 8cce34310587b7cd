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
    """Read an RGB EXR (channels R, G, B) as (rows, cols, 3) float32."""
    _, channels = read_exr(path)
    if not {"R", "G", "B"} <= set(channels):
        raise DataError(f"{path}: expected channels R, G, B (an RGB EXR), got {sorted(channels)}")
    return np.stack([channels[c] for c in "RGB"], axis=-1)


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
    if not path.is_file():
        raise DataError(f"EXR file {path} does not exist")
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
