"""The CANopen backends: ``can`` (the DAROR-01's drives) and ``can-sim`` (simulated drives on a virtual bus).

Both are the same master (:class:`hal.canopen.master.CanMaster`) behind the HAL contract; the
runtime above ``hal`` is identical for every backend. What differs:

=============  ======================================  ==========================================
               ``can`` (:class:`CanHal`)                ``can-sim`` (:class:`SimulatedCanHal`)
=============  ======================================  ==========================================
the bus        python-can, from the configuration       python-can ``virtual``, one per backend
               (or a bus handed in)
receiving      python-can's Notifier thread stores      drained in the tick (no thread: a fixed
               frames; the tick drains them             order, deterministic in lock-step)
time           the wall clock since ``open``            the plant's robot time (virtual: each
                                                        write is one SYNC, one plant tick)
the drives     real ones                                :mod:`hal.canopen.sim` in front of the
                                                        simulated plant, processed after each
                                                        cycle the master sends
=============  ======================================  ==========================================

The loop's rate is the SYNC rate: the configuration's ``rate_hz``, or the highest rate the PDO
mapping allows within the bus-load budget (:mod:`hal.canopen.busload`: its worst cycle, every
heartbeat in it; 400 Hz for four DAROR drives on 1 Mbit/s, D160). A configuration over the budget
is refused with the numbers. The tick's SDO transfers go only into cycles with room for them
(:mod:`hal.canopen.cycle_budget`, D161).

What each drive does by itself when it loses the master is the runtime's to declare
(:meth:`CanHal.set_drive_reaction`, before ``open``; category 0 when it declares nothing); the
master configures it at start-up where a drive supports it and says per drive what it got
(:meth:`CanHal.drive_reaction_report`, :mod:`hal.canopen.reaction`).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import can
import numpy as np

from hal.canopen.bitrate import check_bitrate
from hal.canopen.bus import FrameSource, ListenedFrames, TrafficLog
from hal.canopen.busload import CANDIDATE_RATES_HZ, LOAD_BUDGET, BusLoad, check_bus_load
from hal.canopen.dictionary import load_dictionary
from hal.canopen.master import CanMaster, MasterSettings
from hal.canopen.profile import DriveProfile, resolve_profiles, robot_bus_load
from hal.config import AnyHalConfig, CanHalConfig, CanSimHalConfig
from hal.errors import HalConfigError, HalError, HalNotOpenError, ShapeError
from hal.interface import (
    CheckedCommand,
    CheckedSample,
    Command,
    DriveReaction,
    Hal,
    HalBusFaultError,
    HalFaultError,
    Sample,
)
from hal.robot import N_JOINTS, RobotDescription, load_description

if TYPE_CHECKING:
    from hal.canopen.sim.drives import SimulatedDriveSet
    from hal.canopen.sim.link import LockstepLink
    from hal.canopen.sim.world import CanSimWorld
    from hal.sim.backend import SimHal

__all__ = ["CanHal", "SimulatedCanHal"]

_new_tuple = tuple.__new__
#: Virtual bus channels already handed out in this process (each simulated backend gets its own).
_CHANNELS = itertools.count(1)


def _rate(config: CanHalConfig | CanSimHalConfig, profiles: tuple[DriveProfile, ...], where: str) -> float:
    """The configured rate, or the highest the drives' PDOs allow; refused over the bus-load budget.

    Raises:
        HalConfigError: the load of the configured rate exceeds the budget (the message has the numbers).
    """

    def load(rate_hz: float) -> BusLoad:
        return robot_bus_load(profiles, rate_hz, config.bitrate, config.heartbeat_producer_ms)

    if config.rate_hz is not None:
        rate = float(config.rate_hz)
    else:
        fitting = [r for r in CANDIDATE_RATES_HZ if load(r).worst_cycle <= LOAD_BUDGET]
        if not fitting:
            raise HalConfigError(f"{where}: no loop rate fits the bus: even {load(CANDIDATE_RATES_HZ[-1]).describe()}")
        rate = fitting[0]
    check_bus_load(load(rate), where)
    return rate


class CanHal(Hal):
    """The DAROR-01's four CiA 402 SEA drives over CANopen (python-can for the bus, canopen for the EDS).

    Args:
        config: the ``can`` configuration (interface, channel, bit rate, node ids, rate, heartbeats, EDS).
        description: the robot (default: the packaged DAROR-01); its peak motor torque is the drives'.
        bus: an already open python-can bus to use instead of opening one from ``config`` (it is
            not shut down by :meth:`close`).
        traffic_log: where to log every frame in candump format (None: no log).
        profiles: the drives, resolved (None: resolved from ``config`` and ``description``,
            :func:`hal.canopen.profile.resolve_profiles`).

    Raises:
        HalConfigError: an EDS cannot be read or lacks an object the robot file names; the bus
            would be over its load budget.
    """

    kind = "can"
    virtual_time = False
    drives_hardware = True

    def __init__(
        self,
        config: CanHalConfig | CanSimHalConfig,
        description: RobotDescription | None = None,
        bus: can.BusABC | None = None,
        traffic_log: Path | None = None,
        profiles: tuple[DriveProfile, ...] | None = None,
    ) -> None:
        super().__init__(description or load_description())
        self.config = config
        self.profiles: tuple[DriveProfile, ...] = profiles or resolve_profiles(
            config, self.description.sea.spring_stiffness_nm_per_rad
        )
        self._rate_hz = _rate(config, self.profiles, f"HAL backend {self.kind}")
        self._given_bus = bus
        self._bus: can.BusABC | None = None
        self._source: FrameSource | None = None
        self._master: CanMaster | None = None
        self._traffic_path = traffic_log or (Path(config.traffic_log) if config.traffic_log is not None else None)
        self._traffic: TrafficLog | None = None
        self._traffic_epoch_s: int | None = None
        self._bitrate_check = "not checked: the bus was not opened by the backend"
        self._counts: dict[str, object] = {}
        self._is_open = False
        self._sample: Sample | None = None
        self._pending_fault: str | None = None
        self._t0 = 0.0
        self._reaction = DriveReaction(None)  # category 0 until the runtime declares otherwise
        self._reaction_report: tuple[str, ...] = ()

    @classmethod
    def from_config(cls, config: AnyHalConfig) -> CanHal:
        """The backend of a ``can`` configuration, not opened.

        Raises:
            HalConfigError: not a ``can`` configuration, or see the constructor.
        """
        if not isinstance(config, CanHalConfig):
            raise HalConfigError(f"the {cls.kind} backend takes a {cls.kind} configuration, not {config.backend!r}")
        return cls(config)

    @property
    def rate_hz(self) -> float:
        return self._rate_hz

    @property
    def master(self) -> CanMaster:
        """The master of the open session (its counters and drives, for tests and benchmarks).

        Raises:
            HalNotOpenError: the backend is not open.
        """
        if self._master is None:
            raise HalNotOpenError(f"{self.kind} backend is not open; call open() first")
        return self._master

    def settings(self) -> MasterSettings:
        """The master's settings from the configuration and the robot description."""
        c = self.config
        return MasterSettings(
            node_ids=tuple(c.node_ids),
            period_s=1.0 / self._rate_hz,
            heartbeat_producer_ms=c.heartbeat_producer_ms,
            heartbeat_consumer_ms=c.heartbeat_consumer_ms,
            master_node_id=c.master_node_id,
            peak_torque_nm=float(self.description.sea.max_motor_torque_nm),
            velocity_filter_hz=self._velocity_filter_hz(),
            sdo_timeout_s=c.sdo_timeout_ms / 1000.0,
            boot_timeout_s=c.boot_timeout_ms / 1000.0,
            rpdo_deadline_ms=(
                c.rpdo_deadline_ms if c.rpdo_deadline_ms is not None else math.ceil(5000.0 / self._rate_hz)
            ),
            ramp_s=self._reaction.ramp_s,
            bitrate=c.bitrate,
        )

    # --- the drives' own reaction to losing the master ------------------------------------------------

    def set_drive_reaction(self, reaction: DriveReaction) -> None:
        """What every drive does by itself when it loses the master, configured at the next :meth:`open`.

        ``reaction.ramp_s`` None: each drive disables at once (0x6007 disable voltage, category 0,
        also what the backend configures when nothing was declared); a time: each ramps its torque
        from the last target to zero over it (0x6007 quick stop, 0x605A, 0x6087), where the drive
        supports it. Each drive's outcome is in :meth:`drive_reaction_report` after ``open``.

        Raises:
            HalError: the backend is open (the drives are configured at start-up only), or ``ramp_s``
                is not a finite, positive time.
        """
        if self._is_open:
            raise HalError(
                f"{self.kind} backend: the drives' reaction to losing the master is configured at start-up; "
                "set it before open()"
            )
        ramp_s = reaction.ramp_s
        if ramp_s is not None and (
            isinstance(ramp_s, bool)
            or not isinstance(ramp_s, int | float)
            or not (math.isfinite(ramp_s) and ramp_s > 0)
        ):
            raise HalError(f"{self.kind} backend: a drive ramp of {ramp_s!r} s; expected a finite, positive time")
        self._reaction = DriveReaction(None if ramp_s is None else float(ramp_s))

    def drive_reaction_report(self) -> tuple[str, ...]:
        """After :meth:`open`: per drive, one sentence on what it does when it loses the master (empty before).

        The last start-up's (and a recovery's, when it configured a drive again); kept after :meth:`close`.
        """
        if self._master is not None:
            self._reaction_report = self._master.reaction_report()
        return self._reaction_report

    def _velocity_filter_hz(self) -> float:
        return float(getattr(self.config, "velocity_filter_hz", 50.0))

    # --- lifecycle --------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the bus, start a traffic log, reset, configure and start every drive (blocks until they answer).

        Raises:
            HalError: the bus cannot be opened, or a drive does not answer or has other units than its EDS.
        """
        if self._is_open:
            self.close()
        self._t0 = time.monotonic()
        bus = self._given_bus or self._open_bus()
        self._bus = bus
        self._open_traffic()
        now = self._now
        self._source = self._frame_source(bus, now)
        self._start(self._make_master(bus, self._source, now))

    def _start(self, master: CanMaster) -> None:
        """Run ``master``'s start-up; the backend is open after it (shut down again if it fails)."""
        self._master = master
        try:
            master.start()
        except HalError:
            self._shutdown()
            raise
        self._is_open = True
        self._sample = None
        self._pending_fault = None
        self._pending_bus = False

    def _now(self) -> float:
        return time.monotonic() - self._t0

    def _open_bus(self) -> can.BusABC:
        c = self.config
        # A SocketCAN interface runs at the rate the OS gave it, whatever python-can is told: read and compared.
        self._bitrate_check = check_bitrate(c.interface, c.channel, c.bitrate, "hal config: bitrate")
        try:
            return can.Bus(interface=c.interface, channel=c.channel, bitrate=c.bitrate)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise HalError(f"CAN interface {c.interface!r} channel {c.channel!r}: cannot be opened: {exc}") from None

    def _open_traffic(self) -> None:
        """The bus log of this session (one file: a second open of the backend appends to it)."""
        if self._traffic_path is not None and self._traffic is None:
            if self._traffic_epoch_s is None:
                self._traffic_epoch_s = int(time.time())
                self._traffic = TrafficLog(self._traffic_path, self._traffic_epoch_s, channel=str(self.config.channel))
            else:
                self._traffic = TrafficLog(
                    self._traffic_path, self._traffic_epoch_s, str(self.config.channel), append=True
                )

    def bus_report(self) -> dict[str, object]:
        """The bus of this backend: rate, bit rate, worst-case load, frames, the log (:class:`hal.capabilities.BusStatistics`)."""
        c = self.config
        load = robot_bus_load(self.profiles, self._rate_hz, c.bitrate, c.heartbeat_producer_ms)
        report: dict[str, object] = {
            "backend": self.kind,
            "rate_hz": self._rate_hz,
            "bitrate": c.bitrate,
            "node_ids": list(c.node_ids),
            "worst_case_load": round(load.total, 4),
            "worst_cycle_load": round(load.worst_cycle, 4),
            "load": load.describe(),
            "traffic_log": str(self._traffic_path) if self._traffic_path is not None else None,
            "traffic_log_epoch_s": self._traffic_epoch_s,
            "bitrate_check": self._bitrate_check,
        }
        if self._master is not None:
            self._counts = self._master_counts(self._master)
        return report | self._counts

    @staticmethod
    def _master_counts(m: CanMaster) -> dict[str, object]:
        return {
            "syncs": m.syncs,
            "frames_sent": m.frames_sent,
            "frames_received": m.frames_received,
            "unknown_frames": m.unknown_frames,
            "sdo_deferred": m.cycle_budget.deferred,  # transfers that waited for a cycle with room (D161)
            "bus_health": m.health.report(),
            "receive_times": m.source.receive_time_report(),
            "emcy_warnings": m.emcy_warnings.report(),
        }

    def _frame_source(self, bus: can.BusABC, now: object) -> FrameSource:
        return ListenedFrames(bus, now)  # type: ignore[arg-type]

    def _make_master(self, bus: can.BusABC, source: FrameSource, now: object) -> CanMaster:
        # Start-up waits for the drives' answers woken by the frame that arrives, not polling on a sleep.
        wait = source.wait if isinstance(source, ListenedFrames) else time.sleep
        return CanMaster(bus, source, self.profiles, self.settings(), now, wait=wait, traffic=self._traffic)  # type: ignore[arg-type]

    def close(self) -> None:
        """Torque off, every drive to pre-operational, the receive thread stopped, the bus closed. Safe twice.

        Raises:
            HalError: the torque-off frames could not be sent (the bus is closed anyway; the drives'
                own heartbeat consumers stop them when the master's heartbeat ends).
        """
        master, was_open = self._master, self._is_open
        self._is_open = False
        try:
            if was_open and master is not None:
                master.stop()
        finally:
            self._shutdown()

    def _shutdown(self) -> None:
        if self._master is not None:
            self._counts = self._master_counts(self._master)  # what the last session did, for bus_report
            self._reaction_report = self._master.reaction_report()
        if self._source is not None:
            self._source.close()
            self._source = None
        if self._bus is not None and self._given_bus is None:
            self._bus.shutdown()
        self._bus = None
        if self._traffic is not None:
            self._traffic.close()
            self._traffic = None
        self._master = None

    # --- the tick ---------------------------------------------------------------------------------

    def read(self) -> Sample:
        """The sample of the drives' TPDOs of the last SYNC (the same object until the next write).

        Raises:
            HalFaultError: faults latched since the last read (EMCY, a drive lost, the receive thread), once.
            HalNotOpenError: the backend is not open.
        """
        if not self._is_open or self._master is None:
            raise HalNotOpenError(f"{self.kind} backend is not open; call open() first")
        sample = self._sample
        if sample is None:
            master = self._master
            master.receive()
            sample = self._sample = self._build_sample(master)
            latched = master.take_latched()
            bus = master.health.take_fault()
            if bus is not None:  # the bus itself failed: its own fault kind (hal/canopen/health.py)
                self._pending_bus = True
                latched = bus if latched is None else f"{bus}; {latched}"
            if latched is not None:
                self._pending_fault = latched
        if self._pending_fault is not None:
            message, self._pending_fault = self._pending_fault, None
            bus_failed, self._pending_bus = self._pending_bus, False
            raise (HalBusFaultError if bus_failed else HalFaultError)(message)
        return sample

    def _build_sample(self, master: CanMaster) -> Sample:
        states, codes, (operator, pilot) = master.drive_states()
        # CheckedSample: the master's arrays are float64 (4,) and replaced, never changed, per cycle.
        return _new_tuple(
            CheckedSample,
            (max(master.sample_sync, 0), master.sample_t_s, master.q_rad, master.dq_rad_s, master.theta_rad,
             master.tau_nm, (operator, pilot), states, codes),
        )  # fmt: skip

    def write(self, command: Command) -> None:
        """The cycle: each drive's power state machine one step, the RPDOs, the SYNC. Never blocks.

        Raises:
            HalError: an enabled command with a non-finite torque (torque removed first), or the bus refused a frame.
            ShapeError: an enabled command's torque is not of shape (4,) (torque removed first).
            HalNotOpenError: the backend is not open.
        """
        if not self._is_open or self._master is None:
            raise HalNotOpenError(f"{self.kind} backend is not open; call open() first")
        master = self._master
        enable = bool(command.enable)
        torque = None
        if enable:
            torque = command.motor_torque_nm
            if type(command) is not CheckedCommand:
                shape = getattr(torque, "shape", None)
                if shape != (N_JOINTS,):
                    self._torque_off()
                    raise ShapeError(f"motor_torque_nm: expected shape ({N_JOINTS},), got {shape}")
                torque = np.asarray(torque, dtype=float)
            if not all(map(math.isfinite, torque.tolist())):  # Python floats, tested in C: no generator a tick
                self._torque_off()
                raise HalError(f"motor_torque_nm = {np.asarray(torque).tolist()} is not finite; torque removed")
        self._sample = None
        joints_off = command.joints_off if enable else ()
        if joints_off and any(isinstance(j, bool) or j not in range(1, N_JOINTS + 1) for j in joints_off):
            self._torque_off()
            raise ShapeError(f"joints_off: expected joint numbers 1-{N_JOINTS}, got {joints_off!r}")
        master.send_cycle(enable, torque, joints_off)

    def _torque_off(self) -> None:
        self._sample = None
        if self._master is not None:
            self._master.send_torque_off()

    def request_fault_reset(self) -> None:
        """A fault reset edge to drives in fault; lost drives are reset, configured and started again (over the next ticks)."""
        if self._master is not None:
            self._master.request_fault_reset()


class SimulatedCanHal(CanHal):
    """``can-sim``: the CANopen backend against simulated SEA drives, frame by frame in lock-step.

    The same master as :class:`CanHal` (its controller a python-can ``virtual`` handle of its own),
    its frames carried to and from the drives by the lock-step link (:mod:`hal.canopen.sim.link`)
    and drained in the tick; the drives process the bus after each cycle the master sends, and move
    the simulated plant one tick per SYNC. Lock-step is deterministic; the backend also runs in
    real time (the loop's clock paces the SYNCs).

    Args:
        config: the ``can-sim`` configuration (scenario, seed, node ids, rate, heartbeats, EDS).
        description: the robot (default: the one the scenario names); its e-stop wiring
            (``estop``: sto, or ss1 with a relay delay) is the plant's, which the drives' safe
            torque off inputs follow.
        traffic_log: where to log every frame in candump format (None: no log).
        drive_eds: node id -> the EDS a simulated drive is built from instead of the master's (a
            drive of another firmware, that lacks or limits objects the master writes; tests).

    Raises:
        HalConfigError: as :class:`CanHal`, an interface other than ``virtual``, a ``drive_eds``
            that cannot be read or names a node that is not a drive's.
        DescriptionError: the scenario or the robot description cannot be loaded.
    """

    kind = "can-sim"
    virtual_time = True
    drives_hardware = False

    def __init__(
        self,
        config: CanSimHalConfig,
        description: RobotDescription | None = None,
        traffic_log: Path | None = None,
        drive_eds: Mapping[int, Path | str] | None = None,
    ) -> None:
        from hal.sim.backend import SimHal
        from hal.sim.scenario import load_scenario

        if config.interface != "virtual":
            raise HalConfigError(
                f"HAL backend can-sim: interface {config.interface!r}; the simulated drives live on python-can's "
                "'virtual' bus (use --hal can for a real interface)"
            )
        scenario = load_scenario(config.scenario)
        if config.seed is not None:
            scenario = scenario.model_copy(update={"seed": config.seed})
        # The drives quantise their encoders in the units of their EDS: the plant's sensors do not.
        scenario = scenario.model_copy(update={"sensors": scenario.sensors.model_copy(update={"quantise": False})})
        self._scenario = scenario
        robot = description or scenario.description()
        profiles = resolve_profiles(config, robot.sea.spring_stiffness_nm_per_rad)
        rate = _rate(config, profiles, "HAL backend can-sim")
        self._plant = SimHal(scenario, rate, robot)
        super().__init__(config, self._plant.description, None, traffic_log, profiles)
        self._channel = f"{config.channel}-{next(_CHANNELS)}"
        unknown = sorted(set(drive_eds or {}) - set(config.node_ids))
        if unknown:
            raise HalConfigError(f"HAL backend can-sim: drive_eds names node(s) {unknown}, which are not the drives'")
        self._drive_dictionaries = {node: load_dictionary(path) for node, path in (drive_eds or {}).items()}
        # A drive of another firmware: the profile its master expects, on another EDS (tests).
        self._drive_profiles = tuple(
            dataclasses.replace(p, dictionary=self._drive_dictionaries[p.node_id])
            if p.node_id in self._drive_dictionaries
            else p
            for p in self.profiles
        )
        self._link: LockstepLink | None = None
        self._drives: SimulatedDriveSet | None = None
        self._world: CanSimWorld | None = None

    @classmethod
    def from_config(cls, config: AnyHalConfig) -> SimulatedCanHal:
        if not isinstance(config, CanSimHalConfig):
            raise HalConfigError(f"the {cls.kind} backend takes a {cls.kind} configuration, not {config.backend!r}")
        return cls(config)

    def _velocity_filter_hz(self) -> float:
        return float(self._scenario.sensors.velocity_filter_hz)  # the same estimate the sim backend's drives make

    def _drive_set(self) -> SimulatedDriveSet:
        from hal.canopen.sim.drives import SimulatedDriveSet

        if self._drives is None:
            self._drives = SimulatedDriveSet(None, self._plant, self._drive_profiles, self.config.master_node_id)
        return self._drives

    @property
    def world(self) -> CanSimWorld:
        """The plant's pilot and buttons, and faults injected into the drives (:class:`hal.canopen.sim.world.CanSimWorld`)."""
        from hal.canopen.sim.world import CanSimWorld

        if self._world is None:
            self._world = CanSimWorld(self._plant.world, self._drive_set())
        return self._world

    @property
    def applied_motor_torque_nm(self) -> np.ndarray:
        """The torque the drives' power stages apply now, Nm (tests)."""
        return self._drive_set().applied_motor_torque_nm

    @property
    def plant(self) -> SimHal:
        """The simulated plant behind the drives (tests: its truth, the torque it applied, its e-stop circuit)."""
        return self._plant

    @property
    def drive_set(self) -> SimulatedDriveSet:
        """The simulated drives (tests: their power states and objects; :class:`hal.canopen.sim.drives.SimulatedDriveSet`)."""
        return self._drive_set()

    def tick_without_master(self) -> None:
        """One SYNC period of robot time in which the master sends nothing: a crashed or hung runtime (tests).

        The drives and the plant go on as they would on the robot: the drives' own timers (the
        master's heartbeat they consume, their RPDO deadline, a stop ramp under way), their power
        stages and the physics. No SYNC: no TPDO, no RPDO applied. What the drives send waits in
        the master's receive queue until it reads again.

        Raises:
            HalNotOpenError: the backend is not open.
            HalError: the plant failed (diverged).
        """
        if not self._is_open:
            raise HalNotOpenError(f"{self.kind} backend is not open; call open() first")
        self._drive_set().tick_without_sync()

    def _now(self) -> float:
        return self._plant.time_s  # the plant world's time (world.t_s), without its two properties

    def open(self) -> None:
        """A new session: the plant at rest, the drives switched on, then the master's start-up (see :class:`CanHal`)."""
        drives = self._drive_set()
        if self._is_open:
            self.close()
        from hal.canopen.sim.bus import SimulationBus
        from hal.canopen.sim.link import LinkFrames, LockstepLink

        # The master's controller (its state, python-can's handle) and the lock-step link that carries
        # every frame between it and the drives (hal/canopen/sim/link.py).
        self._bus = SimulationBus(channel=self._channel, preserve_timestamps=True)
        link = self._link = LockstepLink()
        drives.attach(link)
        drives.line.attach(self._bus, link)  # bus-off and error-passive of the master's controller
        drives.power_on()
        self._open_traffic()
        self._source = LinkFrames(link, self._now)
        self._start(
            CanMaster(
                self._bus, self._source, self.profiles, self.settings(), self._now,
                pump=drives.step, wait=self._master_wait, traffic=self._traffic, transmit=link.send,
            )
        )  # fmt: skip

    def _master_wait(self, seconds: float) -> None:
        """How the master's start-up waits ``seconds`` (s) for answers: not at all, no time passes.

        The simulated drives answer within the call that sent the request (the lock-step pump), so
        nothing is gained by waiting. A drive set whose timers must run while the master waits
        (tests/durand_lockstep.py: durand's first heartbeat comes a period after NMT start, D169)
        overrides it to let robot time pass.
        """

    def _shutdown(self) -> None:
        super()._shutdown()  # the master's bus: this backend made it, CanHal shuts it down
        if self._link is not None:
            if self._drives is not None:
                self._drives.attach(None)
            self._link.close()
            self._link = None
