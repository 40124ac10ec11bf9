"""A commissioning command's hold on the CANopen backend: its clock, its ticks, and torque off at the end.

Every ``daror can`` command that boots the bus (check, zero, tare) goes through
:func:`commissioning_backend` and :class:`BusSession`:

* the backend is a CANopen one (``can`` or ``can-sim``), built with the drives' peak torque
  (0x6072, which the master writes at start-up and the drives saturate at) lowered to the
  command's torque limit;
* the clock is lock-step only on a backend that owns its time (``can-sim``): lock-step on
  hardware is refused before the bus is touched (:func:`daror_runtime.clocks.check_clock`);
* one tick is the runtime's: wait for the clock, read the drives' TPDOs of the last SYNC, write
  the next command (one SYNC). A fault the backend latched is recorded, not raised;
* :meth:`BusSession.disable_all` ends every command: torque off until a fresh sample shows no
  drive enabled, then the backend closed (torque off again, every drive pre-operational),
  whatever happened before (an exception, Ctrl-C, a fault).

Units: times in s, angles in rad, torques in N m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from daror_runtime.clocks import Clock, LockStepClock, RealTimeClock, check_clock
from daror_runtime.errors import UsageError
from hal.commissioning import bus_probe
from hal.config import AnyHalConfig
from hal.errors import HalError
from hal.interface import Command, Hal, HalFaultError, Sample, hal_class
from hal.robot import N_JOINTS

__all__ = [
    "ZERO_TORQUE_NM",
    "BusSession",
    "Stats",
    "commissioning_backend",
    "commissioning_clock",
    "only_joint",
    "stats",
]

#: The clocks a commissioning command may run on (``--clock``).
CLOCK_CHOICES = ("realtime", "lockstep")


def commissioning_backend(config: AnyHalConfig, torque_limit_nm: float) -> Hal:
    """The CANopen backend of ``config`` (not opened), its drives' peak torque (0x6072) at ``torque_limit_nm``.

    Raises:
        UsageError: ``config`` is not a CANopen backend's (``sim`` has no bus), or the limit is not
            a positive torque at most the robot's peak.
        HalConfigError, BackendUnavailableError, InputError: as :func:`hal.interface.open_hal`.
    """
    if config.backend not in ("can", "can-sim"):
        raise UsageError(
            f"the HAL configuration names backend {config.backend!r}; the CAN commissioning commands need "
            "backend can (the drives) or can-sim (simulated drives)"
        )
    cls: Any = hal_class(config.backend)
    built = cls.from_config(config)
    sea = built.description.sea
    if not (math.isfinite(torque_limit_nm) and 0 < torque_limit_nm <= sea.max_motor_torque_nm):
        raise UsageError(
            f"--torque-limit-nm {torque_limit_nm:g}: expected a torque above 0 and at most the drives' peak "
            f"({sea.max_motor_torque_nm:g} N m)"
        )
    limited = built.description.model_copy(
        update={"sea": sea.model_copy(update={"max_motor_torque_nm": float(torque_limit_nm)})}
    )
    return cls(config, limited)


def commissioning_clock(hal: Hal, choice: str | None) -> Clock:
    """The clock of a commissioning command: ``choice``, or lock-step where the backend owns its time, else real time.

    Raises:
        UsageError: an unknown ``choice``.
        LockStepRefusedError: ``lockstep`` on a backend that drives hardware (one line; nothing was sent).
    """
    period = 1.0 / hal.rate_hz
    if choice is None:
        choice = "lockstep" if hal.virtual_time else "realtime"
    if choice == "lockstep":
        clock: Clock = LockStepClock(period)
    elif choice == "realtime":
        clock = RealTimeClock(period)
    else:
        raise UsageError(f"--clock {choice!r}: expected one of {', '.join(CLOCK_CHOICES)}")
    check_clock(clock, hal)
    return clock


@dataclass(frozen=True)
class Stats:
    """Mean and spread (population standard deviation) of one joint's readings over a window, and how many."""

    mean: float
    spread: float
    n: int


def stats(values: list[float]) -> Stats:
    """:class:`Stats` of ``values`` (NaN for none)."""
    if not values:
        return Stats(math.nan, math.nan, 0)
    array = np.asarray(values, dtype=float)
    return Stats(float(array.mean()), float(array.std()), len(values))


@dataclass(frozen=True)
class Rest:
    """Whether the arm came to rest: the fastest joint at the end (rad/s), how long it took (s), the last sample."""

    at_rest: bool
    speed_rad_s: float
    waited_s: float
    sample: Sample


@dataclass
class BusSession:
    """Ticks of an opened CANopen backend on its clock (see the module docstring).

    Args:
        hal: the backend, opened by the caller (:meth:`open`).
        clock: the command's clock (:func:`commissioning_clock`).

    Attributes:
        faults: every fault the backend latched, in order.
        probe: the drives' own words once open (:func:`hal.commissioning.bus_probe`).
        sample: the last sample read.
        stage_on: per drive, what its own statusword of the last SYNC says: True its power stage
            is on (OPERATION ENABLED, QUICK STOP ACTIVE, FAULT REACTION ACTIVE), False off, None no
            statusword of that SYNC arrived. The sample's drive states are the master's view, which
            counts a drive it commanded off as disabled before the drive says so.
    """

    hal: Hal
    clock: Clock
    faults: list[str] = field(default_factory=list)
    sample: Sample | None = None
    stage_on: tuple[bool | None, ...] = ()
    probe: Any = None
    _started: bool = False

    @property
    def period_s(self) -> float:
        return self.clock.period_s

    def open(self) -> None:
        """Boot the bus: the backend's start-up (reset, identity, units, configuration, NMT start).

        Raises:
            HalError: a drive did not answer, refused its configuration or has other units than its EDS.
        """
        self.hal.open()
        self._started = True
        self.probe = bus_probe(self.hal)
        self.clock.start()

    def tick(self, command: Command) -> Sample:
        """One tick: wait for the clock, read (a latched fault recorded), write ``command``; the sample read.

        Raises:
            HalError: the bus failed (a frame refused).
        """
        self.clock.wait()
        try:
            sample = self.hal.read()
        except HalFaultError as exc:
            self.faults.append(str(exc))
            sample = self.hal.read()  # the same cycle's sample: the fault is raised once
        self.sample = sample
        self.stage_on = self._stage_on(sample)
        self.hal.write(command)
        return sample

    def _stage_on(self, sample: Sample) -> tuple[bool | None, ...]:
        """Each drive's own statusword of the last SYNC (None: the cycle was not fresh, or the drive is lost)."""
        if self.probe is None:
            return tuple(None for _ in range(N_JOINTS))
        return tuple(self.probe.stage_on(sample))

    def wait_for_rest(self, window_s: float, timeout_s: float, speed_rad_s: float) -> Rest:
        """Torque off until every joint is slower than ``speed_rad_s`` for ``window_s``, for at most ``timeout_s``.

        Raises:
            HalError: the bus failed.
        """
        needed = self.ticks_for(window_s)
        still = waited = 0
        sample = self.tick(Command.torque_off())
        while waited < self.ticks_for(timeout_s) and still < needed:
            sample = self.tick(Command.torque_off())
            waited += 1
            still = still + 1 if float(np.max(np.abs(sample.dq_rad_s))) < speed_rad_s else 0
        return Rest(still >= needed, float(np.max(np.abs(sample.dq_rad_s))), waited * self.period_s, sample)

    def ticks_for(self, seconds: float) -> int:
        """How many ticks ``seconds`` take (at least one)."""
        return max(1, math.ceil(seconds / self.period_s))

    def disable_all(self, confirm_s: float = 1.0) -> bool:
        """Torque off until every drive's own statusword shows its power stage off (three SYNCs in a row), then close.

        True if that was seen (a drive that said nothing of a SYNC breaks the row), or if the bus never
        started (nothing was enabled: the start-up enables no drive).

        Runs whatever happened before; a second failure while disabling is not allowed to stop
        the close (which sends torque off once more and every drive to pre-operational).
        """
        confirmed = not self._started
        try:
            if self._started:
                in_a_row = 0
                for _ in range(self.ticks_for(confirm_s)):
                    self.tick(Command.torque_off())
                    in_a_row = in_a_row + 1 if self.stage_on and all(on is False for on in self.stage_on) else 0
                    if in_a_row >= 3:
                        confirmed = True
                        break
        except HalError as exc:
            self.faults.append(f"while disabling: {exc}")
        finally:
            self._started = False
            self.hal.close()
        return confirmed


#: No torque on any joint: the command a commissioning command enables a joint with.
ZERO_TORQUE_NM = np.zeros(N_JOINTS)


def only_joint(joint: int) -> Command:
    """Joint ``joint`` (1-4) enabled at zero torque, every other drive disabled."""
    return Command(ZERO_TORQUE_NM.copy(), True, tuple(j for j in range(1, N_JOINTS + 1) if j != joint))
