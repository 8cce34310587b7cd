"""The table of channel sensitivities per band, and its files (CSV, YAML).

:class:`ChannelSensitivity` is what Algorithm 12 measures (:mod:`calibration.sensitivity.ratios`)
and what the rig predicts (:mod:`calibration.sensitivity.nominal`); :func:`load_response` reads a
camera response from a dataset name, a response CSV or such a table.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from labkit.errors import DataError
from labkit.io.atomic import write_text_atomic
from labkit.io.plain import to_plain
from labkit.spectra import (
    Spectra,
    camera_response,
)

FORMAT_VERSION = 1

#: Columns of the CSV form, in order (also the keys of each YAML band entry).
COLUMNS = (
    "wavelength_nm",
    "illumination",
    "r_over_g",
    "b_over_g",
    "green_level",
    "pairs_r",
    "pairs_b",
    "residual_r",
    "residual_b",
    "reliable_r",
    "reliable_b",
    "reason_r",
    "reason_b",
)
_REQUIRED = ("wavelength_nm", "r_over_g", "b_over_g")

#: Band wavelengths a table may hold, nm: those of a rig filter (FilterConfig.centre_nm).
WAVELENGTH_RANGE_NM = (300.0, 1100.0)

#: Two bands closer than this are the same band, nm.
BAND_TOLERANCE_NM = 0.05


@dataclass
class ChannelSensitivity:
    """Red/Green and Blue/Green sensitivity ratios per filter band.

    Attributes
    ----------
    wavelengths_nm : ndarray (n,) float64
        Band centre wavelengths, nm, increasing.
    illuminations : tuple of str
        Illumination (slider position) names of the bands.
    r_over_g, b_over_g : ndarray (n,) float64
        Ratios R/G and B/G (dimensionless); NaN only where the matching
        ``reliable_*`` flag is False.
    pairs_r, pairs_b : ndarray (n,) int64
        Green–Red and Green–Blue pixel pairs used (0 for predicted ratios).
    residual_r, residual_b : ndarray (n,) float64
        RMS distance of the normalised pairs from the fitted line
        (:class:`~labkit.fitting.SlopeFit` ``residual_rms``); NaN when unknown.
    reliable_r, reliable_b : ndarray (n,) bool
        Whether each ratio passed the pair-count and signal tests.
    reason_r, reason_b : tuple of str
        Why a ratio is unreliable ("" when it is reliable).
    green_level : ndarray (n,) float64
        Green signal of each band: the mean Green value of its images per second of
        exposure (fraction of saturation per s) for a measured table, the predicted Green
        integral (relative units) for a nominal one; NaN where unknown. Only the ratios
        between bands matter: they put the bands of a reconstruction on the scale of the
        light the camera saw (:meth:`as_response`).
    source : str
        ``"measured"``, ``"nominal"`` or the file the table was read from.
    labkit : dict
        Provenance (method, options, input files, rig).
    """

    wavelengths_nm: np.ndarray
    illuminations: tuple[str, ...]
    r_over_g: np.ndarray
    b_over_g: np.ndarray
    pairs_r: np.ndarray
    pairs_b: np.ndarray
    residual_r: np.ndarray
    residual_b: np.ndarray
    reliable_r: np.ndarray
    reliable_b: np.ndarray
    reason_r: tuple[str, ...]
    reason_b: tuple[str, ...]
    green_level: np.ndarray | None = None
    source: str = "measured"
    labkit: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.wavelengths_nm = np.asarray(self.wavelengths_nm, dtype=np.float64).ravel()
        n = self.wavelengths_nm.size
        if self.green_level is None:
            self.green_level = np.full(n, np.nan)
        for name in ("r_over_g", "b_over_g", "green_level", "residual_r", "residual_b"):
            setattr(self, name, _column(getattr(self, name), np.float64, n, name))
        for name in ("pairs_r", "pairs_b"):
            setattr(self, name, _column(getattr(self, name), np.int64, n, name))
        for name in ("reliable_r", "reliable_b"):
            setattr(self, name, _column(getattr(self, name), np.bool_, n, name))
        for name in ("illuminations", "reason_r", "reason_b"):
            values = tuple(str(v) for v in getattr(self, name))
            if len(values) != n:
                raise DataError(f"ChannelSensitivity: {name} has {len(values)} entries, not {n}")
            setattr(self, name, values)
        if np.any(np.diff(self.wavelengths_nm) <= BAND_TOLERANCE_NM):
            raise DataError(
                f"ChannelSensitivity: band wavelengths must increase by more than "
                f"{BAND_TOLERANCE_NM} nm, got {self.wavelengths_nm.tolist()}"
            )
        for channel in ("r", "b"):
            ratios = getattr(self, f"{channel}_over_g")
            reliable = getattr(self, f"reliable_{channel}")
            silent = ~np.isfinite(ratios) & reliable
            if silent.any():
                raise DataError(
                    f"ChannelSensitivity: {channel}_over_g is missing at "
                    f"{self.wavelengths_nm[silent].tolist()} nm but marked reliable"
                )

    def __len__(self) -> int:
        return int(self.wavelengths_nm.size)

    @property
    def reliable(self) -> np.ndarray:
        """(n,) bool: both ratios of the band are reliable."""
        return self.reliable_r & self.reliable_b

    def index_of(self, wavelength_nm: float) -> int | None:
        """Index of the band centred at `wavelength_nm` (± 0.05 nm), or None."""
        if len(self) == 0:
            return None
        distance = np.abs(self.wavelengths_nm - float(wavelength_nm))
        best = int(np.argmin(distance))
        return best if distance[best] <= BAND_TOLERANCE_NM else None

    def rows(self) -> list[dict[str, Any]]:
        """One dict per band with the keys of :data:`COLUMNS` (NaN → None)."""
        return [
            {
                "wavelength_nm": float(self.wavelengths_nm[i]),
                "illumination": self.illuminations[i],
                "r_over_g": _finite_or_none(self.r_over_g[i]),
                "b_over_g": _finite_or_none(self.b_over_g[i]),
                "green_level": _finite_or_none(self.green_level[i]),
                "pairs_r": int(self.pairs_r[i]),
                "pairs_b": int(self.pairs_b[i]),
                "residual_r": _finite_or_none(self.residual_r[i]),
                "residual_b": _finite_or_none(self.residual_b[i]),
                "reliable_r": bool(self.reliable_r[i]),
                "reliable_b": bool(self.reliable_b[i]),
                "reason_r": self.reason_r[i],
                "reason_b": self.reason_b[i],
            }
            for i in range(len(self))
        ]

    def to_csv(self, path: str | Path) -> None:
        """Write the table as CSV (header :data:`COLUMNS`; empty cell = not available)."""
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
        writer.writeheader()
        for row in self.rows():
            writer.writerow({key: _cell(value) for key, value in row.items()})
        write_text_atomic(path, buffer.getvalue())

    def to_yaml(self, path: str | Path) -> None:
        """Write the table with its provenance as YAML (``format``, ``bands``, ``labkit``)."""
        import yaml

        document = {
            "format": FORMAT_VERSION,
            "kind": "channel_sensitivity",
            "source": self.source,
            "bands": self.rows(),
            "labkit": to_plain(self.labkit),
        }
        write_text_atomic(path, yaml.safe_dump(document, sort_keys=False, allow_unicode=True))

    def as_response(self) -> Spectra:
        """The table as a camera response sampled at its bands (the thesis' sensor map).

        R = r/g · ℓ, G = ℓ, B = b/g · ℓ per band, with ℓ the band's Green level relative to
        the brightest band's (:attr:`green_level`), or ℓ = 1 in every band when the table
        has no levels (the thesis' normalisation, Algorithm 12). With levels, a spectral
        image reconstructed with this response is in units of the light the camera saw in
        each band, so its bands are on comparable scales; without, each band is in units
        of its own Green response, and bands the camera barely sees (e.g. 400 and 700 nm)
        are hundreds of times smaller than the brightest. A reconstruction treats a response
        sampled only at its bands as a discrete model
        (:class:`reconstruction.model.image_formation.LatentSpace`).

        Raises
        ------
        DataError
            A ratio could not be fitted (NaN), or fewer than two bands.
        """
        for channel in ("r", "b"):
            ratios = getattr(self, f"{channel}_over_g")
            missing = ~np.isfinite(ratios)
            if missing.any():
                band = float(self.wavelengths_nm[missing][0])
                raise DataError(
                    f"sensitivity {self.source}: {channel}_over_g at {band:g} nm is unknown, so "
                    "the table cannot serve as a camera response; calibrate with images that "
                    "have signal in that band or leave the band out of the file"
                )
        known = np.isfinite(self.green_level) & (self.green_level > 0)
        if known.any() and not known.all():
            band = float(self.wavelengths_nm[~known][0])
            raise DataError(
                f"sensitivity {self.source}: the Green level at {band:g} nm is missing or not "
                "positive while other bands have one, so the bands' scales would disagree; "
                "calibrate that band again, or remove every green_level to use the thesis' "
                "normalisation (G = 1 in each band)"
            )
        level = self.relative_green_level if self.has_levels else np.ones(len(self))
        values = (
            np.column_stack([self.r_over_g, np.ones(len(self)), self.b_over_g]) * level[:, None]
        )
        return Spectra(self.wavelengths_nm, np.maximum(values, 0.0), ("R", "G", "B"))

    @property
    def has_levels(self) -> bool:
        """Whether every band has a positive, finite :attr:`green_level`."""
        return bool(np.all(np.isfinite(self.green_level)) and np.all(self.green_level > 0))

    @property
    def relative_green_level(self) -> np.ndarray:
        """(n,) :attr:`green_level` relative to the brightest band's; NaN without levels."""
        if not self.has_levels:
            return np.full(len(self), np.nan)
        return self.green_level / self.green_level.max()

    @classmethod
    def from_file(cls, path: str | Path) -> ChannelSensitivity:
        """Read a table written by :meth:`to_csv` or :meth:`to_yaml` (or by hand).

        Only ``wavelength_nm``, ``r_over_g`` and ``b_over_g`` are required; missing
        optional columns default to 0 pairs, unknown residuals, reliable, no reason.

        Raises
        ------
        DataError
            Unreadable file, unknown suffix, or an invalid value; the message names the
            file and the column (CSV) or key (YAML).
        """
        path = Path(path)
        if path.is_dir():
            inside = [path / f"sensitivity.{suffix}" for suffix in ("csv", "yaml")]
            found = [str(p) for p in inside if p.is_file()]
            hint = (
                f"give the table in it: {' or '.join(found)}"
                if found
                else f"give a sensitivity table file, such as {inside[0]} as written by "
                "`labkit calibrate sensitivity`"
            )
            raise DataError(f"sensitivity file {path} is a folder, not a file; {hint}")
        if not path.is_file():
            raise DataError(f"sensitivity file {path} does not exist")
        suffix = path.suffix.lower()
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as error:
            raise DataError(f"{path}: cannot read the sensitivity file ({error})") from None
        if suffix == ".csv":
            return _from_csv(path, text)
        if suffix in (".yaml", ".yml"):
            return _from_yaml(path, text)
        raise DataError(
            f"{path}: unknown sensitivity file type {suffix!r}; use .csv or .yaml "
            "(as written by `labkit calibrate sensitivity`)"
        )


def _column(values: Any, dtype: type, n: int, name: str) -> np.ndarray:
    array = np.asarray(values, dtype=dtype).ravel()
    if array.size != n:
        raise DataError(f"ChannelSensitivity: {name} has {array.size} entries, not {n}")
    return array


def _finite_or_none(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def _cell(value: Any) -> str:
    """A CSV cell: None → empty, bools lower-case, floats exact (shortest repr)."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value) if isinstance(value, float) else str(value)


def _from_csv(path: Path, text: str) -> ChannelSensitivity:
    reader = csv.DictReader(io.StringIO(text))
    header = reader.fieldnames or []
    unknown = [name for name in header if name not in COLUMNS]
    if unknown:
        raise DataError(
            f"{path}: column {unknown[0]!r} is not a known column; "
            f"expected columns {', '.join(COLUMNS)}"
        )
    missing = [name for name in _REQUIRED if name not in header]
    if missing:
        raise DataError(
            f"{path}: column {missing[0]!r} is missing; a sensitivity CSV needs at least "
            f"{', '.join(_REQUIRED)}"
        )
    rows = []
    for number, row in enumerate(reader, start=2):
        if None in row:
            raise DataError(f"{path}: line {number} has more cells than the header has columns")
        rows.append((f"line {number}", {k: v for k, v in row.items() if v is not None}))
    return _build(path, rows, lambda where, key: f"{where}, column {key!r}", source=str(path))


def _from_yaml(path: Path, text: str) -> ChannelSensitivity:
    import yaml

    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise DataError(f"{path}: not valid YAML ({error})") from None
    if not isinstance(document, dict):
        raise DataError(f"{path}: a sensitivity YAML file must be a mapping with `bands`")
    if document.get("format", FORMAT_VERSION) != FORMAT_VERSION:
        raise DataError(
            f"{path}: format is {document['format']!r}; this labkit reads format {FORMAT_VERSION}"
        )
    kind = document.get("kind", "channel_sensitivity")
    if kind != "channel_sensitivity":
        raise DataError(f"{path}: kind is {kind!r}; expected 'channel_sensitivity'")
    bands = document.get("bands")
    if not isinstance(bands, list):
        raise DataError(f"{path}: bands is missing or not a list; expected one entry per band")
    rows = []
    for number, band in enumerate(bands):
        if not isinstance(band, dict):
            raise DataError(f"{path}: bands[{number}] must be a mapping of {', '.join(COLUMNS)}")
        unknown = [key for key in band if key not in COLUMNS]
        if unknown:
            raise DataError(
                f"{path}: bands[{number}].{unknown[0]} is not a known key; "
                f"expected keys {', '.join(COLUMNS)}"
            )
        rows.append((f"bands[{number}]", band))
    provenance = document.get("labkit") or {}
    return _build(
        path,
        rows,
        lambda where, key: f"{where}.{key}",
        source=str(document.get("source", path)),
        provenance=provenance if isinstance(provenance, dict) else {},
    )


def _build(
    path: Path,
    rows: list[tuple[str, Mapping[str, Any]]],
    locate: Callable[[str, str], str],
    *,
    source: str,
    provenance: dict[str, Any] | None = None,
) -> ChannelSensitivity:
    if not rows:
        raise DataError(f"{path}: no bands; the file must list at least one band")

    def fail(where: str, key: str, problem: str) -> DataError:
        return DataError(f"{path}: {locate(where, key)} {problem}")

    def number(where: str, row: Mapping[str, Any], key: str, *, required: bool) -> float:
        value = row.get(key)
        if value is None or (isinstance(value, str) and value.strip() == ""):
            if required:
                raise fail(where, key, "is missing; give a number")
            return math.nan
        if isinstance(value, bool):
            raise fail(where, key, f"is {value!r}; expected a number")
        try:
            result = float(value)
        except (TypeError, ValueError):
            raise fail(where, key, f"is {value!r}; expected a number") from None
        if not math.isfinite(result):
            if required:
                raise fail(where, key, f"is {value!r}; expected a finite number")
            return math.nan
        return result

    def flag(where: str, row: Mapping[str, Any], key: str) -> bool:
        value = row.get(key)
        if value is None or value == "":
            return True
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower()
        if text in ("true", "yes", "1"):
            return True
        if text in ("false", "no", "0"):
            return False
        raise fail(where, key, f"is {value!r}; expected true or false")

    columns: dict[str, list[Any]] = {key: [] for key in COLUMNS}
    for where, row in rows:
        wavelength = number(where, row, "wavelength_nm", required=True)
        if not WAVELENGTH_RANGE_NM[0] <= wavelength <= WAVELENGTH_RANGE_NM[1]:
            low, high = WAVELENGTH_RANGE_NM
            raise fail(
                where,
                "wavelength_nm",
                f"is {wavelength:g}; expected a filter band's centre, {low:g}–{high:g} nm "
                "(the range of a rig filter's centre_nm)",
            )
        columns["wavelength_nm"].append(wavelength)
        illumination = row.get("illumination")
        columns["illumination"].append(
            f"{wavelength:g}" if illumination in (None, "") else str(illumination)
        )
        for key in ("pairs_r", "pairs_b"):
            count = number(where, row, key, required=False)
            if math.isnan(count):
                count = 0
            if count < 0 or count != int(count):
                raise fail(where, key, f"is {row.get(key)!r}; expected a whole number ≥ 0")
            columns[key].append(int(count))
        for key in ("residual_r", "residual_b"):
            columns[key].append(number(where, row, key, required=False))
        level = number(where, row, "green_level", required=False)
        if level <= 0:
            raise fail(where, "green_level", f"is {level:g}; a Green level must be positive")
        columns["green_level"].append(level)
        for channel in ("r", "b"):
            reliable = flag(where, row, f"reliable_{channel}")
            key = f"{channel}_over_g"
            ratio = number(where, row, key, required=reliable)
            if ratio < 0:
                raise fail(where, key, f"is {ratio:g}; a sensitivity ratio cannot be negative")
            columns[key].append(ratio)
            columns[f"reliable_{channel}"].append(reliable)
            reason = row.get(f"reason_{channel}")
            columns[f"reason_{channel}"].append("" if reason is None else str(reason))
    order = np.argsort(columns["wavelength_nm"], kind="stable")
    sorted_w = np.asarray(columns["wavelength_nm"])[order]
    close = np.flatnonzero(np.diff(sorted_w) <= BAND_TOLERANCE_NM)
    if close.size:
        duplicate = rows[order[close[0] + 1]][0]
        raise fail(duplicate, "wavelength_nm", f"repeats the band at {sorted_w[close[0]]:g} nm")
    picked = {key: [values[i] for i in order] for key, values in columns.items()}
    return ChannelSensitivity(
        wavelengths_nm=picked["wavelength_nm"],
        illuminations=tuple(picked["illumination"]),
        r_over_g=picked["r_over_g"],
        b_over_g=picked["b_over_g"],
        pairs_r=picked["pairs_r"],
        pairs_b=picked["pairs_b"],
        residual_r=picked["residual_r"],
        residual_b=picked["residual_b"],
        reliable_r=picked["reliable_r"],
        reliable_b=picked["reliable_b"],
        reason_r=tuple(picked["reason_r"]),
        reason_b=tuple(picked["reason_b"]),
        green_level=picked["green_level"],
        source=source,
        labkit={**(provenance or {}), "file": str(path)},
    )


def is_sensitivity_file(source: str | Path) -> bool:
    """Whether `source` names a table written by ``labkit calibrate sensitivity``."""
    path = Path(str(source))
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):
        return True
    if suffix != ".csv" or not path.is_file():
        return False
    with path.open(newline="", encoding="utf-8", errors="replace") as handle:
        header = next(csv.reader(handle), [])
    return "r_over_g" in [cell.strip() for cell in header]


def load_response(source: object) -> Spectra:
    """A camera response from a dataset name, a response CSV, a measured sensitivity, or
    spectra in memory.

    Parameters
    ----------
    source : str, Path, or spectra
        The ``sensitivity.yaml``/``.csv`` of ``labkit calibrate sensitivity`` (then
        :meth:`ChannelSensitivity.as_response`: sampled at its bands), or anything
        :func:`labkit.spectra.camera_response` takes: a colour-science camera dataset name,
        a CSV ``wavelength_nm,R,G,B``, a :class:`Spectra`, colour-science spectral
        distributions, ``(wavelengths_nm, values)``.
    """
    if isinstance(source, str | Path) and is_sensitivity_file(source):
        return ChannelSensitivity.from_file(source).as_response()
    return camera_response(source)
