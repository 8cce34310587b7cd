"""Tests of the Elliptec ELL6/ELL9 slider simulator, through a real pyserial port on its pty."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import serial

from labkit.errors import ConfigError
from labkit.sim.elliptec import ElliptecFramer, ElliptecHandler, ElliptecSimulator

TIMEOUT = 3.0  # s; generous: a reply normally arrives within milliseconds
SILENCE = 0.2  # s; how long to listen to conclude that nothing comes
#: type 09, serial 11200456, 2019, firmware 17, hardware 01, travel 0x1F, 0 pulses per unit
ELL9_INFO = b"0IN091120045620191701001F00000000\r\n"


def open_port(sim: ElliptecSimulator, timeout: float = TIMEOUT) -> serial.Serial:
    return serial.Serial(sim.port, 9600, timeout=timeout)


def ask(ser: serial.Serial, command: bytes) -> bytes:
    """Send one command (no terminator) and read one CR LF terminated reply."""
    ser.write(command)
    reply = ser.read_until(b"\r\n")
    assert reply.endswith(b"\r\n"), f"no reply within {ser.timeout} s, got {reply!r}"
    return reply


def silent(ser: serial.Serial) -> bool:
    ser.timeout = SILENCE
    try:
        return ser.read(64) == b""
    finally:
        ser.timeout = TIMEOUT


@pytest.fixture
def sim() -> Iterator[ElliptecSimulator]:
    with ElliptecSimulator("ELL9", time_scale=0, seed=1234) as simulator:
        yield simulator


@pytest.fixture
def ser(sim: ElliptecSimulator) -> Iterator[serial.Serial]:
    with open_port(sim) as port:
        yield port


# -- protocol ---------------------------------------------------------------------------------


def test_info_reply_exact_bytes(ser: serial.Serial) -> None:
    assert ask(ser, b"0in") == ELL9_INFO


def test_ell6_info_and_slots() -> None:
    with ElliptecSimulator("ELL6", time_scale=0, serial_number="10600051", year=2017) as sim:
        assert sim.slot_count == 2
        assert sim.slot_positions == (0, 31)
        with open_port(sim) as ser:
            assert ask(ser, b"0in") == b"0IN061060005120171701001F00000000\r\n"
            assert ask(ser, b"0ma0000001F") == b"0PO0000001F\r\n"
            assert ask(ser, b"0fw") == b"0GS0C\r\n"  # already at the far end
        assert sim.position == 2


def test_status_and_position(sim: ElliptecSimulator, ser: serial.Serial) -> None:
    assert ask(ser, b"0gs") == b"0GS00\r\n"
    assert ask(ser, b"0gp") == b"0PO00000000\r\n"
    assert (sim.position, sim.pulses) == (1, 0)


@pytest.mark.parametrize(
    ("data", "slot", "reply"),
    [
        (b"0000003E", 3, b"0PO0000003E\r\n"),
        (b"0000005D", 4, b"0PO0000005D\r\n"),
        (b"00000021", 2, b"0PO0000001F\r\n"),  # 33 pulses: snaps to the nearest detent, 31
        (b"FFFFFFF6", 1, b"0PO00000000\r\n"),  # -10 pulses: still slot 1
        (b"0000002d", 2, b"0PO0000001F\r\n"),  # lower-case hex is accepted
    ],
)
def test_move_absolute(
    sim: ElliptecSimulator, ser: serial.Serial, data: bytes, slot: int, reply: bytes
) -> None:
    assert ask(ser, b"0ma" + data) == reply
    assert sim.position == slot
    assert ask(ser, b"0gp") == reply


@pytest.mark.parametrize("data", [b"0000007D", b"FFFFFFF0", b"7FFFFFFF"])
def test_move_beyond_travel_is_out_of_range(
    sim: ElliptecSimulator, ser: serial.Serial, data: bytes
) -> None:
    assert ask(ser, b"0ma" + data) == b"0GS0C\r\n"  # 125, -16, 2**31 - 1 pulses
    assert sim.position == 1


def test_relative_forward_backward_and_home(sim: ElliptecSimulator, ser: serial.Serial) -> None:
    assert ask(ser, b"0mr0000001F") == b"0PO0000001F\r\n"
    assert ask(ser, b"0fw") == b"0PO0000003E\r\n"
    assert ask(ser, b"0fw") == b"0PO0000005D\r\n"
    assert ask(ser, b"0fw") == b"0GS0C\r\n"
    assert ask(ser, b"0mrFFFFFFE1") == b"0PO0000003E\r\n"  # -31
    assert ask(ser, b"0bw") == b"0PO0000001F\r\n"
    assert ask(ser, b"0ho0") == b"0PO00000000\r\n"
    assert ask(ser, b"0bw") == b"0GS0C\r\n"
    assert ask(ser, b"0ho2") == b"0GS04\r\n"
    assert sim.position == 1


@pytest.mark.parametrize("command", [b"0zz", b"0GS", b"0maXYZ12345", b"0st"])
def test_unknown_or_malformed_command(
    sim: ElliptecSimulator, ser: serial.Serial, command: bytes
) -> None:
    assert ask(ser, command) == b"0GS03\r\n"
    assert sim.position == 1
    assert ask(ser, b"0gs") == b"0GS00\r\n"  # the framing is intact


def test_other_address_gets_no_reply(sim: ElliptecSimulator, ser: serial.Serial) -> None:
    ser.write(b"1in")
    ser.write(b"2ma0000003E")
    assert silent(ser)
    assert sim.position == 1  # not executed either
    assert ask(ser, b"0gs") == b"0GS00\r\n"


def test_address_other_than_zero() -> None:
    with ElliptecSimulator("ELL9", address="b", time_scale=0) as sim, open_port(sim) as ser:
        assert sim.address == "B"
        assert ask(ser, b"Bgp") == b"BPO00000000\r\n"
        assert ask(ser, b"Bin").startswith(b"BIN09")
        ser.write(b"0in")
        assert silent(ser)


def test_framing_by_length_across_writes_and_junk(ser: serial.Serial) -> None:
    ser.write(b"0m")
    ser.write(b"a0000")
    assert silent(ser)  # incomplete: waits for the rest
    ser.write(b"003E")
    assert ser.read_until(b"\r\n") == b"0PO0000003E\r\n"
    ser.write(b"\r\n0gs\r0gp\n")  # CR/LF between commands are ignored
    assert ser.read_until(b"\r\n") == b"0GS00\r\n"
    assert ser.read_until(b"\r\n") == b"0PO0000003E\r\n"
    assert silent(ser)


def test_framer_known_answers() -> None:
    framer = ElliptecFramer()
    assert framer.feed(b"0gs0gp0ma000") == [b"0gs", b"0gp"]
    assert framer.feed(b"0003E\r\n1ho") == [b"0ma0000003E"]
    assert framer.feed(b"0xx*0in") == [b"1ho0", b"0in"]  # x, x and * cannot start a command
    assert framer.feed(b"zz0") == []
    assert framer.feed(b"zz") == [b"0zz"]


# -- timing -----------------------------------------------------------------------------------


def test_move_time_formula() -> None:
    handler = ElliptecHandler("ELL9")
    assert handler.move_time(1, 2) == pytest.approx(0.45)
    assert handler.move_time(4, 1) == pytest.approx(0.15 + 3 * 0.3)
    assert handler.move_time(2, 2) == 0.0
    assert ElliptecHandler("ELL9", time_scale=0.5).move_time(1, 2) == pytest.approx(0.225)


def test_real_time_move_takes_the_move_time() -> None:
    with ElliptecSimulator("ELL9", time_scale=1.0) as sim, open_port(sim) as ser:
        start = time.monotonic()
        assert ask(ser, b"0ma0000001F") == b"0PO0000001F\r\n"
        elapsed = time.monotonic() - start
        assert 0.4 <= elapsed < 1.5
        start = time.monotonic()
        assert ask(ser, b"0gp") == b"0PO0000001F\r\n"  # a query does not wait
        assert time.monotonic() - start < 0.3


def test_time_scale_zero_is_fast(ser: serial.Serial) -> None:
    start = time.monotonic()
    for data in (b"0000005D", b"00000000", b"0000005D"):
        ask(ser, b"0ma" + data)
    assert time.monotonic() - start < 0.5


# -- on_move ----------------------------------------------------------------------------------


def test_on_move_called_with_new_slot_before_reply() -> None:
    moves: list[int] = []
    with ElliptecSimulator(time_scale=0, on_move=moves.append) as sim, open_port(sim) as ser:
        assert ask(ser, b"0ma0000003E") == b"0PO0000003E\r\n"
        assert moves == [3]
        assert ask(ser, b"0ma0000007D") == b"0GS0C\r\n"
        assert ask(ser, b"0ho1") == b"0PO00000000\r\n"
        assert moves == [3, 1]
        seen: list[int] = []
        sim.on_move = seen.append
        assert ask(ser, b"0fw") == b"0PO0000001F\r\n"
        assert (moves, seen) == ([3, 1], [2])


# -- faults -----------------------------------------------------------------------------------


def test_no_reply_swallows_command(sim: ElliptecSimulator, ser: serial.Serial) -> None:
    sim.inject_fault("no_reply")
    ser.write(b"0ma0000003E")
    assert silent(ser)
    assert sim.position == 1
    assert sim.pending_faults() == {}
    assert ask(ser, b"0ma0000003E") == b"0PO0000003E\r\n"


def test_garbled_reply_keeps_length_and_terminator(
    sim: ElliptecSimulator, ser: serial.Serial
) -> None:
    sim.inject_fault("garbled")
    garbled = ask(ser, b"0ma0000005D")
    assert garbled != b"0PO0000005D\r\n"
    assert len(garbled) == len(b"0PO0000005D\r\n")
    assert b"\r" not in garbled[:-2] and b"\n" not in garbled[:-2]
    assert garbled[:1] != b"0"  # every byte is corrupted, the address included
    assert sim.position == 4  # the command was executed
    assert ask(ser, b"0gp") == b"0PO0000005D\r\n"


def test_garbled_is_deterministic_given_seed() -> None:
    replies = []
    for _ in range(2):
        with ElliptecSimulator(time_scale=0, seed=7) as sim, open_port(sim) as ser:
            sim.inject_fault("garbled", count=2)
            replies.append((ask(ser, b"0gp"), ask(ser, b"0in")))
    assert replies[0] == replies[1]
    assert replies[0][0] != b"0PO00000000\r\n"


def test_stuck_move_replies_old_position(sim: ElliptecSimulator, ser: serial.Serial) -> None:
    moves: list[int] = []
    sim.on_move = moves.append
    assert ask(ser, b"0ma0000001F") == b"0PO0000001F\r\n"
    sim.inject_fault("stuck")
    assert ask(ser, b"0gp") == b"0PO0000001F\r\n"  # queries do not consume it
    assert ask(ser, b"0ma0000007D") == b"0GS0C\r\n"  # nor invalid moves
    assert sim.pending_faults() == {"stuck": 1}
    assert ask(ser, b"0ma0000005D") == b"0PO0000001F\r\n"
    assert sim.position == 2
    assert moves == [2]
    assert ask(ser, b"0ma0000005D") == b"0PO0000005D\r\n"
    assert moves == [2, 4]


def test_busy_and_mechanical_timeout_statuses(sim: ElliptecSimulator, ser: serial.Serial) -> None:
    sim.inject_fault("busy")
    assert ask(ser, b"0fw") == b"0GS09\r\n"
    sim.inject_fault("mechanical_timeout")
    assert ask(ser, b"0ma0000003E") == b"0GS02\r\n"
    assert sim.position == 1
    assert ask(ser, b"0ma0000003E") == b"0PO0000003E\r\n"


def test_transcript_records_commands_replies_and_faults(
    sim: ElliptecSimulator, ser: serial.Serial
) -> None:
    sim.clear_transcript()
    assert ask(ser, b"0ma0000001F") == b"0PO0000001F\r\n"
    sim.inject_fault("stuck")
    assert ask(ser, b"0fw") == b"0PO0000001F\r\n"
    events = [(e.direction, e.data) for e in sim.transcript()]
    assert events == [
        ("rx", b"0ma0000001F"),
        ("tx", b"0PO0000001F\r\n"),
        ("rx", b"0fw"),
        ("fault", b"stuck"),
        ("tx", b"0PO0000001F\r\n"),
    ]


@pytest.mark.parametrize(("kind", "count"), [("jammed", 1), ("stuck", 0), ("busy", -1)])
def test_inject_fault_rejects_bad_arguments(sim: ElliptecSimulator, kind: str, count: int) -> None:
    with pytest.raises(ConfigError):
        sim.inject_fault(kind, count)
    assert sim.fault_kinds == {"no_reply", "garbled", "stuck", "busy", "mechanical_timeout"}


# -- construction -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [
        {"model": "ELL14"},
        {"address": 16},
        {"address": "G"},
        {"slot": 5},
        {"slot": 0},
        {"slot_positions": (0, 31)},
        {"slot_positions": (0, 31, 31, 62)},
        {"serial_number": "123"},
        {"year": 10000},
        {"time_scale": -1.0},
        {"move_per_slot": -0.1},
    ],
)
def test_constructor_rejects_bad_options(kwargs: dict[str, object]) -> None:
    with pytest.raises(ConfigError):
        ElliptecSimulator(**kwargs)  # type: ignore[arg-type]


def test_custom_slot_positions_and_initial_slot() -> None:
    with ElliptecSimulator(slot=3, slot_positions=(0, 32, 64, 96), time_scale=0) as sim:
        assert (sim.position, sim.pulses) == (3, 64)
        with open_port(sim) as ser:
            assert ask(ser, b"0gp") == b"0PO00000040\r\n"
            assert ask(ser, b"0ma0000001F") == b"0PO00000020\r\n"  # 31 -> detent 32
        assert sim.position == 2
