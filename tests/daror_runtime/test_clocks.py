"""Clocks: lock-step virtual time and the real-time clock's deadline, overrun, missed-deadline and skip logic."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

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
    clock.wait()  # tick 1 at 1 ms: the grid starts
    fake.t += 0.0035  # the tick's work took 3.5 ms: deadlines 2 ms, 3 ms and 4 ms passed
    late = clock.wait()
    assert late.overrun
    assert late.index == 4  # deadlines 2 and 3 were skipped, not burst through
    assert late.deadline_s == pytest.approx(0.004)
    assert late.missed_deadlines == 3  # the two skipped ones and its own late start
    assert late.consecutive_overruns == 3  # missed deadlines in a row, not late wake-ups
    assert late.lateness_s == pytest.approx(0.0025, abs=1e-5)  # against the deadline it was due at (2 ms)
    assert clock.skipped_deadlines == 2
    fake.t += 0.0012  # 1.2 ms of work from 4.5 ms: due at 5 ms, starts at 5.7 ms
    again = clock.wait()
    assert again.overrun
    assert again.missed_deadlines == 1
    assert again.consecutive_overruns == 4
    assert again.lateness_s == pytest.approx(0.0007, abs=1e-5)
    on_time = clock.wait()
    assert not on_time.overrun
    assert on_time.consecutive_overruns == 0
    assert on_time.missed_deadlines == 0
    assert clock.overruns == 2
    stats = clock.stats
    assert (stats.ticks, stats.overruns, stats.missed_deadlines, stats.skipped_deadlines) == (5, 2, 4, 2)
    assert stats.worst_lateness_s == pytest.approx(0.0025, abs=1e-5)


def test_a_20_ms_stall_misses_20_deadlines_and_is_20_ms_late() -> None:
    """The tester's case: one long stall is one late wake-up but 20 missed deadlines and ~20 ms late."""
    fake = FakeTime()
    clock = RealTimeClock(0.001, now=fake.now, sleep=fake.sleep)
    clock.start()
    clock.wait()
    clock.wait()  # on time at 1 ms
    fake.t += 0.0205  # the tick's work stalled: 20.5 ms, so the next tick (due at 2 ms) starts at 21.5 ms
    stalled = clock.wait()
    assert stalled.overrun
    assert stalled.missed_deadlines == 20  # due at 2 ms, 19 skipped (3..21 ms), its own late start
    assert stalled.consecutive_overruns == 20
    assert stalled.lateness_s == pytest.approx(0.0195, abs=1e-5)
    assert stalled.index == 21
    assert clock.stats.worst_lateness_s == pytest.approx(0.0195, abs=1e-5)
    assert clock.stats.missed_deadlines == 20
    assert clock.stats.overruns == 1


def test_the_grid_starts_when_the_first_tick_ends() -> None:
    """A session opens (start) well before its loop thread's first tick, and that tick runs cold
    (first calls load compiled code): neither is a stall, no command of the loop was on the drives."""
    fake = FakeTime()
    clock = RealTimeClock(0.001, now=fake.now, sleep=fake.sleep)
    clock.start()
    fake.t += 0.2  # the console is built
    first = clock.wait()
    fake.t += 0.04  # the first tick's work: 40 ms, cold
    timings = [first] + [clock.wait() for _ in range(3)]
    assert [(t.index, t.overrun, t.missed_deadlines) for t in timings] == [(i, False, 0) for i in range(4)]
    assert [t.lateness_s for t in timings[:2]] == [0.0, 0.0]
    assert clock.stats.worst_lateness_s < 5e-6
    fake.t += 0.04  # the same after tick 1 is a stall
    assert clock.wait().missed_deadlines == 40


def test_start_resets_the_totals_and_lock_step_reports_zeros() -> None:
    fake = FakeTime()
    clock = RealTimeClock(0.001, now=fake.now, sleep=fake.sleep)
    clock.start()
    clock.wait()
    clock.wait()
    fake.t += 0.005
    clock.wait()
    assert clock.stats.overruns == 1
    clock.start()
    assert clock.stats == (0, 0, 0, 0, 0.0)
    lock_step = LockStepClock(0.001)
    lock_step.start()
    timings = [lock_step.wait() for _ in range(100)]
    assert all(t.missed_deadlines == 0 and t.consecutive_overruns == 0 for t in timings)
    assert lock_step.stats == (100, 0, 0, 0, 0.0)


def test_period_must_be_positive() -> None:
    with pytest.raises(ConfigurationError):
        LockStepClock(0.0)


def test_a_real_time_clock_never_started_starts_at_its_first_wait() -> None:
    """Without start(), the grid must not begin at time 0 (that would be one stall of the machine's uptime)."""
    fake = FakeTime()
    clock = RealTimeClock(0.001, now=fake.now, sleep=fake.sleep)
    timings = [clock.wait() for _ in range(3)]
    assert [t.index for t in timings] == [0, 1, 2]
    assert not any(t.overrun for t in timings)
    assert clock.stats.missed_deadlines == 0


@given(phase_fraction=st.floats(0.0, 0.999), ticks=st.integers(2, 50))
def test_until_quiet_lands_in_the_part_of_the_period_where_the_loop_sleeps(phase_fraction: float, ticks: int) -> None:
    """Other threads of the loop's process wait for the quiet part (after the tick's work, before the spin)."""
    fake = FakeTime(cost_s=1e-7)
    clock = RealTimeClock(0.001, spin_s=3e-4, now=fake.now, sleep=fake.sleep)
    clock.start()
    assert clock.until_quiet_s() == 0.0  # no grid yet: nothing to avoid
    for _ in range(ticks):
        timing = clock.wait()
    deadline = fake.t - timing.lateness_s  # the spin ends within a clock reading after the deadline
    fake.t = deadline + phase_fraction * 0.001
    delay = clock.until_quiet_s()
    assert 0.0 <= delay < 0.001
    arrived = ((fake.t + delay - deadline) % 0.001) / 0.001
    assert 0.35 - 1e-3 <= arrived <= 0.65 + 1e-3  # after 0.35 ms of tick work, before the spin at 0.7 ms
    if 0.351 <= phase_fraction <= 0.649:
        assert delay == 0.0


def test_lock_step_is_always_quiet() -> None:
    clock = LockStepClock(0.001)
    clock.start()
    clock.wait()
    clock.wait()
    assert clock.until_quiet_s() == 0.0
