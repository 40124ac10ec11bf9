"""The lock-step bus between the master and the simulated drives: every frame's COB-ID and bytes, in bus order.

python-can's ``virtual`` bus hands a frame to a receiver as a :class:`can.Message` put into a
``queue.Queue`` (a lock and a condition per put): with the master's own message that was three
objects and two locked puts per frame, a third of a lock-step tick (docs/performance.md, issue 25).
In lock-step nothing waits on a queue: the master sends its cycle, the drives process it
(:meth:`hal.canopen.sim.drives.SimulatedDriveSet.step`), the master drains their answers, in one
thread. :class:`LockstepLink` is that bus without the objects: a frame is its COB-ID and its bytes
in a deque, one per direction, in the order sent. The master's side of it is the same
:class:`hal.canopen.master.CanMaster` code path as on hardware (its ``transmit`` and its frame
source are the only two calls that differ: :meth:`LockstepLink.send` for ``bus.send`` and
:class:`LinkFrames` for :class:`hal.canopen.bus.PolledFrames`); every frame is still counted and
logged by the master.

The master's controller fails as :class:`hal.canopen.sim.bus.SimulationBus` makes it fail
(:class:`hal.canopen.sim.bus.LineFaults`, the same rules): from the SYNC at which bus-off is
injected the master's frames reach no drive, and it reads only what it had received, then its
own error frames; error-passive puts an error frame in its receive queue and frames flow.

python-can's ``virtual`` bus stays for everything that is not lock-step: the drives in a thread of
their own (``daror can scan``, tests/can_rig.py) and the independent stack (tests/durand_drives.py).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

import can

from hal.canopen.bus import Frame, FrameSource
from hal.canopen.cia301.nmt import SYNC_COB_ID
from hal.canopen.health import ControllerState
from hal.errors import HalError

if TYPE_CHECKING:
    from hal.canopen.sim.bus import LineFaults

__all__ = ["LinkFrames", "LockstepLink"]


class LockstepLink:
    """Frames between the master and the drives in lock-step (see the module docstring).

    The master's receive queue holds ``(CAN id, data, error frame)`` in arrival order; the drives'
    holds ``(COB-ID, data)``.
    """

    def __init__(self) -> None:
        self.to_drives: deque[tuple[int, bytes]] = deque()
        self.to_master: deque[tuple[int, bytes, bool]] = deque()
        #: The master's controller faults (:meth:`hal.canopen.sim.bus.LineFaults.attach` sets it).
        self.line: LineFaults | None = None
        self._kept = 0  # frames received before the controller went bus-off, still to be read
        self._closed = False

    def send(self, cob_id: int, data: bytes, t_s: float) -> None:
        """The master transmits a frame at robot time ``t_s`` (a bus-off controller sends nothing).

        Raises:
            can.CanOperationError: the link is closed (as python-can's closed bus raises).
        """
        if self._closed:  # _check_open's test, written out: five frames a cycle
            raise can.CanOperationError("Cannot operate on a closed bus")
        line = self.line
        if line is not None:
            if cob_id == SYNC_COB_ID:
                line._at_sync(t_s)
            if line.state is ControllerState.BUS_OFF:
                if cob_id == SYNC_COB_ID:
                    line._lost_syncs += 1
                return
        self.to_drives.append((cob_id, data))

    def send_from_drive(self, cob_id: int, data: bytes) -> None:
        """A drive transmits a frame (the master receives it; the drives do not hear each other)."""
        if not self._closed:
            self.to_master.append((cob_id, data, False))

    def drive_sender(self) -> Callable[[int, bytes], None]:
        """:meth:`send_from_drive` as one function for the drives (each sends two TPDOs a cycle: a call less a frame)."""
        append = self.to_master.append

        def send(cob_id: int, data: bytes) -> None:
            if not self._closed:
                append((cob_id, data, False))

        return send

    def put_error_frame(self, can_id: int, data: bytes) -> None:
        """The master's controller reports an event: an error frame in its receive queue."""
        self.to_master.append((can_id, data, True))

    def went_off(self) -> None:
        """Bus-off from now on: what was received stays readable, nothing more arrives (but error frames)."""
        self._kept = len(self.to_master)

    def take_for_master(self) -> tuple[int, bytes, bool] | None:
        """The master's next received frame, None when there is none (a bus-off controller: see the module docstring).

        Raises:
            can.CanOperationError: the link is closed.
        """
        self._check_open()
        pending = self.to_master
        line = self.line
        if line is None or line.state is not ControllerState.BUS_OFF:
            return pending.popleft() if pending else None
        while pending:
            frame = pending.popleft()
            if self._kept > 0:
                self._kept -= 1
                return frame
            if frame[2]:
                return frame
        return None

    def close(self) -> None:
        """Nothing passes any more; what was queued is gone (a closed bus)."""
        self._closed = True
        self.to_drives.clear()
        self.to_master.clear()

    def _check_open(self) -> None:
        if self._closed:
            raise can.CanOperationError("Cannot operate on a closed bus")


class LinkFrames(FrameSource):
    """The master's frame source on a :class:`LockstepLink`: what :class:`hal.canopen.bus.PolledFrames` does on a bus.

    Args:
        link: the lock-step link.
        now: the time a frame is stamped with when it is drained (robot time).
    """

    def __init__(self, link: LockstepLink, now: Callable[[], float]) -> None:
        self._link = link
        self._now = now
        self._errors: deque[tuple[int, bytes]] = deque()

    def take_error_frames(self) -> list[tuple[int, bytes]]:
        taken = list(self._errors)
        self._errors.clear()
        return taken

    def drain(self) -> list[Frame]:
        link = self._link
        now = self._now()
        frames = []
        try:
            if link.line is None or link.line.state is not ControllerState.BUS_OFF:
                pending = link.to_master
                link._check_open()
                while pending:
                    cob_id, data, error = pending.popleft()
                    if error:
                        self._errors.append((cob_id, data))
                    else:
                        frames.append((cob_id, data, now))
                return frames
            take = link.take_for_master
            while (frame := take()) is not None:
                cob_id, data, error = frame
                if error:
                    self._errors.append((cob_id, data))
                else:
                    frames.append((cob_id, data, now))
        except can.CanError as exc:
            raise HalError(f"reading the CAN bus failed: {exc}") from None
        return frames
