"""Decoding of raw GenICam pixel buffers into numpy mosaics (private to the camera backends).

Supported layouts (``<cfa>`` is one of ``BayerRG``, ``BayerBG``, ``BayerGR``, ``BayerGB``,
or ``Mono``):

- ``<cfa>8``: one byte per pixel → uint8.
- ``<cfa>10``, ``<cfa>12``, ``<cfa>14``, ``<cfa>16``: one little-endian 16-bit word per
  pixel, value in the low bits → uint16.
- ``<cfa>10p``, ``<cfa>12p``: GenICam PFNC packed, LSB first: the pixel bits are laid end to
  end starting at bit 0 of byte 0 (12p: 2 pixels in 3 bytes; 10p: 4 pixels in 5 bytes) →
  uint16.
- ``<cfa>10Packed``, ``<cfa>12Packed``: the legacy GigE Vision packing, 2 pixels in 3 bytes:
  byte 0 and byte 2 hold the most significant bits of pixel 0 and pixel 1, byte 1 holds
  their least significant bits (pixel 0 in the low nibble, pixel 1 in the high nibble) →
  uint16.

Values are returned as delivered (no scaling to 16 bits). Everything is vectorised numpy.
The integer codes are the PFNC / GigE Vision pixel-format identifiers, the same numbers as
Aravis' ``ARV_PIXEL_FORMAT_*`` constants.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from labkit.errors import DataError

_STEMS = ("BayerGR", "BayerRG", "BayerGB", "BayerBG")

#: PFNC / GigE Vision pixel-format codes (== Aravis' ``ARV_PIXEL_FORMAT_*``) → names.
PIXEL_FORMAT_CODES: dict[int, str] = {
    0x01080001: "Mono8",
    0x01100003: "Mono10",
    0x010C0004: "Mono10Packed",
    0x01100005: "Mono12",
    0x010C0006: "Mono12Packed",
    0x01100025: "Mono14",
    0x01100007: "Mono16",
    0x010A0046: "Mono10p",
    0x010C0047: "Mono12p",
    # Bayer, in the order GR, RG, GB, BG
    0x01080008: "BayerGR8",
    0x01080009: "BayerRG8",
    0x0108000A: "BayerGB8",
    0x0108000B: "BayerBG8",
    0x0110000C: "BayerGR10",
    0x0110000D: "BayerRG10",
    0x0110000E: "BayerGB10",
    0x0110000F: "BayerBG10",
    0x01100010: "BayerGR12",
    0x01100011: "BayerRG12",
    0x01100012: "BayerGB12",
    0x01100013: "BayerBG12",
    0x0110002E: "BayerGR16",
    0x0110002F: "BayerRG16",
    0x01100030: "BayerGB16",
    0x01100031: "BayerBG16",
    0x010C0026: "BayerGR10Packed",
    0x010C0027: "BayerRG10Packed",
    0x010C0028: "BayerGB10Packed",
    0x010C0029: "BayerBG10Packed",
    0x010C002A: "BayerGR12Packed",
    0x010C002B: "BayerRG12Packed",
    0x010C002C: "BayerGB12Packed",
    0x010C002D: "BayerBG12Packed",
    0x010A0056: "BayerGR10p",
    0x010A0058: "BayerRG10p",
    0x010A0054: "BayerGB10p",
    0x010A0052: "BayerBG10p",
    0x010C0057: "BayerGR12p",
    0x010C0059: "BayerRG12p",
    0x010C0055: "BayerGB12p",
    0x010C0053: "BayerBG12p",
}

_NAME_TO_CODE = {name: code for code, name in PIXEL_FORMAT_CODES.items()}

_FORMAT_RE = re.compile(
    r"^(?P<stem>Bayer(?:RG|BG|GR|GB)|Mono)(?P<bits>8|10|12|14|16)(?P<pack>p|Packed)?$"
)


@dataclass(frozen=True)
class PixelLayout:
    """How one pixel format is laid out in memory.

    Attributes
    ----------
    name : str
        GenICam pixel-format name, e.g. ``BayerRG12p``.
    bits : int
        Significant bits per pixel.
    packing : str
        ``"none"`` (8 bits per byte or one 16-bit word per pixel), ``"pfnc"`` (``…p``,
        LSB-first bit stream) or ``"gev"`` (legacy GigE Vision ``…Packed``).
    """

    name: str
    bits: int
    packing: str

    @property
    def dtype(self) -> np.dtype:
        """Numpy dtype of the decoded image (uint8 for 8-bit formats, else uint16)."""
        return np.dtype(np.uint8) if self.bits == 8 else np.dtype(np.uint16)

    @property
    def storage_bits(self) -> int:
        """Bits one pixel occupies in memory (``…Packed`` stores 2 pixels in 3 bytes)."""
        if self.packing == "none":
            return 8 if self.bits == 8 else 16
        return 12 if self.packing == "gev" else self.bits

    def row_bytes(self, width: int) -> int:
        """Bytes one row of `width` pixels occupies, without padding."""
        return (width * self.storage_bits + 7) // 8

    def image_bytes(self, width: int, height: int) -> int:
        """Bytes of a contiguous `height` × `width` image, without padding."""
        if self.packing == "none":
            return height * self.row_bytes(width)
        return (width * height * self.storage_bits + 7) // 8


def pixel_format_layout(pixel_format: str) -> PixelLayout:
    """The memory layout of `pixel_format`, or DataError naming the decodable formats."""
    match = _FORMAT_RE.match(pixel_format)
    if match is None or (match["pack"] and match["bits"] not in ("10", "12")):
        raise DataError(
            f"pixel format {pixel_format!r} cannot be decoded; use one of "
            f"{', '.join(decodable_formats())}"
        )
    packing = {None: "none", "p": "pfnc", "Packed": "gev"}[match["pack"]]
    return PixelLayout(pixel_format, int(match["bits"]), packing)


def decodable_formats() -> list[str]:
    """Names of every pixel format :func:`decode` handles."""
    return sorted(PIXEL_FORMAT_CODES.values())


def is_decodable(pixel_format: str) -> bool:
    """Whether :func:`decode` handles `pixel_format`."""
    try:
        pixel_format_layout(pixel_format)
    except DataError:
        return False
    return True


def pixel_format_name(code: int) -> str | None:
    """GenICam name of a PFNC / GigE Vision pixel-format code (None if unknown)."""
    return PIXEL_FORMAT_CODES.get(int(code))


def pixel_format_code(name: str) -> int | None:
    """PFNC / GigE Vision code of a pixel-format name (None if unknown)."""
    return _NAME_TO_CODE.get(name)


# -- unpacking ---------------------------------------------------------------------------------
def _groups(raw: np.ndarray, n_pixels: int, group_bytes: int, group_pixels: int) -> np.ndarray:
    """`raw` (…, nbytes) zero-padded to whole groups and reshaped to (…, groups, bytes)."""
    n_groups = -(-n_pixels // group_pixels)
    need = n_groups * group_bytes
    have = raw.shape[-1]
    if have < need:
        pad = np.zeros((*raw.shape[:-1], need - have), dtype=np.uint8)
        raw = np.concatenate([raw, pad], axis=-1)
    return raw[..., :need].reshape(*raw.shape[:-1], n_groups, group_bytes).astype(np.uint16)


def _interleave(raw: np.ndarray, n_pixels: int, *pixels: np.ndarray) -> np.ndarray:
    """Pixels decoded per byte group (one array each) back in order, trimmed to `n_pixels`."""
    out = np.stack(pixels, axis=-1).reshape(*raw.shape[:-1], -1)
    return out[..., :n_pixels]


def unpack_12p(raw: np.ndarray, n_pixels: int) -> np.ndarray:
    """Unpack PFNC ``…12p`` bytes (LSB first, 2 pixels in 3 bytes) along the last axis.

    Parameters
    ----------
    raw : ndarray of uint8, shape (..., nbytes)
        Packed bytes; ``nbytes >= ceil(1.5 n_pixels)``.
    n_pixels : int
        Pixels to return per row of `raw`.

    Returns
    -------
    ndarray of uint16, shape (..., n_pixels)
    """
    g = _groups(raw, n_pixels, 3, 2)
    b0, b1, b2 = g[..., 0], g[..., 1], g[..., 2]
    p0 = b0 | ((b1 & 0x0F) << 8)
    p1 = (b1 >> 4) | (b2 << 4)
    return _interleave(raw, n_pixels, p0, p1)


def unpack_12packed(raw: np.ndarray, n_pixels: int) -> np.ndarray:
    """Unpack legacy GigE Vision ``…12Packed`` bytes (2 pixels in 3 bytes) along the last axis.

    Byte 0 holds bits 11..4 of pixel 0, byte 2 bits 11..4 of pixel 1; byte 1 holds bits 3..0
    of pixel 0 in its low nibble and bits 3..0 of pixel 1 in its high nibble.

    Parameters
    ----------
    raw : ndarray of uint8, shape (..., nbytes)
    n_pixels : int

    Returns
    -------
    ndarray of uint16, shape (..., n_pixels)
    """
    g = _groups(raw, n_pixels, 3, 2)
    b0, b1, b2 = g[..., 0], g[..., 1], g[..., 2]
    p0 = (b0 << 4) | (b1 & 0x0F)
    p1 = (b2 << 4) | (b1 >> 4)
    return _interleave(raw, n_pixels, p0, p1)


def unpack_10p(raw: np.ndarray, n_pixels: int) -> np.ndarray:
    """Unpack PFNC ``…10p`` bytes (LSB first, 4 pixels in 5 bytes) along the last axis.

    Parameters
    ----------
    raw : ndarray of uint8, shape (..., nbytes)
    n_pixels : int

    Returns
    -------
    ndarray of uint16, shape (..., n_pixels)
    """
    g = _groups(raw, n_pixels, 5, 4)
    b0, b1, b2, b3, b4 = (g[..., i] for i in range(5))
    p0 = b0 | ((b1 & 0x03) << 8)
    p1 = (b1 >> 2) | ((b2 & 0x0F) << 6)
    p2 = (b2 >> 4) | ((b3 & 0x3F) << 4)
    p3 = (b3 >> 6) | (b4 << 2)
    return _interleave(raw, n_pixels, p0, p1, p2, p3)


def unpack_10packed(raw: np.ndarray, n_pixels: int) -> np.ndarray:
    """Unpack legacy GigE Vision ``…10Packed`` bytes (2 pixels in 3 bytes) along the last axis.

    Byte 0 holds bits 9..2 of pixel 0, byte 2 bits 9..2 of pixel 1; byte 1 holds bits 1..0
    of pixel 0 in bits 1..0 and bits 1..0 of pixel 1 in bits 5..4.

    Parameters
    ----------
    raw : ndarray of uint8, shape (..., nbytes)
    n_pixels : int

    Returns
    -------
    ndarray of uint16, shape (..., n_pixels)
    """
    g = _groups(raw, n_pixels, 3, 2)
    b0, b1, b2 = g[..., 0], g[..., 1], g[..., 2]
    p0 = (b0 << 2) | (b1 & 0x03)
    p1 = (b2 << 2) | ((b1 >> 4) & 0x03)
    return _interleave(raw, n_pixels, p0, p1)


_UNPACKERS = {
    ("pfnc", 12): unpack_12p,
    ("gev", 12): unpack_12packed,
    ("pfnc", 10): unpack_10p,
    ("gev", 10): unpack_10packed,
}


def decode(
    data: bytes | bytearray | memoryview | np.ndarray,
    pixel_format: str,
    width: int,
    height: int,
    *,
    padding_x: int = 0,
) -> np.ndarray:
    """Decode one raw image buffer into a (height, width) array.

    Parameters
    ----------
    data : bytes-like or ndarray
        The image payload as received (an array is read as its raw bytes); trailing bytes
        beyond the image are ignored.
    pixel_format : str
        GenICam pixel-format name, e.g. ``BayerRG8``, ``BayerGB12``, ``BayerRG12p``.
    width, height : int
        Image size, pixels.
    padding_x : int
        Bytes of padding at the end of each row (GigE Vision ``padding_x``). When 0 the
        image is one contiguous stream (packed formats may then straddle rows).

    Returns
    -------
    ndarray, shape (height, width)
        uint8 for 8-bit formats, uint16 otherwise; a new, writable array.

    Raises
    ------
    DataError
        The format is not decodable or `data` is shorter than the image.
    """
    layout = pixel_format_layout(pixel_format)
    if width <= 0 or height <= 0 or padding_x < 0:
        raise DataError(
            f"{pixel_format} image size {width}×{height} (padding {padding_x}) is invalid; "
            "width and height must be positive"
        )
    raw = np.frombuffer(
        np.ascontiguousarray(data) if isinstance(data, np.ndarray) else data, np.uint8
    )
    if padding_x:
        stride = layout.row_bytes(width) + padding_x
        need = stride * height - padding_x
    else:
        stride = 0
        need = layout.image_bytes(width, height)
    if raw.size < need:
        raise DataError(
            f"{pixel_format} buffer holds {raw.size} bytes, a {width}×{height} image needs "
            f"{need}; the frame is truncated or the pixel format / size is wrong"
        )
    if padding_x:
        body = np.zeros(stride * height, dtype=np.uint8)
        body[:need] = raw[:need]
        rows = body.reshape(height, stride)[:, : layout.row_bytes(width)]
    else:
        rows = raw[:need].reshape(1, need) if layout.packing != "none" else raw[:need]
    if layout.packing == "none":
        if layout.bits == 8:
            return np.array(rows, dtype=np.uint8).reshape(height, width)
        words = np.ascontiguousarray(rows).view("<u2")
        return words.astype(np.uint16).reshape(height, width)
    unpack = _UNPACKERS[(layout.packing, layout.bits)]
    if padding_x:
        return unpack(rows, width)
    return unpack(rows, width * height).reshape(height, width)
