"""Tick clocks: real time and lock-step (virtual) time. The same loop code runs under both.

* :class:`LockStepClock`: virtual time, as fast as the CPU allows. Used by tests, by the
  identification protocol in simulation and by the demo; time is owned by the simulated plant
  (Drake style), the clock only counts ticks.
* :class:`RealTimeClock`: sleeps until shortly before each deadline, then spins to it (sleep alone
  wakes up 50-100 us late on Linux). A tick that starts after the *next* deadline has passed
  overran; the clock counts overruns and consecutive overruns (the loop turns too many in a row
  into a fault) and skips missed deadlines instead of bursting to catch up.

Deadlines are ``start + k * period`` on one grid, so lateness never accumulates.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import NamedTuple

from daror_runtime.errors import ConfigurationError


class TickTiming(NamedTuple):
    """When a tick started relative to its deadline (a NamedTuple: built every tick, it must be cheap)."""

    index: int
    deadline_s: float  # since the clock started
    lateness_s: float  # start - deadline; 0 in lock-step
    overrun: bool  # the previous tick's work ran past this tick's deadline
    consecutive_overruns: int


class Clock(ABC):
    def __init__(self, period_s: float) -> None:
        if not period_s > 0:
            raise ConfigurationError(f"tick period must be positive, got {period_s} s")
        self.period_s = period_s
        self.ticks = 0
        self.overruns = 0
        self.skipped_deadlines = 0
        self._consecutive = 0

    @abstractmethod
    def start(self) -> None:
        """Start counting; the first :meth:`wait` returns at deadline 0."""

    @abstractmethod
    def wait(self) -> TickTiming:
        """Return at the start of the next tick."""


class LockStepClock(Clock):
    """Virtual time: every tick starts exactly on its deadline, immediately."""

    def start(self) -> None:
        self.ticks = 0

    def wait(self) -> TickTiming:
        index = self.ticks
        self.ticks = index + 1
        return TickTiming(index, index * self.period_s, 0.0, False, 0)


class RealTimeClock(Clock):
    """Wall-clock ticks: sleep, then spin the last ``spin_s`` to the deadline.

    Args:
        period_s: tick period (1 ms at 1 kHz).
        spin_s: how long before a deadline to stop sleeping and start spinning.
        now: monotonic time source in seconds (injectable for tests).
        sleep: sleep function (injectable for tests).
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
        self._next = 0

    def start(self) -> None:
        self.ticks = 0
        self._next = 0
        self._consecutive = 0
        self._t0 = self._now()

    def wait(self) -> TickTiming:
        index = self._next
        deadline = self._t0 + index * self.period_s
        now = self._now()
        overrun = index > 0 and now > deadline
        if overrun:
            self.overruns += 1
            self._consecutive += 1
            behind = math.floor((now - deadline) / self.period_s)
            if behind > 0:  # start on the most recent deadline rather than burst through the missed ones
                self.skipped_deadlines += behind
                index += behind
                deadline += behind * self.period_s
        else:
            self._consecutive = 0
            remaining = deadline - now
            if remaining > self.spin_s:
                self._sleep(remaining - self.spin_s)
            while self._now() < deadline:
                pass
        started = self._now()
        self._next = index + 1
        self.ticks += 1
        return TickTiming(index, deadline - self._t0, started - deadline, overrun, self._consecutive)
