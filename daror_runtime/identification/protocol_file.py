"""The designed-protocol file (``PROTOCOL.yaml``): what ``daror protocol design`` writes and the
trajectory generator runs (``daror identify --protocol``, a session's ``protocol_file``).

A protocol is a list of *visits*, ISB poses in degrees in the order the robot goes through them,
each with the time it stands still there (``stop_s``; 0 for a via pose it only passes through),
plus the trajectory settings the moves are timed with, the pilot's ISB limits it was designed in,
the start pose its approach was timed from, how it was designed and what the design predicts
(robot time, standard errors of the base parameters, validation error). Only the visits, the
trajectory settings and the limits change what the robot does; the rest is the record.

A file that does not match is refused in one line naming the file, the line and the field::

    p.yaml: line 31, field visits.4.stop_s: Input should be greater than or equal to 0
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from daror_runtime.errors import InputError
from daror_runtime.identification.trajectory_planning import TrajectorySettings
from daror_runtime.identification.waypoints import Waypoint, WaypointSet
from daror_runtime.util.atomic import write_text_atomic
from hal.isb import IsbLimits
from hal.robot import N_JOINTS, FloatArray
from hal.yamlfile import Integer, Number, format_validation_error, line_of, read_yaml

__all__ = [
    "FORMAT",
    "MIN_DATA_STOP_S",
    "DesignedProtocol",
    "ProtocolFileError",
    "load_protocol",
    "protocol_text",
    "write_protocol",
]

FORMAT = "daror-identification-protocol"
#: A stop shorter than this gives no stationary point (the 2 Hz velocity filter needs the time).
MIN_DATA_STOP_S = 0.3


class ProtocolFileError(InputError):
    """A protocol file is missing, not YAML, or does not match the schema (file, line, field named)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Angle = Annotated[Number, Field(ge=-180.0, le=180.0)]
PerJointNm = Annotated[
    list[Annotated[Number, Field(ge=0.0, le=100.0)]], Field(min_length=N_JOINTS, max_length=N_JOINTS)
]


class IsbPose(_Strict):
    """One ISB pose, degrees (hal.isb convention)."""

    elevation_deg: Annotated[Number, Field(ge=0.0, le=180.0)]
    horizontal_rotation_deg: Angle
    axial_rotation_deg: Angle
    elbow_deg: Angle

    @property
    def isb_rad(self) -> FloatArray:
        """[elevation, horizontal rotation, axial rotation, elbow] (4,) rad."""
        deg = [self.elevation_deg, self.horizontal_rotation_deg, self.axial_rotation_deg, self.elbow_deg]
        return np.deg2rad(np.array(deg, dtype=float))

    @classmethod
    def from_rad(cls, isb: FloatArray) -> IsbPose:
        e, h, a, w = (float(v) for v in np.degrees(np.asarray(isb, dtype=float)))
        return cls(elevation_deg=e, horizontal_rotation_deg=h, axial_rotation_deg=a, elbow_deg=w)


class Visit(IsbPose):
    """A pose on the way: ``stop_s`` 0 passes through it, more gives data; ``pose`` numbers the designed pose."""

    stop_s: Annotated[Number, Field(ge=0.0, le=30.0)]
    pose: Annotated[Integer, Field(ge=1)]

    @model_validator(mode="after")
    def _long_enough(self) -> Visit:
        if 0.0 < self.stop_s < MIN_DATA_STOP_S:
            raise ValueError(
                f"stop_s {self.stop_s} s gives no data; expected 0 (pass through) or at least {MIN_DATA_STOP_S} s"
            )
        return self


class ProtocolTrajectory(_Strict):
    """How the moves are timed (:class:`~daror_runtime.identification.trajectory_planning.TrajectorySettings`)."""

    shoulder_speed_rad_s: Annotated[Number, Field(gt=0.0, le=2.0)] = 0.40
    elbow_speed_rad_s: Annotated[Number, Field(gt=0.0, le=3.0)] = 0.60
    max_joint_speed_rad_s: Annotated[Number, Field(gt=0.0, le=3.0)] = 1.0
    min_move_s: Annotated[Number, Field(gt=0.0, le=10.0)] = 0.6
    min_sigma: Annotated[Number, Field(ge=0.0, lt=1.0)] = 0.3

    def settings(self, stop_s: float, rate_hz: float = 1000.0) -> TrajectorySettings:
        """The generator's settings for these moves (no sub-waypoints; ``stop_s`` the longest stop)."""
        return TrajectorySettings(
            shoulder_speed_rad_s=self.shoulder_speed_rad_s,
            elbow_speed_rad_s=self.elbow_speed_rad_s,
            max_joint_speed_rad_s=self.max_joint_speed_rad_s,
            sub_waypoint_spacing_deg=None,
            stop_s=stop_s,
            min_move_s=self.min_move_s,
            rate_hz=rate_hz,
            min_sigma=self.min_sigma,
        )


class DesignRecord(_Strict):
    """How the protocol was designed (the inputs of ``daror protocol design``)."""

    criterion: Literal["D-optimal"] = "D-optimal"
    base: str
    effects: list[str] = []
    approach: Literal["both", "once"]
    budget_s: Annotated[Number, Field(gt=0.0)]
    seed: Annotated[Integer, Field(ge=0)]
    candidates: Annotated[Integer, Field(ge=0)]
    via_deg: Annotated[Number, Field(gt=0.0, le=20.0)] | None = None
    margin_deg: Annotated[Number, Field(ge=0.0, le=30.0)]
    direction_error_nm: PerJointNm
    sensor_noise_nm: PerJointNm


class BaseParameterPrediction(_Strict):
    """One identifiable combination and its predicted standard error (its own unit: Nm, Nm/rad^k)."""

    expression: str
    std_error: Annotated[Number, Field(ge=0.0)]


class Prediction(_Strict):
    """What the design predicts: robot time (s) as ``daror identify`` runs it, and the model's errors."""

    robot_time_s: Annotated[Number, Field(ge=0.0)]
    approach_s: Annotated[Number, Field(ge=0.0)]
    settle_s: Annotated[Number, Field(ge=0.0)]
    moves_s: Annotated[Number, Field(ge=0.0)]
    stops_s: Annotated[Number, Field(ge=0.0)]
    poses: Annotated[Integer, Field(ge=1)]
    data_stops: Annotated[Integer, Field(ge=1)]
    log_det: Number
    condition_number: Annotated[Number, Field(ge=1.0)]  # information scaled to unit diagonal
    workspace_condition_number: Annotated[Number, Field(ge=1.0)]  # relative to the pilot's whole range
    validation_rmse_nm: Annotated[Number, Field(ge=0.0)]
    validation_rmse_per_joint_nm: PerJointNm
    base_parameters: list[BaseParameterPrediction]


class DesignedProtocol(_Strict):
    """A designed identification protocol (the file's schema; see the module docstring)."""

    format: Literal["daror-identification-protocol"] = FORMAT
    version: Literal[1] = 1
    description: str = ""
    start: IsbPose
    limits: IsbLimits
    trajectory: ProtocolTrajectory = ProtocolTrajectory()
    design: DesignRecord
    prediction: Prediction
    visits: Annotated[list[Visit], Field(min_length=2)]

    @model_validator(mode="after")
    def _gives_data(self) -> DesignedProtocol:
        if not any(v.stop_s > 0.0 for v in self.visits):
            raise ValueError("no visit has a stop (stop_s > 0), so the protocol would give no data")
        return self

    @property
    def stops_s(self) -> list[float]:
        """Stop of every visit, seconds (0: passed through)."""
        return [v.stop_s for v in self.visits]

    def trajectory_settings(self, rate_hz: float = 1000.0) -> TrajectorySettings:
        return self.trajectory.settings(max(self.stops_s), rate_hz)

    def waypoint_set(self, source: str = "<memory>", lines: tuple[int, ...] = ()) -> WaypointSet:
        """The visits as a waypoint set in visiting order (what the trajectory generator walks)."""
        points = [
            Waypoint(
                elevation_deg=v.elevation_deg,
                horizontal_rotation_deg=v.horizontal_rotation_deg,
                axial_rotation_deg=v.axial_rotation_deg,
                elbow_deg=v.elbow_deg,
            )
            for v in self.visits
        ]
        n = len(points)
        visits = WaypointSet(
            description=self.description,
            waypoints=points,
            training_order=list(range(1, n + 1)),
            validation_order=list(range(n, 0, -1)),
        )
        return visits.with_source(source, lines)


def load_protocol(path: Path | str) -> tuple[DesignedProtocol, WaypointSet]:
    """Read a protocol file; also its visits as a waypoint set that names the file's lines in messages.

    Raises:
        ProtocolFileError: the file is missing, not YAML, or does not match the schema; the message
            names the file, the line and the field.
    """
    path = Path(path)
    data, root = read_yaml(path, ProtocolFileError)
    try:
        protocol = DesignedProtocol.model_validate(data)
    except ValidationError as exc:
        raise ProtocolFileError(format_validation_error(str(path), exc, root)) from None
    lines = tuple(line_of(root, ("visits", i)) or 0 for i in range(len(protocol.visits)))
    return protocol, protocol.waypoint_set(str(path), lines)


_HEADER = """\
# A designed identification protocol (daror protocol design; docs/identification.md, section 8).
# visits: ISB poses in degrees (hal/isb.py convention), in the order the robot goes through them;
# stop_s 0 = passed through (a via pose that sets the direction of arrival), more = a stop with data.
# Run it: daror identify --protocol THIS_FILE ...; in a session: identification.protocol_file.
"""


def protocol_text(protocol: DesignedProtocol) -> str:
    """The file's text: a header, then the fields in schema order (one line per visit)."""
    document = protocol.model_dump(mode="json")
    body = yaml.safe_dump(document, sort_keys=False, default_flow_style=None, width=200, allow_unicode=True)
    return _HEADER + body


def write_protocol(path: Path | str, protocol: DesignedProtocol) -> None:
    """Write ``protocol`` to ``path`` atomically (temporary file, then rename)."""
    write_text_atomic(path, protocol_text(protocol))
