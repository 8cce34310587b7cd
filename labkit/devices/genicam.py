"""GenICam camera backend: any GenTL producer (``.cti``) driven through Harvesters.

:func:`list_devices` discovers the cameras a producer offers; :class:`GenICamCamera`
opens one and implements the :class:`~labkit.devices.camera.Camera` protocol on top of
its GenICam node map (``ExposureTime`` in µs, ``Gain`` in dB, ``PixelFormat``,
``TriggerMode``/``TriggerSource``/``TriggerSoftware``…).

Acquisition
-----------
:meth:`GenICamCamera.grab` validates the requested exposure against the device's
bounds *before* anything is captured, then

* uses a software trigger when the device has ``TriggerMode``, ``TriggerSource`` (with
  a ``Software`` entry) and ``TriggerSoftware``: the acquisition keeps running between
  grabs, buffers left over from earlier grabs are drained and every returned frame
  answers a trigger sent after the settings changed;
* otherwise runs the device free-running: the acquisition is (re)started after the
  settings changed (stopping flushes every buffer that was in flight) and stopped again
  after the last frame.

In both modes a fetched buffer is only kept when its frame id is newer than every id
seen before the change (and than the previous kept frame), its device timestamp (when
the producer reports one) is later than the previous kept frame's and it arrived after
the change; anything else is counted as *discarded*. Timed-out or incomplete fetches are
retried at most ``retries`` times per frame (re-sending the trigger), then a
DeviceError is raised.

Images are copied out of the GenTL buffer before it is queued back. Single-component
formats (``Bayer*``, ``Mono*``) give a ``(rows, cols)`` uint8/uint16 mosaic;
multi-component formats (e.g. ``RGBa8``) give ``(rows, cols, components)``; they are
not raw mosaics and :attr:`GenICamCamera.cfa` refuses them.

One GenTL producer can be loaded only once per process, so cameras on the same
``.cti`` share one Harvester; :func:`list_devices` reuses it while a camera is open
(reporting the devices found when it was opened).
"""

from __future__ import annotations

import contextlib
import math
import time
import weakref
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from labkit.devices._gentl import (
    BACKEND,
    Producer,
    acquire_producer,
    check_cti,
    close_device,
    first_line,
    format_devices,
    genicam_errors,
    info_text,
    release_producer,
)
from labkit.devices.camera import CameraIdentity
from labkit.devices.genicam_features import GenICamFeatures
from labkit.devices.gentl_producers import list_devices
from labkit.errors import ConfigError, DeviceError
from labkit.frame import Frame

if TYPE_CHECKING:
    from harvesters.core import Buffer

__all__ = ["GenICamCamera", "list_devices"]


#: GenApi access modes (genicam.genapi.EAccessMode values) by their names.
_NI = 0
_ACCESS_MODES = {0: "NI", 1: "NA", 2: "WO", 3: "RO", 4: "RW"}

#: Seconds a drain fetch waits for an already-delivered buffer.
_DRAIN_TIMEOUT_S = 0.002
#: Stale buffers tolerated per frame before a grab gives up.
_MAX_DISCARDS_PER_FRAME = 64


class GenICamCamera(GenICamFeatures):
    """A camera behind a GenTL producer, opened through Harvesters.

    Parameters
    ----------
    cti : str or Path
        Path of the GenTL producer (``.cti``).
    device_id : str or None
        Which device: matched against the producer's device id, then the serial number,
        then the model name. None opens the first device.
    pixel_format : str or None
        Pixel format to select on opening (e.g. ``BayerRG12``); None keeps the device's.
    timeout_s : float
        How long one fetch waits for a buffer, s (the exposure time is added).
    retries : int
        How many failed or timed-out fetches are retried per frame.

    Raises
    ------
    DeviceError
        When the producer is unusable, `device_id` matches no device (the message lists
        the devices found) or several, or the device cannot be opened.
    ConfigError
        When `timeout_s` or `retries` is invalid.
    """

    backend = BACKEND
    no_exposure_hint = (
        "use a fixed exposure (grab(None, n) or grab_free_running(n), a plan without "
        "exposure times) or a camera with exposure control"
    )

    def __init__(
        self,
        cti: str | Path,
        device_id: str | None = None,
        *,
        pixel_format: str | None = None,
        timeout_s: float = 2.0,
        retries: int = 3,
    ) -> None:
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ConfigError(
                f"genicam camera: timeout_s must be a positive time in s, got {timeout_s!r}"
            )
        if int(retries) != retries or retries < 0:
            raise ConfigError(
                f"genicam camera: retries must be a whole number >= 0, got {retries!r}"
            )
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.cti = check_cti(cti)
        self._closed = True
        self._stats = dict.fromkeys(
            ("acquisitions_started", "buffers_fetched", "frames_delivered", "buffers_failed",
             "buffers_discarded", "retries", "triggers_sent"), 0,
        )  # fmt: skip
        self._host_frame_id = 0
        self._acquisition_last_id: int | None = None
        producer = acquire_producer(self.cti)
        try:
            index = self._match(producer, device_id)
            self.device_id = producer.devices[index].device_id
            self._info = producer.devices[index]
            self._version = info_text(producer.harvester.device_info_list[index], "version")
            try:
                self._ia = producer.harvester.create(index)
            except Exception as exc:
                raise DeviceError(
                    f"camera {self.device_id} ({self.cti}) cannot be opened ({first_line(exc)}); "
                    "close other programs (or GenICamCamera objects) using it"
                ) from None
        except BaseException:
            release_producer(self.cti)
            raise
        self._closed = False
        self._finalizer = weakref.finalize(self, close_device, self._ia, self.cti)
        self._nodes = self._ia.remote_device.node_map
        if pixel_format is not None:
            try:
                self.set_pixel_format(pixel_format)
            except BaseException:
                self.close()
                raise

    def _match(self, producer: Producer, device_id: str | None) -> int:
        devices = producer.devices
        where = f"GenTL producer {producer.cti}"
        if not devices:
            raise DeviceError(
                f"{where} found no camera; check that it is connected and powered, and that "
                "no other process holds the producer"
            )
        if device_id is None:
            return 0
        for key in ("device_id", "serial", "model"):
            hits = [i for i, d in enumerate(devices) if getattr(d, key) == device_id]
            if len(hits) == 1:
                return hits[0]
            if len(hits) > 1:
                raise DeviceError(
                    f"{where}: {device_id!r} matches the {key} of {len(hits)} cameras "
                    f"({format_devices([devices[i] for i in hits])}); give a device id instead"
                )
        raise DeviceError(
            f"{where} has no camera {device_id!r}; devices found: {format_devices(devices)}; "
            "set the rig's camera device to one of these ids or serial numbers"
        )

    # -- identity and features -----------------------------------------------------------
    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"GenICamCamera({self.cti!r}, {self.device_id!r}) [{state}]"

    @property
    def _where(self) -> str:
        return f"camera {self.device_id} ({self.cti})"

    def _check_open(self) -> None:
        if self._closed:
            raise DeviceError(f"{self._where} is closed; open a new GenICamCamera")

    # -- the node-map primitives of GenICamFeatures ---------------------------------------------
    def _usable(self) -> None:
        self._check_open()

    def _kind(self, name: str) -> str | None:
        if not self._nodes.has_node(name):
            return None
        from genicam.genapi import EInterfaceType

        kind = self._nodes.get_node(name).node.principal_interface_type
        return str(EInterfaceType(kind).name).removeprefix("intfI").lower()

    def _access(self, name: str) -> str | None:
        mode = self._nodes.get_node(name).node.get_access_mode()
        return _ACCESS_MODES.get(int(mode), str(mode))

    def _read(self, name: str, kind: str) -> Any:
        return self._nodes.get_node(name).value

    def _write(self, name: str, kind: str, value: Any) -> None:
        self._nodes.get_node(name).value = value

    def _limits(self, name: str, kind: str) -> tuple[float, float]:
        node = self._nodes.get_node(name)
        return float(node.min), float(node.max)

    def _increment(self, name: str, kind: str) -> float:
        try:
            return float(self._nodes.get_node(name).inc)
        except Exception:  # GenApi raises for a float without an increment
            return 0.0

    def _choices(self, name: str) -> list[str]:
        return [str(entry) for entry in self._nodes.get_node(name).symbolics]

    def _run(self, name: str) -> None:
        self._nodes.get_node(name).execute()

    def _unit(self, name: str) -> str:
        try:
            return str(self._nodes.get_node(name).unit)
        except Exception:
            return ""

    @contextlib.contextmanager
    def _device_call(self, action: str) -> Iterator[None]:
        try:
            yield
        except genicam_errors() as exc:
            raise DeviceError(f"{self._where}: {action} failed ({first_line(exc)})") from None

    @property
    def identity(self) -> CameraIdentity:
        """Vendor, model, serial and firmware (node-map features, else the producer's info)."""

        def first(names: tuple[str, ...], fallback: str) -> str:
            for name in names:
                if self.has_feature(name):
                    try:
                        return str(self.get(name))
                    except DeviceError:
                        continue
            return fallback

        info = self._info
        return CameraIdentity(
            vendor=first(("DeviceVendorName",), info.vendor),
            model=first(("DeviceModelName",), info.model),
            serial=first(("DeviceSerialNumber", "DeviceID"), info.serial),
            firmware=first(("DeviceFirmwareVersion", "DeviceVersion"), self._version),
        )

    def feature_names(self) -> list[str]:
        """Names of the device's implemented features (categories left out), node-map order."""
        from genicam.genapi import EInterfaceType

        self._check_open()
        category = EInterfaceType.intfICategory
        names = []
        for item in self._nodes.nodes:
            node = item.node
            if (
                node.is_feature()
                and node.principal_interface_type != category
                and node.get_access_mode() != _NI
            ):
                names.append(node.name)
        return names

    # -- exposure and gain ---------------------------------------------------------------
    def _gain_db(self) -> float:
        return float(self.get("Gain")) if self.has_feature("Gain") else math.nan

    # -- image format --------------------------------------------------------------------
    @property
    def pixel_format(self) -> str:
        """Current GenICam pixel format, e.g. ``BayerGB12`` (Viky: ``RGBa8`` or ``Mono8``)."""
        return str(self.get("PixelFormat"))

    def set_pixel_format(self, pixel_format: str) -> None:
        """Choose the pixel format (stops a running acquisition first).

        Raises
        ------
        DeviceError
            When the device does not offer `pixel_format` (the message lists what it offers).
        """
        self._check_offered(pixel_format)
        self._stop()
        self.set("PixelFormat", pixel_format)

    # -- acquisition ---------------------------------------------------------------------
    def _start(self) -> None:
        if self._ia.is_acquiring():
            return
        self._continuous_acquisition()
        try:
            self._ia.start()
        except Exception as exc:
            raise DeviceError(
                f"{self._where}: starting the acquisition failed ({first_line(exc)}); check "
                "the connection and that no other program streams from the camera"
            ) from None
        self._stats["acquisitions_started"] += 1
        self._acquisition_last_id = None  # producers may restart their frame counter

    def _stop(self) -> None:
        if not self._closed and self._ia.is_acquiring():
            self._ia.stop()

    def _stop_for_change(self) -> None:
        self._stop()

    def _drain(self) -> int | None:
        """Fetch and discard buffers already delivered; return the largest frame id seen."""
        newest: int | None = None
        for _ in range(_MAX_DISCARDS_PER_FRAME):
            buffer = self._ia.try_fetch(timeout=_DRAIN_TIMEOUT_S)
            if buffer is None:
                break
            try:
                frame_id = self._frame_id(buffer)
            finally:
                buffer.queue()
            self._stats["buffers_fetched"] += 1
            self._stats["buffers_discarded"] += 1
            newest = frame_id if newest is None else max(newest, frame_id)
        return newest

    def grab(self, exposure_s: float | None, n: int = 1) -> list[Frame]:
        """Capture `n` frames exposed for `exposure_s` seconds.

        Parameters
        ----------
        exposure_s : float or None
            Exposure time, s; None captures at the exposure as configured (the only
            choice on a camera without ``ExposureTime``/``ExposureTimeAbs``).
        n : int
            Number of frames (>= 1).

        Returns
        -------
        list of Frame
            Frames exposed after this call changed the settings, frame ids strictly
            increasing, status ``"SUCCESS"``. ``exposure_s``/``exposure_readback_s``
            are NaN when the camera has no exposure feature, ``gain_db`` NaN when it has
            no ``Gain`` feature; ``device_timestamp_ns`` is 0 when the producer reports
            no timestamps.

        Raises
        ------
        DeviceError
            Before anything is captured when the exposure is out of range or the camera
            has no exposure feature (the message names ``ExposureTime``); after
            ``retries`` failed fetches of one frame.
        ConfigError
            When `n` is not a positive whole number.
        """
        self._check_open()
        if int(n) != n or n < 1:
            raise ConfigError(f"{self._where}: grab needs n >= 1 frames, got {n!r}")
        if exposure_s is not None:
            self._check_exposure(exposure_s)  # missing feature or out of range: no capture
        return self._capture(exposure_s, int(n), trigger=self._software_trigger_available())

    def grab_free_running(self, n: int = 1, exposure_s: float | None = None) -> list[Frame]:
        """Capture `n` frames without a trigger, at the configured (or given) exposure.

        Works on cameras without exposure control or trigger features (e.g. Viky).
        See :meth:`grab` for the returned frames.
        """
        self._check_open()
        if int(n) != n or n < 1:
            raise ConfigError(f"{self._where}: grab needs n >= 1 frames, got {n!r}")
        if exposure_s is not None:
            self._check_exposure(exposure_s)
        return self._capture(exposure_s, int(n), trigger=False)

    def _capture(self, exposure_s: float | None, n: int, *, trigger: bool) -> list[Frame]:
        self._use_software_trigger(trigger)
        if not trigger:
            self._stop()  # flushes every buffer in flight
        if exposure_s is not None:
            try:
                self._set_exposure(exposure_s)
            except DeviceError:
                if not self._ia.is_acquiring():
                    raise
                self._stop()  # some devices lock the exposure while acquiring
                self._set_exposure(exposure_s)
        readback_s = self._exposure_readback_s()
        requested_s = readback_s if exposure_s is None else float(exposure_s)
        gain_db = self._gain_db()
        pixel_format = self.pixel_format
        changed_at = time.time()
        self._start()  # a (re)start forgets the frame ids of the previous acquisition
        floor = self._acquisition_last_id
        if trigger:  # buffers delivered since the last grab are stale
            drained = self._drain()
            if drained is not None:
                floor = drained if floor is None else max(floor, drained)
        fetch_timeout = self.timeout_s + (0.0 if math.isnan(readback_s) else readback_s)
        try:
            return self._collect(
                n, trigger=trigger, floor=floor, changed_at=changed_at,
                fetch_timeout=fetch_timeout, requested_s=requested_s, readback_s=readback_s,
                gain_db=gain_db, pixel_format=pixel_format,
            )  # fmt: skip
        except BaseException:
            self._stop()
            raise
        finally:
            if not trigger:
                self._stop()

    def _collect(
        self, n: int, *, trigger: bool, floor: int | None, changed_at: float,
        fetch_timeout: float, requested_s: float, readback_s: float, gain_db: float,
        pixel_format: str,
    ) -> list[Frame]:  # fmt: skip
        frames: list[Frame] = []
        last_id = floor
        last_stamp = 0
        failures = discards = 0
        need_trigger = trigger
        while len(frames) < n:
            if need_trigger:
                self.execute("TriggerSoftware")
                self._stats["triggers_sent"] += 1
                need_trigger = False
            buffer = self._ia.try_fetch(timeout=fetch_timeout)
            if buffer is None:
                self._stats["buffers_failed"] += 1
                failures += 1
                if failures > self.retries:
                    raise DeviceError(
                        f"{self._where}: no complete frame {len(frames) + 1} of {n} after "
                        f"{failures} attempts of {fetch_timeout:g} s each "
                        f"(statistics {self.stream_statistics()}); check the cable and "
                        "bandwidth, or raise timeout_s / retries"
                    )
                self._stats["retries"] += 1
                need_trigger = trigger
                continue
            try:
                arrived = time.time()
                frame_id = self._frame_id(buffer)
                stamp = self._device_timestamp_ns(buffer)
                stale = (
                    (last_id is not None and frame_id <= last_id)
                    or (stamp > 0 and last_stamp > 0 and stamp <= last_stamp)
                    or arrived < changed_at
                )
                image = None if stale else self._image(buffer, pixel_format)
            finally:
                buffer.queue()
            self._stats["buffers_fetched"] += 1
            if stale:
                self._stats["buffers_discarded"] += 1
                discards += 1
                if discards > _MAX_DISCARDS_PER_FRAME * n:
                    raise DeviceError(
                        f"{self._where}: {discards} stale buffers (frame ids or timestamps "
                        "not newer than the settings change); the producer's frame counter "
                        "or clock looks broken; restart the camera"
                    )
                continue
            assert image is not None
            frames.append(
                Frame(
                    image=image,
                    frame_id=frame_id,
                    exposure_s=requested_s,
                    exposure_readback_s=readback_s,
                    gain_db=gain_db,
                    pixel_format=pixel_format,
                    device_timestamp_ns=stamp,
                    host_timestamp_s=arrived,
                    extra={
                        "backend": BACKEND,
                        "cti": self.cti,
                        "device_id": self.device_id,
                        "trigger": "software" if trigger else "free-running",
                    },
                )
            )
            self._stats["frames_delivered"] += 1
            last_id, last_stamp = frame_id, stamp or last_stamp
            self._acquisition_last_id = frame_id
            need_trigger = trigger
        return frames

    def _frame_id(self, buffer: Buffer) -> int:
        try:
            return int(buffer.module.frame_id)
        except Exception:  # the producer keeps no frame counter: count on the host
            self._host_frame_id += 1
            return self._host_frame_id

    @staticmethod
    def _device_timestamp_ns(buffer: Buffer) -> int:
        """Device timestamp, ns; 0 when the producer reports none."""
        module = buffer.module
        with contextlib.suppress(Exception):  # producers without ns timestamps raise
            return int(module.timestamp_ns)
        try:
            ticks = int(module.timestamp)
            frequency = int(module.parent.parent.timestamp_frequency)
        except Exception:
            return 0
        return ticks * 1_000_000_000 // frequency if frequency > 0 else 0

    def _image(self, buffer: Buffer, pixel_format: str) -> np.ndarray:
        """Copy the buffer's first 2-D image component into a uint8/uint16 array."""
        payload = buffer.payload
        components = [] if payload is None else payload.components
        component = next((c for c in components if hasattr(c, "width")), None)
        if component is None or component.data is None:
            raise DeviceError(
                f"{self._where}: buffer holds no image component (payload {payload!r}); "
                "select an image pixel format"
            )
        rows, cols = int(component.height), int(component.width)
        channels = component.num_components_per_pixel
        data = component.data
        if data.dtype not in (np.uint8, np.uint16) or channels != int(channels):
            raise DeviceError(
                f"{self._where}: pixel format {component.data_format} ({data.dtype}, {channels} "
                "components per pixel) is not an integer image; select a Bayer or Mono format"
            )
        channels = int(channels)
        if data.size != rows * cols * channels:
            raise DeviceError(
                f"{self._where}: buffer has {data.size} values for a {rows}×{cols}×{channels} "
                f"{pixel_format} image (line padding?); check Width/PixelFormat"
            )
        shape = (rows, cols) if channels == 1 else (rows, cols, channels)
        return np.array(data.reshape(shape), copy=True)

    def stream_statistics(self) -> dict[str, int]:
        """Counters since opening, plus the producer's stream counters while acquiring.

        Returns
        -------
        dict of str to int
            ``acquisitions_started``, ``buffers_fetched`` (complete buffers received),
            ``frames_delivered`` (returned by grab), ``buffers_failed`` (timeouts and
            incomplete buffers), ``buffers_discarded`` (stale), ``retries``,
            ``triggers_sent``, and ``stream_<name>`` for the GenTL data-stream counters
            the producer reports (``stream_num_delivered``, ``stream_num_underrun``…).
        """
        stats = dict(self._stats)
        if self._closed:
            return stats
        for stream in self._ia.data_streams:
            for name in ("num_delivered", "num_underrun", "num_announced", "num_queued",
                         "num_started"):  # fmt: skip
                try:
                    stats[f"stream_{name}"] = int(getattr(stream.module, name))
                except Exception:
                    continue
            break
        return stats

    # -- lifetime ------------------------------------------------------------------------
    def close(self) -> None:
        """Stop any acquisition and release the device (and the producer, if last). Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._finalizer()

    def __enter__(self) -> GenICamCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
