"""Calibration: vignetting, keypoints, dispersion models, channel sensitivity (thesis §3.2, §4.2.4).

Contents
--------
Channel sensitivity (thesis Algorithm 12, :mod:`calibration.sensitivity`)
    :class:`ChannelSensitivity` — R/G and B/G per filter band, CSV/YAML files;
    :func:`channel_sensitivity` — calibrate it from filtered HDR images;
    :func:`nominal_channel_sensitivity` — what a rig's camera response predicts;
    :func:`plot_channel_sensitivity` — measured vs nominal (thesis Figure 4.12).
Multispectral synthesis (thesis Algorithm 13, :mod:`calibration.multispectral`)
    :class:`Synthesis`, :func:`synthesize_multispectral`, :func:`write_synthesis`,
    :func:`green_bilinear`.
HDR inputs
    :func:`load_filtered_hdr` — the filtered images of an HDR folder, per scene.

Vignetting, keypoints and dispersion models are built in later issues.
"""

from calibration._hdr_inputs import load_filtered_hdr
from calibration.multispectral import (
    Synthesis,
    green_bilinear,
    synthesize_multispectral,
    write_synthesis,
)
from calibration.sensitivity import (
    ChannelSensitivity,
    channel_sensitivity,
    nominal_channel_sensitivity,
    plot_channel_sensitivity,
)

__all__ = [
    "ChannelSensitivity",
    "Synthesis",
    "channel_sensitivity",
    "green_bilinear",
    "load_filtered_hdr",
    "nominal_channel_sensitivity",
    "plot_channel_sensitivity",
    "synthesize_multispectral",
    "write_synthesis",
]
