"""Every command's outputs are one set: names that would collide are refused before any
work, a folder another program wrote is never replaced, and nothing is destroyed."""

from __future__ import annotations

from pathlib import Path

import pytest

from labkit.cli import EXPECTED, main


def _run(args: list[str], capsys) -> tuple[int, str]:
    status = main(args)
    return status, capsys.readouterr().err


@pytest.mark.parametrize(
    ("command", "out"),
    [
        (["calibrate", "dispersion", "HDR", "--reference", "600"], "model.png"),
        (["calibrate", "vignetting", "HDR", "--illumination", "600"], "v.png"),
        (["correct", "warp", "RAW.exr", "--model", "MODEL.yaml"], "x.png"),
    ],
)
def test_an_output_named_like_its_own_plot_is_refused_and_kept(tmp_path, capsys, command, out):
    target = tmp_path / out
    target.write_text("an earlier result")
    args = [str(tmp_path / a) if (a.isupper() and "." in a) or a == "HDR" else a for a in command]
    status, err = _run([*args, "--out", str(target)], capsys)
    assert status == EXPECTED and "twice" in err and err.count("\n") == 1
    assert target.read_text() == "an earlier result"


def test_sim_render_with_the_preview_as_the_frame_is_refused(tmp_path, small_rig_file, capsys):
    frame = tmp_path / "p.tiff"
    frame.write_text("an earlier frame")
    args = ["sim", "render", str(small_rig_file), "--scene", "disks", "--illumination", "550",
            "--exposure", "0.01", "--out", str(frame), "--preview", str(frame)]  # fmt: skip
    status, err = _run(args, capsys)
    assert status == EXPECTED and "twice" in err
    assert frame.read_text() == "an earlier frame"


@pytest.mark.parametrize("kind", ["file", "foreign folder"])
@pytest.mark.parametrize(
    "command",
    [
        ["calibrate", "sensitivity", "HDR"],
        ["synthesize", "HDR", "--sensitivity", "S.csv"],
        ["evaluate", "RAW.exr"],
        ["reconstruct", "RAW.exr", "--response", "Nikon 5100 (NPL)"],
    ],
)
def test_folder_outputs_refuse_what_labkit_did_not_write(tmp_path, capsys, command, kind):
    out = tmp_path / "out"
    if kind == "file":
        out.write_text("precious")
    else:
        out.mkdir()
        (out / "notes.txt").write_text("precious")
    args = [str(tmp_path / a) if a in ("HDR", "S.csv", "RAW.exr") else a for a in command]
    status, err = _run([*args, "--out", str(out)], capsys)
    assert status == EXPECTED and err.count("\n") == 1 and "Traceback" not in err
    assert ("not a folder" if kind == "file" else "no labkit run wrote") in err
    kept = out.read_text() if kind == "file" else (out / "notes.txt").read_text()
    assert kept == "precious"


def test_sim_render_writes_frame_and_preview_as_one_set(tmp_path, small_rig_file, capsys):
    frame, preview = tmp_path / "f.tiff", tmp_path / "sub" / "p.png"
    args = ["sim", "render", str(small_rig_file), "--scene", "disks", "--illumination", "550",
            "--exposure", "0.01", "--out", str(frame), "--preview", str(preview)]  # fmt: skip
    status, _ = _run(args, capsys)
    assert status == 0 and frame.stat().st_size > 0 and preview.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.tiff", "sub"]  # nothing left over


def test_inf_exposure_is_refused(tmp_path: Path, small_rig_file: Path, capsys) -> None:
    args = ["sim", "render", str(small_rig_file), "--scene", "disks", "--illumination", "550",
            "--exposure", "inf", "--out", str(tmp_path / "f.tiff")]  # fmt: skip
    status, err = _run(args, capsys)
    assert status == EXPECTED and "--exposure must be > 0 s" in err
    assert list(tmp_path.iterdir()) == []
