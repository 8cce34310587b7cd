"""A spectral image in memory: a (rows, cols, bands) cube with its band centres, and its
conversion to and from an ``xarray.DataArray`` for notebooks."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from labkit.errors import ConfigError, DataError
from labkit.io.exr import checked_plane

DIMS = ("y", "x", "wavelength")
"""Dimensions of :meth:`SpectralImage.to_xarray`: rows, columns (pixels), band centre (nm)."""


@dataclass
class SpectralImage:
    """A spectral image (rows, cols, bands) with band centres in nm.

    Attributes
    ----------
    cube : ndarray (rows, cols, bands)
        The values; labkit writes them as float32.
    wavelengths_nm : ndarray (bands,)
        Band centres, nm, increasing.
    labkit : dict
        Provenance and method-specific facts (JSON), e.g. ``units``.
    """

    cube: np.ndarray
    wavelengths_nm: np.ndarray
    labkit: dict[str, Any] = field(default_factory=dict)

    def to_xarray(self) -> Any:
        """The image as an ``xarray.DataArray`` with dimensions ``y``, ``x``, ``wavelength``.

        Coordinates: ``y`` and ``x`` in pixels from the top-left corner, ``wavelength`` in
        nm. Attributes: ``units`` (the values' units, when known), ``wavelength_units``
        (``"nm"``) and ``labkit`` (the provenance). The values are not copied.

        Needs xarray (``pip install 'labkit[xarray]'``).
        """
        xarray = _xarray()
        cube, wavelengths = checked_cube(self.cube, self.wavelengths_nm)
        rows, cols, _ = cube.shape
        attrs: dict[str, Any] = {"wavelength_units": "nm", "labkit": dict(self.labkit)}
        if "units" in self.labkit:
            attrs["units"] = str(self.labkit["units"])
        return xarray.DataArray(
            cube,
            dims=DIMS,
            coords={"y": np.arange(rows), "x": np.arange(cols), "wavelength": wavelengths},
            attrs=attrs,
            name="spectral",
        )

    @classmethod
    def from_xarray(cls, array: Any) -> SpectralImage:
        """A spectral image from an ``xarray.DataArray`` with a ``wavelength`` (nm)
        dimension and two spatial ones (``y`` and ``x`` by default; any order, transposed
        to ``y, x, wavelength``)."""
        if "wavelength" not in getattr(array, "dims", ()):
            raise DataError(
                "the DataArray has no 'wavelength' dimension (dims: "
                f"{getattr(array, 'dims', None)}); name the band dimension 'wavelength' (nm)"
            )
        units = array.attrs.get("wavelength_units", "nm")
        if units != "nm":
            raise DataError(
                f"the DataArray's wavelengths are in {units!r}; convert them to nm first"
            )
        spatial = [d for d in array.dims if d != "wavelength"]
        if len(spatial) != 2:
            raise DataError(
                f"a spectral image needs two spatial dimensions besides 'wavelength', got {spatial}"
            )
        order = ["y", "x"] if set(spatial) == {"y", "x"} else spatial
        array = array.transpose(*order, "wavelength")
        provenance = dict(array.attrs.get("labkit") or {})
        if "units" in array.attrs:
            provenance.setdefault("units", array.attrs["units"])
        wavelengths = np.asarray(array["wavelength"].values, dtype=np.float64)
        return cls(np.asarray(array.values), wavelengths, provenance)


def checked_cube(cube: np.ndarray, wavelengths_nm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`cube` as a (rows, cols, bands) array and the band centres as increasing float64 nm;
    raises :class:`DataError` naming what does not fit."""
    cube = np.asarray(cube)
    wavelengths = np.asarray(wavelengths_nm, dtype=np.float64).ravel()
    if cube.ndim != 3 or cube.shape[2] != wavelengths.size:
        raise DataError(
            "a spectral image must be (rows, cols, bands) with one wavelength per band; "
            f"got {cube.shape} and {wavelengths.size} wavelengths"
        )
    if wavelengths.size == 0:
        raise DataError("a spectral image needs at least one band")
    if not np.all(np.isfinite(wavelengths)) or np.any(wavelengths <= 0):
        raise DataError(f"band centres must be positive numbers of nm, got {wavelengths}")
    if np.any(np.diff(wavelengths) <= 0):
        raise DataError(f"band centres must increase, got {wavelengths}")
    return cube, wavelengths


def float32_bands(path: str | Path, image: SpectralImage) -> tuple[np.ndarray, np.ndarray]:
    """`image` checked for writing to `path`: its (rows, cols, bands) float32 values and
    increasing float64 band centres, nm. Raises :class:`DataError` naming the file and the
    band for a mismatched cube or NaN/Inf values."""
    try:
        cube, wavelengths = checked_cube(image.cube, image.wavelengths_nm)
    except DataError as error:
        raise DataError(f"{path}: {error}") from None
    bands = [
        checked_plane(path, f"band {w:g} nm", cube[:, :, i]) for i, w in enumerate(wavelengths)
    ]
    return np.stack(bands, axis=-1), wavelengths


def _xarray() -> Any:
    try:
        import xarray
    except ImportError:
        raise ConfigError(
            "xarray is not installed; install it with `pip install 'labkit[xarray]'` "
            "(or `pip install xarray`)"
        ) from None
    return xarray
