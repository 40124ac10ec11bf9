"""What a joint position controller is given: the reference it follows and the links it moves.

* :data:`Reference`: a trajectory, ``t_s -> (q_ref (4,) rad, dq_ref (4,) rad/s)``, ``t_s`` counted
  from the sample the controller was reset with. The identification's
  :class:`~daror_runtime.identification.trajectory.ReferenceTrajectory` is one.
* :class:`LinkBounds`: per joint, the range of link inertia and the largest gravity stiffness the
  controller's gains are checked over, before the loop starts
  (:class:`~daror_runtime.control.motor_position.MotorPositionPD` refuses gains that are unstable
  anywhere in that range). :meth:`LinkBounds.from_description` derives them from the robot.

Design time only: nothing here runs in the tick.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from daror_runtime.control.base import ControlSettingError
from daror_runtime.errors import ShapeError
from hal.robot import N_JOINTS, FloatArray, RobotDescription

#: A joint reference: ``t_s -> (q_ref (4,) rad, dq_ref (4,) rad/s)``.
Reference = Callable[[float], tuple[FloatArray, FloatArray]]


@dataclass(frozen=True)
class LinkBounds:
    """Per joint (4,): the range of link inertia about the joint axis (kg m^2) and the largest gravity
    stiffness ``|d g_j / d q_j|`` (Nm/rad) the PD must hold against.

    Raises:
        ShapeError: a field is not a finite vector, or the fields differ in length.
        ControlSettingError: an inertia range with ``min <= 0`` or ``max < min``, or a negative
            gravity stiffness.
    """

    inertia_min_kgm2: FloatArray
    inertia_max_kgm2: FloatArray
    gravity_stiffness_nm_per_rad: FloatArray

    def __post_init__(self) -> None:
        for name in ("inertia_min_kgm2", "inertia_max_kgm2", "gravity_stiffness_nm_per_rad"):
            value = np.array(getattr(self, name), dtype=float, ndmin=1)
            if value.ndim != 1 or not np.all(np.isfinite(value)):
                raise ShapeError(f"{name} must be a finite vector, got {value!r}")
            object.__setattr__(self, name, value)
        if not (self.inertia_min_kgm2.shape == self.inertia_max_kgm2.shape == self.gravity_stiffness_nm_per_rad.shape):
            raise ShapeError("link bounds must have one value per joint in every field")
        if np.any(self.inertia_min_kgm2 <= 0.0) or np.any(self.inertia_max_kgm2 < self.inertia_min_kgm2):
            raise ControlSettingError("link inertias must satisfy 0 < min <= max")
        if np.any(self.gravity_stiffness_nm_per_rad < 0.0):
            raise ControlSettingError("gravity stiffness bounds must not be negative")

    @classmethod
    def from_description(
        cls,
        description: RobotDescription,
        load_in_minimum: float = 0.0,
        radius_of_gyration_m: float = 0.05,
        samples: int = 2000,
        seed: int = 0,
        rotational_factor: float = 2.0,
    ) -> LinkBounds:
        """Bounds from the design masses and centres of mass, over the joint range.

        Minimum: the *effective* inertia ``1 / (M^-1)_jj`` (every other joint free) of the exoskeleton
        links plus ``load_in_minimum`` times the Dummy Arm
        (0: no arm, the lightest the joint can be; 0.5: a pilot with half the Dummy Arm's mass is
        always installed, as in the identification state). The minimum decides the D-gain limit.
        Maximum: the diagonal ``M_jj`` of links plus the Dummy Arm, times
        ``rotational_factor`` for the segments' own inertia and production tolerance the
        description does not hold. A body without an inertia tensor (the description has none) gets
        ``m radius_of_gyration_m^2`` about every axis: 0.05 m is below the 0.06-0.08 m of the simulated
        as-built segments, and without it the effective inertias of point masses are several times
        too small. Gravity stiffness: ``sum m g r`` of everything beyond the joint (links and Dummy
        Arm), an upper bound on ``|d g_j / d q_j|``.

        Raises:
            ControlSettingError: ``load_in_minimum`` outside [0, 1].
        """
        if not 0.0 <= load_in_minimum <= 1.0:
            raise ControlSettingError(f"load_in_minimum must be in [0, 1], got {load_in_minimum}")
        kinematics = description.kinematics()
        rng = np.random.default_rng(seed)
        lo, hi = description.lower_limits_rad, description.upper_limits_rad
        q = lo + (hi - lo) * rng.random((samples, N_JOINTS))
        rotors = kinematics.rotor_rotations(q)
        origins = kinematics.frame_origins(q)
        exo = [(i, link.mass_kg, np.asarray(link.com_m), link.inertia_kgm2) for i, link in enumerate(description.links)]
        arm = description.dummy_arm
        load = [
            (2, arm.upper_arm_mass_kg, np.array([arm.upper_arm_com_m, 0.0, 0.0]), None),
            (3, arm.lower_arm_mass_kg, np.array([arm.lower_arm_com_m, 0.0, 0.0]), None),
        ]

        def mass_matrix(bodies: list) -> tuple[FloatArray, FloatArray]:
            """M(q) (samples, 4, 4) and the gravity lever bound sum m g |z_j x r| (samples, 4)."""
            m_q = np.zeros((samples, N_JOINTS, N_JOINTS))
            lever = np.zeros((samples, N_JOINTS))
            for link, mass, com, inertia in bodies:
                centre = origins[:, link] + np.einsum("nab,b->na", rotors[:, link], com)
                jv = np.zeros((samples, 3, N_JOINTS))
                jw = np.zeros((samples, 3, N_JOINTS))
                for j in range(link + 1):
                    axis = rotors[:, j, :, 2]
                    jw[:, :, j] = axis
                    jv[:, :, j] = np.cross(axis, centre - origins[:, j])
                    lever[:, j] += mass * description.gravity_mps2 * np.linalg.norm(jv[:, :, j], axis=1)
                m_q += mass * np.einsum("nai,naj->nij", jv, jv)
                moments = np.full(3, mass * radius_of_gyration_m**2) if inertia is None else np.asarray(inertia)
                world = np.einsum("nab,b,ncb->nac", rotors[:, link], moments, rotors[:, link])
                m_q += np.einsum("nai,nab,nbj->nij", jw, world, jw)
            return m_q, lever

        light_load = [(link, load_in_minimum * mass, com, inertia) for link, mass, com, inertia in load]
        m_light, _ = mass_matrix(exo + light_load)
        m_heavy, lever = mass_matrix(exo + load)
        # A joint whose neighbours give way (compliant, or saturated) moves only its effective inertia
        # 1 / (M^-1)_jj, 7-10 % of M_jj for the three shoulder joints, whose axes meet at the CoR.
        inertia_min = (1.0 / np.einsum("nii->ni", np.linalg.inv(m_light))).min(axis=0)
        inertia_max = np.einsum("nii->ni", m_heavy).max(axis=0) * rotational_factor
        gravity = lever.max(axis=0)
        return cls(inertia_min, inertia_max, gravity)
