"""Tests of the FW102C filter-wheel driver against the FW102C simulator on a pty."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import serial

from labkit.devices.fw102c import FW102C, MalformedReply, identify_fw102c, parse_reply
from labkit.devices.slider import FilterSlider
from labkit.errors import ConfigError, DeviceError
from labkit.sim.fw102c import FW102CSimulator

IDN = "THORLABS FW102C/FW212C Filter Wheel version 1.07"
RETRIES = 3


def open_wheel(port: str, *, slots: int | None = None) -> FW102C:
    """The driver with short timeouts (the simulator answers within milliseconds)."""
    return FW102C(port, slots=slots, timeout_s=0.3, move_timeout_s=0.4, retries=RETRIES)


@pytest.fixture
def moves() -> list[int]:
    return []


@pytest.fixture
def sim(moves: list[int]) -> Iterator[FW102CSimulator]:
    with FW102CSimulator(time_scale=0, seed=99, on_move=moves.append) as simulator:
        yield simulator


@pytest.fixture
def wheel(sim: FW102CSimulator) -> Iterator[FW102C]:
    with open_wheel(sim.port) as driver:
        sim.clear_transcript()
        yield driver


def commands_sent(sim: FW102CSimulator) -> list[bytes]:
    return [entry.data for entry in sim.transcript() if entry.direction == "rx"]


def last_tx(sim: FW102CSimulator) -> bytes:
    return [entry.data for entry in sim.transcript() if entry.direction == "tx"][-1]


# -- reply parsing ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("command", "reply", "lines"),
    [
        ("pos=3", b"pos=3\r> ", []),
        ("pos?", b"pos?\r3\r> ", ["3"]),
        ("*idn?", b"*idn?\r" + IDN.encode() + b"\r> ", [IDN]),
        ("pos=13", b"pos=13\rCommand error CMD_ARG_INVALID\r> ", ["Command error CMD_ARG_INVALID"]),
    ],
)
def test_parse_reply_known_answers(command: str, reply: bytes, lines: list[str]) -> None:
    assert parse_reply(command, reply) == lines


@pytest.mark.parametrize(
    "reply",
    [b"", b"pos?\r3\r", b"pos=3\r3\r> ", b"pOs?\r3\r> ", b"pos?\r3> ", b"pos?\r\x833\r> "],
)
def test_parse_reply_rejects_malformed(reply: bytes) -> None:
    with pytest.raises(MalformedReply):
        parse_reply("pos?", reply)


# -- opening ----------------------------------------------------------------------------------


def test_identity_and_slot_count(sim: FW102CSimulator, wheel: FW102C) -> None:
    assert wheel.identity == IDN
    assert wheel.slot_count == 12
    assert wheel.port == sim.port
    assert wheel.driver == "fw102c"
    assert isinstance(wheel, FilterSlider)


def test_six_position_wheel() -> None:
    with FW102CSimulator(6, time_scale=0) as sim, open_wheel(sim.port) as wheel:
        assert wheel.slot_count == 6


def test_slots_more_than_the_wheel_has_is_refused() -> None:
    with FW102CSimulator(6, time_scale=0) as sim:
        with open_wheel(sim.port, slots=6) as wheel:
            assert wheel.slot_count == 6
        with pytest.raises(DeviceError, match=r"slot 8 is needed but the wheel has 6 positions"):
            open_wheel(sim.port, slots=8)


def test_missing_port_names_it() -> None:
    with pytest.raises(DeviceError, match=r"serial port /dev/ttyLABKIT9 does not exist"):
        FW102C("/dev/ttyLABKIT9")


def test_silent_device_names_port_and_command() -> None:
    with FW102CSimulator(time_scale=0) as sim:
        sim.inject_fault("no_reply", count=10)
        with pytest.raises(DeviceError) as caught:
            open_wheel(sim.port)
    message = str(caught.value)
    assert sim.port in message
    assert "`*idn?` — no valid reply after 3 attempts (last reply none within 0.3 s)" in message


def test_port_is_exclusive_until_closed(sim: FW102CSimulator) -> None:
    first = open_wheel(sim.port)
    with pytest.raises(DeviceError, match="in use by another program"):
        open_wheel(sim.port)
    first.close()
    first.close()  # idempotent
    with open_wheel(sim.port) as second:
        assert second.position() == 1
    with pytest.raises(DeviceError, match="is closed"):
        first.position()


@pytest.mark.parametrize(
    "kwargs", [{"retries": 0}, {"timeout_s": 0.0}, {"move_timeout_s": -1.0}, {"slots": 2.5}]
)
def test_bad_options_are_config_errors(sim: FW102CSimulator, kwargs: dict[str, object]) -> None:
    with pytest.raises(ConfigError):
        FW102C(sim.port, **kwargs)  # type: ignore[arg-type]


# -- moving -----------------------------------------------------------------------------------


def test_move_then_read_back(sim: FW102CSimulator, wheel: FW102C, moves: list[int]) -> None:
    wheel.move(5)
    assert sim.position == 5
    assert moves == [5]
    assert wheel.position() == 5
    assert commands_sent(sim) == [b"pos=5", b"pos?", b"pos?"]
    wheel.move(5)  # already there: still commanded and verified
    wheel.move(12)
    assert moves == [5, 5, 12]
    assert sim.position == 12


@pytest.mark.parametrize(
    ("kind", "expected_moves"),
    [
        ("no_reply", [7]),  # the first pos=7 was swallowed
        ("garbled", [7, 7]),  # the first pos=7 was executed, its reply corrupted
        ("stuck", [7]),  # the first pos=7 left the wheel where it was
    ],
)
def test_single_fault_is_retried(
    sim: FW102CSimulator, wheel: FW102C, moves: list[int], kind: str, expected_moves: list[int]
) -> None:
    sim.inject_fault(kind)
    wheel.move(7)
    assert sim.position == 7
    assert moves == expected_moves
    assert sim.pending_faults() == {}
    assert commands_sent(sim).count(b"pos=7") == 2


def test_garbled_query_is_retried(sim: FW102CSimulator, wheel: FW102C) -> None:
    sim.inject_fault("garbled")
    assert wheel.position() == 1
    assert commands_sent(sim) == [b"pos?", b"pos?"]


def test_persistent_stuck_names_port_command_and_last_reply(
    sim: FW102CSimulator, wheel: FW102C
) -> None:
    sim.inject_fault("stuck", count=RETRIES + 1)
    with pytest.raises(DeviceError) as caught:
        wheel.move(3)
    assert str(caught.value) == (
        f"filter slider on {sim.port}: `pos=3` — position reads back 1 after 3 attempts "
        "(last reply 'pos?\\r1\\r> '); check that the wheel is not blocked"
    )
    assert commands_sent(sim).count(b"pos=3") == RETRIES


def test_persistent_garbled_names_last_reply(sim: FW102CSimulator, wheel: FW102C) -> None:
    sim.inject_fault("garbled", count=RETRIES + 1)
    with pytest.raises(DeviceError) as caught:
        wheel.move(4)
    message = str(caught.value)
    assert sim.port in message
    assert "`pos=4` — no valid reply after 3 attempts" in message
    assert repr(last_tx(sim).decode("latin-1")) in message
    assert "\n" not in message


def test_persistent_no_reply(sim: FW102CSimulator, wheel: FW102C) -> None:
    sim.inject_fault("no_reply", count=RETRIES + 1)
    with pytest.raises(DeviceError) as caught:
        wheel.move(2)
    assert f"filter slider on {sim.port}: `pos=2` — no valid reply after 3 attempts" in str(
        caught.value
    )
    assert "last reply none within 0.4 s" in str(caught.value)
    assert sim.position == 1


@pytest.mark.parametrize("slot", [0, 13, -1, True, "3", 2.0])
def test_slot_out_of_range_sends_nothing(
    sim: FW102CSimulator, wheel: FW102C, moves: list[int], slot: object
) -> None:
    with pytest.raises(DeviceError, match=sim.port):
        wheel.move(slot)  # type: ignore[arg-type]
    assert sim.transcript() == []
    assert moves == []


def test_command_error_is_not_retried(sim: FW102CSimulator, wheel: FW102C) -> None:
    # another program turns the wheel into a 6-position one behind the driver's back
    with serial.Serial(sim.port, 115200, timeout=1.0) as other:
        other.write(b"pcount=6\r")
        assert other.read_until(b"> ") == b"pcount=6\r> "
    sim.clear_transcript()
    with pytest.raises(DeviceError, match=r"`pos=9` — the wheel answered 'Command error "):
        wheel.move(9)
    assert commands_sent(sim) == [b"pos=9"]


# -- discovery helper -------------------------------------------------------------------------


def test_identify_fw102c_on_the_simulator(sim: FW102CSimulator) -> None:
    with serial.Serial(sim.port, 115200, timeout=0.3) as ser:
        assert identify_fw102c(ser) == IDN
    assert sim.position == 1


def test_identify_fw102c_on_a_silent_wheel(sim: FW102CSimulator) -> None:
    sim.inject_fault("no_reply", count=2)
    with serial.Serial(sim.port, 115200, timeout=0.2) as ser:
        assert identify_fw102c(ser) is None
