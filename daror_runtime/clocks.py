"""Tick clocks: real time and lock-step (virtual) time. The same loop code runs under both.

* :class:`LockStepClock`: virtual time, as fast as the CPU allows. Used by tests, by the
  identification protocol in simulation and by the demo; time is owned by the simulated plant
  (Drake style), the clock only counts ticks. It never reports lateness or missed deadlines.
* :class:`RealTimeClock`: sleeps until shortly before each deadline, then spins to it (sleep alone
  wakes up 50-100 us late on Linux). A tick that starts after the deadline it was due at overran.
  The clock counts every deadline that passed before the tick started (a 20 ms stall at 1 kHz
  misses 20 deadlines, not one) and skips the missed ones instead of bursting to catch up; the
  loop's watchdog turns too many missed deadlines in a row, or one long stall, into a fault.

A clock says whether its time is virtual (:attr:`Clock.virtual`); a HAL backend says whether it
owns its time (:attr:`hal.interface.Hal.virtual_time`). Lock-step needs both: :func:`check_clock`
refuses a virtual clock on a backend whose time is the wall clock's (hardware, a bus), and
:func:`clock_for` picks the clock a backend runs on by default.

Deadlines are ``t0 + k * period`` on one grid, so lateness never accumulates; the grid is anchored
when the first tick of a run has ended (it runs cold, and no command of the loop was on the drives
before it). Lateness is measured against the deadline a tick was originally due at, so a stall
shows in the recording with its full length.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

from daror_runtime.errors import ConfigurationError, UsageError

if TYPE_CHECKING:
    from hal.interface import Hal


class TickTiming(NamedTuple):
    """When a tick started relative to its deadline (a NamedTuple: built every tick, it must be cheap).

    Attributes:
        index: the tick's slot on the deadline grid (after any skipped deadlines).
        deadline_s: that slot's deadline in s since the clock started (``index * period``).
        lateness_s: the tick's start minus the deadline it was originally due at, in s (after a
            20 ms stall, ~20 ms even though the tick took a later slot); 0 in lock-step.
        overrun: the tick started after the deadline it was due at (the previous tick's work ran
            past it).
        consecutive_overruns: deadlines missed in a row, up to and including this tick's (reset by a
            tick that starts on time); a tick that starts 20 ms late adds 20, not 1.
        missed_deadlines: deadlines this tick alone missed: the skipped ones plus its own late start
            (0 on time; ``floor(lateness / period) + 1`` when late).
    """

    index: int
    deadline_s: float
    lateness_s: float
    overrun: bool
    consecutive_overruns: int
    missed_deadlines: int = 0


_new_tuple = tuple.__new__


class ClockStats(NamedTuple):
    """Totals of a clock since :meth:`Clock.start` (a read-only snapshot for a status view).

    Attributes:
        ticks: ticks started.
        overruns: ticks that started after the deadline they were due at.
        missed_deadlines: deadlines missed in all (each overrun's own plus the skipped ones).
        skipped_deadlines: deadlines skipped over rather than run (``missed - overruns``).
        worst_lateness_s: the latest start of a tick after the deadline it was due at, in s (0 in lock-step).
    """

    ticks: int
    overruns: int
    missed_deadlines: int
    skipped_deadlines: int
    worst_lateness_s: float


class Clock(ABC):
    """The tick clock the loop waits on.

    Args:
        period_s: tick period in s (1 ms at 1 kHz).

    Raises:
        ConfigurationError: the period is not positive.
    """

    def __init__(self, period_s: float) -> None:
        if not period_s > 0:
            raise ConfigurationError(f"tick period must be positive, got {period_s} s")
        self.period_s = period_s
        self._reset_totals()

    @property
    def virtual(self) -> bool:
        """True for virtual time: ticks start at once, one after the other, and time is the backend's (lock-step).

        Only a backend that owns its time (:attr:`hal.interface.Hal.virtual_time`) can run on it.
        """
        return False

    @abstractmethod
    def start(self) -> None:
        """Start counting (and reset the totals); the first :meth:`wait` returns at once as tick 0, at deadline 0."""

    @abstractmethod
    def wait(self) -> TickTiming:
        """Return at the start of the next tick (a clock never started starts at its first wait)."""

    def until_quiet_s(self) -> float:
        """Seconds until the loop is between ticks and not about to wake (0: now, or no such time).

        Other threads of the loop's process do their short work then (:meth:`Runtime.add_publisher`):
        the loop does not need the interpreter, so they never make it wait for it. Virtual time: 0.
        """
        return 0.0

    def advance(self, ticks: int) -> None:
        """Count ``ticks`` ticks that ran on their deadlines without :meth:`wait` (a lock-step batch).

        Raises:
            ConfigurationError: the clock is not virtual (a real-time tick cannot be skipped).
        """
        raise ConfigurationError(f"{type(self).__name__} is not virtual: ticks cannot run ahead of it")

    @property
    def stats(self) -> ClockStats:
        """The totals since :meth:`start` (built on each read; never touched by the tick)."""
        return ClockStats(
            self.ticks, self.overruns, self.missed_deadlines, self.skipped_deadlines, self.worst_lateness_s
        )

    def _reset_totals(self) -> None:
        self.ticks = 0
        self.overruns = 0
        self.missed_deadlines = 0
        self.skipped_deadlines = 0
        self.worst_lateness_s = 0.0
        self._consecutive = 0


class LockStepClock(Clock):
    """Virtual time: every tick starts exactly on its deadline, immediately."""

    @property
    def virtual(self) -> bool:
        return True

    def start(self) -> None:
        self._reset_totals()

    def advance(self, ticks: int) -> None:
        """``ticks`` ticks started exactly on their deadlines (a lock-step batch ran them)."""
        self.ticks += ticks

    def wait(self) -> TickTiming:
        index = self.ticks
        self.ticks = index + 1
        # TickTiming(index, deadline, lateness, overrun, consecutive, missed), every field in order;
        # tuple.__new__ skips the NamedTuple's Python-level __new__ (this runs every tick).
        return _new_tuple(TickTiming, (index, index * self.period_s, 0.0, False, 0, 0))


class RealTimeClock(Clock):
    """Wall-clock ticks: sleep, then spin the last ``spin_s`` to the deadline.

    Tick 0 (the first :meth:`wait` after :meth:`start`, or ever) returns at once, and the grid is
    anchored when it ends: tick 1 is on its deadline by definition. Neither the time between
    opening a session and its first tick nor the first tick's own work (it runs cold: first calls
    load compiled code, 10-40 ms measured) is a stall: no command of this loop was on the drives
    before tick 0 wrote its own.

    Args:
        period_s: tick period in s (1 ms at 1 kHz).
        spin_s: how long before a deadline to stop sleeping and start spinning, in s.
        now: monotonic time source in s (injectable for tests).
        sleep: sleep function taking s (injectable for tests).

    Raises:
        ConfigurationError: the period is not positive.
    """

    def __init__(
        self,
        period_s: float,
        spin_s: float = 3e-4,
        now: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        super().__init__(period_s)
        self.spin_s = spin_s
        self._now = now
        self._sleep = sleep
        self._t0 = 0.0
        self._next = -1  # -1: tick 0 is next; 0: tick 1 is next and anchors the grid

    def start(self) -> None:
        self._reset_totals()
        self._next = -1

    def until_quiet_s(self) -> float:
        """Seconds until the quiet part of the period: from 35 % of it to 5 % before the spin starts.

        The loop wakes ``spin_s`` before a deadline and holds the interpreter until its tick's work
        is done (0.07 ms on average on the simulated plant at 1 kHz, measured); between the two it
        sleeps. 0 before the grid is anchored, or when the period has no quiet part.
        """
        period = self.period_s
        start, end = 0.35 * period, period - self.spin_s - 0.05 * period
        if self._next <= 1 or end <= start:
            return 0.0
        phase = (self._now() - self._t0) % period
        return 0.0 if start <= phase <= end else (start - phase) % period

    def wait(self) -> TickTiming:
        index = self._next
        period = self.period_s
        if index <= 0:  # tick 0 at once; tick 1 at once too, and the grid starts one period before it
            if index < 0:
                self._next = 0
                tick = 0
            else:
                self._t0 = self._now() - period
                self._next = 2
                tick = 1
            self.ticks += 1
            return TickTiming(tick, tick * period, 0.0, False, 0, 0)
        due = self._t0 + index * period
        now = self._now()
        if now > due:  # late: every deadline up to now was missed
            lateness = now - due
            skipped = int(lateness / period)  # floor: lateness > 0
            missed = skipped + 1
            self.overruns += 1
            self.missed_deadlines += missed
            self.skipped_deadlines += skipped
            consecutive = self._consecutive + missed
            self._consecutive = consecutive
            if lateness > self.worst_lateness_s:
                self.worst_lateness_s = lateness
            index += skipped  # start in the most recent slot rather than burst through the missed ones
            self._next = index + 1
            self.ticks += 1
            return TickTiming(index, index * period, lateness, True, consecutive, missed)
        self._consecutive = 0
        remaining = due - now
        if remaining > self.spin_s:
            self._sleep(remaining - self.spin_s)
        now = self._now()
        while now < due:
            now = self._now()
        lateness = now - due
        if lateness > self.worst_lateness_s:
            self.worst_lateness_s = lateness
        self._next = index + 1
        self.ticks += 1
        return TickTiming(index, index * period, lateness, False, 0, 0)


class LockStepRefusedError(UsageError):
    """Lock-step (a virtual clock) was asked for on a backend whose time is the wall clock's."""


def check_clock(clock: Clock, hal: Hal) -> None:
    """Refuse a virtual clock on a backend that does not own its time.

    A virtual clock starts each tick as soon as the previous one ends; on hardware that would send
    commands as fast as the CPU allows, with the time in every sample passing at its own pace.

    Raises:
        LockStepRefusedError: ``clock`` is virtual and ``hal`` is not (one line, naming the backend).
    """
    if clock.virtual and not hal.virtual_time:
        what = "drives hardware" if hal.drives_hardware else "runs on wall-clock time"
        raise LockStepRefusedError(
            f"the {hal.kind or type(hal).__name__} HAL backend {what}: it cannot run lock-step (virtual time); "
            "run it in real time (daror console --realtime)"
        )


def clock_for(hal: Hal, period_s: float | None = None) -> Clock:
    """The clock ``hal`` runs on by default: lock-step if it owns its time, else real time.

    Args:
        hal: the backend.
        period_s: the tick period, s; default ``1 / hal.rate_hz``.

    Raises:
        ConfigurationError: the period is not positive.
    """
    period = period_s if period_s is not None else 1.0 / hal.rate_hz
    return LockStepClock(period) if hal.virtual_time else RealTimeClock(period)
