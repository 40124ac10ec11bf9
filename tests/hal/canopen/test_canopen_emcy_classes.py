"""EMCY errors and warnings (hal/canopen/cia301/emcy.py, the master's use of them; D154).

An EMCY whose error register says no error is present, or that reports the drive's own CAN
controller state (0x8110, 0x8120, 0x8140), is a warning: logged and counted, the drive keeps its
torque. Any other is an error: the master shows the drive in FAULT and gives it no torque until
an error reset (0x0000), its statusword leaving FAULT, or the operator's fault reset. The drive's
statusword stays the authority: a drive that shows FAULT is in FAULT whatever its EMCY said.
"""

from __future__ import annotations

import itertools
import struct
from collections.abc import Iterator

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hal.canopen.bus import Frame
from hal.canopen.cia301.emcy import (
    COMMUNICATION_WARNINGS,
    EmcyClass,
    EmcyMessage,
    classify_emcy,
    emcy_frame_data,
    parse_emcy,
)
from hal.canopen.cia402.statemachine import PowerState, statusword_of
from hal.canopen.master import CanMaster, MasterSettings
from hal.canopen.profile import resolve_profiles
from hal.config import hal_config
from hal.interface import DriveState
from tests.hal.canopen.test_canopen_master import Clock, ScriptedFrames

NODES = (1, 2, 3, 4)
PERIOD_S = 0.002
_CHANNELS = itertools.count()


@pytest.mark.parametrize(
    ("code", "register", "expected"),
    [
        (0x8120, 0x11, EmcyClass.WARNING),  # CAN in error passive mode: the drive's controller, it operates on
        (0x8110, 0x11, EmcyClass.WARNING),  # CAN overrun: objects lost (the master's watchdogs judge the data)
        (0x8140, 0x11, EmcyClass.WARNING),  # recovered from bus off
        (0x8130, 0x11, EmcyClass.ERROR),  # heartbeat lost: the drive reacted by itself (0x6007)
        (0x8250, 0x11, EmcyClass.ERROR),  # its RPDO deadline: it stopped by itself
        (0x2310, 0x03, EmcyClass.ERROR),  # continuous overcurrent
        (0x4210, 0x09, EmcyClass.ERROR),  # excess temperature, device
        (0x3210, 0x05, EmcyClass.ERROR),  # DC link overvoltage
        (0xFF00, 0x81, EmcyClass.ERROR),  # manufacturer specific, an error present
        (0xFF00, 0x80, EmcyClass.WARNING),  # manufacturer specific, the register says no error is present
        (0x4210, 0x08, EmcyClass.WARNING),  # a temperature warning: the class bit without the generic one
        (0x2310, 0x00, EmcyClass.WARNING),  # no error present
        (0x0000, 0x00, EmcyClass.RESET),
        (0x0000, 0x05, EmcyClass.RESET),  # one error gone, the register shows others: still a reset of that one
    ],
)
def test_the_codes_of_the_standard_classify_as_decided(code: int, register: int, expected: EmcyClass) -> None:
    assert classify_emcy(parse_emcy(emcy_frame_data(code, register))) is expected


@given(code=st.integers(0, 0xFFFF), register=st.integers(0, 0xFF), length=st.integers(0, 8))
def test_an_emcy_is_a_warning_only_when_it_says_so(code: int, register: int, length: int) -> None:
    """Never a warning without words for it: a frame too short for the register is an error unless its code
    is one of the communication warnings; a register with the generic bit set is an error unless its code is."""
    message = parse_emcy(emcy_frame_data(code, register, b"", length))
    kind = classify_emcy(message)
    if length < 2:
        assert kind is EmcyClass.ERROR  # no whole code: an error of an unknown kind
    elif code == 0:
        assert kind is EmcyClass.RESET
    elif code in COMMUNICATION_WARNINGS:
        assert kind is EmcyClass.WARNING
    elif length == 2 or register & 0x01:
        assert kind is EmcyClass.ERROR
    else:
        assert kind is EmcyClass.WARNING


# --- the master: what a drive shows after a sequence of EMCYs ------------------------------------------------


@pytest.fixture(scope="module")
def profiles() -> object:
    return resolve_profiles(hal_config("can-sim", node_ids=list(NODES)), 289.0)


def _master(profiles: object) -> tuple[CanMaster, ScriptedFrames, Clock, can.BusABC]:
    bus = can.Bus(interface="virtual", channel=f"emcy-test-{next(_CHANNELS)}")
    source, clock = ScriptedFrames(), Clock()
    master = CanMaster(bus, source, profiles, MasterSettings(node_ids=NODES, period_s=PERIOD_S), clock)  # type: ignore[arg-type]
    master.heartbeats.start(0.0)
    return master, source, clock, bus


def _cycle(master: CanMaster, source: ScriptedFrames, clock: Clock, extra: list[Frame], fault: bool = False) -> None:
    """A cycle whose TPDOs show every drive enabled (joint 2 in FAULT if ``fault``), with ``extra`` frames."""
    master.send_cycle(True, np.full(4, 1.0))
    clock.t_s += PERIOD_S
    t = clock.t_s - PERIOD_S + 1e-4
    frames = []
    for node in NODES:
        state = PowerState.FAULT if fault and node == 2 else PowerState.OPERATION_ENABLED
        frames += [
            (0x180 + node, struct.pack("<Hi", statusword_of(state), 0), t),
            (0x280 + node, struct.pack("<ih", 0, 0), t),
            (0x700 + node, b"\x05", t),
        ]
    source.queued = frames + extra
    master.receive()


def _emcy(code: int, register: int) -> Frame:
    return (0x082, emcy_frame_data(code, register), 0.0)


#: One step of a sequence: an EMCY of node 2 (code, register), the operator's fault reset, or a spell in FAULT.
steps = st.one_of(
    st.tuples(st.just("emcy"), st.sampled_from([0x0000, 0x8120, 0x8110, 0x2310, 0x4210, 0xFF00]), st.sampled_from([0x00, 0x01, 0x11, 0x80, 0x81])),
    st.tuples(st.just("reset"), st.just(0), st.just(0)),
    st.tuples(st.just("fault"), st.just(0), st.just(0)),
)  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(st.lists(steps, min_size=1, max_size=12))
def test_an_emcy_error_holds_until_0x0000_a_fault_reset_or_the_drive_leaves_fault_and_a_warning_never(
    profiles: object, sequence: list[tuple[str, int, int]]
) -> None:
    master, source, clock, bus = _master(profiles)
    try:
        for _ in range(3):
            _cycle(master, source, clock, [])
        master.take_latched()
        error: int | None = None  # the model: the code of the error the master holds for drive 2
        for what, code, register in sequence:
            if what == "emcy":
                kind = classify_emcy(EmcyMessage(code, register, bytes(5), 8))
                _cycle(master, source, clock, [_emcy(code, register)])
                if kind is EmcyClass.RESET:
                    error = None
                elif kind is EmcyClass.ERROR:
                    error = code
            elif what == "reset":
                master.request_fault_reset()  # the drive shows no fault: the acknowledge ends the EMCY's error
                error = None
                _cycle(master, source, clock, [])
            else:  # a spell in FAULT and out of it (a fault reset in the drive): its errors are over
                _cycle(master, source, clock, [], fault=True)
                states, codes, _ = master.drive_states()
                assert states[1] is DriveState.FAULT  # the statusword is the authority
                _cycle(master, source, clock, [])
                error = None
            states, codes, _ = master.drive_states()
            latched = master.take_latched() or ""
            if error is None:
                assert states[1] is not DriveState.FAULT, (what, code, register)
                assert "drive 2: EMCY" not in latched
            else:
                assert (states[1], codes[1]) == (DriveState.FAULT, error)
            assert states[0] is DriveState.ENABLED  # the others untouched
    finally:
        bus.shutdown()


@pytest.fixture
def rig(profiles: object) -> Iterator[tuple[CanMaster, ScriptedFrames, Clock]]:
    master, source, clock, bus = _master(profiles)
    for _ in range(3):
        _cycle(master, source, clock, [])
    master.take_latched()
    yield master, source, clock
    bus.shutdown()


def test_a_warning_keeps_the_torque_and_is_counted_and_logged_once(
    rig: tuple[CanMaster, ScriptedFrames, Clock], capsys: pytest.CaptureFixture[str]
) -> None:
    from daror_runtime.logs import configure_logging, flush_logs

    master, source, clock = rig
    configure_logging("warning")
    for _ in range(3):
        _cycle(master, source, clock, [_emcy(0x8120, 0x11)])
    flush_logs()
    states, codes, _ = master.drive_states()
    assert (states[1], codes[1]) == (DriveState.ENABLED, 0)
    assert master.take_latched() is None
    assert master.emcy_warnings.report() == {"0x02 EMCY 0x8120 CAN in error passive mode, error register 0x11": 3}
    err = capsys.readouterr().err
    assert err.count("drive warning") == 1
    assert "drive 2: EMCY 0x8120 CAN in error passive mode" in err


def test_an_error_takes_the_drives_torque_until_its_error_reset(rig: tuple[CanMaster, ScriptedFrames, Clock]) -> None:
    master, source, clock = rig
    _cycle(master, source, clock, [_emcy(0x2310, 0x03)])
    states, codes, _ = master.drive_states()
    assert (states[1], codes[1]) == (DriveState.FAULT, 0x2310)
    assert "drive 2: EMCY 0x2310 current, error register 0x03" in (master.take_latched() or "")
    _cycle(master, source, clock, [])
    assert master.drives[1].controlword != master.drives[0].controlword  # no enable operation for it
    _cycle(master, source, clock, [_emcy(0x0000, 0x00)])
    states, codes, _ = master.drive_states()
    assert (states[1], codes[1]) == (DriveState.DISABLED, 0)  # the error is over; not yet commanded again
    _cycle(master, source, clock, [])
    assert master.drives[1].controlword == master.drives[0].controlword  # enable operation again
    states, codes, _ = master.drive_states()
    assert (states[1], codes[1]) == (DriveState.ENABLED, 0)
