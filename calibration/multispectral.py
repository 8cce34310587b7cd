"""Multispectral and synthetic RGB/raw images from filtered HDR images (thesis Algorithm 13).

For one scene with HDR images under narrowband illuminations b = 1…n:

1. each image is converted to a **rate**, ``raw / exposure_s`` (fraction of saturation
   per second), so bands merged at different reference exposures are comparable;
2. its Green channel is interpolated to every pixel by bilinear demosaicing
   (:func:`green_bilinear`) → band image ``G_b`` of the multispectral cube;
3. the synthetic colour image is ``RGB = Σ_b G_b · (r_b, 1, b_b)`` with the calibrated
   ratios ``r_b = R/G`` and ``b_b = B/G`` of band b (Algorithm 12), so its Green channel
   is the plain sum of the band images;
4. the synthetic raw image samples RGB with the scene's CFA layout.

The synthetic raw image is what reconstruction takes as input; the multispectral cube is
its exact ground truth under the (simplified) image-formation model of step 3.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration._hdr_inputs import check_consistent, source_of
from calibration.sensitivity import ChannelSensitivity
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import channel_index, check_layout, mosaic
from labkit.errors import DataError
from labkit.io import RawImage, SpectralImage, write_raw_exr, write_spectral_exr
from labkit.io.preview import to_display, write_png

#: Units of the synthetic images.
RATE_UNITS = "fraction of saturation per second"


@dataclass
class Synthesis:
    """Result of :func:`synthesize_multispectral`.

    Attributes
    ----------
    multispectral : SpectralImage
        Cube (rows, cols, bands) float32, fraction of saturation per second, bands
        sorted by wavelength.
    rgb : ndarray (rows, cols, 3) float32
        Synthetic colour image, same units.
    raw : RawImage
        The CFA-sampled synthetic image (``exposure_s = 1.0``, illumination
        ``"synthetic"``, no wavelength), same units.
    """

    multispectral: SpectralImage
    rgb: np.ndarray
    raw: RawImage


def green_bilinear(raw: np.ndarray, layout: str) -> np.ndarray:
    """Green channel of a Bayer mosaic at every pixel, by bilinear interpolation.

    Green pixels keep their value; every other pixel gets the mean of its four
    (Green) 4-neighbours, with the mosaic mirrored at the borders (which keeps the
    Bayer phase). Equal to the Green channel of
    :func:`labkit.io.preview.demosaic_bilinear`, without computing Red and Blue.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Mosaic (any linear units); at least 2 × 2.
    layout : str
        CFA layout, e.g. ``"GBRG"``.

    Returns
    -------
    ndarray (rows, cols) float64
    """
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 2 or min(raw.shape) < 2:
        raise DataError(f"green_bilinear needs a mosaic of at least 2 × 2, got {raw.shape}")
    padded = np.pad(raw, 1, mode="reflect")
    vertical = padded[:-2, 1:-1] + padded[2:, 1:-1]
    neighbours = 0.25 * (vertical + padded[1:-1, :-2] + padded[1:-1, 2:])
    green = channel_index(check_layout(layout), raw.shape) == 1
    return np.where(green, raw, neighbours)


@fixed_blas_threads
def synthesize_multispectral(
    images: Sequence[RawImage], sensitivity: ChannelSensitivity
) -> Synthesis:
    """Multispectral, synthetic RGB and synthetic raw images of one scene (Algorithm 13).

    Parameters
    ----------
    images : sequence of RawImage
        The filtered-light HDR images of ONE scene, one per band (``wavelength_nm``
        set; values: fraction of saturation at ``exposure_s``), all of one shape and
        CFA layout.
    sensitivity : ChannelSensitivity
        R/G and B/G per band (:func:`~calibration.sensitivity.channel_sensitivity`);
        every band of `images` needs an entry with finite ratios. Ratios flagged
        unreliable are used and listed in the provenance (``unreliable_bands``).

    Returns
    -------
    Synthesis
        All images in fraction of saturation per second (each band divided by its
        own ``exposure_s``).

    Raises
    ------
    DataError
        No images, an unfiltered image, two images of one band, mismatched shape or
        CFA, or a band the sensitivity table lacks (or has no ratio for).
    """
    if not images:
        raise DataError("synthesize_multispectral needs the filtered HDR images of one scene")
    for image in images:
        if image.wavelength_nm is None:
            raise DataError(
                f"{source_of(image)}: illumination {image.illumination!r} is unfiltered; "
                "multispectral synthesis takes bandpass-filtered images only"
            )
    scenes = sorted({str(image.labkit["scene"]) for image in images if "scene" in image.labkit})
    scene = scenes[0] if len(scenes) == 1 else None
    check_consistent(images, what=f"scene {scene!r}" if scene else "synthesis input")
    ordered = sorted(images, key=lambda image: float(image.wavelength_nm))
    wavelengths = np.array([float(image.wavelength_nm) for image in ordered])
    repeats = np.flatnonzero(np.diff(wavelengths) <= 0.05)
    if repeats.size:
        i = int(repeats[0])
        raise DataError(
            f"{source_of(ordered[i])} and {source_of(ordered[i + 1])} are both the "
            f"{wavelengths[i]:g} nm band; give one image per band of one scene"
        )

    ratios = np.empty((wavelengths.size, 2))
    used, unreliable = {}, []
    for band, image in enumerate(ordered):
        entry = sensitivity.index_of(wavelengths[band])
        if entry is None:
            raise DataError(
                f"{source_of(image)}: the sensitivity table ({sensitivity.source}) has no "
                f"{wavelengths[band]:g} nm band (it has "
                f"{', '.join(f'{w:g}' for w in sensitivity.wavelengths_nm)} nm); calibrate "
                "it with `labkit calibrate sensitivity` on images that include this band"
            )
        ratios[band] = sensitivity.r_over_g[entry], sensitivity.b_over_g[entry]
        if not np.all(np.isfinite(ratios[band])):
            reasons = "; ".join(
                r for r in (sensitivity.reason_r[entry], sensitivity.reason_b[entry]) if r
            )
            raise DataError(
                f"the sensitivity table ({sensitivity.source}) has no R/G or B/G for the "
                f"{wavelengths[band]:g} nm band ({reasons or 'value missing'}); "
                "enter the ratios by hand or recalibrate"
            )
        if not sensitivity.reliable[entry]:
            unreliable.append(float(wavelengths[band]))
        used[f"{wavelengths[band]:g}"] = {
            "r_over_g": float(ratios[band, 0]),
            "b_over_g": float(ratios[band, 1]),
            "reliable": bool(sensitivity.reliable[entry]),
        }

    layout = ordered[0].cfa
    cube = np.stack(
        [green_bilinear(image.raw, layout) / float(image.exposure_s) for image in ordered],
        axis=-1,
    )
    rgb = np.stack([cube @ ratios[:, 0], cube.sum(axis=-1), cube @ ratios[:, 1]], axis=-1)
    cube = cube.astype(np.float32)
    rgb = rgb.astype(np.float32)
    provenance = {
        "method": "bilinear Green per band, collapsed with R/G, B/G (the thesis' synthesis)",
        "scene": scene,
        "units": RATE_UNITS,
        "sources": [source_of(image) for image in ordered],
        "source_exposures_s": [float(image.exposure_s) for image in ordered],
        "sensitivity": used,
        "sensitivity_source": sensitivity.labkit.get("file", sensitivity.source),
        "unreliable_bands": unreliable,
    }
    raw = RawImage(
        raw=mosaic(rgb, layout),
        cfa=layout,
        exposure_s=1.0,
        illumination="synthetic",
        wavelength_nm=None,
        labkit={**provenance, "kind": "synthetic raw"},
    )
    spectral = SpectralImage(cube, wavelengths, {**provenance, "basis": "bands (Green channel)"})
    return Synthesis(multispectral=spectral, rgb=rgb, raw=raw)


def write_synthesis(synthesis: Synthesis, out_dir: str | Path, scene: str) -> dict[str, Path]:
    """Write a synthesis as ``<scene>-multispectral.exr``, ``-synthetic-raw.exr``, ``-rgb.png``.

    Parameters
    ----------
    synthesis : Synthesis
        From :func:`synthesize_multispectral`.
    out_dir : str or Path
        Output folder (created if needed).
    scene : str
        File-name stem.

    Returns
    -------
    dict of str to Path
        ``"multispectral"``, ``"raw"`` and ``"rgb"`` → the written files (atomic writes).
    """
    if not scene or "/" in scene or "\\" in scene:
        raise DataError(f"scene name {scene!r} cannot be used in a file name")
    folder = Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {
        "multispectral": folder / f"{scene}-multispectral.exr",
        "raw": folder / f"{scene}-synthetic-raw.exr",
        "rgb": folder / f"{scene}-synthetic-rgb.png",
    }
    write_spectral_exr(paths["multispectral"], synthesis.multispectral)
    write_raw_exr(paths["raw"], synthesis.raw)
    write_png(paths["rgb"], to_display(synthesis.rgb))
    return paths
