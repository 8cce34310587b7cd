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

Each step's effect on a planted shift, and the run time, are in docs/notes/calibration.md.

Patches are rejected when their registration error exceeds `max_error` (content that
differs between the images, e.g. colours whose contrast changes between bands), when
their texture is below `min_texture` (flat patches, and patches holding one straight
edge, whose shift along the edge is undetermined), or when the shift reaches the
search limit.

Sign convention: a keypoint says that the feature at (x, y) in the reference image is at
(x + dx, y + dy) in the band (``from_reference``); scikit-image's shift is the opposite
(what registers the moving image onto the reference).
"""

from calibration.registration.keypoints import (
    channel_registration_keypoints,
    registration_keypoints,
)
from calibration.registration.shifts import MAX_ERROR, MIN_TEXTURE, PatchShifts, patch_shifts

__all__ = [
    "MAX_ERROR",
    "MIN_TEXTURE",
    "PatchShifts",
    "channel_registration_keypoints",
    "patch_shifts",
    "registration_keypoints",
]
