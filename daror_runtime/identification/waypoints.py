"""The identification waypoints: ISB poses the protocol visits (thesis Sec. 4.3.1, Fig. 4.4).

A waypoint set is a YAML file a person edits: every waypoint is an ISB pose in degrees
(elevation, horizontal rotation, axial rotation, elbow; the convention of :mod:`hal.isb`), and two
orders (training and validation) list the waypoint numbers, counted from 1 in the order of the
file. Both orders are permutations of all waypoints: the two trajectories span the same workspace
along different paths. Whether the robot can reach the poses and the paths between them is the
trajectory generator's check (it needs the robot and the pilot's limits);
this module checks the file.

A mistake is reported with file, line and field::

    waypoints.yaml: line 41, waypoint 17, field elbow_deg: Input should be less than or equal to 180
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Annotated

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, ValidationInfo, field_validator

from daror_runtime.errors import InputError
from hal.robot import FloatArray
from hal.yamlfile import line_of, read_yaml

__all__ = ["DEFAULT_WAYPOINTS_FILE", "Waypoint", "WaypointFileError", "WaypointSet", "load_waypoints"]

DEFAULT_WAYPOINTS_FILE = "waypoints.yaml"


class WaypointFileError(InputError):
    """A waypoint file is missing, not YAML, or does not match the schema (file, line, field named)."""


Angle = Annotated[float, Field(ge=-180.0, le=180.0)]


class Waypoint(BaseModel):
    """One ISB pose, degrees (hal.isb convention)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    elevation_deg: Annotated[float, Field(ge=0.0, le=180.0)]
    horizontal_rotation_deg: Angle
    axial_rotation_deg: Angle
    elbow_deg: Angle

    @property
    def isb_deg(self) -> FloatArray:
        return np.array([self.elevation_deg, self.horizontal_rotation_deg, self.axial_rotation_deg, self.elbow_deg])

    @property
    def isb_rad(self) -> FloatArray:
        """[elevation, horizontal rotation, axial rotation, elbow] (4,) rad."""
        return np.deg2rad(self.isb_deg)


class WaypointSet(BaseModel):
    """Waypoints and the two orders they are visited in.

    ``training_order`` and ``validation_order`` hold waypoint numbers (1 = the first waypoint of
    the list); each must name every waypoint exactly once, and the two must differ.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    description: str = ""
    waypoints: Annotated[list[Waypoint], Field(min_length=2)]
    training_order: list[int]
    validation_order: list[int]

    _source: str = PrivateAttr(default="<memory>")
    _lines: tuple[int, ...] = PrivateAttr(default=())

    @field_validator("training_order", "validation_order")
    @classmethod
    def _permutation(cls, order: list[int], info: ValidationInfo) -> list[int]:
        waypoints = info.data.get("waypoints")
        if waypoints is None:  # the waypoints themselves failed; their error says why
            return order
        n = len(waypoints)
        unknown = sorted({i for i in order if not 1 <= i <= n})
        if unknown:
            raise ValueError(f"waypoint numbers {unknown} do not exist (there are {n} waypoints, numbered 1-{n})")
        repeated = sorted({i for i in order if order.count(i) > 1})
        if repeated:
            raise ValueError(f"waypoints {repeated} appear more than once")
        missing = sorted(set(range(1, n + 1)) - set(order))
        if missing:
            raise ValueError(f"waypoints {missing} are missing; the order must visit every waypoint once")
        if info.field_name == "validation_order" and order == info.data.get("training_order"):
            raise ValueError("the validation order equals the training order; it must visit the waypoints differently")
        return order

    @property
    def source(self) -> str:
        """The file this set was read from, or ``<memory>``."""
        return self._source

    def __len__(self) -> int:
        return len(self.waypoints)

    @property
    def isb_rad(self) -> FloatArray:
        """All waypoints as ISB angles (N, 4) rad, row i = waypoint i + 1."""
        return np.array([w.isb_rad for w in self.waypoints])

    def order(self, kind: str) -> tuple[int, ...]:
        """The waypoint numbers of ``kind`` ("training" or "validation") in visiting order.

        Raises:
            ValueError: an unknown kind (a programming error).
        """
        if kind == "training":
            return tuple(self.training_order)
        if kind == "validation":
            return tuple(self.validation_order)
        raise ValueError(f"unknown trajectory kind {kind!r}; expected 'training' or 'validation'")

    def describe(self, number: int) -> str:
        """``waypoint 17`` plus, for a set read from a file, ``(file line 41)``."""
        if self._lines and 1 <= number <= len(self._lines):
            return f"waypoint {number} ({self._source} line {self._lines[number - 1]})"
        return f"waypoint {number}"

    def with_source(self, source: str, lines: tuple[int, ...]) -> WaypointSet:
        """This set, remembering where each waypoint was written (for messages)."""
        copy = self.model_copy()
        copy._source = source
        copy._lines = tuple(lines)
        return copy


def _format(source: str, exc: ValidationError, root: yaml.Node | None) -> str:
    """One phrase per problem, naming the line, the waypoint by its number (from 1) and the field."""
    problems = []
    for problem in exc.errors():
        loc = tuple(problem["loc"])
        line = line_of(root, loc)
        where = f"line {line}, " if line is not None else ""
        if len(loc) >= 2 and loc[0] == "waypoints" and isinstance(loc[1], int):
            field = ".".join(str(p) for p in loc[2:]) or "(the waypoint)"
            problems.append(f"{source}: {where}waypoint {loc[1] + 1}, field {field}: {problem['msg']}")
        else:
            field = ".".join(str(p) for p in loc) or "(top level)"
            problems.append(f"{source}: {where}field {field}: {problem['msg']}")
    return "; ".join(problems)


def load_waypoints(path: Path | str | None = None) -> WaypointSet:
    """Read a waypoint set; ``None`` reads the shipped ``daror_runtime/identification/waypoints.yaml``.

    Raises:
        WaypointFileError: the file is missing, not YAML, or does not match the schema; the
            message names the file, the line, the waypoint number and the field.
    """
    if path is None:
        with resources.as_file(resources.files(__package__) / DEFAULT_WAYPOINTS_FILE) as packaged:
            return load_waypoints(packaged)
    path = Path(path)
    data, root = read_yaml(path, WaypointFileError)
    try:
        waypoint_set = WaypointSet.model_validate(data)
    except ValidationError as exc:
        raise WaypointFileError(_format(str(path), exc, root)) from None
    lines = tuple(line_of(root, ("waypoints", i)) or 0 for i in range(len(waypoint_set)))
    return waypoint_set.with_source(str(path), lines)
