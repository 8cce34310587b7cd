"""Files: atomic writes, raw TIFF frames, OpenEXR raw images, spectral images (OpenEXR in
the Fichet et al. 2021 layout, ENVI, xarray), raw mosaics from other software and cameras,
PNG previews, masks."""

from labkit.io.atomic import atomic_path, atomic_write, fsync_directory, write_text_atomic
from labkit.io.envi import read_envi, write_envi
from labkit.io.exr import (
    RawImage,
    read_raw_exr,
    read_rgb_exr,
    write_raw_exr,
    write_rgb_exr,
)
from labkit.io.mosaic import MOSAIC_SUFFIXES, read_mosaic
from labkit.io.plain import to_plain
from labkit.io.plane import read_plane
from labkit.io.preview import (
    SpectralPreview,
    demosaic_bilinear,
    display_on_one_scale,
    raw_preview,
    spectral_preview,
    to_display,
    write_png,
)
from labkit.io.spectral_exr import read_spectral_exr, write_spectral_exr
from labkit.io.spectral_image import SpectralImage
from labkit.io.tiff import encode_raw_tiff, read_raw_tiff, write_raw_tiff

__all__ = [
    "MOSAIC_SUFFIXES",
    "RawImage",
    "SpectralImage",
    "SpectralPreview",
    "atomic_path",
    "atomic_write",
    "demosaic_bilinear",
    "display_on_one_scale",
    "encode_raw_tiff",
    "fsync_directory",
    "raw_preview",
    "read_envi",
    "read_mosaic",
    "read_plane",
    "read_raw_exr",
    "read_raw_tiff",
    "read_rgb_exr",
    "read_spectral_exr",
    "spectral_preview",
    "to_display",
    "to_plain",
    "write_envi",
    "write_png",
    "write_raw_exr",
    "write_raw_tiff",
    "write_rgb_exr",
    "write_spectral_exr",
    "write_text_atomic",
]
