"""``labkit capture`` and ``labkit session``: dry run, crash safety, resume, import, errors."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile
from _helpers import QUICK_PLAN_FRAMES

from labkit.cli import main
from labkit.protocol import build_plan
from labkit.rig import load_rig
from labkit.session import MANIFEST_FILE, Session


def _labkit(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "labkit", *args], capture_output=True,
                          text=True, timeout=timeout, check=False)  # fmt: skip


def _assert_consistent(folder: Path) -> list[str]:
    """Manifest lines are unique, parse, and point at files with matching checksums."""
    lines = (folder / MANIFEST_FILE).read_text().splitlines()
    keys = [json.loads(line)["key"] for line in lines]
    assert len(keys) == len(set(keys)), "duplicated manifest records"
    assert Session.open(folder).verify() == {}
    return keys


def test_dry_run_prints_the_plan_and_moves_nothing(
    quick_rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["capture", str(quick_rig_file), "--session", str(tmp_path / "s"),
                 "--dry-run"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert f"total: {QUICK_PLAN_FRAMES} frames" in out
    assert "move slider to slot 3 (450)" in out and "grab dark at 500ms × 2" in out
    assert "OK" in out and not (tmp_path / "s").exists()


def test_capture_then_show(quick_rig_file: Path, tmp_path: Path, capsys) -> None:
    session = tmp_path / "s"
    args = ["capture", str(quick_rig_file), "--session", str(session), "--fast", "--no-progress"]
    assert main(args) == 0
    assert f"complete, {QUICK_PLAN_FRAMES} frames" in capsys.readouterr().out
    assert main(args) == 0
    assert "already complete" in capsys.readouterr().out
    assert main(["session", "show", str(session), "--verify"]) == 0
    out = capsys.readouterr().out
    assert f"{QUICK_PLAN_FRAMES} stored of {QUICK_PLAN_FRAMES} planned (0 missing)" in out
    assert "disks        450: 100ms×2, 500ms×2" in out
    assert "(dark)       dark: 3ms×3, 12ms×3, 100ms×2, 500ms×2" in out
    assert f"all {QUICK_PLAN_FRAMES} frames match their sha256" in out


def test_sigkill_at_random_points_then_resume_gives_exactly_the_plan(
    make_rig, tmp_path: Path
) -> None:
    """Kill the capture process ≥ 10 times mid-capture; the resumed session is exact."""
    from _helpers import quick_plan

    changes = quick_plan()
    changes["plan.replicates"] = {"unfiltered": 6, "filtered": 4}
    rig_file = make_rig(**changes)
    folder = tmp_path / "s"
    planned = sorted(k.id for k in build_plan(load_rig(rig_file)).keys())
    assert len(planned) == 76
    command = [sys.executable, "-m", "labkit", "capture", str(rig_file),
               "--session", str(folder), "--fast", "--no-progress"]  # fmt: skip
    rng = random.Random(2019)
    kills = attempts = 0
    while kills < 10 and attempts < 40:
        attempts += 1
        stored = len(Session.open(folder).records) if (folder / "session.yaml").exists() else 0
        if stored >= len(planned) - 2:
            break  # too close to the end to kill mid-way; finish below
        target = min(stored + rng.randint(1, 3), len(planned) - 1)
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        manifest = folder / MANIFEST_FILE
        deadline = time.monotonic() + 60
        while process.poll() is None and time.monotonic() < deadline:
            if manifest.exists() and manifest.read_bytes().count(b"\n") >= target:
                time.sleep(rng.uniform(0, 0.004))  # land anywhere in the next frame's write
                break
            time.sleep(0.0005)
        if process.poll() is None:
            os.kill(process.pid, signal.SIGKILL)
            process.wait()
            kills += 1
        keys = _assert_consistent(folder)
        assert set(keys) <= set(planned)
    assert kills >= 10, f"only {kills} kills landed mid-capture in {attempts} attempts"
    result = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert sorted(_assert_consistent(folder)) == planned
    files = sorted(
        str(p.relative_to(folder)) for p in (folder / "frames").rglob("*") if p.is_file()
    )
    assert files == sorted(f"frames/{key}.tiff" for key in planned)  # no orphans or temp files
    runs = Session.open(folder).info["runs"]
    assert runs[-1]["status"] == "complete" and len(runs) >= 11


def test_resume_with_a_different_rig_is_a_one_line_error(
    quick_rig_file: Path, make_rig, tmp_path: Path
) -> None:
    from _helpers import quick_plan

    session = tmp_path / "s"
    assert main(["capture", str(quick_rig_file), "--session", str(session), "--fast",
                 "--no-progress"]) == 0  # fmt: skip
    before = (session / MANIFEST_FILE).read_bytes()
    other = make_rig(**quick_plan(), **{"plan.replicates.filtered": 4})
    result = _labkit("capture", str(other), "--session", str(session), "--fast")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().count("\n") == 0
    assert "plan.replicates.filtered: 2 → 4" in result.stderr
    assert (session / MANIFEST_FILE).read_bytes() == before


def test_missing_serial_port_is_a_one_line_error(make_rig, tmp_path: Path) -> None:
    from _helpers import quick_plan

    rig = make_rig(**quick_plan(), **{"slider.port": "/dev/ttyLABKIT9"})
    result = _labkit("capture", str(rig), "--session", str(tmp_path / "s"), "--fast")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().count("\n") == 0
    assert "/dev/ttyLABKIT9" in result.stderr and "does not exist" in result.stderr
    assert not (tmp_path / "s").exists()


def test_import_flycapture_style_names(tmp_path: Path, sim_rig_path: Path, capsys) -> None:
    source = tmp_path / "fc"
    source.mkdir()
    rng = np.random.default_rng(0)
    written = {}
    for illumination, exposure in [("450nm", "100ms"), ("unfiltered", "3ms")]:
        for replicate in (4, 5, 6):
            name = f"d1_disks32cmV2_{illumination}_{exposure}_2019-02-08-174831-{replicate:04d}.tif"
            written[name] = rng.integers(0, 4096, (16, 24), dtype=np.uint16)
            tifffile.imwrite(source / name, written[name])
    for replicate in (1, 2):
        name = f"d1_dark_100ms_2019-02-08-180000-{replicate:04d}.tif"
        written[name] = rng.integers(0, 100, (16, 24), dtype=np.uint16)
        tifffile.imwrite(source / name, written[name])
    (source / "notes.tif").write_bytes(b"not matched")
    folder = tmp_path / "s"
    assert main(["session", "import", str(folder), "--from", str(source), "--rig",
                 str(sim_rig_path), "--pattern",
                 "d1_{scene}_{illumination}_{exposure}_{date}-{replicate}.tif",
                 "--pattern", "d1_dark_{exposure}_{date}-{replicate}.tif"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "imported 8 frames" in out and "notes.tif" in out
    session = Session.open(folder)
    assert session.status == "imported"
    by_key = {k: r for k, r in session.records.items()}
    assert sorted(by_key) == sorted([
        *(f"disks32cmV2/450/100ms/r{r:03d}" for r in range(3)),
        *(f"disks32cmV2/unfiltered/3ms/r{r:03d}" for r in range(3)),
        "dark/100ms/r000", "dark/100ms/r001",
    ])  # fmt: skip
    record = by_key["disks32cmV2/450/100ms/r001"]
    assert record["exposure_s"] == 0.1 and record["frame_id"] == 5
    source_name = record["source_file"]
    image, _ = tifffile.imread(folder / record["file"]), None
    np.testing.assert_array_equal(image, written[source_name])
    assert session.verify() == {}


def test_import_with_unknown_illumination_names_the_fix(tmp_path: Path, sim_rig_path: Path):
    source = tmp_path / "fc"
    source.mkdir()
    tifffile.imwrite(source / "a_red_10ms_1.tif", np.zeros((4, 4), np.uint16))
    result = _labkit("session", "import", str(tmp_path / "s"), "--from", str(source),
                     "--rig", str(sim_rig_path), "--pattern",
                     "a_{illumination}_{exposure}_{replicate}.tif")  # fmt: skip
    assert result.returncode == 2 and "--map red=NAME" in result.stderr
    assert not (tmp_path / "s").exists()


def test_ctrl_c_stops_after_the_current_frame_and_leaves_a_resumable_session(
    quick_rig_file: Path, tmp_path: Path
) -> None:
    folder = tmp_path / "s"
    command = [sys.executable, "-m", "labkit", "capture", str(quick_rig_file),
               "--session", str(folder), "--no-progress"]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    manifest = folder / MANIFEST_FILE
    while time.monotonic() < deadline and process.poll() is None:
        if manifest.exists() and manifest.read_bytes().count(b"\n") >= 3:
            break
        time.sleep(0.01)
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr and "run the same command again to resume" in stderr
    session = Session.open(folder)
    assert session.status == "stopped" and 3 <= len(session.records) < QUICK_PLAN_FRAMES
    _assert_consistent(folder)
    assert main([*command[3:], "--fast"]) == 0
    assert sorted(Session.open(folder).records) == sorted(
        k.id for k in build_plan(load_rig(quick_rig_file)).keys()
    )


def test_devices_lists_backends_and_probes_a_simulated_slider(capsys, monkeypatch) -> None:
    from labkit.devices import serial_ports
    from labkit.sim import FW102CSimulator

    with FW102CSimulator(time_scale=0) as simulator:
        port = serial_ports.SerialPortInfo(simulator.port, "pty", "sim")
        monkeypatch.setattr(serial_ports, "list_serial_ports", lambda: [port])
        assert main(["devices", "--probe"]) == 0
    out = capsys.readouterr().out
    assert "aravis (GigE Vision):" in out and "genicam (GenTL):" in out
    assert f"{simulator.port}" in out and "fw102c: THORLABS FW102C" in out


def test_unknown_camera_id_is_a_one_line_error_and_creates_nothing(tmp_path: Path) -> None:
    rig = tmp_path / "gige.yaml"
    rig.write_text(
        "format: 1\ncamera: {backend: aravis, device: No-Such-Camera, pixel_format: BayerRG8}\n"
        "slider: {driver: fw102c, port: sim, positions: {1: {name: unfiltered}}}\n"
        "plan: {scenes: [target]}\n"
    )
    result = _labkit("capture", str(rig), "--session", str(tmp_path / "s"), "--yes")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().count("\n") == 0, result.stderr
    assert "no camera with id 'No-Such-Camera'; cameras found:" in result.stderr
    assert not (tmp_path / "s").exists()


def test_genicam_camera_without_exposure_control_fails_before_capturing(tmp_path: Path) -> None:
    genicam = pytest.importorskip("genicam")
    cti = Path(genicam.__file__).parent / "viky.cti"
    if not cti.is_file():
        pytest.skip("the genicam wheel ships no viky.cti")
    rig = tmp_path / "viky.yaml"
    rig.write_text(
        f"format: 1\ncamera: {{backend: genicam, cti: {cti}, pixel_format: BayerRG8}}\n"
        "slider: {driver: fw102c, port: sim, positions: {1: {name: unfiltered}}}\n"
        "plan: {scenes: [target]}\n"
    )
    result = _labkit("capture", str(rig), "--session", str(tmp_path / "s"), "--yes")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    missing = "has no exposure-time feature (neither ExposureTime nor ExposureTimeAbs)"
    assert missing in result.stderr
    assert not (tmp_path / "s").exists()


# -- one writer per session; an import is all or nothing -----------------------------------
_FLYCAPTURE = "d1_{scene}_{illumination}_{exposure}_{date}-{replicate}.tif"


def _flycapture_folder(folder: Path, scene: str = "disks") -> Path:
    folder.mkdir()
    rng = np.random.default_rng(1)
    for replicate in (1, 2, 3):
        name = f"d1_{scene}_unfiltered_3ms_2019-02-08-174831-{replicate:04d}.tif"
        tifffile.imwrite(folder / name, rng.integers(0, 4096, (16, 24), dtype=np.uint16))
    return folder


def test_a_second_capture_of_one_session_is_refused_naming_the_first(
    quick_rig_file: Path, tmp_path: Path, capsys
) -> None:
    folder = tmp_path / "s"
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time\n"
         "from labkit.io.output_folder import writer_lock\n"
         "with writer_lock(sys.argv[1], command='labkit capture', option='--session'):\n"
         "    print('locked', flush=True); time.sleep(60)\n",
         str(folder)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        args = ["capture", str(quick_rig_file), "--session", str(folder), "--fast",
                "--no-progress"]  # fmt: skip
        assert main(args) == 2
        err = capsys.readouterr().err
        assert f"pid {holder.pid}" in err and "labkit capture" in err and err.count("\n") == 1
        assert not folder.exists()
    finally:
        holder.kill()
        holder.wait()
    assert main(args) == 0  # the lock died with its holder
    assert len(_assert_consistent(folder)) == QUICK_PLAN_FRAMES


def test_an_import_that_fails_part_way_leaves_nothing_and_can_be_rerun(
    tmp_path: Path, sim_rig_path: Path, monkeypatch, capsys
) -> None:
    import errno

    source = _flycapture_folder(tmp_path / "fc")
    folder = tmp_path / "s"
    args = ["session", "import", str(folder), "--from", str(source), "--rig",
            str(sim_rig_path), "--pattern", _FLYCAPTURE, "--no-progress"]  # fmt: skip
    real_store, stored = Session.store, []

    def store_until_the_disk_is_full(self, *a, **kw):
        if len(stored) == 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.folder / "x"))
        stored.append(1)
        return real_store(self, *a, **kw)

    monkeypatch.setattr(Session, "store", store_until_the_disk_is_full)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "disk is full" in err and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fc"]  # nothing half-built left
    monkeypatch.setattr(Session, "store", real_store)
    assert main(args) == 0
    assert len(_assert_consistent(folder)) == 3


@pytest.mark.parametrize("scene", ["..", ".hidden"])
def test_an_import_refuses_a_scene_name_that_would_leave_the_session(
    tmp_path: Path, sim_rig_path: Path, capsys, scene: str
) -> None:
    source = _flycapture_folder(tmp_path / "fc", scene=scene)
    args = ["session", "import", str(tmp_path / "s"), "--from", str(source), "--rig",
            str(sim_rig_path), "--pattern", _FLYCAPTURE, "--no-progress"]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"gives scene {scene!r}, which cannot name a folder" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fc"]


def test_a_dry_run_writes_nothing_into_a_session(quick_rig_file: Path, tmp_path: Path) -> None:
    folder = tmp_path / "s"
    assert main(["capture", str(quick_rig_file), "--session", str(folder), "--fast",
                 "--no-progress"]) == 0  # fmt: skip
    manifest = folder / MANIFEST_FILE
    torn = manifest.read_bytes() + b'{"key": "torn'
    manifest.write_bytes(torn)
    assert main(["capture", str(quick_rig_file), "--session", str(folder), "--dry-run"]) == 0
    assert main(["session", "show", str(folder)]) == 0
    assert manifest.read_bytes() == torn  # readers skip a torn line and never write
