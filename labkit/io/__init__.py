"""Files: atomic writes, raw TIFF frames and PNG previews."""

from labkit.io.atomic import atomic_path, atomic_write, fsync_directory, write_text_atomic
from labkit.io.preview import demosaic_bilinear, raw_preview, to_display, write_png
from labkit.io.tiff import encode_raw_tiff, read_raw_tiff, write_raw_tiff

__all__ = [
    "atomic_path",
    "atomic_write",
    "demosaic_bilinear",
    "encode_raw_tiff",
    "fsync_directory",
    "raw_preview",
    "read_raw_tiff",
    "to_display",
    "write_png",
    "write_raw_tiff",
    "write_text_atomic",
]
