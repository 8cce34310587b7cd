"""Figures of calibration results: dispersion fields, keypoint residuals, vignetting."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.dispersion_model import DispersionModel
from calibration.keypoints import DispersionKeypoints
from labkit.plots import plot_dispersion_field, plt, save_figure


def _bands(model: DispersionModel) -> list:
    if model.variables == "xy":
        return model.channels
    bands = [float(b) for b in model.provenance.get("bands", [])]
    others = [b for b in bands if abs(b - float(model.reference)) > 0.5]
    if not others and model.region.wavelength_nm is not None:
        others = list(model.region.wavelength_nm)
    return others


def plot_model(model: DispersionModel, path: str | Path, *, bands: list | None = None) -> Path:
    """Signed radial magnitude and angle of a model's dispersion per band (Figure 5.3).

    Parameters
    ----------
    model : DispersionModel
    path : str or Path
        PNG to write.
    bands : list, optional
        Wavelengths (nm) or channels to show (default: every calibrated non-reference band).
    """
    bands = bands or _bands(model)

    def field(x: np.ndarray, y: np.ndarray, band: float | str):
        if model.variables == "xy":
            return model.displacement(x, y, channel=band)
        return model.displacement(x, y, band)

    reference = (
        str(model.reference) if model.variables == "xy" else f"{float(model.reference):.1f} nm"
    )
    plot_dispersion_field(
        field,
        model.image_shape,
        bands,
        path,
        reference=f"{reference} ({model.type}, {model.direction})",
        hull=model.region.hull_xy,
    )
    return Path(path)


def keypoint_residuals(
    model: DispersionModel, keypoints: DispersionKeypoints
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Model input positions and residuals (measured − model) of keypoints, px."""
    if model.direction == "from_reference":
        x, y, dx, dy = keypoints.x, keypoints.y, keypoints.dx, keypoints.dy
    else:
        x, y, dx, dy = keypoints.swapped()
    if keypoints.spectral:
        mx, my = model.displacement(x, y, keypoints.wavelength_nm)
    else:
        mx, my = np.zeros_like(x), np.zeros_like(y)
        for channel in np.unique(keypoints.channel):
            pick = keypoints.channel == channel
            mx[pick], my[pick] = model.displacement(x[pick], y[pick], channel=str(channel))
    return x, y, dx - mx, dy - my


def plot_keypoint_residuals(
    model: DispersionModel, keypoints: DispersionKeypoints, path: str | Path
) -> Path:
    """Keypoint residuals: arrows over the image (magnified) and RMS per band."""
    x, y, rx, ry = keypoint_residuals(model, keypoints)
    labels = keypoints.band
    bands = keypoints.bands
    rms = [float(np.sqrt(np.mean(rx[labels == b] ** 2 + ry[labels == b] ** 2))) for b in bands]
    figure, (left, right) = plt.subplots(1, 2, figsize=(12, 4.8))
    magnitude = np.hypot(rx, ry)
    scale = 0.05 * max(model.image_shape) / max(float(np.percentile(magnitude, 99)), 1e-6)
    left.quiver(x, y, rx * scale, ry * scale, magnitude, angles="xy", scale_units="xy", scale=1)
    left.set_xlim(0, model.image_shape[1])
    left.set_ylim(model.image_shape[0], 0)
    left.set_aspect("equal")
    left.set_title(f"residuals × {scale:.0f} (colour: |r| px)")
    names = [f"{b:g}" if isinstance(b, float) else str(b) for b in bands]
    right.bar(names, rms)
    right.set_xlabel("band (nm)" if keypoints.spectral else "channel")
    right.set_ylabel("RMS residual (px)")
    right.set_title(f"{len(keypoints)} {keypoints.source} keypoints, {model.type} model")
    figure.tight_layout()
    save_figure(figure, path)
    return Path(path)


def plot_vignetting(model, path: str | Path) -> Path:
    """The fitted relative illumination of a :class:`~calibration.vignetting.VignettingModel`."""
    image = model.image()
    figure, axis = plt.subplots(figsize=(6, 4.6))
    shown = axis.imshow(image, cmap="magma")
    axis.contour(image, levels=8, colors="white", linewidths=0.5)
    axis.set_title(f"relative illumination (degree {model.degree})")
    figure.colorbar(shown, ax=axis, shrink=0.8)
    save_figure(figure, path)
    return Path(path)
