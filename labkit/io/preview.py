"""Preview images (PNG) of raw mosaics and colour images, for people to look at."""

from __future__ import annotations

from pathlib import Path

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
    linear_rgb: np.ndarray, *, max_side: int | None = 1024, percentile: float = 99.5
) -> np.ndarray:
    """Linear (rows, cols, 3) → gamma-encoded uint8, scaled to the given percentile."""
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
    scale = float(np.percentile(image, percentile))
    if not np.isfinite(scale) or scale <= 0:
        scale = 1.0
    normalised = np.clip(image / scale, 0.0, 1.0)
    encoded = np.where(
        normalised <= 0.0031308, 12.92 * normalised, 1.055 * normalised ** (1 / 2.4) - 0.055
    )
    return (encoded * 255 + 0.5).astype(np.uint8)


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write a uint8 (rows, cols[, 3]) image as PNG, atomically."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise DataError(f"PNG {path}: expected uint8 pixels, got {image.dtype}")
    with atomic_write(path) as handle:
        Image.fromarray(image).save(handle, format="PNG")
