"""Data shipped with labkit: measured lab spectra and real frames from the thesis' lab."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

#: File-name patterns of the vendored real frames (``labkit session import --pattern``).
REAL_COLORCHECKER_PATTERNS = (
    "d2_{scene}_{illumination}_{exposure}_{date}-{replicate}.tif",
    "d2_dark_{exposure}_{date}-{replicate}.tif",
)


def real_colorchecker() -> Path:
    """Folder of the real ColorChecker frames (``frames/``, ``darks/``, ``labels.png``).

    Seven bandpass filters × seven exposures of a ColorChecker Classic and 14 dark
    frames from a Flea3 FL3-GE-50S5C, reduced to 8 bits and 1/6 size (342×408, GBRG);
    its ``README.md`` says how they were made and under which licence.
    """
    return Path(str(resources.files("labkit") / "data" / "real_colorchecker"))
