"""Algorithm 12: the R/G and B/G ratios of each band, measured from HDR images of it
(the method is described in :mod:`calibration.sensitivity`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration._hdr_inputs import source_of
from calibration.sensitivity.table import ChannelSensitivity
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import channel_index
from labkit.errors import DataError
from labkit.fitting import principal_slope
from labkit.io.exr import RawImage
from labkit.io.light import check_light

_RED, _GREEN, _BLUE = 0, 1, 2
_NAMES = {_RED: "red", _BLUE: "blue"}


@fixed_blas_threads
def channel_sensitivity(
    images: Sequence[RawImage],
    *,
    saturation: float = 0.95,
    gradient_quantile: float = 0.5,
    min_pairs: int = 200,
    min_signal_ratio: float = 0.01,
) -> ChannelSensitivity:
    """Calibrate R/G and B/G per filter band from HDR raw images (thesis Algorithm 12).

    Parameters
    ----------
    images : sequence of RawImage
        Filtered-light HDR mosaics (values: fraction of saturation, 1.0 = saturated;
        ``wavelength_nm`` set). Images of the same band (e.g. several scenes) are pooled;
        they may differ in shape, CFA layout and exposure.
    saturation : float
        Pixels at or above this value (fraction of saturation) are discarded.
    gradient_quantile : float
        Keep pixels whose gradient magnitude (per CFA colour plane, in value units per
        2 px) is at most this quantile of their plane's magnitudes (0.5: the median).
    min_pairs : int
        Fewest pixel pairs for a ratio to count as reliable.
    min_signal_ratio : float
        Signal test (see the module notes): a channel whose median kept value is below
        this fraction of Green's (or Green below this fraction of the brighter other
        channel) makes the band's ratio unreliable.

    Returns
    -------
    ChannelSensitivity
        One band per distinct ``wavelength_nm``, sorted by wavelength.

    Raises
    ------
    DataError
        No images, an image without ``wavelength_nm``, an image smaller than 4 × 4 px,
        or an option out of range.
    """
    if not images:
        raise DataError("channel_sensitivity needs at least one filtered HDR image")
    if not 0 < saturation <= 1 or not 0 < gradient_quantile <= 1:
        raise DataError(
            f"channel_sensitivity: need 0 < saturation ≤ 1 and 0 < gradient_quantile ≤ 1, "
            f"got {saturation} and {gradient_quantile}"
        )
    if min_pairs < 2 or not 0 < min_signal_ratio < 1:
        raise DataError(
            f"channel_sensitivity: need min_pairs ≥ 2 and 0 < min_signal_ratio < 1, "
            f"got {min_pairs} and {min_signal_ratio}"
        )
    bands: dict[float, list[RawImage]] = {}
    for image in images:
        if image.wavelength_nm is None:
            raise DataError(
                f"{source_of(image)}: illumination {image.illumination!r} is unfiltered "
                "(no wavelength_nm); channel sensitivity needs bandpass-filtered images"
            )
        if min(image.raw.shape) < 4:
            raise DataError(f"{source_of(image)}: image {image.raw.shape} is smaller than 4 × 4")
        check_light(image.raw, name=source_of(image))
        bands.setdefault(round(float(image.wavelength_nm), 1), []).append(image)

    results = [
        _calibrate_band(
            group,
            saturation=saturation,
            gradient_quantile=gradient_quantile,
            min_pairs=min_pairs,
            min_signal_ratio=min_signal_ratio,
        )
        for _, group in sorted(bands.items())
    ]
    _check_results(results, bands)
    scenes = sorted({str(image.labkit["scene"]) for image in images if "scene" in image.labkit})
    return ChannelSensitivity(
        wavelengths_nm=np.array(sorted(bands)),
        illuminations=tuple(r["illumination"] for r in results),
        r_over_g=[r["r"].ratio for r in results],
        b_over_g=[r["b"].ratio for r in results],
        pairs_r=[r["r"].pairs for r in results],
        pairs_b=[r["b"].pairs for r in results],
        residual_r=[r["r"].residual for r in results],
        residual_b=[r["b"].residual for r in results],
        reliable_r=[not r["r"].reasons for r in results],
        reliable_b=[not r["b"].reasons for r in results],
        reason_r=tuple("; ".join(r["r"].reasons) for r in results),
        reason_b=tuple("; ".join(r["b"].reasons) for r in results),
        green_level=[r["green_level"] for r in results],
        source="measured",
        labkit={
            "method": "first principal component of neighbour pairs (the thesis' ratios)",
            "saturation": saturation,
            "gradient_quantile": gradient_quantile,
            "min_pairs": min_pairs,
            "min_signal_ratio": min_signal_ratio,
            "scenes": scenes,
            "sources": [source_of(image) for image in images],
        },
    )


def _check_results(results: list[dict[str, Any]], bands: dict[float, list[RawImage]]) -> None:
    """Refuse a band without a positive Green level; a reliable ratio must be positive."""
    for result, (wavelength, group) in zip(results, sorted(bands.items()), strict=True):
        level = result["green_level"]
        if not (math.isfinite(level) and level > 0):
            names = ", ".join(source_of(image) for image in group)
            raise DataError(
                f"the {wavelength:g} nm band ({names}) has no usable Green level ({level}): no "
                "green pixel is lit, unsaturated and smooth; re-take it with an exposure that "
                "leaves the green channel between black and saturation"
            )
        for fit in (result["r"], result["b"]):
            if not fit.reasons and not (math.isfinite(fit.ratio) and fit.ratio > 0):
                fit.reasons.append(f"fitted ratio {fit.ratio:.3g} is not positive")


@dataclass
class _RatioFit:
    ratio: float = math.nan
    pairs: int = 0
    residual: float = math.nan
    reasons: list[str] = field(default_factory=list)


def _calibrate_band(
    images: Sequence[RawImage],
    *,
    saturation: float,
    gradient_quantile: float,
    min_pairs: int,
    min_signal_ratio: float,
) -> dict[str, Any]:
    """Pooled pairs and fits of one band."""
    pairs: dict[int, tuple[list[np.ndarray], list[np.ndarray]]] = {
        _RED: ([], []),
        _BLUE: ([], []),
    }
    kept_values: dict[int, list[np.ndarray]] = {_RED: [], _GREEN: [], _BLUE: []}
    for image in images:
        raw = np.asarray(image.raw, dtype=np.float64)
        keep = smooth_unsaturated_mask(
            raw, saturation=saturation, gradient_quantile=gradient_quantile
        )
        index = channel_index(image.cfa, raw.shape)
        for channel, values in kept_values.items():
            values.append(raw[keep & (index == channel)])
        for channel, (greens, others) in pairs.items():
            g, x = neighbour_pairs(raw, keep, index, channel)
            greens.append(g)
            others.append(x)
    medians = {
        channel: float(np.median(np.concatenate(values))) if sum(v.size for v in values) else 0.0
        for channel, values in kept_values.items()
    }
    green = medians[_GREEN]
    brightest_other = max(medians[_RED], medians[_BLUE])
    fits = {}
    for channel, (greens, others) in pairs.items():
        name = _NAMES[channel]
        fit = _RatioFit()
        g = np.concatenate(greens)
        x = np.concatenate(others)
        fit.pairs = int(g.size)
        if fit.pairs >= 2:
            try:
                slope = principal_slope(g, x)
                fit.ratio, fit.residual = slope.slope, slope.residual_rms
            except DataError as error:
                fit.reasons.append(f"no fit ({str(error).removeprefix('principal_slope: ')})")
        if fit.pairs < min_pairs:
            fit.reasons.append(f"only {fit.pairs} green–{name} pairs (need {min_pairs})")
        if green <= 0:
            fit.reasons.append("no green pixel passed the gradient and saturation masks")
        else:
            if medians[channel] < min_signal_ratio * green:
                fit.reasons.append(
                    f"{name} has no signal (median {name}/green {medians[channel] / green:.2g} "
                    f"< {min_signal_ratio:g})"
                )
            if green < min_signal_ratio * brightest_other:
                fit.reasons.append(
                    f"green has no signal (median green/brightest {green / brightest_other:.2g} "
                    f"< {min_signal_ratio:g})"
                )
        fits[channel] = fit
    names = sorted({image.illumination for image in images})
    return {
        "illumination": "+".join(names),
        "r": fits[_RED],
        "b": fits[_BLUE],
        "green_level": green_level(images),
    }


def green_level(images: Sequence[RawImage]) -> float:
    """Mean Green value per second of exposure over images of one band (NaN if unknown).

    Each image contributes the mean of its Green pixels divided by its ``exposure_s``
    (fraction of saturation per s); the images of the band (several scenes) are averaged.
    """
    levels = []
    for image in images:
        if image.exposure_s is None or not image.exposure_s > 0:
            return math.nan
        raw = np.asarray(image.raw, dtype=np.float64)
        green = raw[channel_index(image.cfa, raw.shape) == _GREEN]
        levels.append(float(green.mean()) / float(image.exposure_s))
    return float(np.mean(levels))


def smooth_unsaturated_mask(
    raw: np.ndarray, *, saturation: float = 0.95, gradient_quantile: float = 0.5
) -> np.ndarray:
    """Pixels of a mosaic in textureless, unsaturated regions (Algorithm 12 steps 2–3).

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic, fraction of saturation; at least 4 × 4.
    saturation : float
        Keep values strictly below this (and strictly above 0).
    gradient_quantile : float
        Keep pixels whose gradient magnitude within their CFA colour plane (the
        stride-2 sub-image of their 2 × 2 phase, central differences) is at most this
        quantile of that plane's magnitudes.

    Returns
    -------
    ndarray (rows, cols) bool
    """
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 2 or min(raw.shape) < 4:
        raise DataError(f"a mosaic of at least 4 × 4 pixels is needed, got shape {raw.shape}")
    keep = np.zeros(raw.shape, dtype=bool)
    for dy in (0, 1):
        for dx in (0, 1):
            plane = raw[dy::2, dx::2]
            gy, gx = np.gradient(plane)
            magnitude = np.hypot(gx, gy)
            keep[dy::2, dx::2] = magnitude <= np.quantile(magnitude, gradient_quantile)
    return keep & (raw > 0) & (raw < saturation)


def neighbour_pairs(
    raw: np.ndarray, keep: np.ndarray, index: np.ndarray, channel: int
) -> tuple[np.ndarray, np.ndarray]:
    """Values of every (Green pixel, 4-neighbour `channel` pixel) pair where both are kept.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Mosaic values.
    keep : ndarray (rows, cols) bool
        Pixels allowed in a pair.
    index : ndarray (rows, cols)
        Channel of each pixel (0 R, 1 G, 2 B; :func:`labkit.cfa.channel_index`).
    channel : int
        0 (Red) or 2 (Blue).

    Returns
    -------
    green, other : ndarray (n,)
        Paired values; each Green pixel appears once per kept neighbour of `channel`
        (two in a Bayer mosaic), each `channel` pixel once per kept Green neighbour.
    """
    greens, others = [], []
    horizontal = (np.s_[:, :-1], np.s_[:, 1:])
    vertical = (np.s_[:-1, :], np.s_[1:, :])
    for first, second in (horizontal, vertical):
        both = keep[first] & keep[second]
        a_raw, b_raw = raw[first], raw[second]
        a_index, b_index = index[first], index[second]
        forward = both & (a_index == _GREEN) & (b_index == channel)
        backward = both & (a_index == channel) & (b_index == _GREEN)
        greens += [a_raw[forward], b_raw[backward]]
        others += [b_raw[forward], a_raw[backward]]
    return np.concatenate(greens), np.concatenate(others)
