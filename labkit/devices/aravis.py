"""Aravis camera backend: GigE Vision cameras through PyGObject and the system's Aravis 0.8.

:func:`list_devices` discovers the cameras Aravis sees; :class:`AravisCamera` opens one by
its Aravis device id (``<vendor>-<model>-<serial>``, as ``labkit devices`` prints it) and
implements the :class:`~labkit.devices.camera.Camera` protocol. Exposure times are in
seconds in this API and µs at the GenICam boundary; Aravis itself chooses between the
``ExposureTime`` and the older ``ExposureTimeAbs`` feature (and between ``Gain``, dB, and
``GainRaw``, device units).

Acquisition
-----------
:meth:`AravisCamera.grab` checks the exposure against the device's bounds before anything
is triggered, then runs the camera software triggered (``TriggerMode=On``,
``TriggerSource=Software``, ``AcquisitionMode=Continuous``, ``ExposureAuto`` and
``GainAuto`` off) into a stream with a pool of buffers; the acquisition keeps running
between grabs. After a setting changes, buffers still in flight are drained, and a buffer
is only accepted when its status is ``SUCCESS``, its frame id is newer than the last
accepted one (16-bit GigE Vision block ids are unwrapped) and it arrived (host clock)
after the change. Failed buffers (``TIMEOUT``, ``MISSING_PACKETS``…), missing ones and
stalled ones (packets stopped arriving but Aravis holds the incomplete frame back, as it
does for the most recent frame) are re-triggered up to ``retries`` times per frame, then
a :class:`~labkit.errors.DeviceError` says which frame failed and why. Pixels are decoded
by :mod:`labkit.devices._pixels` (8-bit, 10/12/14/16-bit in 16-bit words, PFNC ``…p``
and GigE Vision ``…Packed`` layouts).

Aravis sizes a stream's socket receive buffer only when the first packet arrives, so the
first large frame of a fresh stream may lose packets; a camera that can resend recovers
them, otherwise that frame is simply retried.

Reconnection
------------
The ``control-lost`` signal of the Aravis device (heartbeat failure) sets a flag; the next
operation, or a frame wait that timed out, closes the camera, re-opens it by its device
id (``reconnect_attempts`` times with a growing back-off), re-applies the pixel format,
gain and every feature written through :meth:`AravisCamera.set`, re-arms the software
trigger and resumes. Reconnects are counted in :meth:`AravisCamera.stream_statistics`.

Streams to a camera on a loopback address (the ``arv-fake-gv-camera-0.8`` simulator) use
ordinary UDP sockets: Aravis' packet-socket receiver listens on the physical interface and
never sees loopback traffic.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
import weakref
from collections.abc import Iterator
from typing import Any

from labkit.devices import _pixels
from labkit.devices.camera import CameraIdentity, DeviceInfo
from labkit.devices.genicam_features import EXPOSURE_FEATURES, GAIN_FEATURES, GenICamFeatures
from labkit.errors import DataError, DeviceError
from labkit.frame import Frame

try:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis, GLib, GObject
except (ImportError, ValueError) as _error:  # no PyGObject, or no Aravis 0.8 typelib
    Aravis = None
    GLib = None
    GObject = None
    _IMPORT_ERROR: Exception | None = _error
else:
    _IMPORT_ERROR = None

__all__ = ["BACKEND", "AravisCamera", "list_devices"]

BACKEND = "aravis"

#: Features that change the payload or the stream: writing one stops the acquisition and
#: the stream is rebuilt (with buffers of the new payload size) by the next grab.
STREAM_FEATURES = frozenset({
    "PixelFormat", "Width", "Height", "OffsetX", "OffsetY", "BinningHorizontal",
    "BinningVertical", "DecimationHorizontal", "DecimationVertical", "AcquisitionMode",
    "GevSCPSPacketSize", "ChunkModeActive", "ChunkEnable", "ChunkSelector",
})  # fmt: skip

#: GenICam SFNC categories, walked besides ``Root`` by :meth:`AravisCamera.feature_names`
#: (Aravis' Python binding offers no safe way to enumerate every node of the XML).
SFNC_CATEGORIES = (
    "DeviceControl", "ImageFormatControl", "AcquisitionControl", "AnalogControl",
    "LUTControl", "ColorTransformationControl", "DigitalIOControl", "CounterAndTimerControl",
    "EventControl", "UserSetControl", "ChunkDataControl", "TransportLayerControl",
    "FileAccessControl", "SequencerControl", "SoftwareSignalControl", "TestControl",
)  # fmt: skip
#: GigE Vision 1.x block ids are 16 bits and skip 0: they run 1, 2, …, 65535, 1, …
_GV_ID_PERIOD = 0xFFFF
#: Bytes of socket receive buffer asked for per byte of payload (the kernel caps it at
#: ``net.core.rmem_max``), and its bounds.
_SOCKET_BUFFER_FACTOR = 4
_SOCKET_BUFFER_BOUNDS = (1 << 20, 1 << 26)
#: Seconds a frame wait sleeps between checks of the stream's packet counter.
_POLL_S = 0.05
#: Seconds without packets after which a frame that started arriving counts as stalled
#: (longer than Aravis' default frame retention, 0.1 s).
_STALL_S = 0.3


def _require_aravis() -> None:
    """Raise DeviceError when PyGObject or the Aravis 0.8 typelib cannot be loaded."""
    if _IMPORT_ERROR is not None:
        raise DeviceError(
            f"the aravis camera backend needs PyGObject and Aravis 0.8 ({_IMPORT_ERROR}); "
            "install the system packages gir1.2-aravis-0.8 (and aravis-tools for the "
            "simulator), then the Python extra: pip install 'labkit[gige]'"
        )


def list_devices() -> list[DeviceInfo]:
    """Discover the cameras Aravis sees (GigE Vision, and USB3 Vision when built in).

    Discovery broadcasts on every interface and waits about a second for answers.

    Returns
    -------
    list of DeviceInfo
        ``device_id`` is what :class:`AravisCamera` takes; ``address`` is the camera's IP
        address (GigE) or bus position (USB).
    """
    _require_aravis()
    Aravis.update_device_list()
    return [
        DeviceInfo(
            backend=BACKEND,
            device_id=Aravis.get_device_id(i) or "",
            vendor=Aravis.get_device_vendor(i) or "",
            model=Aravis.get_device_model(i) or "",
            serial=Aravis.get_device_serial_nbr(i) or "",
            address=Aravis.get_device_address(i) or "",
        )
        for i in range(Aravis.get_n_devices())
    ]


def unwrap_frame_id(raw: int, reference: int | None) -> int:
    """Unwrap a 16-bit GigE Vision block id against the last accepted (unwrapped) id.

    GigE Vision 1.x block ids run 1…65535 and wrap to 1 (0 is never used); ids above
    65535 (GigE Vision 2 extended ids) are returned as they are.

    Parameters
    ----------
    raw : int
        Frame id as the buffer reports it.
    reference : int or None
        The last accepted unwrapped id (None: nothing accepted yet in this acquisition).

    Returns
    -------
    int
        The unwrapped id nearest to `reference`: larger than `reference` for a newer frame
        (including across a wrap), not larger for a stale one.
    """
    if reference is None or raw > _GV_ID_PERIOD or reference <= 0:
        return raw
    epoch = reference - ((reference - 1) % _GV_ID_PERIOD + 1)
    candidates = (epoch - _GV_ID_PERIOD + raw, epoch + raw, epoch + _GV_ID_PERIOD + raw)
    return min(candidates, key=lambda c: abs(c - reference))


def _format_s(seconds: float) -> str:
    """Seconds for messages: ``0.010`` for ms-scale values, ``1e-05`` below."""
    return f"{seconds:.3f}" if seconds >= 1e-3 else f"{seconds:.3g}"


class AravisCamera(GenICamFeatures):
    """A GigE Vision camera driven through Aravis 0.8 (implements the Camera protocol).

    Parameters
    ----------
    device_id : str or None
        Aravis device id (``<vendor>-<model>-<serial>``, see :func:`list_devices`); None
        opens the first camera found.
    pixel_format : str or None
        Pixel format to select (e.g. ``BayerRG12p``); None keeps the camera's.
    timeout_s : float
        How long one frame may take to arrive after its trigger, s (beyond the exposure).
    retries : int
        Re-triggers allowed per frame after a failed or missing buffer.
    reconnect_attempts : int
        Re-open attempts after control of the camera is lost (0: do not reconnect).

    Raises
    ------
    DeviceError
        Aravis is not installed, no camera has `device_id` (the message lists those
        found), or the camera cannot be opened or configured.
    """

    # Aravis' GObjects (PyGObject ships no types); None while disconnected
    _cam: Any
    _dev: Any
    _stream: Any

    backend = BACKEND
    #: Buffers in the stream's pool.
    n_buffers = 8
    #: Back-off before reconnect attempt k is ``k * reconnect_backoff_s`` seconds.
    reconnect_backoff_s = 0.5

    def __init__(
        self,
        device_id: str | None = None,
        *,
        pixel_format: str | None = None,
        timeout_s: float = 2.0,
        retries: int = 3,
        reconnect_attempts: int = 3,
    ) -> None:
        self._closed = True  # until opened, so close() is safe on a failed construction
        _require_aravis()
        if not (isinstance(timeout_s, int | float) and math.isfinite(timeout_s) and timeout_s > 0):
            raise DeviceError(
                f"aravis camera: timeout_s must be a positive number of s, not {timeout_s!r}"
            )
        for name, value in (("retries", retries), ("reconnect_attempts", reconnect_attempts)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise DeviceError(f"aravis camera: {name} must be an integer ≥ 0, not {value!r}")
        self.timeout_s = float(timeout_s)
        self.retries = retries
        self.reconnect_attempts = reconnect_attempts

        self._cam = None
        self._dev = None
        self._stream = None
        self._handler: int | None = None
        self._generation = 0
        self._control_lost = threading.Event()
        self._acquiring = False
        self._acquisitions = 0
        self._payload = 0
        self._outstanding = 0  # triggers whose buffer has not been popped yet
        self._last_frame_id: int | None = None
        self._exposure_set: float | None = None
        self._exposure_readback = math.nan
        self._gain: float | None = None
        self._change_ns = 0  # host time (ns, µs resolution) of the last settings change
        self._applied: dict[str, Any] = {}  # features written through set(), re-applied
        self._pixel_format_wanted = pixel_format
        self._pixel_format = ""
        self._stream_totals = dict.fromkeys(
            ("completed_buffers", "failed_buffers", "underrun_buffers"), 0
        )
        self._counters = dict.fromkeys(
            ("frames", "retries", "failed_attempts", "pop_timeouts", "stalled_frames",
             "late_failed_buffers", "rejected_stale", "drained", "reconnects"), 0,
        )  # fmt: skip

        if device_id is None:
            found = list_devices()
            if not found:
                raise DeviceError(
                    "aravis: no camera found; check the camera's power, network link and "
                    "IP configuration (same subnet as this host), then run `labkit devices`"
                )
            device_id = found[0].device_id
        self.device_id = device_id
        self._open()
        self._closed = False
        try:
            self._identity = self._read_identity()
            self._gain_at_open = self._read_gain()
            if pixel_format is not None:
                self.set_pixel_format(pixel_format)
            else:
                with self._gerror("reading PixelFormat"):
                    self._pixel_format = self._cam.get_pixel_format_as_string()
        except BaseException:
            self.close()
            raise

    # -- opening, closing, reconnecting ------------------------------------------------------
    def _open(self) -> None:
        """Open the camera by :attr:`device_id` and watch its ``control-lost`` signal."""
        try:
            cam = Aravis.Camera.new(self.device_id)
        except GLib.GError as error:
            if error.matches(Aravis.device_error_quark(), Aravis.DeviceError.NOT_FOUND):
                found = list_devices()
                names = ", ".join(f"{d.device_id} ({d.address})" for d in found) or "none"
                raise DeviceError(
                    f"aravis: no camera with id {self.device_id!r}; cameras found: {names}; "
                    "pass one of these ids (`labkit devices` lists them)"
                ) from None
            raise DeviceError(
                f"camera {self.device_id}: cannot open it: {error.message}; check that no "
                "other program controls it and that it is on this host's subnet"
            ) from error
        dev = cam.get_device()
        self._generation += 1
        generation = self._generation
        owner = weakref.ref(self)

        def on_control_lost(_device: Any) -> None:  # runs on Aravis' heartbeat thread
            camera = owner()
            if camera is not None and camera._generation == generation:
                camera._control_lost.set()

        self._handler = dev.connect("control-lost", on_control_lost)
        self._cam, self._dev = cam, dev
        self._control_lost.clear()
        self._acquiring = False
        self._exposure_set = None
        self._gain = None

    def _teardown(self, *, alive: bool) -> None:
        """Release the stream and the camera; `alive`: try to stop the acquisition first."""
        if self._stream is not None:
            if self._acquiring and alive:
                with contextlib.suppress(GLib.GError):
                    self._cam.stop_acquisition()
            self._drop_stream()
        self._acquiring = False
        if self._dev is not None and self._handler is not None:
            with contextlib.suppress(Exception):
                self._dev.disconnect(self._handler)
        self._handler = None
        self._generation += 1  # a late control-lost of the old device is ignored
        self._cam = self._dev = None

    def _reconnect(self, reason: str) -> None:
        """Close and re-open the camera, restore its settings; DeviceError if that fails."""
        self._teardown(alive=False)
        if self.reconnect_attempts == 0:
            raise DeviceError(
                f"camera {self.device_id}: {reason} and reconnecting is disabled "
                "(reconnect_attempts=0); check the camera and the network, then resume"
            )
        last: Exception | None = None
        for attempt in range(1, self.reconnect_attempts + 1):
            time.sleep(self.reconnect_backoff_s * attempt)
            try:
                self._open()
                self._restore()
            except DeviceError as error:
                last = error
                self._teardown(alive=False)
                continue
            self._counters["reconnects"] += 1
            return
        raise DeviceError(
            f"camera {self.device_id}: {reason} and {self.reconnect_attempts} reconnect "
            f"attempts failed (last: {last}); check power and network, then resume the session"
        )

    def _restore(self) -> None:
        """Re-apply the pixel format, gain and features written through :meth:`set`."""
        with self._gerror("restoring its settings after a reconnect"):
            if self._pixel_format_wanted is not None:
                self._cam.set_pixel_format_from_string(self._pixel_format_wanted)
            for name, value in self._applied.items():
                self._write_feature(name, value)
            if self._gain_at_open is not None and not set(GAIN_FEATURES) & set(self._applied):
                self._cam.set_gain(self._gain_at_open)
            self._pixel_format = self._cam.get_pixel_format_as_string()

    def _ensure_open(self) -> None:
        """DeviceError if closed; reconnect first if control of the camera was lost."""
        if self._closed:
            raise DeviceError(f"camera {self.device_id} is closed; open a new AravisCamera")
        if self._control_lost.is_set() or self._cam is None:
            self._reconnect("control of the camera was lost")

    @property
    def control_lost(self) -> bool:
        """Whether Aravis reported the camera lost and it has not been reconnected yet."""
        return self._control_lost.is_set()

    @property
    def aravis_camera(self) -> Any:
        """The underlying ``Aravis.Camera`` (for what this class does not wrap)."""
        self._ensure_open()
        return self._cam

    def close(self) -> None:
        """Stop the acquisition and release the camera (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._teardown(alive=not self._control_lost.is_set())

    def __enter__(self) -> AravisCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"AravisCamera({self.device_id!r}, {state})"

    @contextlib.contextmanager
    def _gerror(self, action: str) -> Iterator[None]:
        """Turn an Aravis GError into a one-line DeviceError naming the camera and action."""
        try:
            yield
        except GLib.GError as error:
            if error.matches(Aravis.device_error_quark(), Aravis.DeviceError.TIMEOUT):
                self._control_lost.set()  # the next operation re-opens the camera
                hint = (
                    "the camera does not answer: check its power and network link; the next "
                    "call tries to reconnect"
                )
            else:
                hint = "check the feature names, values and access modes (feature_names(), get())"
            raise DeviceError(
                f"camera {self.device_id}: {action} failed: {error.message}; {hint}"
            ) from error

    # -- identity and generic features ---------------------------------------------------------
    def _read_identity(self) -> CameraIdentity:
        with self._gerror("reading its identity"):
            firmware = ""
            for name in ("DeviceFirmwareVersion", "DeviceVersion"):
                if self._dev.get_feature(name) is not None:
                    firmware = self._dev.get_string_feature_value(name) or ""
                    break
            return CameraIdentity(
                vendor=self._cam.get_vendor_name() or "",
                model=self._cam.get_model_name() or "",
                serial=self._cam.get_device_serial_number() or "",
                firmware=firmware,
            )

    @property
    def identity(self) -> CameraIdentity:
        """Vendor, model, serial number and firmware version (read when opened)."""
        return self._identity

    def feature_names(self) -> list[str]:
        """Names of the device's GenICam features (the leaves of its ``Root`` category)."""
        self._ensure_open()
        genicam = self._dev.get_genicam()
        names: list[str] = []
        seen: set[str] = set()

        def walk(category: str) -> None:
            node = genicam.get_node(category)
            if node is None or not isinstance(node, Aravis.GcCategory):
                return
            for name in node.get_features() or []:
                if name in seen:
                    continue
                seen.add(name)
                child = genicam.get_node(name)
                if isinstance(child, Aravis.GcCategory):
                    walk(name)
                elif child is not None:
                    names.append(name)

        with self._gerror("listing its features"):
            walk("Root")
            # standard categories a device may leave out of Root (the simulator's AnalogControl)
            for category in SFNC_CATEGORIES:
                if category not in seen:
                    seen.add(category)
                    walk(category)
        return names

    # -- the node-map primitives of GenICamFeatures ---------------------------------------------
    @property
    def _where(self) -> str:
        return f"camera {self.device_id}"

    def _usable(self) -> None:
        self._ensure_open()

    def _kind(self, name: str) -> str | None:
        node = self._dev.get_feature(name)
        if node is None:
            return None
        # interfaces, not classes: a Converter node is a GcFloat, an enumeration a GcInteger
        for interface, kind in (
            (Aravis.GcEnumeration, "enumeration"),
            (Aravis.GcBoolean, "boolean"),
            (Aravis.GcFloat, "float"),
            (Aravis.GcInteger, "integer"),
            (Aravis.GcString, "string"),
            (Aravis.GcCommand, "command"),
        ):
            if isinstance(node, interface):
                return kind
        return type(node).__name__.removeprefix("Gc").lower()  # a register, a category…

    def _read(self, name: str, kind: str) -> Any:
        dev = self._dev
        if kind == "boolean":
            return bool(dev.get_boolean_feature_value(name))
        if kind == "float":
            return float(dev.get_float_feature_value(name))
        if kind == "integer":
            return int(dev.get_integer_feature_value(name))
        return dev.get_string_feature_value(name)  # enumerations and strings

    def _write(self, name: str, kind: str, value: Any) -> None:
        dev = self._dev
        if kind == "boolean":
            dev.set_boolean_feature_value(name, value)
        elif kind == "float":
            dev.set_float_feature_value(name, value)
        elif kind == "integer":
            dev.set_integer_feature_value(name, value)
        else:
            dev.set_string_feature_value(name, value)

    def _limits(self, name: str, kind: str) -> tuple[float, float]:
        if kind == "float":
            low, high = self._dev.get_float_feature_bounds(name)
        else:
            low, high = self._dev.get_integer_feature_bounds(name)
        return float(low), float(high)

    def _increment(self, name: str, kind: str) -> float:
        if kind == "float":
            return float(self._cam.get_float_increment(name))
        return float(self._cam.get_integer_increment(name))

    def _choices(self, name: str) -> list[str]:
        return list(self._dev.dup_available_enumeration_feature_values_as_strings(name) or [])

    def _run(self, name: str) -> None:
        self._dev.execute_command(name)

    def _device_call(self, action: str) -> contextlib.AbstractContextManager[None]:
        return self._gerror(action)

    def _stop_for_change(self) -> None:
        self._stop_acquisition()

    def set(self, name: str, value: Any) -> None:
        """Write a feature (GenICam units); numbers are checked against the feature's bounds.

        Writing a feature that changes the payload (``Width``, ``PixelFormat``…) stops the
        acquisition; the next :meth:`grab` restarts it. Written features are re-applied
        after a reconnect.
        """
        self._ensure_open()
        if name == "PixelFormat":
            self.set_pixel_format(str(value))
            return
        self._feature_kind(name)
        if name in STREAM_FEATURES:
            self._stop_acquisition()
        value = self._write_feature(name, value)
        if name in EXPOSURE_FEATURES:
            self._exposure_set = None
        else:
            self._applied.pop(name, None)
            self._applied[name] = value
        if name in GAIN_FEATURES:
            self._gain = None
        self._settings_changed()

    # -- gain, pixel format ----------------------------------------------------------------------
    def _read_gain(self) -> float | None:
        if self._present(GAIN_FEATURES) is None:
            return None
        with self._gerror("reading the gain"):
            return float(self._cam.get_gain())

    @property
    def pixel_format(self) -> str:
        """Current GenICam pixel format, e.g. ``BayerRG12p``."""
        return self._pixel_format

    def set_pixel_format(self, pixel_format: str) -> None:
        """Select a pixel format the camera offers and labkit can decode.

        Stops the acquisition (the payload changes); the next grab restarts it.
        """
        self._ensure_open()
        offered = self._check_offered(pixel_format)
        if not _pixels.is_decodable(pixel_format):
            usable = [f for f in offered if _pixels.is_decodable(f)]
            raise DeviceError(
                f"camera {self.device_id}: labkit cannot decode pixel format {pixel_format!r}; "
                f"choose one of {', '.join(usable) or '(none offered)'}"
            )
        self._stop_acquisition()
        with self._gerror(f"setting PixelFormat={pixel_format}"):
            self._cam.set_pixel_format_from_string(pixel_format)
            self._pixel_format = self._cam.get_pixel_format_as_string()
        self._pixel_format_wanted = pixel_format
        self._settings_changed()

    # -- stream ----------------------------------------------------------------------------------
    def _create_stream(self) -> None:
        cam, dev = self._cam, self._dev
        with self._gerror("creating the stream"):
            if cam.is_gv_device():
                address = dev.get_device_address()
                if address is not None and address.get_address().get_is_loopback():
                    dev.set_stream_options(Aravis.GvStreamOption.PACKET_SOCKET_DISABLED)
            stream = cam.create_stream(None, None)
            payload = int(cam.get_payload())
            if isinstance(stream, Aravis.GvStream):
                lo, hi = _SOCKET_BUFFER_BOUNDS
                size = min(max(_SOCKET_BUFFER_FACTOR * payload, lo), hi)
                stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.FIXED)
                stream.set_property("socket-buffer-size", size)
            for _ in range(self.n_buffers):
                stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        self._stream = stream
        self._payload = payload

    def _stream_counts(self, stream: Any) -> dict[str, int]:
        counts: dict[str, int] = {}
        completed, failures, underruns = Aravis.Stream.get_statistics(stream)
        counts["completed_buffers"] = int(completed)
        counts["failed_buffers"] = int(failures)
        counts["underrun_buffers"] = int(underruns)
        if hasattr(stream, "get_n_infos"):
            for i in range(stream.get_n_infos()):
                name = stream.get_info_name(i)
                if name in ("n_completed_buffers", "n_failures", "n_underruns"):
                    continue
                if stream.get_info_type(i) == GObject.TYPE_UINT64:
                    counts[name.removeprefix("n_")] = int(stream.get_info_uint64(i))
        elif isinstance(stream, Aravis.GvStream):
            resent, missing = stream.get_statistics()
            counts["resent_packets"], counts["missing_packets"] = int(resent), int(missing)
        return counts

    def _drop_stream(self) -> None:
        if self._stream is None:
            return
        for key, value in self._stream_counts(self._stream).items():
            self._stream_totals[key] = self._stream_totals.get(key, 0) + value
        self._stream = None

    def _stop_acquisition(self) -> None:
        """Stop the acquisition (if running) and drop the stream; the next grab rebuilds them."""
        if self._acquiring:
            with self._gerror("stopping the acquisition"):
                self._cam.stop_acquisition()
            self._acquiring = False
        self._drop_stream()

    def _ensure_acquisition(self) -> None:
        if self._acquiring:
            return
        with contextlib.suppress(GLib.GError):  # a previous program may have left it running
            self._cam.stop_acquisition()
        if not self._software_trigger_available():
            raise DeviceError(
                f"camera {self.device_id}: no software trigger (TriggerSoftware with "
                "TriggerSource=Software); labkit needs one to time exposures"
            )
        self._continuous_acquisition()
        self._use_software_trigger(True)
        self._manual_exposure_and_gain()
        if self._stream is None:
            self._create_stream()
        with self._gerror("starting the acquisition"):
            self._cam.start_acquisition()
        self._acquiring = True
        self._acquisitions += 1
        self._outstanding = 0
        self._last_frame_id = None
        self._exposure_set = None

    def stream_statistics(self) -> dict[str, int]:
        """Stream counters since the camera was opened (summed over streams and reconnects).

        Returns
        -------
        dict of str to int
            From Aravis: ``completed_buffers``, ``failed_buffers``, ``underrun_buffers`` and,
            where this Aravis exposes them, ``missing_packets``, ``resent_packets``,
            ``resend_requests``, ``timeouts``, ``missing_frames``… From this class:
            ``frames`` (accepted), ``retries`` (re-triggers), ``failed_attempts`` (failed
            buffers answering a trigger), ``pop_timeouts`` (no buffer within ``timeout_s``),
            ``stalled_frames`` (incomplete frames Aravis held back), ``late_failed_buffers``
            (failures of abandoned attempts), ``rejected_stale`` (buffers from before a
            change), ``drained`` and ``reconnects``.
        """
        stats = dict(self._stream_totals)
        if self._stream is not None:
            for key, value in self._stream_counts(self._stream).items():
                stats[key] = stats.get(key, 0) + value
        stats.update(self._counters)
        return stats

    # -- acquisition -----------------------------------------------------------------------------
    def _settings_changed(self) -> None:
        """Frames from now on must be exposed after this moment."""
        self._change_ns = time.time_ns() // 1000 * 1000  # Aravis host stamps have µs steps
        self._gain = None
        if self._acquiring:
            self._drain()

    def _drain(self) -> None:
        """Discard queued buffers and wait (≤ timeout_s) for those still in flight."""
        stream = self._stream
        deadline = time.monotonic() + self.timeout_s
        while True:
            if self._outstanding > 0:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                buffer = stream.timeout_pop_buffer(max(1, int(remaining * 1e6)))
            else:
                buffer = stream.try_pop_buffer()
            if buffer is None:
                if self._outstanding <= 0:
                    break
                continue
            self._outstanding -= 1
            self._counters["drained"] += 1
            stream.push_buffer(buffer)
        self._outstanding = 0

    def _prepare(self, exposure_s: float) -> None:
        """Start the acquisition if needed and set the exposure (draining on a change)."""
        self._ensure_acquisition()
        if self._exposure_set != exposure_s:
            self._set_exposure(exposure_s)
            self._exposure_readback = self._exposure_readback_s()
            self._exposure_set = exposure_s
            self._settings_changed()
        if self._gain is None:
            gain = self._read_gain()
            self._gain = 0.0 if gain is None else gain

    def grab(self, exposure_s: float, n: int = 1) -> list[Frame]:
        """Capture `n` software-triggered frames each exposed for `exposure_s` seconds.

        Parameters
        ----------
        exposure_s : float
            Exposure time, s; checked against :meth:`exposure_bounds` before any trigger.
        n : int
            Number of frames.

        Returns
        -------
        list of Frame
            Status ``SUCCESS``, strictly increasing frame ids, exposed after the exposure
            change. ``exposure_readback_s`` is the feature read back after setting it;
            ``gain_db`` is in device units when the camera only has ``GainRaw``.

        Raises
        ------
        DeviceError
            Exposure out of bounds, retries exhausted for a frame, or the camera lost and
            not recovered.
        """
        self._ensure_open()
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise DeviceError(f"camera {self.device_id}: grab needs n ≥ 1 frames, not {n!r}")
        try:
            exposure_s = float(exposure_s)
        except (TypeError, ValueError):
            raise DeviceError(
                f"camera {self.device_id}: exposure must be a number of seconds, not {exposure_s!r}"
            ) from None
        self._check_exposure(exposure_s)
        self._prepare(exposure_s)
        return [self._grab_one(i, n, exposure_s) for i in range(n)]

    def _grab_one(self, index: int, n: int, exposure_s: float) -> Frame:
        attempts = 0
        reconnects = 0
        last_status = "none"
        while True:
            if self._control_lost.is_set():
                if reconnects >= max(1, self.reconnect_attempts):
                    raise DeviceError(
                        f"camera {self.device_id}: frame {index + 1} of {n}: control lost "
                        f"{reconnects} times while grabbing; check the camera and its network "
                        "link; the session can be resumed"
                    )
                reconnects += 1
                self._reconnect("control of the camera was lost")
                self._prepare(exposure_s)
                attempts = 0  # the failures so far were the connection's, not the frame's
                continue
            if attempts > self.retries:
                raise DeviceError(
                    f"camera {self.device_id}: frame {index + 1} of {n} at "
                    f"{_format_s(exposure_s)} s failed {attempts} time{'s' * (attempts > 1)} "
                    f"(last status {last_status}); check the network link / packet size "
                    "(or allow more retries); the session can be resumed"
                )
            if attempts:
                self._counters["retries"] += 1
            attempts += 1
            trigger_s = time.time()
            try:
                self._cam.software_trigger()
            except GLib.GError as error:
                if self._probe_lost():
                    continue
                raise DeviceError(
                    f"camera {self.device_id}: software trigger for frame {index + 1} of {n} "
                    f"failed: {error.message}; check the camera's trigger settings"
                ) from error
            self._outstanding += 1
            result = self._wait_for_frame(exposure_s)
            if isinstance(result, Frame):
                result.extra["retries"] = attempts - 1
                result.extra["trigger_host_time_s"] = trigger_s
                self._counters["frames"] += 1
                return result
            last_status = result
            self._counters["failed_attempts"] += 1
            if result == "NO_BUFFER":
                self._probe_lost()

    def _probe_lost(self) -> bool:
        """After a silence: read a register; on failure treat control as lost."""
        if not self._control_lost.is_set():
            try:
                if self._cam.is_gv_device():
                    self._dev.read_register(0x0)  # GigE Vision bootstrap: version
                else:
                    self._cam.get_payload()
            except GLib.GError:
                self._control_lost.set()
        return self._control_lost.is_set()

    def _received_packets(self) -> int | None:
        """Packets the GigE Vision stream has received so far (None: not exposed)."""
        stream = self._stream
        if not isinstance(stream, Aravis.GvStream) or not hasattr(
            stream, "get_info_uint64_by_name"
        ):
            return None
        return int(stream.get_info_uint64_by_name("n_received_packets"))

    def _wait_for_frame(self, exposure_s: float) -> Frame | str:
        """Pop buffers until one answers the last trigger: a Frame, or a failure's name.

        Besides the buffer statuses, the failures are ``NO_BUFFER`` (nothing within
        ``timeout_s`` + exposure), ``CONTROL_LOST`` and ``STALLED``: packets arrived after
        the exposure, then nothing for :data:`_STALL_S` although no buffer came out. Aravis
        does not time out the most recent frame while only its leader is contiguous, so
        such a frame waits for the next one; the re-trigger releases it, and its late
        failed buffer is then skipped (failed buffers that arrive while a later trigger is
        still in flight belong to an abandoned attempt).
        """
        stream = self._stream
        start = time.monotonic()
        deadline = start + self.timeout_s + exposure_s
        packets_at_trigger = packets = self._received_packets()
        quiet_since = start
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._counters["pop_timeouts"] += 1
                self._outstanding = max(0, self._outstanding - 1)  # assume it was lost
                return "NO_BUFFER"
            buffer = stream.timeout_pop_buffer(max(1, int(min(remaining, _POLL_S) * 1e6)))
            if buffer is None:
                if self._control_lost.is_set():
                    return "CONTROL_LOST"
                if packets is None:
                    continue
                now = time.monotonic()
                current = self._received_packets()
                if current != packets:
                    packets, quiet_since = current, now
                elif (
                    packets != packets_at_trigger
                    and now - quiet_since > _STALL_S
                    and now - start > exposure_s + _STALL_S
                ):
                    self._counters["stalled_frames"] += 1
                    return "STALLED"
                continue
            self._outstanding = max(0, self._outstanding - 1)
            try:
                result = self._inspect(buffer, exposure_s)
            finally:
                stream.push_buffer(buffer)
            if isinstance(result, str) and self._outstanding > 0:
                self._counters["late_failed_buffers"] += 1
                continue
            if result is not None:
                return result

    def _inspect(self, buffer: Any, exposure_s: float) -> Frame | str | None:
        """A Frame for a fresh good buffer, a status name for a fresh bad one, None if stale.

        A failed buffer whose leader was lost carries no frame id and no host time (both 0):
        it cannot be told stale, so it counts as the answer to the current trigger.
        """
        raw_id = int(buffer.get_frame_id())
        frame_id = unwrap_frame_id(raw_id, self._last_frame_id)
        host_ns = int(buffer.get_system_timestamp())
        status = buffer.get_status()
        if raw_id > 0 and host_ns > 0:
            if host_ns < self._change_ns or (
                self._last_frame_id is not None and frame_id <= self._last_frame_id
            ):
                self._counters["rejected_stale"] += 1
                return None
        elif status == Aravis.BufferStatus.SUCCESS:
            return "NO_FRAME_ID"
        if status != Aravis.BufferStatus.SUCCESS:
            return str(status.value_name).removeprefix("ARV_BUFFER_STATUS_")
        payload_type = buffer.get_payload_type()
        if payload_type not in (
            Aravis.BufferPayloadType.IMAGE,
            Aravis.BufferPayloadType.EXTENDED_CHUNK_DATA,
        ):
            return f"PAYLOAD_{payload_type.value_nick.upper()}"
        code = int(buffer.get_image_pixel_format())
        pixel_format = _pixels.pixel_format_name(code)
        if pixel_format is None:
            if code == int(self._cam.get_pixel_format()):
                pixel_format = self._pixel_format
            else:
                raise DeviceError(
                    f"camera {self.device_id}: frame {raw_id} has unknown pixel format "
                    f"0x{code:08x}; choose a Bayer format with set_pixel_format"
                )
        width, height = int(buffer.get_image_width()), int(buffer.get_image_height())
        data = buffer.get_image_data()
        try:
            image = _pixels.decode(
                data, pixel_format, width, height, padding_x=int(buffer.get_image_padding()[0])
            )
        except DataError as error:
            if not _pixels.is_decodable(pixel_format):
                raise DeviceError(
                    f"camera {self.device_id}: {error}; select a decodable format with "
                    "set_pixel_format"
                ) from None
            return "SIZE_MISMATCH"
        self._last_frame_id = frame_id
        return Frame(
            image=image,
            frame_id=frame_id,
            exposure_s=exposure_s,
            exposure_readback_s=self._exposure_readback,
            gain_db=float(self._gain or 0.0),
            pixel_format=pixel_format,
            device_timestamp_ns=int(buffer.get_timestamp()),
            host_timestamp_s=host_ns * 1e-9,
            status="SUCCESS",
            extra={
                "device_id": self.device_id,
                "raw_frame_id": raw_id,
                "acquisition": self._acquisitions,
                "payload_bytes": len(data),
                "exposure_feature": self._present(EXPOSURE_FEATURES),
                "gain_feature": self._present(GAIN_FEATURES),
                "settings_changed_host_time_s": self._change_ns * 1e-9,
            },
        )
