"""Fixtures for the device-backend tests: Aravis' GigE Vision camera simulator.

``arv-fake-gv-camera-0.8`` (Debian package aravis-tools) answers GigE Vision discovery and
control on 127.0.0.1 and streams a test pattern. Every simulator needs UDP port 3956 on
that address (Linux's loopback has no second address such as 127.0.0.2 unless one is
added), so :class:`FakeGvManager` runs at most one at a time: asking for a different
configuration (serial number, packet loss, GenICam file) stops the running one first.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import socket
import subprocess
import tempfile
import time
import tty
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import pytest

from labkit.devices import serial_ports

FAKE_BINARY = "arv-fake-gv-camera-0.8"
FAKE_ADDRESS = "127.0.0.1"
GVCP_PORT = 3956
#: Seconds a freshly started simulator may take to become openable.
START_TIMEOUT_S = 10.0
#: Seconds to wait for another test run on this machine to finish with the simulator.
LOCK_TIMEOUT_S = 180.0


def aravis_skip_reason() -> str | None:
    """Why the Aravis simulator tests cannot run here (None: they can)."""
    if shutil.which(FAKE_BINARY) is None:
        return f"{FAKE_BINARY} not found (install the Debian package aravis-tools)"
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as error:
        return f"Aravis 0.8 typelib unavailable ({error}); install gir1.2-aravis-0.8 and PyGObject"
    return None


def _port_busy() -> bool:
    """Whether something already listens on the simulator's GVCP port."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((FAKE_ADDRESS, GVCP_PORT))
    except OSError:
        return True
    finally:
        probe.close()
    return False


@dataclass
class FakeGvCamera:
    """One ``arv-fake-gv-camera-0.8`` process.

    Attributes
    ----------
    serial : str
        Serial number; the Aravis device id is ``Aravis-Fake-<serial>``.
    loss_per_mille : int
        GVSP packets dropped per thousand (``-r``).
    genicam : Path or None
        Alternative GenICam XML (``-g``); its features must map the simulator's registers.
    """

    serial: str
    loss_per_mille: int = 0
    genicam: Path | None = None
    process: subprocess.Popen | None = field(default=None, repr=False)

    @property
    def device_id(self) -> str:
        """The Aravis device id of this simulator."""
        return f"Aravis-Fake-{self.serial}"

    @property
    def config(self) -> tuple[str, int, Path | None]:
        return (self.serial, self.loss_per_mille, self.genicam)

    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def start(self) -> None:
        """Start the process and wait until the camera can be opened (RuntimeError if not)."""
        if self.running():
            return
        if _port_busy():
            raise RuntimeError(
                f"UDP port {GVCP_PORT} on {FAKE_ADDRESS} is in use (another GigE Vision "
                "simulator or camera program?)"
            )
        command = [FAKE_BINARY, "-i", FAKE_ADDRESS, "-s", self.serial]
        if self.loss_per_mille:
            command += ["-r", str(self.loss_per_mille)]
        if self.genicam is not None:
            command += ["-g", str(self.genicam)]
        self.process = subprocess.Popen(
            command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        self._wait_openable()

    def _wait_openable(self) -> None:
        from gi.repository import Aravis, GLib

        deadline = time.monotonic() + START_TIMEOUT_S
        time.sleep(0.1)
        while True:
            if not self.running():
                err = self.process.stderr.read() if self.process and self.process.stderr else ""
                raise RuntimeError(f"{FAKE_BINARY} exited at start: {err.strip()[-300:]}")
            try:
                camera = Aravis.Camera.new(self.device_id)
            except GLib.GError:
                if time.monotonic() > deadline:
                    self.kill()
                    raise RuntimeError(
                        f"{self.device_id} not discoverable within {START_TIMEOUT_S} s"
                    ) from None
                time.sleep(0.1)
                continue
            del camera  # releases control of the device
            return

    def kill(self) -> None:
        """Kill the process at once (as a camera losing power)."""
        if self.process is not None:
            with contextlib.suppress(ProcessLookupError):
                self.process.kill()
            self.process.wait(timeout=10)
            if self.process.stderr is not None:
                self.process.stderr.close()
        self.process = None

    def restart(self) -> None:
        """Kill and start again (the simulator comes back with its default settings)."""
        self.kill()
        self.start()


class FakeGvManager:
    """Runs at most one simulator at a time (all of them need UDP port 3956)."""

    def __init__(self) -> None:
        self.current: FakeGvCamera | None = None

    def ensure(
        self, serial: str, *, loss_per_mille: int = 0, genicam: Path | None = None
    ) -> FakeGvCamera:
        """A running simulator with this configuration (pytest.skip if none can start)."""
        wanted = FakeGvCamera(serial, loss_per_mille, genicam)
        if self.current is not None and self.current.config == wanted.config:
            if not self.current.running():
                self._start(self.current)
            return self.current
        self.stop()
        self._start(wanted)
        self.current = wanted
        return wanted

    def restart(self, fake: FakeGvCamera) -> None:
        """Start `fake` again after a test killed it (pytest.skip if it cannot start)."""
        self._start(fake)

    @staticmethod
    def _start(fake: FakeGvCamera) -> None:
        try:
            fake.start()
        except RuntimeError as error:
            pytest.skip(f"cannot run the Aravis simulator: {error}")

    def stop(self) -> None:
        if self.current is not None:
            self.current.kill()
        self.current = None


@contextlib.contextmanager
def _simulator_lock(timeout_s: float) -> Iterator[bool]:
    """Hold an exclusive lock on the simulator port for this process (other test runs on
    this machine wait for it); yields False if it could not be taken within `timeout_s`."""
    path = Path(tempfile.gettempdir()) / f"labkit-arv-fake-{GVCP_PORT}.lock"
    with path.open("a") as handle:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError:
                if time.monotonic() > deadline:
                    yield False
                    return
                time.sleep(0.2)
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@pytest.fixture(scope="module")
def fake_gv_manager() -> Iterator[FakeGvManager]:
    """The module's simulator manager; the simulator is killed when the module ends.

    Test runs in parallel on one machine take turns (a lock file in the temp folder).
    """
    reason = aravis_skip_reason()
    if reason is not None:
        pytest.skip(reason)
    with _simulator_lock(LOCK_TIMEOUT_S) as locked:
        if not locked:
            pytest.skip(f"another test run held the Aravis simulator for {LOCK_TIMEOUT_S} s")
        manager = FakeGvManager()
        try:
            yield manager
        finally:
            manager.stop()


@pytest.fixture
def fake_gv(fake_gv_manager: FakeGvManager) -> FakeGvCamera:
    """A loss-free simulator, serial LK01 (device id ``Aravis-Fake-LK01``)."""
    return fake_gv_manager.ensure("LK01")


@pytest.fixture
def lossy_fake_gv(fake_gv_manager: FakeGvManager) -> FakeGvCamera:
    """A simulator dropping 20 ‰ of its stream packets (``-r 20``), serial LK20."""
    return fake_gv_manager.ensure("LK20", loss_per_mille=20)


# -- serial ports --------------------------------------------------------------------------

#: What ``serial.tools.list_ports.comports`` returns in the `fake_ports` fixture.
FAKE_PORTS = [
    SimpleNamespace(device="/dev/ttyUSB0", description="FT230X Basic UART", hwid="USB VID:PID"),
    SimpleNamespace(device="/dev/ttyS0", description="", hwid=""),
]


@pytest.fixture
def fake_ports(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(serial_ports.list_ports, "comports", lambda: list(FAKE_PORTS))


@pytest.fixture
def silent_port() -> Iterator[str]:
    """A pseudo-terminal nobody answers on."""
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        yield os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)
