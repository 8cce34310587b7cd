"""Spectral images as OpenEXR files in the published layout for spectral images.

The layout is Fichet, Pacanowski and Wilkie, "An OpenEXR Layout for Spectral Images",
JCGT 10(3), 2021. Files are written with colour-science's implementation,
:func:`colour.io.write_spectral_image_Fichet2021`, which runs on OpenImageIO.

What a labkit spectral EXR holds:

- One float32 channel per band, ``S0.<centre>nm``.

  - The layout's decimal separator is a comma (``S0.552,5nm``). colour-science writes 12
    significant digits; the exact float64 centres are in the ``labkit`` attribute.
  - ``S0`` is the layout's emissive (radiance-like) component: labkit images are light
    that reached the camera.
- ``spectralLayoutVersion`` (``"1.0"``) and ``emissiveUnits``.

  - The layout's unit is W·m⁻²·sr⁻¹. labkit's values are relative (raw units per nm), so
    it writes its own unit string, taken from the image's ``units`` entry.
  - The layout's reference reader then warns and reads the values on its own scale, which
    is right for relative data.
- Linear sRGB channels ``R``, ``G``, ``B``, so that ordinary EXR viewers show an image.
  They are the CIE 1931 colour of the spectrum, with an equal-energy spectrum of value 1
  at Y = 1, and ``chromaticities`` give the sRGB primaries.
- ``labkit``: labkit's provenance as JSON (units, basis, options, software). It also holds
  the exact float64 band centres.

:func:`read_spectral_exr` reads this layout from any software: the ``S0`` component, or
``T`` for reflectance images. It also reads labkit's older layout (channels ``S400.0``, …;
header ``wavelengths_nm``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from labkit.errors import ConfigError, DataError
from labkit.io.atomic import atomic_path
from labkit.io.exr import (
    FORMAT_VERSION,
    is_spectral_layout,
    read_exr,
    read_exr_header,
    read_provenance,
)
from labkit.io.spectral_image import SpectralImage, float32_bands
from labkit.io.tiff import json_default

LAYOUT_VERSION = "1.0"
"""``spectralLayoutVersion`` that labkit writes (Fichet et al. 2021)."""

DEFAULT_UNITS = "relative (raw units per nm)"
"""``emissiveUnits`` written when the image does not say what its values are."""


def write_spectral_exr(path: str | Path, image: SpectralImage) -> None:
    """Write `image` as a spectral EXR in the Fichet et al. (2021) layout, atomically.

    Parameters
    ----------
    path : str or Path
        Output file, conventionally ``*.exr``.
    image : SpectralImage
        Values of any real dtype, written as float32. Band centres must increase. Its
        ``labkit`` dict is stored as the ``labkit`` header attribute. Its ``units`` entry,
        when present, is the ``emissiveUnits`` attribute.

    Raises
    ------
    DataError
        A cube and band centres that do not match, or NaN/Inf values. Nothing is written.
    """
    values, wavelengths = float32_bands(path, image)
    units = str(image.labkit.get("units", DEFAULT_UNITS))
    provenance = {
        "format": FORMAT_VERSION,
        "kind": "spectral",
        "layout": f"Fichet2021 {LAYOUT_VERSION}",
        **image.labkit,
        "wavelengths_nm": wavelengths,
        "units": units,
    }
    colour_io, oiio = _colour_io()
    rgb = _linear_srgb(values, wavelengths)
    specification = colour_io.Specification_Fichet2021(is_emissive=True)
    attribute = colour_io.Image_Specification_Attribute
    specification.attributes = [
        attribute("spectralLayoutVersion", LAYOUT_VERSION),
        attribute("emissiveUnits", units),
        attribute("compression", "zip"),
        attribute("labkit", json.dumps(provenance, default=json_default)),
    ]

    def preview(_components: Any, _specification: Any) -> tuple[np.ndarray | None, list[Any]]:
        if rgb is None:
            return None, []
        chromaticities = [0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290]
        return rgb, [attribute("chromaticities", chromaticities, oiio.TypeDesc("float[8]"))]

    # OpenImageIO picks the file format from the name, so the temporary file ends in .exr
    with atomic_path(path, suffix=".part.exr") as temp:
        written = colour_io.write_spectral_image_Fichet2021(
            {"S0": (wavelengths, values)},
            temp,
            "float32",
            specification,
            components_to_RGB_callable=preview,
        )
        if not written:
            raise DataError(
                f"{path}: OpenImageIO could not write the spectral EXR ({oiio.geterror()})"
            )


def read_spectral_exr(path: str | Path) -> SpectralImage:
    """Read a spectral EXR: the Fichet et al. (2021) layout, or labkit's older one.

    In the published layout, the image is the emissive component ``S0`` (the total
    intensity of polarised images), or else the reflective ``T``; bi-spectral images are
    refused. The returned ``labkit`` dict is the file's ``labkit`` attribute, or else holds
    ``units`` from ``emissiveUnits``.

    Raises
    ------
    DataError
        The file is missing, unreadable, or not a spectral image in either layout.
    """
    header = read_exr_header(path)  # which layout, before any pixel is decoded
    provenance = read_provenance(path, header)
    names = [channel.name for channel in header.get("channels", [])]
    if "wavelengths_nm" in header and not is_spectral_layout(header, names):
        return _read_older_layout(path, provenance, header)
    if not is_spectral_layout(header, names):
        raise DataError(
            f"{path}: not a spectral EXR (channels {sorted(names)[:8]}…): expected the "
            "Fichet et al. (2021) layout (channels such as 'S0.550nm' or 'T.550nm') or "
            "labkit's older one ('S550.0' with a 'wavelengths_nm' attribute)"
        )
    colour_io, _ = _colour_io()
    try:
        components = colour_io.read_spectral_image_Fichet2021(str(path), "float32")
    except Exception as error:  # OpenImageIO and colour raise several kinds on bad files
        raise DataError(f"{path}: could not read the spectral layout ({error})") from None
    component = next((c for c in ("S0", "T") if c in components), None)
    if component is None:
        raise DataError(
            f"{path}: holds the components {sorted(map(str, components))}; labkit reads "
            "an emissive (S0) or reflective (T) image, not a bi-spectral one"
        )
    wavelengths, values = components[component]
    order = np.argsort(wavelengths)
    cube = np.ascontiguousarray(np.asarray(values, dtype=np.float32)[:, :, order])
    wavelengths = np.asarray(wavelengths, dtype=np.float64)[order]
    if not provenance:
        units = header.get("emissiveUnits" if component == "S0" else "reflectiveUnits")
        provenance = {"units": str(units)} if units is not None else {}
    return SpectralImage(cube, _exact_centres(wavelengths, provenance), provenance)


def _exact_centres(from_names: np.ndarray, provenance: dict[str, Any]) -> np.ndarray:
    """The band centres: the float64 values of labkit's header where they match the channel
    names, which colour-science writes to 12 significant digits."""
    recorded = provenance.get("wavelengths_nm")
    if recorded is None:
        return from_names
    recorded = np.asarray(recorded, dtype=np.float64).ravel()
    if recorded.shape == from_names.shape and np.allclose(recorded, from_names, rtol=1e-9, atol=0):
        return recorded
    return from_names


def _read_older_layout(
    path: str | Path, provenance: dict[str, Any], header: dict[str, Any]
) -> SpectralImage:
    _, channels = read_exr(path)
    wavelengths = provenance.get("wavelengths_nm", header.get("wavelengths_nm"))
    wavelengths = np.asarray(wavelengths, dtype=np.float64).ravel()
    try:
        planes = [channels[f"S{float(w):.1f}"] for w in wavelengths]
    except KeyError as missing:
        raise DataError(f"{path}: band channel {missing} is missing") from None
    return SpectralImage(np.stack(planes, axis=-1), wavelengths, provenance)


def _linear_srgb(values: np.ndarray, wavelengths: np.ndarray) -> np.ndarray | None:
    """Linear sRGB of the spectra (equal-energy white at Y = 1), or None for one band."""
    from labkit.spectra.conversion import spectral_to_xyz, xyz_to_linear_srgb

    if wavelengths.size < 2:
        return None
    # both steps are linear: one (bands × 3) matrix, applied in float32
    matrix = xyz_to_linear_srgb(spectral_to_xyz(np.eye(wavelengths.size), wavelengths))
    rgb = values @ matrix.astype(np.float32)
    return np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)


def _colour_io() -> tuple[Any, Any]:
    """colour-science's I/O module and OpenImageIO (loaded on first use: both are slow to
    import and most users of labkit.io write raw images only)."""
    try:
        import colour.io as colour_io
        import OpenImageIO as oiio
    except ImportError as error:
        raise ConfigError(
            f"spectral EXRs need OpenImageIO and colour-science ({error}); reinstall labkit "
            "(`pip install labkit` pulls in `openimageio`)"
        ) from None
    return colour_io, oiio
