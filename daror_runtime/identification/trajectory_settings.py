"""The parameters of an identification trajectory, and the kinds of run (planning and the tick share them).

Its own module so that the tick-side trajectory (:mod:`daror_runtime.identification.trajectory`)
carries its settings without importing the planner (:mod:`daror_runtime.identification.trajectory_planning`),
which imports it: no import circle (issue 26).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from daror_runtime.errors import InputError

__all__ = ["TrajectoryError", "TrajectoryKind", "TrajectorySettings"]

TrajectoryKind = Literal["training", "validation"]


class TrajectoryError(InputError):
    """A waypoint set cannot be turned into a safe trajectory; the message names the waypoint."""


@dataclass(frozen=True)
class TrajectorySettings:
    """Parameters of one trajectory. Angles in degrees where the name says so, else SI.

    Attributes:
        shoulder_speed_rad_s: peak angular speed of the shoulder in a move (the thesis's ``v``).
        elbow_speed_rad_s: peak elbow speed in a move.
        max_joint_speed_rad_s: no joint may move faster (also capped by the device's limits); a
            move is slowed down to respect it, and the integrated path is checked against it.
        sub_waypoint_spacing_deg: largest shoulder rotation (and elbow change) between two stops;
            ``None``: stop only at waypoints.
        stop_s: how long the robot stands still at every (sub-)waypoint.
        min_move_s: shortest move (a short, gentle step is still a step for the pilot).
        feedback_gain_per_s: K_fb of the rotation-error feedback.
        rate_hz: integration rate, the loop rate; every sample at this rate is checked.
        knot_rate_hz: rate of the stored knots of the moves (cubic Hermite in between).
        min_sigma: smallest allowed singular value of the shoulder Jacobian along the path.
    """

    shoulder_speed_rad_s: float = 0.40
    elbow_speed_rad_s: float = 0.60
    max_joint_speed_rad_s: float = 1.0
    sub_waypoint_spacing_deg: float | None = 10.0
    stop_s: float = 1.0
    min_move_s: float = 0.6
    feedback_gain_per_s: float = 20.0
    rate_hz: float = 1000.0
    knot_rate_hz: float = 100.0
    min_sigma: float = 0.3

    def __post_init__(self) -> None:
        positive = {
            "shoulder_speed_rad_s": self.shoulder_speed_rad_s,
            "elbow_speed_rad_s": self.elbow_speed_rad_s,
            "max_joint_speed_rad_s": self.max_joint_speed_rad_s,
            "stop_s": self.stop_s,
            "min_move_s": self.min_move_s,
            "rate_hz": self.rate_hz,
            "knot_rate_hz": self.knot_rate_hz,
        }
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise TrajectoryError(f"trajectory setting {name} must be a positive number, got {value}")
        if self.sub_waypoint_spacing_deg is not None and not self.sub_waypoint_spacing_deg > 0:
            raise TrajectoryError(
                f"sub_waypoint_spacing_deg must be positive or None, got {self.sub_waypoint_spacing_deg}"
            )
        if not 0 <= self.feedback_gain_per_s * 4 / self.rate_hz < 1:  # RK4 stays well inside its stable range
            raise TrajectoryError(
                f"feedback_gain_per_s {self.feedback_gain_per_s} is too high for rate_hz {self.rate_hz}"
            )
        if not 0 <= self.min_sigma < 1:
            raise TrajectoryError(f"min_sigma must be in [0, 1), got {self.min_sigma}")
        ratio = self.rate_hz / self.knot_rate_hz
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise TrajectoryError(
                f"rate_hz ({self.rate_hz}) must be a whole multiple of knot_rate_hz ({self.knot_rate_hz})"
            )

    @classmethod
    def training(cls) -> TrajectorySettings:
        """Defaults of the training run: stops every 8 deg, 1 s each."""
        return cls()

    @classmethod
    def validation(cls) -> TrajectorySettings:
        """Defaults of the validation run: one move per segment, 1.5 s stops at waypoints only."""
        return cls(sub_waypoint_spacing_deg=None, stop_s=1.5)

    @classmethod
    def for_kind(cls, kind: TrajectoryKind) -> TrajectorySettings:
        return cls.training() if kind == "training" else cls.validation()
