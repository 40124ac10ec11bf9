"""Tick clocks: real time, lock-step (virtual) time and paced virtual time. The same loop code runs under all three.

* :class:`LockStepClock`: virtual time, as fast as the CPU allows. Used by tests, by the
  identification protocol in simulation and by the demo; time is owned by the simulated plant
  (Drake style), the clock only counts ticks. It never reports lateness or missed deadlines.
* :class:`PacedClock`: virtual time paced to the wall clock, for a simulated session a person
  watches (typed at a terminal, the web console). The plant's time advances exactly one period per
  tick, as in lock-step, and the clock sleeps so that tick ``k`` starts ``k`` periods after the
  grid's anchor. A stall of the process stalls the simulated world with it: nothing physical ran
  open, so it is counted (:class:`PacingStats`) and never an overrun. A lag up to
  ``max_catch_up_s`` is caught up by starting ticks without sleeping; a longer one is dropped (the
  world waited; docs/decisions.md D140).
* :class:`RealTimeClock`: sleeps until shortly before each deadline, then spins to it (sleep alone
  wakes up 50-100 us late on Linux). A tick that starts after the deadline it was due at overran.
  The clock counts every deadline that passed before the tick started (a 20 ms stall at 1 kHz
  misses 20 deadlines, not one) and skips the missed ones instead of bursting to catch up; the
  loop's watchdog turns too many missed deadlines in a row, or one long stall, into a fault.

A clock says whether it runs lock-step (:attr:`Clock.virtual`: ticks start at once) and whether
it needs a backend that owns its time (:attr:`Clock.needs_virtual_time`: lock-step and paced); a
HAL backend says whether it owns its time (:attr:`hal.interface.Hal.virtual_time`).
:func:`check_clock` refuses a clock that needs virtual time on a backend whose time is the wall
clock's (hardware, a bus): there a stall is a stall of the drives' commands and only the real-time
clock's watchdog may run. :func:`clock_for` picks the clock a backend runs on by default,
:func:`session_clock` the clock of a console session.

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


class PacingStats(NamedTuple):
    """How a paced virtual clock kept up with the wall clock since :meth:`Clock.start` (a read-only snapshot).

    Attributes:
        stalls: times the process held the simulated world so long that the real-time clock's
            watchdog would have faulted that one stall (a tick ``stall_periods`` periods or more
            past its place on the grid; one stall however many ticks its catch-up takes); never faults.
        lag_s: how far the world is behind its grid now, in s (0 when on time; at most the
            clock's ``max_catch_up_s``: it is being caught up).
        worst_lag_s: the longest a tick started after its place on the grid, in s (the longest stall).
        behind_s: how far the world's time is behind the wall clock since the start, in s: the lags
            dropped (stalls longer than ``max_catch_up_s``) plus the current lag.
    """

    stalls: int
    lag_s: float
    worst_lag_s: float
    behind_s: float


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

    #: What the status and the audit log call this clock.
    name = "real time"

    @property
    def virtual(self) -> bool:
        """True for virtual time: ticks start at once, one after the other, and time is the backend's (lock-step).

        Only a backend that owns its time (:attr:`hal.interface.Hal.virtual_time`) can run on it.
        """
        return False

    @property
    def needs_virtual_time(self) -> bool:
        """True when the backend's time must be its own (lock-step and paced): a stall of the loop stalls its world.

        :func:`check_clock` refuses such a clock on a backend whose time is the wall clock's.
        """
        return self.virtual

    @property
    def pacing(self) -> PacingStats | None:
        """How a paced clock kept up with the wall clock (:class:`PacedClock`); None for the other clocks."""
        return None

    @abstractmethod
    def start(self) -> None:
        """Start counting (and reset the totals); the first :meth:`wait` returns at once as tick 0, at deadline 0."""

    @abstractmethod
    def wait(self) -> TickTiming:
        """Return at the start of the next tick (a clock never started starts at its first wait)."""

    def until_quiet_s(self) -> float:
        """Seconds until the loop is between ticks and not about to wake (0: now, or no such time).

        Other threads of the loop's process do their short work then (:meth:`LoopRunner.add_publisher`):
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

    name = "lock-step"

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


class _WallClock(Clock):
    """Ticks on the wall clock's grid: sleep, then spin the last ``spin_s`` to each tick's place on it.

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

    def _first_ticks(self, index: int) -> TickTiming:
        """Tick 0 (``index`` -1) or tick 1 (``index`` 0), both at once; the grid starts one period before tick 1."""
        period = self.period_s
        if index < 0:
            self._next = 0
            tick = 0
        else:
            self._t0 = self._now() - period
            self._next = 2
            tick = 1
        self.ticks += 1
        return TickTiming(tick, tick * period, 0.0, False, 0, 0)

    def _sleep_until(self, due: float, now: float) -> float:
        """Sleep until ``spin_s`` before ``due`` (the time source's s), then spin to it; returns the time it woke at."""
        remaining = due - now
        if remaining > self.spin_s:
            self._sleep(remaining - self.spin_s)
        now = self._now()
        while now < due:
            now = self._now()
        return now


class RealTimeClock(_WallClock):
    """Wall-clock ticks with deadlines the robot depends on: a tick that starts late overran.

    A late tick counts every deadline that passed before it started and takes the most recent slot
    (the missed ones are skipped, not burst through); the loop's watchdog judges the counts. See
    :class:`_WallClock` for the grid, its anchor and the arguments.

    Raises:
        ConfigurationError: the period is not positive.
    """

    def wait(self) -> TickTiming:
        index = self._next
        period = self.period_s
        if index <= 0:  # tick 0 at once; tick 1 at once too, and the grid starts one period before it
            return self._first_ticks(index)
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
        lateness = self._sleep_until(due, now) - due
        if lateness > self.worst_lateness_s:
            self.worst_lateness_s = lateness
        self._next = index + 1
        self.ticks += 1
        return TickTiming(index, index * period, lateness, False, 0, 0)


#: The longest lag a paced clock catches up by starting ticks without sleeping, s (D140). At ~0.1 ms
#: of work per tick at 1 kHz, 50 ms of lag is made up in ~5 ms: no one watching sees the burst.
DEFAULT_MAX_CATCH_UP_S = 0.05


class PacedClock(_WallClock):
    """Virtual time paced to the wall clock: tick ``k`` starts ``k`` periods after the grid's anchor, never earlier.

    The backend's time advances one period per tick whatever the wall clock did (it owns its time:
    :func:`check_clock`), so no tick is ever skipped and nothing is an overrun: a tick that starts
    late is a stall of the simulated world with the process, counted in :attr:`pacing` and recorded
    as the tick's lateness. The lag is caught up by starting the following ticks without sleeping
    (each makes up a period less its own work), unless it is longer than ``max_catch_up_s``: then it
    is dropped (the grid moves on; the world stays behind the wall clock by that much). A stall is a
    tick that starts ``stall_periods`` periods or more late, what the real-time watchdog faults as
    one stall (:data:`daror_runtime.loop.DEFAULT_MAX_STALL_PERIODS`): the figure says what a
    real-time session would have failed on; one stall however many ticks its catch-up takes.

    Args:
        period_s: tick period in s (1 ms at 1 kHz).
        max_catch_up_s: the longest lag caught up, s; a longer one is dropped (0: drop every lag).
        stall_periods: how late a tick starts, in periods, to count as a stall (at least 1).
        spin_s: how long before a tick's place to stop sleeping and start spinning, in s.
        now: monotonic time source in s (injectable for tests).
        sleep: sleep function taking s (injectable for tests).

    Raises:
        ConfigurationError: the period is not positive, ``max_catch_up_s`` is negative, or
            ``stall_periods`` below 1.
    """

    name = "paced"

    def __init__(
        self,
        period_s: float,
        max_catch_up_s: float = DEFAULT_MAX_CATCH_UP_S,
        stall_periods: int = 3,
        spin_s: float = 3e-4,
        now: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        super().__init__(period_s, spin_s, now, sleep)
        if not max_catch_up_s >= 0.0:
            raise ConfigurationError(f"max_catch_up_s must be at least 0 s, got {max_catch_up_s} s")
        if stall_periods < 1:
            raise ConfigurationError(f"stall_periods must be at least 1, got {stall_periods}")
        self.max_catch_up_s = max_catch_up_s
        self.stall_periods = stall_periods
        self._stall_s = stall_periods * period_s

    @property
    def needs_virtual_time(self) -> bool:
        return True

    @property
    def pacing(self) -> PacingStats:
        lag = self._lag_s
        return PacingStats(self.stalls, lag, self.worst_lateness_s, self.dropped_s + lag)

    def _reset_totals(self) -> None:
        super()._reset_totals()
        self.stalls = 0
        self.dropped_s = 0.0  # the lags dropped rather than caught up, s
        self._lag_s = 0.0
        self._stalled = False

    def wait(self) -> TickTiming:
        index = self._next
        period = self.period_s
        if index <= 0:  # tick 0 at once; tick 1 at once too, and the grid starts one period before it
            return self._first_ticks(index)
        due = self._t0 + index * period
        now = self._now()
        lateness = now - due
        if lateness > 0.0:  # the world waited for the process: start at once
            if lateness >= self._stall_s:
                if not self._stalled:
                    self.stalls += 1
                    self._stalled = True
            else:
                self._stalled = False
            if lateness > self.worst_lateness_s:
                self.worst_lateness_s = lateness
            if lateness > self.max_catch_up_s:  # too long to catch up: the grid moves on, this tick is on it
                self._t0 += lateness
                self.dropped_s += lateness
                self._lag_s = 0.0
            else:  # made up by the next ticks, which start without sleeping until the grid is reached
                self._lag_s = lateness
        else:
            self._stalled = False
            self._lag_s = 0.0
            lateness = self._sleep_until(due, now) - due
            if lateness > self.worst_lateness_s:
                self.worst_lateness_s = lateness
        self._next = index + 1
        self.ticks += 1
        # TickTiming(index, deadline, lateness, overrun, consecutive, missed), every field in order
        return _new_tuple(TickTiming, (index, index * period, lateness, False, 0, 0))


class LockStepRefusedError(UsageError):
    """Lock-step (a virtual clock) was asked for on a backend whose time is the wall clock's."""


def check_clock(clock: Clock, hal: Hal) -> None:
    """Refuse a clock that needs virtual time (lock-step, paced) on a backend that does not own its time.

    A lock-step clock starts each tick as soon as the previous one ends; on hardware that would send
    commands as fast as the CPU allows, with the time in every sample passing at its own pace. A
    paced clock takes a stall for the world's and never faults it; on hardware the drives would
    hold the last command through the stall with no watchdog to stop them.

    Raises:
        LockStepRefusedError: ``clock`` needs virtual time and ``hal`` does not own its time (one
            line, naming the backend).
    """
    if clock.needs_virtual_time and not hal.virtual_time:
        what = "drives hardware" if hal.drives_hardware else "runs on wall-clock time"
        backend = f"the {hal.kind or type(hal).__name__} HAL backend {what}"
        if clock.virtual:
            raise LockStepRefusedError(
                f"{backend}: it cannot run lock-step (virtual time); run it in real time (daror console --realtime)"
            )
        raise LockStepRefusedError(
            f"{backend}: it cannot run on the {clock.name} clock (virtual time, stalls not watched); "
            "run it in real time (--clock realtime)"
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


#: The clocks a console session may be asked for (``daror console --clock``): paced virtual time,
#: the real-time clock with its overrun watchdog, lock-step virtual time.
CLOCK_CHOICES = ("paced", "realtime", "lockstep")


def session_clock(hal: Hal, choice: str | None, live: bool) -> Clock:
    """The clock of a console session on ``hal`` at its rate: ``choice``, or the default for how the session runs.

    The default (D142): a live session (typed at a terminal, or served on the web) runs paced on a
    backend that owns its time (a stall of a busy PC is not a fault of a simulated robot) and in
    real time on one that does not (hardware: the watchdog stands); a script or piped lines run
    lock-step, as fast as the CPU allows (refused on hardware: ``--clock realtime``).

    Args:
        hal: the backend (not opened yet).
        choice: one of :data:`CLOCK_CHOICES`, or None for the default.
        live: a person watches the session as it runs: its loop runs on its own thread.

    Raises:
        UsageError: an unknown ``choice``, or ``lockstep`` for a live session (its ticks would run
            as fast as the CPU allows while a person watches).
        LockStepRefusedError: ``paced`` or ``lockstep`` on a backend that does not own its time.
    """
    if choice is None:
        choice = ("paced" if hal.virtual_time else "realtime") if live else "lockstep"
    period = 1.0 / hal.rate_hz
    if choice == "paced":
        clock: Clock = PacedClock(period)
    elif choice == "realtime":
        clock = RealTimeClock(period)
    elif choice == "lockstep":
        if live:
            raise UsageError(
                "--clock lockstep runs ticks only between the lines of a script or a pipe; a session typed at a "
                "terminal or served on the web runs its loop by itself: expected --clock paced or realtime"
            )
        clock = LockStepClock(period)
    else:
        raise UsageError(f"--clock {choice!r}: expected one of {', '.join(CLOCK_CHOICES)}")
    check_clock(clock, hal)
    return clock
