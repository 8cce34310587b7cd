"""Camera raw brackets (DNG here, as any LibRaw format) go through ``session import`` →
``hdr`` → ``calibrate sensitivity``: counts stored as the camera wrote them, levels and
exposure times from the files, contradictions refused before anything is written."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import tifffile
import yaml
from _helpers import write_rig
from _raw_files import write_dng

from calibration import ChannelSensitivity, nominal_channel_sensitivity
from labkit.cli import EXPECTED, main
from labkit.errors import DataError
from labkit.rig import load_rig
from labkit.session import Session
from labkit.session.importer import import_session
from labkit.sim import SimCamera, SimulatedRig

SHAPE = (96, 128)
BRACKETS = {
    "unfiltered": (0.004, 0.016),
    "450": (0.025, 0.1),
    "550": (0.02, 0.08),
    "650": (0.2, 0.8),
}
BLACK, WHITE = 32, 4032  # the simulated camera's levels (12-bit, black level 32)


def _exposure_tag(seconds: float) -> tuple:
    """EXIF ExposureTime (33434), a rational, as cameras record it."""
    value = Fraction(seconds).limit_denominator(100000)
    return (33434, "2I", 1, (value.numerator, value.denominator), True)


@pytest.fixture(scope="module")
def dng_brackets(tmp_path_factory: pytest.TempPathFactory, sim_rig_path: Path):
    """(rig file, folder of DNGs, {file name: counts}): the simulated ColorChecker under four
    illuminations at two exposures each, 3 replicates, and darks, written as a camera would:
    names without the exposure, which each file records."""
    root = tmp_path_factory.mktemp("dng")
    rig_file = write_rig(
        root,
        sim_rig_path,
        **{"sim.sensor.width": SHAPE[1], "sim.sensor.height": SHAPE[0]},
        **{"plan.illuminations": list(BRACKETS), "plan.scenes": ["colorchecker"]},
    )
    camera = SimCamera(SimulatedRig(load_rig(rig_file)), seed=5, fast=True)
    camera.set_scene("colorchecker")
    folder = root / "card"
    folder.mkdir()
    shots = [(illumination, t) for illumination, times in BRACKETS.items() for t in times]
    shots += [("dark", t) for t in sorted({t for _, t in shots})]
    written: dict[str, np.ndarray] = {}
    for illumination, exposure in shots:
        camera.set_illumination(illumination)
        for frame in camera.grab(exposure, 3):
            prefix = "dark" if illumination == "dark" else f"colorchecker_{illumination}"
            name = f"{prefix}_IMG{len(written) + 1:04d}.dng"
            write_dng(folder / name, frame.image, black=BLACK, white=WHITE,
                      extra=(_exposure_tag(exposure),))  # fmt: skip
            written[name] = frame.image
    return rig_file, folder, written


def test_dng_brackets_import_merge_and_calibrate(dng_brackets, tmp_path: Path) -> None:
    rig_file, folder, written = dng_brackets
    session_dir, hdr_dir, out = tmp_path / "s", tmp_path / "hdr", tmp_path / "sens"
    patterns = ["--pattern", "{scene}_{illumination}_IMG*.dng", "--pattern", "dark_IMG*.dng"]
    assert main(["session", "import", str(session_dir), "--from", str(folder),
                 "--rig", str(rig_file), *patterns]) == 0  # fmt: skip
    session = Session.open(session_dir)
    assert len(session.records) == len(written)
    for record in session.records.values():
        stored = tifffile.imread(session_dir / record["file"])
        np.testing.assert_array_equal(stored, written[record["source_file"]])  # as written
        assert (record["black_level"], record["saturation_dn"]) == (BLACK, WHITE)
        assert record["source_exposure_s"] == pytest.approx(record["exposure_s"])
    exposures = {(r["illumination"], r["exposure_s"]) for r in session.records.values()}
    for illumination, times in BRACKETS.items():
        assert {(illumination, t) for t in times} <= exposures
    assert main(["hdr", str(session_dir), "--out", str(hdr_dir), "--no-progress"]) == 0
    index = yaml.safe_load((hdr_dir / "hdr.yaml").read_text())
    assert len(index["images"]) == len(BRACKETS) and not any(i["warnings"] for i in index["images"])
    for image in index["images"]:  # the recorded times chain the bracket: factors fitted
        assert all(pair["fitted"] for pair in image["pairs"]), image["illumination"]
        assert abs(image["exposures"][-1]["disagreement_percent"]) < 2
    assert main(["calibrate", "sensitivity", str(hdr_dir), "--out", str(out),
                 "--rig", str(rig_file)]) == 0  # fmt: skip
    # the filtered brackets give the ratios the simulated camera's response predicts
    table = ChannelSensitivity.from_file(out / "sensitivity.yaml")
    nominal = nominal_channel_sensitivity(load_rig(rig_file), ["450", "550", "650"])
    np.testing.assert_array_equal(table.wavelengths_nm, nominal.wavelengths_nm)
    np.testing.assert_allclose(table.r_over_g, nominal.r_over_g, rtol=0.03, atol=1e-3)
    np.testing.assert_allclose(table.b_over_g, nominal.b_over_g, rtol=0.03, atol=1e-3)
    assert (out / "sensitivity.csv").is_file()


def test_per_position_black_levels_become_one(tmp_path: Path, sim_rig_path: Path) -> None:
    """Black levels 30, 32, 34, 36 by CFA position: each position's counts drop by its
    excess over 30 (lossless), the frame's black level is 30 and its saturation 4032 − 6."""
    folder = tmp_path / "card"
    folder.mkdir()
    counts = np.full(SHAPE, 1000, np.uint16)
    write_dng(folder / "colorchecker_550_IMG1.dng", counts, black=(30, 32, 34, 36), white=WHITE,
              extra=(_exposure_tag(0.01),))  # fmt: skip
    session, _ = import_session(
        tmp_path / "s", folder, ["{scene}_{illumination}_IMG*.dng"], load_rig(sim_rig_path)
    )
    (record,) = session.records.values()
    stored = tifffile.imread(tmp_path / "s" / record["file"])
    np.testing.assert_array_equal(stored[0::2, 0::2], 1000)
    np.testing.assert_array_equal(stored[0::2, 1::2], 998)
    np.testing.assert_array_equal(stored[1::2, 0::2], 996)
    np.testing.assert_array_equal(stored[1::2, 1::2], 994)
    assert (record["black_level"], record["saturation_dn"]) == (30, WHITE - 6)
    assert record["source_black_levels"] == [[30, 32], [34, 36]]


@pytest.mark.parametrize(
    ("name", "options", "pattern", "match"),
    [
        ("colorchecker_550_IMG1.dng", {"cfa": "RGGB"}, "{scene}_{illumination}_IMG*.dng",
         "CFA layout is RGGB but the rig's camera"),
        ("colorchecker_550_50ms_IMG1.dng", {}, "{scene}_{illumination}_{exposure}_IMG*.dng",
         "its name gives 0.05 s but the file records 0.01 s"),
        ("colorchecker_550_IMG1.dng", {"white": 900}, "{scene}_{illumination}_IMG*.dng",
         "above the file's white level 900"),
        ("colorchecker_550_IMG1.dng", {"exposure": None}, "{scene}_{illumination}_IMG*.dng",
         "its metadata records none"),
    ],
    ids=["cfa", "exposure-disagrees", "above-white", "no-exposure"],
)  # fmt: skip
def test_raw_files_that_contradict_are_refused_and_nothing_is_written(
    tmp_path: Path, sim_rig_path: Path, name: str, options: dict, pattern: str, match: str
) -> None:
    folder = tmp_path / "card"
    folder.mkdir()
    exposure = options.pop("exposure", 0.01)
    extra = () if exposure is None else (_exposure_tag(exposure),)
    write_dng(folder / name, np.full(SHAPE, 1000, np.uint16), **{"white": WHITE, **options},
              extra=extra)  # fmt: skip
    with pytest.raises(DataError, match=match):
        import_session(tmp_path / "s", folder, [pattern], load_rig(sim_rig_path))
    assert not (tmp_path / "s").exists()
    status = main(["session", "import", str(tmp_path / "s"), "--from", str(folder),
                   "--pattern", pattern, "--rig", str(sim_rig_path)])  # fmt: skip
    assert status == EXPECTED and not (tmp_path / "s").exists()
