"""Exposure scaling factors between consecutive exposures (thesis §4.2.3, Table 4.1).

Instead of trusting the shutter, the factor relating two exposures is fitted from the
pixels that are properly exposed in both (between 2 % and 95 % of the saturation
range): the first principal component of their (shorter, longer) pairs, after
Darrodi et al. It is fitted per colour channel (reported) and for all channels pooled
(used). Factors are chained from pair to pair; the shortest exposure is the reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from labkit.fitting import principal_slope

CHANNEL_NAMES = ("R", "G", "B")


@dataclass
class PairFactor:
    """Fitted ratio between the signals of a longer and a shorter exposure.

    Attributes
    ----------
    longer_s, shorter_s : float
        The two exposure times, s.
    ratio : float
        ``signal(longer) / signal(shorter)``: the fitted value, or the nominal
        ``longer_s / shorter_s`` when `fallback` says why no fit was possible.
    per_channel : dict
        The same ratio fitted per colour channel (None where too few pixels).
    pairs : int
        Number of pixel pairs in the pooled fit.
    fallback : str or None
        Why the nominal ratio was used instead of a fit.
    """

    longer_s: float
    shorter_s: float
    ratio: float
    per_channel: dict[str, float | None] = field(default_factory=dict)
    pairs: int = 0
    fallback: str | None = None

    @property
    def nominal(self) -> float:
        """Ratio of the exposure times."""
        return self.longer_s / self.shorter_s

    @property
    def disagreement(self) -> float:
        """Relative difference of the fitted from the nominal ratio (0.01 = 1 %)."""
        return self.ratio / self.nominal - 1.0


MIN_PAIRS = 100
"""Fewest pixels properly exposed in both of two exposures (and away from clipping) from
which their ratio is fitted; with fewer, the exposure-time ratio is used."""


@fixed_blas_threads
def fit_pair_factor(
    longer: np.ndarray,
    shorter: np.ndarray,
    usable: np.ndarray,
    channels: np.ndarray,
    *,
    longer_s: float,
    shorter_s: float,
    saturation_range: float,
    low: float = 0.02,
    high: float = 0.95,
    min_pairs: int = MIN_PAIRS,
) -> PairFactor:
    """Fit the ratio between two dark-subtracted exposures of the same scene.

    Parameters
    ----------
    longer, shorter : ndarray (rows, cols)
        Mean dark-subtracted signals, DN.
    usable : ndarray of bool (rows, cols)
        Pixels unclipped and unbloomed in both exposures.
    channels : ndarray of int (rows, cols)
        Colour channel of each pixel (0 = R, 1 = G, 2 = B).
    longer_s, shorter_s : float
        Exposure times, s (for the nominal fallback and the report).
    saturation_range : float
        Signal of a saturated pixel, DN (saturation minus black level).
    low, high : float
        Fractions of `saturation_range` a pixel must lie between in both exposures.
    min_pairs : int
        Fewest pixel pairs for a fit; below it the nominal ratio is used.
    """
    lo, hi = low * saturation_range, high * saturation_range
    select = usable & (shorter >= lo) & (shorter <= hi) & (longer >= lo) & (longer <= hi)
    x = shorter[select]
    y = longer[select]
    picked = channels[select]
    nominal = longer_s / shorter_s
    per_channel: dict[str, float | None] = {}
    for index, name in enumerate(CHANNEL_NAMES):
        mine = picked == index
        per_channel[name] = _slope_or_none(x[mine], y[mine], min_pairs)
    result = PairFactor(longer_s, shorter_s, nominal, per_channel, int(x.size))
    if x.size < min_pairs:
        result.fallback = (
            f"only {x.size} pixels lie in [{low:.0%}, {high:.0%}] of saturation at both "
            f"{longer_s:g} s and {shorter_s:g} s (need {min_pairs}); used the exposure-time ratio"
        )
        return result
    result.ratio = principal_slope(x, y).slope
    if not np.isfinite(result.ratio) or result.ratio <= 0:
        result.fallback = f"the fitted ratio {result.ratio!r} is not positive; used the nominal"
        result.ratio = nominal
    return result


def _slope_or_none(x: np.ndarray, y: np.ndarray, min_pairs: int) -> float | None:
    if x.size < min_pairs:
        return None
    try:
        return principal_slope(x, y).slope
    except DataError:
        return None
