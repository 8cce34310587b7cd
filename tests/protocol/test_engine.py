"""The capture engine on the simulated rig: right frames, stop/resume, faults, bad input."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest
from _helpers import THESIS_EXPOSURES, expected_counts, quick_plan

from labkit.errors import ConfigError, DeviceError
from labkit.io import read_raw_tiff
from labkit.protocol import CaptureStopped, Engine, build_plan
from labkit.protocol.engine import Progress
from labkit.protocol.hardware import open_hardware
from labkit.rig import load_rig
from labkit.session import MANIFEST_FILE, Session, key_of
from labkit.sim import SimCamera


def _run(rig, folder: Path, **engine_options):
    session, _ = Session.open_for(folder, rig)
    with open_hardware(rig, fast=True) as hw:
        engine = Engine(rig, hw.camera, hw.slider, hw.stage, session, **engine_options)
        return engine.run(), session, hw


def test_plan_runs_into_a_session_with_the_right_light_in_every_frame(
    quick_rig_file: Path, tmp_path: Path
) -> None:
    rig = load_rig(quick_rig_file)
    report, session, hw = _run(rig, tmp_path / "s")
    plan = build_plan(rig)
    assert report.status == "complete" and session.status == "complete"
    assert sorted(session.records) == sorted(k.id for k in plan.keys())
    ids = [r["frame_id"] for r in session.records.values()]
    assert len(set(ids)) == len(ids)
    world = hw.camera.rig
    reference = SimCamera(world, seed=99)
    for record in session.records.values():
        key = key_of(record)
        image, _ = read_raw_tiff(session.folder / record["file"])
        expected, clean = expected_counts(world, key.scene, key.illumination, key.exposure_s)
        # the slider's moves reached the simulated light, and darks were covered
        if clean.mean() > 0.2:
            assert image[clean].mean() == pytest.approx(expected[clean].mean(), rel=0.02), key.id
        else:  # mostly saturated, blooming spoils the rest: compare with a fresh grab
            reference.set_scene(key.scene or "disks")
            reference.set_illumination(key.illumination)
            fresh = reference.grab(key.exposure_s)[0].image
            assert image.mean() == pytest.approx(fresh.mean(), rel=0.02), key.id
        assert record["exposure_readback_s"] == pytest.approx(key.exposure_s)
    assert session.verify() == {}


def test_stop_then_resume_completes_without_duplicates(quick_rig_file: Path, tmp_path: Path):
    rig = load_rig(quick_rig_file)
    stop = threading.Event()

    class StopAfter(Progress):
        def __init__(self) -> None:
            self.done = 0

        def advance(self, frames: int) -> None:
            self.done += frames
            if self.done == 9:
                stop.set()

    with pytest.raises(CaptureStopped, match="run the same command again"):
        _run(rig, tmp_path / "s", progress=StopAfter(), stop=stop)
    session = Session.open(tmp_path / "s")
    assert session.status == "stopped" and len(session.records) == 9
    first_ids = {r["frame_id"] for r in session.records.values()}
    report, session, _ = _run(rig, tmp_path / "s")
    assert report.stored_before == 9 and report.stored_now == len(build_plan(rig).keys()) - 9
    ids = [r["frame_id"] for r in session.records.values()]
    assert len(set(ids)) == len(ids) and first_ids <= set(ids)  # noise never replayed
    assert [run["status"] for run in session.info["runs"]] == ["stopped", "complete"]


def test_corrupt_frame_is_recaptured_on_resume(quick_rig_file: Path, tmp_path: Path) -> None:
    rig = load_rig(quick_rig_file)
    _, session, _ = _run(rig, tmp_path / "s")
    victim = next(iter(session.records.values()))
    (session.folder / victim["file"]).write_bytes(b"garbage")
    session.set_status("running")  # as if a crash happened after the damage
    report, session, _ = _run(rig, tmp_path / "s")
    assert report.recaptured == {victim["key"]: "wrong size"} and report.stored_now == 1
    assert session.verify() == {}


def test_slider_fault_is_reported_with_port_and_reply_and_session_resumes(
    make_rig, tmp_path: Path
) -> None:
    path = make_rig(
        **_quick(), **{"slider.timeout_s": 0.2, "slider.move_timeout_s": 0.5, "slider.retries": 2}
    )
    rig = load_rig(path)
    session, _ = Session.open_for(tmp_path / "s", rig)
    with open_hardware(rig, fast=True) as hw:
        hw.simulator.inject_fault("no_reply", count=100)
        engine = Engine(rig, hw.camera, hw.slider, hw.stage, session)
        with pytest.raises(DeviceError) as caught:
            engine.run()
        message = str(caught.value)
        assert hw.slider.port in message and "reply" in message
        assert session.status == "failed" and session.info["stop_reason"] == message
        hw.simulator.clear_faults()
        report = Engine(rig, hw.camera, hw.slider, hw.stage, session).run()
    assert report.status == "complete"
    assert len(session.records) == len(build_plan(rig).keys())


def test_exposure_outside_camera_bounds_is_rejected_before_anything_moves(
    make_rig, tmp_path: Path
) -> None:
    rig = load_rig(make_rig(**_quick(), **{"plan.exposures_s.filtered": [0.1, 40.0]}))
    session, _ = Session.open_for(tmp_path / "s", rig)
    with open_hardware(rig, fast=True) as hw:
        start = hw.simulator.position
        with pytest.raises(ConfigError, match=r"40 s \(for 450, 600, dark\) are outside"):
            Engine(rig, hw.camera, hw.slider, hw.stage, session).run()
        assert hw.simulator.position == start
        assert hw.camera.next_frame_id == 1
    assert session.records == {}


def test_auto_bracketing_captures_fewer_frames_and_resumes_with_its_choice(
    make_rig, tmp_path: Path
) -> None:
    changes = _quick()
    changes["plan.exposures_s"] = {"unfiltered": "auto", "filtered": "auto"}
    rig = load_rig(make_rig(**changes))
    changes["plan.exposures_s"] = THESIS_EXPOSURES
    fixed = load_rig(make_rig(**changes))
    report, session, _ = _run(rig, tmp_path / "s")
    lit = [r for r in session.records.values() if not r["dark"]]
    fixed_lit = [k for k in build_plan(fixed).keys() if not k.is_dark]
    assert 0 < len(lit) < len(fixed_lit)
    brackets = session.brackets
    assert set(brackets) == {(s, i) for s in rig.plan.scenes for i in rig.illuminations()}
    assert set(report.brackets) == {f"{s}/{i}" for s, i in brackets}
    darks = {r["exposure_s"] for r in session.records.values() if r["dark"]}
    assert darks == {t for times in brackets.values() for t in times}
    again, session2, _ = _run(rig, tmp_path / "s")  # complete: nothing re-metered or re-taken
    assert again.stored_now == 0 and session2.brackets == brackets


def _quick() -> dict:
    return quick_plan()


def test_frames_still_being_written_are_not_captured_again_after_metering(
    make_rig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After each metering the plan is rebuilt; a frame queued but not yet on disk must
    count as taken, or a second grab of the same key races the first to the same file."""
    changes = _quick()
    changes["plan.exposures_s"] = {"unfiltered": "auto", "filtered": "auto"}
    rig = load_rig(make_rig(**changes))
    store = Session.store

    def slow_store(self, key, frame, **facts):
        time.sleep(0.05)  # a slow disk: writes are still pending when the next meter ends
        return store(self, key, frame, **facts)

    monkeypatch.setattr(Session, "store", slow_store)
    report, session, _ = _run(rig, tmp_path / "s")
    lines = (session.folder / MANIFEST_FILE).read_text().splitlines()
    keys = [json.loads(line)["key"] for line in lines]
    assert len(keys) == len(set(keys)) == report.stored_now
    assert session.verify() == {}
