"""The steps both demos share: named stages timed under one progress bar, the report's
stage table, a dispersion calibration saved with its plots, a reconstruction saved with its
summary, the report's notes on the choices labkit made, and every method's figures."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from labkit.io import display_on_one_scale, write_png
from labkit.plots import plot_channel_errors, plot_crops
from labkit.report import Report, file_stem

if TYPE_CHECKING:
    from calibration.dispersion_model import DispersionModel
    from reconstruction import Reconstruction


class Stages:
    """Runs the named stages of a job under one progress bar and records their wall time.

    ``stages(name, function)`` runs `function` and returns its value; :attr:`seconds` maps
    each stage's name to its wall time, s, in order.
    """

    def __init__(self, total: int, description: str, *, disable: bool | None = False) -> None:
        self.description = description
        self.seconds: dict[str, float] = {}
        self.bar = tqdm(total=total, desc=description, unit="stage", disable=disable)

    def __call__(self, name: str, function: Callable[[], Any]) -> Any:
        self.bar.set_description(f"{self.description}: {name}")
        start = time.perf_counter()
        value = function()
        self.seconds[name] = time.perf_counter() - start
        self.bar.update()
        return value

    def close(self) -> None:
        self.bar.close()


def stage_table(report: Report, seconds: dict[str, float]) -> None:
    """Add the time of every stage, and their total, to `report` as a table."""
    report.table(
        ["stage", "time (s)"],
        [[name, f"{value:.1f}"] for name, value in seconds.items()]
        + [["total", f"{sum(seconds.values()):.1f}"]],
    )


@dataclass
class DispersionModels:
    """A spectral and a colour-channel dispersion model, calibrated and saved by a demo.

    Attributes
    ----------
    spectral : DispersionModel
        The ``to_reference`` spectral model of the reconstruction.
    colour : DispersionModel
        The colour-channel model of the synthetic raw image (the warping baselines).
    summary : dict
        Bands kept or dropped and why, keypoints, degrees (for the report).
    """

    spectral: DispersionModel
    colour: DispersionModel
    summary: dict[str, Any]


@dataclass(frozen=True)
class SavedReconstruction:
    """A reconstruction a demo made and saved, and its summary for the report.

    Attributes
    ----------
    result : reconstruction.Reconstruction
        The reconstruction.
    folder : Path
        Where it was saved.
    summary : dict
        Seconds, bands, weights, patch counts, median ADMM iterations, warnings and the
        choices labkit made (what the report and ``results.json`` show).
    """

    result: Reconstruction
    folder: Path
    summary: dict[str, Any]


def save_models(spectral: Any, colour: Any, folder: Path) -> dict[str, Any]:
    """Save a spectral and a colour-channel dispersion calibration with their plots.

    Writes ``spectral_to_reference.yaml``, ``colour_from_reference.yaml`` and a PNG of
    each into `folder`; returns their summary for the report.
    """
    from calibration.plots import plot_model

    spectral.model.save(folder / "spectral_to_reference.yaml")
    colour.model.save(folder / "colour_from_reference.yaml")
    plot_model(spectral.model, folder / "spectral_model.png")
    plot_model(colour.model, folder / "colour_model.png")
    selection = spectral.model.selection
    return {
        "spectral": {
            "bands_used_nm": sorted(b.wavelength_nm for b in spectral.bands if b.used),
            "reference_nm": float(spectral.model.reference),
            "keypoints": len(spectral.keypoints),
            "degree_xy": selection.get("degree_xy"),
            "degree_lambda": selection.get("degree_lambda"),
            "condition_number": selection.get("condition_number"),
            "warnings": list(spectral.warnings),
        },
        "colour": {
            "keypoints": len(colour.keypoints),
            "degree_xy": colour.model.selection.get("degree_xy"),
            "warnings": list(colour.warnings),
        },
    }


def reconstruct_and_save(
    raw: np.ndarray,
    folder: Path,
    *,
    name: str,
    command: str = "labkit demo",
    disable_progress: bool | None = False,
    **options: Any,
) -> SavedReconstruction:
    """Reconstruct `raw` with a progress bar and save it into `folder`
    (:meth:`reconstruction.Reconstruction.save`); return it with its summary.
    """
    from reconstruction import reconstruct

    bar = tqdm(desc=f"reconstruct {name}", unit="patch", leave=False, disable=disable_progress)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    start = time.perf_counter()
    result = reconstruct(raw, progress=progress, **options)
    seconds = time.perf_counter() - start
    bar.close()
    result.save(folder, provenance={"command": command})
    patches = result.log["patches"]
    summary = {
        "seconds": seconds,
        "bands_nm": [float(b) for b in result.wavelengths_nm],
        "weights": result.log["weights"]["values"],
        "patches": patches["count"],
        "phi_used": patches["phi_used"],
        "flat": patches["flat"],
        "median_iterations": patches["iterations_median"],
        "exact": patches["exact"],
        "warnings": list(result.log.get("warnings", [])),
        "choices": result.log.get("choices", {}),
    }
    return SavedReconstruction(result, folder, summary)


def reconstruction_notes(report: Any, summaries: dict[str, dict[str, Any]]) -> None:
    """Add the reconstructions' warnings (their logs' ``warnings``), if any, and the
    choices labkit made for each (their logs' ``choices``: value, how, why) to `report`."""
    notices = [f"{name}: {w}" for name, s in summaries.items() for w in s.get("warnings", [])]
    if notices:
        report.bullets(notices)
    rows = [
        [name, option, _choice_value(c["value"]), c["source"], c["reason"]]
        for name, s in summaries.items()
        for option, c in s.get("choices", {}).items()
        if c["source"] != "given"
    ]
    if rows:
        report.paragraph(
            "Choices labkit made (each can be given as an option instead; `log.json`'s "
            "`choices` records them with their evidence):"
        )
        report.table(["image", "option", "value", "how", "why"], rows)


def _choice_value(value: Any) -> str:
    if isinstance(value, list) and value and all(isinstance(v, (int, float)) for v in value):
        return f"{len(value)} values, {value[0]:g}–{value[-1]:g}"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def method_figures(
    out: Path,
    folder: Path,
    images: dict[str, np.ndarray],
    evaluation: Any,
    centres: list[tuple[int, int]],
    side: int,
    *,
    edge: bool,
) -> dict[str, Any]:
    """Every method's image on one display scale, zoomed crops and the edge-error chart.

    Parameters
    ----------
    out : Path
        The report's folder (figure paths are returned relative to it).
    folder : Path
        Where the PNGs go.
    images : dict of str to ndarray (rows, cols, 3)
        Colour images by method (``"bilinear"`` among them: the display scale's reference).
    evaluation : reconstruction.Evaluation
        Their scores (the edge chart needs residual aberration).
    centres : list of (row, col)
        Centres of the zoomed crops, px.
    side : int
        Crop side, px.
    edge : bool
        Draw the edge-strip RMSE chart.
    """
    display = display_on_one_scale(images, reference="bilinear")
    previews = []
    for name, image in display.items():
        path = folder / f"{file_stem(name)}.png"
        write_png(path, image)
        previews.append((str(path.relative_to(out)), name))
    rows, cols = next(iter(images.values())).shape[:2]
    windows = [
        (int(np.clip(r - side // 2, 0, rows - side)), int(np.clip(c - side // 2, 0, cols - side)),
         side)
        for r, c in centres
    ]  # fmt: skip
    chosen = ["bilinear", "malvar + warp", "menon", "menon + warp"]
    chosen += [n for n in display if n.startswith("spectral")]
    plot_crops({n: display[n] for n in chosen if n in display}, windows, folder / "crops.png")
    figures = {"previews": previews, "crops": str((folder / "crops.png").relative_to(out))}
    if edge:
        rmse = {n: s.residual.edge.rmse for n, s in evaluation.scores.items() if s.residual}
        plot_channel_errors(
            rmse, folder / "edge_rmse.png", ylabel="edge-strip RMSE (fraction of raw mean)"
        )
        figures["edge"] = str((folder / "edge_rmse.png").relative_to(out))
    return figures
