"""GenTL producers (``.cti``) for the genicam camera backend: loaded once per process
through Harvesters, shared by reference count, and the devices they find.

:class:`labkit.devices.genicam.GenICamCamera` checks a producer (:func:`check_cti`),
acquires it (:func:`acquire_producer`) and releases it when it closes
(:func:`close_device`); :func:`labkit.devices.gentl_producers.list_devices` asks it for
its devices (:func:`producer_devices`).

Harvesters and the GenICam binding are imported on use (:func:`_harvesters`): they are an
optional dependency, and a missing one becomes a :class:`~labkit.errors.DeviceError` that
says how to install it.
"""

from __future__ import annotations

import ctypes
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labkit.devices.camera import DeviceInfo
from labkit.errors import DeviceError

if TYPE_CHECKING:
    from harvesters.core import Harvester, ImageAcquirer

BACKEND = "genicam"

#: Symbols every GenTL producer exports (checked before the library is handed to the
#: GenTL binding, which crashes the process on a shared library that lacks them).
_GENTL_SYMBOLS = ("GCInitLib", "TLOpen", "TLUpdateInterfaceList", "DSStartAcquisition")


def _harvesters() -> Any:
    """Import harvesters (and the genicam binding) or raise DeviceError saying how to get it."""
    try:
        from harvesters import core
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DeviceError(
            f"the genicam camera backend needs the 'harvesters' and 'genicam' packages ({exc}); "
            "install them with `pip install harvesters genicam`"
        ) from exc
    return core


def genicam_errors() -> tuple[type[BaseException], ...]:
    """The GenApi and GenTL exception base classes."""
    from genicam.genapi import GenericException as GenApiError
    from genicam.gentl import GenericException as GenTLError

    return GenApiError, GenTLError


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (GenICam messages carry file/line noise)."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


# -- producers (.cti) ----------------------------------------------------------------------


def check_cti(cti: str | Path) -> str:
    """Resolve `cti` and check it is a loadable GenTL producer; return the resolved path."""
    path = Path(cti).expanduser()
    if not path.is_file():
        what = "is a directory" if path.is_dir() else "does not exist"
        raise DeviceError(
            f"GenTL producer {str(cti)!r} {what}; give the path of the camera vendor's .cti "
            "file (e.g. the rig's camera.cti)"
        )
    resolved = str(path.resolve())
    try:
        library = ctypes.CDLL(resolved)
    except OSError as exc:
        raise DeviceError(
            f"GenTL producer {resolved!r} cannot be loaded ({exc}); check that it is a .cti "
            "built for this platform and that its dependencies are installed"
        ) from None
    missing = [name for name in _GENTL_SYMBOLS if not hasattr(library, name)]
    if missing:
        raise DeviceError(
            f"{resolved!r} is a shared library but not a GenTL producer (it lacks "
            f"{', '.join(missing)}); give the camera vendor's .cti file"
        )
    return resolved


@dataclass
class Producer:
    """A loaded producer shared by the cameras opened on it in this process."""

    cti: str
    harvester: Harvester
    users: int = 0
    devices: list[DeviceInfo] = field(default_factory=list)


_PRODUCERS: dict[str, Producer] = {}
_PRODUCERS_LOCK = threading.Lock()


def _load_producer(cti: str) -> Harvester:
    """A fresh Harvester with `cti` loaded and its device list updated."""
    core = _harvesters()
    harvester = core.Harvester()
    try:
        harvester.add_file(cti)
        harvester.update()
    except Exception as exc:
        harvester.reset()
        raise DeviceError(
            f"GenTL producer {cti!r} failed to enumerate devices ({first_line(exc)}); check "
            "the camera's connection and the producer's installation"
        ) from None
    return harvester


def info_text(info: Any, name: str) -> str:
    """A device-info property as text ('' when the producer does not report it)."""
    try:
        value = getattr(info, name)
    except Exception:
        return ""
    return "" if value is None else str(value)


def _describe(infos: list[Any]) -> list[DeviceInfo]:
    return [
        DeviceInfo(
            backend=BACKEND,
            device_id=info_text(info, "id_"),
            vendor=info_text(info, "vendor"),
            model=info_text(info, "model"),
            serial=info_text(info, "serial_number"),
            address=info_text(info, "display_name"),
        )
        for info in infos
    ]


def acquire_producer(cti: str) -> Producer:
    with _PRODUCERS_LOCK:
        producer = _PRODUCERS.get(cti)
        if producer is None:
            harvester = _load_producer(cti)
            producer = Producer(cti, harvester, devices=_describe(harvester.device_info_list))
            _PRODUCERS[cti] = producer
        producer.users += 1
        return producer


def release_producer(cti: str) -> None:
    with _PRODUCERS_LOCK:
        producer = _PRODUCERS.get(cti)
        if producer is None:
            return
        producer.users -= 1
        if producer.users <= 0:
            del _PRODUCERS[cti]
            producer.harvester.reset()


def format_devices(devices: list[DeviceInfo]) -> str:
    if not devices:
        return "none"
    return "; ".join(
        f"{d.device_id} ({d.vendor} {d.model}, serial {d.serial or '?'})" for d in devices
    )


def producer_devices(cti: str) -> list[DeviceInfo]:
    """The devices of producer `cti` (a path checked by :func:`check_cti`).

    While a camera on `cti` is open in this process, the list found when it was opened;
    otherwise the producer is loaded, asked and unloaded again.
    """
    with _PRODUCERS_LOCK:
        shared = _PRODUCERS.get(cti)
        if shared is not None:
            return list(shared.devices)
        harvester = _load_producer(cti)
        try:
            return _describe(harvester.device_info_list)
        finally:
            harvester.reset()


def close_device(acquirer: ImageAcquirer, cti: str) -> None:
    """Stop and destroy `acquirer`, then release the shared producer (finaliser)."""
    try:
        acquirer.destroy()
    finally:
        release_producer(cti)
