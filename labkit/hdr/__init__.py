"""HDR raw images from exposure brackets (thesis §4.2.3, Algorithm 11, and a noise-aware merge).

- :mod:`~labkit.hdr.stack` — streaming replicate statistics (mean, max, variance)
- :mod:`~labkit.hdr.scaling` — exposure scaling factors from the first principal component
- :mod:`~labkit.hdr.levels` — black and saturation levels, dark frames
- :mod:`~labkit.hdr.weights` — the thesis' blending weights (4.1), (4.2) with erosion
- :mod:`~labkit.hdr.blending` — the merge's weightings by name (``thesis``, ``noise``)
- :mod:`~labkit.hdr.noise` — Poisson–Gaussian noise fitted from replicates and darks
- :mod:`~labkit.hdr.merge` — one bracket → one HDR mosaic (``thesis`` or ``noise`` weights)
- :mod:`~labkit.hdr.session` — a whole session → ``OUT/<scene>/<illumination>.exr``
"""

from labkit.hdr.blending import BLENDINGS
from labkit.hdr.levels import DarkFrame, SensorLevels
from labkit.hdr.merge import (
    METHODS,
    ExposureSummary,
    HDRResult,
    merge_exposures,
)
from labkit.hdr.noise import NoiseEstimator, NoiseModel
from labkit.hdr.scaling import PairFactor, fit_pair_factor
from labkit.hdr.session import (
    HDRJob,
    HDRPlan,
    HDRRun,
    factor_table,
    image_summary,
    plan_hdr,
    plan_sessions,
    run_hdr,
)
from labkit.hdr.stack import ExposureInput, FrameSource, FrameStats, accumulate
from labkit.hdr.weights import blend_weight, bloom_weight, local_weight

__all__ = [
    "BLENDINGS",
    "METHODS",
    "DarkFrame",
    "ExposureInput",
    "ExposureSummary",
    "FrameSource",
    "FrameStats",
    "HDRJob",
    "HDRPlan",
    "HDRResult",
    "HDRRun",
    "NoiseEstimator",
    "NoiseModel",
    "PairFactor",
    "SensorLevels",
    "accumulate",
    "blend_weight",
    "bloom_weight",
    "factor_table",
    "fit_pair_factor",
    "image_summary",
    "local_weight",
    "merge_exposures",
    "plan_hdr",
    "plan_sessions",
    "run_hdr",
]
