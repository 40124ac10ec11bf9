"""The bus's own health (hal/canopen/health.py, hal/canopen/bus.py, hal/canopen/sim/bus.py): bus-off,
error-passive and error frames are faults with their cause, warnings are counted; frames carry the
interface's receive time.

Checked on what a bench would see: the error frames a socketcan driver sends (linux/can/error.h),
the state an interface reports, the frames that reach (or do not reach) the drives, the torque the
drives' power stages apply, and the exception the backend's read raises.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import time
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hal.canopen.backend import SimulatedCanHal
from hal.canopen.bus import ListenedFrames, ReceiveClock
from hal.canopen.health import (
    CAN_ERR_BUSOFF,
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_TX_PASSIVE,
    CAN_ERR_RESTARTED,
    BusHealth,
    ControllerState,
    decode_error_frame,
    error_frame_data,
    state_reader,
)
from hal.canopen.sim.bus import LineFaults, SimulationBus
from hal.config import hal_config
from hal.interface import Command, HalBusFaultError, HalFaultError, open_hal

A = ControllerState.ACTIVE
W = ControllerState.WARNING
P = ControllerState.PASSIVE
OFF = ControllerState.BUS_OFF
_CHANNELS = itertools.count()


def _frame(b1: int = 0, b2: int = 0, tx: int = 0, rx: int = 0) -> bytes:
    return bytes((0, b1, b2, 0, 0, 0, tx, rx))


# --- error frames, as a socketcan driver sends them -------------------------------------------------


@pytest.mark.parametrize(
    ("can_id", "data", "state", "events"),
    [
        (0x040, _frame(), OFF, ()),  # CAN_ERR_BUSOFF
        (0x004, _frame(0x20), P, ()),  # CAN_ERR_CRTL, TX passive
        (0x004, _frame(0x10), P, ()),  # RX passive
        (0x004, _frame(0x08), W, ()),  # TX warning
        (0x004, _frame(0x04), W, ()),  # RX warning
        (0x004, _frame(0x40), A, ()),  # back to error active (CAN_ERR_CRTL_ACTIVE)
        (0x008, _frame(0, 0x40), None, ("protocol error",)),  # CAN_ERR_PROT_ACTIVE: an error flag, no recovery
        (0x100, _frame(), A, ()),  # restarted after bus-off
        (0x020, _frame(), None, ("no acknowledge",)),  # nobody acknowledged: no state
        (0x088, _frame(0, 0x04), None, ("protocol error", "bus error")),  # a form error: counted
        (0x002, _frame(), None, ("lost arbitration",)),
        (0x004, _frame(0x01), None, ("rx overflow",)),
        (0x044, _frame(0x20), OFF, ()),  # bus-off wins over the passive flag in the same frame
    ],
)
def test_error_frames_decode_as_linux_can_error_h_says(
    can_id: int, data: bytes, state: ControllerState | None, events: tuple[str, ...]
) -> None:
    frame = decode_error_frame(can_id, data)
    assert frame.state is state
    assert frame.events == events
    assert frame.restarted == bool(can_id & 0x100)


def test_error_counters_are_read_when_the_frame_carries_them() -> None:
    with_counters = decode_error_frame(CAN_ERR_CRTL | 0x200, _frame(0x20, 0, 131, 7))
    assert (with_counters.tx_errors, with_counters.rx_errors) == (131, 7)
    without = decode_error_frame(CAN_ERR_CRTL, _frame(0x20, 0, 131, 7))
    assert (without.tx_errors, without.rx_errors) == (None, None)


@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_any_error_frame_decodes_and_bus_off_and_passive_are_never_missed(can_id: int, data: bytes) -> None:
    frame = decode_error_frame(can_id, data)
    flags = data[1] if len(data) > 1 else 0
    if can_id & CAN_ERR_BUSOFF:
        assert frame.state is OFF
    elif can_id & CAN_ERR_CRTL and flags & 0x30:
        assert frame.state is P
    else:
        assert frame.state in (None, A, W)


@given(st.sampled_from(list(ControllerState)), st.integers(0, 300), st.integers(0, 300))
def test_the_simulated_error_frames_read_back_as_their_state(state: ControllerState, tx: int, rx: int) -> None:
    can_id, data = error_frame_data(state, tx, rx)
    frame = decode_error_frame(can_id, data)
    assert frame.state is state
    assert (frame.tx_errors, frame.rx_errors) == (min(tx, 255), min(rx, 255))


# --- the master's view: what is a fault, once ---------------------------------------------------------

_RANK = {A: 0, W: 1, P: 2, OFF: 3}


@settings(max_examples=200)
@given(st.lists(st.tuples(st.sampled_from(["frame", "read"]), st.sampled_from([A, W, P, OFF])), max_size=30))
def test_a_fault_is_latched_exactly_when_the_controller_enters_passive_or_bus_off(
    steps: list[tuple[str, ControllerState]],
) -> None:
    """The state is the worse of the last error frame's and the last reading's; entering error-passive or
    bus-off latches one fault naming it, taken once; warnings and recoveries latch nothing."""
    read_now: list[ControllerState | None] = [None]
    health = BusHealth(lambda: read_now[0])
    last = {"frame": A, "read": A}
    state = A
    for n, (source, new) in enumerate(steps):
        frames: list[tuple[int, bytes]] = []
        if source == "frame":
            frames = [error_frame_data(new)]
        read_now[0] = new if source == "read" else None  # None: the interface names no state this tick
        last[source] = new
        health.check(frames, float(n))
        expected = max(last.values(), key=_RANK.__getitem__)
        assert health.state is expected
        fault = health.take_fault()
        if expected is not state and expected in (P, OFF):
            assert fault is not None
            assert fault.startswith(f"CAN bus: {expected.value} (")
        else:
            assert fault is None
        assert health.take_fault() is None  # taken once
        state = expected
        assert health.faulted == (state in (P, OFF))


def test_acknowledging_while_the_bus_is_still_faulted_raises_it_again() -> None:
    health = BusHealth(None)
    health.check([error_frame_data(P, 128)], 1.0)
    assert health.take_fault() == (
        "CAN bus: error-passive (the controller counts more than 127 errors: it may no longer signal the "
        "errors it sees and waits before every frame it sends; commands are late or lost; error counters tx 128, rx 0)"
    )
    health.on_fault_reset()
    again = health.take_fault()
    assert again is not None
    assert again.startswith("CAN bus: error-passive")
    assert again.endswith("since t = 1.000 s")
    health.check([error_frame_data(A)], 2.0)
    health.on_fault_reset()
    assert health.take_fault() is None  # recovered: the acknowledge stands
    assert health.report()["controller_states_entered"] == {"error-passive": 1, "error-active": 1}


def test_a_bus_that_failed_during_start_up_is_raised_only_if_it_still_fails() -> None:
    """A master that talks before the drives are powered goes error-passive until they acknowledge."""
    recovered = BusHealth(None)
    recovered.check([error_frame_data(P, 128)], 0.01)
    recovered.check([error_frame_data(A)], 0.2)
    recovered.settle()
    assert recovered.take_fault() is None
    assert recovered.report()["controller_states_entered"] == {"error-passive": 1, "error-active": 1}
    lasting = BusHealth(None)
    lasting.check([error_frame_data(P, 128)], 0.01)
    lasting.settle()
    assert (lasting.take_fault() or "").startswith("CAN bus: error-passive (")


def test_a_start_up_on_an_error_passive_bus_succeeds_and_the_first_read_raises_it() -> None:
    hal = open_hal(hal_config("can-sim"))
    assert isinstance(hal, SimulatedCanHal)
    hal.drive_set.line.schedule("error_passive", 0.0)  # at the first SYNC start-up sends: frames still flow
    hal.open()
    try:
        assert isinstance(_tick(hal, Command(np.zeros(4), False)), HalBusFaultError)
        assert _tick(hal, Command(np.zeros(4), False)) is None
    finally:
        hal.close()


def test_warnings_and_protocol_errors_are_counted_not_faults() -> None:
    health = BusHealth(None)
    frames = [(0x004, _frame(0x08))] + [(0x088, _frame(0, 0x04))] * 5 + [(0x020, _frame())] * 2
    health.check(frames, 0.5)
    assert health.take_fault() is None
    assert health.state is W
    report = health.report()
    assert report["error_frames"] == 8
    assert report["bus_errors"] == {"protocol error": 5, "bus error": 5, "no acknowledge": 2}


def test_a_state_reader_that_fails_is_counted_and_the_error_frames_still_stand() -> None:
    def broken() -> ControllerState:
        raise can.CanOperationError("driver gone")

    health = BusHealth(broken)
    health.check([error_frame_data(OFF, 255)], 0.1)
    assert health.state is OFF
    assert (health.take_fault() or "").startswith("CAN bus: bus-off (the controller stopped transmitting")
    assert health.state_reads_failed == 1


def test_error_frames_of_an_interface_that_is_not_socketcan_are_only_counted() -> None:
    health = BusHealth(None, decode_frames=False)
    health.check([(CAN_ERR_BUSOFF, _frame())], 0.0)  # a vendor's error frame: its bits mean something else
    assert health.state is A
    assert health.take_fault() is None
    assert health.error_frames == 1


# --- how each interface's state is read ------------------------------------------------------------------


def _fake_bus(name: str, **attributes: object) -> can.BusABC:
    return type(name, (), attributes)()  # type: ignore[return-value]


@pytest.mark.parametrize(
    ("status", "state"), [(0x0, A), (0x4, W), (0x8, W), (0x40000, P), (0x10, OFF), (0x10 | 0x40000, OFF)]
)
def test_pcan_is_read_by_its_status_not_by_its_state(status: int, state: ControllerState) -> None:
    """python-can's PcanBus.state is the listen-only mode the caller set: its status() is the controller's."""
    bus = _fake_bus("PcanBus", status=lambda self: status, state=can.BusState.ACTIVE)
    reader = state_reader(bus)
    assert reader is not None
    assert reader() is state


@pytest.mark.parametrize(
    ("bus_state", "state"),
    [(can.BusState.ACTIVE, A), (can.BusState.PASSIVE, P), (can.BusState.ERROR, OFF), (None, None)],
)
def test_ixxat_and_etas_are_read_by_their_state(bus_state: can.BusState | None, state: ControllerState | None) -> None:
    for name in ("IXXATBus", "EtasBus"):
        reader = state_reader(_fake_bus(name, state=bus_state))
        assert reader is not None
        assert reader() is state


def test_socketcan_and_kvaser_have_no_state_to_read() -> None:
    """Their ``state`` is python-can's default (always ACTIVE): socketcan tells by error frames, kvaser not at all."""
    for name in ("SocketcanBus", "KvaserBus", "VirtualBus"):
        assert state_reader(_fake_bus(name, state=can.BusState.ACTIVE)) is None
    assert BusHealth.for_bus(_fake_bus("SocketcanBus")).decode_frames
    assert not BusHealth.for_bus(_fake_bus("KvaserBus")).decode_frames


# --- the simulated controller: what a real one does when it fails ------------------------------------------


@pytest.fixture
def handles() -> Iterator[tuple[SimulationBus, SimulationBus, LineFaults]]:
    channel = f"health-{next(_CHANNELS)}"
    master = SimulationBus(channel=channel, preserve_timestamps=True)
    other = SimulationBus(channel=channel, preserve_timestamps=True)
    line = LineFaults([])
    line.attach(master)
    yield master, other, line
    master.shutdown()
    other.shutdown()


def _msg(cob_id: int, t_s: float = 0.0) -> can.Message:
    return can.Message(arbitration_id=cob_id, data=b"\x01", is_extended_id=False, timestamp=t_s)


def _all(bus: SimulationBus) -> list[can.Message]:
    return list(iter(lambda: bus.recv(timeout=0), None))


def test_a_bus_off_controller_neither_sends_nor_receives_and_says_so(
    handles: tuple[SimulationBus, SimulationBus, LineFaults],
) -> None:
    master, other, line = handles
    other.send(_msg(0x181))  # received before the controller fails: still readable
    line.inject("bus_off", 1.0)
    master.send(_msg(0x201))
    other.send(_msg(0x182))
    assert _all(other) == []
    received = _all(master)
    assert [m.arbitration_id for m in received] == [0x181, CAN_ERR_BUSOFF | 0x200]
    assert received[1].is_error_frame
    assert master.state is can.BusState.ERROR
    assert line.events == [(1.0, 0, "injected bus_off")]
    line.clear()  # restarted
    restart = _all(master)
    assert len(restart) == 1
    assert restart[0].is_error_frame
    assert restart[0].arbitration_id & CAN_ERR_RESTARTED
    assert master.state is can.BusState.ACTIVE
    master.send(_msg(0x201))
    other.send(_msg(0x182))
    assert [m.arbitration_id for m in _all(other)] == [0x201]
    assert [m.arbitration_id for m in _all(master)] == [0x182]


def test_an_error_passive_controller_still_carries_frames(
    handles: tuple[SimulationBus, SimulationBus, LineFaults],
) -> None:
    master, other, line = handles
    line.inject("error_passive", 1.0)
    assert master.state is can.BusState.PASSIVE
    (error,) = _all(master)
    assert error.is_error_frame
    assert error.arbitration_id & CAN_ERR_CRTL
    assert error.data[1] == CAN_ERR_CRTL_TX_PASSIVE
    master.send(_msg(0x201))
    other.send(_msg(0x182))
    assert [m.arbitration_id for m in _all(other)] == [0x201]
    assert [m.arbitration_id for m in _all(master)] == [0x182]


def test_a_scheduled_bus_fault_hits_at_the_first_sync_at_or_after_its_time(
    handles: tuple[SimulationBus, SimulationBus, LineFaults],
) -> None:
    master, other, line = handles
    line.schedule("bus_off", 0.005)
    for k in range(5):
        master.send(_msg(0x080, k * 0.002))  # SYNCs at 0, 2, 4, 6, 8 ms
    syncs = [m.timestamp for m in _all(other)]
    assert syncs == [0.0, 0.002, 0.004]  # the SYNC of 6 ms is the first lost
    assert line.events == [(0.006, 0, "injected bus_off")]
    assert line.take_lost_syncs() == 2


# --- the backend: the fault raised by the next read, by either path ----------------------------------------


@contextlib.contextmanager
def _open_sim() -> Iterator[SimulatedCanHal]:
    hal = open_hal(hal_config("can-sim"))
    assert isinstance(hal, SimulatedCanHal)
    hal.open()
    try:
        yield hal
    finally:
        hal.close()


def _tick(hal: SimulatedCanHal, command: Command) -> BaseException | None:
    """One tick (read, write); the read's fault, if it raised one."""
    raised = None
    try:
        hal.read()
    except HalFaultError as exc:
        raised = exc
    hal.write(command)
    return raised


TORQUE = Command(np.full(4, 2.0), True)


@pytest.mark.parametrize("path", ["state", "error frames"])
@pytest.mark.parametrize("kind", ["bus_off", "error_passive"])
def test_the_next_read_raises_the_bus_fault_by_either_path(kind: str, path: str) -> None:
    with _open_sim() as hal:
        line = hal.drive_set.line
        line.reports_state = path == "state"
        line.sends_error_frames = path == "error frames"
        for _ in range(20):
            assert _tick(hal, TORQUE) is None
        line.inject(kind, hal.plant.world.t_s)
        raised = _tick(hal, TORQUE)
        assert isinstance(raised, HalBusFaultError)
        word = "bus-off" if kind == "bus_off" else "error-passive"
        assert str(raised).startswith(f"CAN bus: {word} (")
        assert hal.bus_report()["bus_health"]["controller_states_entered"] == {word: 1}  # type: ignore[index]


@pytest.mark.parametrize("kind", ["bus_off", "error_passive"])
def test_without_detection_the_bus_fault_is_not_raised_as_one(kind: str) -> None:
    """Neither path: error-passive goes unseen, bus-off is only found as four lost drives three SYNCs later."""
    with _open_sim() as hal:
        line = hal.drive_set.line
        line.reports_state = line.sends_error_frames = False
        for _ in range(20):
            _tick(hal, TORQUE)
        line.inject(kind, hal.plant.world.t_s)
        raised = [_tick(hal, TORQUE) for _ in range(10)]
        assert not any(isinstance(r, HalBusFaultError) for r in raised)
        if kind == "bus_off":
            first = next(n for n, r in enumerate(raised) if r is not None)
            assert first >= 3
            assert "lost: no TPDO for 3 SYNCs" in str(raised[first])
        else:
            assert raised == [None] * 10


def test_error_passive_commands_still_reach_the_drives_and_acknowledging_early_raises_it_again() -> None:
    with _open_sim() as hal:
        for _ in range(20):
            _tick(hal, TORQUE)
        hal.drive_set.line.inject("error_passive", hal.plant.world.t_s)
        assert isinstance(_tick(hal, TORQUE), HalBusFaultError)
        seq = hal.master.sample_sync
        for _ in range(5):
            assert _tick(hal, Command(np.full(4, 1.5), True)) is None  # frames flow: fresh readings, no fault
        assert hal.master.sample_sync == seq + 5
        assert hal.applied_motor_torque_nm == pytest.approx(1.5)  # the commands arrived
        hal.request_fault_reset()  # the operator acknowledges while the bus is still error-passive
        again = _tick(hal, TORQUE)
        assert isinstance(again, HalBusFaultError)
        assert "since t = " in str(again)
        hal.world.clear_faults()  # the bus recovers (error-active again)
        _tick(hal, TORQUE)
        hal.request_fault_reset()
        assert [_tick(hal, TORQUE) for _ in range(3)] == [None] * 3


def test_after_bus_off_the_drives_stop_by_their_own_reaction_not_by_the_masters_torque_off() -> None:
    """No command reaches the drives: the runtime's torque off does not arrive, and each drive stops by its
    own RPDO deadline (5 SYNC periods; category 0, the backend's default reaction, H19); robot time goes
    on without SYNCs."""
    with _open_sim() as hal:
        period_s, deadline_s = 1.0 / hal.rate_hz, hal.settings().rpdo_deadline_ms / 1000.0
        for _ in range(20):
            _tick(hal, TORQUE)
        t_fault = hal.plant.world.t_s
        hal.drive_set.line.inject("bus_off", t_fault)
        applied = []
        for _ in range(200):
            _tick(hal, Command(np.zeros(4), False))  # the runtime's torque off: it reaches nobody
            applied.append((hal.plant.world.t_s - t_fault, hal.applied_motor_torque_nm.copy()))
        held = [t for t, torque in applied if np.all(torque == 2.0)]
        off = next(t for t, torque in applied if np.all(torque == 0.0))
        assert held
        assert held == [t for t, _ in applied[: len(held)]]
        assert off <= deadline_s + period_s  # their deadline after the last RPDO that arrived
        assert all(np.all(torque == 0.0) for t, torque in applied if t >= off)
        assert hal.plant.world.t_s - t_fault == pytest.approx(200 * period_s, abs=1e-9)  # time went on without SYNCs


def test_error_passive_lets_the_runtimes_torque_off_reach_the_drives_in_the_next_cycle() -> None:
    with _open_sim() as hal:
        for _ in range(20):
            _tick(hal, TORQUE)
        hal.drive_set.line.inject("error_passive", hal.plant.world.t_s)
        assert isinstance(_tick(hal, Command(np.zeros(4), False)), HalBusFaultError)
        assert np.all(hal.applied_motor_torque_nm == 0.0)  # disable voltage arrived with that cycle's RPDOs


def test_a_start_up_on_a_controller_gone_bus_off_says_so() -> None:
    """The drives do not answer because nothing reaches them: the refusal names the controller's state."""
    from hal.errors import HalError

    hal = open_hal(hal_config("can-sim"))
    assert isinstance(hal, SimulatedCanHal)
    hal.drive_set.line.schedule("bus_off", 0.0)  # at the first SYNC start-up sends
    with pytest.raises(HalError, match=r"within [0-9.]+ s; CAN bus: bus-off \(the controller stopped transmitting"):
        hal.open()
    hal.close()


# --- receive times: the interface's stamp, not when Python took the frame -----------------------------------


def test_a_frame_takes_its_stamp_put_on_the_masters_clock_by_its_age() -> None:
    wall = [1_000.0]
    clock = ReceiveClock(lambda: 50.0, lambda: wall[0])
    assert clock(1_000.0 - 0.0015) == pytest.approx(50.0 - 0.0015)  # 1.5 ms in the kernel's queue
    assert clock(1_000.0 + 0.001) == 50.0  # within the clocks' granularity: now
    assert (clock.stamped, clock.fallbacks) == (2, 0)
    for stamp in (0.0, 1_000.0 + 0.01, 1_000.0 - 2.0):  # missing, from the future, on another clock
        assert clock(stamp) == 50.0
    assert (clock.stamped, clock.fallbacks) == (2, 3)
    wall[0] += 3600.0  # a wall clock stepped by an hour: ages are taken on it, stamps follow it
    assert clock(wall[0] - 0.002) == pytest.approx(50.0 - 0.002)


def test_listened_frames_use_the_interfaces_stamp_and_keep_error_frames_apart() -> None:
    channel = f"stamps-{next(_CHANNELS)}"
    master = can.Bus(interface="virtual", channel=channel)
    drives = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    source = ListenedFrames(master, lambda: 100.0)
    try:
        now = time.time()
        drives.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=now - 0.010))
        drives.send(can.Message(arbitration_id=CAN_ERR_BUSOFF, data=_frame(), is_error_frame=True, timestamp=now))
        drives.send(can.Message(arbitration_id=0x182, data=b"\x02", is_extended_id=False, timestamp=0.0))
        frames, deadline = [], time.monotonic() + 2.0
        while len(frames) < 2 and time.monotonic() < deadline:
            frames += source.drain()
            time.sleep(0.002)
        errors = source.take_error_frames()
    finally:
        source.close()
        master.shutdown()
        drives.shutdown()
    assert [cob_id for cob_id, _, _ in frames] == [0x181, 0x182]
    assert 100.0 - 0.010 - 0.5 < frames[0][2] <= 100.0 - 0.010  # 10 ms old when stamped, less when taken
    assert frames[1][2] == 100.0  # no stamp: the time it was taken
    assert errors == [(CAN_ERR_BUSOFF, _frame())]
    assert source.receive_time_report() | {"source": ""} == {"source": "", "stamped": 1, "fallbacks": 1}


# --- daror hil --fault bus_off@T / error_passive@T: the acceptance -----------------------------------------

#: To pilot_installation (minimal impedance: the drives hold the arm, a fault fails the robot), then the fault.
HIL_SCRIPT = """\
wait 0.5
advance
advance
sim estop operator on
wait 0.3
sim estop operator off
wait 0.5
sim estop pilot on
wait 0.3
sim estop pilot off
wait 0.5
advance
confirm settings
advance
expect state pilot_installation
wait 100
expect state FAIL
wait 3.5
"""


@pytest.mark.slow
@pytest.mark.parametrize(("kind", "word"), [("bus_off", "bus-off"), ("error_passive", "error-passive")])
def test_hil_a_bus_fault_fails_the_robot_in_its_tick_without_dropping_the_arm_and_its_cause_audited(
    tmp_path: Path, kind: str, word: str
) -> None:
    from daror_runtime.cli import main

    script = tmp_path / "to_pilot_installation.txt"
    script.write_text(HIL_SCRIPT)
    out = tmp_path / "run"
    assert main(["hil", "--script", str(script), "--out", str(out), "--fault", f"{kind}@4"]) == 0
    report = json.loads((out / "hil.json").read_text())
    period_s = 1.0 / report["bus"]["rate_hz"]
    (fault,) = report["faults"]
    assert (fault["kind"], fault["node"], fault["joint"], fault["injected_s"]) == (kind, None, None, 4.0)
    assert (fault["state_before"], fault["state_after"]) == ("pilot_installation", "FAIL")
    assert fault["ticks_to_state_after"] <= 3
    assert fault["found"][0]["kind"] == "bus"
    assert f"CAN bus: {word} (" in fault["found"][0]["message"]
    # D166: error-passive still carries the lowering; on bus-off the readings stop too, and the stale fault's
    # reaction (off) is the stricter: the runtime's commands reach nobody either way, the drives' ramps act
    assert fault["reaction"]["reaction"] == ("lower" if kind == "error_passive" else "off")
    assert "bus" in fault["reaction"]["causes"]
    assert fault["declared_reaction"]["bus"]["reaction"] == "lower"
    assert report["bus"]["bus_health"]["controller_states_entered"] == {word: 1}
    events = [json.loads(line) for line in (out / "audit.jsonl").read_text().splitlines()]
    (bus,) = [e for e in events if e.get("event") == "fault" and e.get("kind") == "bus"]
    assert f"CAN bus: {word} (" in bus["message"]
    fail = next(e for e in events if e.get("event") == "transition" and e["dest"] == "FAIL")
    assert 4.0 - period_s - 1e-9 <= fail["t_s"] <= 4.0 + 3 * period_s
    stages = fault["power_stage"]
    assert all(stage["on_at_injection"] for stage in stages.values())  # the drives held the arm
    if kind == "error_passive":  # frames still flow: the drives keep the arm while it is lowered, no drop (D166)
        assert all(stage["off_s"] is None or stage["off_s"] > 4.0 + 3.0 for stage in stages.values()), stages
    else:  # nothing reaches them: each stops by its own reaction (its RPDO deadline, 5 periods, then its 3 s ramp)
        latest = 4.0 + 6 * period_s + 3.0
        assert all(stage["off_s"] is not None and 4.0 < stage["off_s"] <= latest for stage in stages.values()), stages


@pytest.mark.parametrize(
    ("fault", "fragment"),
    [
        ("bus_off:2@1", "bus_off is a fault of the bus, not of a node: expected bus_off@T_S"),
        ("error_passive:1@0.5", "error_passive is a fault of the bus, not of a node"),
        ("emcy@1", "emcy is a drive's fault: expected emcy:NODE@T_S"),
        ("bus_of@1", "unknown fault 'bus_of'; expected one of heartbeat_loss, emcy, frozen_pdo, drive_fault"),
        ("bus_off@-1", "expected KIND:NODE@T_S or a bus fault KIND@T_S"),
    ],
)
def test_a_bus_fault_with_a_node_or_a_drives_fault_without_one_is_one_line_exit_2_nothing_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fault: str, fragment: str
) -> None:
    from daror_runtime.cli import main

    script = tmp_path / "short.txt"
    script.write_text("wait 1\n")
    out = tmp_path / "run"
    assert main(["hil", "--script", str(script), "--out", str(out), "--fault", fault]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert "Traceback" not in err
    assert fragment in err
    assert not (out / "hil.json").exists()
    assert not (out / "can.log.gz").exists()
