"""The natural-like scene (dead leaves): its statistics, its materials, and its place in
rigs and the bench's simulated cases."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage

from labkit.rig import SimSceneConfig
from labkit.sim import natural_scene
from labkit.spectra import colorchecker_reflectances

SHAPE = (172, 204)


def test_dead_leaves_cover_the_view_at_every_scale() -> None:
    """Every pixel is covered once (area fractions sum to 1), the same seed gives the same
    scene, and the leaves span scales: the largest connected leaf is over 100 times the
    median one, as the r⁻³ size density makes it (a single-scale texture would not)."""
    scene = natural_scene(SHAPE, seed=3)
    coverage = scene.coverage_image(SHAPE)
    np.testing.assert_allclose(coverage.sum(axis=2), 1.0, atol=1e-6)
    np.testing.assert_array_equal(scene.grid.labels, natural_scene(SHAPE, seed=3).grid.labels)
    assert not np.array_equal(scene.grid.labels, natural_scene(SHAPE, seed=4).grid.labels)
    labels = coverage.argmax(axis=2)
    sizes = []
    for material in np.unique(labels):
        regions, _ = scipy.ndimage.label(labels == material)
        sizes += list(np.bincount(regions.ravel())[1:])
    assert max(sizes) > 100 * np.median(sizes)


def test_leaves_are_smooth_mixtures_of_chart_reflectances() -> None:
    """Each material is a convex mixture of three ColorChecker reflectances: within the
    chart's range at every wavelength, and inside the chart's convex hull (non-negative
    least-squares weights summing to 1 reproduce it)."""
    scene = natural_scene(SHAPE, seed=0, materials=12)
    chart = colorchecker_reflectances("measured")
    values = scene.materials.values
    assert values.shape == (chart.values.shape[0], 12)
    assert np.all(values >= chart.values.min(axis=1, keepdims=True) - 1e-12)
    assert np.all(values <= chart.values.max(axis=1, keepdims=True) + 1e-12)
    from scipy.optimize import nnls

    for k in range(12):
        weights, residual = nnls(chart.values, values[:, k])
        assert residual < 1e-8 and weights.sum() == pytest.approx(1.0, abs=1e-6)
        assert np.count_nonzero(weights > 1e-9) <= 3


def test_a_rig_may_name_it_with_a_seed_only() -> None:
    """Like the textured scene it takes a seed and nothing else."""
    assert SimSceneConfig(type="natural", seed=5).options() == {"seed": 5}
    with pytest.raises(ValueError, match="does not take"):
        SimSceneConfig(type="natural", radius_px=3.0)
