"""Whether an image holds usable light: refused where it enters a calibration or a
reconstruction, never carried into a result that looks complete.

An image is refused if it has NaN/Inf values, no light (its 99th percentile is ≤ 0: all
zeros, or negated), more negative than positive signal (negated, or a dark frame
subtracted twice), or saturation almost everywhere (≥ 99 % of its pixels at the
saturation level: 1.0 for images scaled to a fraction of saturation, as ``labkit hdr`` and
:func:`labkit.io.read_mosaic` give them, or the integer type's largest value).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from labkit.errors import DataError

SATURATED_FRACTION = 0.99
"""Share of saturated pixels from which an image holds nothing to measure."""


def light_problem(image: ArrayLike, *, saturation: float | None = None) -> str | None:
    """What makes `image` unusable as a measurement of light, or None if nothing does.

    `saturation` is the value of a saturated pixel (default: 1.0 for floats, the largest
    value of an integer type).
    """
    values = np.asarray(image)
    if values.size == 0:
        return "it is empty"
    if values.dtype.kind not in "biuf":
        return f"it holds {values.dtype} values, not numbers"
    finite = np.isfinite(values)
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        return (
            f"it has {int((~finite).sum())} NaN/Inf value(s), first at (row, col) = "
            f"{tuple(int(i) for i in bad[:2])}"
        )
    flat = values.reshape(-1).astype(np.float64, copy=False)
    if np.percentile(flat, 99) <= 0:
        return "it holds no light (99 % of its values are ≤ 0: all zeros, or negated)"
    positive = float(flat[flat > 0].sum())
    negative = float(-flat[flat < 0].sum())
    if negative > positive:
        return (
            f"its negative values outweigh its positive ones ({negative:.3g} against "
            f"{positive:.3g}): it looks negated, or its dark frame was subtracted twice"
        )
    if saturation is None:
        saturation = float(np.iinfo(values.dtype).max) if values.dtype.kind in "iu" else 1.0
    saturated = float(np.count_nonzero(flat >= saturation * (1 - 1e-3))) / flat.size
    if saturated >= SATURATED_FRACTION:
        return (
            f"{saturated:.1%} of its pixels are saturated (≥ {saturation:.4g}): there is "
            "nothing to measure; re-take it with a shorter exposure or less light"
        )
    return None


def check_light(
    image: ArrayLike, *, name: str, fix: str = "", saturation: float | None = None
) -> None:
    """Raise DataError naming `name` (and the `fix`) if :func:`light_problem` finds one."""
    problem = light_problem(image, saturation=saturation)
    if problem is not None:
        raise DataError(f"{name}: {problem}" + (f"; {fix}" if fix else ""))
