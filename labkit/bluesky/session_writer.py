"""A Bluesky callback that writes :func:`labkit.bluesky.labkit_plan`'s documents as a
labkit session, so that ``labkit session show`` and ``labkit hdr`` work on a Bluesky
capture unchanged.

The session is the one ``labkit capture`` writes: ``session.yaml`` (the rig snapshot and
plan fingerprint from the start document, devices, auto-bracketing choices, stream
counters, runs), ``frames.jsonl`` and the TIFF frames, stored crash-safely on background
threads. A run that ends before its plan is complete (an error, ``RE.abort()``,
``RE.stop()``) leaves a ``stopped`` or ``failed`` session, which ``labkit capture
--session`` with the same rig resumes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from bluesky.callbacks.core import CallbackBase

from labkit.bluesky.devices import frame_from_reading
from labkit.bluesky.streams import BRACKETS, PRIMARY, STATISTICS
from labkit.errors import DataError
from labkit.frame import DARK, FrameKey
from labkit.io.plain import now_iso
from labkit.protocol.capture_run import plan_shortfall, resume_hint
from labkit.rig import rig_from_dict
from labkit.session.store import FrameWriter, Session, plan_fingerprint


class SessionWriter(CallbackBase):
    """Write the labkit capture run that a RunEngine emits into the session `folder`.

    Subscribe it before running the plan: ``RE.subscribe(SessionWriter(folder))``. Runs
    that are not :func:`labkit_plan` captures are ignored. One writer writes one run.

    Parameters
    ----------
    folder : str or Path
        A new or empty folder (checked now, before anything is captured).
    writer_workers : int
        Threads storing frames.
    """

    def __init__(self, folder: str | Path, *, writer_workers: int = 2) -> None:
        super().__init__()
        self.folder = Path(folder)
        Session.check_creatable(self.folder)
        self.writer_workers = writer_workers
        self.session: Session | None = None
        self._writer: FrameWriter | None = None
        self._streams: dict[str, str] = {}
        self._devices: dict[str, str] = {}

    def start(self, doc: dict[str, Any]) -> None:
        facts = doc.get("labkit")
        if not isinstance(facts, dict) or facts.get("kind") != "labkit-capture":
            return
        if self.session is not None:
            raise DataError(
                f"SessionWriter for {self.folder} already wrote run {self.session.info['bluesky']}"
                "; subscribe a new writer (with a new folder) for each capture"
            )
        rig = rig_from_dict(facts["rig"], source=str(facts.get("rig_source") or ""))
        if plan_fingerprint(facts["rig"]) != facts.get("plan_fingerprint"):
            raise DataError(
                f"run {doc['uid']}: the start document's rig does not match its plan "
                "fingerprint; the documents were altered"
            )
        session = Session.create(self.folder, rig, bluesky={"run_uid": doc["uid"]})
        session.info["camera"] = facts["camera"]
        session.info["slider"] = facts["slider"]
        session.info["runs"].append({"started": now_iso(), "resumed_with": 0})
        session.save()
        session.log("bluesky_start", run_uid=doc["uid"], plan=doc.get("plan_name"))
        self.session = session
        self._devices = dict(facts["devices"])
        self._writer = FrameWriter(session, workers=self.writer_workers)

    def descriptor(self, doc: dict[str, Any]) -> None:
        if self.session is not None:
            self._streams[doc["uid"]] = doc.get("name", PRIMARY)

    def event(self, doc: dict[str, Any]) -> None:
        if self.session is None or self._writer is None:
            return
        stream = self._streams.get(doc["descriptor"])
        data = doc["data"]
        if stream == PRIMARY:
            label = self._devices["label"]
            scene = str(data[f"{label}_scene"]) or None
            illumination = str(data[f"{label}_illumination"])
            if scene is None and illumination != DARK:
                raise DataError(f"event {doc['uid']}: a frame without a scene must be a dark")
            frame = frame_from_reading(data, self._devices["camera"])
            key = FrameKey(scene, illumination, frame.exposure_s, int(data[f"{label}_replicate"]))
            self._writer.submit(key, frame)
        elif stream == BRACKETS:
            note = self._devices["note"]
            scene, illumination = str(data[f"{note}_scene"]), str(data[f"{note}_illumination"])
            choice = json.loads(data[f"{note}_text"])
            self.session.save_bracket(scene, illumination, choice)
            self.session.log("meter", scene=scene, illumination=illumination, choice=choice)
        elif stream == STATISTICS:
            note = self._devices["note"]
            self.session.info["stream_statistics"] = json.loads(data[f"{note}_text"])

    def stop(self, doc: dict[str, Any]) -> None:
        session, writer = self.session, self._writer
        if session is None or writer is None:
            return
        self._writer = None
        failure = None
        try:
            writer.close()
        except Exception as error:  # the frame that failed to store is missing: resumable
            failure = f"storing frames failed: {type(error).__name__}: {error}"
        shortfall = plan_shortfall(session)
        exit_status = doc.get("exit_status")
        if failure is None and exit_status == "success" and shortfall is None:
            status, reason = "complete", None
        else:
            status = "failed" if exit_status == "fail" or failure else "stopped"
            reason = (
                failure
                or doc.get("reason")
                or f"the run ended ({exit_status}) with {shortfall or '0 planned frame(s) missing'}"
            )
            reason += f"; {resume_hint(self.folder)}"
        stored = len(session.records)
        session.info["runs"][-1].update({"stopped": now_iso(), "status": status, "stored": stored})
        session.log("finish", status=status, reason=reason, stored=stored)
        session.set_status(status, reason)
        if failure is not None:
            raise DataError(f"session {self.folder}: {failure}")
