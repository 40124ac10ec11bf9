"""The DAROR-01 robot description and its forward kinematics (thesis Sec. 2.1, Eq. 2.1-2.15).

Frames: the world frame ``Psi_0`` sits in the shoulder's centre of rotation (CoR) with a vertical
``y`` axis pointing up. Every actuator turns about its own ``z`` axis. Stator 1 is fixed in the
world (Eq. 2.1-2.9); stators 2 and 3 are rotated ``Ry(60 deg)`` from the previous rotor
(Eq. 2.14); stator 4 is parallel to rotor 3, translated by ``delta`` along the upper arm
(Eq. 2.15). Joints are numbered 1-4 in everything a person reads and indexed 0-3 in arrays.

All angles in radians, lengths in metres, masses in kilograms, unless a name says ``_deg``.
"""

from __future__ import annotations

from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from hal.errors import ShapeError
from hal.yamlfile import Number, load_yaml_model

N_JOINTS = 4

FloatArray = NDArray[np.float64]
Vec3 = Annotated[tuple[Number, Number, Number], Field(description="x, y, z in metres")]
PositiveFloat = Annotated[Number, Field(gt=0)]
Inertia = Annotated[tuple[Number, Number, Number], Field(description="Ixx, Iyy, Izz about the CoM")]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class BaseRotation(_Strict):
    """Orientation of stator 1 in the world frame, Eq. 2.1-2.9."""

    about_x_deg: Number = Field(-30.0, description="R_a = Rx(.): AoR of R1 tilted backwards (Eq. 2.1)")
    about_z_deg: Number = Field(-10.0, description="R_b = Rz(.): tilted towards the head (Eq. 2.2)")
    own_z_deg: Number = Field(-45.0, description="final rotation about the stator's own z (Eq. 2.9)")


class Geometry(_Strict):
    """The constant transforms of the kinematic chain."""

    base_rotation: BaseRotation = BaseRotation()
    inter_axis_deg: Number = Field(60.0, description="Ry angle from rotor 1 to stator 2 and rotor 2 to stator 3")
    elbow_offset_m: Vec3 = Field((0.275, 0.0, 0.0), description="delta: rotor 3 to stator 4 (Eq. 2.15)")


class LinkInertial(_Strict):
    """Mass and centre of mass of one link, the CoM expressed in the link's rotor frame.

    ``inertia_kgm2``: principal moments of inertia about the CoM along the rotor frame's axes;
    only the dynamic simulation needs them (statics and the models do not).
    """

    mass_kg: PositiveFloat
    com_m: Vec3
    inertia_kgm2: Inertia | None = None


class SeaConstants(_Strict):
    """Series elastic actuator constants (Sec. 2.2.1) and the nominal drive-train model.

    The nominal values are what the controllers are designed for (the DOB's nominal model
    ``H_n``); the simulated plant's as-built values come from the scenario.
    """

    spring_stiffness_nm_per_rad: PositiveFloat = 289.0
    encoder_resolution_rad: PositiveFloat = 1e-4
    gearbox_inertia_kgm2: PositiveFloat = Field(
        0.25, description="motor and gearbox inertia seen at the gearbox output"
    )
    gearbox_viscous_nms_per_rad: Annotated[Number, Field(ge=0)] = 1.0
    max_motor_torque_nm: PositiveFloat = Field(40.0, description="motor torque saturation at the gearbox output")
    max_spring_deflection_rad: PositiveFloat = Field(0.12, description="mechanical end stop of the spring")

    @property
    def torque_resolution_nm(self) -> float:
        """Smallest torque step one spring-deflection count resolves."""
        return self.spring_stiffness_nm_per_rad * self.encoder_resolution_rad


class AngleRange(_Strict):
    """A closed angle interval in degrees (human-edited), exposed in radians."""

    lower_deg: Number
    upper_deg: Number

    @model_validator(mode="after")
    def _ordered(self) -> AngleRange:
        if not self.lower_deg < self.upper_deg:
            raise ValueError(f"lower_deg ({self.lower_deg}) must be below upper_deg ({self.upper_deg})")
        return self

    @property
    def lower_rad(self) -> float:
        return float(np.deg2rad(self.lower_deg))

    @property
    def upper_rad(self) -> float:
        return float(np.deg2rad(self.upper_deg))


#: A joint's range of motion.
JointRange = AngleRange


class DeviceLimits(_Strict):
    """Limits of the device itself, per joint (the safety monitor's outermost envelope)."""

    max_velocity_rad_s: Annotated[list[PositiveFloat], Field(min_length=N_JOINTS, max_length=N_JOINTS)] = [
        2.0,
        2.0,
        2.0,
        3.0,
    ]
    max_spring_torque_nm: Annotated[list[PositiveFloat], Field(min_length=N_JOINTS, max_length=N_JOINTS)] = [
        30.0,
        30.0,
        30.0,
        20.0,
    ]


class DummyArm(_Strict):
    """The Dummy Arm of Sec. 4.4.3 as the thesis describes it (design values)."""

    upper_arm_mass_kg: PositiveFloat = 1.710
    upper_arm_com_m: PositiveFloat = Field(0.136, description="from the shoulder CoR along rotor-3 x")
    lower_arm_mass_kg: PositiveFloat = 1.053
    lower_arm_com_m: PositiveFloat = Field(0.109, description="from the elbow along rotor-4 x")
    elbow_offset_m: PositiveFloat = Field(0.275, description="CoR to elbow joint")
    elbow_spring_stiffness_nm_per_rad: PositiveFloat = Field(2.84, description="each of the two springs")


class ElbowStiffnessPrior(_Strict):
    """First-order elbow stiffness of the A Priori model, Eq. 4.7 (from S. Filius)."""

    mu0_nm: Number = 1.3
    mu1_nm_per_rad: Number = 1.14


#: The longest delay a safe stop 1 relay may be set to (s): a controlled stop longer than this is no
#: longer an emergency stop (IEC 60204-1 leaves the value to the risk assessment; docs/safety.md).
MAX_RELAY_DELAY_S = 30.0


class EstopWiring(_Strict):
    """How the two e-stop buttons act on the drives (docs/safety.md, "E-stop wiring").

    * ``sto``: both buttons cut the drives' power stages (safe torque off) at once, whatever the
      software does: a category 0 stop in hardware; the runtime only reads which was pressed.
    * ``ss1``: safe stop 1. A press tells the runtime at once (the drives' input bits) and starts a
      safety relay that cuts the power stages ``relay_delay_s`` later, whatever the runtime does,
      unless the button is released before; the runtime has that long for a controlled stop
      (category 1).
    """

    wiring: Literal["sto", "ss1"] = "sto"
    relay_delay_s: Annotated[Number, Field(gt=0.0, le=MAX_RELAY_DELAY_S)] | None = Field(
        None, description="ss1 only: the relay cuts the drives' power this long after a press, s"
    )

    @model_validator(mode="after")
    def _delay_with_ss1_only(self) -> EstopWiring:
        if self.wiring == "ss1" and self.relay_delay_s is None:
            raise ValueError("an ss1 wiring needs relay_delay_s: how long after a press the relay cuts the power")
        if self.wiring == "sto" and self.relay_delay_s is not None:
            raise ValueError("relay_delay_s belongs to an ss1 wiring; with sto the buttons cut the power at once")
        return self


class RobotDescription(_Strict):
    """Everything the software knows about the robot before it has measured anything."""

    name: str = "DAROR-01"
    gravity_mps2: PositiveFloat = 9.81
    geometry: Geometry = Geometry()
    links: Annotated[list[LinkInertial], Field(min_length=N_JOINTS, max_length=N_JOINTS)]
    sea: SeaConstants = SeaConstants()
    joint_limits: Annotated[list[JointRange], Field(min_length=N_JOINTS, max_length=N_JOINTS)]
    limits: DeviceLimits = DeviceLimits()
    dummy_arm: DummyArm = DummyArm()
    ap_elbow_stiffness: ElbowStiffnessPrior = ElbowStiffnessPrior()
    estop: EstopWiring = EstopWiring()

    @property
    def lower_limits_rad(self) -> FloatArray:
        return np.array([r.lower_rad for r in self.joint_limits])

    @property
    def upper_limits_rad(self) -> FloatArray:
        return np.array([r.upper_rad for r in self.joint_limits])

    def kinematics(self) -> Kinematics:
        """The forward kinematics of this robot's geometry (:class:`Kinematics`).

        Built once a process per geometry and shared by every caller (a description is frozen; a
        chain is ~0.3 ms to build and some commands ask thousands of times): callers must not change
        the instance or its arrays (:meth:`Kinematics.with_base_rotation` returns a new one). The
        key is the geometry's JSON, every number to the bit (``-0.0`` is not ``0.0``).
        """
        key = self.geometry.model_dump_json()
        kinematics = _KINEMATICS_BY_GEOMETRY.get(key)
        if kinematics is None:
            if len(_KINEMATICS_BY_GEOMETRY) >= _KINEMATICS_CACHE_SIZE:
                _KINEMATICS_BY_GEOMETRY.clear()  # bounded: generated geometries (tests) do not pile up
            kinematics = _KINEMATICS_BY_GEOMETRY[key] = Kinematics(self.geometry)
        return kinematics


#: Geometries whose chain :meth:`RobotDescription.kinematics` keeps at most (then starts afresh).
_KINEMATICS_CACHE_SIZE = 64
#: The shared chains, by the geometry's JSON (exact: JSON numbers are the shortest round-trip repr).
_KINEMATICS_BY_GEOMETRY: dict[str, Kinematics] = {}


DEFAULT_DESCRIPTION_FILE = "daror01.yaml"


def load_description(path: Path | str | None = None) -> RobotDescription:
    """Load a robot description; ``None`` loads the packaged ``hal/daror01.yaml``.

    Raises:
        hal.errors.DescriptionError: the file is missing or does not match the schema.
    """
    if path is None:
        with resources.as_file(resources.files("hal") / DEFAULT_DESCRIPTION_FILE) as packaged:
            return load_yaml_model(packaged, RobotDescription)
    return load_yaml_model(path, RobotDescription)


# --- rotations -------------------------------------------------------------------------------


def rot_x(angle_rad: float | FloatArray) -> FloatArray:
    """Rotation about x; shape ``(..., 3, 3)`` for an angle array of shape ``(...)``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(angle_rad: float | FloatArray) -> FloatArray:
    """Rotation about y; shape ``(..., 3, 3)``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(angle_rad: float | FloatArray) -> FloatArray:
    """Rotation about z; shape ``(..., 3, 3)``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def base_stator_rotation(base: BaseRotation) -> FloatArray:
    """``0R_{1,s}`` of Eq. 2.1-2.9, built literally as the thesis writes it."""
    r_a = rot_x(np.deg2rad(base.about_x_deg))
    r_b = rot_z(np.deg2rad(base.about_z_deg))
    e_x, e_z = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    v1 = -np.cross(e_x @ r_b, e_z @ r_a)  # Eq. 2.3 (row vectors times matrices)
    v1 /= np.linalg.norm(v1)  # Eq. 2.4
    v2 = np.cross(v1, e_z)  # Eq. 2.5
    v2 /= np.linalg.norm(v2)  # Eq. 2.6
    v3 = np.cross(v2, v1)  # Eq. 2.7
    r_bar = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])  # Eq. 2.8
    return np.column_stack([v2, v1, v3]) @ r_bar @ rot_z(np.deg2rad(base.own_z_deg))  # Eq. 2.9


class Kinematics:
    """Forward kinematics of the chain, vectorised over ``N`` configurations ``q`` of shape (N, 4)."""

    def __init__(self, geometry: Geometry) -> None:
        self.geometry = geometry
        self.base_rotation = base_stator_rotation(geometry.base_rotation)
        self.inter_rotation = rot_y(np.deg2rad(geometry.inter_axis_deg))
        self.elbow_offset_m = np.asarray(geometry.elbow_offset_m, dtype=float)

    def with_base_rotation(self, base_rotation: FloatArray) -> Kinematics:
        """A copy of this chain whose stator 1 has the world orientation ``base_rotation``.

        For the simulator's as-built truth (a base mounted tilted, ``hal.sim.scenario``); the
        geometry record keeps the nominal angles, only ``base_rotation`` differs.

        Args:
            base_rotation: (3, 3) proper rotation matrix, ``0R_{1,s}``.

        Raises:
            ShapeError: ``base_rotation`` is not (3, 3), or not a proper rotation (orthonormal
                to 1e-9, determinant +1).
        """
        rotation = np.array(base_rotation, dtype=float)
        if rotation.shape != (3, 3):
            raise ShapeError(f"base_rotation: expected shape (3, 3), got {rotation.shape}")
        if not (np.allclose(rotation @ rotation.T, np.eye(3), rtol=0.0, atol=1e-9) and np.linalg.det(rotation) > 0):
            raise ShapeError("base_rotation: not a proper rotation matrix (orthonormal, determinant +1)")
        # A fresh instance, not a mutated copy: stator_offsets is a cached_property that would
        # otherwise keep the old base rotation.
        tilted = Kinematics(self.geometry)
        tilted.base_rotation = rotation
        return tilted

    @cached_property
    def stator_offsets(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Constant rotation from the previous rotor (world for joint 1) to each stator."""
        return (self.base_rotation, self.inter_rotation, self.inter_rotation, np.eye(3))

    def rotor_rotations_component_major(self, q: FloatArray) -> FloatArray:
        """World orientation ``0R_{i,r}`` of every rotor, laid out (4, 3, 3, N).

        Element ``[i, a, b]`` is a contiguous length-N vector, which keeps the chain products
        element-wise and fast for large N (the regressor of 25,000 points is built in ms).
        """
        q = as_configurations(q)
        n = q.shape[0]
        q_t = np.ascontiguousarray(q.T)  # (4, N): each joint a contiguous vector
        c, s = np.cos(q_t), np.sin(q_t)
        out = np.empty((N_JOINTS, 3, 3, n))
        stator = np.empty((3, 3, n))
        scratch = np.empty((3, n))
        # In-place products: this runs on 25,000 configurations per fit, temporaries would dominate.
        for i, offset in enumerate(self.stator_offsets):
            if i == 0:
                stator[:] = offset[:, :, None]
            else:  # stator = previous rotor @ constant offset, skipping the offset's zeros
                prev = out[i - 1]
                for k in range(3):
                    np.multiply(prev[:, 0], offset[0, k], out=stator[:, k])
                    for m in (1, 2):
                        if offset[m, k] != 0.0:
                            np.multiply(prev[:, m], offset[m, k], out=scratch)
                            stator[:, k] += scratch
            # rotor = stator @ Rz(q_i)
            np.multiply(stator[:, 0], c[i], out=out[i, :, 0])
            np.multiply(stator[:, 1], s[i], out=scratch)
            out[i, :, 0] += scratch
            np.multiply(stator[:, 1], c[i], out=out[i, :, 1])
            np.multiply(stator[:, 0], s[i], out=scratch)
            out[i, :, 1] -= scratch
            out[i, :, 2] = stator[:, 2]
        return out

    def rotor_rotations(self, q: FloatArray) -> FloatArray:
        """World orientation ``0R_{i,r}`` of every rotor frame; shape (N, 4, 3, 3)."""
        return np.moveaxis(self.rotor_rotations_component_major(q), -1, 0)

    def frame_origins(self, q: FloatArray) -> FloatArray:
        """World position of every rotor frame origin; shape (N, 4, 3).

        Frames 1-3 sit in the shoulder CoR; frame 4 (the elbow) sits at ``0R_{3,r} delta``.
        """
        rotors = self.rotor_rotations(q)
        origins = np.zeros((*rotors.shape[:2], 3))
        origins[:, 3] = rotors[:, 2] @ self.elbow_offset_m
        return origins

    def joint_axes(self, q: FloatArray) -> FloatArray:
        """World direction of every joint's axis of rotation (rotor z); shape (N, 4, 3)."""
        return self.rotor_rotations(q)[..., :, 2]

    def point_in_world(self, q: FloatArray, joint: int, point_m: FloatArray) -> FloatArray:
        """World position of a point fixed in rotor frame ``joint`` (1-4); shape (N, 3)."""
        rotors = self.rotor_rotations(q)
        origins = self.frame_origins(q)
        return origins[:, joint - 1] + rotors[:, joint - 1] @ np.asarray(point_m, dtype=float)


def as_configurations(q: FloatArray) -> FloatArray:
    """View ``q`` as (N, 4) float configurations; a single (4,) configuration becomes (1, 4)."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != N_JOINTS:
        raise ShapeError(f"expected joint angles of shape (N, {N_JOINTS}), got {q.shape}")
    return q
