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
from typing import Any

from labkit.devices import _pixels
from labkit.devices._aravis_gi import Aravis, GLib, require_aravis
from labkit.devices._aravis_stream import AravisStream
from labkit.devices.camera import CameraIdentity, DeviceInfo
from labkit.devices.genicam_features import EXPOSURE_FEATURES, GAIN_FEATURES
from labkit.errors import DeviceError
from labkit.frame import Frame

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


def list_devices() -> list[DeviceInfo]:
    """Discover the cameras Aravis sees (GigE Vision, and USB3 Vision when built in).

    Discovery broadcasts on every interface and waits about a second for answers.

    Returns
    -------
    list of DeviceInfo
        ``device_id`` is what :class:`AravisCamera` takes; ``address`` is the camera's IP
        address (GigE) or bus position (USB).
    """
    require_aravis()
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


class AravisCamera(AravisStream):
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
        require_aravis()
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

    def _usable(self) -> None:
        self._ensure_open()

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

    # -- identity and generic features ---------------------------------------------------------
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

    # -- pixel format, stream statistics -------------------------------------------------------
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

    # -- grabbing --------------------------------------------------------------------------------
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
