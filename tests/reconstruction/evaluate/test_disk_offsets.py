"""Residual lateral chromatic aberration from disk-centre offsets: synthetic disk charts
with known, sub-pixel channel shifts rendered by moving the disks (no interpolation)."""

from __future__ import annotations

import numpy as np
import pytest

from labkit.errors import DataError
from reconstruction.evaluate.metrics import DiskOffsets, disk_channel_offsets

SHAPE = (200, 240)
RADIUS_PX = 9.0
SUPERSAMPLE = 4
#: A 3 × 5 grid of disk centres (x, y), px: the first column is cut by the left border,
#: the other 12 disks lie whole inside the image, at least 10 px from its border.
GRID = np.array([(x, y) for y in (35.2, 100.4, 164.8) for x in (-2.0, 40.3, 100.7, 160.1, 219.6)])
WHOLE = int(
    np.sum(np.all((GRID >= RADIUS_PX) & (GRID <= np.array(SHAPE[::-1]) - 1 - RADIUS_PX), 1))
)
SHIFT_R = (0.6, -0.3)
SHIFT_B = (-0.4, 0.2)
#: (disk, paper) lightness per channel R, G, B: the same pattern at different exposures.
LEVELS = ((0.15, 0.9), (0.1, 1.0), (0.2, 0.7))


def _render(centres: np.ndarray, disk: float, paper: float) -> np.ndarray:
    """Disks of RADIUS_PX at `centres` (x, y), each pixel the mean of 4 × 4 samples."""
    rows, cols = SHAPE
    offset = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    ys = (np.arange(rows)[:, None] + offset).ravel()
    xs = (np.arange(cols)[:, None] + offset).ravel()
    dark = np.zeros((ys.size, xs.size), dtype=bool)
    for cx, cy in centres:
        dark |= (xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2 <= RADIUS_PX**2
    fine = np.where(dark, disk, paper)
    return fine.reshape(rows, SUPERSAMPLE, cols, SUPERSAMPLE).mean(axis=(1, 3))


def _chart(shift_r: tuple[float, float], shift_b: tuple[float, float]) -> np.ndarray:
    shifts = (shift_r, (0.0, 0.0), shift_b)
    return np.stack(
        [_render(GRID + s, *levels) for s, levels in zip(shifts, LEVELS, strict=True)], axis=2
    )


@pytest.fixture(scope="module")
def shifted() -> np.ndarray:
    return _chart(SHIFT_R, SHIFT_B)


@pytest.fixture(scope="module")
def result(shifted: np.ndarray) -> DiskOffsets:
    return disk_channel_offsets(shifted, workers=1)


def test_planted_channel_shifts_are_recovered(result: DiskOffsets) -> None:
    assert WHOLE == 12
    assert result.count == WHOLE
    assert result.rg_px == pytest.approx(np.hypot(*SHIFT_R), abs=0.03)
    assert result.bg_px == pytest.approx(np.hypot(*SHIFT_B), abs=0.03)
    assert result.offsets.shape == (WHOLE, 2, 2)
    np.testing.assert_allclose(
        result.offsets[:, 0], np.broadcast_to(SHIFT_R, (WHOLE, 2)), atol=0.03
    )
    np.testing.assert_allclose(
        result.offsets[:, 1], np.broadcast_to(SHIFT_B, (WHOLE, 2)), atol=0.03
    )


def test_green_centres_are_the_whole_disks(result: DiskOffsets) -> None:
    whole = GRID[GRID[:, 0] > 0]
    assert result.centres_g.shape == (WHOLE, 2)
    order = np.lexsort((result.centres_g[:, 0], np.rint(result.centres_g[:, 1])))
    np.testing.assert_allclose(result.centres_g[order], whole, atol=0.03)


def test_unshifted_channels_give_no_offset() -> None:
    found = disk_channel_offsets(_chart((0.0, 0.0), (0.0, 0.0)), workers=1)
    assert found.count == WHOLE
    assert found.rg_px < 0.02
    assert found.bg_px < 0.02


def test_float32_and_float64_agree(shifted: np.ndarray, result: DiskOffsets) -> None:
    single = disk_channel_offsets(shifted.astype(np.float32), workers=1)
    assert single.count == result.count
    assert single.rg_px == pytest.approx(result.rg_px, abs=0.01)
    assert single.bg_px == pytest.approx(result.bg_px, abs=0.01)


def test_a_flat_image_has_no_disks() -> None:
    with pytest.raises(DataError, match="no calibration disks found in flat field"):
        disk_channel_offsets(np.ones((*SHAPE, 3)), name="flat field", workers=1)


def test_too_few_disks_are_refused(shifted: np.ndarray) -> None:
    with pytest.raises(DataError, match=r"only 12 disks .* need ≥ 20"):
        disk_channel_offsets(shifted, min_disks=20, workers=1)


@pytest.mark.parametrize("shape", [SHAPE, (*SHAPE, 4), (*SHAPE, 3, 1)])
def test_a_wrong_shape_is_refused(shape: tuple[int, ...]) -> None:
    with pytest.raises(DataError, match=r"\(rows, cols, 3\) colour image"):
        disk_channel_offsets(np.ones(shape), workers=1)


def test_nan_is_refused(shifted: np.ndarray) -> None:
    bad = shifted.copy()
    bad[5, 7, 2] = np.nan
    with pytest.raises(DataError, match="chart: 1 values are NaN or Inf"):
        disk_channel_offsets(bad, name="chart", workers=1)
