"""``labkit calibrate sensitivity|dispersion|vignetting`` and ``labkit synthesize`` under
mixed or degenerate HDR folders, bad outputs, interruption and a second writer."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from _faults import another_writer, leftovers, ok, read_only, snapshot

from labkit.cli import main
from labkit.io.exr import read_exr, write_exr
from labkit.io.output_folder import RUN_MANIFEST

COMMANDS = {
    "calibrate sensitivity": (["calibrate", "sensitivity", "{H}"], "C2"),
    "calibrate dispersion": (["calibrate", "dispersion", "{H}", "--reference", "600"],
                             "M2/model.yaml"),
    "calibrate vignetting": (["calibrate", "vignetting", "{H}", "--illumination", "600"],
                             "V2/v.yaml"),
    "synthesize": (["synthesize", "{H}", "--sensitivity", "{w}/C/sensitivity.csv"], "Y2"),
}  # fmt: skip


def _args(w: Path, command: str, *, hdr: str = "H", out: str | None = None) -> tuple[list, Path]:
    template, default_out = COMMANDS[command]
    target = w / (out or default_out)
    args = [a.format(H=w / hdr, w=w) for a in template]
    return [*args, "--out", target], target


def companions(out: Path) -> list[Path]:
    """The files a model's run writes beside it (plots, keypoints)."""
    if out.suffix != ".yaml":
        return []
    names = [".png", ".residuals.png", ".keypoints.csv"]
    return [out.with_name(out.stem + n) for n in names]


# -- mixed, incomplete or tampered run folders -------------------------------------------------
def _image(w: Path, scene: str = "disks", illumination: str = "600") -> Path:
    return w / "H" / scene / f"{illumination}.exr"


def _one_deleted(w):
    _image(w).unlink()


def _one_extra(w):
    shutil.copy(_image(w), w / "H" / "disks" / "650.exr")


def _one_from_another_run(w):
    shutil.copy(_image(w, "colorchecker", "600"), _image(w))


def _manifest_garbled(w):
    (w / "H" / RUN_MANIFEST).write_bytes(b"\xff\x00garbage")


def _hdr_yaml_deleted(w):
    (w / "H" / "hdr.yaml").unlink()


def _missing(w):
    shutil.rmtree(w / "H")


def _a_file(w):
    shutil.rmtree(w / "H")
    (w / "H").write_text("not an HDR folder")


MIXED = {
    "an image deleted": (_one_deleted, ["600.exr"]),
    "an extra image": (_one_extra, ["650.exr"]),
    "an image of another run": (_one_from_another_run, ["600.exr"]),
    "a garbled run manifest": (_manifest_garbled, [RUN_MANIFEST]),
    "hdr.yaml deleted": (_hdr_yaml_deleted, ["hdr.yaml"]),
    "missing folder": (_missing, ["H"]),
    "a file": (_a_file, ["H"]),
}


@pytest.mark.parametrize("name", MIXED)
@pytest.mark.parametrize("command", COMMANDS)
def test_a_mixed_or_incomplete_hdr_folder_is_refused(probe, workspace, command, name):
    spoil, mentions = MIXED[name]
    spoil(workspace)
    args, out = _args(workspace, command)
    outcome = probe.case(command, "mixed input set").run(
        args, outputs=[out, *companions(out)], mentions=mentions
    )
    ok(outcome)


# -- degenerate images in a hand-assembled folder (no run manifest) ----------------------------
def _degrade(how: str):
    def spoil(w: Path) -> None:
        (w / "H" / RUN_MANIFEST).unlink()  # assembled by hand: the content checks must act
        path = _image(w)
        header, channels = read_exr(path)
        raw = channels["raw"].copy()
        if how == "one NaN pixel":
            raw[5, 7] = np.nan
        elif how == "one Inf pixel":
            raw[5, 7] = np.inf
        elif how == "all zero":
            raw[:] = 0
        elif how == "all saturated":
            raw[:] = 1.0
        elif how == "negated":
            raw = -raw
        write_exr(path, header, {**channels, "raw": raw})

    return spoil


DEGENERATE = ["one NaN pixel", "one Inf pixel", "all zero", "all saturated", "negated"]


@pytest.mark.parametrize("how", DEGENERATE)
@pytest.mark.parametrize("command", COMMANDS)
def test_a_degenerate_image_is_refused_where_it_enters(probe, workspace, command, how):
    _degrade(how)(workspace)
    args, out = _args(workspace, command)
    outcome = probe.case(command, "degenerate image").run(
        args, outputs=[out, *companions(out)], mentions=["600.exr"]
    )
    ok(outcome)


# -- outputs -----------------------------------------------------------------------------------
def _out_cases(command: str) -> dict:
    _, default_out = COMMANDS[command]
    if default_out.endswith(".yaml"):
        return {
            "--out an existing folder": (lambda w: (w / "X.yaml").mkdir(), "X.yaml", ["folder"]),
            "--out named like its plot": (lambda w: (w / "X.png").write_text("old"), "X.png",
                                          ["twice"]),
            "--out under a file": (lambda w: (w / "F").write_text("f"), "F/x.yaml", ["F"]),
            "--out the input folder": (lambda w: None, "H", ["H"]),
            "--out the HDR folder's image": (lambda w: None, "H/disks/600.exr", ["600.exr"]),
        }  # fmt: skip
    return {
        "--out an existing file": (lambda w: (w / "X").write_text("precious"), "X",
                                   ["not a folder"]),
        "--out a folder of other files": (_foreign, "X", ["no labkit run wrote"]),
        "--out the input folder": (lambda w: None, "H", ["H"]),
        "--out under a file": (lambda w: (w / "F").write_text("f"), "F/x", ["F"]),
    }  # fmt: skip


def _foreign(w):
    (w / "X").mkdir()
    (w / "X" / "notes.txt").write_text("precious")


OUT_CASES = [(c, n) for c in COMMANDS for n in _out_cases(c)]


@pytest.mark.parametrize(("command", "name"), OUT_CASES)
def test_a_bad_out_is_refused_and_kept(probe, workspace, command, name):
    prepare, out, mentions = _out_cases(command)[name]
    prepare(workspace)
    args, target = _args(workspace, command, out=out)
    outputs = [target, *companions(target), *([workspace / "H"] if out.startswith("H") else [])]
    ok(probe.case(command, "bad --out").run(args, outputs=outputs, mentions=mentions))


@pytest.mark.parametrize("command", COMMANDS)
def test_a_second_writer_is_refused(probe, workspace, command):
    args, out = _args(workspace, command)
    with another_writer(out):
        outcome = probe.case(command, "two writers").run(
            args, outputs=[out, *companions(out)], mentions=["test-holder"]
        )
    ok(outcome)


@pytest.mark.parametrize("command", COMMANDS)
def test_a_read_only_place_is_a_clear_error(probe, workspace, command):
    (workspace / "ro").mkdir()
    args, out = _args(workspace, command, out="ro/out.yaml" if "dis" in command or "vig"
                      in command else "ro/out")  # fmt: skip
    with read_only(workspace / "ro"):
        outcome = probe.case(command, "read-only --out").run(
            args, outputs=[out, *companions(out)], mentions=["ro"]
        )
    ok(outcome)


@pytest.mark.parametrize("command", COMMANDS)
def test_a_rerun_replaces_the_previous_set(probe, workspace, command):
    args, out = _args(workspace, command)
    first = probe.case(command, "rerun").run(args, outputs=[out, *companions(out)], expect="ok")
    ok(first)
    ok(probe.run(args, outputs=[out, *companions(out)], expect="ok"))


def test_dispersion_without_plots_removes_the_previous_plots(probe, workspace):
    args, out = _args(workspace, "calibrate dispersion", out="M/model.yaml")
    outcome = probe.case("calibrate dispersion", "rerun").run(
        [*args, "--no-plots"], outputs=[out, *companions(out)], expect="ok"
    )
    ok(outcome)
    assert not (workspace / "M" / "model.png").exists()


KILLS = {
    "calibrate sensitivity": [("labkit.io.output_folder:_manifest", "before", 1),
                              ("labkit.io.output_folder:_put_in_place", "before", 1)],
    "calibrate dispersion": [("labkit.io.output_folder:_move_into_place", "before", 1),
                             ("labkit.io.output_folder:fsync_directory", "before", 1)],
    "synthesize": [("labkit.io.output_folder:_put_in_place", "after", 1)],
}  # fmt: skip
KILL_CASES = [(c, *k) for c, kills in KILLS.items() for k in kills]


@pytest.mark.parametrize(("command", "at", "when", "n"), KILL_CASES)
def test_kill_9_leaves_the_previous_or_the_new_set(probe, workspace, command, at, when, n):
    w = workspace
    out = {"calibrate sensitivity": w / "C", "calibrate dispersion": w / "M" / "model.yaml",
           "synthesize": w / "Y"}[command]  # fmt: skip
    folder = out if out.is_dir() else out.parent
    previous = snapshot(folder)
    args, _ = _args(w, command, out=str(out.relative_to(w)))
    if command == "calibrate dispersion":
        args = [*args[:-2], "--model", "spline", *args[-2:]]  # another model
    probe.case(command, "kill -9").killed(args, at=at, when=when, n=n)
    now = {k: v for k, v in snapshot(folder).items() if not k.startswith(".")}
    old = {k: v for k, v in previous.items() if not k.startswith(".")}
    if now != old:
        same = {k for k in now if now[k] == old.get(k)}
        if same - {"model.keypoints.csv"} and command == "calibrate dispersion":
            probe.judge_external("mixed or partial result", f"unchanged beside new: {same}")
    ok(probe.run(args, outputs=[out, *companions(out)], expect="ok"))
    assert leftovers(folder.parent) == []


@pytest.mark.parametrize(
    ("value", "hint"),
    [("2", "fraction"), ("80", "give 0.8"), ("nan", "fraction"), ("x", "not a number")],
)
def test_min_purity_out_of_range_says_what_it_is(probe, workspace, value, hint):
    args, out = _args(workspace, "calibrate dispersion")
    outcome = probe.case("calibrate dispersion", "bad option").run(
        [*args, "--min-purity", value], outputs=[out, *companions(out)],
        mentions=["--min-purity", hint],
    )  # fmt: skip
    ok(outcome)


def test_kill_9_between_renames_is_refused_by_readers_and_finished_by_the_rerun(probe, workspace):
    """A dispersion model's set is put in place one rename at a time (plots first, the model
    last); a kill between them leaves the new plots beside the previous model. Readers of the
    model refuse it, naming the run; the next calibration finishes that set first."""
    w, out = workspace, workspace / "M" / "model.yaml"
    args, _ = _args(w, "calibrate dispersion", out="M/model.yaml")
    args = [*args[:-2], "--model", "spline", *args[-2:]]
    previous_model = out.read_bytes()
    probe.case("calibrate dispersion", "kill -9").killed(
        args, at="labkit.io.output_folder:_move_into_place", when="after", n=1
    )
    assert out.read_bytes() == previous_model  # the model is renamed last
    reader = ["dispersion", "eval", out, "--x", "10", "--y", "10", "--wavelength", "600"]
    outcome = probe.case("dispersion eval", "half-renamed set").run(
        reader, mentions=[str(out), "labkit calibrate dispersion", "run that command again"]
    )
    ok(outcome)
    ok(probe.case("calibrate dispersion", "kill -9").run(
        args, outputs=[out, *companions(out)], expect="ok"
    ))  # fmt: skip
    assert out.read_bytes() != previous_model
    assert leftovers(w / "M") == []


@pytest.mark.parametrize("where", ["absolute", "relative"])
def test_a_session_response_file_outside_the_session_is_not_read(probe, workspace, where):
    """The nominal ratios come from the camera response of the session's rig snapshot; a
    response file it names outside the session is refused, not read."""
    w = workspace
    assert main(["hdr", str(w / "S"), "--out", str(w / "H3"), "--no-progress", "--quiet"]) == 0
    outside = w / "outside.csv"
    outside.write_text("wavelength_nm,R,G,B\n400,1,1,1\n700,1,1,1\n")
    info = yaml.safe_load((w / "S" / "session.yaml").read_text())
    info["rig"]["camera"]["response"] = str(outside) if where == "absolute" else "../outside.csv"
    (w / "S" / "session.yaml").write_text(yaml.safe_dump(info, sort_keys=False))
    outcome = probe.case("calibrate sensitivity", "hostile session").run(
        ["calibrate", "sensitivity", w / "H3", "--out", w / "C3"], outputs=[w / "C3"],
        mentions=["camera.response", "outside the session", "--rig"],
    )  # fmt: skip
    ok(outcome)


# -- options and inputs the audit found misread ------------------------------------------------
def test_a_negative_seed_is_refused_by_the_option(probe, workspace):
    args, out = _args(workspace, "calibrate dispersion")
    outcome = probe.case("calibrate dispersion", "bad option").run(
        [*args, "--seed", "-1"], outputs=[out, *companions(out)], mentions=["--seed", "≥ 0"]
    )
    ok(outcome)


@pytest.mark.parametrize(
    ("value", "hint"),
    [("95", "give 0.95"), ("0", "fraction"), ("nan", "fraction"), ("-1", "fraction")],
)
def test_saturation_out_of_range_names_the_option(probe, workspace, value, hint):
    args, out = _args(workspace, "calibrate sensitivity")
    outcome = probe.case("calibrate sensitivity", "bad option").run(
        [*args, "--saturation", value], outputs=[out], mentions=["--saturation", hint]
    )
    ok(outcome)
    assert "gradient_quantile" not in outcome.err


@pytest.mark.parametrize("command", COMMANDS)
def test_a_capture_session_given_as_the_hdr_folder_says_merge_it_first(probe, workspace, command):
    args, out = _args(workspace, command, hdr="S")
    outcome = probe.case(command, "mixed input set").run(
        args, outputs=[out, *companions(out)],
        mentions=["is a capture session", f"labkit hdr {workspace / 'S'} --out"],
    )  # fmt: skip
    ok(outcome)
    assert f"--out {workspace / 'S'}`" not in outcome.err  # never advise writing into S


def test_a_sensitivity_folder_points_to_its_table(probe, workspace):
    w = workspace
    args, out = _args(w, "synthesize")
    args[args.index(str(w / "C" / "sensitivity.csv"))] = str(w / "C")
    outcome = probe.case("synthesize", "bad option").run(
        args, outputs=[out], mentions=["is a folder", str(w / "C" / "sensitivity.csv")]
    )
    ok(outcome)


def test_a_sensitivity_wavelength_out_of_range_names_its_line(probe, workspace):
    table = workspace / "C" / "sensitivity.csv"
    lines = table.read_text().splitlines()
    first = lines[1].split(",")
    first[0] = "1200"
    lines[1] = ",".join(first)
    table.write_text("\n".join(lines) + "\n")
    args, out = _args(workspace, "synthesize")
    outcome = probe.case("synthesize", "bad option").run(
        args, outputs=[out], mentions=["sensitivity.csv", "line 2", "wavelength_nm", "1200"]
    )
    ok(outcome)


def test_a_mask_of_another_size_names_the_option_and_both_sizes(probe, workspace):
    np.save(workspace / "mask.npy", np.ones((10, 10)))
    args, out = _args(workspace, "calibrate vignetting")
    outcome = probe.case("calibrate vignetting", "bad option").run(
        [*args, "--mask", workspace / "mask.npy"], outputs=[out, *companions(out)],
        mentions=["--mask", "mask.npy", "(10, 10)", "(64, 96)"],
    )  # fmt: skip
    ok(outcome)


def test_a_damaged_session_of_the_hdr_images_is_named_not_replaced_by_the_default_rig(
    probe, workspace
):
    w = workspace
    assert main(["hdr", str(w / "S"), "--out", str(w / "H3"), "--no-progress", "--quiet"]) == 0
    text = (w / "S" / "session.yaml").read_text()
    (w / "S" / "session.yaml").write_text(text[: len(text) // 3])
    outcome = probe.case("calibrate sensitivity", "hostile session").run(
        ["calibrate", "sensitivity", w / "H3", "--out", w / "C3"], outputs=[w / "C3"],
        mentions=["session.yaml", "truncated"],
    )  # fmt: skip
    ok(outcome)
