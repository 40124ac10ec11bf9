"""The CANopen master of the robot's four CiA 402 drives: configured at start-up, one bus cycle per tick.

Each drive is its :class:`hal.canopen.profile.DriveProfile` (the robot file's node: its EDS, its
objects and scales, its PDOs, its e-stop bits, its start-up writes, its timeouts); the DAROR-01's
four SEA drives are the short form's profiles. Start-up (:meth:`CanMaster.start`, outside the
tick, may wait on the bus; docs/canopen.md, "Start-up")::

    NMT reset communication -> every drive's boot-up message
    per drive, by SDO: read its device type, identity (0x1018) and supported modes (0x6502); write
      its mode (0x6060), the peak torque (0x6072), the heartbeat producer (0x1017) and the master's
      heartbeat as its consumer (0x1016), the cycle (0x1006, 0x60C2), every PDO's communication and
      mapping parameters (never the defaults), the robot file's sdo_init, and what it does by itself
      when it loses the master (0x6007, 0x605E, 0x6087, 0x605A: :mod:`hal.canopen.reaction`; a drive
      without them is reported, not refused); read back its units, 0x6061 and every sdo_init value;
      refuse in one line what differs from its robot file (reads judged before failed writes)
    NMT start -> the master's heartbeat and the SYNC at their periods -> every drive's OPERATIONAL
      heartbeat and first TPDOs

The tick, in one order, never waiting (:meth:`CanMaster.receive` is the HAL's read,
:meth:`CanMaster.send_cycle` its write)::

    read:  drain the frames received since the last tick; decode TPDOs, heartbeats, EMCY, SDO
           answers; the watchdogs (heartbeat consumer, TPDO staleness over N SYNCs, the receive
           thread); the sample
    write: the CiA 402 power state machine of every drive, at most one transition per tick
           (timeouts counted in ticks, fault reset on an explicit request only); the RPDOs
           (controlword, target torque); the torque slope of a drive that ramps when it loses the
           master, rewritten as its torque changes (:mod:`hal.canopen.cia402.torque_slope`); due
           SDO transfers; the master's heartbeat; the SYNC (the runtime's tick is the SYNC producer)

A drive that goes silent (heartbeat lost), whose TPDOs stop, or that restarted on its own is
*lost*: it shows as a drive in FAULT with a code (:data:`LOST_CODES`) and gets no torque. Every
such event, every EMCY that reports an error and every drive that does not follow the power state
machine is latched and raised once by the next read (:class:`hal.interface.HalFaultError`). A fault
reset request (:meth:`CanMaster.request_fault_reset`, the operator's acknowledge) sends a fault
reset edge to drives in FAULT and brings lost drives back: NMT reset node, the same SDO
configuration as at start-up (non-blocking, a transfer in flight per drive), NMT start.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import can
import numpy as np

from hal.canopen import objects as obj
from hal.canopen.bus import Frame, FrameSource, TrafficLog
from hal.canopen.cia301.emcy import EmcyClass, EmcyMessage, EmcyWarnings, classify_emcy, parse_emcy
from hal.canopen.cia301.heartbeat import HeartbeatConsumer
from hal.canopen.cia301.nmt import (
    EMCY_BASE,
    HEARTBEAT_BASE,
    SDO_RESPONSE_BASE,
    SYNC_COB_ID,
    NmtCommand,
    NmtState,
    heartbeat_frame,
    nmt_frame,
    parse_heartbeat,
)
from hal.canopen.cia301.pdo import OPTIONAL_SUBS, PdoCodec, PdoMapping
from hal.canopen.cia301.sdo import SdoClient, SdoTransfer
from hal.canopen.cia402.statemachine import (
    CW_DISABLE_VOLTAGE,
    CW_ENABLE_OPERATION,
    PowerState,
    PowerStepper,
    decode_statusword,
    drive_state,
)
from hal.canopen.cia402.torque_slope import SlopeFollower
from hal.canopen.cycle_budget import CycleBudget
from hal.canopen.health import BusHealth
from hal.canopen.profile import DriveProfile, UnitCheck, decode_supported_modes, robot_bus_load
from hal.canopen.reaction import ReactionPlan, format_ramp_s, plan_reaction
from hal.canopen.tpdo_handler import TpdoHandler, tpdo_handler
from hal.errors import HalConfigError, HalError
from hal.interface import DriveState

__all__ = ["LOST_CODES", "CanMaster", "MasterSettings"]

#: The fault code a lost drive shows (CiA 301 error codes, the master's view of the drive).
LOST_CODES = {
    "heartbeat": 0x8130,  # life guard error or heartbeat error
    "pdo": 0x8100,  # communication: its process data stopped
    "restarted": 0x8140,  # recovered from bus off / restarted: its configuration is gone
    "recovery": 0x8000,  # monitoring: bringing it back failed
}


#: Power states in which a drive ramps its torque down by itself (its slope is left alone).
_STOPPING = (PowerState.QUICK_STOP_ACTIVE, PowerState.FAULT_REACTION_ACTIVE)  # a tuple: no Enum hash per tick


#: decode_statusword's answers by statusword (a pure function of it; a session shows a handful of words).
_POWER_OF: dict[int, PowerState | None] = {}


def _power_of(statusword: int) -> PowerState | None:
    """:func:`decode_statusword`, memoised: each TPDO's statusword would walk its patterns again (issue 25, D167)."""
    try:
        return _POWER_OF[statusword]
    except KeyError:
        power = _POWER_OF[statusword] = decode_statusword(statusword)
        return power


@dataclass(frozen=True)
class MasterSettings:
    """How the master runs the bus (from the HAL configuration).

    Attributes:
        node_ids: the drive of joints 1-4.
        period_s: the SYNC period = the tick, s.
        heartbeat_producer_ms: every drive's heartbeat period (0x1017), and the master's own.
        heartbeat_consumer_ms: a drive silent this long is lost; the drives consume the master's
            heartbeat with the same time (0x1016).
        master_node_id: the node id the master's heartbeat uses (0x700 + id).
        peak_torque_nm: the drives' peak torque: commands are saturated there (0x6072 too).
        stale_syncs: a drive whose TPDOs miss this many SYNCs in a row is lost.
        velocity_filter_hz: first-order low-pass of the link velocity estimated from the load encoder.
        sdo_timeout_s: how long an SDO transfer may wait for its answer.
        boot_timeout_s: how long a drive may take to send its boot-up message after a reset.
        rpdo_deadline_ms: the drives' RPDO deadline monitoring (RPDO event timer): a drive that
            receives no RPDO this long faults by itself (0: off).
        ramp_s: what every drive does by itself when it loses the master (its heartbeat consumer or
            RPDO deadline): None, disable at once (category 0); a time, s, ramp its torque from the
            last target to zero over it, then disable (:mod:`hal.canopen.reaction`).
        bitrate: the bus bit rate, bit/s: how many bits a cycle may carry (the tick's SDO transfers
            are admitted only where the cycle has room: :mod:`hal.canopen.cycle_budget`).
    """

    node_ids: tuple[int, ...]
    period_s: float
    heartbeat_producer_ms: int = 100
    heartbeat_consumer_ms: int = 250
    master_node_id: int = 127
    peak_torque_nm: float = 40.0
    stale_syncs: int = 3
    velocity_filter_hz: float = 50.0
    sdo_timeout_s: float = 0.5
    boot_timeout_s: float = 2.0
    rpdo_deadline_ms: int = 0
    ramp_s: float | None = None
    bitrate: int = 1_000_000


@dataclass
class _Recovery:
    """Bringing a lost drive back: reset, configure, start (steps counted in the master's time)."""

    phase: str  # "reset", "configure", "start"
    since_s: float
    transfers: list[SdoTransfer] = field(default_factory=list)


@dataclass
class _Drive:
    """What the master knows of one drive."""

    profile: DriveProfile
    stepper: PowerStepper
    node_id: int = 0
    statusword: int | None = None
    power: PowerState | None = None
    motor_counts: int = 0
    load_counts: int = 0
    torque_counts: int = 0
    estop_word: int = 0
    tpdo_syncs: list[int] = field(default_factory=list)  # per TPDO: the SYNC whose TPDO arrived last
    #: The SYNC all of whose TPDOs arrived last (-1: none yet): min(tpdo_syncs), kept by _dispatch (read
    #: twelve times a cycle: a field, not a property; issue 25).
    last_sync: int = -1
    lost: str | None = None  # a key of LOST_CODES while lost
    lost_why: str = ""
    emcy: EmcyMessage | None = None  # an error reported by EMCY and not reset yet
    recovery: _Recovery | None = None
    controlword: int = CW_DISABLE_VOLTAGE
    was_stale: bool = False  # its values were not of the last update's SYNC
    reaction: ReactionPlan | None = None  # the writes of its own reaction to losing the master
    reaction_sentence: str = ""  # what it got, for the report
    slope: SlopeFollower | None = None  # while it ramps when it loses the master: its torque slope, followed
    slope_write: tuple[SdoTransfer, int] | None = None  # a slope write in flight and its value

    def __post_init__(self) -> None:
        self.node_id = self.profile.node_id
        self.forget_tpdos()

    def forget_tpdos(self) -> None:
        """No TPDO arrived yet (a start, a drive brought back)."""
        self.tpdo_syncs = [-1] * len(self.profile.pdos.tpdos)
        self.last_sync = -1


class _JointScale(NamedTuple):
    """How one joint's TPDO counts become its sample (the profile's scales, commissioning's zeros and tare)."""

    rad_per_link_count: float
    rad_per_motor_count: float
    nm_per_torque_count: float
    spring_k_nm_per_rad: float | None  # the spring torque is k (theta - q); None: the drive's torque object
    link_zero_counts: float
    motor_zero_counts: float
    torque_tare_nm: float


#: The field of :class:`_Drive` each object a TPDO may carry goes to, by the profile's role for it.
def _tpdo_fields(profile: DriveProfile) -> tuple[tuple[str, ...], ...]:
    roles = {(obj.STATUSWORD, 0): "statusword"}
    for mapped, name in ((profile.motor, "motor_counts"), (profile.link, "load_counts"),
                         (profile.torque, "torque_counts"), (profile.estop, "estop_word")):  # fmt: skip
        if mapped is not None:
            roles.setdefault((mapped.index, mapped.sub), name)
    return tuple(tuple(roles[(m.index, m.sub)] for m in pdo.objects) for pdo in profile.pdos.tpdos)


class CanMaster:
    """The protocol engine of the backend: no HAL types beyond the drive states; see the module docstring.

    Args:
        bus: the open python-can bus (the master's handle).
        source: where received frames come from (:mod:`hal.canopen.bus`).
        profiles: the drives of joints 1-4, resolved (:mod:`hal.canopen.profile`): their EDS,
            objects, scales, PDOs, e-stop bits, start-up writes and timeouts.
        settings: see :class:`MasterSettings` (its ``node_ids`` are the profiles').
        now: the master's clock, s (robot time on a simulated bus, wall time since open on hardware).
        pump: called after the master sent frames, before it expects answers (lock-step simulated
            drives process the bus then; None on hardware).
        wait: how start-up waits for answers between polls, given the longest wait in s: ``time.sleep``,
            or on hardware the frame source's :meth:`hal.canopen.bus.ListenedFrames.wait`, which returns
            as soon as a frame arrives and says how long it waited (s; None: the whole time asked, as a
            sleep): the start-up's timeouts count the time waited.
        traffic: the bus log (None: no log).
        transmit: puts one frame on the bus: ``(COB-ID, data, the master's time s)``; None: a
            :class:`can.Message` to ``bus.send`` (hardware). Lock-step over simulated drives gives
            the link's (:class:`hal.canopen.sim.link.LockstepLink`): the same frames, in the same
            order, without a message object each.

    Raises:
        HalConfigError: the profiles' node ids are not the settings', or a PDO does not fit its EDS.
    """

    def __init__(
        self,
        bus: can.BusABC,
        source: FrameSource,
        profiles: tuple[DriveProfile, ...],
        settings: MasterSettings,
        now: Callable[[], float],
        pump: Callable[[], None] | None = None,
        wait: Callable[[float], float | None] | None = None,
        traffic: TrafficLog | None = None,
        transmit: Callable[[int, bytes, float], None] | None = None,
    ) -> None:
        if tuple(p.node_id for p in profiles) != tuple(settings.node_ids):
            raise HalConfigError(
                f"the drive profiles' node ids {[p.node_id for p in profiles]} are not the settings' "
                f"{list(settings.node_ids)}"
            )
        self.bus = bus
        self.source = source
        self.profiles = tuple(profiles)
        self.settings = settings
        self._now = now
        self._pump = pump
        self._wait = wait or (lambda s: None)
        self.traffic = traffic
        self._transmit = transmit or self._send_message
        self.n = len(settings.node_ids)
        self.drives = [
            _Drive(p, PowerStepper(max(2, math.ceil(p.enable_timeout_s / settings.period_s)))) for p in profiles
        ]
        self._by_node = {d.node_id: d for d in self.drives}
        # COB-ID -> (drive, what): one dict lookup per received frame that is not a TPDO
        self._routes: dict[int, tuple[_Drive, str]] = {}
        # COB-ID -> the TPDO's handler, generated for its mapping (hal/canopen/tpdo_handler.py, D171)
        self._tpdo_handlers: dict[int, TpdoHandler] = {}
        for drive in self.drives:
            pdos = drive.profile.pdos
            for k, (pdo, names) in enumerate(zip(pdos.tpdos, _tpdo_fields(drive.profile), strict=True)):
                codec = self._codec(drive.profile, pdo)
                self._tpdo_handlers[pdo.cob_id(drive.node_id)] = tpdo_handler(
                    drive, k, codec.unpack, codec.codes, names, codec.length, _power_of, self._latch
                )
            self._routes[HEARTBEAT_BASE + drive.node_id] = (drive, "heartbeat")
            self._routes[EMCY_BASE + drive.node_id] = (drive, "emcy")
            self._routes[SDO_RESPONSE_BASE + drive.node_id] = (drive, "sdo")
        self._rpdo_cob = [d.profile.pdos.rpdo.cob_id(d.node_id) for d in self.drives]
        # Each drive's e-stop inputs (its profile's): (in the statusword, pressed when clear, operator's bits, pilot's)
        self._estop_bits = [
            None
            if d.profile.estop is None
            else (d.profile.estop_in_statusword, d.profile.estop_pressed_when_clear,
                  d.profile.estop_operator_mask, d.profile.estop_pilot_mask)
            for d in self.drives
        ]  # fmt: skip
        self._pack_sample = struct.Struct(f"={4 * len(self.drives)}d").pack  # _update_arrays' four arrays, as bytes
        self._pack_rpdo = [self._codec(d.profile, d.profile.pdos.rpdo).pack for d in self.drives]
        self.heartbeats = HeartbeatConsumer(settings.node_ids, settings.heartbeat_consumer_ms / 1000.0)
        self.sdo = SdoClient(timeout_s=settings.sdo_timeout_s)
        # The tick's SDO transfers go where a cycle has room beside its PDOs and heartbeats (D161).
        periodic_bits = robot_bus_load(
            profiles, 1.0 / settings.period_s, settings.bitrate, settings.heartbeat_producer_ms
        ).bits_per_cycle
        beats = {p.node_id: p.heartbeat_ms / 1000.0 for p in profiles if p.heartbeat_ms > 0}
        beats[settings.master_node_id] = settings.heartbeat_producer_ms / 1000.0
        self.cycle_budget = CycleBudget(settings.period_s, settings.bitrate, periodic_bits, beats)
        self._nm_per_permille = [p.nm_per_permille for p in profiles]
        self._peak_permille_of = [min(round(settings.peak_torque_nm / p.nm_per_permille), 32767) for p in profiles]
        # How each joint's TPDO counts become its sample, with commissioning's zeros and tare (the robot file's
        # calibration). An uncalibrated drive's are 0.0: (counts - 0.0) * scale and tau - 0.0 are exactly
        # counts * scale and tau, so it reads bit for bit as before calibration existed.
        self._scales = tuple(
            _JointScale(
                p.rad_per_link_count, p.rad_per_motor_count, p.nm_per_torque_count,
                (p.spring_k_nm_per_rad or 0.0) if p.torque is None else None,
                float(p.calibration.link_zero_counts), float(p.calibration.motor_zero_counts),
                float(p.calibration.torque_tare_nm),
            )
            for p in profiles
        )  # fmt: skip
        self._joint = {d.node_id: j + 1 for j, d in enumerate(self.drives)}
        #: Per node: what its start-up reads must show (:meth:`_configuration`, :meth:`_check_configuration`).
        self._expected: dict[int, list[tuple[str, tuple[SdoTransfer, ...], object]]] = {}
        self._transfers: dict[int, list[SdoTransfer]] = {}
        self._latched: list[str] = []
        self.health = BusHealth.for_bus(bus)  # the controller's state and error frames (hal/canopen/health.py)
        self.emcy_warnings = EmcyWarnings()  # EMCYs that take no torque (hal/canopen/cia301/emcy.py)
        self.syncs = 0  # SYNCs sent
        self._last_sync_s = 0.0
        self.sample_t_s = 0.0  # when the SYNC whose TPDOs the arrays hold was sent (the master's clock)
        self._started_s = 0.0
        self._next_heartbeat_s = 0.0
        self.frames_received = 0
        self.frames_sent = 0
        self.unknown_frames = 0
        self._traffic_failed = False
        #: The time from the last SYNC to the last TPDO that answered it, on the master's clock (s):
        #: the reception time of a listening source (hardware), the drain's time of a polled one.
        self.last_tpdo_latency_s = 0.0
        # the sample's arrays: new read-only ones per fresh cycle
        self.q_rad = self.dq_rad_s = self.theta_rad = self.tau_nm = np.zeros(self.n)
        self.q_rad.flags.writeable = False
        self._q_dq_lists = ([0.0] * self.n, [0.0] * self.n)  # q_rad and dq_rad_s as Python floats (_update_arrays)
        self._last_fresh_sync = -1
        self._alpha = 1.0 - math.exp(-2.0 * math.pi * settings.velocity_filter_hz * settings.period_s)

    @staticmethod
    def _codec(profile: DriveProfile, pdo: PdoMapping) -> PdoCodec:
        dictionary = profile.dictionary
        for mapped in pdo.objects:
            if dictionary.size_bits(mapped.index, mapped.sub) != mapped.bits:
                raise HalConfigError(
                    f"{dictionary.path}: {pdo.name} maps {mapped} but the EDS gives the object "
                    f"{dictionary.size_bits(mapped.index, mapped.sub)} bits"
                )
            if not dictionary.pdo_mappable(mapped.index, mapped.sub):
                raise HalConfigError(f"{dictionary.path}: {pdo.name} maps {mapped}, which the EDS says is not mappable")
        return PdoCodec(pdo, tuple(dictionary.data_type(m.index, m.sub) for m in pdo.objects))

    # --- frames out --------------------------------------------------------------------------

    def _send(self, cob_id: int, data: bytes) -> None:
        now = self._now()  # the frame's time, on the bus and in the log
        try:
            self._transmit(cob_id, data, now)
        except can.CanError as exc:
            raise HalError(f"sending frame 0x{cob_id:03X} failed: {exc}") from None
        self.frames_sent += 1
        if self.traffic is not None:
            self.traffic.frame(cob_id, data, now, sent=True)

    def _send_message(self, cob_id: int, data: bytes, now_s: float) -> None:
        self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False, timestamp=now_s))

    # --- start-up (outside the tick) ----------------------------------------------------------

    def start(self) -> None:
        """Reset, identify, configure and start every drive, then run the first cycle (may wait; see the module docstring).

        Raises:
            HalError: a drive did not answer, refused a write, lacks the robot file's mode (its
                0x6502), reports another identity or other units than its robot file, does not keep
                a value written, or did not report OPERATIONAL (the message names the drive, the
                object and the values).
        """
        self.sdo.cancel()
        self._latched.clear()
        for drive in self.drives:
            drive.lost, drive.lost_why, drive.emcy, drive.recovery = None, "", None, None
            drive.power, drive.statusword = None, None
            drive.reaction, drive.reaction_sentence, drive.slope, drive.slope_write = None, "", None, None
        booted: set[int] = set()
        for drive in self.drives:
            self._send(*nmt_frame(NmtCommand.RESET_COMMUNICATION, drive.node_id))
        self._collect(lambda frames: booted.update(self._boot_ups(frames)), lambda: len(booted) == self.n,
                      self.settings.boot_timeout_s, lambda: f"no boot-up message from node(s) {self._missing(booted)}")  # fmt: skip
        for drive in self.drives:
            self._configuration(drive.node_id)
        self._run_sdo()
        self._check_configuration(self.drives)
        for drive in self.drives:
            self._reaction_configured(drive)
        for drive in self.drives:
            self._send(*nmt_frame(NmtCommand.START, drive.node_id))
        # From NMT start on the master is a running master: its heartbeat and the SYNC at their periods
        # (a drive whose consumer or RPDO deadline is armed must not find it silent while it starts).
        self._started_s = self._now()
        self.heartbeats.start(self._now())
        self._next_heartbeat_s = self._now()
        self._send_heartbeat_if_due()
        self._sync()
        operational: set[int] = set()

        def handle(frames: list[Frame]) -> None:
            self._dispatch(frames)
            operational.update(self._operational(frames))

        # Started = every drive OPERATIONAL and current: its TPDOs answered the latest SYNC. Waiting for
        # the latest, not the first: the SYNCs go on while the heartbeats are awaited, and a start that
        # ended with a drive several SYNCs behind would lose it in the first read (stale_syncs).
        self._collect(handle, lambda: len(operational) == self.n and all(d.last_sync >= self.syncs - 1 for d in self.drives),
                      self.settings.boot_timeout_s, lambda: self._not_running(operational), cyclic=True)  # fmt: skip
        self._latched.clear()  # what happened while starting is in the start's own errors
        self.health.settle()  # a bus that failed while starting and is well again: counted, not raised

    def _missing(self, seen: set[int]) -> str:
        return ", ".join(str(d.node_id) for d in self.drives if d.node_id not in seen)

    def _not_running(self, operational: set[int]) -> str:
        """What start-up still waits for: the OPERATIONAL heartbeats and the TPDOs of the latest SYNC, naming the nodes."""
        parts = []
        silent = self._missing(operational)
        if silent:
            parts.append(f"no OPERATIONAL heartbeat from node(s) {silent}")
        quiet = ", ".join(str(d.node_id) for d in self.drives if d.last_sync < self.syncs - 1)
        if quiet:
            parts.append(f"no TPDOs for the latest SYNC from node(s) {quiet}")
        return " and ".join(parts)

    def _operational(self, frames: list[Frame]) -> list[int]:
        """The nodes whose heartbeat among ``frames`` reports OPERATIONAL."""
        return [
            cob_id - HEARTBEAT_BASE
            for cob_id, data, _ in frames
            if cob_id - HEARTBEAT_BASE in self._by_node and parse_heartbeat(data) is NmtState.OPERATIONAL
        ]

    def _boot_ups(self, frames: list[Frame]) -> list[int]:
        found = []
        for cob_id, data, _ in frames:
            node_id = cob_id - HEARTBEAT_BASE
            if node_id in self._by_node and parse_heartbeat(data) is NmtState.BOOT_UP:
                found.append(node_id)
            elif cob_id - SDO_RESPONSE_BASE in self._by_node:
                self.sdo.on_response(cob_id - SDO_RESPONSE_BASE, data)
        return found

    def _collect(
        self,
        handle: Callable[[list[Frame]], object],
        done: Callable[[], bool],
        timeout_s: float,
        missing: Callable[[], str],
        cyclic: bool = False,
    ) -> None:
        """Start-up only: pump, drain and hand frames to ``handle`` until ``done`` or ``timeout_s`` of waiting.

        ``cyclic``: the drives are started; the master's heartbeat and the SYNC go on at their periods
        of the master's clock (on a simulated bus robot time stands still meanwhile: none is due).
        """
        waited = 0.0
        step = min(0.001, timeout_s)
        while True:
            if self._pump is not None:
                self._pump()
            frames = self.source.drain()
            self._log_received(frames)
            handle(frames)
            self.health.check(self.source.take_error_frames(), self._now())
            if done():
                return
            if waited >= timeout_s:
                raise HalError(f"CAN bus: {missing()} within {timeout_s:g} s{self.health.note()}")
            slept = self._wait(step)  # on hardware: until the next frame arrives, at most the step
            waited += step if slept is None else slept
            if cyclic and self._now() - self._last_sync_s >= self.settings.period_s:
                self._send_heartbeat_if_due()
                self._sync()

    def _configuration(self, node_id: int) -> list[SdoTransfer]:
        """Queue the SDO transfers that identify, configure and check ``node_id``; returns them all, in order.

        Reads (device type, identity, supported modes), then the writes (mode, peak torque where the
        drive has 0x6072, heartbeats, cycle period, PDOs, the robot file's ``sdo_init``), the drive's
        own reaction to losing the master (kept in its ``reaction``), then the reads that check:
        the units its profile declares, 0x6061, every ``sdo_init`` value. What each read must show is kept in ``self._expected`` for
        :meth:`_check_configuration`.
        """
        s, sdo = self.settings, self.sdo
        drive = self._by_node[node_id]
        profile = drive.profile
        d = profile.dictionary
        joint = self._joint[node_id]
        peak = self._peak_permille_of[joint - 1]
        expected: list[tuple[str, tuple[SdoTransfer, ...], object]] = [
            ("device type", (sdo.read(node_id, obj.DEVICE_TYPE, 0, "device type"),), None)
        ]
        if profile.identity is not None:
            vendor, product = profile.identity
            expected.append(("vendor id", (sdo.read(node_id, obj.IDENTITY, 1, "vendor id"),), vendor))
            if product is not None:
                expected.append(("product code", (sdo.read(node_id, obj.IDENTITY, 2, "product code"),), product))
        if d.has(obj.SUPPORTED_DRIVE_MODES, 0):
            modes = sdo.read(node_id, obj.SUPPORTED_DRIVE_MODES, 0, "supported drive modes")
            expected.append(("modes", (modes,), profile.mode))
        writes = [
            (obj.MODES_OF_OPERATION, 0, d.encode(obj.MODES_OF_OPERATION, 0, profile.mode), f"modes of operation {profile.mode}"),
            (obj.PRODUCER_HEARTBEAT_TIME, 0, struct.pack("<H", profile.heartbeat_ms), "heartbeat producer time"),
            (obj.CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", (s.master_node_id << 16) | s.heartbeat_consumer_ms),
             "the master's heartbeat, consumed"),
        ]  # fmt: skip
        if d.writable(obj.MAX_TORQUE, 0):  # optional in CiA 402: the master saturates its commands either way
            writes.insert(1, (obj.MAX_TORQUE, 0, d.encode(obj.MAX_TORQUE, 0, peak), "peak torque"))
        writes += self._cycle_writes(profile)
        for pdo in profile.pdos.all:
            writes += pdo.configuration(node_id, s.rpdo_deadline_ms if pdo.direction == "rpdo" else 0)
        for index, sub, value in profile.sdo_init:
            writes.append((index, sub, d.encode(index, sub, value), f"sdo_init 0x{index:04X}:{sub} = {value}"))
        optional = {(pdo.communication_index, sub) for pdo in profile.pdos.all for sub in OPTIONAL_SUBS}
        transfers = [t for _, reads, _ in expected for t in reads]
        for index, sub, data, what in writes:
            transfers.append(sdo.write(node_id, index, sub, data, what, optional=(index, sub) in optional))
        drive.reaction = plan_reaction(sdo, d, joint, node_id, s.ramp_s, peak)
        transfers += drive.reaction.transfers
        for check in profile.unit_checks:  # after sdo_init: a drive whose units the robot file writes (0x6076)
            reads = tuple(sdo.read(node_id, check.index, sub, check.what) for sub in check.subs)
            expected.append(("unit", reads, check))
            transfers += reads
        drive.slope, drive.slope_write = None, None  # a new configuration: followed again once it is done
        display = sdo.read(node_id, obj.MODES_OF_OPERATION_DISPLAY, 0, "modes of operation display")
        expected.append(("mode shown", (display,), profile.mode))
        transfers.append(display)
        for index, sub, value in profile.sdo_init:
            read = sdo.read(node_id, index, sub, f"sdo_init 0x{index:04X}:{sub} read back")
            expected.append(("kept", (read,), value))
            transfers.append(read)
        self._expected[node_id] = expected
        self._transfers[node_id] = transfers
        return transfers

    def _cycle_writes(self, profile: DriveProfile) -> list[tuple[int, int, bytes, str]]:
        """0x1006 (the SYNC period, us) and 0x60C2 (the interpolation period) where the EDS has them writable."""
        d, period_s = profile.dictionary, self.settings.period_s
        writes = []
        if d.writable(obj.COMMUNICATION_CYCLE_PERIOD, 0):
            period_us = round(period_s * 1e6)
            writes.append((obj.COMMUNICATION_CYCLE_PERIOD, 0, d.encode(obj.COMMUNICATION_CYCLE_PERIOD, 0, period_us),
                           f"communication cycle period {period_us} us"))  # fmt: skip
        if d.writable(obj.INTERPOLATION_TIME_PERIOD, 1) and d.writable(obj.INTERPOLATION_TIME_PERIOD, 2):
            value, exponent = interpolation_period(period_s)
            writes += [
                (obj.INTERPOLATION_TIME_PERIOD, 1, d.encode(obj.INTERPOLATION_TIME_PERIOD, 1, value),
                 f"interpolation time period {value}"),
                (obj.INTERPOLATION_TIME_PERIOD, 2, d.encode(obj.INTERPOLATION_TIME_PERIOD, 2, exponent),
                 f"interpolation time index {exponent}"),
            ]  # fmt: skip
        return writes

    def _run_sdo(self) -> None:
        """Start-up only: run the SDO client until every queued transfer is done (failures are judged by the caller).

        On hardware it waits only while nothing arrives (until the next frame, at most 0.5 ms): an answer
        taken lets that drive's next request go at once, as the SDO timeouts run on the master's clock.
        """
        waited = 0.0
        # On a simulated bus (a pump) robot time stands still while nothing is synchronised, so the SDO
        # timeouts count the time waited here, 0.5 ms a pass; on hardware the master's clock runs by itself.
        virtual = self._pump is not None
        while self.sdo.busy:
            # A drive silent for one timeout gets nothing more: the start-up fails then, not after a
            # timeout per queued transfer (38 of them on the DAROR-01: 19 s at the default 500 ms).
            now = self._now() + waited if virtual else self._now()
            for cob_id, data in self.sdo.frames_due(now, abandon_silent=True):
                self._send(cob_id, data)
            if self._pump is not None:
                self._pump()
            frames = self.source.drain()
            self._log_received(frames)
            for cob_id, data, _ in frames:
                node_id = cob_id - SDO_RESPONSE_BASE
                if node_id in self._by_node:
                    self.sdo.on_response(node_id, data)
            if not self.sdo.busy:
                return
            if virtual:
                self._wait(0.0005)
                waited += 0.0005
            elif not frames:
                self._wait(0.0005)  # ListenedFrames.wait: until the next frame arrives

    def _check_configuration(self, drives: list[_Drive]) -> None:
        """Every drive is a CiA 402 drive with the robot file's mode, identity and units and keeps what was written.

        What a read found is judged first (a drive without the mode is refused for that, not for the
        write of 0x6060 it then aborted); then any transfer that failed.

        Raises:
            HalError: one line naming the node, the object and both values.
        """
        for drive in drives:
            profile = drive.profile
            for kind, reads, want in self._expected.get(drive.node_id, []):
                if not all(t.succeeded for t in reads):
                    continue
                raw = [profile.dictionary.decode(t.index, t.sub, t.value) for t in reads]
                problem = _judge(profile, kind, raw, want)
                if problem is not None:
                    raise HalError(f"CAN bus: {profile.name}: {problem}")
        for drive in drives:
            failures = [t.error for t in self._transfers.get(drive.node_id, []) if t.error]
            if failures:
                more = f" (and {len(failures) - 1} more)" if len(failures) > 1 else ""
                raise HalError(f"CAN bus: configuring the drives: {failures[0]}{more}")

    # --- the tick: read --------------------------------------------------------------------------

    def receive(self) -> bool:
        """Drain and decode what arrived since the last tick; run the watchdogs. True if the TPDOs of the last SYNC
        arrived from every drive that is not lost (a fresh cycle: the arrays were updated; a lost drive
        keeps its last values and shows FAULT).

        Raises:
            HalError: the receiving side failed (latched by the frame source, raised once).
        """
        try:
            frames = self.source.drain()
        except HalError as exc:
            self._latch(str(exc))
            frames = []
        self._log_received(frames)
        self._dispatch(frames)
        if self.traffic is not None and self.traffic.error is not None and not self._traffic_failed:
            self._traffic_failed = True
            self._latch(self.traffic.error)
        now = self._now()
        self.health.check(self.source.take_error_frames(), now)
        for node_id in self.heartbeats.newly_lost(now):
            drive = self._by_node[node_id]
            silent_ms = self.heartbeats.silent_s(node_id, now) * 1e3
            self._lose(
                drive,
                "heartbeat",
                f"no heartbeat for {silent_ms:.0f} ms (limit {self.settings.heartbeat_consumer_ms} ms)",
            )
        last = self.syncs - 1
        fresh = True
        for drive in self.drives:
            missed = last - drive.last_sync
            if missed == 0 and drive.lost is None:
                continue  # nearly every drive and tick: its TPDOs of the last SYNC came (none of the tests below acts)
            if missed > 0 and drive.lost is None and drive.recovery is None:
                # A drive already lost (shown in FAULT, without torque) does not hold the others'
                # readings back; one that just went quiet does, until it counts as lost.
                fresh = False
            if missed >= self.settings.stale_syncs and drive.lost is None and drive.recovery is None:
                self._lose(drive, "pdo", f"no TPDO for {missed} SYNCs (limit {self.settings.stale_syncs})")
            elif missed == 0 and drive.lost == "pdo":
                drive.lost, drive.lost_why = None, ""  # its data came back (a dropout that ended)
            if drive.lost == "heartbeat" and not self.heartbeats.is_lost(drive.node_id) and missed == 0:
                drive.lost, drive.lost_why = None, ""  # its heartbeat came back
        self._step_recoveries(now)
        if fresh and last > self._last_fresh_sync:
            self._update_arrays(last)
        return fresh

    def _update_arrays(self, sync: int) -> None:
        """New arrays for the cycle ``sync`` (read-only: a sample that holds the old ones stays as it was).

        A lost drive's joint keeps its last values; when its data come back, its velocity estimate
        starts again from rest rather than differentiating across the gap (the arm may have moved
        while nobody saw it: that is a jump for the safety monitor to judge, not a speed). Computed
        joint by joint in Python floats (the same IEEE operations numpy does element by element, in
        the same order; four numpy calls a cycle instead of fifteen: issue 25).
        """
        first = self._last_fresh_sync < 0
        dt_s = 0.0 if first else (sync - self._last_fresh_sync) * self.settings.period_s
        q_old, dq_old = self._q_dq_lists  # the arrays' values, kept as floats: no tolist a cycle
        alpha = self._alpha
        q_new, dq_new, theta_new, tau_new = [], [], [], []
        for j, (drive, scale) in enumerate(zip(self.drives, self._scales, strict=True)):
            rad_per_link, rad_per_motor, nm_per_count, spring_k, link_zero, motor_zero, tare_nm = scale
            # calibration.angle_rad and spring_torque_nm written out (their formulas; a call each cost more). The
            # counts are ints of at most 32 bits: Python converts them to float exactly, as float() did.
            q = (drive.load_counts - link_zero) * rad_per_link
            theta = (drive.motor_counts - motor_zero) * rad_per_motor
            # the drive's torque object, or the spring torque of the encoders around the spring: k (theta - q)
            measured_nm = drive.torque_counts * nm_per_count if spring_k is None else spring_k * (theta - q)
            dq = 0.0
            if not first:
                raw = (q - q_old[j]) / dt_s
                dq = dq_old[j] + alpha * (raw - dq_old[j])
                fresh_now = drive.last_sync == sync
                if fresh_now and drive.was_stale:
                    dq = 0.0
                drive.was_stale = not fresh_now
            q_new.append(q)
            dq_new.append(dq)
            theta_new.append(theta)
            tau_new.append(measured_nm - tare_nm)
        # One read-only block (numpy over immutable bytes: the floats' bits as they are), the four arrays
        # C-contiguous float64 views of it (one numpy call and four slices, not np.array of four lists)
        n = len(q_new)
        block = np.frombuffer(self._pack_sample(*q_new, *dq_new, *theta_new, *tau_new))
        self.q_rad, self.dq_rad_s, self.theta_rad, self.tau_nm = (
            block[:n],
            block[n : 2 * n],
            block[2 * n : 3 * n],
            block[3 * n :],
        )
        self._q_dq_lists = (q_new, dq_new)
        self._last_fresh_sync = sync
        self.sample_t_s = self._last_sync_s

    @property
    def sample_sync(self) -> int:
        """The SYNC whose TPDOs the arrays hold (-1 before the first)."""
        return self._last_fresh_sync

    def _log_received(self, frames: list[Frame]) -> None:
        self.frames_received += len(frames)
        if self.traffic is not None and frames:
            self.traffic.received(frames)

    def _dispatch(self, frames: list[Frame]) -> None:
        """Decode ``frames`` into the drives' state.

        A TPDO received before the last SYNC was sent answers an earlier SYNC (it came late): its
        values are kept, but it does not make the drive's data of the last SYNC fresh.
        """
        routes = self._routes
        handlers = self._tpdo_handlers
        sync = self.syncs - 1
        sync_s = self._last_sync_s
        latency = -1.0
        for frame in frames:
            cob_id, data, t_s = frame
            handler = handlers.get(cob_id)
            if handler is not None:
                delay = handler(data, t_s, sync, sync_s)
                if delay > latency:
                    latency = delay
                continue
            route = routes.get(cob_id)
            if route is None:
                if cob_id != SYNC_COB_ID:
                    self.unknown_frames += 1
                continue
            drive, what = route
            if what == "heartbeat":
                self._on_heartbeat(drive, frame)
            elif what == "emcy":
                self._on_emcy(drive, parse_emcy(data))
            else:
                done = self.sdo.on_response(drive.node_id, data)
                if done is not None and done.error and drive.recovery is not None:
                    self._recovery_failed(drive, done.error)
        if latency >= 0.0:
            self.last_tpdo_latency_s = latency
        for drive in self.drives:  # the handlers set tpdo_syncs (only they, and forget_tpdos)
            drive.last_sync = min(drive.tpdo_syncs)

    def _on_heartbeat(self, drive: _Drive, frame: Frame) -> None:
        _, data, t_s = frame
        state = parse_heartbeat(data)
        if state is None:
            self._latch(f"drive {drive.node_id}: a heartbeat frame that is not one ({data.hex() or 'empty'})")
            return
        self.heartbeats.on_heartbeat(drive.node_id, state, t_s)
        if state is NmtState.BOOT_UP:
            self.cycle_budget.forget(drive.node_id)  # restarted: its beat's phase is set anew when configured
        else:
            self.cycle_budget.heard(drive.node_id, t_s)
        if drive.recovery is not None:
            if drive.recovery.phase == "reset" and state is NmtState.BOOT_UP:
                self._configure_lost(drive)
            return
        if drive.lost == "restarted":
            return
        settled = t_s - self._started_s > self.settings.heartbeat_consumer_ms / 1000.0
        if state is NmtState.BOOT_UP or (settled and state in (NmtState.PRE_OPERATIONAL, NmtState.STOPPED)):
            # Started drives report OPERATIONAL; a boot-up, or later another state, means it restarted
            # or was stopped: its PDO configuration and its power state are gone. (A heartbeat sent just
            # before the drive took NMT start may still say pre-operational: hence the settling time.)
            self._lose(drive, "restarted", f"reported NMT state {state.name.lower().replace('_', '-')} while running")

    def _on_emcy(self, drive: _Drive, message: EmcyMessage) -> None:
        kind = classify_emcy(message)  # error reset, warning or error (D154)
        if kind is EmcyClass.RESET:
            drive.emcy = None
            self.emcy_warnings.reset(drive.node_id)
            return
        if kind is EmcyClass.WARNING:  # reported; the torque stays (its statusword is the authority for FAULT)
            self.emcy_warnings.warn(drive.node_id, self._joint[drive.node_id], message, self._now())
            return
        drive.emcy = message
        self._latch(f"drive {drive.node_id}: {message.describe()}")

    def _lose(self, drive: _Drive, kind: str, why: str) -> None:
        drive.lost, drive.lost_why = kind, why
        self._latch(f"drive {drive.node_id} lost: {why}")

    def _latch(self, message: str) -> None:
        self._latched.append(message)

    def take_latched(self) -> str | None:
        """The faults latched since the last call, as one message (None if none): the HAL raises it once."""
        if not self._latched:
            return None
        message = "; ".join(self._latched)
        self._latched.clear()
        return message

    def drive_states(self) -> tuple[tuple[DriveState, ...], tuple[int, ...], tuple[bool, bool]]:
        """The drives as the HAL reports them: states, fault codes, and the e-stop inputs (operator, pilot)."""
        states, codes = [], []
        operator = pilot = False
        for drive, estop in zip(self.drives, self._estop_bits, strict=True):
            if (
                drive.power is PowerState.OPERATION_ENABLED
                and drive.controlword == CW_ENABLE_OPERATION
                and drive.lost is None
                and drive.recovery is None
                and drive.emcy is None
            ):  # nearly every drive and tick of a session: what the general steps below give for it
                states.append(DriveState.ENABLED)
                codes.append(0)
            else:
                state, code = self._drive_state(drive)
                states.append(state)
                codes.append(code)
            if estop is not None:
                in_statusword, pressed_when_clear, operator_mask, pilot_mask = estop
                word = (drive.statusword or 0) if in_statusword else drive.estop_word
                if pressed_when_clear:
                    word = ~word
                operator = operator or bool(word & operator_mask)
                pilot = pilot or bool(word & pilot_mask)
        return tuple(states), tuple(codes), (operator, pilot)

    @staticmethod
    def _drive_state(drive: _Drive) -> tuple[DriveState, int]:
        """One drive's state and fault code as the HAL reports them (:meth:`drive_states`)."""
        code = 0
        if drive.lost is not None or drive.recovery is not None:
            return DriveState.FAULT, LOST_CODES[drive.lost or "recovery"]
        state = drive_state(drive.power)
        if state is DriveState.ENABLED and drive.controlword != CW_ENABLE_OPERATION:
            # The master commanded torque off: a drive may sample its statusword at that SYNC
            # before it applies the command (CiA 301 leaves the order open). It is not counted
            # as enabled; one that stays enabled is reported by its power stepper.
            state = DriveState.DISABLED
        if drive.emcy is not None:
            state, code = DriveState.FAULT, drive.emcy.code
        elif state is DriveState.FAULT:
            code = 0x1000  # a fault the drive shows without (yet) an EMCY: generic error
        return state, code

    # --- the tick: write ---------------------------------------------------------------------------

    def send_cycle(self, want_torque: bool, torque_nm: np.ndarray | None, joints_off: tuple[int, ...] = ()) -> None:
        """One bus cycle: the power state machines, the RPDOs, due SDO transfers, the heartbeat, the SYNC.

        ``torque_nm`` (4,) is sent only where ``want_torque``, the joint (1-4) is not in
        ``joints_off`` (its drive is disabled: CiA 402 disable voltage) and the drive is not lost;
        it is saturated at the peak. Never waits.

        Raises:
            HalError: the bus refused a frame (torque cannot be commanded: the caller reports it).
        """
        nm_per_permille = self._nm_per_permille
        peaks = self._peak_permille_of
        packs = self._pack_rpdo
        following = self.settings.ramp_s is not None
        commanded: list[int | None] = []
        torques = torque_nm.tolist() if torque_nm is not None else None  # Python floats: one call, not one a joint
        for j, drive in enumerate(self.drives):
            seen = drive.lost is None and drive.recovery is None  # a lost drive's last statusword is stale
            healthy = seen and drive.emcy is None
            wanted = want_torque and (j + 1) not in joints_off
            # its statusword of the last SYNC: a write without a read since is no tick it "stayed" in a state
            fresh = drive.last_sync >= self.syncs - 1
            outcome = drive.stepper.step(drive.power if seen else None, wanted and healthy, fresh)
            if outcome.timed_out is not None:
                self._latch(f"drive {drive.node_id}: {outcome.timed_out}")
            drive.controlword = outcome.controlword
            permille = 0
            if wanted and healthy and torques is not None:
                peak = peaks[j]
                permille = round(torques[j] / nm_per_permille[j])  # saturated at the peak (comparisons: no calls)
                permille = -peak if permille < -peak else peak if permille > peak else permille
            self._send(self._rpdo_cob[j], packs[j](outcome.controlword, permille))
            if following:
                commanded.append(
                    permille if outcome.controlword == CW_ENABLE_OPERATION and wanted and healthy else None
                )
        now = self._now()
        if following:
            self._follow_slopes(commanded, now)
        startable = self.sdo.startable()
        limit = self.cycle_budget.transfers(self._last_sync_s, startable) if startable else 0
        for cob_id, data in self.sdo.frames_due(now, limit):
            self._send(cob_id, data)
        self._send_heartbeat_if_due()
        self._sync()

    def send_torque_off(self) -> None:
        """A cycle that disables every drive (controlword 0x0000, target torque 0), whatever the state."""
        for j, drive in enumerate(self.drives):
            drive.stepper.step(None, False)
            drive.controlword = CW_DISABLE_VOLTAGE
            self._send(self._rpdo_cob[j], self._pack_rpdo[j](CW_DISABLE_VOLTAGE, 0))
        self._sync()

    def _sync(self) -> None:
        self._last_sync_s = self._now()
        self.syncs += 1
        self._send(SYNC_COB_ID, b"")
        if self._pump is not None:
            self._pump()

    def _send_heartbeat_if_due(self) -> None:
        now = self._now()
        if now >= self._next_heartbeat_s:
            self._send(*heartbeat_frame(self.settings.master_node_id, NmtState.OPERATIONAL))
            self.cycle_budget.heard(self.settings.master_node_id, now)
            self._next_heartbeat_s = now + self.settings.heartbeat_producer_ms / 1000.0

    def stop(self) -> None:
        """Torque off and every drive to pre-operational (PDOs stop); the bus stays open."""
        self.send_torque_off()
        for drive in self.drives:
            self._send(*nmt_frame(NmtCommand.ENTER_PRE_OPERATIONAL, drive.node_id))
        if self._pump is not None:
            self._pump()

    # --- the drives' own reaction to losing the master --------------------------------------------------

    def reaction_report(self) -> tuple[str, ...]:
        """One sentence per drive on what it does by itself when it loses the master (as configured last).

        Empty until every drive was configured (a start-up that failed reports nothing).
        """
        sentences = tuple(drive.reaction_sentence for drive in self.drives)
        return sentences if all(sentences) else ()

    def _reaction_configured(self, drive: _Drive) -> None:
        """Its reaction writes are done: what it got, and the slope follower of a drive that ramps."""
        plan = drive.reaction
        if plan is None:
            return
        drive.reaction_sentence = plan.sentence()
        ramp_s = self.settings.ramp_s
        if plan.ramps and ramp_s is not None:
            drive.slope = SlopeFollower(
                ramp_s, self._peak_permille_of[self._joint[drive.node_id] - 1], plan.slope_permille_per_s
            )

    def _follow_slopes(self, commanded: list[int | None], now: float) -> None:
        """Rewrite the torque slope of drives that ramp, as the torque they are commanded changes (never waits).

        ``commanded`` holds each drive's target torque this cycle, per mille (None: not commanded torque).
        """
        sdo = self.sdo
        sdo_idle = sdo.idle()  # nearly every cycle (a write queued below is for its own drive: not another's)
        for drive, torque in zip(self.drives, commanded, strict=True):
            follower = drive.slope
            if follower is None:
                continue
            if drive.lost is not None or drive.recovery is not None:
                self._drop_slope_write(drive)
                continue
            if drive.slope_write is not None:
                transfer, value = drive.slope_write
                if not transfer.done:
                    continue
                drive.slope_write = None
                if not transfer.succeeded:
                    self._slope_failed(drive, follower, transfer, value)
                    continue
                follower.confirmed(value)
            if (not sdo_idle and sdo.node_busy(drive.node_id)) or drive.emcy is not None or drive.power in _STOPPING:
                # A drive stopping by itself (a quick stop, a fault reaction) ramps at the slope it has:
                # a new one would change the ramp under way (the drive reads it as it goes).
                continue
            slope = follower.due(torque, now)
            if slope is not None:
                data = drive.profile.dictionary.encode(obj.TORQUE_SLOPE, 0, slope)
                drive.slope_write = (sdo.write(drive.node_id, obj.TORQUE_SLOPE, 0, data, "torque slope"), slope)

    def _drop_slope_write(self, drive: _Drive) -> None:
        """A lost drive: its slope write in flight is forgotten (it may or may not have landed: written again when back)."""
        if drive.slope_write is None:
            return
        drive.slope_write = None
        self.sdo.cancel_node(drive.node_id)  # a lost drive has no other transfer: a recovery queues its own later
        if drive.slope is not None:
            drive.slope.confirmed(0)  # unknown: any torque it holds when back wants a write

    def _slope_failed(self, drive: _Drive, follower: SlopeFollower, transfer: SdoTransfer, value: int) -> None:
        """A slope the drive did not take: reported once, and the slope is no longer followed (it keeps what it has)."""
        drive.slope = None
        ramp = format_ramp_s(follower.ramp_s)
        why = transfer.error or transfer.declined or "skipped"
        slope = f"{follower.held} per mille a second" if follower.held > 0 else "the slope it last took"
        drive.reaction_sentence = (
            f"drive {self._joint[drive.node_id]} (node 0x{drive.node_id:02X}): its torque slope could not be set to "
            f"{value} per mille of the rated torque per second ({why}): when it loses the master it ramps at "
            f"{slope} from the torque it holds, not over {ramp} s, then disables"
        )
        self._latch(f"drive {drive.node_id}: 0x6087 torque slope not updated to {value} per mille/s: {why}")

    # --- fault reset and recovery --------------------------------------------------------------------

    def request_fault_reset(self) -> None:
        """The operator acknowledged: a fault reset edge to drives in fault, and lost drives brought back.

        Never waits: the edge goes out with the next cycles; a lost drive is reset (NMT), configured
        (SDO, one transfer in flight per drive) and started over the next ticks.
        """
        self.health.on_fault_reset()  # a bus still error-passive or bus-off is raised again
        for drive in self.drives:  # an EMCY error of a drive whose statusword shows no fault: acknowledged
            if drive.emcy is not None and drive.power not in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
                drive.emcy = None
        now = self._now()
        for drive in self.drives:
            if drive.lost is not None and drive.recovery is None:
                self._drop_slope_write(drive)
                drive.recovery = _Recovery("reset", now)
                drive.emcy = None
                self._send(*nmt_frame(NmtCommand.RESET_NODE, drive.node_id))
            elif drive.power in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE) or drive.emcy is not None:
                drive.stepper.request_fault_reset()

    def _configure_lost(self, drive: _Drive) -> None:
        recovery = drive.recovery
        if recovery is None:
            return
        recovery.phase, recovery.since_s = "configure", self._now()
        recovery.transfers = self._configuration(drive.node_id)

    def _step_recoveries(self, now: float) -> None:
        for drive in self.drives:
            recovery = drive.recovery
            if recovery is None:
                continue
            if recovery.phase == "reset" and now - recovery.since_s > self.settings.boot_timeout_s:
                self._recovery_failed(
                    drive, f"no boot-up message within {self.settings.boot_timeout_s:g} s of NMT reset node"
                )
            elif recovery.phase == "configure" and not self.sdo.node_busy(drive.node_id):
                try:
                    self._check_configuration([drive])  # every transfer answered, the robot file's units and mode
                except HalError as exc:
                    self._recovery_failed(drive, str(exc))
                    continue
                self._reaction_configured(drive)
                self._send(*nmt_frame(NmtCommand.START, drive.node_id))
                recovery.phase, recovery.since_s = "start", now
                drive.forget_tpdos()
                drive.power = None
            elif recovery.phase == "start":
                if drive.last_sync >= self.syncs - 1 >= 0:
                    drive.recovery = None
                    drive.lost, drive.lost_why = None, ""
                elif now - recovery.since_s > self.settings.boot_timeout_s:
                    self._recovery_failed(drive, "no TPDOs after NMT start")

    def _recovery_failed(self, drive: _Drive, why: str) -> None:
        drive.recovery = None
        drive.lost, drive.lost_why = "recovery", why
        self.sdo.cancel_node(drive.node_id)
        self._latch(f"drive {drive.node_id}: bringing it back failed: {why}")


def interpolation_period(period_s: float) -> tuple[int, int]:
    """0x60C2's (value, index) of ``period_s``: ``value * 10**index`` s, value 1-255, the largest index that is exact.

    Raises:
        HalConfigError: no whole value of at most 255 units of 1 us or more expresses it.
    """
    for exponent in range(-3, -7, -1):
        value = round(period_s / 10.0**exponent)
        if 1 <= value <= 255 and math.isclose(value * 10.0**exponent, period_s, rel_tol=1e-9):
            return value, exponent
    raise HalConfigError(f"a cycle of {period_s} s is no whole number of 1-255 ms, 100 us, 10 us or us (0x60C2)")


_MODE_NAMES = {obj.MODE_CYCLIC_SYNCHRONOUS_TORQUE: "cst (cyclic synchronous torque)", obj.MODE_PROFILE_TORQUE: "tq (profile torque)"}  # fmt: skip


def _judge(profile: DriveProfile, kind: str, raw: list[int], want: object) -> str | None:
    """What is wrong with a start-up read of ``profile``'s drive (None: as expected)."""
    value = raw[0]
    if kind == "device type":
        if value & 0xFFFF != obj.CIA402_PROFILE:
            return f"reports device type 0x{value:08X}; expected a CiA 402 drive (low word 0x{obj.CIA402_PROFILE:04X})"
        return None
    if kind in ("vendor id", "product code"):
        if value != want:
            return f"0x1018 {kind} is 0x{value:X}; its robot file expects 0x{want:X}"
        return None
    if kind == "modes":
        if value >> (int(want) - 1) & 1:  # type: ignore[call-overload]
            return None
        names = ", ".join(decode_supported_modes(value)) or "none"
        torque = [name for code, name in _MODE_NAMES.items() if value >> (code - 1) & 1]
        if not torque:
            return f"its 0x6502 supported drive modes are {names}: no cst (cyclic synchronous torque) or tq (profile torque)"
        return (
            f"its 0x6502 supported drive modes are {names}: no {_MODE_NAMES[int(want)]}, the robot file's mode; "  # type: ignore[call-overload]
            f"expected mode: {torque[0].split()[0]}"
        )
    if isinstance(want, UnitCheck):  # kind "unit"
        got = want.value(raw)
        if got != want.expected:
            return (
                f"reports {want.what} {got:g}, its robot file says {want.expected:g}: torques and angles "
                "would be converted wrong"
            )
        return None
    if kind == "mode shown":
        if value != want:
            return f"0x6061 modes of operation display is {value} after 0x6060 was written {want}"
        return None
    if value != want:  # "kept": an sdo_init value read back
        return f"does not keep its sdo_init value: read back {value}, written {want}"
    return None
