"""The controller of a fault's reaction: hold the arm, lower it to its rest, hand it over, torque off.

What a ``hold`` or ``lower`` reaction commands (docs/safety.md, "Fault reactions"), in phases:

* **hold**: the collocated motor position PD holds the pose where the fault found the arm. Its
  feed-forward starts at what the springs carried then (behind an enabled drive: exactly the
  torque that was holding the arm, so the takeover is bumpless whatever the model's error there);
* **lower** (a ``lower`` reaction, after ``hold_s`` and once the path is planned outside the tick):
  the PD follows the lowering path (:mod:`daror_runtime.safety.lowering`) to the rest pose at a
  bounded speed; the feed-forward follows the gravity support of the model in use (or the A Priori
  model, when the fault may come from the model) along the path, offset by what it missed at the
  hold pose;
* **handoff**: at the rest pose the arm is handed to what carries it there (the pilot's lap, an
  armrest, the robot's lower stops), in two steps of ``handoff_s`` each. First the gravity support
  ramps out while the position loop keeps the pose (what is under the arm takes the load); then
  the position loop's torque ramps out (**letting go**). An arm that moves more than
  ``handoff_motion_rad`` meanwhile is not carried there: the torque comes back (5/s, no step) and
  the reaction holds the arm at the rest pose (**held**, category 2) with the reason and the torque
  the robot still carried, for the operator to act. Letting go is quasi-static: the loop's stiffness
  falls slowly, so an arm with nothing under it sinks at a few hundredths of a rad/s before it is
  caught;
* **rested**: the torque is off with the arm at rest on its support: the reaction has ended.

``hold`` reactions stay in **hold** (or **held**) until the operator asks for a lowering
(:meth:`SafeStop.lower_now`) or releases the arm to someone holding it (:meth:`SafeStop.release`:
the torque ramps down without the motion check). An e-stop's safe stop 1 carries a deadline: the
torque has ramped to zero by then wherever the arm is, before the relay cuts the power.

Joints whose torque a fault took off (``joints_off``) are not driven: their reference follows the
measured angle (so the other joints' feed-forward sees the arm as it is) and the command disables
their drives. Runs in the tick: the PD is one compiled call; the rest is a few comparisons.
"""

from __future__ import annotations

import math
from enum import StrEnum
from typing import TYPE_CHECKING

import numpy as np

from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.position import LinkBounds
from daror_runtime.models.base import CompensationModel
from hal.interface import Command, DriveState, Sample
from hal.robot import N_JOINTS, FloatArray, RobotDescription

if TYPE_CHECKING:
    from daror_runtime.safety.lowering import LoweringPath

__all__ = ["DEFAULT_HANDOFF_MOTION_RAD", "DEFAULT_HANDOFF_S", "DEFAULT_HOLD_S", "SafeStop", "SafeStopPhase"]

#: How long the arm is held where the fault found it before it is lowered (s).
DEFAULT_HOLD_S = 2.0
#: How long an e-stop's safe stop 1 holds the arm before it lowers it (s): its bound leaves little time.
E_STOP_HOLD_S = 0.5
#: How long the torque takes to ramp down onto the arm's rest (s).
DEFAULT_HANDOFF_S = 2.0
#: Motion of a driven joint during the handoff (rad) that shows nothing carries the arm at the rest pose.
DEFAULT_HANDOFF_MOTION_RAD = math.radians(2.0)
#: How long the loop's torque is averaged for the reason a handoff gives (s).
_TORQUE_AVERAGE_S = 0.2
#: How fast the torque comes back when the handoff finds nothing carrying the arm (share per second).
TAKE_BACK_PER_S = 5.0


class SafeStopPhase(StrEnum):
    HOLD = "hold"  # holding the pose where the fault found the arm
    LOWER = "lower"  # following the lowering path to the rest pose
    HANDOFF = "handoff"  # at the rest pose, the gravity support ramps out; is the arm carried?
    LETTING_GO = "letting go"  # carried: the whole command ramps out
    RELEASING = "releasing"  # the torque ramps down without the motion check (released, or the deadline)
    HELD = "held"  # holding until the operator acts (category 2)
    RESTED = "rested"  # torque off, the arm at rest: the reaction has ended


class _StopReference:
    """``t -> (q_ref, dq_ref)`` of the safe stop, ``t`` from the controller's reset: the hold pose, then the path."""

    def __init__(self) -> None:
        self.q_hold = np.zeros(N_JOINTS)
        self.path: LoweringPath | None = None
        self.path_start_s = math.inf  # t (from the reset) the path starts at
        self._follow = np.zeros(N_JOINTS, dtype=bool)  # undriven joints follow the measured angle
        self._measured = np.zeros(N_JOINTS)
        self._zero = np.zeros(N_JOINTS)
        self._q = np.zeros(N_JOINTS)

    def hold(self, q_rad: FloatArray) -> None:
        self.q_hold[:] = q_rad
        self.path, self.path_start_s = None, math.inf

    def follow(self, joints_off: tuple[int, ...], q_measured: FloatArray) -> None:
        self._follow[:] = False
        for j in joints_off:
            self._follow[j - 1] = True
        self._measured[:] = q_measured

    def __call__(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        path = self.path
        if path is None or t_s < self.path_start_s:
            q, dq = self.q_hold, self._zero
        else:
            q, dq = path.reference(t_s - self.path_start_s)
        if self._follow.any():
            self._q[:] = np.where(self._follow, self._measured, q)
            return self._q, np.where(self._follow, 0.0, dq)
        return q, dq


class _StopFeedforward:
    """The gravity support along the reference: ``model(q_ref) + offset``, offset = what the model missed at the hold.

    At the hold pose it is exactly the torque that held the arm when the fault came; along the path
    it changes as the model's support does. A model whose torque is not finite is replaced by the
    A Priori model (with its own offset) for the rest of the stop.
    """

    def __init__(self, a_priori: CompensationModel) -> None:
        self.a_priori = a_priori
        self.model: CompensationModel = a_priori
        self.offset = np.zeros(N_JOINTS)
        self.fell_back = False  # the model's torque was not finite: the A Priori model took over
        self.weight = 1.0  # share of the support given (the handoff ramps it out)
        self._held = np.zeros(N_JOINTS)
        self._q_hold = np.zeros(N_JOINTS)

    def start(self, model: CompensationModel, q_hold: FloatArray, held_nm: FloatArray) -> None:
        self._q_hold[:] = q_hold
        self._held[:] = held_nm
        self.fell_back = False
        self.weight = 1.0
        self._use(model)

    def _use(self, model: CompensationModel) -> None:
        at_hold = np.asarray(model.torque(self._q_hold), dtype=float)
        if at_hold.shape != (N_JOINTS,) or not np.all(np.isfinite(at_hold)):
            if model is self.a_priori:  # the design values are finite everywhere: a bug, not a pilot's model
                raise ValueError(f"the A Priori model returned {at_hold.tolist()} at the hold pose")
            self.fell_back = True
            self._use(self.a_priori)
            return
        self.model = model
        self.offset = self._held - at_hold

    def torque(self, q: FloatArray) -> FloatArray:
        support = np.asarray(self.model.torque(q), dtype=float)
        if support.shape != (N_JOINTS,) or not np.all(np.isfinite(support)):
            self.fell_back = True
            self._use(self.a_priori)
            support = np.asarray(self.model.torque(q), dtype=float)
        if self.weight < 1.0:  # the handoff: the support ramps out while the position loop keeps the pose
            return (support + self.offset) * self.weight
        return support + self.offset

    def tick_kernel(self) -> None:
        """No compiled torque: the offset model runs through :meth:`torque`."""
        return None


class SafeStop:
    """The controller of a ``hold`` or ``lower`` reaction (a :class:`~daror_runtime.control.base.Controller`).

    Args:
        description: the robot (spring constant; the PD's gains are checked against it).
        bounds: link inertia and gravity stiffness ranges for the PD's stability check.
        dt_s: the tick.
        a_priori: the A Priori model: the support when the fault may come from the model in use,
            and whenever no other model is approved.
        hold_s: how long the arm is held before it is lowered, s.
        handoff_s: how long the gravity support, then the position loop's torque, ramp out at the rest pose, s.
        handoff_motion_rad: motion during the handoff that shows nothing carries the arm, rad.

    Raises:
        ControlDesignError: the position PD is not stable for this robot (checked at construction).
    """

    def __init__(
        self,
        description: RobotDescription,
        bounds: LinkBounds,
        dt_s: float,
        a_priori: CompensationModel,
        hold_s: float = DEFAULT_HOLD_S,
        handoff_s: float = DEFAULT_HANDOFF_S,
        handoff_motion_rad: float = DEFAULT_HANDOFF_MOTION_RAD,
    ) -> None:
        self._reference = _StopReference()
        self._feedforward = _StopFeedforward(a_priori)
        self.pd = MotorPositionPD(description, self._reference, bounds, feedforward=self._feedforward, dt_s=dt_s)
        self.spring_nm_per_rad = description.sea.spring_stiffness_nm_per_rad
        self.a_priori = a_priori
        self.hold_s = hold_s
        self.handoff_s = handoff_s
        self.handoff_motion_rad = handoff_motion_rad
        self.phase = SafeStopPhase.HOLD
        #: why the stop holds (phase HELD), or how it ended: for the operator and the audit log
        self.note = ""
        self.joints_off: tuple[int, ...] = ()
        self.lowers = False  # a lower reaction: the path follows the hold
        self._model: CompensationModel = a_priori
        self._deadline_s = math.inf  # robot time by which the torque must have ramped to zero
        self._hold_s = hold_s  # this reaction's hold (shorter under an e-stop's bound, none once the operator asked)
        self._t0_s = 0.0  # robot time of the reset
        self._weight = 1.0  # share of the PD's torque commanded (letting go, releasing)
        self._ramp_per_s = 1.0 / handoff_s
        self._handoff_from = np.zeros(N_JOINTS)
        self._loop_torque = np.zeros(N_JOINTS)  # the loop's torque, low-passed (handoff)
        self._last_finite_q = np.zeros(N_JOINTS)
        self._taken_over = False  # reset since the last arm(): the hold pose is the arm's
        self._off_command = Command(np.zeros(N_JOINTS), False)

    # --- set up by the supervisor, in the tick the reaction starts or escalates ---------------------

    def arm(
        self,
        lowers: bool,
        joints_off: tuple[int, ...],
        model: CompensationModel | None,
        deadline_s: float = math.inf,
        last_finite_q_rad: FloatArray | None = None,
    ) -> None:
        """What the next :meth:`reset` takes over with: lower or hold, the joints off, the support model, a deadline,
        and the last finite joint angles (stand-ins for a reading that is not finite, on a joint that is off)."""
        self.lowers = lowers
        self.joints_off = joints_off
        self._model = model if model is not None else self.a_priori
        self._deadline_s = deadline_s
        # An e-stop's safe stop 1 has a bound: the arm is held only briefly before it is lowered.
        self._hold_s = self.hold_s if math.isinf(deadline_s) else min(self.hold_s, E_STOP_HOLD_S)
        self._taken_over = False
        if last_finite_q_rad is not None:
            self._last_finite_q[:] = last_finite_q_rad

    def escalate(self, lowers: bool, joints_off: tuple[int, ...], support_a_priori: bool, deadline_s: float) -> None:
        """A stricter reaction while this one runs (no reset: the arm is where it is held): more joints off,
        hold becomes lower, the A Priori support, an earlier deadline."""
        self.joints_off = joints_off
        self._deadline_s = min(self._deadline_s, deadline_s)
        if support_a_priori and self._feedforward.model is not self.a_priori:
            self._feedforward._use(self.a_priori)
        if lowers and not self.lowers:
            self.lowers = True
            if self.phase is SafeStopPhase.HELD and self.note.startswith("holding"):
                self.phase = SafeStopPhase.HOLD

    def reset(self, sample: Sample) -> None:
        """Take over the arm at ``sample``: hold its pose with the torque the springs carry there.

        Raises:
            ControlError: the sample is not finite (the PD refuses it).
        """
        self._take_over(sample)
        self.phase = SafeStopPhase.HOLD if self.lowers else SafeStopPhase.HELD
        self.note = "" if self.lowers else "holding where the fault found the arm until the operator acts"

    def _take_over(self, sample: Sample) -> None:
        """Hold the arm where ``sample`` finds it, with what the springs carry there (bumpless)."""
        measured = np.asarray(sample.q_rad, dtype=float)
        # A joint whose reading is not finite is off (its sensors are the fault): it stands at its last
        # finite angle for the others' feed-forward.
        q = np.where(np.isfinite(measured), measured, self._last_finite_q)
        self._last_finite_q[:] = q
        self._reference.hold(q)
        self._reference.follow(self.joints_off, q)
        spring = self.spring_nm_per_rad * (np.asarray(sample.theta_rad, dtype=float) - q)
        enabled = np.fromiter((d == DriveState.ENABLED for d in sample.drives), dtype=bool, count=N_JOINTS)
        # What held the arm: the springs' torque behind an enabled drive; the model's where nothing held.
        held = np.where(enabled & np.isfinite(spring), spring, np.asarray(self._model.torque(q), dtype=float))
        self._feedforward.start(self._model, q, held)
        self.pd.reset(sample)
        self._t0_s = sample.t_s
        self._weight = 1.0
        self._feedforward.weight = 1.0
        self._taken_over = True

    # --- requests, at a tick boundary ---------------------------------------------------------------

    @property
    def hold_pose_rad(self) -> FloatArray:
        """The pose held now (4,) rad: where a lowering starts from."""
        path = self._reference.path
        return (path.q_end_rad if path is not None else self._reference.q_hold).copy()

    @property
    def wants_path(self) -> bool:
        """True while a lowering waits for its path (a job plans it)."""
        return self.lowers and self._taken_over and self._reference.path is None and self.phase is SafeStopPhase.HOLD

    def install_path(self, path: LoweringPath | None, why: str = "") -> None:
        """The planned lowering (from :attr:`hold_pose_rad`), or None and why: the arm is then held (category 2)."""
        if self.phase not in (SafeStopPhase.HOLD, SafeStopPhase.HELD):
            return
        if path is None:
            self.phase = SafeStopPhase.HELD
            self.note = f"no safe lowering: {why}; holding the arm until the operator acts"
            return
        reference = self._reference
        if reference.path is not None:  # a second lowering (the operator's): from the end of the first
            reference.hold(reference.path.q_end_rad)
        reference.path = path
        reference.path_start_s = math.inf  # started by update once the hold has lasted hold_s
        self.lowers = True
        self.phase = SafeStopPhase.HOLD
        self.note = ""

    def lower_now(self) -> None:
        """The operator asks a held arm to be lowered (a path is planned next, outside the tick)."""
        if self.phase in (SafeStopPhase.HOLD, SafeStopPhase.HELD):
            self.lowers = True
            self._reference.path = None
            self._reference.hold(self.hold_pose_rad)
            self.phase = SafeStopPhase.HOLD
            self.note = ""
            self._hold_s = 0.0  # the operator asked: no need to wait

    def release(self) -> None:
        """The operator releases the arm to someone holding it: the torque ramps to zero, no motion check."""
        if self.phase is not SafeStopPhase.RESTED:
            self.phase = SafeStopPhase.RELEASING
            self.note = "released by the operator"

    @property
    def finished(self) -> bool:
        """True once the torque is off with the arm at rest (or released): the reaction has ended."""
        return self.phase is SafeStopPhase.RESTED

    # --- the tick ----------------------------------------------------------------------------------------

    def update(self, sample: Sample, dt_s: float) -> Command:
        """The reaction's motor torques (4,) Nm; the joints off disabled; torque off once rested.

        Raises:
            ControlError: see :meth:`MotorPositionPD.update`.
        """
        phase = self.phase
        if phase is SafeStopPhase.RESTED:
            return self._off_command
        t = sample.t_s - self._t0_s
        reference = self._reference
        q = sample.q_rad
        if self.joints_off:
            finite = np.isfinite(q)
            if not finite.all():  # an untrusted joint's reading: its last finite angle stands in
                q = np.where(finite, q, self._last_finite_q)
            self._last_finite_q[:] = q
        reference.follow(self.joints_off, q)
        if sample.t_s >= self._deadline_s - self.handoff_s and phase not in (SafeStopPhase.RELEASING,):
            # An e-stop's bound: the torque has ramped to zero by the deadline, wherever the arm is.
            phase = self.phase = SafeStopPhase.RELEASING
            self.note = "the e-stop's bound ran out: the torque ramped to zero before the relay cuts the power"
        if phase is SafeStopPhase.HOLD and reference.path is not None and t >= self._hold_s:
            reference.path_start_s = t
            phase = self.phase = SafeStopPhase.LOWER
        if phase is SafeStopPhase.LOWER and t >= reference.path_start_s + reference.path.duration_s:  # type: ignore[union-attr]
            phase = self.phase = SafeStopPhase.HANDOFF
            self._handoff_from[:] = q
            self._loop_torque[:] = 0.0
        feedforward = self._feedforward
        if phase is SafeStopPhase.HANDOFF:
            feedforward.weight = max(feedforward.weight - self._ramp_per_s * dt_s, 0.0)
        elif feedforward.weight < 1.0 and phase is not SafeStopPhase.LETTING_GO:  # taken back: the support returns
            feedforward.weight = min(feedforward.weight + TAKE_BACK_PER_S * dt_s, 1.0)
        command = self.pd.update(sample, dt_s)
        torque = command.motor_torque_nm
        for j in self.joints_off:  # disabled by the command anyway; a NaN there must not read as the controller's
            torque[j - 1] = 0.0
        if phase in (SafeStopPhase.HANDOFF, SafeStopPhase.LETTING_GO):
            self._loop_torque += min(dt_s / _TORQUE_AVERAGE_S, 1.0) * (self._weight * torque - self._loop_torque)
            moved = np.abs(np.asarray(q) - self._handoff_from)
            for j in self.joints_off:
                moved[j - 1] = 0.0
            if float(moved.max()) > self.handoff_motion_rad:
                # Nothing under the arm: take it over where it is now, with what its springs carry (no pull
                # back up to the rest pose: that would swing it), and hold it.
                j = int(np.argmax(np.abs(self._loop_torque)))
                self._take_over(sample)
                command = self.pd.update(sample, dt_s)
                torque = command.motor_torque_nm
                for k in self.joints_off:
                    torque[k - 1] = 0.0
                phase = self.phase = SafeStopPhase.HELD
                self.note = (
                    f"the arm moved {math.degrees(float(moved.max())):.1f} deg as the torque went out at the rest "
                    f"pose (the robot still carried {abs(self._loop_torque[j]):.1f} Nm on joint {j + 1}): nothing "
                    "carries it there; holding it until the operator acts"
                )
            elif phase is SafeStopPhase.HANDOFF and feedforward.weight <= 0.0:
                phase = self.phase = SafeStopPhase.LETTING_GO
            elif phase is SafeStopPhase.LETTING_GO:
                self._weight = max(self._weight - self._ramp_per_s * dt_s, 0.0)
        elif phase is SafeStopPhase.RELEASING:
            self._weight = max(self._weight - self._ramp_per_s * dt_s, 0.0)
        elif self._weight < 1.0:  # taken back after letting go failed: the torque returns, ramped
            self._weight = min(self._weight + TAKE_BACK_PER_S * dt_s, 1.0)
        if self._weight <= 0.0:
            self.phase = SafeStopPhase.RESTED
            if not self.note:
                self.note = "the arm rests at its rest pose; torque off"
            return self._off_command
        if self._weight < 1.0:
            torque = torque * self._weight
        return Command(torque, True, self.joints_off)
