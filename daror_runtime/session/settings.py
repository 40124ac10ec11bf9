"""Session settings: a YAML file the operator may edit (``daror console --settings FILE``).

Every value has a default a session can run with; the file only lists what differs::

    support_level: 0.8
    identification:
      waypoint_stride: 3
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict, model_validator
from pydantic_core import PydanticCustomError

from daror_runtime.errors import InputError
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.models.registry import kind_names
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
    model_kind: SessionModelKind = Field(
        "plf+", description="the model trained in state training: a kind of the model registry a session may train"
    )
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
