"""Vignetting correction (thesis §3.2.2): planted cos⁴ fall-off recovered, masks, errors
and files."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration.vignetting import VignettingModel, fit_vignetting
from labkit.errors import ConfigError, DataError
from labkit.sim.lens import Lens

SHAPE = (480, 640)
LEVEL = 4000.0  # counts at the centre: Poisson noise ≈ 1.6 % per pixel


def planted(shape=SHAPE, *, vignetting=0.3, seed=0) -> tuple[np.ndarray, np.ndarray]:
    """(noisy raw mosaic, true relative illumination) for a uniform scene."""
    truth = Lens(shape, vignetting=vignetting).vignetting_map().astype(np.float64)
    rng = np.random.default_rng(seed)
    return rng.poisson(LEVEL * truth).astype(np.float32), truth


def disk_mask(shape=SHAPE, pitch=64, radius=20) -> np.ndarray:
    """True outside a grid of disks (the background of a disk calibration chart)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    dx = (xx % pitch) - pitch / 2
    dy = (yy % pitch) - pitch / 2
    return dx**2 + dy**2 > radius**2


def relative_rms(model: VignettingModel, truth: np.ndarray) -> float:
    """RMS of model / truth − 1 over the image, after matching means."""
    ratio = model.image() / truth
    return float(np.sqrt(np.mean((ratio / ratio.mean() - 1) ** 2)))


@pytest.fixture(scope="module")
def fitted() -> tuple[VignettingModel, np.ndarray]:
    raw, truth = planted()
    return fit_vignetting(raw, cfa="GBRG", mask=disk_mask(), rng=np.random.default_rng(1)), truth


# -- 9. planted fall-off ----------------------------------------------------------------
def test_planted_cos4_falloff_recovered(fitted) -> None:
    model, truth = fitted
    rms = relative_rms(model, truth)
    flat = model.correct(truth)
    nonuniformity = float(flat.std() / flat.mean())
    image = model.image()
    print(
        f"\ndisk-background mask: degree {model.degree}, RMS error {rms:.5f}, corrected "
        f"non-uniformity {nonuniformity:.5f} (planted {truth.std() / truth.mean():.4f}), "
        f"condition number {model.condition_number:.3g}, CV {model.selection['cv_error']}"
    )
    assert rms < 0.005
    assert nonuniformity < 0.005
    assert model.degree >= 2
    assert image.dtype == np.float32 and image.shape == SHAPE
    assert model.condition_number < 1e10
    # mean 1 over the fitted pixels (the G pixels of the background, here ~ the image)
    assert abs(float(image[disk_mask()].mean()) - 1.0) < 2e-3


def partial_masks() -> dict[str, np.ndarray]:
    """Masks covering part of the image."""
    masks = {"outside large disks (40 % of the image)": disk_mask(radius=28)}
    around = np.ones(SHAPE, dtype=bool)
    around[120:360, 160:480] = False
    masks["outside a central chart (75 %)"] = around
    left = np.zeros(SHAPE, dtype=bool)
    left[:, :512] = True
    masks["left 80 %"] = left
    return masks


def test_full_mask_and_partial_masks(fitted) -> None:
    raw, truth = planted(seed=3)
    full = fit_vignetting(raw, cfa="RGGB")
    report = [f"full: degree {full.degree}, RMS {relative_rms(full, truth):.5f}"]
    assert relative_rms(full, truth) < 0.005
    for name, mask in partial_masks().items():
        model = fit_vignetting(raw, cfa="RGGB", mask=mask)
        rms = relative_rms(model, truth)
        report.append(f"{name}: degree {model.degree}, RMS {rms:.5f}")
        assert rms < 0.01, name
    # extrapolating over 40 % of the image is beyond a polynomial (documented; ~3.5 %)
    left = np.zeros(SHAPE, dtype=bool)
    left[:, :384] = True
    extrapolated = fit_vignetting(raw, cfa="RGGB", mask=left)
    report.append(f"left 60 % (extrapolated): RMS {relative_rms(extrapolated, truth):.5f}")
    print("\n" + "; ".join(report))


def test_correct_divides_every_channel(fitted) -> None:
    model, _ = fitted
    raw = np.full(SHAPE, 1000, dtype=np.uint16)
    out = model.correct(raw)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, 1000 / model.image(), rtol=1e-6)
    rgb = np.ones((*SHAPE, 3))
    corrected = model.correct(rgb)
    assert corrected.dtype == np.float64
    for c in range(3):
        np.testing.assert_allclose(corrected[..., c], 1 / model.image(), rtol=1e-6)
    with pytest.raises(DataError, match=r"\(10, 10\) does not match the model's \(480, 640\)"):
        model.correct(np.ones((10, 10)))


def test_image_matches_direct_evaluation(fitted) -> None:
    model, _ = fitted
    rng = np.random.default_rng(4)
    r = rng.integers(0, SHAPE[0], 500)
    c = rng.integers(0, SHAPE[1], 500)
    direct = model.surface(c, r) / model.mean_intensity
    np.testing.assert_allclose(model.image()[r, c], direct, rtol=1e-6)


# -- 10. errors, flat images and files --------------------------------------------------
def test_mask_of_the_wrong_shape_names_the_shapes() -> None:
    raw, _ = planted()
    with pytest.raises(
        DataError, match=r"chart\.exr.*mask shape \(100, 100\).*image shape \(480, 640\)"
    ):
        fit_vignetting(raw, cfa="GBRG", mask=np.ones((100, 100), dtype=bool), name="chart.exr")
    with pytest.raises(DataError, match=r"boolean.*mask shape \(480, 640\) \(float64\)"):
        fit_vignetting(raw, cfa="GBRG", mask=np.ones(SHAPE))
    tiny = np.zeros(SHAPE, dtype=bool)
    tiny[:5, :5] = True
    with pytest.raises(
        DataError, match=r"only 13 G pixels.*mask shape \(480, 640\), image shape \(480, 640\)"
    ):
        fit_vignetting(raw, cfa="GBRG", mask=tiny)
    with pytest.raises(DataError, match="unknown CFA layout"):
        fit_vignetting(raw, cfa="XYZW")
    bad = raw.copy()
    bad[100, 101] = np.nan  # a G pixel of RGGB
    with pytest.raises(DataError, match="NaN"):
        fit_vignetting(bad, cfa="RGGB", mask=np.ones(SHAPE, dtype=bool))


def test_flat_image_gives_degree_zero() -> None:
    rng = np.random.default_rng(5)
    raw = rng.poisson(LEVEL, SHAPE).astype(np.float32)
    model = fit_vignetting(raw, cfa="BGGR", rng=np.random.default_rng(6))
    print(f"\nflat image: degree {model.degree}, CV {model.selection['cv_error']}")
    assert model.degree == 0
    np.testing.assert_allclose(model.image(), 1.0, atol=1e-6)


def test_non_positive_model_is_refused() -> None:
    """A steep ramp marked uniform on the left extrapolates below zero on the right."""
    xx = np.broadcast_to(np.arange(SHAPE[1], dtype=np.float64), SHAPE)
    raw = np.clip(3000 * (1 - xx / 300), 0, None).astype(np.float32)
    mask = np.zeros(SHAPE, dtype=bool)
    mask[:, :250] = True
    with pytest.raises(DataError, match="predicts non-positive intensity"):
        fit_vignetting(raw, cfa="GBRG", mask=mask, name="ramp")


def test_save_load_round_trip(fitted, tmp_path: Path) -> None:
    model, _ = fitted
    path = model.save(tmp_path / "vignetting.yaml")
    data = yaml.safe_load(path.read_text())
    assert data["kind"] == "labkit.vignetting_model" and data["format"] == 1
    loaded = VignettingModel.load(path)
    np.testing.assert_array_equal(loaded.image(), model.image())
    assert loaded.degree == model.degree and loaded.cfa == "GBRG" and loaded.channel == "G"
    assert loaded.selection == data["selection"]


@pytest.mark.parametrize(
    ("change", "key"),
    [
        (lambda d: d.pop("coefficients"), "missing key `coefficients`"),
        (lambda d: d["coefficients"].pop(), r"coefficients must be an array of shape 15"),
        (lambda d: d["coefficients"].__setitem__(2, float("nan")), "coefficients must be"),
        (lambda d: d.__setitem__("degree", -1), "degree must be a non-negative integer"),
        (lambda d: d["xy"].pop("matrix"), r"xy\.matrix"),
        (lambda d: d["intensity"].__setitem__("scale", 0.0), r"intensity\.scale must be positive"),
        (lambda d: d.__setitem__("cfa", "XXXX"), "cfa"),
        (lambda d: d.__setitem__("kind", "something"), "`kind`"),
        (lambda d: d.__setitem__("image_shape", [480]), "image_shape"),
    ],
)
def test_corrupt_file_names_the_key(fitted, tmp_path: Path, change, key) -> None:
    model, _ = fitted
    data = yaml.safe_load(yaml.safe_dump(model.to_dict()))
    if model.degree != 4:
        pytest.skip("the expected coefficient count assumes degree 4")
    change(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=key) as info:
        VignettingModel.load(path)
    assert str(path) in str(info.value)
    with pytest.raises(ConfigError, match="does not exist"):
        VignettingModel.load(tmp_path / "missing.yaml")


@pytest.mark.slow
def test_full_size_fit_is_fast() -> None:
    raw, truth = planted((2048, 2448))
    start = time.perf_counter()
    model = fit_vignetting(raw, cfa="GBRG")
    seconds = time.perf_counter() - start
    rms = relative_rms(model, truth)
    print(f"\n2448 × 2048 fit: {seconds:.2f} s, degree {model.degree}, RMS {rms:.5f}")
    assert seconds < 2.0
    assert relative_rms(model, truth) < 0.005
