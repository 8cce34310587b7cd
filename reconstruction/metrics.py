"""Error metrics of estimated spectral and colour images (thesis §4.4.1–4.4.2, (4.3)–(4.14)).

Spectral images (``(rows, cols, bands)``, :func:`spectral_errors`):

* MRAE (4.3): mean of ``|I − Î| / |I|`` over all values; also per pixel (mean over bands);
* RMSE per pixel (4.4): the mean over pixels of each spectrum's RMS error, and global
  (4.5): the RMS error of all values together;
* GOF (4.6): per pixel ``|⟨I, Î⟩| / (‖I‖ ‖Î‖)`` (the cosine of the spectral angle), and
  its mean over pixels;
* SSIM (4.7): the mean over bands of each band's structural similarity.

Colour images (``(rows, cols, 3)``, raw camera colour, :func:`colour_errors`): MRAE
(4.10), RMSE (4.11) and SSIM (4.12) per channel R, G, B.

Registration (4.8)–(4.9), (4.13)–(4.14) — :func:`registration_scale`: the per-band factor
S_b that best maps the estimate onto the truth in the (weighted) least-squares sense, so
that errors ignore a per-band global intensity factor (e.g. when the reference comes
from another instrument). :func:`patch_weights` gives the weights of (4.13), inversely
proportional to the size of the patch holding each pixel. Pass ``register=True`` to
the error functions to apply the factors first; they are reported in the result.

Near-zero denominators
----------------------
MRAE and GOF divide by the true intensities, which is unreliable where they are close to
zero (thesis §4.4.1). Values (MRAE) or pixels (GOF) whose true intensity is at most a
*floor* are excluded and counted in the result (``mrae_excluded``, ``gof_excluded``).
The floor defaults to :data:`RELATIVE_FLOOR` × the largest ``|I|`` of the evaluated
pixels; for GOF a pixel's intensity is the RMS of its spectrum. A pixel
whose *estimated* spectrum is all zeros has no direction; its GOF is 0 (no fit). No
metric returns NaN or Inf: if every value would be excluded, a :class:`DataError` says so.

SSIM follows Wang et al. (2004) as implemented by
:func:`skimage.metrics.structural_similarity`: an 11 × 11 Gaussian window (σ = 1.5 px),
population covariances, K1 = 0.01, K2 = 0.03; the dynamic range L defaults to the
peak-to-peak range of the true image over all bands (so every band is compared on one
scale). SSIM is computed on whole images; with a mask, its map is averaged over the
masked pixels (without one, skimage's mean leaves out the 5-px border).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labkit.blas_threads import fixed_blas_threads
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
        Threshold on |true value| (MRAE) and true spectral RMS (GOF), image units.
    mrae_excluded : int
        Values left out of the MRAE (|I| ≤ floor).
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
        Threshold on |true value| for the MRAE, image units.
    mrae_excluded : tuple of int
        Values left out of each channel's MRAE (|I| ≤ floor).
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


# -- registration ---------------------------------------------------------------------


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


# -- spectral metrics ------------------------------------------------------------------


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
        Values with |I| ≤ floor are left out of the MRAE, pixels whose true spectral
        RMS is ≤ floor out of the GOF; image units. Default :data:`RELATIVE_FLOOR` ×
        the largest |I| in the mask.
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
    scale = _scale(truth, estimate, region, register, weights)
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


# -- colour metrics --------------------------------------------------------------------


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
        Values with |I| ≤ floor are left out of the MRAE, image units; default
        :data:`RELATIVE_FLOOR` × the largest |I| in the mask.
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
    scale = _scale(truth, estimate, region.any(axis=2), register, weights)
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


# -- helpers ---------------------------------------------------------------------------


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


def _scale(
    truth: np.ndarray,
    estimate: np.ndarray,
    region: np.ndarray,
    register: bool,
    weights: np.ndarray | None,
) -> np.ndarray | None:
    """Registration factors (weights default to the evaluated pixels), or None."""
    if not register:
        if weights is not None:
            raise DataError("registration weights were given but register=False")
        return None
    w = region.astype(np.float64) if weights is None else weights
    return registration_scale(truth, estimate, weights=w)


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
