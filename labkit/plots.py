"""Figures people would rather look at than read: rig spectra, dispersion, crops, errors."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from labkit.io.atomic import atomic_path


def save_figure(figure: plt.Figure, path: str | Path) -> None:
    """Save a matplotlib figure as PNG atomically and close it."""
    with atomic_path(path) as temp:
        figure.savefig(temp, format="png", dpi=110, bbox_inches="tight")
    plt.close(figure)


def plot_rig_spectra(rig, path: str | Path) -> None:
    """Camera response, lamp and filter transmissions of a simulated rig."""
    w = rig.wavelengths
    figure, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    q = rig.response.resample(w).values
    for index, colour in enumerate("rgb"):
        top.plot(w, q[:, index], color=colour, label=f"camera {'RGB'[index]}")
    top.plot(w, rig.lamp / rig.lamp.max(), "k--", label=f"light: {rig.rig.light.source}")
    top.set_ylabel("relative response / power")
    top.legend(loc="upper right", fontsize=8)
    for name in rig.rig.slider.illumination_names():
        filt = rig.rig.filter_for(name)
        if filt is not None:
            bottom.semilogy(w, filt.transmission(w), label=f"{name} nm")
    bottom.set_ylim(1e-5, 2)
    bottom.set_xlabel("wavelength (nm)")
    bottom.set_ylabel("filter transmission")
    bottom.legend(ncol=4, fontsize=8)
    save_figure(figure, path)


def plot_dispersion(
    lens, wavelengths_nm: list[float], path: str | Path, *, step_px: int = 128
) -> None:
    """Magnitude (colour) and direction (arrows) of d(x, y, λ) relative to the reference."""
    rows, cols = lens.shape
    yy, xx = np.mgrid[0:rows, 0:cols][:, :: max(1, rows // 128), :: max(1, cols // 128)]
    ay, ax = np.mgrid[step_px // 2 : rows : step_px, step_px // 2 : cols : step_px]
    figure, axes = plt.subplots(
        1, len(wavelengths_nm) + 1, figsize=(4.2 * (len(wavelengths_nm) + 1), 3.6)
    )
    for axis, wavelength in zip(axes[:-1], wavelengths_nm, strict=False):
        dx, dy = lens.displacement(xx.astype(float), yy.astype(float), wavelength)
        image = axis.imshow(np.hypot(dx, dy), extent=(0, cols, rows, 0), cmap="viridis")
        adx, ady = lens.displacement(ax.astype(float), ay.astype(float), wavelength)
        axis.quiver(ax, ay, adx, ady, color="white", angles="xy")
        axis.set_title(f"{wavelength:g} nm vs {lens.reference_nm:g} nm")
        figure.colorbar(image, ax=axis, label="|d| (px)", shrink=0.8)
    w = np.linspace(380, 780, 401)
    axes[-1].plot(w, lens.spectral_factor(w) * lens.max_shift_px)
    axes[-1].axhline(0, color="grey", lw=0.5)
    axes[-1].set_xlabel("wavelength (nm)")
    axes[-1].set_ylabel("corner displacement (px)")
    axes[-1].set_title(f"{lens.spectral_profile}, {lens.radial_profile}")
    figure.tight_layout()
    save_figure(figure, path)


def plot_dispersion_field(
    displacement,
    shape: tuple[int, int],
    bands: list,
    path: str | Path,
    *,
    centre: tuple[float, float] | None = None,
    reference: str = "reference",
    hull: np.ndarray | None = None,
    step_px: int | None = None,
) -> None:
    """Dispersion per band like the thesis' Figure 5.3: signed radial magnitude and angle.

    Parameters
    ----------
    displacement : callable
        ``displacement(x, y, band) -> (dx, dy)`` in px, vectorised over x and y.
    shape : (rows, cols)
        Image size, px.
    bands : list
        Band labels passed to `displacement` (wavelengths in nm or channel names).
    path : str or Path
        PNG to write.
    centre : (x, y), optional
        Image centre for the radial sign (default: the geometric centre); positive
        magnitudes point away from it.
    reference : str
        Label of the reference band, for titles.
    hull : ndarray (k, 2), optional
        Calibrated region outline to draw.
    step_px : int, optional
        Arrow spacing (default: about 16 arrows across).
    """
    rows, cols = shape
    cx, cy = centre if centre is not None else ((cols - 1) / 2, (rows - 1) / 2)
    stride = max(1, max(rows, cols) // 160)
    yy, xx = np.mgrid[0:rows:stride, 0:cols:stride].astype(np.float64)
    step = step_px or max(8, cols // 16)
    ay, ax = np.mgrid[step // 2 : rows : step, step // 2 : cols : step].astype(np.float64)
    radius = np.hypot(xx - cx, yy - cy)
    radius[radius == 0] = 1.0
    figure, axes = plt.subplots(2, len(bands), figsize=(4.4 * len(bands), 6.8), squeeze=False)
    for k, band in enumerate(bands):
        dx, dy = displacement(xx, yy, band)
        signed = (dx * (xx - cx) + dy * (yy - cy)) / radius
        limit = float(np.abs(signed).max()) or 1.0
        adx, ady = displacement(ax, ay, band)
        label = f"{band:g} nm" if isinstance(band, int | float) else str(band)
        for row, (values, cmap, vmin, vmax, unit) in enumerate(
            [
                (signed, "RdBu_r", -limit, limit, "radial component (px, + outward)"),
                (np.degrees(np.arctan2(dy, dx)), "twilight", -180, 180, "angle (deg)"),
            ]
        ):
            axis = axes[row, k]
            image = axis.imshow(
                values,
                extent=(-0.5, cols - 0.5, rows - 0.5, -0.5),
                cmap=cmap,
                vmin=vmin,
                vmax=vmax,
            )
            axis.quiver(ax, ay, adx, ady, color="black", angles="xy", width=0.004)
            if hull is not None and len(hull) >= 3:
                closed = np.vstack([hull, hull[:1]])
                axis.plot(closed[:, 0], closed[:, 1], "k--", lw=0.8)
            axis.set_title(f"{label} vs {reference}")
            figure.colorbar(image, ax=axis, label=unit, shrink=0.8)
    figure.tight_layout()
    save_figure(figure, path)


def plot_crops(
    images: dict[str, np.ndarray],
    windows: list[tuple[int, int, int]],
    path: str | Path,
    *,
    tile_in: float = 2.2,
) -> None:
    """Zoomed crops of several display images, one row per image, one column per window.

    Parameters
    ----------
    images : dict of str to ndarray (rows, cols, 3) uint8
        Display images of the same size, by name.
    windows : list of (row, col, side)
        Top-left corner and side of each square crop, px.
    path : str or Path
        PNG to write.
    tile_in : float
        Size of each tile, inches.
    """
    figure, axes = plt.subplots(
        len(images),
        len(windows),
        figsize=(tile_in * len(windows) + 1.6, tile_in * len(images)),
        squeeze=False,
    )
    for i, (name, image) in enumerate(images.items()):
        for j, (row, col, side) in enumerate(windows):
            axis = axes[i, j]
            axis.imshow(image[row : row + side, col : col + side], interpolation="nearest")
            axis.set_xticks([])
            axis.set_yticks([])
            if j == 0:
                axis.set_ylabel(name, fontsize=9)
            if i == 0:
                axis.set_title(f"x {col}–{col + side}, y {row}–{row + side}", fontsize=8)
    figure.tight_layout()
    save_figure(figure, path)


def plot_patch_spectra(
    truth: tuple[np.ndarray, np.ndarray],
    estimates: dict[str, tuple[np.ndarray, np.ndarray]],
    names: list[str],
    path: str | Path,
) -> None:
    """Spectra of a few chart patches: truth (lines) against estimates (markers).

    Parameters
    ----------
    truth : (wavelengths_nm (f,), spectra (k, f))
        True spectra of k patches on a fine grid.
    estimates : dict of str to (wavelengths_nm (n,), spectra (k, n))
        Estimated spectra of the same patches, by method.
    names : list of str
        Patch names (k).
    path : str or Path
        PNG to write.
    """
    columns = min(3, len(names))
    rows = -(-len(names) // columns)
    figure, axes = plt.subplots(
        rows, columns, figsize=(4.2 * columns, 3.0 * rows), squeeze=False, sharex=True
    )
    markers = "os^dv"
    for k, name in enumerate(names):
        axis = axes.flat[k]
        axis.plot(truth[0], truth[1][k], "k-", lw=1.2, label="truth")
        for m, (method, (wavelengths, spectra)) in enumerate(estimates.items()):
            axis.plot(wavelengths, spectra[k], markers[m % 5] + "--", ms=4, lw=0.8, label=method)
        axis.set_title(name, fontsize=9)
        axis.set_ylim(bottom=0)
    for axis in axes.flat[len(names) :]:
        axis.set_visible(False)
    for axis in axes[-1]:
        axis.set_xlabel("wavelength (nm)")
    axes.flat[0].legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, path)


def plot_channel_errors(
    values: dict[str, tuple[float, float, float]], path: str | Path, *, ylabel: str
) -> None:
    """Grouped bars of a per-channel figure (R, G, B) for each method."""
    names = list(values)
    x = np.arange(len(names))
    figure, axis = plt.subplots(figsize=(max(6.0, 0.9 * len(names) + 2), 3.6))
    for c, colour in enumerate("rgb"):
        axis.bar(x + (c - 1) * 0.27, [values[n][c] for n in names], 0.27, color=colour,
                 label="RGB"[c])  # fmt: skip
    axis.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
    axis.set_ylabel(ylabel)
    axis.legend(fontsize=8)
    figure.tight_layout()
    save_figure(figure, path)
