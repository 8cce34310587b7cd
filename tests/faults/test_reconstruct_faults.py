"""``labkit reconstruct``, ``evaluate``, ``correct warp``, ``export`` and ``sim render``
under bad and degenerate images, bad models, bad outputs, interruption and a second writer."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
from _faults import FOLDER_KILL_POINTS, another_writer, leftovers, ok, read_only

from labkit.io.exr import read_exr, read_raw_exr, write_exr, write_raw_exr

RECONSTRUCT = "reconstruct"


def _reconstruct(
    w: Path, *extra: object, raw: str = "raw.exr", out: str = "R2", latent: str = "colour"
) -> list:
    """A quick colour reconstruction (``latent="spectral"``: the spectral default)."""
    calibration = ["--rig", w / "rig.yaml"] if "--response" not in extra else ["--cfa", "GBRG"]
    return [RECONSTRUCT, w / raw, *calibration, "--latent", latent, "--out", w / out,
            "--quiet", *extra]  # fmt: skip


# -- bad and degenerate raw images -------------------------------------------------------------
def _exr(how: str):
    def spoil(w: Path) -> None:
        header, channels = read_exr(w / "raw.exr")
        raw = channels["raw"].copy()
        match how:
            case "one NaN pixel":
                raw[3, 3] = np.nan
            case "one Inf pixel":
                raw[3, 3] = -np.inf
            case "all zero":
                raw[:] = 0
            case "all saturated":
                raw[:] = 1
            case "all negative":
                raw = -np.abs(raw) - 0.01
        if how in ("one row", "odd size"):
            image = read_raw_exr(w / "raw.exr")
            cut = image.raw[:1] if how == "one row" else image.raw[:-1, :-1]
            write_raw_exr(w / "raw.exr", dataclasses.replace(image, raw=np.ascontiguousarray(cut)))
            return
        write_exr(w / "raw.exr", header, {"raw": np.ascontiguousarray(raw)})

    return spoil


def _tiff(how: str):
    def spoil(w: Path) -> None:
        data = tifffile.imread(w / "raw.tiff")
        match how:
            case "all zero":
                data = np.zeros_like(data)
            case "all at the maximum":
                data = np.full_like(data, np.iinfo(data.dtype).max)
            case "RGB":
                data = np.stack([data] * 3, axis=-1)
            case "float NaN":
                data = data.astype(np.float32)
                data[0, 0] = np.nan
        tifffile.imwrite(w / "raw.tiff", data)

    return spoil


def _binary(w):
    (w / "raw.exr").write_bytes(b"\x76\x2f\x31\x01" + b"\xff" * 200)


def _empty(w):
    (w / "raw.exr").write_bytes(b"")


def _text(w):
    (w / "raw.exr").write_text("just text\n")


def _missing(w):
    (w / "raw.exr").unlink()


def _folder(w):
    (w / "raw.exr").unlink()
    (w / "raw.exr").mkdir()


def _in_a_changed_run(w):
    header, channels = read_exr(w / "H" / "colorchecker" / "unfiltered.exr")
    write_exr(w / "H" / "colorchecker" / "unfiltered.exr", header,
              {"raw": channels["raw"] * np.float32(1.01)})  # fmt: skip


BAD_RAWS = {
    **{f"EXR {h}": (_exr(h), "raw.exr", ["raw.exr"]) for h in
       ["one NaN pixel", "one Inf pixel", "all zero", "all saturated", "all negative",
        "one row", "odd size"]},
    **{f"TIFF {h}": (_tiff(h), "raw.tiff", ["raw.tiff"]) for h in
       ["all zero", "all at the maximum", "RGB", "float NaN"]},
    "binary EXR": (_binary, "raw.exr", ["raw.exr"]),
    "empty file": (_empty, "raw.exr", ["raw.exr"]),
    "text file": (_text, "raw.exr", ["raw.exr"]),
    "missing": (_missing, "raw.exr", ["raw.exr"]),
    "a folder": (_folder, "raw.exr", ["raw.exr", "is a folder"]),
    "an image of a changed run": (_in_a_changed_run, "H/colorchecker/unfiltered.exr",
                                  ["unfiltered.exr"]),
}  # fmt: skip


@pytest.mark.parametrize("name", BAD_RAWS)
def test_a_bad_or_degenerate_raw_is_refused(probe, workspace, name):
    spoil, raw, mentions = BAD_RAWS[name]
    spoil(workspace)
    outcome = probe.case(RECONSTRUCT, "bad or degenerate raw").run(
        _reconstruct(workspace, raw=raw), outputs=[workspace / "R2"], mentions=mentions
    )
    ok(outcome)


# -- bad calibrations and options --------------------------------------------------------------
def _write(name: str, content: bytes):
    def spoil(w: Path) -> Path:
        (w / name).write_bytes(content)
        return w / name

    return spoil


def _nan_response(w: Path) -> Path:
    text = (w / "C" / "sensitivity.csv").read_text().splitlines()
    fields = text[2].split(",")
    fields[2] = "nan"
    text[2] = ",".join(fields)
    (w / "bad.csv").write_text("\n".join(text) + "\n")
    return w / "bad.csv"


def _negative_response(w: Path) -> Path:
    lines = (w / "C" / "sensitivity.csv").read_text().splitlines()
    out = [lines[0]] + [",".join([f.split(",")[0]] + [f"-{v}" for v in f.split(",")[1:]])
                        for f in lines[1:]]  # fmt: skip
    (w / "bad.csv").write_text("\n".join(out) + "\n")
    return w / "bad.csv"


BAD_OPTIONS = {
    "binary response CSV": (["--response", "BAD_CSV"], _write("bad.csv", b"\xff\xfe\x00" * 40),
                            ["bad.csv"]),
    "empty response CSV": (["--response", "BAD_CSV"], _write("bad.csv", b""), ["bad.csv"]),
    "NaN in the response": (["--response", "BAD_CSV"], _nan_response, ["bad.csv"]),
    "negative response": (["--response", "BAD_CSV"], _negative_response, ["bad.csv"]),
    "unknown response name": (["--response", "Nikon 9999"], None, ["Nikon 9999"]),
    "binary dispersion model": (["--dispersion", "BAD_YAML"],
                                _write("bad.yaml", b"\x00\xff" * 50), ["bad.yaml"]),
    "YAML list as a model": (["--dispersion", "BAD_YAML"], _write("bad.yaml", b"- 1\n- 2\n"),
                             ["bad.yaml"]),
    "missing model": (["--dispersion", "W/none.yaml"], None, ["none.yaml"]),
    "band balance NaN": (["--band-balance", "nan"], None, ["--band-balance", "[0, 1]"]),
    "bands out of order": (["--bands", "600,450"], None, ["--bands"]),
    "bands not numbers": (["--bands", "a,b"], None, ["--bands"]),
    "rtol zero": (["--rtol", "0"], None, ["--rtol"]),
    "rtol NaN": (["--rtol", "nan"], None, ["--rtol"]),
    "negative patch": (["--patch-px", "-8"], None, ["--patch-px"]),
    "negative smoothness": (["--spectral-smoothness", "-1"], None, ["--spectral-smoothness"]),
    "unknown weights": (["--weights", "auto:magic"], None, ["--weights"]),
    "unknown prior": (["--prior", "L7"], None, ["L7"]),
    "scheduler nobody listens on": (["--scheduler", "tcp://127.0.0.1:9"], None, ["127.0.0.1:9"]),
    "scheduler address garbled": (["--scheduler", "tcp://nowhere:xx"], None, ["nowhere:xx"]),
}  # fmt: skip


@pytest.mark.parametrize("name", BAD_OPTIONS)
def test_a_bad_calibration_or_option_is_refused(probe, workspace, name):
    options, prepare, mentions = BAD_OPTIONS[name]
    if prepare is not None:
        prepare(workspace)
    names = {"BAD_CSV": workspace / "bad.csv", "BAD_YAML": workspace / "bad.yaml",
             "W/none.yaml": workspace / "none.yaml"}  # fmt: skip
    options = [str(names.get(o, o)) for o in options]
    outcome = probe.case(RECONSTRUCT, "bad calibration or option").run(
        _reconstruct(workspace, *options), outputs=[workspace / "R2"], mentions=mentions
    )
    ok(outcome)


# -- outputs, reruns, interruption, a second writer --------------------------------------------
BAD_OUTS = {
    "an existing file": (lambda w: (w / "X").write_text("precious"), "X", ["not a folder"]),
    "a folder of other files": (lambda w: (w / "X").mkdir() or (w / "X" / "n.txt").write_text(
        "precious"), "X", ["no labkit run wrote"]),
    "the HDR folder": (lambda w: None, "H", ["labkit hdr"]),
    "inside the HDR folder": (lambda w: None, "H/sub", ["lies inside"]),
    "the session": (lambda w: None, "S", ["S"]),
    "the synthesized folder": (lambda w: None, "Y", ["labkit synthesize"]),
}  # fmt: skip


@pytest.mark.parametrize("name", BAD_OUTS)
def test_a_bad_out_is_refused_and_kept(probe, workspace, name):
    prepare, out, mentions = BAD_OUTS[name]
    prepare(workspace)
    top = workspace / out.split("/")[0]
    outcome = probe.case(RECONSTRUCT, "bad --out").run(
        _reconstruct(workspace, out=out), outputs=[top], mentions=mentions
    )
    ok(outcome)


def test_an_out_holding_the_raw_is_refused_and_kept(probe, workspace):
    (workspace / "Z").mkdir()
    shutil.copy(workspace / "raw.exr", workspace / "Z" / "raw.exr")
    outcome = probe.case(RECONSTRUCT, "bad --out").run(
        _reconstruct(workspace, raw="Z/raw.exr", out="Z"),
        outputs=[workspace / "Z"], mentions=["holds this run's input", "raw.exr"],
    )  # fmt: skip
    ok(outcome)


def test_a_colour_rerun_replaces_a_spectral_set(probe, workspace):
    w = workspace
    first = probe.case(RECONSTRUCT, "rerun").run(
        _reconstruct(w, "--bands", "450,525,600", out="R", latent="spectral"),
        outputs=[w / "R"], expect="ok",
    )  # fmt: skip
    ok(first)
    assert (w / "R" / "spectral.exr").is_file()
    ok(probe.run(_reconstruct(w, out="R"), outputs=[w / "R"], expect="ok"))
    assert not (w / "R" / "spectral.exr").exists()  # the spectral run's image went with its set


def test_a_second_writer_is_refused(probe, workspace):
    with another_writer(workspace / "R"):
        outcome = probe.case(RECONSTRUCT, "two writers").run(
            _reconstruct(workspace, out="R"), outputs=[workspace / "R"], mentions=["test-holder"]
        )
    ok(outcome)


def test_a_read_only_place_is_a_clear_error(probe, workspace):
    (workspace / "ro").mkdir()
    with read_only(workspace / "ro"):
        outcome = probe.case(RECONSTRUCT, "read-only --out").run(
            _reconstruct(workspace, out="ro/R"), outputs=[workspace / "ro"], mentions=["ro"]
        )
    ok(outcome)


def test_a_read_only_input_is_read(probe, workspace):
    (workspace / "in").mkdir()
    shutil.copy(workspace / "raw.exr", workspace / "in" / "raw.exr")
    with read_only(workspace / "in"):
        outcome = probe.case(RECONSTRUCT, "read-only input").run(
            _reconstruct(workspace, raw="in/raw.exr"), outputs=[workspace / "R2"], expect="ok"
        )
    ok(outcome)


RECONSTRUCT_KILLS = {
    "before the solve": ("reconstruction:reconstruct", "before", 1),
    **FOLDER_KILL_POINTS,
}


@pytest.mark.parametrize("point", RECONSTRUCT_KILLS)
def test_kill_9_leaves_the_previous_or_the_new_set(probe, workspace, point):
    at, when, n = RECONSTRUCT_KILLS[point]
    w = workspace
    spectral = _reconstruct(w, "--bands", "450,525,600", out="R", latent="spectral")
    probe.case(RECONSTRUCT, "kill -9").killed_over(
        w / "R", spectral, at=at, when=when, n=n,
        is_new=lambda folder: (folder / "spectral.exr").is_file(),
    )  # fmt: skip
    ok(probe.run(_reconstruct(w, out="R"), outputs=[w / "R"], expect="ok"))
    assert leftovers(w) == []


# -- evaluate, correct warp, export, sim render ------------------------------------------------
def _other_cases(w: Path) -> dict:
    rig = w / "rig.yaml"
    return {
        ("evaluate", "binary raw"): (["evaluate", w / "bad.exr", "--rig", rig, "--out", w / "E"],
                                     [w / "E"], ["bad.exr"]),
        ("evaluate", "foreign --out"): (["evaluate", w / "raw.exr", "--rig", rig, "--scene",
                                         "colorchecker", "--out", w / "S"], [w / "S"], ["S"]),
        ("evaluate", "--out the HDR folder"): (["evaluate", w / "raw.exr", "--rig", rig,
                                                "--scene", "colorchecker", "--out", w / "H"],
                                               [w / "H"], ["labkit hdr"]),
        ("correct warp", "binary model"): (["correct", "warp", w / "raw.exr", "--model",
                                            w / "bad.exr", "--out", w / "c.exr"], [w / "c.exr"],
                                           ["bad.exr"]),
        ("correct warp", "--out over its input"): (["correct", "warp", w / "raw.exr", "--model",
                                                    w / "M" / "model.yaml", "--out",
                                                    w / "raw.exr"], [w / "raw.exr"],
                                                   ["raw.exr", "its own input"]),
        ("correct warp", "--out inside the HDR folder"): (
            ["correct", "warp", w / "raw.exr", "--model", w / "M" / "model.yaml", "--out",
             w / "H" / "c.exr"], [w / "H"], ["lies inside"]),
        ("export", "binary EXR"): (["export", w / "bad.exr", "--to", "envi", "--out",
                                    w / "e.hdr"], [w / "e.hdr", w / "e.img"], ["bad.exr"]),
        ("export", "--out over its input"): (["export", w / "bad.img", "--to", "envi"],
                                             [w / "bad.img", w / "bad.hdr"],
                                             ["bad.img", "its own input"]),
        ("export", "wrong suffix"): (["export", w / "Y" / "disks-multispectral.exr", "--to",
                                      "envi", "--out", w / "e.txt"], [w / "e.txt"], ["e.txt"]),
        ("export", "--out inside a run folder"): (
            ["export", w / "Y" / "disks-multispectral.exr", "--to", "envi", "--out",
             w / "Y" / "e.hdr"], [w / "Y"], ["lies inside"]),
        ("sim render", "unknown scene"): (["sim", "render", rig, "--scene", "moon",
                                           "--illumination", "550", "--exposure", "0.01",
                                           "--out", w / "f.tiff"], [w / "f.tiff"], ["moon"]),
        ("sim render", "negative exposure"): (["sim", "render", rig, "--scene", "disks",
                                               "--illumination", "550", "--exposure", "-1",
                                               "--out", w / "f.tiff"], [w / "f.tiff"],
                                              ["--exposure"]),
        ("sim render", "--out into the session"): (["sim", "render", rig, "--scene", "disks",
                                                    "--illumination", "550", "--exposure",
                                                    "0.01", "--out", w / "S" / "f.tiff"],
                                                   [w / "S"], ["lies inside"]),
        ("sim render", "huge --shape"): (["sim", "render", rig, "--scene", "disks",
                                          "--illumination", "550", "--exposure", "0.01",
                                          "--shape", "100000x100000", "--out", w / "f.tiff"],
                                         [w / "f.tiff"], ["--shape"]),
        ("evaluate", "a spectral EXR as --image"): (
            ["evaluate", w / "raw.exr", "--rig", rig, "--scene", "disks", "--out", w / "E",
             "--image", f"ours={w / 'Y' / 'disks-multispectral.exr'}"], [w / "E"],
            ["--image", "disks-multispectral.exr", "a spectral EXR, not a colour image"]),
        ("evaluate", "a scene with nothing to score"): (
            ["evaluate", w / "raw.exr", "--rig", rig, "--scene", "disks", "--out", w / "E"],
            [w / "E"], ["--scene disks", "not a colour chart", "--truth"]),
        ("evaluate", "a chart too small for its edge strips"): (
            ["evaluate", w / "raw.exr", "--rig", rig, "--scene", "colorchecker", "--out",
             w / "E"], [w / "E"], ["--scene colorchecker", "have no centre", "larger image"]),
        ("evaluate", "a spectral model as --colour-dispersion"): (
            ["evaluate", w / "raw.exr", "--rig", rig, "--scene", "colorchecker", "--out",
             w / "E", "--colour-dispersion", w / "M" / "model.yaml"], [w / "E"],
            ["--colour-dispersion", "model.yaml", "--reference G", "labkit correct warp"]),
        ("sim render", "--out not a TIFF"): (["sim", "render", rig, "--scene", "disks",
                                              "--illumination", "550", "--exposure", "0.01",
                                              "--out", w / "f.exr"], [w / "f.exr"],
                                             ["--out", "f.exr", ".tiff"]),
        ("sim render", "negative seed"): (["sim", "render", rig, "--scene", "disks",
                                           "--illumination", "550", "--exposure", "0.01",
                                           "--seed", "-1", "--out", w / "f.tiff"],
                                          [w / "f.tiff"], ["--seed", "≥ 0"]),
        ("dispersion eval", "NaN wavelength"): (["dispersion", "eval", w / "M" / "model.yaml",
                                                 "--x", "1", "--y", "1", "--wavelength",
                                                 "nan"], [], ["--wavelength", "nan"]),
        ("dispersion eval", "binary model"): (["dispersion", "eval", w / "bad.exr", "--x", "1",
                                               "--y", "1", "--wavelength", "500"], [],
                                              ["bad.exr"]),
        ("dispersion eval", "no wavelength"): (["dispersion", "eval", w / "M" / "model.yaml",
                                                "--x", "1", "--y", "1"], [], ["--wavelength"]),
        ("dispersion eval", "mismatched values"): (["dispersion", "eval", w / "M" / "model.yaml",
                                                    "--x", "1", "2", "3", "--y", "1", "2",
                                                    "--wavelength", "500"], [], ["--x"]),
        ("dispersion crop", "window outside the image"): (
            ["dispersion", "crop", w / "M" / "model.yaml", "--origin", "0,0", "--shape",
             "4000,4000", "--out", w / "crop.yaml"], [w / "crop.yaml"],
            ["does not lie inside"]),
        ("dispersion crop", "binary model"): (
            ["dispersion", "crop", w / "bad.exr", "--origin", "0,0", "--shape", "8,8",
             "--out", w / "crop.yaml"], [w / "crop.yaml"], ["bad.exr"]),
        ("dispersion crop", "--out the model itself"): (
            ["dispersion", "crop", w / "M" / "model.yaml", "--origin", "0,0", "--shape", "8,8",
             "--out", w / "M" / "model.yaml"], [], ["--out", "is the input model"]),
    }  # fmt: skip


OTHER = list(_other_cases(Path("/")))


@pytest.mark.parametrize(("command", "name"), OTHER)
def test_other_commands_refuse_bad_input_and_outputs(probe, workspace, command, name):
    (workspace / "bad.exr").write_bytes(b"\x76\x2f\x31\x01" + b"\xfe" * 300)
    (workspace / "bad.img").write_bytes(b"\x76\x2f\x31\x01" + b"\xfe" * 300)
    args, outputs, mentions = _other_cases(workspace)[command, name]
    outcome = probe.case(command, "bad input or --out").run(
        args, outputs=outputs, mentions=mentions
    )
    ok(outcome)


#: What a command-line message must not advise: Python names and options labkit lacks.
API_WORDING = ("correction='warp'", "correct_spectral", "strip_px", "gradient_quantile")


@pytest.mark.parametrize(("command", "name"), [
    ("evaluate", "a chart too small for its edge strips"),
    ("evaluate", "a spectral model as --colour-dispersion"),
])  # fmt: skip
def test_evaluate_advises_only_what_its_user_can_do(probe, workspace, command, name):
    args, outputs, mentions = _other_cases(workspace)[command, name]
    outcome = probe.case(command, "bad input or --out").run(
        args, outputs=outputs, mentions=mentions
    )
    ok(outcome)
    assert not [w for w in API_WORDING if w in outcome.err], outcome.err


def test_a_raw_that_is_a_folder_is_named_as_one(probe, workspace):
    outcome = probe.case(RECONSTRUCT, "bad or degenerate raw").run(
        _reconstruct(workspace, raw="H"), outputs=[workspace / "R2"],
        mentions=[f"raw image {workspace / 'H'} is a folder"],
    )  # fmt: skip
    ok(outcome)


def test_a_spectral_from_reference_model_for_a_colour_latent_reports_both_needs(probe, workspace):
    """Both problems in one message, in command-line words: following it cannot meet the
    second (a spectral model for a colour reconstruction) after fixing the first."""
    w = workspace
    outcome = probe.case(RECONSTRUCT, "bad calibration or option").run(
        _reconstruct(w, "--dispersion", w / "M" / "model.yaml"), outputs=[w / "R2"],
        mentions=["--dispersion", "spectral from_reference model", "--latent colour",
                  "colour-channel to_reference", "--reference G", "--correction warp"],
    )  # fmt: skip
    ok(outcome)
    assert not [word for word in API_WORDING if word in outcome.err], outcome.err


def test_a_scene_that_is_no_chart_is_scored_with_one_warning(probe, workspace):
    w = workspace
    outcome = probe.case("evaluate", "no chart").run(
        ["evaluate", w / "raw.exr", "--rig", w / "rig.yaml", "--scene", "disks", "--truth",
         "--baselines", "bilinear", "--out", w / "E"], outputs=[w / "E"], expect="ok",
    )  # fmt: skip
    ok(outcome)
    warnings = [line for line in outcome.err.splitlines() if line.startswith("labkit: warning:")]
    assert len(warnings) == 1 and "--scene disks is not a colour chart" in warnings[0], warnings
