"""Images without usable light are named and refused where they enter."""

from __future__ import annotations

import numpy as np
import pytest

from labkit.errors import DataError
from labkit.io.light import check_light, light_problem


@pytest.fixture
def scene() -> np.ndarray:
    """A lit scene with dark-subtracted noise: some values below zero, most well above."""
    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[0:64, 0:96]
    return 0.3 + 0.2 * np.sin(xx / 7) * np.cos(yy / 5) + 0.01 * rng.standard_normal((64, 96))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_lit_scene_passes_in_either_precision(scene, dtype):
    assert light_problem(scene.astype(dtype)) is None
    assert light_problem(np.minimum(scene * 3, 1.0)) is None  # partly saturated: usable
    assert light_problem(np.round(scene * 4095).astype(np.uint16)) is None
    assert light_problem(np.full_like(scene, 0.5)) is None  # flat but unsaturated: a flat field


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda x: np.where(np.arange(x.size).reshape(x.shape) == 100, np.nan, x), "1 NaN/Inf"),
        (lambda x: np.where(np.arange(x.size).reshape(x.shape) == 5, np.inf, x), r"\(0, 5\)"),
        (lambda x: np.zeros_like(x), "holds no light"),
        (lambda x: -x, "holds no light"),
        (lambda x: x - 0.36, "negative values outweigh"),
        (lambda x: np.ones_like(x), r"100.0% of its pixels are saturated \(≥ 1\)"),
        (lambda x: np.minimum(x * 1000, 1.0), "saturated"),
        (lambda x: np.full(x.shape, 65535, np.uint16), r"saturated \(≥ 6.554e\+04\)"),
        (lambda x: x[:0], "empty"),
    ],
)
def test_unusable_images_are_named(scene, damage, match):
    with pytest.raises(DataError, match=rf"frame 7: .*{match}"):
        check_light(damage(scene), name="frame 7")
