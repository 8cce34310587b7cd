"""`spectral_strip_errors`: spectral RMSE of a patch chart split into edge strips and centres."""

from __future__ import annotations

import numpy as np
import pytest

from labkit.errors import DataError
from reconstruction import patch_regions, spectral_strip_errors

SHAPE = (60, 80)
BOXES = np.array([[5.0, 5.0, 35.0, 35.0], [42.0, 10.0, 75.0, 50.0]])


def _chart(bands: int = 4) -> np.ndarray:
    """Two flat patches with different spectra on a dark background."""
    regions = patch_regions(SHAPE, boxes=BOXES)
    spectra = np.array([[0.2, 0.5, 0.8, 0.4], [0.9, 0.3, 0.1, 0.6]])[:, :bands]
    truth = np.full((*SHAPE, bands), 0.05)
    for k, spectrum in zip(regions.patch_ids, spectra, strict=True):
        truth[regions.labels == k] = spectrum
    return truth


def test_a_planted_edge_error_shows_in_the_strips_only() -> None:
    truth = _chart()
    regions = patch_regions(SHAPE, boxes=BOXES, strip_px=6)
    inside = regions.edge | regions.centre
    error = 0.03
    estimate = truth.copy()
    # ±error in a checkerboard: uncorrelated with the truth, so the per-band registration
    # cannot absorb it
    rows, cols = np.indices(SHAPE)
    sign = np.where((rows + cols) % 2, 1.0, -1.0)
    estimate[regions.edge] += error * sign[regions.edge][:, None]
    # a per-band exposure factor, which the registration removes
    gain = np.array([2.0, 0.5, 1.5, 1.0])
    split = spectral_strip_errors(truth, estimate / gain, boxes=BOXES, strip_px=6)
    level = truth[inside].mean()
    # registration fitted over strips and centres leaves the centres nearly exact
    assert split.centre < 0.05 * split.edge
    assert split.edge == pytest.approx(error / level, rel=0.05)
    share = regions.edge.sum() / inside.sum()
    assert split.patches == pytest.approx(np.sqrt(share) * split.edge, rel=0.05)
    assert np.allclose(split.scale, gain, rtol=0.02)


def test_exact_estimate_scores_zero_and_the_mask_leaves_out_bad_pixels() -> None:
    truth = _chart()
    estimate = truth * 3.0  # exposure only
    estimate[8:12, :] = np.nan  # rows across the first patch, which the mask leaves out
    keep = np.ones(SHAPE, bool)
    keep[8:12, :] = False
    split = spectral_strip_errors(truth, estimate, boxes=BOXES, mask=keep, strip_px=6)
    assert split.edge < 1e-12 and split.centre < 1e-12
    assert np.allclose(split.scale, 1 / 3)
    with pytest.raises(DataError, match="NaN or Inf"):
        spectral_strip_errors(truth, estimate, boxes=BOXES, strip_px=6)


def test_bad_inputs_are_refused_with_the_fix() -> None:
    truth = _chart()
    with pytest.raises(DataError, match="same shape"):
        spectral_strip_errors(truth, truth[..., :3], boxes=BOXES)
    with pytest.raises(DataError, match="mask has shape"):
        spectral_strip_errors(truth, truth, boxes=BOXES, mask=np.ones((3, 3), bool))
    with pytest.raises(DataError, match="widen the mask"):
        spectral_strip_errors(truth, truth, boxes=BOXES, mask=np.zeros(SHAPE, bool))
