"""Pairing disk centres between images (mutual nearest neighbours)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from labkit.errors import DataError


def pair_mutual_nearest(
    reference_xy: np.ndarray, band_xy: np.ndarray, *, max_distance_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pair points that are each other's nearest neighbour and closer than a limit.

    Parameters
    ----------
    reference_xy : ndarray (n, 2)
        Points (x, y) in the reference image, px.
    band_xy : ndarray (m, 2)
        Points (x, y) in the other image, px.
    max_distance_px : float
        Pairs farther apart than this are dropped, px.

    Returns
    -------
    reference_index, band_index : ndarray (k,) int64
        Indices of the pairs into `reference_xy` and `band_xy`, sorted by reference index.
    """
    ref = np.asarray(reference_xy, dtype=np.float64)
    band = np.asarray(band_xy, dtype=np.float64)
    for what, points in (("reference_xy", ref), ("band_xy", band)):
        if points.ndim != 2 or points.shape[1] != 2:
            raise DataError(f"{what} must be an (n, 2) array of x, y; got shape {points.shape}")
        if not np.all(np.isfinite(points)):
            raise DataError(f"{what} holds NaN or Inf positions")
    empty = np.zeros(0, dtype=np.int64)
    if len(ref) == 0 or len(band) == 0:
        return empty, empty
    dist, to_band = cKDTree(band).query(ref)
    _, to_ref = cKDTree(ref).query(band)
    ref_index = np.arange(len(ref))
    mutual = (to_ref[to_band] == ref_index) & (dist <= max_distance_px)
    return ref_index[mutual].astype(np.int64), np.asarray(to_band[mutual], dtype=np.int64)
