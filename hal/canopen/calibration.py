"""A drive's encoder zeros and torque tare, applied to what it reports (``daror can zero``, ``daror can tare``).

The robot file stores per node what the commissioning commands measured (docs/canopen.md,
Commissioning)::

    calibration:
      motor_zero_counts: 1234       # the motor encoder's counts at the robot's zero pose
      link_zero_counts: -567        # the link encoder's counts at the robot's zero pose
      zeroed_utc: '2026-11-28T09:30:00Z'
      torque_tare_nm: 0.42          # the spring torque read with the arm unloaded, N m
      tared_utc: '2026-11-28T09:35:00Z'

and the backend applies it to every reading: an angle is ``(counts - zero) * rad_per_count``, the
spring torque ``measured - tare``. Pure functions of numbers, for scalars and arrays alike: no
bus, no state. A drive without a calibration reads as before (zeros 0, tare 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

__all__ = ["NO_CALIBRATION", "Calibration", "angle_rad", "spring_torque_nm"]

Value = TypeVar("Value", float, np.ndarray)


@dataclass(frozen=True)
class Calibration:
    """One drive's zeros and tare (see the module docstring).

    Attributes:
        motor_zero_counts: the motor encoder's counts at the robot's zero pose.
        link_zero_counts: the link encoder's counts at the robot's zero pose.
        torque_tare_nm: the spring torque the drive reports with the arm unloaded, N m.
        zeroed_utc: when the zeros were taken (ISO 8601, UTC), None if never.
        tared_utc: when the tare was taken (ISO 8601, UTC), None if never.

    Raises:
        ValueError: a tare that is not finite.
    """

    motor_zero_counts: int = 0
    link_zero_counts: int = 0
    torque_tare_nm: float = 0.0
    zeroed_utc: str | None = None
    tared_utc: str | None = None

    def __post_init__(self) -> None:
        if not math.isfinite(self.torque_tare_nm):
            raise ValueError(f"torque_tare_nm = {self.torque_tare_nm}: expected a finite torque in N m")


#: A drive never zeroed nor tared: its readings unchanged.
NO_CALIBRATION = Calibration()


def angle_rad(counts: Value, zero_counts: int | np.ndarray, rad_per_count: float | np.ndarray) -> Value:
    """An encoder's angle, rad: ``(counts - zero_counts) * rad_per_count`` (counts as the drive sends them)."""
    return (counts - zero_counts) * rad_per_count  # type: ignore[return-value]


def spring_torque_nm(measured_nm: Value, tare_nm: float | np.ndarray) -> Value:
    """The spring torque, N m: what the drive measured less its tare (the reading with the arm unloaded)."""
    return measured_nm - tare_nm  # type: ignore[return-value]
