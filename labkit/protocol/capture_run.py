"""One run of a capture into a session: what ``labkit capture``'s engine and the Bluesky
detector (:class:`labkit.bluesky.LabkitDetector`) both record before the first frame and
after the last, so that a session reads the same whichever of them captured it.

Before: leftovers of interrupted writes removed, every stored frame checked against its
checksum (a damaged one is forgotten, so it is captured again), the camera's and the
slider's identity recorded, a ``runs`` entry opened, the status set to ``running``, and a
simulated camera's frame counter moved past the stored frames'. After: the camera's stream
counters, the ``runs`` entry closed, a ``finish`` log line and the final status.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from labkit.devices.camera import Camera
from labkit.io.plain import now_iso
from labkit.protocol.plan import build_plan
from labkit.session.store import Session


class CaptureRun:
    """The bookkeeping of one capture run of `camera` into `session`.

    Parameters
    ----------
    session : Session
    camera : Camera
    slider : mapping
        The slider's facts recorded in ``session.yaml`` (``port`` and ``identity``).
    """

    def __init__(self, session: Session, camera: Camera, slider: Mapping[str, Any]) -> None:
        self.session = session
        self.camera = camera
        self.slider = dict(slider)
        self.stored_before = 0
        self.bytes_before = 0

    def begin(self) -> dict[str, str]:
        """Open the run; returns the damaged frames that will be captured again, {key: problem}."""
        session = self.session
        session.remove_leftovers()
        problems = session.verify()
        if problems:
            session.forget(problems)
            session.log("recapture", frames=problems)
        self.stored_before = len(session.records)
        self.bytes_before = session.stored_bytes()
        session.info["camera"] = self.camera.identity.as_dict()
        session.info["slider"] = self.slider
        session.info.setdefault("runs", []).append(
            {"started": now_iso(), "resumed_with": self.stored_before}
        )
        session.set_status("running")
        self._continue_frame_ids()
        return problems

    def _continue_frame_ids(self) -> None:
        """A simulated camera draws noise by frame id: never reuse one within a session."""
        if hasattr(self.camera, "next_frame_id") and self.session.records:
            last = max(int(r.get("frame_id") or 0) for r in self.session.records.values())
            self.camera.next_frame_id = max(self.camera.next_frame_id, last + 1)

    @property
    def stored_now(self) -> int:
        """Frames stored by this run so far."""
        return len(self.session.records) - self.stored_before

    @property
    def bytes_written(self) -> int:
        """Bytes of the frames stored by this run so far."""
        return self.session.stored_bytes() - self.bytes_before

    def finish(self, status: str, reason: str | None) -> None:
        """Close the run with `status` (``complete``, ``stopped`` or ``failed``) and why."""
        session = self.session
        session.info["stream_statistics"] = dict(self.camera.stream_statistics())
        session.info["runs"][-1].update(
            {"stopped": now_iso(), "status": status, "stored": self.stored_now}
        )
        session.log("finish", status=status, reason=reason, stored=self.stored_now)
        session.set_status(status, reason)


def plan_shortfall(session: Session) -> str | None:
    """What `session` still lacks of its rig's plan, in words (frames missing,
    illuminations not yet metered); None when it holds the whole plan."""
    plan = build_plan(session.rig, session.brackets)
    missing = sum(not session.has(key) for key in plan.keys())
    left = [f"{missing} planned frame(s) missing"] if missing else []
    if plan.pending_meters:
        left.append(f"{plan.pending_meters} illumination(s) not yet metered")
    return " and ".join(left) or None


def resume_hint(folder: str | Path) -> str:
    """How to finish a session that a run left unfinished."""
    return f"resume with `labkit capture --session {folder}` and the same rig"
