"""Numerical stress of the HDR merge (issue 7): exposure brackets spanning nine decades,
all-saturated, all-dark and constant stacks, tiny and odd-sized frames, absurd input.

Frames come from a small explicit sensor model (:func:`bracket`: Poisson electrons, a
gain, Gaussian read noise, black level, clipping, rounding to DN), so every expected value
is known in closed form: the merge's output is the signal at the shortest exposure as a
fraction of the saturation range, ``irradiance · t_min · GAIN / (SATURATION − BLACK)``.
The HDR merge works in float32 by design (frames are integers); there is no float64
path to compare, so its float32 output is checked against the float64 closed form.
"""

from __future__ import annotations

import numpy as np
import pytest
from _stress import assert_finite
from hypothesis import given, settings
from hypothesis import strategies as st

from labkit.errors import DataError
from labkit.hdr import DarkFrame, ExposureInput, SensorLevels, merge_exposures

BLACK, SATURATION, GAIN, READ_NOISE = 64, 4095, 0.25, 2.0
LEVELS = SensorLevels(SATURATION, BLACK)
RANGE = SATURATION - BLACK
METHODS = ["thesis", "noise"]


def bracket(
    irradiance: np.ndarray,
    exposures_s: list[float],
    *,
    replicates: int = 4,
    darks: int = 4,
    noise: bool = True,
    seed: int = 0,
) -> tuple[list[ExposureInput], dict[float, DarkFrame]]:
    """Replicate and dark frames (uint16) of `irradiance` (e⁻/s) at each exposure.

    Parameters
    ----------
    irradiance : ndarray (rows, cols)
        Electrons per second per pixel.
    exposures_s : list of float
        Exposure times, s.
    replicates, darks : int
        Frames per exposure, and dark frames per exposure.
    noise : bool
        Poisson shot noise and Gaussian read noise; False: the noise-free counts.
    seed : int
        Seed of the noise.

    Returns
    -------
    (list of ExposureInput, dict of exposure → DarkFrame)
    """
    rng = np.random.default_rng(seed)

    def frame(electrons: np.ndarray) -> np.ndarray:
        if noise:
            electrons = rng.poisson(np.minimum(electrons, 1e12)).astype(np.float64)
        counts = BLACK + GAIN * electrons
        if noise:
            counts = counts + rng.normal(0.0, READ_NOISE, counts.shape)
        return np.clip(np.round(counts), 0, SATURATION).astype(np.uint16)

    inputs, dark_frames = [], {}
    for t in exposures_s:
        inputs.append(
            ExposureInput.from_arrays(t, [frame(irradiance * t) for _ in range(replicates)])
        )
        zero = np.zeros_like(irradiance)
        dark = ExposureInput.from_arrays(t, [frame(zero) for _ in range(darks)])
        dark_frames[t] = DarkFrame.from_frames(dark)
    return inputs, dark_frames


def merge(irradiance: np.ndarray, exposures_s: list[float], method: str, **options):
    """Merge a simulated bracket; every output checked finite."""
    inputs, darks = bracket(irradiance, exposures_s, **options)
    result = merge_exposures(inputs, darks, cfa="GBRG", levels=LEVELS, method=method)
    assert_finite(result.raw)
    if result.variance is not None:
        assert_finite(result.variance)
        assert np.all(result.variance > 0)
    return result


def expected(irradiance: np.ndarray, exposures_s: list[float]) -> np.ndarray:
    """The merge's known answer: signal at the shortest exposure / saturation range."""
    return irradiance * min(exposures_s) * GAIN / RANGE


def well_exposed(irradiance: np.ndarray, exposures_s: list[float]) -> np.ndarray:
    """Pixels between 5 % and 80 % of saturation at one exposure at least."""
    signal = irradiance[..., None] * np.asarray(exposures_s) * GAIN / RANGE
    return np.any((signal > 0.05) & (signal < 0.8), axis=-1)


def log_ramp(shape: tuple[int, int], low: float, high: float) -> np.ndarray:
    """Irradiance rising log-linearly from `low` to `high` e⁻/s along the columns."""
    return np.tile(np.logspace(np.log10(low), np.log10(high), shape[1]), (shape[0], 1))


# -- extreme exposures --------------------------------------------------------------------
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    ("exposures", "ramp"),
    [
        ([1e-6, 1e-3, 1.0, 1e3], (1e2, 1e7)),  # nine decades of exposure time
        ([1e-6, 1e-4, 1e-2, 1.0, 1e2, 1e4], (1e-2, 1e9)),  # ten, and eleven of light
        # twelve: the noise method's float32 squared weights underflowed here (NaN variance)
        ([1e-7, 1e-3, 10.0, 1e5], (1e-3, 1e12)),
    ],
    ids=["1us-1000s", "1us-1e4s", "100ns-1e5s"],
)
def test_brackets_spanning_many_decades_recover_the_irradiance(
    method: str, exposures: list[float], ramp: tuple[float, float]
) -> None:
    irradiance = log_ramp((24, 64), *ramp)
    result = merge(irradiance, exposures, method)
    good = well_exposed(irradiance, exposures)
    assert good.sum() > 0.25 * good.size
    relative = result.raw[good] / expected(irradiance, exposures)[good] - 1
    assert float(np.median(np.abs(relative))) < 0.02
    # the factors are the exposure-time ratios (the fits fall back to them or agree)
    for row in result.exposures:
        assert row.factor == pytest.approx(row.nominal, rel=0.02)


@pytest.mark.slow
@settings(deadline=None, max_examples=30, derandomize=True)
@given(
    shortest=st.floats(min_value=-7.0, max_value=0.0),
    step=st.floats(min_value=0.3, max_value=3.0),
    count=st.integers(min_value=2, max_value=7),
    method=st.sampled_from(METHODS),
)
def test_random_brackets_recover_the_irradiance(
    shortest: float, step: float, count: int, method: str
) -> None:
    """Any bracket from 1e-7 s, 2–7 exposures 2× to 1000× apart, over 11 decades of light."""
    exposures = [10.0 ** (shortest + k * step) for k in range(count)]
    if max(exposures) / min(exposures) > 1e15:
        with pytest.raises(DataError, match="exposure times span"):
            merge(log_ramp((4, 4), 1.0, 10.0), exposures, method)
        return
    # light that exposes well somewhere in the bracket, and beyond it on both sides
    low = 0.01 * RANGE / GAIN / max(exposures)
    high = 5.0 * RANGE / GAIN / min(exposures)
    irradiance = log_ramp((16, 48), low, high)
    try:
        result = merge(irradiance, exposures, method)
    except DataError as error:  # the noise model needs well-exposed replicates
        assert method == "noise" and "cannot estimate the sensor gain" in str(error)
        return
    good = well_exposed(irradiance, exposures)
    relative = result.raw[good] / expected(irradiance, exposures)[good] - 1
    assert float(np.median(np.abs(relative))) < 0.03


def test_absurd_exposure_span_is_refused() -> None:
    irradiance = np.full((8, 8), 1e3)
    inputs, darks = bracket(irradiance, [1e-20, 1e20], noise=False)
    with pytest.raises(DataError, match=r"exposure times span 1e-20 s … 1e\+20 s"):
        merge_exposures(inputs, darks, cfa="GBRG", levels=LEVELS)


# -- all-saturated, all-dark and constant stacks -------------------------------------------
def test_all_saturated_stack_is_all_lower_bounds() -> None:
    irradiance = np.full((16, 24), 1e9)
    result = merge(irradiance, [1e-3, 1e-2], "thesis")
    assert result.saturated_pixels == irradiance.size and result.dark_pixels == 0
    # the shortest exposure's clipped value: (saturation − dark) / range ≈ 1
    # (dark means of 4 frames: σ ≈ READ_NOISE / 2)
    np.testing.assert_allclose(result.raw, 1.0, atol=6 * READ_NOISE / 2 / RANGE)
    assert any("lower bounds" in w for w in result.warnings)


@pytest.mark.parametrize("case", ["saturated", "dark"])
def test_noise_method_without_usable_samples_says_why(case: str) -> None:
    irradiance = np.full((16, 24), 1e9 if case == "saturated" else 0.0)
    with pytest.raises(DataError, match="cannot estimate the sensor gain"):
        merge(irradiance, [1e-3, 1e-2], "noise")


def test_all_dark_stack_is_zero_and_not_called_saturated() -> None:
    irradiance = np.zeros((16, 24))
    result = merge(irradiance, [1e-3, 1e-2], "thesis")
    # dark-subtracted noise: |mean| ≲ a few read-noise σ of the mean of 4 replicates
    assert np.abs(result.raw).max() < 5 * READ_NOISE / RANGE
    assert result.saturated_pixels == 0
    assert result.dark_pixels > 0
    assert any("no signal above the dark level" in n for n in result.notes)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("level", [2e4, 2e5, 2e6])
def test_constant_noisy_stack_gives_the_constant(method: str, level: float) -> None:
    exposures = [1e-3, 4e-3, 1.6e-2]
    irradiance = np.full((24, 32), level)
    try:
        result = merge(irradiance, exposures, method)
    except DataError as error:
        # a flat scene may not determine the noise model's gain: said so
        assert method == "noise"
        assert "signals barely vary (a flat scene)" in str(error)
        return
    want = float(expected(irradiance, exposures)[0, 0])
    assert float(np.mean(result.raw)) == pytest.approx(want, rel=0.01)


@pytest.mark.parametrize("level", [1e3, 2e5, 3e6])
def test_constant_noise_free_stack_is_exact(level: float) -> None:
    """No noise: the merge equals the closed form up to rounding to whole DN."""
    exposures = [1e-3, 4e-3, 1.6e-2]
    irradiance = np.full((10, 14), level)
    result = merge(irradiance, exposures, "thesis", noise=False)
    want = float(expected(irradiance, exposures)[0, 0])
    # rounding error ≤ 0.5 DN at the best-weighted exposure, ≥ 1 % of saturation there
    np.testing.assert_allclose(result.raw, want, rtol=0.5 / (0.01 * RANGE))


# -- tiny and odd-sized frames ----------------------------------------------------------------
@pytest.mark.parametrize("shape", [(1, 1), (2, 2), (3, 5), (7, 9), (1, 64)])
def test_tiny_and_odd_frames_merge_to_the_known_value(shape: tuple[int, int]) -> None:
    exposures = [1e-3, 4e-3]
    irradiance = np.full(shape, 2e5)
    result = merge(irradiance, exposures, "thesis", noise=False)
    assert result.raw.shape == shape
    np.testing.assert_allclose(result.raw, expected(irradiance, exposures), rtol=2e-3)


@pytest.mark.slow
@settings(deadline=None, max_examples=40, derandomize=True)
@given(
    rows=st.integers(min_value=1, max_value=19),
    cols=st.integers(min_value=1, max_value=19),
    level=st.floats(min_value=3.0, max_value=7.0),
    method=st.sampled_from(METHODS),
    seed=st.integers(min_value=0, max_value=2**16),
)
def test_small_frames_any_size_any_level(
    rows: int, cols: int, level: float, method: str, seed: int
) -> None:
    exposures = [1e-3, 4e-3, 1.6e-2]
    irradiance = np.full((rows, cols), 10.0**level)
    try:
        result = merge(irradiance, exposures, method, seed=seed)
    except DataError as error:  # too few samples for the noise model on a few pixels
        assert method == "noise" and "cannot estimate" in str(error)
        return
    want = float(expected(irradiance, exposures)[0, 0])
    signal_dn = 10.0**level * max(exposures) * GAIN
    if signal_dn < 0.8 * RANGE:  # well exposed at the longest exposure
        noise = np.sqrt(GAIN * signal_dn + READ_NOISE**2) / signal_dn  # relative, one frame
        assert abs(float(np.mean(result.raw)) / want - 1) < 6 * noise + 2e-3
    else:
        assert np.all(result.raw > 0)


# -- malformed input ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("frames", "message"),
    [
        ([np.ones((4, 4), np.float32)], r"expected a 2-D integer raw mosaic, got float32"),
        ([np.ones((4, 4, 3), np.uint16)], r"expected a 2-D integer raw mosaic"),
        ([np.ones((4, 4), np.uint16), np.ones((4, 5), np.uint16)], r"frames of different sizes"),
        ([], r"has no frames"),
    ],
    ids=["float", "3-D", "sizes", "empty"],
)
def test_malformed_frames_get_a_clear_error(frames: list[np.ndarray], message: str) -> None:
    exposure = ExposureInput.from_arrays(1e-3, frames)
    dark = {1e-3: DarkFrame.black_level(1e-3, BLACK)}
    with pytest.raises(DataError, match=message):
        merge_exposures([exposure], dark, cfa="GBRG", levels=LEVELS)


@pytest.mark.parametrize("times", [[0.0], [-1e-3], [float("nan")], [float("inf")]])
def test_bad_exposure_times_are_refused(times: list[float]) -> None:
    exposure = ExposureInput.from_arrays(times[0], [np.ones((4, 4), np.uint16)])
    with pytest.raises(DataError, match="positive seconds"):
        merge_exposures(
            [exposure], lambda t: DarkFrame.black_level(t, 0), cfa="GBRG", levels=LEVELS
        )
