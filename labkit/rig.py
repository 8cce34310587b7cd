"""Rig description files (``rigs/*.yaml``): schema, validation and loading.

A rig names the camera, the filter slider and its positions, the light source, the
capture plan and, for the simulated backend, the physics of the simulated rig. Files are
read with ``yaml.safe_load`` and validated; an invalid file raises one
:class:`~labkit.errors.ConfigError` naming the file, the key path, the bad value and
what is expected.
"""

from __future__ import annotations

import difflib
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from labkit.cfa import layout_from_pixel_format
from labkit.errors import ConfigError, DataError
from labkit.frame import path_name_problem
from labkit.spectra import MEASURED_FILTER_COLUMNS, BandpassFilter
from labkit.spectra.illuminants import illuminant_problem

RIG_FORMAT = 1
PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Seed = Annotated[int, Field(ge=0, description="random seed, ≥ 0")]


def _plain_name(name: str) -> str:
    why = path_name_problem(name)
    if why:
        raise ValueError(f"{name!r} names folders and files of the session, but {why}")
    return name


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraConfig(_Strict):
    """The camera: backend, which device, pixel format and spectral response."""

    backend: Literal["aravis", "genicam", "sim"]
    device: str | None = Field(None, description="device id, serial or IP; None = the first found")
    cti: str | None = Field(None, description="GenTL producer (.cti) path, genicam backend only")
    pixel_format: str = "BayerGB12"
    response: str = Field(
        "Nikon 5100 (NPL)",
        description="colour-science dataset, response CSV, or `labkit calibrate sensitivity` file",
    )
    gain_db: NonNegativeFloat = 0.0

    @field_validator("pixel_format")
    @classmethod
    def _bayer(cls, value: str) -> str:
        try:
            layout_from_pixel_format(value)
        except DataError:
            raise ValueError(
                "a Bayer pixel format such as BayerGB12 (Bayer{RG,BG,GR,GB}{8,12,12p,16})"
            ) from None
        return value

    @model_validator(mode="after")
    def _cti_for_genicam(self) -> CameraConfig:
        if self.backend == "genicam" and not self.cti:
            raise ValueError("the genicam backend needs `cti`: the path of a GenTL producer")
        return self

    @property
    def cfa(self) -> str:
        """CFA layout implied by the pixel format."""
        return layout_from_pixel_format(self.pixel_format)


class FilterConfig(_Strict):
    """A bandpass filter in a slider position."""

    centre_nm: Annotated[float, Field(ge=300, le=1100)]
    fwhm_nm: Annotated[float, Field(gt=0, le=200)] = 10.0
    optical_density: Annotated[float, Field(ge=0, le=10)] = 4.0
    peak_transmission: Annotated[float, Field(gt=0, le=1)] = 0.85
    measured: Literal[MEASURED_FILTER_COLUMNS] | None = None  # type: ignore[valid-type]

    def to_filter(self) -> BandpassFilter:
        """The spectral model of this filter."""
        return BandpassFilter(
            self.centre_nm,
            self.fwhm_nm,
            self.optical_density,
            self.peak_transmission,
            self.measured,
        )


class SliderPosition(_Strict):
    """One slot of the slider: a name and optionally a filter (None = open)."""

    name: Annotated[str, Field(min_length=1)]
    filter: FilterConfig | None = None

    @field_validator("name")
    @classmethod
    def _plain_name(cls, value: str) -> str:
        return _plain_name(value)


class SliderConfig(_Strict):
    """The motorised filter slider / wheel."""

    driver: Literal["fw102c", "elliptec", "sim"]
    port: str = Field(..., description="serial port, e.g. /dev/ttyUSB0, or 'sim'")
    address: Annotated[int, Field(ge=0, le=15)] = 0
    timeout_s: Annotated[float, Field(gt=0, le=60)] = Field(2.0, description="reply timeout, s")
    move_timeout_s: Annotated[float, Field(gt=0, le=300)] = Field(5.0, description="per move, s")
    retries: Annotated[int, Field(ge=1, le=20)] = Field(3, description="attempts per command")
    positions: dict[Annotated[int, Field(ge=1, le=12)], SliderPosition] = Field(
        ..., description="slot number (1-based, as the drivers count) → position"
    )

    @model_validator(mode="after")
    def _names(self) -> SliderConfig:
        names = [p.name for p in self.positions.values()]
        if len(set(names)) != len(names):
            raise ValueError(f"position names must be unique, got {names}")
        if "dark" in names:
            raise ValueError("'dark' is reserved for covered-light frames; rename that position")
        if not self.positions:
            raise ValueError("at least one position is needed")
        return self

    def illumination_names(self) -> list[str]:
        """Names of all illuminations: unfiltered (open) positions first."""
        return [p.name for p in self.positions.values()]

    def position_names(self) -> dict[int, str]:
        """Slot → the name of the illumination that slot gives."""
        return {slot: p.name for slot, p in self.positions.items()}


class LightConfig(_Strict):
    """The light source."""

    source: str = Field("projector", description="'projector', 'E' or a colour-science illuminant")

    @field_validator("source")
    @classmethod
    def _known(cls, value: str) -> str:
        hint = illuminant_problem(value)
        if hint:
            raise ValueError(f"'projector', 'E' or a colour-science illuminant; {hint}")
        return value


class ExposureConfig(_Strict):
    """Exposure times, s, for unfiltered and filtered illumination (or 'auto')."""

    unfiltered: list[PositiveFloat] | Literal["auto"] = [0.003, 0.006, 0.012]
    filtered: list[PositiveFloat] | Literal["auto"] = [0.025, 0.05, 0.1, 0.25, 0.5, 2.0, 3.916]


class ReplicateConfig(_Strict):
    """Frames averaged per exposure (thesis: 15 unfiltered, 5 filtered)."""

    unfiltered: Annotated[int, Field(ge=1, le=1000)] = 15
    filtered: Annotated[int, Field(ge=1, le=1000)] = 5


class AutoExposureConfig(_Strict):
    """How ``auto`` exposure lists are chosen (labkit.protocol.bracketing).

    A pixel is properly exposed when its dark-subtracted value lies between
    `low_fraction` and `high_fraction` of the dark-subtracted saturation level; the
    predicted window is narrowed by `margin` at both ends against metering noise.
    """

    low_fraction: Annotated[float, Field(gt=0, lt=0.5)] = 0.02
    high_fraction: Annotated[float, Field(gt=0.5, le=1)] = 0.95
    margin: Annotated[float, Field(ge=1, le=3)] = 1.15
    max_exposure_s: PositiveFloat = Field(4.0, description="longest exposure auto may choose, s")
    steps_per_octave: Annotated[int, Field(ge=1, le=16)] = 4


class PlanConfig(_Strict):
    """What to capture (thesis Algorithm 10)."""

    scenes: list[Annotated[str, Field(min_length=1), AfterValidator(_plain_name)]] = [
        "disks",
        "colorchecker",
    ]

    illuminations: list[str] | Literal["all"] = "all"
    exposures_s: ExposureConfig = ExposureConfig()
    replicates: ReplicateConfig = ReplicateConfig()
    dark_frames: bool = True
    auto: AutoExposureConfig = AutoExposureConfig()


class SimSensorConfig(_Strict):
    """Simulated sensor physics."""

    width: Annotated[int, Field(ge=8, le=16384, multiple_of=2)] = 2448
    height: Annotated[int, Field(ge=8, le=16384, multiple_of=2)] = 2048
    adc_bits: Literal[8, 10, 12, 14, 16] = 12
    full_well_e: PositiveFloat = 10_000.0
    gain_dn_per_e: PositiveFloat = 0.40
    read_noise_e: NonNegativeFloat = 8.0
    dark_current_e_per_s: NonNegativeFloat = 5.0
    dark_current_nonuniformity: NonNegativeFloat = 0.2
    prnu: Annotated[float, Field(ge=0, le=0.5)] = 0.01
    black_level_dn: NonNegativeFloat = 32.0
    bloom_fraction: Annotated[float, Field(ge=0, le=1)] = 0.5
    exposure_jitter_s: NonNegativeFloat = 2e-5

    @model_validator(mode="after")
    def _black_below_saturation(self) -> SimSensorConfig:
        top = 2**self.adc_bits - 1
        if self.black_level_dn >= top:
            raise ValueError(
                f"black_level_dn {self.black_level_dn:g} is not below the {self.adc_bits}-bit "
                f"ADC maximum {top} (2**adc_bits − 1), so every pixel would be saturated; "
                f"lower black_level_dn (typically a few % of {top}) or raise adc_bits"
            )
        return self


class SimLightConfig(_Strict):
    """Simulated light output and its instability."""

    white_rate_e_per_s: PositiveFloat = Field(
        8.0e5, description="electrons/s of a perfect white reflector, unfiltered, brightest channel"
    )
    flicker: NonNegativeFloat = Field(0.0, description="relative frame-to-frame noise (1σ)")
    drift_amplitude: NonNegativeFloat = Field(0.0, description="relative slow sinusoidal drift")
    drift_period_s: PositiveFloat = 600.0


class SimLensConfig(_Strict):
    """Simulated optics (see labkit.sim.lens)."""

    max_shift_px: FiniteFloat = 2.5
    reference_nm: Annotated[float, Field(ge=350, le=1000)] = 600.0
    spectral_profile: Literal["singlet", "achromat"] = "singlet"
    radial_profile: Literal["linear", "nonmonotonic"] = "linear"
    centre_px: tuple[FiniteFloat, FiniteFloat] | None = None
    vignetting: Annotated[float, Field(ge=0, lt=1)] = 0.0
    blur_sigma_px: Annotated[float, Field(ge=0, le=10)] = 0.0


#: Options each simulated scene type takes (see labkit.sim.scenes).
SCENE_OPTIONS = {
    "disks": ("radius_px", "pitch_px"),
    "colorchecker": ("reflectances",),
    "texture": ("seed",),
    "natural": ("seed",),
    "flat": ("reflectance",),
}


class SimSceneConfig(_Strict):
    """A simulated scene: its type and geometry parameters."""

    type: Literal["disks", "colorchecker", "texture", "natural", "flat"]
    radius_px: PositiveFloat | None = None
    pitch_px: PositiveFloat | None = None
    reflectances: str | None = None
    seed: Seed | None = None
    reflectance: Annotated[float, Field(ge=0, le=1)] | None = None

    @model_validator(mode="after")
    def _options_fit_type(self) -> SimSceneConfig:
        given = {k for k, v in self.model_dump().items() if v is not None and k != "type"}
        unused = sorted(given - set(SCENE_OPTIONS[self.type]))
        if unused:
            raise ValueError(
                f"scene type {self.type!r} does not take {unused}; "
                f"it takes {list(SCENE_OPTIONS[self.type])}"
            )
        return self

    def options(self) -> dict[str, Any]:
        """The options that were given, as keyword arguments of the scene builder."""
        return {k: v for k, v in self.model_dump().items() if v is not None and k != "type"}


class SimConfig(_Strict):
    """Everything the simulated rig needs beyond the camera/slider description."""

    seed: Seed = 0
    spectral_step_nm: Annotated[float, Field(gt=0, le=2)] = 1.0
    level_step_px: Annotated[float, Field(gt=0, le=1)] = 0.25
    readout_s: NonNegativeFloat = 0.05
    sensor: SimSensorConfig = SimSensorConfig()
    light: SimLightConfig = SimLightConfig()
    lens: SimLensConfig = SimLensConfig()
    scenes: dict[str, SimSceneConfig] = {
        "disks": SimSceneConfig(type="disks"),
        "colorchecker": SimSceneConfig(type="colorchecker"),
        "texture": SimSceneConfig(type="texture"),
    }


class Rig(_Strict):
    """A validated rig description."""

    format: Literal[1] = Field(..., description=f"file format version, {RIG_FORMAT}")
    name: str = "rig"
    camera: CameraConfig
    slider: SliderConfig
    light: LightConfig = LightConfig()
    plan: PlanConfig = PlanConfig()
    sim: SimConfig | None = None
    source: str | None = Field(None, exclude=True, description="file the rig was read from")

    @model_validator(mode="after")
    def _consistent(self) -> Rig:
        if self.camera.backend == "sim" and self.sim is None:
            object.__setattr__(self, "sim", SimConfig())
        if self.plan.illuminations != "all":
            known = set(self.slider.illumination_names())
            for name in self.plan.illuminations:
                if name not in known:
                    raise ValueError(
                        f"plan.illuminations names {name!r}, which is not a slider position "
                        f"(positions: {sorted(known)})"
                    )
        if self.sim is not None and self.camera.backend == "sim":
            for scene in self.plan.scenes:
                if scene not in self.sim.scenes:
                    raise ValueError(
                        f"plan.scenes names {scene!r}, which sim.scenes does not define "
                        f"(defined: {sorted(self.sim.scenes)})"
                    )
        return self

    @property
    def cfa(self) -> str:
        """The camera's CFA layout."""
        return self.camera.cfa

    def with_changes(self, changes: dict[str, Any]) -> Rig:
        """A variant of this rig: `changes` merged into its keys, validated as a rig file is.

        Parameters
        ----------
        changes : dict
            Nested keys as in a rig file, e.g. ``{"sim": {"sensor": {"height": 256,
            "width": 320}}}``; a mapping is merged key by key, any other value replaces.

        Returns
        -------
        Rig
            The variant, with this rig's `source`.

        Raises
        ------
        ConfigError
            The variant is not a valid rig; the message names the key.
        """
        data = _merged(self.model_dump(mode="json", exclude_unset=False), changes)
        return rig_from_dict(data, source=self.source or "<rig>")

    def illuminations(self) -> list[str]:
        """Illuminations of the plan, in slider order."""
        if self.plan.illuminations == "all":
            return self.slider.illumination_names()
        return list(self.plan.illuminations)

    def exposures_for(self, illumination: str) -> list[float] | Literal["auto"]:
        """The plan's exposure times (s) for an illumination, or ``"auto"``."""
        times = self.plan.exposures_s
        return times.unfiltered if self.filter_for(illumination) is None else times.filtered

    def replicates_for(self, illumination: str) -> int:
        """The plan's replicate count for an illumination."""
        counts = self.plan.replicates
        return counts.unfiltered if self.filter_for(illumination) is None else counts.filtered

    def filter_for(self, illumination: str) -> BandpassFilter | None:
        """The filter of a named slider position (None for an open position)."""
        for position in self.slider.positions.values():
            if position.name == illumination:
                return position.filter.to_filter() if position.filter else None
        raise ConfigError(
            f"rig {self.source or self.name!r} has no illumination {illumination!r}; "
            f"use one of {self.slider.illumination_names()} or 'dark'"
        )

    def response_source(self) -> str:
        """The camera response: a dataset name, or a file path relative to the rig file.

        Files are response CSVs (``wavelength_nm,R,G,B``) or the ``sensitivity.yaml``/
        ``.csv`` that ``labkit calibrate sensitivity`` writes (the thesis' sensor map).
        """
        file = self.response_file()
        return self.camera.response if file is None else str(file)

    def response_file(self) -> Path | None:
        """The camera response's file, resolved relative to the rig file; None where the
        response is a dataset name (not a ``.csv``/``.yaml`` path)."""
        value = self.camera.response
        if not value.lower().endswith((".csv", ".yaml", ".yml")):
            return None
        return Path(self.resolve_path(value))

    def resolve_path(self, value: str) -> str:
        """A path from the rig file, made absolute relative to the file's folder."""
        path = Path(value)
        if path.is_absolute() or self.source is None:
            return str(path)
        return str(Path(self.source).parent / path)


def _key_path(location: tuple[Any, ...]) -> str:
    # pydantic adds union-branch tags such as "list[constrained-float]"; they are not keys
    parts = [str(part) for part in location if "[" not in str(part)]
    text = ""
    for part in parts:
        text += f"[{part}]" if part.isdigit() else (f".{part}" if text else part)
    return text or "(top level)"


def _union_root(location: tuple[Any, ...]) -> str:
    """Key path up to the first union-branch tag: all branches of one field share it."""
    root = []
    for part in location:
        if "[" in str(part):
            break
        root.append(part)
    return _key_path(tuple(root))


def _model_in(annotation: Any) -> type[BaseModel] | None:
    """The pydantic model an annotation holds (through Annotated, Optional and unions)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        return _model_in(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(annotation):
            model = _model_in(arg)
            if model is not None:
                return model
    return None


def _step(annotation: Any, part: Any) -> Any:
    """The annotation one key below `annotation` (a model's field, a dict's or list's item)."""
    model = _model_in(annotation)
    if model is not None:
        field = model.model_fields.get(str(part))
        return None if field is None else field.annotation
    options = [annotation]
    while options:
        option = options.pop(0)
        origin = typing.get_origin(option)
        if origin is dict:
            return typing.get_args(option)[1]
        if origin is list:
            return typing.get_args(option)[0]
        if origin in (Annotated, typing.Union, types.UnionType):
            options.extend(typing.get_args(option)[:1] if origin is Annotated else
                           typing.get_args(option))  # fmt: skip
    return None


def _known_keys(location: tuple[Any, ...]) -> list[str]:
    """The keys the schema allows at `location` (a key path of a mapping), or []."""
    node: Any = Rig
    for part in location:
        if "[" in str(part):
            continue  # a union-branch tag, not a key
        node = _step(node, part)
        if node is None:
            return []
    model = _model_in(node)
    return [name for name in model.model_fields if name != "source"] if model else []


def _did_you_mean(error: dict[str, Any]) -> str | None:
    """For an unknown key: the known key it most likely misspells, or None."""
    *parent, key = error["loc"]
    close = difflib.get_close_matches(str(key), _known_keys(tuple(parent)), n=1, cutoff=0.6)
    return close[0] if close else None


def _describe(error: dict[str, Any]) -> str:
    kind = error["type"]
    ctx = error.get("ctx", {})
    if kind == "missing":
        return "is missing; add it"
    if kind == "extra_forbidden":
        value = error["input"]
        shown = "" if isinstance(value, dict | list) else f" (value {value!r})"
        guess = _did_you_mean(error)
        if guess:
            return f"is not a known key{shown}; did you mean {guess!r}? rename it"
        return f"is not a known key{shown}; remove it or check its spelling"
    if kind == "literal_error":
        return f"is {error['input']!r}; expected {ctx.get('expected')}"
    if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        bounds = {"greater_than": ">", "greater_than_equal": "≥", "less_than": "<",
                  "less_than_equal": "≤"}  # fmt: skip
        limit = next(iter(ctx.values()), "?")
        return f"is {error['input']!r}; expected a number {bounds[kind]} {limit}"
    if kind == "value_error":
        message = str(ctx.get("error", error["msg"]))
        if not error["loc"] or isinstance(error["input"], dict | list):
            return message  # a whole section failed a check: do not dump the section
        return f"is {error['input']!r}; expected {message}"
    message = error["msg"].removeprefix("Input should be ").removeprefix("Value error, ")
    return f"is {error['input']!r}; expected {message}"


def _session_problem(data: dict[str, Any], source: str) -> str:
    """A message when `data` is a capture session's session.yaml rather than a rig, or ""."""
    if data.get("kind") != "labkit-session" and not isinstance(data.get("rig"), dict):
        return ""
    captured = data.get("rig_source")
    origin = f" ({captured!r}, the rig_source it records)" if captured else ""
    return (
        f"{source} is a capture session file, not a rig; the rig is under its "
        f"`rig:` key — give the rig YAML the session was captured with{origin}, or save "
        "that `rig:` section as a rig file of its own"
    )


def _merged(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = _merged(merged[key], value)
        else:
            merged[key] = value
    return merged


def rig_from_dict(data: Any, *, source: str = "<rig>") -> Rig:
    """Validate a parsed rig mapping; errors name `source`."""
    if data is None:
        raise ConfigError(
            f"{source}: the rig is empty; give a rig YAML mapping (see rigs/ for examples)"
        )
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: a rig file must be a YAML mapping, got {type(data).__name__}")
    session = _session_problem(data, source)
    if session:
        raise ConfigError(session)
    try:
        rig = Rig.model_validate({**data, "source": source})
    except ValidationError as error:
        problems = error.errors()
        # an unknown key first: a misspelt key is the cause of the "missing" one it hides
        unknown = [problem for problem in problems if problem["type"] == "extra_forbidden"]
        first = unknown[0] if unknown else problems[0]
        where = {_union_root(problem["loc"]) for problem in problems}  # union branches repeat
        guess = _did_you_mean(first) if unknown else None
        if guess:  # the misspelt key also shows up as its missing twin: one problem
            where.discard(_key_path((*first["loc"][:-1], guess)))
        more = f" (and {len(where) - 1} more problem(s))" if len(where) > 1 else ""
        text = _describe(first)
        if not first["loc"]:
            raise ConfigError(f"{source}: {text}{more}") from None
        joiner = " " if text.startswith("is ") else ": "
        raise ConfigError(f"{source}: {_key_path(first['loc'])}{joiner}{text}{more}") from None
    return rig


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig YAML file.

    Raises
    ------
    ConfigError
        One message naming the file, the key path, the bad value and what is expected.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"rig file {path} does not exist; see rigs/ for examples") from None
    except OSError as error:
        raise ConfigError(f"rig file {path} cannot be read: {error.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(
            f"rig file {path} is not UTF-8 text (is it a binary file?); give a YAML rig file"
        ) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(error, "problem", None) or "invalid YAML"
        raise ConfigError(f"{path}:{where}: {problem}; fix the YAML syntax") from None
    if data is None:
        what = "is empty" if not text.strip() else "holds no YAML data (only comments)"
        raise ConfigError(f"rig file {path} {what}; give a rig YAML file, see rigs/ for examples")
    rig = rig_from_dict(data, source=str(path))
    _check_response_file(rig, path)
    return rig


def _check_response_file(rig: Rig, path: Path) -> None:
    """A response given as a file must exist; a relative path must stay in the rig's folder."""
    file = rig.response_file()
    if file is None:
        return  # a dataset name: checked by `labkit rig check` and where it is used
    value = rig.camera.response
    given = Path(value)
    folder = path.resolve().parent
    resolved = file.resolve()
    if not given.is_absolute() and not resolved.is_relative_to(folder):
        raise ConfigError(
            f"{path}: camera.response {value!r} leads outside the rig file's folder "
            f"({folder}); put the file beside the rig file, or give its absolute path"
        )
    if not resolved.is_file():
        raise ConfigError(
            f"{path}: camera.response {value!r} does not exist (looked for {resolved}); give "
            "a response CSV or `labkit calibrate sensitivity` file, relative to the rig file"
        )


def default_rig_path() -> Path:
    """The packaged simulated rig (a copy of ``rigs/simulated.yaml``)."""
    from importlib import resources

    return Path(str(resources.files("labkit") / "rigs" / "simulated.yaml"))


__all__ = ["RIG_FORMAT", "SCENE_OPTIONS", "Rig", "default_rig_path", "load_rig", "rig_from_dict"]
