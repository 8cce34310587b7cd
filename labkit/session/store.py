"""A capture session on disk: ``session.yaml``, append-only ``frames.jsonl``, TIFF frames.

Crash safety: every frame is encoded in memory, hashed (sha256), written to a temporary
file, fsynced and renamed into place (and its folder fsynced) before its one-line JSON
record is appended to ``frames.jsonl`` and fsynced. A crash therefore leaves either a
complete frame with its record, or a frame file without a record (re-captured on
resume, overwriting it), or a torn last line (dropped on resume) — never a record
pointing at a partial file. ``session.yaml`` is rewritten atomically.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path, PurePosixPath
from typing import Any

import yaml

import labkit
from labkit.errors import ConfigError, DataError
from labkit.frame import Frame, FrameKey, path_name_problem
from labkit.io.atomic import atomic_path, fsync_directory, write_text_atomic
from labkit.io.digest import file_sha256
from labkit.io.plain import now_iso
from labkit.io.tiff import encode_raw_tiff, json_default
from labkit.rig import Rig, rig_from_dict

SESSION_FORMAT = 1
SESSION_FILE = "session.yaml"
MANIFEST_FILE = "frames.jsonl"
LOG_FILE = "log.jsonl"

#: Every status a session can be in (``running`` also after a crash).
STATUSES = ("running", "stopped", "failed", "complete", "imported")

#: The sections :meth:`Session.create` always writes, in its order: one of them missing
#: means a damaged or truncated ``session.yaml`` (``brackets`` and ``runs`` follow ``rig``,
#: so a file cut anywhere before its end lacks them).
REQUIRED_SECTIONS: dict[str, type] = {
    "status": str,
    "plan_fingerprint": str,
    "rig": dict,
    "brackets": dict,
    "runs": list,
}

#: Sections written later (by a capture run); when present they must be mappings.
OPTIONAL_MAPPINGS = ("camera", "slider", "stream_statistics")


def rig_snapshot(rig: Rig) -> dict[str, Any]:
    """The rig as plain data (what a session stores and compares on resume)."""
    return rig.model_dump(mode="json", exclude={"source"})


def plan_fingerprint(snapshot: dict[str, Any]) -> str:
    """sha256 of a rig snapshot, canonical JSON (first 16 hex digits)."""
    text = json.dumps(snapshot, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def first_difference(old: Any, new: Any, path: str = "") -> str | None:
    """Key path and values of the first difference between two nested mappings."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new), key=str):
            where = f"{path}.{key}" if path else str(key)
            if key not in old or key not in new:
                return f"{where}: {'absent' if key not in old else old[key]!r} → " + (
                    "absent" if key not in new else repr(new[key])
                )
            found = first_difference(old[key], new[key], where)
            if found:
                return found
        return None
    return None if old == new else f"{path}: {old!r} → {new!r}"


sha256_file = file_sha256
"""sha256 of a file's bytes (hex): :func:`labkit.io.digest.file_sha256`."""


def _not_a_session(folder: Path) -> str:
    """Why `folder` (which has no ``session.yaml``) is not a session, and what to give."""
    give = "pass the folder given to `labkit capture --session`"
    if not folder.exists():
        return f"session folder {folder} does not exist; {give}"
    if folder.is_file() and folder.name == SESSION_FILE:
        return (
            f"{folder} is the {SESSION_FILE} of a session: give the session folder "
            f"{folder.parent}, not its {SESSION_FILE}"
        )
    if not folder.is_dir():
        return f"{folder} is a file, not a session folder; {give}"
    return f"{folder} is not a labkit session (no {SESSION_FILE}); {give}"


_RESTORE = "restore it from a backup, or capture again into a new --session folder"


def _check_sections(info: dict[str, Any], path: Path) -> None:
    """Raise DataError unless ``session.yaml`` holds every section the writer writes, a rig
    snapshot that is whole (it matches its ``plan_fingerprint``, or validates with every
    key present) and a known status."""
    problems: list[str] = []
    missing = [name for name in REQUIRED_SECTIONS if name not in info]
    if missing:
        problems.append(f"it has no {', '.join(missing)} section{'s' if len(missing) > 1 else ''}")
    rig = info.get("rig")
    if "rig" in info and not isinstance(rig, dict):
        problems.append(f"rig is {rig!r}, not a mapping")
    elif isinstance(rig, dict):
        damage = _rig_damage(rig, info.get("plan_fingerprint"), path)
        if damage:
            problems.append(damage)
    for name, kind in REQUIRED_SECTIONS.items():
        if name != "rig" and name in info and not isinstance(info[name], kind):
            problems.append(f"{name} is {info[name]!r}, expected {_KIND_NAMES[kind]}")
    for name in OPTIONAL_MAPPINGS:
        if name in info and not isinstance(info[name], dict):
            problems.append(f"{name} is {info[name]!r}, expected a mapping")
    if isinstance(info.get("runs"), list) and not all(isinstance(r, dict) for r in info["runs"]):
        problems.append("runs holds an entry that is not a mapping")
    if problems:
        how = "damaged or truncated" if missing else "damaged or was edited"
        raise DataError(f"{path} is {how}: {'; '.join(problems)}; {_RESTORE}")
    status = info["status"]
    if status not in STATUSES:
        fix = "imported" if "imported_from" in info else "stopped"
        raise DataError(
            f"{path}: status {status!r} is not one of {', '.join(STATUSES)}; the file is "
            f"damaged or was edited: restore it from a backup, or set `status: {fix}`"
        )


_KIND_NAMES = {str: "text", dict: "a mapping", list: "a list"}


def _rig_damage(rig: dict[str, Any], fingerprint: Any, path: Path) -> str | None:
    """What is wrong with a rig snapshot that does not match the session's fingerprint
    (invalid, or keys missing that the schema would fill with defaults), or None."""
    try:
        if plan_fingerprint(rig) == fingerprint:
            return None  # as written: readable even where a later schema would differ
    except (TypeError, ValueError):  # not plain JSON data
        pass
    try:
        validated = rig_from_dict(rig, source=str(path))
    except ConfigError as error:
        return _rig_key_message(error, path)
    absent = _first_absent(rig, rig_snapshot(validated))
    # a whole, valid rig that was edited is read as it is; resuming it is refused (open_for)
    return f"rig.{absent} is missing" if absent else None


def _first_absent(data: dict[str, Any], whole: dict[str, Any], path: str = "") -> str | None:
    """The key path of the first key of `whole` that `data` lacks, or None."""
    for key, value in whole.items():
        where = f"{path}[{key}]" if str(key).isdigit() else f"{path}.{key}" if path else str(key)
        if key not in data:
            return where
        if isinstance(value, dict) and isinstance(data[key], dict):
            found = _first_absent(data[key], value, where)
            if found:
                return found
    return None


def _rig_key_message(error: ConfigError, path: Path) -> str:
    """A rig validation error about a session's rig snapshot, keyed as in ``session.yaml``
    (``rig.slider…``) and without the schema's class names."""
    text = str(error).removeprefix(f"{path}: ").replace("is missing; add it", "is missing")
    text = re.sub(r"a valid dictionary or instance of \w+", "a mapping", text)
    top = "|".join(name for name in Rig.model_fields if name != "source")
    return re.sub(rf"^({top})\b", r"rig.\1", text)


class Session:
    """A session folder. Use :meth:`create`, :meth:`open` or :meth:`open_for` to get one."""

    def __init__(self, folder: Path, info: dict[str, Any], records: dict[str, dict]) -> None:
        self.folder = folder
        self.info = info
        self.records = records
        self.torn_records = 0
        """Torn last manifest lines skipped by :meth:`open` (a crash mid-append; 0 or 1)."""
        self._lock = threading.Lock()

    # -- opening ---------------------------------------------------------------------------
    @classmethod
    def create(cls, folder: str | Path, rig: Rig, **facts: Any) -> Session:
        """Start a new session in an empty (or absent) folder."""
        folder = Path(folder)
        cls.check_creatable(folder)
        folder.mkdir(parents=True, exist_ok=True)
        snapshot = rig_snapshot(rig)
        info = {
            "format": SESSION_FORMAT,
            "kind": "labkit-session",
            "labkit_version": labkit.__version__,
            "created": now_iso(),
            "updated": now_iso(),
            "status": "running",
            "stop_reason": None,
            "rig_source": rig.source,
            "plan_fingerprint": plan_fingerprint(snapshot),
            "rig": snapshot,
            "brackets": {},
            "runs": [],
            **facts,
        }
        session = cls(folder, info, {})
        (folder / MANIFEST_FILE).touch()
        session.save()
        fsync_directory(folder)
        return session

    @staticmethod
    def check_creatable(folder: str | Path) -> None:
        """Raise ConfigError unless a new session can be created in `folder`."""
        folder = Path(folder)
        if (folder / SESSION_FILE).is_file():
            raise ConfigError(
                f"session folder {folder} already holds a labkit session; resume it with "
                f"`labkit capture RIG --session {folder}`, or choose a new --session folder"
            )
        if folder.exists() and not folder.is_dir():
            raise ConfigError(
                f"session folder {folder} is a file, not a folder; choose a new --session folder"
            )
        if folder.exists() and any(folder.iterdir()):
            raise ConfigError(
                f"session folder {folder} is not empty and holds no labkit session; "
                "choose a new --session folder"
            )

    @classmethod
    def open(cls, folder: str | Path, *, repair: bool = False) -> Session:
        """Open an existing session.

        A torn last manifest line (a crash mid-append) is skipped; with `repair` (a writer
        about to append) it is also cut off the file. Without `repair` nothing is written.

        Raises
        ------
        DataError
            Not a session, or a damaged ``session.yaml`` or manifest record (unreadable,
            missing or mistyped keys, a frame file outside ``frames/``, a name that is
            not a plain file name).
        """
        folder = Path(folder)
        path = folder / SESSION_FILE
        if not path.is_file():
            raise DataError(_not_a_session(folder))
        try:
            info = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (yaml.YAMLError, UnicodeDecodeError) as error:
            raise DataError(f"{path} is not valid YAML ({error}); the session is damaged") from None
        except OSError as error:
            raise DataError(f"{path} cannot be read ({error.strerror})") from None
        if not isinstance(info, dict) or info.get("kind") != "labkit-session":
            raise DataError(f"{path} is not a labkit session file")
        if info.get("format") != SESSION_FORMAT:
            raise DataError(
                f"{path}: session format {info.get('format')!r} is not supported "
                f"(this labkit reads format {SESSION_FORMAT})"
            )
        _check_sections(info, path)
        records, torn = _read_manifest(folder / MANIFEST_FILE, repair=repair)
        session = cls(folder, info, records)
        session.torn_records = 0 if repair else torn
        return session

    @classmethod
    def open_for(
        cls, folder: str | Path, rig: Rig, *, repair: bool = True, **facts: Any
    ) -> tuple[Session, bool]:
        """Open the session of `rig`'s plan in `folder`, or create it; returns (session, resumed).

        Raises ConfigError, touching nothing, when the folder holds a session of a
        different rig or plan. `repair` as in :meth:`open` (a writer about to append).
        """
        folder = Path(folder)
        if not (folder / SESSION_FILE).exists():
            return cls.create(folder, rig, **facts), False
        session = cls.open(folder, repair=repair)
        snapshot = rig_snapshot(rig)
        if session.info.get("plan_fingerprint") != plan_fingerprint(snapshot):
            change = first_difference(session.info.get("rig", {}), snapshot) or "the rig differs"
            raise ConfigError(
                f"session {folder} was captured with another rig or plan ({change}); "
                "resume with the original rig file or start a new --session folder"
            )
        return session, True

    # -- state -----------------------------------------------------------------------------
    @property
    def rig(self) -> Rig:
        """The rig snapshot the session was captured with."""
        path = self.folder / SESSION_FILE
        try:
            return rig_from_dict(self.info["rig"], source=str(path))
        except ConfigError as error:
            raise DataError(f"{path}: {_rig_key_message(error, path)}") from None

    @property
    def status(self) -> str:
        """``running`` (or crashed), ``stopped``, ``failed``, ``complete`` or ``imported``."""
        return self.info["status"]

    @property
    def brackets(self) -> dict[tuple[str, str], list[float]]:
        """Auto-bracketed exposure times chosen so far, by (scene, illumination)."""
        return {
            (scene, illumination): list(choice["exposures_s"])
            for scene, by_light in self.info.get("brackets", {}).items()
            for illumination, choice in by_light.items()
        }

    def has(self, key: FrameKey) -> bool:
        """Whether a frame is stored."""
        return key.id in self.records

    def save(self) -> None:
        """Rewrite ``session.yaml`` atomically."""
        self.info["updated"] = now_iso()
        text = yaml.safe_dump(self.info, sort_keys=False, allow_unicode=True)
        write_text_atomic(self.folder / SESSION_FILE, text)

    def set_status(self, status: str, reason: str | None = None) -> None:
        """Record a status change (and why) in ``session.yaml``."""
        self.info["status"] = status
        self.info["stop_reason"] = reason
        self.save()

    def save_bracket(self, scene: str, illumination: str, choice: dict[str, Any]) -> None:
        """Store an auto-bracketing decision (so a resumed session reuses it)."""
        self.info.setdefault("brackets", {}).setdefault(scene, {})[illumination] = choice
        self.save()

    def log(self, event: str, **fields: Any) -> None:
        """Append one executed step or event to ``log.jsonl``."""
        line = json.dumps({"time": now_iso(), "event": event, **fields}, default=str)
        with self._lock, open(self.folder / LOG_FILE, "a") as handle:
            handle.write(line + "\n")

    # -- frames ----------------------------------------------------------------------------
    def store(self, key: FrameKey, frame: Frame, **facts: Any) -> dict[str, Any]:
        """Write a frame durably, then append its record; returns the record."""
        record = frame_record(key, frame, **facts)
        data = encode_raw_tiff(frame.image, record)
        record["sha256"] = hashlib.sha256(data).hexdigest()
        record["bytes"] = len(data)
        path = self.folder / key.path
        with atomic_path(path) as temp:
            temp.write_bytes(data)
        self._append(record)
        return record

    def _append(self, record: dict[str, Any]) -> None:
        line = _record_line(record)
        with self._lock:
            fd = os.open(self.folder / MANIFEST_FILE, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
            try:
                os.write(fd, line.encode())
                os.fsync(fd)
            finally:
                os.close(fd)
            self.records[record["key"]] = record

    def verify(
        self, *, progress: Callable[[int], None] | None = None, hashes: bool = True
    ) -> dict[str, str]:
        """Check every recorded frame's file, size and (with `hashes`) checksum; returns
        {key: problem}."""
        problems: dict[str, str] = {}
        for record in list(self.records.values()):
            path = self.folder / record["file"]
            if not path.is_file():
                problems[record["key"]] = "file missing"
            elif path.stat().st_size != record.get("bytes", path.stat().st_size):
                problems[record["key"]] = "wrong size"
            elif hashes and sha256_file(path) != record["sha256"]:
                problems[record["key"]] = "checksum mismatch"
            if progress:
                progress(1)
        return problems

    def forget(self, keys: Iterable[str]) -> None:
        """Drop records (e.g. of corrupt frames) by rewriting the manifest atomically."""
        keys = set(keys)
        with self._lock:
            for key in keys:
                self.records.pop(key, None)
            text = "".join(_record_line(r) for r in self.records.values())
            write_text_atomic(self.folder / MANIFEST_FILE, text)

    def remove_leftovers(self) -> list[Path]:
        """Delete temporary files of interrupted writes; returns what was removed."""
        removed = (
            [p for p in (self.folder / "frames").rglob(".*.part")]
            if (self.folder / "frames").exists()
            else []
        )
        for path in removed:
            path.unlink(missing_ok=True)
        return removed

    def stored_bytes(self) -> int:
        """Total bytes of the recorded frames."""
        return sum(int(r.get("bytes", 0)) for r in self.records.values())


class FrameWriter:
    """Stores frames on a small thread pool so capture never waits on the disk.

    At most `max_pending` frames are in flight (bounded memory); :meth:`submit` blocks
    beyond that. Errors of a write are raised by the next :meth:`submit` or :meth:`close`.
    A key is taken once it is queued (:meth:`has`): a second frame for it would race the
    first to the same file, so :meth:`submit` refuses it.
    """

    def __init__(self, session: Session, *, workers: int = 2, max_pending: int = 4) -> None:
        self.session = session
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="labkit-writer")
        self._slots = threading.BoundedSemaphore(max_pending)
        self._futures: list[Future] = []
        self._queued: set[str] = set()

    def has(self, key: FrameKey) -> bool:
        """Whether a frame is stored or queued for storage."""
        return key.id in self._queued or self.session.has(key)

    def submit(self, key: FrameKey, frame: Frame, **facts: Any) -> None:
        """Queue a frame for durable storage."""
        self._raise_failures()
        if self.has(key):
            raise ValueError(f"frame {key.id} is already stored or queued; it is taken once")
        self._queued.add(key.id)
        self._slots.acquire()
        future = self._pool.submit(self.session.store, key, frame, **facts)
        future.add_done_callback(lambda _: self._done(key))
        self._futures.append(future)

    def _done(self, key: FrameKey) -> None:
        self._queued.discard(key.id)  # stored (a record now) or failed (free to retake)
        self._slots.release()

    def _raise_failures(self) -> None:
        done = [f for f in self._futures if f.done()]
        self._futures = [f for f in self._futures if not f.done()]
        for future in done:
            future.result()

    def close(self) -> None:
        """Wait for every queued frame to be durable; re-raise the first failure."""
        try:
            for future in self._futures:
                future.result()
        finally:
            self._futures = []
            self._pool.shutdown(wait=True)

    def __enter__(self) -> FrameWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def frame_record(key: FrameKey, frame: Frame, **facts: Any) -> dict[str, Any]:
    """The manifest record of a frame (without checksum and size)."""
    return {
        "key": key.id,
        "scene": key.scene,
        "illumination": key.illumination,
        "exposure_s": key.exposure_s,
        "replicate": key.replicate,
        "dark": key.is_dark,
        "exposure_readback_s": frame.exposure_readback_s,
        "gain_db": frame.gain_db,
        "pixel_format": frame.pixel_format,
        "shape": list(frame.image.shape),
        "frame_id": frame.frame_id,
        "device_timestamp_ns": frame.device_timestamp_ns,
        "host_timestamp_s": frame.host_timestamp_s,
        "status": frame.status,
        "temperature_c": frame.extra.get("temperature_c"),
        "black_level": frame.extra.get("black_level"),
        "saturation_dn": frame.extra.get("saturation_dn"),
        "file": key.path,
        "stored": now_iso(),
        **_simulation_truth(frame),
        **facts,
    }


def _simulation_truth(frame: Frame) -> dict[str, Any]:
    """Ground truth a simulated camera knows (the shutter's real exposure, the lamp level)."""
    truth = {name: frame.extra[name] for name in _SIM_TRUTH if name in frame.extra}
    return {"sim": truth} if truth else {}


_SIM_TRUTH = ("true_exposure_s", "light_level")


def key_of(record: dict[str, Any]) -> FrameKey:
    """The FrameKey of a manifest record."""
    return FrameKey(
        record["scene"],
        record["illumination"],
        float(record["exposure_s"]),
        int(record["replicate"]),
    )


def _read_manifest(path: Path, *, repair: bool) -> tuple[dict[str, dict], int]:
    """The records of ``frames.jsonl`` and the number of torn lines skipped (0 or 1): a torn
    last line (a crash mid-append) is skipped, and cut off the file only when `repair` (a
    writer about to append)."""
    if not path.exists():
        return {}, 0
    try:
        data = path.read_bytes()
    except OSError as error:
        raise DataError(f"{path} cannot be read ({error.strerror})") from None
    lines = data.split(b"\n")
    torn = 0
    if lines and lines[-1] and _torn_append(lines[-1]):  # a crash cut the last append
        torn = 1
        if repair:
            torn = len(data) - len(lines[-1])
            with open(path, "r+b") as handle:
                handle.truncate(torn)
                os.fsync(handle.fileno())
        lines = lines[:-1]
    records: dict[str, dict] = {}
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError):
            record = None
        if not isinstance(record, dict) or not isinstance(record.get("key"), str):
            raise DataError(
                f"{path} line {number} is not a frame record; the manifest is damaged "
                "(restore it from a backup, or delete that line and resume the capture, "
                f"`labkit capture RIG --session {path.parent}`, to re-take the frame)"
            )
        problem = record_problem(record, path.parent)
        if problem:
            raise DataError(
                f"{path} line {number} (frame {record['key']!r}): {problem}; the manifest is "
                "damaged or was edited (restore it from a backup, or delete that line and "
                f"resume the capture, `labkit capture RIG --session {path.parent}`, to re-take "
                "the frame)"
            )
        records[record["key"]] = record
    return records, torn


def _torn_append(line: bytes) -> bool:
    """Whether a last line without its newline is the start of a record (JSON objects are
    written as ASCII) rather than damage, which must not be skipped silently."""
    return line.startswith(b"{") and line.isascii()


_RECORD_TYPES: dict[str, tuple[type, ...]] = {
    "illumination": (str,),
    "exposure_s": (int, float),
    "replicate": (int,),
    "dark": (bool,),
    "pixel_format": (str,),
    "shape": (list,),
    "file": (str,),
    "sha256": (str,),
}


def record_problem(record: dict[str, Any], folder: Path) -> str | None:
    """What is wrong with a manifest record (missing or mistyped keys, names or a file
    that would leave the session folder), or None."""
    for name, types in _RECORD_TYPES.items():
        value = record.get(name)
        if not isinstance(value, types) or (bool in types) != isinstance(value, bool):
            return f"key {name!r} is {value!r}, expected {' or '.join(t.__name__ for t in types)}"
    if not math.isfinite(record["exposure_s"]) or record["exposure_s"] <= 0:
        return f"exposure_s {record['exposure_s']!r} is not a positive number of seconds"
    shape = record["shape"]
    if len(shape) != 2 or not all(isinstance(n, int) and n > 0 for n in shape):
        return f"shape {shape!r} is not [rows, cols]"
    if len(record["sha256"]) != 64:
        return "sha256 is not 64 hex digits"
    levels = _levels_problem(record.get("black_level"), record.get("saturation_dn"))
    if levels:
        return levels
    size = record.get("bytes")
    if size is not None and (not isinstance(size, int) or size < 0):
        return f"bytes {size!r} is not a file size"
    names = [("illumination", record["illumination"])]
    if not record["dark"] or record.get("scene") is not None:
        names.append(("scene", record.get("scene")))
    for what, name in names:
        why = path_name_problem(name)
        if why:
            return f"{what} {name!r} cannot name a file: {why}"
    file = record["file"]
    relative = PurePosixPath(file)
    if (
        relative.is_absolute()
        or "\\" in file
        or ".." in relative.parts
        or not file.startswith("frames/")
        or not (folder / relative).resolve().is_relative_to(folder.resolve())
    ):
        return f"file {file!r} is not a path inside the session's frames/ folder"
    return None


def _levels_problem(black: Any, saturation: Any) -> str | None:
    """What is wrong with a record's levels (None: not reported by the camera), or None."""
    for name, value in (("black_level", black), ("saturation_dn", saturation)):
        if value is None:
            continue
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not number or not math.isfinite(value):
            return f"{name} {value!r} is not a finite number of DN"
    if black is not None and black < 0:
        return f"black_level {black!r} is negative"
    if saturation is not None and saturation <= (black or 0):
        return f"saturation_dn {saturation!r} is not above the black level {black or 0!r} DN"
    return None


def _record_line(record: dict[str, Any]) -> str:
    """One manifest line: compact JSON and a newline."""
    return json.dumps(record, separators=(",", ":"), default=json_default) + "\n"
