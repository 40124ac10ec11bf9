"""The control modes the FSM selects, each a :class:`~daror_runtime.control.base.Controller`.

* :class:`TorqueOff`: drives disabled (startup, settings, FAIL); commands nothing.
* :class:`MinimalImpedance`: SEA torque control to zero spring torque (Sec. 2.2.3): the actuator
  follows the pilot with the least resistance the passive torque loop allows.
* :class:`Compensation`: SEA torque control to ``support x model.torque(q)`` (Sec. 2.2.3): gravity
  and stiffness compensation with a support level in [0, 1] the operator sets between ticks.
* :class:`~daror_runtime.control.position.PositionPD`: joint PD through the torque loop
  (Sec. 2.2.4), for the identification protocol.

Every torque mode returns ``Command(motor_torque, enable=True)``; what may actually reach the
drives is the safety filter's decision. Each keeps the torque reference of its last tick in
``last_reference_nm`` (for the recorder and the tests).
"""

from __future__ import annotations

import math

import numpy as np

from daror_runtime.control.base import ControlError, ControlSettingError
from daror_runtime.control.position import PositionPD
from daror_runtime.control.sea_torque import SeaTorqueController
from daror_runtime.errors import ShapeError
from daror_runtime.models.base import CompensationModel
from hal.interface import Command, Sample
from hal.robot import FloatArray

__all__ = ["Compensation", "MinimalImpedance", "PositionPD", "TorqueOff"]


class TorqueOff:
    """Drives disabled: every tick commands ``Command.torque_off()``."""

    commands: tuple[str, ...] = ()

    def reset(self, sample: Sample) -> None:
        """Nothing to initialise."""

    def update(self, sample: Sample, dt_s: float) -> Command:
        """Torque off, whatever the sample."""
        return Command.torque_off()


class MinimalImpedance:
    """Zero spring torque (minimal-impedance mode, Sec. 2.2.3), through the SEA torque controller."""

    commands: tuple[str, ...] = ("motor_torque",)

    def __init__(self, torque: SeaTorqueController) -> None:
        self.torque = torque
        self._zero = np.zeros(torque.n_joints)
        self._zero.flags.writeable = False  # shared every tick; nobody may change it
        self.last_reference_nm: FloatArray = self._zero

    def reset(self, sample: Sample) -> None:
        """Start the torque loop at the sample (no jump).

        Raises:
            ControlError: the sample is not finite.
        """
        self.torque.reset(sample)

    def update(self, sample: Sample, dt_s: float) -> Command:
        """Motor torques (Nm) that drive the spring torque to zero.

        Raises:
            ShapeError, ControlError: see :meth:`SeaTorqueController.motor_torque`.
        """
        return Command(self.torque.motor_torque(self._zero, sample, dt_s), True)


class Compensation:
    """Gravity and stiffness compensation: torque reference ``support x model.torque(q)``.

    Args:
        torque: the SEA torque controller.
        model: the selected compensation model (pure function of ``q``).
        support_level: fraction of the model torque to deliver, in [0, 1].
        ramp_per_s: the delivered level moves toward the set level at most this fast (1/s), so
            neither entering the mode nor the operator's change hits the pilot with a torque step;
            None applies changes at once. On :meth:`reset` the delivered level starts at 0.

    Raises:
        ControlSettingError: a support level outside [0, 1] or not finite, or a ramp that is not
            positive.
    """

    commands: tuple[str, ...] = ("motor_torque",)

    def __init__(
        self,
        torque: SeaTorqueController,
        model: CompensationModel,
        support_level: float = 1.0,
        ramp_per_s: float | None = 0.5,
    ) -> None:
        if ramp_per_s is not None and not (math.isfinite(ramp_per_s) and ramp_per_s > 0.0):
            raise ControlSettingError(f"support ramp must be a positive rate per second or None, got {ramp_per_s!r}")
        self.torque = torque
        self.model = model
        self.ramp_per_s = ramp_per_s
        self._target = _checked_level(support_level)
        self._level = self._target if ramp_per_s is None else 0.0
        self.last_reference_nm: FloatArray = np.zeros(torque.n_joints)

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
        """The level applied in the last tick (ramping toward :attr:`support_level`)."""
        return self._level

    def reset(self, sample: Sample) -> None:
        """Start the torque loop at the sample; the delivered level starts at 0 and ramps in.

        Raises:
            ControlError: the sample is not finite.
        """
        self.torque.reset(sample)
        self._level = self._target if self.ramp_per_s is None else 0.0

    def update(self, sample: Sample, dt_s: float) -> Command:
        """Motor torques (Nm) delivering ``support x model torque`` at the springs.

        Raises:
            ShapeError: the model returns a torque of the wrong shape.
            ControlError: the model's torque is not finite, or see
                :meth:`SeaTorqueController.motor_torque`.
        """
        if self.ramp_per_s is not None and self._level != self._target:
            # A stalled tick (large dt) must not turn the ramp into a step: count at most 10 ms.
            step = self.ramp_per_s * min(max(dt_s, 0.0), 0.01) if math.isfinite(dt_s) else 0.0
            self._level = (
                min(self._target, self._level + step)
                if self._target > self._level
                else max(self._target, self._level - step)
            )
        model_torque = self.model.torque(sample.q_rad)
        try:
            tau_ref = model_torque * self._level  # an (n,) float array; the kernel checks shape and finiteness
        except TypeError:
            raise ShapeError(
                f"compensation model {self.model.name!r} returned {model_torque!r}, not an array"
            ) from None
        try:
            command = self.torque.motor_torque(tau_ref, sample, dt_s)
        except ControlError:
            if not np.all(np.isfinite(tau_ref)):  # name the culprit: the model, not the torque loop
                raise ControlError(
                    f"compensation model {self.model.name!r} returned a non-finite torque {model_torque}"
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
