"""`reconstruction.choices`: every automatic choice made in one place, with its evidence;
`reconstruction.option_table`: one declaration of each option, the same bounds for the
command line and the Python API; the layers below take explicit values."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from _problems import RESPONSE, ConstantField, blobs, spectral_model

from labkit.cli.reconstruct import CLI_NAMES, _declared
from labkit.errors import ConfigError, DataError
from labkit.spectra import Spectra, camera_response
from reconstruction import OptionError, ReconstructOptions, reconstruct
from reconstruction.choices import MIN_PAD_PX, SOURCES
from reconstruction.model.image_formation import LatentSpace, build_formation
from reconstruction.model.problem import SUGGESTED_SMOOTHNESS
from reconstruction.option_table import OPTION_TABLE, OptionSpec
from reconstruction.solve.patches import SolverOptions

RESPONSE_RGB = camera_response(RESPONSE)
BASE = {"cfa": "GBRG", "response": RESPONSE_RGB, "weights": "fixed:0.01", "patch_px": 32}


def _textured(shape=(64, 64), seed=0) -> np.ndarray:
    space = LatentSpace.spectral(RESPONSE_RGB)
    truth = blobs(shape, space.channels, np.random.default_rng(seed))
    return build_formation(space, shape, "GBRG").forward(truth)


def test_defaults_are_recorded_with_where_they_came_from() -> None:
    """Left to labkit, every setting in effect is in log.json's ``choices`` with a source
    and a reason; σ carries the image's evidence (the mean colour's misfit and the
    threshold), and the flat keys agree with the choices."""
    result = reconstruct(_textured(), **BASE)
    choices = result.log["choices"]
    assert set(choices) >= {"bands", "spectral_smoothness", "band_balance", "reference",
                            "weights", "exact_weights", "rtol", "solver", "pad_px"}  # fmt: skip
    assert all(c["source"] in SOURCES and c["reason"] for c in choices.values())
    sigma = choices["spectral_smoothness"]
    assert sigma["value"] == SUGGESTED_SMOOTHNESS and sigma["source"] == "default"
    assert 0 <= sigma["evidence"]["mean_colour_misfit"] < 0.02
    assert choices["reference"]["value"] is None  # a continuous response: the bands' scales
    assert choices["reference"]["source"] == "default"
    assert choices["band_balance"]["value"] == result.log["band_balance"] == 0.5
    assert choices["rtol"]["value"] == result.log["rtol"] == 1e-5
    assert choices["rtol"]["source"] == "follows"
    assert choices["solver"]["value"] == result.log["solver"] == "direct-or-admm"
    assert choices["pad_px"] == {
        "value": MIN_PAD_PX, "source": "default", "reason": choices["pad_px"]["reason"],
        "evidence": {"reach_px": 0.0},
    }  # fmt: skip
    assert choices["bands"]["source"] == "default" and "bandlimit" in choices["bands"]["reason"]
    json.dumps(choices)  # JSON-ready


def test_given_options_override_every_choice() -> None:
    given = {"spectral_smoothness": 0.0, "rtol": 1e-3, "exact": False, "pad_px": 10,
             "bands": [400.0, 450.0, 500.0, 550.0, 600.0, 650.0, 700.0]}  # fmt: skip
    result = reconstruct(_textured(), **BASE, **given)
    choices = result.log["choices"]
    for name, value in given.items():
        if name != "exact":
            assert choices[name]["source"] == "given" and choices[name]["value"] == value
    assert choices["solver"] == {
        "value": "admm", "source": "given", "reason": choices["solver"]["reason"],
        "evidence": {},
    }  # fmt: skip
    assert result.log["patches"]["exact"] == 0  # --no-exact: every patch by ADMM
    # the band balance follows σ = 0 (it needs σ > 0)
    assert choices["band_balance"]["value"] == 0.0
    assert choices["band_balance"]["source"] == "follows"


def test_a_planted_dispersion_sets_the_overlap_from_its_reach() -> None:
    """A planted shift of 4 px per 100 nm: the overlap is the smallest even value ≥ twice
    Φ's reach (7.4 px at the response's ends, 185 nm from 600 nm), chosen from it and
    recorded with it; the interpolation and the extrapolation policy are recorded too."""
    model = spectral_model(ConstantField((3.2, -2.4), per_nm=True), shape=(64, 64))
    result = reconstruct(_textured(), **BASE, dispersion=model)
    pad = result.log["choices"]["pad_px"]
    assert pad["evidence"]["reach_px"] == pytest.approx(7.4, abs=0.05)
    assert pad["value"] == 16 and pad["source"] == "image"
    assert result.log["pad_px"] == pad["value"]
    assert result.log["choices"]["interpolation"]["value"] == "cubic"
    assert result.log["choices"]["extrapolation"]["value"] == "clamp"


MAP_BANDS = [450.0, 500.0, 550.0, 600.0, 650.0]


def _sensor_map(green: np.ndarray) -> Spectra:
    bands = np.array(MAP_BANDS)
    ratios = np.array([[0.3, 4.8], [0.09, 0.9], [0.05, 0.07], [2.5, 0.02], [6.0, 0.01]])
    values = np.column_stack([ratios[:, 0], np.ones(5), ratios[:, 1]]) * green[:, None]
    return Spectra(bands, values, ("R", "G", "B"))


def test_a_map_with_the_same_green_in_every_band_gets_the_mean_colour_reference() -> None:
    """The thesis' normalisation (G = 1 in every band) leaves the bands' relative scales
    unknown: "auto" takes the §6.3 reference, with the evidence; a map with Green levels
    (labkit's levelled convention) keeps the plain problem; a given reference is kept."""
    levels = np.array([0.2, 0.7, 1.0, 0.8, 0.3])
    unlevelled = ReconstructOptions(cfa="GBRG", response=_sensor_map(np.ones(5)), bands=MAP_BANDS)
    levelled = ReconstructOptions(cfa="GBRG", response=_sensor_map(levels), bands=MAP_BANDS)
    assert unlevelled.choices["reference"].value == "mean-colour"
    assert unlevelled.choices["reference"].evidence == {"green_per_band": 1.0}
    assert levelled.choices["reference"].value is None
    plain = ReconstructOptions(
        cfa="GBRG", response=_sensor_map(np.ones(5)), bands=MAP_BANDS, reference=None
    )
    assert plain.choices["reference"].value is None
    assert plain.choices["reference"].source == "given"
    # the reconstruction applies it: the latent's scale is the reference's
    space = LatentSpace.spectral(_sensor_map(np.ones(5)), MAP_BANDS)
    raw = build_formation(space, (32, 32), "GBRG").forward(
        blobs((32, 32), space.channels, np.random.default_rng(1))
    )
    result = reconstruct(raw, unlevelled, weights="fixed:0.01", patch_px=16)
    assert result.log["reference"] == "mean-colour"
    assert not np.allclose(result.log["reference_scale"], 1.0)


def _bad_text(spec: OptionSpec) -> str | None:
    """A text the declaration refuses (None: a flag, which argparse spells)."""
    if spec.kind == "choice":
        return "bogus"
    if spec.kind == "whole":
        return str(int(spec.least) + 1 if spec.even else int(spec.least) - 1)
    if spec.kind == "number":
        return str(spec.most + 1) if spec.most is not None else "-1"
    return None


@pytest.mark.parametrize("spec", [s for s in OPTION_TABLE if _bad_text(s)], ids=lambda s: s.name)
def test_the_command_line_and_the_api_refuse_the_same_values(spec: OptionSpec) -> None:
    """One declaration: a value outside an option's bounds is refused by the flag and by the
    keyword with the same message, each naming the option as its caller spells it."""
    text = _bad_text(spec)
    args = argparse.Namespace(**{s.name: None for s in OPTION_TABLE})
    setattr(args, spec.name, text)
    with pytest.raises(ConfigError) as cli:
        _declared(args)
    value = text if spec.kind == "choice" else type(spec.least)(float(text))
    if spec.kind == "whole":
        value = int(text)
    with pytest.raises(OptionError) as api:
        ReconstructOptions(**{"cfa": "GBRG", "response": RESPONSE_RGB, spec.name: value})
    assert api.value.option == spec.name and spec.flag in str(cli.value)
    # the same message, naming the flag (which quotes the text as given)
    assert str(cli.value) == api.value.message(CLI_NAMES).replace(repr(value), repr(text))


def test_pad_px_has_one_lower_bound() -> None:
    """The overlap the options accept is one the patch driver takes (≥ 2; it was ≥ 0)."""
    with pytest.raises(OptionError, match=r"pad_px is 0; expected an even whole number ≥ 2"):
        ReconstructOptions(cfa="GBRG", response=RESPONSE_RGB, pad_px=0)
    ReconstructOptions(cfa="GBRG", response=RESPONSE_RGB, pad_px=2)


def test_the_layers_below_have_no_defaults_of_their_own() -> None:
    """Φ's sampling is resolved once: build_formation with a model, the dispersion operator
    and the solver settings refuse to be built without it."""
    model = spectral_model(ConstantField((0.4, -0.3), per_nm=True), shape=(32, 32))
    space = LatentSpace.spectral(RESPONSE_RGB)
    with pytest.raises(DataError, match="needs interpolation="):
        build_formation(space, (32, 32), "GBRG", model=model)
    from reconstruction.model.operators import Dispersion

    with pytest.raises(TypeError, match="interpolation"):
        Dispersion(model, space.centres_nm)
    with pytest.raises(TypeError, match="interpolation"):
        SolverOptions(  # type: ignore[call-arg]
            terms=(), weights=(), nonneg=True, rtol=1e-4, atol=None, max_iter=10,
            method="admm", smoothness=0.0,
        )  # fmt: skip
