"""Dispersion keypoints by patch-wise image registration (thesis §3.2.3, Appendix B.2).

The image plane is divided into partially overlapping patches (64 × 64 px every 32 px,
as in Appendix B.2) and each patch of a band image is registered to the same patch of
the reference band by sub-pixel cross-correlation. Following the thesis, filtered images
are registered through their Green channel only, interpolated to every pixel by bilinear
demosaicing (:func:`~calibration.multispectral.green_bilinear`); colour channels of an
unfiltered image are registered through the bilinearly demosaiced R and B channels
against G. The thesis used MATLAB's mutual-information registration; here the
translation comes from the Guizar-Sicairos upsampled-DFT cross-correlation that
:func:`skimage.registration.phase_cross_correlation` implements, re-implemented for a
whole stack of patches at once (batched FFTs and matrix-multiply DFTs) because calling
scikit-image once per patch is several times slower on a full image.

Bayer sampling makes plain phase correlation lock onto whole pixels: the bilinear Green
channel is the scene plus an aliased copy of its content near (½, ½) cycles/px, whose
phase does not follow the shift, and the phase-normalised spectrum weights the aliased
and noisy high frequencies as much as the scene's low ones. The estimator therefore

1. removes each patch's (windowed) mean and applies a Hann window (no wrap-around
   edges);
2. weights the cross-power spectrum with a Gaussian (σ = `lowpass` cycles/px) and does
   not whiten it (scikit-image's ``normalization=None``);
3. refines once: the moving image is resampled (cubic B-spline) at the patch positions
   plus the first estimate and the remaining shift is measured again, which removes
   most of the remaining pull towards whole pixels.

Each step's effect on a planted shift, and the run time, are in the README (calibration).

Patches are rejected when their registration error exceeds `max_error` (content that
differs between the images, e.g. colours whose contrast changes between bands), when
their texture is below `min_texture` (flat patches, and patches holding one straight
edge, whose shift along the edge is undetermined), or when the shift reaches the
search limit.

Sign convention: a keypoint says that the feature at (x, y) in the reference image is at
(x + dx, y + dy) in the band (``from_reference``); scikit-image's shift is the opposite
(what registers the moving image onto the reference).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft
from scipy import ndimage

from calibration._hdr_inputs import check_consistent, source_of
from calibration.keypoints import DispersionKeypoints
from calibration.multispectral import green_bilinear
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from labkit.io.exr import RawImage
from labkit.io.preview import demosaic_bilinear

#: Default ceiling of the per-patch registration error (translation-invariant normalised
#: RMS error of the aligned, windowed, low-passed patches; 0 = identical up to shift).
MAX_ERROR = 0.1
#: Default floor of the patch texture (RMS gradient along the weakest direction over the
#: mean intensity, 1/px): textured scenes give 0.05–0.15, a patch centred on a disk of the
#: calibration pattern ≈ 0.1, a patch with only disk edges in its window's tails ≈ 0.01.
MIN_TEXTURE = 0.03
#: Fewest accepted patches a band needs.
MIN_ACCEPTED = 10
#: Patches processed together (bounds memory: ~40 MB per chunk at 64 px).
_CHUNK = 256
#: Coarse refinement grid of the upsampled DFT: ± this many px around the integer peak.
_COARSE_HALF_PX = 0.8
#: Spectral weights below this are left out of the DFT refinement.
_NEGLIGIBLE_WEIGHT = 1e-6
#: Threads of the batched FFTs.
_WORKERS = -1


@dataclass(frozen=True)
class PatchShifts:
    """Per-patch translations between two images (result of :func:`patch_shifts`).

    Attributes
    ----------
    x, y : ndarray (n,) float64
        Patch centres in the reference image, px (x = column, y = row).
    dx, dy : ndarray (n,) float64
        Displacement reference → moving, px: the feature at (x, y) in the reference is
        at (x + dx, y + dy) in the moving image (``from_reference`` sign).
    error : ndarray (n,) float64
        Translation-invariant normalised RMS error of the aligned patches, 0–1
        (scikit-image's ``error``, computed on the windowed, low-passed patches).
    texture : ndarray (n,) float64
        RMS gradient of the windowed, low-passed patch along its weakest direction
        over its mean intensity, 1/px (the smaller of the two images'); 0 for flat
        patches, small for a single straight edge.
    accepted : ndarray (n,) bool
        Patches that passed the error, texture and search-limit tests.
    """

    x: np.ndarray
    y: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    error: np.ndarray
    texture: np.ndarray
    accepted: np.ndarray

    def __len__(self) -> int:
        return int(self.x.size)

    @property
    def n_accepted(self) -> int:
        """Number of accepted patches."""
        return int(np.count_nonzero(self.accepted))

    @property
    def n_rejected(self) -> int:
        """Number of rejected patches."""
        return len(self) - self.n_accepted


@fixed_blas_threads
def patch_shifts(
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    patch_px: int = 64,
    step_px: int = 32,
    upsample: int = 100,
    max_error: float = MAX_ERROR,
    min_texture: float = MIN_TEXTURE,
    max_shift_px: float = 8.0,
    window: bool = True,
    lowpass: float | None = 0.06,
    normalization: str | None = None,
    iterations: int = 1,
) -> PatchShifts:
    """Sub-pixel translation of every patch of `moving` relative to `reference`.

    Parameters
    ----------
    reference, moving : ndarray (rows, cols)
        Two images of one scene (any linear units; their scales may differ).
    patch_px : int
        Patch side, px (thesis: 64).
    step_px : int
        Distance between neighbouring patch centres, px (thesis: 32). The patch grid is
        centred in the image.
    upsample : int
        Upsampling factor of the DFT refinement: shifts are resolved to 1/`upsample` px.
    max_error : float
        Reject patches whose registration error (0–1) exceeds this.
    min_texture : float
        Reject patches whose texture (see :class:`PatchShifts`, 1/px) is below this.
    max_shift_px : float
        Search range, px; patches whose shift reaches it in x or y are rejected.
    window : bool
        Apply a Hann window to each (mean-subtracted) patch.
    lowpass : float or None
        Standard deviation of the Gaussian weight on the cross-power spectrum,
        cycles/px (None: no weighting, as scikit-image).
    normalization : {None, "phase"}
        ``"phase"`` whitens the cross-power spectrum (phase correlation) before the
        low-pass weight; None keeps it (cross-correlation, scikit-image's
        ``normalization=None``), which was the more accurate on Bayer images.
    iterations : int
        Refinement passes after the first estimate (0 = a single pass).

    Returns
    -------
    PatchShifts
        Rejected patches keep their (unreliable) estimates; nothing is NaN.

    Raises
    ------
    DataError
        Images of different shape, smaller than one patch, or holding NaN/Inf.
    """
    reference = np.asarray(reference, dtype=np.float64)
    moving = np.asarray(moving, dtype=np.float64)
    _check_pair(reference, moving, patch_px, step_px, upsample, max_shift_px, normalization)
    r0, c0 = _patch_grid(reference.shape, patch_px, step_px)
    n = r0.size
    weight = _spectral_weight(patch_px, lowpass)
    taper = _hann(patch_px) if window else np.ones((patch_px, patch_px))
    margin = int(np.ceil(max_shift_px)) + 4
    coefficients = None
    if iterations > 0:
        padded = np.pad(moving, margin, mode="reflect")
        coefficients = ndimage.spline_filter(padded, order=3, mode="mirror")
    ref_windows = np.lib.stride_tricks.sliding_window_view(reference, (patch_px, patch_px))
    mov_windows = np.lib.stride_tricks.sliding_window_view(moving, (patch_px, patch_px))
    dx, dy, error, texture = np.zeros(n), np.zeros(n), np.ones(n), np.zeros(n)
    at_limit = np.zeros(n, dtype=bool)
    for start in range(0, n, _CHUNK):
        part = slice(start, min(start + _CHUNK, n))
        rows, cols = r0[part], c0[part]
        ref_spectrum, ref_level = _spectrum(ref_windows[rows, cols], taper)
        texture[part] = _texture(ref_spectrum, ref_level, weight, taper)
        shift = np.zeros((rows.size, 2))  # (dy, dx)
        for step in range(iterations + 1):
            if step == 0:
                mov_patches = mov_windows[rows, cols]
                search = max_shift_px + 1.0
            else:
                # patches beyond the search range are rejected; keep them inside the padding
                inside = np.clip(shift, 3 - margin, margin - 3)
                mov_patches = _shifted_patches(coefficients, rows, cols, inside, patch_px, margin)
                search = 2.0
            mov_spectrum, mov_level = _spectrum(mov_patches, taper)
            if step == 0:
                texture[part] = np.minimum(
                    texture[part], _texture(mov_spectrum, mov_level, weight, taper)
                )
            cross = np.conj(ref_spectrum) * mov_spectrum
            weighted = cross
            if normalization == "phase":
                weighted = cross / np.maximum(np.abs(cross), np.finfo(np.float64).tiny)
            if weight is not None:
                weighted = weighted * weight
            residual = _correlation_peak(weighted, search, upsample, _support(weight))
            shift = shift + residual
            if step == 0:
                at_limit[part] = np.any(np.abs(residual) > max_shift_px, axis=1)
        error[part] = _registration_error(cross, ref_spectrum, mov_spectrum, weight, residual)
        flat = texture[part] == 0
        shift[flat] = 0.0  # no signal: report no displacement rather than noise
        dy[part], dx[part] = shift[:, 0], shift[:, 1]
    at_limit |= np.maximum(np.abs(dx), np.abs(dy)) > max_shift_px
    accepted = (error <= max_error) & (texture >= min_texture) & ~at_limit
    half = (patch_px - 1) / 2.0
    return PatchShifts(
        x=c0 + half,
        y=r0 + half,
        dx=dx,
        dy=dy,
        error=error,
        texture=texture,
        accepted=accepted,
    )


@fixed_blas_threads
def registration_keypoints(
    images: Sequence[RawImage],
    *,
    reference_nm: float,
    wavelengths: Mapping[str, float] | None = None,
    patch_px: int = 64,
    step_px: int = 32,
    upsample: int = 100,
    max_error: float = MAX_ERROR,
    min_texture: float = MIN_TEXTURE,
    max_shift_px: float = 8.0,
) -> DispersionKeypoints:
    """Spectral dispersion keypoints by registering the Green channel of every band.

    Parameters
    ----------
    images : sequence of RawImage
        Filtered-light (HDR) images of one textured scene, one per band, all of one
        shape and CFA layout.
    reference_nm : float
        Reference band, nm; one image must lie within 0.5 nm of it.
    wavelengths : mapping of str to float, optional
        Band wavelength (nm) by illumination name; default: each image's
        ``wavelength_nm``.
    patch_px, step_px, upsample, max_error, min_texture, max_shift_px
        See :func:`patch_shifts`.

    Returns
    -------
    DispersionKeypoints
        Accepted patch centres of every band with their displacement from the
        reference band, plus the reference band's own patch centres (dx = dy = 0);
        ``source="registration"``, ``quality`` = registration error. ``meta["bands"]``
        maps ``str(wavelength)`` to ``{"file", "patches", "accepted", "rejected"}``
        (rejections counted by reason: ``error``, ``texture``, ``search_limit``; a
        patch may have several); ``meta["rejected"]`` is the total.

    Raises
    ------
    DataError
        No images, mismatched shape/CFA, an image without a wavelength, two images of
        one band, no image at `reference_nm`, or a band with fewer than 10 accepted
        patches (too little texture).
    """
    if not images:
        raise DataError("registration_keypoints needs the filtered images of one scene")
    check_consistent(images, what="registration")
    bands = [_band_wavelength(image, wavelengths) for image in images]
    for i, band in enumerate(bands):
        for j in range(i):
            if abs(bands[j] - band) < 0.5:
                raise DataError(
                    f"{source_of(images[j])} and {source_of(images[i])} are both the "
                    f"{band:g} nm band; pass one image per band"
                )
    distance = np.abs(np.asarray(bands) - float(reference_nm))
    ref_index = int(np.argmin(distance))
    if distance[ref_index] > 0.5:
        listed = ", ".join(f"{b:g}" for b in sorted(bands))
        raise DataError(
            f"no image of the reference band {reference_nm:g} nm among the bands {listed} nm; "
            "pass reference_nm= one of them"
        )
    options = {
        "patch_px": patch_px,
        "step_px": step_px,
        "upsample": upsample,
        "max_error": max_error,
        "min_texture": min_texture,
        "max_shift_px": max_shift_px,
    }
    ref_image = images[ref_index]
    reference_wl = bands[ref_index]
    reference_green = green_bilinear(ref_image.raw, ref_image.cfa)
    _check_signal(reference_green, f"{source_of(ref_image)} ({reference_wl:g} nm)")
    parts, meta_bands = [], {}
    for image, band in zip(images, bands, strict=True):
        if image is ref_image:
            continue
        name = f"{source_of(image)} ({band:g} nm)"
        green = green_bilinear(image.raw, image.cfa)
        _check_signal(green, name)
        shifts = patch_shifts(reference_green, green, **options)
        _require_texture(
            shifts,
            f"{name} vs the reference {source_of(ref_image)}",
            "use the disk keypoints or a textured scene",
        )
        meta_bands[str(band)] = _summary(shifts, source_of(image), max_error, min_texture)
        parts.append(_keypoints(shifts, reference_wl, reference_green.shape, band=band))
    r0, c0 = _patch_grid(reference_green.shape, patch_px, step_px)
    half = (patch_px - 1) / 2.0
    n_ref = r0.size
    meta_bands[str(reference_wl)] = {
        "file": source_of(ref_image),
        "patches": n_ref,
        "accepted": n_ref,
        "reference": True,
    }
    parts.append(
        DispersionKeypoints(
            c0 + half,
            r0 + half,
            np.zeros(n_ref),
            np.zeros(n_ref),
            reference=reference_wl,
            image_shape=reference_green.shape,
            wavelength_nm=np.full(n_ref, reference_wl),
            source="registration",
            quality=np.zeros(n_ref),
        )
    )
    joined = DispersionKeypoints.concatenate(parts)
    order = np.argsort(joined.wavelength_nm, kind="stable")
    return _with_meta(
        joined.select(order),
        {
            "bands": dict(sorted(meta_bands.items(), key=lambda item: float(item[0]))),
            "reference_file": source_of(ref_image),
            "rejected": sum(b["patches"] - b["accepted"] for b in meta_bands.values()),
            "options": options,
        },
    )


@fixed_blas_threads
def channel_registration_keypoints(
    image: RawImage,
    *,
    patch_px: int = 64,
    step_px: int = 32,
    upsample: int = 100,
    max_error: float = MAX_ERROR,
    min_texture: float = MIN_TEXTURE,
    max_shift_px: float = 8.0,
) -> DispersionKeypoints:
    """Colour-channel dispersion keypoints: R and B registered against G.

    Parameters
    ----------
    image : RawImage
        An unfiltered image of a textured scene (bilinearly demosaiced here).
    patch_px, step_px, upsample, max_error, min_texture, max_shift_px
        See :func:`patch_shifts`.

    Returns
    -------
    DispersionKeypoints
        Accepted patch centres with ``channel`` ``"R"`` or ``"B"``, reference ``"G"``
        (no G keypoints); ``meta["channels"]`` maps each channel to
        ``{"file", "patches", "accepted", "rejected"}`` as in
        :func:`registration_keypoints`.

    Raises
    ------
    DataError
        A filtered image, or a channel with fewer than 10 accepted patches.
    """
    name = source_of(image)
    if image.wavelength_nm is not None:
        raise DataError(
            f"{name} was taken under {image.wavelength_nm:g} nm filtered light; colour-channel "
            "registration needs an unfiltered image (use registration_keypoints for bands)"
        )
    rgb = demosaic_bilinear(image.raw, image.cfa).astype(np.float64)
    green = np.ascontiguousarray(rgb[..., 1])
    _check_signal(green, f"{name} (G)")
    options = {
        "patch_px": patch_px,
        "step_px": step_px,
        "upsample": upsample,
        "max_error": max_error,
        "min_texture": min_texture,
        "max_shift_px": max_shift_px,
    }
    parts, meta = [], {}
    for index, channel in ((0, "R"), (2, "B")):
        label = f"{name} ({channel})"
        plane = np.ascontiguousarray(rgb[..., index])
        _check_signal(plane, label)
        shifts = patch_shifts(green, plane, **options)
        _require_texture(shifts, f"{label} vs G", "use the disk keypoints or a textured scene")
        meta[channel] = _summary(shifts, name, max_error, min_texture)
        parts.append(_keypoints(shifts, "G", green.shape, channel=channel))
    return _with_meta(
        DispersionKeypoints.concatenate(parts),
        {
            "channels": meta,
            "rejected": sum(m["patches"] - m["accepted"] for m in meta.values()),
            "options": options,
        },
    )


# -- keypoint assembly ----------------------------------------------------------------


def _band_wavelength(image: RawImage, wavelengths: Mapping[str, float] | None) -> float:
    """The band of an image: ``wavelengths[illumination]`` or its ``wavelength_nm``."""
    if wavelengths is not None:
        if image.illumination not in wavelengths:
            raise DataError(
                f"{source_of(image)}: illumination {image.illumination!r} has no entry in "
                f"wavelengths= (entries: {', '.join(map(str, wavelengths))}); add it"
            )
        value = float(wavelengths[image.illumination])
    elif image.wavelength_nm is None:
        raise DataError(
            f"{source_of(image)}: illumination {image.illumination!r} is unfiltered (no "
            "wavelength_nm); pass only filtered images, or wavelengths= by illumination name "
            "(channel_registration_keypoints registers the channels of unfiltered images)"
        )
    else:
        value = float(image.wavelength_nm)
    if not np.isfinite(value):
        raise DataError(f"{source_of(image)}: band wavelength {value} is not a number")
    return value


def _keypoints(
    shifts: PatchShifts,
    reference: float | str,
    shape: tuple[int, int],
    *,
    band: float | None = None,
    channel: str | None = None,
) -> DispersionKeypoints:
    ok = shifts.accepted
    k = int(np.count_nonzero(ok))
    return DispersionKeypoints(
        shifts.x[ok],
        shifts.y[ok],
        shifts.dx[ok],
        shifts.dy[ok],
        reference=reference,
        image_shape=shape,
        wavelength_nm=None if band is None else np.full(k, band),
        channel=None if channel is None else np.full(k, channel),
        source="registration",
        quality=shifts.error[ok],
    )


def _with_meta(keypoints: DispersionKeypoints, meta: dict) -> DispersionKeypoints:
    return DispersionKeypoints(
        keypoints.x,
        keypoints.y,
        keypoints.dx,
        keypoints.dy,
        reference=keypoints.reference,
        image_shape=keypoints.image_shape,
        wavelength_nm=keypoints.wavelength_nm,
        channel=keypoints.channel,
        source=keypoints.source,
        quality=keypoints.quality,
        meta=meta,
    )


def _summary(shifts: PatchShifts, file: str, max_error: float, min_texture: float) -> dict:
    """Provenance of one band: patches, accepted, and rejections by (overlapping) reason."""
    return {
        "file": file,
        "patches": len(shifts),
        "accepted": shifts.n_accepted,
        "rejected": {
            "error": int(np.count_nonzero(shifts.error > max_error)),
            "texture": int(np.count_nonzero(shifts.texture < min_texture)),
            "search_limit": int(
                np.count_nonzero(
                    ~shifts.accepted & (shifts.error <= max_error) & (shifts.texture >= min_texture)
                )
            ),
        },
    }


def _require_texture(shifts: PatchShifts, name: str, advice: str) -> None:
    if shifts.n_accepted < MIN_ACCEPTED:
        raise DataError(
            f"{name}: too little texture to register: {shifts.n_accepted} of {len(shifts)} "
            f"patches accepted (need {MIN_ACCEPTED}); {advice}"
        )


def _check_signal(image: np.ndarray, name: str) -> None:
    if not np.all(np.isfinite(image)):
        raise DataError(f"{name} holds NaN or Inf pixels; re-merge the HDR image")


# -- the batched estimator ------------------------------------------------------------


def _check_pair(
    reference: np.ndarray,
    moving: np.ndarray,
    patch_px: int,
    step_px: int,
    upsample: int,
    max_shift_px: float,
    normalization: str | None,
) -> None:
    if reference.ndim != 2 or reference.shape != moving.shape:
        raise DataError(
            f"patch_shifts needs two 2-D images of one shape, got {reference.shape} "
            f"and {moving.shape}"
        )
    if patch_px < 8 or step_px < 1 or upsample < 1:
        raise DataError(
            f"patch_px ≥ 8, step_px ≥ 1 and upsample ≥ 1 required, got {patch_px}, "
            f"{step_px}, {upsample}"
        )
    if min(reference.shape) < patch_px:
        raise DataError(
            f"images of {reference.shape[1]}×{reference.shape[0]} px are smaller than one "
            f"{patch_px} px patch; use a smaller patch_px"
        )
    if not 0 < max_shift_px < patch_px / 4:
        raise DataError(
            f"max_shift_px must be in (0, {patch_px / 4:g}) for {patch_px} px patches, "
            f"got {max_shift_px}"
        )
    if normalization not in (None, "phase"):
        raise DataError(f"normalization must be None or 'phase', not {normalization!r}")
    for name, image in (("reference", reference), ("moving", moving)):
        if not np.all(np.isfinite(image)):
            raise DataError(f"the {name} image holds NaN or Inf pixels")


def _patch_grid(shape: tuple[int, int], patch_px: int, step_px: int) -> tuple[np.ndarray, ...]:
    """Top-left corners (rows, cols) of the patch grid, centred in the image."""

    def axis(size: int) -> np.ndarray:
        count = (size - patch_px) // step_px + 1
        first = (size - patch_px - (count - 1) * step_px) // 2
        return first + step_px * np.arange(count)

    rows, cols = np.meshgrid(axis(shape[0]), axis(shape[1]), indexing="ij")
    return rows.ravel(), cols.ravel()


def _hann(size: int) -> np.ndarray:
    """Separable Hann window (size, size) without zero end points."""
    w = np.hanning(size + 2)[1:-1]
    return np.outer(w, w)


def _spectral_weight(size: int, sigma: float | None) -> np.ndarray | None:
    """Gaussian weight (size, size) on the FFT grid, σ in cycles/px (None: no weight)."""
    if sigma is None:
        return None
    if sigma <= 0:
        raise DataError(f"lowpass must be a positive number of cycles/px, got {sigma}")
    f = np.fft.fftfreq(size)
    return np.exp(-(f[:, None] ** 2 + f[None, :] ** 2) / (2.0 * sigma * sigma))


def _support(weight: np.ndarray | None) -> np.ndarray | None:
    """FFT indices (one axis) where the separable spectral weight is not negligible."""
    if weight is None:
        return None
    return np.flatnonzero(weight[0] > _NEGLIGIBLE_WEIGHT)


def _spectrum(patches: np.ndarray, taper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """FFT (n, p, p) of the mean-subtracted, windowed patches and their windowed means."""
    level = np.einsum("nij,ij->n", patches, taper) / taper.sum()
    centred = (patches - level[:, None, None]) * taper
    return sp_fft.fft2(centred, workers=_WORKERS), level


def _texture(
    spectrum: np.ndarray, level: np.ndarray, weight: np.ndarray | None, taper: np.ndarray
) -> np.ndarray:
    """Texture of each patch: RMS gradient along its weakest direction over its mean, 1/px.

    The gradient structure tensor J = mean(∇I ∇Iᵀ) of the windowed, low-passed patch is
    computed from its spectrum (Parseval); sqrt of its smaller eigenvalue is 0 for flat
    patches and for patches holding a single straight edge (the aperture problem), which
    constrain the shift in at most one direction. 0 where the mean is not positive.
    """
    size = spectrum.shape[1]
    f = 2.0 * np.pi * np.fft.fftfreq(size)
    power = np.abs(spectrum) ** 2
    if weight is not None:
        power = power * weight
    scale = size * size * np.sum(taper * taper)
    jyy = np.einsum("nij,i->n", power, f * f) / scale
    jxx = np.einsum("nij,j->n", power, f * f) / scale
    jxy = np.einsum("nij,i,j->n", power, f, f) / scale
    smallest = 0.5 * (jxx + jyy) - np.sqrt(0.25 * (jxx - jyy) ** 2 + jxy * jxy)
    rms = np.sqrt(np.maximum(smallest, 0.0))
    return np.divide(rms, level, out=np.zeros_like(rms), where=level > 0)


def _correlation_peak(
    cross: np.ndarray, search_px: float, upsample: int, support: np.ndarray | None
) -> np.ndarray:
    """Location (n, 2) = (dy, dx) of the maximum of the correlation ``ifft2(cross)``.

    The whole-pixel maximum within ±`search_px` is refined by matrix-multiply DFTs
    (Guizar-Sicairos et al. 2008, as scikit-image): first on a 0.1 px grid over
    ±0.8 px, then on a 1/`upsample` px grid over ±0.1 px. `support` restricts the DFTs
    to the frequencies (per axis) that carry weight.
    """
    n, size, _ = cross.shape
    surface = sp_fft.ifft2(cross, workers=_WORKERS).real
    offsets = np.fft.fftfreq(size, 1.0 / size)  # 0, 1, …, −1
    outside = np.abs(offsets) > search_px
    surface[:, outside, :] = -np.inf
    surface[:, :, outside] = -np.inf
    flat = np.argmax(surface.reshape(n, -1), axis=1)
    peak = np.column_stack([offsets[flat // size], offsets[flat % size]])
    if upsample == 1:
        return peak
    freq = np.fft.fftfreq(size)
    if support is not None:
        cross = cross[:, support][:, :, support]
        freq = freq[support]
    coarse_step = 1.0 / min(upsample, 10)
    for step, half in ((coarse_step, _COARSE_HALF_PX), (1.0 / upsample, coarse_step)):
        if step >= half:
            continue
        grid = step * np.arange(-round(half / step), round(half / step) + 1)
        peak = _refine(cross, freq, peak, grid)
    return peak


def _refine(
    cross: np.ndarray, freq: np.ndarray, centre: np.ndarray, grid: np.ndarray
) -> np.ndarray:
    """Maximum of the correlation sampled at `centre` + `grid` × `grid`, (n, 2) px.

    The DFT kernel factorises, exp(2πi f (c + g)) = exp(2πi f c) exp(2πi f g): each
    spectrum is phase-shifted to its centre, then all patches share two matrix
    products with the grid kernel (two large GEMMs instead of 2n small ones).
    """
    n, m, _ = cross.shape
    k = grid.size
    row = np.exp(2j * np.pi * centre[:, 0:1] * freq[None, :])  # (n, m)
    col = np.exp(2j * np.pi * centre[:, 1:2] * freq[None, :])
    shifted = row[:, :, None] * cross * col[:, None, :]  # (n, m, m)
    kernel = np.exp(2j * np.pi * grid[:, None] * freq[None, :])  # (k, m)
    left = kernel @ shifted.transpose(1, 0, 2).reshape(m, n * m)  # (k, n·m)
    samples = (left.reshape(k * n, m) @ kernel.T).reshape(k, n, k).real  # (k_y, n, k_x)
    flat = np.argmax(samples.transpose(1, 0, 2).reshape(n, -1), axis=1)
    return centre + np.column_stack([grid[flat // k], grid[flat % k]])


def _registration_error(
    cross: np.ndarray,
    ref_spectrum: np.ndarray,
    mov_spectrum: np.ndarray,
    weight: np.ndarray | None,
    shift: np.ndarray,
) -> np.ndarray:
    """Translation-invariant normalised RMS error of the patches at `shift` (n, 2).

    ``sqrt(1 − c² / (E_ref E_mov))`` with c the weighted cross-correlation at the
    shift found in the last pass and E the weighted energies (scikit-image's ``error``
    of the unnormalised correlation); 1 where a patch has no energy or c < 0.
    """
    size = cross.shape[1]
    freq = np.fft.fftfreq(size)
    w = 1.0 if weight is None else weight
    row = np.exp(2j * np.pi * shift[:, 0:1] * freq[None, :])  # (n, p)
    col = np.exp(2j * np.pi * shift[:, 1:2] * freq[None, :])
    peak = np.einsum("ni,nij,nj->n", row, cross * w, col).real
    energy = np.sum(np.abs(ref_spectrum) ** 2 * w, axis=(1, 2)) * np.sum(
        np.abs(mov_spectrum) ** 2 * w, axis=(1, 2)
    )
    ratio = np.divide(peak * peak, energy, out=np.zeros_like(peak), where=energy > 0)
    ratio[peak < 0] = 0.0
    return np.sqrt(np.clip(1.0 - ratio, 0.0, 1.0))


def _bspline_weights(fraction: np.ndarray) -> np.ndarray:
    """Cubic B-spline weights (n, 4) of the samples at −1, 0, 1, 2 for offsets in [0, 1)."""
    t = np.abs(fraction[:, None] - np.arange(-1, 3)[None, :])
    inner = 2.0 / 3.0 - t * t + 0.5 * t**3
    outer = np.maximum(2.0 - t, 0.0) ** 3 / 6.0
    return np.where(t < 1.0, inner, outer)


def _shifted_patches(
    coefficients: np.ndarray,
    r0: np.ndarray,
    c0: np.ndarray,
    shift: np.ndarray,
    patch_px: int,
    margin: int,
) -> np.ndarray:
    """Patches of the moving image sampled at (r0 + i + dy, c0 + j + dx) (cubic B-spline).

    `coefficients` are the B-spline coefficients of the moving image padded by `margin`.
    """
    whole = np.floor(shift).astype(np.int64)
    frac = shift - whole
    top = r0 + whole[:, 0] + margin - 1
    left = c0 + whole[:, 1] + margin - 1
    windows = np.lib.stride_tricks.sliding_window_view(coefficients, (patch_px + 3, patch_px + 3))
    block = windows[top, left]  # (n, p + 3, p + 3)
    wy = _bspline_weights(frac[:, 0])
    wx = _bspline_weights(frac[:, 1])
    cols = sum(wx[:, m, None, None] * block[:, :, m : m + patch_px] for m in range(4))
    return sum(wy[:, m, None, None] * cols[:, m : m + patch_px, :] for m in range(4))
