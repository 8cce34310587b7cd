"""AravisCamera against Aravis' GigE Vision simulator (``arv-fake-gv-camera-0.8``).

The simulator honours software triggers but checks its trigger register only at 25 Hz (so
at most ~25 frames/s), and only its Mono8 test pattern carries information: pixel (x, y) of
frame *id* is ``((x + y + id) mod 255) * (1 + gain + log10(exposure / 10 ms))``, clipped;
Bayer formats arrive as zeros. These tests therefore check protocol mechanics (frame ids,
statuses, host timestamps, exposure bookkeeping, retries, reconnects) and decoding, not
radiometry. Fixtures (``tests/devices/conftest.py``) run one simulator at a time.
"""

from __future__ import annotations

import io
import itertools
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from labkit.devices import _aravis_gi
from labkit.devices._aravis_stream import unwrap_frame_id
from labkit.devices.aravis import AravisCamera, list_devices
from labkit.devices.camera import Bounds, Camera, CameraIdentity
from labkit.errors import DeviceError


def _skip_reason() -> str | None:
    if shutil.which("arv-fake-gv-camera-0.8") is None:
        return "arv-fake-gv-camera-0.8 not found (install the Debian package aravis-tools)"
    if _aravis_gi.Aravis is None:
        error = _aravis_gi.IMPORT_ERROR
        return f"Aravis 0.8 typelib unavailable ({error}); install gir1.2-aravis-0.8"
    return None


pytestmark = pytest.mark.skipif(_skip_reason() is not None, reason=_skip_reason() or "")

#: Exposures alternated by the throughput test, s.
EXPOSURES = (1e-3, 2e-3)


def _ids_strictly_increasing(frames) -> bool:
    ids = [f.frame_id for f in frames]
    return all(b > a for a, b in itertools.pairwise(ids))


# -- pure helpers ---------------------------------------------------------------------------
def test_unwrap_frame_id_across_the_16_bit_wrap() -> None:
    assert unwrap_frame_id(65000, None) == 65000
    assert unwrap_frame_id(65535, 65534) == 65535
    assert unwrap_frame_id(1, 65535) == 65536  # GigE Vision 1.x ids skip 0
    assert unwrap_frame_id(3, 65536 + 1) == 65535 + 3
    assert unwrap_frame_id(65534, 65536) == 65534  # a stale frame from before the wrap
    assert unwrap_frame_id(10, 12) == 10  # stale, no wrap
    assert unwrap_frame_id(70_000, 69_999) == 70_000  # extended (64-bit) ids pass through


def test_missing_aravis_is_a_clear_device_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_aravis_gi, "IMPORT_ERROR", ValueError("Namespace Aravis not available"))
    pattern = r"install the system packages gir1\.2-aravis-0\.8.*labkit\[gige\]"
    with pytest.raises(DeviceError, match=pattern):
        list_devices()
    with pytest.raises(DeviceError, match=pattern):
        AravisCamera("Aravis-Fake-LK01")


# -- discovery, identity, features ------------------------------------------------------------
def test_list_devices_finds_the_simulator(fake_gv) -> None:
    found = {info.device_id: info for info in list_devices()}
    info = found[fake_gv.device_id]
    assert (info.backend, info.vendor, info.model, info.serial, info.address) == (
        "aravis", "Aravis", "Fake", "LK01", "127.0.0.1",
    )  # fmt: skip


def test_unknown_device_id_lists_the_devices_found(fake_gv) -> None:
    with pytest.raises(DeviceError) as info:
        AravisCamera("Aravis-Fake-NOPE")
    message = str(info.value)
    assert "no camera with id 'Aravis-Fake-NOPE'" in message
    assert "Aravis-Fake-LK01 (127.0.0.1)" in message
    assert "\n" not in message


def test_identity_shape_bounds_and_close(fake_gv) -> None:
    cam = AravisCamera(fake_gv.device_id, pixel_format="BayerRG8")
    try:
        _check_identity_shape_bounds(cam)
    finally:
        cam.close()
    cam.close()  # idempotent
    with pytest.raises(DeviceError, match="Aravis-Fake-LK01 is closed"):
        cam.grab(1e-3)


def _check_identity_shape_bounds(cam: AravisCamera) -> None:
    assert isinstance(cam, Camera)
    assert cam.backend == "aravis"
    assert cam.identity.vendor == "Aravis" and cam.identity.model == "Fake"
    assert cam.identity.serial == "LK01"
    assert re.fullmatch(r"0\.8\.\d+", cam.identity.firmware)  # DeviceVersion = Aravis'
    assert isinstance(cam.identity, CameraIdentity)
    assert (cam.get("SensorHeight"), cam.get("SensorWidth")) == (2048, 2048)
    cam.set("Width", 320)
    cam.set("Height", 240)
    assert cam.shape == (240, 320)
    # ExposureTimeAbs spans 10 µs … 10 s; GainRaw 0 … 10 in steps of 1
    bounds = cam.exposure_bounds()
    assert bounds.minimum == pytest.approx(10e-6, rel=1e-9)
    assert bounds.maximum == pytest.approx(10.0, rel=1e-9)
    assert bounds.increment == 0.0
    assert cam.gain_bounds() == Bounds(0.0, 10.0, 1.0)
    assert (cam.pixel_format, cam.cfa) == ("BayerRG8", "RGGB")
    cam.set_pixel_format("BayerGB8")
    assert (cam.pixel_format, cam.cfa) == ("BayerGB8", "GBRG")
    frame = cam.grab(1e-3)[0]
    assert frame.image.shape == (240, 320) and frame.image.dtype == np.uint8
    assert frame.pixel_format == "BayerGB8" and frame.extra["payload_bytes"] == 240 * 320


def test_generic_feature_access(fake_gv) -> None:
    with AravisCamera(fake_gv.device_id) as cam:
        names = cam.feature_names()
        assert {"Width", "PixelFormat", "ExposureTimeAbs", "GainRaw", "TriggerSoftware"} <= set(
            names
        )
        assert cam.get("DeviceVendorName") == "Aravis"
        assert isinstance(cam.get("Width"), int)
        assert isinstance(cam.get("ExposureTimeAbs"), float)
        cam.set("TestBoolean", True)
        assert cam.get("TestBoolean") is True
        cam.set("TestBoolean", False)
        assert cam.get("TestBoolean") is False
        cam.set("GainRaw", 4)
        assert cam.get("GainRaw") == 4
        cam.set("TriggerMode", "Off")
        assert cam.get("TriggerMode") == "Off"
        with pytest.raises(DeviceError, match=r"GainRaw=11 is outside \[0, 10\]"):
            cam.set("GainRaw", 11)
        with pytest.raises(DeviceError, match=r"TriggerMode='Maybe' is not one of \['Off', 'On'\]"):
            cam.set("TriggerMode", "Maybe")
        with pytest.raises(DeviceError, match=r"no feature 'Widht'; similar: Width"):
            cam.get("Widht")
        with pytest.raises(DeviceError, match="TriggerSoftware is a command, not a value"):
            cam.get("TriggerSoftware")
        with pytest.raises(DeviceError, match="not a command"):
            cam.execute("Width")
        cam.set("GainRaw", 0)


def test_pixel_format_errors(fake_gv) -> None:
    with AravisCamera(fake_gv.device_id, pixel_format="Mono8") as cam:
        with pytest.raises(DeviceError, match=r"'BayerRG12' is not offered; it offers .*BayerBG8"):
            cam.set_pixel_format("BayerRG12")
        with pytest.raises(DeviceError, match="cannot decode pixel format 'RGB8'; choose one of"):
            cam.set_pixel_format("RGB8")
        with pytest.raises(DeviceError, match="delivers Mono8, not a Bayer format"):
            _ = cam.cfa


def test_mono8_test_pattern_decodes_end_to_end(fake_gv) -> None:
    """Known answer: at 10 ms and gain 0 the simulator sends (x + y + id) mod 255."""
    with AravisCamera(fake_gv.device_id, pixel_format="Mono8") as cam:
        cam.set("Width", 64)
        cam.set("Height", 48)
        cam.set("GainRaw", 0)
        rows, cols = np.mgrid[0:48, 0:64]
        for frame in cam.grab(0.01, 2):
            expected = (cols + rows + frame.extra["raw_frame_id"]) % 255
            np.testing.assert_array_equal(frame.image, expected)
            assert frame.gain_db == 0.0 and frame.extra["gain_feature"] == "GainRaw"


# -- acquisition ------------------------------------------------------------------------------
def test_300_triggered_frames_at_alternating_exposures(fake_gv, record_property) -> None:
    with AravisCamera(fake_gv.device_id, pixel_format="BayerRG8") as cam:
        cam.set("Width", 512)
        cam.set("Height", 512)
        # Warm-up: Aravis sizes the stream socket's receive buffer when the first packet
        # arrives, so a fresh stream's first 512×512 frame can overflow the default buffer
        # and, as the simulator cannot resend packets, be retried.
        cam.grab(EXPOSURES[1], 1)
        before = cam.stream_statistics()
        frames = []
        previous_host_s = 0.0
        start = time.perf_counter()
        for block in range(100):
            exposure = EXPOSURES[block % 2]
            got = cam.grab(exposure, 3)
            assert len(got) == 3
            for frame in got:
                assert frame.status == "SUCCESS"
                assert frame.exposure_s == exposure
                assert frame.exposure_readback_s == pytest.approx(exposure, abs=1e-9)
                changed_s = frame.extra["settings_changed_host_time_s"]
                assert changed_s > previous_host_s  # the change came after the last block
                assert frame.extra["trigger_host_time_s"] >= changed_s
                assert frame.host_timestamp_s >= changed_s
                assert frame.image.shape == (512, 512)
            previous_host_s = got[-1].host_timestamp_s
            frames += got
        elapsed = time.perf_counter() - start
        stats = cam.stream_statistics()
    fps = len(frames) / elapsed
    record_property("aravis_fake_frames_per_s", round(fps, 2))
    print(f"\naravis simulator: {len(frames)} triggered 512×512 frames in {elapsed:.1f} s "
          f"= {fps:.1f} frames/s")  # fmt: skip
    ids = [f.frame_id for f in frames]
    assert np.all(np.diff(ids) == 1), "a frame id is missing: a frame was lost"
    assert len({f.device_timestamp_ns for f in frames}) == 300
    delta = {k: stats[k] - before.get(k, 0) for k in ("frames", "completed_buffers")}
    assert delta == {"frames": 300, "completed_buffers": 300}
    for key in (
        "failed_buffers",
        "missing_packets",
        "retries",
        "pop_timeouts",
        "stalled_frames",
        "rejected_stale",
        "drained",
        "reconnects",
    ):
        assert stats[key] - before[key] == 0, (key, stats)


def test_exposure_outside_bounds_is_rejected_before_any_trigger(fake_gv) -> None:
    with AravisCamera(fake_gv.device_id, pixel_format="BayerRG8") as cam:
        cam.set("Width", 64)
        cam.set("Height", 48)
        first = cam.grab(1e-3)[0]
        completed = cam.stream_statistics()["completed_buffers"]
        for bad in (20.0, 5e-6, 0.0, -1e-3, float("nan")):
            with pytest.raises(DeviceError, match=r"outside the camera's range \[1e-05, 10\] s"):
                cam.grab(bad)
        assert cam.get("ExposureTimeAbs") == pytest.approx(1000.0)  # never written
        assert cam.stream_statistics()["completed_buffers"] == completed
        after = cam.grab(1e-3)[0]
        assert after.frame_id == first.frame_id + 1  # the device's counter did not move
        with pytest.raises(DeviceError, match="grab needs n ≥ 1 frames"):
            cam.grab(1e-3, 0)


def test_packet_loss_is_retried(lossy_fake_gv, record_property) -> None:
    """-r 20: 2 % of the packets are dropped, so ~13 % of 7-packet frames fail."""
    with AravisCamera(lossy_fake_gv.device_id, pixel_format="BayerRG8", retries=8) as cam:
        cam.set("Width", 128)
        cam.set("Height", 48)  # 6 kB: leader + 5 data packets + trailer
        frames = []
        for block in range(50):
            frames += cam.grab(EXPOSURES[block % 2], 2)
        stats = cam.stream_statistics()
    record_property("aravis_lossy_retries", stats["retries"])
    print(f"\naravis simulator -r 20: {len(frames)} frames, {stats['retries']} retries, "
          f"{stats['failed_buffers']} failed buffers, {stats['missing_packets']} missing "
          "packets")  # fmt: skip
    assert len(frames) == 100
    assert all(f.status == "SUCCESS" for f in frames)
    assert _ids_strictly_increasing(frames)
    assert all(f.exposure_readback_s == pytest.approx(f.exposure_s) for f in frames)
    assert stats["failed_buffers"] > 0 and stats["retries"] > 0
    assert stats["retries"] == sum(f.extra["retries"] for f in frames)
    assert stats["retries"] == stats["failed_attempts"]  # no frame ran out of retries


def test_exhausted_retries_raise_a_clear_error_and_the_session_resumes(lossy_fake_gv) -> None:
    with AravisCamera(lossy_fake_gv.device_id, pixel_format="BayerRG8", retries=0) as cam:
        cam.set("Width", 512)
        cam.set("Height", 512)  # ~195 packets: at 2 % loss only ~2 % of frames arrive whole
        with pytest.raises(DeviceError) as info:
            cam.grab(0.01, 5)
        message = str(info.value)
        assert re.fullmatch(
            r"camera Aravis-Fake-LK20: frame [1-5] of 5 at 0\.010 s failed 1 time "
            r"\(last status (TIMEOUT|MISSING_PACKETS|STALLED)\); check the network link / "
            r"packet size \(or allow more retries\); the session can be resumed",
            message,
        ), message
        # resume: small frames and more retries
        cam.retries = 8
        cam.set("Width", 64)
        cam.set("Height", 48)
        frames = cam.grab(0.01, 3)
        assert [f.status for f in frames] == ["SUCCESS"] * 3


@pytest.fixture
def fake_genicam_xml() -> str:
    """The simulator's GenICam XML, as embedded in libaravis (exactly what it serves)."""
    from gi.repository import Aravis, Gio

    Aravis.FakeCamera.new("XML")  # registers libaravis' resources
    data = Gio.resources_lookup_data("/org/aravis/arv-fake-camera.xml", 0).get_data()
    text = bytes(data).decode("utf-8")
    assert 'Name="ExposureTimeAbs"' in text
    return text


def test_exposure_feature_variants(fake_gv_manager, fake_genicam_xml, tmp_path: Path) -> None:
    """SFNC ``ExposureTime`` works like ``ExposureTimeAbs``; a camera with neither is refused."""
    renamed = tmp_path / "exposure-time.xml"
    renamed.write_text(re.sub(r"\bExposureTimeAbs\b", "ExposureTime", fake_genicam_xml))
    fake = fake_gv_manager.ensure("LKX1", genicam=renamed)
    with AravisCamera(fake.device_id, pixel_format="BayerRG8") as cam:
        assert "ExposureTime" in cam.feature_names()
        assert cam.exposure_bounds().maximum == pytest.approx(10.0)
        frame = cam.grab(2e-3)[0]
        assert frame.extra["exposure_feature"] == "ExposureTime"
        assert frame.exposure_readback_s == pytest.approx(2e-3)
        assert cam.get("ExposureTime") == pytest.approx(2000.0)

    missing = tmp_path / "no-exposure.xml"
    missing.write_text(re.sub(r"\bExposureTimeAbs\b", "ShutterMicroseconds", fake_genicam_xml))
    fake = fake_gv_manager.ensure("LKX2", genicam=missing)
    with AravisCamera(fake.device_id, pixel_format="BayerRG8") as cam:
        pattern = r"no exposure-time feature \(neither ExposureTime nor ExposureTimeAbs\)"
        with pytest.raises(DeviceError, match=pattern):
            cam.exposure_bounds()
        with pytest.raises(DeviceError, match=pattern):
            cam.grab(1e-3)
        assert cam.stream_statistics()["completed_buffers"] == 0


# -- control lost ------------------------------------------------------------------------------
def _configure_for_reconnect(cam: AravisCamera) -> None:
    cam.set("Width", 64)
    cam.set("Height", 48)
    cam.set("GainRaw", 3)


def test_control_lost_signal_reconnects_and_restores_settings(fake_gv) -> None:
    """The reconnect path, entered by emitting the device's ``control-lost`` signal."""
    with AravisCamera(fake_gv.device_id, pixel_format="BayerGB8") as cam:
        _configure_for_reconnect(cam)
        first = cam.grab(1e-3, 2)
        cam.aravis_camera.get_device().emit("control-lost")
        assert cam.control_lost
        frames = cam.grab(2e-3, 2)
        assert not cam.control_lost
        assert cam.stream_statistics()["reconnects"] == 1
        assert [f.status for f in frames] == ["SUCCESS", "SUCCESS"]
        assert frames[0].host_timestamp_s > first[-1].host_timestamp_s
        assert all(f.gain_db == 3.0 and f.image.shape == (48, 64) for f in frames)
        assert all(f.exposure_readback_s == pytest.approx(2e-3) for f in frames)
        assert cam.pixel_format == "BayerGB8"
        cam.set("GainRaw", 0)


def test_killed_camera_is_reopened_after_it_restarts(fake_gv_manager, record_property) -> None:
    """Kill the simulator mid-session (as a power cut), wait for Aravis' heartbeat to report
    control lost, restart it (it comes back with default settings) and grab again."""
    fake = fake_gv_manager.ensure("LKRC")
    with AravisCamera(fake.device_id, pixel_format="BayerGB8", reconnect_attempts=3) as cam:
        cam.reconnect_backoff_s = 0.1
        _configure_for_reconnect(cam)
        assert len(cam.grab(1e-3, 2)) == 2
        fake.kill()
        killed = time.monotonic()
        while not cam.control_lost and time.monotonic() - killed < 15.0:
            time.sleep(0.05)
        lost_after_s = time.monotonic() - killed
        record_property("aravis_control_lost_after_s", round(lost_after_s, 1))
        assert cam.control_lost, "Aravis did not report control-lost within 15 s"
        fake_gv_manager.restart(fake)
        assert fake.running()
        frames = cam.grab(2e-3, 2)
        assert cam.stream_statistics()["reconnects"] == 1
        assert [f.status for f in frames] == ["SUCCESS", "SUCCESS"]
        assert all(f.image.shape == (48, 64) and f.gain_db == 3.0 for f in frames)
        assert (cam.get("Width"), cam.get("GainRaw"), cam.pixel_format) == (64, 3, "BayerGB8")

        # gone for good: the reconnect gives up with a clear error
        fake.kill()
        cam.reconnect_attempts = 1
        cam.aravis_camera.get_device().emit("control-lost")
        with pytest.raises(DeviceError, match=r"1 reconnect attempts failed .*resume the session"):
            cam.grab(1e-3)


def _gige_rig(device_id: str):
    from labkit.rig import rig_from_dict

    return rig_from_dict({
        "format": 1, "name": "fake GigE rig",
        "camera": {"backend": "aravis", "device": device_id, "pixel_format": "BayerRG8"},
        "slider": {"driver": "fw102c", "port": "sim", "timeout_s": 0.5,
                   "positions": {1: {"name": "unfiltered"},
                                 2: {"name": "550", "filter": {"centre_nm": 550}}}},
        "plan": {"scenes": ["target"],
                 "exposures_s": {"unfiltered": list(EXPOSURES), "filtered": list(EXPOSURES)},
                 "replicates": {"unfiltered": 15, "filtered": 15}},
    })  # fmt: skip


def _capture_session(rig, camera: AravisCamera, folder: Path):
    from labkit.protocol import Engine, OperatorStage
    from labkit.protocol.hardware import _start_simulator, open_slider
    from labkit.session import Session

    session, _ = Session.open_for(folder, rig)
    simulator = _start_simulator(rig, fast=True, on_move=None)
    try:
        with open_slider(rig, port=simulator.port) as slider:
            stage = OperatorStage(assume_done=True, out=io.StringIO())
            return Engine(rig, camera, slider, stage, session).run(), session
    finally:
        simulator.stop()


def test_lossy_link_session_completes_or_stops_resumably(lossy_fake_gv, tmp_path: Path) -> None:
    """-r 20 through the engine: a session stops with a resumable error when retries run
    out, and completes once retries are allowed; every stored frame matches its exposure."""
    from labkit.session import Session

    rig = _gige_rig(lossy_fake_gv.device_id)
    folder = tmp_path / "session"
    with AravisCamera(lossy_fake_gv.device_id, pixel_format="BayerRG8", retries=0) as cam:
        cam.set("Width", 128)
        cam.set("Height", 48)  # ~13 % of frames lose a packet: 90 frames cannot all pass
        with pytest.raises(DeviceError, match="the session can be resumed"):
            _capture_session(rig, cam, folder)
        stopped = Session.open(folder)
        assert stopped.status == "failed" and 0 <= len(stopped.records) < 90
        cam.retries = 8
        report, session = _capture_session(rig, cam, folder)
    assert report.status == "complete" and len(session.records) == 90  # 2 × 2 × 15 + darks 2 × 15
    stats = session.info["stream_statistics"]
    assert stats["retries"] > 0 and stats["failed_buffers"] > 0
    records = sorted(session.records.values(), key=lambda r: r["stored"])
    for record in records:
        assert record["status"] == "SUCCESS"
        assert record["exposure_readback_s"] == pytest.approx(record["exposure_s"], rel=1e-3)
    assert session.verify() == {}


def test_a_bluesky_capture_through_the_gige_camera(fake_gv, tmp_path: Path) -> None:
    """The ophyd-async detector over a GigE camera (Aravis, the fake camera on 127.0.0.1)
    with a RunEngine: the whole plan lands in the session with every frame checked, and
    each stored frame is one stream resource naming its file."""
    pytest.importorskip("ophyd_async", reason="labkit[bluesky] is not installed")
    from bluesky import RunEngine

    from labkit.bluesky import capture_protocol, session_devices
    from labkit.protocol import OperatorStage
    from labkit.protocol.hardware import Hardware, _start_simulator, open_slider
    from labkit.session import Session

    rig = _gige_rig(fake_gv.device_id)
    folder = tmp_path / "session"
    documents: list[tuple[str, dict]] = []
    engine = RunEngine({})
    engine.subscribe(lambda name, doc: documents.append((name, doc)))
    simulator = _start_simulator(rig, fast=True, on_move=None)
    try:
        with (
            AravisCamera(fake_gv.device_id, pixel_format="BayerRG8") as cam,
            open_slider(rig, port=simulator.port) as slider,
        ):
            cam.set("Width", 128)
            cam.set("Height", 48)
            stage = OperatorStage(assume_done=True, out=io.StringIO())
            d = session_devices(rig, folder, Hardware(cam, slider, stage))
            engine(capture_protocol(d.detector, d.slider, d.scene, d.cover))
    finally:
        simulator.stop()
    session = Session.open(folder)
    assert session.status == "complete" and len(session.records) == 90
    assert session.info["camera"]["serial"] == "LK01" and session.verify() == {}
    for record in session.records.values():
        assert record["status"] == "SUCCESS" and record["shape"] == [48, 128]
        assert record["exposure_readback_s"] == pytest.approx(record["exposure_s"], rel=1e-3)
    resources = [doc for name, doc in documents if name == "stream_resource"]
    assert sorted(r["parameters"]["labkit_key"] for r in resources) == sorted(session.records)
