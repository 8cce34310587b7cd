"""The labkit error hierarchy.

Every error a user can cause derives from :class:`LabkitError`; its message says what is
wrong, where (file, key, device, frame) and how to fix it. The CLI prints these messages
without a traceback.
"""

from __future__ import annotations


class LabkitError(Exception):
    """Base class of every error labkit raises on purpose."""


class ConfigError(LabkitError):
    """A rig file, plan or option is invalid."""


class DeviceError(LabkitError):
    """A camera, slider or other device failed or answered unexpectedly."""


class DataError(LabkitError):
    """An image, spectrum or file on disk is missing, malformed or inconsistent."""


class DataWarning(UserWarning):
    """Data that labkit can use but the user should know about (e.g. a torn last record of
    a session's manifest: that frame is left out). The CLI prints these as one line each."""
