"""The result of a reconstruction, and the files it writes (``labkit reconstruct``, the demos).

:meth:`Reconstruction.save` writes ``spectral.exr`` (spectral latent space: the spectrum at
the band centres, raw units per nm, in the Fichet et al. 2021 layout for spectral EXRs, with
band centres and basis in labkit's header attribute),
``raw_colour.exr`` (the aberration-free image in raw camera colour, raw units),
``preview.png`` (sRGB; :func:`labkit.io.spectral_preview` for spectra, the raw colour
otherwise) and ``log.json`` (the reconstruction's log with the caller's provenance). Every
file is written atomically and the log last, so a folder with a log holds a complete set.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import labkit
from labkit.errors import DataError
from labkit.io import (
    SpectralImage,
    spectral_preview,
    to_display,
    to_plain,
    write_png,
    write_rgb_exr,
    write_spectral_exr,
    write_text_atomic,
)
from labkit.io.output_folder import staged_output_folder
from reconstruction.model.image_formation import LatentSpace


@dataclass
class Reconstruction:
    """Result of :func:`reconstruct`.

    Attributes
    ----------
    spectral : ndarray (rows, cols, n) float32
        Spectrum at the band centres (spectral latent space) or raw colour R, G, B
        (colour latent space), in the raw image's units per nm (per channel for colour).
    wavelengths_nm : ndarray (n,) or None
        Band centres, nm (None for the colour latent space).
    raw_colour : ndarray (rows, cols, 3) float32
        The latent image in the camera's raw colour space, aberration-free, raw units.
    latent : LatentSpace
    log : dict
        Weights, normalisation, timings, per-patch records (JSON-ready).
    """

    spectral: np.ndarray
    wavelengths_nm: np.ndarray | None
    raw_colour: np.ndarray
    latent: LatentSpace
    log: dict = field(default_factory=dict)

    def save(
        self,
        out: str | Path,
        *,
        provenance: dict[str, Any] | None = None,
        log: dict[str, Any] | None = None,
    ) -> dict[str, Path]:
        """Write ``spectral.exr``, ``raw_colour.exr``, ``preview.png`` and ``log.json``
        into the folder `out`, atomically, the log last; returns the paths by name
        (:func:`save_reconstruction`)."""
        return save_reconstruction(self, out, provenance=provenance, log=log)

    def spectral_image(self, *, provenance: dict[str, Any] | None = None) -> SpectralImage:
        """The spectral latent image as :class:`labkit.io.SpectralImage`, with the
        provenance that ``spectral.exr`` records (units, basis, options).

        Raises
        ------
        DataError
            The result is in the colour latent space (no wavelengths; use `raw_colour`).
        """
        if self.wavelengths_nm is None:
            raise DataError(
                "this reconstruction is in the colour latent space: it has no wavelengths; "
                "use its raw_colour (rows, cols, 3), or reconstruct with --bands"
            )
        centres = np.asarray(self.wavelengths_nm, dtype=np.float64)
        header = file_header(self, provenance)
        basis = {
            "kernel": self.latent.kernel,
            "spacing_nm": float(centres[1] - centres[0]) if centres.size > 1 else None,
            "values": "spectrum at the band centres",
            "reference_scale": [float(v) for v in self.latent.scale],
        }
        return SpectralImage(self.spectral, centres, {**header, "basis": basis, "units": UNITS})

    def to_xarray(self) -> Any:
        """The spectral image as an ``xarray.DataArray`` with dimensions ``y``, ``x`` (pixels)
        and ``wavelength`` (nm), for notebooks (:meth:`labkit.io.SpectralImage.to_xarray`;
        needs ``labkit[xarray]``)."""
        return self.spectral_image().to_xarray()


UNITS = "raw units per nm"
"""Units of the spectral latent image: the raw image's units per nm of wavelength."""

OUTPUT_FILES = ("spectral.exr", "raw_colour.exr", "preview.png", "log.json")
"""Names of the files :func:`save_reconstruction` writes (no spectral.exr for colour)."""


def save_reconstruction(
    result: Reconstruction,
    out: str | Path,
    *,
    provenance: dict[str, Any] | None = None,
    log: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """Write `result` into the folder `out` as one set; returns the paths by name.

    Parameters
    ----------
    result : Reconstruction
    out : str or Path
        Output folder: absent, empty, or written by an earlier labkit run, which is
        replaced as a whole (:func:`labkit.io.output_folder.staged_output_folder`); a
        failed or interrupted save leaves it as it was.
    provenance : dict, optional
        Where the input came from (e.g. ``command``, ``input``, ``raw``, ``rig``,
        ``response``, ``dispersion_model``), added to the options the result records in
        both EXR headers and at the top of ``log.json``.
    log : dict, optional
        Further top-level entries of ``log.json`` (e.g. the command's arguments).

    Returns
    -------
    dict of str to Path
        ``spectral`` (spectral latent space only), ``raw_colour``, ``preview``, ``log``.
    """
    out = Path(out)
    header = file_header(result, provenance)
    names: dict[str, str] = {}
    command = str((provenance or {}).get("command") or "labkit reconstruct (Python)")
    with staged_output_folder(out, command=command) as stage:
        if result.wavelengths_nm is not None:
            names["spectral"] = "spectral.exr"
            image = result.spectral_image(provenance=provenance)
            write_spectral_exr(stage / names["spectral"], image)
            shown = spectral_preview(image.cube, image.wavelengths_nm)
            preview, preview_note = shown.image, shown.as_dict()
        else:
            preview = to_display(np.maximum(result.raw_colour, 0), max_side=None)
            preview_note = {"white_balance": "none", "shows": "raw camera colour"}
        names["raw_colour"] = "raw_colour.exr"
        write_rgb_exr(
            stage / names["raw_colour"], result.raw_colour, {**header, "units": "raw units"}
        )
        names["preview"] = "preview.png"
        write_png(stage / names["preview"], preview)
        names["log"] = "log.json"
        document = {
            **header,
            **(log or {}),
            "outputs": dict(names),
            "preview": preview_note,
            **result.log,
        }
        text = json.dumps(to_plain(document), indent=2, ensure_ascii=False) + "\n"
        write_text_atomic(stage / names["log"], text)
    paths = {name: out / file for name, file in names.items()}
    return paths


def file_header(result: Reconstruction, provenance: dict[str, Any] | None) -> dict[str, Any]:
    """What every output file records: the options, the caller's provenance, the software."""
    header = {**recorded_options(result), **(provenance or {})}
    header.setdefault("software", f"labkit {labkit.__version__}")
    return header


def recorded_options(result: Reconstruction) -> dict[str, Any]:
    """The problem's options as the result's log records them, for file headers."""
    log = result.log
    weights = log.get("weights", {})
    dispersion = log.get("dispersion") or {}
    return {
        "latent": result.latent.kind,
        "prior": log.get("prior"),
        "nonneg": log.get("nonneg"),
        "spectral_smoothness": log.get("spectral_smoothness"),
        "weights": {
            "requested": weights.get("requested"),
            "criterion": weights.get("criterion"),
            "values": weights.get("values"),
        },
        "reference": log.get("reference"),
        "correction": dispersion.get("correction"),
        "interpolation": dispersion.get("interpolation"),
        "extrapolation": (dispersion.get("domain") or {}).get("policy"),
        "warnings": list(log.get("warnings") or []),
    }
