"""What the raw counts are measured against: the sensor's black and saturation levels, and
the dark frame subtracted from each exposure."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from labkit.errors import DataError
from labkit.hdr.stack import ExposureInput, accumulate


@dataclass(frozen=True)
class SensorLevels:
    """Where the raw counts start and stop.

    Attributes
    ----------
    saturation_dn : float
        Count of a saturated pixel (full well or ADC limit), DN.
    black_level_dn : float
        Count of a dark pixel at zero exposure, DN.
    """

    saturation_dn: float
    black_level_dn: float = 0.0

    @property
    def saturation_range(self) -> float:
        """Signal of a saturated pixel above black, DN."""
        return self.saturation_dn - self.black_level_dn

    def __post_init__(self) -> None:
        if not np.isfinite(self.saturation_dn) or self.saturation_range <= 0:
            raise DataError(
                f"saturation {self.saturation_dn} DN must exceed the black level "
                f"{self.black_level_dn} DN"
            )


@dataclass
class DarkFrame:
    """What to subtract from an exposure: the mean dark frame, or a constant black level.

    Attributes
    ----------
    exposure_s : float
        Exposure time, s.
    mean : ndarray (rows, cols) float32 or float
        Mean dark counts, DN.
    variance_dn2 : float or None
        Temporal variance of one dark frame averaged over pixels, DN² (None: unknown).
    count : int
        Dark frames averaged (0 for a constant black level).
    """

    exposure_s: float
    mean: np.ndarray | float
    variance_dn2: float | None
    count: int

    @classmethod
    def from_frames(
        cls,
        exposure: ExposureInput,
        *,
        shape: tuple[int, int] | None = None,
        on_frame: Callable[[], None] | None = None,
    ) -> DarkFrame:
        """Average dark frames (streaming)."""
        stats = accumulate(exposure, shape=shape, with_variance=True, on_frame=on_frame)
        variance = (
            None if stats.variance is None else float(np.mean(stats.variance, dtype=np.float64))
        )
        return cls(exposure.exposure_s, stats.mean, variance, stats.count)

    @classmethod
    def black_level(cls, exposure_s: float, black_level_dn: float) -> DarkFrame:
        """No dark frames: subtract a constant (dark current stays in the image)."""
        return cls(exposure_s, float(black_level_dn), None, 0)
