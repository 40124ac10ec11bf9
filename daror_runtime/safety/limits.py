"""The limits the safety monitor enforces: the device's, the pilot's and the current state's."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from hal.robot import N_JOINTS, FloatArray, RobotDescription

if TYPE_CHECKING:
    from hal.isb import IsbLimits


@dataclass(frozen=True)
class SafetyLimits:
    """Everything one tick is checked against.

    Device limits come from the robot description; ``isb`` is the pilot's range of motion once
    the operator has recorded it; ``command_limit_nm`` is the motor torque the current state
    allows (issue 4's FSM sets it per state; the safety filter clips to it).
    """

    joint_lower_rad: FloatArray
    joint_upper_rad: FloatArray
    max_velocity_rad_s: FloatArray
    max_spring_torque_nm: FloatArray
    max_deflection_rad: float
    command_limit_nm: FloatArray
    max_jump_rad: float = 0.05
    stale_ticks: int = 5
    isb: IsbLimits | None = None
    isb_margin_rad: float = field(default=0.0)

    @classmethod
    def from_description(cls, description: RobotDescription, command_limit_nm: float | None = None) -> SafetyLimits:
        """The device envelope; the command limit defaults to the motors' saturation."""
        sea = description.sea
        limit = sea.max_motor_torque_nm if command_limit_nm is None else command_limit_nm
        return cls(
            joint_lower_rad=description.lower_limits_rad,
            joint_upper_rad=description.upper_limits_rad,
            max_velocity_rad_s=np.asarray(description.limits.max_velocity_rad_s, dtype=float),
            max_spring_torque_nm=np.asarray(description.limits.max_spring_torque_nm, dtype=float),
            max_deflection_rad=0.9 * sea.max_spring_deflection_rad,
            command_limit_nm=np.full(N_JOINTS, float(limit)),
        )

    def with_isb(self, isb: IsbLimits | None, margin_rad: float | None = None) -> SafetyLimits:
        margin = self.isb_margin_rad if margin_rad is None else margin_rad
        return replace(self, isb=isb, isb_margin_rad=margin)

    def for_state(self, torque_nm: float, velocity_rad_s: float) -> SafetyLimits:
        """These (device) limits narrowed to a state's: the lower of each applies, per joint."""
        return replace(
            self,
            command_limit_nm=np.minimum(self.command_limit_nm, float(torque_nm)),
            max_velocity_rad_s=np.minimum(self.max_velocity_rad_s, float(velocity_rad_s)),
        )
