"""A run's output folder is written as one set, by one writer at a time."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from labkit.errors import ConfigError, DataError
from labkit.io.output_folder import (
    RUN_MANIFEST,
    check_output_files,
    check_output_folder,
    lock_file_of,
    staged_output_files,
    staged_output_folder,
    verify_output_file,
    verify_output_folder,
    writer_lock,
)


def _write_set(out: Path, files: dict[str, str], command: str = "labkit holder") -> None:
    with staged_output_folder(out, command=command) as stage:
        for name, text in files.items():
            (stage / name).parent.mkdir(parents=True, exist_ok=True)
            (stage / name).write_text(text)


def _contents(folder: Path) -> dict[str, str]:
    return {
        p.relative_to(folder).as_posix(): p.read_text()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != RUN_MANIFEST
    }


def _siblings(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.parent.iterdir() if p.name != folder.name)


def test_a_set_is_written_with_a_manifest_that_verifies(tmp_path):
    out = tmp_path / "out"
    _write_set(out, {"a.txt": "1", "sub/b.txt": "22"})
    assert _contents(out) == {"a.txt": "1", "sub/b.txt": "22"}
    manifest = verify_output_folder(out, what="test folder", rerun="the test")
    assert manifest is not None and manifest["command"] == "labkit holder"
    assert manifest["files"]["sub/b.txt"]["bytes"] == 2
    assert _siblings(out) == []  # no staging folder, no lock file left beside it
    assert oct(out.stat().st_mode & 0o777) != "0o700"  # not mkdtemp's private mode


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two renames"])
def test_a_new_set_replaces_the_previous_one_as_a_whole(tmp_path, monkeypatch, exchange):
    import labkit.io.output_folder as output_folder

    if not exchange:  # a system or file system without an atomic exchange
        monkeypatch.setattr(output_folder, "_exchange", lambda a, b: False)
    out = tmp_path / "out"
    _write_set(out, {"old.txt": "old", "both.txt": "old"})
    _write_set(out, {"both.txt": "new"})
    assert _contents(out) == {"both.txt": "new"}
    assert _siblings(out) == []


@pytest.mark.parametrize("fail", [RuntimeError("boom"), KeyboardInterrupt()])
def test_a_failed_run_leaves_the_previous_set_and_no_staging(tmp_path, fail):
    out = tmp_path / "out"
    _write_set(out, {"a.txt": "previous"})
    with pytest.raises(type(fail)), staged_output_folder(out, command="labkit holder") as stage:
        (stage / "a.txt").write_text("new")
        raise fail
    assert _contents(out) == {"a.txt": "previous"}
    assert _siblings(out) == []
    verify_output_folder(out, what="test folder", rerun="the test")


def test_a_failed_first_run_leaves_nothing(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError), staged_output_folder(out, command="labkit holder") as stage:
        (stage / "a.txt").write_text("new")
        raise RuntimeError
    assert not out.exists() and _siblings(out) == []


def test_a_full_disk_is_a_clear_error_that_keeps_the_previous_set(tmp_path):
    out = tmp_path / "out"
    _write_set(out, {"a.txt": "previous"})
    with pytest.raises(DataError, match=r"disk is full.*nothing was changed"):
        with staged_output_folder(out, command="labkit holder") as stage:
            (stage / "a.txt").write_text("new")
            raise OSError(errno.ENOSPC, "No space left on device", str(stage / "b.txt"))
    assert _contents(out) == {"a.txt": "previous"}


@pytest.mark.parametrize("kind", ["file", "foreign folder", "symlink"])
def test_outputs_that_are_not_a_run_folder_are_refused_untouched(tmp_path, kind):
    out = tmp_path / "out"
    if kind == "file":
        out.write_text("precious")
        match = "not a folder"
    elif kind == "foreign folder":
        out.mkdir()
        (out / "notes.txt").write_text("precious")
        match = "no labkit run wrote"
    else:
        (tmp_path / "real").mkdir()
        out.symlink_to(tmp_path / "real")
        match = "symbolic link"
    with pytest.raises(ConfigError, match=match):
        _write_set(out, {"a.txt": "new"})
    if kind == "file":
        assert out.read_text() == "precious"
    elif kind == "foreign folder":
        assert _contents(out) == {"notes.txt": "precious"}
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["out", *(["real"] if kind == "symlink" else [])]
    )


def test_an_empty_folder_may_be_the_output(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    _write_set(out, {"a.txt": "1"})
    assert _contents(out) == {"a.txt": "1"}


def test_an_unwritable_place_is_refused_before_any_work(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(ConfigError, match="cannot create files under"):
        check_output_folder(blocker / "out")


_HOLDER = textwrap.dedent(
    """
    import sys, time
    from labkit.io.output_folder import staged_output_folder
    out = sys.argv[1]
    with staged_output_folder(out, command="labkit holder") as stage:
        (stage / "partial.txt").write_text("half")
        print("staged", flush=True)
        time.sleep(60)
    """
)


def _start_holder(out: Path) -> subprocess.Popen:
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(out)], stdout=subprocess.PIPE, text=True
    )
    assert holder.stdout is not None and holder.stdout.readline().strip() == "staged"
    return holder


def test_a_second_writer_is_refused_naming_the_holder(tmp_path):
    out = tmp_path / "out"
    holder = _start_holder(out)
    try:
        with pytest.raises(ConfigError, match=rf"pid {holder.pid} .*labkit holder"):
            _write_set(out, {"a.txt": "second"})
        with pytest.raises(ConfigError, match="being written by another labkit run"):
            with writer_lock(out, command="second"):
                pass
    finally:
        holder.kill()
        holder.wait()
    assert not out.exists()


@pytest.mark.parametrize("previous", [False, True])
def test_kill_9_mid_run_leaves_the_previous_set_and_no_stale_lock(tmp_path, previous):
    out = tmp_path / "out"
    if previous:
        _write_set(out, {"a.txt": "previous"})
    holder = _start_holder(out)
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    if previous:
        assert _contents(out) == {"a.txt": "previous"}
        verify_output_folder(out, what="test folder", rerun="the test")
    else:
        assert not out.exists()
    assert any(name.startswith(".out.staging-") for name in _siblings(out))  # hidden leftover
    _write_set(out, {"a.txt": "rerun"})  # the lock died with its process
    assert _contents(out) == {"a.txt": "rerun"}
    assert _siblings(out) == []  # the rerun removed the killed run's staging folder


def test_the_lock_is_reentrant_in_one_process_and_removed_after(tmp_path):
    out = tmp_path / "out"
    with writer_lock(out, command="outer"):
        info = json.loads(lock_file_of(out).read_text())
        assert info["pid"] == os.getpid() and info["command"] == "outer"
        _write_set(out, {"a.txt": "1"})  # the writer locks it again
        assert lock_file_of(out).exists()
    assert not lock_file_of(out).exists()


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda out: (out / "a.txt").unlink(), "a.txt is missing"),
        (lambda out: (out / "a.txt").write_text("longer"), "a.txt has changed size"),
        (lambda out: (out / "a.txt").write_text("2"), "a.txt has changed content"),
        (lambda out: (out / "extra.exr").write_text("x"), "mixes files.*extra.exr"),
        (lambda out: (out / RUN_MANIFEST).write_text("{"), "not a readable run manifest"),
        (lambda out: (out / RUN_MANIFEST).write_text("[]"), "not a labkit run manifest"),
    ],
)
def test_readers_refuse_a_damaged_or_mixed_set(tmp_path, damage, match):
    out = tmp_path / "out"
    _write_set(out, {"a.txt": "1", "b.txt": "2"})
    damage(out)
    with pytest.raises(DataError, match=match):
        verify_output_folder(out, what="test folder", rerun="the test")


def test_a_folder_without_manifest_is_taken_as_assembled_by_hand(tmp_path):
    (tmp_path / "x.exr").write_text("x")
    assert verify_output_folder(tmp_path, what="test folder", rerun="the test") is None


def test_one_input_file_is_checked_against_its_run(tmp_path):
    out = tmp_path / "out"
    _write_set(out, {"scene/a.exr": "1"})
    verify_output_file(out / "scene" / "a.exr")
    (out / "scene" / "b.exr").write_text("2")
    with pytest.raises(DataError, match="not one of the files"):
        verify_output_file(out / "scene" / "b.exr")
    (out / "scene" / "a.exr").write_text("3")
    with pytest.raises(DataError, match="has changed since"):
        verify_output_file(out / "scene" / "a.exr")
    loose = tmp_path / "loose.exr"
    loose.write_text("x")
    verify_output_file(loose)  # in no run's folder: not checked


# -- a result file and its companions -------------------------------------------------------
def _write_files(paths: list[Path], texts: list[str | None], command: str = "test") -> None:
    with staged_output_files(paths, command=command) as staged:
        for temp, text in zip(staged, texts, strict=True):
            if text is not None:
                temp.write_text(text)


def test_a_result_and_its_companions_are_put_in_place_together(tmp_path):
    paths = [tmp_path / "model.yaml", tmp_path / "model.png", tmp_path / "model.csv"]
    _write_files(paths, ["model 1", "plot 1", "table 1"])
    _write_files(paths, ["model 2", None, "table 2"])  # no plot this time: the old one goes
    assert [p.read_text() if p.exists() else None for p in paths] == ["model 2", None, "table 2"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.csv", "model.yaml"]


def test_a_failed_run_leaves_the_previous_result_and_companions(tmp_path):
    paths = [tmp_path / "model.yaml", tmp_path / "model.png"]
    _write_files(paths, ["model 1", "plot 1"])
    with pytest.raises(RuntimeError), staged_output_files(paths, command="test") as staged:
        staged[0].write_text("model 2")
        raise RuntimeError("killed before its plots")
    assert [p.read_text() for p in paths] == ["model 1", "plot 1"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.png", "model.yaml"]


@pytest.mark.parametrize(
    "names", [["model.png", "model.png"], ["a/../model.yaml", "model.yaml"], ["same", "./same"]]
)
def test_outputs_of_one_run_may_not_collide(tmp_path, names):
    (tmp_path / "a").mkdir()
    paths = [tmp_path / name for name in names]
    paths[0].write_text("precious")
    with pytest.raises(ConfigError, match=r"would write .* twice"):
        _write_files(paths, ["x", "y"])
    assert paths[0].read_text() == "precious"


def test_a_folder_where_a_file_goes_is_refused(tmp_path):
    (tmp_path / "model.png").mkdir()
    with pytest.raises(ConfigError, match="is a folder"):
        check_output_files([tmp_path / "model.yaml", tmp_path / "model.png"])


def test_a_result_needs_its_primary_file(tmp_path):
    with pytest.raises(RuntimeError, match="wrote no"):
        _write_files([tmp_path / "model.yaml", tmp_path / "model.png"], [None, "plot"])
    assert list(tmp_path.iterdir()) == []


def test_another_commands_folder_is_not_replaced(tmp_path):
    out = tmp_path / "out"
    _write_set(out, {"a.txt": "an HDR image"}, command="labkit hdr")
    with pytest.raises(ConfigError, match="holds the outputs of `labkit hdr`"):
        _write_set(out, {"b.txt": "a calibration"}, command="labkit calibrate sensitivity")
    _write_set(out, {"a.txt": "rerun"}, command="labkit hdr --method thesis")  # same program
    assert _contents(out) == {"a.txt": "rerun"}


@pytest.mark.parametrize("owner", [RUN_MANIFEST, "session.yaml"])
def test_nothing_is_written_inside_a_run_folder_or_a_session(tmp_path, owner):
    folder = tmp_path / "owned"
    (folder / "sub").mkdir(parents=True)
    (folder / owner).write_text("{}")
    with pytest.raises(ConfigError, match="lies inside"):
        check_output_files([folder / "sub" / "model.yaml"])
    with pytest.raises(ConfigError, match="lies inside"):
        check_output_folder(folder / "sub" / "out")


def _interrupt_after_renames(monkeypatch, renames: int) -> None:
    """Make a file set's put-in-place stop (as a kill would) after `renames` renames."""
    from labkit.io import output_folder

    original, done = output_folder._move_into_place, [0]

    def move(temp: Path, path: Path) -> None:
        if done[0] == renames:
            raise KeyboardInterrupt
        done[0] += 1
        original(temp, path)

    monkeypatch.setattr(output_folder, "_move_into_place", move)


def test_a_set_stopped_between_renames_is_refused_then_finished_by_the_next_writer(
    tmp_path, monkeypatch
):
    from labkit.io.output_folder import check_file_set

    paths = [tmp_path / "model.yaml", tmp_path / "model.png", tmp_path / "model.csv"]
    _write_files(paths, ["model 1", "plot 1", "table 1"])
    _interrupt_after_renames(monkeypatch, 1)  # companions go first: the table is new
    with pytest.raises(KeyboardInterrupt):
        _write_files(paths, ["model 2", "plot 2", "table 2"])
    monkeypatch.undo()
    assert [p.read_text() for p in paths] == ["model 1", "plot 1", "table 2"]
    with pytest.raises(DataError, match=r"model\.yaml.*`test` run .*stopped while putting"):
        check_file_set(paths[0], what="dispersion model")
    with pytest.raises(DataError, match="stopped while putting"):
        verify_output_file(paths[0])
    # the next writer finishes the committed set before its own work: if it fails, that
    # complete set stays
    with pytest.raises(RuntimeError), staged_output_files(paths, command="test"):
        raise RuntimeError("the rerun fails")
    assert [p.read_text() for p in paths] == ["model 2", "plot 2", "table 2"]
    check_file_set(paths[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == [p.name for p in sorted(paths)]


def test_a_stopped_set_whose_companion_was_dropped_is_finished_without_it(tmp_path, monkeypatch):
    paths = [tmp_path / "model.yaml", tmp_path / "model.png"]
    _write_files(paths, ["model 1", "plot 1"])
    _interrupt_after_renames(monkeypatch, 0)
    with pytest.raises(KeyboardInterrupt):
        _write_files(paths, ["model 2", None])  # --no-plots: the old plot goes
    monkeypatch.undo()
    _write_files(paths, ["model 3", "plot 3"])
    assert [p.read_text() for p in paths] == ["model 3", "plot 3"]


def test_a_journal_is_followed_only_to_the_runs_own_outputs(tmp_path, monkeypatch):
    paths = [tmp_path / "model.yaml", tmp_path / "model.png"]
    _write_files(paths, ["model 1", "plot 1"])
    _interrupt_after_renames(monkeypatch, 0)
    with pytest.raises(KeyboardInterrupt):
        _write_files(paths, ["model 2", "plot 2"])
    monkeypatch.undo()
    (staging,) = tmp_path.glob(".model.yaml.staging-*")
    journal = json.loads((staging / "put-in-place.json").read_text())
    elsewhere = tmp_path / "elsewhere.txt"
    elsewhere.write_text("keep")
    journal["renames"][0]["target"] = str(elsewhere)
    (staging / "put-in-place.json").write_text(json.dumps(journal))
    _write_files(paths, ["model 3", "plot 3"])
    assert elsewhere.read_text() == "keep"
    assert [p.read_text() for p in paths] == ["model 3", "plot 3"]


def test_a_folder_holding_the_runs_input_is_not_replaced(tmp_path):
    out = tmp_path / "out"
    _write_set(out, {"raw.exr": "input"})
    with pytest.raises(ConfigError, match=r"holds this run's input .*raw\.exr"):
        check_output_folder(out, command="labkit holder", inputs=[out / "raw.exr"])
    with pytest.raises(ConfigError, match="holds this run's input"):
        with staged_output_folder(out, command="labkit holder", inputs=[out]):
            pass
    assert _contents(out) == {"raw.exr": "input"}
    check_output_folder(out, command="labkit holder", inputs=[tmp_path / "elsewhere.exr"])


# -- a folder written in place (the demo) ------------------------------------------------------
def _write_in_place(out: Path, files: dict[str, str], fail: bool = False) -> None:
    from labkit.io.output_folder import output_folder_in_place

    with output_folder_in_place(out, command="labkit demo") as folder:
        assert folder == out  # written where it stays: recorded paths remain true
        for name, text in files.items():
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_text(text)
        _write_set(out / "hdr", {"a.exr": "nested run"}, command="labkit hdr")
        if fail:
            raise RuntimeError("the demo fails")


def test_a_folder_written_in_place_becomes_one_set_and_a_failure_restores_the_previous(
    tmp_path,
):
    out = tmp_path / "demo"
    _write_in_place(out, {"report.md": "first"})
    verify_output_folder(out, what="demo folder", rerun="labkit demo")
    with pytest.raises(RuntimeError):
        _write_in_place(out, {"report.md": "second"}, fail=True)
    assert _contents(out) == {"report.md": "first", "hdr/a.exr": "nested run"}
    verify_output_folder(out, what="demo folder", rerun="labkit demo")
    assert _siblings(out) == []
    _write_in_place(out, {"report.md": "third"})
    assert _contents(out)["report.md"] == "third"


_IN_PLACE_HOLDER = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from labkit.io.output_folder import output_folder_in_place
    with output_folder_in_place(sys.argv[1], command="labkit demo") as out:
        (Path(out) / "half.txt").write_text("partial")
        print("writing", flush=True)
        time.sleep(120)
    """
)


def test_a_killed_in_place_run_is_refused_by_readers_and_replaced_by_the_next(tmp_path):
    out = tmp_path / "demo"
    _write_in_place(out, {"report.md": "first"})
    holder = subprocess.Popen(
        [sys.executable, "-c", _IN_PLACE_HOLDER, str(out)], stdout=subprocess.PIPE, text=True
    )
    assert holder.stdout is not None and holder.stdout.readline().strip() == "writing"
    with pytest.raises(DataError, match=r"incomplete: a `labkit demo` run"):
        verify_output_folder(out, what="demo folder", rerun="labkit demo")
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    with pytest.raises(DataError, match="incomplete"):
        verify_output_folder(out, what="demo folder", rerun="labkit demo")
    with pytest.raises(ConfigError, match="`labkit demo`, not of `labkit hdr`"):
        check_output_folder(out, command="labkit hdr")
    _write_in_place(out, {"report.md": "rerun"})
    assert _contents(out) == {"report.md": "rerun", "hdr/a.exr": "nested run"}
    assert _siblings(out) == []
