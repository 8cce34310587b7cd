"""The one writer of an output: an OS file lock that dies with its process.

Only one run may write an output folder, file set or session at a time. The lock is an
``flock`` on a hidden lock file beside the output (the output itself is replaced), which
the kernel releases when its process dies, so a ``kill -9`` never leaves a stale lock. A
second writer is refused at once with a message naming the holder.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

from labkit.errors import ConfigError
from labkit.io.plain import now_iso

_HELD: dict[str, tuple[int, int]] = {}  # lock file → (fd, depth): reentrant in a process
_HELD_GUARD = threading.Lock()


def lock_file_of(target: str | Path) -> Path:
    """The hidden lock file guarding `target` (beside it, since `target` itself is replaced)."""
    target = Path(target)
    parent = Path(os.path.realpath(target.parent))
    return parent / f".{target.name}.lock"


@contextlib.contextmanager
def writer_lock(target: str | Path, *, command: str, option: str = "--out") -> Iterator[None]:
    """Hold the only writer's lock of `target` (a file or folder) for the block.

    Re-entrant within a process (a command may lock its output up front and its writer
    lock it again). The lock is an ``flock`` on ``.<name>.lock`` beside `target`; the
    kernel drops it when the process dies. The lock file is removed on release.

    Raises
    ------
    ConfigError
        Another process holds the lock: the message names it (pid, host, command, since).
    """
    path = lock_file_of(target)
    key = str(path)
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is not None:
            _HELD[key] = (held[0], held[1] + 1)
    if held is None:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = _acquire(path, target=Path(target), command=command, option=option)
        with _HELD_GUARD:
            _HELD[key] = (fd, 1)
    try:
        yield
    finally:
        with _HELD_GUARD:
            fd, depth = _HELD[key]
            if depth > 1:
                _HELD[key] = (fd, depth - 1)
            else:
                del _HELD[key]
                depth = 0
        if depth == 0:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()  # while still locked: a waiter re-checks the inode
            os.close(fd)


def _acquire(path: Path, *, target: Path, command: str, option: str) -> int:
    """Open and ``flock`` the lock file; retries if it was replaced meanwhile."""
    for _ in range(20):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except OSError as error:
            raise ConfigError(
                f"{option} {target}: cannot create its lock file {path} ({error.strerror}); "
                "choose a writable place"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise ConfigError(
                f"{option} {target} is being written by another labkit run ({holder}); wait "
                "for it to finish or stop it, or choose another folder"
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            info = {
                "pid": os.getpid(),
                "host": socket.gethostname(),
                "command": command,
                "since": now_iso(),
            }
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(info).encode(), 0)
            return fd
        os.close(fd)  # the previous holder removed it after we opened it: take the new one
    raise ConfigError(f"{option} {target}: its lock file {path} keeps changing; try again")


def _holder(fd: int) -> str:
    try:
        info = json.loads(os.pread(fd, 4096, 0) or b"{}")
        return f"pid {info['pid']} on {info['host']}, `{info['command']}`, since {info['since']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder unknown"


def held_by_another(target: Path) -> bool:
    """Whether a live process holds `target`'s writer lock."""
    try:
        fd = os.open(lock_file_of(target), os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False
