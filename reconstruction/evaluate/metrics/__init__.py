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

Residual lateral chromatic aberration on a disk-chart image (:func:`disk_channel_offsets`):
the R−G and B−G offsets of the calibration-disk centres, fitted per colour channel with
:mod:`calibration.disks`, px RMS over the disks.
"""

from reconstruction.evaluate.metrics._inputs import BLOCK_PIXELS, RELATIVE_FLOOR, SAFE_MAGNITUDE
from reconstruction.evaluate.metrics.colour import ColourErrors, colour_errors
from reconstruction.evaluate.metrics.disk_offsets import DiskOffsets, disk_channel_offsets
from reconstruction.evaluate.metrics.registration import patch_weights, registration_scale
from reconstruction.evaluate.metrics.spectral import SpectralErrors, spectral_errors

__all__ = [
    "BLOCK_PIXELS",
    "RELATIVE_FLOOR",
    "SAFE_MAGNITUDE",
    "ColourErrors",
    "DiskOffsets",
    "SpectralErrors",
    "colour_errors",
    "disk_channel_offsets",
    "patch_weights",
    "registration_scale",
    "spectral_errors",
]
