"""The ophyd-async devices and plans on a real RunEngine and the simulated rig: a Bluesky
capture is the session `labkit capture` writes (same keys, brackets, records, pixels, HDR
merge), its documents are valid, small and point at the frames' files, the RunEngine stays
free while the camera integrates, and a run that fails is resumed by either."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import bluesky.plan_stubs as bps
import numpy as np
import pytest
import yaml
from _helpers import assert_verified_and_merged_alike, quick_plan
from bluesky import RunEngine
from bluesky.utils import FailedStatus
from event_model import DocumentNames, schema_validators
from ophyd_async.core import TriggerInfo

from labkit.bluesky import (
    FRAME_FACTS,
    PRIMARY,
    bracket,
    capture_protocol,
    dark_series,
    open_session_devices,
    session_run,
)
from labkit.cli import main
from labkit.errors import ConfigError, DeviceError
from labkit.frame import DARK
from labkit.io import read_raw_tiff
from labkit.rig import load_rig
from labkit.session import Session

MAX_DOCUMENT_BYTES = 64_000


def _auto_rig(make_rig) -> Path:
    changes = quick_plan()
    changes["plan.exposures_s"] = {"unfiltered": "auto", "filtered": [0.1, 0.5]}
    return make_rig(**changes)


def _capture(rig, folder: Path, **options: Any) -> list[tuple[str, dict]]:
    documents: list[tuple[str, dict]] = []
    engine = RunEngine({})
    engine.subscribe(lambda name, doc: documents.append((name, doc)))
    with open_session_devices(rig, folder, **options) as d:
        engine(capture_protocol(d.detector, d.slider, d.scene, d.cover))
    return documents


def test_a_bluesky_capture_is_the_session_labkit_capture_writes(
    make_rig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig_file = _auto_rig(make_rig)
    rig = load_rig(rig_file)
    documents = _capture(rig, tmp_path / "bluesky")
    session = Session.open(tmp_path / "bluesky")
    assert main(["capture", str(rig_file), "--session", str(tmp_path / "engine"), "--fast",
                 "--yes", "--no-progress"]) == 0  # fmt: skip
    reference = Session.open(tmp_path / "engine")

    # session.yaml: the same sections and values, but for the times of day
    mine, theirs = (yaml.safe_load((s.folder / "session.yaml").read_text())
                    for s in (session, reference))  # fmt: skip
    assert list(mine) == list(theirs)
    assert [k for k in mine if mine[k] != theirs[k]] == ["created", "updated", "runs"]
    assert [{k: v for k, v in run.items() if k not in ("started", "stopped")}
            for run in mine["runs"]] == [{"resumed_with": 0, "status": "complete",
                                          "stored": len(reference.records)}]  # fmt: skip
    assert session.brackets == reference.brackets and len(session.brackets) == 2
    # frames.jsonl: the same keys and records; the same pixels (noise is drawn by frame id)
    assert sorted(session.records) == sorted(reference.records)
    for key, record in reference.records.items():
        record_here = session.records[key]
        assert set(record_here) == set(record), key
        different = {f for f in record if record_here[f] != record[f]}
        assert different <= {"stored", "host_timestamp_s", "sha256", "bytes"}, (key, different)
        image, _ = read_raw_tiff(session.folder / record_here["file"])
        expected, _ = read_raw_tiff(reference.folder / record["file"])
        np.testing.assert_array_equal(image, expected, err_msg=key)
    # the log: the same events in the same order
    events = [[json.loads(line)["event"] for line in (s.folder / "log.jsonl").open()]
              for s in (session, reference)]  # fmt: skip
    assert events[0] == events[1]

    assert_verified_and_merged_alike(session, tmp_path, capsys, images=2 * 3)

    _check_documents(documents, session)


def _check_documents(documents: list[tuple[str, dict]], session: Session) -> None:
    """Valid, small, no pixels; each stored frame is one primary event whose file is named
    by one stream resource and indexed by one stream datum."""
    for name, doc in documents:
        schema_validators[DocumentNames[name]].validate(doc)
        size = len(json.dumps(doc))
        assert size <= MAX_DOCUMENT_BYTES, (name, size)
    names = [name for name, _ in documents]
    assert names[0] == "start" and names[-1] == "stop"
    assert documents[-1][1]["exit_status"] == "success"
    streams = {doc["uid"]: doc["name"] for name, doc in documents if name == "descriptor"}
    primary = [d for n, d in documents if n == "event" and streams[d["descriptor"]] == PRIMARY]
    assert len(primary) == len(session.records)
    descriptor = next(d for n, d in documents if n == "descriptor" and d["name"] == PRIMARY)
    assert descriptor["data_keys"]["camera"]["external"] == "STREAM:"
    assert {f"camera-{fact}" for fact in FRAME_FACTS} <= set(descriptor["data_keys"])
    resources = {d["uid"]: d for n, d in documents if n == "stream_resource"}
    datums = [d for n, d in documents if n == "stream_datum"]
    assert len(resources) == len(datums) == len(session.records)
    for event, datum in zip(primary, datums, strict=True):
        resource = resources[datum["stream_resource"]]
        assert datum["seq_nums"] == {"start": event["seq_num"], "stop": event["seq_num"] + 1}
        key = event["data"]["camera-key"]
        assert resource["parameters"]["labkit_key"] == key
        path = Path(resource["uri"].removeprefix("file://")) / resource["parameters"]["template"]
        assert path == (session.folder / session.records[key]["file"]).resolve()
        assert event["data"]["camera-frame_id"] == session.records[key]["frame_id"]
    assert [d["indices"]["start"] for d in datums] == list(range(len(datums)))


def test_the_run_engine_stays_free_while_the_camera_integrates(
    quick_rig_file: Path, tmp_path: Path
) -> None:
    """A 0.5 s exposure on the simulated camera in real time: the slider moves and a
    callback on the RunEngine's loop keeps ticking before the frame is in."""
    rig = load_rig(quick_rig_file)
    engine = RunEngine({})
    ticks: list[float] = []

    async def tick() -> None:
        while True:
            ticks.append(time.monotonic())
            await asyncio.sleep(0.01)

    marks: dict[str, float] = {}
    with open_session_devices(rig, tmp_path / "s", fast=False) as d:

        def body(session: Session):
            yield from bps.mv(d.scene, "disks", d.slider, 1)
            yield from bps.mv(
                d.detector.exposure_s, 0.5, d.detector.scene, "disks",
                d.detector.illumination, "unfiltered", d.detector.replicate, 0,
            )  # fmt: skip
            ticker = asyncio.run_coroutine_threadsafe(tick(), engine.loop)
            marks["trigger"] = time.monotonic()
            yield from bps.trigger(d.detector, group="camera")
            yield from bps.mv(d.slider, 2)
            marks["slider"] = time.monotonic()
            yield from bps.wait("camera")
            marks["frame"] = time.monotonic()
            ticker.cancel()

        engine(session_run(d.detector, body, devices=[d.slider, d.scene]))
    assert marks["frame"] - marks["trigger"] >= 0.5
    assert marks["slider"] < marks["frame"]  # moved while the camera integrated
    during = [t for t in ticks if marks["trigger"] <= t <= marks["trigger"] + 0.45]
    assert len(during) >= 15, len(during)  # ~45 at 10 ms; a blocked loop gives 1 or 2
    assert list(Session.open(tmp_path / "s").records) == ["disks/unfiltered/500ms/r000"]


def test_a_failed_run_is_resumed_by_bluesky_or_labkit_capture(
    quick_rig_file: Path, tmp_path: Path
) -> None:
    rig = load_rig(quick_rig_file)
    for resume_with in ("bluesky", "capture"):
        folder = tmp_path / resume_with
        engine = RunEngine({})
        with open_session_devices(rig, folder) as d:
            grab = d.detector.camera.grab
            calls = iter(range(1000))

            def failing_grab(exposure_s: float, n: int = 1, grab=grab, calls=calls):
                if next(calls) == 10:
                    raise DeviceError("camera sim-0: no buffer within 1 s (simulated fault)")
                return grab(exposure_s, n)

            d.detector.camera.grab = failing_grab  # a fault in the device
            with pytest.raises(FailedStatus) as failed:
                engine(capture_protocol(d.detector, d.slider, d.scene, d.cover))
            assert isinstance(failed.value.__cause__, DeviceError)
        session = Session.open(folder)
        assert session.status == "failed" and len(session.records) == 10
        assert session.info["stop_reason"].startswith("camera sim-0: no buffer within 1 s")
        assert f"labkit capture --session {folder}" in session.info["stop_reason"]
        if resume_with == "bluesky":
            documents = _capture(rig, folder)
            primary = [d for n, d in documents if n == "stream_datum"]
            assert len(primary) == 38 - 10  # only the missing frames
        else:
            assert main(["capture", str(quick_rig_file), "--session", str(folder), "--fast",
                         "--yes", "--no-progress"]) == 0  # fmt: skip
        session = Session.open(folder)
        assert session.status == "complete" and len(session.records) == 38
        assert session.info["runs"][-1]["resumed_with"] == 10
        assert session.verify() == {}


def test_brackets_and_dark_series_compose_into_a_plan_of_your_own(
    quick_rig_file: Path, tmp_path: Path
) -> None:
    rig = load_rig(quick_rig_file)
    engine = RunEngine({})
    documents: list[tuple[str, dict]] = []
    engine.subscribe(lambda name, doc: documents.append((name, doc)))
    with open_session_devices(rig, tmp_path / "s") as d:

        def mine(session: Session):
            yield from bps.mv(d.scene, "disks", d.slider, "unfiltered")
            yield from bracket(d.detector, [0.003, 0.012], scene="disks",
                               illumination="unfiltered", replicates=2)  # fmt: skip
            yield from bps.mv(d.slider, "450")
            yield from bracket(d.detector, [0.1], scene="disks", illumination="450")
            yield from dark_series(d.detector, d.cover, [0.003, 0.1], replicates=2)

        engine(session_run(d.detector, mine, devices=[d.slider, d.scene, d.cover]))
    session = Session.open(tmp_path / "s")
    assert sorted(session.records) == sorted(
        [f"disks/unfiltered/{ms}ms/r00{r}" for ms in ("3", "12") for r in (0, 1)]
        + ["disks/450/100ms/r000"]
        + [f"dark/{ms}ms/r00{r}" for ms in ("3", "100") for r in (0, 1)]
    )
    darks = [r for r in session.records.values() if r["illumination"] == DARK]
    assert len(darks) == 4 and all(r["dark"] and r["scene"] is None for r in darks)
    assert session.verify() == {}
    # not the whole plan: the session says so, and labkit capture completes it
    assert session.status == "stopped"
    assert session.info["stop_reason"].startswith(
        "the run ended with 29 planned frame(s) missing;"
    )  # 38 − 9
    assert main(["capture", str(quick_rig_file), "--session", str(tmp_path / "s"), "--fast",
                 "--yes", "--no-progress"]) == 0  # fmt: skip
    assert Session.open(tmp_path / "s").status == "complete"
    for name, doc in documents:
        schema_validators[DocumentNames[name]].validate(doc)


def test_what_the_devices_refuse(make_rig, quick_rig_file: Path, tmp_path: Path) -> None:
    changes = quick_plan()
    changes["plan.exposures_s"] = {"unfiltered": [100.0], "filtered": [0.1]}
    too_long = load_rig(make_rig(**changes))
    engine = RunEngine({})
    documents: list = []
    engine.subscribe(lambda name, doc: documents.append(name))
    with open_session_devices(too_long, tmp_path / "a") as d:
        with pytest.raises(ConfigError, match="outside the camera"):
            engine(capture_protocol(d.detector, d.slider, d.scene, d.cover))
    assert documents == [] and not (tmp_path / "a").exists()

    rig = load_rig(quick_rig_file)
    with open_session_devices(rig, tmp_path / "b") as d:
        with pytest.raises(ConfigError, match="no slot giving 'green'"):
            d.slider.slot_of("green")
        with pytest.raises(ConfigError, match="no slot 99"):
            d.slider.slot_of(99)

        def lightless(session: Session):  # a frame without a scene that is not a dark
            yield from bps.mv(d.detector.illumination, "unfiltered")
            yield from bps.trigger_and_read([d.detector])

        with pytest.raises(FailedStatus) as failed:
            engine(session_run(d.detector, lightless))
        assert isinstance(failed.value.__cause__, ConfigError)
        assert "must be a dark frame (illumination 'dark'), not 'unfiltered'" in str(
            failed.value.__cause__
        )

        def several(session: Session):
            yield from bps.prepare(d.detector, TriggerInfo(number_of_events=3), wait=True)

        with pytest.raises(FailedStatus) as failed:
            engine(session_run(d.detector, several))
        assert "one frame per trigger, not 3" in str(failed.value.__cause__)
    assert Session.open(tmp_path / "b").records == {}
