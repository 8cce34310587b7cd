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
    """1 − (2p − 1)¹² by repeated squaring (cheaper than a float power), float32."""
    q = np.asarray(p, dtype=np.float32) * np.float32(2.0)
    q -= 1.0
    q *= q  # ²
    q6 = q * q
    q6 *= q  # ⁶
    q6 *= q6  # ¹²
    np.subtract(np.float32(1.0), q6, out=q6)
    return q6


def _unit(p: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(p, dtype=np.float32), 0.0, 1.0)


def bloom_weight(p: np.ndarray) -> np.ndarray:
    """Equation (4.1): 1 − (2p − 1)¹² above p = 0.5, else 1."""
    p = _unit(p)
    weight = _hump(p)
    weight[p <= 0.5] = 1.0
    return weight


def local_weight(p: np.ndarray) -> np.ndarray:
    """Equation (4.2): p (1 − (2p − 1)¹²)."""
    p = _unit(p)
    weight = _hump(p)
    weight *= p
    return weight


def blend_weight(p: np.ndarray, *, erode: bool = True) -> np.ndarray:
    """Algorithm 11 lines 3–9: min(eroded bloom weight, local weight), float32.

    `erode=False` skips the greyscale erosion (only to show what blooming does).
    """
    p = _unit(p)
    hump = _hump(p)
    bloom = np.where(p > 0.5, hump, np.float32(1.0))
    if erode:
        bloom = ndimage.grey_erosion(bloom, footprint=DISK_1, mode="nearest")
    hump *= p  # the local weight
    np.minimum(bloom, hump, out=hump)
    return hump
