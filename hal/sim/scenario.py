"""Simulation scenarios: the as-built truth of one simulated session.

A scenario (``hal/sim/scenarios/<name>.yaml``) declares what the real robot would *be*: the
as-built link masses and centres of mass (production tolerance makes them differ from the design
values of ``hal/daror01.yaml``), the load (the Dummy Arm, its springs), the sensor imperfections
and the random seed. Only the simulator reads scenarios; models learn only from measured data.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from hal.errors import DescriptionError
from hal.robot import N_JOINTS, LinkInertial, RobotDescription, load_description
from hal.sim.statics import PointMass, PullSpring, StaticPlant
from hal.yamlfile import load_yaml_model

NonNegative = Annotated[float, Field(ge=0)]
PerJoint = Annotated[list[float], Field(min_length=N_JOINTS, max_length=N_JOINTS)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ElbowSpringTruth(_Strict):
    """One pull-only spring of the Dummy Arm across the elbow (joint 4)."""

    stiffness_nm_per_rad: Annotated[float, Field(gt=0)]
    slack_angle_deg: float
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
    coulomb_smoothing_rad_s: Annotated[float, Field(gt=0)] = Field(
        0.01, description="Coulomb friction is tau_c tanh(v / this): smooth, so the integrator stays stable"
    )
    link_viscous_nms_per_rad: PerJoint = Field(description="joint bearing friction on the link side")
    spring_damping_nms_per_rad: PerJoint = Field(description="internal damping of the torsion spring")
    max_motor_torque_nm: PerJoint
    command_delay_ticks: Annotated[int, Field(ge=0, le=10)] = Field(1, description="ticks before a command acts")


class EndStopTruth(_Strict):
    """The mechanical end stops: a stiff, damped, push-only spring just beyond each device limit.

    They keep a simulated arm whose torque is off (FAIL) from swinging through its range, as the
    real hard stops do; the safety monitor's joint limits trip before they are reached.
    """

    margin_deg: NonNegative = Field(2.0, description="how far beyond the device's joint limits the stops sit")
    stiffness_nm_per_rad: Annotated[float, Field(gt=0)] = 2000.0
    damping_nms_per_rad: NonNegative = 20.0


class SensorTruth(_Strict):
    """Sensor imperfections of the SEAs (Sec. 2.2.1-2.2.2)."""

    encoder_noise_rad: NonNegative = Field(
        0.5e-4, description="std of white noise on each encoder reading, before quantisation"
    )
    quantise: bool = Field(True, description="round encoder readings to the encoder resolution")
    direction_error_nm: PerJoint = Field(
        [0.0] * N_JOINTS,
        description="direction-dependent torque error per joint (Sec. 2.2.2): "
        "measured = true + error x sign of the joint's last motion",
    )
    velocity_filter_hz: Annotated[float, Field(gt=0)] = Field(
        50.0, description="the drives' velocity estimate: first-order low-pass of the encoder difference"
    )
    direction_play_rad: Annotated[float, Field(gt=0)] = Field(
        5e-3,
        description="joint travel after which the direction-dependent error has fully reversed: a hysteresis "
        "(play operator), so the vibration of a held joint does not flip it but a move does",
    )


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
    seed: int = 0
    gravity_mps2: Annotated[float, Field(gt=0)] = 9.81
    links: Annotated[list[LinkInertial], Field(min_length=N_JOINTS, max_length=N_JOINTS)]
    dummy_arm: DummyArmTruth | None = None
    sensors: SensorTruth = SensorTruth()
    workspace: WorkspaceBox
    drive_train: DriveTrainTruth | None = None
    end_stops: EndStopTruth = EndStopTruth()
    initial_q_deg: PerJoint = Field(
        [-20.25, 82.41, -30.27, 30.0], description="where a dynamic simulation starts, at rest (default: arm hanging)"
    )

    def description(self) -> RobotDescription:
        """The robot description this scenario is an as-built instance of."""
        return load_description(self.robot)

    def static_plant(self, description: RobotDescription | None = None) -> StaticPlant:
        """The static physics of this scenario: as-built links, load and springs."""
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
        return StaticPlant(description.kinematics(), masses, springs, gravity_world_mps2=(0.0, -self.gravity_mps2, 0.0))


SCENARIO_PACKAGE = "hal.sim.scenarios"


def scenario_names() -> list[str]:
    """Names of the scenarios shipped with the package."""
    return sorted(
        p.name[: -len(".yaml")] for p in resources.files(SCENARIO_PACKAGE).iterdir() if p.name.endswith(".yaml")
    )


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a shipped scenario by name (``exo``) or any scenario file by path.

    Raises:
        hal.errors.DescriptionError: unknown name, missing file, or a file that does not match.
    """
    candidate = Path(name_or_path)
    if candidate.suffix in {".yaml", ".yml"} or candidate.exists():
        return load_yaml_model(candidate, Scenario)
    names = scenario_names()
    if str(name_or_path) not in names:
        raise DescriptionError(
            f"unknown scenario {str(name_or_path)!r}; expected one of {', '.join(names)} or a .yaml path"
        )
    with resources.as_file(resources.files(SCENARIO_PACKAGE) / f"{name_or_path}.yaml") as path:
        return load_yaml_model(path, Scenario)
