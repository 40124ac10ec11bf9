"""Static physics of the simulated plant: potential energy and holding torque.

This is the simulator's own code path (docs/architecture.md, "Three implementations of gravity"): gravity comes from the world
positions of point masses and their geometric Jacobians, never from the PLF regressor of the
modelling code. A test checks that the two agree on noise-free data (thesis Sec. 3.4 / 4.4.2).

Sign convention: the *holding torque* is the torque the actuators must deliver to keep the
robot still, ``tau = dV/dq`` (Eq. 3.14). At a stationary point it is what the SEA springs carry.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from hal.errors import DescriptionError
from hal.robot import N_JOINTS, FloatArray, Kinematics, as_configurations


@dataclass(frozen=True)
class PointMass:
    """A mass rigidly attached to rotor frame ``joint`` (1-4), its CoM in that frame (m)."""

    joint: int
    mass_kg: float
    com_m: tuple[float, float, float]
    label: str = ""


@dataclass(frozen=True)
class PullSpring:
    """A spring across one joint that can only pull (like a muscle or an extension spring).

    ``resists="flexion"``: it is stretched, and pulls back, when the joint is above
    ``slack_angle_rad``; ``resists="extension"``: when the joint is below it. Two pre-tensioned
    springs whose slack angles lie outside the range of motion act together as one linear spring.
    """

    joint: int
    stiffness_nm_per_rad: float
    slack_angle_rad: float
    resists: Literal["flexion", "extension"]

    def stretch_rad(self, q_joint: FloatArray) -> FloatArray:
        if self.resists == "flexion":
            return np.maximum(0.0, q_joint - self.slack_angle_rad)
        return np.maximum(0.0, self.slack_angle_rad - q_joint)

    def energy_j(self, q_joint: FloatArray) -> FloatArray:
        return 0.5 * self.stiffness_nm_per_rad * self.stretch_rad(q_joint) ** 2

    def holding_torque_nm(self, q_joint: FloatArray) -> FloatArray:
        sign = 1.0 if self.resists == "flexion" else -1.0
        return sign * self.stiffness_nm_per_rad * self.stretch_rad(q_joint)


class StaticPlant:
    """Potential energy and holding torque of point masses and springs on the DAROR-01 chain."""

    def __init__(
        self,
        kinematics: Kinematics,
        masses: Sequence[PointMass],
        springs: Sequence[PullSpring] = (),
        gravity_world_mps2: Sequence[float] = (0.0, -9.81, 0.0),
    ) -> None:
        self.kinematics = kinematics
        self.masses = tuple(masses)
        self.springs = tuple(springs)
        self.gravity_world_mps2 = np.asarray(gravity_world_mps2, dtype=float)
        for m in self.masses:
            if not 1 <= m.joint <= N_JOINTS:
                raise DescriptionError(f"point mass {m.label!r} on joint {m.joint}; joints are 1-{N_JOINTS}")
        self._mass_kg = np.array([m.mass_kg for m in self.masses])
        self._com_local = np.array([m.com_m for m in self.masses]).reshape(-1, 3)
        self._frame = np.array([m.joint - 1 for m in self.masses], dtype=int)

    def com_positions_m(self, q: FloatArray) -> FloatArray:
        """World position of every point mass; shape (N, M, 3)."""
        q = as_configurations(q)
        rotors = self.kinematics.rotor_rotations(q)[:, self._frame]  # (N, M, 3, 3)
        origins = self.kinematics.frame_origins(q)[:, self._frame]  # (N, M, 3)
        return origins + np.einsum("nmij,mj->nmi", rotors, self._com_local)

    def potential_energy_j(self, q: FloatArray) -> FloatArray:
        """Gravitational plus spring potential energy; shape (N,)."""
        q = as_configurations(q)
        heights = self.com_positions_m(q) @ -self.gravity_world_mps2  # g . p with g pointing down
        energy = heights @ self._mass_kg
        for spring in self.springs:
            energy = energy + spring.energy_j(q[:, spring.joint - 1])
        return energy

    def gravity_torque_nm(self, q: FloatArray) -> FloatArray:
        """Holding torque against gravity from CoM Jacobians; shape (N, 4).

        Column ``j`` of the Jacobian of a mass on link ``i >= j`` is ``z_j x (p - o_j)``.
        """
        q = as_configurations(q)
        p = self.com_positions_m(q)  # (N, M, 3)
        axes = self.kinematics.joint_axes(q)  # (N, 4, 3)
        axis_points = self.kinematics.frame_origins(q)  # (N, 4, 3), on each joint's axis
        torque = np.zeros((q.shape[0], N_JOINTS))
        weight = -self._mass_kg[None, :, None] * self.gravity_world_mps2  # force to hold, (1, M, 3)
        for j in range(N_JOINTS):
            moved = self._frame >= j
            if not np.any(moved):
                continue
            lever = p[:, moved] - axis_points[:, j, None, :]
            column = np.cross(axes[:, j, None, :], lever)  # dp/dq_j, (N, Mj, 3)
            torque[:, j] = np.einsum("nmk,mk->n", column, weight[0, moved])
        return torque

    def spring_torque_nm(self, q: FloatArray) -> FloatArray:
        """Holding torque against the springs; shape (N, 4)."""
        q = as_configurations(q)
        torque = np.zeros_like(q)
        for spring in self.springs:
            torque[:, spring.joint - 1] += spring.holding_torque_nm(q[:, spring.joint - 1])
        return torque

    def holding_torque_nm(self, q: FloatArray) -> FloatArray:
        """Total torque the actuators must deliver to hold ``q`` still; shape (N, 4)."""
        return self.gravity_torque_nm(q) + self.spring_torque_nm(q)
