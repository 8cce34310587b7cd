"""Spectral images as ENVI files (``.hdr`` header + ``.img`` raw data), the exchange format
of hyperspectral software, through Spectral Python (``spectral``).

labkit writes float32, band-sequential, little-endian data. The header holds:

- ``wavelength`` (band centres) and ``wavelength units = Nanometers``;
- ``band names``;
- a ``description`` that names the units of the values and the source;
- ``data units``.

ENVI headers cannot carry labkit's JSON provenance (braces delimit lists there), so only
these facts survive an export. Reading accepts any ENVI image with wavelengths in nm or µm.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from labkit.errors import ConfigError, DataError
from labkit.io.atomic import fsync_directory
from labkit.io.spectral_image import SpectralImage, checked_cube, float32_bands

DATA_SUFFIX = ".img"
"""Suffix of the raw data file written beside the ``.hdr`` header."""

#: Wavelengths (nm) of which an ENVI image must reach at least one: the CIE observer's.
VISIBLE_NM = (360.0, 830.0)
#: Suffixes of an ENVI data file beside its header (Spectral Python looks for these).
_DATA_SUFFIXES = (".img", ".dat", ".raw", ".sli", ".hyspex", ".IMG", ".DAT", ".RAW")
_NM_PER_UNIT = {
    "nm": 1.0,
    "nanometers": 1.0,
    "nanometer": 1.0,
    "um": 1e3,
    "µm": 1e3,
    "micrometers": 1e3,
    "micrometer": 1e3,
    "microns": 1e3,
    "micron": 1e3,
}


def write_envi(path: str | Path, image: SpectralImage, *, description: str = "") -> Path:
    """Write `image` as an ENVI header `path` (``*.hdr``) and its data file, atomically.

    Parameters
    ----------
    path : str or Path
        The header, ending in ``.hdr``; the data go to the same name with ``.img``.
    image : SpectralImage
        Written as float32, band-sequential (BSQ), little-endian.
    description : str, optional
        Free text for the header's ``description`` (e.g. the source file), on one line.

    Returns
    -------
    Path
        The data file.

    Raises
    ------
    DataError
        A path that does not end in ``.hdr``, a cube and band centres that do not match,
        or NaN/Inf values. Nothing is written.

    Notes
    -----
    Both files are written into a hidden temporary folder beside `path` and renamed into
    place, the data file first: a crash leaves either the old pair or a new data file
    without a new header, never a header that describes a partial data file.
    """
    header = Path(path)
    if header.suffix.lower() != ".hdr":
        raise DataError(f"{header}: an ENVI header's name must end in .hdr")
    values, wavelengths = float32_bands(header, image)
    units = str(image.labkit.get("units", "relative"))
    text = " ".join(f"labkit spectral image; values in {units}. {description}".split())
    metadata: dict[str, Any] = {
        "description": text,
        "wavelength units": "Nanometers",
        "wavelength": [repr(float(w)) for w in wavelengths],
        "band names": [f"{w:g} nm" for w in wavelengths],
        "data units": units.replace(",", ";"),
    }
    envi = _spectral_envi()
    data = header.with_suffix(DATA_SUFFIX)
    header.parent.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix=f".{header.name}.", suffix=".part", dir=header.parent))
    try:
        temp_header = folder / header.name
        envi.save_image(
            str(temp_header),
            values,
            dtype=np.float32,
            interleave="bsq",
            byteorder=0,
            ext=DATA_SUFFIX,
            force=True,
            metadata=metadata,
        )
        for temp, final in ((temp_header.with_suffix(DATA_SUFFIX), data), (temp_header, header)):
            with open(temp, "rb") as handle:
                os.fsync(handle.fileno())
            os.replace(temp, final)
        fsync_directory(header.parent)
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(folder)
    return data


def read_envi(path: str | Path) -> SpectralImage:
    """Read an ENVI image (header `path`, ``*.hdr``) with band centres as a spectral image.

    Values are read as stored, as float32, without the header's scale factors.
    The returned ``labkit`` dict records the source, the ``data units`` or description,
    and any ``reflectance scale factor``.

    Raises
    ------
    DataError
        A missing or unreadable file, or a header without ``wavelength`` or with
        wavelength units other than nm and µm.
    """
    header = Path(path)
    if header.is_dir():
        raise DataError(f"{header} is a folder; give an ENVI header file (.hdr)")
    if not header.is_file():
        raise DataError(f"ENVI header {header} does not exist")
    if not any(header.with_suffix(s).is_file() for s in _DATA_SUFFIXES) and not (
        header.suffix.lower() == ".hdr" and header.with_suffix("").is_file()
    ):
        raise DataError(
            f"{header.with_suffix('.img')}, the data file of {header}, is missing; keep the "
            "data file (.img, .dat or .raw) beside its header, under the same name"
        )
    envi = _spectral_envi()
    try:
        opened = envi.open(str(header))
    except Exception as error:  # Spectral Python raises several kinds on bad headers
        raise DataError(f"{header} is not a readable ENVI image ({error})") from None
    _check_data_size(header, opened)
    try:
        values = np.asarray(opened.load(dtype=np.float32, scale=False), dtype=np.float32)
    except Exception as error:
        raise DataError(f"{header} is not a readable ENVI image ({error})") from None
    metadata = {key.lower(): value for key, value in opened.metadata.items()}
    if "wavelength" not in metadata:
        raise DataError(
            f"{header}: the header has no 'wavelength' list; labkit needs each band's centre"
        )
    unit = str(metadata.get("wavelength units", "nm")).strip().lower()
    if unit not in _NM_PER_UNIT:
        raise DataError(
            f"{header}: wavelength units {unit!r} are not understood; use Nanometers or Micrometers"
        )
    wavelengths = np.asarray([float(w) for w in metadata["wavelength"]]) * _NM_PER_UNIT[unit]
    low, high = VISIBLE_NM
    if wavelengths.size and (wavelengths.max() < low or wavelengths.min() > high):
        raise DataError(
            f"{header}: its wavelengths ({wavelengths.min():g}–{wavelengths.max():g} nm, read "
            f"with 'wavelength units' = {unit}) miss the visible range {low:g}–{high:g} nm "
            "that labkit works in; check the header's "
            "'wavelength' list and 'wavelength units'"
        )
    bands = 1 if values.ndim == 2 else values.shape[2]
    if wavelengths.size != bands:
        raise DataError(
            f"{header}: the header lists {wavelengths.size} wavelengths for {bands} bands; "
            "give one wavelength per band"
        )
    if values.ndim == 2:
        values = values[:, :, None]
    order = np.argsort(wavelengths)
    provenance: dict[str, Any] = {"source": str(header), "format": "ENVI"}
    if "data units" in metadata:
        provenance["units"] = str(metadata["data units"])
    if "description" in metadata:
        provenance["description"] = str(metadata["description"])
    if "reflectance scale factor" in metadata:
        provenance["reflectance_scale_factor"] = float(metadata["reflectance scale factor"])
    cube = np.ascontiguousarray(values[:, :, order])
    try:
        cube, wavelengths = checked_cube(cube, wavelengths[order])
    except DataError as error:
        raise DataError(f"{header}: {error}") from None
    return SpectralImage(cube, wavelengths, provenance)


def _check_data_size(header: Path, opened: Any) -> None:
    """The data file holds exactly what the header describes (size, type, offset)."""
    data = Path(opened.filename)
    dtype = np.dtype(opened.dtype)
    expected = (
        int(opened.offset)
        + int(opened.nrows) * int(opened.ncols) * int(opened.nbands) * dtype.itemsize
    )
    actual = data.stat().st_size
    if actual != expected:
        raise DataError(
            f"{header}: its data file {data.name} is {actual} bytes, but the header describes "
            f"{opened.nrows}×{opened.ncols}×{opened.nbands} values of {dtype} "
            f"({expected} bytes with the header offset); the header does not match the data "
            "(check 'data type', 'lines', 'samples', 'bands' and 'header offset')"
        )


def _spectral_envi() -> Any:
    try:
        from spectral.io import envi
    except ImportError:
        raise ConfigError(
            "ENVI files need Spectral Python; reinstall labkit (`pip install labkit` pulls in "
            "`spectral`)"
        ) from None
    return envi
