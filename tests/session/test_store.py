"""Session storage: durable frames, manifest repair, verification, resume guards."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from labkit.errors import ConfigError, DataError
from labkit.frame import Frame, FrameKey
from labkit.io import read_raw_tiff
from labkit.rig import load_rig
from labkit.session import MANIFEST_FILE, SESSION_FILE, FrameWriter, Session


def _frame(seed: int, shape: tuple[int, int] = (8, 12)) -> Frame:
    image = np.random.default_rng(seed).integers(0, 4096, shape, dtype=np.uint16)
    return Frame(image, seed + 1, 0.01, 0.01, 0.0, "BayerGB12", 1000 * seed, 1.7e9 + seed,
                 extra={"temperature_c": 35.5, "black_level": 32.0})  # fmt: skip


def _key(replicate: int, scene: str | None = "disks") -> FrameKey:
    return FrameKey(scene, "450" if scene else "dark", 0.01, replicate)


@pytest.fixture
def session(tmp_path: Path, sim_rig_path: Path) -> Session:
    return Session.create(tmp_path / "s", load_rig(sim_rig_path))


def test_stored_frame_round_trips_with_record_and_checksum(session: Session) -> None:
    frame = _frame(3)
    record = session.store(_key(2), frame)
    path = session.folder / "frames/disks/450/10ms/r002.tiff"
    assert record["file"] == "frames/disks/450/10ms/r002.tiff" and path.is_file()
    assert record["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    image, metadata = read_raw_tiff(path)
    np.testing.assert_array_equal(image, frame.image)
    assert metadata["exposure_s"] == 0.01 and metadata["frame_id"] == 4
    reopened = Session.open(session.folder)
    stored = reopened.records["disks/450/10ms/r002"]
    assert stored == json.loads(json.dumps(record))
    assert stored["temperature_c"] == 35.5 and stored["host_timestamp_s"] == 1.7e9 + 3
    assert reopened.verify() == {}


def test_torn_manifest_tail_is_dropped(session: Session) -> None:
    session.store(_key(0), _frame(0))
    session.store(_key(1), _frame(1))
    manifest = session.folder / MANIFEST_FILE
    whole = manifest.read_bytes()
    manifest.write_bytes(whole[:-25])  # the second append was cut by a crash
    reader = Session.open(session.folder)  # a reader skips the torn line, writes nothing
    assert list(reader.records) == ["disks/450/10ms/r000"]
    assert manifest.read_bytes() == whole[:-25]
    reopened = Session.open(session.folder, repair=True)  # a writer cuts it off
    assert list(reopened.records) == ["disks/450/10ms/r000"]
    assert manifest.read_bytes() == whole[: whole.index(b"\n") + 1]


def test_damaged_manifest_line_is_an_error(session: Session) -> None:
    session.store(_key(0), _frame(0))
    manifest = session.folder / MANIFEST_FILE
    manifest.write_text("{not json\n" + manifest.read_text())
    with pytest.raises(DataError, match="line 1 is not a frame record"):
        Session.open(session.folder)


def test_verify_finds_missing_and_corrupt_frames_and_forget_compacts(session: Session) -> None:
    for r in range(3):
        session.store(_key(r), _frame(r))
    (session.folder / "frames/disks/450/10ms/r000.tiff").unlink()
    corrupt = session.folder / "frames/disks/450/10ms/r001.tiff"
    data = bytearray(corrupt.read_bytes())
    data[-1] ^= 0xFF
    corrupt.write_bytes(bytes(data))
    problems = session.verify()
    assert problems == {"disks/450/10ms/r000": "file missing",
                        "disks/450/10ms/r001": "checksum mismatch"}  # fmt: skip
    session.forget(problems)
    lines = (session.folder / MANIFEST_FILE).read_text().splitlines()
    assert [json.loads(line)["key"] for line in lines] == ["disks/450/10ms/r002"]


def test_resume_with_another_plan_is_refused_and_touches_nothing(
    session: Session, sim_rig_path: Path, make_rig
) -> None:
    session.store(_key(0), _frame(0))
    before = {p: p.read_bytes() for p in session.folder.rglob("*") if p.is_file()}
    other = load_rig(make_rig(**{"plan.replicates.filtered": 3}))
    with pytest.raises(ConfigError, match=r"plan\.replicates\.filtered: 5 → 3"):
        Session.open_for(session.folder, other)
    after = {p: p.read_bytes() for p in session.folder.rglob("*") if p.is_file()}
    assert after == before
    same, resumed = Session.open_for(session.folder, load_rig(sim_rig_path))
    assert resumed and list(same.records) == ["disks/450/10ms/r000"]


def test_new_session_refuses_a_foreign_non_empty_folder(tmp_path: Path, sim_rig_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not empty"):
        Session.open_for(tmp_path, load_rig(sim_rig_path))
    assert (tmp_path / "notes.txt").read_text() == "mine"
    assert not (tmp_path / SESSION_FILE).exists()
    with pytest.raises(DataError, match="not a labkit session"):
        Session.open(tmp_path)


def test_frame_writer_stores_every_frame_once(session: Session) -> None:
    with FrameWriter(session, workers=2, max_pending=3) as writer:
        for r in range(24):
            writer.submit(_key(r), _frame(r, (64, 96)))
    lines = (session.folder / MANIFEST_FILE).read_text().splitlines()
    keys = sorted(json.loads(line)["key"] for line in lines)
    assert keys == sorted(_key(r).id for r in range(24))
    assert session.verify() == {}
    assert not list(session.folder.rglob("*.part"))


def test_frame_writer_takes_a_key_once_whether_queued_or_stored(session: Session) -> None:
    with FrameWriter(session, workers=1, max_pending=2) as writer:
        writer.submit(_key(0), _frame(0))
        assert writer.has(_key(0)) and not writer.has(_key(1))
        with pytest.raises(ValueError, match=r"r000 is already stored or queued"):
            writer.submit(_key(0), _frame(1))
    assert writer.has(_key(0)) and session.has(_key(0))
    with FrameWriter(session) as again, pytest.raises(ValueError, match="already stored"):
        again.submit(_key(0), _frame(2))
    assert session.verify() == {} and len(session.records) == 1


def test_frame_writer_reports_a_failed_write(session: Session) -> None:
    bad = _frame(0)
    bad.image = bad.image.astype(np.float32)
    writer = FrameWriter(session)
    writer.submit(_key(0), bad)
    with pytest.raises(DataError, match="uint8/uint16"):
        writer.close()
    assert session.records == {} and not writer.has(_key(0))  # free to take again


def test_dark_keys_and_leftover_temp_files(session: Session) -> None:
    record = session.store(_key(1, scene=None), _frame(1))
    assert record["file"] == "frames/dark/10ms/r001.tiff" and record["dark"] is True
    leftover = session.folder / "frames/dark/.r002.tiff.abc.part"
    leftover.write_bytes(b"partial")
    assert session.remove_leftovers() == [leftover]
    assert not leftover.exists()


# -- a damaged session.yaml or record is refused, naming the key --------------------------------
def _rewrite_info(session: Session, edit) -> None:
    info = yaml.safe_load((session.folder / SESSION_FILE).read_text())
    edit(info)
    (session.folder / SESSION_FILE).write_text(yaml.safe_dump(info, sort_keys=False))


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda info: info.pop("rig"), r"damaged or truncated: it has no rig section"),
        (lambda info: info.pop("runs"), r"it has no runs section"),
        (lambda info: info.update(brackets=None), r"brackets is None, expected a mapping"),
        (lambda info: info.update(camera="x"), r"camera is 'x', expected a mapping"),
        (lambda info: info.update(status="exploded"), r"status 'exploded' is not one of"),
        (lambda info: info["rig"].pop("plan"), r"rig\.plan is missing"),
        (lambda info: info["rig"]["camera"].update(gain_db=-1), r"rig\.camera\.gain_db is -1"),
    ],
)
def test_a_damaged_session_yaml_is_refused_naming_the_key(session: Session, edit, match) -> None:
    _rewrite_info(session, edit)
    with pytest.raises(DataError, match=match):
        Session.open(session.folder)


def test_a_truncated_session_yaml_is_refused_and_an_edited_whole_one_read(
    session: Session,
) -> None:
    path = session.folder / SESSION_FILE
    whole = path.read_text()
    for lines in (12, 30, whole.count("\n") - 3):
        path.write_text("".join(whole.splitlines(keepends=True)[:lines]))
        with pytest.raises(DataError, match=r"session.yaml is damaged or truncated"):
            Session.open(session.folder)
    path.write_text(whole)
    _rewrite_info(session, lambda info: info["rig"].update(name="renamed"))
    assert Session.open(session.folder).rig.name == "renamed"  # whole and valid: read


def test_open_says_what_the_path_is(session: Session, tmp_path: Path) -> None:
    with pytest.raises(DataError, match="does not exist"):
        Session.open(tmp_path / "nowhere")
    with pytest.raises(DataError, match=r"give the session folder .*s, not its session.yaml"):
        Session.open(session.folder / SESSION_FILE)
    (tmp_path / "file").write_text("x")
    with pytest.raises(DataError, match="is a file, not a session folder"):
        Session.open(tmp_path / "file")
    with pytest.raises(ConfigError, match="is a file, not a folder"):
        Session.check_creatable(tmp_path / "file")


@pytest.mark.parametrize(
    ("levels", "match"),
    [
        ({"saturation_dn": 0}, r"saturation_dn 0 is not above the black level 32.0"),
        ({"saturation_dn": float("nan")}, r"saturation_dn nan is not a finite number"),
        ({"black_level": -1.0}, r"black_level -1.0 is negative"),
        ({"black_level": "32"}, r"black_level '32' is not a finite number"),
    ],
)
def test_record_levels_are_checked(session: Session, levels, match) -> None:
    session.store(_key(0), _frame(0), saturation_dn=4095.0)
    manifest = session.folder / MANIFEST_FILE
    record = {**json.loads(manifest.read_text()), **levels}
    manifest.write_text(json.dumps(record) + "\n")
    with pytest.raises(DataError, match=rf"line 1 .*{match}"):
        Session.open(session.folder)


def test_levels_not_reported_by_the_camera_are_allowed(session: Session) -> None:
    frame = _frame(0)
    frame.extra.pop("black_level")
    session.store(_key(0), frame)
    assert Session.open(session.folder).records[_key(0).id]["black_level"] is None


def test_a_torn_tail_is_counted_for_readers(session: Session) -> None:
    session.store(_key(0), _frame(0))
    manifest = session.folder / MANIFEST_FILE
    manifest.write_bytes(manifest.read_bytes() + b'{"key": "to')
    assert Session.open(session.folder).torn_records == 1
    assert Session.open(session.folder, repair=True).torn_records == 0  # cut off: re-taken
