"""Dispersion models: what a calibration produces and reconstruction consumes (thesis §3.2.4).

A :class:`DispersionModel` maps image positions (and, for spectral models, wavelengths)
to displacement vectors in pixels. It is made of one :class:`DisplacementField` per
band label — ``"spectral"`` for a trivariate model in (x, y, λ), or one per colour
channel (``"R"``, ``"B"``) for bivariate models relative to Green — plus what every model
shares: its direction, its reference, the image size and the calibrated region.

Directions (thesis §3.2.4, last paragraph):

``from_reference``
    input = position p in the reference image, output = d such that the feature is
    imaged at p + d in the band. Used to correct images by warping.
``to_reference``
    input = position q in the band image, output = e such that the feature is at
    q + e in the reference image. Used in image formation (reconstruction).

The YAML file (``format: 1``) is documented in docs/formats.md; :func:`load_dispersion_model`
reads it back and validates every field, naming the file and key of any problem.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar, Literal, Protocol

import numpy as np
import yaml

from calibration._model_files import read_model_document
from calibration.model_domain import CalibratedRegion, check_extrapolation
from calibration.polynomial_field import PolynomialField
from calibration.spline_field import SplineField
from labkit.errors import ConfigError, DataError
from labkit.io import write_text_atomic
from labkit.io.plain import to_plain

FORMAT = 1
KIND = "labkit.dispersion_model"
#: Points evaluated per chunk by :meth:`DispersionModel.displacement` (bounds memory).
CHUNK_POINTS = 1 << 20

Direction = Literal["from_reference", "to_reference"]
Variables = Literal["xy", "xylambda"]
SPECTRAL = "spectral"


class DisplacementField(Protocol):
    """One smooth vector field: normalised inputs → displacement in px."""

    #: ``"polynomial"`` or ``"spline"``.
    kind: str

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """Displacements (n, 2) in px at `points` (n, 2) = (x, y) or (n, 3) = (x, y, λ nm)."""
        ...

    def to_dict(self) -> dict[str, Any]:
        """Plain-YAML representation (floats and lists only)."""
        ...


@dataclass(frozen=True)
class ShiftedField:
    """A field seen from a window of its image: evaluated `offset_xy` px further on.

    A model calibrated on the whole sensor, used on a crop of it
    (:meth:`DispersionModel.cropped`): the crop's pixel (x, y) is the sensor's
    (x + offset_x, y + offset_y).
    """

    kind: ClassVar[str] = "shifted"
    inner: DisplacementField
    offset_xy: tuple[float, float]

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        moved = np.array(points, dtype=np.float64, copy=True)
        moved[:, 0] += self.offset_xy[0]
        moved[:, 1] += self.offset_xy[1]
        return self.inner.evaluate(moved)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "offset_xy": [float(self.offset_xy[0]), float(self.offset_xy[1])],
            "field": self.inner.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str) -> ShiftedField:
        offset = data.get("offset_xy")
        if (
            not isinstance(offset, list)
            or len(offset) != 2
            or not all(isinstance(v, int | float) and np.isfinite(v) for v in offset)
        ):
            raise ConfigError(f"{where}.offset_xy must be [x, y] in px, got {offset!r}")
        inner = data.get("field")
        if not isinstance(inner, Mapping):
            raise ConfigError(f"{where}.field must be a mapping (the sensor's field)")
        reader = FIELD_READERS.get(inner.get("kind"))
        if reader is None:
            raise ConfigError(
                f"{where}.field: unknown field kind {inner.get('kind')!r}; known: "
                f"{', '.join(FIELD_READERS)}"
            )
        return cls(reader(inner, f"{where}.field"), (float(offset[0]), float(offset[1])))


#: Field readers by kind (the ``kind`` key of each field in a model file).
FIELD_READERS: dict[str, Callable[[Mapping[str, Any], str], DisplacementField]] = {
    PolynomialField.kind: PolynomialField.from_dict,
    SplineField.kind: SplineField.from_dict,
    ShiftedField.kind: ShiftedField.from_dict,
}


@dataclass(frozen=True)
class DispersionModel:
    """A calibrated model of lateral chromatic aberration.

    Attributes
    ----------
    type : {"polynomial", "spline"}
    variables : {"xy", "xylambda"}
        Colour-channel (bivariate, one field per channel) or spectral (trivariate).
    direction : {"from_reference", "to_reference"}
    reference : float or str
        Reference wavelength (nm) or channel.
    image_shape : (rows, cols)
    fields : dict of str to DisplacementField
        ``{"spectral": field}`` or ``{"R": field, "B": field}``.
    region : CalibratedRegion
    selection : dict
        Model selection report (degrees, CV/GCV errors, condition numbers, smoothing).
    provenance : dict
        Keypoint source, input files, software version, band wavelengths.
    extrapolation : {"allow", "clamp"}
        Outside the calibrated region: evaluate the fitted function (``"allow"``, the
        model as fitted), or first move the inputs into the region
        (:meth:`CalibratedRegion.clamp`; :meth:`within_domain`). Not stored in the file:
        each use chooses, and says so (:func:`calibration.model_domain.domain_use`).
    """

    type: str
    variables: Variables
    direction: Direction
    reference: float | str
    image_shape: tuple[int, int]
    fields: dict[str, DisplacementField]
    region: CalibratedRegion
    selection: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    extrapolation: Literal["allow", "clamp"] = "allow"

    def __post_init__(self) -> None:
        if self.extrapolation not in ("allow", "clamp"):
            raise ConfigError(f"extrapolation must be allow or clamp, not {self.extrapolation!r}")
        if self.variables not in ("xy", "xylambda"):
            raise ConfigError(f"variables must be xy or xylambda, not {self.variables!r}")
        if self.direction not in ("from_reference", "to_reference"):
            raise ConfigError(
                f"direction must be from_reference or to_reference, not {self.direction!r}"
            )
        if self.variables == "xylambda" and set(self.fields) != {SPECTRAL}:
            raise ConfigError(f"a spectral model has one field named {SPECTRAL!r}")
        if not self.fields:
            raise ConfigError("a dispersion model needs at least one field")

    def within_domain(self, policy: str = "clamp") -> DispersionModel:
        """This model as a use's extrapolation `policy` evaluates it: inside its calibrated
        region only (``"clamp"``, and ``"refuse"``, which stops before going outside), or
        as fitted (``"allow"``)."""
        check_extrapolation(policy)
        return replace(self, extrapolation="allow" if policy == "allow" else "clamp")

    def cropped(self, origin: tuple[int, int], shape: tuple[int, int]) -> DispersionModel:
        """This model on the `shape` (rows, cols) px window of its image at `origin`
        (row, col): the displacement at the window's pixel (x, y) is the sensor's at
        (x + col, y + row), the calibrated region moves with it, and the window is
        recorded in ``provenance.crop``. Saved and read like any model.

        Raises
        ------
        DataError
            The window does not lie inside the model's image.
        """
        r0, c0 = (int(v) for v in origin)
        rows, cols = (int(v) for v in shape)
        full_rows, full_cols = self.image_shape
        inside = min(r0, c0) >= 0 and min(rows, cols) >= 1
        if not inside or r0 + rows > full_rows or c0 + cols > full_cols:
            raise DataError(
                f"crop window at (row, col) = ({r0}, {c0}) of {rows}×{cols} px does not lie "
                f"inside the model's {full_rows}×{full_cols} px image"
            )
        offset = (float(c0), float(r0))
        fields = {name: ShiftedField(f, offset) for name, f in self.fields.items()}
        region = replace(self.region, hull_xy=self.region.hull_xy - np.array(offset))
        crop = {"origin": [r0, c0], "shape": [rows, cols], "image_shape": [full_rows, full_cols]}
        earlier = self.provenance.get("crop")
        if isinstance(earlier, Mapping):  # a crop of a crop: the origin on the sensor
            first = earlier.get("origin", [0, 0])
            crop = {**crop, "origin": [r0 + first[0], c0 + first[1]],
                    "image_shape": earlier.get("image_shape")}  # fmt: skip
        return replace(
            self,
            image_shape=(rows, cols),
            fields=fields,
            region=region,
            provenance={**self.provenance, "crop": crop},
        )

    @property
    def channels(self) -> list[str]:
        """Channels with a field (colour-channel models); empty for spectral models."""
        return [] if self.variables == "xylambda" else sorted(self.fields)

    def displacement(
        self,
        x: np.ndarray | float,
        y: np.ndarray | float,
        wavelength_nm: np.ndarray | float | None = None,
        *,
        channel: str | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (dx, dy) in px at positions (x, y) px, broadcast over all inputs.

        Parameters
        ----------
        x, y : array_like
            Column and row, px (pixel centres at integers). For ``from_reference``
            models a reference-image position, for ``to_reference`` a band position.
        wavelength_nm : array_like, optional
            Band wavelength, nm (spectral models; required there).
        channel : str, optional
            ``"R"`` / ``"B"`` (colour-channel models; the reference channel gives 0).

        Returns
        -------
        dx, dy : ndarray, float64, the broadcast shape of the inputs.
        """
        if self.variables == "xylambda":
            if wavelength_nm is None:
                raise DataError("this spectral dispersion model needs wavelength_nm")
            if channel is not None:
                raise DataError("channel= applies to colour-channel models, not spectral ones")
            given = (x, y, wavelength_nm)
            fld = self.fields[SPECTRAL]
        else:
            if wavelength_nm is not None:
                raise DataError(
                    "this colour-channel dispersion model takes channel=, not wavelength_nm; "
                    f"channels: {', '.join(self.channels)}"
                )
            if channel == self.reference:
                zero = np.zeros(np.broadcast_shapes(np.shape(x), np.shape(y)))
                return zero, zero.copy()
            if channel not in self.fields:
                raise DataError(
                    f"channel {channel!r} not in this model; use one of "
                    f"{', '.join([str(self.reference), *self.channels])}"
                )
            given = (x, y)
            fld = self.fields[channel]
        given = self._domain_inputs(*given)
        arrays = np.broadcast_arrays(*given)
        shape = arrays[0].shape
        points = np.column_stack([a.ravel() for a in arrays])
        out = np.empty((points.shape[0], 2))
        for start in range(0, points.shape[0], CHUNK_POINTS):
            out[start : start + CHUNK_POINTS] = fld.evaluate(points[start : start + CHUNK_POINTS])
        return out[:, 0].reshape(shape), out[:, 1].reshape(shape)

    def displacement_grid(
        self, x: np.ndarray, y: np.ndarray, wavelengths_nm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`displacement` of a spectral model at every position (`x`, `y`) (the same
        shape, px) for every wavelength of the 1-D `wavelengths_nm` (nm): (dx, dy), each
        of shape ``x.shape + (len(wavelengths_nm),)``. The same values, evaluated once per
        position and once per wavelength where the field allows it (a polynomial)."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        waves = np.asarray(wavelengths_nm, np.float64).ravel()
        fld = self.fields.get(SPECTRAL)
        if self.variables != "xylambda" or not hasattr(fld, "evaluate_grid"):
            return self.displacement(x[..., None], y[..., None], waves)
        x, y, waves = self._domain_inputs(x, y, waves)
        out = fld.evaluate_grid(np.column_stack([x.ravel(), y.ravel()]), waves)
        shape = (*x.shape, len(waves))
        return out[..., 0].reshape(shape), out[..., 1].reshape(shape)

    def _domain_inputs(self, *given: Any) -> tuple[np.ndarray, ...]:
        """(x, y[, wavelength]) as float64 arrays, checked finite and, for a clamped model,
        moved into its domain before any broadcasting: positions given once for many
        wavelengths are moved once (the hull's nearest point costs far more than the
        polynomial)."""
        arrays = tuple(np.asarray(v, np.float64) for v in given)
        if not all(np.all(np.isfinite(v)) for v in arrays):
            raise DataError("dispersion model inputs hold NaN or Inf")
        if self.extrapolation != "clamp":
            return arrays
        x, y, wave = self.region.clamp(*arrays)
        return (x, y) if wave is None else (x, y, wave)

    # -- files ----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The YAML document (plain types only)."""
        reference = self.reference if isinstance(self.reference, str) else float(self.reference)
        return {
            "format": FORMAT,
            "kind": KIND,
            "type": self.type,
            "variables": self.variables,
            "direction": self.direction,
            "reference": reference,
            "image_shape": [int(self.image_shape[0]), int(self.image_shape[1])],
            "region": self.region.to_dict(),
            "fields": {name: f.to_dict() for name, f in sorted(self.fields.items())},
            "selection": to_plain(self.selection),
            "provenance": to_plain(self.provenance),
        }

    def save(self, path: str | Path) -> Path:
        """Write the model as YAML, atomically; returns the path."""
        text = yaml.safe_dump(self.to_dict(), sort_keys=False, width=120)
        write_text_atomic(path, text)
        return Path(path)

    @classmethod
    def from_dict(cls, data: Any, *, source: str = "<model>") -> DispersionModel:
        """Validate and build a model from its YAML document."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"{source}: a dispersion model file must be a YAML mapping")
        if data.get("kind") != KIND:
            raise ConfigError(
                f"{source}: `kind` is {data.get('kind')!r}, expected {KIND!r}; "
                "is this a dispersion model written by `labkit calibrate dispersion`?"
            )
        if data.get("format") != FORMAT:
            raise ConfigError(
                f"{source}: `format` {data.get('format')!r} is not supported (expected {FORMAT})"
            )
        for key in (
            "type",
            "variables",
            "direction",
            "reference",
            "image_shape",
            "region",
            "fields",
        ):
            if key not in data:
                raise ConfigError(f"{source}: missing key `{key}`")
        fields_data = data["fields"]
        if not isinstance(fields_data, Mapping) or not fields_data:
            raise ConfigError(f"{source}: `fields` must be a non-empty mapping")
        fields: dict[str, DisplacementField] = {}
        for name, fdata in fields_data.items():
            where = f"{source}: fields.{name}"
            if not isinstance(fdata, Mapping):
                raise ConfigError(f"{where} must be a mapping")
            kind = fdata.get("kind", data["type"])
            reader = FIELD_READERS.get(kind)
            if reader is None:
                raise ConfigError(
                    f"{where}: unknown field kind {kind!r}; known: {', '.join(FIELD_READERS)}"
                )
            fields[str(name)] = reader(fdata, where)
        shape = data["image_shape"]
        if (
            not isinstance(shape, list)
            or len(shape) != 2
            or not all(isinstance(v, int) and v > 0 for v in shape)
        ):
            raise ConfigError(f"{source}: image_shape must be [rows, cols], got {shape!r}")
        reference = data["reference"]
        if data["variables"] == "xylambda":
            if not isinstance(reference, int | float):
                raise ConfigError(f"{source}: a spectral model's reference must be a wavelength")
            reference = float(reference)
        try:
            return cls(
                type=str(data["type"]),
                variables=data["variables"],
                direction=data["direction"],
                reference=reference,
                image_shape=(shape[0], shape[1]),
                fields=fields,
                region=CalibratedRegion.from_dict(data["region"], f"{source}: region"),
                selection=dict(data.get("selection") or {}),
                provenance=dict(data.get("provenance") or {}),
            )
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}") from None


def load_dispersion_model(path: str | Path) -> DispersionModel:
    """Read a dispersion model YAML file (see docs/formats.md for its format).

    Raises
    ------
    ConfigError
        The file is missing, is not YAML, or any key is invalid (the message names it).
    """
    data = read_model_document(
        path,
        what="dispersion model",
        missing_fix="create one with `labkit calibrate dispersion HDR_DIR --out MODEL.yaml`",
        writer="labkit calibrate dispersion",
    )
    return DispersionModel.from_dict(data, source=str(path))
