"""A run's output folder, written as one unit by one writer at a time.

A command that writes a set of files (``labkit hdr``, ``labkit reconstruct``, …) writes
them into a hidden staging folder beside its output folder, adds a run manifest
(``labkit-run.json``: the command, when, and every file's size and sha256) last, and then
puts the staging folder in place of the output folder in one rename (Linux's
``renameat2(RENAME_EXCHANGE)``; elsewhere two renames). A run that fails or is killed
therefore leaves the previous complete set, or nothing: never some new files beside old
ones. A killed run's staging folder is hidden and removed by the next run into the same
folder.

A result file with companions (a model and its plots: :func:`staged_output_files`) is
staged the same way and put in place one rename at a time, after a journal that lets the
next writer finish a set a kill interrupted; readers refuse such a set meanwhile
(:func:`check_file_set`). A folder whose files name each other by absolute path (the demo)
is written in place under a marker instead (:func:`output_folder_in_place`).

Only one writer may hold an output: :mod:`labkit.io.writer_lock` (:func:`writer_lock` and
:func:`lock_file_of` are re-exported here).

Readers call :func:`verify_output_folder`: a folder with a run manifest must match it, file
by file; a folder without one was assembled by hand (e.g. images from another program) and
is taken as it is.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import os
import shutil
import tempfile
import time
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import labkit
from labkit.errors import ConfigError, DataError
from labkit.io.atomic import atomic_path, fsync_directory, process_umask, write_text_atomic
from labkit.io.digest import file_sha256
from labkit.io.plain import now_iso
from labkit.io.writer_lock import held_by_another, lock_file_of, writer_lock

RUN_MANIFEST = "labkit-run.json"
"""Name of the run manifest inside an output folder."""

MANIFEST_FORMAT = 1

RUNNING = ".labkit-run.running"
"""Marker of an output folder a run writes in place (:func:`output_folder_in_place`) and
has not finished: the folder is incomplete until its run manifest replaces the marker."""

_STAGING = ".staging-"


# -- checking ------------------------------------------------------------------------------
def check_output_folder(
    out: str | Path,
    *,
    option: str = "--out",
    command: str | None = None,
    inputs: Sequence[str | Path] = (),
) -> Path:
    """Raise unless `out` can become a run's output folder; nothing is created.

    It can if it is absent (and its nearest existing parent is a writable folder), an empty
    folder, or a folder that a labkit run of the same `command` wrote (it holds a run
    manifest): the run replaces it as a whole. Another command's folder (e.g. the HDR
    folder a calibration reads) is refused, and so is a folder holding one of the run's
    `inputs`, which replacing it would remove.

    Raises
    ------
    ConfigError
        `out` is a file or a symbolic link, a folder holding files no labkit run wrote, or
        cannot be created.
    """
    out = Path(out)
    for given in inputs:
        if _inside(Path(given), out):
            raise ConfigError(
                f"{option} {out} holds this run's input {given}, which replacing the folder "
                f"would remove; give {option} a new folder"
            )
    if out.is_symlink():
        raise ConfigError(
            f"{option} {out} is a symbolic link; give the folder it points to "
            f"({os.path.realpath(out)}) or a new folder"
        )
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{option} {out} exists and is not a folder; choose a new folder")
    if out.is_dir():
        try:
            entries = [p.name for p in out.iterdir()]
        except OSError as error:
            raise ConfigError(f"{option} {out} cannot be read ({error.strerror})") from None
        if "session.yaml" in entries and RUN_MANIFEST not in entries:
            raise ConfigError(
                f"{option} {out} holds a session that `labkit capture` wrote; a run replaces "
                "its output folder as a whole, so choose a new folder"
            )
        if entries and RUN_MANIFEST not in entries and RUNNING not in entries:
            raise ConfigError(
                f"{option} {out} holds files that no labkit run wrote (no {RUN_MANIFEST}); a "
                "run replaces its output folder as a whole, so choose a new folder or remove "
                "this one"
            )
        if entries and command is not None:
            manifest = read_run_manifest(out) or _read_running(out)
            if _program(str(manifest.get("command"))) != _program(command):
                raise ConfigError(
                    f"{option} {out} holds the outputs of `{manifest.get('command', 'another')}`"
                    f", not of `{command}`; a run replaces its output folder as a whole, so "
                    "choose a new folder"
                )
    _check_not_inside_another_set(out, option)
    _check_creatable(out, f"{option} {out}: cannot create files under")
    return out


def _program(command: str) -> str:
    """A command without its options or a "(Python)" note: ``labkit demo --real`` →
    ``labkit demo``."""
    words = []
    for word in command.split():
        if word.startswith(("-", "(")):
            break
        words.append(word)
    return " ".join(words)


def _check_creatable(path: Path, message: str) -> None:
    """Raise ConfigError unless `path` can be created: its nearest existing parent is a
    writable folder. `message` starts the error; the parent and the fix follow."""
    existing = path.parent
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        raise ConfigError(
            f"{message} {existing}, which is a file, not a folder; choose another place"
        )
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"{message} {existing}; choose a writable place")


# -- staging and putting in place ------------------------------------------------------------
@contextlib.contextmanager
def staged_output_folder(
    out: str | Path,
    *,
    command: str,
    option: str = "--out",
    details: dict[str, Any] | None = None,
    inputs: Sequence[str | Path] = (),
) -> Iterator[Path]:
    """Yield a hidden staging folder whose content replaces `out` as one set on success.

    Write every output file into the yielded folder. When the block succeeds, a run
    manifest (:data:`RUN_MANIFEST`) listing each file's size and sha256 is written last and
    the staging folder takes `out`'s place in one rename; the previous content of `out` is
    removed. When it fails (an exception, Ctrl-C), the staging folder is removed and `out`
    is untouched. The block runs under :func:`writer_lock`.

    Parameters
    ----------
    out : str or Path
        The output folder (see :func:`check_output_folder` for what it may be).
    command : str
        What is writing (e.g. ``"labkit hdr"``), recorded in the manifest and the lock.
    option : str
        How the user named `out`, for messages.
    details : dict, optional
        Further facts for the manifest (e.g. the input's path).
    inputs : sequence of paths
        The files and folders the run reads, which must not lie inside `out`.

    Raises
    ------
    ConfigError
        `out` cannot be an output folder, or another run is writing it.
    DataError
        The disk is full or the folder cannot be written: nothing was changed.
    """
    out = check_output_folder(out, option=option, command=command, inputs=inputs)
    started = now_iso()
    with _staging(out, command=command, option=option) as staging:
        yield staging
        _write_manifest(staging, command=command, started=started, details=details)
        os.chmod(staging, 0o777 & ~process_umask())
        fsync_directory(staging)
        check_output_folder(out, option=option, command=command, inputs=inputs)  # unchanged?
        _put_in_place(staging, out)
    fsync_directory(out.parent)


@contextlib.contextmanager
def output_folder_in_place(
    out: str | Path, *, command: str, option: str = "--out"
) -> Iterator[Path]:
    """Yield `out` itself, to be written in place, and make it one set on success.

    For runs whose files name each other by absolute path (the demo: sessions, HDR images
    and reports record where they are), which a staging folder renamed into place would
    break. The previous content of `out` is moved aside; while the run writes, a hidden
    marker (:data:`RUNNING`) says the folder is incomplete, and readers refuse it
    (:func:`verify_output_folder`). On success the run manifest replaces the marker and the
    previous content is removed; on failure the partial folder is removed and the previous
    content put back. A killed run leaves its marked, incomplete folder, which the next run
    into `out` replaces. The block runs under :func:`writer_lock`.

    Raises
    ------
    ConfigError
        `out` cannot be an output folder, or another run is writing it.
    DataError
        The disk is full or the folder cannot be written.
    """
    out = check_output_folder(out, option=option, command=command)
    started = now_iso()
    with _staging(out, command=command, option=option) as aside:
        previous = aside / "previous"
        if out.exists():
            os.rename(out, previous)
        out.mkdir()
        marker = {"command": command, "pid": os.getpid(), "started": started}
        write_text_atomic(out / RUNNING, json.dumps(marker) + "\n")
        try:
            yield out
            _write_manifest(out, command=command, started=started)
            (out / RUNNING).unlink()
        except BaseException:
            shutil.rmtree(out, ignore_errors=True)
            if previous.exists():
                os.rename(previous, out)
            raise
    fsync_directory(out.parent)


def _read_running(folder: Path) -> dict[str, Any]:
    """The marker of a run writing `folder` in place (empty if none or unreadable)."""
    try:
        marker = json.loads((folder / RUNNING).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return {}
    return marker if isinstance(marker, dict) else {}


def check_output_files(
    files: Sequence[str | Path], *, option: str = "--out", inputs: Sequence[str | Path] = ()
) -> list[Path]:
    """Raise unless `files` (a run's output files) can be written; nothing is created.

    Each must not be a folder, the places must be writable, no two may be the same file
    (e.g. ``--out model.png`` whose plot would be ``model.png`` too), and none may be one of
    the run's `inputs` (``export x.img`` would write its data file ``x.img``).

    Raises
    ------
    ConfigError
        Naming the file and the fix.
    """
    paths = [Path(f) for f in files]
    read = {os.path.realpath(f): Path(f) for f in inputs}
    seen: dict[str, Path] = {}
    for path in paths:
        if os.path.realpath(path) in read:
            raise ConfigError(
                f"{option} {paths[0]}: this run would write {path} over its own input "
                f"{read[os.path.realpath(path)]}; give {option} another name"
            )
        if path.is_dir():
            named = f"{option} {path}" if path == paths[0] else f"{path}, an output of this run,"
            raise ConfigError(f"{named} is a folder; give a file name")
        real = os.path.realpath(path)
        if real in seen:
            raise ConfigError(
                f"{option} {paths[0]}: this run would write {path} twice (also as "
                f"{seen[real]}), one output over another; give {option} another name or suffix"
            )
        seen[real] = path
        _check_not_inside_another_set(path, option)
        _check_creatable(path, f"{option} {paths[0]}: cannot create {path} under")
    return paths


def _check_not_inside_another_set(path: Path, option: str, levels: int = 4) -> None:
    """Refuse writing into a labkit run folder or a session (their manifests list what they
    hold, so a file added or replaced there would damage them, e.g. an input image)."""
    for parent in _parents(path, levels):
        owner = None
        if (parent / RUN_MANIFEST).is_file():
            owner = "the output folder of a labkit run"
        elif (parent / "session.yaml").is_file():
            owner = "a labkit session"
        if owner:
            raise ConfigError(
                f"{option} {path} lies inside {parent}, {owner}, whose files are listed in its "
                "manifest; write it somewhere else"
            )


@contextlib.contextmanager
def staged_output_files(
    files: Sequence[str | Path], *, command: str, option: str = "--out"
) -> Iterator[list[Path]]:
    """Yield staging paths for a run's output files, put in place together on success.

    The first file is the run's result (e.g. a model YAML), the others its companions
    (plots, tables). Write each at the staging path given for it, or leave a companion
    unwritten to remove an earlier run's file of that name. On success the companions are
    put in place first and the result last, each in one rename; on failure nothing of the
    previous files changes and the staging folder is removed. The block runs under
    :func:`writer_lock` of the result.

    Raises
    ------
    ConfigError
        See :func:`check_output_files`; another run is writing the result.
    DataError
        The disk is full or a file cannot be written: nothing was changed.
    """
    paths = check_output_files(files, option=option)
    primary = paths[0]
    with _staging(primary, command=command, option=option, files=paths) as staging:
        staged = [staging / f"{i}{path.suffix}" for i, path in enumerate(paths)]
        yield staged
        if not staged[0].is_file():
            raise RuntimeError(f"the run wrote no {primary}")
        for path in paths:
            path.parent.mkdir(parents=True, exist_ok=True)
        pairs = list(reversed(list(zip(staged, paths, strict=True))))
        _write_journal(staging, pairs, command=command)
        _roll_forward(staging)


# -- a file set's journal: the renames that put it in place, finished by whoever comes next --
_JOURNAL = "put-in-place.json"


def _write_journal(staging: Path, pairs: Sequence[tuple[Path, Path]], *, command: str) -> None:
    """Record the renames that put a staged file set in place (companions first, the result
    last), atomically: once the journal exists the new set is committed, and a run killed
    between its renames is finished by the next writer (:func:`_roll_forward`) and refused
    by readers meanwhile (:func:`check_file_set`)."""
    journal = {
        "command": command,
        "pid": os.getpid(),
        "written": now_iso(),
        "renames": [
            {"staged": temp.name if temp.exists() else None, "target": os.path.abspath(path)}
            for temp, path in pairs
        ],
    }
    write_text_atomic(staging / _JOURNAL, json.dumps(journal))


def _read_journal(staging: Path) -> dict[str, Any] | None:
    """A staging folder's journal; None when the run was not committed (no journal, or one
    cut short: the run was killed before its set was complete)."""
    try:
        journal = json.loads((staging / _JOURNAL).read_text(encoding="utf-8"))
        renames = [
            (None if r["staged"] is None else staging / r["staged"], Path(r["target"]))
            for r in journal["renames"]
        ]
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
        return None
    if any(temp is not None and temp.parent != staging for temp, _ in renames):
        return None  # not a journal labkit wrote: a staged name that leaves its folder
    return {**journal, "renames": renames}


def _unfinished(journal: dict[str, Any]) -> bool:
    """Whether some rename of a journal is still to be done."""
    return any(
        path.exists() if temp is None else temp.exists() for temp, path in journal["renames"]
    )


def _roll_forward(staging: Path) -> None:
    """Do the renames a staging folder's journal lists (those not done yet); a file a run
    did not write removes an earlier run's file of that name."""
    journal = _read_journal(staging)
    if journal is None:
        return
    for temp, path in journal["renames"]:
        if temp is None:
            path.unlink(missing_ok=True)  # an earlier run's companion this run did not write
        elif temp.exists():
            _move_into_place(temp, path)
    for folder in {path.parent for _, path in journal["renames"]}:
        fsync_directory(folder)
    (staging / _JOURNAL).unlink()


def check_file_set(path: str | Path, *, what: str = "input", wait: float = 5.0) -> None:
    """Refuse a file whose set a killed run left half put in place.

    A run that writes a file with companions (a dispersion model and its plots) puts them
    in place one rename after another, the file itself last. A run killed between those
    renames leaves its journal in a hidden staging folder beside the file: the companions
    are new, the file is the previous one. The next run writing the file finishes the
    renames; until then the set is mixed, and this raises. A live run still renaming is
    waited for, up to `wait` seconds.

    Raises
    ------
    DataError
        Naming the run and the fix.
    """
    path = Path(path)
    deadline = time.monotonic() + wait
    while True:
        pending = [
            (staging, journal)
            for staging in path.parent.glob(f".{path.name}{_STAGING}*")
            if (journal := _read_journal(staging)) is not None and _unfinished(journal)
        ]
        if not pending:
            return
        if not held_by_another(path) or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    staging, journal = pending[0]
    raise DataError(
        f"{what} {path}: a `{journal['command']}` run (pid {journal['pid']}) was stopped "
        f"while putting its files in place ({staging.name} remains), so {path.name} is the "
        "previous run's and its companions the new run's; run that command again to finish "
        "or replace the set"
    )


@contextlib.contextmanager
def _staging(
    target: Path, *, command: str, option: str, files: Sequence[Path] = ()
) -> Iterator[Path]:
    """A hidden staging folder beside `target`, under its writer lock; removed on every exit
    (after a swap it holds the previous content). Disk errors become DataErrors. `files`
    are a file set's outputs (see :func:`_remove_stale_staging`)."""
    with writer_lock(target, command=command, option=option):
        target.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_staging(target, files)
        staging = Path(tempfile.mkdtemp(prefix=f".{target.name}{_STAGING}", dir=target.parent))
        try:
            with _disk_errors(target, option):
                yield staging
        finally:
            if _read_journal(staging) is None:  # else a committed set for the next writer
                shutil.rmtree(staging, ignore_errors=True)


def _move_into_place(temp: Path, path: Path) -> None:
    """Rename a staged file over `path`; across file systems, through a copy beside it."""
    os.chmod(temp, 0o666 & ~process_umask())
    try:
        os.replace(temp, path)
    except OSError as error:
        if error.errno != errno.EXDEV:
            raise
        with atomic_path(path, suffix=temp.suffix) as beside:
            shutil.copyfile(temp, beside)


def _put_in_place(staging: Path, out: Path) -> None:
    """Rename `staging` to `out`. The previous `out` ends up at `staging` (removed by
    :func:`_staging`), through one atomic exchange where the system has it."""
    if not out.exists():
        os.rename(staging, out)
    elif not _exchange(staging, out):
        aside = staging.with_name(f"{staging.name}-new")
        os.rename(staging, aside)
        os.rename(out, staging)
        os.rename(aside, out)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux ``renameat2``); False where it is not available."""
    libc = ctypes.CDLL(None, use_errno=True)  # the process' own symbols, libc's among them
    renameat2 = getattr(libc, "renameat2", None)
    if renameat2 is None:
        return False
    result = renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if result == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False  # the file system cannot exchange: fall back to two renames
    raise OSError(code, os.strerror(code), str(b))


def _remove_stale_staging(out: Path, files: Sequence[Path] = ()) -> None:
    """Staging folders of killed runs into `out` (we hold its lock, so none is live). A run
    killed after committing its file set is finished first (:func:`_roll_forward`), so
    that the previous set, if this run fails, is that run's complete set; only a journal
    whose renames all target this run's own output `files` is followed."""
    mine = {os.path.abspath(f) for f in files}
    for stale in sorted(out.parent.glob(f".{out.name}{_STAGING}*")):
        journal = _read_journal(stale)
        if journal and {os.path.abspath(p) for _, p in journal["renames"]} <= mine:
            _roll_forward(stale)
        shutil.rmtree(stale, ignore_errors=True)


@contextlib.contextmanager
def _disk_errors(out: Path, option: str) -> Iterator[None]:
    try:
        yield
    except OSError as error:
        if error.errno in (errno.ENOSPC, errno.EDQUOT):
            raise DataError(
                f"{option} {out}: the disk is full ({error.strerror}); nothing was changed — "
                "free some space and run the command again"
            ) from None
        if error.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            raise DataError(
                f"{option} {out}: cannot write ({error.strerror}: {error.filename}); nothing "
                "was changed — choose a writable folder"
            ) from None
        raise


def _write_manifest(
    folder: Path, *, command: str, started: str, details: dict[str, Any] | None = None
) -> None:
    """Write `folder`'s run manifest (:data:`RUN_MANIFEST`), atomically and durably."""
    manifest = _manifest(folder, command=command, started=started, details=details)
    text = json.dumps(manifest, indent=1, ensure_ascii=False) + "\n"
    write_text_atomic(folder / RUN_MANIFEST, text)


def _manifest(
    staging: Path, *, command: str, started: str, details: dict[str, Any] | None
) -> dict[str, Any]:
    files = {
        path.relative_to(staging).as_posix(): {
            "bytes": path.stat().st_size,
            "sha256": file_sha256(path),
        }
        for path in sorted(staging.rglob("*"))
        if path.is_file() and not _hidden(path.relative_to(staging))
    }
    return {
        "format": MANIFEST_FORMAT,
        "kind": "labkit-run",
        "run_id": uuid.uuid4().hex,
        "command": command,
        "software": f"labkit {labkit.__version__}",
        "started": started,
        "finished": now_iso(),
        **(details or {}),
        "files": files,
    }


# -- reading -------------------------------------------------------------------------------
def read_run_manifest(folder: str | Path) -> dict[str, Any] | None:
    """The run manifest of an output folder, or None if it has none.

    Raises
    ------
    DataError
        The manifest exists but is not a labkit run manifest.
    """
    path = Path(folder) / RUN_MANIFEST
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataError(f"{path} is not a readable run manifest ({error})") from None
    if (
        not isinstance(manifest, dict)
        or manifest.get("kind") != "labkit-run"
        or not isinstance(manifest.get("files"), dict)
    ):
        raise DataError(f"{path} is not a labkit run manifest; the folder was altered")
    if manifest.get("format") != MANIFEST_FORMAT:
        raise DataError(
            f"{path}: run manifest format {manifest.get('format')!r} is not supported "
            f"(this labkit reads format {MANIFEST_FORMAT})"
        )
    return manifest


def verify_output_folder(
    folder: str | Path, *, what: str, rerun: str, hashes: bool = True
) -> dict[str, Any] | None:
    """Check that an output folder is the complete set one run wrote.

    Parameters
    ----------
    folder : str or Path
        The folder to read.
    what : str
        What the folder is, for messages (e.g. ``"HDR folder"``).
    rerun : str
        The command that makes it again, for messages.
    hashes : bool
        Also compare every file's sha256 (otherwise only sizes).

    Returns
    -------
    dict or None
        The run manifest; None for a folder without one (assembled by hand: not checked).

    Raises
    ------
    DataError
        A listed file is missing or changed, or a file is not from that run (a mixed set).
    """
    folder = Path(folder)
    if (folder / RUNNING).exists():
        running = _read_running(folder)
        raise DataError(
            f"{what} {folder} is incomplete: a `{running.get('command', 'labkit')}` run "
            f"started {running.get('started', '')} is writing it or was stopped; run {rerun} "
            "again"
        )
    manifest = read_run_manifest(folder)
    if manifest is None:
        return None
    run_id = str(manifest.get("run_id"))[:8]
    run = f"`{manifest.get('command')}` run {run_id} of {manifest.get('finished')}"
    files: dict[str, Any] = manifest["files"]
    for name, facts in files.items():
        path = folder / name
        if not _inside(path, folder):
            raise DataError(f"{folder / RUN_MANIFEST} lists {name!r}, outside the folder")
        problem = None
        if not path.is_file():
            problem = "is missing"
        elif path.stat().st_size != facts.get("bytes"):
            problem = "has changed size"
        elif hashes and file_sha256(path) != facts.get("sha256"):
            problem = "has changed content"
        if problem:
            raise DataError(
                f"{what} {folder} is not the complete set of the {run}: {name} {problem}; "
                f"run {rerun} again"
            )
    for path in sorted(folder.rglob("*")):
        name = path.relative_to(folder).as_posix()
        if path.is_file() and name != RUN_MANIFEST and name not in files:
            if _hidden(path.relative_to(folder)):
                continue
            raise DataError(
                f"{what} {folder} mixes files of different runs: {name} is not from the "
                f"{run}; run {rerun} again into a new folder"
            )
    return manifest


def verify_output_file(path: str | Path, *, what: str = "input", levels: int = 3) -> None:
    """Check one input file against the run manifest of the output folder it lies in, if any.

    The folders above `path` (up to `levels` of them) are searched for a run manifest; a
    file inside a run's folder must be listed by it with the same size and sha256. A file
    in no run's folder is not checked.

    Raises
    ------
    DataError
        The file is not from that run (a mixed set) or was changed after it.
    """
    path = Path(path)
    check_file_set(path, what=what)
    for folder in _parents(path, levels):
        manifest = read_run_manifest(folder)
        if manifest is None:
            continue
        name = Path(os.path.abspath(path)).relative_to(folder).as_posix()
        facts = manifest["files"].get(name)
        run = f"`{manifest.get('command')}` run of {manifest.get('finished')}"
        if facts is None:
            raise DataError(
                f"{what} {path} is not one of the files the {run} wrote into {folder}: "
                "the folder mixes runs; use a file from a complete run folder"
            )
        if path.stat().st_size != facts.get("bytes") or file_sha256(path) != facts.get("sha256"):
            raise DataError(
                f"{what} {path} has changed since the {run} wrote it "
                f"({folder / RUN_MANIFEST}); run that command again"
            )
        return


# -- helpers -------------------------------------------------------------------------------
def _parents(path: Path, levels: int) -> list[Path]:
    """The `levels` folders above `path`, nearest first (where a run or session holding it
    would be)."""
    return list(Path(os.path.abspath(path)).parents)[:levels]


def _hidden(relative: Path) -> bool:
    """Hidden files (locks, markers, staging) are not part of a run's set."""
    return any(part.startswith(".") for part in relative.parts)


def _inside(path: Path, folder: Path) -> bool:
    return Path(os.path.realpath(path)).is_relative_to(os.path.realpath(folder))


__all__ = [
    "RUNNING",
    "RUN_MANIFEST",
    "check_file_set",
    "check_output_files",
    "check_output_folder",
    "lock_file_of",
    "output_folder_in_place",
    "read_run_manifest",
    "staged_output_files",
    "staged_output_folder",
    "verify_output_file",
    "verify_output_folder",
    "writer_lock",
]
