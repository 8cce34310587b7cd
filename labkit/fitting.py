"""Scale factors between two measurements of the same signal: first principal component.

Used for the HDR exposure scaling factors (thesis §4.2.3, after Darrodi et al.) and the
relative channel sensitivities (Algorithm 12): pairs ``(x_i, y_i)`` lie on a line
``y = s x`` through the origin, both coordinates noisy. The slope is the direction of the
first principal component of the (uncentred) point cloud, i.e. total least squares
through the origin. Both axes are divided by one common power of two first (the geometry,
and so the principal direction, is unchanged; no overflow or underflow whatever the
units), and the second moments are summed in float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError


@dataclass(frozen=True)
class SlopeFit:
    """Result of :func:`principal_slope`.

    Attributes
    ----------
    slope : float
        ``y ≈ slope · x``.
    count : int
        Number of point pairs used.
    residual_rms : float
        RMS orthogonal distance of the points from the line, relative to the RMS distance
        of the points from the origin (0 for perfectly proportional data).
    explained : float
        Fraction of the second moment along the line (1 = perfect).
    """

    slope: float
    count: int
    residual_rms: float
    explained: float


@fixed_blas_threads
def principal_slope(x: np.ndarray, y: np.ndarray, *, min_count: int = 2) -> SlopeFit:
    """Slope of the line through the origin along the first principal component of (x, y).

    Parameters
    ----------
    x, y : ndarray
        Paired measurements (same shape, any units); NaN/Inf pairs are not allowed.
    min_count : int
        Fewest pairs accepted.

    Raises
    ------
    DataError
        Too few pairs, non-finite values, or no signal on one axis.
    """
    x = np.asarray(x).ravel()
    y = np.asarray(y).ravel()
    if x.shape != y.shape:
        raise DataError(f"principal_slope: x has {x.size} values but y has {y.size}")
    if x.size < max(min_count, 2):
        raise DataError(f"principal_slope: {x.size} pairs, need at least {max(min_count, 2)}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise DataError("principal_slope: pairs contain NaN or Inf")
    sxx, sxy, syy = _moments(x, y)
    if sxx == 0 or syy == 0:
        raise DataError("principal_slope: one of the two measurements is all zero")
    scale = (sxx + syy) / (2.0 * x.size)  # a common scale² for both axes
    moments = np.array([[sxx, sxy], [sxy, syy]]) / (x.size * scale)
    values, vectors = np.linalg.eigh(moments)
    direction = vectors[:, 1]
    if direction[0] == 0:
        raise DataError("principal_slope: the fitted line is vertical (x carries no signal)")
    slope = float(direction[1] / direction[0])
    total = float(values.sum())
    return SlopeFit(
        slope=slope,
        count=int(x.size),
        residual_rms=float(np.sqrt(max(values[0], 0.0))),
        explained=float(values[1] / total) if total > 0 else 0.0,
    )


_CHUNK = 1 << 18


def _moments(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """(Σx², Σxy, Σy²) / u² in float64, a chunk at a time (no full-size float64 copies).

    u is a power of two near the largest |value| of x and y, so the squares neither
    overflow nor underflow whatever the units (the slope does not depend on u).
    """
    peak = max(float(x.max()), -float(x.min()), float(y.max()), -float(y.min()))
    inverse_unit = float(np.ldexp(1.0, -int(np.frexp(peak)[1]))) if peak > 0 else 1.0
    sxx = sxy = syy = 0.0
    for start in range(0, x.size, _CHUNK):
        a = x[start : start + _CHUNK].astype(np.float64) * inverse_unit
        b = y[start : start + _CHUNK].astype(np.float64) * inverse_unit
        sxx += float(a @ a)
        sxy += float(a @ b)
        syy += float(b @ b)
    return sxx, sxy, syy
