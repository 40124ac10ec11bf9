"""The four simulated SEA drives on their side of the bus, in front of the simulated plant.

The drives' side of the bus, one for all four drives: in lock-step the link
(:class:`hal.canopen.sim.link.LockstepLink`: each frame its COB-ID and bytes, no message object),
in a thread of their own a python-can ``virtual`` bus handle (:meth:`SimulatedDriveSet.start_thread`).
:meth:`SimulatedDriveSet.step` processes the frames that arrived since the last call in bus order;
a SYNC is where time passes::

    SYNC: every drive applies the RPDOs received since the previous SYNC and samples its joint
          (q, theta and the spring torque of the plant's readings now, the e-stop buttons, the
          safe torque off input) into its TPDOs; the plant then runs one tick with the torques
          the drives' power stages apply

so a TPDO carries the state at the SYNC that triggered it, and a target torque acts from the
SYNC after the RPDO that carried it (CiA 402 cyclic synchronous torque). The plant is a
:class:`hal.sim.backend.SimHal` (physics, sensors, pilot, e-stop buttons, the e-stop circuit)
whose encoders are not quantised: the drives quantise, in the units of their EDS. Robot time is
the plant's.

The e-stop: the buttons reach every drive's statusword bits 14 and 15 at once; the drives' safe
torque off input is the plant's ``power_cut`` (the robot's ``estop.wiring``: ``sto`` cuts at the
press, ``ss1`` after the safety relay's delay, during which the drives keep their power). The
plant decides the cut when it runs a tick, so a drive sees it at the SYNC after the tick in
which it happened, and is switched off right after that tick (its applied torque then is what
the plant applied: none); its statusword shows it from the next SYNC.

:meth:`SimulatedDriveSet.tick_without_sync` lets the world go on while no SYNC comes (a master
that went silent): the drives' timers, their stop ramps and the physics, one period at a time.

In lock-step the master calls :meth:`step` after it sent its frames (no thread, one fixed order:
the run is deterministic).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from operator import attrgetter

import can
import numpy as np

from hal.canopen.cia301.nmt import HEARTBEAT_BASE, SDO_REQUEST_BASE, SYNC_COB_ID
from hal.canopen.cia402.statemachine import PowerState
from hal.canopen.profile import DriveProfile
from hal.canopen.sim.bus import LineFaults
from hal.canopen.sim.drive import DEFAULT_DROP_S, SimulatedSeaDrive
from hal.canopen.sim.link import LockstepLink
from hal.capabilities import BUS_FAULT_KINDS
from hal.errors import HalError, InputError
from hal.interface import CheckedCommand
from hal.robot import N_JOINTS
from hal.sim.backend import SimHal

__all__ = ["SimulatedDriveSet"]

_new_tuple = tuple.__new__  # a CheckedCommand without the NamedTuple's Python-level __new__ (every tick)
#: The power states in which a drive's power stage applies torque: commanded, or ramping by itself (a tuple:
#: membership by identity, no Python-level Enum.__hash__ per drive and tick).
_PDO_GENERATION = attrgetter("pdo_generation")
#: Heartbeat COB-IDs of nodes 1-127 (a drive hears the master's; the steady cycle takes one a cycle).
_HEARTBEAT_FIRST, _HEARTBEAT_LAST = HEARTBEAT_BASE + 1, HEARTBEAT_BASE + 127
_STAGE_ON = (PowerState.OPERATION_ENABLED, PowerState.QUICK_STOP_ACTIVE, PowerState.FAULT_REACTION_ACTIVE)


class SimulatedDriveSet:
    """The drives of joints 1-4 and the plant they move.

    Args:
        bus: the lock-step link, or the drives' handle on a virtual bus (created with
            ``preserve_timestamps=True``; for :meth:`start_thread`), or None until :meth:`attach`.
        plant: the simulated plant, opened by :meth:`power_on`.
        profiles: the drives of joints 1-4 (:mod:`hal.canopen.profile`): each is built from its
            profile's EDS and reads its sensors into its profile's objects.
        master_node_id: the node id whose heartbeat the drives consume.
    """

    def __init__(
        self,
        bus: can.BusABC | LockstepLink | None,
        plant: SimHal,
        profiles: tuple[DriveProfile, ...],
        master_node_id: int,
    ) -> None:
        self.bus: can.BusABC | LockstepLink | None = None
        self.plant = plant
        self.drives = [
            SimulatedSeaDrive(p.node_id, p.dictionary, self._send, master_node_id, profile=p) for p in profiles
        ]
        self._by_node = {d.node_id: d for d in self.drives}
        self._torques = np.zeros(N_JOINTS)
        self._applied = [0.0] * len(self.drives)  # what each power stage applies, N m (a steady cycle's)
        self._scheduled: list[tuple[float, str, int, float | None]] = []
        #: What happened to the drives, for a HIL run's report: (robot time s, joint 1-4, what), what
        #: ``injected KIND`` (a fault injected into its drive) or ``power stage on``/``off`` (from that
        #: plant tick on the drive applies torque, in OPERATION ENABLED or a stop ramp, or no longer).
        self.events: list[tuple[float, int, str]] = []
        self.line = LineFaults(self.events)  # the master's controller failing (bus_off, error_passive)
        self._stage_on = [False] * len(self.drives)
        self.syncs = 0
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._pending_first: tuple[int, bytes] | None = None  # the frame a thread's blocking receive took
        self._routes_of: tuple[tuple[int, ...], dict[int, SimulatedSeaDrive], dict[int, int]] = ((), {}, {})
        self._take: Callable[[], tuple[int, bytes] | None] = _nothing
        self._put: Callable[[int, bytes], None] = _lose
        self.attach(bus)
        self.thread_error: str | None = None
        self._clock: Callable[[], float] | None = None  # the drives' time in a thread (None: the plant's)

    @property
    def t_s(self) -> float:
        """The drives' time, s: the plant's robot time, or the clock given to :meth:`start_thread`."""
        return self.plant.time_s if self._clock is None else self._clock()  # time_s: the world's t_s

    def attach(self, bus: can.BusABC | LockstepLink | None) -> None:
        """Use ``bus`` from now on: python-can's (a thread, :meth:`start_thread`) or the lock-step link
        (:mod:`hal.canopen.sim.link`); None: detached (frames the drives send are lost, as on an unplugged cable)."""
        self.bus = bus
        self._frames: deque[tuple[int, bytes]] | None = None  # the lock-step link's frames to the drives
        send: Callable[[int, bytes], None] = self._send
        if isinstance(bus, LockstepLink):
            self._frames = bus.to_drives
            self._take: Callable[[], tuple[int, bytes] | None] = _taker(bus.to_drives)
            self._put: Callable[[int, bytes], None] = bus.send_from_drive
            send = bus.drive_sender()  # straight onto the link (eight frames a cycle), as _send would put them
        elif bus is not None:
            self._take = _python_can_taker(bus)
            self._put = _python_can_sender(bus, lambda: self.t_s)
        for drive in self.drives:
            drive.connect(send)

    def _send(self, cob_id: int, data: bytes) -> None:
        if self.bus is not None:
            self._put(cob_id, data)

    def power_on(self) -> None:
        """A new session: the plant at rest, every drive switched on (boot-up message, pre-operational, factory objects)."""
        self.plant.open()
        self.syncs = 0
        while self.bus is not None and self._take() is not None:
            pass  # nothing of an earlier session is left on the drives' side
        now = self.t_s
        for drive in self.drives:
            drive.power_on(now)

    def step(self) -> None:
        """Process every frame received since the last call, in bus order (see the module docstring).

        Raises:
            HalError: the plant failed (diverged): the session cannot go on.
        """
        if self.bus is None:
            return
        lockstep = self._clock is None  # robot time moves only at a SYNC; a thread's clock runs on its own
        drives = self.drives
        if lockstep and self._steady_cycle():
            # The plant's tick just advanced every drive to this time and nothing arrived since: advancing
            # again changes only a stop ramp under way (a ramp from no torque ends at its second step).
            now = self.t_s
            for drive in drives:
                if drive.ramping:
                    drive.advance(now)
        else:
            self._process_frames(lockstep)
            now = self.t_s
            for drive in drives:
                drive.advance(now)
        for _ in range(self.line.take_lost_syncs()):
            self.tick_without_sync()  # a SYNC reached no drive (the master's controller is bus-off): time goes on

    def _process_frames(self, lockstep: bool) -> None:
        """:meth:`step`'s frames one by one: each to the drive it is for, a SYNC to all (the general path)."""
        take = self._take
        drives = self.drives
        routes = self._routes()
        frame, self._pending_first = self._pending_first, None
        if frame is None:
            frame = take()
        now = self.t_s
        while frame is not None:
            cob_id, data = frame
            if cob_id == SYNC_COB_ID:
                self._sync()
                routes = self._routes()  # a SYNC may have changed what the drives listen to (a restart)
                now = self.t_s
            else:
                if not lockstep:
                    now = self.t_s
                target = routes.get(cob_id)
                if target is not None:
                    target.receive(cob_id, data, now)
                else:
                    for drive in drives:  # NMT, heartbeats, anything else: every drive takes what is for it
                        drive.receive(cob_id, data, now)
            frame = take()

    def _steady_cycle(self) -> bool:
        """The cycle of a running session in one pass, if it is one; False (nothing done) if not.

        In lock-step nearly every step is the master's cycle: at most one RPDO for each drive, then
        the SYNC, with every drive steady (:meth:`SimulatedSeaDrive.steady_sync_ready`), no fault
        due and the power stages supplied. Then each drive takes its RPDO and the SYNC in one call
        (:meth:`SimulatedSeaDrive.steady_sync`) and the plant runs its tick: the same frames, values
        and order as :meth:`_process_frames` gives (each drive's frames reach only that drive, so
        taking its RPDO just before its SYNC changes nothing), without a call per layer (issue 25).
        """
        frames = self._frames
        if not frames or frames[-1][0] != SYNC_COB_ID or self._pending_first is not None:
            return False
        now = self.t_s
        if (self._scheduled and self._scheduled[0][0] <= now + 1e-12) or self.plant.power_cut:
            return False  # an injection (_inject_due) or a cut power stage: the general path
        drives = self.drives
        routes = self._steady_routes()
        rpdos: list[tuple[int, bytes] | None] = [None] * len(drives)
        heartbeat = None  # the master's heartbeat in this cycle (every 100 ms: one cycle in 40 at 400 Hz)
        last = len(frames) - 1
        for k, frame in enumerate(frames):
            if k == last:
                break
            j = routes.get(frame[0])
            if j is None:
                if heartbeat is None and _HEARTBEAT_FIRST <= frame[0] <= _HEARTBEAT_LAST:
                    heartbeat = frame
                    continue
                return False
            if rpdos[j] is not None:
                return False
            rpdos[j] = frame
        for drive, rpdo in zip(drives, rpdos, strict=True):
            if not drive.steady_sync_ready(rpdo, now):
                return False
        if heartbeat is not None:
            for drive in drives:
                if not drive.heartbeat_is_quiet():
                    return False
        frames.clear()
        if heartbeat is not None:
            # Every drive takes it (the general path's unrouted frame), before its RPDO: see heartbeat_is_quiet
            for drive in drives:
                drive.receive(heartbeat[0], heartbeat[1], now)
        sample = self.plant.read_without_faults()
        operator, pilot = sample.estop[0], sample.estop[1]
        # Python floats, three calls (the same values as float() of each element: twelve calls)
        q, theta, tau = sample.q_rad.tolist(), sample.theta_rad.tolist(), sample.tau_nm.tolist()
        applied = self._applied
        for j, drive in enumerate(drives):
            applied[j] = drive.steady_sync(rpdos[j], q[j], theta[j], tau[j], operator, pilot, now)
        self.syncs += 1
        self._plant_tick(operator, pilot, applied)
        return True

    def _steady_routes(self) -> dict[int, int]:
        """CAN-ID -> the index of the one drive a frame is for (:meth:`_routes`, derived with it)."""
        self._routes()
        return self._routes_of[2]

    # --- drives on their own thread (real time, as real drives) ----------------------------------

    def start_thread(self, clock: Callable[[], float]) -> None:
        """Process the bus in a thread of its own from now on, each frame as it arrives (real drives' timing).

        For a master on the wall clock (``can``, real time): a SYNC is answered within the time
        the thread takes to wake and process it, not at the master's next call, and ``clock`` (s)
        is the drives' time: heartbeats and their watchdogs run on it whether SYNCs come or not,
        as a real drive's do. Stop it with :meth:`stop_thread` before the bus is closed.
        """
        if self._thread is not None:
            return
        self._clock = clock
        self._running.set()
        self._thread = threading.Thread(target=self._serve, name="simulated CAN drives", daemon=True)
        self._thread.start()

    def stop_thread(self) -> None:
        """Stop the thread of :meth:`start_thread` (waits for it). Raises what it failed with, if it failed.

        Raises:
            HalError: the drives' thread failed (the plant diverged, a bug): the message says how.
        """
        thread, self._thread = self._thread, None
        if thread is not None:
            self._running.clear()
            thread.join()
        self._clock = None
        if self.thread_error is not None:
            raise HalError(f"simulated drives' thread failed: {self.thread_error}")

    def _serve(self) -> None:
        try:
            while self._running.is_set():
                bus = self.bus
                if bus is None:
                    return
                if not isinstance(bus, can.BusABC):
                    raise HalError("the drives' thread runs on a python-can bus, not on the lock-step link")
                message = bus.recv(timeout=0.005)  # python-can's blocking receive: woken by the next frame
                if message is None:
                    now = self.t_s
                    for drive in self.drives:
                        drive.advance(now)  # heartbeats go on while no frame comes
                    continue
                self._pending_first = _frame_of(message)
                self.step()
        except Exception as exc:  # the thread's failure is reported by stop_thread, never lost
            self.thread_error = f"{type(exc).__name__}: {exc}"

    def _routes(self) -> dict[int, SimulatedSeaDrive]:
        """CAN-ID -> the one drive a frame is for: each drive's SDO requests and valid RPDOs (a shared CAN-ID is not routed).

        Derived again only when a drive's PDO parameters changed since (:attr:`SimulatedSeaDrive.pdo_generation`).
        """
        generations = tuple(map(_PDO_GENERATION, self.drives))  # in C: it runs every cycle
        if generations != self._routes_of[0]:
            routes = self._derive_routes()
            index = {id(drive): j for j, drive in enumerate(self.drives)}
            self._routes_of = (generations, routes, {cob: index[id(drive)] for cob, drive in routes.items()})
        return self._routes_of[1]

    def _derive_routes(self) -> dict[int, SimulatedSeaDrive]:
        routes: dict[int, SimulatedSeaDrive] = {}
        shared: set[int] = set()
        for drive in self.drives:
            for cob_id in (SDO_REQUEST_BASE + drive.node_id, *drive.rpdo_can_ids()):
                if cob_id in routes and routes[cob_id] is not drive:
                    shared.add(cob_id)
                routes[cob_id] = drive
        for cob_id in shared:
            del routes[cob_id]
        return routes

    def _sync(self) -> None:
        now = self.t_s
        self._inject_due(now)
        plant = self.plant
        sample = plant.read_without_faults()
        operator, pilot = sample.estop[0], sample.estop[1]
        cut = plant.power_cut
        q, theta, tau = sample.q_rad, sample.theta_rad, sample.tau_nm
        for j, drive in enumerate(self.drives):
            drive.on_sync(float(q[j]), float(theta[j]), float(tau[j]), operator, pilot, now, cut)
        self.syncs += 1
        self._plant_tick(operator, pilot)

    def tick_without_sync(self) -> None:
        """One SYNC period of robot time without a SYNC: the master went silent, the world did not.

        What arrived on the bus is processed first (nothing, from a silent master); then the
        drives read their hardwired inputs, their stop ramps and power stages act on the plant for
        one tick, and their timers run (the master's heartbeat, the RPDO deadline: what makes them
        stop by themselves). They send no TPDO (no SYNC) but their heartbeats and EMCYs.

        Raises:
            HalError: the plant failed (diverged).
        """
        self.step()
        now = self.t_s
        self._inject_due(now)
        sample = self.plant.read_without_faults()
        operator, pilot = sample.estop[0], sample.estop[1]
        cut = self.plant.power_cut
        for drive in self.drives:
            drive.on_inputs(operator, pilot, cut, now)
        self._plant_tick(operator, pilot)

    def _plant_tick(self, operator: bool, pilot: bool, applied_nm: list[float] | None = None) -> None:
        """The plant runs one tick with the torques the drives' power stages apply; then the drives' time moves on.

        The plant decides in its tick whether the e-stop circuit cut the power (at the press with
        sto, once the relay's delay ran out with ss1): a drive whose supply went in that tick is
        off right after it, before its timers run.

        Raises:
            HalError: the plant failed (diverged).
        """
        torques = self._torques
        applied = [drive.applied_torque_nm for drive in self.drives] if applied_nm is None else applied_nm
        torques[:] = applied
        # any torque that is not zero (a NaN counts, -0.0 does not), in Python floats: one call, not four
        enable = applied.count(0.0) != len(applied)
        stage_on = self._stage_on
        for j, drive in enumerate(self.drives):
            on = drive.power_state in _STAGE_ON and not drive.power_cut
            if on is not stage_on[j]:  # a change: a handful a session, for the HIL report
                stage_on[j] = on
                self.events.append((self.t_s, j + 1, "power stage on" if on else "power stage off"))
        plant = self.plant
        try:
            # torques is float64 (4,) by construction: a CheckedCommand the plant takes without converting it
            plant.write(_new_tuple(CheckedCommand, (torques.copy(), enable, ())))
        except HalError as exc:
            raise HalError(f"simulated plant behind the CAN drives: {exc}") from None
        now = self.t_s
        if plant.power_cut:
            for drive in self.drives:
                if not drive.power_cut:
                    drive.on_inputs(operator, pilot, True, now)
        for drive in self.drives:
            drive.advance(now)

    # --- faults -------------------------------------------------------------------------------

    def inject(self, kind: str, joint: int, duration_s: float | None = None) -> None:
        """Inject ``kind`` into the drive of ``joint`` (1-4) now (see :data:`hal.capabilities.BUS_FAULT_KINDS`).

        Raises:
            InputError: an unknown kind, a joint not 1-4, or a duration that is not positive.
        """
        drive = self._drive_of(kind, joint, duration_s)
        now = self.t_s
        drive.inject(kind, now, (duration_s or DEFAULT_DROP_S) if kind == "drop_frames" else None)
        self.events.append((now, joint, f"injected {kind}"))

    def schedule(self, kind: str, joint: int, at_s: float, duration_s: float | None = None) -> None:
        """Inject ``kind`` into the drive of ``joint`` at the first SYNC at or after robot time ``at_s``.

        Raises:
            InputError: as :meth:`inject`, or a time that is negative or not finite.
        """
        self._drive_of(kind, joint, duration_s)
        if not (np.isfinite(at_s) and at_s >= 0):
            raise InputError(f"fault {kind} at {at_s} s: expected a time of 0 s or later")
        self._scheduled.append((float(at_s), kind, joint, duration_s))
        self._scheduled.sort(key=lambda item: item[0])

    def _inject_due(self, now: float) -> None:
        while self._scheduled and self._scheduled[0][0] <= now + 1e-12:
            _, kind, joint, duration = self._scheduled.pop(0)
            self.inject(kind, joint, duration)

    def _drive_of(self, kind: str, joint: int, duration_s: float | None) -> SimulatedSeaDrive:
        if kind not in BUS_FAULT_KINDS:
            raise InputError(f"fault kind {kind!r}; expected one of {', '.join(BUS_FAULT_KINDS)}")
        if not (isinstance(joint, int) and 1 <= joint <= len(self.drives)):
            raise InputError(f"fault {kind}: joint {joint!r}; expected 1-{len(self.drives)}")
        if duration_s is not None and kind != "drop_frames":
            # Only a dropout ends by itself; the other faults last until a fault reset or NMT reset.
            raise InputError(f"fault {kind}: a duration is only for drop_frames; {kind} lasts until it is reset")
        if duration_s is not None and not (np.isfinite(duration_s) and duration_s > 0):
            raise InputError(f"fault {kind}: duration {duration_s} s; expected a positive time")
        return self.drives[joint - 1]

    def clear_faults(self) -> None:
        """Every injected cause removed (heartbeats and TPDOs resume, frames pass, nothing scheduled).

        A drive in FAULT stays there until the master's fault reset (CiA 402: the cause is gone,
        the fault is still latched in the drive), as a real drive does.
        """
        self._scheduled.clear()
        self.line.clear()
        now = self.t_s
        for drive in self.drives:
            drive.clear_injected(now)

    @property
    def applied_motor_torque_nm(self) -> np.ndarray:
        """The torque each drive's power stage applies now (Nm, (4,))."""
        return np.array([d.applied_torque_nm for d in self.drives])


def _frame_of(message: can.Message) -> tuple[int, bytes] | None:
    """A python-can message as the drives take it: (COB-ID, data); None for an error or remote frame (no drive's)."""
    if message.is_error_frame or message.is_remote_frame:
        return None
    return message.arbitration_id, bytes(message.data)


def _python_can_taker(bus: can.BusABC) -> Callable[[], tuple[int, bytes] | None]:
    """The next data frame on ``bus`` (error and remote frames skipped), None when none is queued."""
    recv = bus.recv

    def take() -> tuple[int, bytes] | None:
        while (message := recv(timeout=0)) is not None:
            frame = _frame_of(message)
            if frame is not None:
                return frame
        return None

    return take


def _python_can_sender(bus: can.BusABC, clock: Callable[[], float]) -> Callable[[int, bytes], None]:
    """Sends a frame on ``bus`` stamped with the drives' time ``clock()`` (s)."""

    def send(cob_id: int, data: bytes) -> None:
        bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False, timestamp=clock()))

    return send


def _taker(queue: deque[tuple[int, bytes]]) -> Callable[[], tuple[int, bytes] | None]:
    """The next frame of a lock-step queue, None when it is empty."""
    popleft = queue.popleft

    def take() -> tuple[int, bytes] | None:
        return popleft() if queue else None

    return take


def _nothing() -> None:
    return None


def _lose(cob_id: int, data: bytes) -> None:
    """A frame sent while detached: lost, as on an unplugged cable."""
