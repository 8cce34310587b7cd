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

from calibration.disks.detect import DiskCandidates, background_mask, detect_disks
from calibration.disks.fit import DiskFit, fit_disks
from calibration.disks.keypoints import channel_disk_keypoints, disk_keypoints
from calibration.disks.pair import pair_mutual_nearest

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
