"""`ReconstructOptions`: validated once, the same job as keywords, errors that name the
option as the caller spells it."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest
from _problems import RESPONSE

from labkit.cli.reconstruct import CLI_NAMES
from labkit.errors import ConfigError, DataError
from labkit.spectra import camera_response
from reconstruction import OptionError, ReconstructOptions, reconstruct
from reconstruction.model.problem import SUGGESTED_SMOOTHNESS

RESPONSE_RGB = camera_response(RESPONSE)
BASE = {"cfa": "GBRG", "response": RESPONSE_RGB}


def _raw() -> np.ndarray:
    yy, xx = np.mgrid[:32, :48]
    return 2.0 + np.sin(xx / 4.0) + 0.5 * np.cos(yy / 6.0)


def test_options_object_runs_the_same_job_as_keywords() -> None:
    keywords = {**BASE, "weights": "auto:dmc", "patch_px": 16}
    by_keywords = reconstruct(_raw(), **keywords)
    options = ReconstructOptions(**keywords)
    by_object = reconstruct(_raw(), options)
    np.testing.assert_array_equal(by_object.spectral, by_keywords.spectral)
    assert by_object.log["weights"]["values"] == by_keywords.log["weights"]["values"]
    # keywords given with the object replace its fields
    replaced = reconstruct(_raw(), options, weights="fixed:0.5")
    assert replaced.log["weights"]["values"] == [0.5]
    assert options.weights == "auto:dmc"


def test_defaults_in_effect() -> None:
    spectral = ReconstructOptions(**BASE)
    assert spectral.smoothness == SUGGESTED_SMOOTHNESS and spectral.tolerance == 1e-5
    assert spectral.direct and spectral.exact_weights and spectral.criterion == "dmc"
    colour = ReconstructOptions(cfa="GBRG", latent="colour")
    assert colour.smoothness == 0.0 and colour.tolerance == 1e-4 and not colour.direct
    mdc = ReconstructOptions(**BASE, weights="auto:mdc")
    assert not mdc.exact_weights
    assert ReconstructOptions(**BASE, weights=[0.1]).fixed_weights == (0.1,)


@pytest.mark.parametrize(
    ("change", "option", "python", "cli"),
    [
        ({"cfa": "RGBX"}, "cfa", "cfa:", "--cfa:"),
        ({"latent": "hyper"}, "latent", "unknown latent 'hyper'", "unknown --latent 'hyper'"),
        ({"kernel": "box"}, "kernel", "unknown kernel 'box'", "unknown --kernel 'box'"),
        ({"reference": "white"}, "reference", "unknown reference", "unknown --reference"),
        ({"prior": "TV3"}, "prior", "unknown prior 'TV3'", "unknown --prior 'TV3'"),
        ({"response": None}, "response", "(response)", "(--response)"),
        ({"bands": [300, 400, 500]}, "bands", "bands:", "--bands:"),
        ({"spectral_smoothness": np.nan}, "spectral_smoothness",
         "spectral_smoothness is nan; expected a finite number ≥ 0",
         "--spectral-smoothness is nan; expected a finite number ≥ 0"),
        ({"latent": "colour", "response": None, "spectral_smoothness": 1e-3},
         "spectral_smoothness", "applies to latent spectral",
         "--spectral-smoothness applies to --latent spectral"),
        ({"rtol": 0.0}, "rtol", "rtol is 0.0; expected a number in (0, 1)", "--rtol is 0.0"),
        ({"prior": "L1", "exact": True}, "exact", "L1 has L1 terms", "(--exact)"),
        ({"weights": "best"}, "weights", "weights 'best': use auto:dmc",
         "--weights 'best': use auto:dmc"),
        ({"weights": "fixed:0.1,0.2"}, "weights", "prior EdgeL2 has 1 term(s), so give 1",
         "--prior EdgeL2 has 1 term(s), so give 1"),
        ({"weights": [0.1, 0.2]}, "weights", "has 1 term(s)", "has 1 term(s)"),
        ({"weights": "fixed:-1"}, "weights", "finite and ≥ 0", "--weights:"),
        ({"weights": "auto:dmc-ari"}, "weights", "unknown weight criterion", "--weights:"),
        ({"correction": "warp"}, "correction", "correction warp needs a dispersion model "
         "(dispersion)", "--correction warp needs a dispersion model (--dispersion)"),
        ({"max_iter": 0}, "max_iter", "max_iter is 0; expected a whole number ≥ 1",
         "--max-iter is 0"),
        ({"patch_px": 31}, "patch_px", "patch_px is 31; expected an even", "--patch-px is 31"),
        ({"patch_px": 6}, "patch_px", "≥ 8", "--patch-px"),
        ({"pad_px": 3}, "pad_px", "pad_px is 3", "--pad-px is 3"),
        ({"weight_patch_px": 65}, "weight_patch_px", "weight_patch_px is 65",
         "--weight-patch-px is 65"),
        ({"weight_patches": 0}, "weight_patches", "weight_patches is 0", "--weight-patches is 0"),
        ({"flat_threshold": -0.1}, "flat_threshold", "flat_threshold is -0.1; expected a finite "
         "number ≥ 0", "--flat-threshold is -0.1"),
        ({"pad_px": 0}, "pad_px", "pad_px is 0; expected an even whole number ≥ 2",
         "--pad-px is 0"),
        ({"band_balance": 1.5}, "band_balance", "band_balance is 1.5; expected a number in "
         "[0, 1]", "--band-balance is 1.5"),
        ({"nonneg": "yes"}, "nonneg", "nonneg is 'yes'; expected True or False", "--nonneg"),
    ],
)  # fmt: skip
def test_bad_options_are_refused_when_made(change, option, python, cli) -> None:
    with pytest.raises(OptionError) as caught:
        ReconstructOptions(**{**BASE, **change})
    error = caught.value
    assert isinstance(error, ConfigError) and isinstance(error, DataError)
    assert error.option == option
    assert python in str(error)
    assert cli in error.message(CLI_NAMES)


def test_a_missing_dispersion_file_fails_when_made(tmp_path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        ReconstructOptions(**BASE, dispersion=tmp_path / "missing.yaml")


def test_every_option_has_its_flag() -> None:
    """Every option is settable from the command line, and errors about it name it by its
    flag (generated from reconstruction.option_table)."""
    assert set(CLI_NAMES) == {f.name for f in fields(ReconstructOptions)}


def test_as_dict_is_json_ready(tmp_path) -> None:
    import json

    options = ReconstructOptions(**BASE, bands=[400, 500, 600, 700])
    plain = json.loads(json.dumps(options.as_dict()))
    assert plain["bands"] == [400.0, 500.0, 600.0, 700.0] and plain["response"] == "in memory"


def test_the_stages_run_alone_give_the_job() -> None:
    """prepare_problem → choose_weights → solve_patches → assemble is reconstruct(); the
    weights of one image can be reused on another."""
    from reconstruction.reconstruct import (
        assemble,
        choose_weights,
        prepare_problem,
        solve_patches,
    )

    options = ReconstructOptions(**BASE, patch_px=16)
    whole = reconstruct(_raw(), options)
    job = prepare_problem(_raw(), options)
    weights = choose_weights(job)
    staged = assemble(job, *solve_patches(job, weights))
    np.testing.assert_array_equal(staged.spectral, whole.spectral)
    assert list(weights) == whole.log["weights"]["values"]

    other = prepare_problem(2.0 * _raw()[::-1], options)
    reused = assemble(other, *solve_patches(other, weights))
    assert np.all(np.isfinite(reused.spectral))
    assert reused.log["weights"] == {
        "values": list(weights),
        "criterion": "fixed",
        "requested": list(weights),
    }


def test_braces_in_a_quoted_value_survive_the_message() -> None:
    with pytest.raises(OptionError) as caught:
        ReconstructOptions(**BASE, prior="{weird}")
    assert "unknown prior '{weird}'" in str(caught.value)
    assert "unknown --prior '{weird}'" in caught.value.message(CLI_NAMES)


def test_weight_patches_take_a_count_or_origins() -> None:
    """weight_patches is a count (declared ≥ 1) or the patches' origins, which the weight
    stage checks and uses as given."""
    origins = [(0, 0), (0, 16)]
    options = ReconstructOptions(**BASE, weight_patches=origins, weight_patch_px=16)
    assert options.weight_patches == origins
    result = reconstruct(_raw(), options, patch_px=16)
    assert result.log["weights"]["patches"] == [[0, 0], [0, 16]]
    with pytest.raises(OptionError, match="weight_patches is 0; expected a whole number ≥ 1"):
        ReconstructOptions(**BASE, weight_patches=0)


def test_the_response_is_taken_in_every_form_the_ecosystem_uses(tmp_path) -> None:
    """A dataset name, colour-science's own distributions (all three channels, or one
    SpectralDistribution per channel), a CSV, (wavelengths, values) and Spectra give the
    same response and the same reconstruction; the name is what the options record."""
    import colour

    from labkit.spectra import write_response_csv

    dataset = colour.MSDS_CAMERA_SENSITIVITIES[RESPONSE]
    csv = tmp_path / "response.csv"
    write_response_csv(RESPONSE_RGB, csv)
    forms = {
        "name": RESPONSE,
        "msds": dataset,
        "three sds": [dataset.signals[label].copy() for label in dataset.labels],
        "arrays": (RESPONSE_RGB.wavelengths, RESPONSE_RGB.values),
        "csv": csv,
    }
    reference = reconstruct(_raw(), **BASE, weights="fixed:0.01", patch_px=16)
    for form, response in forms.items():
        options = ReconstructOptions(cfa="GBRG", response=response)
        assert options.response.labels == ("R", "G", "B"), form
        np.testing.assert_allclose(options.response.wavelengths, RESPONSE_RGB.wavelengths)
        np.testing.assert_allclose(options.response.values, RESPONSE_RGB.values, rtol=1e-5)
        result = reconstruct(_raw(), options, weights="fixed:0.01", patch_px=16)
        np.testing.assert_allclose(result.spectral, reference.spectral, rtol=1e-4, atol=1e-7)
    assert ReconstructOptions(cfa="GBRG", response=RESPONSE).as_dict()["response"] == RESPONSE
    assert ReconstructOptions(cfa="GBRG", response=dataset).as_dict()["response"] == "in memory"


@pytest.mark.parametrize(
    ("response", "match"),
    [
        (42, "cannot be made from int"),
        ("No Such Camera", "unknown camera response"),
        ((np.arange(10.0), np.ones((10, 2))), r"shape \(n, 3\)"),
        ((np.arange(10.0), -np.ones((10, 3))), "≥ 0"),
    ],
    ids=["number", "unknown-name", "two-channels", "negative"],
)
def test_a_response_that_cannot_serve_is_a_labkit_error(response, match) -> None:
    with pytest.raises(OptionError, match=match) as info:
        reconstruct(_raw(), cfa="GBRG", response=response)
    assert isinstance(info.value, DataError) and info.value.message(CLI_NAMES).startswith(
        "--response"
    )
