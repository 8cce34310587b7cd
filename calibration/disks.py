"""Disk keypoints: sub-pixel centres of calibration disks and their displacements (§3.2.1).

The calibration pattern is black toner disks on white paper. Following Rudakova and
Monasse (thesis [99]) keypoints are found in two steps:

1. **Detection** (:func:`detect_disks`): Otsu thresholds per colour channel of the raw
   mosaic, fused into one full-resolution "dark" mask, morphological opening and
   closing, connected components, and a filter on their area. Each component gives an
   initial ellipse from its second moments.
2. **Refinement** (:func:`fit_disks`): Levenberg–Marquardt fit of a synthetic disk to the
   raw pixels around each component. The model (thesis §3.2.1) has an interior and an
   exterior lightness per colour channel, an ellipse (semi-axes, orientation, centre)
   and a linear edge of width ``w``: at signed distance ``s`` from the ellipse the
   scene is ::

       exterior + (interior − exterior) · clip(0.5 − s / w, 0, 1)

   ``s`` is measured along the ray from the ellipse's centre (exact for circles, first
   order for ellipses). Two refinements of the thesis' model: each pixel *integrates*
   that profile over its unit square (for a locally straight edge this is a
   convolution with the square's projection on the edge normal, so the value is
   ``1 − F(s)`` with ``F`` the CDF of a sum of three uniform variables, a piecewise
   cubic — evaluating the ramp at pixel centres instead biases centres seen by one
   colour channel's 2-px lattice by up to 0.025 px); and the whole disk is multiplied by
   a local illumination gradient ``G = 1 + gx·x + gy·y``, which absorbs vignetting and
   uneven light (thesis §3.2.2 notes that these violate the uniform-lightness
   assumption) without a separate correction pass.

Disk centres of bandpass-filtered images are paired with those of the reference band by
mutual nearest neighbours (:func:`disk_keypoints`), giving a sparse map of spectral
dispersion; fitting each colour channel of an unfiltered image separately gives the
lateral chromatic aberration between colour channels (:func:`channel_disk_keypoints`).
Displacements that disagree with their neighbours are rejected as outliers.

Conventions: x = column, y = row, pixel centres at integer coordinates, origin top-left;
all positions and lengths in pixels.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from calibration._hdr_inputs import source_of
from calibration.keypoints import DispersionKeypoints
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import CHANNELS, channel_index, check_layout
from labkit.errors import DataError
from labkit.io.exr import RawImage

__all__ = [
    "DiskCandidates",
    "DiskFit",
    "background_mask",
    "channel_disk_keypoints",
    "detect_disks",
    "disk_keypoints",
    "fit_disks",
    "pair_mutual_nearest",
]

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
#: Disks with a relative contrast (exterior − interior) / exterior below this are dropped.
_MIN_RELATIVE_CONTRAST = 0.25
#: Levenberg–Marquardt tolerances (relative change of parameters / of the cost).
_XTOL = 1e-6
_FTOL = 1e-8
#: Contrast-to-noise ratio above which a channel counts as noise-free in joint fits.
_CLEAN_SNR = 50.0
#: Fewest disks a band must pair with the reference.
_MIN_PAIRED = 10
#: Neighbours whose median displacement a keypoint is compared with.
_OUTLIER_NEIGHBOURS = 8
#: Outlier threshold: max(_OUTLIER_FLOOR_PX, _OUTLIER_SIGMAS × robust sigma).
_OUTLIER_FLOOR_PX = 0.3
_OUTLIER_SIGMAS = 5.0
#: Tolerance when matching band wavelengths with the reference, nm.
_WAVELENGTH_TOLERANCE_NM = 0.5
#: Default edge width assumed around detected disks by :func:`background_mask`, px.
_EDGE_WIDTH_PX = 1.5
#: Geometry parameters of the disk model before the lightnesses.
_N_GEOMETRY = 8


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


@dataclass(frozen=True)
class DiskFit:
    """Disks refined by fitting the synthetic disk model.

    Attributes
    ----------
    centres : ndarray (n, 2) float64
        Ellipse centres (x, y), px; for per-channel fits, the Green channel's centres.
    channel_centres : ndarray (n, 3, 2) float64 or None
        Per-channel fits: the R, G and B centres (x, y), px; None for joint fits.
    axes : ndarray (n, 2) float64
        Semi-major and semi-minor axes, px (per-channel fits: Green).
    angle_rad : ndarray (n,) float64
        Orientation of the major axis from the x-axis towards the y-axis, rad.
    edge_width_px : ndarray (n,) float64
        Width of the linear edge ramp of the scene (blur), px, not counting the pixel's
        own footprint (≈ 1 px), which the model integrates over; about 0.02 px (the
        floor) for perfectly sharp disks. Per-channel fits: Green.
    residual : ndarray (n,) float64
        RMS fit residual divided by the disk's contrast (dimensionless); per-channel
        fits: the largest over the channels.
    candidate : ndarray (n,) int64
        Index of the :class:`DiskCandidates` entry each fit started from.
    rejected : dict of str to int
        Disks dropped, by reason.
    """

    centres: np.ndarray
    channel_centres: np.ndarray | None
    axes: np.ndarray
    angle_rad: np.ndarray
    edge_width_px: np.ndarray
    residual: np.ndarray
    candidate: np.ndarray
    rejected: dict[str, int]

    def __len__(self) -> int:
        return int(self.centres.shape[0])


# -- detection ------------------------------------------------------------------------


def _checked_raw(raw: np.ndarray, name: str) -> np.ndarray:
    """`raw` as a finite 2-D float array, or DataError naming the image."""
    array = np.asarray(raw)
    if array.ndim != 2 or min(array.shape) < 8:
        raise DataError(
            f"{name}: a raw mosaic must be a 2-D array of at least 8×8 pixels, "
            f"got shape {array.shape}"
        )
    if array.dtype.kind not in "fiu":
        raise DataError(f"{name}: raw pixels must be numbers, got dtype {array.dtype}")
    if array.dtype.kind != "f":
        array = array.astype(np.float32)
    bad = np.size(array) - int(np.count_nonzero(np.isfinite(array)))
    if bad:
        raise DataError(
            f"{name}: {bad} raw pixels are NaN or Inf; replace or mask them (e.g. re-merge "
            "the HDR image) before locating disks"
        )
    return array


def _channel_noise(raw: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Robust pixel-noise sigma of each colour channel, (3,), raw units.

    From differences of horizontally adjacent pixels of the same channel (2 px apart):
    1.4826 × median |difference| / √2, on at most about 200 000 differences per channel.
    """
    diffs: list[list[np.ndarray]] = [[], [], []]
    for i in range(2):
        for j in range(2):
            plane = raw[i::2, j::2]
            if plane.shape[1] < 2:
                continue
            step = max(1, int(plane.size // 100_000))
            diffs[int(index[i, j])].append(np.diff(plane[::step], axis=1).ravel())
    sigma = np.zeros(3)
    for channel, parts in enumerate(diffs):
        if parts:
            d = np.abs(np.concatenate(parts))
            sigma[channel] = 1.4826 * float(np.median(d)) / np.sqrt(2.0)
    return sigma


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
    noise = _channel_noise(raw, index)
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
    raw = _checked_raw(raw, name)
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


# -- the disk model ---------------------------------------------------------------------


class _Task(NamedTuple):
    """One disk to refine: its neighbourhood and initial ellipse."""

    candidate: int
    values: np.ndarray  # (npix,) float64 raw values
    x: np.ndarray  # (npix,) float64 pixel x relative to the initial centre, px
    y: np.ndarray  # (npix,) float64
    channel: np.ndarray  # (npix,) uint8 colour channel of each pixel
    centre: tuple[float, float]  # initial centre (x, y), px
    q0: tuple[float, float, float]  # initial quadratic form · r0² (qxx, qxy, qyy)
    r0: float  # initial mean radius, px
    s0: np.ndarray  # (npix,) initial signed distance, px


class _Outcome(NamedTuple):
    """Result of refining one disk (one row per fitted channel group)."""

    candidate: int
    reason: str  # "" when accepted
    centres: np.ndarray  # (g, 2) x, y px
    quadratic: np.ndarray  # (g, 3) qxx, qxy, qyy in 1/px²
    edge_width: np.ndarray  # (g,)
    residual: np.ndarray  # (g,)


#: Sign patterns of the 8 corner terms of the CDF of a sum of three uniforms.
_SIGNS = np.array([[e1, e2, e3] for e1 in (1.0, -1.0) for e2 in (1.0, -1.0) for e3 in (1.0, -1.0)])
_PARITY = _SIGNS.prod(axis=1)
#: Σ σ z³ and Σ σ z², Σ σ ε_i z² as matrix products with the (n, 8) corner terms.
_CUBE_WEIGHTS = _PARITY / 6.0
_SQUARE_WEIGHTS = np.column_stack(
    [_PARITY / 2.0, *(_PARITY * _SIGNS[:, i] / 4.0 for i in range(3))]
)
#: Smallest footprint widths (px): keeps the CDF formula well conditioned.
_MIN_FOOTPRINT = 0.02
_MIN_EDGE = 0.02


class _DiskModel:
    """Synthetic disk integrated over pixel areas, with an analytic Jacobian.

    Parameters (vector p): ux, uy (centre offset from the initial centre, px), qa, qb, qc
    (quadratic form of the ellipse times r0², so ≈ 1 for a circle of radius r0), v
    (edge ramp width w = √(0.02² + max(v, 0)), px — parametrised by its square, which
    converges in a few steps where the ramp is sharper than the pixel footprint), gx, gy
    (illumination gradient per r0), then the interior and the exterior lightness of each
    of the `m` lightness groups.

    Across the edge, at signed distance s, the scene falls linearly from exterior to
    interior over the width w (the thesis' linear edge). A pixel integrates the scene
    over its unit square; for a locally straight edge with unit normal (nx, ny) that is
    a convolution with uniform kernels of widths |nx| and |ny|, so the fraction of the
    pixel inside the disk is 1 − F(s), with F the CDF of the sum of three centred
    uniform variables of widths |nx|, |ny| and w (a piecewise cubic in s). The radial
    direction stands in for the normal (they agree for circles).
    """

    def __init__(
        self,
        x: np.ndarray,
        y: np.ndarray,
        group: np.ndarray,
        m: int,
        r0: float,
        weight: np.ndarray | None = None,
    ) -> None:
        self.x = x
        self.y = y
        self.group = group
        self.m = m
        self.r0 = r0
        self.inv_r02 = 1.0 / (r0 * r0)
        self.onehot = (group[:, None] == np.arange(m)[None, :]).astype(np.float64)
        self.xr = x / r0
        self.yr = y / r0
        self.weight = weight
        self._p: np.ndarray | None = None

    def _evaluate(self, p: np.ndarray) -> None:
        if self._p is not None and np.array_equal(p, self._p):
            return
        m = self.m
        ux, uy, qa, qb, qc, w2, gx, gy = p[:_N_GEOMETRY]
        inner = p[_N_GEOMETRY : _N_GEOMETRY + m]
        outer = p[_N_GEOMETRY + m :]
        dx = self.x - ux
        dy = self.y - uy
        r = np.maximum(np.hypot(dx, dy), 1e-9)
        ex = dx / r
        ey = dy / r
        qx = (qa * ex + qb * ey) * self.inv_r02  # Q ĉ, 1/px²
        qy = (qb * ex + qc * ey) * self.inv_r02
        big_r = 1.0 / np.sqrt(np.maximum(ex * qx + ey * qy, 1e-12))  # radius along ĉ, px
        s = r - big_r
        a1 = np.maximum(np.abs(ex), _MIN_FOOTPRINT)
        a2 = np.maximum(np.abs(ey), _MIN_FOOTPRINT)
        w = float(np.sqrt(_MIN_EDGE**2 + max(w2, 0.0)))
        half = 0.5 * (a1 + a2 + w)
        band = np.abs(s) < half
        z = s[:, None] + 0.5 * (a1[:, None] * _SIGNS[:, 0] + a2[:, None] * _SIGNS[:, 1])
        z += 0.5 * w * _SIGNS[:, 2]
        np.maximum(z, 0.0, out=z)
        z2 = z * z
        inv = 1.0 / (a1 * a2 * w)
        cdf = np.where(band, (z2 * z) @ _CUBE_WEIGHTS * inv, (s > 0).astype(np.float64))
        h = 1.0 - np.clip(cdf, 0.0, 1.0)
        if m == 1:
            i_px = np.full(r.size, inner[0])
            e_px = np.full(r.size, outer[0])
        else:
            i_px = inner[self.group]
            e_px = outer[self.group]
        contrast = i_px - e_px
        base = e_px + contrast * h
        gain = 1.0 + gx * self.xr + gy * self.yr
        self._p = p.copy()
        self._cache = (r, ex, ey, qx, qy, big_r, a1, a2, w, band, z2, inv, cdf, h, contrast, base)
        self._gain = gain
        model = gain * base
        self.model = model if self.weight is None else model * self.weight

    def residuals(self, p: np.ndarray, values: np.ndarray) -> np.ndarray:
        self._evaluate(p)
        return self.model - values

    def jacobian(self, p: np.ndarray, values: np.ndarray) -> np.ndarray:
        self._evaluate(p)
        r, ex, ey, qx, qy, big_r, a1, a2, w, band, z2, inv, cdf, h, contrast, base = self._cache
        gain = self._gain
        jac = np.empty((r.size, _N_GEOMETRY + 2 * self.m))
        sums = (z2 @ _SQUARE_WEIGHTS) * inv[:, None]  # ∂F/∂s and Σ σ ε_i z² / (4 a1 a2 w)
        # f = gain (e + contrast (1 − F)); dF/d(param) enters with −gain·contrast
        df = np.where(band, -gain * contrast, 0.0)
        df_ds = df * sums[:, 0]
        df_da1 = np.where(np.abs(ex) > _MIN_FOOTPRINT, df * (sums[:, 1] - cdf / a1), 0.0)
        df_da2 = np.where(np.abs(ey) > _MIN_FOOTPRINT, df * (sums[:, 2] - cdf / a2), 0.0)
        df_dw = df * (sums[:, 3] - cdf / w)
        r3 = big_r**3
        # ∇_d s = ĉ − (R ĉ − R³ Q ĉ) / r ; moving the centre by +u moves d by −u
        grad_x = ex - (big_r * ex - r3 * qx) / r
        grad_y = ey - (big_r * ey - r3 * qy) / r
        # footprints |ex|, |ey| of the radial direction ĉ = d / r
        sx = np.sign(ex) * df_da1 / r
        sy = np.sign(ey) * df_da2 / r
        exy = ex * ey
        jac[:, 0] = -df_ds * grad_x - sx * ey * ey + sy * exy
        jac[:, 1] = -df_ds * grad_y + sx * exy - sy * ex * ex
        half = 0.5 * r3 * self.inv_r02 * df_ds
        jac[:, 2] = half * ex * ex
        jac[:, 3] = 2.0 * half * exy
        jac[:, 4] = half * ey * ey
        jac[:, 5] = df_dw * (0.5 / w) if p[5] > 0 else 0.0
        jac[:, 6] = base * self.xr
        jac[:, 7] = base * self.yr
        m = self.m
        jac[:, _N_GEOMETRY : _N_GEOMETRY + m] = (gain * h)[:, None] * self.onehot
        jac[:, _N_GEOMETRY + m :] = (gain * (1.0 - h))[:, None] * self.onehot
        if self.weight is not None:
            jac *= self.weight[:, None]
        return jac


class _Options(NamedTuple):
    """Settings shared by all disk fits of one image."""

    per_channel: bool
    edge_width: float  # initial edge width, px
    noise: tuple[float, float, float]  # pixel noise sigma of R, G, B, raw units


def _fit_group(
    task: _Task, pick: np.ndarray | None, group: np.ndarray, m: int, options: _Options
) -> tuple[str, np.ndarray, np.ndarray, float, float]:
    """Fit the disk model to the pixels `pick` of a task (None = all).

    `group` gives each picked pixel's lightness group (its colour channel for joint fits,
    0 for single-channel fits). Returns (reason, centre (2,), quadratic form (3,) 1/px²,
    edge width px, relative residual); reason is "" for an accepted fit.
    """
    values = task.values if pick is None else task.values[pick]
    x = task.x if pick is None else task.x[pick]
    y = task.y if pick is None else task.y[pick]
    s0 = task.s0 if pick is None else task.s0[pick]
    channel = task.channel if pick is None else task.channel[pick]
    failed = np.full(2, np.nan), np.full(3, np.nan), np.nan, np.nan
    inner = np.zeros(m)
    outer = np.zeros(m)
    noise = np.zeros(m)
    for g in range(m):
        mine = group == g
        inside = mine & (s0 < -1.5)
        outside = mine & (s0 > 1.5)
        if not inside.any() or not outside.any():
            return ("too few pixels", *failed)
        inner[g] = np.median(values[inside])
        outer[g] = np.median(values[outside])
        noise[g] = options.noise[int(channel[np.argmax(mine)])]
    contrast = outer - inner
    main = int(np.argmax(contrast))
    scale = float(outer[main])
    if not scale > 0 or contrast[main] < _MIN_RELATIVE_CONTRAST * scale:
        return ("low contrast", *failed)
    data = values / scale
    weight = None
    if m > 1:
        # each channel counts by its contrast, or by its noise where that is the larger
        # (channels of a filtered image without signal then add noise, not bias)
        spread = np.maximum(np.abs(contrast), _CLEAN_SNR * noise)
        spread = np.maximum(spread, 1e-3 * contrast[main]) / scale
        weight = 1.0 / spread[group]
        data = data * weight
    model = _DiskModel(x, y, group, m, task.r0, weight)
    start_w = max(options.edge_width - 1.0, 0.25)  # less the pixel footprint (~1 px)
    p0 = np.concatenate([[0.0, 0.0, *task.q0, start_w**2, 0.0, 0.0], inner / scale, outer / scale])
    if data.size <= 2 * p0.size:
        return ("too few pixels", *failed)
    try:
        fit = least_squares(
            model.residuals,
            p0,
            jac=model.jacobian,
            method="lm",
            x_scale="jac",
            xtol=_XTOL,
            ftol=_FTOL,
            gtol=1e-10,
            max_nfev=200,
            args=(data,),
        )
    except (ValueError, np.linalg.LinAlgError):
        return ("not converged", *failed)
    p = fit.x
    if fit.status <= 0 or not np.all(np.isfinite(p)) or not np.all(np.isfinite(fit.fun)):
        return ("not converged", *failed)
    centre = np.array([task.centre[0] + p[0], task.centre[1] + p[1]])
    quad = np.array(p[2:5]) * model.inv_r02
    width = float(np.sqrt(_MIN_EDGE**2 + max(p[5], 0.0)))
    fitted_contrast = float(p[_N_GEOMETRY + m + main] - p[_N_GEOMETRY + main])
    misfit = fit.fun if weight is None else fit.fun / weight
    residual = float(np.sqrt(np.mean(misfit**2))) / max(abs(fitted_contrast), 1e-12)
    relative = fitted_contrast / max(float(p[_N_GEOMETRY + m + main]), 1e-12)
    reason = _checked_geometry(task, p, quad, width, relative)
    return reason, centre, quad, width, residual


def _checked_geometry(
    task: _Task, p: np.ndarray, quad: np.ndarray, width: float, contrast: float
) -> str:
    """Why a converged fit is implausible, or "" if it is fine."""
    if np.hypot(p[0], p[1]) > max(2.0, 0.3 * task.r0):
        return "moved too far"
    if quad[0] <= 0 or quad[0] * quad[2] - quad[1] ** 2 <= 0:
        return "implausible axes"
    semi, _ = _ellipse_from_quadratic(quad[None, :])
    major, minor = semi[0]
    if not (0.6 * task.r0 < minor <= major < 1.6 * task.r0) or major > 2.0 * minor:
        return "implausible axes"
    if width > 0.5 * task.r0:
        return "implausible edge width"
    if contrast < _MIN_RELATIVE_CONTRAST:
        return "low contrast"
    return ""


def _refine(task: _Task, options: _Options) -> _Outcome:
    """Refine one disk: jointly over all channels, or per channel (R, G, B)."""
    if not options.per_channel:
        groups = [(None, task.channel.astype(np.intp), 3)]
    else:
        groups = []
        for c in range(3):
            pick = np.flatnonzero(task.channel == c)
            groups.append((pick, np.zeros(pick.size, dtype=np.intp), 1))
    centres = np.full((len(groups), 2), np.nan)
    quads = np.full((len(groups), 3), np.nan)
    widths = np.full(len(groups), np.nan)
    residuals = np.full(len(groups), np.nan)
    for g, (pick, group, m) in enumerate(groups):
        reason, centres[g], quads[g], widths[g], residuals[g] = _fit_group(
            task, pick, group, m, options
        )
        if reason:
            if options.per_channel:
                reason = f"{reason} ({CHANNELS[g]})"
            return _Outcome(task.candidate, reason, centres, quads, widths, residuals)
    return _Outcome(task.candidate, "", centres, quads, widths, residuals)


@fixed_blas_threads
def _refine_chunk(tasks: list[_Task], options: _Options) -> list[_Outcome]:
    """Refine a chunk of disks (the unit of work of the process pool)."""
    return [_refine(task, options) for task in tasks]


def _quadratic_form(axes: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(n, 3) qxx, qxy, qyy of ellipses with semi-axes (n, 2) and major-axis angles (n,)."""
    c, s = np.cos(angle), np.sin(angle)
    ia = 1.0 / np.maximum(axes[:, 0], 1e-6) ** 2
    ib = 1.0 / np.maximum(axes[:, 1], 1e-6) ** 2
    return np.column_stack([ia * c * c + ib * s * s, (ia - ib) * c * s, ia * s * s + ib * c * c])


def _ellipse_from_quadratic(quad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Semi-axes (n, 2) (major, minor) and major-axis angles (n,) of quadratic forms (n, 3)."""
    a, b, c = quad[:, 0], quad[:, 1], quad[:, 2]
    half_trace = 0.5 * (a + c)
    root = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    small, large = half_trace - root, half_trace + root
    # the major axis is the eigenvector of the smaller eigenvalue
    angle = 0.5 * np.arctan2(-2.0 * b, c - a)
    return np.column_stack([1.0 / np.sqrt(small), 1.0 / np.sqrt(large)]), angle


def _make_tasks(
    raw: np.ndarray, index: np.ndarray, candidates: DiskCandidates, edge_width: float
) -> tuple[list[_Task], int]:
    """Neighbourhoods of the candidates; also the number that leave the image."""
    rows, cols = raw.shape
    quads = _quadratic_form(candidates.axes, candidates.angle_rad)
    r0s = np.sqrt(np.maximum(candidates.axes[:, 0] * candidates.axes[:, 1], 1.0))
    tasks: list[_Task] = []
    outside = 0
    for k in range(len(candidates)):
        r0 = float(r0s[k])
        margin = int(np.ceil(max(3.0, 0.5 * r0)))
        row0, col0, row1, col1 = (int(v) for v in candidates.bbox[k])
        row0, col0, row1, col1 = row0 - margin, col0 - margin, row1 + margin, col1 + margin
        if row0 < 0 or col0 < 0 or row1 > rows or col1 > cols:
            outside += 1
            continue
        cx, cy = (float(v) for v in candidates.centres[k])
        yy, xx = np.mgrid[row0:row1, col0:col1]
        dx = (xx - cx).ravel().astype(np.float64)
        dy = (yy - cy).ravel().astype(np.float64)
        q = quads[k]
        r = np.hypot(dx, dy)
        safe = np.maximum(r, 1e-9)
        ex, ey = dx / safe, dy / safe
        s0 = r - 1.0 / np.sqrt(
            np.maximum(q[0] * ex * ex + 2 * q[1] * ex * ey + q[2] * ey * ey, 1e-12)
        )
        # the ring around the initial edge holds all the information on the geometry
        band = max(3.0, 1.5 + edge_width)
        ring = np.flatnonzero(np.abs(s0) <= band)
        tasks.append(
            _Task(
                candidate=k,
                values=raw[row0:row1, col0:col1].ravel()[ring].astype(np.float64),
                x=dx[ring],
                y=dy[ring],
                channel=index[row0:row1, col0:col1].ravel()[ring],
                centre=(cx, cy),
                q0=tuple(float(v) * r0 * r0 for v in q),
                r0=r0,
                s0=s0[ring],
            )
        )
    return tasks, outside


def _submit(
    tasks: list[_Task], options: _Options, pool: Executor | None, workers: int
) -> list[Future | list[_Outcome]]:
    """Start refining `tasks`: 4 chunks per worker go to the pool, or all run here."""
    if pool is None or len(tasks) < 8:
        return [_refine_chunk(tasks, options)]
    n_chunks = min(len(tasks), 4 * workers)
    bounds = np.linspace(0, len(tasks), n_chunks + 1).astype(int)
    return [
        pool.submit(_refine_chunk, tasks[a:b], options)
        for a, b in itertools.pairwise(bounds)
        if b > a
    ]


def _workers(workers: int | None) -> int:
    """Worker count: `workers`, or the CPUs this process may run on."""
    if workers is None:
        try:
            return max(len(os.sched_getaffinity(0)), 1)
        except AttributeError:  # not on Linux
            return os.cpu_count() or 1
    if int(workers) < 1:
        raise DataError(f"workers must be ≥ 1, got {workers}")
    return int(workers)


@contextmanager
def _maybe_pool(workers: int) -> Iterator[Executor | None]:
    """A process pool for `workers` > 1, else None (fits run in this process)."""
    if workers <= 1:
        yield None
        return
    pool = ProcessPoolExecutor(max_workers=workers)
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


@fixed_blas_threads
def fit_disks(
    raw: np.ndarray,
    *,
    cfa: str,
    candidates: DiskCandidates | None = None,
    per_channel: bool = False,
    name: str = "image",
    edge_width_px: float = 1.5,
    workers: int | None = None,
) -> DiskFit:
    """Refine disk positions with Levenberg–Marquardt fits of a synthetic disk (§3.2.1).

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic, linear.
    cfa : str
        CFA layout.
    candidates : DiskCandidates, optional
        Detected disks (default: :func:`detect_disks` on `raw`).
    per_channel : bool
        False (filtered images): one fit per disk over all channels, each channel with its
        own lightnesses. True (unfiltered images): one fit per disk and colour channel,
        using only that channel's pixels.
    name : str
        What the image is, for error messages.
    edge_width_px : float
        Initial width of the edge as it appears in the image, px, including the pixel
        footprint (≈ 1 px); the model's ramp width starts at ``edge_width_px − 1``
        (at least 0.25 px).
    workers : int, optional
        Processes (default: the CPUs available); 1 fits in this process.

    Returns
    -------
    DiskFit
        The accepted fits, with the reasons and counts of rejected disks.

    Raises
    ------
    DataError
        The image is malformed, shows no disks, or no disk could be refined.

    Notes
    -----
    The fit uses the pixels within max(3 px, 1.5 px + `edge_width_px`) of the detected
    edge, inside the detected bounding box enlarged by half a radius (≥ 3 px); disks
    whose neighbourhood leaves the image are skipped ("touches border"). In joint fits
    each channel's residuals are divided by the larger of its disk contrast and 50 × its
    pixel noise, so that every channel with signal counts equally (their sampling
    lattices then average out) and channels without signal add noise, not bias. Fits are
    rejected when Levenberg–Marquardt does not converge, the centre moves more than
    max(2 px, 0.3 radius), the axes are implausible (outside 0.6–1.6 × the detected
    radius or aspect > 2), the edge ramp is wider than half the radius, or the disk is
    not at least 25 % darker than the paper.
    """
    layout = check_layout(cfa)
    raw = _checked_raw(raw, name)
    if not edge_width_px > 0:
        raise DataError(f"edge_width_px must be > 0, got {edge_width_px}")
    n_workers = _workers(workers)
    with _maybe_pool(n_workers) as pool:
        pending = _start(raw, layout, candidates, per_channel, name, edge_width_px, pool, n_workers)
        return _finish(pending)


class _Pending(NamedTuple):
    """Disk fits of one image under way."""

    name: str
    candidates: DiskCandidates
    outside: int
    per_channel: bool
    parts: list[Future | list[_Outcome]]


def _start(
    raw: np.ndarray,
    layout: str,
    candidates: DiskCandidates | None,
    per_channel: bool,
    name: str,
    edge_width: float,
    pool: Executor | None,
    workers: int,
) -> _Pending:
    """Detect (unless given) and start fitting the disks of one image."""
    if candidates is None:
        candidates = detect_disks(raw, cfa=layout, name=name)
    if candidates.labels.shape != raw.shape:
        raise DataError(
            f"{name}: disk candidates were detected in a {candidates.labels.shape} image, "
            f"but the raw mosaic is {raw.shape}; detect them in this image"
        )
    index = channel_index(layout, raw.shape)
    tasks, outside = _make_tasks(raw, index, candidates, edge_width)
    noise = _channel_noise(raw, index)
    options = _Options(per_channel, edge_width, tuple(float(v) for v in noise))
    return _Pending(name, candidates, outside, per_channel, _submit(tasks, options, pool, workers))


def _finish(pending: _Pending) -> DiskFit:
    """Collect the fits of one image into a :class:`DiskFit`."""
    outcomes = [
        outcome
        for part in pending.parts
        for outcome in (part.result() if isinstance(part, Future) else part)
    ]
    rejected: dict[str, int] = {}
    if pending.outside:
        rejected["touches border"] = pending.outside
    good = []
    for outcome in outcomes:
        if outcome.reason:
            rejected[outcome.reason] = rejected.get(outcome.reason, 0) + 1
        else:
            good.append(outcome)
    if not good:
        raise DataError(
            f"{pending.name}: none of the {len(pending.candidates)} detected disks could be "
            f"refined (rejected: {rejected}); check focus and exposure, and that the disks "
            "lie well inside the image"
        )
    centres = np.stack([o.centres for o in good])  # (n, g, 2)
    quads = np.stack([o.quadratic for o in good])
    widths = np.stack([o.edge_width for o in good])
    residuals = np.stack([o.residual for o in good])
    main = 1 if pending.per_channel else 0  # per-channel fits report the Green channel
    axes, angle = _ellipse_from_quadratic(quads[:, main])
    return DiskFit(
        centres=centres[:, main].copy(),
        channel_centres=centres if pending.per_channel else None,
        axes=axes,
        angle_rad=angle,
        edge_width_px=widths[:, main].copy(),
        residual=residuals.max(axis=1),
        candidate=np.array([o.candidate for o in good], dtype=np.int64),
        rejected=rejected,
    )


# -- pairing and outliers ------------------------------------------------------------


def pair_mutual_nearest(
    reference_xy: np.ndarray, band_xy: np.ndarray, *, max_distance_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pair points that are each other's nearest neighbour and closer than a limit.

    Parameters
    ----------
    reference_xy : ndarray (n, 2)
        Points (x, y) in the reference image, px.
    band_xy : ndarray (m, 2)
        Points (x, y) in the other image, px.
    max_distance_px : float
        Pairs farther apart than this are dropped, px.

    Returns
    -------
    reference_index, band_index : ndarray (k,) int64
        Indices of the pairs into `reference_xy` and `band_xy`, sorted by reference index.
    """
    ref = np.asarray(reference_xy, dtype=np.float64)
    band = np.asarray(band_xy, dtype=np.float64)
    for what, points in (("reference_xy", ref), ("band_xy", band)):
        if points.ndim != 2 or points.shape[1] != 2:
            raise DataError(f"{what} must be an (n, 2) array of x, y; got shape {points.shape}")
        if not np.all(np.isfinite(points)):
            raise DataError(f"{what} holds NaN or Inf positions")
    empty = np.zeros(0, dtype=np.int64)
    if len(ref) == 0 or len(band) == 0:
        return empty, empty
    dist, to_band = cKDTree(band).query(ref)
    _, to_ref = cKDTree(ref).query(band)
    ref_index = np.arange(len(ref))
    mutual = (to_ref[to_band] == ref_index) & (dist <= max_distance_px)
    return ref_index[mutual].astype(np.int64), np.asarray(to_band[mutual], dtype=np.int64)


def _smooth_trend(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """A robust quadratic fit of displacements `d` (n, 2) over positions `xy` (n, 2).

    Iteratively reweighted least squares with Tukey's biweight (scale from the median
    misfit, at least 0.05 px), in normalised coordinates. Returns the fitted values
    (n, 2); zero when there are too few points for a quadratic.
    """
    n = len(xy)
    if n < 12:
        return np.zeros_like(d)
    u = (xy - xy.mean(axis=0)) / np.maximum(xy.std(axis=0), 1e-9)
    design = np.column_stack(
        [np.ones(n), u[:, 0], u[:, 1], u[:, 0] ** 2, u[:, 0] * u[:, 1], u[:, 1] ** 2]
    )
    weight = np.ones(n)
    for _ in range(10):
        root = np.sqrt(weight)[:, None]
        coef, *_ = np.linalg.lstsq(design * root, d * root, rcond=None)
        misfit = np.hypot(*(d - design @ coef).T)
        # the median of |e| for a 2-D Gaussian with sigma per component is 1.177 sigma
        sigma = max(float(np.median(misfit)) / 1.177, 0.05)
        ratio = misfit / (4.685 * sigma)
        new = np.where(ratio < 1.0, (1.0 - ratio**2) ** 2, 0.0)
        if np.count_nonzero(new) < 12 or np.allclose(new, weight, atol=1e-3):
            break
        weight = new
    return design @ coef


def _displacement_outliers(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Boolean (n,): displacements far from the median of their nearest neighbours.

    A displacement is an outlier when it differs from the median displacement of its
    (up to) 8 nearest neighbours by more than max(0.3 px, 5 robust sigma), sigma from the
    median absolute deviation of those differences over all keypoints. The comparison is
    made after removing a robust quadratic trend of the field: otherwise, where the field
    is steep, keypoints at the edge of the pattern (whose neighbours all lie on one side)
    would differ from their neighbours' median by the field's gradient alone.
    """
    n = len(xy)
    if n < 3:
        return np.zeros(n, dtype=bool)
    residual = d - _smooth_trend(xy, d)
    k = min(_OUTLIER_NEIGHBOURS, n - 1)
    _, neighbours = cKDTree(xy).query(xy, k=k + 1)
    neighbours = neighbours[:, 1:]  # drop the point itself
    deviation = residual - np.median(residual[neighbours], axis=1)
    centred = deviation - np.median(deviation, axis=0)
    sigma = 1.4826 * float(np.median(np.abs(centred)))
    limit = max(_OUTLIER_FLOOR_PX, _OUTLIER_SIGMAS * sigma)
    return np.hypot(deviation[:, 0], deviation[:, 1]) > limit


def _median_spacing(xy: np.ndarray) -> float:
    """Median distance from each point to its nearest neighbour, px."""
    if len(xy) < 2:
        return float("inf")
    dist, _ = cKDTree(xy).query(xy, k=2)
    return float(np.median(dist[:, 1]))


# -- keypoints ------------------------------------------------------------------------


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
) -> _Pending:
    """Detect the disks of one image and start fitting them; errors name it as `where`."""
    raw = _checked_raw(image.raw, where)
    layout = check_layout(image.cfa)
    candidates = detect_disks(raw, cfa=layout, name=where)
    return _start(raw, layout, candidates, per_channel, where, _EDGE_WIDTH_PX, pool, workers)


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
    n_workers = _workers(workers)
    bands = [_band_wavelength(image, wavelengths) for image in images]
    order = np.argsort(bands, kind="stable")
    images = [images[i] for i in order]
    bands = [bands[i] for i in order]
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
    if max_shift_px is not None and not max_shift_px > 0:
        raise DataError(f"max_shift_px must be > 0 px, got {max_shift_px}")
    ref_i = near[0]
    shape = images[0].raw.shape
    with _maybe_pool(n_workers) as pool:
        # detection of the next image overlaps the fits of the previous ones
        pending = [
            _start_image(image, f"band {w:g} nm ({source_of(image)})", pool, n_workers)
            for image, w in zip(images, bands, strict=True)
        ]
        fits = [_finish(p) for p in pending]
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
        ri, bi = pair_mutual_nearest(ref_xy, fit.centres, max_distance_px=limit)
        d = fit.centres[bi] - ref_xy[ri]
        outliers = _displacement_outliers(ref_xy[ri], d)
        keep = ~outliers
        info.update(paired=int(ri.size), outliers=int(outliers.sum()))
        if int(keep.sum()) < _MIN_PAIRED:
            raise DataError(
                f"band {w:g} nm ({source_of(image)}): only {int(keep.sum())} of its "
                f"{len(fit)} disks pair with the {len(ref_fit)} disks of the reference "
                f"band {bands[ref_i]:g} nm within {limit:.3g} px (need ≥ {_MIN_PAIRED}); "
                "check that both images show the same view of the pattern, or raise "
                "max_shift_px"
            )
        ri, bi, d = ri[keep], bi[keep], d[keep]
        quality = np.maximum(ref_fit.residual[ri], fit.residual[bi])
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
    n_workers = _workers(workers)
    with _maybe_pool(n_workers) as pool:
        fit = _finish(_start_image(image, where, pool, n_workers, per_channel=True))
    green = fit.channel_centres[:, 1]
    parts = []
    channels_meta: dict[str, dict[str, int]] = {}
    for c, label in ((0, "R"), (2, "B")):
        d = fit.channel_centres[:, c] - green
        outliers = _displacement_outliers(green, d)
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
    raw = _checked_raw(raw, "image")
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
    return distance > margin_px + _EDGE_WIDTH_PX
