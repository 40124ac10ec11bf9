"""The safety monitor: checks every sample, latches faults, and filters every command.

Per tick (docs/loop.md)::

    faults = monitor.check(sample)          # new faults of this tick (also latched)
    ...                                     # the FSM routes faults to FAIL and grants their reaction
    command = monitor.filter(command, ...)  # only what the granted reaction commands while faulted

The check is built for the 1 kHz tick: one vectorised bounds test over every checked signal
(joint angles, velocities, spring torques, deflections, the jump since the last sample) decides
the common case; only when something is out of bounds does a slow path work out what, for the
message. A NaN fails every comparison, so it can never slip through the fast path.

A fault is *latched* until :meth:`SafetyMonitor.clear` is called while its condition is gone;
a condition is only reported again after it went away (no fault storm from one held e-stop).

While a fault is latched (or an e-stop pressed) the filter lets no torque through unless the
supervisor has *granted* the fault's reaction (:meth:`SafetyMonitor.grant`, docs/safety.md "Fault
reactions"): then it passes the reaction controller's command, with the joints the reaction took off
disabled and nothing after the reaction's deadline. Every new fault withdraws the grant the moment it
is latched, so a fault nobody has decided on yet is torque off: the supervisor decides in the same
tick and grants again.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable

import numpy as np
import structlog
from numba import types

from daror_runtime.errors import ConfigurationError
from daror_runtime.safety.faults import Fault, FaultKind
from daror_runtime.safety.kernels import command_status, signals_in_bounds
from daror_runtime.safety.limits import SafetyLimits
from hal.interface import TORQUE_OFF, CheckedCommand, CheckedSample, Command, DriveState, Sample
from hal.isb import IsbLimits
from hal.kernels import SAMPLE_VECTOR, entry_point
from hal.robot import N_JOINTS, FloatArray

log = structlog.get_logger(__name__)

IsbFunction = Callable[[FloatArray], FloatArray]
#: New fault occurrences kept in :attr:`SafetyMonitor.recent` for whoever announces them.
RECENT_FAULTS = 64

#: What :func:`signals_in_bounds` is resolved for: a checked sample's q, dq, tau, theta, then the
#: monitor's own memory and bounds (float64 vectors it makes itself).
IN_BOUNDS_SIGNATURE = (SAMPLE_VECTOR,) * 4 + (types.float64[::1],) * 3
#: What :func:`command_status` is resolved for: a checked command's torque, the monitor's own limit.
STATUS_SIGNATURE = (SAMPLE_VECTOR, types.float64[::1])

#: Order of the signal groups in the vector the fast path checks.
_GROUPS = (
    (FaultKind.JOINT_LIMIT, "joint angle", "rad"),
    (FaultKind.VELOCITY, "joint velocity", "rad/s"),
    (FaultKind.TORQUE, "spring torque", "Nm"),
    (FaultKind.DEFLECTION, "spring deflection", "rad"),
    (FaultKind.JUMP, "jump since the previous sample", "rad"),
)


class SafetyMonitor:
    """Checks samples against :class:`SafetyLimits`; owns the latched faults.

    Args:
        limits: what to check against; replace between ticks with :meth:`set_limits`.
        isb_angles: maps one configuration ``q`` (4,) to its ISB angles (4,) [elevation,
            horizontal rotation, axial rotation, elbow] in rad; needed when ``limits.isb`` is set.
    """

    def __init__(self, limits: SafetyLimits, isb_angles: IsbFunction | None = None) -> None:
        self._isb_angles = isb_angles
        self._latched: dict[tuple[FaultKind, int | None], Fault] = {}
        self._present: set[tuple[FaultKind, int | None]] = set()
        # Faults reported from outside check() (overrun, HAL, software) have no condition to test:
        # one counts as present while it was reported in this tick or the one before.
        self._reported_now: set[tuple[FaultKind, int | None]] = set()
        self._reported_before: set[tuple[FaultKind, int | None]] = set()
        self._previous = np.zeros(2 * (N_JOINTS + 1))  # last finite q (4), a "seen one" flag, and their values before
        self._previous_seq: int | None = None
        self._same_seq = 0
        self._fault_free_drives: tuple[DriveState, ...] | None = None
        # The reaction the supervisor granted while faults are latched: the joints off, and the robot time
        # after which no torque passes (inf: none). None: nothing granted, torque off.
        self._grant: tuple[tuple[int, ...], float] | None = None
        self._blind_ticks = 0  # ticks in a row without a reading in which the last command was kept
        #: A fault :meth:`filter` found (a non-finite command), for the loop to route; the loop clears it.
        self.filter_fault: Fault | None = None
        #: Every new fault occurrence since the monitor was made: a count and the latest ones (for
        #: announcing them outside the tick; the tick only appends).
        self.occurrences = 0
        self.recent: deque[Fault] = deque(maxlen=RECENT_FAULTS)
        self.set_limits(limits)
        # Load the compiled kernels now: the first enabled command would otherwise load one inside
        # a tick (4 ms measured: the first tick of a torque mode missed its deadlines).
        command_status(np.zeros(N_JOINTS), np.ones(N_JOINTS))
        # A CheckedSample's arrays go to this entry point (no type dispatch); any other sample's
        # through the dispatcher, which checks and, for a new type, compiles.
        self._in_bounds_checked = entry_point(signals_in_bounds, IN_BOUNDS_SIGNATURE)
        self._status_checked = entry_point(command_status, STATUS_SIGNATURE)  # a CheckedCommand's torque
        for readonly in (True, False):  # numba compiles per array type: a HAL's read-only arrays and plain ones
            zeros = np.zeros(N_JOINTS)
            zeros.flags.writeable = not readonly
            signals_in_bounds(zeros, zeros, zeros, zeros, np.zeros_like(self._previous), self._lower, self._upper)

    # --- configuration --------------------------------------------------------------------

    def set_limits(self, limits: SafetyLimits, isb_angles: IsbFunction | None = None) -> None:
        """Use ``limits`` from the next check on (call between ticks); ``isb_angles`` replaces the ISB function."""
        if isb_angles is not None:
            self._isb_angles = isb_angles
        self.limits = limits
        # Read every tick: kept as plain attributes (replaced only here, between ticks).
        self._isb_on = limits.isb is not None
        self._command_limit = np.ascontiguousarray(limits.command_limit_nm, dtype=np.float64)
        # float64 vectors made here: the types the kernel's entry point was resolved for.
        self._lower = np.concatenate(
            [
                limits.joint_lower_rad,
                -limits.max_velocity_rad_s,
                -limits.max_spring_torque_nm,
                np.full(N_JOINTS, -limits.max_deflection_rad),
                np.full(N_JOINTS, -limits.max_jump_rad),
            ],
            dtype=np.float64,
        )
        self._upper = np.concatenate(
            [
                limits.joint_upper_rad,
                limits.max_velocity_rad_s,
                limits.max_spring_torque_nm,
                np.full(N_JOINTS, limits.max_deflection_rad),
                np.full(N_JOINTS, limits.max_jump_rad),
            ],
            dtype=np.float64,
        )
        if limits.isb is not None:
            if self._isb_angles is None:
                raise ConfigurationError("ISB limits are set but the monitor has no isb_angles function")
            self._isb_lower = limits.isb.lower_rad - limits.isb_margin_rad
            self._isb_upper = limits.isb.upper_rad + limits.isb_margin_rad
            # the same bounds as Python floats, interleaved (lower, upper) per angle: the tick's box test
            self._isb_box = tuple(
                bound for pair in zip(self._isb_lower.tolist(), self._isb_upper.tolist(), strict=True) for bound in pair
            )

    # --- state ----------------------------------------------------------------------------

    @property
    def faulted(self) -> bool:
        """True while any fault is latched: torque stays off."""
        return bool(self._latched)

    @property
    def latched(self) -> list[Fault]:
        return list(self._latched.values())

    # --- the fault's reaction ---------------------------------------------------------------

    def grant(self, joints_off: tuple[int, ...], until_t_s: float = float("inf")) -> None:
        """Let the reaction's commands through while faults are latched: ``joints_off`` (1-4) disabled, none after ``until_t_s``.

        Called by the supervisor in the tick it decided the reaction (after every new fault, which
        withdraws the grant when it is latched).
        """
        self._grant = (tuple(joints_off), until_t_s)

    def withdraw(self) -> None:
        """No torque while a fault is latched (the reaction is off, or has ended)."""
        self._grant = None

    @property
    def granted(self) -> bool:
        """True while a reaction's commands may pass although faults are latched."""
        return self._grant is not None

    def last_finite_q(self) -> FloatArray | None:
        """The joint angles (4,) rad of the last sample whose angles were all finite (a copy), None before one."""
        previous = self._previous
        return previous[0:4].copy() if previous[4] > 0.0 else None

    @property
    def torque_permitted(self) -> bool:
        """True when a controller's command may reach the drives: nothing latched, or a reaction granted."""
        return not self._latched or self._grant is not None

    def _holds(self, key: tuple[FaultKind, int | None]) -> bool:
        return key in self._present or key in self._reported_now or key in self._reported_before

    @property
    def clearable(self) -> bool:
        """True when the condition of every latched fault is gone (:meth:`clear` would unlatch them all)."""
        return not any(self._holds(key) for key in self._latched)

    def conditions_present(self) -> set[FaultKind]:
        """Fault classes whose condition held at the last check (or were reported this tick or the last)."""
        return {kind for kind, _ in self._present | self._reported_now | self._reported_before}

    def clear(self) -> list[Fault]:
        """Unlatch every fault whose condition is gone; returns the faults that remain latched."""
        for key in list(self._latched):
            if not self._holds(key):
                del self._latched[key]
        return self.latched

    def clear_kinds(self, kinds: Iterable[FaultKind]) -> bool:
        """Unlatch faults of ``kinds`` whose condition is gone (an e-stop test once released); True if any."""
        wanted = set(kinds)
        gone = [key for key in self._latched if key[0] in wanted and not self._holds(key)]
        for key in gone:
            del self._latched[key]
        return bool(gone)

    def begin_tick(self) -> None:
        """A new tick starts (the loop calls it first): reports older than the last tick no longer hold."""
        if self._reported_now or self._reported_before:
            self._reported_before = self._reported_now
            self._reported_now = set()

    def reset_history(self) -> None:
        """Forget the previous sample (after the HAL was reopened: no jump or staleness across it)."""
        self._previous[:] = 0.0
        self._previous_seq = None
        self._same_seq = 0

    # --- lock-step batches (daror_runtime/loop_batch.py) ------------------------------------

    def batch_arrays(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None:
        """``(previous, lower, upper, command_limit)`` for a batch's compiled checks, or None.

        A batch runs :meth:`check`'s and :meth:`filter`'s common case in compiled code
        (:func:`~daror_runtime.safety.kernels.signals_in_bounds`, :func:`~daror_runtime.safety.kernels.command_status`
        on these very arrays) and hands any tick whose check or filter is not the common case back to
        them. Only when nothing is latched, present or reported, and no ISB limits are checked (their
        angles are computed in Python): None otherwise.
        """
        if self._latched or self._present or self._reported_now or self._reported_before or self._isb_on:
            return None
        return self._previous, self._lower, self._upper, self._command_limit

    def after_batch(self, last_seq: int) -> None:
        """A batch checked fresh samples up to ``last_seq``, every one in bounds (what :meth:`check` would record)."""
        self._previous_seq = last_seq
        self._same_seq = 0

    # --- per tick -------------------------------------------------------------------------

    def report(self, kind: FaultKind, t_s: float, message: str, joint: int | None = None) -> Fault | None:
        """A fault found outside :meth:`check` (HAL error, overrun, software); latched like the rest."""
        new = self._raise_edge({(kind, joint): Fault(kind, t_s, message, joint)}, transient=True)
        return new[0] if new else None

    def check(self, sample: Sample) -> list[Fault]:
        """Check one sample; returns the faults that appeared with it (already latched)."""
        previous = self._previous  # the kernel updates it: the angles of the last finite sample
        in_bounds = (self._in_bounds_checked if type(sample) is CheckedSample else signals_in_bounds)(
            sample.q_rad, sample.dq_rad_s, sample.tau_nm, sample.theta_rad, previous, self._lower, self._upper
        )
        seq = sample.seq
        drives = sample.drives
        if (
            in_bounds
            and seq != self._previous_seq
            and not self._present
            and True not in sample.estop
            and (drives is self._fault_free_drives or self._drives_fault_free(drives))
            and (not self._isb_on or self._isb_inside(sample.q_rad))
        ):
            # The common case, decided without building anything: every signal in bounds, the ISB
            # angles inside their limits (if any), a fresh sample, no e-stop, no drive fault, and no
            # condition held at the previous check (so nothing to latch or to clear). The same outcome
            # as the full path below: the stale count restarts and no fault appears.
            self._same_seq = 0
            self._previous_seq = seq
            return []  # a fresh list: the loop appends the tick's other faults to it
        found: dict[tuple[FaultKind, int | None], Fault] = {}
        if not in_bounds:
            self._diagnose(sample, found, previous[5:9] if previous[9] > 0.0 else None)
        elif self.limits.isb is not None:
            self._check_isb(sample, found)
        if sample.seq == self._previous_seq:
            self._same_seq += 1
            if self._same_seq >= self.limits.stale_ticks:
                found[(FaultKind.STALE, None)] = Fault(
                    FaultKind.STALE,
                    sample.t_s,
                    f"no fresh sample for {self._same_seq} ticks (seq {sample.seq})",
                    value=float(self._same_seq),
                    limit=float(self.limits.stale_ticks),
                )
        else:
            self._same_seq = 0
        if True in sample.estop:
            pressed = ", ".join(name for name, on in zip(("operator", "pilot"), sample.estop, strict=False) if on)
            found[(FaultKind.ESTOP, None)] = Fault(FaultKind.ESTOP, sample.t_s, f"e-stop pressed ({pressed})")
        if DriveState.FAULT in sample.drives:
            for j, state in enumerate(sample.drives, start=1):
                if state == DriveState.FAULT:
                    code = sample.drive_fault_codes[j - 1] if j - 1 < len(sample.drive_fault_codes) else 0
                    found[(FaultKind.DRIVE, j)] = Fault(
                        FaultKind.DRIVE, sample.t_s, f"drive {j} reports a fault (code 0x{code:04x})", joint=j
                    )
        self._previous_seq = sample.seq
        if not found and not self._present:  # nothing to latch or clear
            return []  # a fresh list: the loop appends the tick's other faults to it
        return self._raise_edge(found)

    def _drives_fault_free(self, drives: tuple[DriveState, ...]) -> bool:
        """True if no drive reports FAULT; remembers the last fault-free tuple, so a backend that
        hands out the same tuple every tick (an immutable one: only a ``tuple`` is remembered) is
        checked by identity."""
        if drives is self._fault_free_drives:
            return True
        if DriveState.FAULT in drives:
            return False
        if type(drives) is tuple:
            self._fault_free_drives = drives
        return True

    def filter(self, command: Command, sample: Sample | None) -> Command:
        """The command that may reach the drives, clipped to the state's torque limit.

        Off while a fault is latched or an e-stop is pressed, unless the supervisor granted the
        fault's reaction (:meth:`grant`): then the reaction's command passes with the joints it took
        off disabled, until its deadline. In a tick without a reading (``sample`` None) a granted
        reaction keeps the command the loop hands back (the last one written: what the drives
        apply between two frames anyway) for at most ``stale_ticks`` ticks in a row; then off.
        """
        if sample is None:
            return self._blind(command)
        if self._blind_ticks:
            self._blind_ticks = 0
        if not command.enable:
            return TORQUE_OFF
        joints_off: tuple[int, ...] = ()
        if self._latched or True in sample.estop:
            grant = self._grant
            if grant is None or sample.t_s > grant[1]:
                return TORQUE_OFF
            joints_off = grant[0]
        torque = command.motor_torque_nm
        limit = self._command_limit
        status = (self._status_checked if type(command) is CheckedCommand else command_status)(torque, limit)
        if status == 0 and not joints_off:  # the common case: the controller's own command, untouched
            return command
        if status < 0:
            self.filter_fault = self.report(
                FaultKind.SOFTWARE, sample.t_s, f"controller produced a non-finite torque {torque.tolist()}"
            )
            return TORQUE_OFF
        if joints_off:
            joints_off = tuple(sorted({*command.joints_off, *joints_off}))
        return Command(np.clip(torque, -limit, limit) if status else torque, True, joints_off or command.joints_off)

    def _blind(self, command: Command) -> Command:
        """A tick without a reading: the last command stays only under a granted reaction, a few ticks at most."""
        if self._grant is None or not command.enable or self._blind_ticks >= self.limits.stale_ticks:
            return TORQUE_OFF
        self._blind_ticks += 1
        return command

    # --- internals ------------------------------------------------------------------------

    def _raise_edge(self, found: dict[tuple[FaultKind, int | None], Fault], transient: bool = False) -> list[Fault]:
        """Latch and return faults whose condition was not present at the previous check."""
        new = []
        for key, fault in found.items():
            # A condition that went away and came back is a new occurrence, even while still latched
            # (it needs its own acknowledgement). A report is new unless it was reported last tick too.
            if not self._holds(key):
                new.append(fault)
                log.error("fault", **fault.as_dict())
                self._latched[key] = fault
                self._grant = None  # undecided: torque off until the supervisor decides the reaction
                self.occurrences += 1
                self.recent.append(fault)
            else:
                self._latched.setdefault(key, fault)
        if transient:
            self._reported_now.update(found)
            return new
        self._present = set(found)
        return new

    def _diagnose(
        self, sample: Sample, found: dict[tuple[FaultKind, int | None], Fault], jump_base: FloatArray | None
    ) -> None:
        """Name every violated bound (the slow path, only when the fast check failed)."""
        q = sample.q_rad
        jump = np.zeros(N_JOINTS) if jump_base is None else q - jump_base
        signals = np.concatenate([q, sample.dq_rad_s, sample.tau_nm, sample.theta_rad - q, jump])
        lower, upper = self._lower, self._upper
        for g, (kind, what, unit) in enumerate(_GROUPS):
            for j in range(N_JOINTS):
                i = 4 * g + j
                value = float(signals[i])
                if not np.isfinite(value):
                    key = (FaultKind.NOT_FINITE, j + 1)
                    found.setdefault(
                        key, Fault(FaultKind.NOT_FINITE, sample.t_s, f"joint {j + 1}: {what} is {value}", joint=j + 1)
                    )
                elif value < lower[i] or value > upper[i]:
                    limit = float(lower[i] if value < lower[i] else upper[i])
                    found[(kind, j + 1)] = Fault(
                        kind,
                        sample.t_s,
                        f"joint {j + 1}: {what} {value:.4g} {unit} beyond the limit {limit:.4g} {unit}",
                        joint=j + 1,
                        value=value,
                        limit=limit,
                    )

    def _isb_inside(self, q_rad: FloatArray) -> bool:
        """True if the ISB angles of ``q_rad`` are inside the limits plus the margin (a NaN is not)."""
        # The box test in Python floats (one call, not four numpy operations a tick; a NaN fails it as in numpy)
        a0, a1, a2, a3 = self._isb_angles(q_rad).tolist()  # type: ignore[misc]
        lo0, hi0, lo1, hi1, lo2, hi2, lo3, hi3 = self._isb_box
        return lo0 <= a0 <= hi0 and lo1 <= a1 <= hi1 and lo2 <= a2 <= hi2 and lo3 <= a3 <= hi3

    def _check_isb(self, sample: Sample, found: dict[tuple[FaultKind, int | None], Fault]) -> None:
        if self._isb_inside(sample.q_rad):
            return
        angles = self._isb_angles(sample.q_rad)  # type: ignore[misc]  # outside: which angle, by how much
        names = ISB_ANGLE_NAMES
        for j in range(N_JOINTS):
            value = float(angles[j])
            if not self._isb_lower[j] <= value <= self._isb_upper[j]:
                limit = float(self._isb_lower[j] if value < self._isb_lower[j] else self._isb_upper[j])
                found[(FaultKind.ISB_LIMIT, j + 1)] = Fault(
                    FaultKind.ISB_LIMIT,
                    sample.t_s,
                    isb_excess_text(names[j], value, self.limits.isb, self.limits.isb_margin_rad, j),  # type: ignore[arg-type]
                    joint=4 if j == 3 else None,
                    value=value,
                    limit=limit,
                )


ISB_ANGLE_NAMES = ("elevation", "horizontal rotation", "axial rotation", "elbow")


def isb_excess(angles_rad: FloatArray, isb: IsbLimits, margin_rad: float) -> str | None:
    """The angle farthest outside ``isb`` plus ``margin_rad``, as :func:`isb_excess_text`; None when all are inside."""
    lower, upper = isb.lower_rad - margin_rad, isb.upper_rad + margin_rad
    beyond = np.maximum(lower - angles_rad, angles_rad - upper)
    worst = int(np.argmax(beyond))
    if beyond[worst] <= 0.0:
        return None
    return isb_excess_text(ISB_ANGLE_NAMES[worst], float(angles_rad[worst]), isb, margin_rad, worst)


def isb_excess_text(name: str, value_rad: float, isb: IsbLimits, margin_rad: float, index: int) -> str:
    """How far an ISB angle is outside the pilot's recorded range, with the range and the margin named.

    ``index``: 0-3, elevation, horizontal rotation, axial rotation, elbow.
    """
    lower, upper = float(isb.lower_rad[index]), float(isb.upper_rad[index])
    outside = lower - value_rad if value_rad < lower else value_rad - upper
    return (
        f"{name} {np.degrees(value_rad):.1f} deg is {np.degrees(outside):.1f} deg outside the pilot's recorded range "
        f"{np.degrees(lower):.1f}..{np.degrees(upper):.1f} deg (the monitor allows {np.degrees(margin_rad):.1f} deg "
        "beyond it: isb_margin_deg)"
    )


def faults_text(faults: Iterable[Fault]) -> str:
    return "; ".join(f"{f.kind.value}: {f.message}" for f in faults)
