"""Dispersion keypoints: sparse samples of lateral chromatic aberration (thesis §3.2.1, §3.2.3).

A keypoint says that a feature imaged at ``(x, y)`` in the reference image (a reference
filter band or the Green channel) is imaged at ``(x + dx, y + dy)`` in another band or
colour channel. Keypoints come from disk centres (:mod:`calibration.disks`) or patch-wise
registration (:mod:`calibration.registration`) and are what the dispersion models
(:mod:`calibration.polynomial`, :mod:`calibration.spline`) are fitted to.

Spectral keypoints carry the band's wavelength (nm); colour-channel keypoints carry a
channel name (``"R"`` or ``"B"``, relative to ``"G"``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from labkit.errors import DataError
from labkit.io import write_text_atomic


@dataclass(frozen=True)
class DispersionKeypoints:
    """Keypoints in the ``from_reference`` direction.

    Attributes
    ----------
    x, y : ndarray (n,) float64
        Position in the reference image, px (x = column, y = row).
    dx, dy : ndarray (n,) float64
        Displacement to the same feature in the band, px (band − reference).
    wavelength_nm : ndarray (n,) float64 or None
        Band wavelength of each keypoint, nm (spectral keypoints).
    channel : ndarray (n,) str or None
        Colour channel of each keypoint (colour-channel keypoints).
    reference : float or str
        Reference wavelength (nm) or channel (``"G"``).
    image_shape : (rows, cols)
        Size of the images the keypoints were measured in, px.
    source : str
        ``"disks"`` or ``"registration"`` (or anything describing the origin).
    quality : ndarray (n,) float64 or None
        Per-keypoint fit residual (disks: RMS of the disk-model fit relative to the
        disk's contrast; registration: phase-correlation error), for plots and filtering.
    meta : dict
        Provenance (files, bands dropped and why, options).
    """

    x: np.ndarray
    y: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    reference: float | str
    image_shape: tuple[int, int]
    wavelength_nm: np.ndarray | None = None
    channel: np.ndarray | None = None
    source: str = "disks"
    quality: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        arrays = {}
        for name in ("x", "y", "dx", "dy"):
            arrays[name] = np.asarray(getattr(self, name), dtype=np.float64).ravel()
        n = arrays["x"].size
        for name in ("wavelength_nm", "quality"):
            value = getattr(self, name)
            if value is not None:
                arrays[name] = np.asarray(value, dtype=np.float64).ravel()
        if self.channel is not None:
            arrays["channel"] = np.asarray(self.channel, dtype=str).ravel()
        for name, value in arrays.items():
            if value.size != n:
                raise DataError(f"keypoint field {name!r} has {value.size} values, x has {n}")
            if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
                raise DataError(f"keypoint field {name!r} holds NaN or Inf")
            object.__setattr__(self, name, value)
        if (self.wavelength_nm is None) == (self.channel is None):
            raise DataError("keypoints need exactly one of wavelength_nm (spectral) or channel")
        object.__setattr__(
            self, "image_shape", (int(self.image_shape[0]), int(self.image_shape[1]))
        )

    # -- views ----------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.x.size)

    @property
    def spectral(self) -> bool:
        """True for keypoints between filter bands, False for colour channels."""
        return self.wavelength_nm is not None

    @property
    def band(self) -> np.ndarray:
        """Per-keypoint band label: wavelength (nm) or channel name."""
        return self.wavelength_nm if self.wavelength_nm is not None else self.channel

    @property
    def bands(self) -> list[float] | list[str]:
        """Distinct bands, sorted."""
        return sorted(np.unique(self.band).tolist())

    def positions(self) -> np.ndarray:
        """Reference positions (n, 2) as (x, y), px."""
        return np.column_stack([self.x, self.y])

    def displacements(self) -> np.ndarray:
        """Displacements (n, 2) as (dx, dy), px."""
        return np.column_stack([self.dx, self.dy])

    def select(self, mask: np.ndarray) -> DispersionKeypoints:
        """The keypoints where boolean `mask` (or an index array) selects."""
        pick = np.asarray(mask)

        def part(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[pick]

        return DispersionKeypoints(
            self.x[pick],
            self.y[pick],
            self.dx[pick],
            self.dy[pick],
            reference=self.reference,
            image_shape=self.image_shape,
            wavelength_nm=part(self.wavelength_nm),
            channel=part(self.channel),
            source=self.source,
            quality=part(self.quality),
            meta=dict(self.meta),
        )

    def for_band(self, band: float | str) -> DispersionKeypoints:
        """Keypoints of one band (wavelength in nm or channel name)."""
        if self.spectral:
            return self.select(np.isclose(self.wavelength_nm, float(band)))
        return self.select(self.channel == str(band))

    def subsample(self, fraction: float, *, rng: np.random.Generator) -> DispersionKeypoints:
        """A random `fraction` of the keypoints (at least one per band)."""
        if not 0 < fraction <= 1:
            raise DataError(f"subsample fraction must be in (0, 1], got {fraction}")
        keep = rng.random(len(self)) < fraction
        for b in self.bands:
            in_band = np.flatnonzero(self.band == b)
            if in_band.size and not keep[in_band].any():
                keep[rng.choice(in_band)] = True
        return self.select(keep)

    def swapped(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Positions and displacements in the ``to_reference`` direction.

        Returns ``(x + dx, y + dy, −dx, −dy)``: the band position and the displacement
        that maps it back to the reference image (thesis §3.2.4, last paragraph).
        """
        return self.x + self.dx, self.y + self.dy, -self.dx, -self.dy

    @staticmethod
    def concatenate(parts: Sequence[DispersionKeypoints]) -> DispersionKeypoints:
        """Join keypoint sets measured against the same reference in the same images."""
        if not parts:
            raise DataError("no keypoint sets to concatenate")
        first = parts[0]
        for p in parts[1:]:
            if p.reference != first.reference or p.image_shape != first.image_shape:
                raise DataError(
                    "keypoint sets disagree in reference or image size: "
                    f"{first.reference}/{first.image_shape} vs {p.reference}/{p.image_shape}"
                )
            if p.spectral != first.spectral:
                raise DataError("cannot join spectral and colour-channel keypoints")

        def cat(name: str) -> np.ndarray | None:
            values = [getattr(p, name) for p in parts]
            if any(v is None for v in values):
                return None
            return np.concatenate(values)

        return DispersionKeypoints(
            cat("x"),
            cat("y"),
            cat("dx"),
            cat("dy"),
            reference=first.reference,
            image_shape=first.image_shape,
            wavelength_nm=cat("wavelength_nm"),
            channel=cat("channel"),
            source=first.source,
            quality=cat("quality"),
            meta={k: v for p in parts for k, v in p.meta.items()},
        )

    def to_csv(self, path: str | Path) -> Path:
        """Write the keypoints as CSV (x, y, dx, dy, band, quality), atomically."""
        band = self.band.astype(str)
        quality = self.quality if self.quality is not None else np.full(len(self), np.nan)
        label = "wavelength_nm" if self.spectral else "channel"
        lines = [f"x,y,dx,dy,{label},quality"]
        lines += [
            f"{x:.4f},{y:.4f},{dx:.5f},{dy:.5f},{b},{q:.4g}"
            for x, y, dx, dy, b, q in zip(
                self.x, self.y, self.dx, self.dy, band, quality, strict=True
            )
        ]
        write_text_atomic(path, "\n".join(lines) + "\n")
        return Path(path)
