"""CiA 402 drives on an independent CANopen stack (durand), knowing only their EDS: a test harness.

The drives share nothing with ``hal.canopen`` but the EDS file and the bus: their object
dictionary is built from the EDS (``hal/canopen/daror_sea.eds`` for the DAROR SEA drives, or each
node's EDS of a robot file; parsed by ``canopen``, served by durand's SDO server, sent and
received by durand's PDOs, NMT, heartbeat and EMCY), and the CiA 402 application behind it is
written here, from the standard's tables, without importing the backend's own state machine. A
master that talks to these drives correctly talks CANopen, not merely to itself.

Which objects a drive reports its encoders, its spring torque and its e-stop inputs in is its
:class:`DriveWiring`: the DAROR SEA drive's (0x6064, 0x2010, 0x6077, statusword bits 14/15,
:meth:`DriveWiring.daror`), or a robot file node's, read here from the YAML itself
(:func:`robot_file_drives`, not through ``hal``). Values an EDS leaves open (a vendor's EDS has no
0x1000, 0x1018 or 0x6502 value: the device knows them) are a CiA 402 servo drive's: the EDS's
[DeviceInfo] identity and the torque modes the application implements (cst, tq).

Threads (durand is not thread-safe; all of its processing is serialised by one lock)::

    one python-can Notifier thread per drive (durand's CANBusNetwork): every frame a drive
        receives is handled there, holding the lock (NMT, SDO, RPDOs, SYNC -> TPDOs)
    one scheduler thread: durand's timers (heartbeats, inhibit times) on the wall clock, and
        every action of the test (set a joint, inject a fault, read the dictionary), holding the lock

The test's own thread never touches durand: :meth:`DurandDrives.call` runs a function in the
scheduler thread and returns its result. Errors durand swallows (its callbacks run in "ignore"
mode, its listener logs and goes on) are collected in :attr:`DurandDrives.errors`.

What is not about threads is shared with the lock-step drive set (tests/durand_lockstep.py, which
runs the same drives on the caller's thread, in lock-step with the simulated plant): the node
built from an EDS (:func:`create_node`, :func:`durand_dictionary`), the CiA 402 application
(:class:`Cia402Device`), the wiring (:class:`DriveWiring`, :func:`robot_file_drives`), the
collection of durand's swallowed errors (:class:`Errors`, :class:`LogWatch`,
:func:`watch_durand_logs`) and the guard that lets one harness at a time own durand's
process-global scheduler (:func:`claim_durand`).

Units are the EDS's for the DAROR drive: torques in per mille of the rated torque 0x6076 (mNm);
the motor-side position 0x6064 in 0x608F:1 increments per 0x608F:2 revolutions; the load-side
position 0x2010 in 0x2011 increments per revolution. A robot file's drive: its node's scales.
"""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple, TypeVar

import can
import canopen
import durand
import yaml
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from durand.object_dictionary import ObjectDictionary
from durand.scheduler import AbstractScheduler, VirtualScheduler
from durand.services.nmt import StateEnum

__all__ = [
    "DURAND_TPDO_SYNC_WHILE_INACTIVE",
    "EDS_PATH",
    "Cia402Device",
    "DevicePower",
    "DriveWiring",
    "DurandDrives",
    "EdsUnits",
    "Errors",
    "JointCounts",
    "LogWatch",
    "MasterProbe",
    "TimedFrame",
    "WallClockScheduler",
    "claim_durand",
    "create_node",
    "durand_dictionary",
    "fire_due_events",
    "holds_durand",
    "release_durand",
    "robot_file_drives",
    "sdo_requests",
    "sdo_responses",
    "watch_durand_logs",
]

T = TypeVar("T")

#: The drives' EDS (the file the backend ships; the drives know nothing else of the master's side).
EDS_PATH = Path(__file__).resolve().parents[1] / "hal" / "canopen" / "daror_sea.eds"
#: How long a call into the scheduler thread, or a wait for the drives, may take before it is a failure, s.
DEFAULT_TIMEOUT_S = 2.0
#: How often the receive threads look at their stop flag, s (durand's own adapter uses 1 s).
NOTIFIER_TIMEOUT_S = 0.05
#: The longest the scheduler thread sleeps without looking at its timers, s.
SCHEDULER_IDLE_S = 0.01
#: Frames kept per drive and direction (a test runs a few hundred cycles of ~4 frames).
FRAME_LOG_LENGTH = 20_000

# COB-IDs (CiA 301 pre-defined connection set), written out here rather than imported from the backend.
SYNC_COB_ID = 0x080
EMCY_BASE = 0x080
TPDO1_BASE = 0x180
TPDO2_BASE = 0x280
SDO_TX_BASE = 0x580
SDO_RX_BASE = 0x600
HEARTBEAT_BASE = 0x700

# Objects of the CiA 402 application (CiA 402-2 and the DAROR EDS).
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
ERROR_CODE = 0x603F
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
TARGET_TORQUE = 0x6071
TORQUE_ACTUAL = 0x6077
MOTOR_RATED_TORQUE = 0x6076
POSITION_ENCODER_RESOLUTION = 0x608F
LOAD_POSITION_ACTUAL = 0x2010
LOAD_ENCODER_RESOLUTION = 0x2011
PRODUCER_HEARTBEAT_TIME = 0x1017
#: Modes of operation: cyclic synchronous torque, profile torque; the drive applies 0x6071 only in these.
MODE_CST = 10
MODE_TQ = 4
#: Values the device knows where its EDS gives none: a CiA 402 servo drive, its torque modes (tq, cst).
SERVO_DEVICE_TYPE = 0x0002_0192
SUPPORTED_DRIVE_MODES = 0x6502
TORQUE_MODES = 1 << (MODE_TQ - 1) | 1 << (MODE_CST - 1)

# Statusword bits (CiA 402-2 table 30) and the DAROR manufacturer bits 14/15 (the e-stop inputs).
SW_VOLTAGE_ENABLED = 0x0010
SW_REMOTE = 0x0200
SW_ESTOP_OPERATOR = 0x4000
SW_ESTOP_PILOT = 0x8000
# Controlword bits (CiA 402-2 table 28).
CW_SWITCH_ON = 0x0001
CW_ENABLE_VOLTAGE = 0x0002
CW_QUICK_STOP = 0x0004  # active low
CW_ENABLE_OPERATION = 0x0008
CW_FAULT_RESET = 0x0080  # acts on its rising edge

#: Objects durand's Node creates itself (it would overwrite copies): their EDS values are applied after creation.
_DURAND_OWNED = frozenset(
    {0x1000, 0x1001, 0x1005, 0x1008, 0x1009, 0x100A, 0x1014, 0x1015, 0x1017, 0x1018, 0x1021, 0x1022}
)
#: EDS access types durand knows under another name (durand has no rww/rwr: "rw" both ways).
_ACCESS = {"ro": "ro", "wo": "wo", "rw": "rw", "rwr": "rw", "rww": "rw", "const": "const"}

_active_lock = threading.Lock()
_active: list[object] = []  # durand's scheduler is process-global: one harness at a time


def claim_durand(owner: object) -> None:
    """``owner`` (a harness) is the one that sets durand's process-global scheduler until :func:`release_durand`.

    Raises:
        RuntimeError: another harness holds it.
    """
    with _active_lock:
        if _active:
            raise RuntimeError(
                f"a durand harness is already running ({type(_active[0]).__name__}; durand's scheduler is process-global)"
            )
        _active.append(owner)


def release_durand(owner: object) -> None:
    """``owner`` no longer holds durand's scheduler (nothing if it did not)."""
    with _active_lock:
        if owner in _active:
            _active.remove(owner)


def holds_durand(owner: object) -> bool:
    """Whether ``owner`` holds durand's scheduler (:func:`claim_durand`)."""
    with _active_lock:
        return owner in _active


def watch_durand_logs(handler: logging.Handler) -> Callable[[], None]:
    """durand's log records go to ``handler`` alone (durand reports swallowed callback exceptions at DEBUG).

    Returns the function that puts durand's logger back as it was.
    """
    logger = logging.getLogger("durand")
    level, propagate = logger.level, logger.propagate
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    logger.addHandler(handler)

    def unwatch() -> None:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate

    return unwatch


def _durand_owned(index: int) -> bool:
    return index in _DURAND_OWNED or 0x1200 <= index <= 0x12FF or 0x1400 <= index <= 0x1BFF


class TimedFrame(NamedTuple):
    """A frame a drive received or sent (``t_s``: ``time.monotonic()``)."""

    t_s: float
    cob_id: int
    data: bytes


class JointCounts(NamedTuple):
    """What :meth:`DurandDrives.set_joint` wrote: raw values in the EDS's units."""

    motor_increments: int  # 0x6064
    load_increments: int  # 0x2010
    torque_permille: int  # 0x6077


@dataclass(frozen=True)
class EdsUnits:
    """The drive's units, from its EDS.

    Attributes:
        rated_torque_mnm: 0x6076; torques are in per mille of it.
        motor_increments_per_rev: 0x608F:1 / 0x608F:2.
        load_increments_per_rev: 0x2011.
    """

    rated_torque_mnm: int
    motor_increments_per_rev: float
    load_increments_per_rev: float

    @classmethod
    def from_eds(cls, od: canopen.ObjectDictionary) -> EdsUnits:
        resolution = od[POSITION_ENCODER_RESOLUTION]
        return cls(
            rated_torque_mnm=int(od[MOTOR_RATED_TORQUE].default),
            motor_increments_per_rev=resolution[1].default / resolution[2].default,
            load_increments_per_rev=float(od[LOAD_ENCODER_RESOLUTION].default),
        )

    def permille(self, torque_nm: float) -> int:
        """``torque_nm`` in per mille of the rated torque (rounded to the nearest)."""
        return round(torque_nm * 1e6 / self.rated_torque_mnm)

    def motor_increments(self, angle_rad: float) -> int:
        return round(angle_rad * self.motor_increments_per_rev / (2.0 * math.pi))

    def load_increments(self, angle_rad: float) -> int:
        return round(angle_rad * self.load_increments_per_rev / (2.0 * math.pi))


@dataclass(frozen=True)
class DriveWiring:
    """Which objects a drive reports its sensors in, and in which units.

    Attributes:
        motor: the motor-side position object (index, sub); ``rad_per_motor_count`` its scale.
        link: the link-side position object (index, sub); ``rad_per_link_count`` its scale.
        torque: the spring torque object (index, sub), or None (the master computes it from the
            encoders); ``nm_per_torque_count`` its scale.
        estop: the e-stop object (index, sub) or None; ``operator_mask``/``pilot_mask`` its bits;
            ``pressed_when_clear``: wired normally closed.
        torque_gear: the gear ratio between the motor, whose torque 0x6071 and 0x6076 are, and the
            arm (a robot file's ``motor_position.gear_ratio``; 1 for the DAROR drive).
    """

    motor: tuple[int, int]
    rad_per_motor_count: float
    link: tuple[int, int]
    rad_per_link_count: float
    torque: tuple[int, int] | None
    nm_per_torque_count: float
    estop: tuple[int, int] | None
    operator_mask: int = 0
    pilot_mask: int = 0
    pressed_when_clear: bool = False
    torque_gear: float = 1.0

    def applied_torque_nm(self, permille: int, rated_torque_mnm: int) -> float:
        """The torque at the gearbox's output of ``permille`` of the rated torque ``rated_torque_mnm`` (0x6076, mNm), N m."""
        return permille * rated_torque_mnm / 1e6 * self.torque_gear

    @classmethod
    def daror(cls, od: canopen.ObjectDictionary) -> DriveWiring:
        """The DAROR SEA drive's: 0x6064, 0x2010, 0x6077 in its EDS's units, the e-stops in statusword bits 14, 15."""
        units = EdsUnits.from_eds(od)
        return cls(
            (POSITION_ACTUAL, 0), 2.0 * math.pi / units.motor_increments_per_rev,
            (LOAD_POSITION_ACTUAL, 0), 2.0 * math.pi / units.load_increments_per_rev,
            (TORQUE_ACTUAL, 0), units.rated_torque_mnm / 1e6,
            (STATUSWORD, 0), SW_ESTOP_OPERATOR, SW_ESTOP_PILOT,
        )  # fmt: skip

    @property
    def estop_in_statusword(self) -> bool:
        return self.estop == (STATUSWORD, 0)


def robot_file_drives(path: Path) -> dict[int, tuple[Path, DriveWiring]]:
    """Node id -> (its EDS, its wiring) of every node of a robot file, read from the YAML (the schema of docs/canopen.md).

    The motor position's ``gear_ratio`` scales it; a spring torque object without ``nm_per_count``
    is in per mille of ``rated_torque_mnm`` times that ratio.
    """
    data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    drives = {}
    for node in data["nodes"]:
        motor, link, spring, estop = (
            node["motor_position"],
            node["link_position"],
            node["spring_torque"],
            node.get("estop"),
        )
        gear = float(motor.get("gear_ratio", 1.0))
        torque = (spring["index"], spring.get("subindex", 0)) if "index" in spring else None
        nm_per_count = spring.get("nm_per_count") or node["rated_torque_mnm"] / 1e6 * gear
        wired = isinstance(estop, dict)
        drives[int(node["node_id"])] = (
            Path(path).parent / node["eds"],
            DriveWiring(
                (motor["index"], motor.get("subindex", 0)), 2.0 * math.pi / (motor["counts_per_rev"] * gear),
                (link["index"], link.get("subindex", 0)),
                2.0 * math.pi / (link["counts_per_rev"] * link.get("gear_ratio", 1.0)),
                torque, nm_per_count if torque is not None else 0.0,
                (estop["index"], estop.get("subindex", 0)) if wired else None,
                1 << estop["operator_bit"] if wired else 0, 1 << estop["pilot_bit"] if wired else 0,
                bool(estop.get("pressed_when_clear", False)) if wired else False,
                gear,
            ),
        )  # fmt: skip
    return drives


class DevicePower(Enum):
    """The CiA 402 power states the drives take, valued by their statusword bits 0-6 (CiA 402-2 table 30)."""

    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0021 | SW_VOLTAGE_ENABLED
    SWITCHED_ON = 0x0023 | SW_VOLTAGE_ENABLED
    OPERATION_ENABLED = 0x0027 | SW_VOLTAGE_ENABLED
    QUICK_STOP_ACTIVE = 0x0007 | SW_VOLTAGE_ENABLED
    FAULT = 0x0008


def _next_power(state: DevicePower, controlword: int, previous: int) -> DevicePower:
    """What a drive in ``state`` does with ``controlword`` (CiA 402-2 table 28: commands; figure 23: transitions).

    One transition per controlword: "enable operation" (0x0F) in READY TO SWITCH ON switches on
    (transition 3); the next one enables (4).
    """
    if state is DevicePower.FAULT:
        rising = bool(controlword & CW_FAULT_RESET) and not previous & CW_FAULT_RESET
        return DevicePower.SWITCH_ON_DISABLED if rising else state  # 15
    if controlword & CW_FAULT_RESET:
        return state  # the fault reset command outside FAULT: nothing
    if not controlword & CW_ENABLE_VOLTAGE:
        return DevicePower.SWITCH_ON_DISABLED  # disable voltage: 7, 9, 10, 12
    if not controlword & CW_QUICK_STOP:  # quick stop (active low): 11 from operation enabled, else 7 / 10
        return (
            DevicePower.QUICK_STOP_ACTIVE if state is DevicePower.OPERATION_ENABLED else DevicePower.SWITCH_ON_DISABLED
        )
    if state is DevicePower.QUICK_STOP_ACTIVE:
        return DevicePower.SWITCH_ON_DISABLED  # the quick stop completed: 12
    switch_on = bool(controlword & CW_SWITCH_ON)
    enable_operation = bool(controlword & CW_ENABLE_OPERATION)
    if not switch_on:  # shutdown (xxxx x110): 2, 6, 8
        return DevicePower.READY_TO_SWITCH_ON
    if state is DevicePower.SWITCH_ON_DISABLED:
        return state  # switch on (0x07 / 0x0F) needs READY TO SWITCH ON first
    if state is DevicePower.READY_TO_SWITCH_ON:
        return DevicePower.SWITCHED_ON  # 3
    if state is DevicePower.SWITCHED_ON:
        return DevicePower.OPERATION_ENABLED if enable_operation else state  # 4
    return state if enable_operation else DevicePower.SWITCHED_ON  # operation enabled: 5 on disable operation


class Errors:
    """Errors from the drives' threads (durand swallows them): collected, asserted empty by the tests."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: list[str] = []

    def add(self, message: str) -> None:
        with self._lock:
            self._items.append(message)

    def snapshot(self) -> list[str]:
        with self._lock:
            return list(self._items)


#: durand 0.5.0 defect: a synchronous TPDO's SYNC handler stays registered when the TPDO is deactivated
#: (NMT pre-operational or stopped), and calls ``TPDO.transmit``, which fails on the dropped cache
#: (``b"".join(None)``: TypeError, swallowed by durand's callback handler). No frame goes out, which
#: is what CiA 301 wants of a node that is not operational; counted, not an error.
DURAND_TPDO_SYNC_WHILE_INACTIVE = "durand: SYNC handler of an inactive TPDO (node not operational)"


def _durand_defect(exc_info: Any) -> str | None:
    """The known durand defect a swallowed exception is (None: an error)."""
    _, exc, tb = exc_info
    if not isinstance(exc, TypeError) or tb is None:
        return None
    last = tb
    while last.tb_next is not None:
        last = last.tb_next
    code = last.tb_frame.f_code
    tpdo = last.tb_frame.f_locals.get("self")
    node = getattr(tpdo, "node", None)
    if (
        code.co_name == "transmit"
        and code.co_filename.replace("\\", "/").endswith("durand/services/pdo/tpdo.py")
        and getattr(tpdo, "_cache", 0) is None
        and node is not None
        and node.nmt.state != StateEnum.OPERATIONAL
    ):
        return DURAND_TPDO_SYNC_WHILE_INACTIVE
    return None


class LogWatch(logging.Handler):
    """durand's log records that report a swallowed exception (or worse): collected as errors.

    A known durand defect (:func:`_durand_defect`) is counted in :attr:`defects` instead.
    """

    def __init__(self, errors: Errors) -> None:
        super().__init__(logging.DEBUG)
        self._errors = errors
        self.defects: dict[str, int] = {}

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if record.exc_info or record.levelno >= logging.WARNING or "during processing" in message:
            detail = ""
            if record.exc_info and record.exc_info[1] is not None:
                defect = _durand_defect(record.exc_info)
                if defect is not None:
                    self.defects[defect] = self.defects.get(defect, 0) + 1
                    return
                detail = f": {type(record.exc_info[1]).__name__}: {record.exc_info[1]}"
            self._errors.add(f"durand logged ({record.name}, {record.levelname}) {message}{detail}")


def fire_due_events(scheduler: VirtualScheduler, until_s: float, errors: Errors) -> None:
    """Fire every event of ``scheduler`` due at or before ``until_s`` (s), each at its own time; then the time is ``until_s``.

    Events fire in time order (equal times: in the order they were added: the lower entry), the
    scheduler's time set to each one's as it fires (a timer re-armed in it counts from there). An
    event's failure (a timer of durand's, or a bug here) is collected in ``errors``; the rest fire.
    The wall-clock and the lock-step schedulers share it (durand 0.5.0's entry and time fields).
    """
    due_at = scheduler._timestamp_dict
    while due_at:
        entry = min(due_at, key=lambda e: (due_at[e], e))
        due = due_at[entry]
        if due > until_s:
            break
        del due_at[entry]
        event = scheduler._entry_dict.pop(entry)
        scheduler._time = max(scheduler._time, due)
        try:
            event.callback(*event.args, **event.kwargs)
        except Exception as exc:  # collected, never raised into the caller's thread or tick
            errors.add(f"scheduler event {event.callback!r}: {type(exc).__name__}: {exc}")
    scheduler._time = max(scheduler._time, until_s)


class WallClockScheduler(VirtualScheduler):
    """durand's VirtualScheduler, run by one thread on the wall clock.

    durand 0.5.0's ``VirtualScheduler.run`` never advances its time while it runs (a timer that
    re-arms itself, as the heartbeat does, loops forever); this one sets its time to each event's
    before firing it. Timers are placed on the wall clock (``add`` counts from now, not from the
    last run). Its lock (``lock``, re-entrant) is the harness's one lock: the thread holds it
    while it fires events, the drives' receive threads while they handle a frame.
    """

    def __init__(self, errors: Errors) -> None:
        super().__init__()
        self._lock: threading.RLock = threading.RLock()  # type: ignore[assignment]
        self._wake = threading.Condition(self._lock)
        self._t0 = time.monotonic()
        self._errors = errors
        self._stopping = False
        self.thread: threading.Thread | None = None

    @property
    def lock(self) -> threading.RLock:
        return self._lock

    def now(self) -> float:
        """Seconds since the scheduler was made (wall clock)."""
        return time.monotonic() - self._t0

    def add(self, delay: float, callback: Callable[..., Any], args: Iterable[Any] = (), kwargs: Any = None) -> int:
        with self._lock:
            entry = self._entry_index
            self._entry_index += 1
            self._entry_dict[entry] = VirtualScheduler.Entry(callback, tuple(args), dict(kwargs or {}))
            self._timestamp_dict[entry] = max(self._time, self.now()) + max(float(delay), 0.0)
            self._wake.notify_all()
            return entry

    def cancel(self, entry: int) -> None:
        with self._lock:  # an entry that already fired is gone: cancelling it is nothing
            self._entry_dict.pop(entry, None)
            self._timestamp_dict.pop(entry, None)

    def run(self, duration: float) -> None:
        """Fire every event due within ``duration`` of the scheduler's time, in time order, each at its time."""
        with self._lock:
            fire_due_events(self, self._time + duration, self._errors)

    def start(self) -> None:
        self.thread = threading.Thread(target=self._loop, name="durand drives scheduler", daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        with self._lock:
            while not self._stopping:
                self.run(self.now() - self._time)
                wait = SCHEDULER_IDLE_S
                if self._timestamp_dict:
                    wait = min(wait, min(self._timestamp_dict.values()) - self.now())
                if wait > 0:
                    self._wake.wait(wait)

    def stop(self) -> None:
        with self._lock:
            self._stopping = True
            self._wake.notify_all()
        if self.thread is not None:
            self.thread.join(DEFAULT_TIMEOUT_S)
            if self.thread.is_alive():
                self._errors.add("the scheduler thread did not stop")
        with self._lock:
            self._entry_dict.clear()
            self._timestamp_dict.clear()


@dataclass
class _Traffic:
    """One drive's frames and counters (changed only while holding the harness's lock)."""

    received: deque[TimedFrame] = field(default_factory=lambda: deque(maxlen=FRAME_LOG_LENGTH))
    sent: deque[TimedFrame] = field(default_factory=lambda: deque(maxlen=FRAME_LOG_LENGTH))
    syncs: int = 0  # SYNC frames completely handled (its TPDOs sent, its RPDOs applied)
    answers_sent: int = 0  # frames sent but heartbeats: TPDOs, EMCY, SDO responses (each caused by the bus or the test)
    heartbeats_sent: int = 0
    last_heartbeat_s: float | None = None


class _Network(durand.CANBusNetwork):  # type: ignore[misc]
    """durand's stock adapter (its Notifier thread, its filters) with every callback run holding the harness's lock.

    Also records every frame the drive handles and sends, counts completed SYNCs, collects the
    errors of callbacks (durand's listener would only log them), and accepts the ``callback``
    keyword durand's own SYNC consumer passes to ``remove_subscription`` (its adapter does not).
    """

    def __init__(
        self, bus: can.BusABC, node_id: int, lock: threading.RLock, synced: threading.Condition, errors: Errors
    ) -> None:
        super().__init__(bus)
        self._notifier.timeout = NOTIFIER_TIMEOUT_S  # stop() within 50 ms instead of 1 s
        self.node_id = node_id
        self.traffic = _Traffic()
        self._harness_lock = lock
        self._synced = synced
        self._errors = errors

    def add_subscription(self, cob_id: int, callback: Callable[[int, bytes], None]) -> None:
        super().add_subscription(cob_id, self._guarded(callback))

    def remove_subscription(self, cob_id: int, callback: object = None) -> None:
        super().remove_subscription(cob_id)

    def _guarded(self, callback: Callable[[int, bytes], None]) -> Callable[[int, bytes], None]:
        def guarded(cob_id: int, data: bytes) -> None:
            with self._harness_lock:
                frame = TimedFrame(time.monotonic(), cob_id, bytes(data))
                self.traffic.received.append(frame)
                try:
                    callback(cob_id, frame.data)
                except Exception as exc:
                    self._errors.add(
                        f"node {self.node_id}: {type(exc).__name__}: {exc} while handling 0x{cob_id:03X} {frame.data.hex()}"
                    )
                if cob_id == SYNC_COB_ID:
                    self.traffic.syncs += 1
                    self._synced.notify_all()

        return guarded

    def send(self, cob_id: int, msg: bytes) -> None:
        now = time.monotonic()  # before it is on the bus: no receiver can have it earlier
        super().send(cob_id, msg)
        self.traffic.sent.append(TimedFrame(now, cob_id, bytes(msg)))
        if cob_id == HEARTBEAT_BASE + self.node_id:  # the heartbeat and the boot-up message
            self.traffic.heartbeats_sent += 1
            self.traffic.last_heartbeat_s = now
        else:
            self.traffic.answers_sent += 1

    def stop(self) -> None:
        self._notifier.stop(timeout=DEFAULT_TIMEOUT_S)
        if self._notifier.exception is not None:
            exc = self._notifier.exception
            self._errors.add(f"node {self.node_id}: receive thread failed: {type(exc).__name__}: {exc}")


def _durand_variable(variable: ODVariable) -> durand.Variable:
    datatype = durand.DatatypeEnum(int(variable.data_type))
    value = variable.default
    if isinstance(value, str):
        value = value.encode()
    return durand.Variable(datatype, _ACCESS[variable.access_type], 0 if value is None else value, name=variable.name)


def durand_dictionary(eds: canopen.ObjectDictionary) -> ObjectDictionary:
    """durand's object dictionary of every EDS object durand does not create itself (durand cannot read an EDS)."""
    od = ObjectDictionary()
    for index, entry in eds.items():
        if _durand_owned(index):
            continue
        if isinstance(entry, ODVariable):
            od[index] = _durand_variable(entry)
        elif isinstance(entry, ODRecord):
            record = durand.Record(name=entry.name)
            for sub, variable in entry.subindices.items():
                if sub:
                    record[sub] = _durand_variable(variable)
            od[index] = record
        elif isinstance(entry, ODArray):
            subs = sorted(s for s in entry.subindices if s)
            first = entry.subindices[subs[0]]
            if any(entry.subindices[s].data_type != first.data_type for s in subs):
                raise ValueError(f"EDS 0x{index:04X}: an array whose elements differ in type")
            # a vendor's arrays may skip sub-indices (maxon's 0x1011 has 1 and 4): up to the highest one
            od[index] = durand.Array(_durand_variable(first), length=max(subs), name=entry.name)
            for sub in subs:  # durand's array has one descriptor; each element's default is a value
                default = entry.subindices[sub].default
                if default is not None:
                    od.write(index, sub, default)
        else:
            raise ValueError(f"EDS 0x{index:04X}: unsupported object {type(entry).__name__}")
    return od


#: The CiA 402 power states in which the power stage has its supply (CiA 402-2 figure 23: voltage enabled).
_POWER_STAGE_STATES = (
    DevicePower.READY_TO_SWITCH_ON,
    DevicePower.SWITCHED_ON,
    DevicePower.OPERATION_ENABLED,
    DevicePower.QUICK_STOP_ACTIVE,
)


class Cia402Device:
    """The drive's application: the CiA 402 power state machine on controlword writes, the applied torque.

    Runs in durand's callbacks (the wall-clock harness: holding its lock; the lock-step drive set:
    on the caller's thread). Never writes the controlword or the target torque (only the master
    does, by RPDO); keeps the statusword, the error code and the modes of operation display in the
    dictionary with ``od.write`` (so the TPDOs carry them).

    The safe torque off input, :attr:`power_cut`: None, either e-stop button removes the torque (the
    wall-clock harness: the state machine keeps its state); True or False, the e-stop circuit's
    cut as the plant decides it (the lock-step drive set: ``sto`` or ``ss1`` wiring), and while it
    is cut a power stage without supply is SWITCH ON DISABLED, which it cannot leave (as the
    project's simulated drive, hal/canopen/sim/drive.py).
    """

    def __init__(self, node: durand.MinimalNode, errors: Errors, wiring: DriveWiring) -> None:
        self.node = node
        self.wiring = wiring
        self.od: ObjectDictionary = node.object_dictionary
        self.power = DevicePower.SWITCH_ON_DISABLED
        self.previous_controlword = 0
        self.estop_operator = False
        self.estop_pilot = False
        self.power_cut: bool | None = None
        self.applied_permille = 0
        self.controlwords: deque[int] = deque(maxlen=FRAME_LOG_LENGTH)  # every controlword the drive took
        self._errors = errors
        for index, handler in (
            (CONTROLWORD, self._on_controlword),
            (TARGET_TORQUE, self._on_target_torque),
            (MODES_OF_OPERATION, self._on_mode),
        ):
            self.od.update_callbacks[(index, 0)].add(self._reported(handler))
        node.nmt.state_callbacks.add(self._reported(self._on_nmt_state))
        self.publish()

    def _reported(self, handler: Callable[[Any], None]) -> Callable[[Any], None]:
        def run(value: Any) -> None:
            try:
                handler(value)
            except Exception as exc:  # durand would swallow it (its callbacks ignore exceptions)
                self._errors.add(
                    f"node {self.node.node_id}: {handler.__name__}({value!r}): {type(exc).__name__}: {exc}"
                )

        return run

    def _on_controlword(self, value: int) -> None:
        controlword = int(value)
        self.controlwords.append(controlword)
        was = self.power
        self.power = _next_power(was, controlword, self.previous_controlword)
        self.previous_controlword = controlword
        if self.power_cut and self.power in _POWER_STAGE_STATES:
            self.power = DevicePower.SWITCH_ON_DISABLED  # safe torque off: no supply, no transition out of it
        self.publish()
        if was is DevicePower.FAULT and self.power is not DevicePower.FAULT:
            self.after_fault_reset()

    def _on_target_torque(self, _value: int) -> None:
        self.publish()

    def _on_mode(self, value: int) -> None:
        self.od.write(MODES_OF_OPERATION_DISPLAY, 0, int(value))  # the drive takes the mode at once
        self.publish()

    def _on_nmt_state(self, state: StateEnum) -> None:
        # Reset (node or communication) or leaving OPERATIONAL (no more PDOs): the power stage is
        # switched off; a fault stays until it is reset.
        if state != StateEnum.OPERATIONAL and self.power is not DevicePower.FAULT:
            self.power = DevicePower.SWITCH_ON_DISABLED
            self.publish()

    def fault(self, code: int, register: int, data: bytes) -> None:
        """A fault: FAULT, the error code in 0x603F, then the EMCY (in that order: the EMCY tells of a fault shown)."""
        self.power = DevicePower.FAULT
        self.od.write(ERROR_CODE, 0, code)
        self.publish()
        self.node.emcy.set(code, register, data)

    def publish(self) -> None:
        """The statusword and the applied torque from the state (the only place either changes)."""
        wiring = self.wiring
        if self.power_cut and self.power in _POWER_STAGE_STATES:
            self.power = DevicePower.SWITCH_ON_DISABLED  # the e-stop circuit cut the power stage's supply
        word = self.power.value | SW_REMOTE
        if wiring.estop_in_statusword:
            word = self._with_estop(word)
        elif wiring.estop is not None:
            inputs = self._with_estop(int(self.od.read(*wiring.estop)))
            if self.od.read(*wiring.estop) != inputs:
                self.od.write(*wiring.estop, inputs)
        if self.od.read(STATUSWORD, 0) != word:
            self.od.write(STATUSWORD, 0, word)
        torque_allowed = (
            self.power is DevicePower.OPERATION_ENABLED
            and self.od.read(MODES_OF_OPERATION_DISPLAY, 0) in (MODE_CST, MODE_TQ)
            # both e-stops drive the safe torque off input (sto), unless the caller says when the circuit cuts
            and not (self.estop_operator or self.estop_pilot if self.power_cut is None else self.power_cut)
        )
        self.applied_permille = int(self.od.read(TARGET_TORQUE, 0)) if torque_allowed else 0

    def _with_estop(self, word: int) -> int:
        """``word`` with the buttons in the wiring's bits (a pressed one clears its bit when wired normally closed)."""
        wiring = self.wiring
        for pressed, mask in ((self.estop_operator, wiring.operator_mask), (self.estop_pilot, wiring.pilot_mask)):
            word = word | mask if pressed != wiring.pressed_when_clear else word & ~mask
        return word

    def after_fault_reset(self) -> None:
        """Left FAULT by a fault reset: the error is gone (0x603F 0, EMCY "error reset", CiA 301 7.2.7)."""
        self.od.write(ERROR_CODE, 0, 0)
        self.node.emcy.set(0x0000, 0x00)


def create_node(
    network: durand.network.NetworkABC, node_id: int, eds: canopen.ObjectDictionary, wiring: DriveWiring, errors: Errors
) -> tuple[durand.MinimalNode, Cia402Device]:
    """A durand node on ``network`` with ``eds``'s values and the CiA 402 application behind it (sends its boot-up message).

    Shared by the wall-clock harness (:class:`DurandDrives`) and the lock-step drive set
    (tests/durand_lockstep.py): the dictionary is the EDS's (:func:`durand_dictionary`), the
    objects durand makes itself get the EDS's values (or the device's own: 0x1000, 0x1018 from
    [DeviceInfo], 0x6502 with the torque modes), every PDO is in the EDS's factory state.

    Raises:
        ValueError: an object durand fixes has another value in the EDS, or the EDS has an object
            durand cannot hold.
    """
    node = durand.MinimalNode(network, node_id, durand_dictionary(eds))
    _apply_owned_objects(node, eds)
    _apply_factory_pdos(node, eds)
    if SUPPORTED_DRIVE_MODES in eds and eds[SUPPORTED_DRIVE_MODES].default is None:
        node.object_dictionary.write(SUPPORTED_DRIVE_MODES, 0, TORQUE_MODES)  # the device's own value
    return node, Cia402Device(node, errors, wiring)


def _apply_owned_objects(node: durand.MinimalNode, eds: canopen.ObjectDictionary) -> None:
    """The EDS's values of the objects durand made itself; the ones durand fixes must agree with the EDS."""
    od = node.object_dictionary
    device_type = eds[0x1000].default
    od.write(0x1000, 0, SERVO_DEVICE_TYPE if device_type is None else int(device_type))
    od.write(0x1008, 0, str(eds[0x1008].default or "").encode())
    info = eds.device_information
    known = {1: info.vendor_number, 2: info.product_number, 3: info.revision_number}
    for sub in range(1, 5):
        value = eds[0x1018][sub].default if sub in eds[0x1018].subindices else None
        od.write(0x1018, sub, int(value if value is not None else known.get(sub) or 0))
    for index in (0x1001, 0x1005, 0x1014, PRODUCER_HEARTBEAT_TIME):
        if index in eds and eds[index].default is not None and od.read(index, 0) != eds[index].default:
            raise ValueError(
                f"node {node.node_id}: durand's 0x{index:04X} is {od.read(index, 0)}, the EDS says {eds[index].default}"
            )


def _apply_factory_pdos(node: durand.MinimalNode, eds: canopen.ObjectDictionary) -> None:
    """Each PDO of the EDS as the EDS's defaults have it (the factory state the master must overwrite)."""
    od = node.object_dictionary
    for pdos, comm_base, map_base in ((node.rpdo, 0x1400, 0x1600), (node.tpdo, 0x1800, 0x1A00)):
        for number, pdo in enumerate(pdos):
            if comm_base + number not in eds:
                continue
            comm, mapping = eds[comm_base + number], eds[map_base + number]
            entries = [int(mapping[s].default) for s in range(1, int(mapping[0].default) + 1)]
            pdo.mapping = [(entry >> 16, (entry >> 8) & 0xFF) for entry in entries]
            pdo.transmission_type = int(comm[2].default)
            od.write(comm_base + number, 1, int(comm[1].default), downloaded=True)  # as a download sets it


class _Drive:
    """One drive of the wall-clock harness: its bus, durand's network adapter and node, its application."""

    def __init__(
        self,
        channel: str,
        node_id: int,
        eds_path: Path,
        lock: threading.RLock,
        synced: threading.Condition,
        errors: Errors,
        wiring: DriveWiring | None = None,
    ) -> None:
        self.node_id = node_id
        self.eds = canopen.import_od(str(eds_path), node_id)
        self.wiring = wiring or DriveWiring.daror(self.eds)
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.network = _Network(self.bus, node_id, lock, synced, errors)
        self.node: durand.MinimalNode | None = None
        self.device: Cia402Device | None = None
        self._errors = errors

    def create(self) -> None:
        """The node (sends its boot-up message) with the EDS's values; runs in the scheduler thread."""
        self.node, self.device = create_node(self.network, self.node_id, self.eds, self.wiring, self._errors)


class DurandDrives:
    """Four (or any number of) durand drives on python-can's ``virtual`` bus ``channel``.

    Args:
        channel: the virtual bus channel (unique per test: a channel is process-global).
        node_ids: the drives' node ids.
        eds: the EDS the drives are built from (DAROR SEA drives: :meth:`DriveWiring.daror`).
        drives: node id -> (its EDS, its wiring) instead (a robot file's: :func:`robot_file_drives`).

    Use as a context manager (or :meth:`start` / :meth:`stop`). Only one harness may run at a
    time in a process (durand's scheduler is process-global).
    """

    def __init__(
        self,
        channel: str,
        node_ids: Iterable[int],
        eds: Path = EDS_PATH,
        drives: Mapping[int, tuple[Path, DriveWiring]] | None = None,
    ) -> None:
        self.channel = channel
        self.node_ids = tuple(node_ids)
        self.eds_path = Path(eds)
        self._given = dict(drives or {})
        self.units = EdsUnits.from_eds(canopen.import_od(str(self.eds_path))) if not self._given else None
        self._errors = Errors()
        self._scheduler = WallClockScheduler(self._errors)
        self._lock = self._scheduler.lock
        self._synced = threading.Condition(self._lock)
        self._drives: dict[int, _Drive] = {}
        self._log_watch = LogWatch(self._errors)
        self._previous_scheduler: AbstractScheduler | None = None
        self._unwatch_logs: Callable[[], None] = lambda: None
        self._running = False

    # --- lifecycle ------------------------------------------------------------------------------

    def __enter__(self) -> DurandDrives:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def start(self) -> None:
        """Buses, receive threads, the scheduler thread, then every node (each sends its boot-up message).

        Raises:
            RuntimeError: another harness is running in this process.
        """
        claim_durand(self)
        try:
            self._unwatch_logs = watch_durand_logs(self._log_watch)
            self._previous_scheduler = durand.get_scheduler()
            durand.set_scheduler(self._scheduler)
            self._scheduler.start()
            self._running = True
            for node_id in self.node_ids:
                eds, wiring = self._given.get(node_id, (self.eds_path, None))
                self._drives[node_id] = _Drive(
                    self.channel, node_id, eds, self._lock, self._synced, self._errors, wiring
                )
            for drive in self._drives.values():
                self.call(drive.create)
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """Heartbeats off, the scheduler and the receive threads stopped, the buses closed. Safe twice."""
        if holds_durand(self):
            if self._running and self._scheduler.thread is not None and self._scheduler.thread.is_alive():
                try:
                    self.call(self._quiesce)
                except Exception as exc:
                    self._errors.add(f"stopping the drives: {type(exc).__name__}: {exc}")
            self._running = False
            self._scheduler.stop()
            for drive in self._drives.values():
                drive.network.stop()
            for drive in self._drives.values():
                drive.bus.shutdown()
            if self._previous_scheduler is not None:
                durand.set_scheduler(self._previous_scheduler)
            self._unwatch_logs()
            self._unwatch_logs = lambda: None
            release_durand(self)

    def _quiesce(self) -> None:
        for drive in self._drives.values():
            if drive.node is not None:  # no timer may fire on a closed bus
                drive.node.object_dictionary.write(PRODUCER_HEARTBEAT_TIME, 0, 0)

    # --- running code with the drives ---------------------------------------------------------------

    def call(self, function: Callable[[], T], timeout_s: float = DEFAULT_TIMEOUT_S) -> T:
        """``function()`` run in the scheduler thread, holding the lock; its result (or its exception, raised here).

        Raises:
            TimeoutError: the scheduler thread did not run it within ``timeout_s``.
        """
        if threading.current_thread() is self._scheduler.thread:
            return function()
        if not self._running:
            raise RuntimeError("the drives are not running")
        done = threading.Event()
        outcome: list[tuple[bool, Any]] = []

        def task() -> None:
            try:
                outcome.append((True, function()))
            except BaseException as exc:
                outcome.append((False, exc))
            finally:
                done.set()

        self._scheduler.add(0.0, task)
        if not done.wait(timeout_s):
            raise TimeoutError(f"the drives' scheduler thread did not run {function!r} within {timeout_s} s")
        ok, value = outcome[0]
        if not ok:
            raise value
        return value  # type: ignore[no-any-return]

    def _drive(self, node_id: int) -> _Drive:
        try:
            return self._drives[node_id]
        except KeyError:
            raise KeyError(f"no drive with node id {node_id} (drives: {self.node_ids})") from None

    def _device(self, node_id: int) -> Cia402Device:
        device = self._drive(node_id).device
        if device is None:
            raise RuntimeError(f"node {node_id} is not created")
        return device

    def node(self, node_id: int) -> durand.MinimalNode:
        """The durand node (touch it only inside :meth:`call`)."""
        node = self._drive(node_id).node
        if node is None:
            raise RuntimeError(f"node {node_id} is not created")
        return node

    # --- what the test reads ----------------------------------------------------------------------

    def read(self, node_id: int, index: int, sub: int = 0) -> Any:
        """The value of ``index:sub`` in the drive's dictionary."""
        return self.call(lambda: self.node(node_id).object_dictionary.read(index, sub))

    def nmt_state(self, node_id: int) -> int:
        """The drive's NMT state (durand's ``StateEnum`` value: 0, 4 stopped, 5 operational, 127 pre-operational)."""
        return self.call(lambda: int(self.node(node_id).nmt.state))

    def power(self, node_id: int) -> DevicePower:
        return self.call(lambda: self._device(node_id).power)

    def applied_torque_permille(self, node_id: int) -> int:
        """The torque the drive's power stage applies now, per mille (0 unless operation enabled in CST)."""
        return self.call(lambda: self._device(node_id).applied_permille)

    def controlwords(self, node_id: int) -> list[int]:
        """Every controlword the drive took (each RPDO's, in order)."""
        return self.call(lambda: list(self._device(node_id).controlwords))

    def received(self, node_id: int) -> list[TimedFrame]:
        """Every frame the drive handled (those it subscribes to), in order."""
        with self._lock:
            return list(self._drive(node_id).network.traffic.received)

    def sent(self, node_id: int) -> list[TimedFrame]:
        """Every frame the drive sent, in order."""
        with self._lock:
            return list(self._drive(node_id).network.traffic.sent)

    def sync_counts(self) -> dict[int, int]:
        """SYNC frames each drive handled completely (its TPDOs sent, its RPDOs applied)."""
        with self._lock:
            return {n: d.network.traffic.syncs for n, d in self._drives.items()}

    def answer_counts(self) -> dict[int, int]:
        """Frames each drive sent but its heartbeats and boot-up messages: TPDOs, EMCY, SDO responses.

        Each is sent in answer to a frame on the bus or to the test (a heartbeat comes by the
        scheduler's clock, at any time): all of them sent before a moment can be waited for.
        """
        with self._lock:
            return {n: d.network.traffic.answers_sent for n, d in self._drives.items()}

    def last_heartbeat_s(self, node_id: int) -> float | None:
        """When the drive last sent a heartbeat (``time.monotonic()``), None if never."""
        with self._lock:
            return self._drive(node_id).network.traffic.last_heartbeat_s

    def wait_syncs(self, targets: Mapping[int, int], timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        """Until every drive handled at least ``targets[node]`` SYNCs.

        Raises:
            AssertionError: not within ``timeout_s`` (the counts are in the message).
        """

        def reached() -> bool:
            return all(self._drives[n].network.traffic.syncs >= c for n, c in targets.items())

        with self._synced:
            if not self._synced.wait_for(reached, timeout_s):
                raise AssertionError(f"drives handled SYNCs {self.sync_counts()}, expected {dict(targets)}")

    @property
    def errors(self) -> list[str]:
        """Errors in the drives' threads so far (callbacks, timers, durand's swallowed exceptions)."""
        return self._errors.snapshot()

    @property
    def durand_defects(self) -> dict[str, int]:
        """How often each known durand defect showed (not errors: see :data:`DURAND_TPDO_SYNC_WHILE_INACTIVE`)."""
        with self._lock:  # the log records come from the drives' threads, which hold the lock
            return dict(self._log_watch.defects)

    # --- what the test does to the drives -------------------------------------------------------------

    def set_joint(self, node_id: int, theta_rad: float, q_rad: float, tau_nm: float) -> JointCounts:
        """The drive's measurements: motor-side angle, link-side angle, spring torque, in its wiring's objects.

        The DAROR drive's: 0x6064, 0x2010, 0x6077. Converted with the wiring's scales (rounded to
        the nearest count) and written with ``od.write``: the TPDOs of the next SYNC carry them. A
        drive without a torque object reports none (``torque_permille`` 0).

        Raises:
            ValueError: a value out of its object's range.
        """
        wiring = self._drive(node_id).wiring
        counts = JointCounts(
            round(theta_rad / wiring.rad_per_motor_count),
            round(q_rad / wiring.rad_per_link_count),
            round(tau_nm / wiring.nm_per_torque_count) if wiring.torque is not None else 0,
        )

        def write() -> None:
            od = self.node(node_id).object_dictionary
            od.write(*wiring.motor, counts.motor_increments)
            od.write(*wiring.link, counts.load_increments)
            if wiring.torque is not None:
                od.write(*wiring.torque, counts.torque_permille)

        self.call(write)
        return counts

    def stop_heartbeat(self, node_id: int) -> float | None:
        """The drive's heartbeat producer off (0x1017 = 0, its timer cancelled); returns when it sent the last one."""

        def stop() -> float | None:
            self.node(node_id).object_dictionary.write(PRODUCER_HEARTBEAT_TIME, 0, 0)
            return self._drive(node_id).network.traffic.last_heartbeat_s

        return self.call(stop)

    def emergency(self, node_id: int, code: int, register: int, data: bytes = b"") -> None:
        """A fault in the drive: FAULT (statusword), 0x603F = ``code``, then an EMCY (``node.emcy.set``)."""
        self.call(lambda: self._device(node_id).fault(code, register, data))

    def restart(self, node_id: int) -> None:
        """The drive restarts by itself (a brown-out): NMT initialisation, boot-up message, pre-operational.

        Its dictionary keeps its values (durand resets none); its application starts switched off.
        """
        self.call(lambda: self.node(node_id).nmt.reset())

    def set_estop(self, node_id: int, operator: bool, pilot: bool) -> None:
        """The e-stop inputs the drive reads back (statusword bits 14, 15); either removes its torque."""

        def press() -> None:
            device = self._device(node_id)
            device.estop_operator, device.estop_pilot = operator, pilot
            device.publish()

        self.call(press)


class _ProbeListener(can.Listener):
    def __init__(self, probe: MasterProbe) -> None:
        self._probe = probe

    def on_message_received(self, msg: can.Message) -> None:
        self._probe._on_frame(msg)


class MasterProbe:
    """What the master's receive thread has taken from the bus: a listener added after the master's own.

    python-can calls a Notifier's listeners in order, so a frame this probe has seen is already
    stored by the master (its listener is first): waiting here is waiting for the master.

    Args:
        bus: the master's bus (its Notifier must be running: attach after the backend opened).
        node_ids: the drives.
        baseline: the drives' :meth:`DurandDrives.answer_counts` when attached (every such frame
            sent before was already received by the master: its start-up waits for the answers).

    Raises:
        RuntimeError: no Notifier runs on ``bus``.
    """

    def __init__(self, bus: can.BusABC, baseline: Mapping[int, int]) -> None:
        notifiers = can.Notifier.find_instances(bus)
        if len(notifiers) != 1:
            raise RuntimeError(f"expected one Notifier on the master's bus, found {len(notifiers)}")
        self._notifier = notifiers[0]
        self._baseline = dict(baseline)
        self._condition = threading.Condition()
        self._frames: list[TimedFrame] = []
        self._answers: dict[int, int] = dict.fromkeys(self._baseline, 0)
        self._listener = _ProbeListener(self)
        self._notifier.add_listener(self._listener)

    def _on_frame(self, msg: can.Message) -> None:
        frame = TimedFrame(time.monotonic(), msg.arbitration_id, bytes(msg.data))
        node_id, function = frame.cob_id & 0x07F, frame.cob_id & 0x780
        with self._condition:
            self._frames.append(frame)
            if node_id in self._answers and function in (EMCY_BASE, TPDO1_BASE, TPDO2_BASE, SDO_TX_BASE):
                self._answers[node_id] += 1
            self._condition.notify_all()

    def frames(self) -> list[TimedFrame]:
        """Every frame the master received since attaching, in order."""
        with self._condition:
            return list(self._frames)

    def wait_for(self, predicate: Callable[[TimedFrame], bool], timeout_s: float = DEFAULT_TIMEOUT_S) -> TimedFrame:
        """The first frame received since attaching that satisfies ``predicate``, waiting for it if need be.

        Raises:
            AssertionError: none within ``timeout_s``.
        """
        found: list[TimedFrame] = []

        def seen() -> bool:
            found[:] = [f for f in self._frames if predicate(f)][:1]
            return bool(found)

        with self._condition:
            if not self._condition.wait_for(seen, timeout_s):
                raise AssertionError(f"the master received no such frame within {timeout_s} s")
        return found[0]

    def wait_answers(self, sent: Mapping[int, int], timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        """Until the master holds every answer the drives sent (``sent``: :meth:`DurandDrives.answer_counts`).

        Raises:
            AssertionError: not within ``timeout_s``.
        """
        expected = {n: c - self._baseline[n] for n, c in sent.items()}

        def delivered() -> bool:
            return all(self._answers[n] >= c for n, c in expected.items())

        with self._condition:
            if not self._condition.wait_for(delivered, timeout_s):
                raise AssertionError(
                    f"the master received {self._answers} frames since attaching; drives sent {expected}"
                )

    def detach(self) -> None:
        if not self._notifier.stopped:
            with contextlib.suppress(ValueError):  # already removed
                self._notifier.remove_listener(self._listener)


def sdo_requests(frames: Iterable[TimedFrame], node_id: int) -> Iterator[tuple[str, int, int, bytes]]:
    """The expedited SDO requests in ``frames`` to ``node_id``: ``(kind, index, sub, data)``; kind "write" or "read"."""
    for frame in frames:
        if frame.cob_id != SDO_RX_BASE + node_id or len(frame.data) != 8:
            continue
        command, index, sub = struct.unpack_from("<BHB", frame.data)
        if command >> 5 == 1 and command & 0x02:
            size = 4 - ((command >> 2) & 0x03) if command & 0x01 else 4
            yield "write", index, sub, frame.data[4 : 4 + size]
        elif command >> 5 == 2:
            yield "read", index, sub, b""


def sdo_responses(frames: Iterable[TimedFrame], node_id: int) -> Iterator[tuple[str, int, int, int]]:
    """The SDO responses in ``frames`` from ``node_id``: ``(kind, index, sub, value or abort code)``."""
    for frame in frames:
        if frame.cob_id != SDO_TX_BASE + node_id or len(frame.data) != 8:
            continue
        command, index, sub, value = struct.unpack("<BHBI", frame.data)
        if command == 0x80:
            yield "abort", index, sub, value
        elif command >> 5 == 3:
            yield "written", index, sub, 0
        elif command >> 5 == 2 and command & 0x02:
            size = 4 - ((command >> 2) & 0x03) if command & 0x01 else 4
            yield "read", index, sub, int.from_bytes(frame.data[4 : 4 + size], "little")
