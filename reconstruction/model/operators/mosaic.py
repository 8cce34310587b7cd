"""Mosaicing operator M of problem (3.1) (thesis §3.4).

M samples a (rows, cols, 3) colour image (R, G, B) into a (rows, cols) raw Bayer mosaic:
each pixel keeps the one channel its colour filter passes. As a matrix it is the sparse
selection matrix "with elements equal to one where the corresponding pixel measures the
corresponding colour channel"; its adjoint scatters each raw value back into its channel
and leaves the other two channels zero.
"""

from __future__ import annotations

import numpy as np

from labkit.cfa import channel_index, channel_masks, check_layout
from labkit.errors import DataError
from reconstruction.model.operators._base import LinearOperator


class Mosaic(LinearOperator):
    """Bayer mosaicing M: (rows, cols, 3) colour → (rows, cols) raw.

    Parameters
    ----------
    shape : tuple of int
        Image size (rows, cols), pixels. Odd sizes are allowed: the 2×2 pattern is
        tiled from the top-left pixel and cropped.
    cfa : str
        Bayer layout, one of ``RGGB``, ``GRBG``, ``GBRG``, ``BGGR`` (top-left 2×2 block
        read row by row; see :mod:`labkit.cfa`).

    Notes
    -----
    Values are unitless (whatever the colour image carries). The output keeps the input's
    floating dtype. ``M Mᵀ = I`` (each raw pixel reads exactly one channel).
    """

    name = "M"

    def __init__(self, shape: tuple[int, int], cfa: str) -> None:
        size = tuple(int(n) for n in shape)
        if len(size) != 2 or min(size) < 1:
            raise DataError(
                f"Mosaic needs an image size (rows, cols) of positive integers, got {size}"
            )
        shape = (size[0], size[1])
        self.cfa = check_layout(cfa)
        super().__init__((*shape, 3), shape)
        self.index = channel_index(self.cfa, shape).astype(np.intp)
        self.masks = channel_masks(self.cfa, shape)

    def _forward(self, x: np.ndarray) -> np.ndarray:
        return np.take_along_axis(x, self.index[..., None], axis=2)[..., 0]

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return np.where(self.masks, y[..., None], np.zeros((), dtype=y.dtype))
