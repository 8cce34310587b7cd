"""GenTL producers (``.cti``) for the genicam camera backend: loaded once per process
through Harvesters, shared by reference count, and the devices they find.

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


def _genicam_errors() -> tuple[type[BaseException], ...]:
    """The GenApi and GenTL exception base classes."""
    from genicam.genapi import GenericException as GenApiError
    from genicam.gentl import GenericException as GenTLError

    return GenApiError, GenTLError


def _first_line(exc: BaseException) -> str:
    """The first line of an exception's message (GenICam messages carry file/line noise)."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


# -- producers (.cti) ----------------------------------------------------------------------


def _check_cti(cti: str | Path) -> str:
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
class _Producer:
    """A loaded producer shared by the cameras opened on it in this process."""

    cti: str
    harvester: Harvester
    users: int = 0
    devices: list[DeviceInfo] = field(default_factory=list)


_PRODUCERS: dict[str, _Producer] = {}
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
            f"GenTL producer {cti!r} failed to enumerate devices ({_first_line(exc)}); check "
            "the camera's connection and the producer's installation"
        ) from None
    return harvester


def _info_text(info: Any, name: str) -> str:
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
            device_id=_info_text(info, "id_"),
            vendor=_info_text(info, "vendor"),
            model=_info_text(info, "model"),
            serial=_info_text(info, "serial_number"),
            address=_info_text(info, "display_name"),
        )
        for info in infos
    ]


def _acquire_producer(cti: str) -> _Producer:
    with _PRODUCERS_LOCK:
        producer = _PRODUCERS.get(cti)
        if producer is None:
            harvester = _load_producer(cti)
            producer = _Producer(cti, harvester, devices=_describe(harvester.device_info_list))
            _PRODUCERS[cti] = producer
        producer.users += 1
        return producer


def _release_producer(cti: str) -> None:
    with _PRODUCERS_LOCK:
        producer = _PRODUCERS.get(cti)
        if producer is None:
            return
        producer.users -= 1
        if producer.users <= 0:
            del _PRODUCERS[cti]
            producer.harvester.reset()


def _format_devices(devices: list[DeviceInfo]) -> str:
    if not devices:
        return "none"
    return "; ".join(
        f"{d.device_id} ({d.vendor} {d.model}, serial {d.serial or '?'})" for d in devices
    )


def list_devices(cti: str | Path) -> list[DeviceInfo]:
    """The cameras a GenTL producer offers.

    Parameters
    ----------
    cti : str or Path
        Path of the GenTL producer (``.cti``).

    Returns
    -------
    list of DeviceInfo
        One entry per device: ``device_id`` is the producer's device id, ``address`` its
        display name. While a :class:`GenICamCamera` on the same producer is open in this
        process, the list found when it was opened.

    Raises
    ------
    DeviceError
        When the file is missing, cannot be loaded or is not a GenTL producer, or the
        producer fails to enumerate its devices.
    """
    path = _check_cti(cti)
    with _PRODUCERS_LOCK:
        shared = _PRODUCERS.get(path)
        if shared is not None:
            return list(shared.devices)
        harvester = _load_producer(path)
        try:
            return _describe(harvester.device_info_list)
        finally:
            harvester.reset()


def _close_device(acquirer: ImageAcquirer, cti: str) -> None:
    """Stop and destroy `acquirer`, then release the shared producer (finaliser)."""
    try:
        acquirer.destroy()
    finally:
        _release_producer(cti)
