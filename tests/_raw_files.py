"""Raw files as other software writes them, built at test time (no binary fixtures).

A real frame shipped with labkit (8-bit GBRG, 342×408) becomes a 12-bit DNG with a planted
black level; the tags are the ones LibRaw needs to read a Bayer DNG's levels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import tifffile

from labkit.data import real_colorchecker

#: CFA colour codes of the TIFF/EP CFAPattern tag: 0 red, 1 green, 2 blue.
_CODES = {"R": 0, "G": 1, "B": 2}
#: Fujifilm's 6×6 X-Trans colour filter pattern (CFAPattern codes, row by row).
X_TRANS = (
    1, 1, 0, 1, 1, 2,
    1, 1, 2, 1, 1, 0,
    2, 0, 1, 0, 2, 1,
    1, 1, 2, 1, 1, 0,
    1, 1, 0, 1, 1, 2,
    0, 2, 1, 2, 0, 1,
)  # fmt: skip
#: The 12-bit scaling of the tests: DN = frame · 16 + black, white level 4095 + black.
SCALE = 16
BLACK = 64
WHITE = 4095 + BLACK


def real_frame() -> np.ndarray:
    """A real 8-bit GBRG mosaic (342×408, uint8) of the ColorChecker under the 550 nm filter."""
    folder = real_colorchecker() / "frames"
    (path,) = sorted(folder.glob("d2_colorChecker30cm_550nm_3916ms_*.tif"))
    return tifffile.imread(path)


def write_dng(
    path: Path,
    counts: np.ndarray,
    *,
    cfa: str = "GBRG",
    black: int | tuple[int, int, int, int] = BLACK,
    white: int = WHITE,
    pattern: tuple[int, ...] | None = None,
    extra: tuple = (),
) -> Path:
    """Write `counts` (uint16 DN, black level included) as a minimal Bayer DNG.

    Parameters
    ----------
    path : Path
    counts : ndarray (rows, cols) uint16
        Sensor values, DN.
    cfa : str
        Bayer layout of the top-left 2×2 block (of the active area).
    black : int or 4 ints
        Black level, DN: one for all pixels, or one per 2×2 position (row by row).
    white : int
        White level, DN.
    pattern : tuple of int, optional
        A square CFA pattern (codes 0 R, 1 G, 2 B, row by row) instead of `cfa`.
    extra : tuple
        Further ``tifffile`` extratags (code, dtype, count, value, writeonce).
    """
    codes = tuple(_CODES[c] for c in cfa) if pattern is None else tuple(pattern)
    side = round(len(codes) ** 0.5)
    levels = (black,) if isinstance(black, int) else tuple(black)
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, "labkit test camera", True),  # UniqueCameraModel
        (33421, "H", 2, (side, side), True),  # CFARepeatPatternDim
        (33422, "B", len(codes), codes, True),  # CFAPattern
        (50713, "H", 2, (1, 1) if len(levels) == 1 else (2, 2), True),  # BlackLevelRepeatDim
        (50714, "H", len(levels), levels, True),  # BlackLevel
        (50717, "H", 1, (white,), True),  # WhiteLevel
        *extra,
    ]
    tifffile.imwrite(
        path, np.asarray(counts, np.uint16), photometric=32803, subfiletype=0, extratags=tags
    )
    return path


def frame_dng(path: Path, frame: np.ndarray, **options) -> Path:
    """`frame` (uint8) as 12-bit counts (value · 16 + black) in a DNG; see :func:`write_dng`."""
    return write_dng(path, frame.astype(np.uint16) * SCALE + BLACK, **options)
