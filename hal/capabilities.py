"""What a backend may offer besides the :class:`hal.interface.Hal` contract: the simulated world, batches.

A backend that simulates the robot (``sim``, later ``can-sim``) can also play the world around
it: the pilot in the sleeve, the two e-stop buttons, faults to inject. The console and the demo
use that world through :class:`SimulatedWorld` only, reached as :attr:`hal.interface.Hal.world`
(``None`` on a backend that drives hardware), so they never import a backend or ask which one
they have. None of it goes through the runtime: it acts on the simulation, as a person acts on
the robot.

A backend on virtual time may also run ticks inside compiled code (:class:`LockStepBatches`,
reached as :attr:`hal.interface.Hal.lockstep_batches`): the runtime's loop then runs many
lock-step ticks in one compiled call when every part of the tick offers its compiled form
(``daror_runtime/loop_batch.py``, docs/loop.md). Never on a backend that drives hardware.

Units: rad, rad/s, Nm, s; arrays are ``float64`` of shape (4,), joints 1-4 at indices 0-3.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Literal, NamedTuple, Protocol, runtime_checkable

from hal.robot import FloatArray

if TYPE_CHECKING:
    from hal.kernels import CompiledFunction

__all__ = [
    "BUS_FAULT_KINDS",
    "BUS_LINE_FAULT_KINDS",
    "ESTOP_OPERATOR",
    "ESTOP_PILOT",
    "FAULT_KINDS",
    "PLANT_FAULT_KINDS",
    "BackendBatch",
    "BusStatistics",
    "FaultKind",
    "FaultSchedule",
    "LockStepBatches",
    "SimulatedWorld",
]

#: Index of the operator's e-stop in :attr:`hal.interface.Sample.estop`.
ESTOP_OPERATOR = 0
#: Index of the pilot's e-stop in :attr:`hal.interface.Sample.estop`.
ESTOP_PILOT = 1

FaultKind = Literal["nan", "jump", "stale", "drive_fault", "bus", "heartbeat_loss", "emcy", "frozen_pdo", "drop_frames"]
#: The faults the simulated plant injects in its sensors and drives (``sim``).
PLANT_FAULT_KINDS: tuple[str, ...] = ("nan", "jump", "stale", "drive_fault", "bus")
#: The faults simulated CANopen drives inject on the bus (``can-sim``, hal/canopen/sim).
BUS_FAULT_KINDS: tuple[str, ...] = ("heartbeat_loss", "emcy", "frozen_pdo", "drive_fault", "drop_frames")
#: The faults of the simulated CAN bus itself, the master's controller (``can-sim``; ``daror hil --fault KIND@T_S``).
BUS_LINE_FAULT_KINDS: tuple[str, ...] = ("bus_off", "error_passive")
#: Every fault a simulated world may offer (what each does: :meth:`SimulatedWorld.inject_fault`);
#: a world offers its own subset (:attr:`SimulatedWorld.fault_kinds`).
FAULT_KINDS: tuple[str, ...] = (*PLANT_FAULT_KINDS, *(k for k in BUS_FAULT_KINDS if k not in PLANT_FAULT_KINDS))


@runtime_checkable
class SimulatedWorld(Protocol):
    """The world around a simulated robot: the pilot, the e-stop buttons and fault injection.

    Every method acts from the next tick on (the next sample built, the next plant step). The
    pilot's methods need a seated pilot (:meth:`seat_pilot`); without one they raise
    :class:`hal.errors.HalError`. Reading a property never raises.
    """

    @property
    def fault_kinds(self) -> tuple[str, ...]:
        """The fault kinds :meth:`inject_fault` takes (a subset of :data:`FAULT_KINDS`)."""
        ...

    @property
    def t_s(self) -> float:
        """The world's time now: the robot time of the latest tick, s."""
        ...

    @property
    def carries_dummy_arm(self) -> bool:
        """True if the simulated robot carries the Dummy Arm (what the session settings should say)."""
        ...

    @property
    def scenario(self) -> str:
        """The name of the simulated scenario (its robot and pilot: whose data a recording holds)."""
        ...

    @property
    def pilot_seated(self) -> bool:
        """True once :meth:`seat_pilot` was called."""
        ...

    @property
    def pilot_carried(self) -> float:
        """The share, in [0, 1], of the arm's weight the pilot carries of what the robot does not (0 without a pilot)."""
        ...

    @property
    def pilot_moving(self) -> bool:
        """True while the pilot moves the arm (a move or sweep under way; False without a pilot)."""
        ...

    def press_estop(self, which: int, pressed: bool) -> None:
        """Press (True) or release an e-stop: :data:`ESTOP_OPERATOR` or :data:`ESTOP_PILOT`.

        The world only reports the input (``Sample.estop``, from the next sample); removing
        torque is the runtime's job.

        Raises:
            InputError: ``which`` is not one of the two buttons.
        """
        ...

    def inject_fault(self, kind: str, joint: int | None = None, value: float | None = None) -> None:
        """Inject a fault, effective from the next sample or tick (``joint`` 1-4, None for all).

        The simulated plant (``sim``): ``nan``: the next ``q`` reading is NaN. ``jump``: the ``q``
        reading is offset by ``value`` rad from now on. ``stale``: the next ``value`` (default 1)
        samples repeat the latest one. ``drive_fault``: the drive reports FAULT with code ``value``
        (default 0x1000) and applies no torque until :meth:`clear_faults` or a fault reset.
        ``bus``: the next ``read`` raises :class:`hal.interface.HalFaultError`.

        Simulated CANopen drives (``can-sim``, ``joint`` names the drive): ``heartbeat_loss``: its
        heartbeat stops. ``emcy``: it reports an error by a short EMCY and faults. ``frozen_pdo``:
        its TPDOs stop. ``drive_fault``: its power stage faults (EMCY, FAULT). ``drop_frames``:
        every frame to and from it is lost for ``value`` s (default 0.02).

        Raises:
            InputError: an unknown kind, a joint not 1-4, or a missing/invalid value.
            HalNotOpenError: the backend is not open.
        """
        ...

    def clear_faults(self) -> None:
        """Clear every injected fault; a drive whose fault is cleared reports DISABLED until enabled."""
        ...

    def seat_pilot(self) -> None:
        """The pilot sits in the sleeve and holds the arm where it is now, carrying its weight.

        From the next tick on the pilot's torque acts on the links. A second call seats a new
        pilot in place of the first (at the arm's pose then).

        Raises:
            HalNotOpenError: the backend is not open.
        """
        ...

    def pilot_carries(self, share: float) -> None:
        """The share of the arm's weight the pilot carries (1 alone, 0 relaxed on the robot).

        Raises:
            InputError: ``share`` outside [0, 1].
        """
        ...

    def pilot_stiffness(self, scale: float) -> None:
        """Scale the pilot's arm stiffness (0: limp, the robot moves the arm freely; 1: a calm pilot).

        Raises:
            InputError: ``scale`` outside [0, 2].
        """
        ...

    def pilot_hold_here(self) -> None:
        """The pilot keeps the arm where it is now (any motion under way is dropped)."""
        ...

    def pilot_stop(self) -> None:
        """The pilot stops moving: the motion under way is dropped where the pilot's target is now."""
        ...

    def pilot_move(self, q_rad: FloatArray, seconds: float | None = None) -> float:
        """The pilot moves the arm to joint angles ``q_rad`` (replacing any motion); returns the end time, s.

        ``seconds`` None: at the pilot's own pace.

        Raises:
            InputError: a duration that is not positive, or not four finite angles.
        """
        ...

    def pilot_sweep_isb(self, poses_isb_rad: Sequence[FloatArray], seconds_per_move: float | None = None) -> float:
        """The pilot moves the arm through ISB poses (elevation, plane, axial, elbow; rad) and back.

        Replaces any motion under way; the arm returns to where it was at the end. Returns the
        end time, s. ``seconds_per_move`` None: each move at the pilot's own pace.

        Raises:
            InputError: a duration that is not positive, or a pose that is not four finite angles.
        """
        ...

    def place_rest_support(self) -> int:
        """Something carries the arm where it is now (the pilot's lap, an armrest, a tray): a support under it.

        What a fault's ``lower`` reaction hands the arm to at the rest pose. Returns how many joints
        it supports (those gravity pulls there).
        """
        ...

    def remove_rest_support(self) -> None:
        """Take the rest support away."""
        ...

    def support_torques(self) -> tuple[FloatArray, FloatArray]:
        """``(holding, pilot)`` now, (4,) Nm each: the torque that holds the arm still where it truly is,
        and the torque the pilot applies (the simulation's truth: for reports of what the robot carries).
        """
        ...

    def pilot_torque_nm(self) -> FloatArray:
        """The pilot's torque (4,) Nm as the plant's last step computed it: a read, never an evaluation
        (safe beside a running loop, unlike :meth:`support_torques`)."""
        ...

    def pilot_rating(self, effort_nm: float) -> float:
        """The simulated pilot's rating (0-10, one decimal) of a support under which his own mean effort
        was ``effort_nm`` (the sum over joints of his torque's magnitude, Nm): less effort, a better
        rating, with a person's noise (a blind comparison's rater, issue 29)."""
        ...


class BackendBatch(NamedTuple):
    """What a backend hands a lock-step batch: its compiled tick, its state and where its readings are.

    Attributes:
        step: the backend's tick (:data:`hal.kernels.BACKEND_STEP`), called once per tick with the
            state arrays below, the commanded torque and the readings block.
        state: the four state arrays ``step`` takes first (the backend's own; the batch only passes them).
        readings: the block the readings go to; the current sample's readings are rows ``row ..
            row + 3`` (:data:`hal.kernels.READING_ROWS`), each tick's ``step`` writes the next four.
        row: the first row of the current sample's readings.
        seq: the current sample's ``seq``; its time is ``seq * period_s`` (virtual time).
        period_s: the tick, s.
        ticks: how many ticks may run before the backend needs Python again (at least 1).
    """

    step: CompiledFunction
    state: tuple[FloatArray, FloatArray, FloatArray, FloatArray]
    readings: FloatArray
    row: int
    seq: int
    period_s: float
    ticks: int


class LockStepBatches(Protocol):
    """A backend on virtual time that can run ticks inside compiled code (``Hal.lockstep_batches``).

    The loop calls :meth:`begin` between ticks, runs up to ``ticks`` ticks of the backend's compiled
    step (each exactly what ``read(); write(command)`` would have done with that command), then
    :meth:`end` with how many ran; nothing else touches the backend in between. A batch tick is
    a plain tick: fresh readings, no e-stop pressed, no drive in fault, nothing pending from the
    world (a fault to inject, a pilot's torque to compute): :meth:`begin` returns None otherwise.
    """

    def begin(self) -> BackendBatch | None:
        """Prepare a batch at the current tick; None when the next tick must run through read and write."""
        ...

    def end(self, ticks: int, status: int) -> None:
        """``ticks`` (at least 1) of the batch ran; ``status`` is what the last one's step returned.

        Raises:
            HalError: the last step failed (negative ``status``): that tick does not count, torque
                was removed, and the next :meth:`hal.interface.Hal.read` shows the failed tick's
                sample with no drive enabled, as after a :meth:`hal.interface.Hal.write` that raised.
        """
        ...


@runtime_checkable
class FaultSchedule(Protocol):
    """A simulated world that injects faults at a robot time of its own (``daror hil --fault``)."""

    def schedule_fault(self, kind: str, joint: int, at_s: float, duration_s: float | None = None) -> None:
        """Inject ``kind`` (one of the world's ``fault_kinds``) into ``joint``'s drive at robot time ``at_s``.

        Raises:
            InputError: an unknown kind, a joint not 1-4, a negative time or a duration that is not positive.
        """
        ...

    def drive_events(self) -> list[tuple[float, int, str]]:
        """What happened to the drives so far, oldest first: ``(robot time s, joint 1-4, what)`` with what
        ``injected KIND``, ``power stage on`` or ``power stage off`` (from that tick on it applies torque,
        or no longer)."""
        ...


@runtime_checkable
class BusStatistics(Protocol):
    """A backend on a field bus that reports on it (CANopen: rate, load, frame counts)."""

    def bus_report(self) -> dict[str, object]:
        """What the bus did since the backend opened: plain values, ready for JSON."""
        ...
