"""Evaluation metrics (thesis §4.4.1–4.4.2, (4.3)–(4.14)) against hand-computed values."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labkit.errors import DataError
from reconstruction.evaluate import metrics
from reconstruction.evaluate.metrics import (
    RELATIVE_FLOOR,
    colour_errors,
    patch_weights,
    registration_scale,
    spectral_errors,
)

# Two pixels (1 row × 2 columns), two bands:
#   truth    [1, 2] [4, 1]
#   estimate [2, 2] [2, 1]      difference [-1, 0] [2, 0]
TRUTH = np.array([[[1.0, 2.0], [4.0, 1.0]]])
ESTIMATE = np.array([[[2.0, 2.0], [2.0, 1.0]]])


def test_spectral_metrics_match_hand_computed_values() -> None:
    errors = spectral_errors(TRUTH, ESTIMATE, ssim=False)
    # (4.3): (|−1|/1 + 0/2 + |2|/4 + 0/1) / 4
    assert errors.mrae == pytest.approx(0.375, rel=1e-12)
    # (4.4): mean of √((1 + 0)/2) and √((4 + 0)/2)
    assert errors.rmse_pixel == pytest.approx((np.sqrt(0.5) + np.sqrt(2.0)) / 2, rel=1e-12)
    # (4.5): √((1 + 4) / 4)
    assert errors.rmse_global == pytest.approx(np.sqrt(5 / 4), rel=1e-12)
    # (4.6): pixel 0: (1·2 + 2·2) / (√5 √8); pixel 1: (4·2 + 1·1) / (√17 √5)
    gof = (6 / np.sqrt(40), 9 / np.sqrt(85))
    assert errors.gof == pytest.approx(np.mean(gof), rel=1e-12)
    np.testing.assert_allclose(errors.gof_map.compressed(), gof, rtol=1e-12)
    np.testing.assert_allclose(errors.rmse_map.compressed(), [np.sqrt(0.5), np.sqrt(2.0)])
    np.testing.assert_allclose(errors.mrae_map.compressed(), [0.5, 0.25])
    assert (errors.n_pixels, errors.n_bands) == (2, 2)
    assert errors.floor == pytest.approx(RELATIVE_FLOOR * 4.0)
    assert (errors.mrae_excluded, errors.gof_excluded) == (0, 0)
    assert errors.ssim is None and errors.scale is None
    # as_dict is plain JSON
    assert json.loads(json.dumps(errors.as_dict()))["mrae"] == pytest.approx(0.375)


def test_registration_scale_plain_and_patch_weighted() -> None:
    # (4.9): band 0: (1·2 + 4·2) / (2² + 2²) = 1.25; band 1: (2·2 + 1·1) / (2² + 1²) = 1
    np.testing.assert_allclose(registration_scale(TRUTH, ESTIMATE), [1.25, 1.0], rtol=1e-12)
    # (4.14) with w = (1, 3): band 0: (2 + 3·8) / (4 + 3·4) = 1.625; band 1: (4 + 3) / (4 + 3)
    weights = np.array([[1.0, 3.0]])
    np.testing.assert_allclose(
        registration_scale(TRUTH, ESTIMATE, weights=weights), [1.625, 1.0], rtol=1e-12
    )
    # point measurements (n, bands) work too, and a scaled estimate is registered exactly
    points = np.array([[1.0, 2.0], [3.0, 5.0], [2.0, 0.5]])
    np.testing.assert_allclose(
        registration_scale(points, points * [0.5, 4.0]), [2.0, 0.25], rtol=1e-12
    )


def test_register_removes_a_per_band_gain() -> None:
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.1, 1.0, (16, 16, 4))
    gains = np.array([0.5, 2.0, 1.0, 3.0])
    plain = spectral_errors(truth, truth * gains)
    assert plain.mrae > 0.5
    registered = spectral_errors(truth, truth * gains, register=True)
    assert registered.mrae < 1e-12 and registered.rmse_global < 1e-12
    assert registered.ssim == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(registered.scale, 1 / gains, rtol=1e-12)
    # the GOF is scale-free per pixel only for a common gain; both are 1 here
    assert spectral_errors(truth, 2.5 * truth).gof == pytest.approx(1.0, abs=1e-12)


def test_patch_weights_make_every_patch_count_equally() -> None:
    labels = np.array([[0, 1, 1], [2, 2, 2]])
    expected = np.array([[0.0, 0.5, 0.5], [1 / 3, 1 / 3, 1 / 3]])
    np.testing.assert_allclose(patch_weights(labels), expected, rtol=1e-12)
    with pytest.raises(DataError, match="integer"):
        patch_weights(labels.astype(float))
    with pytest.raises(DataError, match="≥ 0"):
        patch_weights(-labels)


def test_near_zero_denominators_are_excluded_and_counted() -> None:
    truth = np.array([[[0.0, 2.0], [4.0, 1.0], [0.0, 0.0]]])
    estimate = np.array([[[2.0, 2.0], [2.0, 1.0], [0.5, 0.5]]])
    errors = spectral_errors(truth, estimate, ssim=False)
    # the three zeros (floor 0.004) are left out: (0 + 0.5 + 0) / 3
    assert errors.mrae == pytest.approx(0.5 / 3, rel=1e-12)
    assert errors.mrae_excluded == 3
    # pixel 2 (all zero) has no GOF; pixel 0: 4 / (2 · √8), pixel 1: 9 / (√17 √5)
    assert errors.gof_excluded == 1
    assert errors.gof == pytest.approx((4 / (2 * np.sqrt(8)) + 9 / np.sqrt(85)) / 2, rel=1e-12)
    assert errors.gof_map.mask.tolist() == [[False, False, True]]
    assert errors.mrae_map.mask.tolist() == [[False, False, True]]
    # RMSE needs no denominator: every value counts, √((4 + 0 + 4 + 0 + 0.25 + 0.25) / 6)
    assert errors.rmse_global == pytest.approx(np.sqrt(8.5 / 6), rel=1e-12)
    for value in errors.as_dict().values():
        assert value is None or np.all(np.isfinite(value))
    # an explicit floor: |I| ≤ 1 also leaves out the 1
    assert spectral_errors(truth, estimate, floor=1.0, ssim=False).mrae_excluded == 4
    with pytest.raises(DataError, match="floor"):
        spectral_errors(truth, estimate, floor=10.0, ssim=False)
    with pytest.raises(DataError, match="floor"):
        spectral_errors(truth, estimate, floor=-1.0, ssim=False)


def test_a_zero_estimate_has_zero_goodness_of_fit() -> None:
    truth = np.array([[[1.0, 2.0], [4.0, 1.0]]])
    estimate = np.array([[[0.0, 0.0], [4.0, 1.0]]])
    errors = spectral_errors(truth, estimate, ssim=False)
    np.testing.assert_allclose(errors.gof_map.compressed(), [0.0, 1.0])
    assert errors.gof == pytest.approx(0.5)


def test_mask_selects_the_evaluated_pixels() -> None:
    truth = np.concatenate([TRUTH, np.full((1, 2, 2), 7.0)], axis=0)
    estimate = np.concatenate([ESTIMATE, np.zeros((1, 2, 2))], axis=0)
    mask = np.array([[True, True], [False, False]])
    errors = spectral_errors(truth, estimate, mask=mask, ssim=False)
    assert errors.mrae == pytest.approx(0.375) and errors.n_pixels == 2
    assert errors.rmse_map.mask.tolist() == [[False, False], [True, True]]
    with pytest.raises(DataError, match="no pixel"):
        spectral_errors(truth, estimate, mask=np.zeros((2, 2), bool), ssim=False)
    with pytest.raises(DataError, match="boolean image of shape"):
        spectral_errors(truth, estimate, mask=np.ones((3, 2), bool), ssim=False)


def test_ssim_of_constant_bands_matches_the_closed_form() -> None:
    """For constant images SSIM = (2 μx μy + C1) / (μx² + μy² + C1), C1 = (0.01 L)²."""
    truth = np.empty((16, 16, 2))
    truth[..., 0], truth[..., 1] = 0.5, 0.2
    estimate = np.full((16, 16, 2), 0.25)
    errors = spectral_errors(truth, estimate, data_range=1.0)
    c1 = 1e-4
    expected = [(2 * m * 0.25 + c1) / (m * m + 0.0625 + c1) for m in (0.5, 0.2)]
    np.testing.assert_allclose(errors.ssim_bands, expected, rtol=1e-9)
    assert errors.ssim == pytest.approx(np.mean(expected), rel=1e-9)


def test_ssim_is_one_for_identical_images_and_lower_for_noise() -> None:
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 1, (24, 32, 3))
    assert spectral_errors(truth, truth).ssim == pytest.approx(1.0, abs=1e-12)
    noisy = spectral_errors(truth, truth + 0.2 * rng.standard_normal(truth.shape))
    assert noisy.ssim < 0.8
    with pytest.raises(DataError, match="11 × 11"):
        spectral_errors(truth[:8], truth[:8])
    with pytest.raises(DataError, match="data_range"):
        spectral_errors(np.ones((16, 16, 2)), np.ones((16, 16, 2)))


def test_colour_metrics_match_hand_computed_values() -> None:
    # one row of two pixels, channels R, G, B
    truth = np.array([[[1.0, 2.0, 4.0], [2.0, 2.0, 0.0]]])
    estimate = np.array([[[1.5, 2.0, 3.0], [1.0, 2.0, 1.0]]])
    errors = colour_errors(truth, estimate, ssim=False)
    # R: (0.5/1 + 1/2) / 2; G: 0; B: the 0 is excluded → (1/4) / 1
    np.testing.assert_allclose(errors.mrae, [0.5, 0.0, 0.25], rtol=1e-12)
    # R: √((0.25 + 1) / 2); G: 0; B: √((1 + 1) / 2)
    np.testing.assert_allclose(errors.rmse, [np.sqrt(0.625), 0.0, 1.0], rtol=1e-12)
    assert errors.mrae_excluded == (0, 0, 1)
    assert errors.n_pixels == (2, 2, 2)
    as_dict = json.loads(json.dumps(errors.as_dict()))
    assert as_dict["rmse"]["B"] == pytest.approx(1.0) and as_dict["ssim"] is None
    # a per-channel mask (e.g. CFA sites): R and B at pixel 0 only, G at pixel 1 only
    mask = np.array([[[True, False, True], [False, True, False]]])
    sites = colour_errors(truth, estimate, mask=mask, ssim=False)
    assert sites.n_pixels == (1, 1, 1)
    np.testing.assert_allclose(sites.rmse, [0.5, 0.0, 1.0], rtol=1e-12)
    np.testing.assert_allclose(sites.mrae, [0.5, 0.0, 0.25], rtol=1e-12)
    with pytest.raises(DataError, match="B channel's MRAE is undefined"):
        colour_errors(truth, estimate, mask=~mask, ssim=False)  # B's only true value is 0


def test_colour_ssim_and_registration() -> None:
    rng = np.random.default_rng(1)
    truth = rng.uniform(0.2, 1.0, (20, 20, 3))
    gains = np.array([1.1, 1.0, 0.7])
    errors = colour_errors(truth, truth * gains, register=True)
    np.testing.assert_allclose(errors.scale, 1 / gains, rtol=1e-12)
    np.testing.assert_allclose(errors.ssim, 1.0, atol=1e-12)
    np.testing.assert_allclose(errors.rmse, 0.0, atol=1e-12)
    with pytest.raises(DataError, match="register=False"):
        colour_errors(truth, truth, weights=np.ones((20, 20)))


def test_invalid_inputs_are_refused_with_clear_errors() -> None:
    with pytest.raises(DataError, match=r"shape \(1, 2, 2\) but the estimate \(1, 2, 3\)"):
        spectral_errors(TRUTH, np.zeros((1, 2, 3)))
    with pytest.raises(DataError, match=r"\(rows, cols, bands\)"):
        spectral_errors(TRUTH[0], ESTIMATE[0])
    bad = ESTIMATE.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(DataError, match="estimate holds NaN"):
        spectral_errors(TRUTH, bad, ssim=False)
    with pytest.raises(DataError, match="spectral_errors for spectral"):
        colour_errors(TRUTH, ESTIMATE)
    with pytest.raises(DataError, match=r"band\(s\) \[1\]"):
        registration_scale(TRUTH, ESTIMATE * [1.0, 0.0])
    with pytest.raises(DataError, match="shape"):
        registration_scale(TRUTH, ESTIMATE, weights=np.ones(3))
    with pytest.raises(DataError, match="≥ 0"):
        registration_scale(TRUTH, ESTIMATE, weights=np.array([[1.0, -1.0]]))


def test_blockwise_evaluation_matches_one_block(monkeypatch: pytest.MonkeyPatch) -> None:
    """Large cubes are evaluated in blocks of pixels; blocks of 7 px (with a ragged last
    block and a mask) give the one-block answers, and float32 input is accepted."""
    rng = np.random.default_rng(5)
    truth = rng.uniform(0.1, 1.0, (13, 17, 5)).astype(np.float32)
    truth[2, 3] = 0.0  # excluded values and an excluded GOF pixel
    estimate = truth + rng.normal(0.0, 0.05, truth.shape).astype(np.float32)
    mask = rng.uniform(size=(13, 17)) < 0.8
    mask[2, 3] = True
    whole = spectral_errors(truth, estimate, mask=mask, register=True)
    monkeypatch.setattr(metrics, "BLOCK_PIXELS", 7)
    blocks = spectral_errors(truth, estimate, mask=mask, register=True)
    for key, value in whole.as_dict().items():
        np.testing.assert_allclose(blocks.as_dict()[key], value, rtol=1e-12, err_msg=key)
    np.testing.assert_allclose(blocks.gof_map.filled(-1), whole.gof_map.filled(-1), rtol=1e-12)
    assert whole.mrae_excluded == 5 and whole.gof_excluded == 1
    assert whole.n_pixels == mask.sum()
