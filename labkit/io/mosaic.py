"""Raw Bayer mosaics from any source: labkit's EXRs, other software's EXR/TIFF/PNG, camera raws.

:func:`read_mosaic` picks the reader by the file's suffix and returns a
:class:`~labkit.io.RawImage` whatever the source, so that the commands which start from one
raw image (``labkit reconstruct``, ``labkit evaluate``, ``labkit correct warp``) accept
images that labkit did not write:

- **OpenEXR** (``.exr``): a labkit raw EXR (:func:`~labkit.io.read_raw_exr`'s format), or
  an EXR from other software holding the mosaic in a channel named ``raw`` or in its only
  channel. Values are taken as they are.
- **TIFF / PNG** (``.tif``, ``.tiff``, ``.png``): one single-channel 2-D mosaic, uint8,
  uint16 or floating point. Integers are divided by the container's maximum (255 or
  65535), so 1.0 is the largest storable value; floats are taken as they are. No black
  level is subtracted.
- **Camera raw files** (``.dng``, ``.nef``, ``.cr2``, … :data:`CAMERA_RAW_SUFFIXES`), read
  by LibRaw (through ``rawpy``): the sensor's visible area (a DNG's ActiveArea; its
  DefaultCrop, a rendering hint, is not applied), black level subtracted per CFA channel
  and divided by the white level's distance from it, so 0 is black and 1.0 the white
  level.

The CFA layout comes from the file when it names one (a labkit EXR's ``cfa`` attribute, a
labkit raw TIFF's metadata, a camera raw's colour filter pattern); otherwise it must be
given (``cfa=``, the commands' ``--cfa``). A given layout that contradicts the file's own
is an error. The exposure is known only where the file records it (``exposure_s`` is None
otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np

from labkit.cfa import CFA_LAYOUTS, check_layout, layout_from_pixel_format
from labkit.errors import ConfigError, DataError
from labkit.io.exr import RawImage, read_exr, read_provenance
from labkit.io.tiff import description_metadata

#: Suffixes of OpenEXR files.
EXR_SUFFIXES = (".exr",)
#: Suffixes of single-channel TIFF/PNG mosaics (they need ``cfa=`` unless labkit wrote them).
IMAGE_SUFFIXES = (".tif", ".tiff", ".png")
#: Suffixes of camera raw files read through LibRaw (Adobe DNG and the makers' formats).
CAMERA_RAW_SUFFIXES = (
    ".dng", ".nef", ".nrw", ".cr2", ".cr3", ".crw", ".arw", ".srf", ".sr2", ".orf", ".rw2",
    ".raf", ".pef", ".ptx", ".srw", ".erf", ".kdc", ".dcr", ".dcs", ".mrw", ".mef", ".mos",
    ".3fr", ".fff", ".iiq", ".x3f", ".rwl", ".raw", ".rwz", ".gpr", ".bay", ".cap",
)  # fmt: skip
#: Every suffix :func:`read_mosaic` accepts (case-insensitive).
MOSAIC_SUFFIXES = EXR_SUFFIXES + IMAGE_SUFFIXES + CAMERA_RAW_SUFFIXES

#: Largest value of the integer containers a TIFF/PNG mosaic may use.
_CONTAINER_MAX = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}
#: What the commands call the option that supplies a missing CFA layout.
_CFA_OPTION = "--cfa"


def read_mosaic(path: str | Path, *, cfa: str | None = None, cfa_from: str = "--cfa") -> RawImage:
    """Read a raw Bayer mosaic from an EXR, TIFF, PNG or camera raw file.

    Parameters
    ----------
    path : str or Path
        The file; its suffix (:data:`MOSAIC_SUFFIXES`, case-insensitive) picks the reader.
    cfa : {"RGGB", "BGGR", "GRBG", "GBRG"}, optional
        Bayer layout (top-left 2×2 block, row by row) for files that do not name their own.
        For a file that does, it must agree.
    cfa_from : str
        How error messages name the source of `cfa` (default ``"--cfa"``, the option of the
        commands; e.g. a rig file's path when the layout came from a rig).

    Returns
    -------
    RawImage
        ``raw`` is the (rows, cols) float32 mosaic: as stored for EXRs and float TIFFs; the
        fraction of the integer container's range (value / 255 or value / 65535) for
        integer TIFF/PNG; (value − black) / (white − black), clipped below at 0, for camera
        raws (black per CFA channel, values in the sensor's visible area only).
        ``exposure_s`` is the exposure in s where the file records it, else None;
        ``illumination`` is ``""`` unless a labkit file names it. For files labkit did not
        write, ``labkit["source"]`` records the file, the reader, where the CFA layout came
        from and the scaling applied (for camera raws: the black levels per CFA position,
        the white level, the camera make and model where the file names them, and the
        visible area's place on the sensor); a labkit raw TIFF's metadata (CFA layout from
        its ``cfa`` or ``pixel_format``, ``exposure_s``, ``illumination``) is kept under
        ``labkit["frame"]``.

    Raises
    ------
    ConfigError
        `cfa` is not a Bayer layout name.
    DataError
        The file is missing, unreadable or of an unsupported kind; holds no single Bayer
        mosaic (a colour, spectral or multi-channel image, X-Trans or a non-Bayer sensor);
        its size is odd or below 2×2 px; its values are not finite (or negative, for float
        TIFFs); its CFA layout is unknown and `cfa` is None, or contradicts `cfa`.
    """
    path = Path(path)
    if cfa is not None:
        try:
            cfa = check_layout(cfa)
        except DataError:
            raise ConfigError(
                f"{cfa_from} is {cfa!r}; use one of {', '.join(CFA_LAYOUTS)} (the top-left 2×2 "
                "block of the mosaic, row by row)"
            ) from None
    if path.is_dir():
        raise DataError(f"{path} is a folder; give a raw image file")
    suffix = path.suffix.lower()
    if suffix not in MOSAIC_SUFFIXES:
        raise DataError(
            f"{path}: unsupported kind of file {suffix or '(no suffix)'!r}; labkit reads raw "
            "Bayer mosaics from OpenEXR (.exr), single-channel TIFF/PNG (.tif, .tiff, .png) "
            "and camera raw files (" + ", ".join(CAMERA_RAW_SUFFIXES) + ")"
        )
    if not path.is_file():
        raise DataError(f"raw image {path} does not exist")
    if suffix in EXR_SUFFIXES:
        image = _read_exr(path, cfa, cfa_from)
    elif suffix in IMAGE_SUFFIXES:
        image = _read_image(path, cfa, cfa_from)
    else:
        image = _read_camera_raw(path, cfa, cfa_from)
    _check_size(path, image.raw.shape)
    return image


# -- OpenEXR ----------------------------------------------------------------------------
def _read_exr(path: Path, cfa: str | None, cfa_from: str) -> RawImage:
    header, channels = read_exr(path)
    provenance = read_provenance(path, header)
    names = sorted(channels)
    if "wavelengths_nm" in header or provenance.get("kind") == "spectral":
        raise DataError(
            f"{path}: no 'raw' channel (channels: {names}); it is a spectral image rather "
            "than a raw mosaic"
        )
    if "raw" in channels:
        name = "raw"
    elif len(channels) == 1:
        name = names[0]
    else:
        raise DataError(
            f"{path}: no 'raw' channel and {len(names)} channels ({', '.join(names)}); a raw "
            "mosaic EXR holds the Bayer mosaic in a channel named 'raw' or in its only channel "
            "(an RGB EXR is a demosaiced/colour image, labkit needs the raw Bayer mosaic)"
        )
    plane = channels[name]
    _check_finite(path, plane)
    own = header.get("cfa")
    own = None if own is None else _own_layout(path, str(own))
    layout = _layout(path, own, cfa, cfa_from)
    exposure = provenance.get("exposure_s", header.get("exposure_s"))
    wavelength = provenance.get("wavelength_nm", header.get("wavelength_nm"))
    labkit_raw = own is not None and exposure is not None
    if not labkit_raw:
        provenance = {
            **provenance,
            "source": {
                "file": str(path),
                "reader": "OpenEXR",
                "channel": name,
                "cfa_from": "file" if own is not None else cfa_from,
                "scale": "as stored",
            },
        }
    return RawImage(
        raw=plane,
        cfa=layout,
        exposure_s=_exposure(path, exposure),
        illumination=str(header.get("illumination", "")),
        wavelength_nm=None if wavelength is None else float(wavelength),
        variance=channels.get("variance") if name == "raw" else None,
        labkit=provenance,
    )


# -- TIFF and PNG -----------------------------------------------------------------------
def _read_image(path: Path, cfa: str | None, cfa_from: str) -> RawImage:
    if path.suffix.lower() == ".png":
        data, reader = _read_png(path), "Pillow"
        metadata: dict[str, Any] = {}
    else:
        data, metadata = _read_tiff(path)
        reader = "tifffile"
    if data.ndim != 2:
        raise DataError(
            f"{path}: expected a single-channel 2-D Bayer mosaic, got shape {data.shape}; "
            "save the raw mosaic as one grey channel"
        )
    if data.dtype in _CONTAINER_MAX:
        scale = _CONTAINER_MAX[data.dtype]
        raw = data.astype(np.float32) / np.float32(scale)
        scaling = f"value / {scale:g} (the {data.dtype} container's maximum)"
    elif data.dtype.kind == "f":
        raw = data.astype(np.float32)
        _check_finite(path, raw)
        negative = int(np.count_nonzero(raw < 0))
        if negative:
            raise DataError(
                f"{path}: {negative} negative pixel value(s); a raw mosaic holds light "
                "measurements ≥ 0 (clip or re-export the image)"
            )
        scaling = "as stored (float)"
    else:
        raise DataError(
            f"{path}: pixel type {data.dtype} is not supported; save the mosaic as uint8, "
            "uint16 or floating point"
        )
    own = metadata.get("cfa")
    if own is None and isinstance(metadata.get("pixel_format"), str):
        try:
            own = layout_from_pixel_format(metadata["pixel_format"])
        except DataError:
            own = None
    own = None if own is None else _own_layout(path, str(own))
    illumination = metadata.get("illumination")
    source = {
        "file": str(path),
        "reader": reader,
        "dtype": str(data.dtype),
        "cfa_from": "file" if own is not None else cfa_from,
        "scale": scaling,
    }
    return RawImage(
        raw=raw,
        cfa=_layout(path, own, cfa, cfa_from),
        exposure_s=_exposure(path, metadata.get("exposure_s")),
        illumination="" if illumination is None else str(illumination),
        labkit={"source": source, **({"frame": metadata} if metadata else {})},
    )


def _read_tiff(path: Path) -> tuple[np.ndarray, dict[str, Any]]:
    """A TIFF's only image and its labkit metadata (ImageDescription JSON; {} if none)."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            pages = len(tif.pages)
            page = tif.pages.first
            samples = int(page.samplesperpixel)
            photometric = int(page.photometric)
            data = page.asarray() if pages == 1 and samples == 1 else None
            description = page.description or ""
    except Exception as error:  # tifffile raises many types on corrupt files
        raise DataError(f"{path} is not a readable TIFF ({error})") from None
    if samples in (3, 4) or photometric in (2, 3, 6):  # RGB(A), palette, YCbCr
        _refuse_colour(path, "RGBA" if samples == 4 else "RGB")
    if pages > 1:
        raise DataError(
            f"{path} holds {pages} images (pages); labkit needs one raw Bayer mosaic per file"
        )
    if data is None:
        raise DataError(
            f"{path}: {samples} samples per pixel; labkit needs a single-channel raw Bayer mosaic"
        )
    return data, description_metadata(description)


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            mode = image.mode
            if mode not in ("RGB", "RGBA", "P", "PA", "CMYK", "YCbCr"):
                data = np.asarray(image)
    except (OSError, UnidentifiedImageError, ValueError) as error:
        raise DataError(f"{path} is not a readable PNG ({error})") from None
    if mode in ("RGB", "RGBA", "P", "PA", "CMYK", "YCbCr"):
        _refuse_colour(path, "RGBA" if mode in ("RGBA", "PA") else "RGB")
    if mode in ("I", "I;16", "I;16B", "I;16L"):  # PNG stores at most 16 bits per grey sample
        return data.astype(np.uint16)
    if mode != "L":
        raise DataError(
            f"{path}: PNG mode {mode!r} is not a single-channel 8/16-bit mosaic; save the raw "
            "mosaic as one grey channel"
        )
    return data


def _refuse_colour(path: Path, kind: str) -> None:
    raise DataError(
        f"{path}: a 3-channel ({kind}) image is a demosaiced/colour image, labkit needs the raw "
        "Bayer mosaic (one channel, each pixel behind one colour filter)"
    )


# -- camera raw files (LibRaw) ----------------------------------------------------------
@dataclass(frozen=True)
class CameraRawCounts:
    """The sensor counts of a camera raw file and the levels and exposure it records.

    Attributes
    ----------
    counts : ndarray (rows, cols) uint16
        The visible area's values, DN, black level included.
    cfa : str
        Bayer layout of the visible area's top-left 2×2 block.
    black_levels : ndarray (2, 2) float
        Black level of each 2×2 CFA position, DN.
    white_level : float
        Saturation, DN.
    exposure_s : float or None
        Exposure time from the file's metadata, s (None where it records none).
    source : dict
        Reader, visible area and camera names, for provenance.
    """

    counts: np.ndarray
    cfa: str
    black_levels: np.ndarray
    white_level: float
    exposure_s: float | None
    source: dict[str, Any]


def read_camera_raw_counts(path: str | Path) -> CameraRawCounts:
    """Read a camera raw file's Bayer counts and levels with LibRaw (rawpy).

    Raises
    ------
    DataError
        Not a file LibRaw reads, not a 2×2 RGB Bayer mosaic (X-Trans, Foveon, demosaiced
        DNGs), or broken levels (white not above black).
    """
    import rawpy

    path = Path(path)
    try:
        with rawpy.imread(str(path)) as raw:
            kind = raw.raw_type
            description = raw.color_desc.decode("ascii", "replace").rstrip("\x00")
            pattern = raw.raw_pattern
            if kind != rawpy.RawType.Flat or pattern is None:
                raise DataError(
                    f"{path}: LibRaw reads it as a {kind.name} (non-Bayer or already "
                    "demosaiced) raw image; labkit needs a Bayer mosaic (one colour filter "
                    "per pixel)"
                )
            if pattern.shape != (2, 2):
                raise DataError(
                    f"{path}: its colour filter pattern repeats every {pattern.shape[0]}×"
                    f"{pattern.shape[1]} px (e.g. Fujifilm X-Trans); labkit needs a 2×2 Bayer "
                    "mosaic"
                )
            colours = raw.raw_colors_visible
            counts = np.array(raw.raw_image_visible, dtype=np.uint16)
            black = np.asarray(raw.black_level_per_channel, dtype=np.float64)
            white = float(raw.white_level)
            shutter = float(raw.other.shutter_speed)
            sizes = raw.sizes
            layout = _libraw_layout(path, colours, description)
    except rawpy.LibRawError as error:
        detail = error.args[0] if error.args else error
        if isinstance(detail, bytes):
            detail = detail.decode("ascii", "replace")
        raise DataError(
            f"{path} is not a camera raw image LibRaw can read (LibRaw: {detail}); give a "
            "camera raw file, a raw EXR or a single-channel TIFF/PNG mosaic"
        ) from None
    levels = black[colours[:2, :2]]
    if np.any(white - levels <= 0):
        raise DataError(
            f"{path}: white level {white:g} is not above the black levels "
            f"{levels.ravel().tolist()}; the file's levels are broken"
        )
    source = {
        "file": str(path),
        "reader": f"LibRaw {'.'.join(map(str, rawpy.libraw_version))} (rawpy {version('rawpy')})",
        "cfa_from": "file",
        "colours": description,
        "black_levels": levels.tolist(),
        "white_level": white,
        "visible_area": {
            "top": int(sizes.top_margin),
            "left": int(sizes.left_margin),
            "rows": int(counts.shape[0]),
            "cols": int(counts.shape[1]),
            "sensor_rows": int(sizes.raw_height),
            "sensor_cols": int(sizes.raw_width),
        },
        **_camera_names(path),
    }
    return CameraRawCounts(counts, layout, levels, white, _shutter_s(shutter), source)


def read_camera_raw_exposure(path: str | Path) -> float | None:
    """A camera raw file's exposure time, s, from its metadata alone (no pixels are read);
    None where it records none or LibRaw cannot open it (:func:`read_camera_raw_counts`
    says why when the file is read)."""
    import rawpy

    raw = rawpy.RawPy()
    try:
        raw.open_file(str(path))
        return _shutter_s(float(raw.other.shutter_speed))
    except rawpy.LibRawError:
        return None
    finally:
        raw.close()


def _shutter_s(shutter: float) -> float | None:
    """LibRaw's exposure time, s, to the 7 significant digits its float32 holds; None where
    the file records none."""
    return float(f"{shutter:.7g}") if np.isfinite(shutter) and shutter > 0 else None


def _read_camera_raw(path: Path, cfa: str | None, cfa_from: str) -> RawImage:
    found = read_camera_raw_counts(path)
    # (raw − black) / (white − black) per 2×2 CFA position (float64, one rounding)
    image = np.empty(found.counts.shape, np.float32)
    for row in (0, 1):
        for col in (0, 1):
            black = found.black_levels[row, col]
            part = (found.counts[row::2, col::2] - black) / (found.white_level - black)
            image[row::2, col::2] = np.maximum(part, 0.0)
    source = {
        **found.source,
        "scale": "(value - black[c]) / (white - black[c]), clipped below at 0",
    }
    return RawImage(
        raw=image,
        cfa=_layout(path, found.cfa, cfa, cfa_from),
        exposure_s=found.exposure_s,
        illumination="",
        labkit={"source": source},
    )


def _libraw_layout(path: Path, colours: np.ndarray, description: str) -> str:
    """The Bayer layout of LibRaw's per-pixel colour indices (G2 counted as G)."""
    rows, cols = colours.shape
    if rows < 2 or cols < 2:
        _check_size(path, colours.shape)
    letters = []
    for index in colours[:2, :2].ravel():
        letter = description[index] if index < len(description) else "?"
        if letter not in "RGB":
            raise DataError(
                f"{path}: its sensor's colour filters are {description!r}, not red, green and "
                "blue; labkit needs an RGB Bayer mosaic"
            )
        letters.append(letter)
    layout = "".join(letters)
    if layout not in CFA_LAYOUTS:
        raise DataError(
            f"{path}: its 2×2 colour filter block is {layout}, not a Bayer layout "
            f"({', '.join(CFA_LAYOUTS)})"
        )
    even_rows, even_cols = rows - rows % 2, cols - cols % 2
    block = colours[:2, :2]
    tiled = np.tile(block, (even_rows // 2, even_cols // 2))
    if not np.array_equal(colours[:even_rows, :even_cols], tiled):
        raise DataError(
            f"{path}: its colour filter pattern does not repeat every 2×2 px; labkit needs a "
            "Bayer mosaic"
        )
    return layout


def _camera_names(path: Path) -> dict[str, str]:
    """Camera make and model from a TIFF-based raw file's tags ({} where not available)."""
    import tifffile

    names: dict[str, str] = {}
    try:
        with tifffile.TiffFile(path) as tif:
            tags = tif.pages.first.tags
            for key, code in (("make", 271), ("model", 272), ("unique_camera_model", 50708)):
                tag = tags.get(code)
                if tag is not None and isinstance(tag.value, str) and tag.value.strip():
                    names[f"camera_{key}"] = tag.value.strip()
    except Exception:  # not TIFF-based (CR3, RAF, …): LibRaw read it, the names stay unknown
        return {}
    return names


# -- shared checks ----------------------------------------------------------------------
def _own_layout(path: Path, text: str) -> str:
    try:
        return check_layout(text)
    except DataError:
        raise DataError(
            f"{path}: its CFA layout {text!r} is not one of {', '.join(CFA_LAYOUTS)}"
        ) from None


def _layout(path: Path, own: str | None, given: str | None, given_from: str) -> str:
    """The file's own layout, else the given one; a contradiction or neither is an error."""
    if own is not None and given is not None and own != given:
        raise DataError(
            f"CFA layouts disagree: {path} says {own}, {given_from} says {given}; use the "
            "layout the image was taken with"
        )
    if own is not None:
        return own
    if given is None:
        raise DataError(
            f"{path} does not say its CFA layout; pass {_CFA_OPTION} "
            f"{{{','.join(CFA_LAYOUTS)}}} (the colours of the mosaic's top-left 2×2 block, "
            "row by row)"
        )
    return given


def _exposure(path: Path, value: Any) -> float | None:
    if value is None:
        return None
    try:
        exposure = float(value)
    except (TypeError, ValueError):
        exposure = float("nan")
    if not np.isfinite(exposure) or exposure <= 0:
        raise DataError(f"{path}: exposure_s is {value!r}; expected a positive number of seconds")
    return exposure


def _check_finite(path: Path, plane: np.ndarray) -> None:
    bad = int(np.count_nonzero(~np.isfinite(plane)))
    if bad:
        raise DataError(
            f"{path}: {bad} NaN/Inf pixel(s) in the mosaic; repair or mask them and save again"
        )


def _check_size(path: Path, shape: tuple[int, ...]) -> None:
    rows, cols = shape[:2]
    if rows % 2 or cols % 2 or rows < 2 or cols < 2:
        raise DataError(
            f"{path} is not a Bayer mosaic: size {rows}×{cols} px; a Bayer mosaic needs an even "
            "number of rows and columns, at least 2×2: crop to even dimensions (keeping the "
            "CFA phase)"
        )
