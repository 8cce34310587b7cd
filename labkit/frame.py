"""A captured frame and its metadata, as every camera backend returns it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Frame:
    """One raw frame.

    Attributes
    ----------
    image : ndarray (rows, cols), uint8 or uint16
        The Bayer mosaic as delivered in `pixel_format`.
    frame_id : int
        Device frame counter (strictly increasing within an acquisition).
    exposure_s : float
        Exposure requested, s.
    exposure_readback_s : float
        Exposure the device reports it used, s.
    gain_db : float
        Analogue gain, dB.
    pixel_format : str
        GenICam pixel format, e.g. ``BayerGB12``.
    device_timestamp_ns : int
        Device clock at the start of exposure, ns.
    host_timestamp_s : float
        Host wall-clock time when the frame arrived, s since the epoch.
    status : str
        Buffer status, ``"SUCCESS"`` or the backend's failure name.
    extra : dict
        Backend-specific facts (temperature, stream statistics, simulator ground truth).
    """

    image: np.ndarray
    frame_id: int
    exposure_s: float
    exposure_readback_s: float
    gain_db: float
    pixel_format: str
    device_timestamp_ns: int
    host_timestamp_s: float
    status: str = "SUCCESS"
    extra: dict[str, Any] = field(default_factory=dict)
