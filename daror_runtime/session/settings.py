"""Session settings: a YAML file the operator may edit (``daror console --settings FILE``).

Every value has a default a session can run with; the file only lists what differs::

    support_level: 0.8
    identification:
      waypoint_stride: 3
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from daror_runtime.errors import InputError
from hal.yamlfile import Flag, Integer, Number, load_yaml_model


class SessionSettingsError(InputError):
    """The session settings file is missing, not YAML, or wrong (file, line and field named)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class IdentificationSettings(_Strict):
    """How the protocol runs inside a session (state ``identification``)."""

    waypoints_file: Path | None = Field(None, description="waypoint YAML; default the shipped 83 waypoints")
    waypoint_stride: Integer = Field(1, ge=1, le=20, description="use every n-th waypoint (a shorter protocol)")
    approach_speed_rad_s: Number = Field(0.25, gt=0.0, le=1.0, description="mean speed of the approach move")
    settle_s: Number = Field(2.0, ge=0.0, le=30.0, description="hold at the start pose before the trajectory")
    points_per_stop: Integer = Field(3, ge=1, le=20, description="training points averaged per stop")
    waypoint_tolerance_deg: Number = Field(
        2.0,
        ge=0.0,
        le=10.0,
        description="waypoints this close outside the recorded ISB range are kept; the trajectory may use it too",
    )


class SessionSettings(_Strict):
    """Settings of one session; units in the names."""

    dummy_arm: Flag = Field(False, description="the Dummy Arm is installed (the A Priori model includes it)")
    support_level: Number = Field(1.0, ge=0.0, le=1.0, description="fraction of the model torque delivered")
    support_ramp_per_s: Number = Field(
        0.5,
        gt=0.0,
        le=10.0,
        description="how fast the delivered support level, and missing support at a mode's entry, move",
    )
    handover_tolerance_nm: Number = Field(
        0.5,
        ge=0.0,
        le=5.0,
        description="entering compensation, support the springs miss by up to this is handed over by the pilot's motion",
    )
    at_rest_rad_s: Number = Field(0.05, gt=0.0, le=1.0, description="every joint slower than this: at rest")
    isb_margin_deg: Number = Field(5.0, ge=0.0, le=30.0, description="tolerance outside the recorded ISB limits")
    rom_min_range_deg: Number = Field(5.0, gt=0.0, le=90.0, description="a recorded ISB range must span at least this")
    model_kind: Literal["ap", "plf", "plf+"] = Field("plf+", description="the model trained in state training")
    max_validation_rmse_nm: Number = Field(
        1.5, gt=0.0, le=20.0, description="a model is validated when its validation RMSE is at most this"
    )
    identification: IdentificationSettings = Field(default_factory=IdentificationSettings)

    @model_validator(mode="after")
    def _tolerance_inside_margin(self) -> SessionSettings:
        # The protocol may use the tolerance beyond the recorded range; the monitor allows the margin.
        if (
            self.identification.waypoint_tolerance_deg >= self.isb_margin_deg
            and self.identification.waypoint_tolerance_deg > 0
        ):
            raise ValueError(
                f"identification.waypoint_tolerance_deg ({self.identification.waypoint_tolerance_deg}) must be below "
                f"isb_margin_deg ({self.isb_margin_deg}): the protocol must stay inside what the safety monitor allows"
            )
        return self


def load_session_settings(path: Path | str | None) -> SessionSettings:
    """The settings in ``path`` (None: the defaults).

    Raises:
        SessionSettingsError: the file cannot be read or does not match (file, line, field named).
    """
    if path is None:
        return SessionSettings()
    return load_yaml_model(path, SessionSettings, SessionSettingsError)
