"""The simulated world of ``can-sim``: the plant's pilot and e-stop buttons, and faults injected on the bus.

Everything but the faults is the plant's own world (:class:`hal.sim.world.PlantWorld`): the pilot
pushes the plant's links, an e-stop press reaches the drives' safe torque off inputs and their
statuswords (the runtime sees it through the CAN backend, as on the robot). The faults are the
drives' (:data:`hal.capabilities.BUS_FAULT_KINDS`): ``joint`` names the drive.
"""

from __future__ import annotations

from collections.abc import Sequence

from hal.canopen.sim.bus import LINE_FAULT_KINDS
from hal.canopen.sim.drives import SimulatedDriveSet
from hal.capabilities import BUS_FAULT_KINDS
from hal.errors import InputError
from hal.robot import FloatArray
from hal.sim.world import PlantWorld

__all__ = ["CanSimWorld"]


class CanSimWorld:
    """:class:`hal.capabilities.SimulatedWorld` of the simulated drives and their plant."""

    def __init__(self, plant_world: PlantWorld, drives: SimulatedDriveSet) -> None:
        self._plant = plant_world
        self._drives = drives

    @property
    def fault_kinds(self) -> tuple[str, ...]:
        return BUS_FAULT_KINDS

    @property
    def t_s(self) -> float:
        return self._plant.t_s

    @property
    def carries_dummy_arm(self) -> bool:
        return self._plant.carries_dummy_arm

    @property
    def scenario(self) -> str:
        return self._plant.scenario

    @property
    def pilot_seated(self) -> bool:
        return self._plant.pilot_seated

    @property
    def pilot_carried(self) -> float:
        return self._plant.pilot_carried

    @property
    def pilot_moving(self) -> bool:
        return self._plant.pilot_moving

    def press_estop(self, which: int, pressed: bool) -> None:
        self._plant.press_estop(which, pressed)

    def inject_fault(self, kind: str, joint: int | None = None, value: float | None = None) -> None:
        """Inject a bus fault into the drive of ``joint`` (1-4; None: joint 1) now; ``value``: the duration of ``drop_frames``, s.

        Raises:
            InputError: an unknown kind, a joint not 1-4, a duration that is not positive or given
                for a kind other than ``drop_frames``.
        """
        if kind not in BUS_FAULT_KINDS:
            raise InputError(f"fault kind {kind!r}; expected one of {', '.join(BUS_FAULT_KINDS)}")
        self._drives.inject(kind, 1 if joint is None else joint, value)

    def schedule_fault(self, kind: str, joint: int, at_s: float, duration_s: float | None = None) -> None:
        """Inject ``kind`` into the drive of ``joint`` at robot time ``at_s`` (the first SYNC at or after it);
        a bus fault (``bus_off``, ``error_passive``: the master's controller) ignores ``joint``.

        Raises:
            InputError: an unknown kind, a joint not 1-4, a negative time or a duration that is not positive.
        """
        if kind in LINE_FAULT_KINDS:
            self._drives.line.schedule(kind, at_s)
            return
        self._drives.schedule(kind, joint, at_s, duration_s)

    def clear_faults(self) -> None:
        self._drives.clear_faults()

    def drive_events(self) -> list[tuple[float, int, str]]:
        """What happened to the drives so far: faults injected, power stages on and off (a copy)."""
        return list(self._drives.events)

    def seat_pilot(self) -> None:
        self._plant.seat_pilot()

    def pilot_carries(self, share: float) -> None:
        self._plant.pilot_carries(share)

    def pilot_stiffness(self, scale: float) -> None:
        self._plant.pilot_stiffness(scale)

    def pilot_hold_here(self) -> None:
        self._plant.pilot_hold_here()

    def pilot_stop(self) -> None:
        self._plant.pilot_stop()

    def pilot_move(self, q_rad: FloatArray, seconds: float | None = None) -> float:
        return self._plant.pilot_move(q_rad, seconds)

    def pilot_sweep_isb(self, poses_isb_rad: Sequence[FloatArray], seconds_per_move: float | None = None) -> float:
        return self._plant.pilot_sweep_isb(poses_isb_rad, seconds_per_move)

    def support_torques(self) -> tuple[FloatArray, FloatArray]:
        return self._plant.support_torques()

    def pilot_torque_nm(self) -> FloatArray:
        return self._plant.pilot_torque_nm()

    def pilot_rating(self, effort_nm: float) -> float:
        return self._plant.pilot_rating(effort_nm)

    def place_rest_support(self) -> int:
        return self._plant.place_rest_support()

    def remove_rest_support(self) -> None:
        self._plant.remove_rest_support()
