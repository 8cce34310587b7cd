"""`labkit demo --real`: the main job on real frames from the thesis' lab, end to end.

The input is a folder of real captures laid out like :func:`labkit.data.real_colorchecker`
(``frames/`` of one chart under bandpass filters at several exposures, ``darks/``, and
``labels.png`` naming the 24 ColorChecker patches); by default the vendored one.

1. **Import** the frames and darks into a session under the Flea3 example rig: bit depth,
   saturation and black level are read from the files (8-bit here).
2. **HDR**: merge each filter's bracket (thesis Algorithm 11); Table 4.1 per filter.
3. **Sensor map**: the R/G and B/G ratios of every band measured from the filtered
   images (Algorithm 12), compared with the rig's stand-in response.
4. **Multispectral and synthetic raw images** from the filtered images (Algorithm 13),
   as in thesis §4.2.4: the lab has no raw image of this chart whose truth is known, so
   the reconstruction input is synthesised from the filtered frames.
5. **Dispersion calibration** from the filtered images themselves (registration
   keypoints; bands kept or dropped from the evidence in the images): a spectral
   ``to_reference`` model for the reconstruction and a colour-channel model of the
   synthetic raw image for the warping baselines.
6. **Reconstruct** the synthetic raw image with the sensor map as the camera response:
   default options and the §6.3 variant (mean-colour reference, no spectral smoothness).
7. **Evaluate**: patch-centre spectra against the ASD spectrometer's reflectances of the
   same chart (thesis Table 5.7) for the multispectral image and each reconstruction;
   residual chromatic aberration on the chart (§4.4.3) against bilinear, Malvar and Menon
   demosaicing, with and without channel warping.
8. **Report**: ``report.html``, ``report.md`` and ``results.json``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from labkit.demo import (
    Stages,
    method_figures,
    reconstruct_and_save,
    reconstruction_notes,
    save_models,
    stage_table,
)
from labkit.errors import DataError
from labkit.io import spectral_preview, write_png, write_text_atomic
from labkit.io.tiff import json_default
from labkit.plots import plot_patch_spectra
from labkit.report import Report
from labkit.spectra.datasets import COLORCHECKER_PATCHES

if TYPE_CHECKING:
    from calibration.multispectral import Synthesis

REFERENCE_BAND = "600"
"""Filter whose geometry the spectral dispersion model maps every band onto."""
VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "defaults": ("defaults", {}),
    "§6.3 mean-colour, σ = 0": (
        "mean_colour_sigma0",
        {"reference": "mean-colour", "spectral_smoothness": 0.0},
    ),
}
"""Reconstructions of the synthetic raw image: name → (folder, options of
:func:`reconstruction.reconstruct`)."""
CENTRE_FRACTION = 0.5
"""Patch centre: the pixels at least this fraction of the patch's largest distance to its
edge away from the edge (the inner half, by the distance transform of each label)."""
SPECTRA_PATCHES = (0, 2, 6, 11, 14, 18)
"""ColorChecker patches whose spectra are plotted (chart order)."""


def real_rig_path() -> Path:
    """The packaged rig of the thesis' lab (``rigs/example-flea3.yaml``)."""
    from importlib import resources

    return Path(str(resources.files("labkit") / "rigs" / "example-flea3.yaml"))


def run_real_demo(
    out: str | Path,
    *,
    data: str | Path | None = None,
    rig_path: str | Path | None = None,
    patterns: Sequence[str] | None = None,
    progress: bool | None = None,
) -> Path:
    """Run the whole job on real captures into `out`; return the path of ``report.html``.

    Parameters
    ----------
    out : str or Path
        Output folder (created; existing demo outputs in it are replaced).
    data : str or Path, optional
        Folder with ``frames/``, ``darks/`` and ``labels.png`` named as the vendored set
        (:data:`labkit.data.REAL_COLORCHECKER_PATTERNS`); default
        :func:`labkit.data.real_colorchecker`.
    rig_path : str or Path, optional
        Rig YAML of the lab (default: :func:`real_rig_path`).
    patterns : sequence of str, optional
        File-name patterns of the frames and darks (``labkit session import --pattern``;
        default :data:`labkit.data.REAL_COLORCHECKER_PATTERNS`).
    progress : bool, optional
        Progress bars; default: only on a terminal.

    Raises
    ------
    DataError
        A folder or file is missing, or a stage cannot trust its input.
    """
    out = Path(out)
    disable = None if progress is None else not progress
    stage = Stages(7, "demo --real", disable=disable)
    real = prepare_real_inputs(out, data=data, rig_path=rig_path, patterns=patterns, stage=stage)
    hdr, sensor, models = real.hdr, real.sensor, real.models
    recons = stage("reconstruct", lambda: _reconstruct(real, out, disable))
    evaluation = stage("evaluate", lambda: _evaluate(real, recons, out))
    stage.close()
    results = {
        "data": str(real.data),
        "rig": str(real.rig),
        "scene": real.scene,
        "seconds": stage.seconds,
        "import": real.session,
        "hdr": hdr["summary"],
        "sensor_map": sensor["summary"],
        "calibration": models["summary"],
        "reconstruction": {name: r["summary"] for name, r in recons.items()},
        "evaluation": evaluation["summary"],
    }
    report = Report("labkit demo --real — the thesis' ColorChecker, real frames")
    _write_report(report, results, hdr, sensor, models, recons, evaluation)
    write_text_atomic(
        out / "results.json", json.dumps(results, indent=1, default=json_default) + "\n"
    )
    _, page = report.write(out)
    return page


@dataclass
class RealInputs:
    """Real captures carried up to reconstruction (the demo's stages 1–5), and what scores
    a reconstruction of them.

    Attributes
    ----------
    data, rig : Path
        The capture folder and the rig YAML.
    scene : str
        The chart's scene name.
    inputs : dict of str to Path
        ``frames``, ``darks`` and ``labels`` (``labels.png``).
    session, hdr : dict
        Import and HDR summaries (``hdr["summary"]``: Table 4.1 per filter).
    sensor : dict
        ``sensitivity`` (:class:`calibration.ChannelSensitivity`), ``response`` (its
        :meth:`~calibration.ChannelSensitivity.as_response`) and ``summary``.
    synthesis : calibration.multispectral.Synthesis
        The multispectral and synthetic raw images (Algorithm 13).
    models : dict
        ``spectral`` (``to_reference``) and ``colour`` dispersion models, and ``summary``.
    labels : ndarray (rows, cols) int
        Patch labels 1–24 (0: background).
    """

    data: Path
    rig: Path
    scene: str
    inputs: dict[str, Path]
    session: dict[str, Any]
    hdr: dict[str, Any]
    sensor: dict[str, Any]
    synthesis: Synthesis
    models: dict[str, Any]
    labels: np.ndarray

    def reconstruct_options(self) -> dict[str, Any]:
        """The inputs of :func:`reconstruction.reconstruct` for the synthetic raw image:
        ``cfa``, ``response`` (the sensor map), ``bands`` (its band centres, nm) and
        ``dispersion`` (the spectral model)."""
        response = self.sensor["response"]
        return {
            "cfa": self.synthesis.raw.cfa,
            "response": response,
            "bands": [float(w) for w in response.wavelengths],
            "dispersion": self.models["spectral"],
        }

    @cached_property
    def centres(self) -> list[np.ndarray]:
        """Masks of the 24 patch centres (:func:`patch_centres` of :attr:`labels`)."""
        return patch_centres(self.labels)

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
        model = self.models["spectral"].within_domain()
        # each band's light, where the reconstruction evaluates its dispersion too
        light = filter_light(cube.wavelengths_nm, model)
        waves = cube.wavelengths_nm if light is None else light
        return correct_spectral(np.asarray(cube.cube, dtype=np.float64), waves, model)

    def pixel_errors(self, result: Any) -> dict[str, float]:
        """A reconstruction's spectral RMSE per pixel against :attr:`reference_truth`: over
        the chart (its patches and the strip width around them, the 8-px border left out)
        and in the patches' edge strips, centres and surround
        (:func:`reconstruction.spectral_strip_errors`; relative to the chart's mean truth).

        Returns
        -------
        dict
            ``chart``, ``strips``, ``centres``, ``surround``.

        Raises
        ------
        DataError
            The reconstruction's bands are not the multispectral image's.
        """
        from reconstruction import patch_regions, spectral_strip_errors

        bands = np.asarray(self.synthesis.multispectral.wavelengths_nm, dtype=float)
        wanted = np.asarray(result.wavelengths_nm, dtype=float)
        index = np.abs(bands[None, :] - wanted[:, None]).argmin(axis=1)
        if not np.allclose(bands[index], wanted, atol=1.0):
            raise DataError(
                f"the reconstruction's bands {wanted.tolist()} nm are not among the "
                f"multispectral image's {bands.tolist()} nm; reconstruct at its bands"
            )
        # the chart: its patches and their surround (the rest of the frame holds the lab,
        # whose multispectral truth is dark and noisy)
        regions = patch_regions(self.labels.shape, labels=self.labels)
        keep = (regions.labels > 0) | regions.surround
        keep[:8] = keep[-8:] = keep[:, :8] = keep[:, -8:] = False
        split = spectral_strip_errors(
            self.reference_truth[..., index], result.spectral, labels=self.labels, mask=keep
        )
        return {
            "chart": split.whole,
            "strips": split.strips,
            "centres": split.centres,
            "surround": split.surround,
        }

    def edge_rmse(self, images: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
        """Edge-strip RMSE per channel (§4.4.3, fractions of the raw mean, as ``labkit
        evaluate`` reports them) of each raw colour image of the chart, by name:
        {name: {"R": …, "G": …, "B": …}}."""
        from reconstruction import evaluate

        raw = self.synthesis.raw
        methods = evaluate(raw.raw, images, cfa=raw.cfa, labels=self.labels).as_dict()["methods"]
        return {
            name: {c: float(methods[name]["residual_aberration"]["edge"]["rmse"][c]) for c in "RGB"}
            for name in images
        }

    def score(self, result: Any) -> dict[str, float]:
        """A reconstruction's patch-centre MRAE and RMSE against the chart's ASD reflectances
        (:func:`patch_spectral_errors`), edge-strip RMSE R/G/B of its raw colour image
        (§4.4.3, fractions of the raw mean, as ``labkit evaluate`` reports them), and its
        per-pixel spectral RMSE (:meth:`pixel_errors`: ``spectral_rmse`` over the chart,
        ``spectral_rmse_strips``, ``…_centres``, ``…_surround``).
        """
        from labkit.spectra import colorchecker_reflectances

        patch = patch_spectral_errors(
            result.spectral,
            result.wavelengths_nm,
            self.centres,
            colorchecker_reflectances("measured"),
        )
        edge = self.edge_rmse({"x": result.raw_colour})["x"]
        pixels = self.pixel_errors(result)
        return {
            "mrae": patch["mrae"],
            "rmse": patch["rmse"],
            **{f"edge_rmse_{c}": edge[c] for c in "RGB"},
            "spectral_rmse": pixels["chart"],
            **{f"spectral_rmse_{k}": pixels[k] for k in ("strips", "centres", "surround")},
        }


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
    session = stage("import", lambda: _import(inputs, rig, out, patterns))
    hdr = stage("hdr", lambda: _hdr(out))
    scene, images = _filtered(out)
    sensor = stage("sensor map", lambda: _sensor_map(images, rig, out))
    synthesis = stage("synthesize", lambda: _synthesize(images, sensor, scene, out))
    models = stage("calibrate", lambda: _calibrate(images, synthesis, rig, out))
    labels = read_labels(inputs["labels"], synthesis.raw.raw.shape, what="label image")
    return RealInputs(
        data, rig_file, scene, inputs, session, hdr, sensor, synthesis, models, labels
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


def _import(inputs: dict[str, Path], rig, out: Path, patterns) -> dict[str, Any]:
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
    return {
        "frames": sum(not r["dark"] for r in records),
        "dark_frames": sum(bool(r["dark"]) for r in records),
        "source_dtype": first.get("source_dtype"),
        "sample_bits": first.get("sample_bits"),
        "saturation_dn": first.get("saturation_dn"),
        "black_level": first.get("black_level"),
        "levels_from": first.get("levels_from"),
    }


def _hdr(out: Path) -> dict[str, Any]:
    from labkit.hdr import run_hdr

    run = run_hdr(out / "session", out / "hdr", previews=True)
    rows = {}
    for output in run.outputs:
        result = output.result
        rows[output.job.illumination] = {
            "exposures_s": [e.exposure_s for e in result.exposures],
            "nominal": [e.nominal for e in result.exposures],
            "fitted": [e.factor for e in result.exposures],
            "largest_difference": max(
                (e.disagreement for e in result.exposures), key=abs, default=0.0
            ),
            "warnings": list(result.warnings),
            "preview": str(output.preview.relative_to(out)) if output.preview else None,
        }
    return {"summary": rows}


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


def _sensor_map(images: list, rig, out: Path) -> dict[str, Any]:
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
    return {
        "sensitivity": measured,
        "response": measured.as_response(),
        "summary": {"bands": rows, "stand_in": rig.camera.response},
    }


def _synthesize(images: list, sensor: dict[str, Any], scene: str, out: Path) -> Synthesis:
    from calibration import synthesize_multispectral, write_synthesis

    synthesis = synthesize_multispectral(images, sensor["sensitivity"])
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


def _calibrate(images: list, synthesis: Synthesis, rig, out: Path) -> dict[str, Any]:
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
    return {"spectral": spectral.model, "colour": colour.model, "summary": summary}


def _reconstruct(real: RealInputs, out: Path, disable: bool | None) -> dict[str, Any]:
    results = {}
    for name, (slug, options) in VARIANTS.items():
        folder = out / "reconstruction" / slug
        result, summary = reconstruct_and_save(
            real.synthesis.raw.raw,
            folder,
            name=f"({name})",
            command="labkit demo --real",
            disable_progress=disable,
            **real.reconstruct_options(),
            **options,
        )
        summary["options"] = options
        results[name] = {"result": result, "folder": folder, "summary": summary}
    return results


def patch_centres(labels: np.ndarray, *, fraction: float = CENTRE_FRACTION) -> list[np.ndarray]:
    """Boolean masks of the centres of patches 1…24 of a label image.

    A patch's centre is the set of its pixels whose distance to the patch's edge is at
    least ``1 − fraction`` of the largest such distance (``fraction = 0.5``: the inner half).

    Raises
    ------
    DataError
        A patch label 1…24 is missing.
    """
    from scipy import ndimage

    masks = []
    missing = []
    for label in range(1, 25):
        patch = labels == label
        if not patch.any():
            missing.append(label)
            continue
        distance = ndimage.distance_transform_edt(patch)
        masks.append(distance >= (1.0 - fraction) * distance.max())
    if missing:
        raise DataError(
            f"the label image has no pixels for patch(es) {missing}; it needs labels 1–24 "
            "(ColorChecker order, row by row from the top left) and 0 for the background"
        )
    return masks


def patch_spectral_errors(
    cube: np.ndarray,
    wavelengths_nm: Sequence[float],
    centres: list[np.ndarray],
    reflectances,
) -> dict[str, Any]:
    """Patch-centre spectra of `cube` against measured reflectances (thesis Table 5.7).

    Each patch's mean spectrum over its centre is compared with its reflectance sampled at
    the cube's band wavelengths, after scaling each band by least squares over the 24
    patches (eq. 4.9: the cube's units are not reflectance).

    Returns
    -------
    dict
        ``"mrae"``, ``"rmse"`` (means over the patches), ``"per_patch_mrae"`` (24,),
        ``"estimate"`` (24, bands) in reflectance units after the registration, and
        ``"truth"`` (24, bands).
    """
    from reconstruction.metrics import spectral_errors

    wavelengths = np.asarray(wavelengths_nm, dtype=float)
    estimate = np.stack([cube[mask].mean(axis=0) for mask in centres]).astype(float)
    truth = reflectances.resample(wavelengths).values.T.astype(float)
    errors = spectral_errors(
        truth[:, None, :], estimate[:, None, :], ssim=False, register=True, floor=0.0
    )
    return {
        "mrae": float(errors.mrae),
        "rmse": float(errors.rmse_pixel),
        "per_patch_mrae": errors.mrae_map[:, 0].filled(np.nan),
        "estimate": estimate * np.asarray(errors.scale),
        "truth": truth,
    }


def _evaluate(real: RealInputs, recons: dict[str, Any], out: Path) -> dict[str, Any]:
    from labkit.spectra import colorchecker_reflectances
    from reconstruction import baseline_images, evaluate

    synthesis, models, labels = real.synthesis, real.models, real.labels
    raw = synthesis.raw
    centres = real.centres
    reflectances = colorchecker_reflectances("measured")
    multispectral = synthesis.multispectral
    patch = {
        "multispectral": patch_spectral_errors(
            multispectral.cube, multispectral.wavelengths_nm, centres, reflectances
        )
    }
    for name, r in recons.items():
        result = r["result"]
        patch[name] = patch_spectral_errors(
            result.spectral, result.wavelengths_nm, centres, reflectances
        )
    images, seconds = baseline_images(raw.raw, cfa=raw.cfa, colour_dispersion=models["colour"])
    for name, r in recons.items():
        images[f"spectral: {name}"] = r["result"].raw_colour
        seconds[f"spectral: {name}"] = r["summary"]["seconds"]
    evaluation = evaluate(raw.raw, images, cfa=raw.cfa, labels=labels, seconds=seconds)
    folder = out / "evaluation"
    figures = _figures(out, folder, labels, images, evaluation)
    figures["spectra"] = _spectra_figure(folder, out, patch, recons, multispectral, reflectances)
    summary = {
        "patch_centres": {
            name: {
                "mrae": e["mrae"],
                "rmse": e["rmse"],
                "per_patch_mrae": dict(
                    zip(COLORCHECKER_PATCHES, e["per_patch_mrae"].tolist(), strict=True)
                ),
            }
            for name, e in patch.items()
        },
        "pixels": {name: real.pixel_errors(r["result"]) for name, r in recons.items()},
        "residual_aberration": evaluation.as_dict(),
    }
    return {"summary": summary, "evaluation": evaluation, "figures": figures, "patch": patch}


def _figures(out, folder, labels, images, evaluation) -> dict[str, Any]:
    """Display images on one scale, crops at the chart's corners, the edge-error chart."""

    ys, xs = np.nonzero(labels)
    corners = [(ys.min(), xs.min()), (ys.min(), xs.max()), (ys.max(), xs.max())]
    side = max(32, min(labels.shape) // 6)
    return method_figures(out, folder, images, evaluation, corners, side, edge=True)


def _spectra_figure(folder, out, patch, recons, multispectral, reflectances) -> str:
    fine = np.arange(400.0, 701.0, 2.0)
    truth = reflectances.resample(fine).values.T[list(SPECTRA_PATCHES)]
    wavelengths = {"multispectral": multispectral.wavelengths_nm}
    wavelengths.update({name: r["result"].wavelengths_nm for name, r in recons.items()})
    estimates = {
        name: (np.asarray(w), patch[name]["estimate"][list(SPECTRA_PATCHES)])
        for name, w in wavelengths.items()
    }
    path = folder / "patch_spectra.png"
    names = [COLORCHECKER_PATCHES[i] for i in SPECTRA_PATCHES]
    plot_patch_spectra((fine, truth), estimates, names, path)
    return str(path.relative_to(out))


def _write_report(report, results, hdr, sensor, models, recons, evaluation) -> None:
    from reconstruction.residual_aberration import STRIP_PX

    times = results["seconds"]
    imported = results["import"]
    report.paragraph(
        f"Real frames of a ColorChecker from the thesis' lab (`{results['data']}`), under the "
        f"rig `{results['rig']}`: import → HDR → sensor map → multispectral and synthetic "
        "raw images (thesis §4.2.4) → dispersion calibration → reconstruction → evaluation "
        f"against the chart's ASD spectrometer reflectances. Total {sum(times.values()):.0f} s."
    )
    stage_table(report, times)
    report.heading("Import and HDR")
    report.paragraph(
        f"{imported['frames']} frames and {imported['dark_frames']} dark frames; levels "
        f"from {imported['levels_from']}: {imported['source_dtype']} files, "
        f"{imported['sample_bits']}-bit samples, saturation {imported['saturation_dn']:g} DN, "
        f"black level {imported['black_level']:g} DN. Table 4.1: the exposure factors fitted "
        "from the data (t_ref/t; a factor the data cannot fit keeps the exposure-time ratio, "
        "with a warning below)."
    )
    rows_hdr = hdr["summary"]
    exposures = sorted({t for row in rows_hdr.values() for t in row["exposures_s"]})
    header = ["filter"] + [f"{t * 1e3:g} ms" for t in exposures] + ["largest difference"]
    rows = []
    for name, row in sorted(rows_hdr.items(), key=lambda item: float(item[0])):
        fitted = dict(zip(row["exposures_s"], row["fitted"], strict=True))
        rows.append(
            [name]
            + [f"{fitted[t]:.4f}" if t in fitted else "–" for t in exposures]
            + [f"{row['largest_difference']:+.1%}"]
        )
    report.table(header, rows)
    warnings = [f"{n}: {w}" for n, row in rows_hdr.items() for w in row["warnings"]]
    if warnings:
        report.bullets(warnings)
    report.figures(
        [(row["preview"], f"{n} nm (HDR)") for n, row in rows_hdr.items() if row["preview"]],
        width_px=220,
    )
    report.heading("Sensor map")
    report.paragraph(
        "R/G and B/G of every band measured from the filtered images (thesis Algorithm 12), "
        f"against the rig's stand-in response ({sensor['summary']['stand_in']}), and each "
        "band's mean Green level relative to the brightest band's. The map is the camera "
        "response of the synthesis (ratios) and of the reconstruction (ratios × level: a "
        "discrete model, one warp per band)."
    )
    report.table(
        ["band (nm)", "R/G", "stand-in", "B/G", "stand-in", "Green level", "reliable"],
        [
            [f"{b['wavelength_nm']:.0f}", f"{b['r_over_g']:.4g}", _cell(b["nominal_r_over_g"]),
             f"{b['b_over_g']:.4g}", _cell(b["nominal_b_over_g"]), _cell(b["green_level"]),
             "yes" if b["reliable"] else "no"]
            for b in sensor["summary"]["bands"]
        ],
    )  # fmt: skip
    report.figures([("sensor_map/sensitivity.png", "measured (solid) and stand-in (dotted)")])
    scene = results["scene"]
    report.figures(
        [
            (f"synthesis/{scene}-multispectral.png", "multispectral image (sRGB)"),
            (f"synthesis/{scene}-synthetic-rgb.png", "synthetic colour image"),
        ],
        width_px=340,
    )
    calibration = results["calibration"]
    spectral = calibration["spectral"]
    report.heading("Dispersion calibration")
    report.paragraph(
        "Bands are kept or dropped from the evidence in the images (their brightness against "
        "the leakage the rig predicts); keypoints by registering each band's image onto the "
        f"{REFERENCE_BAND} nm one. Spectral model: {spectral['keypoints']} keypoints, degree "
        f"{spectral['degree_xy']} in x, y and {spectral['degree_lambda']} in λ by "
        f"cross-validation (condition number {spectral['condition_number']:.3g}). Colour "
        f"model of the synthetic raw image (R and B onto G): {calibration['colour']['keypoints']}"
        f" keypoints, degree {calibration['colour']['degree_xy']}."
    )
    report.table(
        ["filter", "wavelength (nm)", "purity", "used", "why"],
        [
            [b["filter"], _cell(b["wavelength_nm"], ".1f"), _cell(b["purity"], ".0%"),
             "yes" if b["used"] else "no", b["why"]]
            for b in calibration["bands"]
        ],
    )  # fmt: skip
    report.figures(
        [
            ("calibration/spectral_model.png", "spectral model (to the reference), per band"),
            ("calibration/colour_model.png", "colour-channel model (from G)"),
        ]
    )
    report.heading("Reconstruction")
    report.paragraph(
        "The synthetic raw image, reconstructed with the sensor map as the camera response, "
        "its bands, and the spectral dispersion model."
    )
    report.table(
        ["variant", "time (s)", "weight", "patches", "Φ used", "flat", "exact",
         "median ADMM iterations"],
        [
            [name, f"{s['seconds']:.1f}", f"{s['weights'][0]:.2g}", str(s["patches"]),
             str(s["phi_used"]), str(s["flat"]), str(s["exact"]), f"{s['median_iterations']:.0f}"]
            for name, s in results["reconstruction"].items()
        ],
    )  # fmt: skip
    reconstruction_notes(report, results["reconstruction"])
    report.figures(
        [(f"reconstruction/{r['folder'].name}/preview.png", f"{n}: sRGB")
         for n, r in recons.items()],
        width_px=340,
    )  # fmt: skip
    report.heading("Evaluation")
    report.heading("Patch-centre spectra against the ASD reflectances", 3)
    report.paragraph(
        "Mean spectrum of the inner half of each patch against the spectrometer's reflectance, "
        "each band scaled by least squares over the 24 patches (eq. 4.9). The thesis (full "
        "resolution): multispectral image MRAE 0.194, its best reconstruction 0.258 (Table 5.7)."
    )
    report.table(
        ["image", "MRAE", "RMSE"],
        [
            [name, f"{e['mrae']:.3f}", f"{e['rmse']:.4f}"]
            for name, e in results["evaluation"]["patch_centres"].items()
        ],
    )
    report.figures([(evaluation["figures"]["spectra"], "patch-centre spectra (registered)")])
    report.heading("Per-pixel spectra against the multispectral image", 3)
    report.paragraph(
        "Spectral RMSE of every pixel against the multispectral image the synthetic raw image "
        "is made from, moved into the reconstruction's geometry, each band scaled by least "
        "squares (eq. 4.9), relative to the chart's mean: over the chart, in strips inside "
        f"the patch edges ({STRIP_PX:g} px), in the patch centres, and in the frame just "
        "outside the patches."
    )
    report.table(
        ["reconstruction", "chart", "edge strips", "centres", "frame"],
        [
            [name, *(f"{e[k]:.4f}" for k in ("chart", "strips", "centres", "surround"))]
            for name, e in results["evaluation"]["pixels"].items()
        ],
    )
    report.heading("Residual chromatic aberration", 3)
    report.paragraph(
        "Edge/centre RMSE: residual chromatic aberration in strips inside the patch edges and "
        "in the patch centres, against an ideal image synthesised from the raw patch centres "
        "(§4.4.3); fractions of the raw image's mean."
    )
    header, rows = evaluation["evaluation"].table()
    report.table(header, rows)
    report.figures([(evaluation["figures"]["edge"], "edge-strip RMSE per channel")])
    report.heading("Images (one display scale for all)", 4)
    report.figures(evaluation["figures"]["previews"], width_px=300)
    report.figures([(evaluation["figures"]["crops"], "crops at the chart's corners")])


def _explain(bands: dict, illumination: str) -> str:
    return bands[illumination].explain() if illumination in bands else ""


def _cell(value: float | None, spec: str = ".4g") -> str:
    return "–" if value is None or not np.isfinite(value) else format(value, spec)
