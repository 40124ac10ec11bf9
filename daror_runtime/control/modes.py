"""The control modes the FSM selects, each a :class:`~daror_runtime.control.base.Controller`.

* :class:`TorqueOff`: drives disabled (startup, settings, FAIL); commands nothing.
* :class:`MinimalImpedance`: SEA torque control to zero spring torque (Sec. 2.2.3): the actuator
  follows the pilot with the least resistance the passive torque loop allows.
* :class:`Compensation`: SEA torque control to ``support x model.torque(q)`` (Sec. 2.2.3): gravity
  and stiffness compensation with a support level in [0, 1] the operator sets between ticks.
  When the model knows the torque reading's hysteresis (issue 16), the reading's error, tracked
  tick by tick, is added to the reference, so the springs carry what the model says.

Both SEA torque modes enter bumplessly: the torque the springs carry at entry is handed over
(:mod:`daror_runtime.control.handover`), never dropped or stepped.
The identification protocol's position control is the collocated motor position PD
(:mod:`daror_runtime.control.motor_position`), not a mode of this module.

Every torque mode returns ``Command(motor_torque, enable=True)``; what may actually reach the
drives is the safety filter's decision. Each keeps the torque reference of its last tick in
``last_reference_nm`` (for the recorder and the tests).
"""

from __future__ import annotations

import math

import numpy as np

from daror_runtime.control.base import ControlError, ControlSettingError
from daror_runtime.control.handover import DEFAULT_TOLERANCE_NM, MAX_RAMP_DT_S, Handover, handover_reference
from daror_runtime.control.sea_torque import SeaTorqueController
from daror_runtime.control.soft_walls import SoftWalls
from daror_runtime.errors import ShapeError
from daror_runtime.models.base import CompensationModel, ReadingErrorTracker
from hal.interface import Command, Sample
from hal.robot import FloatArray

__all__ = ["Compensation", "MinimalImpedance", "TorqueOff"]

#: The damping's low-pass on the joints' speed: 5 Hz at the 1 kHz tick (first order, one step per tick).
DAMPING_FILTER_HZ = 5.0
DAMPING_FILTER_ALPHA = 1.0 - math.exp(-2.0 * math.pi * DAMPING_FILTER_HZ * 1e-3)


class TorqueOff:
    """Drives disabled: every tick commands ``Command.torque_off()``."""

    def reset(self, sample: Sample) -> None:
        """Nothing to initialise."""

    def update(self, sample: Sample, dt_s: float) -> Command:
        """Torque off, whatever the sample."""
        return Command.torque_off()


class MinimalImpedance:
    """Zero spring torque (minimal-impedance mode, Sec. 2.2.3), through the SEA torque controller.

    Entering it never drops what the springs were carrying: the torque held at entry ramps out at
    ``ramp_per_s`` (the whole of it in ``1 / ramp_per_s`` s, :class:`~daror_runtime.control.handover.Handover`),
    so a pilot whose arm the robot was supporting has time to take its weight.
    """

    def __init__(self, torque: SeaTorqueController, ramp_per_s: float = 0.5, walls: SoftWalls | None = None) -> None:
        self.torque = torque
        self.handover = Handover(ramp_per_s, by_motion=False)
        self.walls = walls
        self._zero = np.zeros(torque.n_joints)
        self._zero.flags.writeable = False  # shared every tick; nobody may change it
        self._reference = np.zeros(torque.n_joints)
        self.last_reference_nm: FloatArray = self._zero

    def reset(self, sample: Sample) -> None:
        """Start the torque loop at the sample (no jump); the torque the springs carry ramps out.

        Raises:
            ControlError: the sample is not finite.
        """
        self.torque.reset(sample)
        self.handover.start(sample, self.torque.spring_torque_nm(sample), self._zero)

    def update(self, sample: Sample, dt_s: float) -> Command:
        """Motor torques (Nm) that drive the spring torque to zero (after the entry's ramp).

        Raises:
            ShapeError, ControlError: see :meth:`SeaTorqueController.motor_torque`.
        """
        reference = self._zero
        if self.handover.active:
            self.handover.set_dt(dt_s)
            handover_reference(self._zero, sample.q_rad, self.handover.state, self._reference)
            reference = self._reference
        wall = self.walls.torque_for(sample) if self.walls is not None else None
        if wall is not None:
            reference = reference + wall  # a few degrees inside a limit: the wall pushes back
        command = Command(self.torque.motor_torque(reference, sample, dt_s), True)
        self.last_reference_nm = reference
        return command


class Compensation:
    """Gravity and stiffness compensation: torque reference ``support x model.torque(q) + e(path)``.

    ``e`` is the torque reading's error the model knows (its
    :meth:`~daror_runtime.models.base.CompensationModel.reading_error_tracker`: the SEA's
    hysteresis, 0 for most models), added only where the torque loop regulates a signal that
    carries it (:attr:`SeaTorqueController.regulates_reading_error`; the default loop regulates
    ``k (theta - q)``, which in the simulator does not). The loop then drives the *reading* to the
    reference, so the springs carry ``support x model.torque(q)``: ``e`` is not scaled by the
    support level (at support 0 the springs carry nothing, not minus the error). It is
    continuous in the path (it turns over a joint's travel constant after a reversal, never
    steps) and bounded by the model's amplitudes (D110).

    Args:
        torque: the SEA torque controller.
        model: the compensation model in use (pure function of ``q``), or None until one is
            approved (validated on this pilot's held-out data, or the A Priori model the operator
            confirmed): :meth:`reset` refuses to start without one, so no state can apply the
            torque of a model nobody approved.
        support_level: fraction of the model torque to deliver, in [0, 1].
        ramp_per_s: the operator's changes of the support level reach the arm at most this fast
            (1/s), and the entry's handover (:class:`~daror_runtime.control.handover.Handover`)
            brings in missing support at this rate; None applies level changes at once.
        handover_tolerance_nm: missing support per joint, at entry, that is handed over by the
            pilot's motion rather than by time (what a validated model may be off by at one pose).
        walls: soft walls a few degrees inside the device's joint limits and the pilot's ISB limits
            (:mod:`daror_runtime.control.soft_walls`), added to the reference where they act (not
            scaled by the support level: a wall holds whatever the level); None: none.

    :attr:`damping_nms_per_rad` (set between ticks, 0 by default) subtracts ``b dq`` from the
    reference: the session sets it while the model in use is not validated on this pilot's data
    (the A Priori model the operator confirmed), so the model's error moves a limp arm only slowly
    (docs/safety.md, "Fault reactions": the operative check).

    Entering the mode is bumpless: the reference starts at the torque the springs carry and never
    dips below what was holding the arm until the pilot moves it (docs/control.md, "handover").

    Raises:
        ControlSettingError: a support level outside [0, 1] or not finite, or a ramp that is not
            positive.
    """

    def __init__(
        self,
        torque: SeaTorqueController,
        model: CompensationModel | None,
        support_level: float = 1.0,
        ramp_per_s: float | None = 0.5,
        handover_tolerance_nm: float = DEFAULT_TOLERANCE_NM,
        walls: SoftWalls | None = None,
    ) -> None:
        if ramp_per_s is not None and not (math.isfinite(ramp_per_s) and ramp_per_s > 0.0):
            raise ControlSettingError(f"support ramp must be a positive rate per second or None, got {ramp_per_s!r}")
        self.torque = torque
        self.model = model
        self.ramp_per_s = ramp_per_s
        self.handover = Handover(ramp_per_s or 0.5, by_motion=True, tolerance_nm=handover_tolerance_nm)
        self._target = _checked_level(support_level)
        self._level = self._target
        self._support = np.zeros(torque.n_joints)
        self._reading_error: ReadingErrorTracker | None = None
        self.walls = walls
        self._damping = 0.0
        self._damping_weight = 1.0  # ramps in after a reset: the damping never steps the reference
        self._speed = np.zeros(torque.n_joints)  # the joints' speed, low-passed for the damping (rad/s)
        self.last_reference_nm: FloatArray = np.zeros(torque.n_joints)
        #: (model, sample, the model's torque there) of the last tick that delivered the model: what the
        #: session's online indicators read between ticks. One tuple, replaced whole (atomic under the
        #: GIL): a reader on another thread never calls the model, whose compiled kernel may own a
        #: scratch buffer the tick is using (a neural model's), and never sees a torque of another pose.
        self.last_model_torque: tuple[CompensationModel, Sample, FloatArray] | None = None

    @property
    def damping_nms_per_rad(self) -> float:
        """Viscous damping on the joints' speed in the reference, Nms/rad (0: none)."""
        return self._damping

    @damping_nms_per_rad.setter
    def damping_nms_per_rad(self, value: float) -> None:
        """Set between ticks.

        Raises:
            ControlSettingError: not a finite number >= 0.
        """
        if isinstance(value, bool) or not (math.isfinite(value) and value >= 0.0):
            raise ControlSettingError(f"compensation damping must be a finite number >= 0 Nms/rad, got {value!r}")
        self._damping = float(value)

    def switch_model(self, model: CompensationModel, damping_nms_per_rad: float, sample: Sample) -> None:
        """Hand the support over to ``model`` (with its damping) as at the mode's entry: bumpless.

        Set between ticks, in compensation, with the tick's ``sample``. The reference starts at the
        torque the springs carry and moves to ``model``'s at the support's ramp, never dipping below
        what held the arm until the pilot moves it (the entry's :class:`Handover`); the new damping
        ramps in likewise. A blind comparison of two approved models switches with it (issue 29).

        Raises:
            ControlSettingError: a damping that is not a finite number >= 0.
            ControlError: ``model``'s torque at the sample's pose is not finite.
        """
        if isinstance(damping_nms_per_rad, bool) or not (
            math.isfinite(damping_nms_per_rad) and damping_nms_per_rad >= 0.0
        ):
            raise ControlSettingError(f"compensation damping must be >= 0 Nms/rad, got {damping_nms_per_rad!r}")
        target = self._level * np.asarray(model.torque(sample.q_rad), dtype=float)
        if target.shape != (self.torque.n_joints,) or not np.all(np.isfinite(target)):
            raise ControlError(f"compensation model {model.name!r} returned {target.tolist()} at the switch's pose")
        self.model = model
        self._reading_error = model.reading_error_tracker() if self.torque.regulates_reading_error else None
        if self._reading_error is not None:
            self._reading_error.reset(sample.q_rad)
        held_nm = self.torque.spring_torque_nm(sample)  # what carries the arm now: the handover starts there
        self.handover.start(sample, held_nm, target)
        if damping_nms_per_rad != self._damping:
            self._damping = float(damping_nms_per_rad)
            self._damping_weight = 0.0  # it ramps in, as after a reset

    @property
    def support_level(self) -> float:
        """The support level set by the operator, in [0, 1]."""
        return self._target

    @support_level.setter
    def support_level(self, value: float) -> None:
        """Set between ticks; refused (and the old level kept) unless finite and in [0, 1].

        Raises:
            ControlSettingError: NaN, infinite, not a number, or outside [0, 1].
        """
        self._target = _checked_level(value)
        if self.ramp_per_s is None:
            self._level = self._target

    @property
    def delivered_support_level(self) -> float:
        """The level applied in the last tick (ramping toward :attr:`support_level` after a change)."""
        return self._level

    def reset(self, sample: Sample) -> None:
        """Start the torque loop at the sample and hand over from the torque the springs carry.

        Raises:
            ControlError: no approved model, the sample is not finite, or the model's torque there
                is not finite.
        """
        model = self.model
        if model is None:
            raise ControlError("no compensation model is approved for this pilot: compensation cannot start")
        self.torque.reset(sample)
        self.last_model_torque = None
        self._level = self._target
        target = self._level * np.asarray(model.torque(sample.q_rad), dtype=float)
        if target.shape != (self.torque.n_joints,) or not np.all(np.isfinite(target)):
            raise ControlError(f"compensation model {model.name!r} returned {target.tolist()} at the entry pose")
        # The reading's error starts at 0 (its state unknown, half way): the target at entry is the model's.
        self._reading_error = model.reading_error_tracker() if self.torque.regulates_reading_error else None
        if self._reading_error is not None:
            self._reading_error.reset(sample.q_rad)
        self.handover.start(sample, self.torque.spring_torque_nm(sample), target)
        self._damping_weight = 0.0
        self._speed[:] = sample.dq_rad_s

    def update(self, sample: Sample, dt_s: float) -> Command:
        """Motor torques (Nm) delivering ``support x model torque`` (plus the entry's handover) at the springs.

        The model's reading error (if it has one) moves with the sample's angles and is added to
        the reference.

        Raises:
            ShapeError: the model returns a torque of the wrong shape.
            ControlError: no model, the model's torque is not finite, or see
                :meth:`SeaTorqueController.motor_torque`.
        """
        model = self.model
        if model is None:
            raise ControlError("no compensation model is approved for this pilot")
        if self.ramp_per_s is not None and self._level != self._target:
            # A stalled tick (large dt) must not turn the ramp into a step: count at most 10 ms.
            step = self.ramp_per_s * min(max(dt_s, 0.0), MAX_RAMP_DT_S) if math.isfinite(dt_s) else 0.0
            self._level = (
                min(self._target, self._level + step)
                if self._target > self._level
                else max(self._target, self._level - step)
            )
        model_torque = model.torque(sample.q_rad)
        self.last_model_torque = (model, sample, model_torque)
        try:
            tau_ref = model_torque * self._level  # an (n,) float array; the kernel checks shape and finiteness
        except TypeError:
            raise ShapeError(f"compensation model {model.name!r} returned {model_torque!r}, not an array") from None
        if self._reading_error is not None:
            tau_ref = tau_ref + self._reading_error.update(sample.q_rad, dt_s)
        if self.handover.active:
            if np.shape(tau_ref) != self._support.shape:
                raise ShapeError(f"compensation model {model.name!r} returned a torque of shape {np.shape(tau_ref)}")
            self.handover.set_dt(dt_s)
            handover_reference(np.asarray(tau_ref, dtype=float), sample.q_rad, self.handover.state, self._support)
            tau_ref = self._support.copy()
        wall = self.walls.torque_for(sample) if self.walls is not None else None
        if wall is not None:
            tau_ref = tau_ref + wall  # a few degrees inside a limit: the wall pushes back
        if self._damping:
            # An arm that moves when the mode takes over (a pilot who lets go, torque back after an e-stop)
            # would make the damping a step in the reference: it comes in at the support ramp's rate.
            if self._damping_weight < 1.0:
                rate = self.ramp_per_s or 1.0 / MAX_RAMP_DT_S
                self._damping_weight = min(self._damping_weight + rate * min(max(dt_s, 0.0), MAX_RAMP_DT_S), 1.0)
            # The drives' speed estimate carries the encoders' noise, which the torque loop would amplify:
            # the damping acts on slow motion (a sagging arm), so it sees the speed low-passed.
            self._speed += DAMPING_FILTER_ALPHA * (sample.dq_rad_s - self._speed)
            tau_ref = tau_ref - (self._damping * self._damping_weight) * self._speed
        try:
            command = self.torque.motor_torque(tau_ref, sample, dt_s)
        except ControlError:
            if not np.all(np.isfinite(tau_ref)):  # name the culprit: the model, not the torque loop
                raise ControlError(
                    f"compensation model {model.name!r} returned a non-finite torque {model_torque}"
                ) from None
            raise
        self.last_reference_nm = tau_ref
        return Command(command, True)


def _checked_level(value: float) -> float:
    if isinstance(value, bool):  # True would pass float() as 1.0: full support by accident
        raise ControlSettingError(f"support level must be a number in [0, 1], got {value!r}")
    try:
        level = float(value)
    except (TypeError, ValueError):
        raise ControlSettingError(f"support level must be a number in [0, 1], got {value!r}") from None
    if not math.isfinite(level) or not 0.0 <= level <= 1.0:
        raise ControlSettingError(f"support level must be a finite number in [0, 1], got {value!r}")
    return level
