"""Disk keypoints of images: spectral dispersion between filtered bands and lateral chromatic
aberration between the colour channels of one image.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from concurrent.futures import Executor
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from calibration._hdr_inputs import source_of
from calibration.disks._outliers import displacement_outliers
from calibration.disks._pool import Pending, finish, maybe_pool, start, worker_count
from calibration.disks._raw import checked_raw
from calibration.disks.detect import EDGE_WIDTH_PX, detect_disks
from calibration.disks.fit import DiskFit
from calibration.disks.pair import pair_mutual_nearest
from calibration.keypoints import DispersionKeypoints
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import check_layout
from labkit.errors import DataError
from labkit.io.exr import RawImage

#: Fewest disks a band must pair with the reference.
_MIN_PAIRED = 10
#: Tolerance when matching band wavelengths with the reference, nm.
_WAVELENGTH_TOLERANCE_NM = 0.5


def _band_wavelength(image: RawImage, wavelengths: Mapping[str, float] | None) -> float:
    if wavelengths is not None and image.illumination in wavelengths:
        return float(wavelengths[image.illumination])
    if image.wavelength_nm is None:
        hint = "" if wavelengths is None else f" and `wavelengths` has no {image.illumination!r}"
        raise DataError(
            f"{source_of(image)}: illumination {image.illumination!r} has no wavelength_nm"
            f"{hint}; disk keypoints need bandpass-filtered images (pass `wavelengths` to "
            "name the band of each illumination)"
        )
    return float(image.wavelength_nm)


def _check_images(images: Sequence[RawImage]) -> None:
    if not images:
        raise DataError("disk keypoints need at least one image per filter band; got none")
    first = images[0]
    for image in images[1:]:
        if image.raw.shape != first.raw.shape or check_layout(image.cfa) != check_layout(first.cfa):
            raise DataError(
                f"{source_of(image)} is {image.raw.shape[1]}×{image.raw.shape[0]} {image.cfa} "
                f"but {source_of(first)} is {first.raw.shape[1]}×{first.raw.shape[0]} "
                f"{first.cfa}; all disk images must come from the same camera mode"
            )


def _start_image(
    image: RawImage, where: str, pool: Executor | None, workers: int, *, per_channel: bool = False
) -> Pending:
    """Detect the disks of one image and start fitting them; errors name it as `where`."""
    raw = checked_raw(image.raw, where)
    layout = check_layout(image.cfa)
    candidates = detect_disks(raw, cfa=layout, name=where)
    return start(raw, layout, candidates, per_channel, where, EDGE_WIDTH_PX, pool, workers)


@fixed_blas_threads
def disk_keypoints(
    images: Sequence[RawImage],
    *,
    reference_nm: float,
    wavelengths: Mapping[str, float] | None = None,
    max_shift_px: float | None = None,
    workers: int | None = None,
) -> DispersionKeypoints:
    """Spectral dispersion keypoints from images of the disk pattern, one per filter band.

    Parameters
    ----------
    images : sequence of RawImage
        Bandpass-filtered images of the disk pattern (one per band, same size and CFA).
    reference_nm : float
        Reference band, nm; one image must have this wavelength (±0.5 nm).
    wavelengths : mapping of str to float, optional
        Band wavelength (nm) per illumination name (e.g. effective wavelengths); images
        whose illumination it lacks, or all when it is None, use their ``wavelength_nm``.
    max_shift_px : float, optional
        Largest displacement paired, px (default: a quarter of the median disk spacing).
    workers : int, optional
        Processes for the disk fits (default: the CPUs available); 1 fits in this
        process.

    Returns
    -------
    DispersionKeypoints
        ``source="disks"``; reference positions, displacements (band − reference) and
        band wavelengths, including the reference band's own disks with zero
        displacement; ``quality`` is the larger relative fit residual of the two disks.
        ``meta["bands"][str(wavelength)]`` records per band the file, disks fitted,
        disks paired, outliers rejected and the reasons fits were rejected.

    Raises
    ------
    DataError
        Images disagree in size or CFA, a band has no wavelength, two images share a
        band, no image is the reference band, or a band shows no disks or pairs fewer
        than 10 disks with the reference.
    """
    _check_images(images)
    n_workers = worker_count(workers)
    bands = [_band_wavelength(image, wavelengths) for image in images]
    order = np.argsort(bands, kind="stable")
    images = [images[i] for i in order]
    bands = [bands[i] for i in order]
    ref_i = _reference_band(images, bands, reference_nm)
    if max_shift_px is not None and not max_shift_px > 0:
        raise DataError(f"max_shift_px must be > 0 px, got {max_shift_px}")
    shape = images[0].raw.shape
    with maybe_pool(n_workers) as pool:
        # detection of the next image overlaps the fits of the previous ones
        pending = [
            _start_image(image, f"band {w:g} nm ({source_of(image)})", pool, n_workers)
            for image, w in zip(images, bands, strict=True)
        ]
        fits = [DiskFit(**finish(p)) for p in pending]
    ref_fit = fits[ref_i]
    ref_xy = ref_fit.centres
    limit = 0.25 * _median_spacing(ref_xy) if max_shift_px is None else float(max_shift_px)
    parts: list[tuple[np.ndarray, ...]] = []
    meta_bands: dict[str, dict[str, Any]] = {}
    for i, (image, w, fit) in enumerate(zip(images, bands, fits, strict=True)):
        info: dict[str, Any] = {
            "file": source_of(image),
            "disks": len(fit),
            "rejected": dict(fit.rejected),
        }
        meta_bands[str(w)] = info
        if i == ref_i:
            info.update(paired=len(fit), outliers=0, reference=True)
            zeros = np.zeros(len(fit))
            parts.append((ref_xy, zeros, zeros, np.full(len(fit), w), fit.residual))
            continue
        ri, d, quality = _paired(
            ref_fit,
            fit,
            limit,
            info,
            f"band {w:g} nm ({source_of(image)})",
            f"band {bands[ref_i]:g} nm",
        )
        parts.append((ref_xy[ri], d[:, 0], d[:, 1], np.full(ri.size, w), quality))
    xy = np.concatenate([p[0] for p in parts])
    return DispersionKeypoints(
        xy[:, 0],
        xy[:, 1],
        np.concatenate([p[1] for p in parts]),
        np.concatenate([p[2] for p in parts]),
        reference=float(bands[ref_i]),
        image_shape=shape,
        wavelength_nm=np.concatenate([p[3] for p in parts]),
        source="disks",
        quality=np.concatenate([p[4] for p in parts]),
        meta={
            "method": "disks",
            "reference_nm": float(bands[ref_i]),
            "reference_file": source_of(images[ref_i]),
            "max_shift_px": limit,
            "bands": meta_bands,
        },
    )


def _reference_band(images: list[RawImage], bands: list[float], reference_nm: float) -> int:
    """Index of the reference band among `bands` (sorted); an error for two images of one
    band or none of the reference band."""
    for a, b, image in zip(bands[:-1], bands[1:], images[1:], strict=True):
        if abs(a - b) < _WAVELENGTH_TOLERANCE_NM:
            raise DataError(
                f"two images are of band {b:g} nm (one is {source_of(image)}); "
                "give one image per filter band"
            )
    near = [i for i, w in enumerate(bands) if abs(w - reference_nm) <= _WAVELENGTH_TOLERANCE_NM]
    if not near:
        raise DataError(
            f"no image is of the reference band {reference_nm:g} nm; the bands are "
            f"{', '.join(f'{w:g}' for w in bands)} nm; choose one of them as the reference"
        )
    return near[0]


def _paired(
    ref_fit: DiskFit, fit: DiskFit, limit: float, info: dict[str, Any], name: str, reference: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reference disks paired with `fit`'s within `limit` px, outliers left out: their
    indices, displacements (band − reference) and qualities; `info` records the counts."""
    ref_xy = ref_fit.centres
    ri, bi = pair_mutual_nearest(ref_xy, fit.centres, max_distance_px=limit)
    d = fit.centres[bi] - ref_xy[ri]
    outliers = displacement_outliers(ref_xy[ri], d)
    keep = ~outliers
    info.update(paired=int(ri.size), outliers=int(outliers.sum()))
    if int(keep.sum()) < _MIN_PAIRED:
        raise DataError(
            f"{name}: only {int(keep.sum())} of its {len(fit)} disks pair with the "
            f"{len(ref_fit)} disks of the reference {reference} within {limit:.3g} px "
            f"(need ≥ {_MIN_PAIRED}); check that both images show the same view of the "
            "pattern, or raise max_shift_px"
        )
    ri, bi, d = ri[keep], bi[keep], d[keep]
    return ri, d, np.maximum(ref_fit.residual[ri], fit.residual[bi])


@fixed_blas_threads
def channel_disk_keypoints(image: RawImage, *, workers: int | None = None) -> DispersionKeypoints:
    """Colour-channel keypoints (R and B relative to G) from one unfiltered disk image.

    Parameters
    ----------
    image : RawImage
        An image of the disk pattern under unfiltered (broadband) light.
    workers : int, optional
        Processes for the disk fits (default: the CPUs available); 1 fits in this
        process.

    Returns
    -------
    DispersionKeypoints
        Channels ``"R"`` and ``"B"`` with ``reference="G"``: positions are the Green
        channel's disk centres, displacements the channel's centre minus the Green one.
        ``meta["channels"]`` records per channel the disks paired and outliers rejected.

    Raises
    ------
    DataError
        The image shows no disks, or fewer than 10 disks survive in a channel.
    """
    where = f"{image.illumination} image ({source_of(image)})"
    n_workers = worker_count(workers)
    with maybe_pool(n_workers) as pool:
        fit = DiskFit(**finish(_start_image(image, where, pool, n_workers, per_channel=True)))
    green = fit.channel_centres[:, 1]
    parts = []
    channels_meta: dict[str, dict[str, int]] = {}
    for c, label in ((0, "R"), (2, "B")):
        d = fit.channel_centres[:, c] - green
        outliers = displacement_outliers(green, d)
        keep = ~outliers
        channels_meta[label] = {"paired": len(fit), "outliers": int(outliers.sum())}
        if int(keep.sum()) < _MIN_PAIRED:
            raise DataError(
                f"{where}: only {int(keep.sum())} disks give consistent {label}−G "
                f"displacements (need ≥ {_MIN_PAIRED}); use a sharper, better exposed "
                "image of the disk pattern"
            )
        parts.append((green[keep], d[keep], np.full(int(keep.sum()), label), fit.residual[keep]))
    xy = np.concatenate([p[0] for p in parts])
    d = np.concatenate([p[1] for p in parts])
    return DispersionKeypoints(
        xy[:, 0],
        xy[:, 1],
        d[:, 0],
        d[:, 1],
        reference="G",
        image_shape=image.raw.shape,
        channel=np.concatenate([p[2] for p in parts]),
        source="disks",
        quality=np.concatenate([p[3] for p in parts]),
        meta={
            "method": "disks",
            "file": source_of(image),
            "disks": len(fit),
            "rejected": dict(fit.rejected),
            "channels": channels_meta,
        },
    )


def _median_spacing(xy: np.ndarray) -> float:
    """Median distance from each point to its nearest neighbour, px."""
    if len(xy) < 2:
        return float("inf")
    dist, _ = cKDTree(xy).query(xy, k=2)
    return float(np.median(dist[:, 1]))
