"""A simulated pilot: the person in the sleeve, as an external torque on the links.

A session on the simulated plant needs someone to hold the arm while the robot applies no support
(minimal impedance lets the arm fall otherwise), to move it through its range when the operator
records it, and to relax once the robot compensates. The pilot is a joint-space impedance toward
where the pilot wants the arm, plus the share of the arm's weight the pilot carries::

    tau_pilot = carried x g(q) + K (q_target(t) - q) - D q'

``g(q)`` is the plant's true holding torque (exoskeleton, arm and springs: the simulation's truth,
never seen by a model). ``q_target`` moves with minimum-jerk timing between poses. Used through
:meth:`hal.sim.backend.SimHal.set_external_torque` (it is an ``ExternalTorque``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hal.errors import InputError
from hal.robot import N_JOINTS, FloatArray
from hal.sim import dynamics
from hal.sim.plant import DynamicPlant, joint_vector

#: A calm adult's arm impedance around a held pose (Nm/rad, Nms/rad), joints 1-4.
DEFAULT_STIFFNESS_NM_PER_RAD = (20.0, 20.0, 20.0, 10.0)
DEFAULT_DAMPING_NMS_PER_RAD = (4.0, 4.0, 4.0, 1.5)


@dataclass(frozen=True)
class _Move:
    start_s: float
    duration_s: float
    q_from: FloatArray
    q_to: FloatArray


class SimulatedPilot:
    """The pilot's torque ``f(t_s, q, dq)`` on the links (Nm).

    Args:
        plant: the simulated plant (its true holding torque).
        q_rad: the pose the pilot holds at first.
        carried: share of the arm's weight the pilot carries, in [0, 1] (1: the pilot holds the
            arm alone; 0: relaxed, the robot must carry it).
        stiffness_nm_per_rad, damping_nms_per_rad: the pilot's impedance per joint.
    """

    def __init__(
        self,
        plant: DynamicPlant,
        q_rad: FloatArray,
        carried: float = 1.0,
        stiffness_nm_per_rad: Sequence[float] = DEFAULT_STIFFNESS_NM_PER_RAD,
        damping_nms_per_rad: Sequence[float] = DEFAULT_DAMPING_NMS_PER_RAD,
    ) -> None:
        self._params = plant.params
        self._work = dynamics.new_work()  # the pilot's own scratch: never the plant's
        self._zero = np.zeros(N_JOINTS)
        self._gravity = np.zeros(N_JOINTS)
        self._k_nominal = np.asarray(stiffness_nm_per_rad, dtype=float)
        self._k = self._k_nominal.copy()
        self._d = np.asarray(damping_nms_per_rad, dtype=float)
        if self._k.shape != (N_JOINTS,) or self._d.shape != (N_JOINTS,) or np.any(self._k < 0) or np.any(self._d < 0):
            raise InputError("pilot stiffness and damping need four non-negative values each")
        self._moves: list[_Move] = []
        self._hold = joint_vector(q_rad, "pilot pose").copy()
        self.carried = carried

    @property
    def carried(self) -> float:
        return self._carried

    @carried.setter
    def carried(self, value: float) -> None:
        if not 0.0 <= value <= 1.0:
            raise InputError(f"the share of the arm the pilot carries must be in [0, 1], got {value}")
        self._carried = float(value)

    def set_stiffness_scale(self, scale: float) -> None:
        """Scale the pilot's stiffness (0: limp, the robot moves the arm freely; 1: as constructed)."""
        if not 0.0 <= scale <= 2.0:
            raise InputError(f"pilot stiffness scale must be in [0, 2], got {scale}")
        self._k = self._k_nominal * scale

    def target(self, t_s: float) -> FloatArray:
        """Where the pilot wants the arm at ``t_s`` (4,), rad."""
        while self._moves and t_s >= self._moves[0].start_s + self._moves[0].duration_s:
            self._hold = self._moves.pop(0).q_to
        if not self._moves or t_s < self._moves[0].start_s:
            return self._hold
        move = self._moves[0]
        s = (t_s - move.start_s) / move.duration_s
        shape = s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
        return move.q_from + (move.q_to - move.q_from) * shape

    def move_to(self, q_rad: FloatArray, start_s: float, duration_s: float) -> float:
        """Move (minimum jerk) to ``q_rad`` from ``start_s`` (after the moves already planned); returns the end time."""
        if not duration_s > 0.0:
            raise InputError(f"a pilot's move needs a positive duration, got {duration_s}")
        q_to = joint_vector(q_rad, "pilot pose").copy()
        if self._moves:
            last = self._moves[-1]
            start_s = max(start_s, last.start_s + last.duration_s)
            q_from = last.q_to
        else:
            q_from = self._hold
        self._moves.append(_Move(start_s, duration_s, q_from, q_to))
        return start_s + duration_s

    def sweep(self, poses_rad: Sequence[FloatArray], start_s: float, seconds_per_move: float) -> float:
        """Visit ``poses_rad`` in order (e.g. to show the operator the range of motion); returns the end time."""
        end = start_s
        for pose in poses_rad:
            end = self.move_to(pose, end, seconds_per_move)
        return end

    @property
    def moving(self) -> bool:
        return bool(self._moves)

    def __call__(self, t_s: float, q_rad: FloatArray, dq_rad_s: FloatArray) -> FloatArray:
        torque = self._k * (self.target(t_s) - q_rad) - self._d * dq_rad_s
        if self._carried > 0.0:  # g(q) straight from the plant's compiled kernel: q comes from the plant itself
            dynamics.bias_torque(q_rad, self._zero, self._params, self._work, self._gravity)
            torque += self._carried * self._gravity
        return torque
