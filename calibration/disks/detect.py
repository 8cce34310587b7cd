"""Disk detection (the first step of :mod:`calibration.disks`): candidate disks from Otsu
thresholds of the raw mosaic, and the background mask of a disk image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from calibration.disks._raw import channel_noise, checked_raw
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import channel_index, check_layout
from labkit.errors import DataError

#: Otsu's effectiveness (between-class / total variance) a channel needs to count as
#: bimodal; a split Gaussian (pure noise) scores 2/π ≈ 0.64, the disk pattern > 0.9 (0.77
#: for radius-4 disks under a blur of σ = 1.5 px).
_MIN_EFFECTIVENESS = 0.7
#: Separation of Otsu's class means a channel needs, in units of its pixel noise.
_MIN_CONTRAST_NOISE = 6.0
#: Least ellipticity (intersection over union with the moment ellipse) of a disk region.
_MIN_ELLIPSE_IOU = 0.7
#: Areas within max(2 robust sigma, this fraction of the median area) of the median pass.
_AREA_TOLERANCE = 0.4
#: Fewest disks an image of the pattern must show.
_MIN_DISKS = 4
#: Least share of the dark area (away from the border) that disk-like regions must cover.
_MIN_DISK_SHARE = 0.5
#: Width of a disk's edge as it appears in the image (pixel footprint included), px, where
#: it is not measured: the margin :func:`background_mask` keeps beyond detected disks, and
#: the width the fits of disk keypoints start from.
EDGE_WIDTH_PX = 1.5


@dataclass(frozen=True)
class DiskCandidates:
    """Disks detected in a raw mosaic (thesis §3.2.1, first paragraph of the method).

    Attributes
    ----------
    centres : ndarray (n, 2) float64
        Region centroids as (x, y), px.
    axes : ndarray (n, 2) float64
        Semi-major and semi-minor axes of the ellipse with the region's second moments, px.
    angle_rad : ndarray (n,) float64
        Orientation of the major axis, rad, from the image x-axis towards the y-axis
        (rows, i.e. clockwise on screen), in (−π/2, π/2].
    bbox : ndarray (n, 4) int64
        Bounding boxes ``row0, col0, row1, col1`` (row1, col1 exclusive).
    area_px : ndarray (n,) float64
        Region areas, px.
    labels : ndarray (rows, cols) int32
        Label image of the kept disks: candidate ``k`` is label ``k + 1``; 0 = background.
    """

    centres: np.ndarray
    axes: np.ndarray
    angle_rad: np.ndarray
    bbox: np.ndarray
    area_px: np.ndarray
    labels: np.ndarray

    def __len__(self) -> int:
        return int(self.centres.shape[0])


def _otsu_split(values: np.ndarray, noise: float) -> tuple[float, bool]:
    """Otsu threshold of `values` and whether they are bimodal enough to use."""
    from skimage.filters import threshold_otsu

    if values.size < 16 or float(values.max()) <= float(values.min()):
        return float(values.min()) if values.size else 0.0, False
    threshold = float(threshold_otsu(values))
    low = values < threshold
    n_low = int(np.count_nonzero(low))
    if n_low == 0 or n_low == values.size:
        return threshold, False
    w0 = n_low / values.size
    m0 = float(values[low].mean())
    m1 = float(values[~low].mean())
    total = float(values.var())
    effectiveness = w0 * (1.0 - w0) * (m1 - m0) ** 2 / total if total > 0 else 0.0
    usable = (
        effectiveness >= _MIN_EFFECTIVENESS
        and (m1 - m0) >= _MIN_CONTRAST_NOISE * noise
        and min(w0, 1.0 - w0) >= 1e-3
    )
    return threshold, usable


def _dark_mask(raw: np.ndarray, cfa: str) -> tuple[np.ndarray, np.ndarray]:
    """Fused per-channel Otsu decision "dark" (rows, cols) and the channels used (3,) bool."""
    from skimage.morphology import closing, disk, opening

    index = channel_index(cfa, raw.shape)
    noise = channel_noise(raw, index)
    thresholds = np.zeros(3)
    usable = np.zeros(3, dtype=bool)
    for channel in range(3):
        values = raw[index == channel]
        thresholds[channel], usable[channel] = _otsu_split(values, noise[channel])
    if not usable.any():
        return np.zeros(raw.shape, dtype=bool), usable
    valid = usable[index]
    dark = (raw < thresholds[index]) & valid
    if not valid.all():
        # pixels of ignored channels take the majority vote of their usable 3×3 neighbours
        votes = ndimage.uniform_filter(dark.astype(np.float32), 3, mode="nearest")
        voters = ndimage.uniform_filter(valid.astype(np.float32), 3, mode="nearest")
        dark = np.where(valid, dark, votes > 0.5 * voters)
    footprint = disk(1)
    dark = closing(opening(dark, footprint), footprint)
    return dark, usable


def _no_disks(name: str, why: str) -> DataError:
    return DataError(
        f"no calibration disks found in {name}; is this an image of the disk pattern? "
        f"({why}). Check that the pattern fills the view, is in focus and well exposed "
        "(paper well above black, not saturated)"
    )


@fixed_blas_threads
def detect_disks(
    raw: np.ndarray, *, cfa: str, name: str = "image", min_area_px: float = 12.0
) -> DiskCandidates:
    """Find the dark disks of the calibration pattern in a raw mosaic.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic, linear (dark disks on bright paper).
    cfa : str
        CFA layout, e.g. ``"GBRG"``.
    name : str
        What the image is (file or illumination), for error messages.
    min_area_px : float
        Components smaller than this (px) are noise, not disks.

    Returns
    -------
    DiskCandidates
        The kept disks with initial ellipses from their second moments.

    Raises
    ------
    DataError
        The image is malformed or does not show the disk pattern: no colour channel has
        bimodal contrast, fewer than 4 disk-like regions, or disk-like regions cover
        less than half of the dark area inside the view (e.g. a ColorChecker or text).

    Notes
    -----
    Otsu thresholds are computed per colour channel; channels without bimodal contrast
    (Otsu's effectiveness below 0.7 or class means closer than 6 noise sigmas, e.g. the
    Red channel under 450 nm light) are ignored and their pixels take the majority
    decision of their 3×3 neighbours. After opening and closing with a 3×3 cross,
    components touching the image border, smaller than `min_area_px` or not elliptical
    (intersection over union with their moment ellipse below 0.7) are dropped, and so are
    components whose area is far from the median: the thesis keeps areas within two
    standard deviations of the mean; here the spread is robust (median absolute
    deviation) and at least 40 % of the median area, so that vignetting and blur (which
    change the thresholded area of small disks by ±20 %) or a few huge blobs do not
    remove real disks.
    """
    from skimage.measure import label, regionprops_table

    layout = check_layout(cfa)
    raw = checked_raw(raw, name)
    dark, usable = _dark_mask(raw, layout)
    if not usable.any():
        raise _no_disks(name, "no colour channel separates into dark and bright pixels")
    labels = label(dark, connectivity=1).astype(np.int32)
    if labels.max() == 0:
        raise _no_disks(name, "no dark regions")
    props = regionprops_table(labels, properties=("area", "bbox"))
    area = np.asarray(props["area"], dtype=np.float64)
    bbox = np.column_stack([props[f"bbox-{i}"] for i in range(4)]).astype(np.int64)
    centre, cov, iou = _region_moments(labels, bbox)
    rows, cols = raw.shape
    inside = (bbox[:, 0] > 0) & (bbox[:, 1] > 0) & (bbox[:, 2] < rows) & (bbox[:, 3] < cols)
    keep = inside & (area >= min_area_px) & (iou >= _MIN_ELLIPSE_IOU)
    if not keep.any():
        raise _no_disks(name, f"no round dark region of ≥ {min_area_px:g} px inside the view")
    median = float(np.median(area[keep]))
    spread = 1.4826 * float(np.median(np.abs(area[keep] - median)))
    keep &= np.abs(area - median) <= max(2.0 * spread, _AREA_TOLERANCE * median)
    disk_share = float(area[keep].sum() / area[inside].sum())
    if disk_share < _MIN_DISK_SHARE:
        raise _no_disks(
            name,
            f"only {disk_share:.0%} of the dark area inside the view is in disk-like regions",
        )
    sel = np.flatnonzero(keep)
    if sel.size < _MIN_DISKS:
        raise _no_disks(
            name, f"only {sel.size} disk-like region(s) inside the view; need ≥ {_MIN_DISKS}"
        )
    cxx, cyy, cxy = cov[sel, 0], cov[sel, 1], cov[sel, 2]
    half_trace = 0.5 * (cxx + cyy)
    root = np.sqrt(0.25 * (cxx - cyy) ** 2 + cxy**2)
    # a uniform ellipse with semi-axis a has variance a²/4 along it
    major = 2.0 * np.sqrt(np.maximum(half_trace + root, 0.0))
    minor = 2.0 * np.sqrt(np.maximum(half_trace - root, 0.0))
    lut = np.zeros(area.size + 1, dtype=np.int32)
    lut[sel + 1] = np.arange(1, sel.size + 1, dtype=np.int32)
    return DiskCandidates(
        centres=centre[sel],
        axes=np.column_stack([major, minor]),
        angle_rad=0.5 * np.arctan2(2.0 * cxy, cxx - cyy),
        bbox=bbox[sel],
        area_px=area[sel],
        labels=lut[labels],
    )


def _region_moments(
    labels: np.ndarray, bbox: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroids (n, 2), covariances (n, 3: cxx, cyy, cxy) and ellipticity (n,) of regions.

    `labels` holds regions 1…n (consecutive) with bounding boxes `bbox` (n, 4). The
    ellipticity is the intersection over union of a region's pixels and its moment ellipse
    (a uniform ellipse with semi-axis a has variance a²/4 along it): ≈ 1 for a disk or
    ellipse, 0.83 for a square, less for ragged or merged shapes.
    """
    n = bbox.shape[0]
    ys, xs = np.nonzero(labels)
    region = labels[ys, xs].astype(np.intp) - 1
    xs = xs - bbox[region, 1].astype(np.float64)  # local coordinates: no cancellation
    ys = ys - bbox[region, 0].astype(np.float64)
    count = np.maximum(np.bincount(region, minlength=n), 1).astype(np.float64)

    def mean_of(values: np.ndarray) -> np.ndarray:
        return np.bincount(region, weights=values, minlength=n) / count

    mx, my = mean_of(xs), mean_of(ys)
    cxx = mean_of(xs * xs) - mx * mx
    cyy = mean_of(ys * ys) - my * my
    cxy = mean_of(xs * ys) - mx * my
    det = np.maximum(cxx * cyy - cxy * cxy, 1e-12)
    ux, uy = xs - mx[region], ys - my[region]
    rho2 = cyy[region] * ux * ux - 2.0 * cxy[region] * ux * uy + cxx[region] * uy * uy
    overlap = np.bincount(region, weights=rho2 <= 4.0 * det[region], minlength=n)
    ellipse_area = 4.0 * np.pi * np.sqrt(det)
    iou = overlap / (count + ellipse_area - overlap)
    centre = np.column_stack([mx + bbox[:, 1], my + bbox[:, 0]])
    return centre, np.column_stack([cxx, cyy, cxy]), iou


def background_mask(
    raw: np.ndarray,
    *,
    cfa: str,
    candidates: DiskCandidates | None = None,
    margin_px: float = 3.0,
) -> np.ndarray:
    """Paper pixels well away from every disk, for fitting vignetting (thesis §3.2.2).

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic of the disk pattern.
    cfa : str
        CFA layout.
    candidates : DiskCandidates, optional
        Disks detected in `raw` (default: :func:`detect_disks`). Their regions are
        excluded together with every dark pixel of the fused Otsu mask, which also covers
        disks cut by the image border.
    margin_px : float
        Distance kept from any disk beyond the assumed 1.5 px edge width, px.

    Returns
    -------
    ndarray (rows, cols) bool
        True on paper at least ``margin_px + 1.5`` px from every dark pixel.

    Raises
    ------
    DataError
        `raw` does not show the disk pattern (detection fails: callers may then fit
        vignetting to the whole image instead).
    """
    layout = check_layout(cfa)
    raw = checked_raw(raw, "image")
    if not margin_px >= 0:
        raise DataError(f"margin_px must be ≥ 0, got {margin_px}")
    if candidates is None:
        candidates = detect_disks(raw, cfa=layout)
    elif candidates.labels.shape != raw.shape:
        raise DataError(
            f"disk candidates are of a {candidates.labels.shape} image but the raw "
            f"mosaic is {raw.shape}; detect them in this image"
        )
    dark, _ = _dark_mask(raw, layout)
    dark |= candidates.labels > 0
    distance = ndimage.distance_transform_edt(~dark)
    return distance > margin_px + EDGE_WIDTH_PX
