"""`reconstruction.reconstruct`: validation, the patch driver's skipping, weights, known answers."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
from _helpers import planted_dispersion_model
from _problems import RESPONSE, ConstantField, blobs, smooth_blobs, spectral_model

from labkit.cfa import mosaic
from labkit.errors import DataError, LabkitError
from labkit.spectra import camera_response
from reconstruction.model.image_formation import LatentSpace, build_formation
from reconstruction.model.problem import SUGGESTED_SMOOTHNESS
from reconstruction.reconstruct import DomainWarning, reconstruct

RESPONSE_RGB = camera_response(RESPONSE)
SHAPE = (40, 60)


def grey_raw(shape=SHAPE, colour=(0.3, 0.5, 0.2)) -> np.ndarray:
    return mosaic(np.broadcast_to(np.array(colour), (*shape, 3)).copy(), "GBRG")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"raw": np.ones((41, 60))}, "even"),
        ({"raw": np.where(np.eye(40, 60) > 0, np.nan, 1.0)}, "NaN"),
        (
            {"dispersion": spectral_model(ConstantField((0.1, 0.0)), shape=(20, 20))},
            "calibrated for",
        ),
        ({"bands": np.linspace(300, 600, 7)}, "not covered"),
        ({"prior": "TV3"}, "unknown prior"),
        ({"weights": "fixed:0.1,0.2"}, "1 term"),
        ({"weights": "auto:best"}, "criterion"),
        (
            {
                "dispersion": spectral_model(ConstantField((0.1, 0.0)), shape=SHAPE).__class__(
                    **{
                        **spectral_model(ConstantField((0.1, 0.0))).__dict__,
                        "direction": "from_reference",
                    }
                )
            },
            "^the dispersion model is a from_reference model, but correction model needs a "
            "to_reference one",
        ),
        ({"response": None}, "camera response"),
        ({"correction": "sideways"}, "unknown correction"),
        ({"correction": "warp"}, "needs a dispersion model"),
        ({"interpolation": "lanczos"}, "unknown interpolation"),
        ({"spectral_smoothness": -1e-3}, "spectral_smoothness is -0.001; expected a finite"),
        ({"latent": "colour", "spectral_smoothness": 1e-3}, "applies to latent spectral"),
        ({"rtol": 1.5}, r"rtol is 1.5; expected a number in \(0, 1\)"),
        ({"rtol": "1e-4"}, "rtol is '1e-4'; expected a number"),
    ],
)
def test_bad_input_is_refused_early(change: dict, message: str) -> None:
    kwargs = {"raw": grey_raw(), "cfa": "GBRG", "response": RESPONSE_RGB, "weights": "fixed:0.1"}
    kwargs.update(change)
    raw = kwargs.pop("raw")
    with pytest.raises(DataError, match=message):
        reconstruct(raw, **kwargs)


def _six_patches_with_phi(raw: np.ndarray):
    """`raw` (64 × 96) in six 32-px patches, with a constant dispersion."""
    model = spectral_model(ConstantField((0.4, -0.3), per_nm=True), shape=(64, 96))
    return reconstruct(
        raw,
        cfa="GBRG",
        response=RESPONSE_RGB,
        dispersion=model,
        weights="fixed:0.01",
        patch_px=32,
        pad_px=8,
    )


def test_flat_scene_is_reproduced_and_skipped() -> None:
    """A uniform grey mosaic: raw colour back to 1e-3 (the smoothness term leaves a flat
    patch's colour free), every patch flat, Φ skipped."""
    raw = grey_raw((64, 96))
    result = _six_patches_with_phi(raw)
    np.testing.assert_allclose(
        result.raw_colour, np.broadcast_to([0.3, 0.5, 0.2], (64, 96, 3)), rtol=1e-3
    )
    assert result.spectral.min() >= 0
    summary = result.log["patches"]
    assert result.log["rtol"] == 1e-5  # the defaults
    assert result.log["spectral_smoothness"] == SUGGESTED_SMOOTHNESS
    assert summary["count"] == 6
    assert summary["phi_skipped_flat"] == 6
    assert all(r["iterations"] <= 3 for r in result.log["patch_records"])


def test_narrow_band_light_keeps_the_default_smoothness_and_records_its_evidence() -> None:
    """A flat mosaic of the colour of one basis band (559 nm; its smooth non-negative fit
    misses it by 10 %): the default σ stays (no switch on one statistic: on the validation
    matrix σ > 0 gave the lower spectral error on every row, narrow-band light included),
    without a warning; the log records the misfit as evidence; σ = 0 stays available and
    keeps the band's raw colour, which σ > 0 moves (the documented price)."""
    space = LatentSpace.spectral(RESPONSE_RGB)
    colour = space.colour_matrix()[:, 4]
    settings = {"cfa": "GBRG", "response": RESPONSE_RGB, "weights": "fixed:0.01"}
    narrow = grey_raw((32, 32), colour=colour / colour.max())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        default = reconstruct(narrow, **settings)
        thesis = reconstruct(narrow, spectral_smoothness=0.0, **settings)
        grey = reconstruct(grey_raw((32, 32)), **settings)
    assert default.log["spectral_smoothness"] == SUGGESTED_SMOOTHNESS
    assert default.log["warnings"] == [] and default.log["band_balance"] == 0.5
    sigma = default.log["choices"]["spectral_smoothness"]
    assert sigma["source"] == "default"
    assert sigma["evidence"]["mean_colour_misfit"] == pytest.approx(0.10, abs=0.01)
    grey_sigma = grey.log["choices"]["spectral_smoothness"]
    assert grey_sigma["evidence"]["mean_colour_misfit"] < 0.02
    assert thesis.log["choices"]["spectral_smoothness"]["source"] == "given"
    # the thesis' problem keeps the band's colour (measured 0.1 % off); the smoothness term
    # moves it (12.8 %)
    truth = colour / colour.max()

    def colour_error(result) -> float:
        mean = result.raw_colour[8:-8, 8:-8].reshape(-1, 3).mean(axis=0)
        return float(np.linalg.norm(mean - truth) / np.linalg.norm(truth))

    assert colour_error(thesis) < 0.01 and colour_error(default) > 0.05


def test_spectral_smoothness_recovers_smooth_spectra_better() -> None:
    """Blobs of smooth spectra (Gaussian across bands, σ = 1.5 bands), 0.5 % noise, L2 at
    w = 0.003, non-negativity: with spectral_smoothness = 1e-3 the spectral error falls by
    more than half (measured 0.270 → 0.120) and the raw colour stays as close to the
    noise-free data (0.62 % → 0.65 %, the noise is 0.5 %)."""
    rng = np.random.default_rng(11)
    space = LatentSpace.spectral(RESPONSE_RGB)
    formation = build_formation(space, (64, 64), "GBRG")
    truth = smooth_blobs((64, 64), space.channels, rng)
    clean = formation.forward(truth)
    raw = clean + 0.005 * clean.mean() * rng.standard_normal(clean.shape)
    settings = {"cfa": "GBRG", "response": RESPONSE_RGB, "weights": "fixed:0.003"}
    results = {s: reconstruct(raw, spectral_smoothness=s, **settings) for s in (0.0, 1e-3)}
    expected = space.spectral_values(truth)  # the spectrum at the band centres
    errors = {
        s: np.linalg.norm(r.spectral - expected) / np.linalg.norm(expected)
        for s, r in results.items()
    }
    assert results[1e-3].log["spectral_smoothness"] == 1e-3
    assert errors[1e-3] < 0.6 * errors[0.0]
    misfit = {
        s: np.linalg.norm(mosaic(r.raw_colour, "GBRG") - clean) / np.linalg.norm(clean)
        for s, r in results.items()
    }
    assert misfit[1e-3] < 0.01 and misfit[0.0] < 0.01


@pytest.mark.parametrize(("smoothness", "expected"), [(0.0, 1e-4), (1e-3, 1e-5)])
def test_default_tolerance_is_tighter_with_smoothness(smoothness: float, expected: float) -> None:
    """ADMM's default ε_rel: 1e-5 with σ > 0 (within 1e-4 of the optimum), 1e-4 for the
    thesis' problem, whatever the prior; an explicit rtol wins."""
    settings = {"cfa": "GBRG", "response": RESPONSE_RGB, "weights": "fixed:0.01", "prior": "L1"}
    raw = grey_raw((32, 32))
    result = reconstruct(raw, spectral_smoothness=smoothness, **settings)
    assert result.log["rtol"] == expected
    assert reconstruct(raw, spectral_smoothness=smoothness, rtol=3e-4, **settings).log[
        "rtol"
    ] == pytest.approx(3e-4)
    l2 = reconstruct(raw, spectral_smoothness=smoothness, **{**settings, "prior": "L2"})
    assert l2.log["rtol"] == expected


def test_noisy_flat_scene_is_still_taken_as_flat() -> None:
    """0.2 % noise on the grey mosaic: the noise allowance keeps every patch flat (without
    it the plain texture statistic, ≈ 0.6 %, would not be below a 0.5 % threshold)."""
    raw = grey_raw((64, 96))
    raw = raw + np.random.default_rng(5).normal(0.0, 0.002 * raw.max(), raw.shape)
    model = spectral_model(ConstantField((0.4, -0.3), per_nm=True), shape=(64, 96))
    settings = {"cfa": "GBRG", "response": RESPONSE_RGB, "dispersion": model}
    result = reconstruct(raw, weights="fixed:0.01", flat_threshold=0.005, **settings)
    assert result.log["noise_sigma"] == pytest.approx(0.002 * raw.max(), rel=0.15)
    assert result.log["patches"]["phi_skipped_flat"] == result.log["patches"]["count"]
    np.testing.assert_allclose(result.raw_colour.mean(axis=(0, 1)), [0.3, 0.5, 0.2], rtol=2e-3)


def test_a_patch_crossed_by_one_edge_is_not_flat() -> None:
    """Grey with a dark disk whose edge runs through the corners of four patches (a few
    percent of their pixels): those patches use Φ, the two without it stay flat."""
    raw = grey_raw((64, 96))
    rows, cols = np.mgrid[0:64, 0:96]
    raw = raw * np.where((rows - 32) ** 2 + (cols - 32) ** 2 <= 6**2, 0.3, 1.0)
    result = _six_patches_with_phi(raw)
    summary = result.log["patches"]
    assert (summary["phi_used"], summary["phi_skipped_flat"]) == (4, 2)


def test_negligible_dispersion_is_skipped_and_textured_patches_use_phi() -> None:
    rng = np.random.default_rng(0)
    space = LatentSpace.spectral(RESPONSE_RGB)
    a = build_formation(space, (64, 64), "GBRG")
    raw = a.forward(blobs((64, 64), space.channels, rng))

    def patches(shift_per_100nm: float) -> dict:
        model = spectral_model(ConstantField((shift_per_100nm, 0.0), per_nm=True), shape=(64, 64))
        settings = {"weights": "fixed:0.01", "patch_px": 32, "pad_px": 8, "flat_threshold": None}
        result = reconstruct(raw, cfa="GBRG", response=RESPONSE_RGB, dispersion=model, **settings)
        return result.log["patches"]

    assert patches(0.01)["phi_skipped_negligible"] == 4
    strong = patches(0.8)
    assert strong["phi_used"] == 4
    assert strong["cg_iterations_max"] <= 10


def test_planted_shift_is_undone() -> None:
    """A planted per-band shift (up to 3 px): Φ in the problem, and the §3.9.2 variant
    (solve without Φ, then warp with the to_reference model inverted, or with the
    equivalent from_reference model), each more than halve the plain solve's raw-colour
    error. Measured RMS: plain 5.2, Φ 1.4, warp 2.0 (both directions equal)."""
    rng = np.random.default_rng(1)
    space = LatentSpace.spectral(RESPONSE_RGB)
    model = spectral_model(ConstantField((1.5, -1.0), per_nm=True), shape=(64, 64))
    truth = blobs((64, 64), space.channels, rng, count=6)
    raw = build_formation(space, (64, 64), "GBRG", model=model, interpolation="bilinear").forward(
        truth
    )
    truth_colour = space.raw_colour(truth)
    from_model = planted_dispersion_model(
        {"spectral": ConstantField((-1.5, 1.0), per_nm=True)},
        shape=(64, 64),
        direction="from_reference",
        wavelength_span=(400.0, 700.0),
    )
    errors, results = {}, {}
    for name, disp, correction in (
        ("plain", None, "model"),
        ("dispersion", model, "model"),
        ("warp", model, "warp"),
        ("warp from_reference", from_model, "warp"),
    ):
        result = reconstruct(
            raw,
            cfa="GBRG",
            response=RESPONSE_RGB,
            dispersion=disp,
            correction=correction,
            weights="fixed:0.003",
            patch_px=64,
            pad_px=8,
            flat_threshold=None,
        )
        inner = (slice(8, -8), slice(8, -8))
        results[name] = result
        errors[name] = float(
            np.sqrt(np.mean((result.raw_colour[inner] - truth_colour[inner]) ** 2))
        )
    assert errors["dispersion"] < 0.5 * errors["plain"]
    assert errors["warp"] < 0.5 * errors["plain"]
    assert results["warp"].log["dispersion"]["correction"] == "warp"
    assert "warp_seconds" in results["warp"].log
    assert results["warp"].log["patches"]["phi_used"] == 0
    np.testing.assert_allclose(
        results["warp"].spectral, results["warp from_reference"].spectral, atol=1e-5
    )


def test_exact_finish_lowers_every_patch_objective() -> None:
    """exact=True: every textured patch ends at its KKT point (records say so), each
    patch objective no higher than ADMM's, and L1 priors are refused up front."""
    rng = np.random.default_rng(4)
    space = LatentSpace.spectral(RESPONSE_RGB)
    raw = build_formation(space, (64, 64), "GBRG").forward(blobs((64, 64), space.channels, rng))
    settings = {"cfa": "GBRG", "response": RESPONSE_RGB, "weights": "fixed:0.0005",
                "patch_px": 32, "flat_threshold": None}  # fmt: skip
    plain = reconstruct(raw, **settings)
    exact = reconstruct(raw, exact=True, **settings)
    assert exact.log["exact"] and exact.log["patches"]["exact"] == 4
    assert all(r["exact"] and r["polish_rounds"] >= 1 for r in exact.log["patch_records"])
    for a, b in zip(exact.log["patch_records"], plain.log["patch_records"], strict=True):
        assert a["objective"] <= b["objective"] * (1 + 1e-12)
    assert exact.spectral.min() >= 0
    with pytest.raises(DataError, match="L1 terms"):
        reconstruct(raw, exact=True, **{**settings, "weights": "fixed:0.01"}, prior="L1")


def test_weights_by_mse_are_locally_optimal() -> None:
    """auto:msec returns a weight whose MSE is no worse than at 0.3× and 3× that weight."""
    rng = np.random.default_rng(2)
    space = LatentSpace.spectral(RESPONSE_RGB)
    a = build_formation(space, (32, 32), "GBRG")
    truth = blobs((32, 32), space.channels, rng, count=5)
    raw = a.forward(truth)
    raw = raw + 0.02 * raw.mean() * rng.standard_normal(raw.shape)
    spectral_truth = space.spectral_values(truth)
    chosen = reconstruct(
        raw,
        cfa="GBRG",
        response=RESPONSE_RGB,
        weights="auto:msec",
        truth=spectral_truth,
        weight_patch_px=32,
        patch_px=32,
        pad_px=4,
    )
    w = chosen.log["weights"]["values"][0]
    assert 1e-12 < w < 1e6

    def mse(weight):
        r = reconstruct(
            raw, cfa="GBRG", response=RESPONSE_RGB, weights=[weight], patch_px=32, pad_px=4
        )
        return float(np.mean((r.spectral - spectral_truth) ** 2))

    best = mse(w)
    assert best <= 1.02 * mse(0.3 * w)
    assert best <= 1.02 * mse(3 * w)


@pytest.mark.parametrize(
    ("prior", "smoothness", "criterion"), [("VTV", 0.0, "msec"), ("L1", 1e-3, "dmc")]
)
def test_l1_type_weights_leave_machine_epsilon(
    prior: str, smoothness: float, criterion: str
) -> None:
    """Weight search with an L1-type prior (VTV; L1 with σ): each weight starts from its own
    initial estimate, so the criterion sees the weight's effect and returns a weight whose
    MSE is well below that of a weight near machine epsilon; by MSE (3.23), no worse than
    0.3× and 3× itself. Warm-started from neighbouring weights, every weight scored alike
    and the search drifted: VTV by MSE to ~1e-15, L1 with σ by DMC to 7.9e-8 here (MSE
    0.0225 against 0.0130)."""
    rng = np.random.default_rng(2)
    space = LatentSpace.spectral(RESPONSE_RGB)
    truth = blobs((32, 32), space.channels, rng, count=5)
    raw = build_formation(space, (32, 32), "GBRG").forward(truth)
    raw = raw + 0.02 * raw.mean() * rng.standard_normal(raw.shape)
    spectral_truth = space.spectral_values(truth)
    settings = {"cfa": "GBRG", "response": RESPONSE_RGB, "prior": prior, "patch_px": 32,
                "pad_px": 4, "spectral_smoothness": smoothness}  # fmt: skip
    chosen = reconstruct(
        raw, weights=f"auto:{criterion}", truth=spectral_truth, weight_patch_px=32, **settings
    )
    w = chosen.log["weights"]["values"][0]

    def mse(weight):
        r = reconstruct(raw, weights=[weight], **settings)
        return float(np.mean((r.spectral - spectral_truth) ** 2))

    best = mse(w)
    assert w > 1e-6
    assert best < 0.8 * mse(1e-12)
    if criterion == "msec":
        assert best <= 1.02 * mse(0.3 * w)
        assert best <= 1.02 * mse(3 * w)


def six_dispersive_patches(seed: int) -> tuple[np.ndarray, dict]:
    """A 64×96 raw image of blobs under a constant dispersion, and settings that cut it into
    six patches which all use Φ."""
    rng = np.random.default_rng(seed)
    space = LatentSpace.spectral(RESPONSE_RGB)
    model = spectral_model(ConstantField((0.6, -0.4), per_nm=True), shape=(64, 96))
    raw = build_formation(space, (64, 96), "GBRG", model=model, interpolation="bilinear").forward(
        blobs((64, 96), space.channels, rng)
    )
    settings = {
        "cfa": "GBRG",
        "response": RESPONSE_RGB,
        "dispersion": model,
        "weights": "fixed:0.003",
        "patch_px": 32,
        "pad_px": 8,
        "flat_threshold": None,
    }
    return raw, settings


def test_local_cluster_of_two_processes_equals_the_local_scheduler() -> None:
    """The same image on a dask.distributed LocalCluster (2 worker processes) to 1e-6."""
    from distributed import Client, LocalCluster

    raw, settings = six_dispersive_patches(4)
    local = reconstruct(raw, scheduler="threads", **settings)
    with (
        LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
        ) as cluster,
        Client(cluster) as client,
    ):
        remote = reconstruct(raw, scheduler=client, **settings)
        worker_pids = set(client.run(os.getpid).values())
    assert len(worker_pids) == 2 and os.getpid() not in worker_pids
    assert local.log["patches"]["phi_used"] == 6
    np.testing.assert_allclose(remote.spectral, local.spectral, rtol=1e-6, atol=1e-6)
    assert [r["iterations"] for r in remote.log["patch_records"]] == [
        r["iterations"] for r in local.log["patch_records"]
    ]


def test_every_local_scheduler_gives_the_same_image_and_records() -> None:
    """The pool of processes, threads (the default) and the calling thread solve the same
    patches to the same bits, report every patch to `progress`, and the pool's workers are
    other processes, kept for the next reconstruction."""
    from reconstruction.solve.worker_pool import worker_pids

    raw, settings = six_dispersive_patches(5)
    done: dict[str, list[tuple[int, int]]] = {}
    results = {
        name: reconstruct(
            raw, scheduler=name, progress=lambda *a, n=name: done.setdefault(n, []).append(a),
            **settings,
        )
        for name in ("processes", "threads", "sync")
    }  # fmt: skip
    pids = worker_pids()
    assert pids and os.getpid() not in pids
    for name in ("threads", "sync"):
        np.testing.assert_array_equal(results[name].spectral, results["processes"].spectral)
        assert results[name].log["patch_records"] == [
            {**r, "seconds": results[name].log["patch_records"][i]["seconds"],
             "formation_seconds": results[name].log["patch_records"][i]["formation_seconds"]}
            for i, r in enumerate(results["processes"].log["patch_records"])
        ]  # fmt: skip
    assert all(sorted(calls) == [(k, 6) for k in range(1, 7)] for calls in done.values())
    assert set(done) == {"processes", "threads", "sync"}
    reconstruct(raw, scheduler="processes", **settings)  # the same pool again
    assert worker_pids() == pids


def test_a_worker_that_dies_breaks_that_run_only() -> None:
    """A pool worker killed between runs: the next run starts a new pool and succeeds."""
    import signal

    from reconstruction.solve.worker_pool import worker_pids, worker_pool

    worker_pool().submit(os.getpid).result()
    os.kill(worker_pids()[0], signal.SIGKILL)
    raw = grey_raw()
    settings = {"cfa": "GBRG", "response": RESPONSE_RGB, "weights": "fixed:0.01"}
    try:
        reconstruct(raw, scheduler="processes", **settings)
    except LabkitError as error:  # the pool may notice the death only during this run
        assert "worker process solving the patches died" in str(error)
    result = reconstruct(raw, scheduler="processes", **settings)
    assert np.all(np.isfinite(result.spectral))


def test_sensor_map_bands_take_their_filters_light() -> None:
    """A response tabulated per filter (a sensor map at 400…700 nm) with a model that
    recorded the filters' effective wavelengths: Φ of the "700 nm" band is evaluated at
    686.6 nm, and of the "400 nm" band at 450 nm (the model's range starts there); the log
    says both."""
    from dataclasses import replace

    from labkit.spectra import Spectra
    from reconstruction.model.image_formation import DISCRETE
    from reconstruction.options import ReconstructOptions, filter_light

    bands = np.arange(400.0, 701.0, 50.0)
    ratios = np.column_stack([np.linspace(0.1, 2.0, 7), np.ones(7), np.linspace(3.0, 0.05, 7)])
    sensor_map = Spectra(bands, ratios, ("R", "G", "B"))
    model = replace(
        spectral_model(ConstantField((1.0, 0.0), per_nm=True), shape=(64, 64)),
        provenance={
            "bands_table": [
                {"illumination": "450", "nominal_nm": 450.0, "wavelength_nm": 451.0},
                {"illumination": "700", "nominal_nm": 700.0, "wavelength_nm": 686.6},
                {"illumination": "odd", "nominal_nm": None, "wavelength_nm": 500.0},
            ]
        },
    )
    model = replace(model, region=replace(model.region, wavelength_nm=(450.0, 690.0)))
    light = filter_light(bands, model)
    np.testing.assert_allclose(light, [400, 451, 500, 550, 600, 650, 686.6])
    assert filter_light(bands, replace(model, provenance={})) is None

    options = ReconstructOptions(
        cfa="GBRG", response=sensor_map, bands=bands, dispersion=model, weights="fixed:0.01",
        patch_px=32, pad_px=8, flat_threshold=None, spectral_smoothness=0.0,
    )  # fmt: skip
    assert options.space.kernel == DISCRETE
    np.testing.assert_allclose(options.space.phi_nm, light)
    rng = np.random.default_rng(4)
    raw = 0.5 + 0.1 * rng.random((64, 64))
    with pytest.warns(DomainWarning, match=r"400.0 → 450.0 nm"):
        result = reconstruct(raw, options)
    log = result.log
    assert log["dispersion"]["band_light_nm"]["values"] == pytest.approx(light)
    assert log["dispersion"]["domain"]["outside_nm"] == [400.0]
    assert "400.0 → 450.0 nm (calibrated 450.0–690.0 nm" in log["warnings"][0]
