"""Registration of an estimate onto the truth, (4.8)–(4.9), (4.13)–(4.14): per-band
least-squares scale factors and the patch weights of (4.13).
"""

from __future__ import annotations

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from reconstruction.evaluate.metrics._inputs import BLOCK_PIXELS, _pair, _unit, _weights


@fixed_blas_threads
def registration_scale(
    truth: np.ndarray, estimate: np.ndarray, *, weights: np.ndarray | None = None
) -> np.ndarray:
    """Per-band factors S that best map the estimate onto the truth, (4.9) / (4.14).

    ``S_b = Σ_x w_x I_{x,b} Î_{x,b} / Σ_x w_x Î_{x,b}²`` minimises
    ``Σ_x Σ_b w_x (I_{x,b} − S_b Î_{x,b})²``.

    Parameters
    ----------
    truth, estimate : ndarray (..., bands)
        Reference and estimated data: images (rows, cols, bands) or point measurements
        (n, bands), any units (the same for both).
    weights : ndarray (...), optional
        Non-negative weight of every pixel or measurement (4.13), e.g. from
        :func:`patch_weights`; default 1 everywhere (4.8). Zero-weight pixels are ignored.

    Returns
    -------
    ndarray (bands,), float64
        Unitless factors; ``S * estimate`` is the registered estimate.

    Raises
    ------
    DataError
        Shapes that differ, NaN/Inf, negative or all-zero weights, or a band whose
        estimate is zero wherever the weight is positive.
    """
    truth, estimate = _pair(truth, estimate, "registration_scale", min_ndim=1)
    unit = _unit(truth, estimate)  # S is unchanged by a common scale
    if unit != 1.0:
        truth, estimate = truth / unit, estimate / unit
    w = _weights(weights, truth.shape[:-1]).reshape(-1)
    bands = truth.shape[-1]
    t_all = truth.reshape(-1, bands)
    e_all = estimate.reshape(-1, bands)
    numerator = np.zeros(bands)
    denominator = np.zeros(bands)
    for start in range(0, w.size, BLOCK_PIXELS):
        block = slice(start, start + BLOCK_PIXELS)
        t = t_all[block].astype(np.float64)
        e = e_all[block].astype(np.float64)
        numerator += w[block] @ (t * e)
        denominator += w[block] @ (e * e)
    empty = np.flatnonzero(~(denominator > 0))
    if empty.size:
        raise DataError(
            f"the estimate is zero in band(s) {empty.tolist()} wherever the registration "
            "weight is positive, so no scale factor maps it onto the truth; check the "
            "estimate or give those pixels weight"
        )
    return numerator / denominator


def patch_weights(labels: np.ndarray) -> np.ndarray:
    """Weights of (4.13): 1 / (pixels of the patch) inside each patch, 0 on the background.

    Parameters
    ----------
    labels : ndarray (rows, cols) of int
        0 = background, k > 0 = patch k.

    Returns
    -------
    ndarray (rows, cols), float64
        Each patch's weights sum to 1, so every patch counts equally.
    """
    labels = np.asarray(labels)
    if labels.ndim != 2 or not np.issubdtype(labels.dtype, np.integer):
        raise DataError(
            f"patch labels must be a 2-D integer image, got {labels.dtype} of shape {labels.shape}"
        )
    if labels.size and labels.min() < 0:
        raise DataError("patch labels must be ≥ 0 (0 = background, k = patch k)")
    counts = np.bincount(labels.ravel()).astype(np.float64)
    inverse = np.divide(1.0, counts, out=np.zeros_like(counts), where=counts > 0)
    inverse[0] = 0.0
    return inverse[labels]


def requested_scale(
    truth: np.ndarray,
    estimate: np.ndarray,
    region: np.ndarray,
    register: bool,
    weights: np.ndarray | None,
) -> np.ndarray | None:
    """The metrics' registration factors where `register` asks for them, else None.

    The weights default to the evaluated pixels (`region`); weights without `register`
    are refused.
    """
    if not register:
        if weights is not None:
            raise DataError("registration weights were given but register=False")
        return None
    w = region.astype(np.float64) if weights is None else weights
    return registration_scale(truth, estimate, weights=w)
