"""Session settings: a YAML file the operator may edit (``daror console --settings FILE``).

Every value has a default a session can run with; the file only lists what differs::

    support_level: 0.8
    identification:
      waypoint_stride: 3
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict, model_validator
from pydantic_core import PydanticCustomError

from daror_runtime.errors import InputError
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.models.registry import kind_names
from daror_runtime.records.codes import PILOT_CODE_PATTERN
from hal.isb import ISB_NAMES, IsbLimits
from hal.robot import FloatArray
from hal.yamlfile import Flag, Number, load_yaml_model


class SessionSettingsError(InputError):
    """The session settings file is missing, not YAML, or wrong (file, line and field named)."""


def _session_model_kind(kind: str) -> str:
    """``kind`` if the registry has it and a session may train it (capability ``session_training``).

    Raises:
        PydanticCustomError: an unknown kind, or one a session may not train; the message lists
            the kinds a session may train.
    """
    trainable = kind_names(lambda entry: entry.session_training)
    if kind in trainable:
        return kind
    problem = (
        "model kind {kind} cannot be trained in a session" if kind in kind_names() else "unknown model kind {kind}"
    )
    raise PydanticCustomError(
        "model_kind",
        problem + "; expected one of {kinds}",
        {"kind": repr(kind), "kinds": ", ".join(trainable)},
    )


#: A model kind of the registry that a session may train (the registry is the one list of kinds).
SessionModelKind = Annotated[str, Strict(), AfterValidator(_session_model_kind)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RestSettings(_Strict):
    """Where the pilot's arm rests with the torque off: the end of every ``lower`` reaction (docs/safety.md)."""

    support: Literal["lap", "armrest", "stops"] = Field(
        "lap", description="what carries the arm there: the pilot's lap, an armrest or tray, or the robot's lower stops"
    )
    pose_isb_deg: tuple[Number, Number, Number, Number] = Field(
        (0.0, 0.0, 0.0, 30.0),
        description="the rest pose in ISB angles (elevation, horizontal rotation, axial rotation, elbow), deg: "
        "inside the pilot's ISB limits",
    )

    tolerance_deg: Number = Field(
        2.0,
        ge=0.0,
        le=5.0,
        description="the rest pose may lie this far outside the recorded ISB range (a hanging arm is recorded at "
        "the very edge of its range), deg",
    )

    @property
    def pose_isb_rad(self) -> FloatArray:
        return np.deg2rad(np.asarray(self.pose_isb_deg, dtype=float))

    def outside(self, limits: IsbLimits) -> list[str]:
        """What puts the rest pose outside ``limits`` beyond the tolerance, one phrase per angle; empty when inside."""
        boxed = np.degrees(limits.for_box_check(self.pose_isb_rad))
        found = []
        for name, value, rng in zip(ISB_NAMES, boxed, limits.ranges, strict=True):
            if value < rng.lower_deg - self.tolerance_deg or value > rng.upper_deg + self.tolerance_deg:
                found.append(f"{name} {value:.1f} deg outside [{rng.lower_deg:g}, {rng.upper_deg:g}] deg")
        return found


class SafeStopSettings(_Strict):
    """How a ``hold`` or ``lower`` reaction holds and lowers the arm (docs/safety.md, "Fault reactions")."""

    hold_s: Number = Field(2.0, ge=0.0, le=30.0, description="the arm is held where the fault found it this long, s")
    lowering_speed_rad_s: Number = Field(
        0.15, gt=0.0, le=0.2, description="no joint moves faster than this while the arm is lowered, rad/s"
    )
    handoff_s: Number = Field(
        2.0,
        ge=0.2,
        le=10.0,
        description="at the rest pose the gravity support, then the position loop's torque, ramp out over this each, s",
    )
    handoff_motion_deg: Number = Field(
        2.0,
        gt=0.0,
        le=10.0,
        description="motion during the handoff that shows nothing carries the arm (the reaction then holds it), deg",
    )


class SessionSettings(_Strict):
    """Settings of one session; units in the names."""

    pilot: str | None = Field(
        None,
        pattern=PILOT_CODE_PATTERN,
        description="the pilot's code in the lab's records (e.g. P-007; a code, never a name): a model is validated "
        "only on data recorded from this pilot",
    )
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
    limits_max_age_days: Number = Field(
        90.0,
        gt=0.0,
        le=3650.0,
        description="a returning pilot's last range of motion from the records is offered (rom last) only if it is "
        "at most this old, days; older limits are recorded anew (DMD progresses)",
    )
    model_kind: SessionModelKind = Field(
        "plf+", description="the model trained in state training: a kind of the model registry a session may train"
    )
    max_validation_rmse_nm: Number = Field(
        1.5, gt=0.0, le=20.0, description="a model is validated when its validation RMSE is at most this"
    )
    unvalidated_model_damping_nms_per_rad: Number = Field(
        4.0,
        ge=0.0,
        le=6.0,
        description="while compensation uses a model not validated on this pilot's data (the A Priori model the "
        "operator confirmed), this damping on the joints' speed keeps the model's error from moving a limp arm "
        "fast, Nms/rad",
    )
    identification: IdentificationSettings = Field(default_factory=IdentificationSettings)
    rest: RestSettings = Field(default_factory=RestSettings)
    safe_stop: SafeStopSettings = Field(default_factory=SafeStopSettings)

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
