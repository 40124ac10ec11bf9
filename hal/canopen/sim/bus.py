"""python-can's ``virtual`` bus, handing each receiver a new message instead of a deep copy.

python-can's :class:`can.interfaces.virtual.VirtualBus` delivers a frame by putting a
``copy.deepcopy`` of the message into every other handle's queue: 10-25 us a receiver on this VM,
half the time of a simulated cycle (13 frames). The simulated drives and the backend never change
a message after sending it, so a new :class:`can.Message` with the same fields (and its own copy of
the data) is the same delivery for a fifth of the cost. Everything else is python-can's: the
channels, the queues, the timestamps, and handles of plain ``virtual`` buses on the same channel
(a test's sniffer) see the same frames. :meth:`SimulationBus.recv` with ``timeout=0`` (the tick's
non-blocking drain) takes the next frame straight from the handle's queue, without python-can's
per-call timing and logging; a frame is still put with the queue's own locking, so a receiver
that waits in another thread is woken as before.

:class:`LineFaults` makes the master's handle behave as a real controller that fails (``daror hil
--fault bus_off@T``, ``error_passive@T``: :data:`LINE_FAULT_KINDS`): from the first SYNC the
master sends at or after ``T``, bus-off: the master's frames (that SYNC first) reach no drive, the
frames the drives send reach the master no more, its ``state`` reads ``BusState.ERROR`` and a
socketcan error frame (CAN_ERR_BUSOFF) arrives in its receive queue; error-passive: its ``state``
reads ``BusState.PASSIVE``, a CAN_ERR_CRTL error frame with the passive flag arrives, and frames
flow. Either detection path can be switched off (:attr:`LineFaults.reports_state`,
:attr:`LineFaults.sends_error_frames`), as an interface may offer only one. While no SYNC reaches
the drives, the world goes on without it (the drives' timers, their stop ramps, the plant: the drive
set runs a tick without SYNC per SYNC lost, :meth:`LineFaults.take_lost_syncs`).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import can
from can.interfaces.virtual import VirtualBus

from hal.canopen.cia301.nmt import SYNC_COB_ID
from hal.canopen.health import CAN_ERR_RESTARTED, ControllerState, error_frame_data
from hal.capabilities import BUS_LINE_FAULT_KINDS
from hal.errors import InputError

if TYPE_CHECKING:
    from hal.canopen.sim.link import LockstepLink

__all__ = ["LINE_FAULT_KINDS", "LineFaults", "SimulationBus"]

#: Faults of the master's CAN controller, not of a drive (``--fault KIND@T_S``, no node).
LINE_FAULT_KINDS: tuple[str, ...] = BUS_LINE_FAULT_KINDS
#: The joint a line fault is recorded with in the drives' events (it is no drive's).
LINE_JOINT = 0
#: The error counters a simulated controller reports on entering a state (tx; rx stays 0).
_TX_ERRORS = {ControllerState.BUS_OFF: 255, ControllerState.PASSIVE: 128, ControllerState.ACTIVE: 0}
_BUS_STATE = {
    ControllerState.ACTIVE: can.BusState.ACTIVE,
    ControllerState.WARNING: can.BusState.ACTIVE,
    ControllerState.PASSIVE: can.BusState.PASSIVE,
    ControllerState.BUS_OFF: can.BusState.ERROR,
}


class LineFaults:
    """The master's controller failing, in robot time (see the module docstring).

    Args:
        events: where an injection is recorded as ``(robot time s, 0, "injected KIND")`` (the drives' events).
    """

    def __init__(self, events: list[tuple[float, int, str]]) -> None:
        self.events = events
        self.state = ControllerState.ACTIVE
        #: The master's ``bus.state`` tells the controller's state (as ixxat's and etas' do).
        self.reports_state = True
        #: socketcan-style error frames arrive in the master's receive queue.
        self.sends_error_frames = True
        self._scheduled: list[tuple[float, str]] = []
        self._receiver: SimulationBus | LockstepLink | None = None
        self._lost_syncs = 0

    def attach(self, bus: SimulationBus | None, receiver: LockstepLink | None = None) -> None:
        """The master's handle from now on (a new handle is a restarted controller: error-active).

        ``receiver``: where the master receives in lock-step (:class:`hal.canopen.sim.link.LockstepLink`):
        the controller's error frames go there, and a bus-off stops what it carries; None: the handle's
        own queue.
        """
        self._receiver = receiver if receiver is not None else bus
        self.state = ControllerState.ACTIVE
        self._lost_syncs = 0
        if bus is not None:
            bus.line = self
        if receiver is not None:
            receiver.line = self

    def schedule(self, kind: str, at_s: float) -> None:
        """``kind`` at the first SYNC the master sends at or after robot time ``at_s``.

        Raises:
            InputError: not one of :data:`LINE_FAULT_KINDS`, or a time that is negative or not finite.
        """
        _check_kind(kind)
        if not (at_s >= 0 and at_s != float("inf")):
            raise InputError(f"fault {kind} at {at_s} s: expected a time of 0 s or later")
        self._scheduled.append((float(at_s), kind))
        self._scheduled.sort()

    def inject(self, kind: str, now_s: float) -> None:
        """``kind`` now (the master's next frames already meet it).

        Raises:
            InputError: not one of :data:`LINE_FAULT_KINDS`.
        """
        _check_kind(kind)
        self._enter(ControllerState.BUS_OFF if kind == "bus_off" else ControllerState.PASSIVE)
        self.events.append((now_s, LINE_JOINT, f"injected {kind}"))

    def clear(self) -> None:
        """Nothing scheduled; a failed controller is restarted (bus-off) or back to error-active."""
        self._scheduled.clear()
        if self.state is not ControllerState.ACTIVE:
            restarted = self.state is ControllerState.BUS_OFF
            self._enter(ControllerState.ACTIVE, restarted)

    def take_lost_syncs(self) -> int:
        """SYNCs the master sent that reached no drive since the last call."""
        lost, self._lost_syncs = self._lost_syncs, 0
        return lost

    @property
    def bus_state(self) -> can.BusState:
        return _BUS_STATE[self.state] if self.reports_state else can.BusState.ACTIVE

    def _at_sync(self, t_s: float) -> None:
        while self._scheduled and self._scheduled[0][0] <= t_s + 1e-12:
            _, kind = self._scheduled.pop(0)
            self.inject(kind, t_s)

    def _enter(self, state: ControllerState, restarted: bool = False) -> None:
        receiver = self._receiver
        if receiver is not None and state is ControllerState.BUS_OFF and self.state is not ControllerState.BUS_OFF:
            receiver.went_off()
        self.state = state
        if receiver is not None and self.sends_error_frames:
            can_id, data = error_frame_data(state, _TX_ERRORS.get(state, 0))
            receiver.put_error_frame(can_id | (CAN_ERR_RESTARTED if restarted else 0), data)


def _check_kind(kind: str) -> None:
    if kind not in LINE_FAULT_KINDS:
        raise InputError(f"bus fault {kind!r}; expected one of {', '.join(LINE_FAULT_KINDS)}")


class SimulationBus(VirtualBus):
    """A ``virtual`` bus handle whose :meth:`send` builds a new message per receiver (see the module docstring)."""

    #: The controller faults of this handle (the master's; None: it never fails).
    line: LineFaults | None = None
    _kept = 0  # frames received before the controller went bus-off, still to be read

    @property
    def state(self) -> can.BusState:
        """The controller's state: error-active unless a :class:`LineFaults` says otherwise."""
        return can.BusState.ACTIVE if self.line is None else self.line.bus_state

    def went_off(self) -> None:
        """Bus-off from now on: what was received stays readable, nothing more arrives (but error frames)."""
        self._kept = self.queue.qsize()

    def put_error_frame(self, can_id: int, data: bytes) -> None:
        """The controller reports an event: a socketcan error frame in this handle's receive queue."""
        self.queue.put(
            can.Message(
                arbitration_id=can_id, is_error_frame=True, data=data, timestamp=time.time(),
                channel=self.channel_id, check=False,
            )
        )  # fmt: skip

    def recv(self, timeout: float | None = None) -> can.Message | None:
        line = self.line
        if line is not None and line.state is ControllerState.BUS_OFF:
            return self._recv_off()
        if timeout == 0 and not self._filters:
            self._check_if_open()
            try:
                return self.queue.queue.popleft()  # the deque behind the queue: an atomic pop
            except IndexError:
                return None
        return super().recv(timeout)

    def _recv_off(self) -> can.Message | None:
        """A bus-off controller's receive: the frames it had, then only its own error frames."""
        self._check_if_open()
        pending = self.queue.queue
        while pending:
            message = pending.popleft()
            if self._kept > 0:
                self._kept -= 1
                return message
            if message.is_error_frame:
                return message
        return None

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._check_if_open()
        line = self.line
        if line is not None:
            if msg.arbitration_id == SYNC_COB_ID:
                line._at_sync(msg.timestamp)
            if line.state is ControllerState.BUS_OFF:
                if msg.arbitration_id == SYNC_COB_ID:
                    line._lost_syncs += 1
                return  # a bus-off controller sends nothing (python-can's socketcan queues or refuses it)
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        data = bytes(msg.data)
        channel_id = self.channel_id
        for bus_queue in self.channel:
            own = bus_queue is self.queue
            if own and not self.receive_own_messages:
                continue
            bus_queue.put(
                can.Message(
                    timestamp=timestamp,
                    arbitration_id=msg.arbitration_id,
                    is_extended_id=msg.is_extended_id,
                    is_remote_frame=msg.is_remote_frame,
                    is_error_frame=msg.is_error_frame,
                    dlc=msg.dlc,
                    data=data,
                    channel=channel_id,
                    is_rx=not own,
                    check=False,
                ),
                block=True,
                timeout=timeout,
            )
