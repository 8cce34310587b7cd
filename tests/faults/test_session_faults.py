"""``labkit rig check``, ``capture``, ``session import`` and ``session show`` under bad
rigs, hostile names, interruption, a second writer and full or read-only disks."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
import yaml
from _faults import another_writer, leftovers, ok, read_only, snapshot
from _helpers import write_rig

from labkit.session import Session

# -- rig check: everything capture would refuse later ------------------------------------------
BAD_RIGS = {
    "an infinite exposure": ({"plan.exposures_s.unfiltered": [".inf"]}, ["exposures_s"]),
    "an odd sensor width": ({"sim.sensor.width": 95}, ["width"]),
    "a 2×2 sensor": ({"sim.sensor.width": 2, "sim.sensor.height": 2}, ["width"]),
    "a negative seed": ({"sim.seed": -1}, ["seed"]),
    "slot 0": ({"slider.positions": {0: {"name": "unfiltered"}}}, ["0"]),
    "an unknown response": ({"camera.response": "Nikon 9999"}, ["Nikon 9999"]),
    "a missing response file": ({"camera.response": "none.csv"}, ["none.csv"]),
    "a response outside the rig folder": ({"camera.response": "../../x.csv"}, ["x.csv"]),
    "a scene named like a path": ({"plan.scenes": ["../up"]}, ["../up"]),
    "NaN gain": ({"camera.gain_db": ".nan"}, ["gain_db"]),
}


@pytest.mark.parametrize("name", BAD_RIGS)
def test_rig_check_refuses_what_capture_would(probe, workspace, sim_rig_path, name):
    changes, mentions = BAD_RIGS[name]
    folder = workspace / "badrig"
    folder.mkdir()
    rig = write_rig(folder, sim_rig_path, **changes)
    text = rig.read_text().replace("'.inf'", ".inf").replace("'.nan'", ".nan")
    rig.write_text(text)
    ok(probe.case("rig check", "bad rig").run(["rig", "check", rig], mentions=mentions))
    capture = ["capture", rig, "--session", workspace / "S2", "--fast", "--yes", "--no-progress"]
    outcome = probe.run(capture, outputs=[workspace / "S2"], mentions=mentions)
    ok(outcome)


@pytest.mark.parametrize(
    ("content", "name"),
    [
        (b"\x89PNG\r\n\x1a\n\xff", "binary"),
        (b"", "empty"),
        (b"- a\n- b\n", "a YAML list"),
        (b"format: 1\ncamera: [", "truncated"),
    ],
)
def test_rig_check_refuses_unreadable_rig_files(probe, workspace, content, name):
    (workspace / "bad.yaml").write_bytes(content)
    ok(probe.case("rig check", "bad rig file").run(["rig", "check", workspace / "bad.yaml"],
                                                   mentions=["bad.yaml"]))  # fmt: skip


# -- capture -----------------------------------------------------------------------------------
def _capture(w: Path, session: str = "S2") -> list:
    return ["capture", w / "rig.yaml", "--session", w / session, "--fast", "--yes", "--no-progress"]


@pytest.mark.parametrize("n", [1, 7, 25])
def test_capture_killed_after_n_frames_resumes_to_a_complete_session(probe, workspace, n):
    w = workspace
    probe.case("capture", "kill -9").killed(
        _capture(w), at="labkit.session.store:Session._append", when="after", n=n
    )
    resumed = probe.run(_capture(w), outputs=[w / "S2"], expect="ok")
    ok(resumed)
    session = Session.open(w / "S2")
    lines = (w / "S2" / "frames.jsonl").read_text().splitlines()
    planned = len(Session.open(w / "S").records)  # the pipeline's complete capture
    assert session.status == "complete" and len(session.records) == planned
    assert len(lines) == planned, "each frame recorded once"
    assert session.verify() == {}
    assert leftovers(w / "S2") == []


def test_capture_refuses_a_second_writer(probe, workspace):
    with another_writer(workspace / "S"):
        outcome = probe.case("capture", "two writers").run(
            _capture(workspace, "S"), outputs=[workspace / "S"], mentions=["test-holder"]
        )
    ok(outcome)


@pytest.mark.parametrize(
    ("prepare", "name", "mentions"),
    [
        (lambda w: (w / "S2").write_text("a file"), "--session a file", ["S2 is a file"]),
        (
            lambda w: (w / "S2").mkdir() or (w / "S2" / "x.txt").write_text("x"),
            "--session a folder of other files",
            ["S2"],
        ),
        (lambda w: None, "--session the HDR folder", ["H"]),
    ],
)
def test_capture_refuses_a_bad_session_folder(probe, workspace, prepare, name, mentions):
    prepare(workspace)
    session = "H" if "HDR" in name else "S2"
    outcome = probe.case("capture", "bad --session").run(
        _capture(workspace, session), outputs=[workspace / session], mentions=mentions
    )
    ok(outcome)


def test_capture_on_a_full_disk_stops_clearly_and_resumes(probe, workspace, small_disk):
    shutil.copy(workspace / "rig.yaml", small_disk / "rig.yaml")
    (small_disk / "filler").write_bytes(b"\0" * (1024 * 1024 - 200 * 1024))
    args = ["capture", small_disk / "rig.yaml", "--session", small_disk / "S", "--fast", "--yes",
            "--no-progress"]  # fmt: skip
    # a capture stops with the frames stored so far: a session to resume, by design
    full = probe.case("capture", "full disk (tmpfs)").run(
        args, extra_ok=[small_disk / "S"], mentions=["disk is full"]
    )
    ok(full)
    (small_disk / "filler").unlink()
    resumed = probe.run(args, outputs=[small_disk / "S"], expect="ok")
    ok(resumed)
    assert len(Session.open(small_disk / "S").records) == len(Session.open(workspace / "S").records)


# -- session import ----------------------------------------------------------------------------
PATTERN = "{scene}_{illumination}_{exposure}_{replicate}.tif"


def _source(w: Path, names: dict[str, str] | None = None) -> Path:
    """TIFFs named like another program's, copied from the session's lit frames."""
    source = w / "src"
    source.mkdir(exist_ok=True)
    for record in Session.open(w / "S").records.values():
        if record["dark"] or record["scene"] != "disks":
            continue
        ms = round(record["exposure_s"] * 1000)
        name = f"{record['scene']}_{record['illumination']}_{ms}ms_{record['replicate']:04d}.tif"
        shutil.copy(w / "S" / record["file"], source / (names or {}).get(name, name))
    return source


def _import(w: Path, source: Path, *extra: object, session: str = "I") -> list:
    return ["session", "import", w / session, "--from", source, "--rig", w / "rig.yaml",
            "--pattern", PATTERN, "--no-progress", *extra]  # fmt: skip


def _unmatched(w: Path) -> Path:
    """Frames named so that no pattern matches them."""
    source = _source(w)
    for number, path in enumerate(sorted(source.iterdir())):
        path.rename(source / f"frame{number:04d}.tif")
    return source


def _hostile(name):
    def make(w):
        source = _source(w)
        first = sorted(source.iterdir())[0]
        first.rename(source / name)
        return source

    return make


def _binary_tiff(w):
    source = _source(w)
    sorted(source.iterdir())[0].write_bytes(b"II*\x00" + b"\xff" * 64)
    return source


def _rgb_tiff(w):
    source = _source(w)
    path = sorted(source.iterdir())[0]
    tifffile.imwrite(path, np.zeros((64, 96, 3), np.uint16))
    return source


def _mixed_sizes(w):
    source = _source(w)
    path = sorted(source.iterdir())[0]
    tifffile.imwrite(path, np.zeros((32, 48), np.uint16))
    return source


IMPORT_CASES = {
    "a scene escaping by name": (_hostile(".._unfiltered_3ms_0009.tif"), [], [".."]),
    "an illumination escaping": (_hostile("disks_..%2f_3ms_0009.tif"), [], ["..%2f"]),
    "nothing matches": (_unmatched, [], ["check --pattern", "frame0000.tif"]),
    "a source that is missing": (lambda w: w / "nowhere", [], ["nowhere"]),
    "a binary TIFF": (_binary_tiff, [], ["disks_"]),
    "an RGB TIFF": (_rgb_tiff, [], ["disks_"]),
    "frames of different sizes": (_mixed_sizes, [], ["disks_"]),
    "--bits 0": (lambda w: _source(w), ["--bits", "0"], ["--bits"]),
    "--saturation -1": (lambda w: _source(w), ["--saturation", "-1"], ["--saturation"]),
    "--map to a missing slot": (lambda w: _source(w), ["--map", "red=9"], ["9"]),
}  # fmt: skip


@pytest.mark.parametrize("name", IMPORT_CASES)
def test_session_import_refuses_bad_sources(probe, workspace, name):
    make, extra, mentions = IMPORT_CASES[name]
    source = make(workspace)
    outcome = probe.case("session import", "bad source").run(
        _import(workspace, source, *extra), outputs=[workspace / "I"], mentions=mentions
    )
    ok(outcome)
    assert not list(workspace.parent.glob("*unfiltered*"))


@pytest.mark.parametrize(
    ("session", "mentions"),
    [("S", ["S", "labkit capture"]), ("H", ["H", "labkit hdr"]), ("raw.tiff", ["raw.tiff"])],
)
def test_session_import_refuses_a_folder_it_did_not_write(probe, workspace, session, mentions):
    source = _source(workspace)
    outcome = probe.case("session import", "bad session folder").run(
        _import(workspace, source, session=session), outputs=[workspace / session],
        mentions=mentions,
    )  # fmt: skip
    ok(outcome)


@pytest.mark.parametrize("n", [1, 4])
def test_session_import_killed_leaves_nothing_and_reruns(probe, workspace, n):
    w = workspace
    source = _source(w)
    probe.case("session import", "kill -9").killed(
        _import(w, source), at="labkit.session.store:Session._append", n=n
    )
    if (w / "I").exists():
        probe.judge_external("mixed or partial result", "a killed import left a session")
    ok(probe.run(_import(w, source), outputs=[w / "I"], expect="ok"))
    assert Session.open(w / "I").verify() == {}
    assert leftovers(w) == []


def test_session_import_on_a_full_disk_leaves_nothing(probe, workspace, small_disk):
    source = _source(workspace)
    (small_disk / "filler").write_bytes(b"\0" * (1024 * 1024 - 120 * 1024))
    outcome = probe.case("session import", "full disk (tmpfs)").run(
        ["session", "import", small_disk / "I", "--from", source, "--rig",
         workspace / "rig.yaml", "--pattern", PATTERN, "--no-progress"],
        outputs=[small_disk / "I"], mentions=["disk is full"],
    )  # fmt: skip
    ok(outcome)
    assert sorted(p.name for p in small_disk.iterdir()) == ["filler"]


# -- session show: read-only, never writes -----------------------------------------------------
def test_session_show_reads_a_read_only_session(probe, workspace):
    manifest = workspace / "S" / "frames.jsonl"
    manifest.write_bytes(manifest.read_bytes() + b'{"key": "torn')
    with read_only(workspace / "S"):
        outcome = probe.case("session show", "read-only input").run(
            ["session", "show", workspace / "S", "--verify"], expect="ok"
        )
    ok(outcome)
    assert manifest.read_bytes().endswith(b'{"key": "torn')


def _escape(w):
    lines = (w / "S" / "frames.jsonl").read_text().splitlines()
    record = json.loads(lines[0])
    record["file"] = "/etc/passwd"
    lines[0] = json.dumps(record)
    (w / "S" / "frames.jsonl").write_text("\n".join(lines) + "\n")


def _scene_escape(w):
    lines = (w / "S" / "frames.jsonl").read_text().splitlines()
    record = json.loads(lines[-1])
    record["scene"] = "../../x"
    lines[-1] = json.dumps(record)
    (w / "S" / "frames.jsonl").write_text("\n".join(lines) + "\n")


SHOW_CASES = {
    "a record pointing at /etc/passwd": (_escape, ["/etc/passwd"]),
    "a binary session.yaml": (lambda w: (w / "S" / "session.yaml").write_bytes(b"\xff" * 30),
                              ["session.yaml"]),
    "session.yaml a YAML list": (lambda w: (w / "S" / "session.yaml").write_text("- 1\n"),
                                 ["session.yaml"]),
    "a record with a scene escaping": (_scene_escape, ["../../x"]),
}  # fmt: skip


@pytest.mark.parametrize("name", SHOW_CASES)
def test_session_show_refuses_hostile_contents(probe, workspace, name):
    spoil, mentions = SHOW_CASES[name]
    spoil(workspace)
    before = snapshot(workspace / "S")
    outcome = probe.case("session show", "hostile session").run(
        ["session", "show", workspace / "S", "--verify"], mentions=mentions
    )
    ok(outcome)
    assert "root:" not in outcome.err + outcome.out
    assert snapshot(workspace / "S") == before


def test_bench_refuses_zero_repeats(probe, workspace):
    outcome = probe.case("bench", "bad option").run(
        ["bench", "sim", "--repeats", "0", "--out", workspace / "B"], outputs=[workspace / "B"],
        mentions=["--repeats"],
    )  # fmt: skip
    ok(outcome)


REPORT_OUTS = {
    "a folder of other files": ("X", ["no labkit run wrote"]),
    "the HDR folder": ("H", ["labkit hdr"]),
    "inside the session": ("S/report", ["lies inside"]),
}


@pytest.mark.parametrize("name", REPORT_OUTS)
@pytest.mark.parametrize("command", [["bench", "sim", "--repeats", "1"], ["demo", "--quick"]])
def test_a_report_folder_is_checked_before_any_work(probe, workspace, command, name):
    out, mentions = REPORT_OUTS[name]
    (workspace / "X").mkdir()
    (workspace / "X" / "notes.txt").write_text("precious")
    top = workspace / out.split("/")[0]
    outcome = probe.case(command[0], "bad --out").run(
        [*command, "--out", workspace / out], outputs=[top], mentions=mentions
    )
    ok(outcome)


def test_session_import_again_replaces_the_earlier_import(probe, workspace):
    source = _source(workspace)
    first = probe.case("session import", "rerun").run(
        _import(workspace, source), outputs=[workspace / "I"], expect="ok"
    )
    ok(first)
    ok(probe.run(_import(workspace, source), outputs=[workspace / "I"], expect="ok"))
    assert Session.open(workspace / "I").verify() == {}


# -- a damaged session.yaml is refused, naming the key and the cause (audit s01–s18) ----------
def _session_yaml(w: Path) -> Path:
    return w / "S" / "session.yaml"


def _cut_before(marker: str, extra: int = 0):
    """A spoiler cutting session.yaml before `marker` (plus `extra` characters of it)."""

    def spoil(w: Path) -> None:
        text = _session_yaml(w).read_text()
        _session_yaml(w).write_text(text[: text.index(marker) + extra])

    return spoil


def _yaml_edit(edit):
    def spoil(w: Path) -> None:
        info = yaml.safe_load(_session_yaml(w).read_text())
        edit(info)
        _session_yaml(w).write_text(yaml.safe_dump(info, sort_keys=False))

    return spoil


def _zero_transmission(info: dict) -> None:
    info["rig"]["slider"]["positions"]["3"]["filter"]["peak_transmission"] = 0


DAMAGED_SESSION_YAML = {
    "no rig (s08)": (_yaml_edit(lambda info: info.pop("rig")), ["session.yaml", "no rig"]),
    "an unknown status (s07)": (_yaml_edit(lambda info: info.update(status="exploded")),
                                ["session.yaml", "status 'exploded'", "status: stopped"]),
    "cut after slider: (s01)": (_cut_before("\n    driver:"),
                                ["truncated", "rig.slider is None; expected a mapping"]),
    "cut before rig.light (s13)": (_cut_before("\n  light:"),
                                   ["truncated", "rig.light is missing", "brackets"]),
    "cut inside the plan (s14)": (_cut_before("\n    dark_frames:"),
                                  ["truncated", "rig.plan.dark_frames is missing"]),
    "cut mid-word (s16)": (_cut_before("- colorchecker", extra=8),
                           ["truncated", "rig.plan.scenes names 'colorc'"]),
    "an invalid rig value (s09)": (
        _yaml_edit(_zero_transmission),
        ["edited", "rig.slider.positions[3].filter.peak_transmission is 0"],
    ),
}  # fmt: skip


@pytest.mark.parametrize("name", DAMAGED_SESSION_YAML)
def test_session_show_refuses_a_damaged_session_yaml(probe, workspace, name):
    spoil, mentions = DAMAGED_SESSION_YAML[name]
    spoil(workspace)
    outcome = probe.case("session show", "damaged session.yaml").run(
        ["session", "show", workspace / "S"], mentions=mentions
    )
    ok(outcome)
    assert "SliderConfig" not in outcome.err


def test_capture_dry_run_refuses_a_truncated_session_yaml(probe, workspace):
    """s18: the dry run reported '0 still to capture … OK' on a cut-off rig snapshot."""
    _cut_before("\n  light:")(workspace)
    outcome = probe.case("capture", "damaged session.yaml").run(
        [*_capture(workspace, "S")[:4], "--dry-run"], mentions=["session.yaml", "truncated"]
    )
    ok(outcome)


def test_an_edited_but_whole_rig_snapshot_is_still_read(probe, workspace):
    """A session.yaml whose rig is whole and valid but differs from its fingerprint (an older
    or hand-edited session) is read; only a damaged one is refused."""
    _yaml_edit(lambda info: info["rig"].update(name="renamed"))(workspace)
    outcome = probe.case("session show", "edited session.yaml").run(
        ["session", "show", workspace / "S"], expect="ok"
    )
    ok(outcome)
    assert "renamed" in outcome.out


@pytest.mark.parametrize(
    ("target", "mentions"),
    [("nope", ["nope does not exist"]),
     ("S/session.yaml", ["give the session folder", "not its session.yaml"])],
)  # fmt: skip
def test_session_show_names_a_missing_folder_or_a_session_yaml(probe, workspace, target, mentions):
    """s12, h26 (same message in hdr): not 'not a labkit session (no session.yaml)'."""
    outcome = probe.case("session show", "bad session path").run(
        ["session", "show", workspace / target], mentions=mentions
    )
    ok(outcome)


def test_session_show_reports_a_torn_last_record(probe, workspace):
    manifest = workspace / "S" / "frames.jsonl"
    manifest.write_bytes(manifest.read_bytes() + b'{"key": "torn')
    outcome = probe.case("session show", "torn manifest").run(
        ["session", "show", workspace / "S"], expect="ok"
    )
    ok(outcome)
    assert "frames.jsonl ends with 1 torn record" in outcome.out


# -- capture: --session and --shape checked in a dry run too; a complete session is verified --
@pytest.mark.parametrize("dry", [True, False], ids=["dry run (c06)", "real run (c09)"])
def test_capture_says_a_session_file_is_a_file(probe, workspace, dry):
    args = ["capture", workspace / "rig.yaml", "--session", workspace / "raw.tiff"]
    args += ["--dry-run"] if dry else ["--fast", "--yes", "--no-progress"]
    outcome = probe.case("capture", "bad --session").run(
        args, outputs=[workspace / "raw.tiff"], mentions=["raw.tiff is a file, not a folder"]
    )
    ok(outcome)


@pytest.mark.parametrize(
    ("shape", "mentions"),
    [("63x95", ["--shape", "'63x95'", "ROWS 63"]), ("64x95", ["--shape", "COLS 95"]),
     ("4x8", ["--shape", "ROWS 4"])],
)  # fmt: skip
def test_capture_checks_shape_as_given(probe, workspace, shape, mentions):
    """c04, c10: was 'sensor size 95×63' (cols×rows), naming no option."""
    outcome = probe.case("capture", "bad option").run(
        [*_capture(workspace), "--dry-run", "--shape", shape], outputs=[workspace / "S2"],
        mentions=mentions,
    )  # fmt: skip
    ok(outcome)


def _frame_file(w: Path, index: int = 0) -> Path:
    return (
        w
        / "S"
        / sorted(Session.open(w / "S").records.values(), key=lambda r: r["key"])[index]["file"]
    )


RESUME_DAMAGE = {
    "frames.jsonl missing (h14)": lambda w: (w / "S" / "frames.jsonl").unlink(),
    "frames.jsonl empty (h03)": lambda w: (w / "S" / "frames.jsonl").write_text(""),
    "a frame deleted (h27)": lambda w: _frame_file(w).unlink(),
    "a frame truncated (h16)": lambda w: _frame_file(w).write_bytes(
        _frame_file(w).read_bytes()[:300]
    ),
    "a frame replaced by another (h17)": lambda w: shutil.copy(_frame_file(w, 1), _frame_file(w)),
    "a record deleted": lambda w: (w / "S" / "frames.jsonl").write_text(
        "".join((w / "S" / "frames.jsonl").read_text().splitlines(keepends=True)[1:])
    ),
}


@pytest.mark.parametrize("name", RESUME_DAMAGE)
def test_resuming_a_complete_session_re_takes_missing_or_damaged_frames(probe, workspace, name):
    """The advice of `labkit hdr` ('resume the capture to re-take them') works: a complete
    session is checked against its plan and its frames' sha256, not trusted."""
    w = workspace
    planned = len(Session.open(w / "S").records)
    RESUME_DAMAGE[name](w)
    outcome = probe.case("capture", "resume a damaged session").run(
        _capture(w, "S"), outputs=[w / "S"], expect="ok"
    )
    ok(outcome)
    assert "marked complete but" in outcome.err and "nothing to do" not in outcome.out
    session = Session.open(w / "S")
    assert session.status == "complete" and len(session.records) == planned
    assert session.verify() == {}
    ok(probe.run(["hdr", w / "S", "--out", w / "H2", "--no-progress", "--quiet"],
                 outputs=[w / "H2"], expect="ok"))  # fmt: skip
    again = probe.run(_capture(w, "S"), outputs=[w / "S"], expect="ok")
    ok(again)
    assert "already complete" in again.out


# -- session import: a frame given twice; an exposure without unit -------------------------------
def test_session_import_refuses_the_same_folder_twice(probe, workspace):
    """i18: every frame was imported twice, renumbered."""
    source = _source(workspace)
    outcome = probe.case("session import", "bad source").run(
        [*_import(workspace, source), "--from", source], outputs=[workspace / "I"],
        mentions=[f"--from {source} is given twice"],
    )  # fmt: skip
    ok(outcome)


def test_session_import_refuses_a_frame_given_twice(probe, workspace):
    """i17: a copy of the source folder doubled every frame."""
    source = _source(workspace)
    shutil.copytree(source, workspace / "copy")
    name = sorted(p.name for p in source.iterdir())[0]
    outcome = probe.case("session import", "bad source").run(
        [*_import(workspace, source), "--from", workspace / "copy"], outputs=[workspace / "I"],
        mentions=[f"src/{name}", f"copy/{name}", "imported twice"],
    )  # fmt: skip
    ok(outcome)


def test_session_import_says_an_exposure_lacks_its_unit(probe, workspace):
    """i05: names like disks_450_100_0001.tif got 'no file matches … check --pattern'."""
    source = _source(workspace)
    for path in source.iterdir():
        path.rename(path.with_name(path.name.replace("ms_", "_")))
    outcome = probe.case("session import", "bad source").run(
        _import(workspace, source), outputs=[workspace / "I"],
        mentions=["{exposure}", "has no unit", "ms)"],
    )  # fmt: skip
    ok(outcome)
