"""Residual chromatic aberration at the edges of ColorChecker patches (thesis §4.4.3).

A reference-free measure of how well an image is corrected for lateral chromatic
aberration: in a scene of homogeneous patches with sharp edges, the ideal image is
known from the patches' centres, far from any colour fringe. The measure is the error
of the estimated image against that ideal image in narrow strips just inside the patch
edges (where fringes appear), next to the same error in the patch centres (which
should be small).

Procedure (:func:`residual_aberration`)

1. **Patches.** Each patch is a connected set of pixels, from a label image (0 =
   background, k = patch k, e.g. marked by hand on the reference channel) or from patch
   rectangles (e.g. :func:`labkit.sim.colorchecker_patch_boxes`), which keep the pixels
   whose whole unit box lies inside the rectangle (pixels straddling an edge mix two
   colours and have no ideal value). A pixel's depth is its Euclidean distance to the
   nearest pixel outside its patch (1 next to the edge; image borders are not edges).
   The *edge strip* is depth ≤ `strip_px` (12 px in the thesis), the *centre* the rest.
2. **Ideal image.** For every patch and every colour-filter-array channel, a smooth
   shading model — a polynomial in (x, y) of total degree `shading_degree` — is fitted
   by least squares to the raw samples of that channel in the patch centre (no
   demosaicing: each channel is sampled at its own CFA sites), and evaluated over the
   whole patch. The thesis replicates each patch's centre colour under a shading
   pattern calibrated on the chart's frame; a per-patch, per-channel plane (the default
   degree 1) captures the same smooth illumination fall-off locally.
3. **Errors.** Per-channel RMSE (4.11) and MRAE (4.10) of the estimate against the
   ideal image over the edge strips and over the centres
   (:func:`reconstruction.evaluate.metrics.colour_errors`). An estimate may be a colour image
   (rows, cols, 3) — demosaiced, warped or reconstructed — or a raw mosaic
   (rows, cols), which is evaluated at each channel's CFA sites (the thesis' sanity
   check of the captured image itself).

The patch geometry must be where edges belong after correction: in the geometry of the
dispersion model's reference (the Green channel for colour-channel models; in the
simulator, the lens' reference wavelength). Choose `strip_px` wider than the largest
colour fringe (dispersion plus blur) so that the centres are fringe-free.

Limitation: pixels cut by a patch edge are left out (their ideal value would need a
sub-pixel model of the edge and of the surround), so a fringe narrower than the gap
between the edge and the first whole pixel (under 1 px) is not seen; the measure
responds to fringes of about half a pixel and more.

Where the spectral truth is known (a simulation, or the multispectral image of a real
chart), :func:`spectral_strip_errors` splits the spectral error between the same strips
and centres (beyond the thesis).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from scipy import ndimage

from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import CHANNELS, channel_index, check_layout
from labkit.errors import DataError
from reconstruction.evaluate.metrics import (
    ColourErrors,
    colour_errors,
    patch_weights,
    registration_scale,
)

#: Edge strip width of the thesis, px.
STRIP_PX = 12.0
#: Largest shading polynomial degree accepted.
MAX_SHADING_DEGREE = 3


@dataclass(frozen=True, eq=False)
class PatchRegions:
    """Patches split into edge strips and centres (:func:`patch_regions`).

    Attributes
    ----------
    labels : ndarray (rows, cols) of int32
        0 = background, k = patch k.
    patch_ids : tuple of int
        The patch labels, ascending.
    depth : ndarray (rows, cols), float64
        Distance of each patch pixel to the nearest pixel outside its patch, px (0 on
        the background).
    edge : ndarray (rows, cols) of bool
        Patch pixels with depth ≤ `strip_px`.
    centre : ndarray (rows, cols) of bool
        Patch pixels with depth > `strip_px`.
    strip_px : float
        Strip width, px.
    """

    labels: np.ndarray
    patch_ids: tuple[int, ...]
    depth: np.ndarray
    edge: np.ndarray
    centre: np.ndarray
    strip_px: float

    @cached_property
    def surround(self) -> np.ndarray:
        """Background pixels within `strip_px` of a patch (a chart's frame and gaps),
        (rows, cols) bool."""
        outside = self.labels == 0
        return outside & (ndimage.distance_transform_edt(outside) <= self.strip_px)


@dataclass(frozen=True, eq=False)
class ResidualAberration:
    """Result of :func:`residual_aberration`.

    Attributes
    ----------
    edge : ColourErrors
        Per-channel RMSE and MRAE in the edge strips (the residual aberration).
    centre : ColourErrors
        The same in the patch centres (the floor set by noise and shading fit).
    patch_edge_rmse : ndarray (n_patches, 3)
        Edge-strip RMSE of every patch and channel, image units, in `regions.patch_ids`
        order.
    shading_degree : int
        Degree of the per-patch shading polynomials.
    regions : PatchRegions
        The patches, strips and centres.
    ideal : ndarray (rows, cols, 3), float64
        The synthesised aberration-free image (0 outside the patches).
    """

    edge: ColourErrors
    centre: ColourErrors
    patch_edge_rmse: np.ndarray = field(repr=False)
    shading_degree: int
    regions: PatchRegions = field(repr=False)
    ideal: np.ndarray = field(repr=False)

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON types: the edge and centre errors, geometry and per-patch RMSE."""
        return {
            "edge": self.edge.as_dict(),
            "centre": self.centre.as_dict(),
            "strip_px": self.regions.strip_px,
            "shading_degree": self.shading_degree,
            "patch_ids": list(self.regions.patch_ids),
            "patch_edge_rmse": {
                name: self.patch_edge_rmse[:, c].tolist() for c, name in enumerate(CHANNELS)
            },
        }


@fixed_blas_threads
def residual_aberration(
    estimate: np.ndarray,
    raw: np.ndarray,
    *,
    cfa: str,
    boxes: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    strip_px: float = STRIP_PX,
    shading_degree: int = 1,
    floor: float | None = None,
    register: bool = False,
) -> ResidualAberration:
    """Residual chromatic aberration of an image of a ColorChecker-like chart (§4.4.3).

    Parameters
    ----------
    estimate : ndarray (rows, cols, 3) or (rows, cols)
        The image to assess, in the raw image's colour space and units: a colour image
        (demosaiced, warped, reconstructed in raw colour), or a raw mosaic evaluated at
        its CFA sites.
    raw : ndarray (rows, cols)
        The captured raw mosaic of the chart, from whose patch centres the ideal image
        is synthesised (any linear units, e.g. HDR e⁻/s).
    cfa : str
        Bayer layout of `raw` (and of a mosaic `estimate`), e.g. ``"GBRG"``.
    boxes : ndarray (n, 4), optional
        Patch rectangles (x0, y0, x1, y1) as edge positions, px (pixel centres at
        integers), as returned by :func:`labkit.sim.colorchecker_patch_boxes`.
    labels : ndarray (rows, cols) of int, optional
        Patch label image: 0 = background, k = patch k. Give exactly one of `boxes`
        and `labels`.
    strip_px : float
        Width of the edge strips, px (12 px in the thesis).
    shading_degree : int
        Total degree (0–3) of the per-patch, per-channel shading polynomial fitted to
        the centre samples; 0 replicates the centre mean.
    floor : float, optional
        MRAE floor in image units (see :mod:`reconstruction.evaluate.metrics`); default 1e-3 ×
        the largest ideal value of the evaluated pixels.
    register : bool
        Scale each channel of the estimate by the patch-weighted factors (4.13)–(4.14),
        fitted over the whole area of all patches, before measuring (for estimates in
        other units than the raw image).

    Returns
    -------
    ResidualAberration

    Raises
    ------
    DataError
        Shapes that disagree, NaN/Inf, invalid patches (no edge, no centre, too few
        centre samples of a channel for the shading fit), or both/neither of `boxes`
        and `labels`.
    """
    layout = check_layout(cfa)
    raw = _plane(raw, "the raw image")
    estimate = np.asarray(estimate, dtype=np.float64)
    if estimate.shape not in (raw.shape, (*raw.shape, 3)):
        raise DataError(
            f"the estimate has shape {estimate.shape} but the raw image {raw.shape}; pass a "
            f"(rows, cols, 3) colour image or a (rows, cols) mosaic of the same size"
        )
    if not np.all(np.isfinite(estimate)):
        raise DataError("the estimate holds NaN or Inf; fix those pixels first")
    regions = patch_regions(raw.shape, boxes=boxes, labels=labels, strip_px=strip_px)
    ideal = ideal_image(raw, regions, cfa=layout, shading_degree=shading_degree)

    if estimate.ndim == 2:
        sites = channel_index(layout, raw.shape)[..., None] == np.arange(3)
        colour = np.repeat(estimate[..., None], 3, axis=2)
    else:
        sites = np.ones((*raw.shape, 3), dtype=bool)
        colour = estimate
    if register:
        weights = patch_weights(regions.labels)
        scale = _channel_scale(ideal, colour, weights[..., None] * sites)
        colour = colour * scale
    edge_mask = regions.edge[..., None] & sites
    centre_mask = regions.centre[..., None] & sites
    options = {"floor": floor, "ssim": False}
    edge = colour_errors(ideal, colour, mask=edge_mask, **options)
    centre = colour_errors(ideal, colour, mask=centre_mask, **options)
    if register:
        edge = _with_scale(edge, scale)
        centre = _with_scale(centre, scale)
    return ResidualAberration(
        edge=edge,
        centre=centre,
        patch_edge_rmse=_patch_rmse(ideal, colour, regions, edge_mask),
        shading_degree=shading_degree,
        regions=regions,
        ideal=ideal,
    )


@dataclass(frozen=True)
class SpectralStripErrors:
    """Result of :func:`spectral_strip_errors`: the spectral RMSE of an image split between
    the patches' edge strips, their centres and the surround just outside them, each
    relative to the mean true value of all evaluated pixels (so that, weighted by their
    pixel shares, the regions' squares add up to the whole image's).

    Attributes
    ----------
    strips, centres, surround, whole : float
        RMS error of every band of every evaluated pixel of the region, after
        registration, over the mean true value (unitless). `surround`: pixels outside
        every patch within the strip width of one (a chart's frame and gaps).
    scale : tuple of float
        The per-band registration factors (4.9) applied to the estimate.
    """

    strips: float
    centres: float
    surround: float
    whole: float
    scale: tuple[float, ...]


def spectral_strip_errors(
    truth: np.ndarray,
    estimate: np.ndarray,
    *,
    boxes: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    strip_px: float = STRIP_PX,
    mask: np.ndarray | None = None,
) -> SpectralStripErrors:
    """Spectral error of an image of a patch chart in the edge strips, centres and surround.

    The spectral counterpart of :func:`residual_aberration` for images whose spectral
    truth is known (a simulation, or a multispectral image of the chart in the
    reconstruction's geometry): a prior that smooths across edges shows in the strips and
    in the surround (the dark frame between patches), the metamer problem (§6.3) in the
    centres. The estimate is registered per band (4.9) over all evaluated pixels first.

    Parameters
    ----------
    truth, estimate : ndarray (rows, cols, bands)
        Spectral images on the same grid and bands.
    boxes, labels
        The patches, as for :func:`patch_regions` (exactly one).
    strip_px : float
        Width of the edge strips inside the patches and of the surround outside them, px.
    mask : ndarray (rows, cols) of bool, optional
        Pixels to evaluate (e.g. leaving out a border); default all. Only these need to
        be finite.

    Returns
    -------
    SpectralStripErrors

    Raises
    ------
    DataError
        Shapes that differ, NaN/Inf in evaluated pixels, invalid patches, or no evaluated
        pixel in the strips, the centres or the surround.
    """
    truth = np.asarray(truth, dtype=np.float64)
    estimate = np.asarray(estimate, dtype=np.float64)
    if truth.ndim != 3 or truth.shape != estimate.shape:
        raise DataError(
            f"truth {truth.shape} and estimate {estimate.shape} must be (rows, cols, bands) "
            "spectral images of the same shape"
        )
    keep = np.ones(truth.shape[:2], bool) if mask is None else np.asarray(mask, dtype=bool)
    if keep.shape != truth.shape[:2]:
        raise DataError(f"mask has shape {keep.shape}; the images are {truth.shape[:2]}")
    regions = patch_regions(truth.shape[:2], boxes=boxes, labels=labels, strip_px=strip_px)
    strips, centres = regions.edge & keep, regions.centre & keep
    surround = regions.surround & keep
    if not (strips.any() and centres.any() and surround.any()):
        raise DataError(
            "no evaluated pixel in the edge strips, the centres or the surround; widen the mask"
        )
    if not (np.all(np.isfinite(truth[keep])) and np.all(np.isfinite(estimate[keep]))):
        raise DataError("NaN or Inf in the evaluated pixels; mask them out")
    scale = registration_scale(truth[keep], estimate[keep])
    level = float(np.mean(truth[keep]))
    if not level > 0:
        raise DataError("the true image is not positive where evaluated; nothing to compare")
    squared = np.mean((estimate * scale - truth) ** 2, axis=-1)

    def relative(region: np.ndarray) -> float:
        return float(np.sqrt(np.mean(squared[region]))) / level

    return SpectralStripErrors(
        relative(strips),
        relative(centres),
        relative(surround),
        relative(keep),
        tuple(float(v) for v in scale),
    )


def patch_regions(
    shape: tuple[int, int],
    *,
    boxes: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    strip_px: float = STRIP_PX,
) -> PatchRegions:
    """Patches, their edge strips and centres, from rectangles or a label image.

    Parameters
    ----------
    shape : (rows, cols)
        Image size, px.
    boxes : ndarray (n, 4), optional
        Patch rectangles (x0, y0, x1, y1), px; patch k + 1 holds the pixels whose unit
        box lies inside rectangle k.
    labels : ndarray (rows, cols) of int, optional
        0 = background, k = patch k.
    strip_px : float
        Edge strip width, px.

    Returns
    -------
    PatchRegions

    Raises
    ------
    DataError
        Both or neither of `boxes` and `labels`, malformed or overlapping rectangles,
        a label image of another shape, an empty patch, a patch with no edge (filling
        the image) or no centre (narrower than two strips).
    """
    shape = (int(shape[0]), int(shape[1]))
    if (boxes is None) == (labels is None):
        raise DataError(
            "give the patch geometry as exactly one of boxes= (n × (x0, y0, x1, y1) px) "
            "and labels= (an integer image, 0 = background)"
        )
    strip = float(strip_px)
    if not np.isfinite(strip) or strip < 2:
        raise DataError(
            f"strip_px must be at least 2 px (so that every strip holds every CFA channel), "
            f"got {strip_px}"
        )
    grid = labels_from_boxes(boxes, shape) if boxes is not None else _check_labels(labels, shape)
    ids = np.unique(grid)
    ids = ids[ids > 0]
    if ids.size == 0:
        raise DataError("no patch: the label image is all background (0)")
    depth = _depth(grid, ids)
    inside = grid > 0
    edge = inside & (depth <= strip)
    centre = inside & (depth > strip)
    no_centre = np.setdiff1d(ids, np.unique(grid[centre]))
    if no_centre.size:
        # a caller that chose strip_px may lower it; `labkit evaluate` uses the thesis' width
        lower = " (or a smaller strip_px)" if strip != STRIP_PX else ""
        raise DataError(
            f"patch(es) {no_centre.tolist()} have no centre: they are no wider than two "
            f"{strip:g}-px edge strips; use a larger image of the chart, whose patches are "
            f"over {2 * strip:g} px across{lower}"
        )
    return PatchRegions(grid, tuple(int(k) for k in ids), depth, edge, centre, strip)


def ideal_image(
    raw: np.ndarray, regions: PatchRegions, *, cfa: str, shading_degree: int = 1
) -> np.ndarray:
    """The aberration-free image of the patches, synthesised from their raw centres.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Raw mosaic, any linear units.
    regions : PatchRegions
        Patches and centres (:func:`patch_regions`).
    cfa : str
        Bayer layout of `raw`.
    shading_degree : int
        Total degree (0–3) of the polynomial in (x, y) fitted, per patch and channel, to
        the centre samples of that channel.

    Returns
    -------
    ndarray (rows, cols, 3), float64
        The fitted shading of every channel over every patch, raw units; 0 on the
        background.

    Raises
    ------
    DataError
        A raw image of another shape or holding NaN/Inf, a degree outside 0–3, or a
        patch channel with too few (or collinear) centre samples to fit.
    """
    raw = _plane(raw, "the raw image")
    if raw.shape != regions.labels.shape:
        raise DataError(
            f"the raw image is {raw.shape} but the patch regions {regions.labels.shape}"
        )
    degree = int(shading_degree)
    if degree != shading_degree or not 0 <= degree <= MAX_SHADING_DEGREE:
        raise DataError(
            f"shading_degree must be an integer 0–{MAX_SHADING_DEGREE}, got {shading_degree}"
        )
    ids = np.asarray(regions.patch_ids)
    n = ids.size
    # patch index (0…n−1) per pixel, −1 on the background
    lookup = np.full(int(regions.labels.max()) + 1, -1)
    lookup[ids] = np.arange(n)
    patch = lookup[regions.labels]
    centre_xy, half = _patch_frames(regions.labels, ids)

    rows, cols = np.nonzero(regions.centre)
    p = patch[rows, cols]
    ch = channel_index(cfa, raw.shape)[rows, cols].astype(np.intp)
    basis = _basis(cols, rows, centre_xy[p], half[p], degree)  # (m, terms)
    group = 3 * p + ch
    terms = basis.shape[1]
    count = np.bincount(group, minlength=3 * n)
    gram = np.empty((3 * n, terms, terms))
    for i in range(terms):
        for j in range(i, terms):
            gram[:, i, j] = gram[:, j, i] = np.bincount(
                group, weights=basis[:, i] * basis[:, j], minlength=3 * n
            )
    values = raw[rows, cols]
    rhs = np.stack(
        [np.bincount(group, weights=basis[:, i] * values, minlength=3 * n) for i in range(terms)],
        axis=1,
    )
    tunable = [name for name, chosen in (("strip_px", regions.strip_px != STRIP_PX),
                                         ("shading_degree", degree != 1)) if chosen]  # fmt: skip
    _check_fits(gram, count, ids, terms, tunable)
    coef = np.linalg.solve(gram, rhs[..., None])[..., 0]  # (3n, terms)

    ideal = np.zeros((*raw.shape, 3))
    rows, cols = np.nonzero(regions.labels > 0)
    p = patch[rows, cols]
    basis = _basis(cols, rows, centre_xy[p], half[p], degree)
    for c in range(3):
        ideal[rows, cols, c] = np.einsum("ij,ij->i", basis, coef[3 * p + c])
    return ideal


# -- helpers ---------------------------------------------------------------------------


def _plane(image: np.ndarray, what: str) -> np.ndarray:
    plane = np.asarray(image, dtype=np.float64)
    if plane.ndim != 2:
        raise DataError(f"{what} must be a (rows, cols) mosaic, got shape {plane.shape}")
    if not np.all(np.isfinite(plane)):
        raise DataError(f"{what} holds NaN or Inf; fix those pixels first")
    return plane


def labels_from_boxes(boxes: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Label image: patch k + 1 = pixels whose unit box lies inside rectangle k."""
    b = np.asarray(boxes, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 4 or not np.all(np.isfinite(b)):
        raise DataError(f"boxes must be a finite (n, 4) array of (x0, y0, x1, y1), got {b.shape}")
    if np.any(b[:, 2] <= b[:, 0]) or np.any(b[:, 3] <= b[:, 1]):
        raise DataError("every box needs x1 > x0 and y1 > y0 (edge positions, px)")
    rows, cols = shape
    eps = 1e-9
    c0 = np.clip(np.ceil(b[:, 0] + 0.5 - eps), 0, cols).astype(int)
    c1 = np.clip(np.floor(b[:, 2] - 0.5 + eps) + 1, 0, cols).astype(int)
    r0 = np.clip(np.ceil(b[:, 1] + 0.5 - eps), 0, rows).astype(int)
    r1 = np.clip(np.floor(b[:, 3] - 0.5 + eps) + 1, 0, rows).astype(int)
    grid = np.zeros(shape, dtype=np.int32)
    for k in range(b.shape[0]):
        if r1[k] <= r0[k] or c1[k] <= c0[k]:
            raise DataError(
                f"box {k} {b[k].tolist()} holds no whole pixel of the {cols}×{rows} image"
            )
        block = grid[r0[k] : r1[k], c0[k] : c1[k]]
        if block.any():
            raise DataError(f"box {k} overlaps box {int(block.max()) - 1}; patches must be apart")
        block[...] = k + 1
    return grid


def _check_labels(labels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    grid = np.asarray(labels)
    if grid.shape != shape or not np.issubdtype(grid.dtype, np.integer):
        raise DataError(
            f"labels must be an integer image of shape {shape} (the raw image's), got "
            f"{grid.dtype} of shape {grid.shape}"
        )
    if grid.min() < 0:
        raise DataError("labels must be ≥ 0 (0 = background, k = patch k)")
    return grid.astype(np.int32)


def _depth(grid: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Distance of every patch pixel to the nearest pixel outside its patch, px."""
    depth = np.zeros(grid.shape)
    rows, cols = grid.shape
    objects = ndimage.find_objects(grid)
    for k in ids:
        found = objects[k - 1]
        if found is None:  # pragma: no cover - ids come from the grid
            continue
        sr, sc = found
        # one pixel of context each side (where the image has it): the neighbours
        r0, r1 = max(sr.start - 1, 0), min(sr.stop + 1, rows)
        c0, c1 = max(sc.start - 1, 0), min(sc.stop + 1, cols)
        member = grid[r0:r1, c0:c1] == k
        if member.all():
            raise DataError(
                f"patch {k} has no edge inside the image (it fills its whole neighbourhood); "
                "label the background around each patch 0"
            )
        distance = ndimage.distance_transform_edt(member)
        depth[r0:r1, c0:c1][member] = distance[member]
    return depth


def _patch_frames(grid: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding-box centre (n, 2) as (x, y) and half-size (n,) of every patch, px."""
    objects = ndimage.find_objects(grid)
    centre = np.empty((ids.size, 2))
    half = np.empty(ids.size)
    for i, k in enumerate(ids):
        sr, sc = objects[k - 1]
        centre[i] = ((sc.start + sc.stop - 1) / 2.0, (sr.start + sr.stop - 1) / 2.0)
        half[i] = max(sc.stop - sc.start, sr.stop - sr.start) / 2.0
    return centre, half


def _basis(
    x: np.ndarray, y: np.ndarray, centre: np.ndarray, half: np.ndarray, degree: int
) -> np.ndarray:
    """Monomials uⁱ vʲ (i + j ≤ degree) of patch-normalised coordinates, (m, terms)."""
    u = (x - centre[:, 0]) / half
    v = (y - centre[:, 1]) / half
    columns = [u**i * v ** (g - i) for g in range(degree + 1) for i in range(g, -1, -1)]
    return np.stack(columns, axis=1)


def _check_fits(
    gram: np.ndarray, count: np.ndarray, ids: np.ndarray, terms: int, tunable: list[str]
) -> None:
    """Refuse patch channels with fewer samples than terms or a singular design.

    `tunable` names the parameters the caller chose (not left at their defaults): only
    those are advised, as a command line that uses the defaults cannot change them.
    """
    few = np.flatnonzero(count < terms)
    if few.size == 0:
        condition = np.linalg.cond(gram)
        few = np.flatnonzero(~(condition < 1e12))
    if few.size:
        where = ", ".join(
            f"patch {ids[g // 3]} {CHANNELS[g % 3]} ({count[g]} samples)" for g in few[:6]
        )
        raise DataError(
            f"too few centre samples to fit the shading of {where}; a degree-"
            f"{_degree(terms)} polynomial needs {terms} well-spread samples per channel: "
            "use a larger image of the chart"
            + (f" (or lower {' or '.join(tunable)})" if tunable else "")
        )


def _degree(terms: int) -> int:
    return {1: 0, 3: 1, 6: 2, 10: 3}[terms]


def _channel_scale(ideal: np.ndarray, colour: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per-channel factors (4.14) with per-channel pixel weights (rows, cols, 3)."""
    numerator = np.sum(weights * ideal * colour, axis=(0, 1))
    denominator = np.sum(weights * colour * colour, axis=(0, 1))
    empty = [CHANNELS[c] for c in range(3) if not denominator[c] > 0]
    if empty:
        raise DataError(
            f"the estimate is zero over the patches in channel(s) {empty}; it cannot be "
            "registered onto the ideal image"
        )
    return numerator / denominator


def _with_scale(errors: ColourErrors, scale: np.ndarray) -> ColourErrors:
    return replace(errors, scale=tuple(float(s) for s in scale))


def _patch_rmse(
    ideal: np.ndarray, colour: np.ndarray, regions: PatchRegions, mask: np.ndarray
) -> np.ndarray:
    """Edge-strip RMSE (n_patches, 3) of every patch and channel."""
    ids = np.asarray(regions.patch_ids)
    size = int(regions.labels.max()) + 1
    out = np.empty((ids.size, 3))
    for c in range(3):
        inside = mask[..., c]
        label = regions.labels[inside]
        sq = (ideal[..., c][inside] - colour[..., c][inside]) ** 2
        total = np.bincount(label, weights=sq, minlength=size)[ids]
        count = np.bincount(label, minlength=size)[ids]
        out[:, c] = np.sqrt(np.divide(total, count, out=np.zeros(ids.size), where=count > 0))
    return out
