"""The cameras a GenTL producer (``.cti``) offers, for the genicam camera backend.

One producer can be loaded only once per process, so the producers are loaded, shared by
reference count and released by :mod:`labkit.devices._gentl`; :func:`list_devices` reuses
a producer that an open :class:`~labkit.devices.genicam.GenICamCamera` holds.
"""

from __future__ import annotations

from pathlib import Path

from labkit.devices._gentl import check_cti, producer_devices
from labkit.devices.camera import DeviceInfo


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
    return producer_devices(check_cti(cti))
