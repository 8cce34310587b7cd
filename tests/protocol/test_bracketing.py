"""Auto-bracketing: optimal interval stabbing, rate estimation, and the simulator's truth."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from labkit.devices.camera import Bounds
from labkit.errors import DataError
from labkit.frame import Frame
from labkit.protocol.bracketing import (
    choose_exposures,
    estimate_rates,
    exposure_ladder,
    meter,
)
from labkit.sim import SimCamera, SimulatedRig


def _properly(rate: np.ndarray, t: float, low: float = 0.02, high: float = 0.95) -> np.ndarray:
    return (rate * t >= low) & (rate * t <= high)


def test_ladder_is_geometric_inside_bounds() -> None:
    ladder = exposure_ladder(Bounds(1e-5, 32.0, 1e-6), maximum_s=4.0, steps_per_octave=4)
    assert ladder[-1] == pytest.approx(4.0)
    assert ladder[0] >= 1e-5 and np.all(np.diff(ladder) > 0)
    ratios = ladder[-20:][1:] / ladder[-20:][:-1]
    np.testing.assert_allclose(ratios, 2**0.25, rtol=1e-3)
    np.testing.assert_allclose(np.round(ladder / 1e-6), ladder / 1e-6, atol=1e-6)  # quantised
    with pytest.raises(DataError, match="max_exposure_s"):
        exposure_ladder(Bounds(1e-3, 1.0), maximum_s=1e-4)


def test_two_clusters_need_two_exposures() -> None:
    ladder = exposure_ladder(Bounds(1e-5, 10.0), steps_per_octave=4)
    rate = np.concatenate([np.full(50, 100.0), np.full(50, 0.1)])  # fraction of range per s
    choice = choose_exposures(rate, ladder)
    assert len(choice.exposures_s) == 2
    short, long = choice.exposures_s
    assert _properly(rate[:50], short).all() and _properly(rate[50:], long).all()
    assert choice.covered == 100 and choice.too_dark == choice.too_bright == 0


def test_unreachable_pixels_are_reported_not_chased() -> None:
    ladder = exposure_ladder(Bounds(1e-3, 1.0), steps_per_octave=2)
    rate = np.array([1.0, 1e-6, 1e6, 0.0])  # fine, too dark, too bright, black
    choice = choose_exposures(rate, ladder)
    assert len(choice.exposures_s) == 1
    assert (choice.too_dark, choice.too_bright, choice.covered) == (2, 1, 1)


@pytest.mark.parametrize("seed", range(6))
def test_greedy_choice_is_minimal_and_every_exposure_adds_pixels(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ladder = exposure_ladder(Bounds(1e-3, 2.0), steps_per_octave=1)  # 11 steps
    rate = 10.0 ** rng.uniform(-0.5, 2.5, size=40)
    choice = choose_exposures(rate, ladder, margin=1.0)
    chosen = choice.exposures_s
    covered = np.zeros(rate.size, bool)
    for t in chosen:
        covered |= _properly(rate, t)
    reachable = np.any([_properly(rate, t) for t in ladder], axis=0)
    assert np.array_equal(covered, reachable)
    for t in chosen:  # dropping any exposure loses some pixel
        others = np.any([_properly(rate, u) for u in chosen if u != t] or [covered & False], axis=0)
        assert np.any(covered & ~others)
    for k in range(1, len(chosen)):  # no smaller subset of the ladder covers the same pixels
        for subset in itertools.combinations(ladder, k):
            assert not np.array_equal(np.any([_properly(rate, t) for t in subset], axis=0), covered)


def _frame(image: np.ndarray, exposure_s: float) -> Frame:
    return Frame(image.astype(np.uint16), 1, exposure_s, exposure_s, 0.0, "BayerGB12", 0, 0.0,
                 extra={"black_level": 100.0, "saturation_dn": 4100.0})  # fmt: skip


def test_rates_use_longest_unsaturated_frame_and_skip_bloomed_neighbours() -> None:
    truth = np.array([[10.0, 10.0, 10.0], [10.0, 400.0, 10.0], [10.0, 10.0, 10.0]])  # range/s
    short, long = 0.001, 0.05
    frames = [_frame(100 + 4000 * np.minimum(truth * t, 1.0), t) for t in (short, long)]
    rate = estimate_rates(frames)
    # centre saturates at 0.05 s (20 × range): it and its 4-neighbours use the short frame
    assert rate[1, 1] == pytest.approx(400.0, rel=0.01)
    assert rate[0, 0] == pytest.approx(10.0, rel=0.01)
    saturated_always = estimate_rates([frames[1]])
    assert saturated_always[1, 1] < 0  # only a lower bound is known


def test_auto_bracketing_exposes_every_reachable_pixel_of_the_simulator(
    small_sim_rig: SimulatedRig,
) -> None:
    """Ground truth: noise-free signal of every pixel at the chosen exposures."""
    rig = small_sim_rig.rig
    auto = rig.plan.auto
    camera = SimCamera(small_sim_rig, seed=3)
    auto_frames = fixed_frames = 0
    for scene, illumination in [("colorchecker", "unfiltered"), ("colorchecker", "450"),
                                ("disks", "600"), ("colorchecker", "700")]:  # fmt: skip
        camera.set_scene(scene)
        camera.set_illumination(illumination)
        bounds = camera.exposure_bounds()
        frames = meter(camera, bounds=bounds, maximum_s=auto.max_exposure_s)
        ladder = exposure_ladder(bounds, maximum_s=auto.max_exposure_s)
        choice = choose_exposures(estimate_rates(frames), ladder, margin=auto.margin)

        def proper(times: list[float], scene: str = scene, light: str = illumination):
            fractions = (small_sim_rig.exposure_fraction(scene, light, t) for t in times)
            return np.any([_properly(f, 1.0) for f in fractions], axis=0)

        exposed, reachable = proper(choice.exposures_s), proper(list(ladder))
        assert np.count_nonzero(reachable & ~exposed) == 0, (scene, illumination)
        replicates = rig.replicates_for(illumination)
        auto_frames += len(choice.exposures_s) * replicates
        fixed_frames += len(rig.exposures_for(illumination)) * replicates
    assert auto_frames < fixed_frames
