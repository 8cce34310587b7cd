"""The ``labkit`` command line: known outputs, one-line errors, no tracebacks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from labkit.bench import Measurement, write_report
from labkit.cli import main
from labkit.io import read_raw_tiff


def test_version_and_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("labkit ")
    assert main([]) == 0
    help_text = capsys.readouterr().out
    for command in ("rig", "sim", "demo", "bench"):
        assert command in help_text


def test_rig_check_summarises_the_thesis_plan(
    thesis_rig_path: Path, sim_rig_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["rig", "check", str(thesis_rig_path)]) == 0
    out = capsys.readouterr().out
    # thesis protocol: 2 scenes × (3 exposures × 15 + 7 filters × 7 exposures × 5) + darks
    # (3 × 15 + 7 × 5) = 580 + 80
    assert "660 frames" in out
    assert "CFA GBRG" in out and "measured '442 nm'" in out
    assert main(["rig", "check", str(sim_rig_path)]) == 0  # the shipped rig auto-brackets
    assert "8 illuminations, auto-bracketed" in capsys.readouterr().out


def test_rig_check_error_is_one_line_without_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "format: 1\ncamera: {backend: usb3}\n"
        "slider: {driver: sim, port: sim, positions: {1: {name: a}}}\n"
    )
    result = subprocess.run(
        [sys.executable, "-m", "labkit", "rig", "check", str(bad)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert f"{bad}: camera.backend is 'usb3'" in result.stderr


def test_sim_render_writes_a_known_frame(tmp_path: Path, small_rig_file: Path) -> None:
    out = tmp_path / "frame.tiff"
    args = ["sim", "render", str(small_rig_file), "--scene", "colorchecker",
            "--illumination", "550", "--exposure", "0.1", "--out", str(out),
            "--preview", str(tmp_path / "p.png")]  # fmt: skip
    assert main(args) == 0
    image, meta = read_raw_tiff(out)
    assert image.shape == (64, 96) and image.dtype == np.uint16
    assert meta["scene"] == "colorchecker" and meta["illumination"] == "550"
    assert meta["exposure_s"] == 0.1 and meta["cfa"] == "GBRG"
    assert 32 <= image.min() and image.max() <= 4095
    assert (tmp_path / "p.png").stat().st_size > 0
    again = tmp_path / "again.tiff"
    assert main([*args[:-4], "--out", str(again)]) == 0
    assert np.array_equal(read_raw_tiff(again)[0], image), "same seed and frame id → same frame"


def test_eight_bit_preview_keeps_dark_patches(tmp_path: Path, small_rig_file: Path) -> None:
    """The preview subtracts the black level in the frame's own counts (2 DN at 8 bits)."""
    from PIL import Image

    from labkit.rig import load_rig
    from labkit.sim import SimulatedRig, colorchecker_patch_boxes

    args = ["sim", "render", str(small_rig_file), "--scene", "colorchecker", "--illumination",
            "unfiltered", "--exposure", "0.006", "--bits", "8", "--out", str(tmp_path / "f.tiff"),
            "--preview", str(tmp_path / "p.png")]  # fmt: skip
    assert main(args) == 0
    preview = np.asarray(Image.open(tmp_path / "p.png"))
    scene = SimulatedRig(load_rig(small_rig_file)).scene("colorchecker")
    x0, y0, x1, y1 = colorchecker_patch_boxes(scene)[0]  # dark skin, ≈ 16 counts at 8 bits
    patch = preview[int(y0) + 1 : int(y1), int(x0) + 1 : int(x1)]
    assert patch.size and patch.min() > 20, "dark skin must not be clipped to black"


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--scene", "disk", "defines no scene 'disk'"),
        ("--illumination", "475", "no illumination '475'"),
        ("--exposure", "-1", "--exposure must be > 0 s"),
        ("--exposure", "100", "exposure 100 s is outside"),
    ],
)
def test_sim_render_bad_input(
    tmp_path: Path, small_rig_file: Path, capsys: pytest.CaptureFixture[str],
    option: str, value: str, message: str,
) -> None:  # fmt: skip
    args = {"--scene": "disks", "--illumination": "550", "--exposure": "0.1"}
    args[option] = value
    flat = [item for pair in args.items() for item in pair]
    out = tmp_path / "f.tiff"
    assert main(["sim", "render", str(small_rig_file), *flat, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists(), "nothing is written on error"


def test_bench_report_files(tmp_path: Path) -> None:
    cases = [Measurement("render", 2.0, [1.9, 2.0, 2.1], 100.0, target_s=15.0, passed=True,
                         extra={"size": "64x96"})]  # fmt: skip
    md = write_report(tmp_path, {"sim": cases}, ["a note"])
    data = json.loads((tmp_path / "bench.json").read_text())
    assert data["stages"]["sim"][0]["seconds"] == 2.0
    assert data["machine"]["cores"] >= 1
    text = md.read_text()
    assert "| render | 2.000 | 3 | 100 | 15 | pass | size=64x96 |" in text
    assert "- a note" in text
