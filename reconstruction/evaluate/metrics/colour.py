"""Errors of an estimated raw colour image (thesis §4.4.2, (4.10)–(4.12))."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import CHANNELS
from labkit.errors import DataError
from reconstruction.evaluate.metrics._inputs import (
    RELATIVE_FLOOR,
    _all_excluded,
    _channel_mask,
    _check_floor,
    _data_range,
    _pair,
    _rescaled,
    _ssim,
)
from reconstruction.evaluate.metrics.registration import requested_scale


@dataclass(frozen=True)
class ColourErrors:
    """Per-channel errors of an estimated colour image (:func:`colour_errors`).

    Every tuple holds one entry per channel, in the order R, G, B.

    Attributes
    ----------
    mrae : tuple of float
        MRAE_c (4.10) over the values above the floor (unitless).
    rmse : tuple of float
        RMSE_c (4.11), image units.
    ssim : tuple of float or None
        SSIM_c (4.12); None when not computed.
    n_pixels : tuple of int
        Pixels evaluated per channel.
    floor : float
        Threshold on abs(true value) for the MRAE, image units.
    mrae_excluded : tuple of int
        Values left out of each channel's MRAE (abs(I) ≤ floor).
    scale : tuple of float or None
        Registration factors applied to the estimate, or None.
    """

    mrae: tuple[float, float, float]
    rmse: tuple[float, float, float]
    ssim: tuple[float, float, float] | None
    n_pixels: tuple[int, int, int]
    floor: float
    mrae_excluded: tuple[int, int, int]
    scale: tuple[float, float, float] | None

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON types, per-channel values keyed by ``"R"``, ``"G"``, ``"B"``."""

        def per_channel(values: tuple | None) -> dict[str, Any] | None:
            return None if values is None else dict(zip(CHANNELS, values, strict=True))

        return {
            "mrae": per_channel(self.mrae),
            "rmse": per_channel(self.rmse),
            "ssim": per_channel(self.ssim),
            "n_pixels": per_channel(self.n_pixels),
            "floor": self.floor,
            "mrae_excluded": per_channel(self.mrae_excluded),
            "scale": per_channel(self.scale),
        }


@fixed_blas_threads
def colour_errors(
    truth: np.ndarray,
    estimate: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    floor: float | None = None,
    ssim: bool = True,
    data_range: float | None = None,
    register: bool = False,
    weights: np.ndarray | None = None,
) -> ColourErrors:
    """MRAE, RMSE and SSIM of every channel of an estimated colour image (4.10)–(4.12).

    Parameters
    ----------
    truth, estimate : ndarray (rows, cols, 3)
        True and estimated images in one colour space (R, G, B; e.g. the camera's raw
        colour space), same units.
    mask : ndarray (rows, cols) or (rows, cols, 3) of bool, optional
        Pixels to evaluate, for all channels or per channel (e.g. the sites of a
        colour-filter array); default all.
    floor : float, optional
        Values with abs(I) ≤ floor are left out of the MRAE, image units; default
        :data:`RELATIVE_FLOOR` × the largest abs(I) in the mask.
    ssim : bool
        Compute SSIM (needs images of at least 11 × 11 px; the SSIM map is averaged
        over each channel's mask when one is given).
    data_range : float, optional
        SSIM's dynamic range L, image units; default the true image's peak-to-peak
        range over all channels.
    register : bool
        Multiply each channel of the estimate by :func:`registration_scale` first.
    weights : ndarray (rows, cols), optional
        Registration weights (only with ``register=True``); default the mask.

    Returns
    -------
    ColourErrors

    Raises
    ------
    DataError
        Shapes that differ or are not (rows, cols, 3), NaN/Inf, an empty mask, a floor
        that excludes a whole channel, or an image too small or too flat for SSIM.
    """
    truth, estimate = _pair(truth, estimate, "colour_errors", min_ndim=3, max_ndim=3)
    if truth.shape[2] != 3:
        raise DataError(
            f"colour_errors needs (rows, cols, 3) images (R, G, B), got {truth.shape}; "
            "use spectral_errors for spectral images"
        )
    truth, estimate, unit = _rescaled(truth, estimate)
    floor = None if floor is None else _check_floor(floor) / unit
    data_range = None if data_range is None else float(data_range) / unit
    region = _channel_mask(mask, truth.shape)
    scale = requested_scale(truth, estimate, region.any(axis=2), register, weights)
    if scale is not None:
        estimate = estimate * scale
    if floor is None:
        thr = RELATIVE_FLOOR * float(np.abs(truth[region]).max())
    else:
        thr = _check_floor(floor)
    L = _data_range(truth, data_range) if ssim else 0.0
    mrae, rmse, counts, excluded, ssims = [], [], [], [], []
    for c, name in enumerate(CHANNELS):
        inside = region[..., c]
        t = truth[..., c][inside].astype(np.float64)
        e = estimate[..., c][inside].astype(np.float64)
        diff = t - e
        rmse.append(float(np.sqrt(np.mean(diff * diff))))
        valid = np.abs(t) > thr
        if not valid.any():
            raise _all_excluded(f"the {name} channel's MRAE", thr * unit)
        mrae.append(float(np.mean(np.abs(diff[valid]) / np.abs(t[valid]))))
        counts.append(int(inside.sum()))
        excluded.append(int(inside.sum() - valid.sum()))
        if ssim:
            partial = inside if mask is not None else None
            ssims.append(_ssim(truth[..., c], estimate[..., c], partial, L))
    return ColourErrors(
        mrae=tuple(mrae),
        rmse=tuple(r * unit for r in rmse),
        ssim=tuple(ssims) if ssim else None,
        n_pixels=tuple(counts),
        floor=thr * unit,
        mrae_excluded=tuple(excluded),
        scale=None if scale is None else tuple(float(s) for s in scale),
    )
