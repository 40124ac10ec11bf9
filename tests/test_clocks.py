"""Clocks: lock-step virtual time and the real-time clock's deadline, overrun and skip logic."""

from __future__ import annotations

import pytest

from daror_runtime.clocks import LockStepClock, RealTimeClock
from daror_runtime.errors import ConfigurationError


class FakeTime:
    """A controllable monotonic clock: sleeping advances it, every reading costs ``cost_s``."""

    def __init__(self, cost_s: float = 1e-6) -> None:
        self.t = 100.0
        self.cost_s = cost_s
        self.slept: list[float] = []

    def now(self) -> float:
        self.t += self.cost_s
        return self.t

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.t += seconds + 5e-5  # the OS wakes us 50 us late


def test_lock_step_ticks_are_on_time_and_numbered() -> None:
    clock = LockStepClock(0.001)
    clock.start()
    timings = [clock.wait() for _ in range(5)]
    assert [t.index for t in timings] == [0, 1, 2, 3, 4]
    assert [t.deadline_s for t in timings] == pytest.approx([0.0, 0.001, 0.002, 0.003, 0.004])
    assert all(t.lateness_s == 0.0 and not t.overrun for t in timings)


def test_real_time_sleeps_then_spins_to_the_deadline() -> None:
    fake = FakeTime()
    clock = RealTimeClock(0.001, spin_s=3e-4, now=fake.now, sleep=fake.sleep)
    clock.start()
    first = clock.wait()
    assert first.index == 0
    for expected in range(1, 6):
        timing = clock.wait()
        assert timing.index == expected
        assert timing.deadline_s == pytest.approx(expected * 0.001)
        assert 0.0 <= timing.lateness_s < 5e-6  # spinning lands within a clock reading of the deadline
        assert not timing.overrun
    # it slept until 0.3 ms before each deadline, and the OS's 50 us lateness was absorbed by the spin
    assert all(s == pytest.approx(0.001 - 3e-4, abs=2e-5) for s in fake.slept[1:])


def test_overruns_are_counted_and_missed_deadlines_skipped() -> None:
    fake = FakeTime()
    clock = RealTimeClock(0.001, now=fake.now, sleep=fake.sleep)
    clock.start()
    clock.wait()
    fake.t += 0.0035  # the tick's work took 3.5 ms
    late = clock.wait()
    assert late.overrun
    assert late.consecutive_overruns == 1
    assert late.index == 3  # deadlines 1 and 2 were skipped, not burst through
    assert clock.skipped_deadlines == 2
    assert late.lateness_s == pytest.approx(0.0005, abs=1e-5)
    fake.t += 0.0012
    again = clock.wait()
    assert again.overrun
    assert again.consecutive_overruns == 2
    on_time = clock.wait()
    assert not on_time.overrun
    assert on_time.consecutive_overruns == 0
    assert clock.overruns == 2


def test_period_must_be_positive() -> None:
    with pytest.raises(ConfigurationError):
        LockStepClock(0.0)
