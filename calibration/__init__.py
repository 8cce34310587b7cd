"""Calibration: vignetting, keypoints, dispersion models, channel sensitivity (thesis §3.2, §4.2.4).

Built in later issues; this package is part of the labkit distribution from the start.
"""
