"""Preview images (PNG) of raw mosaics and colour images, for people to look at."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from labkit.cfa import check_layout
from labkit.errors import DataError
from labkit.io.atomic import atomic_write


def demosaic_bilinear(raw: np.ndarray, layout: str) -> np.ndarray:
    """Bilinear demosaic of a (rows, cols) mosaic into (rows, cols, 3) float32.

    The mosaic is mirrored by 2 pixels first (which keeps the Bayer phase), so borders
    are interpolated from real neighbours instead of zero padding.
    """
    from colour_demosaicing import demosaicing_CFA_Bayer_bilinear

    padded = np.pad(np.asarray(raw, dtype=np.float64), 2, mode="reflect")
    rgb = demosaicing_CFA_Bayer_bilinear(padded, check_layout(layout))[2:-2, 2:-2]
    return rgb.astype(np.float32)


def raw_preview(
    raw: np.ndarray,
    layout: str,
    *,
    black_level: float = 0.0,
    white_balance: bool = True,
    max_side: int | None = 1024,
) -> np.ndarray:
    """A display image (rows, cols, 3) uint8 of a raw mosaic.

    Bilinear demosaic, black-level subtraction, grey-world white balance, normalisation
    to the 99.5th percentile, sRGB-like gamma; optionally downsampled so the longer side
    is at most `max_side` pixels.
    """
    rgb = demosaic_bilinear(np.asarray(raw, dtype=np.float32) - black_level, layout)
    np.maximum(rgb, 0, out=rgb)
    if white_balance:
        means = rgb.reshape(-1, 3).mean(axis=0)
        if np.all(means > 0):
            rgb *= means.mean() / means
    return to_display(rgb, max_side=max_side)


def to_display(
    linear_rgb: np.ndarray,
    *,
    max_side: int | None = 1024,
    percentile: float = 99.5,
    white: float | None = None,
) -> np.ndarray:
    """Linear (rows, cols, 3) → gamma-encoded uint8, scaled to the given percentile.

    `white`, when given, is the linear value shown as white instead (to show several
    images on one scale).
    """
    image = np.asarray(linear_rgb, dtype=np.float32)
    if max_side and max(image.shape[:2]) > max_side:
        step = int(np.ceil(max(image.shape[:2]) / max_side))
        rows = image.shape[0] // step * step
        cols = image.shape[1] // step * step
        image = (
            image[:rows, :cols]
            .reshape(rows // step, step, cols // step, step, -1)
            .mean(axis=(1, 3))
        )
    scale = float(np.percentile(image, percentile)) if white is None else float(white)
    if not np.isfinite(scale) or scale <= 0:
        scale = 1.0
    normalised = np.clip(image / scale, 0.0, 1.0)
    encoded: np.ndarray = np.where(
        normalised <= 0.0031308, 12.92 * normalised, 1.055 * normalised ** (1 / 2.4) - 0.055
    )
    return (encoded * 255 + 0.5).astype(np.uint8)


def display_on_one_scale(
    images: dict[str, np.ndarray], *, reference: str | None = None, percentile: float = 99.5
) -> dict[str, np.ndarray]:
    """Display images (uint8) of linear colour images, all on the scale of one of them.

    Grey-world white balance and the `percentile` white point come from `reference`
    (default: the first image), so differences between the images stay visible.
    """
    first = images[reference if reference is not None else next(iter(images))]
    means = np.maximum(first, 0).reshape(-1, 3).mean(axis=0)
    gains = np.where(means > 0, means.mean() / np.maximum(means, 1e-30), 1.0)
    white = float(np.percentile(np.maximum(first, 0) * gains, percentile))
    return {
        name: to_display(np.maximum(image, 0) * gains, max_side=None, white=white)
        for name, image in images.items()
    }


@dataclass(frozen=True)
class SpectralPreview:
    """A display image of a spectral image and how its colours were balanced.

    Attributes
    ----------
    image : ndarray (rows, cols, 3) uint8
        sRGB.
    white_balance : str
        ``"grey-world"`` (the image's mean colour shown as neutral, CAT02 adaptation to
        D65) or ``"none"`` (the colours relative to the light the spectra are relative to).
    scene_white_xy : tuple of float or None
        CIE 1931 chromaticity taken as white (grey-world only).
    """

    image: np.ndarray
    white_balance: str
    scene_white_xy: tuple[float, float] | None = None

    def as_dict(self) -> dict[str, Any]:
        """For logs: the method and the white."""
        return {"white_balance": self.white_balance, "scene_white_xy": self.scene_white_xy}


def spectral_preview(
    spectral: np.ndarray,
    wavelengths_nm: np.ndarray,
    *,
    percentile: float = 99.5,
    white_balance: bool = True,
) -> SpectralPreview:
    """sRGB preview of a spectral image (CIE 1931 2° → sRGB, colour-science).

    With `white_balance` the image's mean colour is taken as the scene's white
    (grey-world) and adapted to D65 (von Kries, CAT02), so the light's own colour (a
    projector lamp's green and yellow lines) does not tint the preview. The `percentile`
    of luminance Y is shown as white.
    """
    from labkit.spectra.conversion import (
        adapt_to_d65,
        grey_world_white,
        spectral_to_xyz,
        xyz_to_srgb,
    )

    xyz = spectral_to_xyz(spectral, np.asarray(wavelengths_nm, dtype=np.float64))
    white_xy = None
    if white_balance:
        white = grey_world_white(xyz)
        xyz = adapt_to_d65(xyz, white)
        white_xy = (float(white[0] / white.sum()), float(white[1] / white.sum()))
    scale = float(np.percentile(xyz[..., 1], percentile))
    if not np.isfinite(scale) or scale <= 0:
        scale = 1.0
    image = (xyz_to_srgb(xyz / scale) * 255 + 0.5).astype(np.uint8)
    return SpectralPreview(image, "grey-world" if white_balance else "none", white_xy)


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write a uint8 (rows, cols[, 3]) image as PNG, atomically."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise DataError(f"PNG {path}: expected uint8 pixels, got {image.dtype}")
    with atomic_write(path) as handle:
        Image.fromarray(image).save(handle, format="PNG")
