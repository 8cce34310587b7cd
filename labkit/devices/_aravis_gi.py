"""Aravis 0.8 through PyGObject, loaded once for the aravis camera backend.

:data:`Aravis`, :data:`GLib` and :data:`GObject` are the introspected modules, or None when
PyGObject or the Aravis 0.8 typelib is missing (:data:`IMPORT_ERROR` then says why);
:func:`require_aravis` turns that into a :class:`~labkit.errors.DeviceError` saying what to
install. The camera itself is :class:`labkit.devices.aravis.AravisCamera`.
"""

from __future__ import annotations

from labkit.errors import DeviceError

try:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis, GLib, GObject
except (ImportError, ValueError) as _error:  # no PyGObject, or no Aravis 0.8 typelib
    Aravis = None
    GLib = None
    GObject = None
    IMPORT_ERROR: Exception | None = _error
else:
    IMPORT_ERROR = None

__all__ = ["IMPORT_ERROR", "Aravis", "GLib", "GObject", "require_aravis"]


def require_aravis() -> None:
    """Raise DeviceError when PyGObject or the Aravis 0.8 typelib cannot be loaded."""
    if IMPORT_ERROR is not None:
        raise DeviceError(
            f"the aravis camera backend needs PyGObject and Aravis 0.8 ({IMPORT_ERROR}); "
            "install the system packages gir1.2-aravis-0.8 (and aravis-tools for the "
            "simulator), then the Python extra: pip install 'labkit[gige]'"
        )
