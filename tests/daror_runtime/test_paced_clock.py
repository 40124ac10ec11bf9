"""Issue 24, defect 5: a simulated session on a busy PC runs on virtual time paced to the wall clock.

A stall of the process delays the simulated world, is counted and shown (loop status,
``session.json``), and is not a fault; the same stall on the real-time clock still faults; a paced
clock is refused on hardware. Every test runs on a patched time source: deterministic whatever the
machine's load.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from daror_runtime.cli import main
from daror_runtime.clocks import (
    DEFAULT_MAX_CATCH_UP_S,
    Clock,
    LockStepRefusedError,
    PacedClock,
    RealTimeClock,
    check_clock,
    session_clock,
)
from daror_runtime.errors import ConfigurationError, UsageError
from daror_runtime.logs import configure_logging
from daror_runtime.loop import DEFAULT_MAX_STALL_PERIODS, TickResult
from daror_runtime.runtime import Runtime
from hal.sim.backend import SimHal
from tests.standin_drives import StandInDrives

PERIOD_S = 1e-3


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


@pytest.fixture(autouse=True)
def default_logging() -> Iterator[None]:
    """``main`` configures logging for the process; put the defaults back afterwards."""
    yield
    configure_logging()


def _paced(fake: FakeTime, **kwargs: float) -> PacedClock:
    clock = PacedClock(PERIOD_S, now=fake.now, sleep=fake.sleep, **kwargs)
    clock.start()
    clock.wait()
    clock.wait()  # tick 1: the grid starts
    return clock


# --- the clock ----------------------------------------------------------------------------------


def test_paced_ticks_sleep_then_spin_to_their_place_on_the_grid() -> None:
    fake = FakeTime()
    clock = _paced(fake)
    for expected in range(2, 8):
        timing = clock.wait()
        assert timing.index == expected
        assert timing.deadline_s == pytest.approx(expected * PERIOD_S)
        assert 0.0 <= timing.lateness_s < 5e-6
        assert not timing.overrun
    assert all(s == pytest.approx(PERIOD_S - 3e-4, abs=2e-5) for s in fake.slept)
    assert clock.pacing == (0, 0.0, clock.worst_lateness_s, 0.0)
    assert clock.name == "paced"
    assert not clock.virtual  # it waits for the wall clock: not lock-step
    assert clock.needs_virtual_time


def test_a_20_ms_stall_is_one_stall_caught_up_without_sleeping_and_never_an_overrun() -> None:
    fake = FakeTime()
    clock = _paced(fake)
    clock.wait()  # tick 2, on time
    fake.t += 0.020  # the process stalls 20 ms after tick 2
    late = clock.wait()
    assert late.index == 3  # the world's next tick: nothing skipped on virtual time
    assert late.deadline_s == pytest.approx(3 * PERIOD_S)
    assert late.lateness_s == pytest.approx(0.019, abs=1e-4)  # tick 3 was due 1 ms after tick 2
    assert (late.overrun, late.consecutive_overruns, late.missed_deadlines) == (False, 0, 0)
    assert clock.pacing.stalls == 1
    assert clock.pacing.lag_s == pytest.approx(0.019, abs=1e-4)
    slept = len(fake.slept)
    # catching up: each tick costs 0.1 ms of work and starts at once until the grid is reached
    lags = []
    while True:
        fake.t += 1e-4
        timing = clock.wait()
        lags.append(timing.lateness_s)
        if timing.lateness_s < 1e-5:
            break
    assert len(fake.slept) == slept + 1  # no sleep until the tick that is on the grid again
    assert all(a > b for a, b in itertools.pairwise(lags))  # the lag shrinks tick by tick
    assert len(lags) == pytest.approx(0.019 / 0.9e-3, abs=2)  # 0.9 ms made up per tick
    pacing = clock.pacing
    assert pacing.stalls == 1  # one stall however many ticks its catch-up took
    assert pacing.lag_s == 0.0
    assert pacing.behind_s == 0.0  # caught up: the world's time is the wall clock's again
    assert pacing.worst_lag_s == pytest.approx(0.019, abs=1e-4)
    stats = clock.stats
    assert (stats.overruns, stats.missed_deadlines, stats.skipped_deadlines) == (0, 0, 0)
    assert stats.worst_lateness_s == pacing.worst_lag_s


def test_a_stall_longer_than_the_catch_up_bound_is_dropped_the_world_waited() -> None:
    fake = FakeTime()
    clock = _paced(fake)
    fake.t += 0.200  # 200 ms: a stall of the whole machine
    late = clock.wait()
    assert late.index == 2
    assert late.lateness_s == pytest.approx(0.199, abs=1e-4)
    pacing = clock.pacing
    assert (pacing.stalls, pacing.lag_s) == (1, 0.0)
    assert pacing.behind_s == pytest.approx(0.199, abs=1e-4)  # the world stays that far behind the wall clock
    slept = len(fake.slept)
    after = clock.wait()  # paced again on the moved grid: a sleep, on time
    assert after.index == 3
    assert 0.0 <= after.lateness_s < 5e-6
    assert len(fake.slept) == slept + 1
    assert DEFAULT_MAX_CATCH_UP_S == 0.05


def test_a_stall_is_what_the_watchdog_would_fault_alone_and_start_resets_the_figures() -> None:
    """3 periods late or more: the real-time watchdog faults such a stall (loop.DEFAULT_MAX_STALL_PERIODS)."""
    fake = FakeTime()
    clock = _paced(fake)
    assert clock.stall_periods == DEFAULT_MAX_STALL_PERIODS
    for late_s, stalls in ((0.0004, 0), (0.0029, 0), (0.0031, 1), (0.0040, 2)):
        fake.t += PERIOD_S + late_s  # the last tick started on the grid: the next is due a period later
        assert clock.wait().lateness_s == pytest.approx(late_s, abs=1e-5)
        assert clock.pacing.stalls == stalls, late_s
        while clock.wait().lateness_s > 1e-5:  # caught up: back on the grid, the stall has ended
            pass
    assert clock.pacing.worst_lag_s == pytest.approx(0.0040, abs=1e-5)
    clock.start()
    assert clock.pacing == (0, 0.0, 0.0, 0.0)
    assert clock.stats == (0, 0, 0, 0, 0.0)


def test_the_catch_up_bound_and_the_stall_are_checked() -> None:
    with pytest.raises(ConfigurationError, match="max_catch_up_s must be at least 0 s, got -1"):
        PacedClock(PERIOD_S, max_catch_up_s=-1.0)
    with pytest.raises(ConfigurationError, match="stall_periods must be at least 1, got 0"):
        PacedClock(PERIOD_S, stall_periods=0)


def test_the_other_clocks_report_no_pacing() -> None:
    assert RealTimeClock(PERIOD_S).pacing is None
    assert not RealTimeClock(PERIOD_S).needs_virtual_time


# --- which clock, and where ------------------------------------------------------------------------


def test_a_paced_clock_is_refused_on_hardware_in_one_line() -> None:
    with pytest.raises(LockStepRefusedError) as caught:
        check_clock(PacedClock(PERIOD_S), StandInDrives())
    assert str(caught.value) == (
        "the stand-in HAL backend drives hardware: it cannot run on the paced clock (virtual time, stalls not "
        "watched); run it in real time (--clock realtime)"
    )
    check_clock(PacedClock(PERIOD_S), SimHal("exo"))


@pytest.mark.parametrize(
    ("hardware", "choice", "live", "name"),
    [
        (False, None, True, "paced"),  # typed at a terminal or on the web, simulated: paced
        (False, None, False, "lock-step"),  # a script or a pipe: lock-step, as fast as the CPU allows
        (True, None, True, "real time"),  # hardware: the watchdog stands
        (False, "realtime", True, "real time"),  # rehearsing the timing on the simulated plant
        (False, "paced", False, "paced"),
        (True, "realtime", False, "real time"),
    ],
)
def test_the_session_clock_by_default_and_on_request(hardware: bool, choice: str | None, live: bool, name: str) -> None:
    hal = StandInDrives() if hardware else SimHal("exo")
    clock: Clock = session_clock(hal, choice, live)
    assert clock.name == name
    assert clock.period_s == pytest.approx(1.0 / hal.rate_hz)


def test_the_session_clock_refuses_what_cannot_run() -> None:
    with pytest.raises(LockStepRefusedError, match="cannot run on the paced clock"):
        session_clock(StandInDrives(), "paced", True)
    with pytest.raises(LockStepRefusedError, match="cannot run lock-step"):
        session_clock(StandInDrives(), None, False)  # a script on hardware: --clock realtime
    with pytest.raises(UsageError, match="--clock lockstep runs ticks only between the lines of a script or a pipe"):
        session_clock(SimHal("exo"), "lockstep", True)
    with pytest.raises(UsageError, match="--clock 'fast': expected one of paced, realtime, lockstep"):
        session_clock(SimHal("exo"), "fast", False)


# --- a session: the defect -------------------------------------------------------------------------


def _session_with_a_stall(tmp_path: Path, clock_kind: type[RealTimeClock] | type[PacedClock]) -> Runtime:
    """A session's loop on a patched wall clock: 300 ticks, the process stalls 20 ms after tick 100."""
    fake = FakeTime()
    runtime = Runtime(SimHal("exo_dummy_arm"), tmp_path / clock_kind.__name__, clock=clock_kind(
        PERIOD_S, now=fake.now, sleep=fake.sleep))  # fmt: skip

    def stall_once(result: TickResult) -> bool:
        if result.timing.index == 100:
            fake.t += 0.020
        return False

    runtime.open()
    runtime.runner.run_ticks(300, stop=stall_once)
    return runtime


def test_a_paced_session_whose_process_stalls_counts_the_stall_and_does_not_fail(tmp_path: Path) -> None:
    runtime = _session_with_a_stall(tmp_path, PacedClock)
    try:
        status = runtime.snapshot()
        assert status.state == "startup"
        assert status.faults == []
        loop = status.loop
        assert loop.clock == "paced"
        assert (loop.ticks, loop.overruns, loop.missed_deadlines, loop.stalls) == (300, 0, 0, 1)
        assert loop.worst_lateness_ms == pytest.approx(19.0, abs=0.2)
        assert (loop.lag_ms, loop.behind_ms) == (0.0, 0.0)  # caught up within the 300 ticks
        assert status.t_s == pytest.approx(0.299)  # the world's time: one period per tick, nothing skipped
    finally:
        runtime.shutdown("test done")
        runtime.close()
    saved = json.loads((tmp_path / "PacedClock" / "session.json").read_text())
    assert saved["loop"]["clock"] == "paced"
    assert saved["loop"]["stalls"] == 1
    assert saved["loop"]["overruns"] == 0
    assert saved["faults"] == []


def test_the_same_stall_on_the_real_time_clock_still_faults(tmp_path: Path) -> None:
    runtime = _session_with_a_stall(tmp_path, RealTimeClock)
    try:
        status = runtime.snapshot()
        assert status.state == "FAIL"
        assert [f["kind"] for f in status.faults] == ["overrun"]
        assert (
            "the loop stalled 19.0 ms past a deadline: 20 deadlines of 1 ms missed at once"
            in (status.faults[0]["message"])
        )
        assert (status.loop.clock, status.loop.overruns, status.loop.stalls) == ("real time", 1, 0)
    finally:
        runtime.shutdown("test done")
        runtime.close()


# --- the command line ----------------------------------------------------------------------------


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    assert "Traceback" not in err
    return err


def test_daror_console_refuses_the_paced_clock_on_can_before_anything_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text("backend: can\ninterface: socketcan\nchannel: can9\n")
    script = tmp_path / "s.txt"
    script.write_text("status\n")
    out = tmp_path / "session"
    argv = ["console", "--hal-config", str(config), "--script", str(script), "--out", str(out)]
    assert main([*argv, "--clock", "paced"]) == 2
    assert _one_line_error(capsys) == (
        "daror console: error: the can HAL backend drives hardware: it cannot run on the paced clock (virtual time, "
        "stalls not watched); run it in real time (--clock realtime)"
    )
    assert not out.exists()
    assert main([*argv, "--realtime", "--clock", "paced"]) == 2
    assert _one_line_error(capsys) == (
        "daror console: error: --realtime is --clock realtime; it contradicts --clock paced: give one of them"
    )
    assert not out.exists()


def test_daror_console_clock_paced_runs_a_script_live_on_the_paced_clock(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    script = tmp_path / "s.txt"
    script.write_text("status\n")
    out = tmp_path / "session"
    assert main(["console", "--clock", "paced", "--script", str(script), "--out", str(out)]) == 0
    loop = json.loads((out / "session.json").read_text())["loop"]
    assert loop["clock"] == "paced"
    assert loop["overruns"] == 0
    assert "loop: paced at 1000 Hz" in capsys.readouterr().out  # the status view names the clock
