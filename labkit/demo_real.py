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
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from labkit.demo_steps import (
    SavedReconstruction,
    Stages,
    method_figures,
    reconstruct_and_save,
    reconstruction_notes,
    stage_table,
)
from labkit.io import write_text_atomic
from labkit.io.tiff import json_default
from labkit.plots import plot_patch_spectra
from labkit.real_chart import REFERENCE_BAND, RealInputs, prepare_real_inputs
from labkit.report import Report
from labkit.spectra.datasets import COLORCHECKER_PATCHES

if TYPE_CHECKING:
    from reconstruction import Evaluation

VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "defaults": ("defaults", {}),
    "reference spectrum from the mean colour, σ = 0": (
        "mean_colour_sigma0",
        {"reference": "mean-colour", "spectral_smoothness": 0.0},
    ),
}
"""Reconstructions of the synthetic raw image: name → (folder, options of
:func:`reconstruction.reconstruct`)."""
SPECTRA_PATCHES = (0, 2, 6, 11, 14, 18)
"""ColorChecker patches whose spectra are plotted (chart order)."""


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
        "import": real.imported.as_dict(),
        "hdr": {name: merge.as_dict() for name, merge in hdr.items()},
        "sensor_map": sensor.summary,
        "calibration": models.summary,
        "reconstruction": {name: r.summary for name, r in recons.items()},
        "evaluation": evaluation.summary,
    }
    report = Report("labkit demo --real — the thesis' ColorChecker, real frames")
    _write_report(report, results, hdr, sensor, models, recons, evaluation)
    write_text_atomic(
        out / "results.json", json.dumps(results, indent=1, default=json_default) + "\n"
    )
    _, page = report.write(out)
    return page


@dataclass(frozen=True)
class ChartEvaluation:
    """The evaluation stage of ``labkit demo --real``.

    Attributes
    ----------
    summary : dict
        Patch-centre errors, per-pixel errors and residual aberration (``results.json``).
    evaluation : reconstruction.Evaluation
        The scoreboard of every method.
    figures : dict
        The report's figures, relative to the output folder.
    patch : dict
        Per estimate, its patch-centre errors and spectra.
    """

    summary: dict[str, Any]
    evaluation: Evaluation
    figures: dict[str, Any]
    patch: dict[str, Any]


def _reconstruct(
    real: RealInputs, out: Path, disable: bool | None
) -> dict[str, SavedReconstruction]:
    results = {}
    for name, (slug, options) in VARIANTS.items():
        folder = out / "reconstruction" / slug
        saved = reconstruct_and_save(
            real.synthesis.raw.raw,
            folder,
            name=f"({name})",
            command="labkit demo --real",
            disable_progress=disable,
            **real.reconstruct_options(),
            **options,
        )
        saved.summary["options"] = options
        results[name] = saved
    return results


def _evaluate(
    real: RealInputs, recons: dict[str, SavedReconstruction], out: Path
) -> ChartEvaluation:
    from reconstruction import baseline_images, evaluate

    synthesis, models, labels = real.synthesis, real.models, real.labels
    raw = synthesis.raw
    scorer = real.scorer
    reflectances = scorer.reflectances
    multispectral = synthesis.multispectral
    patch = {"multispectral": scorer.patch_errors(multispectral.cube, multispectral.wavelengths_nm)}
    for name, r in recons.items():
        result = r.result
        patch[name] = scorer.patch_errors(result.spectral, result.wavelengths_nm)
    images, seconds = baseline_images(raw.raw, cfa=raw.cfa, colour_dispersion=models.colour)
    for name, r in recons.items():
        images[f"spectral: {name}"] = r.result.raw_colour
        seconds[f"spectral: {name}"] = r.summary["seconds"]
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
        "pixels": {name: scorer.pixel_errors(r.result) for name, r in recons.items()},
        "residual_aberration": evaluation.as_dict(),
    }
    return ChartEvaluation(summary, evaluation, figures, patch)


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
    wavelengths.update({name: r.result.wavelengths_nm for name, r in recons.items()})
    estimates = {
        name: (np.asarray(w), patch[name]["estimate"][list(SPECTRA_PATCHES)])
        for name, w in wavelengths.items()
    }
    path = folder / "patch_spectra.png"
    names = [COLORCHECKER_PATCHES[i] for i in SPECTRA_PATCHES]
    plot_patch_spectra((fine, truth), estimates, names, path)
    return str(path.relative_to(out))


def _write_report(report, results, hdr, sensor, models, recons, evaluation) -> None:
    _report_inputs(report, results, hdr)
    _report_sensor_map(report, results, sensor)
    _report_calibration(report, results)
    _report_reconstruction(report, results, recons)
    _report_evaluation(report, results, evaluation)


def _report_inputs(report, results, hdr) -> None:
    """The job, its stages' times, the import and the HDR merge."""
    times = results["seconds"]
    imported = results["import"]
    report.paragraph(
        f"Real frames of a ColorChecker from the thesis' lab (`{results['data']}`), under the "
        f"rig `{results['rig']}`: import → HDR → sensor map → multispectral and synthetic "
        "raw images → dispersion calibration → reconstruction → evaluation "
        f"against the chart's ASD spectrometer reflectances. Total {sum(times.values()):.0f} s."
    )
    stage_table(report, times)
    report.heading("Import and HDR")
    report.paragraph(
        f"{imported['frames']} frames and {imported['dark_frames']} dark frames; levels "
        f"from {imported['levels_from']}: {imported['source_dtype']} files, "
        f"{imported['sample_bits']}-bit samples, saturation {imported['saturation_dn']:g} DN, "
        f"black level {imported['black_level']:g} DN. The exposure factors fitted "
        "from the data (t_ref/t; a factor the data cannot fit keeps the exposure-time ratio, "
        "with a warning below)."
    )
    exposures = sorted({t for row in hdr.values() for t in row.exposures_s})
    header = ["filter"] + [f"{t * 1e3:g} ms" for t in exposures] + ["largest difference"]
    rows = []
    for name, row in sorted(hdr.items(), key=lambda item: float(item[0])):
        fitted = dict(zip(row.exposures_s, row.fitted, strict=True))
        rows.append(
            [name]
            + [f"{fitted[t]:.4f}" if t in fitted else "–" for t in exposures]
            + [f"{row.largest_difference:+.1%}"]
        )
    report.table(header, rows)
    warnings = [f"{n}: {w}" for n, row in hdr.items() for w in row.warnings]
    if warnings:
        report.bullets(warnings)
    report.figures(
        [(row.preview, f"{n} nm (HDR)") for n, row in hdr.items() if row.preview],
        width_px=220,
    )


def _report_sensor_map(report, results, sensor) -> None:
    """The sensor map against the stand-in response, and the synthesised images."""
    report.heading("Sensor map")
    report.paragraph(
        "R/G and B/G of every band measured from the filtered images, "
        f"against the rig's stand-in response ({sensor.summary['stand_in']}), and each "
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
            for b in sensor.summary["bands"]
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


def _report_calibration(report, results) -> None:
    """The bands kept and the dispersion models."""
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


def _report_reconstruction(report, results, recons) -> None:
    """Each variant's times, weights, patches and choices."""
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
        [(f"reconstruction/{r.folder.name}/preview.png", f"{n}: sRGB")
         for n, r in recons.items()],
        width_px=340,
    )  # fmt: skip


def _report_evaluation(report, results, evaluation) -> None:
    """Patch-centre and per-pixel spectra, residual chromatic aberration, the images."""
    from reconstruction.evaluate.residual_aberration import STRIP_PX

    report.heading("Evaluation")
    report.heading("Patch-centre spectra against the ASD reflectances", 3)
    report.paragraph(
        "Mean spectrum of the inner half of each patch against the spectrometer's reflectance, "
        "each band scaled by least squares over the 24 patches. The thesis (full "
        "resolution): multispectral image MRAE 0.194, its best reconstruction 0.258."
    )
    report.table(
        ["image", "MRAE", "RMSE"],
        [
            [name, f"{e['mrae']:.3f}", f"{e['rmse']:.4f}"]
            for name, e in results["evaluation"]["patch_centres"].items()
        ],
    )
    report.figures([(evaluation.figures["spectra"], "patch-centre spectra (registered)")])
    report.heading("Per-pixel spectra against the multispectral image", 3)
    report.paragraph(
        "Spectral RMSE of every pixel against the multispectral image the synthetic raw image "
        "is made from, moved into the reconstruction's geometry, each band scaled by least "
        "squares, relative to the chart's mean: over the chart, in strips inside "
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
        "in the patch centres, against an ideal image synthesised from the raw patch centres; "
        "fractions of the raw image's mean."
    )
    header, rows = evaluation.evaluation.table()
    report.table(header, rows)
    report.figures([(evaluation.figures["edge"], "edge-strip RMSE per channel")])
    report.heading("Images (one display scale for all)", 4)
    report.figures(evaluation.figures["previews"], width_px=300)
    report.figures([(evaluation.figures["crops"], "crops at the chart's corners")])


def _cell(value: float | None, spec: str = ".4g") -> str:
    return "–" if value is None or not np.isfinite(value) else format(value, spec)
