"""Simulation scenarios: the as-built truth of one simulated session.

A scenario (``hal/sim/scenarios/<name>.yaml``) declares what the real robot would *be*: the
as-built link masses and centres of mass (production tolerance makes them differ from the design
values of ``hal/daror01.yaml``), the load (the Dummy Arm, its springs), the sensor imperfections
and the random seed. Only the simulator reads scenarios; models learn only from measured data.

A scenario may also carry effects that no compensation model declares (a base mounted tilted,
a joint spring, an SEA spring stiffer than its nominal constant, a wrong joint zero, a drifting
torque reading; docs/simulation.md, "Undeclared effects"), so that residual analysis can be
tested on data with such an effect in it. Every one of them defaults to absent. A scenario file
may start from another with ``extends: NAME`` (see :func:`load_scenario_file`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hal.errors import DescriptionError
from hal.robot import N_JOINTS, FloatArray, Kinematics, LinkInertial, RobotDescription, load_description, rot_x, rot_z
from hal.sim.statics import PointMass, PullSpring, StaticPlant
from hal.yamlfile import Flag, Integer, Number, format_validation_error, line_of, read_yaml

NonNegative = Annotated[Number, Field(ge=0)]
PerJoint = Annotated[list[Number], Field(min_length=N_JOINTS, max_length=N_JOINTS)]
Finite = Annotated[Number, Field(allow_inf_nan=False)]
#: Per-joint values that must be finite (the undeclared effects: NaN would poison a whole run).
FinitePerJoint = Annotated[list[Finite], Field(min_length=N_JOINTS, max_length=N_JOINTS)]
PositivePerJoint = Annotated[
    list[Annotated[Number, Field(gt=0, allow_inf_nan=False)]], Field(min_length=N_JOINTS, max_length=N_JOINTS)
]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ElbowSpringTruth(_Strict):
    """One pull-only spring of the Dummy Arm across the elbow (joint 4)."""

    stiffness_nm_per_rad: Annotated[Number, Field(gt=0)]
    slack_angle_deg: Number
    resists: Literal["flexion", "extension"]


class DummyArmTruth(_Strict):
    """As-built Dummy Arm: segment masses and CoMs (upper arm in rotor-3, lower arm in rotor-4)."""

    upper_arm: LinkInertial
    lower_arm: LinkInertial
    elbow_springs: list[ElbowSpringTruth] = []


class DriveTrainTruth(_Strict):
    """As-built drive train of each SEA (motor and gearbox up to the spring), per joint."""

    gearbox_inertia_kgm2: PerJoint = Field(description="motor + gearbox inertia at the gearbox output")
    gearbox_viscous_nms_per_rad: PerJoint
    gearbox_coulomb_nm: PerJoint
    coulomb_smoothing_rad_s: Annotated[Number, Field(gt=0)] = Field(
        0.01, description="Coulomb friction is tau_c tanh(v / this): smooth, so the integrator stays stable"
    )
    link_viscous_nms_per_rad: PerJoint = Field(description="joint bearing friction on the link side")
    spring_damping_nms_per_rad: PerJoint = Field(description="internal damping of the torsion spring")
    max_motor_torque_nm: PerJoint
    command_delay_ticks: Annotated[Integer, Field(ge=0, le=10)] = Field(1, description="ticks before a command acts")


class EndStopTruth(_Strict):
    """The mechanical end stops: a stiff, damped, push-only spring just beyond each device limit.

    They keep a simulated arm whose torque is off (FAIL) from swinging through its range, as the
    real hard stops do; the safety monitor's joint limits trip before they are reached.
    """

    margin_deg: NonNegative = Field(2.0, description="how far beyond the device's joint limits the stops sit")
    stiffness_nm_per_rad: Annotated[Number, Field(gt=0)] = 2000.0
    damping_nms_per_rad: NonNegative = 20.0


class SensorTruth(_Strict):
    """Sensor imperfections of the SEAs (Sec. 2.2.1-2.2.2)."""

    encoder_noise_rad: NonNegative = Field(
        0.5e-4, description="std of white noise on each encoder reading, before quantisation"
    )
    quantise: Flag = Field(True, description="round encoder readings to the encoder resolution")
    direction_error_nm: PerJoint = Field(
        [0.0] * N_JOINTS,
        description="direction-dependent torque error per joint (Sec. 2.2.2): "
        "measured = true + error x sign of the joint's last motion",
    )
    velocity_filter_hz: Annotated[Number, Field(gt=0)] = Field(
        50.0, description="the drives' velocity estimate: first-order low-pass of the encoder difference"
    )
    direction_play_rad: Annotated[Number, Field(gt=0)] = Field(
        5e-3,
        description="joint travel after which the direction-dependent error has fully reversed: a hysteresis "
        "(play operator), so the vibration of a held joint does not flip it but a move does",
    )
    angle_offset_deg: FinitePerJoint = Field(
        [0.0] * N_JOINTS,
        description="undeclared: the joint's zero is calibrated wrong; both encoders of the joint read "
        "true + offset (degrees), so q reads off by it and the measured torque does not change",
    )
    torque_drift_nm_per_min: FinitePerJoint = Field(
        [0.0] * N_JOINTS,
        description="undeclared: slow (thermal) drift of the measured torque, Nm per minute of robot time "
        "since the session started: measured = true + drift x t / 60",
    )


class JointSpringTruth(_Strict):
    """An undeclared linear spring across one joint (a cable harness, a stiff bearing seal).

    Two-sided: it holds ``stiffness (q - rest)`` on its joint, whichever side of the rest angle
    the joint is on. No model's family declares it on joints 1-3.
    """

    joint: Annotated[Integer, Field(ge=1, le=N_JOINTS, description="joint 1-4")]
    stiffness_nm_per_rad: Annotated[Number, Field(gt=0, allow_inf_nan=False)]
    rest_angle_deg: Finite = Field(description="joint angle at which the spring is relaxed, degrees")


class WorkspaceBox(_Strict):
    """Joint-space box (degrees) the static dataset generator draws waypoints from."""

    lower_deg: PerJoint
    upper_deg: PerJoint

    @model_validator(mode="after")
    def _ordered(self) -> WorkspaceBox:
        for j, (lo, hi) in enumerate(zip(self.lower_deg, self.upper_deg, strict=True), start=1):
            if not lo < hi:
                raise ValueError(f"joint {j}: lower_deg {lo} must be below upper_deg {hi}")
        return self

    @property
    def lower_rad(self) -> np.ndarray:
        return np.deg2rad(self.lower_deg)

    @property
    def upper_rad(self) -> np.ndarray:
        return np.deg2rad(self.upper_deg)


class Scenario(_Strict):
    """The as-built truth of one simulated session."""

    name: str
    summary: str = ""
    robot: str | None = Field(None, description="robot description file; default the packaged DAROR-01")
    seed: Integer = 0
    gravity_mps2: Annotated[Number, Field(gt=0)] = 9.81
    links: Annotated[list[LinkInertial], Field(min_length=N_JOINTS, max_length=N_JOINTS)]
    dummy_arm: DummyArmTruth | None = None
    sensors: SensorTruth = SensorTruth()
    workspace: WorkspaceBox
    drive_train: DriveTrainTruth | None = None
    end_stops: EndStopTruth = EndStopTruth()
    initial_q_deg: PerJoint = Field(
        [-20.25, 82.41, -30.27, 30.0], description="where a dynamic simulation starts, at rest (default: arm hanging)"
    )
    # --- undeclared effects (docs/simulation.md, "Undeclared effects"); all absent by default ---
    mounting_tilt_deg: Annotated[
        list[Annotated[Number, Field(ge=-90, le=90, allow_inf_nan=False)]], Field(min_length=2, max_length=2)
    ] = Field(
        [0.0, 0.0],
        description="[about_x, about_z] degrees: the base is mounted rotated by Rx(about_x) Rz(about_z) "
        "(world-frame rotations) relative to the nominal base rotation; gravity stays world -y",
    )
    joint_springs: Annotated[list[JointSpringTruth], Field(max_length=N_JOINTS)] = Field(
        [], description="linear two-sided springs across joints, holding torque k (q - rest)"
    )
    sea_stiffness_scale: PositivePerJoint = Field(
        [1.0] * N_JOINTS,
        description="as-built SEA spring constant = nominal x scale; the drives still compute torque with the "
        "nominal constant, so measured torque = true torque / scale",
    )

    def description(self) -> RobotDescription:
        """The robot description this scenario is an as-built instance of."""
        return load_description(self.robot)

    def mounting_rotation(self) -> FloatArray:
        """``R_tilt = Rx(about_x) Rz(about_z)`` (3, 3): the base's mounting error, in the world frame.

        The identity when ``mounting_tilt_deg`` is ``[0, 0]``.
        """
        about_x, about_z = np.deg2rad(self.mounting_tilt_deg)
        return rot_x(about_x) @ rot_z(about_z)

    def true_kinematics(self, description: RobotDescription | None = None) -> Kinematics:
        """The as-built kinematic chain: the description's, with the base tilted by :meth:`mounting_rotation`.

        True base rotation ``0R_{1,s} = R_tilt @ nominal``. Without a tilt this is exactly
        ``description.kinematics()`` (the very same floats).
        """
        description = description or self.description()
        kinematics = description.kinematics()
        if not any(self.mounting_tilt_deg):
            return kinematics
        return kinematics.with_base_rotation(self.mounting_rotation() @ kinematics.base_rotation)

    def stiffness_nm_per_rad(self, description: RobotDescription | None = None) -> FloatArray:
        """As-built SEA spring constants (4,), Nm/rad: the description's nominal one times ``sea_stiffness_scale``."""
        description = description or self.description()
        return description.sea.spring_stiffness_nm_per_rad * np.asarray(self.sea_stiffness_scale, dtype=float)

    def joint_pull_springs(self) -> list[PullSpring]:
        """The undeclared ``joint_springs`` as pairs of pull-only springs.

        A flexion and an extension spring with their slack angle at the rest angle together hold
        exactly ``k (q - rest)``: one is stretched on each side, never both.
        """
        springs: list[PullSpring] = []
        for s in self.joint_springs:
            rest_rad = float(np.deg2rad(s.rest_angle_deg))
            springs.append(PullSpring(s.joint, s.stiffness_nm_per_rad, rest_rad, "flexion"))
            springs.append(PullSpring(s.joint, s.stiffness_nm_per_rad, rest_rad, "extension"))
        return springs

    def static_plant(self, description: RobotDescription | None = None) -> StaticPlant:
        """The static physics of this scenario: as-built links, load, springs and mounting tilt."""
        description = description or self.description()
        masses = [
            PointMass(joint=i + 1, mass_kg=link.mass_kg, com_m=link.com_m, label=f"link {i + 1}")
            for i, link in enumerate(self.links)
        ]
        springs: list[PullSpring] = []
        if self.dummy_arm is not None:
            masses.append(PointMass(3, self.dummy_arm.upper_arm.mass_kg, self.dummy_arm.upper_arm.com_m, "upper arm"))
            masses.append(PointMass(4, self.dummy_arm.lower_arm.mass_kg, self.dummy_arm.lower_arm.com_m, "lower arm"))
            springs = [
                PullSpring(4, s.stiffness_nm_per_rad, float(np.deg2rad(s.slack_angle_deg)), s.resists)
                for s in self.dummy_arm.elbow_springs
            ]
        springs += self.joint_pull_springs()
        return StaticPlant(
            self.true_kinematics(description), masses, springs, gravity_world_mps2=(0.0, -self.gravity_mps2, 0.0)
        )


SCENARIO_PACKAGE = "hal.sim.scenarios"


def scenario_names() -> list[str]:
    """Names of the scenarios shipped with the package."""
    return sorted(
        p.name[: -len(".yaml")] for p in resources.files(SCENARIO_PACKAGE).iterdir() if p.name.endswith(".yaml")
    )


#: Longest chain of ``extends`` one scenario file may start (a guard beside the cycle check).
MAX_EXTENDS_DEPTH = 8
EXTENDS_KEY = "extends"


def deep_merge(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``override`` laid over ``base``: mappings merge key by key, recursively; lists and scalars replace.

    Lists replace rather than concatenate because a scenario's lists are per-joint vectors or
    complete sets (springs): half of one and half of another is never what a person meant.
    Neither argument is modified.
    """
    merged = dict(base)
    for key, value in override.items():
        below = merged.get(key)
        if isinstance(value, Mapping) and isinstance(below, Mapping):
            merged[key] = deep_merge(below, value)
        else:
            merged[key] = value
    return merged


def _is_path_like(reference: str) -> bool:
    """True if an ``extends`` value names a file rather than a shipped scenario."""
    return Path(reference).suffix in {".yaml", ".yml"} or "/" in reference or "\\" in reference


def _line_suffix(root: Any, key: str) -> str:
    """``: line L`` of a top-level key in a composed YAML node tree, or empty."""
    line = line_of(root, (key,))
    return f": line {line}" if line is not None else ""


def _resolved_mapping(path: Path, chain: tuple[Path, ...]) -> tuple[Any, Any, Any, list[str]]:
    """Read one scenario file and resolve its ``extends`` chain.

    Args:
        path: the file to read.
        chain: files already being resolved, outermost first (cycle detection).

    Returns:
        ``(data, node tree of this file, own data of this file, bases)``: ``data`` is the merged
        mapping without any ``extends`` key (the file's raw content when it has no ``extends``),
        ``bases`` the files it inherits from, nearest first.

    Raises:
        DescriptionError: naming the file: unreadable, an ``extends`` that is not a string, that
            names an unknown scenario or a missing file, that forms a cycle, or a chain deeper
            than :data:`MAX_EXTENDS_DEPTH`.
    """
    data, root = read_yaml(path, DescriptionError)
    if not isinstance(data, dict) or EXTENDS_KEY not in data:
        return data, root, data, []
    where = f"{path}{_line_suffix(root, EXTENDS_KEY)}"
    reference = data[EXTENDS_KEY]
    if not isinstance(reference, str) or not reference.strip():
        raise DescriptionError(
            f"{where}, field {EXTENDS_KEY}: expected the name of a shipped scenario or a .yaml path, got {reference!r}"
        )
    if len(chain) >= MAX_EXTENDS_DEPTH:
        raise DescriptionError(
            f"{where}, field {EXTENDS_KEY}: more than {MAX_EXTENDS_DEPTH} levels of extends "
            f"({' -> '.join(str(p) for p in (*chain, path))})"
        )
    own = {key: value for key, value in data.items() if key != EXTENDS_KEY}
    here = (*chain, path.resolve())

    def merged_with(base_path: Path) -> tuple[Any, Any, Any, list[str]]:
        resolved = base_path.resolve()
        if resolved in here:
            cycle = " -> ".join(str(p) for p in (*here, resolved))
            raise DescriptionError(f"{where}, field {EXTENDS_KEY}: {reference!r} forms a cycle: {cycle}")
        base, _, _, bases = _resolved_mapping(base_path, here)
        if not isinstance(base, dict):
            raise DescriptionError(
                f"{where}, field {EXTENDS_KEY}: {base_path} is not a YAML mapping, so it cannot be extended"
            )
        return deep_merge(base, own), root, own, [str(base_path), *bases]

    if _is_path_like(reference):
        base_path = Path(reference)
        if not base_path.is_absolute():
            base_path = path.parent / base_path  # relative to the extending file, not to the cwd
        if not base_path.is_file():
            raise DescriptionError(f"{where}, field {EXTENDS_KEY}: base scenario file {str(base_path)!r} not found")
        return merged_with(base_path)
    names = scenario_names()
    if reference not in names:
        raise DescriptionError(
            f"{where}, field {EXTENDS_KEY}: unknown scenario {reference!r}; expected one of {', '.join(names)} "
            "or a .yaml path"
        )
    with resources.as_file(resources.files(SCENARIO_PACKAGE) / f"{reference}.yaml") as base_path:
        return merged_with(base_path)


def _owned_by_file(data: Any, location: tuple[int | str, ...]) -> bool:
    """True if the value at ``location`` was written in the extending file itself (not inherited)."""
    node = data
    for key in location:
        if isinstance(node, dict):
            if key not in node:
                return False
            node = node[key]
        else:
            return True  # a list or scalar the file wrote replaces the base's as a whole
    return True


def load_scenario_file(path: Path | str) -> Scenario:
    """Load one scenario file, resolving ``extends: NAME`` (a shipped scenario or a .yaml path).

    The base's mapping is deep-merged under this file's (:func:`deep_merge`), recursively for a
    base that extends another, then the result is validated once. A relative path in
    ``extends`` is relative to the extending file's directory.

    Raises:
        hal.errors.DescriptionError: naming the file (and the line where known): unreadable,
            bad ``extends`` (not a string, unknown, missing, a cycle, too deep), or a merged
            mapping that does not match :class:`Scenario`; a problem in a value inherited from a
            base names that base too.
    """
    path = Path(path)
    data, root, own, bases = _resolved_mapping(path, ())
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        if not bases:
            raise DescriptionError(format_validation_error(str(path), exc, root)) from None
        problems = []
        for problem in exc.errors():
            location = tuple(problem["loc"])
            field = ".".join(str(p) for p in location) or "(top level)"
            if _owned_by_file(own, location):
                line = line_of(root, location)
                where = f"{path}: line {line}, " if line is not None else f"{path}: "
            else:
                where = f"{path}: inherited from {' <- '.join(bases)}, "
            problems.append(f"{where}field {field}: {problem['msg']}")
        raise DescriptionError("; ".join(problems)) from None


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a shipped scenario by name (``exo``) or any scenario file by path.

    Either may use ``extends`` (:func:`load_scenario_file`).

    Raises:
        hal.errors.DescriptionError: unknown name, missing file, or a file that does not match.
    """
    candidate = Path(name_or_path)
    # lexists: a broken link or a symlink loop is still a path the person named, not a scenario name
    if candidate.suffix in {".yaml", ".yml"} or os.path.lexists(candidate):
        return load_scenario_file(candidate)
    names = scenario_names()
    if str(name_or_path) not in names:
        raise DescriptionError(
            f"unknown scenario {str(name_or_path)!r}; expected one of {', '.join(names)} or a .yaml path"
        )
    with resources.as_file(resources.files(SCENARIO_PACKAGE) / f"{name_or_path}.yaml") as path:
        return load_scenario_file(path)
