"""Errors of an estimated spectral image (thesis §4.4.1, (4.3)–(4.7))."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from reconstruction.evaluate.metrics._inputs import (
    BLOCK_PIXELS,
    RELATIVE_FLOOR,
    _all_excluded,
    _as_map,
    _check_floor,
    _data_range,
    _gof,
    _mask,
    _pair,
    _rescaled,
    _ssim,
)
from reconstruction.evaluate.metrics.registration import requested_scale


@dataclass(frozen=True, eq=False)
class SpectralErrors:
    """Errors of an estimated spectral image (:func:`spectral_errors`).

    Attributes
    ----------
    mrae : float
        Mean relative absolute error (4.3) over the values above the floor (unitless).
    rmse_pixel : float
        Mean over pixels of the per-pixel spectral RMSE (4.4), image units.
    rmse_global : float
        RMSE over all values (4.5), image units.
    gof : float
        Mean goodness of fit (4.6) over the pixels above the floor, in [0, 1].
    ssim : float or None
        Mean SSIM over bands (4.7); None when not computed (``ssim=False``).
    ssim_bands : tuple of float or None
        SSIM of each band.
    n_pixels, n_bands : int
        Pixels evaluated (inside the mask) and bands.
    floor : float
        Threshold on abs(true value) (MRAE) and true spectral RMS (GOF), image units.
    mrae_excluded : int
        Values left out of the MRAE (abs(I) ≤ floor).
    gof_excluded : int
        Pixels left out of the GOF (spectral RMS of I ≤ floor).
    scale : tuple of float or None
        Registration factors (4.9)/(4.14) applied to the estimate, or None.
    mrae_map, rmse_map, gof_map : numpy.ma.MaskedArray (rows, cols)
        Per-pixel MRAE (mean over the bands above the floor), RMSE and GOF; masked
        outside the evaluated pixels and where a pixel was excluded.
    """

    mrae: float
    rmse_pixel: float
    rmse_global: float
    gof: float
    ssim: float | None
    ssim_bands: tuple[float, ...] | None
    n_pixels: int
    n_bands: int
    floor: float
    mrae_excluded: int
    gof_excluded: int
    scale: tuple[float, ...] | None
    mrae_map: np.ma.MaskedArray = field(repr=False)
    rmse_map: np.ma.MaskedArray = field(repr=False)
    gof_map: np.ma.MaskedArray = field(repr=False)

    def as_dict(self) -> dict[str, Any]:
        """The scalar results as plain JSON types (the per-pixel maps are left out)."""
        return {
            "mrae": self.mrae,
            "rmse_pixel": self.rmse_pixel,
            "rmse_global": self.rmse_global,
            "gof": self.gof,
            "ssim": self.ssim,
            "ssim_bands": None if self.ssim_bands is None else list(self.ssim_bands),
            "n_pixels": self.n_pixels,
            "n_bands": self.n_bands,
            "floor": self.floor,
            "mrae_excluded": self.mrae_excluded,
            "gof_excluded": self.gof_excluded,
            "scale": None if self.scale is None else list(self.scale),
        }


@fixed_blas_threads
def spectral_errors(
    truth: np.ndarray,
    estimate: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    floor: float | None = None,
    ssim: bool = True,
    data_range: float | None = None,
    register: bool = False,
    weights: np.ndarray | None = None,
) -> SpectralErrors:
    """MRAE, RMSE, GOF and SSIM of an estimated spectral image (4.3)–(4.7).

    Parameters
    ----------
    truth, estimate : ndarray (rows, cols, bands)
        True and estimated spectral images, same units (e.g. radiance).
    mask : ndarray (rows, cols) of bool, optional
        Pixels to evaluate (default: all).
    floor : float, optional
        Values with abs(I) ≤ floor are left out of the MRAE, pixels whose true spectral
        RMS is ≤ floor out of the GOF; image units. Default :data:`RELATIVE_FLOOR` ×
        the largest abs(I) in the mask.
    ssim : bool
        Compute SSIM (needs images of at least 11 × 11 px; the SSIM map is averaged
        over the mask when one is given).
    data_range : float, optional
        SSIM's dynamic range L, image units; default the true image's peak-to-peak
        range over all bands.
    register : bool
        Multiply the estimate by :func:`registration_scale` first.
    weights : ndarray (rows, cols), optional
        Registration weights (4.13) (only with ``register=True``); default the mask.

    Returns
    -------
    SpectralErrors

    Raises
    ------
    DataError
        Shapes that differ or are not 3-D, NaN/Inf, an empty mask, a floor that
        excludes every value, or an image too small or too flat for SSIM.
    """
    truth, estimate = _pair(truth, estimate, "spectral_errors", min_ndim=3, max_ndim=3)
    truth, estimate, unit = _rescaled(truth, estimate)
    floor = None if floor is None else _check_floor(floor) / unit
    data_range = None if data_range is None else float(data_range) / unit
    rows, cols, bands = truth.shape
    region = _mask(mask, (rows, cols), "spectral_errors")
    scale = requested_scale(truth, estimate, region, register, weights)
    index = np.flatnonzero(region)
    pixels = index.size
    t_all = truth.reshape(-1, bands)
    e_all = estimate.reshape(-1, bands)
    blocks = [slice(start, start + BLOCK_PIXELS) for start in range(0, pixels, BLOCK_PIXELS)]
    if floor is None:
        peak = max(float(np.abs(t_all[index[block]]).max()) for block in blocks)
        thr = RELATIVE_FLOOR * peak
    else:
        thr = _check_floor(floor)

    rmse_px = np.empty(pixels)
    mrae_px = np.empty(pixels)
    mrae_ok = np.empty(pixels, dtype=bool)
    gof_px = np.empty(pixels)
    gof_ok = np.empty(pixels, dtype=bool)
    squares = relative_sum = 0.0
    valid_count = 0
    for block in blocks:
        t = t_all[index[block]].astype(np.float64)
        e = e_all[index[block]].astype(np.float64)
        if scale is not None:
            e *= scale
        diff = t - e
        sq = diff * diff
        rmse_px[block] = np.sqrt(sq.mean(axis=1))
        squares += float(sq.sum())
        valid = np.abs(t) > thr
        relative = np.divide(np.abs(diff), np.abs(t), out=np.zeros_like(diff), where=valid)
        counts = valid.sum(axis=1)
        relative_sum += float(relative.sum())
        valid_count += int(counts.sum())
        mrae_px[block] = np.divide(
            relative.sum(axis=1), counts, out=np.zeros(counts.size), where=counts > 0
        )
        mrae_ok[block] = counts > 0
        gof_px[block], gof_ok[block] = _gof(t, e, thr)
    if valid_count == 0:
        raise _all_excluded("MRAE", thr * unit)
    if not gof_ok.any():
        raise _all_excluded("GOF", thr * unit)

    ssim_bands = None
    if ssim:
        L = _data_range(truth, data_range)
        partial = region if mask is not None else None
        gains = np.ones(bands) if scale is None else scale
        ssim_bands = tuple(
            _ssim(truth[..., b], estimate[..., b] * gains[b], partial, L) for b in range(bands)
        )

    return SpectralErrors(
        mrae=relative_sum / valid_count,
        rmse_pixel=float(rmse_px.mean()) * unit,
        rmse_global=float(np.sqrt(squares / (pixels * bands))) * unit,
        gof=float(gof_px[gof_ok].mean()),
        ssim=None if ssim_bands is None else float(np.mean(ssim_bands)),
        ssim_bands=ssim_bands,
        n_pixels=pixels,
        n_bands=bands,
        floor=thr * unit,
        mrae_excluded=pixels * bands - valid_count,
        gof_excluded=int(pixels - gof_ok.sum()),
        scale=None if scale is None else tuple(float(s) for s in scale),
        mrae_map=_as_map(mrae_px, region, mrae_ok),
        rmse_map=_as_map(rmse_px * unit, region, np.ones(pixels, dtype=bool)),
        gof_map=_as_map(gof_px, region, gof_ok),
    )
