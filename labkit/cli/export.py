"""``labkit export SPECTRAL --to envi|exr``: spectral images in other software's formats.

A spectral EXR (``labkit reconstruct``'s ``spectral.exr``, ``labkit synthesize``'s
multispectral image, or any file in the Fichet et al. 2021 layout) becomes an ENVI image
(``.hdr`` + ``.img``, float32, band-sequential, wavelengths in nm). The reverse turns an
ENVI image with band centres into a spectral EXR. Values are copied exactly (float32).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from labkit.cli._commands import Commands

if TYPE_CHECKING:
    from labkit.io import SpectralImage

FORMATS = {"envi": ".hdr", "exr": ".exr"}
"""Export formats and the suffix of the file that ``--out`` names."""


def register(commands: Commands) -> None:
    """Add ``labkit export``."""
    parser = commands.add_parser(
        "export",
        description="Convert a spectral image. `--to envi` writes OUT.hdr (ENVI header: "
        "wavelength, wavelength units = Nanometers, band names, the values' units) and "
        "OUT.img (float32, band-sequential, little-endian) from a spectral EXR. `--to exr` "
        "reads an ENVI image whose header lists each band's wavelength (nm or µm) and writes "
        "a spectral EXR in the Fichet et al. (2021) layout. Both are exact for float32 data. "
        "Files are written atomically; an existing output is replaced.",
    )
    parser.add_argument("image", type=Path, help="spectral EXR, or ENVI header (.hdr)")
    parser.add_argument("--to", choices=sorted(FORMATS), required=True, help="format to write")
    parser.add_argument(
        "--out",
        type=Path,
        help="file to write (default: IMAGE with the new format's suffix, .hdr or .exr)",
    )
    parser.set_defaults(handler=_export)


def _export(args: argparse.Namespace) -> int:
    from labkit.errors import DataError
    from labkit.io import read_envi, read_spectral_exr, write_envi, write_spectral_exr
    from labkit.io.output_folder import check_output_files, writer_lock

    source: Path = args.image
    reading_envi = source.suffix.lower() == ".hdr"
    if args.to == "envi" and reading_envi:
        raise DataError(f"{source} is already an ENVI header; `--to envi` exports a spectral EXR")
    if args.to == "exr" and not reading_envi:
        raise DataError(f"{source}: `--to exr` reads an ENVI header (.hdr)")
    suffix = FORMATS[args.to]
    out: Path = args.out if args.out is not None else source.with_suffix(suffix)
    if out.suffix.lower() != suffix:
        raise DataError(f"--out {out}: {args.to.upper()} files end in {suffix}")
    outputs = [out, out.with_suffix(".img")] if args.to == "envi" else [out]
    check_output_files(outputs, inputs=[source])
    with writer_lock(out, command="labkit export"):
        image = read_envi(source) if reading_envi else read_spectral_exr(source)
        if args.to == "envi":
            data = write_envi(out, image, description=f"exported from {source.name}")
            print(f"wrote {out} and {data.name}: {_summary(image)}")
        else:
            write_spectral_exr(out, image)
            print(f"wrote {out}: {_summary(image)}")
    return 0


def _summary(image: SpectralImage) -> str:
    rows, cols, bands = image.cube.shape
    low, high = image.wavelengths_nm.min(), image.wavelengths_nm.max()
    return f"{rows}×{cols} pixels, {bands} bands {low:g}–{high:g} nm"
