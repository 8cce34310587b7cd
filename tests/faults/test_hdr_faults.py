"""``labkit hdr`` under bad sessions, bad outputs, interruption, a second writer and a full
or read-only disk."""

from __future__ import annotations

import errno
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
from _faults import FOLDER_KILL_POINTS, another_writer, leftovers, ok, read_only

HDR = "hdr"


def _hdr(w: Path, *extra: object, session: str = "S", out: str = "H2") -> list[object]:
    return [HDR, w / session, "--out", w / out, "--no-progress", "--quiet", *extra]


def _records(w: Path) -> list[dict]:
    return [json.loads(line) for line in (w / "S" / "frames.jsonl").read_text().splitlines()]


def _write_records(w: Path, records: list[dict]) -> None:
    text = "".join(json.dumps(r) + "\n" for r in records)
    (w / "S" / "frames.jsonl").write_text(text)


def _first_frame(w: Path, *, dark: bool = False) -> Path:
    record = next(r for r in _records(w) if r["dark"] == dark)
    return w / "S" / record["file"]


# -- bad sessions ------------------------------------------------------------------------------
def _missing(w):
    shutil.rmtree(w / "S")


def _a_file(w):
    shutil.rmtree(w / "S")
    (w / "S").write_text("not a session")


def _empty(w):
    shutil.rmtree(w / "S")
    (w / "S").mkdir()


def _binary_yaml(w):
    (w / "S" / "session.yaml").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00" * 8)


def _truncated_yaml(w):
    text = (w / "S" / "session.yaml").read_text()
    (w / "S" / "session.yaml").write_text(text[: len(text) // 3])


def _binary_manifest(w):
    (w / "S" / "frames.jsonl").write_bytes(b"\xff\xfe\x00\x01" * 64)


_DELETE = object()


def _edit_record(key: str, value: object, index: int = 3):
    """A spoiler setting (or, with ``_DELETE``, removing) one key of one manifest record."""

    def spoil(w: Path) -> None:
        records = _records(w)
        if value is _DELETE:
            del records[index][key]
        else:
            records[index][key] = value
        _write_records(w, records)

    return spoil


def _scene_escapes(w):
    records = _records(w)
    for r in records:
        if r["scene"] == "disks":
            r["scene"] = "../../../escaped"
    _write_records(w, records)


def _bit_flip(w):
    frame = _first_frame(w)
    data = bytearray(frame.read_bytes())
    data[-100] ^= 0x10
    frame.write_bytes(bytes(data))


def _swapped_exposure(w):
    records = [r for r in _records(w) if not r["dark"] and r["illumination"] == "unfiltered"]
    short = next(r for r in records if r["exposure_s"] == 0.003)
    long = next(r for r in records if r["exposure_s"] == 0.012 and r["scene"] == short["scene"])
    shutil.copy(w / "S" / long["file"], w / "S" / short["file"])


def _frame_deleted(w):
    _first_frame(w).unlink()


def _frame_truncated(w):
    frame = _first_frame(w)
    frame.write_bytes(frame.read_bytes()[:300])


def _frame_replaced_by_folder(w):
    frame = _first_frame(w)
    frame.unlink()
    frame.mkdir()


def _frame_symlink_out(w):
    frame = _first_frame(w)
    frame.unlink()
    frame.symlink_to("/etc/passwd")


def _dark_bit_flip(w):
    frame = _first_frame(w, dark=True)
    data = bytearray(frame.read_bytes())
    data[-50] ^= 0x01
    frame.write_bytes(bytes(data))


def _manifest_missing(w):
    (w / "S" / "frames.jsonl").unlink()


def _manifest_empty(w):
    (w / "S" / "frames.jsonl").write_text("")


RETAKE = "labkit capture RIG --session"  # advice that works: a resume re-takes damaged frames

BAD_SESSIONS = {
    "missing": (_missing, ["S does not exist"]),
    "a file": (_a_file, ["S"]),
    "empty folder": (_empty, ["S"]),
    "binary session.yaml": (_binary_yaml, ["session.yaml"]),
    "truncated session.yaml": (_truncated_yaml, ["session.yaml"]),
    "binary frames.jsonl": (_binary_manifest, ["frames.jsonl"]),
    "record without a key": (_edit_record("exposure_s", _DELETE), ["exposure_s"]),
    "record with a text exposure": (_edit_record("exposure_s", "fast"), ["exposure_s"]),
    "record with a negative exposure": (_edit_record("exposure_s", -0.1), ["exposure"]),
    "record file outside frames/": (
        _edit_record("file", "../../outside/x.tiff"),
        ["../../outside/x.tiff"],
    ),
    "record file absolute": (_edit_record("file", "/etc/passwd"), ["/etc/passwd"]),
    "scene escaping": (_scene_escapes, ["escaped"]),
    "illumination absolute": (_edit_record("illumination", "/tmp/x"), ["/tmp/x"]),
    "bit-flipped frame": (_bit_flip, ["sha256"]),
    "frame of another exposure": (_swapped_exposure, ["sha256"]),
    "frame deleted": (_frame_deleted, ["r00", RETAKE]),
    "frame truncated": (_frame_truncated, ["r00", RETAKE]),
    "frames.jsonl missing (h04)": (
        _manifest_missing,
        ["frames.jsonl is missing but", "frame file(s)", RETAKE],
    ),
    "frames.jsonl empty (h03)": (
        _manifest_empty,
        ["frames.jsonl lists no frames but", "frame file(s)", RETAKE],
    ),
    "record shape not its file's (h05)": (
        _edit_record("shape", [32, 48]),
        ["frames.jsonl says it is 32×48 but its file"],
    ),
    "record saturation 0 (h06)": (_edit_record("saturation_dn", 0), ["saturation_dn 0"]),
    "record saturation NaN": (_edit_record("saturation_dn", float("nan")), ["saturation_dn"]),
    "record black level negative": (_edit_record("black_level", -1), ["black_level -1"]),
    "record black level null (h08)": (
        _edit_record("black_level", None),
        ["no black level (null", "frames.jsonl", RETAKE],
    ),
    "frame is a folder": (_frame_replaced_by_folder, ["r00"]),
    "frame is a link outside": (_frame_symlink_out, ["r00"]),
    "bit-flipped dark frame": (_dark_bit_flip, ["dark"]),
}


@pytest.mark.parametrize("name", BAD_SESSIONS)
def test_a_bad_session_is_refused_and_nothing_is_written(probe, workspace, name):
    spoil, mentions = BAD_SESSIONS[name]
    spoil(workspace)
    outcome = probe.case(HDR, "bad session").run(
        _hdr(workspace), outputs=[workspace / "H2"], mentions=mentions
    )
    ok(outcome)
    assert "root:" not in outcome.err  # never prints another file's content
    assert not (workspace.parent / "escaped").exists()
    assert not list(workspace.parent.glob("*escaped*"))


# -- bad outputs and options -------------------------------------------------------------------
def _out_file(w):
    (w / "H2").write_text("precious")


def _out_foreign(w):
    (w / "H2").mkdir()
    (w / "H2" / "notes.txt").write_text("precious")


def _out_session(w):
    return "S"


BAD_OUTS = {
    "--out an existing file": (_out_file, "H2", ["not a folder"]),
    "--out a folder of other files": (_out_foreign, "H2", ["no labkit run wrote"]),
    "--out the session itself": (lambda w: None, "S", ["S"]),
    "--out the raw file": (lambda w: None, "raw.tiff", ["raw.tiff"]),
}


@pytest.mark.parametrize("name", BAD_OUTS)
def test_a_bad_out_is_refused_and_kept(probe, workspace, name):
    prepare, out, mentions = BAD_OUTS[name]
    prepare(workspace)
    outcome = probe.case(HDR, "bad --out").run(
        _hdr(workspace, out=out), outputs=[workspace / out], mentions=mentions
    )
    ok(outcome)


@pytest.mark.parametrize(
    ("options", "mentions"),
    [
        (["--scene", "nowhere"], ["nowhere"]),
        (["--illumination", "999"], ["999"]),
        (["--method", "magic"], ["magic"]),
        (["--scene", "../S"], ["../S"]),
    ],
)
def test_bad_options_are_refused(probe, workspace, options, mentions):
    outcome = probe.case(HDR, "bad option").run(
        _hdr(workspace, *options), outputs=[workspace / "H2"], mentions=mentions
    )
    ok(outcome)


# -- a rerun replaces the set; interruption leaves the previous or the new set -----------------
def test_a_rerun_with_another_method_replaces_the_whole_set(probe, workspace):
    outcome = probe.case(HDR, "rerun").run(
        _hdr(workspace, "--method", "thesis", out="H"), outputs=[workspace / "H"], expect="ok"
    )
    ok(outcome)
    assert "method: thesis" in (workspace / "H" / "hdr.yaml").read_text()


KILL_POINTS = {
    "after the 2nd image": ("labkit.hdr.session:write_raw_exr", "after", 2),
    **FOLDER_KILL_POINTS,
}


@pytest.mark.parametrize("point", KILL_POINTS)
def test_kill_9_leaves_the_previous_or_the_new_set(probe, workspace, point):
    at, when, n = KILL_POINTS[point]
    w = workspace
    probe.case(HDR, "kill -9").killed_over(
        w / "H", _hdr(w, "--method", "thesis", out="H"), at=at, when=when, n=n,
        is_new=lambda folder: "method: thesis" in (folder / "hdr.yaml").read_text(),
    )  # fmt: skip
    # downstream accepts it (previous or new complete set), and a rerun cleans up
    assert probe.workspace == w
    downstream = probe.run(
        ["calibrate", "sensitivity", w / "H", "--out", w / "C2"], outputs=[w / "C2"], expect="ok"
    )
    ok(downstream)
    rerun = probe.run(_hdr(w, out="H"), outputs=[w / "H"], expect="ok")
    ok(rerun)
    assert leftovers(w) == []


def test_a_second_writer_is_refused_naming_it(probe, workspace):
    with another_writer(workspace / "H"):
        outcome = probe.case(HDR, "two writers").run(
            _hdr(workspace, out="H"), outputs=[workspace / "H"], mentions=["test-holder", "pid"]
        )
    ok(outcome)


# -- disks -------------------------------------------------------------------------------------
def test_a_full_disk_leaves_nothing_and_says_so(probe, workspace, small_disk):
    big = small_disk / "filler"
    big.write_bytes(b"\0" * (1024 * 1024 - 96 * 1024))
    outcome = probe.case(HDR, "full disk (tmpfs)").run(
        _hdr(workspace, out=str(small_disk / "H")), outputs=[small_disk / "H"],
        mentions=["disk is full"],
    )  # fmt: skip
    ok(outcome)
    assert sorted(p.name for p in small_disk.iterdir()) == ["filler"]


def test_a_simulated_full_disk_leaves_the_previous_set(probe, workspace, monkeypatch):
    import labkit.hdr.session as hdr_session

    calls = []

    def full(path, image, *args, **kwargs):
        calls.append(path)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return original(path, image, *args, **kwargs)

    original = hdr_session.write_raw_exr
    monkeypatch.setattr(hdr_session, "write_raw_exr", full)
    outcome = probe.case(HDR, "full disk (simulated)").run(
        _hdr(workspace, "--method", "thesis", out="H"), outputs=[workspace / "H"],
        mentions=["disk is full"],
    )  # fmt: skip
    ok(outcome)


def test_a_read_only_session_is_merged_without_writing_to_it(probe, workspace):
    with read_only(workspace / "S"):
        outcome = probe.case(HDR, "read-only input").run(
            _hdr(workspace), outputs=[workspace / "H2"], expect="ok"
        )
    ok(outcome)


def test_a_read_only_out_folder_is_a_clear_error(probe, workspace):
    (workspace / "ro").mkdir()
    with read_only(workspace / "ro"):
        outcome = probe.case(HDR, "read-only --out").run(
            _hdr(workspace, out="ro/H"), outputs=[workspace / "ro"],
            mentions=["ro"],
        )  # fmt: skip
    ok(outcome)


def test_a_torn_manifest_line_is_not_repaired_by_a_reader(probe, workspace):
    manifest = workspace / "S" / "frames.jsonl"
    manifest.write_bytes(manifest.read_bytes() + b'{"key": "disks/450/10')
    outcome = probe.case(HDR, "torn manifest").run(
        _hdr(workspace), outputs=[workspace / "H2"], expect="ok"
    )
    ok(outcome)
    assert manifest.read_bytes().endswith(b'{"key": "disks/450/10')
    # h02: not silent: one warning line naming the manifest and the fix
    warnings = [line for line in outcome.err.splitlines() if "warning" in line]
    assert len(warnings) == 1, outcome.err
    assert "frames.jsonl ends with a torn record" in warnings[0] and RETAKE in warnings[0]
    assert "torn record" in (workspace / "H2" / "hdr.yaml").read_text()


def test_a_session_lacking_planned_frames_is_merged_with_one_warning(probe, workspace):
    manifest = workspace / "S" / "frames.jsonl"
    manifest.write_text("".join(manifest.read_text().splitlines(keepends=True)[1:]))
    outcome = probe.case(HDR, "torn manifest").run(
        _hdr(workspace), outputs=[workspace / "H2"], expect="ok"
    )
    ok(outcome)
    warnings = [line for line in outcome.err.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "lacks 1 of its" in warnings[0], outcome.err
    assert RETAKE in warnings[0]


def test_a_session_yaml_given_for_its_folder_says_so(probe, workspace):
    """h26: 'S/session.yaml is not a labkit session (no session.yaml)'."""
    outcome = probe.case(HDR, "bad session").run(
        _hdr(workspace, session="S/session.yaml"), outputs=[workspace / "H2"],
        mentions=["give the session folder", "not its session.yaml"],
    )  # fmt: skip
    ok(outcome)


def test_a_truncated_session_yaml_is_named_not_its_illumination(probe, workspace):
    """s17: 'rig … has no illumination 550' on a rig snapshot cut before its light."""
    path = workspace / "S" / "session.yaml"
    text = path.read_text()
    path.write_text(text[: text.index("\n  light:")])
    outcome = probe.case(HDR, "bad session").run(
        _hdr(workspace), outputs=[workspace / "H2"], mentions=["session.yaml", "truncated"]
    )
    ok(outcome)


def test_a_saturated_frame_set_is_not_merged_silently(probe, workspace):
    """Every frame of one scene at the saturation level: the merge must refuse or flag it."""
    for record in _records(workspace):
        if record["scene"] == "colorchecker" and not record["dark"]:
            path = workspace / "S" / record["file"]
            data = tifffile.imread(path)
            tifffile.imwrite(path, np.full_like(data, 4095 << 4 if data.max() > 4095 else 4095))
    outcome = probe.case(HDR, "bad session").run(
        _hdr(workspace), outputs=[workspace / "H2"], mentions=["changed or replaced"]
    )
    ok(outcome)
