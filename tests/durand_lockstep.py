"""Drives on the independent stack (durand) in lock-step with the simulated plant: a drive set for ``can-sim``.

:class:`DurandDriveSet` has what :class:`hal.canopen.backend.SimulatedCanHal` needs of
:class:`hal.canopen.sim.drives.SimulatedDriveSet` (``attach``, ``line``, ``power_on``, ``step``,
``tick_without_sync``, the faults and events of :class:`hal.canopen.sim.world.CanSimWorld`), but its
drives are durand nodes: each built from its node's EDS of a robot file with the CiA 402
application of tests/durand_drives.py (:func:`tests.durand_drives.create_node`, the same code the
wall-clock harness runs), knowing nothing of ``hal`` but the bus. :class:`DurandCanHal` is the
``can-sim`` backend with that drive set in place of the project's drives.

Lock-step, on the caller's thread (no python-can Notifier, no wall clock): the master sends its
cycle into the link (:class:`hal.canopen.sim.link.LockstepLink`), :meth:`DurandDriveSet.step`
hands every frame, in bus order, to each node that subscribes to its COB-ID (durand's own
dispatch: NMT, SDO, RPDOs, SYNC), and a SYNC is where time passes::

    SYNC: durand's timers (heartbeats, inhibit times) run up to the plant's robot time on the
          VirtualScheduler; every drive samples the plant (motor and link encoders, the spring
          torque object if it has one, the e-stop buttons in its wiring's object, the e-stop
          circuit's cut on its safe torque off input) into its dictionary; every node handles the
          SYNC (durand applies the synchronous RPDOs and sends its synchronous TPDOs); the plant
          then runs one tick with the torques the drives' power stages apply (0x6071 per mille of
          the drive's own 0x6076, times the gear)

so a TPDO carries the plant's state at the SYNC that triggered it, as the project's drives do.
Robot time is the plant's; durand's scheduler is process-global and is this drive set's from
:meth:`DurandDriveSet.power_on` until it is detached (:func:`tests.durand_drives.claim_durand`: one
durand harness at a time).

Errors durand swallows (its callbacks run in "ignore" mode) are collected in
:attr:`DurandDriveSet.errors`, as the wall-clock harness collects them. Units: torques in per mille
of 0x6076 (mNm) inside, N m outside; angles in the wiring's counts inside, rad outside.
"""

from __future__ import annotations

import hashlib
import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import canopen
import durand
import numpy as np
from durand.network import NetworkABC
from durand.scheduler import AbstractScheduler, VirtualScheduler
from durand.services.nmt import StateEnum

from hal.canopen.backend import SimulatedCanHal
from hal.canopen.master import CanMaster
from hal.canopen.sim.bus import LineFaults
from hal.canopen.sim.link import LockstepLink
from hal.config import CanSimHalConfig
from hal.errors import HalError, InputError
from hal.interface import Command
from hal.robot import RobotDescription
from hal.sim.backend import SimHal
from tests.durand_drives import (
    MOTOR_RATED_TORQUE,
    PRODUCER_HEARTBEAT_TIME,
    SYNC_COB_ID,
    TPDO1_BASE,
    TPDO2_BASE,
    Cia402Device,
    DevicePower,
    DriveWiring,
    Errors,
    LogWatch,
    TimedFrame,
    claim_durand,
    create_node,
    fire_due_events,
    holds_durand,
    release_durand,
    watch_durand_logs,
)

__all__ = ["CHECKPOINT_SYNCS", "DURAND_FAULT_KINDS", "DurandCanHal", "DurandDriveSet", "LockstepScheduler"]

#: Faults a durand drive takes (:meth:`DurandDriveSet.inject`): its heartbeat producer off, a fault with its EMCY.
DURAND_FAULT_KINDS: tuple[str, ...] = ("heartbeat_loss", "emcy", "drive_fault")
#: The EMCY (error code, error register) of an injected fault (CiA 301 table 21: generic; current, device output side).
_FAULT_EMCY = {"emcy": (0x1000, 0x01), "drive_fault": (0x2320, 0x03)}
#: The states in which a drive's power stage is on (for the HIL report's "power stage on/off" events).
_STAGE_ON = (DevicePower.OPERATION_ENABLED, DevicePower.QUICK_STOP_ACTIVE)
#: The data of a heartbeat that says OPERATIONAL (CiA 301 7.2.8.3.2.2).
HEARTBEAT_OPERATIONAL = bytes((int(StateEnum.OPERATIONAL),))
#: The function codes of a MinimalNode's four TPDOs (CiA 301's pre-defined connection set).
_TPDO_FUNCTIONS = (TPDO1_BASE, TPDO2_BASE, TPDO2_BASE + 0x100, TPDO2_BASE + 0x200)
#: Every this many SYNCs the stream's digest so far is kept (:attr:`DurandDriveSet.checkpoints`).
CHECKPOINT_SYNCS = 1000
_FRAME_HEAD = struct.Struct("<IHB")  # SYNC count, COB-ID, length: what the stream digest takes of a frame


class LockstepScheduler(VirtualScheduler):
    """durand's VirtualScheduler on the plant's robot time, advanced by the drive set (:meth:`run_until`).

    durand 0.5.0's ``VirtualScheduler.run`` never advances its time while it fires events (a timer
    that re-arms itself, as the heartbeat does, is due at once again and loops forever), and its
    ``cancel`` raises KeyError on an entry that already fired. Here an event's
    time is the scheduler's while it fires (a re-armed timer counts from it), events fire in time
    order (equal times: in the order they were added) and cancelling a fired entry is nothing. An
    event's failure is collected in ``errors``, never raised into the master's tick.
    """

    def __init__(self, errors: Errors) -> None:
        super().__init__()
        self._errors = errors

    @property
    def time_s(self) -> float:
        """The scheduler's time: robot time of the last :meth:`run_until`, s."""
        return float(self._time)

    def add(self, delay: float, callback: Callable[..., Any], args: Any = (), kwargs: Any = None) -> int:
        entry = self._entry_index
        self._entry_index += 1
        self._entry_dict[entry] = VirtualScheduler.Entry(callback, tuple(args), dict(kwargs or {}))
        self._timestamp_dict[entry] = self._time + max(float(delay), 0.0)
        return entry

    def cancel(self, entry: int) -> None:
        self._entry_dict.pop(entry, None)
        self._timestamp_dict.pop(entry, None)

    def run(self, duration: float) -> None:
        self.run_until(self._time + duration)

    def run_until(self, t_s: float) -> None:
        """Fire every event due at or before robot time ``t_s`` (s), each at its own time; then the time is ``t_s``."""
        fire_due_events(self, t_s, self._errors)

    def restart(self, t_s: float) -> None:
        """No event left, the time ``t_s`` (s): a new session's drives start with no timer of the last one's."""
        self._entry_dict.clear()
        self._timestamp_dict.clear()
        self._time = t_s


@dataclass
class DriveTraffic:
    """What one durand drive did on the bus (counted on the caller's thread).

    Attributes:
        handled: frames handed to the node (those it subscribes to), by COB-ID.
        sent: frames the node sent, by COB-ID.
        service_frames: every frame the node sent but its PDOs, in order, stamped with robot time:
            the boot-up message, heartbeats, SDO responses, EMCYs.
        syncs: SYNCs the node handled.
    """

    handled: dict[int, int] = field(default_factory=dict)
    sent: dict[int, int] = field(default_factory=dict)
    service_frames: list[TimedFrame] = field(default_factory=list)
    syncs: int = 0


class _LinkNetwork(NetworkABC):  # type: ignore[misc]
    """durand's network of one node on the lock-step link: its subscriptions, its sends into the master's queue.

    Accepts the ``callback`` keyword durand's own SYNC consumer passes to ``remove_subscription``.
    """

    def __init__(
        self, node_id: int, errors: Errors, now: Callable[[], float], record: Callable[[int, bytes], None]
    ) -> None:
        self.node_id = node_id
        self.subscriptions: dict[int, Callable[[int, bytes], None]] = {}
        self.traffic = DriveTraffic()
        self.put: Callable[[int, bytes], None] | None = None  # the link's send_from_drive; None: detached
        self._errors = errors
        self._now = now
        self._record = record

    def add_subscription(self, cob_id: int, callback: Callable[[int, bytes], None]) -> None:
        self.subscriptions[cob_id] = callback

    def remove_subscription(self, cob_id: int, callback: object = None) -> None:
        self.subscriptions.pop(cob_id, None)

    def send(self, cob_id: int, msg: bytes) -> None:
        data = bytes(msg)
        counts = self.traffic.sent
        counts[cob_id] = counts.get(cob_id, 0) + 1
        if cob_id & 0x780 not in _TPDO_FUNCTIONS:
            self.traffic.service_frames.append(TimedFrame(self._now(), cob_id, data))
        self._record(cob_id, data)
        if self.put is not None:
            self.put(cob_id, data)

    def deliver(self, cob_id: int, data: bytes) -> None:
        """The frame to the node if it subscribes to ``cob_id`` (its callback's failure collected, as durand's listener would log it)."""
        callback = self.subscriptions.get(cob_id)
        if callback is None:
            return
        counts = self.traffic.handled
        counts[cob_id] = counts.get(cob_id, 0) + 1
        try:
            callback(cob_id, data)
        except Exception as exc:
            self._errors.add(
                f"node {self.node_id}: {type(exc).__name__}: {exc} while handling 0x{cob_id:03X} {data.hex()}"
            )
        if cob_id == SYNC_COB_ID:
            self.traffic.syncs += 1


class _DurandDrive:
    """One drive: its EDS and wiring, its network on the link, its durand node and CiA 402 application."""

    def __init__(self, node_id: int, eds_path: Path, wiring: DriveWiring) -> None:
        self.node_id = node_id
        self.eds = canopen.import_od(str(eds_path), node_id)
        self.wiring = wiring
        self.network: _LinkNetwork | None = None
        self.node: durand.MinimalNode | None = None
        self.device: Cia402Device | None = None
        # The counts last written to the dictionary: an unchanged encoder is not written again (each write
        # packs every TPDO that maps it, in durand's update callbacks).
        self.last_counts: list[int | None] = [None, None, None]


class DurandDriveSet:
    """Durand drives of joints 1-4 and the plant they move, in lock-step (see the module docstring).

    Args:
        plant: the simulated plant (:class:`hal.sim.backend.SimHal`), opened by :meth:`power_on`.
        drives: node id -> (its EDS, its wiring), joints 1-4 in node id order of the master's
            configuration (:func:`tests.durand_drives.robot_file_drives`).

    Raises:
        ValueError: not four drives.
    """

    def __init__(self, plant: SimHal, drives: Mapping[int, tuple[Path, DriveWiring]]) -> None:
        if len(drives) != 4:
            raise ValueError(f"{len(drives)} drives; the robot has 4 joints")
        self.plant = plant
        self.bus: LockstepLink | None = None
        self.drives = [_DurandDrive(n, path, wiring) for n, (path, wiring) in drives.items()]
        #: What happened to the drives (as the project's drive set records it, for the HIL report).
        self.events: list[tuple[float, int, str]] = []
        self.line = LineFaults(self.events)
        self.syncs = 0
        self.errors = Errors()
        self._log_watch = LogWatch(self.errors)
        self._scheduler = LockstepScheduler(self.errors)
        self._previous_scheduler: AbstractScheduler | None = None
        self._unwatch_logs: Callable[[], None] | None = None
        self._scheduled: list[tuple[float, int, str, int]] = []  # (robot time, order, kind, joint)
        self._stage_on = [False] * len(self.drives)
        self._torques = np.zeros(len(self.drives))
        self._digest = hashlib.sha256()
        #: (SYNCs so far, robot time s, :meth:`stream_digest` then) every :data:`CHECKPOINT_SYNCS` SYNCs of the session.
        self.checkpoints: list[tuple[int, float, str]] = []

    # --- what the tests read ------------------------------------------------------------------

    @property
    def t_s(self) -> float:
        """Robot time, s (the plant's)."""
        return float(self.plant.time_s)

    @property
    def node_ids(self) -> list[int]:
        return [d.node_id for d in self.drives]

    def traffic(self, node_id: int) -> DriveTraffic:
        """What the drive of ``node_id`` handled and sent in this session."""
        network = self._drive(node_id).network
        if network is None:
            raise RuntimeError(f"node {node_id} is not powered on")
        return network.traffic

    def device(self, node_id: int) -> Cia402Device:
        """The drive's CiA 402 application (its power state, its applied torque)."""
        device = self._drive(node_id).device
        if device is None:
            raise RuntimeError(f"node {node_id} is not powered on")
        return device

    def read(self, node_id: int, index: int, sub: int = 0) -> Any:
        """``index:sub`` of the drive's dictionary (durand's)."""
        node = self._drive(node_id).node
        if node is None:
            raise RuntimeError(f"node {node_id} is not powered on")
        return node.object_dictionary.read(index, sub)

    def stream_digest(self) -> str:
        """sha256 of every frame the drives handled and sent this session, in order, each with its SYNC count."""
        return self._digest.hexdigest()

    @property
    def durand_defects(self) -> dict[str, int]:
        """How often each known durand defect showed (see :data:`tests.durand_drives.DURAND_TPDO_SYNC_WHILE_INACTIVE`)."""
        return dict(self._log_watch.defects)

    @property
    def applied_motor_torque_nm(self) -> np.ndarray:
        """The torque each drive's power stage applies now (N m at the gearbox's output, (4,))."""
        return np.array([self._applied_nm(d) for d in self.drives])

    def _drive(self, node_id: int) -> _DurandDrive:
        for drive in self.drives:
            if drive.node_id == node_id:
                return drive
        raise KeyError(f"no drive with node id {node_id} (drives: {self.node_ids})")

    # --- the bus ------------------------------------------------------------------------------

    def attach(self, bus: LockstepLink | None) -> None:
        """Use the lock-step link from now on; None: detached (frames are lost) and durand's scheduler given back.

        Raises:
            HalError: a bus that is not the lock-step link (durand's drives run only in lock-step here).
        """
        if bus is not None and not isinstance(bus, LockstepLink):
            raise HalError("the durand drive set runs in lock-step only: expected the lock-step link")
        self.bus = bus
        for drive in self.drives:
            if drive.network is not None:
                drive.network.put = None if bus is None else bus.send_from_drive
        if bus is None:
            self.release()

    def release(self) -> None:
        """durand's scheduler and logger as they were before :meth:`power_on`; timers stopped. Safe twice."""
        self._scheduler.restart(self._scheduler.time_s)
        if self._previous_scheduler is not None:
            durand.set_scheduler(self._previous_scheduler)
            self._previous_scheduler = None
        if self._unwatch_logs is not None:
            self._unwatch_logs()
            self._unwatch_logs = None
        release_durand(self)

    def power_on(self) -> None:
        """A new session: the plant at rest, every drive a new durand node (boot-up message, pre-operational, factory PDOs).

        Raises:
            RuntimeError: another durand harness runs in this process (durand's scheduler is process-global).
        """
        if not holds_durand(self):
            claim_durand(self)
            self._previous_scheduler = durand.get_scheduler()
            durand.set_scheduler(self._scheduler)
            self._unwatch_logs = watch_durand_logs(self._log_watch)
        self.plant.open()
        self.syncs = 0
        self._digest = hashlib.sha256()
        self.checkpoints = []
        bus = self.bus
        if bus is not None:
            bus.to_drives.clear()  # nothing of an earlier session is left on the drives' side
        self._scheduler.restart(self.t_s)
        for drive in self.drives:
            drive.network = _LinkNetwork(drive.node_id, self.errors, lambda: self.t_s, self._record)
            drive.network.put = None if bus is None else bus.send_from_drive
            drive.last_counts = [None, None, None]
            drive.node, drive.device = create_node(drive.network, drive.node_id, drive.eds, drive.wiring, self.errors)
            drive.device.power_cut = bool(self.plant.power_cut)

    def _record(self, cob_id: int, data: bytes) -> None:
        self._digest.update(_FRAME_HEAD.pack(self.syncs, cob_id, len(data)) + data)

    def step(self) -> None:
        """Every frame the master sent since the last call, in bus order, to the nodes that subscribe to it (a SYNC: time passes).

        Raises:
            HalError: the plant failed (diverged).
        """
        bus = self.bus
        if bus is None:
            return
        pending = bus.to_drives
        networks = [d.network for d in self.drives if d.network is not None]
        record = self._record
        while pending:
            cob_id, data = pending.popleft()
            record(cob_id, data)
            if cob_id == SYNC_COB_ID:
                self._sync()
            else:
                for network in networks:
                    network.deliver(cob_id, data)
        for _ in range(self.line.take_lost_syncs()):
            self.tick_without_sync()  # a SYNC reached no drive (the master's controller is bus-off): time goes on

    def _sync(self) -> None:
        now = self.t_s
        self._scheduler.run_until(now)
        self._inject_due(now)
        operator, pilot = self._sample()
        for drive in self.drives:
            if drive.network is not None:
                drive.network.deliver(SYNC_COB_ID, b"")
        self.syncs += 1
        if self.syncs % CHECKPOINT_SYNCS == 0:
            self.checkpoints.append((self.syncs, now, self._digest.hexdigest()))
        self._plant_tick(operator, pilot)

    def tick_without_sync(self) -> None:
        """One SYNC period of robot time without a SYNC (a silent master): durand's timers, the inputs, the physics.

        Raises:
            HalError: the plant failed (diverged).
        """
        self.step()
        now = self.t_s
        self._scheduler.run_until(now)
        self._inject_due(now)
        operator, pilot = self._sample()
        self._plant_tick(operator, pilot)

    def _sample(self) -> tuple[bool, bool]:
        """Every drive's inputs now: its encoders (and spring torque object) in its wiring's counts, the e-stops, the cut."""
        sample = self.plant.read_without_faults()
        operator, pilot = bool(sample.estop[0]), bool(sample.estop[1])
        cut = bool(self.plant.power_cut)
        q, theta, tau = sample.q_rad, sample.theta_rad, sample.tau_nm
        for j, drive in enumerate(self.drives):
            device, node = drive.device, drive.node
            if device is None or node is None:
                continue
            wiring = drive.wiring
            od = node.object_dictionary
            counts = (
                round(float(theta[j]) / wiring.rad_per_motor_count),
                round(float(q[j]) / wiring.rad_per_link_count),
                round(float(tau[j]) / wiring.nm_per_torque_count) if wiring.torque is not None else None,
            )
            last = drive.last_counts
            for k, (where, value) in enumerate(zip((wiring.motor, wiring.link, wiring.torque), counts, strict=True)):
                if where is not None and value is not None and value != last[k]:
                    od.write(*where, value)
                    last[k] = value
            if (device.estop_operator, device.estop_pilot, device.power_cut) != (operator, pilot, cut):
                device.estop_operator, device.estop_pilot, device.power_cut = operator, pilot, cut
                device.publish()
        return operator, pilot

    def _applied_nm(self, drive: _DurandDrive) -> float:
        if drive.device is None or drive.node is None or not drive.device.applied_permille:
            return 0.0
        rated = int(
            drive.node.object_dictionary.read(MOTOR_RATED_TORQUE, 0)
        )  # the drive's own 0x6076, as the master set it
        return drive.wiring.applied_torque_nm(drive.device.applied_permille, rated)

    def _plant_tick(self, operator: bool, pilot: bool) -> None:
        """The plant runs one tick with the torques the drives' power stages apply; a cut in that tick switches them off.

        Raises:
            HalError: the plant failed (diverged).
        """
        torques = self._torques
        for j, drive in enumerate(self.drives):
            torques[j] = self._applied_nm(drive)
            device = drive.device
            on = device is not None and device.power in _STAGE_ON and not device.power_cut
            if on is not self._stage_on[j]:
                self._stage_on[j] = on
                self.events.append((self.t_s, j + 1, "power stage on" if on else "power stage off"))
        try:
            self.plant.write(Command(torques.copy(), bool(np.any(torques != 0.0))))
        except HalError as exc:
            raise HalError(f"simulated plant behind the durand drives: {exc}") from None
        if self.plant.power_cut:
            for drive in self.drives:
                device = drive.device
                if device is not None and not device.power_cut:
                    device.estop_operator, device.estop_pilot, device.power_cut = operator, pilot, True
                    device.publish()

    # --- faults -------------------------------------------------------------------------------

    def inject(self, kind: str, joint: int, duration_s: float | None = None) -> None:
        """``kind`` (:data:`DURAND_FAULT_KINDS`) in the drive of ``joint`` (1-4) now.

        ``heartbeat_loss``: its producer off (0x1017 = 0) until :meth:`clear_faults`; ``emcy``,
        ``drive_fault``: FAULT with 0x603F set, then the EMCY (the application's ``fault``).

        Raises:
            InputError: a kind durand's drives do not take, a joint not 1-4, or a duration (none of them ends by itself).
        """
        drive = self._drive_of(kind, joint, duration_s)
        if drive.node is None or drive.device is None:
            raise InputError(f"fault {kind}: the drive of joint {joint} is not powered on")
        if kind == "heartbeat_loss":
            drive.node.object_dictionary.write(PRODUCER_HEARTBEAT_TIME, 0, 0)
        else:
            code, register = _FAULT_EMCY[kind]
            drive.device.fault(code, register, b"")
        self.events.append((self.t_s, joint, f"injected {kind}"))

    def schedule(self, kind: str, joint: int, at_s: float, duration_s: float | None = None) -> None:
        """``kind`` in the drive of ``joint`` at the first SYNC at or after robot time ``at_s`` (s).

        Raises:
            InputError: as :meth:`inject`, or a time that is negative or not finite.
        """
        self._drive_of(kind, joint, duration_s)
        if not (math.isfinite(at_s) and at_s >= 0):
            raise InputError(f"fault {kind} at {at_s} s: expected a time of 0 s or later")
        self._scheduled.append((float(at_s), len(self._scheduled), kind, joint))
        self._scheduled.sort()

    def _inject_due(self, now: float) -> None:
        while self._scheduled and self._scheduled[0][0] <= now + 1e-12:
            _, _, kind, joint = self._scheduled.pop(0)
            self.inject(kind, joint)

    def _drive_of(self, kind: str, joint: int, duration_s: float | None) -> _DurandDrive:
        if kind not in DURAND_FAULT_KINDS:
            raise InputError(f"fault kind {kind!r}: the durand drives take {', '.join(DURAND_FAULT_KINDS)}")
        if not (isinstance(joint, int) and 1 <= joint <= len(self.drives)):
            raise InputError(f"fault {kind}: joint {joint!r}; expected 1-{len(self.drives)}")
        if duration_s is not None:
            raise InputError(f"fault {kind}: lasts until it is reset; no duration")
        return self.drives[joint - 1]

    def clear_faults(self) -> None:
        """Nothing scheduled, the master's controller healthy, every heartbeat producer back at the EDS's time (a
        drive in FAULT stays there until the master's fault reset)."""
        self._scheduled.clear()
        self.line.clear()
        for drive in self.drives:
            node = drive.node
            if node is None:
                continue
            period = drive.eds[PRODUCER_HEARTBEAT_TIME].default if PRODUCER_HEARTBEAT_TIME in drive.eds else None
            if node.object_dictionary.read(PRODUCER_HEARTBEAT_TIME, 0) == 0 and period:
                node.object_dictionary.write(PRODUCER_HEARTBEAT_TIME, 0, int(period))


class DurandCanHal(SimulatedCanHal):
    """``can-sim`` with durand's drives (:class:`DurandDriveSet`) in place of the project's: the same master, link and plant.

    Args:
        config: the ``can-sim`` configuration (``daror hil``'s of a robot file: :func:`daror_runtime.hil.hil_config`).
        drives: node id -> (its EDS, its wiring), the configuration's nodes.
        description: the robot (default: the scenario's).
        traffic_log: where to log every frame in candump format (None: the configuration's).

    Raises:
        HalConfigError: as :class:`hal.canopen.backend.SimulatedCanHal`.
        ValueError: ``drives`` are not the configuration's node ids, in its order.
    """

    def __init__(
        self,
        config: CanSimHalConfig,
        drives: Mapping[int, tuple[Path, DriveWiring]],
        description: RobotDescription | None = None,
        traffic_log: Path | None = None,
    ) -> None:
        super().__init__(config, description, traffic_log)
        if list(drives) != list(config.node_ids):
            raise ValueError(f"durand drives {list(drives)}; the configuration's nodes are {list(config.node_ids)}")
        self.durand = DurandDriveSet(self._plant, drives)
        # SimulatedCanHal keeps its drive set here (its open and shutdown attach and detach it).
        self._drives = self.durand  # type: ignore[assignment]
        self._owed_s = 0.0

    def _drive_set(self) -> Any:
        return self.durand

    def _start(self, master: CanMaster) -> None:
        self._owed_s = 0.0  # a new start-up: no robot time owed from an earlier one
        super()._start(master)

    def _master_wait(self, seconds: float) -> None:
        """The master's start-up waits robot time for the drives (D169): :meth:`_robot_time_passes`.

        The project's drives answer everything the start-up waits for at once (their heartbeat at
        NMT start included), so ``SimulatedCanHal``'s master waits without time passing. durand's
        heartbeat producer sends on its timer only (the first OPERATIONAL heartbeat one period after
        NMT start): the master's start-up would wait for it while robot time stood still. Here each
        wait of the master is robot time: the drives and the plant run a period without SYNC for
        each period waited (the master's own SYNCs go on at their period meanwhile, as on hardware).
        """
        self._robot_time_passes(seconds)

    def _robot_time_passes(self, seconds: float) -> None:
        """The master waits ``seconds`` (s): the drive set runs a SYNC period without SYNC for each whole period waited."""
        self._owed_s += seconds
        period = 1.0 / self.rate_hz
        while self._owed_s >= period - 1e-12:
            self._owed_s -= period
            self.durand.tick_without_sync()
