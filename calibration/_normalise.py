"""Affine normalisation of keypoint positions, wavelengths and displacements (§3.2.2, §3.2.4).

Fitting polynomials or splines to raw pixel coordinates (0…2448) and wavelengths
(400…700 nm) is badly conditioned. Before any fit:

* positions (x, y) are centred and whitened — zero mean, unit variance along each
  principal direction (an affine map ``u = M (p − o)``);
* wavelengths are centred and scaled to unit variance, separately from positions;
* displacements are centred per component and scaled by one common factor (the x and
  y components are normalised jointly, so the field's direction is not distorted).

The same normaliser is stored with a model and applied when it is evaluated.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration._model_files import float_array
from labkit.errors import ConfigError, DataError


@dataclass(frozen=True)
class Normaliser:
    """Affine maps of inputs and outputs of a displacement field.

    Attributes
    ----------
    xy_offset : ndarray (2,)
        Mean position, px.
    xy_matrix : ndarray (2, 2)
        Whitening matrix, 1/px.
    wavelength_offset, wavelength_scale : float or None
        Mean and standard deviation of wavelengths, nm (spectral fields only).
    displacement_offset : ndarray (2,)
        Mean displacement, px.
    displacement_scale : float
        Common standard deviation of both displacement components, px.
    """

    xy_offset: np.ndarray
    xy_matrix: np.ndarray
    displacement_offset: np.ndarray
    displacement_scale: float
    wavelength_offset: float | None = None
    wavelength_scale: float | None = None

    @property
    def n_inputs(self) -> int:
        """2 for (x, y), 3 for (x, y, λ)."""
        return 2 if self.wavelength_offset is None else 3

    @classmethod
    def fit(
        cls, points: np.ndarray, displacements: np.ndarray, *, what: str = "keypoints"
    ) -> Normaliser:
        """Normaliser of `points` (n, 2 | 3) and `displacements` (n, 2).

        Raises
        ------
        DataError
            The positions do not span an area, or the wavelengths do not vary.
        """
        points = np.asarray(points, dtype=np.float64)
        displacements = np.asarray(displacements, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] not in (2, 3) or len(points) < 3:
            raise DataError(f"{what}: need at least 3 points of (x, y) or (x, y, λ)")
        xy = points[:, :2]
        offset = xy.mean(axis=0)
        cov = np.cov((xy - offset).T)
        eigvals, eigvecs = np.linalg.eigh(cov)
        if eigvals[0] <= 1e-9 * max(eigvals[1], 1e-300):
            raise DataError(
                f"{what}: the positions lie on a line or a point and span no area; "
                "keypoints must cover a 2-D region of the image"
            )
        matrix = (eigvecs / np.sqrt(eigvals)).T
        w_offset = w_scale = None
        if points.shape[1] == 3:
            w = points[:, 2]
            w_offset, w_scale = float(w.mean()), float(w.std())
            if w_scale <= 0:
                raise DataError(
                    f"{what}: all keypoints have the same wavelength; a spectral model needs "
                    "keypoints from several filter bands"
                )
        d_offset = displacements.mean(axis=0)
        d_scale = float(np.sqrt(np.mean((displacements - d_offset) ** 2)))
        if not np.isfinite(d_scale) or d_scale <= 0:
            d_scale = 1.0
        return cls(offset, matrix, d_offset, d_scale, w_offset, w_scale)

    def inputs(self, points: np.ndarray) -> np.ndarray:
        """Normalised inputs (n, 2 | 3) of positions (and wavelengths) `points`."""
        points = np.asarray(points, dtype=np.float64)
        if points.shape[1] != self.n_inputs:
            raise DataError(
                f"this field takes {self.n_inputs} inputs per point, got {points.shape[1]}"
            )
        out = np.empty_like(points)
        out[:, :2] = (points[:, :2] - self.xy_offset) @ self.xy_matrix.T
        if self.n_inputs == 3:
            out[:, 2] = (points[:, 2] - self.wavelength_offset) / self.wavelength_scale
        return out

    def outputs(self, displacements: np.ndarray) -> np.ndarray:
        """Normalised displacements (n, 2) of `displacements` px."""
        return (np.asarray(displacements, dtype=np.float64) - self.displacement_offset) / (
            self.displacement_scale
        )

    def restore(self, normalised: np.ndarray) -> np.ndarray:
        """Displacements in px from normalised ones (n, 2)."""
        return normalised * self.displacement_scale + self.displacement_offset

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "xy": {"offset": self.xy_offset.tolist(), "matrix": self.xy_matrix.tolist()},
            "displacement": {
                "offset": self.displacement_offset.tolist(),
                "scale": float(self.displacement_scale),
            },
        }
        if self.n_inputs == 3:
            out["wavelength"] = {
                "offset": float(self.wavelength_offset),
                "scale": float(self.wavelength_scale),
            }
        return out

    @classmethod
    def from_dict(cls, data: Any, where: str) -> Normaliser:
        """Read back :meth:`to_dict`; errors name `where`."""
        if not isinstance(data, Mapping) or "xy" not in data or "displacement" not in data:
            raise ConfigError(f"{where} must have `xy` and `displacement` entries")
        xy, disp = data["xy"], data["displacement"]
        if not isinstance(xy, Mapping) or not isinstance(disp, Mapping):
            raise ConfigError(f"{where}.xy and {where}.displacement must be mappings")
        w_offset = w_scale = None
        if "wavelength" in data:
            wl = data["wavelength"]
            if not isinstance(wl, Mapping):
                raise ConfigError(f"{where}.wavelength must be a mapping")
            w_offset = float(float_array(wl.get("offset"), f"{where}.wavelength.offset", shape=()))
            w_scale = float(float_array(wl.get("scale"), f"{where}.wavelength.scale", shape=()))
            if w_scale <= 0:
                raise ConfigError(f"{where}.wavelength.scale must be positive")
        scale = float(float_array(disp.get("scale"), f"{where}.displacement.scale", shape=()))
        if scale <= 0:
            raise ConfigError(f"{where}.displacement.scale must be positive")
        return cls(
            float_array(xy.get("offset"), f"{where}.xy.offset", shape=(2,)),
            float_array(xy.get("matrix"), f"{where}.xy.matrix", shape=(2, 2)),
            float_array(disp.get("offset"), f"{where}.displacement.offset", shape=(2,)),
            scale,
            w_offset,
            w_scale,
        )
