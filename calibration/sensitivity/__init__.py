"""Relative sensitivity of the colour channels per filter band (thesis §4.2.4, Algorithm 12).

Under narrowband light of band b every channel sees the same scene radiance, so in
textureless regions neighbouring pixels of different colours are proportional:
``R ≈ r_b G`` and ``B ≈ b_b G``. Algorithm 12 estimates ``r_b = R/G`` and ``b_b = B/G``
from HDR images (values: fraction of saturation):

1. per CFA colour plane (the four stride-2 sub-images, so no gradient crosses channels),
   keep pixels whose gradient magnitude is at most the plane's median (a quantile, by
   default 0.5);
2. keep values strictly between 0 and `saturation` (0.95 of saturation);
3. pair every Green pixel with its 4-neighbour Red pixels, and separately its 4-neighbour
   Blue pixels, keeping a pair only if both members passed; pool the pairs of every
   image (scene) of the band;
4. fit the line through the origin along the first principal component of the
   (G, R) and (G, B) point clouds (:func:`labkit.fitting.principal_slope`).

**Signal test.** A band can be dark in one channel (e.g. Red at 400 nm on most sensors):
its ratio is then noise. A channel *has signal* in a band when the median of its kept
pixels is at least `min_signal_ratio` (default 1 %) of the median of the kept Green
pixels; Green has signal when its median is at least `min_signal_ratio` of the brighter
of the Red and Blue medians. A ratio whose channel (or Green) lacks signal, or that rests
on fewer than `min_pairs` pairs, is reported with ``reliable = False`` and a reason; when
nothing can be fitted it is NaN, again with ``reliable = False`` — never a silent NaN.

:func:`nominal_channel_sensitivity` gives the ratios a rig's camera response predicts,
``∫ q_c T L dλ / ∫ q_G T L dλ`` (thesis Figure 4.12, dotted lines); for the simulated rig
they are the ground truth for a spectrally flat scene.
"""

from calibration.sensitivity.nominal import nominal_channel_sensitivity
from calibration.sensitivity.plot import plot_channel_sensitivity
from calibration.sensitivity.ratios import (
    channel_sensitivity,
    green_level,
    neighbour_pairs,
    smooth_unsaturated_mask,
)
from calibration.sensitivity.table import (
    BAND_TOLERANCE_NM,
    COLUMNS,
    FORMAT_VERSION,
    ChannelSensitivity,
    is_sensitivity_file,
    load_response,
)

__all__ = [
    "BAND_TOLERANCE_NM",
    "COLUMNS",
    "FORMAT_VERSION",
    "ChannelSensitivity",
    "channel_sensitivity",
    "green_level",
    "is_sensitivity_file",
    "load_response",
    "neighbour_pairs",
    "nominal_channel_sensitivity",
    "plot_channel_sensitivity",
    "smooth_unsaturated_mask",
]
