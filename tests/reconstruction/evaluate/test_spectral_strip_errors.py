"""`spectral_strip_errors`: a chart's spectral RMSE split into edge strips, centres, surround."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from labkit.errors import DataError
from reconstruction import patch_regions, spectral_strip_errors

SHAPE = (60, 80)
BOXES = np.array([[5.0, 5.0, 35.0, 35.0], [42.0, 10.0, 75.0, 50.0]])
STRIP = 6


def _chart(bands: int = 4) -> np.ndarray:
    """Two flat patches with different spectra on a dark background."""
    regions = patch_regions(SHAPE, boxes=BOXES)
    spectra = np.array([[0.2, 0.5, 0.8, 0.4], [0.9, 0.3, 0.1, 0.6]])[:, :bands]
    truth = np.full((*SHAPE, bands), 0.05)
    for k, spectrum in zip(regions.patch_ids, spectra, strict=True):
        truth[regions.labels == k] = spectrum
    return truth


def _checkerboard() -> np.ndarray:
    """±1 per pixel: uncorrelated with the truth, so registration cannot absorb it."""
    rows, cols = np.indices(SHAPE)
    return np.where((rows + cols) % 2, 1.0, -1.0)[..., None]


def test_planted_errors_show_in_their_own_region_only() -> None:
    truth = _chart()
    regions = patch_regions(SHAPE, boxes=BOXES, strip_px=STRIP)
    outside = regions.labels == 0
    surround = outside & (ndimage.distance_transform_edt(outside) <= STRIP)
    in_strips, in_surround = 0.03, 0.01
    estimate = truth + _checkerboard() * (
        in_strips * regions.edge[..., None] + in_surround * surround[..., None]
    )
    gain = np.array([2.0, 0.5, 1.5, 1.0])  # a per-band exposure, which registration removes
    split = spectral_strip_errors(truth, estimate / gain, boxes=BOXES, strip_px=STRIP)
    level = truth.mean()
    assert split.strips == pytest.approx(in_strips / level, rel=0.05)
    assert split.surround == pytest.approx(in_surround / level, rel=0.05)
    assert split.centres < 0.05 * split.strips  # what registration leaves
    shares = np.array([regions.edge.mean(), surround.mean()])
    squares = np.array([split.strips, split.surround]) ** 2
    assert split.whole == pytest.approx(np.sqrt(shares @ squares), rel=0.05)
    assert np.allclose(split.scale, gain, rtol=0.02)


def test_exact_estimate_scores_zero_and_the_mask_leaves_out_bad_pixels() -> None:
    truth = _chart()
    estimate = truth * 3.0  # exposure only
    estimate[8:12, :] = np.nan  # rows across the first patch, which the mask leaves out
    keep = np.ones(SHAPE, bool)
    keep[8:12, :] = False
    split = spectral_strip_errors(truth, estimate, boxes=BOXES, mask=keep, strip_px=STRIP)
    assert max(split.strips, split.centres, split.surround, split.whole) < 1e-12
    assert np.allclose(split.scale, 1 / 3)
    with pytest.raises(DataError, match="NaN or Inf"):
        spectral_strip_errors(truth, estimate, boxes=BOXES, strip_px=STRIP)


def test_bad_inputs_are_refused_with_the_fix() -> None:
    truth = _chart()
    with pytest.raises(DataError, match="same shape"):
        spectral_strip_errors(truth, truth[..., :3], boxes=BOXES)
    with pytest.raises(DataError, match="mask has shape"):
        spectral_strip_errors(truth, truth, boxes=BOXES, mask=np.ones((3, 3), bool))
    with pytest.raises(DataError, match="widen the mask"):
        spectral_strip_errors(truth, truth, boxes=BOXES, mask=np.zeros(SHAPE, bool))
    with pytest.raises(DataError, match="not positive"):
        spectral_strip_errors(-truth, truth, boxes=BOXES)
