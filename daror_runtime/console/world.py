"""The console's words for the simulated world: the pilot, the e-stop buttons, faults to inject.

On hardware these are people and physics; on a backend that simulates the robot the console
plays them, so a session script can be a complete rehearsal: the pilot presses the e-stop, the
operator records the pilot's range of motion while the pilot moves the arm, the pilot relaxes once
the robot compensates. None of this goes through the runtime: it acts on the simulation, like a
person acts on the robot.

The simulation itself is the backend's (:class:`hal.capabilities.SimulatedWorld`, reached as
``hal.world``); this module holds only what the console adds: the words (``operator``,
``pilot``), its messages, and which poses a sweep visits (the session's waypoints). The console
never imports a backend and never asks which one it has: a backend without a world has none.
"""

from __future__ import annotations

import numpy as np

from daror_runtime.errors import UsageError
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.identification.waypoints import load_waypoints
from daror_runtime.session.settings import SessionSettings
from hal.capabilities import ESTOP_OPERATOR, ESTOP_PILOT, SimulatedWorld
from hal.robot import FloatArray

#: The console's names of the e-stop buttons -> the world's button.
BUTTONS = {"operator": ESTOP_OPERATOR, "pilot": ESTOP_PILOT}
#: How far past each waypoint the simulated pilot's sweep reaches, deg (see :meth:`SimWorld.pilot_sweep`).
SWEEP_BEYOND_DEG = 1.0


class SimWorld:
    """The pilot and the buttons of a backend's simulated world, in the console's words.

    Seats the pilot: from now on the pilot holds the arm where it is.

    Args:
        hal: an opened backend that offers a simulated world (``hal.world`` is not None).

    Raises:
        UsageError: the backend has no simulated world (it drives hardware).
        HalNotOpenError: the backend is not open.
    """

    def __init__(self, world: SimulatedWorld | None) -> None:
        if world is None:
            raise UsageError(
                "this HAL backend drives hardware and has no simulated world: "
                "there is no simulated pilot, e-stop or fault to act on"
            )
        self.simulated: SimulatedWorld = world
        #: The fault kinds this world offers (``sim fault KIND``).
        self.fault_kinds: tuple[str, ...] = tuple(world.fault_kinds)
        world.seat_pilot()

    @property
    def t_s(self) -> float:
        """The world's time now, s."""
        return self.simulated.t_s

    @property
    def pilot_carried(self) -> float:
        """The share of the arm's weight the pilot carries."""
        return self.simulated.pilot_carried

    @property
    def pilot_moving(self) -> bool:
        """True while the pilot moves the arm."""
        return self.simulated.pilot_moving

    def notes(self, settings: SessionSettings) -> list[str]:
        """What the operator should know about the settings against this simulated world."""
        has_arm = self.simulated.carries_dummy_arm
        if has_arm and not settings.dummy_arm:
            return [
                "the simulated plant carries the Dummy Arm but the settings say dummy_arm: false: the A Priori "
                "model leaves the arm's weight to the pilot (a validated model includes it)"
            ]
        if settings.dummy_arm and not has_arm:
            return ["the settings say dummy_arm: true but the simulated plant has no Dummy Arm"]
        return []

    def estop(self, button: str, pressed: bool) -> None:
        """Press (True) or release the ``operator`` or ``pilot`` e-stop.

        Raises:
            UsageError: not one of the two buttons.
        """
        if button not in BUTTONS:
            raise UsageError(f"e-stop {button!r}: expected operator or pilot")
        self.simulated.press_estop(BUTTONS[button], pressed)

    def fault(self, kind: str, joint: int | None = None, value: float | None = None) -> None:
        """Inject a fault of ``kind`` (:meth:`hal.capabilities.SimulatedWorld.inject_fault`).

        Raises:
            UsageError: a kind the world does not offer.
            InputError: a joint not 1-4, or a missing/invalid value.
        """
        if kind not in self.fault_kinds:
            raise UsageError(f"fault {kind!r}: expected one of {', '.join(self.fault_kinds)}")
        self.simulated.inject_fault(kind, joint, value)

    def clear_faults(self) -> None:
        self.simulated.clear_faults()

    def rest_here(self) -> None:
        """The pilot's arm lies on something where it is now (his lap, an armrest): what a fault's lowering hands it to."""
        self.simulated.place_rest_support()

    def rest_off(self) -> None:
        """Take the rest away: nothing but the robot carries the arm."""
        self.simulated.remove_rest_support()

    def pilot_carries(self, share: float) -> None:
        """The share of the arm's weight the pilot carries (1 alone, 0 relaxed on the robot)."""
        self.simulated.pilot_carries(share)

    def pilot_stiffness(self, scale: float) -> None:
        """Scale the pilot's arm stiffness (0: limp, the robot moves the arm freely; 1: a calm pilot)."""
        self.simulated.pilot_stiffness(scale)

    def pilot_hold_here(self) -> None:
        """The pilot keeps the arm where it is now (any motion under way is dropped)."""
        self.simulated.pilot_hold_here()

    def pilot_stop(self) -> None:
        """The pilot stops moving: the motion under way is dropped where the pilot's target is now."""
        self.simulated.pilot_stop()

    def pilot_move(self, q_rad: FloatArray, seconds: float | None = None) -> float:
        """The pilot moves the arm to ``q_rad`` (replacing any motion under way); returns the end time."""
        return self.simulated.pilot_move(q_rad, seconds)

    def pilot_sweep(self, settings: IdentificationSettings, seconds_per_move: float | None = None) -> float:
        """The pilot moves through the session's waypoints (what the operator records as the range of motion).

        Replaces any motion under way; the arm comes back to where it was. ``seconds_per_move``
        None: each move at the pilot's own pace (in the simulated plant, a peak joint speed of
        :data:`hal.sim.pilot.DEFAULT_PEAK_SPEED_RAD_S`, a third of the slowest velocity limit of
        the states where the pilot moves). Returns the end time.
        """
        waypoints = load_waypoints(settings.waypoints_file)
        numbers = [n for n in waypoints.training_order if (n - 1) % settings.waypoint_stride == 0]
        poses = np.array([waypoints.waypoints[n - 1].isb_rad for n in numbers])
        # A pilot's range of motion is larger than the poses the protocol visits: the pilot reaches
        # SWEEP_BEYOND_DEG past each of them (away from the poses' middle, every angle), so the
        # recorded envelope holds every waypoint with room for the measurement (quantised, a SYNC
        # late over CAN) instead of touching it.
        middle = poses.mean(axis=0)
        beyond = np.sign(poses - middle) * np.deg2rad(SWEEP_BEYOND_DEG)
        return self.simulated.pilot_sweep_isb(list(poses + beyond), seconds_per_move)

    def support_torques(self) -> tuple[FloatArray, FloatArray]:
        """``(holding, pilot)`` now, (4,) Nm: what holds the arm still where it is, and what the pilot adds."""
        return self.simulated.support_torques()
