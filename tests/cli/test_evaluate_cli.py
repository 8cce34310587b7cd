"""`labkit evaluate` on a simulated ColorChecker: the truth scores zero, baselines do not."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from labkit.cli import main
from labkit.io import RawImage, write_raw_exr, write_rgb_exr
from labkit.rig import load_rig
from labkit.sim import SimulatedRig
from labkit.sim.truth import colour_truth

SHAPE = (256, 320)


@pytest.fixture(scope="module")
def chart_files(tmp_path_factory: pytest.TempPathFactory, sim_rig_path: Path):
    """A raw EXR of the rig's ColorChecker (lens dispersion included) and its truth EXR,
    with the lens' blur off (``sharp.yaml``): blurred patch edges differ from the measure's
    ideal of uniform patches, so only a sharp truth scores zero."""
    folder = tmp_path_factory.mktemp("evaluate")
    text = sim_rig_path.read_text()
    assert "blur_sigma_px: 0.40" in text
    (folder / "sharp.yaml").write_text(text.replace("blur_sigma_px: 0.40", "blur_sigma_px: 0.0"))
    world = SimulatedRig(load_rig(folder / "sharp.yaml"), shape=SHAPE)
    raw = world.irradiance("colorchecker", "unfiltered").astype(np.float32)
    write_raw_exr(folder / "raw.exr", RawImage(raw, world.rig.cfa, 1.0, "unfiltered"))
    write_rgb_exr(folder / "truth.exr", colour_truth(world, "colorchecker"))
    return folder


def test_truth_image_scores_zero_against_the_simulator_and_beats_the_baselines(
    chart_files: Path, capsys: pytest.CaptureFixture
) -> None:
    """Noise-free render. Measured edge RMSE R/G/B: truth 0.0004/0.0007/0.0005 (vignetting
    against the planar shading fit), bilinear 0.042/0.047/0.066, Menon 0.033/0.028/0.058;
    the truth's colour RMSE is 0 (< 1e-4 printed), the baselines' 0.06–0.12."""
    out = chart_files / "out"
    status = main([
        "evaluate", str(chart_files / "raw.exr"), "--scene", "colorchecker", "--truth",
        "--rig", str(chart_files / "sharp.yaml"),
        "--image", f"truth={chart_files / 'truth.exr'}", "--baselines", "bilinear,menon",
        "--out", str(out),
    ])  # fmt: skip
    assert status == 0
    result = json.loads((out / "evaluation.json").read_text())
    methods = result["methods"]
    assert list(methods) == ["bilinear", "menon", "truth"]
    truth = methods["truth"]
    assert max(truth["colour"]["rmse"].values()) < 1e-6
    edge = {name: m["residual_aberration"]["edge"]["rmse"]["G"] for name, m in methods.items()}
    assert edge["truth"] < 0.1 * min(edge["bilinear"], edge["menon"]), edge
    assert min(methods["menon"]["colour"]["rmse"].values()) > 0.03
    for name in ("bilinear", "menon", "truth"):
        assert (out / f"{name}.png").is_file()
    page = (out / "evaluation.html").read_text()
    assert "<table>" in page and 'src="menon.png"' in page
    assert "truth" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--image", "nameonly"], "expected NAME=PATH.exr"),
        (["--truth"], "--truth needs --scene"),
        (["--scene", "nowhere"], "not in the rig; its scenes"),
        (["--baselines", "nearest"], "unknown baseline"),
        (["--baselines", "none"], "nothing to evaluate"),
    ],
)
def test_bad_arguments_are_refused_before_writing(
    chart_files: Path, arguments: list[str], message: str, capsys: pytest.CaptureFixture
) -> None:
    out = chart_files / "refused"
    status = main(["evaluate", str(chart_files / "raw.exr"), "--out", str(out), *arguments])
    assert status == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_an_image_of_another_size_is_named(chart_files: Path, capsys) -> None:
    small = chart_files / "small.exr"
    write_rgb_exr(small, np.ones((8, 8, 3), dtype=np.float32))
    out = chart_files / "refused"
    status = main(["evaluate", str(chart_files / "raw.exr"), "--image", f"x={small}",
                   "--out", str(out)])  # fmt: skip
    assert status == 2 and "small.exr is 8×8 px but the raw image is 320×256 px" in (
        capsys.readouterr().err
    )
