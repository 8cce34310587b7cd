"""``labkit hdr`` on captured sessions: outputs, accuracy against the simulator, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from _helpers import write_rig

from labkit.cli import main
from labkit.errors import DataError
from labkit.hdr.truth import effective_exposures
from labkit.io import read_raw_exr, read_raw_tiff
from labkit.protocol import Engine
from labkit.protocol.hardware import open_hardware
from labkit.rig import load_rig
from labkit.session import Session, sha256_file
from labkit.sim import SimulatedRig

HDR_PLAN = {
    "sim.sensor.width": 96,
    "sim.sensor.height": 64,
    "plan.scenes": ["colorchecker"],
    "plan.illuminations": ["unfiltered", "550"],
    "plan.exposures_s": {"unfiltered": [0.002, 0.008, 0.032], "filtered": [0.02, 0.08, 0.32]},
    "plan.replicates": {"unfiltered": 4, "filtered": 4},
}


def _capture(rig_file: Path, folder: Path) -> Session:
    rig = load_rig(rig_file)
    session, _ = Session.open_for(folder, rig)
    with open_hardware(rig, fast=True) as hw:
        Engine(rig, hw.camera, hw.slider, hw.stage, session).run()
    return Session.open(folder)


@pytest.fixture(scope="module")
def captured(tmp_path_factory, sim_rig_path):
    """A 48-frame session: colorchecker under unfiltered light and the 550 nm filter."""
    root = tmp_path_factory.mktemp("hdr")
    rig_file = write_rig(root, sim_rig_path, **HDR_PLAN)
    return rig_file, _capture(rig_file, root / "session")


@pytest.fixture
def session_copy(captured, tmp_path):
    """A private copy of the captured session (safe to damage)."""
    _, session = captured
    target = tmp_path / "session"
    shutil.copytree(session.folder, target)
    return target


def _truth(rig_file: Path, session: Session, illumination: str, reference_s: float):
    """Noise-free signal at the reference exposure, fraction of saturation (true shutter)."""
    world = SimulatedRig(load_rig(rig_file))
    records = list(session.records.values())
    effective = effective_exposures(records, illumination=illumination)[reference_s]
    saturation = records[0]["saturation_dn"] - records[0]["black_level"]
    rate = world.irradiance("colorchecker", illumination) * world.sensor.prnu_map
    return rate * effective * world.sensor.model.gain_factor(0.0) / saturation


def _true_ratio(session: Session, illumination: str, reference_s: float, exposure_s: float):
    effective = effective_exposures(session.records.values(), illumination=illumination)
    return effective[reference_s] / effective[exposure_s]


@pytest.mark.parametrize("method", ["thesis", "noise"])
def test_session_merges_to_the_simulated_truth(captured, tmp_path, method):
    from labkit.hdr import run_hdr

    rig_file, session = captured
    run = run_hdr(session.folder, tmp_path / "hdr", method=method)
    assert sorted(o.exr.relative_to(run.out).as_posix() for o in run.outputs) == [
        "colorchecker/550.exr",
        "colorchecker/unfiltered.exr",
    ]
    for output in run.outputs:
        image = read_raw_exr(output.exr)
        illumination = output.job.illumination
        assert image.cfa == "GBRG" and image.illumination == illumination
        assert image.exposure_s == min(
            HDR_PLAN["plan.exposures_s"]["filtered" if illumination == "550" else "unfiltered"]
        )
        assert image.wavelength_nm == (550.0 if illumination == "550" else None)
        assert (image.variance is not None) == (method == "noise")
        assert image.labkit["scene"] == "colorchecker" and image.labkit["method"] == method
        assert np.isfinite(image.raw).all()
        assert output.preview.is_file()
        for row in output.result.exposures:  # scaling factors against the true shutter
            true = _true_ratio(session, illumination, image.exposure_s, row.exposure_s)
            assert row.factor == pytest.approx(true, rel=0.003)
        truth = _truth(rig_file, session, illumination, image.exposure_s)
        exposed = truth * 16 > 0.05  # properly exposed at the longest exposure
        relative = image.raw[exposed] / truth[exposed] - 1
        assert abs(float(np.median(relative))) < 0.005
        # measured 0.0302 / 0.0310: the lens blur lets dim pixels beside edges pass the cut
        assert float(np.sqrt(np.mean(relative**2))) < 0.035
    index = yaml.safe_load(run.index.read_text())
    assert index["method"] == method and len(index["images"]) == 2
    assert index["images"][0]["exposures"][0]["nominal_factor"] == 1.0


def test_missing_darks_are_refused_unless_no_dark(tmp_path, sim_rig_path):
    from labkit.hdr import run_hdr

    plan = {**HDR_PLAN, "plan.dark_frames": False, "plan.illuminations": ["unfiltered"]}
    rig_file = write_rig(tmp_path, sim_rig_path, **plan)
    session = _capture(rig_file, tmp_path / "s")
    with pytest.raises(DataError, match=r"no dark frames at 2ms, 8ms, 32ms.*--no-dark"):
        run_hdr(session.folder, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    run = run_hdr(session.folder, tmp_path / "out", no_dark=True, method="noise")
    image = read_raw_exr(run.outputs[0].exr)
    assert image.labkit["dark_subtraction"] == "black level only"
    assert any("--no-dark" in w for w in image.labkit["warnings"])
    noise = image.labkit["noise"]["constant_variance_dn2"]
    assert {v["from"] for v in noise.values()} == {"fit"}


def test_corrupt_tiff_names_the_frame_and_leaves_no_partial_exr(session_copy, tmp_path):
    from labkit.hdr import run_hdr

    session = Session.open(session_copy)
    record = next(r for r in session.records.values() if r["illumination"] == "unfiltered")
    (session_copy / record["file"]).write_bytes(b"II*\x00garbage")
    with pytest.raises(DataError, match=rf"{record['key']}.*--verify"):
        run_hdr(session_copy, tmp_path / "out")
    leftovers = [p for p in (tmp_path / "out").rglob("*") if p.is_file()]
    assert all(p.suffix in (".exr", ".png") and not p.name.startswith(".") for p in leftovers)
    assert not (tmp_path / "out" / "colorchecker" / "unfiltered.exr").exists()


def _edit_manifest(folder: Path, edit) -> None:
    path = folder / "frames.jsonl"
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    edit(lines)
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))


def test_mismatched_sizes_and_cfa_are_refused(session_copy, tmp_path):
    from labkit.hdr import plan_hdr
    from labkit.io import write_raw_tiff

    def shrink(lines):
        lines[5]["shape"] = [32, 48]

    _edit_manifest(session_copy, shrink)  # the record lies about its file: it is named
    with pytest.raises(DataError, match=r"frames.jsonl says it is 32×48 but its file .* 64×96"):
        plan_hdr(session_copy)
    record = json.loads((session_copy / "frames.jsonl").read_text().splitlines()[5])
    image, meta = read_raw_tiff(session_copy / record["file"])
    write_raw_tiff(session_copy / record["file"], image[:32, :48], meta)  # a smaller frame
    with pytest.raises(DataError, match=r"is 32×48 but frame .* is 64×96.*different sizes"):
        plan_hdr(session_copy)

    def other_cfa(lines):
        lines[5]["shape"] = [64, 96]
        lines[7]["pixel_format"] = "BayerRG12"

    _edit_manifest(session_copy, other_cfa)
    with pytest.raises(DataError, match=r"has CFA RGGB .* GBRG"):
        plan_hdr(session_copy)


def test_frame_of_wrong_size_on_disk_is_named(session_copy, tmp_path):
    from labkit.hdr import plan_hdr, run_hdr
    from labkit.io import write_raw_tiff

    session = Session.open(session_copy)
    record = next(r for r in session.records.values() if r["replicate"] == 2 and not r["dark"])
    image, meta = read_raw_tiff(session_copy / record["file"])
    write_raw_tiff(session_copy / record["file"], image[:32], meta)
    size = (session_copy / record["file"]).stat().st_size
    with pytest.raises(DataError, match=rf"{record['key']}.* is {size} bytes but .* recorded"):
        run_hdr(session_copy, tmp_path / "out", illuminations=[record["illumination"]])
    assert not (tmp_path / "out").exists()  # nothing written
    # a record that lies about the shape of a frame that matches its checksum
    record.update(shape=[32, 96], sha256=sha256_file(session_copy / record["file"]), bytes=size)
    session.forget([])
    with pytest.raises(DataError, match=rf"{record['key']}.*32×96 .* 64×96"):
        plan_hdr(session_copy)


def test_cli_prints_a_line_per_image_the_factor_table_and_one_line_errors(
    captured, tmp_path, capsys
):
    _, session = captured
    out = tmp_path / "cli"
    status = main(["hdr", str(session.folder), "--out", str(out), "--no-progress"])
    lines = capsys.readouterr().out.splitlines()
    assert status == 0 and len(lines) == 3, lines  # two images and the closing line
    assert lines[0].startswith("colorchecker/550: 3 exposures 20ms–320ms, factors within ")
    assert "warning" not in " ".join(lines)
    status = main(["hdr", str(session.folder), "--out", str(out), "--no-progress", "--factors"])
    text = capsys.readouterr().out
    assert status == 0
    assert "| exposure | t_ref/t | fitted |" in text and "colorchecker/550" in text
    assert (out / "hdr.yaml").is_file()
    status = main(["hdr", str(tmp_path / "nowhere"), "--out", str(out), "--no-progress"])
    error = capsys.readouterr().err
    assert status == 2 and error.count("\n") == 1 and "nowhere does not exist" in error


# -- a run is one set; frames are verified; session contents stay inside the session --------
def _fingerprint(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*.*")}


def test_an_interrupted_rerun_leaves_the_previous_complete_set(captured, tmp_path):
    from calibration import load_filtered_hdr
    from labkit.hdr import run_hdr

    _, session = captured
    out = tmp_path / "hdr"
    run_hdr(session.folder, out, method="noise", previews=False)
    before = _fingerprint(out)

    def interrupt(output) -> None:
        raise KeyboardInterrupt  # Ctrl-C after the first image of the thesis rerun

    with pytest.raises(KeyboardInterrupt):
        run_hdr(session.folder, out, method="thesis", previews=False, on_image=interrupt)
    assert _fingerprint(out) == before
    assert yaml.safe_load((out / "hdr.yaml").read_text())["method"] == "noise"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hdr"]  # no staging, no lock left
    assert set(load_filtered_hdr(out)) == {"colorchecker"}


def test_a_mixed_hdr_folder_is_refused_by_its_readers(captured, tmp_path, capsys):
    from calibration import load_filtered_hdr
    from labkit.hdr import run_hdr

    _, session = captured
    out = tmp_path / "hdr"
    run_hdr(session.folder, out, previews=False)
    stray = out / "colorchecker" / "600.exr"
    shutil.copy(out / "colorchecker" / "550.exr", stray)
    with pytest.raises(DataError, match=r"mixes files of different runs: colorchecker/600.exr"):
        load_filtered_hdr(out)
    stray.unlink()
    (out / "colorchecker" / "550.exr").write_bytes(b"truncated")
    with pytest.raises(DataError, match=r"550.exr has changed size"):
        load_filtered_hdr(out)
    changed = out / "colorchecker" / "unfiltered.exr"
    changed.write_bytes(changed.read_bytes()[:-1] + b"\0")
    for command in (
        ["reconstruct", str(changed), "--response", "Nikon 5100 (NPL)"],
        ["evaluate", str(changed), "--baselines", "bilinear"],
    ):
        assert main([*command, "--out", str(tmp_path / command[0])]) == 2
        assert "has changed since the `labkit hdr` run" in capsys.readouterr().err
        assert not (tmp_path / command[0]).exists()


def test_two_sessions_merge_into_one_set_and_may_not_overlap(captured, tmp_path):
    from labkit.hdr import run_hdr

    _, session = captured
    lit = tmp_path / "lit"
    shutil.copytree(session.folder, lit)
    _edit_manifest(lit, lambda lines: [r.update(scene="other") for r in lines if not r["dark"]])
    run = run_hdr([session.folder, lit], tmp_path / "hdr", previews=False)
    index = yaml.safe_load((tmp_path / "hdr" / "hdr.yaml").read_text())
    assert sorted(o.job.name for o in run.outputs) == [
        "colorchecker/550",
        "colorchecker/unfiltered",
        "other/550",
        "other/unfiltered",
    ]
    assert index["sessions"] == [str(session.folder), str(lit)]
    assert {i["session"] for i in index["images"] if i["scene"] == "other"} == {str(lit)}
    with pytest.raises(DataError, match=r"is given twice"):
        run_hdr([session.folder, session.folder.parent / "session" / "."], tmp_path / "again")
    duplicate = tmp_path / "duplicate"
    shutil.copytree(session.folder, duplicate)
    with pytest.raises(DataError, match=r"colorchecker/550 is in both session"):
        run_hdr([session.folder, duplicate], tmp_path / "again")
    assert not (tmp_path / "again").exists()


def test_a_bit_flipped_or_swapped_frame_is_refused(session_copy, tmp_path):
    from labkit.hdr import run_hdr

    session = Session.open(session_copy)
    lit = [r for r in session.records.values() if r["illumination"] == "550"]
    short, long = lit[0], next(r for r in lit if r["exposure_s"] != lit[0]["exposure_s"])
    path = session_copy / short["file"]
    data = bytearray(path.read_bytes())
    data[-100] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(DataError, match=rf"{short['key']} .*does not match its recorded sha256"):
        run_hdr(session_copy, tmp_path / "out", illuminations=["550"])
    shutil.copy(session_copy / long["file"], path)  # the longer exposure's frame in its place
    with pytest.raises(DataError, match=rf"{short['key']} .*(sha256|bytes but)"):
        run_hdr(session_copy, tmp_path / "out", illuminations=["550"])
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        ({"file": "../../outside/x.tiff"}, "not a path inside the session's frames/"),
        ({"file": "/etc/passwd"}, "not a path inside the session's frames/"),
        ({"file": "frames/../../../etc/passwd"}, "not a path inside the session's frames/"),
        ({"scene": "../../../escaped"}, "scene '../../../escaped' cannot name a file"),
        ({"illumination": "a/b"}, "illumination 'a/b' cannot name a file"),
        ({"exposure_s": "fast"}, "key 'exposure_s' is 'fast'"),
        ({"exposure_s": -1.0}, "not a positive number"),
        ({"replicate": True}, "key 'replicate' is True"),
        ({"shape": [64]}, r"shape \[64\] is not"),
        ({"sha256": None}, "key 'sha256' is None"),
    ],
)
def test_hostile_or_malformed_records_are_refused_naming_the_line(
    session_copy, tmp_path, edit, match
):
    from labkit.hdr import run_hdr

    def hostile(lines):
        lit = next(r for r in lines if not r["dark"])
        lit.update(edit)

    _edit_manifest(session_copy, hostile)
    manifest = (session_copy / "frames.jsonl").read_bytes()
    with pytest.raises(DataError, match=rf"frames.jsonl line \d+ .*{match}") as error:
        run_hdr(session_copy, tmp_path / "out")
    assert "root:" not in str(error.value)  # nothing of /etc/passwd was read
    assert not (tmp_path / "out").exists() and not (tmp_path / "escaped").exists()
    assert (session_copy / "frames.jsonl").read_bytes() == manifest  # a reader writes nothing


def test_the_cli_refuses_an_output_folder_it_did_not_write(captured, tmp_path, capsys):
    _, session = captured
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.pdf").write_text("precious")
    status = main(["hdr", str(session.folder), "--out", str(out), "--no-progress"])
    error = capsys.readouterr().err
    assert status == 2 and "no labkit run wrote" in error and error.count("\n") == 1
    assert sorted(p.name for p in out.iterdir()) == ["thesis.pdf"]
