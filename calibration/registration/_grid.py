"""The patch grid of patch-wise registration: overlapping square patches at a fixed step,
the grid centred in the image."""

from __future__ import annotations

import numpy as np


def patch_grid(shape: tuple[int, int], patch_px: int, step_px: int) -> tuple[np.ndarray, ...]:
    """Top-left corners (rows, cols) of the patch grid, centred in the image."""

    def axis(size: int) -> np.ndarray:
        count = (size - patch_px) // step_px + 1
        first = (size - patch_px - (count - 1) * step_px) // 2
        return first + step_px * np.arange(count)

    rows, cols = np.meshgrid(axis(shape[0]), axis(shape[1]), indexing="ij")
    return rows.ravel(), cols.ravel()
