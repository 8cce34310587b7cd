"""The thesis' exposure-blending weights, equations (4.1) and (4.2) (after Reinhard et al.).

`p` is a pixel's value as a fraction of the saturation range *at its own exposure*
(clipped to [0, 1]). The blooming weight is eroded with a radius-1 disk so that pixels
next to saturated ones are distrusted even when they are not saturated themselves.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

#: Radius-1 disk structuring element (the pixel and its 4 neighbours).
DISK_1 = ndimage.generate_binary_structure(2, 1)


def _hump(p: np.ndarray) -> np.ndarray:
    """1 − (2p − 1)¹² by repeated squaring (cheaper than a float power)."""
    q = 2.0 * p - 1.0
    q *= q  # ²
    q6 = q * q * q
    q6 *= q6  # ¹²
    return 1.0 - q6


def bloom_weight(p: np.ndarray) -> np.ndarray:
    """Equation (4.1): 1 − (2p − 1)¹² above p = 0.5, else 1."""
    p = np.clip(np.asarray(p, dtype=np.float32), 0.0, 1.0)
    return np.where(p > 0.5, _hump(p), np.float32(1.0)).astype(np.float32)


def local_weight(p: np.ndarray) -> np.ndarray:
    """Equation (4.2): p (1 − (2p − 1)¹²)."""
    p = np.clip(np.asarray(p, dtype=np.float32), 0.0, 1.0)
    return (p * _hump(p)).astype(np.float32)


def blend_weight(p: np.ndarray, *, erode: bool = True) -> np.ndarray:
    """Algorithm 11 lines 3–9: min(eroded bloom weight, local weight), float32.

    `erode=False` skips the greyscale erosion (only to show what blooming does).
    """
    bloom = bloom_weight(p)
    if erode:
        bloom = ndimage.grey_erosion(bloom, footprint=DISK_1, mode="nearest")
    return np.minimum(bloom, local_weight(p))
