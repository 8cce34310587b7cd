"""Spectral → raw camera colour (thesis (3.6)) and spectral → CIE XYZ → sRGB."""

from __future__ import annotations

import numpy as np

from labkit.errors import DataError
from labkit.spectra.container import Spectra, trapezoid_weights
from labkit.spectra.datasets import cie_1931_cmfs


def integration_matrix(wavelengths: np.ndarray, response: Spectra) -> np.ndarray:
    """Matrix Ω (n_bands × n_channels) with ``raw = spectral @ Ω`` by the trapezoid rule.

    Parameters
    ----------
    wavelengths : ndarray, shape (n,)
        Band centres of the spectral image, nm (≥ 2, increasing).
    response : Spectra
        Channel responses Q_c(λ); must cover every band (no silent extrapolation).
    """
    sampled = response.resample(wavelengths, extrapolate="error")
    return sampled.values * trapezoid_weights(wavelengths)[:, None]


def spectral_to_raw(image: np.ndarray, wavelengths: np.ndarray, response: Spectra) -> np.ndarray:
    """Integrate a spectral image (…, n_bands) into raw colour (…, n_channels).

    Implements thesis (3.6) with G = 1 and the trapezoid rule over `wavelengths` (nm).
    """
    image = np.asarray(image)
    if image.shape[-1] != len(wavelengths):
        raise DataError(
            f"spectral image has {image.shape[-1]} bands but {len(wavelengths)} wavelengths"
        )
    dtype = np.result_type(image.dtype, np.float32)  # integer images integrate in float
    return image.astype(dtype, copy=False) @ integration_matrix(wavelengths, response).astype(dtype)


def spectral_to_xyz(
    image: np.ndarray, wavelengths: np.ndarray, *, white: np.ndarray | None = None
) -> np.ndarray:
    """CIE 1931 XYZ of a spectral image (…, n_bands), trapezoid rule.

    Normalised so that the spectrum `white` (default: 1 in every band, i.e. a perfect
    reflector under the light the image is relative to) has Y = 1.
    """
    cmfs = cie_1931_cmfs()
    matrix = cmfs.resample(wavelengths, extrapolate="zero").values
    matrix = matrix * trapezoid_weights(wavelengths)[:, None]
    reference = np.ones(len(wavelengths)) if white is None else np.asarray(white, float)
    luminance = reference @ matrix[:, 1]
    if luminance <= 0:
        raise DataError("the white spectrum has no luminance over these wavelengths")
    return np.asarray(image, dtype=np.float64) @ (matrix / luminance)


def xyz_to_linear_srgb(xyz: np.ndarray) -> np.ndarray:
    """Linear CIE XYZ → linear sRGB (D65 white, no encoding and no clipping: values outside
    the sRGB gamut stay negative or above 1)."""
    import colour

    return colour.XYZ_to_sRGB(np.asarray(xyz, dtype=np.float64), apply_cctf_encoding=False)


def xyz_to_srgb(xyz: np.ndarray) -> np.ndarray:
    """Linear CIE XYZ (white Y = 1, D65-adapted) → gamma-encoded sRGB in [0, 1]."""
    import colour

    rgb = colour.XYZ_to_sRGB(np.asarray(xyz, dtype=np.float64), apply_cctf_encoding=True)
    return np.clip(np.nan_to_num(rgb, nan=0.0), 0.0, 1.0)


#: CIE 1931 chromaticity of D65, the white of sRGB.
D65_XY = (0.3127, 0.3290)


def grey_world_white(xyz: np.ndarray) -> np.ndarray:
    """The scene's white by the grey-world assumption: the mean XYZ of the image's finite
    pixels with positive luminance, scaled to Y = 1 (the D65 white when there are none)."""
    pixels = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    pixels = pixels[np.all(np.isfinite(pixels), axis=1) & (pixels[:, 1] > 0)]
    mean = pixels.mean(axis=0) if len(pixels) else None
    if mean is None or np.any(mean <= 0):
        x, y = D65_XY
        return np.array([x / y, 1.0, (1.0 - x - y) / y])
    return mean / mean[1]


def adapt_to_d65(xyz: np.ndarray, white: np.ndarray) -> np.ndarray:
    """Von Kries chromatic adaptation (CAT02 cone space) of `xyz` from the scene white
    `white` to D65: a surface of the white's colour becomes neutral in sRGB."""
    import colour

    x, y = D65_XY
    target = np.array([x / y, 1.0, (1.0 - x - y) / y])
    source = np.asarray(white, dtype=np.float64)
    matrix = colour.adaptation.matrix_chromatic_adaptation_VonKries(
        source / source[1], target, transform="CAT02"
    )
    return np.asarray(xyz, dtype=np.float64) @ np.asarray(matrix).T


def spectral_to_srgb(image: np.ndarray, wavelengths: np.ndarray) -> np.ndarray:
    """Display sRGB (…, 3) in [0, 1] of a spectral image relative to its light source."""
    return xyz_to_srgb(spectral_to_xyz(image, wavelengths))
