"""Pixel decoding (labkit.devices._pixels) against hand-computed byte patterns."""

from __future__ import annotations

import re

import numpy as np
import pytest

from labkit.devices import _pixels
from labkit.errors import DataError


def test_8bit_is_row_major_uint8() -> None:
    image = _pixels.decode(bytes([1, 2, 3, 4, 5, 6]), "BayerRG8", 3, 2)
    assert image.dtype == np.uint8
    np.testing.assert_array_equal(image, [[1, 2, 3], [4, 5, 6]])
    image[0, 0] = 9  # a writable copy, not a view of the buffer


def test_16bit_words_are_little_endian() -> None:
    data = bytes([0x34, 0x12, 0xFF, 0x0F, 0x00, 0x80, 0x01, 0x00])
    for fmt in ("BayerGB16", "BayerGB12", "BayerGB10", "Mono14"):
        image = _pixels.decode(data, fmt, 2, 2)
        assert image.dtype == np.uint16
        np.testing.assert_array_equal(image, [[0x1234, 0x0FFF], [0x8000, 0x0001]])
    words = np.array([0x1234, 0x0FFF, 0x8000, 0x0001], dtype="<u2")  # an array: its raw bytes
    np.testing.assert_array_equal(_pixels.decode(words, "BayerGB16", 2, 2), words.reshape(2, 2))


def test_12p_pfnc_lsb_first() -> None:
    # p0 = 0xABC, p1 = 0x123: byte0 = p0[7:0], byte1 = p1[3:0] p0[11:8], byte2 = p1[11:4]
    data = bytes([0xBC, 0x3A, 0x12])
    np.testing.assert_array_equal(_pixels.decode(data, "BayerRG12p", 2, 1), [[0xABC, 0x123]])


def test_12packed_gige_vision_legacy() -> None:
    # p0 = 0xABC, p1 = 0x123: byte0 = p0[11:4], byte1 = p1[3:0] p0[3:0], byte2 = p1[11:4]
    data = bytes([0xAB, 0x3C, 0x12])
    image = _pixels.decode(data, "BayerRG12Packed", 2, 1)
    assert image.dtype == np.uint16
    np.testing.assert_array_equal(image, [[0xABC, 0x123]])


def test_12p_and_12packed_differ_on_the_same_bytes() -> None:
    data = bytes([0xAB, 0x3C, 0x12])
    np.testing.assert_array_equal(_pixels.decode(data, "BayerBG12p", 2, 1), [[0xCAB, 0x123]])


def test_12p_odd_pixel_count_and_rows_straddling_groups() -> None:
    # 2 rows × 3 pixels = 6 pixels = 9 bytes; row 0 ends in the middle of group 1
    pixels = [0xABC, 0x123, 0x321, 0xFFF, 0x000, 0x800]
    data = bytes([0xBC, 0x3A, 0x12, 0x21, 0xF3, 0xFF, 0x00, 0x00, 0x80])
    image = _pixels.decode(data, "BayerGR12p", 3, 2)
    np.testing.assert_array_equal(image, np.reshape(pixels, (2, 3)))
    # 3 pixels need ceil(36 / 8) = 5 bytes
    np.testing.assert_array_equal(
        _pixels.decode(data[:5], "BayerGR12p", 3, 1), [[0xABC, 0x123, 0x321]]
    )


def test_10p_pfnc_lsb_first() -> None:
    # p = 0x3FF, 0x000, 0x155, 0x2AA laid end to end from bit 0
    data = bytes([0xFF, 0x03, 0x50, 0x95, 0xAA])
    image = _pixels.decode(data, "BayerGB10p", 4, 1)
    np.testing.assert_array_equal(image, [[0x3FF, 0x000, 0x155, 0x2AA]])


def test_10packed_gige_vision_legacy() -> None:
    # p0 = 0x2B7, p1 = 0x1C9: byte0 = p0[9:2], byte1 = 00 p1[1:0] 00 p0[1:0], byte2 = p1[9:2]
    data = bytes([0xAD, 0x13, 0x72])
    np.testing.assert_array_equal(_pixels.decode(data, "BayerGB10Packed", 2, 1), [[0x2B7, 0x1C9]])


def test_row_padding_is_skipped() -> None:
    data = bytes([1, 2, 3, 0xEE, 4, 5, 6])  # last row may come without its padding
    np.testing.assert_array_equal(
        _pixels.decode(data, "BayerRG8", 3, 2, padding_x=1), [[1, 2, 3], [4, 5, 6]]
    )
    packed = bytes([0xBC, 0x3A, 0x12, 0xEE, 0xEE, 0xAB, 0x3C, 0x12])
    np.testing.assert_array_equal(
        _pixels.decode(packed, "BayerRG12p", 2, 2, padding_x=2), [[0xABC, 0x123], [0xCAB, 0x123]]
    )


def test_trailing_bytes_are_ignored_and_short_buffers_rejected() -> None:
    np.testing.assert_array_equal(_pixels.decode(bytes([7, 8, 9]), "Mono8", 2, 1), [[7, 8]])
    with pytest.raises(DataError, match=r"holds 5 bytes, a 2×2 image needs 6"):
        _pixels.decode(bytes(5), "BayerRG12p", 2, 2)
    with pytest.raises(DataError, match=r"holds 2 bytes, a 2×1 image needs 3"):
        _pixels.decode(bytes(2), "BayerRG10Packed", 2, 1)  # 2 pixels in 3 bytes, not 20 bits
    with pytest.raises(DataError, match=r"holds 7 bytes, a 2×2 image needs 8"):
        _pixels.decode(bytes(7), "BayerRG16", 2, 2)


def test_unknown_format_names_the_decodable_ones() -> None:
    with pytest.raises(DataError, match=r"'RGB8' cannot be decoded; use one of .*BayerRG12p"):
        _pixels.decode(bytes(3), "RGB8", 1, 1)
    assert not _pixels.is_decodable("BayerRG14p")
    assert _pixels.pixel_format_layout("BayerBG12Packed").packing == "gev"
    assert _pixels.pixel_format_layout("BayerBG12p").packing == "pfnc"


def _pack_lsb_first(values: np.ndarray, bits: int) -> bytes:
    """Reference PFNC packer: one bit at a time (slow, obviously right)."""
    stream = 0
    for i, value in enumerate(values.tolist()):
        stream |= int(value) << (i * bits)
    return stream.to_bytes((len(values) * bits + 7) // 8, "little")


def _pack_gev(values: np.ndarray, bits: int) -> bytes:
    """Reference GigE Vision ``Packed`` packer, pair by pair."""
    low = bits - 8
    mask = (1 << low) - 1
    out = bytearray()
    padded = list(values.tolist()) + [0] * (len(values) % 2)
    for p0, p1 in zip(padded[0::2], padded[1::2], strict=True):
        out += bytes([p0 >> low, (p0 & mask) | ((p1 & mask) << 4), p1 >> low])
    return bytes(out)


@pytest.mark.parametrize(
    ("fmt", "bits", "packer"),
    [
        ("BayerRG12p", 12, _pack_lsb_first),
        ("BayerRG10p", 10, _pack_lsb_first),
        ("BayerRG12Packed", 12, _pack_gev),
        ("BayerRG10Packed", 10, _pack_gev),
    ],
)
def test_packed_round_trip_on_random_images(fmt: str, bits: int, packer) -> None:
    rng = np.random.default_rng(7)
    for rows, cols in ((4, 6), (3, 5), (1, 7)):
        values = rng.integers(0, 1 << bits, size=rows * cols, dtype=np.uint16)
        data = packer(values, bits)
        image = _pixels.decode(data, fmt, cols, rows)
        np.testing.assert_array_equal(image, values.reshape(rows, cols))


def test_codes_match_aravis_constants() -> None:
    """The PFNC code table agrees with Aravis' ARV_PIXEL_FORMAT_* (when Aravis is here)."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError):
        pytest.skip("Aravis 0.8 typelib not installed")
    checked = 0
    for code, name in _pixels.PIXEL_FORMAT_CODES.items():
        match = re.match(r"^(Bayer)?(RG|BG|GR|GB|Mono)(\d+)(p|Packed)?$", name)
        assert match is not None
        stem = f"BAYER_{match[2]}" if match[1] else "MONO"
        suffix = {None: "", "p": "P", "Packed": "_PACKED"}[match[4]]
        constant = f"PIXEL_FORMAT_{stem}_{match[3]}{suffix}"
        if hasattr(Aravis, constant):
            assert getattr(Aravis, constant) == code, name
            checked += 1
    assert checked >= 39  # all but Mono10p / Mono12p, which Aravis 0.8.26 lacks
    assert _pixels.pixel_format_name(Aravis.PIXEL_FORMAT_BAYER_GB_12P) == "BayerGB12p"
    assert _pixels.pixel_format_code("BayerGB12Packed") == Aravis.PIXEL_FORMAT_BAYER_GB_12_PACKED
