"""Scores of a reconstruction of a labelled chart (:mod:`reconstruction.evaluate.chart_scores`),
against known answers."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from labkit.errors import DataError
from labkit.spectra import colorchecker_reflectances
from reconstruction.evaluate.chart_scores import ChartScorer, patch_centres, patch_spectral_errors


def test_patch_centres_are_the_inner_half_of_each_label() -> None:
    labels = np.zeros((120, 180), dtype=np.int32)
    for k in range(24):
        row, col = divmod(k, 6)
        labels[row * 30 + 5 : row * 30 + 25, col * 30 + 5 : col * 30 + 25] = k + 1
    centres = patch_centres(labels)
    assert len(centres) == 24
    # a 20×20 square: the largest distance to the edge is 10 px; the inner half keeps ≥ 5
    assert all(mask.sum() == 12 * 12 for mask in centres)
    assert (
        centres[7][40:50, 40:50].all()
        and not centres[7][36, 36]
        and not centres[6].any(where=labels != 7)
    )
    labels[labels == 13] = 0
    with pytest.raises(DataError, match=r"patch\(es\) \[13\]"):
        patch_centres(labels)


def test_patch_spectral_errors_register_each_band() -> None:
    """A cube whose patches are the measured reflectances times any per-band scale scores 0;
    a 10 % bias on half of the patches scores about 0.05 MRAE."""
    reflectances = colorchecker_reflectances("measured")
    wavelengths = np.array([450.0, 500.0, 550.0, 600.0, 650.0])
    truth = reflectances.resample(wavelengths).values.T
    labels = np.repeat(np.repeat(np.arange(1, 25).reshape(4, 6), 10, axis=0), 10, axis=1)
    centres = patch_centres(labels)
    scale = np.array([3.0, 0.5, 7.0, 1.0, 0.02])
    cube = (truth * scale)[labels - 1]
    exact = patch_spectral_errors(cube, wavelengths, centres, reflectances)
    assert exact["mrae"] < 1e-9 and exact["rmse"] < 1e-9
    assert np.allclose(exact["estimate"], truth)
    biased = cube.copy()
    biased[labels <= 12] *= 1.1
    errors = patch_spectral_errors(biased, wavelengths, centres, reflectances)
    assert 0.03 < errors["mrae"] < 0.07


def _chart(wavelengths: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Labels of 24 patches 40 px square in a 50 px grid (wider than two edge strips),
    and a cube of the measured reflectances times `scale` per band on them (0 on the
    background)."""
    truth = colorchecker_reflectances("measured").resample(wavelengths).values.T
    labels = np.zeros((4 * 50 + 30, 6 * 50 + 30), dtype=np.int32)
    for k in range(24):
        row, col = divmod(k, 6)
        labels[row * 50 + 20 : row * 50 + 60, col * 50 + 20 : col * 50 + 60] = k + 1
    cube = np.where(labels[..., None] > 0, (truth * scale)[labels - 1], 0.0)
    return labels, cube


def test_a_reconstruction_equal_to_the_truth_scores_zero_and_a_bias_shows() -> None:
    """Patch centres and per-pixel errors of a result equal to the (scaled) truth are 0; a
    10 % bias on the upper half of the chart shows in both; the truth is made once, when
    a per-pixel error first needs it."""
    wavelengths = np.array([450.0, 500.0, 550.0, 600.0, 650.0])
    labels, cube = _chart(wavelengths, np.array([3.0, 0.5, 7.0, 1.0, 0.02]))
    made = []

    def truth() -> np.ndarray:
        made.append(1)
        return cube

    scorer = ChartScorer(
        labels, np.zeros(labels.shape), "GBRG", colorchecker_reflectances("measured"),
        truth=truth, truth_wavelengths_nm=wavelengths,
    )  # fmt: skip
    exact = SimpleNamespace(spectral=cube, wavelengths_nm=wavelengths)
    assert scorer.patch_errors(cube, wavelengths)["mrae"] < 1e-9 and not made
    pixels = scorer.pixel_errors(exact)
    assert max(pixels.values()) < 1e-9 and made == [1]
    biased = cube.copy()
    biased[: labels.shape[0] // 2] *= 1.1
    assert 0.02 < scorer.patch_errors(biased, wavelengths)["mrae"] < 0.08
    assert (
        scorer.pixel_errors(SimpleNamespace(spectral=biased, wavelengths_nm=wavelengths))["centres"]
        > 0.01
    )
    assert made == [1]


def test_per_pixel_errors_need_a_truth_at_the_reconstructions_bands() -> None:
    wavelengths = np.array([450.0, 550.0, 650.0])
    labels, cube = _chart(wavelengths, np.ones(3))
    reflectances = colorchecker_reflectances("measured")
    result = SimpleNamespace(spectral=cube, wavelengths_nm=np.array([460.0, 550.0, 650.0]))
    with pytest.raises(DataError, match=r"needs? a spectral truth"):
        ChartScorer(labels, cube[..., 0], "GBRG", reflectances).pixel_errors(result)
    scorer = ChartScorer(
        labels, cube[..., 0], "GBRG", reflectances, truth=cube, truth_wavelengths_nm=wavelengths
    )
    with pytest.raises(DataError, match=r"\[460.0, 550.0, 650.0\] nm are not among"):
        scorer.pixel_errors(result)
