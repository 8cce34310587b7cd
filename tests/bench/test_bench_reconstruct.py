"""`labkit bench reconstruct`: its simulated truth and error plumbing give known answers."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from labkit.bench.reconstruct_cases import edge_errors, errors, lens_model, simulated_case
from labkit.rig import default_rig_path


def test_lens_model_undoes_the_lens() -> None:
    """The analytic to_reference model is minus the lens' displacement (first order)."""
    case = simulated_case(default_rig_path(), (64, 80), "colorchecker")
    model = case["model"]
    from labkit.rig import load_rig
    from labkit.sim import SimulatedRig

    lens = SimulatedRig(load_rig(default_rig_path()), shape=(64, 80)).lens
    x, y = np.array([0.0, 79.0]), np.array([0.0, 63.0])
    for wavelength in (450.0, 650.0):
        ex, ey = model.displacement(x, y, wavelength)
        dx, dy = lens.relative_displacement(x, y, wavelength, reference_nm=600.0)
        np.testing.assert_allclose(np.hypot(ex + dx, ey + dy), 0.0, atol=0.02)
        assert np.all(np.hypot(dx, dy) > 0.2)
    assert lens_model(lens).direction == "to_reference"


def test_a_perfect_reconstruction_scores_zero_and_a_biased_one_does_not() -> None:
    case = simulated_case(default_rig_path(), (48, 64), "colorchecker", flat_fraction=0.5)
    bands = np.linspace(430.0, 650.0, 5)
    truth = case["truth"](bands)
    wall = np.isnan(truth[..., 0])
    assert 0.4 < wall.mean() < 0.6  # the grey wall has no spectral truth
    perfect = SimpleNamespace(
        wavelengths_nm=bands,
        spectral=np.nan_to_num(truth).astype(np.float32),
        raw_colour=case["colour"].astype(np.float32),
    )
    scores = errors(case, perfect)
    assert scores["spectral_rmse_rel"] < 1e-6 and scores["colour_rmse_G"] < 1e-6
    biased = SimpleNamespace(
        wavelengths_nm=bands,
        spectral=perfect.spectral * np.linspace(0.8, 1.2, 5),  # removed by registration
        raw_colour=perfect.raw_colour * 1.1,
    )
    scores = errors(case, biased)
    assert scores["spectral_rmse_rel"] < 1e-5
    assert abs(scores["colour_rmse_G"] - 0.1 * _mean_over_peak(case, 1)) < 0.02
    # the colour truth is the render: away from edges the raw differs by the planted noise
    # (measured 0.0025: on this 48×64 chart the lens blur leaves few pixels far from an edge)
    residual = case["raw"] - _mosaic_of(case)
    robust_std = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    assert abs(robust_std / np.max(case["colour"]) - 0.002) < 0.0007


def _mean_over_peak(case, channel: int) -> float:
    inner = case["colour"][8:-8, 8:-8]
    return float(np.sqrt(np.mean(inner[..., channel] ** 2)) / inner.max())


def _mosaic_of(case) -> np.ndarray:
    from labkit.cfa import mosaic

    return mosaic(case["colour"], case["cfa"])


def test_edge_errors_score_the_truth_near_zero_and_bilinear_demosaicing_high() -> None:
    """The ColorChecker cases report the §4.4.3 edge-strip RMSE: the aberration-free colour
    truth scores at the floor that the lens blur sets in the pixels next to each edge
    (measured R/G/B 0.0060/0.0099/0.0067; 0.0015 in green without blur), bilinear
    demosaicing of the dispersed raw image far above it (0.033 in green); charts too small
    for edge strips have none."""
    from reconstruction import baseline

    case = simulated_case(default_rig_path(), (344, 408), "colorchecker")
    truth = edge_errors(case, case["colour"])
    assert set(truth) == {"edge_rmse_R", "edge_rmse_G", "edge_rmse_B"}
    assert 0.003 < max(truth.values()) < 0.012
    bilinear = edge_errors(case, baseline(case["raw"], "bilinear", cfa=case["cfa"]))
    assert bilinear["edge_rmse_G"] > 2.5 * truth["edge_rmse_G"]
    assert "boxes" not in simulated_case(default_rig_path(), (64, 80), "colorchecker")


def test_strip_errors_score_the_truth_zero_and_a_blurred_estimate_in_the_strips() -> None:
    """The ColorChecker cases split the spectral error between the edge strips, the
    centres and the surround: the truth itself (any per-band exposure) scores zero in all;
    a 2-px blur raises the strips' and the surround's error far above the centres'
    (measured 0.078 and 0.185 against 0.0064)."""
    from types import SimpleNamespace

    from scipy import ndimage

    from labkit.bench.reconstruct_cases import strip_errors

    case = simulated_case(default_rig_path(), (344, 408), "colorchecker")
    bands = np.linspace(430.0, 650.0, 5)
    truth = np.nan_to_num(case["truth"](bands))
    exact = SimpleNamespace(wavelengths_nm=bands, spectral=truth * np.linspace(0.8, 1.2, 5))
    scores = strip_errors(case, exact)
    assert max(scores.values()) < 1e-6
    assert set(scores) == {f"spectral_rmse_{r}" for r in ("strips", "centres", "surround")}
    blurred = SimpleNamespace(
        wavelengths_nm=bands, spectral=ndimage.gaussian_filter(truth, (2.0, 2.0, 0.0))
    )
    scores = strip_errors(case, blurred)
    assert scores["spectral_rmse_strips"] > 5 * scores["spectral_rmse_centres"] > 0
    assert scores["spectral_rmse_surround"] > 5 * scores["spectral_rmse_centres"]
