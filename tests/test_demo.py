"""`labkit demo --quick`: the whole job on the simulated rig, and its report in Chromium."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from labkit.cli import main

CHECK_SCRIPT = """<script>
window.addEventListener("load", () => {
  const images = [...document.images];
  const broken = images.filter(i => !(i.complete && i.naturalWidth > 0))
                       .map(i => i.getAttribute("src"));
  const out = document.createElement("pre");
  out.id = "image-check";
  out.textContent = JSON.stringify({total: images.length, broken: broken});
  document.body.appendChild(out);
});
</script>"""


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    return out


def images_in_chromium(page: Path) -> dict:
    """Load `page` (a copy with a checking script) in headless Chromium: images loaded."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("Debian's chromium is not installed (make test installs it)")
    probe = page.with_name("_image_check.html")
    probe.write_text(page.read_text().replace("</body>", CHECK_SCRIPT + "</body>"))
    result = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=10000",
         "--dump-dom", probe.as_uri()],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    probe.unlink()
    found = re.search(r'<pre id="image-check">(.*?)</pre>', result.stdout)
    assert found, f"chromium gave no result (status {result.returncode}): {result.stderr[-500:]}"
    return json.loads(found.group(1).replace("&quot;", '"'))


def test_demo_runs_the_whole_job_with_known_answers(demo_out: Path) -> None:
    """Quick demo (256×320): measured calibration RMS 0.003 px against the lens; GOF
    0.98 (ColorChecker) and 0.94 (texture); the reconstruction's green edge RMSE is
    below bilinear demosaicing's (0.034 against 0.048)."""
    results = json.loads((demo_out / "results.json").read_text())
    assert set(results["seconds"]) == {"capture", "hdr", "calibrate", "reconstruct", "evaluate"}
    assert results["calibration"]["spectral"]["error_vs_lens_px"]["rms_px"] < 0.05
    assert set(results["reconstruction"]) == {
        "colorchecker", "texture", "colorchecker (§6.3 mean-colour)",
        "colorchecker (§3.9.2 warp)",
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
