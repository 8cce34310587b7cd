"""Dispersion keypoints from patch shifts: between filtered bands (through bilinear Green)
and between the colour channels of one image.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from calibration._hdr_inputs import check_consistent, source_of
from calibration.keypoints import DispersionKeypoints
from calibration.multispectral import green_bilinear
from calibration.registration._grid import patch_grid
from calibration.registration.shifts import MAX_ERROR, MIN_TEXTURE, PatchShifts, patch_shifts
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from labkit.io.exr import RawImage
from labkit.io.preview import demosaic_bilinear

#: Fewest accepted patches a band needs.
MIN_ACCEPTED = 10


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
    ref_index = _reference_index(images, bands, reference_nm)
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
    reference, meta_bands[str(reference_wl)] = _reference_keypoints(
        reference_green.shape, reference_wl, source_of(ref_image), patch_px, step_px
    )
    parts.append(reference)
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


def _reference_index(images: Sequence[RawImage], bands: list[float], reference_nm: float) -> int:
    """Which image is the reference band's; an error for two images of one band or none of
    the reference band."""
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
    return ref_index


def _reference_keypoints(
    shape: tuple[int, int], reference_wl: float, source: str, patch_px: int, step_px: int
) -> tuple[DispersionKeypoints, dict[str, Any]]:
    """The reference band's own patch centres (zero displacement) and its summary."""
    r0, c0 = patch_grid(shape, patch_px, step_px)
    half = (patch_px - 1) / 2.0
    n_ref = r0.size
    keypoints = DispersionKeypoints(
        c0 + half,
        r0 + half,
        np.zeros(n_ref),
        np.zeros(n_ref),
        reference=reference_wl,
        image_shape=shape,
        wavelength_nm=np.full(n_ref, reference_wl),
        source="registration",
        quality=np.zeros(n_ref),
    )
    return keypoints, {"file": source, "patches": n_ref, "accepted": n_ref, "reference": True}


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
