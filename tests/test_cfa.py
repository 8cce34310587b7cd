"""Bayer CFA layouts: channel placement, mosaicking, pixel formats, and the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from labkit.cfa import (
    CFA_LAYOUTS,
    channel_index,
    channel_masks,
    check_layout,
    layout_from_pixel_format,
    mosaic,
    pixel_format_for,
)
from labkit.errors import DataError
from labkit.sim import SimulatedRig

CHANNEL = {"R": 0, "G": 1, "B": 2}


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
def test_channel_index_block_and_period(layout: str) -> None:
    index = channel_index(layout, (6, 8))
    assert index.shape == (6, 8) and index.dtype == np.uint8
    block = [[CHANNEL[layout[0]], CHANNEL[layout[1]]], [CHANNEL[layout[2]], CHANNEL[layout[3]]]]
    np.testing.assert_array_equal(index[:2, :2], block)
    # period 2 in both axes
    np.testing.assert_array_equal(index[2:], index[:-2])
    np.testing.assert_array_equal(index[:, 2:], index[:, :-2])
    # every 2×2 block holds one R, two G and one B
    counts = np.bincount(index.ravel(), minlength=3)
    np.testing.assert_array_equal(counts, [12, 24, 12])


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
def test_channel_index_odd_shape_and_masks(layout: str) -> None:
    index = channel_index(layout, (5, 7))
    np.testing.assert_array_equal(index, channel_index(layout, (6, 8))[:5, :7])
    masks = channel_masks(layout, (5, 7))
    assert masks.shape == (5, 7, 3)
    np.testing.assert_array_equal(masks.sum(axis=2), 1)
    np.testing.assert_array_equal(np.argmax(masks, axis=2), index)


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
def test_mosaic_picks_the_named_channel(layout: str) -> None:
    rows, cols = 6, 8
    yy, xx = np.mgrid[0:rows, 0:cols]
    # channel-coded values: hundreds digit = channel + 1, the rest = pixel number
    image = np.stack([(c + 1) * 1000 + yy * cols + xx for c in range(3)], axis=2)
    raw = mosaic(image, layout)
    assert raw.shape == (rows, cols)
    np.testing.assert_array_equal(raw % 1000, yy * cols + xx)
    channel = raw // 1000 - 1
    for r in range(2):
        for c in range(2):
            expected = CHANNEL[layout[2 * r + c]]
            np.testing.assert_array_equal(channel[r::2, c::2], expected)


def test_mosaic_rejects_non_rgb() -> None:
    with pytest.raises(DataError, match=r"\(rows, cols, 3\)"):
        mosaic(np.zeros((4, 4)), "RGGB")
    with pytest.raises(DataError, match="unknown CFA layout"):
        channel_index("RGBG", (2, 2))
    assert check_layout("gbrg") == "GBRG"


@pytest.mark.parametrize(
    ("pixel_format", "layout"),
    [
        ("BayerRG12", "RGGB"),
        ("BayerBG8", "BGGR"),
        ("BayerGR16", "GRBG"),
        ("BayerGB12", "GBRG"),
        ("BayerGB12p", "GBRG"),
    ],
)
def test_layout_from_pixel_format(pixel_format: str, layout: str) -> None:
    assert layout_from_pixel_format(pixel_format) == layout


@pytest.mark.parametrize("pixel_format", ["Mono8", "RGB8", "YUV422_8", ""])
def test_layout_from_pixel_format_rejects_non_bayer(pixel_format: str) -> None:
    with pytest.raises(DataError, match="not a Bayer format"):
        layout_from_pixel_format(pixel_format)


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
@pytest.mark.parametrize("bits", [8, 12, 16])
def test_pixel_format_round_trip(layout: str, bits: int) -> None:
    name = pixel_format_for(layout, bits)
    assert name.endswith(str(bits)) and name.startswith("Bayer")
    assert layout_from_pixel_format(name) == layout


def test_pixel_format_for_rejects_bits() -> None:
    with pytest.raises(DataError, match="8, 12 or 16"):
        pixel_format_for("RGGB", 10)


# -- end to end through the simulator ---------------------------------------------------------


@pytest.fixture(scope="module")
def chart_rgb(small_sim_rig: SimulatedRig) -> np.ndarray:
    rgb = small_sim_rig.render_rgb("colorchecker", ["unfiltered"])["unfiltered"]
    assert rgb.shape == (*small_sim_rig.shape, 3)
    return rgb


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
def test_simulated_chart_mosaic_matches_channel_index(chart_rgb: np.ndarray, layout: str) -> None:
    rows, cols, _ = chart_rgb.shape
    raw = mosaic(chart_rgb, layout)
    index = channel_index(layout, (rows, cols))
    yy, xx = np.mgrid[0:rows, 0:cols]
    np.testing.assert_array_equal(raw, chart_rgb[yy, xx, index])
    # the channels of a chart differ, so a wrong layout would be caught
    for other in CFA_LAYOUTS:
        if other != layout:
            assert not np.array_equal(raw, mosaic(chart_rgb, other))


def test_simulated_rig_irradiance_is_gbrg(
    small_sim_rig: SimulatedRig, chart_rgb: np.ndarray
) -> None:
    assert small_sim_rig.rig.cfa == "GBRG"
    irradiance = small_sim_rig.irradiance("colorchecker", "unfiltered")
    np.testing.assert_array_equal(irradiance[0::2, 0::2], chart_rgb[0::2, 0::2, 1])  # G
    np.testing.assert_array_equal(irradiance[0::2, 1::2], chart_rgb[0::2, 1::2, 2])  # B
    np.testing.assert_array_equal(irradiance[1::2, 0::2], chart_rgb[1::2, 0::2, 0])  # R
    np.testing.assert_array_equal(irradiance[1::2, 1::2], chart_rgb[1::2, 1::2, 1])  # G
    np.testing.assert_array_equal(small_sim_rig.sensor.channels, channel_index("GBRG", (128, 160)))
