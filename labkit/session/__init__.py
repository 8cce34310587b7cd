"""Capture sessions: the on-disk format, crash-safe frame storage, import from other software."""

from labkit.session.store import (
    MANIFEST_FILE,
    SESSION_FILE,
    SESSION_FORMAT,
    FrameWriter,
    Session,
    frame_record,
    key_of,
    plan_fingerprint,
    rig_snapshot,
    sha256_file,
)

__all__ = [
    "MANIFEST_FILE",
    "SESSION_FILE",
    "SESSION_FORMAT",
    "FrameWriter",
    "Session",
    "frame_record",
    "key_of",
    "plan_fingerprint",
    "rig_snapshot",
    "sha256_file",
]
