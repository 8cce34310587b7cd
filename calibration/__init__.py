"""Calibration: vignetting, keypoints, dispersion models, channel sensitivity, optical blur
(thesis §3.2, §4.2.4).

Contents
--------
Dispersion calibration (thesis §3.2; :func:`calibrate_dispersion` runs the chain)
    :class:`DispersionModel`, :func:`load_dispersion_model` — the YAML model file and
    ``model.displacement(x, y, wavelength_nm)`` / ``(x, y, channel="R")`` in px;
    :class:`DispersionKeypoints` — sparse displacement samples;
    :func:`disk_keypoints`, :func:`channel_disk_keypoints`, :func:`detect_disks`,
    :func:`fit_disks` — disk centres (§3.2.1, :mod:`calibration.disks`);
    :func:`registration_keypoints`, :func:`channel_registration_keypoints`,
    :func:`patch_shifts` — patch-wise registration (§3.2.3, :mod:`calibration.registration`);
    :func:`fit_polynomial_model` — Algorithm 1 (:mod:`calibration.polynomial`);
    :func:`fit_spline_model` — thin-plate splines, Algorithm 2 (:mod:`calibration.spline`);
    :func:`filter_bands` — effective wavelength and purity of each filter band;
    :func:`plot_model`, :func:`plot_keypoint_residuals` — figures.
Vignetting (§3.2.2, :mod:`calibration.vignetting`)
    :class:`VignettingModel`, :func:`fit_vignetting`, :func:`background_mask`.
Correction by warping (the Rudakova–Monasse baseline, :mod:`calibration.warp`)
    :func:`warp`, :func:`correct_channels`, :func:`correct_spectral`.
Channel sensitivity (thesis Algorithm 12, :mod:`calibration.sensitivity`)
    :class:`ChannelSensitivity` — R/G and B/G per filter band, CSV/YAML files;
    :func:`channel_sensitivity` — calibrate it from filtered HDR images;
    :func:`nominal_channel_sensitivity` — what a rig's camera response predicts;
    :func:`plot_channel_sensitivity` — measured vs nominal (thesis Figure 4.12).
Multispectral synthesis (thesis Algorithm 13, :mod:`calibration.multispectral`)
    :class:`Synthesis`, :func:`synthesize_multispectral`, :func:`write_synthesis`,
    :func:`green_bilinear`.
Optical blur (beyond the thesis, :mod:`calibration.edge_blur`)
    :class:`EdgeBlur`, :func:`edge_blur` — the blur of a raw image, measured on a chart's
    patch edges (what the simulated rig's ``blur_sigma_px`` is chosen from).
HDR inputs
    :func:`load_filtered_hdr`, :func:`load_scene_hdr` — images of an HDR folder;
    :func:`source_of` — the file an image was read from.
"""

from calibration._hdr_inputs import load_filtered_hdr, load_scene_hdr, source_of
from calibration.bands import FilterBand, filter_bands
from calibration.disks import (
    background_mask,
    channel_disk_keypoints,
    detect_disks,
    disk_keypoints,
    fit_disks,
)
from calibration.dispersion_calibration import DispersionCalibration, calibrate_dispersion
from calibration.dispersion_model import DispersionModel, load_dispersion_model
from calibration.edge_blur import EdgeBlur, edge_blur
from calibration.keypoints import DispersionKeypoints
from calibration.multispectral import (
    Synthesis,
    green_bilinear,
    synthesize_multispectral,
    write_synthesis,
)
from calibration.plots import plot_keypoint_residuals, plot_model
from calibration.polynomial import fit_polynomial_model
from calibration.registration import (
    channel_registration_keypoints,
    patch_shifts,
    registration_keypoints,
)
from calibration.sensitivity import (
    ChannelSensitivity,
    channel_sensitivity,
    nominal_channel_sensitivity,
    plot_channel_sensitivity,
)
from calibration.spline import fit_spline_model
from calibration.vignetting import VignettingModel, fit_vignetting
from calibration.warp import correct_channels, correct_spectral, warp

__all__ = [
    "ChannelSensitivity",
    "DispersionCalibration",
    "DispersionKeypoints",
    "DispersionModel",
    "EdgeBlur",
    "FilterBand",
    "Synthesis",
    "VignettingModel",
    "background_mask",
    "calibrate_dispersion",
    "channel_disk_keypoints",
    "channel_registration_keypoints",
    "channel_sensitivity",
    "correct_channels",
    "correct_spectral",
    "detect_disks",
    "disk_keypoints",
    "edge_blur",
    "filter_bands",
    "fit_disks",
    "fit_polynomial_model",
    "fit_spline_model",
    "fit_vignetting",
    "green_bilinear",
    "load_dispersion_model",
    "load_filtered_hdr",
    "load_scene_hdr",
    "nominal_channel_sensitivity",
    "patch_shifts",
    "plot_channel_sensitivity",
    "plot_keypoint_residuals",
    "plot_model",
    "registration_keypoints",
    "source_of",
    "synthesize_multispectral",
    "warp",
    "write_synthesis",
]
