"""A simulated pilot: the person in the sleeve, as an external torque on the links.

A session on the simulated plant needs someone to hold the arm while the robot applies no support
(minimal impedance lets the arm fall otherwise), to move it through its range when the operator
records it, and to relax once the robot compensates. The pilot is a joint-space impedance toward
where the pilot wants the arm, plus the share of the arm's weight the pilot carries *of what the
robot does not carry*::

    tau_pilot = carried x (g(q) - s) + K (q_target(t) - q) - D q'

``g(q)`` is the plant's true holding torque (exoskeleton, arm and springs: the simulation's truth,
never seen by a model). ``s`` is the support the pilot feels: the robot's spring torque, low-passed
with the time a person needs to notice and adapt to a load (``adaptation_s``, 0.3 s), and counted
per joint only between zero and the full ``g`` (support beyond the arm's weight is a push, which
the impedance answers). A person does not keep lifting the weight a robot has taken over: when the
robot supports the arm fully, a pilot "carrying" it carries nothing, and relaxing changes nothing.
(The first version carried ``carried x g(q)`` whatever the robot did; under compensation it lifted
the arm 20 degrees against its own stiffness, and "relaxing" then let that stiffness fling the
elbow back at 2.2 rad/s: a person would not do that. docs/decisions.md D50.)

``q_target`` moves with minimum-jerk timing between poses. A new motion replaces the one under
way, from where the pilot's target is at that moment (so the target never jumps); :meth:`stop`
keeps the target where it is. Used through :meth:`hal.sim.backend.SimHal.set_external_torque`
(it is an ``ExternalTorque``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hal.errors import InputError, ShapeError
from hal.robot import N_JOINTS, FloatArray
from hal.sim import dynamics
from hal.sim.plant import DynamicPlant, joint_vector

#: A calm adult's arm impedance around a held pose (Nm/rad, Nms/rad), joints 1-4.
DEFAULT_STIFFNESS_NM_PER_RAD = (20.0, 20.0, 20.0, 10.0)
DEFAULT_DAMPING_NMS_PER_RAD = (4.0, 4.0, 4.0, 1.5)
#: How long a person takes to notice a change of support and adapt the effort to it (s).
DEFAULT_ADAPTATION_S = 0.3
#: The peak joint speed of the pilot's own moves when no duration is given (rad/s): a third of the
#: slowest limit of a state where the pilot moves the arm (1.5 rad/s in rom_limits and
#: safety_experience) and half of the 1.0 rad/s of safety_check and pilot_installation.
DEFAULT_PEAK_SPEED_RAD_S = 0.5
#: Minimum-jerk motion: peak speed = MIN_JERK_PEAK x distance / duration.
MIN_JERK_PEAK = 1.875
#: The shortest move (s) the pilot makes when the duration follows from the distance.
MIN_MOVE_S = 1.0


@dataclass(frozen=True)
class _Move:
    start_s: float
    duration_s: float
    q_from: FloatArray
    q_to: FloatArray

    def shape(self, t_s: float) -> float:
        """The share (0-1) of the way from ``q_from`` to ``q_to`` at ``t_s`` (s), minimum-jerk timing."""
        s = (t_s - self.start_s) / self.duration_s
        return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def move_duration_s(q_from: FloatArray, q_to: FloatArray, peak_speed_rad_s: float) -> float:
    """The duration (s) of a minimum-jerk move whose fastest joint peaks at ``peak_speed_rad_s``."""
    distance = float(np.max(np.abs(np.asarray(q_to) - np.asarray(q_from))))
    return max(MIN_MOVE_S, MIN_JERK_PEAK * distance / peak_speed_rad_s)


class SimulatedPilot:
    """The pilot's torque ``f(t_s, q, dq)`` on the links (Nm).

    Args:
        plant: the simulated plant (its true holding torque and spring torque).
        q_rad: the pose the pilot holds at first.
        carried: share, in [0, 1], of the arm's weight the robot does not carry that the pilot
            carries (1: the pilot holds the arm alone when the robot does not; 0: relaxed).
        stiffness_nm_per_rad, damping_nms_per_rad: the pilot's impedance per joint.
        adaptation_s: time constant of the support the pilot feels (s).

    Raises:
        InputError: a share outside [0, 1], negative impedances, or a non-positive adaptation time.

    The torque is computed in one compiled kernel (:func:`hal.sim.dynamics.pilot_torque`), the
    same operations in the same order as numpy on arrays, so bit for bit what the formula gives
    with numpy; the simulated HAL calls it through :meth:`torque_into` every tick.
    """

    def __init__(
        self,
        plant: DynamicPlant,
        q_rad: FloatArray,
        carried: float = 1.0,
        stiffness_nm_per_rad: Sequence[float] = DEFAULT_STIFFNESS_NM_PER_RAD,
        damping_nms_per_rad: Sequence[float] = DEFAULT_DAMPING_NMS_PER_RAD,
        adaptation_s: float = DEFAULT_ADAPTATION_S,
    ) -> None:
        # The plant's own arrays (DynamicPlant never replaces them): its state for the spring
        # torque, its parameters for the spring constants and g(q).
        self._state = plant.state
        self._params = plant.params
        self._work = dynamics.new_work()  # the pilot's own scratch: never the plant's
        self._k_nominal = np.asarray(stiffness_nm_per_rad, dtype=float)
        damping = np.asarray(damping_nms_per_rad, dtype=float)
        if (
            self._k_nominal.shape != (N_JOINTS,)
            or damping.shape != (N_JOINTS,)
            or np.any(self._k_nominal < 0)
            or np.any(damping < 0)
        ):
            raise InputError("pilot stiffness and damping need four non-negative values each")
        if not (math.isfinite(adaptation_s) and adaptation_s > 0.0):
            raise InputError(f"the pilot's adaptation time must be a positive number of seconds, got {adaptation_s}")
        self._adaptation_s = adaptation_s
        # Impedance, felt support (zero: a session starts with the drives off, the pilot holds the
        # arm) and scratch in one array (dynamics.PILOT_*): each array argument of a kernel call costs.
        self._vector = np.zeros(dynamics.PILOT_VECTOR_SIZE)
        self._vector[dynamics.PILOT_STIFFNESS : dynamics.PILOT_STIFFNESS + N_JOINTS] = self._k_nominal
        self._vector[dynamics.PILOT_DAMPING : dynamics.PILOT_DAMPING + N_JOINTS] = damping
        self._kernel = dynamics.pilot_torque_entry()
        self._discarded = np.empty(N_JOINTS)  # the kernel's out when the caller wants the torque whatever it is
        self._last_t_s: float | None = None
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
        self._vector[dynamics.PILOT_STIFFNESS : dynamics.PILOT_STIFFNESS + N_JOINTS] = self._k_nominal * scale

    def _move_at(self, t_s: float) -> _Move | None:
        """The move under way at ``t_s`` (s), None while the pilot holds ``_hold``; finished moves are dropped."""
        moves = self._moves
        while moves and t_s >= moves[0].start_s + moves[0].duration_s:
            self._hold = moves.pop(0).q_to
        if not moves or t_s < moves[0].start_s:
            return None
        return moves[0]

    def target(self, t_s: float) -> FloatArray:
        """Where the pilot wants the arm at ``t_s`` (4,), rad."""
        move = self._move_at(t_s)
        if move is None:
            return self._hold
        return move.q_from + (move.q_to - move.q_from) * move.shape(t_s)

    def stop(self, t_s: float) -> None:
        """Stop where the target is at ``t_s``: every planned move is dropped."""
        self._hold = np.array(self.target(t_s), dtype=float)
        self._moves.clear()

    def hold(self, q_rad: FloatArray) -> None:
        """Want the arm at ``q_rad`` from now on (e.g. where it is): every planned move is dropped."""
        self._hold = joint_vector(q_rad, "pilot pose").copy()
        self._moves.clear()

    def move_to(self, q_rad: FloatArray, start_s: float, duration_s: float | None = None) -> float:
        """Replace whatever motion is planned by one move to ``q_rad`` from ``start_s``; returns the end time.

        ``duration_s`` None: as long as a peak speed of :data:`DEFAULT_PEAK_SPEED_RAD_S` needs.

        Raises:
            InputError: a duration that is not positive.
        """
        return self.sweep([q_rad], start_s, duration_s)

    def sweep(self, poses_rad: Sequence[FloatArray], start_s: float, seconds_per_move: float | None = None) -> float:
        """Replace whatever motion is planned by visits to ``poses_rad`` in order; returns the end time.

        ``seconds_per_move`` None: each move as long as a peak speed of
        :data:`DEFAULT_PEAK_SPEED_RAD_S` needs (at least :data:`MIN_MOVE_S`).

        Raises:
            InputError: a duration that is not positive, or a pose that is not four finite angles.
        """
        if seconds_per_move is not None and not (math.isfinite(seconds_per_move) and seconds_per_move > 0.0):
            raise InputError(f"a pilot's move needs a positive duration, got {seconds_per_move}")
        q_from = np.array(self.target(start_s), dtype=float)
        moves = []
        t = start_s
        for pose in poses_rad:
            q_to = joint_vector(pose, "pilot pose").copy()
            duration = (
                seconds_per_move
                if seconds_per_move is not None
                else move_duration_s(q_from, q_to, DEFAULT_PEAK_SPEED_RAD_S)
            )
            moves.append(_Move(t, duration, q_from, q_to))
            q_from, t = q_to, t + duration
        self._hold = np.array(self.target(start_s), dtype=float)
        self._moves = moves
        return t

    @property
    def moving(self) -> bool:
        return bool(self._moves)

    @property
    def torque_nm(self) -> FloatArray:
        """The torque of the last evaluation (4,), Nm, finite or not (a copy)."""
        return self._vector[dynamics.PILOT_TORQUE : dynamics.PILOT_TORQUE + N_JOINTS].copy()

    def __call__(self, t_s: float, q_rad: FloatArray, dq_rad_s: FloatArray) -> FloatArray:
        """The pilot's torque (4,), Nm, at plant time ``t_s`` (s) and link state ``q_rad``, ``dq_rad_s``.

        A new array, finite or not (the caller checks). The felt support follows the plant's spring
        torque now, with the adaptation lag over the time since the previous evaluation.

        Raises:
            ShapeError: ``q_rad`` or ``dq_rad_s`` is not of shape (4,).
        """
        q = np.asarray(q_rad, dtype=np.float64)
        dq = np.asarray(dq_rad_s, dtype=np.float64)
        if q.shape != (N_JOINTS,) or dq.shape != (N_JOINTS,):
            raise ShapeError(f"the pilot needs q and dq of shape ({N_JOINTS},), got {q.shape} and {dq.shape}")
        self.torque_into(t_s, q, dq, self._discarded)
        return self.torque_nm

    def torque_into(self, t_s: float, q_rad: FloatArray, dq_rad_s: FloatArray, out: FloatArray) -> bool:
        """The pilot's torque (Nm) at ``t_s`` (s) and ``q_rad``, ``dq_rad_s`` into ``out``; False if not finite.

        What :meth:`__call__` computes, without allocating: the simulated HAL's tick passes views
        of the plant's state and its drive vector. A torque with a non-finite element is not
        written (``out`` keeps what it held; :attr:`torque_nm` has it).

        The types are not checked (the compiled entry point reads the arrays as such): ``q_rad``
        and ``dq_rad_s`` float64 arrays of shape (4,), ``out`` a writable C-contiguous float64
        array of shape (4,).
        """
        move = self._move_at(t_s)
        if move is None:
            q_from = q_to = self._hold
            moving, shape = False, 0.0
        else:
            q_from, q_to = move.q_from, move.q_to
            moving, shape = True, move.shape(t_s)
        dt = 0.0 if self._last_t_s is None else max(t_s - self._last_t_s, 0.0)
        self._last_t_s = t_s
        # The support the pilot feels follows the springs' torque with the adaptation lag (only
        # when time moved on). g(q) comes from the plant's compiled bias_torque inside the kernel;
        # support counts there between 0 and the full weight, per joint: beyond it the robot pushes.
        adapt = dt > 0.0
        alpha = 1.0 - math.exp(-dt / self._adaptation_s) if adapt else 0.0
        return self._kernel(
            q_rad, dq_rad_s, self._state, self._params, self._work, self._vector,
            q_from, q_to, moving, shape, adapt, alpha, self._carried, out,
        )  # fmt: skip
