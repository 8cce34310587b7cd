"""`labkit demo --quick`: the whole job on the simulated rig, and its report in Chromium."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from _report_check import images_in_chromium

from labkit.cli import main


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    return out


def test_demo_runs_the_whole_job_with_known_answers(demo_out: Path) -> None:
    """Quick demo (256×320): measured calibration RMS 0.003 px against the lens; GOF
    0.98 (ColorChecker) and 0.94 (texture); the reconstruction's green edge RMSE is
    below bilinear demosaicing's (0.034 against 0.048)."""
    results = json.loads((demo_out / "results.json").read_text())
    assert set(results["seconds"]) == {"capture", "hdr", "calibrate", "reconstruct", "evaluate"}
    assert results["calibration"]["spectral"]["error_vs_lens_px"]["rms_px"] < 0.05
    assert set(results["reconstruction"]) == {
        "colorchecker", "texture", "colorchecker (reference spectrum from the mean colour)",
        "colorchecker (solved without the dispersion, then warped)",
    }  # fmt: skip
    chart = results["evaluation"]["colorchecker"]["methods"]
    ours = chart["spectral: colorchecker"]
    assert ours["spectral"]["gof"] > 0.95
    edge_g = {name: m["residual_aberration"]["edge"]["rmse"]["G"] for name, m in chart.items()}
    assert edge_g["spectral: colorchecker"] < edge_g["bilinear"]
    texture = results["evaluation"]["texture"]["methods"]["spectral: texture"]
    assert texture["spectral"]["gof"] > 0.9
    assert (demo_out / "calibration" / "spectral_to_reference.yaml").is_file()
    assert (demo_out / "reconstruction" / "texture" / "spectral.exr").is_file()


def test_every_image_of_the_report_loads_in_chromium(demo_out: Path) -> None:
    page = demo_out / "report.html"
    markdown = (demo_out / "report.md").read_text()
    linked = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", markdown)
    assert len(linked) >= 25 and all((demo_out / path).is_file() for path in linked)
    check = images_in_chromium(page)
    assert check == {"total": len(linked), "broken": []}
    # the check can fail: a missing image is reported by name
    missing = demo_out / linked[0]
    kept = missing.read_bytes()
    missing.unlink()
    try:
        assert images_in_chromium(page)["broken"] == [linked[0]]
    finally:
        missing.write_bytes(kept)


def test_the_demo_folder_is_one_verified_set(demo_out: Path) -> None:
    from labkit.io.output_folder import RUNNING, verify_output_folder

    manifest = verify_output_folder(demo_out, what="demo folder", rerun="labkit demo")
    assert manifest is not None and manifest["command"] == "labkit demo"
    assert "report.html" in manifest["files"] and not (demo_out / RUNNING).exists()
