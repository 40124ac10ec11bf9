"""The world around the simulated plant: the pilot, the e-stop buttons, faults to inject.

On hardware these are people and physics; on :class:`~hal.sim.backend.SimHal` this class plays
them, so a session script can be a complete rehearsal: the pilot presses the e-stop, moves the arm
through its range while the operator records it, and relaxes once the robot compensates. It is
the :class:`hal.capabilities.SimulatedWorld` of ``SimHal.world``; the console reaches it only
through that protocol.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from hal.capabilities import PLANT_FAULT_KINDS
from hal.errors import HalError
from hal.isb import Shoulder
from hal.robot import FloatArray
from hal.sim.pilot import SimulatedPilot

if TYPE_CHECKING:
    from hal.sim.backend import SimHal

__all__ = ["PlantWorld"]

#: The simulated pilot's ratings (issue 29's blind comparison): 9 with no effort of his own, one
#: point less per 0.5 Nm of mean effort (summed over the joints), a person's scatter of half a point.
RATING_AT_NO_EFFORT = 9.0
RATING_PER_NM = 2.0
RATING_NOISE = 0.5


class PlantWorld:
    """The :class:`~hal.capabilities.SimulatedWorld` around one :class:`~hal.sim.backend.SimHal`.

    Args:
        hal: the simulated backend (open or not; the pilot is seated once it is open).
    """

    def __init__(self, hal: SimHal) -> None:
        self.hal = hal
        self._pilot: SimulatedPilot | None = None
        self._ratings: np.random.Generator | None = None  # the simulated pilot's scatter when he rates

    # --- what the world is ----------------------------------------------------------------------

    @property
    def fault_kinds(self) -> tuple[str, ...]:
        return PLANT_FAULT_KINDS

    @property
    def t_s(self) -> float:
        """Plant time now, s."""
        return self.hal.time_s

    @property
    def carries_dummy_arm(self) -> bool:
        return self.hal.scenario.dummy_arm is not None

    @property
    def scenario(self) -> str:
        return self.hal.scenario.name

    @property
    def pilot(self) -> SimulatedPilot:
        """The seated pilot (tests and tools).

        Raises:
            HalError: no pilot is seated (:meth:`seat_pilot`).
        """
        if self._pilot is None:
            raise HalError("no pilot is seated in the simulated world; call seat_pilot() first")
        return self._pilot

    @property
    def pilot_seated(self) -> bool:
        return self._pilot is not None

    @property
    def pilot_carried(self) -> float:
        return self._pilot.carried if self._pilot is not None else 0.0

    @property
    def pilot_moving(self) -> bool:
        return self._pilot is not None and self._pilot.moving

    # --- buttons and faults -----------------------------------------------------------------------

    def press_estop(self, which: int, pressed: bool) -> None:
        """See :meth:`hal.capabilities.SimulatedWorld.press_estop` (:meth:`SimHal.press_estop`)."""
        self.hal.press_estop(which, pressed)

    def inject_fault(self, kind: str, joint: int | None = None, value: float | None = None) -> None:
        """See :meth:`hal.capabilities.SimulatedWorld.inject_fault` (:meth:`SimHal.inject_fault`)."""
        self.hal.inject_fault(kind, joint, value)  # type: ignore[arg-type]

    def clear_faults(self) -> None:
        self.hal.clear_faults()

    # --- the pilot ----------------------------------------------------------------------------------

    def seat_pilot(self) -> None:
        """A new pilot holds the arm where the sensors read it now, carrying its weight (see the protocol).

        Raises:
            HalNotOpenError: the backend is not open.
        """
        hal = self.hal
        pilot = SimulatedPilot(hal.plant, hal.read_without_faults().q_rad)
        hal.set_external_torque(pilot)
        self._pilot = pilot

    def pilot_carries(self, share: float) -> None:
        self.pilot.carried = share

    def pilot_stiffness(self, scale: float) -> None:
        self.pilot.set_stiffness_scale(scale)

    def pilot_hold_here(self) -> None:
        self.pilot.hold(self.hal.truth().q_rad)

    def pilot_stop(self) -> None:
        self.pilot.stop(self.t_s)

    def pilot_move(self, q_rad: FloatArray, seconds: float | None = None) -> float:
        return self.pilot.move_to(q_rad, self.t_s, seconds)

    def pilot_sweep_isb(self, poses_isb_rad: Sequence[FloatArray], seconds_per_move: float | None = None) -> float:
        """Through the ISB poses and back (see the protocol); each pose solved from the one before.

        Each pose's joint angles are solved from the previous pose's (the first from where the arm
        truly is), so a sweep stays on one branch of the shoulder's inverse kinematics.
        """
        pilot = self.pilot
        shoulder = Shoulder.from_description(self.hal.description)
        q = self.hal.truth().q_rad
        poses = []
        for isb in poses_isb_rad:
            q = shoulder.q_from_isb(isb, seed=q)
            poses.append(q)
        poses.append(self.hal.truth().q_rad)  # and back to where the arm was
        return pilot.sweep(poses, self.t_s, seconds_per_move)

    def place_rest_support(self) -> int:
        """The arm rests on something where it is now (the pilot's lap, an armrest): a support under it there.

        Returns how many joints it supports (those gravity pulls at that pose; hal.sim.plant).
        """
        return self.hal.plant.place_rest_support(self.hal.truth().q_rad)

    def remove_rest_support(self) -> None:
        """Take the rest support away (the arm hangs in the robot alone again)."""
        self.hal.plant.place_rest_support(None)

    def pilot_torque_nm(self) -> FloatArray:
        """The seated pilot's torque of the plant's last step (a copy; nothing is evaluated)."""
        return self.pilot.torque_nm

    def pilot_rating(self, effort_nm: float) -> float:
        """His rating (0-10, one decimal): :data:`RATING_AT_NO_EFFORT` less :data:`RATING_PER_NM` per Nm of
        his mean effort, plus a person's scatter (normal, :data:`RATING_NOISE` of a point; the
        scenario's seed)."""
        if self._ratings is None:
            self._ratings = np.random.default_rng(self.hal.scenario.seed + 29)
        noise = float(self._ratings.normal(0.0, RATING_NOISE))
        return round(float(np.clip(RATING_AT_NO_EFFORT - RATING_PER_NM * effort_nm + noise, 0.0, 10.0)), 1)

    def support_torques(self) -> tuple[FloatArray, FloatArray]:
        """``(holding, pilot)`` now, (4,) Nm: the plant's true holding torque and the pilot's torque."""
        pilot = self.pilot
        hal = self.hal
        truth = hal.truth()
        return hal.plant.holding_torque_nm(truth.q_rad), pilot(hal.time_s, truth.q_rad, truth.dq_rad_s)
