"""Real captures of a ColorChecker carried up to reconstruction, and what scores a
reconstruction of them: the inputs of ``labkit demo --real`` and of the real rows of
``labkit bench``.

:func:`prepare_real_inputs` imports a folder of filtered frames and darks (laid out like
:func:`labkit.data.real_colorchecker`) under the lab's rig, merges the brackets, measures the
sensor map, synthesises the multispectral and raw images from the filtered images (the lab
has no raw image of the chart whose truth is known) and calibrates the dispersion from the
same images. The :class:`RealInputs` it returns give the options of a reconstruction and a
:class:`~reconstruction.evaluate.chart_scores.ChartScorer` of it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from labkit.demo_steps import DispersionModels, Stages, save_models
from labkit.errors import DataError
from labkit.io import spectral_preview, write_png

if TYPE_CHECKING:
    from calibration.multispectral import Synthesis
    from calibration.sensitivity import ChannelSensitivity
    from labkit.spectra import Spectra
    from reconstruction.evaluate.chart_scores import ChartScorer

REFERENCE_BAND = "600"
"""Filter whose geometry the spectral dispersion model maps every band onto."""


def real_rig_path() -> Path:
    """The packaged rig of the thesis' lab (``rigs/example-flea3.yaml``)."""
    from importlib import resources

    return Path(str(resources.files("labkit") / "rigs" / "example-flea3.yaml"))


@dataclass(frozen=True)
class ImportSummary:
    """What the import of the frames found.

    Attributes
    ----------
    frames, dark_frames : int
        Filtered frames and dark frames imported.
    source_dtype : str or None
        The files' sample type (``uint16``, say).
    sample_bits : int or None
        Significant bits per sample.
    saturation_dn, black_level : float or None
        The sensor's levels, DN.
    levels_from : str or None
        Where the levels came from (the rig, the files' metadata, …).
    """

    frames: int
    dark_frames: int
    source_dtype: str | None
    sample_bits: int | None
    saturation_dn: float | None
    black_level: float | None
    levels_from: str | None

    def as_dict(self) -> dict[str, Any]:
        """The fields as a JSON-ready dictionary."""
        return asdict(self)


@dataclass(frozen=True)
class BracketFactors:
    """One filter's HDR merge: the exposures and their scaling factors (Table 4.1).

    Attributes
    ----------
    exposures_s : list of float
        Exposure times of the bracket, s.
    nominal, fitted : list of float
        Each exposure's factor t_ref/t from the exposure times, and as fitted from the data.
    largest_difference : float
        The fitted factor's largest relative difference from the nominal one.
    warnings : list of str
        The merge's warnings.
    preview : str or None
        The HDR preview, relative to the output folder.
    """

    exposures_s: list[float]
    nominal: list[float]
    fitted: list[float]
    largest_difference: float
    warnings: list[str]
    preview: str | None

    def as_dict(self) -> dict[str, Any]:
        """The fields as a JSON-ready dictionary."""
        return asdict(self)


@dataclass
class SensorMap:
    """The camera's R/G and B/G per band, measured from the filtered images.

    Attributes
    ----------
    sensitivity : calibration.ChannelSensitivity
        The measured ratios and Green levels.
    response : Spectra
        Its :meth:`~calibration.ChannelSensitivity.as_response`: the camera response of
        the reconstruction.
    summary : dict
        Per band, the ratios against the rig's stand-in response (for the report).
    """

    sensitivity: ChannelSensitivity
    response: Spectra
    summary: dict[str, Any]


@dataclass
class RealInputs:
    """Real captures carried up to reconstruction (stages 1–5 of ``labkit demo --real``),
    and what scores a reconstruction of them (:attr:`scorer`).

    Attributes
    ----------
    data, rig : Path
        The capture folder and the rig YAML.
    scene : str
        The chart's scene name.
    inputs : dict of str to Path
        ``frames``, ``darks`` and ``labels`` (``labels.png``).
    imported : ImportSummary
        What the import found.
    hdr : dict of str to BracketFactors
        The HDR merge of each filter (by filter name): Table 4.1.
    sensor : SensorMap
    synthesis : calibration.multispectral.Synthesis
        The multispectral and synthetic raw images (Algorithm 13).
    models : DispersionModels
    labels : ndarray (rows, cols) int
        Patch labels 1–24 (0: background).
    """

    data: Path
    rig: Path
    scene: str
    inputs: dict[str, Path]
    imported: ImportSummary
    hdr: dict[str, BracketFactors]
    sensor: SensorMap
    synthesis: Synthesis
    models: DispersionModels
    labels: np.ndarray

    def reconstruct_options(self) -> dict[str, Any]:
        """The inputs of :func:`reconstruction.reconstruct` for the synthetic raw image:
        ``cfa``, ``response`` (the sensor map), ``bands`` (its band centres, nm) and
        ``dispersion`` (the spectral model)."""
        response = self.sensor.response
        return {
            "cfa": self.synthesis.raw.cfa,
            "response": response,
            "bands": [float(w) for w in response.wavelengths],
            "dispersion": self.models.spectral,
        }

    @cached_property
    def reference_truth(self) -> np.ndarray:
        """The multispectral image (rows, cols, bands) warped onto the spectral dispersion
        model's reference geometry, where a reconstruction's bands lie: the per-pixel
        spectral truth of the synthetic raw image (bilinear resampling; each band with the
        dispersion of its filter's light, the model clamped to its domain, as the
        reconstruction does)."""
        from calibration.warp import correct_spectral
        from reconstruction.options import filter_light

        cube = self.synthesis.multispectral
        model = self.models.spectral.within_domain()
        # each band's light, where the reconstruction evaluates its dispersion too
        light = filter_light(cube.wavelengths_nm, model)
        waves = cube.wavelengths_nm if light is None else light
        return correct_spectral(np.asarray(cube.cube, dtype=np.float64), waves, model)

    @cached_property
    def scorer(self) -> ChartScorer:
        """What scores reconstructions of the synthetic raw image: the chart's labels, the
        ASD spectrometer's reflectances of its patches, and :attr:`reference_truth` (made
        when a per-pixel error first needs it)."""
        from labkit.spectra import colorchecker_reflectances
        from reconstruction.evaluate.chart_scores import ChartScorer

        raw = self.synthesis.raw
        return ChartScorer(
            self.labels,
            raw.raw,
            raw.cfa,
            colorchecker_reflectances("measured"),
            truth=lambda: self.reference_truth,
            truth_wavelengths_nm=self.synthesis.multispectral.wavelengths_nm,
        )


def prepare_real_inputs(
    out: str | Path,
    *,
    data: str | Path | None = None,
    rig_path: str | Path | None = None,
    patterns: Sequence[str] | None = None,
    stage: Stages | None = None,
) -> RealInputs:
    """Import, merge, map, synthesise and calibrate real captures into `out` (stages 1–5).

    Parameters are those of :func:`run_real_demo`; `stage` times each step (default: a
    timer without a progress bar).

    Raises
    ------
    DataError
        A folder or file is missing, or a stage cannot trust its input.
    """
    from labkit.data import real_colorchecker
    from labkit.io.plane import read_labels
    from labkit.rig import load_rig

    out = Path(out)
    data = Path(data) if data is not None else real_colorchecker()
    inputs = _inputs(data)
    rig_file = Path(rig_path) if rig_path else real_rig_path()
    rig = load_rig(rig_file)
    out.mkdir(parents=True, exist_ok=True)
    stage = stage if stage is not None else Stages(5, "real inputs", disable=True)
    imported = stage("import", lambda: _import(inputs, rig, out, patterns))
    hdr = stage("hdr", lambda: _hdr(out))
    scene, images = _filtered(out)
    sensor = stage("sensor map", lambda: _sensor_map(images, rig, out))
    synthesis = stage("synthesize", lambda: _synthesize(images, sensor, scene, out))
    models = stage("calibrate", lambda: _calibrate(images, synthesis, rig, out))
    labels = read_labels(inputs["labels"], synthesis.raw.raw.shape, what="label image")
    return RealInputs(
        data, rig_file, scene, inputs, imported, hdr, sensor, synthesis, models, labels
    )


def _inputs(data: Path) -> dict[str, Path]:
    inputs = {"frames": data / "frames", "darks": data / "darks", "labels": data / "labels.png"}
    missing = [str(path) for path in inputs.values() if not path.exists()]
    if missing:
        raise DataError(
            f"{data} is not a real-capture folder: missing {', '.join(missing)}; it needs "
            "frames/ (filtered frames), darks/ and labels.png (patch labels 1–24) named like "
            "the vendored set (labkit.data.real_colorchecker())"
        )
    return inputs


def _import(inputs: dict[str, Path], rig, out: Path, patterns) -> ImportSummary:
    import shutil

    from labkit.data import REAL_COLORCHECKER_PATTERNS
    from labkit.session.importer import import_session

    folder = out / "session"
    if folder.exists():
        shutil.rmtree(folder)
    session, _ = import_session(
        folder,
        [inputs["frames"], inputs["darks"]],
        list(patterns or REAL_COLORCHECKER_PATTERNS),
        rig,
    )
    records = list(session.records.values())
    first = records[0]
    return ImportSummary(
        frames=sum(not r["dark"] for r in records),
        dark_frames=sum(bool(r["dark"]) for r in records),
        source_dtype=first.get("source_dtype"),
        sample_bits=first.get("sample_bits"),
        saturation_dn=first.get("saturation_dn"),
        black_level=first.get("black_level"),
        levels_from=first.get("levels_from"),
    )


def _hdr(out: Path) -> dict[str, BracketFactors]:
    from labkit.hdr import run_hdr

    run = run_hdr(out / "session", out / "hdr", previews=True)
    rows: dict[str, BracketFactors] = {}
    for output in run.outputs:
        result = output.result
        rows[output.job.illumination] = BracketFactors(
            exposures_s=[e.exposure_s for e in result.exposures],
            nominal=[e.nominal for e in result.exposures],
            fitted=[e.factor for e in result.exposures],
            largest_difference=max(
                (e.disagreement for e in result.exposures), key=abs, default=0.0
            ),
            warnings=list(result.warnings),
            preview=str(output.preview.relative_to(out)) if output.preview else None,
        )
    return rows


def _filtered(out: Path) -> tuple[str, list]:
    from calibration import load_filtered_hdr

    scenes = load_filtered_hdr(out / "hdr")
    if len(scenes) != 1:
        raise DataError(
            f"{out / 'hdr'}: expected the filtered images of one chart, found scenes "
            f"{sorted(scenes)}"
        )
    scene, images = next(iter(scenes.items()))
    return scene, images


def _sensor_map(images: list, rig, out: Path) -> SensorMap:
    from calibration import channel_sensitivity, nominal_channel_sensitivity
    from calibration.sensitivity import plot_channel_sensitivity

    measured = channel_sensitivity(images)
    nominal = nominal_channel_sensitivity(rig)
    folder = out / "sensor_map"
    folder.mkdir(parents=True, exist_ok=True)
    measured.to_yaml(folder / "sensitivity.yaml")
    measured.to_csv(folder / "sensitivity.csv")
    plot_channel_sensitivity(measured, nominal, folder / "sensitivity.png")
    rows = []
    for i, wavelength in enumerate(measured.wavelengths_nm):
        entry = nominal.index_of(wavelength)
        rows.append(
            {
                "wavelength_nm": float(wavelength),
                "r_over_g": float(measured.r_over_g[i]),
                "b_over_g": float(measured.b_over_g[i]),
                "nominal_r_over_g": None if entry is None else float(nominal.r_over_g[entry]),
                "nominal_b_over_g": None if entry is None else float(nominal.b_over_g[entry]),
                "green_level": float(measured.relative_green_level[i]),
                "reliable": bool(measured.reliable[i]),
            }
        )
    return SensorMap(
        measured, measured.as_response(), {"bands": rows, "stand_in": rig.camera.response}
    )


def _synthesize(images: list, sensor: SensorMap, scene: str, out: Path) -> Synthesis:
    from calibration import synthesize_multispectral, write_synthesis

    synthesis = synthesize_multispectral(images, sensor.sensitivity)
    write_synthesis(synthesis, out / "synthesis", scene)
    cube = synthesis.multispectral
    write_png(
        out / "synthesis" / f"{scene}-multispectral.png",
        spectral_preview(cube.cube, cube.wavelengths_nm).image,
    )
    return synthesis


def calibrate_spectral(
    images: list,
    rig: Any,
    *,
    min_purity: float | None = None,
    bands: Any = None,
    rng: np.random.Generator | None = None,
) -> Any:
    """The demo's spectral calibration (``to_reference``, registration keypoints, reference
    :data:`REFERENCE_BAND`, the filters' bands measured on the `images`) of the filtered
    HDR `images` of one chart; `min_purity` as :func:`calibration.calibrate_dispersion`'s
    (by default its own: the 400 nm filter, whose light leaks, is left out; 0 keeps it);
    `bands` are :func:`calibration.bands.filter_bands` of the rig and images (computed when
    not given); `rng` draws the cross-validation folds (default: seeded 2019).
    Returns the :class:`~calibration.dispersion_calibration.DispersionCalibration`."""
    from calibration.bands import filter_bands
    from calibration.dispersion_calibration import MIN_PURITY, calibrate_dispersion

    return calibrate_dispersion(
        images,
        reference=REFERENCE_BAND,
        keypoints="registration",
        direction="to_reference",
        bands=bands if bands is not None else filter_bands(rig, images=images),
        rng=rng if rng is not None else np.random.default_rng(2019),
        workers=2,
        min_purity=MIN_PURITY if min_purity is None else min_purity,
    )


def _calibrate(images: list, synthesis: Synthesis, rig, out: Path) -> DispersionModels:
    from calibration.bands import filter_bands
    from calibration.dispersion_calibration import calibrate_dispersion

    bands = filter_bands(rig, images=images)
    rng = np.random.default_rng(2019)
    spectral = calibrate_spectral(images, rig, bands=bands, rng=rng)
    colour = calibrate_dispersion([synthesis.raw], reference="G", keypoints="registration", rng=rng)
    summary = save_models(spectral, colour, out / "calibration")
    summary["bands"] = [
        {
            "filter": band.illumination,
            "wavelength_nm": band.wavelength_nm,
            "purity": band.purity,
            "used": band.used,
            "why": band.reason or _explain(bands, band.illumination),
        }
        for band in spectral.bands
    ]
    return DispersionModels(spectral.model, colour.model, summary)


def _explain(bands: dict, illumination: str) -> str:
    return bands[illumination].explain() if illumination in bands else ""
