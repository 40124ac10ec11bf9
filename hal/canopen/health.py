"""The health of the master's CAN controller: bus-off, error-passive, warnings and error frames.

CAN's fault confinement (ISO 11898-1) counts every transmit and receive error in the controller:
over 96 errors it warns, over 127 it is *error-passive* (it still sends and receives, but may no
longer signal an error it sees, and waits before each frame it sends), over 255 transmit errors it
is *bus-off* (it neither sends nor receives until it is restarted). The master learns of this in one
of two ways, whichever the interface offers:

* **the controller's state**, read in the tick (:func:`state_reader`): python-can's ``bus.state``
  where it is the controller's (ixxat, etas, the simulated bus); PCAN's ``status()`` (python-can's
  ``PcanBus.state`` is the listen-only mode the caller chose, not the controller's); none on
  socketcan and kvaser, whose ``state`` is python-can's default (always ``ACTIVE``);
* **error frames** (:func:`decode_error_frame`): socketcan delivers the controller's events as
  frames with ``is_error_frame`` set, the CAN_ERR_* class bits of ``linux/can/error.h`` in the
  CAN id and the details in the data (byte 1: the controller's warning/passive flags, bytes 6-7:
  its error counters). python-can 4.6's socketcan bus enables them itself (``CAN_RAW_ERR_FILTER``
  set to every class unless ``ignore_rx_error_frames``): the backend opens it with the default.

What is a fault (D150, D151): bus-off and error-passive, each when it begins (the robot fails:
nothing can be commanded reliably); again when the operator acknowledges while it lasts. Warnings,
protocol and acknowledge errors, lost arbitration and overflows are counted for the bus report and
are no fault: the controller's own counters are the threshold (a bus that keeps erring goes
error-passive), and the frames they cost are the heartbeat and TPDO watchdogs' to judge.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import StrEnum

import can

__all__ = [
    "BusHealth",
    "ControllerState",
    "ErrorFrame",
    "decode_error_frame",
    "error_frame_data",
    "state_reader",
]

# linux/can/error.h: the error class, in the CAN id of an error frame
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_LOSTARB = 0x002
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_TRX = 0x010
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100
CAN_ERR_CNT = 0x200
# data[1]: the controller's error status
CAN_ERR_CRTL_RX_OVERFLOW = 0x01
CAN_ERR_CRTL_TX_OVERFLOW = 0x02
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40

# PCAN-Basic's status bits (python-can's can.interfaces.pcan.basic: PCAN_ERROR_*)
_PCAN_BUSLIGHT = 0x00004
_PCAN_BUSHEAVY = 0x00008
_PCAN_BUSOFF = 0x00010
_PCAN_BUSPASSIVE = 0x40000


class ControllerState(StrEnum):
    """The master's controller in CAN's fault confinement, best first."""

    ACTIVE = "error-active"
    WARNING = "warning"
    PASSIVE = "error-passive"
    BUS_OFF = "bus-off"


#: What each faulted state means for the robot, for the fault's message.
_WHY = {
    ControllerState.PASSIVE: (
        "the controller counts more than 127 errors: it may no longer signal the errors it sees and "
        "waits before every frame it sends; commands are late or lost"
    ),
    ControllerState.BUS_OFF: (
        "the controller stopped transmitting and receiving after more than 255 transmit errors: "
        "no command reaches the drives, which stop by their own reaction to losing the master"
    ),
}


@dataclass(frozen=True)
class ErrorFrame:
    """One error frame decoded (socketcan's ``linux/can/error.h``).

    Attributes:
        state: the controller state it reports (None: it reports none).
        restarted: the controller was restarted after bus-off (it is error-active again).
        events: what else it reports, in the header's words (counted, not faults).
        tx_errors, rx_errors: the controller's error counters, when the frame carries them.
    """

    state: ControllerState | None
    restarted: bool
    events: tuple[str, ...]
    tx_errors: int | None = None
    rx_errors: int | None = None


_EVENTS = (
    (CAN_ERR_TX_TIMEOUT, "tx timeout"),
    (CAN_ERR_LOSTARB, "lost arbitration"),
    (CAN_ERR_PROT, "protocol error"),
    (CAN_ERR_TRX, "transceiver error"),
    (CAN_ERR_ACK, "no acknowledge"),
    (CAN_ERR_BUSERROR, "bus error"),
)


def decode_error_frame(can_id: int, data: bytes) -> ErrorFrame:
    """What a socketcan error frame says: ``can_id`` its class bits (without CAN_ERR_FLAG), ``data`` 0-8 bytes.

    The worst state it names wins: bus-off over passive over warning; "back to error active"
    (CAN_ERR_CRTL_ACTIVE) and a restart say active. CAN_ERR_PROT_ACTIVE in the protocol byte is
    not read as a recovery: it is the active error flag of a protocol error, which a few old drivers
    also send on returning to error-active; read as a recovery, it could end a passive state that
    lasts (the acknowledge would then not raise it again).
    """
    b = data.ljust(8, b"\0")
    state: ControllerState | None = None
    events = [name for bit, name in _EVENTS if can_id & bit]
    if can_id & CAN_ERR_CRTL:
        flags = b[1]
        if flags & (CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE):
            state = ControllerState.PASSIVE
        elif flags & (CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING):
            state = ControllerState.WARNING
        elif flags & CAN_ERR_CRTL_ACTIVE:
            state = ControllerState.ACTIVE
        if flags & CAN_ERR_CRTL_RX_OVERFLOW:
            events.append("rx overflow")
        if flags & CAN_ERR_CRTL_TX_OVERFLOW:
            events.append("tx overflow")
    restarted = bool(can_id & CAN_ERR_RESTARTED)
    if restarted and state is None:
        state = ControllerState.ACTIVE
    if can_id & CAN_ERR_BUSOFF:
        state = ControllerState.BUS_OFF
    counters = bool(can_id & CAN_ERR_CNT)
    return ErrorFrame(state, restarted, tuple(events), b[6] if counters else None, b[7] if counters else None)


def error_frame_data(state: ControllerState, tx_errors: int = 0, rx_errors: int = 0) -> tuple[int, bytes]:
    """The CAN id (class bits) and data of the error frame a socketcan controller sends on entering ``state``."""
    counters = bytes((0, 0, 0, 0, 0, 0, min(tx_errors, 255), min(rx_errors, 255)))
    if state is ControllerState.BUS_OFF:
        return CAN_ERR_BUSOFF | CAN_ERR_CNT, counters
    flags = {
        ControllerState.PASSIVE: CAN_ERR_CRTL_TX_PASSIVE,
        ControllerState.WARNING: CAN_ERR_CRTL_TX_WARNING,
        ControllerState.ACTIVE: CAN_ERR_CRTL_ACTIVE,
    }[state]
    return CAN_ERR_CRTL | CAN_ERR_CNT, bytes((0, flags)) + counters[2:]


def _from_bus_state(value: object) -> ControllerState | None:
    if value is can.BusState.ERROR:
        return ControllerState.BUS_OFF
    if value is can.BusState.PASSIVE:
        return ControllerState.PASSIVE
    if value is can.BusState.ACTIVE:
        return ControllerState.ACTIVE
    return None  # an interface that cannot tell now (etas answers None for a state it does not name)


def _from_pcan_status(value: object) -> ControllerState:
    status = int(getattr(value, "value", value))  # a ctypes TPCANStatus or an int
    if status & _PCAN_BUSOFF:
        return ControllerState.BUS_OFF
    if status & _PCAN_BUSPASSIVE:
        return ControllerState.PASSIVE
    if status & (_PCAN_BUSHEAVY | _PCAN_BUSLIGHT):
        return ControllerState.WARNING
    return ControllerState.ACTIVE


#: Interfaces whose error frames are socketcan's (``linux/can/error.h``).
_SOCKETCAN_FRAMES = frozenset({"SocketcanBus", "SimulationBus"})
#: Interfaces whose ``state`` is the controller's (python-can 4.6): read every tick.
_STATE_IS_THE_CONTROLLERS = frozenset({"IXXATBus", "EtasBus", "SimulationBus"})


def state_reader(bus: can.BusABC) -> Callable[[], ControllerState | None] | None:
    """How to read ``bus``'s controller state in the tick, or None where the interface cannot tell
    (socketcan: its error frames tell; kvaser, virtual: nothing does). See the module docstring.

    The reader returns None when the interface answers with no state it names.
    """
    kind = type(bus).__name__
    if kind == "PcanBus" and callable(getattr(bus, "status", None)):
        status = bus.status  # type: ignore[attr-defined]
        return lambda: _from_pcan_status(status())
    if kind in _STATE_IS_THE_CONTROLLERS:
        return lambda: _from_bus_state(bus.state)
    return None


@dataclass
class BusHealth:
    """The master's view of its controller: the state now, the fault latched, the counts.

    Args:
        read_state: the controller's state, read once per :meth:`check` (None: the interface cannot tell).
        decode_frames: error frames carry socketcan's classes (socketcan, the simulated bus); other
            interfaces' error frames are counted only (their layout is the vendor's).
        interface: the bus's class name, for the report.
    """

    read_state: Callable[[], ControllerState | None] | None
    decode_frames: bool = True
    interface: str = ""
    state: ControllerState = ControllerState.ACTIVE
    since_s: float = 0.0
    error_frames: int = 0
    events: dict[str, int] = field(default_factory=dict)
    entered: dict[str, int] = field(default_factory=dict)
    restarts: int = 0
    tx_errors: int | None = None
    rx_errors: int | None = None
    state_reads_failed: int = 0
    _latched: str | None = field(default=None, init=False, repr=False)
    _by_frame: ControllerState = field(default=ControllerState.ACTIVE, init=False, repr=False)
    _by_read: ControllerState = field(default=ControllerState.ACTIVE, init=False, repr=False)

    @classmethod
    def for_bus(cls, bus: can.BusABC) -> BusHealth:
        """The health of ``bus``, read the way its interface allows (:func:`state_reader`)."""
        kind = type(bus).__name__
        return cls(state_reader(bus), kind in _SOCKETCAN_FRAMES, kind)

    @property
    def faulted(self) -> bool:
        """True while the controller is error-passive or bus-off."""
        return self.state in _WHY

    def check(self, error_frames: Iterable[tuple[int, bytes]], t_s: float) -> None:
        """One tick: the error frames received since the last (CAN id, data), then the controller's state.

        A reader that raises (a driver's error) is counted and treated as no answer: the error
        frames and the watchdogs still stand, and the next tick reads again.
        """
        for can_id, data in error_frames:
            self.error_frames += 1
            if not self.decode_frames:
                continue
            frame = decode_error_frame(can_id, data)
            for event in frame.events:
                self.events[event] = self.events.get(event, 0) + 1
            if frame.tx_errors is not None:
                self.tx_errors, self.rx_errors = frame.tx_errors, frame.rx_errors
            if frame.restarted:
                self.restarts += 1
            if frame.state is not None:
                self._by_frame = frame.state
        if self.read_state is not None:
            try:
                read = self.read_state()
            except (can.CanError, OSError, ValueError):
                self.state_reads_failed += 1
                read = None
            if read is not None:
                self._by_read = read
        by_frame, by_read = self._by_frame, self._by_read
        # nearly always one state (error-active): no rank look-up then (an Enum's hash is a Python call)
        worst = by_frame if by_frame is by_read else max(by_frame, by_read, key=_RANK.__getitem__)
        if worst is not self.state:
            self._enter(worst, t_s)

    def _enter(self, state: ControllerState, t_s: float) -> None:
        self.state, self.since_s = state, t_s
        self.entered[state.value] = self.entered.get(state.value, 0) + 1
        if state in _WHY:
            self._latched = self.describe()

    def describe(self) -> str:
        """The controller's state as one line (a fault's message when it is error-passive or bus-off)."""
        counters = f"; error counters tx {self.tx_errors}, rx {self.rx_errors}" if self.tx_errors is not None else ""
        why = f" ({_WHY[self.state]}{counters})" if self.state in _WHY else counters
        return f"CAN bus: {self.state.value}{why}"

    def note(self) -> str:
        """``"; "`` and :meth:`describe` while the controller is not error-active (for a start-up that failed), else ``""``."""
        return "" if self.state is ControllerState.ACTIVE else f"; {self.describe()}"

    def settle(self) -> None:
        """Start-up is over: a fault latched while it lasted is dropped if the controller is error-active
        again (a master that talked before the drives were powered goes error-passive until they
        acknowledge: counted in the report, not a fault of the session); one still in force stays
        latched for the first read."""
        if not self.faulted:
            self._latched = None

    def take_fault(self) -> str | None:
        """The fault latched since the last call (None if none): the backend raises it once."""
        latched, self._latched = self._latched, None
        return latched

    def on_fault_reset(self) -> None:
        """The operator acknowledged: a state that still holds is latched again (the robot does not restart on it)."""
        if self.faulted:
            self._latched = self.describe() + f", since t = {self.since_s:.3f} s"

    def report(self) -> dict[str, object]:
        """The counts for the bus report (plain values)."""
        return {
            "controller_state": self.state.value,
            "controller_state_source": _source(self.read_state is not None, self.decode_frames),
            "controller_states_entered": dict(self.entered),
            "error_frames": self.error_frames,
            "bus_errors": dict(self.events),
            "controller_restarts": self.restarts,
            "error_counters": None if self.tx_errors is None else {"tx": self.tx_errors, "rx": self.rx_errors},
            "state_reads_failed": self.state_reads_failed,
        }


_RANK = {s: n for n, s in enumerate(ControllerState)}


def _source(read: bool, frames: bool) -> str:
    if read:
        return "the interface's state and error frames" if frames else "the interface's state"
    return "error frames" if frames else "none: the interface reports neither (the watchdogs only)"
