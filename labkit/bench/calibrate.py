"""`labkit bench calibrate`: dispersion calibration of a full-size disk pattern.

Target (issue 5): a 2448×2048 image of the disk pattern (≥ 800 disks) under the 7
filters — keypoints and model selection in ≤ 60 s on 2 cores. The HDR inputs come from
the simulator (noise-free render plus the noise of a merged bracket,
:func:`labkit.hdr.truth.simulated_hdr_images`; rendering is not timed), and every
model is compared with the lens' true dispersion inside the keypoints' convex hull.

Issue 7 adds the keypoint count: polynomial and spline fits to random subsets of the disk
keypoints (1/16 … all), timed alone and plotted as fit time against error.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from labkit.bench.harness import Measurement, Plot, Table, peak_rss_mib, repeat_timed
from labkit.bench.plots import plot_time_vs_error
from labkit.rig import ExposureConfig, load_rig
from labkit.sim.truth import model_error

if TYPE_CHECKING:
    from calibration.keypoints import DispersionKeypoints

TARGET_S = 60.0
SCENE = "disks"
MODELS = ("polynomial", "spline")
KEYPOINT_SOURCE = "disks + polynomial, clean bands"
"""The case whose keypoints the keypoint-count cases subsample."""
KEYPOINT_FRACTIONS = (1.0, 0.5, 0.25, 0.125, 0.0625)
"""Fractions of the disk keypoints the models are fitted to."""
SHORT_S = 10.0
"""Model fits shorter than this (s) are repeated (median)."""
TIME_ERROR_PNG = "calibrate_time_vs_error.png"


def bench_calibrate(
    rig_path: Path, *, repeats: int = 1, out: Path | None = None
) -> tuple[list[Measurement], list[str | Plot | Table]]:
    """Keypoints + model selection on simulated full-size HDR images of the disk pattern.

    Parameters
    ----------
    rig_path : Path
        Rig YAML of the simulated rig.
    repeats : int
        Runs per case (median reported); model fits of ≥ :data:`SHORT_S` s run once.
    out : Path, optional
        Report folder: the time-against-error plot is written there.

    Returns
    -------
    cases : list of Measurement
        The whole chain (keypoints + model) per keypoint method and model, then the model
        fits alone on subsets of the disk keypoints (:func:`keypoint_count_cases`).
    notes : list of str, Plot and Table
    """
    from calibration.bands import filter_bands
    from calibration.dispersion_calibration import MIN_PURITY, calibrate_dispersion
    from labkit.hdr.truth import simulated_hdr_images
    from labkit.sim import SimulatedRig

    rig = load_rig(rig_path)
    sim = SimulatedRig(rig)
    filtered = [name for name in rig.slider.illumination_names() if rig.filter_for(name)]
    start = time.perf_counter()
    thesis = ExposureConfig().filtered  # the thesis' bracket (§4.2.2), whatever the rig plans
    images = simulated_hdr_images(
        sim, SCENE, filtered, rng=np.random.default_rng(5), exposures_s=thesis
    )
    render_s = time.perf_counter() - start
    bands = filter_bands(rig, images=images)
    disks = len(sim.scene(SCENE).disks.centres())
    workers = os.cpu_count() or 1
    cases = [
        ("disks + polynomial, all 7 filters", "disks", "polynomial", 0.0, TARGET_S),
        ("disks + polynomial, clean bands", "disks", "polynomial", MIN_PURITY, TARGET_S),
        ("registration + polynomial, clean bands", "registration", "polynomial", MIN_PURITY, None),
        ("disks + spline, clean bands", "disks", "spline", MIN_PURITY, None),
    ]
    results: list[Measurement] = []
    models: dict[str, Any] = {}
    source_points, source_wavelengths = None, []
    for name, keypoints, kind, purity, target in cases:
        times = []
        for _ in range(max(1, repeats)):
            start = time.perf_counter()
            result = calibrate_dispersion(
                images,
                reference="600",
                model=kind,
                keypoints=keypoints,
                bands=bands,
                min_purity=purity,
                workers=workers,
            )
            times.append(time.perf_counter() - start)
        seconds = float(np.median(times))
        fitted = result.model
        used = [b.wavelength_nm for b in result.bands if b.used]
        reference_nm = float(fitted.reference)
        lo, hi = min(used), max(used)
        between = np.arange(np.ceil(lo / 5) * 5, hi, 5.0)
        error = model_error(fitted, sim.lens, reference_nm, sorted({*used, *between}))
        models[name] = fitted
        if name == KEYPOINT_SOURCE:
            source_points, source_wavelengths = result.keypoints, sorted({*used, *between})
        selection = fitted.selection
        results.append(
            Measurement(
                f"calibrate dispersion: {name}",
                seconds,
                times,
                peak_rss_mib(),
                target,
                None if target is None else seconds <= target,
                {
                    "image": f"{sim.shape[1]}×{sim.shape[0]}",
                    "disks_in_scene": disks,
                    "bands_used": len(used),
                    "keypoints": len(result.keypoints),
                    "selection": {
                        k: selection[k]
                        for k in ("degree_xy", "degree_lambda", "smoothing", "condition_number")
                        if k in selection
                    },
                    "error_vs_truth": error,
                    "workers": workers,
                },
            )
        )
    counted = keypoint_count_cases(source_points, sim.lens, source_wavelengths, repeats=repeats)
    results += counted
    notes: list[str | Plot | Table] = [
        f"Inputs: simulated HDR images of the disk pattern ({disks} disks, rendered in "
        f"{render_s:.0f} s, not timed) under {len(filtered)} filters; effective band "
        "wavelengths from the rig. 'clean bands' leaves out bands whose signal is < 90 % "
        "in-band (the simulated camera barely sees 400 and 700 nm, so leakage dominates).",
        "Errors: |model − lens truth| on a 16-px grid inside the keypoints' convex hull, at "
        "the used bands' effective wavelengths and every 5 nm between them.",
        "Peak memory: the largest resident set of this process or of any worker process "
        "so far (ru_maxrss), MiB; for the keypoint-count cases, the traced allocations of "
        "the first fit.",
        f"Keypoint count: the {len(source_points)} disk keypoints of '{KEYPOINT_SOURCE}' "
        "subsampled at random (the same subset for both models, at least one keypoint per "
        "band), then only the model fit (with its degree or smoothing selection) is timed.",
        keypoint_table(counted),
    ]
    if out is not None:
        notes.append(time_error_plot(counted, Path(out)))
    return results, notes


def keypoint_count_cases(
    keypoints: DispersionKeypoints,
    lens: Any,
    wavelengths_nm: list[float],
    *,
    repeats: int = 1,
    fractions: tuple[float, ...] = KEYPOINT_FRACTIONS,
    seed: int = 3,
) -> list[Measurement]:
    """Polynomial and spline fits on random subsets of `keypoints`: time and error vs truth.

    Parameters
    ----------
    keypoints : DispersionKeypoints
        Spectral keypoints (``from_reference``, as :func:`calibrate_dispersion` finds them).
    lens : Lens
        The simulated lens, whose true dispersion the models are compared with.
    wavelengths_nm : list of float
        Wavelengths at which the error is evaluated, nm.
    repeats : int
        Fits per case when a fit takes less than :data:`SHORT_S` s (median reported).
    fractions : tuple of float
        Fractions of the keypoints kept, in (0, 1].
    seed : int
        Seed of the random subsets.

    Returns
    -------
    list of Measurement
        Per fraction, the polynomial then the spline fit; ``extra`` holds ``model``,
        ``keypoints``, ``fraction``, ``selection`` and ``error_vs_truth`` (px).
    """
    from calibration.polynomial import fit_polynomial_model
    from calibration.spline import fit_spline_model

    fitters = {
        "polynomial": lambda points: fit_polynomial_model(points, rng=np.random.default_rng(2019)),
        "spline": lambda points: fit_spline_model(points),
    }
    cases = []
    for fraction in fractions:
        subset = (
            keypoints
            if fraction >= 1
            else keypoints.subsample(fraction, rng=np.random.default_rng(seed))
        )
        for kind, fit in fitters.items():
            model, times, peak = repeat_timed(
                lambda fit=fit, subset=subset: fit(subset),
                repeats=repeats,
                short_s=SHORT_S,
                trace=True,
            )
            seconds = float(np.median(times))
            selection = model.selection
            cases.append(
                Measurement(
                    f"fit {kind} to {len(subset)} disk keypoints",
                    seconds,
                    times,
                    peak,
                    None,
                    None,
                    {
                        "model": kind,
                        "keypoints": len(subset),
                        "fraction": fraction,
                        "selection": {
                            k: selection[k]
                            for k in ("degree_xy", "degree_lambda", "smoothing", "n_centres")
                            if k in selection
                        },
                        "error_vs_truth": model_error(
                            model, lens, float(model.reference), wavelengths_nm
                        ),
                    },
                )
            )
    return cases


def keypoint_table(cases: list[Measurement]) -> Table:
    """The keypoint-count cases side by side: fit time and RMS error of each model."""
    rows: dict[int, dict[str, Measurement]] = {}
    for case in cases:
        rows.setdefault(case.extra["keypoints"], {})[case.extra["model"]] = case
    columns = ["keypoints"]
    for kind in MODELS:
        columns += [f"{kind} fit (s)", f"{kind} RMS error (px)"]
    body = []
    for count, by_model in sorted(rows.items(), reverse=True):
        row = [str(count)]
        for kind in MODELS:
            case = by_model.get(kind)
            row += (
                ["—", "—"]
                if case is None
                else [f"{case.seconds:.3f}", f"{case.extra['error_vs_truth']['rms_px']:.4f}"]
            )
        body.append(row)
    title = (
        "Keypoint count: model fit time (selection included) and RMS error against the "
        "lens' true dispersion."
    )
    return Table(title, columns, body)


def time_error_plot(cases: list[Measurement], out: Path) -> Plot:
    """Fit time against RMS error per model, one point per keypoint count."""
    series = {
        kind: [
            (c.seconds, c.extra["error_vs_truth"]["rms_px"], f"{c.extra['keypoints']}")
            for c in cases
            if c.extra["model"] == kind
        ]
        for kind in MODELS
    }
    plot_time_vs_error(
        series,
        out / TIME_ERROR_PNG,
        title="labkit calibrate dispersion: fit time against error (labels: keypoints)",
        error_label="RMS |model − true dispersion| (px)",
        connect=True,
        log_error=True,
    )
    title = "Calibration: time against error, polynomial vs spline per keypoint count"
    return Plot(title, TIME_ERROR_PNG)
