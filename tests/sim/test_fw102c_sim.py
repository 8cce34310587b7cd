"""Tests of the FW102C filter-wheel simulator, through a real pyserial port on its pty."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
import serial

from labkit.errors import ConfigError, DeviceError
from labkit.sim.fw102c import FW102CHandler, FW102CSimulator
from labkit.sim.serial_protocol import LineFramer, Wait

PROMPT = b"> "
IDN = b"THORLABS FW102C/FW212C Filter Wheel version 1.07"
TIMEOUT = 3.0  # s; generous: a reply normally arrives within milliseconds


def open_port(sim: FW102CSimulator, timeout: float = TIMEOUT) -> serial.Serial:
    return serial.Serial(sim.port, 115200, timeout=timeout)


def read_reply(ser: serial.Serial) -> bytes:
    """Read up to and including the prompt; fail clearly if it does not come."""
    reply = ser.read_until(PROMPT)
    assert reply.endswith(PROMPT), f"no prompt within {ser.timeout} s, got {reply!r}"
    return reply


def ask(ser: serial.Serial, command: bytes) -> bytes:
    ser.write(command + b"\r")
    return read_reply(ser)


@pytest.fixture
def sim() -> Iterator[FW102CSimulator]:
    with FW102CSimulator(time_scale=0, seed=1234) as simulator:
        yield simulator


@pytest.fixture
def ser(sim: FW102CSimulator) -> Iterator[serial.Serial]:
    with open_port(sim) as port:
        yield port


# -- protocol ---------------------------------------------------------------------------------


def test_idn_round_trip_exact_bytes(ser: serial.Serial) -> None:
    assert ask(ser, b"*idn?") == b"*idn?\r" + IDN + b"\r> "


def test_move_then_query_position(sim: FW102CSimulator, ser: serial.Serial) -> None:
    assert ask(ser, b"pos?") == b"pos?\r1\r> "
    assert ask(ser, b"pos=3") == b"pos=3\r> "
    assert ask(ser, b"pos?") == b"pos?\r3\r> "
    assert sim.position == 3


def test_pcount_query_and_set(sim: FW102CSimulator, ser: serial.Serial) -> None:
    assert ask(ser, b"pcount?") == b"pcount?\r12\r> "
    assert ask(ser, b"pos=9") == b"pos=9\r> "
    assert ask(ser, b"pcount=6") == b"pcount=6\r> "
    assert ask(ser, b"pcount?") == b"pcount?\r6\r> "
    # position 9 no longer exists: the wheel re-homes to 1, and 7 is now out of range
    assert ask(ser, b"pos?") == b"pos?\r1\r> "
    assert ask(ser, b"pos=7") == b"pos=7\rCommand error CMD_ARG_INVALID\r> "
    assert sim.positions == 6


def test_six_position_constructor() -> None:
    with FW102CSimulator(6, time_scale=0) as sim, open_port(sim) as ser:
        assert ask(ser, b"pcount?") == b"pcount?\r6\r> "


@pytest.mark.parametrize(
    ("key", "default", "other"),
    [
        (b"speed", b"1", b"0"),
        (b"trig", b"0", b"1"),
        (b"sensors", b"0", b"1"),
        (b"baud", b"1", b"0"),
    ],
)
def test_settings_round_trip(ser: serial.Serial, key: bytes, default: bytes, other: bytes) -> None:
    assert ask(ser, key + b"?") == key + b"?\r" + default + b"\r> "
    assert ask(ser, key + b"=" + other) == key + b"=" + other + b"\r> "
    assert ask(ser, key + b"?") == key + b"?\r" + other + b"\r> "


def test_save_is_accepted(ser: serial.Serial) -> None:
    assert ask(ser, b"save") == b"save\r> "


@pytest.mark.parametrize("command", [b"foo", b"POS?", b"pos", b"*idn", b"save=1", b"position?"])
def test_unknown_command(ser: serial.Serial, command: bytes) -> None:
    assert ask(ser, command) == command + b"\rCommand error CMD_NOT_DEFINED\r> "


def test_empty_line_is_not_defined(ser: serial.Serial) -> None:
    assert ask(ser, b"") == b"\rCommand error CMD_NOT_DEFINED\r> "


@pytest.mark.parametrize(
    "command",
    [b"pos=0", b"pos=13", b"pos=x", b"pos=", b"pos=-1", b"pos=2.5", b"pcount=8", b"speed=2"],
)
def test_invalid_argument(sim: FW102CSimulator, ser: serial.Serial, command: bytes) -> None:
    assert ask(ser, command) == command + b"\rCommand error CMD_ARG_INVALID\r> "
    assert sim.position == 1


def test_crlf_and_lf_terminators_and_pipelining(ser: serial.Serial) -> None:
    ser.write(b"pos=2\r\n")
    assert read_reply(ser) == b"pos=2\r> "
    ser.write(b"pos?\n")
    assert read_reply(ser) == b"pos?\r2\r> "
    ser.write(b"pos=4\rpos?\r")
    assert read_reply(ser) == b"pos=4\r> "
    assert read_reply(ser) == b"pos?\r4\r> "
    ser.timeout = 0.2
    assert ser.read(64) == b""  # the CR LF above did not produce a stray empty command


def test_line_framer_split_crlf() -> None:
    framer = LineFramer()
    assert framer.feed(b"pos?\r") == [b"pos?"]
    assert framer.feed(b"\npcount") == []
    assert framer.feed(b"?\n\r") == [b"pcount?", b""]


def test_reconnect_after_client_closes(sim: FW102CSimulator) -> None:
    with open_port(sim) as ser:
        assert ask(ser, b"pos=5") == b"pos=5\r> "
    with open_port(sim) as ser:
        assert ask(ser, b"pos?") == b"pos?\r5\r> "


# -- timing -----------------------------------------------------------------------------------


def test_move_time_is_shortest_way_round() -> None:
    handler = FW102CHandler(12)
    assert handler.move_time(1, 2) == pytest.approx(0.45)
    assert handler.move_time(1, 12) == pytest.approx(0.45)
    assert handler.move_time(12, 1) == pytest.approx(0.45)
    assert handler.move_time(1, 7) == pytest.approx(0.25 + 6 * 0.2)
    assert handler.move_time(2, 10) == pytest.approx(0.25 + 4 * 0.2)
    assert handler.move_time(3, 3) == 0.0
    assert handler.move_time(1, 2, speed=0) == pytest.approx(0.9)
    assert FW102CHandler(6).move_time(1, 4) == pytest.approx(0.25 + 3 * 0.2)
    assert FW102CHandler(12, time_scale=0.5).move_time(1, 2) == pytest.approx(0.225)


def test_handler_yields_echo_wait_prompt() -> None:
    moves: list[int] = []
    handler = FW102CHandler(12, on_move=moves.append)
    assert list(handler.handle("pos=3")) == [b"pos=3\r", Wait(pytest.approx(0.65)), b"> "]
    assert moves == [3]


@pytest.mark.parametrize("target", [2, 12])
def test_real_time_move_one_slot(target: int) -> None:
    """1 -> 2 and 1 -> 12 are both one slot (0.45 s); the echo comes first, the prompt last."""
    with FW102CSimulator(time_scale=1.0) as sim, open_port(sim) as ser:
        command = b"pos=%d" % target
        start = time.monotonic()
        ser.write(command + b"\r")
        echo = ser.read_until(b"\r")
        echoed = time.monotonic() - start
        rest = read_reply(ser)
        elapsed = time.monotonic() - start
        assert echo + rest == command + b"\r> "
        assert 0.4 <= elapsed < 1.5
        assert echoed < elapsed - 0.2
        assert sim.position == target


def test_time_scale_zero_is_fast(sim: FW102CSimulator, ser: serial.Serial) -> None:
    start = time.monotonic()
    assert ask(ser, b"pos=7") == b"pos=7\r> "  # the longest move: 6 slots
    assert ask(ser, b"speed=0") == b"speed=0\r> "
    assert ask(ser, b"pos=1") == b"pos=1\r> "
    assert time.monotonic() - start < 0.5


# -- on_move ----------------------------------------------------------------------------------


def test_on_move_called_with_new_position_before_prompt() -> None:
    moves: list[int] = []
    with FW102CSimulator(time_scale=0, on_move=moves.append) as sim, open_port(sim) as ser:
        assert ask(ser, b"pos=3") == b"pos=3\r> "
        assert moves == [3]
        assert ask(ser, b"pos=13") == b"pos=13\rCommand error CMD_ARG_INVALID\r> "
        assert ask(ser, b"pos=11") == b"pos=11\r> "
        assert moves == [3, 11]
        seen: list[int] = []
        sim.on_move = seen.append
        assert ask(ser, b"pos=2") == b"pos=2\r> "
        assert (moves, seen) == ([3, 11], [2])


# -- faults -----------------------------------------------------------------------------------


def test_no_reply_swallows_command(sim: FW102CSimulator, ser: serial.Serial) -> None:
    sim.inject_fault("no_reply")
    ser.write(b"pos=4\r")
    ser.timeout = 0.3
    assert ser.read(64) == b""
    ser.timeout = TIMEOUT
    assert sim.pending_faults() == {}
    assert ask(ser, b"pos?") == b"pos?\r1\r> "  # swallowed: not executed either
    assert ask(ser, b"pos=4") == b"pos=4\r> "
    assert sim.position == 4


def test_no_reply_count(sim: FW102CSimulator, ser: serial.Serial) -> None:
    sim.inject_fault("no_reply", count=2)
    ser.write(b"pos?\rpcount?\r")
    ser.timeout = 0.3
    assert ser.read(64) == b""
    ser.timeout = TIMEOUT
    assert ask(ser, b"pcount?") == b"pcount?\r12\r> "


def test_garbled_reply_then_resync(sim: FW102CSimulator, ser: serial.Serial) -> None:
    correct = b"*idn?\r" + IDN + b"\r> "
    sim.inject_fault("garbled")
    garbled = ask(ser, b"*idn?")
    assert garbled != correct
    assert len(garbled) == len(correct)
    assert garbled.endswith(PROMPT)
    assert PROMPT not in garbled[:-2] and b"\r" not in garbled[:-2]
    assert ask(ser, b"*idn?") == correct


def test_garbled_still_executes_command(sim: FW102CSimulator, ser: serial.Serial) -> None:
    sim.inject_fault("garbled")
    assert ask(ser, b"pos=6") != b"pos=6\r> "
    assert ask(ser, b"pos?") == b"pos?\r6\r> "


def test_garbled_is_deterministic_given_seed() -> None:
    replies = []
    for _ in range(2):
        with FW102CSimulator(time_scale=0, seed=7) as sim, open_port(sim) as ser:
            sim.inject_fault("garbled", count=2)
            replies.append((ask(ser, b"pos?"), ask(ser, b"*idn?")))
    assert replies[0] == replies[1]
    assert replies[0][0] != b"pos?\r1\r> "


def test_stuck_move_keeps_old_position(sim: FW102CSimulator, ser: serial.Serial) -> None:
    moves: list[int] = []
    sim.on_move = moves.append
    assert ask(ser, b"pos=2") == b"pos=2\r> "
    sim.inject_fault("stuck")
    assert ask(ser, b"pos?") == b"pos?\r2\r> "  # queries do not consume it
    assert ask(ser, b"pos=0") == b"pos=0\rCommand error CMD_ARG_INVALID\r> "  # nor bad moves
    assert sim.pending_faults() == {"stuck": 1}
    assert ask(ser, b"pos=5") == b"pos=5\r> "
    assert ask(ser, b"pos?") == b"pos?\r2\r> "
    assert sim.position == 2
    assert moves == [2]
    assert ask(ser, b"pos=5") == b"pos=5\r> "
    assert ask(ser, b"pos?") == b"pos?\r5\r> "


def test_clear_faults(sim: FW102CSimulator, ser: serial.Serial) -> None:
    sim.inject_fault("garbled", count=3)
    sim.inject_fault("stuck")
    sim.inject_fault("stuck", count=2)
    assert sim.pending_faults() == {"garbled": 3, "stuck": 3}
    sim.clear_faults("stuck")
    assert sim.pending_faults() == {"garbled": 3}
    sim.clear_faults()
    assert sim.pending_faults() == {}
    assert ask(ser, b"pos=3") == b"pos=3\r> "
    assert ask(ser, b"pos?") == b"pos?\r3\r> "


@pytest.mark.parametrize(("kind", "count"), [("jammed", 1), ("garbled", 0), ("stuck", -2)])
def test_inject_fault_rejects_bad_arguments(sim: FW102CSimulator, kind: str, count: int) -> None:
    with pytest.raises(ConfigError):
        sim.inject_fault(kind, count)
    assert sim.fault_kinds == {"no_reply", "garbled", "stuck"}


# -- transcript -------------------------------------------------------------------------------


def test_transcript_records_exchange_and_faults(sim: FW102CSimulator, ser: serial.Serial) -> None:
    sim.clear_transcript()
    assert ask(ser, b"pos=2") == b"pos=2\r> "
    sim.inject_fault("stuck")
    assert ask(ser, b"pos=3") == b"pos=3\r> "
    events = [(e.direction, e.data) for e in sim.transcript()]
    assert events == [
        ("rx", b"pos=2"),
        ("tx", b"pos=2\r"),
        ("tx", b"> "),
        ("rx", b"pos=3"),
        ("tx", b"pos=3\r"),
        ("fault", b"stuck"),
        ("tx", b"> "),
    ]
    times = [e.time for e in sim.transcript()]
    assert times == sorted(times)


def test_transcript_is_bounded() -> None:
    with FW102CSimulator(time_scale=0, transcript_limit=5) as sim, open_port(sim) as ser:
        for _ in range(10):
            assert ask(ser, b"pos?") == b"pos?\r1\r> "
        transcript = sim.transcript()
        assert len(transcript) == 5
        assert (transcript[-1].direction, transcript[-1].data) == ("tx", b"> ")


# -- lifecycle --------------------------------------------------------------------------------


def test_stop_during_move_with_client_connected_is_prompt() -> None:
    moves: list[int] = []
    sim = FW102CSimulator(time_scale=1.0, on_move=moves.append).start()
    ser = open_port(sim, timeout=1.0)
    try:
        ser.write(b"pos=7\r")  # 6 slots: 1.45 s
        assert ser.read_until(b"\r") == b"pos=7\r"
        start = time.monotonic()
        sim.stop()
        assert time.monotonic() - start < 1.0
        assert not sim.running
        assert sim.position == 1  # the move was abandoned
        assert moves == []
        sim.stop()  # idempotent
    finally:
        start = time.monotonic()
        ser.close()
        assert time.monotonic() - start < 1.0


def test_stop_idle_with_client_connected() -> None:
    sim = FW102CSimulator(time_scale=0).start()
    with open_port(sim, timeout=0.5) as ser:
        assert ask(ser, b"pos?") == b"pos?\r1\r> "
        start = time.monotonic()
        sim.stop()
        assert time.monotonic() - start < 1.0
        # the pty is gone: the client fails at once instead of hanging
        with pytest.raises(serial.SerialException):
            ser.write(b"pos?\r")
        with pytest.raises(serial.SerialException):
            ser.read(1)


def test_lifecycle_errors() -> None:
    sim = FW102CSimulator()
    with pytest.raises(DeviceError):
        _ = sim.port
    assert sim.start() is sim
    assert sim.start() is sim  # already running: no-op
    assert sim.port.startswith("/dev/")
    assert sim.running
    sim.stop()
    sim.stop()
    with pytest.raises(DeviceError):
        sim.start()


def test_thread_failure_is_reported_by_stop() -> None:
    def broken(position: int) -> None:
        raise RuntimeError(f"camera exploded at {position}")

    sim = FW102CSimulator(time_scale=0, on_move=broken).start()
    with open_port(sim, timeout=0.5) as ser:
        ser.write(b"pos=2\r")
        deadline = time.monotonic() + TIMEOUT
        while sim.running and time.monotonic() < deadline:
            time.sleep(0.01)
    assert isinstance(sim.error, RuntimeError)
    with pytest.raises(DeviceError, match="camera exploded at 2"):
        sim.stop()
    sim.stop()  # reported once


@pytest.mark.parametrize(
    "kwargs",
    [
        {"positions": 8},
        {"position": 13},
        {"position": 0},
        {"speed": 2},
        {"time_scale": -1.0},
        {"move_per_slot": -0.1},
        {"transcript_limit": -1},
    ],
)
def test_constructor_rejects_bad_options(kwargs: dict[str, object]) -> None:
    with pytest.raises(ConfigError):
        FW102CSimulator(**kwargs)  # type: ignore[arg-type]


def test_position_is_readable_from_other_threads_during_moves() -> None:
    with FW102CSimulator(time_scale=0) as sim, open_port(sim) as ser:
        seen: set[int] = set()
        done = threading.Event()

        def poll() -> None:
            while not done.is_set():
                seen.add(sim.position)

        poller = threading.Thread(target=poll)
        poller.start()
        try:
            for target in (4, 8, 12):
                assert ask(ser, b"pos=%d" % target) == b"pos=%d\r> " % target
        finally:
            done.set()
            poller.join()
        assert seen <= {1, 4, 8, 12}
        assert sim.position == 12
