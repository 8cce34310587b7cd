"""Thin-plate spline dispersion models (thesis §3.2.4, Algorithm 2): known answers from
planted fields, GCV against brute force, files, bad input and speed."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration.dispersion_model import DispersionModel
from calibration.keypoints import DispersionKeypoints
from calibration.spline import (
    GRID_HIGH,
    GRID_LOW,
    _decompose,
    _fit_field,
    fit_spline_model,
    gcv_grid_search,
)
from calibration.spline_field import SplineField
from labkit.errors import ConfigError, DataError
from labkit.sim.lens import Lens

ROWS, COLS = 512, 640
LENS = Lens((ROWS, COLS), max_shift_px=2.5)
WAVELENGTHS = np.arange(400.0, 701.0, 50.0)
BETWEEN = np.arange(400.0, 701.0, 5.0)
#: A 12 × 10 grid of "disk" keypoint positions over the 640 × 512 image.
GRID_X, GRID_Y = (
    g.ravel() for g in np.meshgrid(np.linspace(24, COLS - 25, 12), np.linspace(20, ROWS - 21, 10))
)


def truth(x, y, wavelength):
    """Planted dispersion relative to 600 nm, px."""
    dx, dy = LENS.displacement(x, y, wavelength)
    rx, ry = LENS.displacement(x, y, 600.0)
    return dx - rx, dy - ry


def spectral_keypoints(
    sigma: float, rng: np.random.Generator, *, x=GRID_X, y=GRID_Y, wavelengths=WAVELENGTHS
) -> DispersionKeypoints:
    x_all = np.tile(x, len(wavelengths))
    y_all = np.tile(y, len(wavelengths))
    w_all = np.repeat(wavelengths, len(x))
    dx, dy = truth(x_all, y_all, w_all)
    return DispersionKeypoints(
        x_all,
        y_all,
        dx + rng.normal(0, sigma, dx.size),
        dy + rng.normal(0, sigma, dy.size),
        reference=600.0,
        image_shape=(ROWS, COLS),
        wavelength_nm=w_all,
        meta={"test": "planted"},
    )


def query_points(model: DispersionModel, step: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions inside the model's calibrated hull."""
    qx, qy = np.meshgrid(np.arange(0, COLS, step, float), np.arange(0, ROWS, step, float))
    inside = model.region.contains(qx, qy)
    return qx[inside], qy[inside]


def spectral_rms(model: DispersionModel, wavelengths: np.ndarray) -> float:
    qx, qy = query_points(model)
    errors = []
    for w in wavelengths:
        dx, dy = model.displacement(qx, qy, w)
        tx, ty = truth(qx, qy, w)
        errors.append(np.concatenate([dx - tx, dy - ty]))
    return float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))


@pytest.fixture(scope="module")
def spectral_model() -> DispersionModel:
    """The planted spectral field, σ = 0.02 px keypoint noise."""
    return fit_spline_model(spectral_keypoints(0.02, np.random.default_rng(7)))


# -- 1. planted spectral field -----------------------------------------------------------
def test_planted_spectral_field_recovered(spectral_model: DispersionModel) -> None:
    model = spectral_model
    assert model.type == "spline" and model.variables == "xylambda"
    assert model.direction == "from_reference" and model.reference == 600.0
    assert model.image_shape == (ROWS, COLS)
    assert model.region.wavelength_nm == (400.0, 700.0)
    # measured: 0.013 px at the bands, 0.014 px every 5 nm (GCV: near-interpolation)
    assert spectral_rms(model, WAVELENGTHS) <= 0.03
    assert spectral_rms(model, BETWEEN) <= 0.03
    sel = model.selection
    assert sel["method"] == "gcv" and sel["kernel"] == "-r"
    assert sel["n_keypoints"] == sel["n_centres"] == 840
    assert sel["reduction"] == {"method": "none"}
    assert sel["search"][0]["iteration"] == 1 and len(sel["search"]) >= 13 + 2 * 2
    assert sel["gcv"] == min(s["gcv"] for s in sel["search"] if s["w"] == sel["smoothing"])
    assert 4 <= sel["effective_dof"] <= 840
    assert model.provenance["keypoints"] == "disks"
    assert model.provenance["bands"] == WAVELENGTHS.tolist()
    assert model.provenance["test"] == "planted"


# -- 2. GCV ------------------------------------------------------------------------------
def test_heavy_noise_gets_more_smoothing(spectral_model: DispersionModel) -> None:
    noisy = fit_spline_model(spectral_keypoints(0.3, np.random.default_rng(7)))
    light, heavy = spectral_model.selection, noisy.selection
    # measured: w 1.4e-15 → 2.6, effective dof 840 → 123, RMS 0.074 px
    assert heavy["smoothing"] > 100 * light["smoothing"]
    assert heavy["effective_dof"] < 0.5 * light["effective_dof"]
    # smoothing pays: far better than the noise itself (0.3 px)
    assert spectral_rms(noisy, WAVELENGTHS) < 0.12


@pytest.mark.parametrize("spectral", [True, False])
def test_affine_field_reproduced_exactly(spectral: bool) -> None:
    x = np.tile(GRID_X, 3)
    y = np.tile(GRID_Y, 3)

    def field(x, y, w):
        return (
            0.3 + 2e-3 * x - 1e-3 * y + 4e-3 * (w - 600),
            -0.2 + 5e-4 * x + 3e-3 * y - 2e-3 * (w - 600),
        )

    if spectral:
        w = np.repeat([450.0, 550.0, 650.0], GRID_X.size)
        dx, dy = field(x, y, w)
        kp = DispersionKeypoints(x, y, dx, dy, 600.0, (ROWS, COLS), wavelength_nm=w)
    else:
        w = np.full(x.size, 600.0)
        dx, dy = field(x, y, w)
        channel = np.repeat(["R", "B", "R"], GRID_X.size)
        kp = DispersionKeypoints(x, y, dx, dy, "G", (ROWS, COLS), channel=channel)
    model = fit_spline_model(kp)
    # everywhere, including far outside the keypoints and the wavelength range
    qx, qy = np.meshgrid(np.linspace(-300, 900, 31), np.linspace(-200, 700, 23))
    qw = np.linspace(350, 750, qx.size).reshape(qx.shape) if spectral else 600.0
    tx, ty = field(qx, qy, qw)
    for channel in [None] if spectral else ["R", "B"]:
        got = model.displacement(qx, qy, qw if spectral else None, channel=channel)
        assert np.max(np.abs(got[0] - tx)) < 1e-6
        assert np.max(np.abs(got[1] - ty)) < 1e-6


@pytest.mark.parametrize("dim", [2, 3])
def test_gcv_and_coefficients_match_the_full_system(dim: int) -> None:
    """Eigen-space GCV and coefficients equal brute force on the bordered system."""
    rng = np.random.default_rng(3)
    n = 40
    u = rng.normal(size=(n, dim))
    d = np.column_stack([np.sin(u[:, 0]) + u[:, 1] ** 2, np.cos(u[:, 1])])
    d = d + rng.normal(0, 0.05, d.shape)
    dec = _decompose(u, d, "test")
    kernel = dec.kernel
    basis = np.column_stack([np.ones(n), u])
    p = dim + 1
    r = np.linalg.norm(u[:, None] - u[None], axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(r > 0, r**2 * np.log(r), 0.0) if dim == 2 else -r
    np.testing.assert_allclose(kernel, phi, atol=1e-13)
    for w in (1e-6, 0.03, 1.0, 50.0):
        system = np.block([[kernel + w * np.eye(n), basis], [basis.T, np.zeros((p, p))]])
        # influence matrix: fitted values of unit data vectors
        solution = np.linalg.solve(system, np.vstack([np.eye(n), np.zeros((p, n))]))
        influence = kernel @ solution[:n] + basis @ solution[n:]
        residual = d - influence @ d
        trace = np.trace(np.eye(n) - influence)
        brute = n * np.sum(residual**2) / trace**2
        assert dec.gcv(w) == pytest.approx(brute, rel=1e-7)
        assert dec.trace_residual(w) == pytest.approx(trace, rel=1e-7)
    # coefficients at the GCV choice solve the bordered system
    fld, report = _fit_field(u, d, label="t", tolerance=1e-3, min_iterations=3, max_iterations=20)
    w = report["smoothing"]
    un, dn = fld.normaliser.inputs(u), fld.normaliser.outputs(d)
    dec_n = _decompose(un, dn, "t")
    basis_n = np.column_stack([np.ones(n), un])
    system = np.block([[dec_n.kernel + w * np.eye(n), basis_n], [basis_n.T, np.zeros((p, p))]])
    expected = np.linalg.solve(system, np.vstack([dn, np.zeros((p, 2))]))
    np.testing.assert_allclose(fld.weights, expected[:n], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(fld.affine, expected[n:], rtol=1e-6, atol=1e-9)


def test_grid_search_follows_algorithm_2() -> None:
    target = 10**2.3

    def objective(w: float) -> float:
        return (np.log10(w) - np.log10(target)) ** 2 + 1.0

    w, v, search = gcv_grid_search(objective, tolerance=1e-6, min_iterations=3)
    initial = np.logspace(np.log10(GRID_LOW), np.log10(GRID_HIGH), 15)[1:-1]
    np.testing.assert_allclose([s["w"] for s in search[:13]], initial, rtol=1e-12)
    assert all(s["iteration"] == 1 for s in search[:13])
    assert {s["iteration"] for s in search[13:]} <= set(range(2, 20))
    assert (len(search) - 13) % 2 == 0
    assert w == pytest.approx(target, rel=0.02)
    assert v == objective(w)
    assert all(GRID_LOW <= s["w"] <= GRID_HIGH for s in search)
    # a flat objective stops as soon as s ≥ min_iterations (s starts at 2)
    _, _, flat = gcv_grid_search(lambda w: 1.0, min_iterations=3)
    assert len(flat) == 13 + 2 * 2
    # an objective that keeps improving stops at max_iterations
    _, _, falling = gcv_grid_search(lambda w: -np.log(w), max_iterations=6)
    assert len(falling) == 13 + 2 * 4


# -- 3. colour channels ------------------------------------------------------------------
def channel_field(channel: str, x, y):
    lens = Lens((ROWS, COLS), max_shift_px=2.0, radial_profile="nonmonotonic")
    ux, uy = lens.radial_field(x, y)
    factor = 0.7 if channel == "R" else -1.0
    return factor * ux, factor * uy


def test_colour_channel_fields_recovered() -> None:
    rng = np.random.default_rng(11)
    x = np.tile(GRID_X, 2)
    y = np.tile(GRID_Y, 2)
    channel = np.repeat(["R", "B"], GRID_X.size)
    dx = np.empty(x.size)
    dy = np.empty(x.size)
    for c in ("R", "B"):
        pick = channel == c
        dx[pick], dy[pick] = channel_field(c, x[pick], y[pick])
    kp = DispersionKeypoints(
        x,
        y,
        dx + rng.normal(0, 0.01, x.size),
        dy + rng.normal(0, 0.01, x.size),
        reference="G",
        image_shape=(ROWS, COLS),
        channel=channel,
        source="registration",
    )
    model = fit_spline_model(kp)
    assert model.variables == "xy" and sorted(model.fields) == ["B", "R"]
    assert model.region.wavelength_nm is None
    assert model.selection["kernel"] == "r^2 log r"
    assert model.selection["n_keypoints"] == {"R": 120, "B": 120}
    assert model.selection["n_keypoints_total"] == model.selection["n_centres_total"] == 240
    assert set(model.selection["smoothing"]) == {"R", "B"}
    assert model.provenance["keypoints"] == "registration"
    qx, qy = query_points(model)
    for c in ("R", "B"):
        gx, gy = model.displacement(qx, qy, channel=c)
        tx, ty = channel_field(c, qx, qy)
        rms = np.sqrt(np.mean(np.concatenate([gx - tx, gy - ty]) ** 2))
        assert rms <= 0.02, (c, rms)  # measured: R 0.0097, B 0.0102 px
    zero = model.displacement(qx, qy, channel="G")
    assert not np.any(zero[0]) and not np.any(zero[1])
    loaded = DispersionModel.from_dict(yaml.safe_load(yaml.safe_dump(model.to_dict())))
    for c in ("R", "B"):
        np.testing.assert_array_equal(
            np.stack(loaded.displacement(qx, qy, channel=c)),
            np.stack(model.displacement(qx, qy, channel=c)),
        )


# -- 4. to_reference ---------------------------------------------------------------------
def test_to_reference_inverts_from_reference(spectral_model: DispersionModel) -> None:
    kp = spectral_keypoints(0.02, np.random.default_rng(7))
    backward = fit_spline_model(kp, direction="to_reference")
    assert backward.direction == "to_reference"
    qx, qy = query_points(spectral_model, step=16)
    inside = backward.region.contains(qx, qy)
    qx, qy = qx[inside], qy[inside]
    errors = []
    for w in BETWEEN[::4]:
        fx, fy = spectral_model.displacement(qx, qy, w)
        bx, by = backward.displacement(qx + fx, qy + fy, w)
        errors.append(np.concatenate([fx + bx, fy + by]))
    # measured: 0.0001 px RMS, 0.0006 px at worst (both fits see the same noisy keypoints)
    assert np.max(np.abs(np.concatenate(errors))) <= 0.02


# -- 5. reduction ------------------------------------------------------------------------
def test_many_keypoints_are_cell_averaged() -> None:
    rng = np.random.default_rng(5)
    n_per_band, bands = 1000, np.array([400.0, 475.0, 550.0, 625.0, 700.0])
    x = rng.uniform(10, COLS - 11, n_per_band)
    y = rng.uniform(10, ROWS - 11, n_per_band)
    kp = spectral_keypoints(0.02, rng, x=x, y=y, wavelengths=bands)
    assert len(kp) == 5000
    model = fit_spline_model(kp, max_points=1500)
    sel = model.selection
    assert sel["n_keypoints"] == 5000
    assert 1000 <= sel["n_centres"] <= 1500
    assert len(model.fields["spectral"].centres) == sel["n_centres"]
    assert sel["reduction"]["method"] == "cell_average"
    assert sel["reduction"]["centres"] == sel["n_centres"]
    assert sel["reduction"]["cell_px"] > 0
    # measured: 0.008 px at the bands, 0.019 px every 10 nm (bands 75 nm apart)
    assert spectral_rms(model, bands) <= 0.03
    assert spectral_rms(model, BETWEEN[::2]) <= 0.03


# -- 6. files ----------------------------------------------------------------------------
def test_save_load_round_trip(spectral_model: DispersionModel, tmp_path: Path) -> None:
    path = spectral_model.save(tmp_path / "model.yaml")
    loaded = DispersionModel.from_dict(yaml.safe_load(path.read_text()), source=str(path))
    field = loaded.fields["spectral"]
    assert isinstance(field, SplineField) and field.dimension == 3
    qx, qy = query_points(spectral_model, step=32)
    for w in (420.0, 600.0, 690.0):
        a = spectral_model.displacement(qx, qy, w)
        b = loaded.displacement(qx, qy, w)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
    assert loaded.selection["smoothing"] == spectral_model.selection["smoothing"]


def corrupt_missing(f: dict) -> None:
    del f["weights"]


def corrupt_centres(f: dict) -> None:
    f["centres"] = [row[:2] for row in f["centres"]]


def corrupt_weights(f: dict) -> None:
    f["weights"][3][1] = float("nan")


def corrupt_affine(f: dict) -> None:
    f["affine"] = f["affine"][:3]


def corrupt_dimension(f: dict) -> None:
    f["dimension"] = 4


def corrupt_normaliser(f: dict) -> None:
    del f["normaliser"]["wavelength"]


def corrupt_unknown(f: dict) -> None:
    f["colour"] = "blue"


@pytest.mark.parametrize(
    ("corrupt", "key"),
    [
        (corrupt_missing, "weights"),
        (corrupt_centres, "centres"),
        (corrupt_weights, "weights"),
        (corrupt_affine, "affine"),
        (corrupt_dimension, "dimension"),
        (corrupt_normaliser, "normaliser"),
        (corrupt_unknown, "colour"),
    ],
)
def test_corrupt_files_are_refused(
    spectral_model: DispersionModel, tmp_path: Path, corrupt, key: str
) -> None:
    path = spectral_model.save(tmp_path / "model.yaml")
    data = yaml.safe_load(path.read_text())
    corrupt(data["fields"]["spectral"])
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=rf"fields\.spectral.*{key}"):
        DispersionModel.from_dict(yaml.safe_load(path.read_text()), source=str(path))


# -- 7. bad input ------------------------------------------------------------------------
def test_one_band_is_refused() -> None:
    kp = spectral_keypoints(0.02, np.random.default_rng(1), wavelengths=np.array([450.0]))
    with pytest.raises(DataError, match="1 band"):
        fit_spline_model(kp)


def test_too_few_keypoints_are_refused() -> None:
    kp = DispersionKeypoints(
        [10.0, 200.0, 50.0],
        [10.0, 30.0, 300.0],
        [0.1, 0.2, 0.3],
        [0.0, 0.1, 0.2],
        reference="G",
        image_shape=(ROWS, COLS),
        channel=["R", "R", "R"],
    )
    with pytest.raises(DataError, match=r"channel R \(3 keypoints\).*at least 4"):
        fit_spline_model(kp)
    spectral = spectral_keypoints(
        0.0, np.random.default_rng(1), x=GRID_X[:2], y=GRID_Y[:2], wavelengths=WAVELENGTHS[:2]
    )
    with pytest.raises(DataError, match=r"4 keypoint.*at least 5"):
        fit_spline_model(spectral)


def test_collinear_keypoints_are_refused() -> None:
    x = np.linspace(0, 600, 20)
    kp = DispersionKeypoints(
        x, 0.5 * x, 0 * x, 0 * x, "G", (ROWS, COLS), channel=np.full(x.size, "B")
    )
    with pytest.raises(DataError, match="span no area"):
        fit_spline_model(kp)


def test_bad_options_are_refused(spectral_model: DispersionModel) -> None:
    kp = spectral_keypoints(0.02, np.random.default_rng(1), wavelengths=WAVELENGTHS[:2])
    with pytest.raises(ConfigError, match="direction"):
        fit_spline_model(kp, direction="sideways")
    with pytest.raises(ConfigError, match="max_points"):
        fit_spline_model(kp, max_points=2)
    with pytest.raises(DataError, match="shape"):
        spectral_model.fields["spectral"].evaluate(np.zeros((4, 2)))


@pytest.mark.parametrize("sigma", [0.0, 0.01])
def test_duplicate_keypoints_stay_finite(sigma: float) -> None:
    """Repeated measurements at the same positions: conditioning is bounded, no NaN.

    Noise-free repeats make GCV choose interpolation (w ≈ machine ε), whose system is
    singular (two identical rows); w is then raised to meet MAX_CONDITION.
    """
    rng = np.random.default_rng(2)
    x = np.tile(GRID_X, 3)
    y = np.tile(GRID_Y, 3)
    dx, dy = channel_field("R", x, y)
    kp = DispersionKeypoints(
        x,
        y,
        dx + rng.normal(0, sigma, x.size),
        dy + rng.normal(0, sigma, x.size),
        "G",
        (ROWS, COLS),
        channel=np.full(x.size, "R"),
    )
    model = fit_spline_model(kp)
    sel = model.selection
    assert sel["condition"]["R"] <= 1e10 * (1 + 1e-9)
    if sigma == 0:
        assert sel["gcv_smoothing"]["R"] < sel["smoothing"]["R"]
    qx, qy = query_points(model)
    gx, gy = model.displacement(qx, qy, channel="R")
    tx, ty = channel_field("R", qx, qy)
    assert np.all(np.isfinite(gx)) and np.all(np.isfinite(gy))
    # measured: 0.005 px (σ = 0), 0.007 px (σ = 0.01)
    assert np.sqrt(np.mean(np.concatenate([gx - tx, gy - ty]) ** 2)) < 0.02


# -- 8. float32 and chunking -------------------------------------------------------------
def test_float32_inputs_match_float64(spectral_model: DispersionModel) -> None:
    kp64 = spectral_keypoints(0.02, np.random.default_rng(7))
    kp32 = DispersionKeypoints(
        kp64.x.astype(np.float32),
        kp64.y.astype(np.float32),
        kp64.dx.astype(np.float32),
        kp64.dy.astype(np.float32),
        reference=600.0,
        image_shape=(ROWS, COLS),
        wavelength_nm=kp64.wavelength_nm.astype(np.float32),
    )
    model32 = fit_spline_model(kp32)
    qx, qy = query_points(spectral_model, step=16)
    for w in (450.0, 575.0):
        a = np.stack(spectral_model.displacement(qx, qy, w))
        b = np.stack(model32.displacement(qx.astype(np.float32), qy.astype(np.float32), w))
        np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-6 * np.abs(a).max())
    # evaluating float32 points directly gives the float64 result
    field = spectral_model.fields["spectral"]
    points = np.column_stack([qx, qy, np.full(qx.size, 512.5)]).astype(np.float32)
    np.testing.assert_allclose(
        field.evaluate(points), field.evaluate(points.astype(np.float64)), rtol=1e-12
    )


def test_blocked_evaluation_equals_pointwise(spectral_model: DispersionModel) -> None:
    field = spectral_model.fields["spectral"]
    rng = np.random.default_rng(4)
    points = np.column_stack(
        [rng.uniform(0, COLS, 3000), rng.uniform(0, ROWS, 3000), rng.uniform(380, 720, 3000)]
    )
    whole = field.evaluate(points)
    parts = np.vstack([field.evaluate(points[i : i + 7]) for i in range(0, 3000, 7)])
    np.testing.assert_allclose(whole, parts, rtol=0, atol=1e-12)
    assert field.evaluate(np.zeros((0, 3))).shape == (0, 2)
    # at the keypoints themselves the kernel's r = 0 is finite
    at_keys = field.evaluate(np.column_stack([GRID_X, GRID_Y, np.full(GRID_X.size, 500.0)]))
    assert np.all(np.isfinite(at_keys))


# -- speed -------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("spectral", [True, False])
def test_speed_with_3000_centres(spectral: bool) -> None:
    """Targets: fit ≲ 15 s, 10⁶ evaluations ≲ 10 s on 2 cores (asserted with 2× slack)."""
    rng = np.random.default_rng(9)
    n = 3000
    x = rng.uniform(0, COLS - 1, n)
    y = rng.uniform(0, ROWS - 1, n)
    if spectral:
        w = rng.choice(WAVELENGTHS, n)
        dx, dy = truth(x, y, w)
        kp = DispersionKeypoints(x, y, dx, dy, 600.0, (ROWS, COLS), wavelength_nm=w)
    else:
        dx, dy = channel_field("R", x, y)
        kp = DispersionKeypoints(x, y, dx, dy, "G", (ROWS, COLS), channel=np.full(n, "R"))
    start = time.perf_counter()
    model = fit_spline_model(kp)
    fit_s = time.perf_counter() - start
    assert model.selection["n_centres"] == (n if spectral else {"R": n})
    qx = rng.uniform(0, COLS, 1_000_000)
    qy = rng.uniform(0, ROWS, 1_000_000)
    start = time.perf_counter()
    if spectral:
        model.displacement(qx, qy, 550.0)
    else:
        model.displacement(qx, qy, channel="R")
    evaluate_s = time.perf_counter() - start
    print(f"spectral={spectral}: fit {fit_s:.1f} s, 1e6 evaluations {evaluate_s:.1f} s")
    assert fit_s < 30
    assert evaluate_s < 20
