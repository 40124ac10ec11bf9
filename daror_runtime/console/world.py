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
from daror_runtime.session.settings import IdentificationSettings, SessionSettings
from hal.isb import Shoulder
from hal.robot import FloatArray
from hal.sim.backend import FAULT_KINDS, SimHal
from hal.sim.pilot import SimulatedPilot

BUTTONS = {"operator": 0, "pilot": 1}


class SimWorld:
    """The pilot and the buttons of a :class:`SimHal` (opened)."""

    fault_kinds: tuple[str, ...] = FAULT_KINDS

    def __init__(self, hal: SimHal) -> None:
        self.hal = hal
        self.pilot = SimulatedPilot(hal.plant, hal.read_without_faults().q_rad)
        hal.set_external_torque(self.pilot)

    @property
    def t_s(self) -> float:
        return self.hal.time_s

    def notes(self, settings: SessionSettings) -> list[str]:
        """What the operator should know about the settings against this simulated world."""
        has_arm = self.hal.scenario.dummy_arm is not None
        if has_arm and not settings.dummy_arm:
            return [
                "the simulated plant carries the Dummy Arm but the settings say dummy_arm: false: the A Priori "
                "model leaves the arm's weight to the pilot (a validated model includes it)"
            ]
        if settings.dummy_arm and not has_arm:
            return ["the settings say dummy_arm: true but the simulated plant has no Dummy Arm"]
        return []

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
        """The pilot keeps the arm where it is now (any motion under way is dropped)."""
        self.pilot.hold(self.hal.truth().q_rad)

    def pilot_stop(self) -> None:
        """The pilot stops moving: the motion under way is dropped where the pilot's target is now."""
        self.pilot.stop(self.t_s)

    def pilot_move(self, q_rad: FloatArray, seconds: float | None = None) -> float:
        """The pilot moves the arm to ``q_rad`` (replacing any motion under way); returns the end time."""
        return self.pilot.move_to(q_rad, self.t_s, seconds)

    def pilot_sweep(self, settings: IdentificationSettings, seconds_per_move: float | None = None) -> float:
        """The pilot moves through the session's waypoints (what the operator records as the range of motion).

        Replaces any motion under way. ``seconds_per_move`` None: each move at the pilot's own pace
        (a peak joint speed of :data:`hal.sim.pilot.DEFAULT_PEAK_SPEED_RAD_S`, a third of the
        slowest velocity limit of the states where the pilot moves). Returns the end time.
        """
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
