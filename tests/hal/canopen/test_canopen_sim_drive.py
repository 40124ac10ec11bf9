"""The simulated DAROR SEA drive (hal/canopen/sim/drive.py): bytes on the bus, NMT, SDO, PDOs, CiA 402, faults.

The drive is configured exactly as the master will configure it (``PdoMapping.configuration`` and
``sdo.download_request``), and every frame it sends is checked byte by byte.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hal.canopen import objects as obj
from hal.canopen.cia301 import sdo
from hal.canopen.cia301.nmt import NmtCommand, NmtState, nmt_frame
from hal.canopen.cia402.statemachine import (
    CW_DISABLE_VOLTAGE,
    CW_ENABLE_OPERATION,
    CW_FAULT_RESET,
    CW_QUICK_STOP,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    SW_ESTOP_OPERATOR,
    SW_ESTOP_PILOT,
    PowerState,
    PowerStepper,
    statusword_of,
)
from hal.canopen.dictionary import DEFAULT_EDS, DriveDictionary, load_dictionary
from hal.canopen.mapping import DAROR_MAPPING
from hal.canopen.sim.drive import DEFAULT_DROP_S, FAULT_KINDS, SimulatedSeaDrive

NODE = 5
MASTER = 127
SDO_RX = 0x600 + NODE
SDO_TX = 0x580 + NODE
EMCY = 0x080 + NODE
HEARTBEAT = 0x700 + NODE
TPDO1 = 0x180 + NODE
TPDO2 = 0x280 + NODE
RPDO1 = 0x200 + NODE
INT32_MAX = 2**31 - 1
DICTIONARY = load_dictionary()
RAD_PER_INC = 2 * math.pi / 65536  # both encoders of the shipped EDS: 65536 increments a revolution
SW_OFF = statusword_of(PowerState.SWITCH_ON_DISABLED)


@dataclass
class Rig:
    """One drive on a recording bus: every frame it sent, in order."""

    drive: SimulatedSeaDrive
    frames: list[tuple[int, bytes]] = field(default_factory=list)

    def take(self) -> list[tuple[int, bytes]]:
        """The frames sent since the last call."""
        taken, self.frames[:] = list(self.frames), []
        return taken

    def on(self, cob_id: int) -> list[bytes]:
        """The data of the frames sent on ``cob_id`` since the last call (the others are dropped too)."""
        return [data for cob, data in self.take() if cob == cob_id]

    def write(self, index: int, sub: int, data: bytes, now_s: float = 0.0) -> bytes | None:
        """An SDO download; the drive's answer (None: it did not answer)."""
        self.take()
        self.drive.receive(SDO_RX, sdo.download_request(index, sub, data), now_s)
        answers = self.on(SDO_TX)
        assert len(answers) <= 1
        return answers[0] if answers else None

    def read(self, index: int, sub: int = 0, now_s: float = 0.0) -> bytes | None:
        self.take()
        self.drive.receive(SDO_RX, sdo.upload_request(index, sub), now_s)
        answers = self.on(SDO_TX)
        return answers[0] if answers else None

    def nmt(self, command: NmtCommand, now_s: float = 0.0, node_id: int = NODE) -> None:
        self.drive.receive(*nmt_frame(command, node_id), now_s)

    def rpdo(self, controlword: int, torque_permille: int = 0, now_s: float = 0.0) -> None:
        self.drive.receive(RPDO1, struct.pack("<Hh", controlword, torque_permille), now_s)

    def sync(
        self,
        now_s: float = 0.0,
        q: float = 0.0,
        theta: float = 0.0,
        tau: float = 0.0,
        operator: bool = False,
        pilot: bool = False,
    ) -> None:
        self.drive.on_sync(q, theta, tau, operator, pilot, now_s)

    def step(self, controlword: int, torque_permille: int = 0, now_s: float = 0.0, **sync: float | bool) -> None:
        """One cycle as the master runs it: the RPDO, then the SYNC that makes it act."""
        self.rpdo(controlword, torque_permille, now_s)
        self.sync(now_s, **sync)  # type: ignore[arg-type]

    def configure(self, now_s: float = 0.0) -> list[tuple[int, bytes]]:
        """The master's start-up writes (DAROR_MAPPING, cyclic synchronous torque); the drive's answers."""
        self.take()
        for pdo in DAROR_MAPPING.all:
            for index, sub, data, _ in pdo.configuration(NODE):
                self.drive.receive(SDO_RX, sdo.download_request(index, sub, data), now_s)
        self.drive.receive(SDO_RX, sdo.download_request(obj.MODES_OF_OPERATION, 0, b"\x0a"), now_s)
        return self.take()

    def enable(self, now_s: float = 0.0) -> None:
        """Configured, started and in OPERATION ENABLED (shutdown, switch on, enable operation)."""
        assert all(data[0] == 0x60 for _, data in self.configure(now_s))
        self.nmt(NmtCommand.START, now_s)
        for controlword in (CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION):
            self.step(controlword, 0, now_s)
        assert self.drive.power_state is PowerState.OPERATION_ENABLED
        self.take()


def rig(power: bool = True, dictionary: DriveDictionary = DICTIONARY) -> Rig:
    frames: list[tuple[int, bytes]] = []
    drive = SimulatedSeaDrive(NODE, dictionary, lambda cob, data: frames.append((cob, data)), MASTER)
    bench = Rig(drive, frames)
    if power:
        drive.power_on(0.0)
    return bench


def ok(index: int, sub: int) -> bytes:
    return sdo.download_response(index, sub)


def abort(index: int, sub: int, code: int) -> bytes:
    return sdo.abort_frame(index, sub, code)


def u8(v: int) -> bytes:
    return struct.pack("<B", v)


def u16(v: int) -> bytes:
    return struct.pack("<H", v)


def u32(v: int) -> bytes:
    return struct.pack("<I", v)


def emcy(code: int, register: int) -> bytes:
    return struct.pack("<HB5x", code, register)


# ---------------------------------------------------------------------------- construction, power, factory state


@pytest.mark.parametrize(("node_id", "master"), [(0, 127), (128, 127), (5, 0), (5, 128), (5, 5)])
def test_node_ids_out_of_range_or_shared_are_refused(node_id: int, master: int) -> None:
    with pytest.raises(ValueError, match="node id"):
        SimulatedSeaDrive(node_id, DICTIONARY, lambda cob, data: None, master)


def test_an_unpowered_drive_hears_and_sends_nothing() -> None:
    bench = rig(power=False)
    drive = bench.drive
    assert (drive.nmt_state, drive.power_state, drive.powered) == (
        NmtState.BOOT_UP,
        PowerState.NOT_READY_TO_SWITCH_ON,
        False,
    )
    bench.nmt(NmtCommand.START)
    drive.receive(SDO_RX, sdo.upload_request(0x1000, 0), 0.0)
    bench.sync(0.1)
    drive.advance(10.0)
    assert bench.take() == []
    assert drive.applied_torque_nm == 0.0
    with pytest.raises(ValueError, match="not powered"):
        drive.inject("drive_fault", 0.0)


def test_power_on_sends_the_boot_up_message_and_waits_in_pre_operational() -> None:
    bench = rig()
    assert bench.take() == [(HEARTBEAT, b"\x00")]
    assert bench.drive.nmt_state is NmtState.PRE_OPERATIONAL
    assert bench.drive.power_state is PowerState.SWITCH_ON_DISABLED
    assert bench.drive.value(obj.STATUSWORD) == 0x0240  # switch on disabled, remote


def test_factory_values_are_the_eds_defaults_with_the_node_id_resolved() -> None:
    drive = rig().drive
    assert drive.value(0x1400, 1) == 0x205
    assert drive.value(0x1800, 1) == 0x185
    assert drive.value(0x1801, 1) == 0x285
    assert drive.value(0x1014) == 0x85
    assert drive.value(0x1800, 2) == drive.value(0x1801, 2) == drive.value(0x1400, 2) == 255
    assert drive.value(0x1A00, 0) == drive.value(0x1A01, 0) == 1
    assert drive.value(0x1A00, 1) == drive.value(0x1A01, 1) == 0x60410010
    assert drive.value(obj.MAX_TORQUE) == 1000
    assert drive.value(obj.PRODUCER_HEARTBEAT_TIME) == 0
    assert drive.value(obj.DEVICE_TYPE) == 0x00020192
    with pytest.raises(KeyError):
        drive.value(0x1234)
    with pytest.raises(TypeError):
        drive.value(0x1008)  # the device name: a string


# ---------------------------------------------------------------------------- configuration and TPDOs


def test_the_master_s_configuration_is_accepted_byte_by_byte() -> None:
    bench = rig()
    bench.take()
    answers = bench.configure()
    writes = [(index, sub) for pdo in DAROR_MAPPING.all for index, sub, _, _ in pdo.configuration(NODE)]
    assert answers == [(SDO_TX, ok(index, sub)) for index, sub in [*writes, (obj.MODES_OF_OPERATION, 0)]]
    drive = bench.drive
    for pdo in DAROR_MAPPING.all:
        assert drive.value(pdo.communication_index, 1) == pdo.cob_id(NODE)
        assert drive.value(pdo.communication_index, 2) == 1
        assert drive.value(pdo.mapping_index, 0) == len(pdo.objects)
        for n, mapped in enumerate(pdo.objects, start=1):
            assert drive.value(pdo.mapping_index, n) == mapped.entry
    assert drive.value(obj.MODES_OF_OPERATION_DISPLAY) == obj.MODE_CYCLIC_SYNCHRONOUS_TORQUE


def test_the_factory_state_sends_no_daror_tpdos_only_its_statusword_on_change() -> None:
    bench = rig()
    bench.nmt(NmtCommand.START)
    bench.take()
    bench.sync(0.002, theta=1.0, tau=-2.5)
    sw = u16(SW_OFF)
    assert bench.take() == [(TPDO1, sw), (TPDO2, sw)]  # event-driven (255), statusword only: 2 bytes
    bench.sync(0.004, theta=1.5)
    assert bench.take() == []  # nothing changed
    bench.drive.receive(RPDO1, u16(CW_SHUTDOWN), 0.005)  # the factory RPDO1: the controlword, event-driven
    assert bench.drive.power_state is PowerState.READY_TO_SWITCH_ON
    bench.sync(0.006)
    ready = u16(statusword_of(PowerState.READY_TO_SWITCH_ON))
    assert bench.take() == [(TPDO1, ready), (TPDO2, ready)]


def test_tpdos_carry_the_values_sampled_at_the_sync() -> None:
    bench = rig()
    bench.configure()
    bench.nmt(NmtCommand.START)
    bench.take()
    bench.sync(0.002, q=0.5, theta=1.0, tau=-2.5)
    theta_inc = round(65536 / (2 * math.pi))
    q_inc = round(0.5 / RAD_PER_INC)
    assert theta_inc == 10430
    assert bench.take() == [
        (TPDO1, struct.pack("<HI", SW_OFF, theta_inc)),
        (TPDO2, struct.pack("<ih", q_inc, -250)),
    ]
    bench.sync(0.004, q=-0.5, theta=-1.0, tau=2.5)
    assert bench.take() == [
        (TPDO1, struct.pack("<Hi", SW_OFF, -theta_inc)),
        (TPDO2, struct.pack("<ih", -q_inc, 250)),
    ]


def test_actual_values_saturate_at_their_types() -> None:
    bench = rig()
    bench.sync(0.0, q=-1e12, theta=1e12, tau=1e6)
    drive = bench.drive
    assert drive.value(obj.POSITION_ACTUAL) == INT32_MAX
    assert drive.value(obj.LOAD_POSITION_ACTUAL) == -(2**31)
    assert drive.value(obj.TORQUE_ACTUAL) == 2**15 - 1


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_sensor_value_is_a_simulation_bug(bad: float) -> None:
    bench = rig()
    bench.sync(0.0, theta=0.3)
    with pytest.raises(ValueError, match="non-finite"):
        bench.sync(0.002, theta=bad, operator=True)
    assert bench.drive.value(obj.POSITION_ACTUAL) == round(0.3 / RAD_PER_INC)  # nothing changed


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_the_steady_sync_meets_a_non_finite_reading_as_the_general_path_does(bad: float) -> None:
    """The generated steady program takes the general way for a non-finite reading: the RPDO taken, ValueError."""
    bench = rig()
    bench.enable()
    bench.sync(0.002, theta=0.3)
    frame = (RPDO1, struct.pack("<Hh", CW_ENABLE_OPERATION, 300))
    assert bench.drive.steady_sync_ready(frame, 0.004)
    with pytest.raises(ValueError, match="non-finite"):
        bench.drive.steady_sync(frame, bad, 0.3, 0.0, False, False, 0.004)
    assert bench.drive.value(obj.POSITION_ACTUAL) == round(0.3 / RAD_PER_INC)  # nothing sampled
    assert bench.drive.applied_torque_nm == 0.0
    bench.sync(0.006, theta=0.3)  # the RPDO was received: it acts at the next SYNC, as on the general path
    assert bench.drive.applied_torque_nm == pytest.approx(3.0)


def test_a_tpdo_of_transmission_type_n_goes_every_nth_sync_since_the_node_started() -> None:
    bench = rig()
    bench.configure()
    assert bench.write(0x1801, 2, u8(3)) == ok(0x1801, 2)  # may change while the PDO is valid
    bench.nmt(NmtCommand.START)
    sent = []
    for k in range(1, 8):
        bench.sync(k * 0.002)
        sent.append([cob for cob, _ in bench.take()])
    assert sent == [[TPDO1], [TPDO1], [TPDO1, TPDO2], [TPDO1], [TPDO1], [TPDO1, TPDO2], [TPDO1]]
    bench.nmt(NmtCommand.STOP)
    bench.nmt(NmtCommand.START)  # operational again: the count starts over
    sent = []
    for k in range(1, 4):
        bench.sync(1 + k * 0.002)
        sent.append([cob for cob, _ in bench.take()])
    assert sent == [[TPDO1], [TPDO1], [TPDO1, TPDO2]]


# ---------------------------------------------------------------------------- RPDOs, torque, CiA 402


def test_an_rpdo_acts_at_the_next_sync_and_the_last_one_wins() -> None:
    bench = rig()
    bench.enable()
    drive = bench.drive
    assert drive.applied_torque_nm == 0.0
    bench.rpdo(CW_ENABLE_OPERATION, 100)
    bench.rpdo(CW_ENABLE_OPERATION, 300)
    assert drive.applied_torque_nm == 0.0  # buffered until the SYNC
    assert drive.value(obj.TARGET_TORQUE) == 0
    bench.sync(0.002)
    assert drive.applied_torque_nm == pytest.approx(3.0)  # 300 per mille of 10 Nm
    bench.step(CW_ENABLE_OPERATION, -250, 0.004)
    assert drive.applied_torque_nm == pytest.approx(-2.5)


def test_the_applied_torque_saturates_at_the_max_torque() -> None:
    bench = rig()
    assert bench.write(obj.MAX_TORQUE, 0, u16(200)) == ok(obj.MAX_TORQUE, 0)
    bench.enable()
    bench.step(CW_ENABLE_OPERATION, 900)
    assert bench.drive.applied_torque_nm == pytest.approx(2.0)
    bench.step(CW_ENABLE_OPERATION, -32768)
    assert bench.drive.applied_torque_nm == pytest.approx(-2.0)


def test_the_statusword_follows_the_enable_sequence_one_sync_at_a_time() -> None:
    bench = rig()
    bench.configure()
    bench.nmt(NmtCommand.START)
    bench.take()
    shown = []
    for controlword in (CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION, CW_QUICK_STOP, CW_DISABLE_VOLTAGE):
        bench.step(controlword, 400)
        shown.append(struct.unpack_from("<H", bench.on(TPDO1)[0])[0])
        if controlword == CW_ENABLE_OPERATION:
            assert bench.drive.applied_torque_nm == pytest.approx(4.0)
        else:
            assert bench.drive.applied_torque_nm == 0.0
    assert shown == [0x0231, 0x0233, 0x0237, 0x0217, 0x0240]  # remote; voltage enabled until switch on disabled


def test_switch_on_disabled_cannot_jump_to_operation_enabled() -> None:
    bench = rig()
    bench.configure()
    bench.nmt(NmtCommand.START)
    for controlword in (CW_ENABLE_OPERATION, CW_SWITCH_ON, CW_ENABLE_OPERATION):
        bench.step(controlword, 500)
        assert bench.drive.power_state is PowerState.SWITCH_ON_DISABLED
        assert bench.drive.applied_torque_nm == 0.0


def test_a_controlword_written_by_sdo_acts_at_once() -> None:
    bench = rig()
    assert bench.write(obj.CONTROLWORD, 0, u16(CW_SHUTDOWN)) == ok(obj.CONTROLWORD, 0)
    assert bench.drive.power_state is PowerState.READY_TO_SWITCH_ON


# ---------------------------------------------------------------------------- NMT


def test_pre_operational_processes_no_pdo() -> None:
    bench = rig()
    bench.configure()
    bench.take()
    for controlword in (CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION):
        bench.step(controlword, 300)
    assert bench.take() == []
    assert bench.drive.power_state is PowerState.SWITCH_ON_DISABLED
    assert bench.drive.value(obj.TARGET_TORQUE) == 0


def test_nmt_stop_ends_pdos_and_sdo_and_the_drive_s_torque() -> None:
    bench = rig()
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(10))
    bench.enable()
    bench.step(CW_ENABLE_OPERATION, 300)
    bench.rpdo(CW_ENABLE_OPERATION, 500)  # buffered, then the node stops: never applied
    bench.nmt(NmtCommand.STOP)
    drive = bench.drive
    assert drive.nmt_state is NmtState.STOPPED
    assert drive.power_state is PowerState.SWITCH_ON_DISABLED  # its PDOs are gone: no torque nobody can change
    assert drive.applied_torque_nm == 0.0
    bench.take()
    bench.step(CW_ENABLE_OPERATION, 700, 0.002)
    assert bench.take() == []
    assert drive.value(obj.TARGET_TORQUE) == 300
    assert bench.read(0x1000) is None  # no SDO while stopped
    drive.advance(0.010)
    assert bench.take() == [(HEARTBEAT, b"\x04")]  # the heartbeat goes on, saying STOPPED


def test_enter_pre_operational_ends_pdos_but_not_sdo() -> None:
    bench = rig()
    bench.enable()
    bench.nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
    assert bench.drive.power_state is PowerState.SWITCH_ON_DISABLED
    bench.step(CW_SHUTDOWN, 0, 0.002)
    assert bench.take() == []
    assert bench.read(obj.STATUSWORD) == sdo.upload_response(obj.STATUSWORD, 0, u16(SW_OFF))


def test_nmt_commands_for_another_node_or_malformed_are_ignored_broadcasts_act() -> None:
    bench = rig()
    bench.nmt(NmtCommand.START, node_id=NODE + 1)
    bench.drive.receive(0x000, bytes((NmtCommand.START,)), 0.0)  # 1 byte
    bench.drive.receive(0x000, bytes((0x55, NODE)), 0.0)  # unknown command
    assert bench.drive.nmt_state is NmtState.PRE_OPERATIONAL
    bench.nmt(NmtCommand.START, node_id=0)
    assert bench.drive.nmt_state is NmtState.OPERATIONAL


def test_frames_that_cannot_be_on_a_can_bus_are_refused() -> None:
    drive = rig().drive
    with pytest.raises(ValueError, match="11-bit"):
        drive.receive(0x800, b"", 0.0)
    with pytest.raises(ValueError, match="8 bytes"):
        drive.receive(RPDO1, bytes(9), 0.0)


def test_reset_node_is_a_power_cycle() -> None:
    bench = rig()
    bench.write(obj.MAX_TORQUE, 0, u16(200))
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(10))
    bench.enable()
    bench.drive.inject("frozen_pdo", 0.0)
    bench.nmt(NmtCommand.RESET_NODE, 0.5)
    drive = bench.drive
    assert bench.take() == [(HEARTBEAT, b"\x00")]
    assert (drive.nmt_state, drive.power_state) == (NmtState.PRE_OPERATIONAL, PowerState.SWITCH_ON_DISABLED)
    assert drive.value(obj.MAX_TORQUE) == 1000
    assert drive.value(0x1800, 2) == 255
    assert drive.value(obj.MODES_OF_OPERATION) == 0
    drive.advance(1.0)
    assert bench.take() == []  # the producer time is back to 0


def test_reset_communication_resets_the_communication_objects_only() -> None:
    bench = rig()
    bench.write(obj.MAX_TORQUE, 0, u16(200))
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(10))
    bench.enable()
    bench.step(CW_ENABLE_OPERATION, 300)
    bench.take()
    bench.nmt(NmtCommand.RESET_COMMUNICATION, 0.5)
    drive = bench.drive
    assert bench.take() == [(HEARTBEAT, b"\x00")]
    assert drive.nmt_state is NmtState.PRE_OPERATIONAL
    assert drive.power_state is PowerState.SWITCH_ON_DISABLED  # it lost its PDOs: the master re-enables
    assert drive.applied_torque_nm == 0.0
    assert drive.value(0x1800, 2) == 255  # communication objects: factory
    assert drive.value(0x1A00, 0) == 1
    assert drive.value(obj.PRODUCER_HEARTBEAT_TIME) == 0
    assert drive.value(obj.MAX_TORQUE) == 200  # device objects: kept
    assert drive.value(obj.MODES_OF_OPERATION) == obj.MODE_CYCLIC_SYNCHRONOUS_TORQUE


def test_reset_communication_keeps_a_state_without_torque() -> None:
    bench = rig()
    bench.configure()
    bench.nmt(NmtCommand.START)
    bench.step(CW_SHUTDOWN)
    bench.step(CW_SWITCH_ON)
    bench.nmt(NmtCommand.RESET_COMMUNICATION)
    assert bench.drive.power_state is PowerState.SWITCHED_ON


# ---------------------------------------------------------------------------- heartbeat producer


def test_heartbeats_come_exactly_at_the_producer_period_in_robot_time() -> None:
    bench = rig()
    bench.take()
    times = []
    for ms in range(0, 701):
        now = ms / 1000
        if ms == 50:
            assert bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(100), now) == ok(obj.PRODUCER_HEARTBEAT_TIME, 0)
        if ms == 400:
            bench.nmt(NmtCommand.START, now)
        bench.drive.advance(now)
        times += [(ms, data) for cob, data in bench.take() if cob == HEARTBEAT]
    pre, op = b"\x7f", b"\x05"
    # One more at NMT start (a heartbeat at every NMT state change, as CANopenNode sends): the grid stays.
    assert times == [(150, pre), (250, pre), (350, pre), (400, op), (450, op), (550, op), (650, op)]


def test_a_late_advance_sends_one_heartbeat_and_keeps_the_period_grid() -> None:
    bench = rig()
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(100), 0.0)
    bench.drive.advance(0.55)
    assert bench.on(HEARTBEAT) == [b"\x7f"]
    bench.drive.advance(0.599)
    assert bench.on(HEARTBEAT) == []
    bench.drive.advance(0.6)
    assert bench.on(HEARTBEAT) == [b"\x7f"]


def test_a_producer_time_of_zero_stops_the_heartbeat() -> None:
    bench = rig()
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(10), 0.0)
    bench.drive.advance(0.01)
    assert bench.on(HEARTBEAT) == [b"\x7f"]
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(0), 0.015)
    bench.drive.advance(1.0)
    assert bench.on(HEARTBEAT) == []


# ---------------------------------------------------------------------------- heartbeat consumer


@pytest.mark.parametrize("step_s", [1 / 1024, 0.0025, 0.001])
def test_the_rpdo_deadline_faults_at_the_first_advance_past_it(step_s: float) -> None:
    """advance() skips the deadline check while no deadline can run out: never past the first late advance."""
    bench = rig()
    bench.enable()
    assert bench.write(0x1400, 5, u16(10)) == ok(0x1400, 5)  # RPDO1's event timer: a 10 ms deadline
    deadline_s = 0.010
    last_rpdo_s, faulted_at = 0.0, None
    for n in range(1, 400):
        now = n * step_s
        if now < 0.1:  # the master commands until 0.1 s, then goes quiet
            bench.step(CW_ENABLE_OPERATION, 0, now)
            last_rpdo_s = now
        bench.drive.advance(now)
        if faulted_at is None and any(data[:2] == struct.pack("<H", 0x8250) for data in bench.on(EMCY)):
            faulted_at = now
    assert faulted_at == next(k * step_s for k in range(1, 400) if k * step_s - last_rpdo_s > deadline_s)


def consumer_rig(consumer_ms: int = 100) -> Rig:
    bench = rig()
    assert bench.write(obj.CONSUMER_HEARTBEAT_TIME, 1, u32(MASTER << 16 | consumer_ms)) == ok(0x1016, 1)
    return bench


def master_heartbeat(bench: Rig, now_s: float) -> None:
    bench.drive.receive(0x700 + MASTER, b"\x05", now_s)


def test_the_consumer_faults_the_drive_when_the_master_goes_silent() -> None:
    bench = consumer_rig(100)
    bench.enable()
    bench.step(CW_ENABLE_OPERATION, 300)
    drive = bench.drive
    emcys = []
    for ms in range(0, 600):
        now = ms / 1000
        if ms % 50 == 0 and ms <= 300:
            master_heartbeat(bench, now)
        drive.advance(now)
        emcys += [(ms, data) for cob, data in bench.take() if cob == EMCY]
        if ms <= 400:
            assert drive.power_state is PowerState.OPERATION_ENABLED, ms
    assert emcys == [(401, emcy(0x8130, 0x11))]  # silent for more than 100 ms after the heartbeat at 300 ms
    assert drive.power_state is PowerState.FAULT  # through FAULT REACTION ACTIVE at the next advance
    assert drive.value(obj.ERROR_CODE) == 0x8130
    assert drive.value(obj.ERROR_REGISTER) == 0x11
    assert drive.applied_torque_nm == 0.0


def test_the_consumer_waits_for_the_first_heartbeat_of_the_master() -> None:
    bench = consumer_rig(100)
    bench.enable()
    for ms in range(0, 1000, 10):
        bench.drive.advance(ms / 1000)
    assert bench.drive.power_state is PowerState.OPERATION_ENABLED


def test_the_consumer_counts_from_its_configuration_when_the_master_was_heard_before() -> None:
    bench = rig()
    master_heartbeat(bench, 0.0)
    bench.enable(0.0)
    bench.write(obj.CONSUMER_HEARTBEAT_TIME, 1, u32(MASTER << 16 | 100), 0.2)
    bench.drive.advance(0.3)
    assert bench.drive.power_state is PowerState.OPERATION_ENABLED
    bench.drive.advance(0.301)
    assert bench.drive.power_state is PowerState.FAULT_REACTION_ACTIVE


def test_the_consumer_hears_only_the_node_it_was_told_to_watch() -> None:
    bench = consumer_rig(100)
    bench.enable()
    for ms in range(0, 500, 10):
        bench.drive.receive(0x700 + MASTER - 1, b"\x05", ms / 1000)  # another node's heartbeat
        bench.drive.receive(0x700 + MASTER, b"", ms / 1000)  # not a heartbeat: no state byte
        bench.drive.advance(ms / 1000)
    assert bench.drive.power_state is PowerState.OPERATION_ENABLED  # never armed: the master was never heard
    master_heartbeat(bench, 0.5)
    bench.drive.advance(0.6)
    assert bench.drive.power_state is PowerState.OPERATION_ENABLED
    bench.drive.advance(0.601)
    assert bench.drive.power_state is PowerState.FAULT_REACTION_ACTIVE


def test_the_consumer_faults_only_an_operational_drive() -> None:
    bench = consumer_rig(100)
    master_heartbeat(bench, 0.0)
    bench.drive.advance(0.5)
    assert bench.drive.power_state is PowerState.SWITCH_ON_DISABLED
    bench.nmt(NmtCommand.START, 0.5)
    bench.drive.advance(0.501)  # the master is still silent
    assert bench.drive.power_state is PowerState.FAULT_REACTION_ACTIVE
    assert bench.on(EMCY) == [emcy(0x8130, 0x11)]


def test_the_consumer_reports_one_loss_once() -> None:
    bench = consumer_rig(100)
    bench.enable()
    master_heartbeat(bench, 0.0)
    for ms in range(0, 1000, 10):
        bench.drive.advance(ms / 1000)
    assert bench.on(EMCY) == [emcy(0x8130, 0x11)]


@pytest.mark.parametrize("entry", [NODE << 16 | 100, 0x01_7F_0064, 0x80 << 16 | 100])
def test_a_consumer_entry_that_cannot_be_is_refused(entry: int) -> None:
    bench = rig()
    assert bench.write(obj.CONSUMER_HEARTBEAT_TIME, 1, u32(entry)) == abort(0x1016, 1, 0x06090030)


# ---------------------------------------------------------------------------- e-stop


def test_either_e_stop_takes_the_power_stage_off_and_holds_it_off() -> None:
    bench = rig()
    bench.enable()
    bench.step(CW_ENABLE_OPERATION, 300)
    drive = bench.drive
    assert drive.applied_torque_nm == pytest.approx(3.0)
    bench.take()
    bench.step(CW_ENABLE_OPERATION, 300, operator=True)
    assert drive.power_state is PowerState.SWITCH_ON_DISABLED
    assert drive.applied_torque_nm == 0.0
    status = struct.unpack_from("<H", bench.on(TPDO1)[0])[0]
    assert status == SW_OFF | SW_ESTOP_OPERATOR
    for controlword in (CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION):  # pressed: it cannot leave
        bench.step(controlword, 300, pilot=True)
        assert drive.power_state is PowerState.SWITCH_ON_DISABLED
    assert struct.unpack_from("<H", bench.on(TPDO1)[-1])[0] == SW_OFF | SW_ESTOP_PILOT
    assert bench.write(obj.CONTROLWORD, 0, u16(CW_SHUTDOWN)) == ok(obj.CONTROLWORD, 0)
    assert drive.power_state is PowerState.SWITCH_ON_DISABLED  # not by SDO either
    for controlword in (CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION):  # released
        bench.step(controlword, 300)
    assert drive.applied_torque_nm == pytest.approx(3.0)


def test_the_e_stop_acts_outside_operational_too() -> None:
    bench = rig()
    bench.write(obj.CONTROLWORD, 0, u16(CW_SHUTDOWN))
    assert bench.drive.power_state is PowerState.READY_TO_SWITCH_ON
    bench.sync(0.0, operator=True)
    assert bench.drive.power_state is PowerState.SWITCH_ON_DISABLED
    assert bench.drive.value(obj.STATUSWORD) == SW_OFF | SW_ESTOP_OPERATOR


# ---------------------------------------------------------------------------- injected faults


def test_unknown_fault_kinds_and_misplaced_durations_are_refused() -> None:
    drive = rig().drive
    with pytest.raises(ValueError, match="unknown fault kind"):
        drive.inject("bus_off", 0.0)
    with pytest.raises(ValueError, match="duration"):
        drive.inject("heartbeat_loss", 0.0, 1.0)
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="duration"):
            drive.inject("drop_frames", 0.0, bad)


@pytest.mark.parametrize("reset", [NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION])
def test_heartbeat_loss_stops_only_the_heartbeat_until_a_reset(reset: NmtCommand) -> None:
    bench = rig()
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(10))
    bench.enable()
    bench.drive.advance(0.01)
    assert bench.on(HEARTBEAT) == [b"\x05"]
    bench.drive.inject("heartbeat_loss", 0.012)
    for ms in range(12, 100):
        bench.drive.advance(ms / 1000)
    assert bench.on(HEARTBEAT) == []
    bench.sync(0.1)
    assert [cob for cob, _ in bench.take()] == [TPDO1, TPDO2]
    assert bench.read(0x1000, 0, 0.1) is not None
    bench.nmt(reset, 0.2)
    assert bench.on(HEARTBEAT) == [b"\x00"]
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(10), 0.2)
    bench.drive.advance(0.21)
    assert bench.on(HEARTBEAT) == [b"\x7f"]


def fault_reset(bench: Rig, now_s: float = 0.0) -> None:
    """The master's fault reset: disable voltage, then the rising edge of bit 7."""
    bench.step(CW_DISABLE_VOLTAGE, 0, now_s)
    bench.step(CW_FAULT_RESET, 0, now_s)


@pytest.mark.parametrize(
    ("kind", "frame", "code", "register"),
    [
        ("emcy", bytes((0x10, 0x43, 0x09, 0x00)), 0x4310, 0x09),  # a short EMCY: 4 bytes
        ("drive_fault", bytes((0x10, 0x23, 0x03, 0, 0, 0, 0, 0)), 0x2310, 0x03),
    ],
)
def test_a_drive_fault_and_its_reset(kind: str, frame: bytes, code: int, register: int) -> None:
    bench = rig()
    bench.enable()
    bench.step(CW_ENABLE_OPERATION, 300)
    drive = bench.drive
    bench.take()
    drive.inject(kind, 0.1)
    assert bench.take() == [(EMCY, frame)]
    assert drive.power_state is PowerState.FAULT_REACTION_ACTIVE
    assert drive.applied_torque_nm == 0.0
    assert (drive.value(obj.ERROR_CODE), drive.value(obj.ERROR_REGISTER)) == (code, register)
    drive.advance(0.1)
    assert drive.power_state is PowerState.FAULT
    bench.step(CW_ENABLE_OPERATION, 300, 0.102)  # the master keeps asking: no effect
    assert struct.unpack_from("<H", bench.on(TPDO1)[0])[0] == statusword_of(PowerState.FAULT)
    assert drive.applied_torque_nm == 0.0
    fault_reset(bench, 0.104)
    assert bench.on(EMCY) == [bytes(8)]  # the error reset: code 0, register 0, 8 bytes
    assert drive.power_state is PowerState.SWITCH_ON_DISABLED
    assert (drive.value(obj.ERROR_CODE), drive.value(obj.ERROR_REGISTER)) == (0, 0)
    for controlword in (CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION):
        bench.step(controlword, 300, 0.106)
    assert drive.applied_torque_nm == pytest.approx(3.0)


def test_a_fault_reset_needs_a_rising_edge() -> None:
    bench = rig()
    bench.enable()
    bench.step(CW_FAULT_RESET)  # bit 7 already high when the fault comes
    bench.drive.inject("drive_fault", 0.0)
    bench.sync(0.002)
    bench.step(CW_FAULT_RESET, 0, 0.004)
    assert bench.drive.power_state is PowerState.FAULT
    bench.step(CW_DISABLE_VOLTAGE, 0, 0.006)
    bench.step(CW_FAULT_RESET, 0, 0.008)
    assert bench.drive.power_state is PowerState.SWITCH_ON_DISABLED


def test_a_fault_survives_reset_communication() -> None:
    bench = rig()
    bench.enable()
    bench.drive.inject("drive_fault", 0.0)
    bench.nmt(NmtCommand.RESET_COMMUNICATION, 0.01)
    assert bench.drive.power_state is PowerState.FAULT_REACTION_ACTIVE
    assert bench.drive.value(obj.ERROR_CODE) == 0x2310
    assert bench.drive.value(obj.ERROR_REGISTER) == 0x03


def test_no_emcy_while_stopped() -> None:
    bench = rig()
    bench.nmt(NmtCommand.STOP)
    bench.take()
    bench.drive.inject("drive_fault", 0.0)
    assert bench.take() == []
    assert bench.drive.power_state is PowerState.FAULT_REACTION_ACTIVE


@pytest.mark.parametrize("reset", [NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION])
def test_a_frozen_pdo_engine_sends_no_tpdo_until_a_reset(reset: NmtCommand) -> None:
    bench = rig()
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(10))
    bench.enable()
    bench.drive.inject("frozen_pdo", 0.0)
    bench.step(CW_ENABLE_OPERATION, 300, 0.002)
    assert bench.take() == []
    assert bench.drive.applied_torque_nm == pytest.approx(3.0)  # the RPDOs still act
    bench.drive.advance(0.01)
    assert bench.take() == [(HEARTBEAT, b"\x05")]
    assert bench.read(0x1000, 0, 0.01) is not None
    bench.nmt(reset, 0.02)
    bench.configure(0.02)
    bench.nmt(NmtCommand.START, 0.02)
    bench.sync(0.022)
    assert [cob for cob, _ in bench.take()] == [TPDO1, TPDO2]


def test_dropped_frames_are_lost_both_ways_then_the_drive_works_again() -> None:
    bench = rig()
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(10))
    bench.enable()
    drive = bench.drive
    drive.inject("drop_frames", 0.005)
    assert DEFAULT_DROP_S == 0.02
    assert bench.write(obj.MAX_TORQUE, 0, u16(100), 0.006) is None  # the request is lost
    assert drive.value(obj.MAX_TORQUE) == 1000
    bench.step(CW_ENABLE_OPERATION, 300, 0.008)  # the RPDO and the SYNC are lost
    assert drive.applied_torque_nm == 0.0
    drive.advance(0.01)  # a heartbeat was due: lost
    drive.inject("emcy", 0.012)
    assert bench.take() == []
    assert drive.power_state is PowerState.FAULT_REACTION_ACTIVE
    # At 25 ms, 20 ms after the injection, it works again on its own.
    assert bench.write(obj.MAX_TORQUE, 0, u16(100), 0.025) == ok(obj.MAX_TORQUE, 0)
    drive.advance(0.03)
    assert bench.on(HEARTBEAT) == [b"\x05"]
    bench.sync(0.03)
    assert [cob for cob, _ in bench.take()] == [TPDO1, TPDO2]


def test_clearing_injected_causes_leaves_a_latched_fault_to_the_fault_reset() -> None:
    bench = rig()
    bench.write(obj.PRODUCER_HEARTBEAT_TIME, 0, u16(10))
    bench.enable()
    drive = bench.drive
    for kind in FAULT_KINDS:
        drive.inject(kind, 0.001)
    drive.clear_injected(0.004)
    drive.advance(0.01)
    assert bench.on(HEARTBEAT) == [b"\x05"]  # on its grid again, frames pass
    bench.sync(0.012)
    assert [cob for cob, _ in bench.take()] == [TPDO1, TPDO2]
    assert drive.power_state is PowerState.FAULT  # emcy and drive_fault: latched in the drive
    fault_reset(bench, 0.014)
    assert drive.power_state is PowerState.SWITCH_ON_DISABLED


def test_power_on_clears_every_injected_fault() -> None:
    bench = rig()
    for kind in FAULT_KINDS:
        bench.drive.inject(kind, 0.0)
    bench.take()
    bench.drive.power_on(0.001)
    assert bench.take() == [(HEARTBEAT, b"\x00")]
    assert bench.drive.power_state is PowerState.SWITCH_ON_DISABLED
    assert bench.drive.value(obj.ERROR_REGISTER) == 0


# ---------------------------------------------------------------------------- RPDO length, validity, type


def test_an_rpdo_of_the_wrong_length_is_not_processed_and_reported_once() -> None:
    bench = rig()
    bench.enable()
    drive = bench.drive
    drive.receive(RPDO1, struct.pack("<Hb", CW_ENABLE_OPERATION, 100), 0.0)
    assert bench.take() == [(EMCY, emcy(0x8210, 0x11))]
    drive.receive(RPDO1, struct.pack("<Hhh", CW_ENABLE_OPERATION, 100, 0), 0.0)
    assert bench.take() == []  # still the same error: not reported again
    bench.sync(0.002)
    assert drive.value(obj.TARGET_TORQUE) == 0
    assert drive.value(obj.ERROR_REGISTER) == 0x11
    bench.rpdo(CW_ENABLE_OPERATION, 100, 0.004)
    assert bench.on(EMCY) == [emcy(0x0000, 0x00)]  # the error is gone
    bench.sync(0.004)
    assert drive.applied_torque_nm == pytest.approx(1.0)


def test_an_rpdo_made_invalid_before_the_sync_is_dropped() -> None:
    bench = rig()
    bench.enable()
    bench.rpdo(CW_ENABLE_OPERATION, 300)
    assert bench.write(0x1400, 1, u32(0x8000_0205)) == ok(0x1400, 1)
    bench.sync(0.002)
    assert bench.drive.applied_torque_nm == 0.0
    bench.step(CW_ENABLE_OPERATION, 300, 0.004)  # an invalid RPDO does not exist
    assert bench.drive.applied_torque_nm == 0.0


# ---------------------------------------------------------------------------- SDO server


def invalidated_tpdo1(bench: Rig) -> None:
    """TPDO1 invalid with no object mapped: its mapping may change."""
    assert bench.write(0x1800, 1, u32(0x8000_0185)) == ok(0x1800, 1)
    assert bench.write(0x1A00, 0, u8(0)) == ok(0x1A00, 0)


def test_reads_return_the_values_in_their_own_size() -> None:
    bench = rig()
    assert bench.read(0x1000) == sdo.upload_response(0x1000, 0, u32(0x00020192))
    assert bench.read(0x1001) == sdo.upload_response(0x1001, 0, u8(0))
    assert bench.read(0x1800, 2) == sdo.upload_response(0x1800, 2, u8(255))
    assert bench.read(obj.STATUSWORD) == sdo.upload_response(obj.STATUSWORD, 0, u16(SW_OFF))
    bench.sync(0.0, tau=-2.5)
    assert bench.read(obj.TORQUE_ACTUAL) == sdo.upload_response(obj.TORQUE_ACTUAL, 0, struct.pack("<h", -250))


@pytest.mark.parametrize(
    ("request_", "answer"),
    [
        (sdo.upload_request(0x1234, 0), abort(0x1234, 0, 0x06020000)),
        (sdo.upload_request(0x1018, 9), abort(0x1018, 9, 0x06090011)),
        (sdo.upload_request(0x1017, 1), abort(0x1017, 1, 0x06090011)),
        (sdo.download_request(0x1234, 0, u8(1)), abort(0x1234, 0, 0x06020000)),
        (sdo.download_request(0x1000, 0, u32(0)), abort(0x1000, 0, 0x06010002)),
        (sdo.download_request(0x1008, 0, u8(0x41)), abort(0x1008, 0, 0x06010002)),
        (sdo.download_request(obj.STATUSWORD, 0, u16(0)), abort(obj.STATUSWORD, 0, 0x06010002)),
        (sdo.download_request(obj.MAX_TORQUE, 0, u32(100)), abort(obj.MAX_TORQUE, 0, 0x06070010)),
        (sdo.download_request(obj.MAX_TORQUE, 0, u8(100)), abort(obj.MAX_TORQUE, 0, 0x06070010)),
        (sdo.download_request(obj.MODES_OF_OPERATION, 0, u8(8)), abort(obj.MODES_OF_OPERATION, 0, 0x06090030)),
        (sdo.download_request(0x1A00, 1, u32(0x60640020)), abort(0x1A00, 1, 0x06090030)),  # COB-ID valid
        (sdo.download_request(0x1A00, 0, u8(0)), abort(0x1A00, 0, 0x06090030)),
        (sdo.download_request(0x1800, 1, u32(0x186)), abort(0x1800, 1, 0x06090030)),  # valid: cannot move
        (sdo.download_request(0x1800, 1, u32(0x2000_0185)), abort(0x1800, 1, 0x06090030)),  # 29-bit
        (sdo.download_request(0x1800, 1, u32(0x8000_0985)), abort(0x1800, 1, 0x06090030)),  # bits 11-28
        (sdo.download_request(0x1800, 1, u32(0x8000_0605)), abort(0x1800, 1, 0x06090030)),  # an SDO's CAN-ID
        (sdo.download_request(0x1800, 1, u32(0x8000_0705)), abort(0x1800, 1, 0x06090030)),  # a heartbeat's
        (sdo.download_request(0x1800, 2, u8(252)), abort(0x1800, 2, 0x06090030)),  # RTR only
        (sdo.download_request(0x1800, 3, u16(10)), abort(0x1800, 3, 0x06090030)),  # inhibit while valid
        (sdo.upload_request(0x1008, 0), abort(0x1008, 0, 0x06010000)),  # 18 bytes: not expedited
        (bytes((0xE0, 0x00, 0x10, 0x00, 0, 0, 0, 0)), abort(0x1000, 0, 0x05040001)),
        (bytes((0x21, 0x00, 0x10, 0x00, 4, 0, 0, 0)), abort(0x1000, 0, 0x05040001)),  # segmented download
        (bytes((0x40, 0x00, 0x10)), abort(0x0000, 0, 0x05040001)),  # too short to be a request
    ],
)
def test_sdo_requests_the_drive_refuses_get_the_right_abort_code(request_: bytes, answer: bytes) -> None:
    bench = rig()
    bench.take()
    bench.drive.receive(SDO_RX, request_, 0.0)
    assert bench.take() == [(SDO_TX, answer)]


@pytest.mark.parametrize(
    ("entry", "code"),
    [
        (0x60760020, 0x06040041),  # rated torque: not mappable
        (0x60400020, 0x06040041),  # the controlword is 16 bits, not 32
        (0x12340010, 0x06040041),  # no such object
        (0x00000000, 0x06040041),
    ],
)
def test_a_tpdo_mapping_entry_that_cannot_be_mapped_is_refused(entry: int, code: int) -> None:
    bench = rig()
    invalidated_tpdo1(bench)
    assert bench.write(0x1A00, 1, u32(entry)) == abort(0x1A00, 1, code)
    assert bench.drive.value(0x1A00, 1) == 0x60410010


def test_an_rpdo_maps_only_what_the_master_may_write() -> None:
    bench = rig()
    assert bench.write(0x1400, 1, u32(0x8000_0205)) == ok(0x1400, 1)
    assert bench.write(0x1600, 0, u8(0)) == ok(0x1600, 0)
    assert bench.write(0x1600, 1, u32(0x60640020)) == abort(0x1600, 1, 0x06040041)  # read-only
    assert bench.write(0x1600, 1, u32(0x60710010)) == ok(0x1600, 1)


def test_a_mapping_longer_than_a_can_frame_is_refused_at_its_count() -> None:
    bench = rig()
    invalidated_tpdo1(bench)
    for sub, entry in enumerate((0x60640020, 0x20100020, 0x60410010), start=1):
        assert bench.write(0x1A00, sub, u32(entry)) == ok(0x1A00, sub)
    assert bench.write(0x1A00, 0, u8(3)) == abort(0x1A00, 0, 0x06040042)
    assert bench.write(0x1A00, 0, u8(5)) == abort(0x1A00, 0, 0x06090031)  # 4 entries only
    assert bench.write(0x1A00, 0, u8(2)) == ok(0x1A00, 0)


def test_a_mapping_entry_changes_only_while_the_count_is_zero() -> None:
    bench = rig()
    assert bench.write(0x1800, 1, u32(0x8000_0185)) == ok(0x1800, 1)
    assert bench.write(0x1A00, 1, u32(0x60640020)) == abort(0x1A00, 1, 0x06010000)
    assert bench.write(0x1A00, 0, u8(0)) == ok(0x1A00, 0)
    assert bench.write(0x1A00, 1, u32(0x60640020)) == ok(0x1A00, 1)


def test_a_count_over_factory_empty_entries_is_refused() -> None:
    bench = rig()
    invalidated_tpdo1(bench)
    assert bench.write(0x1A00, 0, u8(2)) == abort(0x1A00, 0, 0x06040041)  # entry 2 is still 0


def test_a_write_without_its_size_takes_the_object_s_size() -> None:
    bench = rig()
    bench.take()
    bench.drive.receive(SDO_RX, bytes((0x22, 0x72, 0x60, 0x00, 0xC8, 0x00, 0xEE, 0xEE)), 0.0)
    assert bench.take() == [(SDO_TX, ok(obj.MAX_TORQUE, 0))]
    assert bench.drive.value(obj.MAX_TORQUE) == 200


def test_a_client_abort_is_not_answered() -> None:
    bench = rig()
    bench.take()
    bench.drive.receive(SDO_RX, sdo.abort_frame(0x1000, 0, 0x05040000), 0.0)
    assert bench.take() == []


def test_reading_a_write_only_object_is_refused(tmp_path: Path) -> None:
    text = DEFAULT_EDS.read_text()
    head, tail = text.split("[606C]", 1)
    eds = tmp_path / "write_only.eds"
    eds.write_text(head + "[606C]" + tail.replace("AccessType=ro", "AccessType=wo", 1))
    bench = rig(dictionary=DriveDictionary(eds))
    assert bench.read(obj.VELOCITY_ACTUAL) == abort(obj.VELOCITY_ACTUAL, 0, 0x06010001)


# ---------------------------------------------------------------------------- properties

#: Controlwords: None is what a master would send next (PowerStepper wanting torque, fault resets included);
#: the others are a broken master's: the commands out of order, their neighbours, anything.
CONTROLWORDS = st.one_of(
    st.none(),
    st.sampled_from([CW_DISABLE_VOLTAGE, CW_QUICK_STOP, CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION]),
    st.sampled_from([CW_FAULT_RESET, 0x0B, 0x8F, 0x0E, 0x03]),
    st.integers(0, 0xFFFF),
    st.none(),
)
STEP = st.tuples(
    CONTROLWORDS,
    st.integers(-32768, 32767),
    st.integers(0, 19).map(lambda n: n == 0),  # operator e-stop, one step in twenty
    st.integers(0, 19).map(lambda n: n == 0),  # pilot e-stop
    st.integers(0, 29).map(lambda n: {0: "drive_fault", 1: "emcy"}.get(n)),  # a fault, one step in fifteen
)


@given(steps=st.lists(STEP, min_size=3, max_size=60))
def test_random_controlwords_never_enable_torque_without_the_sequence(
    steps: list[tuple[int | None, int, bool, bool, str | None]],
) -> None:
    bench = rig()
    bench.configure()
    bench.nmt(NmtCommand.START)
    drive = bench.drive
    master = PowerStepper(timeout_ticks=1000)
    previous = drive.power_state
    passed_ready = False  # READY TO SWITCH ON seen since the drive was last off or faulted
    faulted = False
    for n, (chosen, torque, operator, pilot, fault) in enumerate(steps):
        now = n * 0.002
        if drive.power_state is PowerState.FAULT:
            master.request_fault_reset()
        controlword = master.step(drive.power_state, want_torque=True).controlword if chosen is None else chosen
        if fault is not None:
            drive.inject(fault, now)
            faulted = True
            previous = drive.power_state
            assert drive.applied_torque_nm == 0.0
        bench.step(controlword, torque, now, operator=operator, pilot=pilot)
        drive.advance(now)
        state = drive.power_state
        if state is PowerState.FAULT:
            faulted = True
        elif faulted and state is not PowerState.FAULT_REACTION_ACTIVE:
            faulted = False  # left FAULT: only through the fault reset, to SWITCH ON DISABLED
            assert state is PowerState.SWITCH_ON_DISABLED
            assert previous in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)
            assert controlword & CW_FAULT_RESET
        if state in (PowerState.SWITCH_ON_DISABLED, PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
            passed_ready = False
        passed_ready |= state is PowerState.READY_TO_SWITCH_ON
        if state is PowerState.OPERATION_ENABLED:
            assert passed_ready
            assert previous in (PowerState.READY_TO_SWITCH_ON, PowerState.SWITCHED_ON, PowerState.OPERATION_ENABLED)
        if operator or pilot or faulted:
            assert state not in (PowerState.READY_TO_SWITCH_ON, PowerState.SWITCHED_ON, PowerState.OPERATION_ENABLED)
            assert drive.applied_torque_nm == 0.0
        if drive.applied_torque_nm != 0.0:
            assert state is PowerState.OPERATION_ENABLED
            assert abs(drive.applied_torque_nm) <= 10.0  # the factory max torque: 1000 per mille of 10 Nm
        previous = state


#: Writable objects an RPDO may map, and how a frame carries them.
RPDO_OBJECTS = {0x60400010: "H", 0x60710010: "h", 0x60720010: "H", 0x60600008: "b"}
WATCHED = (obj.CONTROLWORD, obj.TARGET_TORQUE, obj.MAX_TORQUE)
FRAME_OP = st.tuples(
    st.just("frame"),
    st.sampled_from([0x205, 0x205, 0x205, 0x206]),
    st.one_of(st.binary(max_size=8), st.binary(min_size=2, max_size=2), st.binary(min_size=4, max_size=4)),
)
SYNC_OP = st.tuples(st.just("sync"), st.just(0), st.just(0))
RPDO_OPS = st.one_of(
    FRAME_OP,
    SYNC_OP,
    st.tuples(
        st.just("comm"),
        st.sampled_from([1, 2]),
        st.one_of(
            st.sampled_from([0x205, 0x8000_0205, 0x206, 0x8000_0206, 1, 255, 254, 0, 240, 7]),
            st.integers(0, 2**32 - 1),
        ),
    ),
    st.tuples(
        st.just("mapping"),
        st.integers(0, 4),
        st.one_of(st.sampled_from([*RPDO_OBJECTS, 0x60640020, 0, 1, 2, 3]), st.integers(0, 2**32 - 1)),
    ),
    st.tuples(
        st.just("nmt"),
        st.sampled_from([NmtCommand.START, NmtCommand.STOP, NmtCommand.ENTER_PRE_OPERATIONAL]),
        st.just(0),
    ),
    FRAME_OP,
    SYNC_OP,
)


@dataclass
class RpdoModel:
    """What the watched objects must hold: an RPDO acts only when valid and operational, and the right length."""

    values: dict[int, int]
    pending: list[tuple[int, int]] | None = None

    def frame(self, drive: SimulatedSeaDrive, cob_id: int, data: bytes) -> None:
        cob = drive.value(0x1400, 1)
        if drive.nmt_state is not NmtState.OPERATIONAL or cob & 0x8000_0000 or cob & 0x7FF != cob_id:
            return
        entries = [drive.value(0x1600, n) for n in range(1, drive.value(0x1600, 0) + 1)]
        layout = "<" + "".join(RPDO_OBJECTS[e] for e in entries)  # only these can be in an accepted mapping
        if len(data) != struct.calcsize(layout):
            return
        writes = [(e >> 16, v) for e, v in zip(entries, struct.unpack(layout, data), strict=True) if e >> 16 in WATCHED]
        if drive.value(0x1400, 2) >= 254:
            self.values.update(writes)
        else:
            self.pending = writes

    def sync(self, drive: SimulatedSeaDrive) -> None:
        if drive.nmt_state is NmtState.OPERATIONAL and self.pending is not None:
            self.values.update(self.pending)
        self.pending = None


@given(configured=st.booleans(), started=st.booleans(), ops=st.lists(RPDO_OPS, min_size=4, max_size=40))
def test_random_sdo_writes_never_let_an_rpdo_act_unless_valid_and_operational(
    configured: bool, started: bool, ops: list[tuple[str, int, int | bytes]]
) -> None:
    bench = rig()
    drive = bench.drive
    if configured:
        bench.configure()  # the DAROR RPDO1: synchronous, controlword and target torque
    if started:
        bench.nmt(NmtCommand.START)
    model = RpdoModel({index: drive.value(index) for index in WATCHED})
    for n, (kind, a, b) in enumerate(ops):
        now = n * 0.002
        if kind == "comm" or kind == "mapping":
            index = 0x1400 if kind == "comm" else 0x1600
            size = 4 if (kind == "comm" and a == 1) or (kind == "mapping" and a > 0) else 1
            answer = bench.write(index, a, int(b).to_bytes(8, "little")[:size], now)  # type: ignore[arg-type]
            assert (answer is None) == (drive.nmt_state is NmtState.STOPPED)
            made_invalid = a == 1 and int(b) & 0x8000_0000  # type: ignore[arg-type]
            if answer is not None and answer[0] == 0x60 and kind == "comm" and (made_invalid or a == 2):
                model.pending = None  # invalid, or of another type: the buffered data are gone
        elif kind == "nmt":
            if drive.nmt_state is NmtState.OPERATIONAL and a != NmtCommand.START:
                model.pending = None
            bench.nmt(NmtCommand(a), now)
        elif kind == "frame":
            model.frame(drive, a, b)  # type: ignore[arg-type]
            drive.receive(a, b, now)  # type: ignore[arg-type]
        else:
            bench.take()
            model.sync(drive)
            bench.sync(now)
            if drive.nmt_state is not NmtState.OPERATIONAL:
                assert [cob for cob, _ in bench.take() if cob in (TPDO1, TPDO2)] == []
        assert {index: drive.value(index) for index in WATCHED} == model.values
        if drive.nmt_state is not NmtState.OPERATIONAL:
            assert drive.power_state not in (PowerState.OPERATION_ENABLED, PowerState.QUICK_STOP_ACTIVE)
