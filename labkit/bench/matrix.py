"""Validation matrix: the default options against the main variants, row by row.

A default or an automatic policy is judged on rows of different kinds, not on one scene:

* **real** — the vendored ColorChecker frames, as ``labkit demo --real`` prepares them
  (the synthetic raw image of Algorithm 13, the dispersion model labkit calibrates from the
  filtered frames): the whole image with the measured sensor map as the response in its
  two conventions, *levelled* (each band at the Green level the camera measured) and
  *G = 1* (the thesis' published normalisation: R and B relative to G, G the same in every
  band); the levelled whole image again with two other dispersion models: Φ at the
  filters' nominal wavelengths (the model without its record of the filters' effective
  wavelengths, as a response tabulated per filter was read before issue 53), and Φ
  calibrated with the 400 nm filter too (whose light leaks: the default calibration leaves
  it out); and two quadrants reaching its corners, each with the whole frame's model moved
  to the crop, as a user who calibrated once and reconstructs crops would;
* **simulated** — the simulated rig's ColorChecker and textured scene under broadband
  light, the same under one 10 nm filter (narrow-band light), a disk chart behind a
  lens whose lateral chromatic aberration reaches :data:`DISK_SHIFT_PX` in the corners,
  and a natural-like scene (:func:`labkit.sim.scenes.natural_scene`: dead leaves of
  smooth, mostly unsaturated reflectances) under broadband light.

Each row is reconstructed with every variant of :data:`VARIANTS`, and scored by its
spectral error against its truth (the real rows: per pixel against the multispectral image
in the reconstruction's geometry, and the patch centres against the spectrometer; the
simulated rows: per pixel against the rendered truth; each band scaled by least squares,
eq. 4.9), its residual chromatic aberration (edge strips of the ColorChecker's patches,
§4.4.3; disk-centre offsets R−G and B−G on the disk chart), its time (wall and CPU; the
defaults' wall time is held to :data:`TARGET_S`) and its ADMM iterations. A row
**passes** when the defaults are within :data:`TOLERANCE` of the best variant on every one
of its error measures.

Where a row measures residual chromatic aberration, every baseline a user would pick
instead is measured the same way (:func:`baseline_table`): bilinear, Malvar and Menon
demosaicing, each alone and followed by warping R and B onto G with a colour-channel
model (Rudakova–Monasse; OpenCV's calibrated correction and the thesis' warping are of
this kind). The real rows' colour model is the one ``labkit demo --real`` calibrates on
the same raw image (moved to the crop for the quadrants); the simulated rows' is the
model a calibration of their lens would find at best
(:func:`labkit.bench.reconstruct_cases.channel_model`), since a calibration on their own
small images finds too few keypoints.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from labkit.bench.harness import Measurement, Plot, Table, peak_rss_mib
from labkit.errors import DataError

TOLERANCE = 0.10
"""How far (relative) the defaults may lie above the best variant's error on a row."""

TARGET_S = 3.5
"""Wall time the defaults must reach on every row (the rows are at most 344×408 px), s:
issue 53's target for the worst 344×408 7-band row with Φ, 2 cores."""

DISK_SHIFT_PX = 3.5
"""Largest lateral chromatic aberration of the disk-chart row's lens (corners, 400–700 nm)."""

NARROW_BAND = "550"
"""The filter of the narrow-band rows (its light is mostly within the band)."""

REAL_CROPS = {"top-left": ((0, 0), (172, 204)), "bottom-right": ((170, 204), (172, 204))}
"""Windows (origin, shape; rows, cols) of the real frames reconstructed as crops: two
quadrants, each reaching a corner of the frame."""

SIM_SHAPE = (172, 204)
"""Size of the simulated rows, px (rows, cols)."""

VARIANTS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("defaults", {}),
    ("σ = 1e-3", {"spectral_smoothness": 1e-3}),
    ("σ = 0", {"spectral_smoothness": 0.0}),
    ("mean-colour reference", {"reference": "mean-colour"}),
    ("mean-colour reference, σ = 1e-3", {"reference": "mean-colour", "spectral_smoothness": 1e-3}),
    ("mean-colour reference, σ = 0", {"reference": "mean-colour", "spectral_smoothness": 0.0}),
    ("no reference (plain problem)", {"reference": None}),
    ("bilinear Φ", {"interpolation": "bilinear"}),
)
"""Label → options of :func:`reconstruction.reconstruct` on top of a row's inputs."""


@dataclass
class Row:
    """One row of the matrix: what to reconstruct and how to score it.

    Attributes
    ----------
    name : str
    kind : {"real", "simulated"}
    light : {"broadband", "narrow-band"}
    inputs : dict
        ``raw`` and the options every variant shares (``cfa``, ``response``, ``bands``,
        ``dispersion``).
    score : callable
        Reconstruction → {measure: error} (lower is better; None where it cannot be
        measured).
    errors : tuple of str
        The measures the verdict compares: the spectral ones first, then residual CA.
    baselines : callable, optional
        () → {baseline: {measure: value}}: the row's residual-CA measures of every baseline
        image (:func:`reconstruction.baseline_images`: each demosaicing method, and each
        followed by warping with the row's colour-channel model).
    """

    name: str
    kind: str
    light: str
    inputs: dict[str, Any]
    score: Callable[[Any], dict[str, float | None]]
    errors: tuple[str, ...]
    baselines: Callable[[], dict[str, dict[str, float | None]]] | None = None


def bench_matrix(
    rig_path: Path,
    *,
    repeats: int = 1,
    out: Path | None = None,
    rows: Sequence[str] | None = None,
    variants: tuple[tuple[str, dict[str, Any]], ...] = VARIANTS,
) -> tuple[list[Measurement], list]:
    """Reconstruct every row with every variant; one :class:`Measurement` per pair.

    Parameters
    ----------
    rig_path : Path
        The simulated rig of the simulated rows.
    repeats : int
        Unused (every pair runs once: the matrix compares errors; the defaults' wall time
        is held to :data:`TARGET_S`, the variants' is reported).
    out : Path, optional
        Where the plot is written (none without).
    rows : sequence of str, optional
        Only the rows whose names contain one of these strings (default: all).
    variants : tuple
        Label → options; the first is the reference the verdict holds to the others.

    Returns
    -------
    measurements : list of Measurement
        ``extra`` holds the row, kind, light, variant, every error measure, ``cpu_s``,
        ``iterations_median``, ``exact`` and the choices the defaults made.
    notes : list
        The verdict table (one line per row) and the plot.
    """
    del repeats
    results: list[Measurement] = []
    with tempfile.TemporaryDirectory(prefix="labkit-bench-matrix-") as work:
        for row in _rows(Path(rig_path), Path(work), rows):
            row_results = [
                _run(row, label, options, TARGET_S if label == variants[0][0] else None)
                for label, options in variants
            ]
            if row.baselines is not None:  # beside the defaults' (the first variant's)
                row_results[0].extra["baselines"] = row.baselines()
            results += row_results
    notes: list = [verdict_table(results, variants[0][0])]
    if any("baselines" in m.extra for m in results):
        notes.append(baseline_table(results))
    notes += [error_table(results, measure) for measure in reported_measures(results)]
    if out is not None and results:
        notes.append(_plot(results, variants[0][0], Path(out)))
    return results, notes


def _run(row: Row, label: str, options: dict[str, Any], target: float | None) -> Measurement:
    from reconstruction import reconstruct

    inputs = dict(row.inputs)
    raw = inputs.pop("raw")
    wall, cpu = time.perf_counter(), time.process_time()
    result = reconstruct(raw, **inputs, **options)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    log = result.log
    choices = {
        name: {"value": c["value"], "source": c["source"]}
        for name, c in log["choices"].items()
        if c["source"] != "given"
    }
    return Measurement(
        f"{row.name}, {label}",
        wall,
        [wall],
        peak_rss_mib(),
        target,
        None if target is None else wall <= target,
        extra={
            "row": row.name,
            "kind": row.kind,
            "light": row.light,
            "variant": label,
            "error_measures": list(row.errors),
            **row.score(result),
            "cpu_s": cpu,
            "iterations_median": log["patches"]["iterations_median"],
            "exact": log["patches"]["exact"],
            "patches": log["patches"]["count"],
            "warnings": len(log["warnings"]),
            "choices": choices,
        },
    )


# -- verdict ----------------------------------------------------------------------------
def row_verdicts(results: Sequence[Measurement], reference: str) -> list[dict[str, Any]]:
    """Per row: each error measure's ratio of `reference` (the defaults) to the best
    variant, the best variant's name, whether every ratio is ≤ 1 + :data:`TOLERANCE`, and
    whether the defaults met their time target (``in_time``; None without one)."""
    verdicts = []
    for name in dict.fromkeys(m.extra["row"] for m in results):
        row = [m for m in results if m.extra["row"] == name]
        base = next((m for m in row if m.extra["variant"] == reference), None)
        if base is None:
            continue
        ratios: dict[str, dict[str, Any]] = {}
        for measure in base.extra["error_measures"]:
            values = [
                (m.extra[measure], m.extra["variant"])
                for m in row
                if m.extra.get(measure) is not None and np.isfinite(m.extra[measure])
            ]
            mine = base.extra.get(measure)
            if not values or mine is None:
                continue
            best, winner = min(values)
            ratio = mine / best if best > 0 else (1.0 if mine == 0 else float("inf"))
            ratios[measure] = {"ratio": ratio, "best": best, "best_variant": winner}
        verdicts.append(
            {
                "row": name,
                "kind": base.extra["kind"],
                "light": base.extra["light"],
                "ratios": ratios,
                "passed": all(r["ratio"] <= 1 + TOLERANCE for r in ratios.values()),
                "seconds": base.seconds,
                "cpu_s": base.extra["cpu_s"],
                "in_time": base.passed,
            }
        )
    return verdicts


def verdict_table(results: Sequence[Measurement], reference: str) -> Table:
    """One line per row: the defaults' error / the best variant's, per measure."""
    lines = []
    for v in row_verdicts(results, reference):
        cells = [
            f"{measure} {r['ratio']:.2f}"
            + ("" if r["ratio"] <= 1 + TOLERANCE else f" (best: {r['best_variant']})")
            for measure, r in v["ratios"].items()
        ]
        lines.append(
            [
                v["row"],
                f"{v['kind']}, {v['light']}",
                "; ".join(cells),
                "yes" if v["passed"] else "**no**",
                f"{v['seconds']:.1f} / {v['cpu_s']:.1f}"
                + (" (**over**)" if v["in_time"] is False else ""),
            ]
        )
    return Table(
        f"The defaults against the best of {len({m.extra['variant'] for m in results})} "
        f"variants on each row: error of the defaults / the best variant's (≤ "
        f"{1 + TOLERANCE:g} passes)",
        ["row", "kind", "defaults / best", "passes", f"defaults: wall / CPU s (≤ {TARGET_S:g})"],
        lines,
    )


#: The residual-CA measures a row may record, and how a table cell names them.
CA_MEASURES = {"edge_rmse_R": "R", "edge_rmse_B": "B", "ca_rg_px": "R−G", "ca_bg_px": "B−G"}


def baseline_table(results: Sequence[Measurement]) -> Table:
    """Per row with baselines: the defaults' residual CA and every baseline's, and whether
    the defaults are below every baseline on every measure."""
    names = list(dict.fromkeys(b for m in results for b in m.extra.get("baselines", {})))
    lines = []
    for m in results:
        baselines = m.extra.get("baselines")
        if baselines is None:
            continue
        measures = [k for k in m.extra["error_measures"] if k in CA_MEASURES]

        def cell(values: dict[str, Any], measures: list[str] = measures) -> str:
            return " / ".join(
                "—" if values.get(k) is None else f"{values[k]:.3f}" for k in measures
            )

        below = all(
            m.extra.get(k) is not None
            and all(b.get(k) is None or m.extra[k] < b[k] for b in baselines.values())
            for k in measures
        )
        lines.append(
            [
                m.extra["row"],
                " / ".join(CA_MEASURES[k] for k in measures),
                cell(m.extra),
                *(cell(baselines[n]) if n in baselines else "—" for n in names),
                "yes" if below else "**no**",
            ]
        )
    return Table(
        "Residual chromatic aberration of the defaults and of every baseline (edge strips: "
        "RMSE as a fraction of the raw mean; disks: R−G and B−G centre offsets, px)",
        ["row", "measures", "labkit defaults", *names, "defaults below every baseline"],
        lines,
    )


#: Measured on some rows, judged on none: the raw colour image's error (σ's price under
#: narrow-band light shows here).
REPORTED_ONLY = ("colour_rmse",)


def reported_measures(results: Sequence[Measurement]) -> list[str]:
    """Every error measure some row judges (spectral first, then residual CA), then those
    only reported (:data:`REPORTED_ONLY`) where a row records them."""
    judged = dict.fromkeys(k for m in results for k in m.extra["error_measures"])
    shown = [k for k in REPORTED_ONLY if any(m.extra.get(k) is not None for m in results)]
    return [*judged, *(k for k in shown if k not in judged)]


def error_table(results: Sequence[Measurement], measure: str) -> Table:
    """Rows × variants: `measure` of every reconstruction (the best of a row in bold), and
    the wall time; rows that do not record `measure` are left out."""
    variants = list(dict.fromkeys(m.extra["variant"] for m in results))
    lines = []
    for name in dict.fromkeys(m.extra["row"] for m in results):
        row = {m.extra["variant"]: m for m in results if m.extra["row"] == name}
        values = {v: row[v].extra.get(measure) for v in variants if v in row}
        finite = [x for x in values.values() if x is not None and np.isfinite(x)]
        if not finite:
            continue
        best = min(finite)
        cells = []
        for v in variants:
            x = values.get(v)
            if x is None:
                cells.append("—")
                continue
            text = f"{x:.4f} ({row[v].seconds:.0f} s)"
            cells.append(f"**{text}**" if x == best else text)
        lines.append([name, *cells])
    return Table(f"{measure} of every row and variant (wall time)", ["row", *variants], lines)


def _plot(results: Sequence[Measurement], reference: str, out: Path) -> Plot:
    import matplotlib.pyplot as plt

    from labkit.plots import save_figure

    verdicts = row_verdicts(results, reference)
    measures = list(dict.fromkeys(k for v in verdicts for k in v["ratios"]))
    figure, axis = plt.subplots(figsize=(8, 0.45 * len(verdicts) + 1.5))
    height = 0.8 / max(len(measures), 1)
    for i, measure in enumerate(measures):
        values = [v["ratios"].get(measure, {}).get("ratio", np.nan) for v in verdicts]
        positions = np.arange(len(verdicts)) + i * height
        axis.barh(positions, values, height=height, label=measure)
    axis.axvline(1 + TOLERANCE, color="grey", linestyle="--", label=f"{1 + TOLERANCE:g}")
    axis.set_yticks(np.arange(len(verdicts)) + 0.4 - height / 2)
    axis.set_yticklabels([v["row"] for v in verdicts], fontsize=7)
    axis.invert_yaxis()
    axis.set_xlabel("defaults' error / best variant's")
    axis.legend(fontsize=7, loc="lower right")
    axis.set_title("Validation matrix: the defaults against the best variant")
    file = "matrix.png"
    save_figure(figure, out / file)
    return Plot("the defaults' error relative to the best variant, per row and measure", file)


# -- rows -------------------------------------------------------------------------------
def _rows(rig_path: Path, work: Path, wanted: Sequence[str] | None) -> list[Row]:
    def keep(name: str) -> bool:
        return wanted is None or any(w in name for w in wanted)

    rows: list[Row] = []
    # the real rows cost a preparation of the frames: only when a wanted name may be one
    if wanted is None or any("real" in w or w in "real" for w in wanted):
        rows += [r for r in real_rows(work / "real") if keep(r.name)]
    rows += simulated_rows(rig_path, keep=keep)
    return rows


def real_rows(work: Path) -> list[Row]:
    """The real ColorChecker rows: whole image (levelled and G = 1 sensor map; Φ at the
    nominal wavelengths, and calibrated with the 400 nm filter) and two quadrants with the
    whole frame's model moved to the crop."""
    from labkit.real_chart import prepare_real_inputs

    real = prepare_real_inputs(work)
    sensitivity = real.sensor.sensitivity
    g1 = replace(sensitivity, green_level=np.full(len(sensitivity), np.nan)).as_response()
    rows = real.synthesis.raw.raw.shape
    whole = f"real ColorChecker {rows[1]}×{rows[0]}"
    out = [
        _real_row(f"{whole}, levelled map", real),
        _real_row(f"{whole}, G = 1 map", real, response=g1),
        _real_row(
            f"{whole}, levelled map, Φ at the filters' nominal wavelengths",
            with_spectral_model(real, without_filter_record(real.models.spectral)),
        ),
        _real_row(
            f"{whole}, levelled map, Φ calibrated with the 400 nm filter",
            with_spectral_model(real, calibrated_with_every_filter(real, work / "hdr")),
        ),
    ]
    for side, (origin, shape) in REAL_CROPS.items():
        crop = crop_real(real, origin, shape)
        name = f"real ColorChecker {side} quadrant {shape[1]}×{shape[0]}, levelled map"
        out.append(_real_row(name, crop))
    return out


def _real_row(name: str, real: Any, *, response: Any = None) -> Row:
    inputs = {"raw": real.synthesis.raw.raw, **real.reconstruct_options()}
    if response is not None:
        inputs["response"] = response
    whole = real.labels.max() > 0 and np.unique(real.labels).size == 25

    def score(result: Any) -> dict[str, float | None]:
        if whole:
            s = real.scorer.score(result)
            return {
                "spectral_rmse": s["spectral_rmse"],
                "mrae": s["mrae"],
                "edge_rmse_R": s["edge_rmse_R"],
                "edge_rmse_B": s["edge_rmse_B"],
            }
        return {
            "spectral_rmse": real.scorer.pixel_errors(result)["chart"],
            **_real_edges(real, {"x": result.raw_colour})["x"],
        }

    def baselines() -> dict[str, dict[str, float | None]]:
        from reconstruction import baseline_images

        raw = real.synthesis.raw
        images, _ = baseline_images(raw.raw, cfa=raw.cfa, colour_dispersion=real.models.colour)
        return _real_edges(real, images)

    measures = ("spectral_rmse", "mrae") if whole else ("spectral_rmse",)
    measures += ("edge_rmse_R", "edge_rmse_B")
    return Row(name, "real", "broadband", inputs, score, measures, baselines)


def _real_edges(real: Any, images: dict[str, np.ndarray]) -> dict[str, dict[str, float | None]]:
    """Edge-strip RMSE R and B of each raw colour image of `real`'s chart, by name
    (:meth:`reconstruction.evaluate.chart_scores.ChartScorer.edge_rmse`)."""
    return {
        name: {f"edge_rmse_{c}": edge[c] for c in "RB"}
        for name, edge in real.scorer.edge_rmse(images).items()
    }


def with_spectral_model(real: Any, model: Any) -> Any:
    """`real` (:class:`labkit.real_chart.RealInputs`) with another spectral dispersion model."""
    return replace(real, models=replace(real.models, spectral=model))


def without_filter_record(model: Any) -> Any:
    """`model` without its record of the filters' effective wavelengths
    (``provenance.bands_table``): a response tabulated per filter then has Φ evaluated at
    the filters' nominal wavelengths (:func:`reconstruction.options.filter_light`)."""
    provenance = {k: v for k, v in model.provenance.items() if k != "bands_table"}
    return replace(model, provenance=provenance)


def calibrated_with_every_filter(real: Any, hdr: Path) -> Any:
    """The spectral model of `real`'s filtered HDR images in `hdr`, calibrated as the demo
    calibrates it but keeping every filter, however impure its light (``min_purity=0``:
    the 400 nm filter, whose light leaks, too)."""
    from calibration import load_filtered_hdr
    from labkit.real_chart import calibrate_spectral
    from labkit.rig import load_rig

    images = load_filtered_hdr(hdr)[real.scene]
    return calibrate_spectral(images, load_rig(real.rig), min_purity=0.0).model


def crop_real(real: Any, origin: tuple[int, int], shape: tuple[int, int]) -> Any:
    """`real` (:class:`labkit.real_chart.RealInputs`) cut to the `shape` px window at
    `origin` (even, so that the Bayer phase is kept), with the whole sensor's dispersion
    models moved to the window (:meth:`calibration.DispersionModel.cropped`), as a user who
    calibrated the sensor once and reconstructs a crop would. (Calibrating on the crop's
    own frames is the other way; the registration keypoints of these frames find too
    little texture in a half of the chart.)"""
    from calibration.multispectral import Synthesis

    r0, c0 = origin
    if r0 % 2 or c0 % 2:
        raise DataError(f"crop origin {origin} must be even (Bayer phase)")
    window = (slice(r0, r0 + shape[0]), slice(c0, c0 + shape[1]))
    synthesis = real.synthesis
    cube = synthesis.multispectral
    cropped = Synthesis(
        replace(cube, cube=cube.cube[window]),
        synthesis.rgb[window],
        replace(synthesis.raw, raw=synthesis.raw.raw[window]),
    )
    models = replace(
        real.models,
        spectral=real.models.spectral.cropped(origin, shape),
        colour=real.models.colour.cropped(origin, shape),
    )
    return replace(real, synthesis=cropped, models=models, labels=real.labels[window])


def simulated_rows(rig_path: Path, *, keep: Callable[[str], bool] = lambda _: True) -> list[Row]:
    """The simulated rows: ColorChecker and texture under broadband and narrow-band light,
    a natural-like scene under broadband light,
    and a disk chart with strong off-axis aberration."""
    from labkit.bench.reconstruct_cases import edge_errors, errors, simulated_case

    rows = []
    shape = SIM_SHAPE
    for scene, light in (
        ("colorchecker", "unfiltered"),
        ("texture", "unfiltered"),
        ("colorchecker", NARROW_BAND),
        ("texture", NARROW_BAND),
        ("disks", "unfiltered"),
        ("natural", "unfiltered"),
    ):
        kind = "broadband" if light == "unfiltered" else "narrow-band"
        where = "" if light == "unfiltered" else f" through the {light} nm filter"
        name = f"simulated {scene}{where} {shape[1]}×{shape[0]}"
        if scene == "disks":
            name += f", {DISK_SHIFT_PX:g} px CA"
        if not keep(name):
            continue
        case = simulated_case(
            rig_path,
            shape,
            scene,
            illumination=light,
            max_shift_px=DISK_SHIFT_PX if scene == "disks" else None,
        )
        inputs = {
            "raw": case["raw"],
            "cfa": case["cfa"],
            "response": case["response"],
            "dispersion": case["model"],
        }

        def score(result: Any, case: dict = case) -> dict[str, float | None]:
            e = errors(case, result)
            out: dict[str, float | None] = {
                "spectral_rmse": e["spectral_rmse_rel"],
                # reported, not judged: σ's price under narrow-band light
                "colour_rmse": float(np.mean([e[f"colour_rmse_{c}"] for c in "RGB"])),
            }
            if "edge_rmse_R" in e:
                out.update(edge_rmse_R=e["edge_rmse_R"], edge_rmse_B=e["edge_rmse_B"])
            if case["scene"] == "disks":
                out.update(_disk_offsets(result.raw_colour))
            return out

        def baselines(case: dict = case) -> dict[str, dict[str, float | None]]:
            from reconstruction import baseline_images

            images, _ = baseline_images(
                case["raw"], cfa=case["cfa"], colour_dispersion=case["colour_model"]()
            )
            if case["scene"] == "disks":
                return {name: dict(_disk_offsets(rgb)) for name, rgb in images.items()}
            return {
                name: {k: v for k, v in edge_errors(case, rgb).items() if k != "edge_rmse_G"}
                for name, rgb in images.items()
            }

        measures = ("spectral_rmse",)
        if scene == "colorchecker":
            measures += ("edge_rmse_R", "edge_rmse_B")
        if scene == "disks":
            measures += ("ca_rg_px", "ca_bg_px")
        with_ca = scene == "disks" or "boxes" in case
        rows.append(
            Row(name, "simulated", kind, inputs, score, measures, baselines if with_ca else None)
        )
    return rows


def _disk_offsets(rgb: np.ndarray) -> dict[str, float | None]:
    from reconstruction.evaluate.metrics import disk_channel_offsets

    try:
        offsets = disk_channel_offsets(np.asarray(rgb, dtype=np.float64))
    except DataError:
        return {"ca_rg_px": None, "ca_bg_px": None}
    return {"ca_rg_px": offsets.rg_px, "ca_bg_px": offsets.bg_px}
