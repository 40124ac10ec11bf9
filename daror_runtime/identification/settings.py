"""How an identification run is carried out: one settings model for the session and ``daror identify``.

The session reads it from its settings file (``identification:`` in ``daror console --settings
FILE``); ``daror identify`` uses the defaults. Every value has a default a run can use, bounds a
run stays safe within, and units in its name.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, model_validator

from daror_runtime.control.motor_position import DEFAULT_KD_NMS_PER_RAD, DEFAULT_KP_NM_PER_RAD
from hal.yamlfile import Integer, Number


class IdentificationSettings(BaseModel):
    """How the identification protocol runs (thesis Sec. 4.3.1-4.3.2); units in the names."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    waypoints_file: Path | None = Field(None, description="waypoint YAML; default the shipped 83 waypoints")
    waypoint_stride: Integer = Field(1, ge=1, le=20, description="use every n-th waypoint (a shorter protocol)")
    approach_speed_rad_s: Number = Field(
        0.25, gt=0.0, le=1.0, description="peak speed of the approach move, on the joint that moves most"
    )
    min_approach_s: Number = Field(2.0, gt=0.0, le=60.0, description="the approach move lasts at least this")
    settle_s: Number = Field(2.0, ge=0.0, le=30.0, description="hold at the start pose before the trajectory")
    kp_nm_per_rad: Number = Field(
        DEFAULT_KP_NM_PER_RAD,
        gt=0.0,
        le=2000.0,
        description="stiffness of the motor position PD (Sec. 2.2.4: 700); checked stable before a run",
    )
    kd_nms_per_rad: Number = Field(
        DEFAULT_KD_NMS_PER_RAD, ge=0.0, le=200.0, description="damping of the motor position PD"
    )
    points_per_stop: Integer = Field(3, ge=1, le=20, description="training points averaged per stop")
    min_samples_per_stop: Integer = Field(
        100, ge=1, le=100_000, description="a stop with fewer stationary samples gives no point (0.1 s at 1 kHz)"
    )
    waypoint_tolerance_deg: Number = Field(
        2.0,
        ge=0.0,
        le=10.0,
        description="waypoints this close outside the recorded ISB range are kept; the trajectory may use it too",
    )
    protocol_file: Path | None = Field(
        None,
        description="a designed protocol (daror protocol design) for the training run instead of the waypoints'",
    )
    protocol_budget_s: Number | None = Field(
        None,
        gt=0.0,
        le=3600.0,
        description="design the training run for the pilot's recorded ISB limits, this many seconds of robot time",
    )

    @model_validator(mode="after")
    def _one_training_protocol(self) -> IdentificationSettings:
        if self.protocol_file is not None and self.protocol_budget_s is not None:
            raise ValueError("protocol_file and protocol_budget_s both choose the training run; set one of them")
        return self

    def approach_duration_s(self, distance_rad: float) -> float:
        """Duration (s) of the minimum-jerk approach over ``distance_rad`` (the joint that moves most).

        A minimum-jerk move's peak speed is 1.875 times its mean (``distance / duration``), so this
        duration makes the peak :attr:`approach_speed_rad_s`; never shorter than
        :attr:`min_approach_s`.
        """
        return max(distance_rad / self.approach_speed_rad_s * 1.875, self.min_approach_s)
