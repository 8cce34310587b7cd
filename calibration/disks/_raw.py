"""The raw mosaic the disk steps work on: the checked input array and its pixel noise per
colour channel."""

from __future__ import annotations

import numpy as np

from labkit.errors import DataError


def checked_raw(raw: np.ndarray, name: str) -> np.ndarray:
    """`raw` as a finite 2-D float array, or DataError naming the image."""
    array = np.asarray(raw)
    if array.ndim != 2 or min(array.shape) < 8:
        raise DataError(
            f"{name}: a raw mosaic must be a 2-D array of at least 8×8 pixels, "
            f"got shape {array.shape}"
        )
    if array.dtype.kind not in "fiu":
        raise DataError(f"{name}: raw pixels must be numbers, got dtype {array.dtype}")
    if array.dtype.kind != "f":
        array = array.astype(np.float32)
    bad = np.size(array) - int(np.count_nonzero(np.isfinite(array)))
    if bad:
        raise DataError(
            f"{name}: {bad} raw pixels are NaN or Inf; replace or mask them (e.g. re-merge "
            "the HDR image) before locating disks"
        )
    return array


def channel_noise(raw: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Robust pixel-noise sigma of each colour channel, (3,), raw units.

    From differences of horizontally adjacent pixels of the same channel (2 px apart):
    1.4826 × median |difference| / √2, on at most about 200 000 differences per channel.
    """
    diffs: list[list[np.ndarray]] = [[], [], []]
    for i in range(2):
        for j in range(2):
            plane = raw[i::2, j::2]
            if plane.shape[1] < 2:
                continue
            step = max(1, int(plane.size // 100_000))
            diffs[int(index[i, j])].append(np.diff(plane[::step], axis=1).ravel())
    sigma = np.zeros(3)
    for channel, parts in enumerate(diffs):
        if parts:
            d = np.abs(np.concatenate(parts))
            sigma[channel] = 1.4826 * float(np.median(d)) / np.sqrt(2.0)
    return sigma
