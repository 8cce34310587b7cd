"""The stream of an Aravis camera and the frames it delivers.

:class:`AravisStream` builds the stream and its pool of buffers, starts the software
triggered acquisition and drains buffers still in flight after a setting changes. It grabs
one frame at a time: a trigger, then a wait for the buffer that answers it (telling failed,
missing, stalled and stale buffers apart) and the frame of a good one; a failed frame is
re-triggered up to ``retries`` times, and a lost camera re-opened through the camera's
``_reconnect``. :func:`unwrap_frame_id` unwraps GigE Vision's 16-bit block ids. The module
docstring of :mod:`labkit.devices.aravis` describes the acquisition as a whole.
"""

from __future__ import annotations

import abc
import contextlib
import time
from typing import Any

from labkit.devices import _pixels
from labkit.devices._aravis_gi import Aravis, GLib, GObject
from labkit.devices._aravis_node_map import AravisNodeMap
from labkit.devices.genicam_features import EXPOSURE_FEATURES, GAIN_FEATURES
from labkit.errors import DataError, DeviceError
from labkit.frame import Frame

__all__ = ["AravisStream", "unwrap_frame_id"]

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


class AravisStream(AravisNodeMap):
    """The stream, the acquisition and the triggered frames of an Aravis camera (see the module)."""

    # the camera's state these methods use, set by AravisCamera (its __init__ and _open)
    _stream: Any  # Aravis.Stream, None until the next grab builds it
    n_buffers: int
    timeout_s: float
    _acquiring: bool
    _acquisitions: int
    _payload: int
    _outstanding: int
    _last_frame_id: int | None
    _exposure_set: float | None
    _exposure_readback: float
    _gain: float | None
    _change_ns: int
    _pixel_format: str
    _stream_totals: dict[str, int]
    _counters: dict[str, int]
    retries: int
    reconnect_attempts: int

    @abc.abstractmethod
    def _reconnect(self, reason: str) -> None:
        """Close and re-open the camera and restore its settings (DeviceError on failure)."""

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

    def _stop_for_change(self) -> None:
        self._stop_acquisition()

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
