"""The evaluation scoreboard: hand-built charts with planted fringes, gains and shifts."""

from __future__ import annotations

import numpy as np
import pytest
from _helpers import planted_dispersion_model
from scipy import ndimage

from labkit.cfa import mosaic
from labkit.errors import DataError
from reconstruction.evaluate.evaluation import baseline_images, evaluate

CFA = "GBRG"
SHAPE = (96, 96)


class UniformShift:
    """A constant displacement field (px)."""

    def __init__(self, dx: float, dy: float) -> None:
        self.d = (dx, dy)

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        return np.tile(self.d, (len(points), 1))

    def to_dict(self) -> dict:
        return {"kind": "uniform shift"}


def chart() -> tuple[np.ndarray, np.ndarray]:
    """Four 40-px patches of distinct colours on grey; (rgb, labels)."""
    rgb = np.full((*SHAPE, 3), 0.2)
    labels = np.zeros(SHAPE, dtype=np.int32)
    colours = [(0.8, 0.3, 0.1), (0.1, 0.6, 0.2), (0.2, 0.3, 0.9), (0.7, 0.7, 0.7)]
    for k, colour in enumerate(colours):
        r, c = divmod(k, 2)
        rows, cols = slice(6 + 46 * r, 46 + 46 * r), slice(6 + 46 * c, 46 + 46 * c)
        rgb[rows, cols] = colour
        labels[rows, cols] = k + 1
    return rgb, labels


def test_truth_scores_zero_and_a_planted_fringe_shows_in_its_channel_only() -> None:
    """The true image: edge and colour RMSE ≤ 1e-12 although the truth is in other units
    (×3, registered away). Red moved 2 px: its edge RMSE rises to > 0.05 of the raw mean;
    Green and Blue stay ≤ 1e-12; patch centres (deeper than 12 px) stay clean."""
    rgb, labels = chart()
    raw = mosaic(rgb, CFA)
    fringed = rgb.copy()
    fringed[..., 0] = np.roll(rgb[..., 0], 2, axis=1)
    result = evaluate(
        raw,
        {"truth": rgb, "red moved": fringed},
        cfa=CFA,
        labels=labels,
        truth_colour=3 * rgb,
        seconds={"truth": 0.5},
    )
    assert result.normalisation == pytest.approx(raw.mean())
    truth, moved = result.scores["truth"], result.scores["red moved"]
    assert max(truth.residual.edge.rmse) < 1e-12 and max(truth.colour.rmse) < 1e-12
    assert moved.residual.edge.rmse[0] > 0.05
    assert max(moved.residual.edge.rmse[1:]) < 1e-12
    assert max(moved.residual.centre.rmse) < 1e-12
    assert truth.seconds == 0.5 and moved.seconds is None
    header, rows = result.table()
    assert header == ["method", "time (s)", "edge RMSE R/G/B", "centre RMSE R/G/B",
                      "colour RMSE R/G/B"]  # fmt: skip
    assert rows[0][:2] == ["truth", "0.5"] and rows[1][1] == "—"
    assert (
        result.as_dict()["methods"]["red moved"]["residual_aberration"]["edge"]["rmse"]["R"] > 0.05
    )


def test_spectral_estimates_are_registered_per_band() -> None:
    """A spectral estimate equal to the truth × (2, 3, 5) per band: RMSE ≤ 1e-12, GOF 1;
    with 10 % noise the RMSE rises above 0.01. Without a chart, no residual is reported."""
    rgb, _ = chart()
    raw = mosaic(rgb, CFA)
    wavelengths = np.array([450.0, 550.0, 650.0])
    rng = np.random.default_rng(3)

    def truth(bands: np.ndarray) -> np.ndarray:
        np.testing.assert_array_equal(bands, wavelengths)
        return rgb[..., ::-1] * (1 + bands / 1000)

    exact = truth(wavelengths) * [2.0, 3.0, 5.0]
    noisy = exact * (1 + 0.1 * rng.standard_normal(exact.shape))
    result = evaluate(
        raw,
        {"exact": rgb},
        cfa=CFA,
        spectral={"exact": (exact, wavelengths), "noisy": (noisy, wavelengths)},
        truth_spectral=truth,
    )
    exact_score, noisy_score = result.scores["exact"], result.scores["noisy"]
    assert exact_score.residual is None and exact_score.colour is None
    assert exact_score.spectral.rmse_global < 1e-12
    assert exact_score.spectral.gof == pytest.approx(1.0, abs=1e-12)
    assert noisy_score.spectral.rmse_global > 0.01
    header, rows = result.table()
    assert header[-3:] == ["spectral RMSE", "MRAE", "GOF"] and rows[1][0] == "noisy"


def test_baselines_with_a_colour_model_add_warped_variants() -> None:
    """A chart blurred by σ = 1.5 px with Red and Blue planted 1.5 px off Green. The blur
    itself is an edge error (the true image scores R/G/B 0.144/0.120/0.159); measured
    bilinear R/B 0.201/0.216 → 0.154/0.173 after warping, Green untouched."""
    rgb, labels = chart()
    rgb = ndimage.gaussian_filter(rgb, (1.5, 1.5, 0))
    shifted = rgb.copy()
    shifted[..., 0] = ndimage.shift(rgb[..., 0], (0, 1.5), mode="nearest")
    shifted[..., 2] = ndimage.shift(rgb[..., 2], (-1.5, 0), mode="nearest")
    model = planted_dispersion_model(
        {"R": UniformShift(1.5, 0.0), "B": UniformShift(0.0, -1.5)},
        shape=SHAPE,
        direction="from_reference",
    )
    images, seconds = baseline_images(
        mosaic(shifted, CFA), cfa=CFA, methods=["bilinear"], colour_dispersion=model
    )
    assert list(images) == ["bilinear", "bilinear + warp"] and set(seconds) == set(images)
    np.testing.assert_array_equal(images["bilinear"][..., 1], images["bilinear + warp"][..., 1])
    result = evaluate(mosaic(rgb, CFA), {**images, "truth": rgb}, cfa=CFA, labels=labels)
    floor = result.scores["truth"].residual.edge.rmse
    plain = result.scores["bilinear"].residual.edge.rmse
    warped = result.scores["bilinear + warp"].residual.edge.rmse
    for channel in (0, 2):
        assert plain[channel] > 1.3 * floor[channel]
        assert warped[channel] < 1.12 * floor[channel]


def test_bad_inputs_are_refused_with_clear_errors() -> None:
    rgb, labels = chart()
    raw = mosaic(rgb, CFA)
    with pytest.raises(DataError, match="unknown baseline"):
        baseline_images(raw, cfa=CFA, methods=["nearest"])
    with pytest.raises(DataError, match=r"small: expected an image of 96×96×3"):
        evaluate(raw, {"small": rgb[:50]}, cfa=CFA, labels=labels)
    bad = rgb.copy()
    bad[3, 3, 1] = np.nan
    with pytest.raises(DataError, match="bad: 1 NaN/Inf"):
        evaluate(raw, {"bad": bad}, cfa=CFA, labels=labels)
    with pytest.raises(DataError, match="need truth_spectral"):
        evaluate(raw, {}, cfa=CFA, spectral={"x": (rgb, np.arange(3.0))})
    with pytest.raises(DataError, match="no signal"):
        evaluate(np.zeros(SHAPE), {}, cfa=CFA)
