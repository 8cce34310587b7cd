"""Auto-bracketing: optimal interval stabbing, rate estimation, and the simulator's truth."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from labkit.devices.camera import Bounds
from labkit.errors import DataError
from labkit.frame import Frame
from labkit.hdr.merge import FIT_MARGIN_PX
from labkit.hdr.scaling import MIN_PAIRS
from labkit.protocol.bracketing import (
    choose_exposures,
    estimate_rates,
    exposure_ladder,
    meter,
    run_auto_bracketing,
    usable_in,
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
    choice = choose_exposures(rate, ladder, margin=1.0, min_overlap=0)
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


def test_every_exposure_but_the_shortest_is_as_short_as_its_own_pixels_allow() -> None:
    """Greedy stabbing would expose the dim pixels at the top of their window (0.826 s for
    rate 1), overexposing the bright ones 80 times; the choice is the shortest exposure that
    still exposes every dim pixel (≥ 0.046 s for rate 0.5); the shortest exposure stays at
    the top of its pixels' window."""
    ladder = exposure_ladder(Bounds(1e-4, 10.0), steps_per_octave=4)
    rate = np.repeat([100.0, 1.0, 0.5], 50)
    choice = choose_exposures(rate, ladder, min_overlap=0)
    short, long = choice.exposures_s
    assert short == ladder[ladder <= 0.95 / 1.15 / 100][-1]
    assert long == ladder[ladder >= 0.02 * 1.15 / 0.5][0]
    assert choice.covered == 150 and not choice.left_out


def _shared(rate: np.ndarray, a: float, b: float) -> int:
    """Pixels the merge can fit the ratio of exposures a < b on (truth): properly exposed in
    both (window narrowed by the margin), no pixel within FIT_MARGIN_PX clipped at either."""
    from scipy import ndimage

    size = 2 * FIT_MARGIN_PX + 1
    ok = [
        _properly(rate, t, 0.02 * 1.15, 0.95 / 1.15)
        & ~ndimage.maximum_filter(rate * t > 0.95 / 1.15, size=size, mode="nearest")
        for t in (a, b)
    ]
    return int(np.count_nonzero(ok[0] & ok[1]))


def test_consecutive_exposures_are_linked_where_the_scene_allows() -> None:
    """Paper (rate 100) and ink (0.1) with a strip of every level between: the fewest
    exposures share no pixel the merge could fit their ratio on; one exposure between them,
    exposing the strip, links both with MIN_PAIRS pixels or more (known: 448 each)."""
    ladder = exposure_ladder(Bounds(1e-4, 10.0), steps_per_octave=4)
    strip = np.tile(np.logspace(-1, 2, 128), (16, 1))
    rate = np.vstack([np.full((24, 128), 100.0), strip, np.full((24, 128), 0.1)])
    plain = choose_exposures(rate, ladder, min_overlap=0)
    linked = choose_exposures(rate, ladder)
    assert [_shared(rate, a, b) for a, b in itertools.pairwise(plain.exposures_s)] == [0]
    assert len(linked.linking_s) == 1 and not linked.unlinked_s
    assert linked.exposures_s == sorted([*plain.exposures_s, *linked.linking_s])
    for a, b in itertools.pairwise(linked.exposures_s):
        assert _shared(rate, a, b) >= MIN_PAIRS, (a, b)
    assert linked.covered == plain.covered == rate.size


def test_two_light_levels_farther_apart_than_one_window_are_reported_unlinked() -> None:
    ladder = exposure_ladder(Bounds(1e-4, 10.0), steps_per_octave=4)
    rate = np.kron(np.array([[100.0, 0.1], [0.1, 100.0]]), np.ones((32, 32)))
    choice = choose_exposures(rate, ladder)
    short, long = choice.exposures_s
    assert choice.unlinked_s == [[short, long]] and not choice.linking_s
    assert "share fewer than" in choice.summary()


def test_a_handful_of_pixels_is_not_worth_an_exposure() -> None:
    ladder = exposure_ladder(Bounds(1e-4, 10.0), steps_per_octave=4)
    rate = np.full((100, 100), 1.0)
    rate[50, 50:55] = 1e-3  # five pixels that would need about 20 s
    rate[10, 10:15] = 0.01  # five that need their own, longer exposure
    choice = choose_exposures(rate, ladder)
    assert len(choice.exposures_s) == 1
    assert choice.left_out == 5 and choice.too_dark == 5
    assert "too few to be worth" in choice.summary()
    every = choose_exposures(rate, ladder, min_pixels=1)
    assert len(every.exposures_s) == 2 and every.left_out == 0


@pytest.mark.parametrize(("scene", "illumination"), [("disks", "600"), ("disks", "unfiltered")])
def test_checked_bracketing_chooses_exposures_the_merge_can_use(
    small_sim_rig: SimulatedRig, scene: str, illumination: str
) -> None:
    """The simulator's sensor blooms: around paper overexposed tens of times the dark disks
    read saturated. Every exposure the checked choice keeps has at least the pixels it was
    kept for usable in a new frame (the merge's rule), and reads them within 10 % of their
    noise-free truth; every kept exposure was checked."""
    rig = small_sim_rig.rig
    auto = rig.plan.auto
    model = small_sim_rig.sensor.model
    scale = model.gain_factor(0.0) / (model.saturation_dn() - model.black_level_dn)
    truth = small_sim_rig.irradiance(scene, illumination) * small_sim_rig.sensor.prnu_map
    least = min(MIN_PAIRS, truth.size // 1000)
    camera = SimCamera(small_sim_rig, seed=3, fast=True)
    camera.set_scene(scene)
    camera.set_illumination(illumination)
    bounds = camera.exposure_bounds()
    choice = run_auto_bracketing(camera, bounds=bounds, auto=auto)
    assert set(choice.exposures_s) <= set(choice.checked_s)
    for exposure in choice.exposures_s:
        frame = camera.grab(exposure, 1)[0]
        usable = usable_in(frame, low=auto.low_fraction, high=auto.high_fraction)
        assert np.count_nonzero(usable) >= least, exposure
        black, saturation = float(frame.extra["black_level"]), float(frame.extra["saturation_dn"])
        reading = (frame.image[usable] - black) / (saturation - black)
        expected = truth[usable] * scale * exposure
        assert np.median(np.abs(reading / expected - 1)) < 0.1, exposure
