"""The world around a simulated robot: the pilot, the e-stop buttons, and faults to inject.

On hardware these are people and physics; on the simulated plant the console plays them, so a
session script can be a complete rehearsal: the pilot presses the e-stop, the operator records
the pilot's range of motion while the pilot moves the arm, the pilot relaxes once the robot
compensates. None of this goes through the runtime: it acts on the simulation, like a person
acts on the robot.
"""

from __future__ import annotations

from daror_runtime.errors import UsageError
from daror_runtime.identification.waypoints import load_waypoints
from daror_runtime.session.settings import IdentificationSettings
from hal.isb import Shoulder
from hal.robot import FloatArray
from hal.sim.backend import FAULT_KINDS, SimHal
from hal.sim.pilot import SimulatedPilot

BUTTONS = {"operator": 0, "pilot": 1}


class SimWorld:
    """The pilot and the buttons of a :class:`SimHal` (opened)."""

    def __init__(self, hal: SimHal) -> None:
        self.hal = hal
        self.pilot = SimulatedPilot(hal.plant, hal.read_without_faults().q_rad)
        hal.set_external_torque(self.pilot)

    @property
    def t_s(self) -> float:
        return self.hal.time_s

    def estop(self, button: str, pressed: bool) -> None:
        if button not in BUTTONS:
            raise UsageError(f"e-stop {button!r}: expected operator or pilot")
        self.hal.press_estop(BUTTONS[button], pressed)

    def fault(self, kind: str, joint: int | None = None, value: float | None = None) -> None:
        if kind not in FAULT_KINDS:
            raise UsageError(f"fault {kind!r}: expected one of {', '.join(FAULT_KINDS)}")
        self.hal.inject_fault(kind, joint, value)  # type: ignore[arg-type]

    def clear_faults(self) -> None:
        self.hal.clear_faults()

    def pilot_carries(self, share: float) -> None:
        """The share of the arm's weight the pilot carries (1 alone, 0 relaxed on the robot)."""
        self.pilot.carried = share

    def pilot_stiffness(self, scale: float) -> None:
        """Scale the pilot's arm stiffness (0: limp, the robot moves the arm freely; 1: a calm pilot)."""
        self.pilot.set_stiffness_scale(scale)

    def pilot_hold_here(self) -> None:
        """The pilot keeps the arm where it is now."""
        self.pilot.move_to(self.hal.truth().q_rad, self.t_s, 1e-3)

    def pilot_move(self, q_rad: FloatArray, seconds: float) -> float:
        return self.pilot.move_to(q_rad, self.t_s, seconds)

    def pilot_sweep(self, settings: IdentificationSettings, seconds_per_move: float) -> float:
        """The pilot moves through the session's waypoints (what the operator records as the range of motion)."""
        waypoints = load_waypoints(settings.waypoints_file)
        shoulder = Shoulder.from_description(self.hal.description)
        numbers = [n for n in waypoints.training_order if (n - 1) % settings.waypoint_stride == 0]
        q = self.hal.truth().q_rad
        poses = []
        for n in numbers:
            q = shoulder.q_from_isb(waypoints.waypoints[n - 1].isb_rad, seed=q)
            poses.append(q)
        poses.append(self.hal.truth().q_rad)  # and back to where the arm was
        return self.pilot.sweep(poses, self.t_s, seconds_per_move)
