"""Residual lateral chromatic aberration of a colour image of the disk chart: the R−G and B−G
offsets of the calibration-disk centres, px RMS (:func:`disk_channel_offsets`).

Method
------
Each colour channel of the full-resolution image (e.g. a reconstruction's raw-colour
image) is treated as a grey image of the disk pattern, and its disks are found and
refined with the calibration keypoint machinery of :mod:`calibration.disks`:
:func:`~calibration.disks.fit_disks` detects them (Otsu threshold, connected components,
area and ellipticity filters) and refines every disk by a Levenberg–Marquardt fit of the
pixel-integrated disk model (ellipse, edge ramp, local illumination gradient), giving
sub-pixel centres. The image is handed to it as if it were a mosaic with a nominal CFA
layout and a *joint* fit (``per_channel=False``): one ellipse per disk is fitted to all
pixels, each nominal 2 × 2 sub-lattice with its own (here equal) lightnesses, so every
pixel of the channel informs the centre. The R and B disks are then paired with the G
disks by mutual nearest neighbours (:func:`~calibration.disks.pair_mutual_nearest`)
closer than a quarter of the median G disk spacing; a disk counts when it is paired in
both R and B.

For each such disk ``k`` the offsets are ``d_RG = c_R − c_G`` and ``d_BG = c_B − c_G``
(centre vectors (x, y)); the metric is the RMS of their lengths over the disks,
``sqrt(mean_k |d_k|²)``. Offsets are not cleaned of outliers: a disk that a channel
renders displaced is exactly what the metric is meant to report. Disks cut by the image
border, or too close to it for the fit's neighbourhood, are left out.

Conventions (as in :mod:`calibration.disks`): x = column, y = row, pixel centres at
integer coordinates, origin top-left; all positions and offsets in pixels of the image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from calibration.disks import fit_disks, pair_mutual_nearest
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import CHANNELS
from labkit.errors import DataError

#: Nominal CFA layout under which one colour channel is handed to the disk fitter.
_NOMINAL_CFA = "RGGB"
#: Largest centre offset paired, as a fraction of the median G disk spacing.
_PAIR_FRACTION = 0.25


@dataclass(frozen=True, eq=False)
class DiskOffsets:
    """Colour-channel offsets of disk centres (:func:`disk_channel_offsets`).

    Attributes
    ----------
    rg_px : float
        RMS over the disks of the length of the R-centre minus G-centre vector, px.
    bg_px : float
        The same for B − G, px.
    count : int
        Disks matched in all three channels.
    offsets : ndarray (count, 2, 2) float64
        Per disk, (R − G, B − G) × (dx, dy), px.
    centres_g : ndarray (count, 2) float64
        G-channel disk centres (x, y), px.
    """

    rg_px: float
    bg_px: float
    count: int
    offsets: np.ndarray
    centres_g: np.ndarray

    def as_dict(self) -> dict[str, Any]:
        """The summary figures as plain JSON types (``rg_px``, ``bg_px``, ``count``)."""
        return {"rg_px": self.rg_px, "bg_px": self.bg_px, "count": self.count}


def _checked_rgb(rgb: np.ndarray, name: str) -> np.ndarray:
    """`rgb` as a finite (rows, cols, 3) array of numbers, or DataError naming it."""
    image = np.asarray(rgb)
    if image.ndim != 3 or image.shape[2] != 3:
        raise DataError(
            f"{name}: disk offsets need a (rows, cols, 3) colour image (R, G, B), got shape "
            f"{image.shape}; demosaic a raw mosaic or render the reconstruction's colour "
            "image first"
        )
    if image.dtype.kind not in "fiu":
        raise DataError(f"{name}: pixels must be numbers, got dtype {image.dtype}")
    bad = image.size - int(np.count_nonzero(np.isfinite(image)))
    if bad:
        raise DataError(
            f"{name}: {bad} values are NaN or Inf; replace or crop them away before "
            "measuring disk offsets"
        )
    return image


@fixed_blas_threads
def disk_channel_offsets(
    rgb: np.ndarray, *, min_disks: int = 4, name: str = "image", workers: int | None = None
) -> DiskOffsets:
    """R−G and B−G offsets of calibration-disk centres in a colour image, px RMS.

    Parameters
    ----------
    rgb : ndarray (rows, cols, 3)
        Full-resolution colour image (R, G, B; e.g. a reconstruction's raw-colour image)
        of the chart of dark disks on a light background; float32 or float64.
    min_disks : int
        Fewest disks that must be matched in all three channels.
    name : str
        What the image is, for error messages.
    workers : int, optional
        Processes for the disk fits (default: the CPUs available); 1 fits in this process.

    Returns
    -------
    DiskOffsets
        RMS offset lengths ``rg_px`` and ``bg_px``, the number of disks matched, their
        per-disk offsets and G centres, ordered as the G channel's fits.

    Raises
    ------
    DataError
        `rgb` is not (rows, cols, 3) or holds NaN/Inf, a channel shows no disk pattern (see
        :func:`calibration.disks.detect_disks`) or none of its disks can be refined, or
        fewer than `min_disks` disks are matched in all three channels.
    """
    image = _checked_rgb(rgb, name)
    if int(min_disks) != min_disks or min_disks < 1:
        raise DataError(f"min_disks must be a whole number ≥ 1, got {min_disks}")
    centres = [
        fit_disks(
            np.ascontiguousarray(image[..., c]),
            cfa=_NOMINAL_CFA,
            name=f"{name} ({label} channel)",
            workers=workers,
        ).centres
        for c, label in enumerate(CHANNELS)
    ]
    green = centres[1]
    if len(green) >= 2:
        spacing, _ = cKDTree(green).query(green, k=2)
        limit = _PAIR_FRACTION * float(np.median(spacing[:, 1]))
    else:
        limit = np.inf
    g_r, r_i = pair_mutual_nearest(green, centres[0], max_distance_px=limit)
    g_b, b_i = pair_mutual_nearest(green, centres[2], max_distance_px=limit)
    g_i, in_r, in_b = np.intersect1d(g_r, g_b, assume_unique=True, return_indices=True)
    if g_i.size < min_disks:
        raise DataError(
            f"{name}: only {g_i.size} disks are found in all of R, G and B (G {len(green)}, "
            f"R {len(centres[0])}, B {len(centres[2])}, paired within {limit:.3g} px; need "
            f"≥ {min_disks}); use an image showing more whole disks of the chart, sharp and "
            "well exposed in every channel"
        )
    centres_g = green[g_i]
    offsets = np.stack(
        [centres[0][r_i[in_r]] - centres_g, centres[2][b_i[in_b]] - centres_g], axis=1
    )
    rms = np.sqrt(np.mean(np.sum(offsets**2, axis=2), axis=0))
    return DiskOffsets(
        rg_px=float(rms[0]),
        bg_px=float(rms[1]),
        count=int(g_i.size),
        offsets=offsets,
        centres_g=centres_g,
    )
