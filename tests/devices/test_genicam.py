"""Tests of the genicam camera backend against Viky, the GenTL producer in the genicam wheel.

What Viky (``viky.cti``, genicam 1.6) offers, and so what these tests expect:

* three devices, ``VikyTL_DEV_red`` / ``_green`` / ``_blue``, vendor "Machine Vision Games
  Ltd.", model "Viky", serials "0" / "1" / "2", version "1.0" (its node map has no
  ``Device*`` identity features: the identity comes from the producer's device info);
* ``Width`` × ``Height`` 400 × 400 (settable 100…800), ``PixelFormat`` ``RGBa8`` (default)
  or ``Mono8``: **no Bayer format**, so ``cfa`` raises; ``RGBa8`` frames come back as
  (rows, cols, 4) uint8, ``Mono8`` frames as (rows, cols) uint8 mosaics;
* free-running ``Continuous`` acquisition at ``AcquisitionFrameRate`` 20 Hz, frame ids
  restarting at 1 with every acquisition, no device timestamps (reported as 0);
* **no** ``ExposureTime``/``ExposureTimeAbs``, ``Gain``/``GainRaw`` or trigger features:
  a bracketed capture must fail before anything is captured.

The software-trigger, stale-buffer and retry paths, which Viky cannot exercise, are tested
with a scripted stand-in for the Harvesters acquirer and node map swapped into an open
camera.
"""

from __future__ import annotations

import collections
import itertools
import math
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

harvesters_core = pytest.importorskip(
    "harvesters.core", reason="the genicam backend tests need the 'harvesters' package"
)
genicam = pytest.importorskip("genicam", reason="the genicam backend tests need 'genicam'")

from genicam.genapi import EInterfaceType  # noqa: E402

from labkit.devices.camera import Bounds, Camera, CameraIdentity, DeviceInfo  # noqa: E402
from labkit.devices.genicam import GenICamCamera, list_devices  # noqa: E402
from labkit.errors import ConfigError, DeviceError  # noqa: E402

VIKY = Path(genicam.__file__).parent / "viky.cti"
pytestmark = pytest.mark.skipif(
    not VIKY.is_file(), reason=f"the Viky GenTL producer is not installed at {VIKY}"
)

VIKY_IDS = ["VikyTL_DEV_red", "VikyTL_DEV_green", "VikyTL_DEV_blue"]
DTYPES = {"RGBa8": np.uint8, "Mono8": np.uint8}  # bits of Viky's formats → numpy dtype


@pytest.fixture
def cti() -> str:
    """Path of Viky's producer."""
    return str(VIKY)


@pytest.fixture
def camera(cti: str) -> Iterator[GenICamCamera]:
    """Viky's first device, opened (and closed after the test)."""
    cam = GenICamCamera(cti, timeout_s=2.0, retries=2)
    try:
        yield cam
    finally:
        cam.close()


# -- discovery and opening -----------------------------------------------------------------


def test_list_devices_finds_viky(cti: str) -> None:
    devices = list_devices(cti)
    assert [d.device_id for d in devices] == VIKY_IDS
    assert all(isinstance(d, DeviceInfo) and d.backend == "genicam" for d in devices)
    assert {d.model for d in devices} == {"Viky"}
    assert [d.serial for d in devices] == ["0", "1", "2"]


def test_list_devices_while_a_camera_is_open(camera: GenICamCamera, cti: str) -> None:
    # a producer loads once per process: the open camera's device list is reported
    assert [d.device_id for d in list_devices(cti)] == VIKY_IDS


def test_missing_cti_names_the_path(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere" / "vendor.cti"
    with pytest.raises(DeviceError, match="does not exist") as info:
        list_devices(missing)
    assert str(missing) in str(info.value)
    with pytest.raises(DeviceError, match="does not exist"):
        GenICamCamera(missing)


def test_unloadable_cti_names_the_path(tmp_path: Path) -> None:
    fake = tmp_path / "fake.cti"
    fake.write_text("not a shared library\n")
    with pytest.raises(DeviceError, match="cannot be loaded") as info:
        list_devices(fake)
    assert str(fake) in str(info.value)


def test_unknown_device_id_lists_the_devices(cti: str) -> None:
    with pytest.raises(DeviceError, match="no camera 'VikyTL_DEV_purple'") as info:
        GenICamCamera(cti, "VikyTL_DEV_purple")
    message = str(info.value)
    assert all(device_id in message for device_id in VIKY_IDS)
    assert cti in message


def test_ambiguous_model_asks_for_a_device_id(cti: str) -> None:
    with pytest.raises(DeviceError, match="matches the model of 3 cameras"):
        GenICamCamera(cti, "Viky")


@pytest.mark.parametrize(("key", "expected"), [("VikyTL_DEV_blue", "2"), ("1", "1")])
def test_device_matched_by_id_or_serial(cti: str, key: str, expected: str) -> None:
    with GenICamCamera(cti, key) as cam:
        assert cam.identity.serial == expected


def test_invalid_options(cti: str) -> None:
    with pytest.raises(ConfigError, match="timeout_s"):
        GenICamCamera(cti, timeout_s=0)
    with pytest.raises(ConfigError, match="retries"):
        GenICamCamera(cti, retries=-1)


# -- identity, features, format ------------------------------------------------------------


CAMERA_MEMBERS = (
    "backend", "identity", "pixel_format", "cfa", "shape", "feature_names", "get", "set",
    "exposure_bounds", "gain_bounds", "set_pixel_format", "grab", "stream_statistics", "close",
    "__enter__", "__exit__",
)  # fmt: skip


def test_implements_the_camera_protocol(camera: GenICamCamera) -> None:
    # isinstance(camera, Camera) reads every property on Python 3.11, and Viky's `cfa`
    # rightly raises (RGBa8 is not Bayer); check the members on the class instead (the
    # scripted Bayer camera below passes isinstance).
    assert all(hasattr(GenICamCamera, name) for name in CAMERA_MEMBERS)
    assert camera.backend == "genicam"


def test_identity(camera: GenICamCamera) -> None:
    assert camera.identity == CameraIdentity(
        vendor="Machine Vision Games Ltd.", model="Viky", serial="0", firmware="1.0"
    )
    assert camera.device_id == "VikyTL_DEV_red"


def test_shape_and_pixel_format(camera: GenICamCamera) -> None:
    assert camera.shape == (camera.get("Height"), camera.get("Width")) == (400, 400)
    assert camera.pixel_format == "RGBa8"
    assert camera.pixel_formats() == ["RGBa8", "Mono8"]


def test_features(camera: GenICamCamera) -> None:
    names = camera.feature_names()
    assert {"Width", "Height", "PixelFormat", "AcquisitionMode"} <= set(names)
    assert "ExposureTime" not in names and "TriggerSoftware" not in names
    camera.set("Width", 320)
    assert camera.get("Width") == 320 and camera.shape == (400, 320)


def test_feature_errors(camera: GenICamCamera) -> None:
    with pytest.raises(DeviceError, match="no feature 'ExposureTime'"):
        camera.get("ExposureTime")
    with pytest.raises(DeviceError, match="PayloadSize is read-only"):
        camera.set("PayloadSize", 1)
    with pytest.raises(DeviceError, match=r"Width=5 is outside \[100, 800\]"):
        camera.set("Width", 5)
    with pytest.raises(DeviceError, match="is a command"):
        camera.get("AcquisitionStart")
    with pytest.raises(DeviceError, match=r"pixel format 'BayerRG12' is not offered; .*RGBa8"):
        camera.set_pixel_format("BayerRG12")


def test_cfa_of_a_non_bayer_format_is_a_clear_error(camera: GenICamCamera) -> None:
    for pixel_format in camera.pixel_formats():
        camera.set_pixel_format(pixel_format)
        with pytest.raises(DeviceError, match=f"delivers {pixel_format}, not a Bayer format"):
            _ = camera.cfa


def test_gain_bounds_without_gain_feature_is_a_clear_error(camera: GenICamCamera) -> None:
    """As exposure_bounds does (and the Aravis backend), naming the features looked for."""
    with pytest.raises(DeviceError, match=r"no gain feature \(neither Gain nor GainRaw\)"):
        camera.gain_bounds()


# -- acquisition ---------------------------------------------------------------------------


def _check_frames(frames: list, cam: GenICamCamera, n: int, pixel_format: str) -> None:
    rows, cols = cam.get("Height"), cam.get("Width")
    assert len(frames) == n
    for frame in frames:
        assert frame.image.shape[:2] == (rows, cols)
        assert frame.image.dtype == DTYPES[pixel_format]
        assert frame.pixel_format == pixel_format and frame.status == "SUCCESS"
        assert math.isnan(frame.exposure_s) and math.isnan(frame.exposure_readback_s)
        assert frame.extra["trigger"] == "free-running"
    ids = [f.frame_id for f in frames]
    assert all(b > a for a, b in itertools.pairwise(ids)), ids
    hosts = [f.host_timestamp_s for f in frames]
    assert all(b >= a for a, b in itertools.pairwise(hosts)), hosts
    stamps = [f.device_timestamp_ns for f in frames]
    assert all(b >= a for a, b in itertools.pairwise(stamps)), stamps


def test_free_running_acquisition_rgba8(camera: GenICamCamera) -> None:
    frames = camera.grab_free_running(4)
    _check_frames(frames, camera, 4, "RGBa8")
    assert frames[0].image.shape == (400, 400, 4)  # multi-component: not a mosaic
    assert frames[0].image.flags.owndata  # copied out of the GenTL buffer
    stats = camera.stream_statistics()
    assert stats["frames_delivered"] == 4 and stats["buffers_failed"] == 0
    assert not camera._ia.is_acquiring()  # free-running grabs stop when done


def test_free_running_acquisition_mono8_mosaic(cti: str) -> None:
    with GenICamCamera(cti, "VikyTL_DEV_green", pixel_format="Mono8") as cam:
        cam.set("Width", 256)
        cam.set("Height", 128)
        frames = cam.grab(None, 3)  # None: "as configured", the same path as free running
        _check_frames(frames, cam, 3, "Mono8")
        assert frames[0].image.shape == (128, 256)
        again = cam.grab_free_running(2)  # a new acquisition: nothing stale leaks in
        _check_frames(again, cam, 2, "Mono8")
        assert cam.stream_statistics()["buffers_discarded"] == 0


def test_bracketed_capture_fails_before_capturing(camera: GenICamCamera) -> None:
    before = camera.stream_statistics()
    for request in (camera.exposure_bounds, lambda: camera.grab(0.01, 1)):
        with pytest.raises(DeviceError, match="ExposureTime") as info:
            request()
        message = str(info.value)
        assert "ExposureTimeAbs" in message and camera.device_id in message
        assert camera.cti in message and "fixed exposure" in message
    assert camera.stream_statistics() == before
    assert before["acquisitions_started"] == before["buffers_fetched"] == 0
    assert not camera._ia.is_acquiring()
    assert camera._ia.statistics.num_images == 0
    with pytest.raises(DeviceError, match="ExposureTime"):
        camera.grab_free_running(1, exposure_s=0.01)
    assert camera.stream_statistics() == before


def test_grab_rejects_bad_frame_counts(camera: GenICamCamera) -> None:
    with pytest.raises(ConfigError, match="n >= 1"):
        camera.grab(None, 0)


def test_close_is_idempotent_and_releases_the_device(cti: str) -> None:
    cam = GenICamCamera(cti, "VikyTL_DEV_blue")
    with pytest.raises(DeviceError, match="cannot be opened"):
        GenICamCamera(cti, "VikyTL_DEV_blue")  # held by `cam`
    cam.close()
    cam.close()
    with pytest.raises(DeviceError, match="is closed"):
        cam.grab(None, 1)
    with GenICamCamera(cti, "VikyTL_DEV_blue") as again:
        assert again.grab_free_running(1)[0].frame_id == 1


# -- software trigger, stale buffers and retries (scripted stand-in) -----------------------


class _Node:
    """A GenApi-like node: typed value, access mode and bounds."""

    def __init__(self, name: str, kind: str, value: Any = None, *, access: int = 4,
                 low: float = 0, high: float = 0, inc: float = 0,
                 choices: tuple[str, ...] = (), action: Any = None) -> None:  # fmt: skip
        self.name, self.kind, self.value, self.access = name, kind, value, access
        self.min, self.max, self.inc, self.symbolics, self.unit = low, high, inc, choices, ""
        self._action = action
        interface = getattr(EInterfaceType, f"intfI{kind.capitalize()}")
        self.node = SimpleNamespace(
            name=name, principal_interface_type=interface, is_feature=lambda: True,
            get_access_mode=lambda: self.access,
        )  # fmt: skip

    def execute(self) -> None:
        self._action()


class _NodeMap:
    def __init__(self, nodes: list[_Node]) -> None:
        self._nodes = {n.name: n for n in nodes}
        self.nodes = list(nodes)

    def has_node(self, name: str) -> bool:
        return name in self._nodes

    def get_node(self, name: str) -> _Node:
        return self._nodes[name]


class _Acquirer:
    """Stands in for harvesters' ImageAcquirer: buffers on trigger or on demand.

    `script` holds what successive fetches see: ``"lose"`` (a timeout), ``"dup"`` (the
    previous buffer's id again) or ``None`` (the next frame).
    """

    def __init__(self, nodes: _NodeMap, shape: tuple[int, int]) -> None:
        self.nodes, self.shape = nodes, shape
        self.acquiring = False
        self.next_id = 1
        self.ready: collections.deque[int] = collections.deque()
        self.script: collections.deque[str | None] = collections.deque()
        self.queued = 0
        self.starts = 0
        self.data_streams: list = []

    def is_acquiring(self) -> bool:
        return self.acquiring

    def start(self) -> None:
        self.acquiring, self.ready, self.next_id = True, collections.deque(), 1
        self.starts += 1

    def stop(self) -> None:
        self.acquiring = False
        self.ready.clear()

    def trigger(self) -> None:
        assert self.acquiring and self.nodes.get_node("TriggerMode").value == "On"
        self.ready.append(self.next_id)
        self.next_id += 1

    def try_fetch(self, *, timeout: float) -> Any:
        assert self.acquiring
        triggered = self.nodes.get_node("TriggerMode").value == "On"
        if triggered and not self.ready:
            return None  # nothing triggered: a timeout
        action = self.script.popleft() if self.script else None
        if action == "lose":
            if self.ready:
                self.ready.popleft()
            return None
        if action == "dup":
            return self._buffer(self.next_id - 1)
        if not self.ready:  # free running: expose one now
            self.ready.append(self.next_id)
            self.next_id += 1
        return self._buffer(self.ready.popleft())

    def _buffer(self, frame_id: int) -> Any:
        rows, cols = self.shape
        data = np.full(rows * cols, frame_id, dtype=np.uint16)
        component = SimpleNamespace(width=cols, height=rows, data=data, data_format="BayerRG12",
                                    num_components_per_pixel=1.0)  # fmt: skip

        def queue() -> None:
            self.queued += 1

        return SimpleNamespace(
            module=SimpleNamespace(frame_id=frame_id, timestamp_ns=1000 * frame_id),
            payload=SimpleNamespace(components=[component]), queue=queue,
        )  # fmt: skip


@pytest.fixture
def scripted(camera: GenICamCamera) -> Iterator[tuple[GenICamCamera, _Acquirer]]:
    """`camera` with a scripted Bayer camera (ExposureTime, Gain, software trigger) swapped in."""
    real = camera._ia, camera._nodes
    nodes = _NodeMap([
        _Node("Width", "integer", 8, access=3), _Node("Height", "integer", 6, access=3),
        _Node("PixelFormat", "enumeration", "BayerRG12", choices=("BayerRG12", "Mono8")),
        _Node("ExposureTime", "float", 5000.0, low=20.0, high=1e6, inc=1.0),
        _Node("Gain", "float", 3.0, low=0.0, high=24.0),
        _Node("AcquisitionMode", "enumeration", "Continuous", choices=("Continuous",)),
        _Node("TriggerSelector", "enumeration", "FrameStart", choices=("FrameStart",)),
        _Node("TriggerMode", "enumeration", "Off", choices=("Off", "On")),
        _Node("TriggerSource", "enumeration", "Line1", choices=("Line1", "Software")),
    ])  # fmt: skip
    acquirer = _Acquirer(nodes, (6, 8))
    nodes._nodes["TriggerSoftware"] = _Node("TriggerSoftware", "command", action=acquirer.trigger)
    camera._ia, camera._nodes = acquirer, nodes  # type: ignore[assignment]
    try:
        yield camera, acquirer
    finally:
        camera._ia, camera._nodes = real


def test_software_triggered_bracket(scripted: tuple[GenICamCamera, _Acquirer]) -> None:
    cam, acq = scripted
    assert isinstance(cam, Camera)
    assert cam.cfa == "RGGB"
    exposure = cam.exposure_bounds()
    assert (exposure.minimum, exposure.maximum, exposure.increment) == pytest.approx(
        (20e-6, 1.0, 1e-6)
    )
    assert cam.gain_bounds() == Bounds(0.0, 24.0, 0.0)
    short = cam.grab(0.01, 2)
    assert cam.get("TriggerMode") == "On" and cam.get("TriggerSource") == "Software"
    assert cam.get("ExposureTime") == pytest.approx(10_000.0)
    assert [f.frame_id for f in short] == [1, 2]
    assert short[0].image.shape == (6, 8) and short[0].image.dtype == np.uint16
    assert short[0].exposure_readback_s == pytest.approx(0.01)
    assert short[0].gain_db == 3.0 and short[0].device_timestamp_ns == 1000
    assert short[0].extra["trigger"] == "software"
    # a frame the camera delivered between grabs is stale: drained, never returned
    acq.trigger()
    long = cam.grab(0.02, 2)
    assert [f.frame_id for f in long] == [4, 5]
    assert all(f.exposure_s == 0.02 for f in long)
    stats = cam.stream_statistics()
    assert stats["buffers_discarded"] == 1 and stats["triggers_sent"] == 4
    assert acq.starts == 1  # the triggered acquisition keeps running between grabs
    assert acq.queued == stats["buffers_fetched"] == 5  # every buffer went back


def test_out_of_range_exposure_captures_nothing(scripted: tuple[GenICamCamera, _Acquirer]) -> None:
    cam, acq = scripted
    with pytest.raises(DeviceError, match=r"exposure 5 s is outside .*\[2e-05, 1\] s"):
        cam.grab(5.0, 1)
    assert acq.starts == 0 and cam.get("TriggerMode") == "Off"
    assert cam.get("ExposureTime") == 5000.0


def test_lost_frame_is_retriggered(scripted: tuple[GenICamCamera, _Acquirer]) -> None:
    cam, acq = scripted
    acq.script.extend(["lose", None])
    frames = cam.grab(0.001, 1)
    assert [f.frame_id for f in frames] == [2]
    stats = cam.stream_statistics()
    assert stats["retries"] == 1 and stats["buffers_failed"] == 1 and stats["triggers_sent"] == 2


def test_retries_are_bounded(scripted: tuple[GenICamCamera, _Acquirer]) -> None:
    cam, acq = scripted
    acq.script.extend(["lose"] * 3)  # the fixture's camera has retries=2
    with pytest.raises(DeviceError, match="no complete frame 1 of 1 after 3 attempts"):
        cam.grab(0.001, 1)
    assert cam.stream_statistics()["triggers_sent"] == 3
    assert not acq.acquiring  # a failed grab stops the acquisition


def test_free_running_discards_repeated_frames(
    scripted: tuple[GenICamCamera, _Acquirer],
) -> None:
    cam, acq = scripted
    acq.script.extend([None, "dup", None])
    frames = cam.grab_free_running(2, exposure_s=0.002)
    assert [f.frame_id for f in frames] == [1, 2]
    assert cam.get("TriggerMode") == "Off" and cam.get("ExposureTime") == pytest.approx(2000.0)
    assert cam.stream_statistics()["buffers_discarded"] == 1
    assert not acq.acquiring
