"""labkit on a Bluesky RunEngine (the real one, on the simulated rig): Algorithm 10 as a
plan, the rig's devices as ophyd devices, and a callback that writes a labkit session
which `labkit session show --verify` accepts and `labkit hdr` merges exactly as it merges
a `labkit capture` session of the same seed and frame order."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _helpers import assert_verified_and_merged_alike, quick_plan
from bluesky import RunEngine

from labkit.bluesky import SessionWriter, labkit_plan, open_devices
from labkit.cli import main
from labkit.errors import ConfigError, DeviceError
from labkit.io import read_raw_tiff
from labkit.protocol import Engine
from labkit.protocol.hardware import open_hardware
from labkit.rig import load_rig
from labkit.session import Session


def _auto_rig(make_rig) -> Path:
    changes = quick_plan()
    changes["plan.exposures_s"] = {"unfiltered": "auto", "filtered": [0.1, 0.5]}
    return make_rig(**changes)


def _bluesky_capture(rig, folder: Path) -> tuple[list[dict], Session]:
    documents: list[dict] = []
    engine = RunEngine({})
    engine.subscribe(lambda name, doc: documents.append((name, doc)))
    engine.subscribe(SessionWriter(folder))
    with open_devices(rig) as devices:
        engine(labkit_plan(devices.camera, devices.slider, rig, stage=devices.stage))
    return documents, Session.open(folder)


def test_a_bluesky_capture_is_a_labkit_session_that_merges_like_labkit_capture(
    make_rig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig_file = _auto_rig(make_rig)
    rig = load_rig(rig_file)
    documents, session = _bluesky_capture(rig, tmp_path / "bluesky")
    assert main(["capture", str(rig_file), "--session", str(tmp_path / "engine"), "--fast",
                 "--yes", "--no-progress"]) == 0  # fmt: skip
    reference = Session.open(tmp_path / "engine")

    # the same plan, auto-bracketing choices, frames and frame order (the simulator's
    # noise is drawn by frame id, so equal ids and equal pixels mean the same captures)
    assert session.status == "complete" and session.info["camera"] == reference.info["camera"]
    assert session.info["plan_fingerprint"] == reference.info["plan_fingerprint"]
    assert session.brackets == reference.brackets and len(session.brackets) == 2
    assert sorted(session.records) == sorted(reference.records)
    assert session.info["stream_statistics"] == reference.info["stream_statistics"]
    for key, record in reference.records.items():
        mine = session.records[key]
        assert set(mine) == set(record), key  # the provenance frames.jsonl carries
        for field in ("frame_id", "exposure_readback_s", "gain_db", "pixel_format", "sim",
                      "black_level", "saturation_dn", "temperature_c"):  # fmt: skip
            assert mine[field] == record[field], (key, field)
        image, _ = read_raw_tiff(session.folder / mine["file"])
        expected, _ = read_raw_tiff(reference.folder / record["file"])
        np.testing.assert_array_equal(image, expected, err_msg=key)

    assert_verified_and_merged_alike(session, tmp_path, capsys, images=2 * 3)

    # the documents: start metadata, and one primary event per stored frame
    names = [name for name, _ in documents]
    assert names[0] == "start" and names[-1] == "stop"
    start = documents[0][1]
    assert start["labkit"]["rig"]["plan"]["exposures_s"]["unfiltered"] == "auto"
    streams = {doc["uid"]: doc["name"] for name, doc in documents if name == "descriptor"}
    events = [doc for name, doc in documents if name == "event"]
    primary = [e for e in events if streams[e["descriptor"]] == "primary"]
    assert len(primary) == len(session.records)
    assert {streams[e["descriptor"]] for e in events} == {
        "primary", "labkit_metering", "labkit_brackets", "labkit_statistics"
    }  # fmt: skip


def test_a_plan_the_camera_cannot_run_is_refused_before_any_document(
    make_rig, tmp_path: Path
) -> None:
    changes = quick_plan()
    changes["plan.exposures_s"] = {"unfiltered": [100.0], "filtered": [0.1]}
    rig = load_rig(make_rig(**changes))
    documents: list = []
    engine = RunEngine({})
    engine.subscribe(lambda name, doc: documents.append(name))
    engine.subscribe(SessionWriter(tmp_path / "s"))
    with open_devices(rig) as devices, pytest.raises(ConfigError, match="outside the camera"):
        engine(labkit_plan(devices.camera, devices.slider, rig, stage=devices.stage))
    assert documents == [] and not (tmp_path / "s").exists()


def test_a_failed_run_leaves_a_session_that_labkit_capture_resumes(
    quick_rig_file: Path, tmp_path: Path
) -> None:
    rig = load_rig(quick_rig_file)
    engine = RunEngine({})
    engine.subscribe(SessionWriter(tmp_path / "s"))
    with open_devices(rig) as devices:
        grab = devices.camera.camera.grab
        calls = iter(range(1000))

        def failing_grab(exposure_s: float, n: int = 1):
            if next(calls) == 10:
                raise DeviceError("camera sim-0: no buffer within 1 s (simulated fault)")
            return grab(exposure_s, n)

        devices.camera.camera.grab = failing_grab  # a fault in the device, not a mock engine
        with pytest.raises(DeviceError, match="simulated fault"):
            engine(labkit_plan(devices.camera, devices.slider, rig, stage=devices.stage))
    session = Session.open(tmp_path / "s")
    assert session.status == "failed" and len(session.records) == 10
    assert "labkit capture --session" in session.info["stop_reason"]

    with open_hardware(rig, fast=True) as hardware:  # resume with labkit's own engine
        report = Engine(
            rig, hardware.camera, hardware.slider, hardware.stage, Session.open_for(
                tmp_path / "s", rig)[0]
        ).run()  # fmt: skip
    assert report.status == "complete" and report.stored_before == 10
    assert Session.open(tmp_path / "s").verify() == {}


def test_the_writer_refuses_a_folder_that_holds_something(tmp_path: Path) -> None:
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not empty"):
        SessionWriter(tmp_path / "s")
