"""Bayer colour-filter-array layouts.

A layout is named by the channels of its top-left 2×2 block read row by row, e.g.
``"GBRG"``: row 0 = G B, row 1 = R G. Channel indices are 0 = R, 1 = G, 2 = B.
"""

from __future__ import annotations

import numpy as np

from labkit.errors import DataError

CFA_LAYOUTS = ("RGGB", "BGGR", "GRBG", "GBRG")
CHANNELS = ("R", "G", "B")

#: GenICam PFNC pixel-format stems → CFA layout (BayerRG12 → RGGB, …).
_PFNC_STEMS = {"BayerRG": "RGGB", "BayerBG": "BGGR", "BayerGR": "GRBG", "BayerGB": "GBRG"}


def check_layout(layout: str) -> str:
    """Return `layout` upper-cased, or raise DataError naming the valid layouts."""
    name = str(layout).upper()
    if name not in CFA_LAYOUTS:
        raise DataError(f"unknown CFA layout {layout!r}; use one of {', '.join(CFA_LAYOUTS)}")
    return name


def channel_index(layout: str, shape: tuple[int, int]) -> np.ndarray:
    """Per-pixel channel index (0 R, 1 G, 2 B), shape `shape` (rows, cols), uint8."""
    name = check_layout(layout)
    block = np.array([[CHANNELS.index(c) for c in name[:2]], [CHANNELS.index(c) for c in name[2:]]])
    rows, cols = shape
    tiled = np.tile(block, ((rows + 1) // 2, (cols + 1) // 2))
    return tiled[:rows, :cols].astype(np.uint8)


def channel_masks(layout: str, shape: tuple[int, int]) -> np.ndarray:
    """Boolean masks (rows, cols, 3): True where the pixel senses R, G or B."""
    index = channel_index(layout, shape)
    return index[..., None] == np.arange(3, dtype=np.uint8)


def mosaic(image: np.ndarray, layout: str) -> np.ndarray:
    """Sample a (rows, cols, 3) colour image into a (rows, cols) Bayer mosaic."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise DataError(f"mosaic needs a (rows, cols, 3) image, got shape {image.shape}")
    index = channel_index(layout, image.shape[:2])
    return np.take_along_axis(image, index[..., None].astype(np.intp), axis=2)[..., 0]


def layout_from_pixel_format(pixel_format: str) -> str:
    """CFA layout of a GenICam Bayer pixel format (e.g. ``BayerGB12`` → ``GBRG``)."""
    for stem, layout in _PFNC_STEMS.items():
        if pixel_format.startswith(stem):
            return layout
    raise DataError(
        f"pixel format {pixel_format!r} is not a Bayer format; use Bayer{{RG,BG,GR,GB}}{{8,12,16}}"
    )


def pixel_format_for(layout: str, bits: int) -> str:
    """GenICam pixel-format name for a CFA layout and bit depth (e.g. GBRG, 12 → BayerGB12)."""
    name = check_layout(layout)
    stem = next(s for s, lay in _PFNC_STEMS.items() if lay == name)
    if bits not in (8, 12, 16):
        raise DataError(f"Bayer pixel formats have 8, 12 or 16 bits, not {bits}")
    return f"{stem}{bits}"


def pixel_format_bits(pixel_format: str) -> int:
    """Bits per pixel of a GenICam Bayer format (BayerGB12 → 12, BayerRG12p → 12)."""
    layout_from_pixel_format(pixel_format)
    digits = "".join(ch for ch in pixel_format[len("BayerXX") :] if ch.isdigit())
    if not digits:
        raise DataError(f"pixel format {pixel_format!r} has no bit depth")
    return int(digits)
