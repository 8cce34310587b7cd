"""Reconstruction on the real ColorChecker frames, next to the simulated ColorChecker.

The real rows reconstruct what ``labkit demo --real`` reconstructs: the synthetic raw image
made from the thesis' filtered frames (Algorithm 13), with the measured sensor map as the
camera response and the dispersion model labkit calibrates from those frames. They are
scored against the chart's ASD reflectances in the patch centres (MRAE, RMSE), by the
residual aberration in the patch edge strips (§4.4.3, fractions of the raw mean), and per
pixel against the multispectral image moved into the reconstruction's geometry, in the
edge strips and in the centres (:func:`reconstruction.spectral_strip_errors`; the
simulated rows get the same split against their truth). Every
variant of :data:`MAIN_VARIANTS` runs on both kinds of data, so that a change shows its
effect on both.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from labkit.bench.harness import Measurement, Table, peak_rss_mib

MAIN_VARIANTS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("defaults", {}),
    ("no band balance (every band alike)", {"band_balance": 0.0}),
    ("σ = 0 (thesis)", {"spectral_smoothness": 0.0}),
    ("reference spectrum from the mean colour", {"reference": "mean-colour"}),
    (
        "reference spectrum from the mean colour, σ = 0",
        {"reference": "mean-colour", "spectral_smoothness": 0.0},
    ),
    ("no non-negativity", {"nonneg": False}),
    ("L2 prior (the thesis')", {"prior": "L2", "band_balance": 0.0}),
    ("bilinear Φ (the thesis')", {"interpolation": "bilinear"}),
    (
        "VTV, cubic Φ, auto:dmc-menon, σ = 0",
        {
            "prior": "VTV",
            "interpolation": "cubic",
            "weights": "auto:dmc-menon",
            "spectral_smoothness": 0.0,
        },
    ),
)
"""The default problem and the main variants: label → options of
:func:`reconstruction.reconstruct` (on top of the inputs of each kind of data)."""

REAL_PREFIX = "real ColorChecker"


def real_measurements(
    variants: tuple[tuple[str, dict[str, Any]], ...] = MAIN_VARIANTS,
) -> tuple[list[Measurement], dict[str, tuple[float, float, float]]]:
    """One :class:`Measurement` per variant on the vendored real frames.

    The frames are imported, merged, mapped and calibrated once (into a temporary folder),
    then each variant reconstructs the synthetic raw image. ``extra`` holds ``mrae`` and
    ``rmse`` (patch centres against the ASD reflectances), ``edge_rmse_R/G/B``, the weights,
    the weight-selection time (s), and the patches solved exactly and the median ADMM
    iterations.

    Returns
    -------
    measurements : list of Measurement
    baselines : dict
        Edge-strip RMSE (R, G, B) of the demosaicing baselines on the same raw image.
    """
    from labkit.real_chart import prepare_real_inputs
    from reconstruction import baseline_images, evaluate, reconstruct

    results = []
    with tempfile.TemporaryDirectory(prefix="labkit-bench-real-") as work:
        real = prepare_real_inputs(Path(work))
        raw = real.synthesis.raw.raw
        rows, cols = raw.shape
        images, _ = baseline_images(raw, cfa=real.synthesis.raw.cfa)
        methods = evaluate(raw, images, cfa=real.synthesis.raw.cfa, labels=real.labels)
        baselines = {
            name: tuple(float(v) for v in entry["residual_aberration"]["edge"]["rmse"].values())
            for name, entry in methods.as_dict()["methods"].items()
        }
        for label, options in variants:
            start = time.perf_counter()
            result = reconstruct(raw, **real.reconstruct_options(), **options)
            seconds = time.perf_counter() - start
            log = result.log
            results.append(
                Measurement(
                    f"{REAL_PREFIX} {cols}×{rows} (synthetic raw), 7 bands, {label}",
                    seconds,
                    [seconds],
                    peak_rss_mib(),
                    extra={
                        "variant": label,
                        "image": f"{cols}×{rows}",
                        **real.scorer.score(result),
                        "weights": [float(w) for w in log["weights"]["values"]],
                        "weight_s": float(log["weights"]["seconds"]),
                        "patches": log["patches"]["count"],
                        "exact": log["patches"]["exact"],
                        "iterations_median": log["patches"]["iterations_median"],
                        "patch_cost": patch_cost(log["patch_records"]),
                    },
                )
            )
    return results, baselines


def comparison_table(real: list[Measurement], simulated: list[Measurement]) -> Table:
    """Each variant's time and errors on the real and on the simulated ColorChecker."""

    def triple(m: Measurement) -> str:
        return "/".join(f"{m.extra[f'edge_rmse_{c}']:.4f}" for c in "RGB")

    def strips(m: Measurement | None) -> str:
        if m is None or "spectral_rmse_strips" not in m.extra:
            return "—"
        return "/".join(
            f"{m.extra[f'spectral_rmse_{region}']:.4f}"
            for region in ("strips", "centres", "surround")
        )

    by_variant = {m.extra["variant"]: m for m in simulated}
    rows = []
    for m in real:
        sim = by_variant.get(m.extra["variant"])
        rows.append(
            [
                m.extra["variant"],
                f"{m.seconds:.1f}",
                f"{m.extra['mrae']:.4f}",
                f"{m.extra['rmse']:.4f}",
                triple(m),
                f"{m.extra['spectral_rmse']:.4f}" if "spectral_rmse" in m.extra else "—",
                strips(m),
                "—" if sim is None else f"{sim.seconds:.1f}",
                "—" if sim is None else f"{sim.extra['spectral_rmse_rel']:.4f}",
                "—" if sim is None else f"{sim.extra['spectral_mrae']:.4f}",
                "—" if sim is None else triple(sim),
                strips(sim),
            ]
        )
    return Table(
        "Main variants on both kinds of data. Real: the thesis' ColorChecker frames "
        "(synthetic raw image, sensor map as response), patch-centre MRAE and RMSE against "
        "the ASD reflectances. Simulated: the 344×408 ColorChecker, spectral RMSE (relative "
        "to the mean truth) and MRAE per pixel. Edge RMSE R/G/B: the edge strips of the "
        "raw colour image. Real spectral RMSE: per pixel over the chart (its patches and "
        "the 12 px around them) against the multispectral image moved into the "
        "reconstruction's geometry. Spectral strips/centres/surround: the spectral RMSE in "
        "the patches' 12-px edge strips, their centres, and the 12 px outside them (the "
        "chart's frame), relative to the mean truth (real: of the chart; simulated: of the "
        "image).",
        [
            "variant",
            "real s",
            "real MRAE",
            "real RMSE",
            "real edge R/G/B",
            "real spectral RMSE (chart)",
            "real spectral strips/centres/surround",
            "sim s",
            "sim RMSE",
            "sim MRAE",
            "sim edge R/G/B",
            "sim spectral strips/centres/surround",
        ],
        rows,
    )


def patch_cost(records: Sequence[dict]) -> dict[str, float | int]:
    """Per-patch iterations and the cost of Φ, from a reconstruction's ``patch_records``.

    Patches solved with Φ and those solved without it (no model, negligible dispersion or a
    flat patch) are summarised apart: their counts, the Φ samples (wavelengths) of the
    former, ADMM iterations, projected-Newton rounds and CG iterations per solve, and the
    median time per patch and to build its image formation (ms).
    """

    def median(values: list[float]) -> float:
        return float(np.median(values)) if values else float("nan")

    def most(values: list[float]) -> float:
        return float(np.max(values)) if values else float("nan")

    with_phi = [r for r in records if r["phi"] == "used"]
    without = [r for r in records if r["phi"] != "used"]
    summary: dict[str, float | int] = {
        "patches": len(records),
        "phi_patches": len(with_phi),
        "exact": int(sum(bool(r["exact"]) for r in records)),
        "samples_median": median([r["samples"] for r in with_phi]),
        "samples_max": most([r["samples"] for r in with_phi]),
    }
    for tag, group in (("phi", with_phi), ("plain", without)):
        summary |= {
            f"{tag}_iterations_median": median([r["iterations"] for r in group]),
            f"{tag}_iterations_max": most([r["iterations"] for r in group]),
            f"{tag}_rounds_median": median([r["polish_rounds"] for r in group]),
            f"{tag}_cg_mean": median([r["cg_mean"] for r in group]),
            f"{tag}_ms_median": 1e3 * median([r["seconds"] for r in group]),
            f"{tag}_formation_ms_median": 1e3 * median([r["formation_seconds"] for r in group]),
        }
    return summary


def patch_cost_table(real: list[Measurement], simulated: list[Measurement]) -> Table:
    """Per-patch iterations and Φ cost of each variant, real and simulated side by side."""

    def number(value: float, digits: int = 0) -> str:
        return "—" if not np.isfinite(value) else f"{value:.{digits}f}"

    def pair(cost: dict, key: str, digits: int = 0) -> str:
        return f"{number(cost[f'phi_{key}'], digits)} / {number(cost[f'plain_{key}'], digits)}"

    by_variant = {m.extra["variant"]: m for m in simulated}
    rows = []
    for m in real:
        for kind, measurement in (("real", m), ("simulated", by_variant.get(m.extra["variant"]))):
            if measurement is None or "patch_cost" not in measurement.extra:
                continue
            cost = measurement.extra["patch_cost"]
            rows.append(
                [
                    m.extra["variant"],
                    kind,
                    f"{cost['phi_patches']} / {cost['patches'] - cost['phi_patches']}",
                    f"{number(cost['samples_median'])} ({number(cost['samples_max'])})",
                    f"{pair(cost, 'iterations_median')} (max {number(cost['phi_iterations_max'])})",
                    pair(cost, "rounds_median"),
                    pair(cost, "cg_mean", 1),
                    f"{cost['exact']}",
                    pair(cost, "ms_median"),
                    pair(cost, "formation_ms_median", 1),
                ]
            )
    return Table(
        "Per-patch cost with and without Φ, real and simulated. Each cell: patches solved "
        "with Φ / without it (no model, negligible dispersion, flat patch). Samples: Φ's "
        "wavelength samples per patch, median (max); iterations: ADMM iterations (0: solved "
        "directly by the active-set methods); rounds: projected-Newton or dual active-set "
        "rounds; CG: iterations per CG solve (mean, median over patches); times: median per "
        "patch, on one thread of the Dask pool.",
        [
            "variant",
            "data",
            "patches Φ / no Φ",
            "Φ samples",
            "ADMM iterations",
            "Newton rounds",
            "CG per solve",
            "exact",
            "ms per patch",
            "formation ms",
        ],
        rows,
    )
