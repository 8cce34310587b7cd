"""Checks and shared pieces of the error metrics: input pairs, masks, weights, floors,
SSIM (see :mod:`reconstruction.evaluate.metrics`).
"""

from __future__ import annotations

import numpy as np

from labkit.cfa import CHANNELS
from labkit.errors import DataError

#: Default MRAE/GOF floor, relative to the largest |true value| of the evaluated pixels.
RELATIVE_FLOOR = 1e-3
#: Pixels per block in spectral_errors and registration_scale (bounds the float64
#: temporaries to a few × BLOCK_PIXELS × bands values, whatever the image size).
BLOCK_PIXELS = 1 << 16
#: Largest |value| (and, inverted, smallest peak) the metrics square without rescaling.
SAFE_MAGNITUDE = 1e100
#: Side of SSIM's Gaussian window (σ = 1.5 px, truncated at 3.5 σ), px.
SSIM_WINDOW_PX = 11


def _pair(
    truth: np.ndarray, estimate: np.ndarray, what: str, *, min_ndim: int, max_ndim: int = 32
) -> tuple[np.ndarray, np.ndarray]:
    """Both arrays as float64, checked for equal shape, dimensions and finiteness."""
    t, e = _floating(truth), _floating(estimate)
    if t.shape != e.shape:
        raise DataError(
            f"{what}: the true image has shape {t.shape} but the estimate {e.shape}; "
            "compare images of the same size and band count (crop or resample one)"
        )
    if not min_ndim <= t.ndim <= max_ndim:
        expected = "(rows, cols, bands)" if max_ndim == 3 else "(..., bands)"
        raise DataError(f"{what} needs {expected} arrays, got shape {t.shape}")
    if t.size == 0:
        raise DataError(f"{what}: the images are empty (shape {t.shape})")
    for name, array in (("true image", t), ("estimate", e)):
        if not np.all(np.isfinite(array)):
            raise DataError(
                f"{what}: the {name} holds NaN or Inf; fix those pixels or leave them out "
                "with a mask of valid pixels"
            )
    return t, e


def _unit(*arrays: np.ndarray) -> float:
    """A power of two near the arrays' largest |value|, or 1 when squares are safe.

    Products of values beyond :data:`SAFE_MAGNITUDE` (or below its inverse) overflow or
    underflow in float64; dividing by an exact power of two leaves every relative metric
    unchanged and absolute ones exact after multiplying back.
    """
    peak = max(max(float(a.max()), -float(a.min())) for a in arrays)
    if peak == 0 or 1 / SAFE_MAGNITUDE <= peak <= SAFE_MAGNITUDE:
        return 1.0
    return float(np.ldexp(1.0, int(np.frexp(peak)[1])))


def _rescaled(truth: np.ndarray, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(truth / u, estimate / u, u) with u from :func:`_unit` (no copies when u = 1)."""
    unit = _unit(truth, estimate)
    if unit == 1.0:
        return truth, estimate, unit
    return truth / unit, estimate / unit, unit


def _floating(array: np.ndarray) -> np.ndarray:
    """float32/float64 arrays as they are (no copy of a large cube), others as float64."""
    a = np.asarray(array)
    return a if a.dtype in (np.float32, np.float64) else a.astype(np.float64)


def _mask(mask: np.ndarray | None, shape: tuple[int, int], what: str) -> np.ndarray:
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask)
    if m.shape != shape or m.dtype != bool:
        raise DataError(
            f"{what}: the mask must be a boolean image of shape {shape}, got {m.dtype} "
            f"of shape {m.shape}"
        )
    if not m.any():
        raise DataError(f"{what}: the mask selects no pixel; select the pixels to evaluate")
    return m


def _channel_mask(mask: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """A (rows, cols, 3) mask from None, a (rows, cols) or a (rows, cols, 3) one."""
    rows, cols, channels = shape
    if mask is not None and np.ndim(mask) == 3:
        m = np.asarray(mask)
        if m.shape != shape or m.dtype != bool:
            raise DataError(
                f"colour_errors: a per-channel mask must be boolean of shape {shape}, got "
                f"{m.dtype} of shape {m.shape}"
            )
        empty = [CHANNELS[c] for c in range(channels) if not m[..., c].any()]
        if empty:
            raise DataError(f"colour_errors: the mask selects no pixel of channel(s) {empty}")
        return m
    plane = _mask(mask, (rows, cols), "colour_errors")
    return np.repeat(plane[..., None], channels, axis=2)


def _weights(weights: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    if weights is None:
        return np.ones(shape)
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != shape:
        raise DataError(f"registration weights must have shape {shape}, got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise DataError("registration weights must be finite and ≥ 0")
    if not np.any(w > 0):
        raise DataError("every registration weight is zero; give some pixels weight")
    return w


def _check_floor(floor: float) -> float:
    value = float(floor)
    if not np.isfinite(value) or value < 0:
        raise DataError(f"the MRAE/GOF floor must be finite and ≥ 0, got {floor}")
    return value


def _all_excluded(what: str, thr: float) -> DataError:
    return DataError(
        f"{what} is undefined: every true value in the evaluated pixels is at most the "
        f"floor {thr:g} (near-zero denominators); evaluate brighter pixels or pass a "
        "smaller floor"
    )


def _gof(t: np.ndarray, e: np.ndarray, thr: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel GOF (4.6) of spectra (n, bands) and which pixels are above the floor."""
    norm_t = np.sqrt(np.sum(t * t, axis=1))
    norm_e = np.sqrt(np.sum(e * e, axis=1))
    valid = norm_t / np.sqrt(t.shape[1]) > thr
    denominator = norm_t * norm_e
    usable = valid & (denominator > 0)
    dot = np.abs(np.sum(t * e, axis=1))
    gof = np.divide(dot, denominator, out=np.zeros_like(norm_t), where=usable)
    return np.clip(gof, 0.0, 1.0), valid


def _as_map(values: np.ndarray, region: np.ndarray, valid: np.ndarray) -> np.ma.MaskedArray:
    """A masked (rows, cols) image of per-pixel values known at `region` (where `valid`)."""
    data = np.zeros(region.shape)
    data[region] = np.where(valid, values, 0.0)
    hidden = np.ones(region.shape, dtype=bool)
    hidden[region] = ~valid
    return np.ma.MaskedArray(data, mask=hidden)


def _data_range(truth: np.ndarray, data_range: float | None) -> float:
    value = float(np.ptp(truth)) if data_range is None else float(data_range)
    if not np.isfinite(value) or value <= 0:
        raise DataError(
            f"SSIM needs a positive dynamic range, got {value:g} (the true image is "
            "constant); pass data_range (the signal's full scale) or ssim=False"
        )
    return value


def _ssim(truth: np.ndarray, estimate: np.ndarray, mask: np.ndarray | None, L: float) -> float:
    """SSIM of one plane; the mean over `mask` of the SSIM map when a mask is given."""
    from skimage.metrics import structural_similarity

    if min(truth.shape) < SSIM_WINDOW_PX:
        raise DataError(
            f"SSIM needs images of at least {SSIM_WINDOW_PX} × {SSIM_WINDOW_PX} px (its "
            f"Gaussian window), got {truth.shape[1]} × {truth.shape[0]}; pass ssim=False"
        )
    mean, ssim_map = structural_similarity(
        np.asarray(truth, dtype=np.float64),
        np.asarray(estimate, dtype=np.float64),
        data_range=L,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        full=True,
    )
    value = float(mean) if mask is None else float(ssim_map[mask].mean())
    if not np.isfinite(value):  # pragma: no cover - guarded by the checks above
        raise DataError("SSIM came out NaN or Inf; check the images and data_range")
    return value
