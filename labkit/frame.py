"""A captured frame and its metadata, as every camera backend returns it, and its plan key."""

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


DARK = "dark"

_FORBIDDEN = set('/\\:*?"<>|')


def path_name_problem(name: str) -> str | None:
    """Why `name` (a scene or illumination) cannot name a file or folder, or None if it can.

    Scene and illumination names become path components of session frames
    (``frames/<scene>/<illumination>/…``) and HDR images (``<scene>/<illumination>.exr``),
    so they must be one plain component: not empty, not ``.``/``..`` or hidden (a leading
    dot), no path separator, no control or reserved characters, at most 100 characters.
    """
    if not isinstance(name, str) or not name:
        return "it is empty or not text"
    if name.startswith("."):
        return "it starts with a dot (a hidden or parent-folder name)"
    if len(name) > 100:
        return "it is longer than 100 characters"
    bad = sorted({c for c in name if c in _FORBIDDEN or ord(c) < 32 or ord(c) == 127})
    if bad:
        return f"it contains {', '.join(repr(c) for c in bad)}"
    if name != name.strip():
        return "it starts or ends with white space"
    return None


def exposure_label(exposure_s: float) -> str:
    """A file-name-safe, unique label of an exposure time, e.g. ``12ms``, ``3.916s``."""
    if exposure_s >= 1.0:
        return f"{exposure_s:.6g}s"
    if exposure_s >= 1e-3:
        return f"{exposure_s * 1e3:.6g}ms"
    return f"{exposure_s * 1e6:.6g}us"


@dataclass(frozen=True, order=True)
class FrameKey:
    """Identifies one planned frame. Dark frames have ``scene=None``, illumination ``dark``."""

    scene: str | None
    illumination: str
    exposure_s: float
    replicate: int

    @property
    def id(self) -> str:
        """Unique text id, e.g. ``disks/450/100ms/r002`` or ``dark/100ms/r002``."""
        parts = [self.scene, self.illumination] if self.scene is not None else [DARK]
        return "/".join([*parts, exposure_label(self.exposure_s), f"r{self.replicate:03d}"])

    @property
    def path(self) -> str:
        """File path of the frame inside a session folder."""
        return f"frames/{self.id}.tiff"

    @property
    def is_dark(self) -> bool:
        """Whether this is a dark (covered-light) frame."""
        return self.scene is None
