"""``labkit target``: the printed chart, rendered at the camera's scale, shows the disks the
detector is to find, at the radius and pitch the chart was made for."""

from __future__ import annotations

import re
import subprocess
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np
import pytest
import yaml
from _report_check import chromium
from PIL import Image

from calibration.disks import detect_disks
from calibration.disks.chart import design_disk_chart, paper_size
from labkit.cli import EXPECTED, main

CAMERA = ["--pixel-um", "3.45", "--focal-mm", "8", "--distance-m", "0.3"]
CSS_PX_PER_MM = 96 / 25.4


def _render(svg: Path, paper_mm: tuple[float, float], px_per_mm: float, out: Path) -> np.ndarray:
    """The SVG as headless Chromium draws it, `px_per_mm` image pixels per mm of paper."""
    size = [round(side * CSS_PX_PER_MM) for side in paper_mm]
    subprocess.run(
        [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
         f"--force-device-scale-factor={px_per_mm / CSS_PX_PER_MM:.6f}",
         f"--window-size={size[0]},{size[1]}", f"--screenshot={out}", svg.as_uri()],
        check=True, capture_output=True, timeout=120,
    )  # fmt: skip
    return np.asarray(Image.open(out).convert("L"), dtype=np.float64) / 255.0


def test_the_chart_rendered_at_the_camera_scale_has_the_disks_it_promises(tmp_path: Path):
    out = tmp_path / "chart"
    assert main(["target", "--out", str(out), "--paper", "100x80", *CAMERA]) == 0
    design = yaml.safe_load((out / "chart.yaml").read_text())
    assert design["radius_px"] == 14 and design["pitch_px"] == 64 and design["disks"] == 36
    mm_per_px = design["mm_per_px"]
    assert mm_per_px == pytest.approx(3.45e-3 * (300 - 8) / 8)  # thin lens: p (D − f) / f
    image = _render(out / "chart.svg", (100, 80), 1 / mm_per_px, tmp_path / "shot.png")
    assert image.shape == (round(80 / mm_per_px), round(100 / mm_per_px))
    rows, cols = (side - side % 2 for side in image.shape)
    found = detect_disks(image[:rows, :cols], cfa="RGGB", name="rendered chart")
    assert len(found) == 36
    radii = np.sqrt(found.area_px / np.pi)
    assert np.median(radii) == pytest.approx(14, rel=0.03)
    gaps = np.sort(np.linalg.norm(found.centres[:, None] - found.centres[None], axis=2))[:, 1]
    assert np.median(gaps) == pytest.approx(64, rel=0.01)
    # the scale bar's length and the parameters are printed in the margin
    svg = (out / "chart.svg").read_text()
    assert "50 mm" in svg and "radius 14 px, pitch 64 px" in svg and "f = 8 mm" in svg


def test_svg_and_pdf_have_the_papers_physical_size(tmp_path: Path) -> None:
    out = tmp_path / "chart"
    assert main(["target", "--out", str(out), "--paper", "A4", "--landscape", *CAMERA]) == 0
    root = ElementTree.parse(out / "chart.svg").getroot()
    assert (root.get("width"), root.get("height")) == ("297mm", "210mm")
    chart = design_disk_chart(paper_size("A4", landscape=True), pixel_um=3.45, focal_mm=8,
                              distance_m=0.3)  # fmt: skip
    circles = root.findall(".//{http://www.w3.org/2000/svg}circle")
    assert len(circles) == len(chart.centres_mm)
    assert {float(c.get("r")) for c in circles} == {round(chart.radius_mm, 4)}
    pdf = (out / "chart.pdf").read_bytes()
    box = re.search(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", pdf)
    assert box and float(box[1]) == pytest.approx(297 / 25.4 * 72, abs=0.1)
    assert float(box[2]) == pytest.approx(210 / 25.4 * 72, abs=0.1)


@pytest.mark.parametrize(
    ("options", "match"),
    [
        (["--distance-m", "0.005"], "not beyond the focal length"),
        (["--paper", "40x40"], "use larger paper"),
        (["--pitch-px", "20"], "at least 3 radii"),
        (["--paper", "A9"], "WIDTHxHEIGHT"),
    ],
    ids=["inside-focal-length", "page-too-small", "disks-touch", "unknown-paper"],
)
def test_impossible_charts_are_refused_and_nothing_is_written(
    tmp_path: Path, options: list[str], match: str, capsys
) -> None:
    args = list(CAMERA)
    for flag, value in zip(options[::2], options[1::2], strict=True):
        if flag in args:
            args[args.index(flag) + 1] = value
        else:
            args += [flag, value]
    assert main(["target", "--out", str(tmp_path / "c"), *args]) == EXPECTED
    assert match in capsys.readouterr().err and not (tmp_path / "c").exists()


def test_a_shot_from_another_distance_is_reported_with_what_to_do(tmp_path: Path) -> None:
    """The chart made for 14 px disks, shot so that it measures 0.7 times that: the check
    says the camera stands 1.43× farther away; shot at the design's scale it says nothing."""
    from calibration.disks.chart import check_shot, load_chart_yaml

    out = tmp_path / "chart"
    assert main(["target", "--out", str(out), "--paper", "100x80", *CAMERA]) == 0
    design = load_chart_yaml(out / "chart.yaml")
    scale = 1 / design["mm_per_px"]
    good = _render(out / "chart.svg", (100, 80), scale, tmp_path / "good.png")
    far = _render(out / "chart.svg", (100, 80), 0.7 * scale, tmp_path / "far.png")
    even = [image[: image.shape[0] // 2 * 2, : image.shape[1] // 2 * 2] for image in (good, far)]
    fine = check_shot(even[0], design, cfa="RGGB", name="good shot")
    assert fine.problem is None and fine.radius_px == pytest.approx(14, rel=0.03)
    off = check_shot(even[1], design, cfa="RGGB", name="far shot")
    assert off.pitch_px == pytest.approx(0.7 * 64, rel=0.02)
    assert "1.43× farther from the chart" in off.problem and "labkit target" in off.problem
