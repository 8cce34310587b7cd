"""Rejecting keypoint displacements that disagree with their neighbours (outliers)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Neighbours whose median displacement a keypoint is compared with.
_OUTLIER_NEIGHBOURS = 8
#: Outlier threshold: max(_OUTLIER_FLOOR_PX, _OUTLIER_SIGMAS × robust sigma).
_OUTLIER_FLOOR_PX = 0.3
_OUTLIER_SIGMAS = 5.0


def _smooth_trend(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """A robust quadratic fit of displacements `d` (n, 2) over positions `xy` (n, 2).

    Iteratively reweighted least squares with Tukey's biweight (scale from the median
    misfit, at least 0.05 px), in normalised coordinates. Returns the fitted values
    (n, 2); zero when there are too few points for a quadratic.
    """
    n = len(xy)
    if n < 12:
        return np.zeros_like(d)
    u = (xy - xy.mean(axis=0)) / np.maximum(xy.std(axis=0), 1e-9)
    design = np.column_stack(
        [np.ones(n), u[:, 0], u[:, 1], u[:, 0] ** 2, u[:, 0] * u[:, 1], u[:, 1] ** 2]
    )
    weight = np.ones(n)
    for _ in range(10):
        root = np.sqrt(weight)[:, None]
        coef, *_ = np.linalg.lstsq(design * root, d * root, rcond=None)
        misfit = np.hypot(*(d - design @ coef).T)
        # the median of |e| for a 2-D Gaussian with sigma per component is 1.177 sigma
        sigma = max(float(np.median(misfit)) / 1.177, 0.05)
        ratio = misfit / (4.685 * sigma)
        new = np.where(ratio < 1.0, (1.0 - ratio**2) ** 2, 0.0)
        if np.count_nonzero(new) < 12 or np.allclose(new, weight, atol=1e-3):
            break
        weight = new
    return design @ coef


def displacement_outliers(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Boolean (n,): displacements far from the median of their nearest neighbours.

    A displacement is an outlier when it differs from the median displacement of its
    (up to) 8 nearest neighbours by more than max(0.3 px, 5 robust sigma), sigma from the
    median absolute deviation of those differences over all keypoints. The comparison is
    made after removing a robust quadratic trend of the field: otherwise, where the field
    is steep, keypoints at the edge of the pattern (whose neighbours all lie on one side)
    would differ from their neighbours' median by the field's gradient alone.
    """
    n = len(xy)
    if n < 3:
        return np.zeros(n, dtype=bool)
    residual = d - _smooth_trend(xy, d)
    k = min(_OUTLIER_NEIGHBOURS, n - 1)
    _, neighbours = cKDTree(xy).query(xy, k=k + 1)
    neighbours = neighbours[:, 1:]  # drop the point itself
    deviation = residual - np.median(residual[neighbours], axis=1)
    centred = deviation - np.median(deviation, axis=0)
    sigma = 1.4826 * float(np.median(np.abs(centred)))
    limit = max(_OUTLIER_FLOOR_PX, _OUTLIER_SIGMAS * sigma)
    return np.hypot(deviation[:, 0], deviation[:, 1]) > limit
