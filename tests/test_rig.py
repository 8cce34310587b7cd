"""Rig files: the shipped rigs load, and malformed rigs give one clear ConfigError."""

from __future__ import annotations

import copy
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from labkit.errors import ConfigError
from labkit.rig import Rig, default_rig_path, load_rig, rig_from_dict


def _no_internals(message: str) -> None:
    assert "Traceback" not in message, message
    assert "For further information" not in message, message
    assert "pydantic" not in message.lower(), message


@pytest.fixture(scope="module")
def sim_rig_data(thesis_rig_path: Path) -> dict[str, Any]:
    """The simulated rig with the thesis' exposure lists, whose entries tests break."""
    return yaml.safe_load(thesis_rig_path.read_text(encoding="utf-8"))


# -- the shipped rigs ---------------------------------------------------------------------


def test_simulated_rig_loads(sim_rig_path: Path) -> None:
    rig = load_rig(sim_rig_path)
    assert isinstance(rig, Rig)
    assert rig.source == str(sim_rig_path)
    assert rig.camera.backend == "sim" and rig.cfa == "GBRG"
    assert rig.illuminations() == ["unfiltered", "400", "450", "500", "550", "600", "650", "700"]
    assert rig.filter_for("unfiltered") is None
    f450 = rig.filter_for("450")
    assert f450 is not None and f450.centre_nm == 450 and f450.measured == "442 nm"
    assert rig.plan.exposures_s.unfiltered == rig.plan.exposures_s.filtered == "auto"
    assert rig.plan.replicates.unfiltered == 15 and rig.plan.replicates.filtered == 5
    assert rig.sim.seed == 2019
    assert (rig.sim.sensor.height, rig.sim.sensor.width) == (2048, 2448)
    assert rig.sim.light.white_rate_e_per_s == pytest.approx(1.2e6)
    assert rig.sim.lens.max_shift_px == pytest.approx(2.5)
    assert set(rig.sim.scenes) == {"disks", "colorchecker", "texture"}
    assert rig.sim.scenes["disks"].radius_px == 14
    with pytest.raises(ConfigError, match="no illumination 'dark'"):
        rig.filter_for("dark")


def test_plan_lookups_per_illumination(thesis_rig_path: Path) -> None:
    rig = load_rig(thesis_rig_path)
    assert rig.exposures_for("unfiltered") == [0.003, 0.006, 0.012]
    assert rig.exposures_for("700") == [0.025, 0.05, 0.1, 0.25, 0.5, 2.0, 3.916]
    assert (rig.replicates_for("unfiltered"), rig.replicates_for("450")) == (15, 5)
    with pytest.raises(ConfigError, match="no illumination '475'"):
        rig.exposures_for("475")


def test_example_flea3_rig_loads(repo_root: Path) -> None:
    rig = load_rig(repo_root / "rigs" / "example-flea3.yaml")
    assert rig.camera.backend == "aravis" and rig.cfa == "GBRG"
    assert rig.sim is None, "a hardware rig has no sim section"
    assert rig.slider.driver == "fw102c" and len(rig.slider.positions) == 8
    f550 = rig.filter_for("550")
    assert (f550.centre_nm, f550.fwhm_nm, f550.optical_density) == (550, 10, 4)
    assert f550.measured is None


def test_packaged_default_rig_matches_repo_copy(sim_rig_path: Path) -> None:
    packaged = default_rig_path()
    assert packaged.is_file()
    assert load_rig(packaged).model_dump() == load_rig(sim_rig_path).model_dump()


def test_sim_backend_without_sim_section_gets_defaults(sim_rig_data: dict[str, Any]) -> None:
    data = copy.deepcopy(sim_rig_data)
    del data["sim"]
    rig = rig_from_dict(data, source="inline")
    assert rig.sim is not None and rig.sim.sensor.adc_bits == 12


def test_response_csv_is_relative_to_the_rig_file(
    tmp_path: Path, sim_rig_data: dict[str, Any]
) -> None:
    data = copy.deepcopy(sim_rig_data)
    data["camera"]["response"] = "responses/cam.csv"
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"camera.response 'responses/cam.csv' does not exist"):
        load_rig(path)
    (tmp_path / "responses").mkdir()
    (tmp_path / "responses" / "cam.csv").write_text("wavelength_nm,R,G,B\n")
    assert load_rig(path).response_source() == str(tmp_path / "responses" / "cam.csv")
    data["camera"]["response"] = "../outside/cam.csv"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="leads outside the rig file's folder"):
        load_rig(path)


@pytest.mark.parametrize(
    ("response", "match"),
    [("Nikon 9999", "unknown camera response 'Nikon 9999'"), ("bad.csv", "header is")],
)
def test_rig_check_loads_the_response(
    tmp_path: Path, sim_rig_data: dict[str, Any], capsys, response: str, match: str
) -> None:
    from labkit.cli import main

    data = copy.deepcopy(sim_rig_data)
    data["camera"]["response"] = response
    (tmp_path / "bad.csv").write_text("not,a,response\n1,2,3\n")
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["rig", "check", str(path)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "camera.response" in err and match in err


# -- malformed rigs -------------------------------------------------------------------------

Mutation = Callable[[dict[str, Any]], None]


def _set(*keys: Any, value: Any) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        node = data
        for key in keys[:-1]:
            node = node[key]
        node[keys[-1]] = value

    return mutate


def _delete(*keys: Any) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        node = data
        for key in keys[:-1]:
            node = node[key]
        del node[keys[-1]]

    return mutate


# (id, mutation, key path that must be named, bad value that must be named or None)
MALFORMED: list[tuple[str, Mutation, str, str | None]] = [
    ("missing-top-level", _delete("camera"), "camera", None),
    ("missing-slider", _delete("slider"), "slider", None),
    ("missing-nested", _delete("camera", "backend"), "camera.backend", None),
    ("missing-port", _delete("slider", "port"), "slider.port", None),
    (
        "wrong-type-number",
        _set("sim", "sensor", "full_well_e", value="lots"),
        "sim.sensor.full_well_e",
        "'lots'",
    ),
    ("wrong-type-list", _set("plan", "scenes", value="disks"), "plan.scenes", "'disks'"),
    ("unknown-backend", _set("camera", "backend", value="usb3"), "camera.backend", "'usb3'"),
    (
        "filter-centre-out-of-range",
        _set("slider", "positions", 2, "filter", "centre_nm", value=2000),
        "slider.positions[2].filter.centre_nm",
        "2000",
    ),
    (
        "negative-exposure",
        _set("plan", "exposures_s", "filtered", 1, value=-0.05),
        "plan.exposures_s.filtered[1]",
        "-0.05",
    ),
    (
        "zero-exposure",
        _set("plan", "exposures_s", "unfiltered", 0, value=0),
        "plan.exposures_s.unfiltered[0]",
        "is 0;",
    ),
    (
        "unknown-key-typo",
        _set("camera", "pixelformat", value="BayerRG12"),
        "camera.pixelformat",
        "'BayerRG12'",
    ),
    ("unknown-top-level-key", _set("plann", value={"scenes": []}), "plann", None),
    (
        "non-bayer-pixel-format",
        _set("camera", "pixel_format", value="Mono8"),
        "camera.pixel_format",
        "'Mono8'",
    ),
    (
        "plan-unknown-illumination",
        _set("plan", "illuminations", value=["unfiltered", "475"]),
        "plan.illuminations",
        "'475'",
    ),
    (
        "plan-unknown-scene",
        _set("plan", "scenes", value=["disks", "bogus"]),
        "plan.scenes",
        "'bogus'",
    ),
    (
        "unknown-measured-filter",
        _set("slider", "positions", 3, "filter", "measured", value="451 nm"),
        "slider.positions[3].filter.measured",
        "'451 nm'",
    ),
    (
        "slot-out-of-range",
        _set("slider", "positions", 13, value={"name": "x"}),
        "slider.positions[13]",
        "is 13;",
    ),
    ("wrong-format-version", _set("format", value=2), "format", "is 2;"),
    ("negative-gain", _set("camera", "gain_db", value=-3), "camera.gain_db", "-3"),
    ("adc-bits", _set("sim", "sensor", "adc_bits", value=11), "sim.sensor.adc_bits", "11"),
    ("vignetting", _set("sim", "lens", "vignetting", value=1.0), "sim.lens.vignetting", "1.0"),
    (
        "duplicate-position-names",
        _set("slider", "positions", 3, "name", value="400"),
        "slider: position names must be unique",
        "'400', '400'",
    ),
    (
        "infinite-exposure",
        _set("plan", "exposures_s", "unfiltered", value=[float("inf")]),
        "plan.exposures_s.unfiltered[0]",
        "inf",
    ),
    ("nan-gain", _set("camera", "gain_db", value=float("nan")), "camera.gain_db", "nan"),
    ("odd-width", _set("sim", "sensor", "width", value=97), "sim.sensor.width", "97"),
    ("tiny-sensor", _set("sim", "sensor", "height", value=2), "sim.sensor.height", "2"),
    ("negative-seed", _set("sim", "seed", value=-1), "sim.seed", "-1"),
    ("slot-zero", _set("slider", "positions", 0, value={"name": "x"}), "slider.positions[0]", None),
    ("escaping-scene", _set("plan", "scenes", value=["../../x"]), "plan.scenes[0]", "../../x"),
    (
        "hidden-position",
        _set("slider", "positions", 2, "name", value=".400"),
        "slider.positions[2].name",
        ".400",
    ),
    (
        "unknown-light-source",
        _set("light", "source", value="laserbeam"),
        "light.source",
        "'laserbeam'",
    ),
    (
        "black-level-at-or-above-the-adc-maximum",
        _set("sim", "sensor", "black_level_dn", value=5000),
        "sim.sensor: black_level_dn 5000 is not below the 12-bit ADC maximum 4095",
        None,
    ),
    (
        "scene-option-of-another-type",
        _set("sim", "scenes", "disks", "seed", value=3),
        "sim.scenes.disks: scene type 'disks' does not take ['seed']",
        None,
    ),
]


@pytest.mark.parametrize(
    ("mutation", "key_path", "bad_value"),
    [case[1:] for case in MALFORMED],
    ids=[case[0] for case in MALFORMED],
)
def test_malformed_rig_names_file_key_and_value(
    tmp_path: Path,
    sim_rig_data: dict[str, Any],
    mutation: Mutation,
    key_path: str,
    bad_value: str | None,
) -> None:
    data = copy.deepcopy(sim_rig_data)
    mutation(data)
    path = tmp_path / "bad-rig.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    message = str(info.value)
    assert message.startswith(str(path)), f"message should start with the file: {message}"
    assert key_path in message, f"message should name {key_path}: {message}"
    if bad_value is not None:
        assert bad_value in message, f"message should show the bad value {bad_value}: {message}"
    assert "\n" not in message, f"one line expected: {message}"
    _no_internals(message)


def test_yaml_syntax_error_names_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "syntax.yaml"
    path.write_text("format: 1\ncamera:\n  backend: sim\n   device: [x\n", encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    message = str(info.value)
    assert str(path) in message and "line 4" in message, message
    assert "YAML" in message
    _no_internals(message)


def test_missing_rig_file(tmp_path: Path) -> None:
    path = tmp_path / "no-such-rig.yaml"
    with pytest.raises(ConfigError, match="does not exist") as info:
        load_rig(path)
    assert str(path) in str(info.value)
    _no_internals(str(info.value))


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("- 1\n- 2\n", "must be a YAML mapping, got list"),
        ("", "is empty; give a rig YAML file"),
        ("# only a comment\n", "holds no YAML data"),
    ],
)
def test_rig_file_must_be_a_mapping(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "not-a-mapping.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=match) as info:
        load_rig(path)
    assert str(path) in str(info.value)
    assert "NoneType" not in str(info.value)


def _rig_check(path: Path, capsys) -> str:
    """`labkit rig check PATH`: must fail with one line; that line."""
    from labkit.cli import main

    assert main(["rig", "check", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    _no_internals(err)
    return err


def test_rig_check_names_an_unknown_light_source_and_the_known_ones(
    tmp_path: Path, sim_rig_data: dict[str, Any], capsys
) -> None:
    data = copy.deepcopy(sim_rig_data)
    data["light"]["source"] = "laserbeam"
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    err = _rig_check(path, capsys)
    assert "light.source is 'laserbeam'" in err, err
    assert all(name in err for name in ("projector", "D65", "colour.SDS_ILLUMINANTS")), err
    assert len(err) < 400, err  # a few names and where the rest are, not all 60
    data["light"]["source"] = "d65"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    assert "did you mean 'D65'" in _rig_check(path, capsys)


def test_a_known_light_source_loads(sim_rig_data: dict[str, Any]) -> None:
    for name in ("projector", "E", "D65", "FL2"):
        data = copy.deepcopy(sim_rig_data)
        data["light"]["source"] = name
        assert rig_from_dict(data, source="inline").light.source == name


def test_rig_check_refuses_a_black_level_at_the_adc_maximum(
    tmp_path: Path, sim_rig_data: dict[str, Any], capsys
) -> None:
    data = copy.deepcopy(sim_rig_data)
    data["sim"]["sensor"].update(black_level_dn=5000, adc_bits=12)
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    err = _rig_check(path, capsys)
    assert "black_level_dn 5000" in err and "4095" in err and "adc_bits" in err, err
    data["sim"]["sensor"].update(adc_bits=14)  # 5000 < 16383: a valid 14-bit black level
    assert rig_from_dict(data, source="inline").sim.sensor.black_level_dn == 5000


def test_a_misspelt_top_level_key_is_named_before_the_key_it_hides(
    tmp_path: Path, sim_rig_data: dict[str, Any], capsys
) -> None:
    data = copy.deepcopy(sim_rig_data)
    data["camara"] = data.pop("camera")
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    err = _rig_check(path, capsys)
    assert "camara is not a known key; did you mean 'camera'?" in err, err
    assert "is missing" not in err and "more problem" not in err, err


def test_a_misspelt_nested_key_gets_a_did_you_mean(sim_rig_data: dict[str, Any]) -> None:
    data = copy.deepcopy(sim_rig_data)
    data["sim"]["sensor"]["blacklevel_dn"] = 3
    with pytest.raises(ConfigError, match="did you mean 'black_level_dn'"):
        rig_from_dict(data, source="inline")


def test_a_session_file_given_as_a_rig_says_so(
    tmp_path: Path, sim_rig_data: dict[str, Any], capsys
) -> None:
    session = {"format": 1, "kind": "labkit-session", "status": "complete",
               "rig_source": "rigs/lab.yaml", "rig": sim_rig_data}  # fmt: skip
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(session, sort_keys=False), encoding="utf-8")
    err = _rig_check(path, capsys)
    assert f"{path} is a capture session file, not a rig" in err, err
    assert "`rig:`" in err and "rigs/lab.yaml" in err and "camera.backend" not in err, err
    del session["kind"]  # an older or hand-made session: its `rig:` mapping gives it away
    with pytest.raises(ConfigError, match="is a capture session file"):
        rig_from_dict(session, source="s.yaml")


def test_single_bad_exposure_reports_one_problem(
    tmp_path: Path, sim_rig_data: dict[str, Any]
) -> None:
    data = copy.deepcopy(sim_rig_data)
    data["plan"]["exposures_s"]["filtered"][1] = -0.05
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    assert "more problem" not in str(info.value), str(info.value)


def test_a_rig_variant_is_merged_and_validated_like_a_rig_file(sim_rig_path: Path) -> None:
    rig = load_rig(sim_rig_path)
    small = rig.with_changes({"sim": {"sensor": {"height": 256, "width": 320}}})
    assert (small.sim.sensor.height, small.sim.sensor.width) == (256, 320)
    # every other key is kept, nested ones included, and the original is untouched
    assert small.sim.sensor.full_well_e == rig.sim.sensor.full_well_e
    assert small.sim.lens == rig.sim.lens and small.source == rig.source
    assert rig.sim.sensor.height != 256
    assert rig.with_changes({}).model_dump() == rig.model_dump()
    with pytest.raises(ConfigError, match=r"sim\.sensor\.heigth .*did you mean 'height'"):
        rig.with_changes({"sim": {"sensor": {"heigth": 256}}})
    with pytest.raises(ConfigError, match=r"plan\.illuminations names 'violet'"):
        rig.with_changes({"plan": {"illuminations": ["violet"]}})
