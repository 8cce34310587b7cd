"""Spectral datasets: camera responses, the CIE 1931 observer, illuminants, reflectances.

Data come from colour-science (copied before any reshaping: its dataset objects are shared
and ``.align()`` would mutate the cached originals) and from the thesis' measured lab
spectra shipped in ``labkit/data/thesis_lab_spectra.csv`` (Boost Software License 1.0,
see ``labkit/data/README.md``).
"""

from __future__ import annotations

import csv
import functools
import io
from importlib import resources
from pathlib import Path

import numpy as np

from labkit.errors import DataError
from labkit.spectra.container import Spectra

#: Columns of the measured lab file holding bandpass-filter transmissions (relative to the
#: unfiltered projector light). "442 nm" is the thesis' nominal 450 nm filter, which has a
#: second transmission peak near 390 nm.
MEASURED_FILTER_COLUMNS = ("400 nm", "442 nm", "500 nm", "550 nm", "600 nm", "650 nm", "700 nm")

#: The ColorChecker patch names, in chart order (row-major from dark skin to black).
COLORCHECKER_PATCHES = (
    "dark skin", "light skin", "blue sky", "foliage", "blue flower", "bluish green",
    "orange", "purplish blue", "moderate red", "purple", "yellow green", "orange yellow",
    "blue", "green", "red", "yellow", "magenta", "cyan",
    "white 9.5 (.05 D)", "neutral 8 (.23 D)", "neutral 6.5 (.44 D)", "neutral 5 (.70 D)",
    "neutral 3.5 (1.05 D)", "black 2 (1.5 D)",
)  # fmt: skip


def _from_colour(dataset: object, labels: tuple[str, ...] | None = None) -> Spectra:
    """Copy a colour-science (multi-)spectral distribution into :class:`Spectra`."""
    copied = dataset.copy()  # never reshape colour's shared cached object
    values = np.array(copied.values, dtype=np.float64)
    names = labels or tuple(getattr(copied, "labels", None) or (copied.name,))
    return Spectra(np.array(copied.wavelengths, dtype=np.float64), values, names)


@functools.cache
def lab_spectra() -> Spectra:
    """The thesis' measured lab spectra (350–2500 nm at 1 nm), all columns."""
    source = resources.files("labkit") / "data" / "thesis_lab_spectra.csv"
    with source.open(newline="") as handle:
        reader = csv.reader(handle)
        header = next(reader)
        rows = np.array([[float(cell) for cell in row] for row in reader])
    return Spectra(rows[:, 0], rows[:, 1:], tuple(header[1:]))


def camera_response(source: object) -> Spectra:
    """Camera spectral response Q_c(λ) with channels ``("R", "G", "B")``.

    Parameters
    ----------
    source : str, Path, Spectra, colour-science distributions, or (wavelengths, values)
        A colour-science camera-sensitivity dataset name (e.g. ``"Nikon 5100 (NPL)"``); a
        CSV file with header ``wavelength_nm,R,G,B`` (relative response); a
        :class:`Spectra` of three channels; a colour-science ``MultiSpectralDistributions``
        of three channels (e.g. ``colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"]``)
        or a sequence of three ``SpectralDistribution`` (R, G, B); or a pair
        ``(wavelengths_nm, values)`` with values of shape (n, 3). Channels are taken in the
        order R, G, B.

    Raises
    ------
    DataError
        For anything else, or a response that is not three finite, non-negative channels.
    """
    if isinstance(source, str | Path):
        return _named_response(source)
    if isinstance(source, Spectra):
        response = source
    elif _is_colour_multi(source):
        response = _from_colour(source)
    elif _is_colour_sequence(source):
        response = _from_colour_sequence(source)
    elif isinstance(source, tuple) and len(source) == 2:
        wavelengths, values = (np.asarray(part, dtype=np.float64) for part in source)
        if values.ndim != 2 or values.shape[1] != 3 or wavelengths.shape != values.shape[:1]:
            raise DataError(
                f"a camera response (wavelengths_nm, values) needs values of shape (n, 3) "
                f"for n wavelengths; got {wavelengths.shape} and {values.shape}"
            )
        response = Spectra(wavelengths, values, ("R", "G", "B"))
    else:
        raise DataError(
            f"a camera response cannot be made from {type(source).__name__}: give a "
            "colour-science dataset name, a CSV path, a Spectra, colour-science spectral "
            "distributions, or (wavelengths_nm, values of shape (n, 3))"
        )
    if response.values.shape[1] != 3:
        raise DataError(
            f"a camera response has three channels (R, G, B); this one has "
            f"{response.values.shape[1]} ({', '.join(response.labels)})"
        )
    if np.any(response.values < 0):
        raise DataError("camera responses must be ≥ 0")
    return Spectra(response.wavelengths, response.values, ("R", "G", "B"))


def _named_response(source: str | Path) -> Spectra:
    import colour

    name = str(source)
    if name in colour.MSDS_CAMERA_SENSITIVITIES:
        data = _from_colour(colour.MSDS_CAMERA_SENSITIVITIES[name], ("R", "G", "B"))
        return data
    path = Path(source)
    if path.suffix.lower() == ".csv":
        return _read_response_csv(path)
    known = ", ".join(sorted(colour.MSDS_CAMERA_SENSITIVITIES))
    raise DataError(
        f"unknown camera response {name!r}: give a CSV file (wavelength_nm,R,G,B) "
        f"or one of the colour-science datasets: {known}"
    )


def _is_colour_multi(value: object) -> bool:
    return all(hasattr(value, name) for name in ("wavelengths", "values", "labels", "copy"))


def _is_colour_sequence(value: object) -> bool:
    return (
        isinstance(value, list | tuple)
        and len(value) == 3
        and all(hasattr(sd, "wavelengths") and hasattr(sd, "values") for sd in value)
    )


def _from_colour_sequence(distributions: object) -> Spectra:
    """Three colour-science SpectralDistributions (R, G, B) on their common wavelengths."""
    grids = [np.asarray(sd.wavelengths, dtype=np.float64) for sd in distributions]
    if any(grid.shape != grids[0].shape or np.any(grid != grids[0]) for grid in grids[1:]):
        raise DataError(
            "the three spectral distributions of a camera response must share their "
            "wavelengths; align them first (colour: sd.align(shape))"
        )
    values = np.stack([np.asarray(sd.values, dtype=np.float64) for sd in distributions], axis=1)
    return Spectra(grids[0], values, ("R", "G", "B"))


def _read_response_csv(path: Path) -> Spectra:
    if not path.is_file():
        raise DataError(f"camera response file {path} does not exist")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(
            f"camera response file {path} cannot be read as text ({error}); give a CSV file "
            "wavelength_nm,R,G,B"
        ) from None
    reader = csv.reader(io.StringIO(text, newline=""))
    header = [cell.strip() for cell in next(reader, [])]
    if header != ["wavelength_nm", "R", "G", "B"]:
        raise DataError(f"{path}: header is {header}; expected wavelength_nm,R,G,B")
    try:
        rows = np.array([[float(cell) for cell in row] for row in reader if row])
    except ValueError as error:
        raise DataError(f"{path}: non-numeric value or ragged row ({error})") from None
    if rows.size and not np.all(np.isfinite(rows)):
        raise DataError(f"{path}: values must be finite numbers (found NaN or Inf)")
    if rows.ndim != 2 or rows.shape[0] < 2:
        raise DataError(f"{path}: needs at least two rows of wavelength_nm,R,G,B")
    if np.any(rows[:, 1:] < 0):
        raise DataError(f"{path}: responses must be ≥ 0")
    try:
        return Spectra(rows[:, 0], rows[:, 1:], ("R", "G", "B"))
    except DataError as error:
        raise DataError(f"{path}: {error}") from None


def write_response_csv(response: Spectra, path: str | Path) -> None:
    """Write a camera response as CSV ``wavelength_nm,R,G,B``."""
    rows = np.column_stack([response.wavelengths, response.select(["R", "G", "B"]).values])
    np.savetxt(path, rows, delimiter=",", header="wavelength_nm,R,G,B", comments="", fmt="%.6g")


@functools.cache
def cie_1931_cmfs() -> Spectra:
    """The CIE 1931 2° standard observer x̄, ȳ, z̄ (360–830 nm at 1 nm)."""
    import colour

    return _from_colour(colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"], ("X", "Y", "Z"))


def colorchecker_reflectances(source: str = "measured") -> Spectra:
    """Reflectances of the 24 ColorChecker patches, labelled as in COLORCHECKER_PATCHES.

    Parameters
    ----------
    source : {"measured", "BabelColor Average", "ColorChecker N Ohta"}
        ``"measured"`` uses the thesis' spectrometer readings of its own chart
        (relative to a white standard); the others are colour-science datasets.
    """
    if source == "measured":
        return lab_spectra().select(COLORCHECKER_PATCHES)
    import colour

    if source not in colour.SDS_COLOURCHECKERS:
        raise DataError(
            f"unknown ColorChecker source {source!r}; use 'measured' or one of "
            f"{sorted(colour.SDS_COLOURCHECKERS)}"
        )
    chart = colour.SDS_COLOURCHECKERS[source]
    parts = [_from_colour(chart[name]) for name in chart]
    values = np.column_stack([part.values[:, 0] for part in parts])
    return Spectra(parts[0].wavelengths, values, COLORCHECKER_PATCHES)
