"""The overrun watchdog counts missed deadlines (defect 5) and the FSM's request queue is bounded (defect 6).

Defect 5: "One 20 ms stall counts as one overrun, so the '5 consecutive overruns' fault never
fires, and recorded lateness hides skipped deadlines." Time here is a fake monotonic clock
(``tests/daror_runtime/test_clocks.py``): a stall is an exact jump of it, so every test is deterministic; the
loop is the real ``ControlLoop`` over the simulated plant (torque at the drives) or over the
scripted HAL of ``tests/daror_runtime/fsm/test_fsm_properties.py`` (the property test: many short loops).

Defect 6: "10^5 posted advance requests took 12 s inside one tick." The tests assert what bounds
a tick's cost (the number of requests applied per tick, refusals at the post), never wall time;
``bench/bench_fsm.py`` measures the time.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import structlog
from hypothesis import given, settings
from hypothesis import strategies as st

from daror_runtime.clocks import LockStepClock, RealTimeClock, TickTiming
from daror_runtime.data.tick_row import RECORD_COLUMNS
from daror_runtime.errors import ConfigurationError
from daror_runtime.fsm.machine import Event
from daror_runtime.fsm.supervisor import (
    DEFAULT_MAX_PENDING_REQUESTS,
    DEFAULT_MAX_REQUESTS_PER_TICK,
    FsmSupervisor,
    Response,
    Ticket,
)
from daror_runtime.logs import configure_logging
from daror_runtime.loop import (
    DEFAULT_MAX_STALL_PERIODS,
    DEFAULT_OVERRUN_LIMIT,
    ControlLoop,
    FixedSupervisor,
    TickResult,
)
from daror_runtime.safety.faults import FaultKind
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from hal.interface import Command, Sample
from tests.daror_runtime.fsm.test_fsm_properties import DESCRIPTION, FAIL, AskForTorque, FsmInTheTick, ScriptedHal
from tests.daror_runtime.safety.test_safety_loop import DT, HoldController, build, run_until_fault, settle
from tests.daror_runtime.test_clocks import FakeTime

FLOOD = 100_000
LATENESS = RECORD_COLUMNS.index("lateness_s")


# --- defect 5: the overrun watchdog ----------------------------------------------------------


class RowsRecorder:
    """Keeps a copy of every row the loop pushes."""

    def __init__(self) -> None:
        self.rows: list[np.ndarray] = []

    def push(self, row: np.ndarray) -> bool:
        self.rows.append(row.copy())
        return True


class Paced:
    """A loop over the scripted HAL on fake time, where the test says how late each next tick starts."""

    def __init__(self, overrun_limit: int = DEFAULT_OVERRUN_LIMIT, max_stall: int = DEFAULT_MAX_STALL_PERIODS) -> None:
        self.fake = FakeTime(cost_s=1e-7)
        self.clock = RealTimeClock(DT, now=self.fake.now, sleep=self.fake.sleep)
        monitor = SafetyMonitor(SafetyLimits.from_description(DESCRIPTION))
        self.hal = ScriptedHal(DESCRIPTION)
        self.loop = ControlLoop(
            self.hal, monitor, FixedSupervisor(AskForTorque()), self.clock,
            overrun_limit=overrun_limit, max_stall_periods=max_stall,
        )  # fmt: skip
        self.loop.start()
        self.fake.t += 0.5  # a pause between start() and the first tick is not a stall
        assert self.loop.tick().timing.index == 0
        self.last = self.loop.tick()
        assert self.last.timing.index == 1
        self.t0 = self.fake.t - DT  # the second wait's one reading anchored the grid at tick 1

    def tick(self, late_periods: float = 0.0) -> TickResult:
        """The next tick, starting ``late_periods`` after the deadline it is due at (0: on time)."""
        if late_periods > 0:
            due = self.t0 + (self.last.timing.index + 1) * DT
            assert self.fake.t < due
            self.fake.t = due + late_periods * DT
        self.last = self.loop.tick()
        return self.last


def overrun_faults(result: TickResult) -> list[str]:
    return [f.message for f in result.faults if f.kind == FaultKind.OVERRUN]


def test_a_20_ms_stall_faults_in_the_tick_after_it_with_torque_off_and_its_lateness_recorded() -> None:
    fake = FakeTime()

    class StallOnce(HoldController):
        calls = 0

        def update(self, sample: Sample, dt_s: float) -> Command:
            self.calls += 1
            if self.calls == 100:
                fake.t += 0.0208  # the stalled tick's work: 20.8 ms, so the next tick starts ~19.8 ms late
            return super().update(sample, dt_s)

    recorder = RowsRecorder()
    controller = StallOnce()
    hal, loop = build(controller=controller, clock=RealTimeClock(DT, now=fake.now, sleep=fake.sleep), recorder=recorder)
    loop.start()
    result = run_until_fault(hal, loop, 200)  # torque off in the command and at the drives, same tick
    assert controller.calls == 100, "the fault must be in the first tick after the stall"
    assert result.timing.missed_deadlines == 20  # a 20 ms stall: 20 deadlines missed, not one overrun
    assert result.timing.consecutive_overruns == 20
    assert result.timing.lateness_s == pytest.approx(0.020, abs=3e-4)
    assert recorder.rows[-1][LATENESS] == pytest.approx(0.020, abs=3e-4)  # the recording shows the stall
    assert max(row[LATENESS] for row in recorder.rows[:-1]) < 1e-5
    [message] = overrun_faults(result)
    assert "stalled 19.8 ms" in message
    assert "20 deadlines of 1 ms missed at once" in message
    stats = loop.stats
    assert (stats.ticks, stats.overruns, stats.missed_deadlines) == (101, 1, 20)
    assert stats.worst_lateness_s == pytest.approx(0.020, abs=3e-4)


def test_four_isolated_overruns_of_1_5_periods_do_not_fault() -> None:
    """A tick whose work takes 1.5 periods makes the next start half a period late: one missed deadline."""
    paced = Paced()
    for _ in range(4):
        result = paced.tick(0.5)
        assert result.timing.overrun
        assert result.timing.missed_deadlines == 1
        assert result.timing.lateness_s == pytest.approx(0.5 * DT, abs=1e-6)
        assert result.faults == []
        assert result.command.enable
        for _ in range(3):
            assert paced.tick().faults == []
    assert paced.loop.stats.overruns == 4
    assert paced.loop.stats.missed_deadlines == 4


def test_four_missed_deadlines_in_a_row_do_not_fault_five_do() -> None:
    paced = Paced()
    for _ in range(4):
        result = paced.tick(0.5)
        assert result.faults == []
    assert result.timing.consecutive_overruns == 4
    assert not paced.tick().timing.overrun  # on time: the count starts again
    for _ in range(4):
        assert paced.tick(0.3).faults == []
    result = paced.tick(0.3)
    [message] = overrun_faults(result)
    assert message.startswith("5 consecutive deadlines of 1 ms missed (limit 5)")
    assert result.command.enable is False


def test_missed_deadlines_count_not_late_wake_ups() -> None:
    """Two late wake-ups that missed 2 and 3 deadlines: 5 in a row (the old watchdog counted 2)."""
    paced = Paced()
    first = paced.tick(1.4)
    assert first.timing.missed_deadlines == 2
    assert first.faults == []
    second = paced.tick(2.6)
    assert second.timing.missed_deadlines == 3  # not more than 3: not a stall by itself
    assert second.timing.consecutive_overruns == 5
    [message] = overrun_faults(second)
    assert "5 consecutive deadlines" in message
    assert "2.6 periods" in message
    assert second.command.enable is False


def test_a_stall_of_more_than_max_stall_periods_is_a_fault_by_itself() -> None:
    # 3 periods: not a fault by itself, and 3 < 5 in a row
    paced = Paced()
    result = paced.tick(2.9)
    assert result.timing.missed_deadlines == 3
    assert result.faults == []
    # 4 periods: a fault, named as a stall
    paced = Paced()
    result = paced.tick(3.2)
    assert result.timing.missed_deadlines == 4
    [message] = overrun_faults(result)
    assert (
        "the loop stalled 3.2 ms past a deadline: 4 deadlines of 1 ms missed at once (more than 3 periods)" in message
    )
    # configurable: a loop that tolerates 25 periods at once and 100 in a row rides out 20 ms
    paced = Paced(overrun_limit=100, max_stall=25)
    assert paced.tick(19.5).faults == []
    assert overrun_faults(Paced(overrun_limit=100, max_stall=25).tick(25.5))


def test_watchdog_settings_are_checked() -> None:
    hal = ScriptedHal(DESCRIPTION)
    monitor = SafetyMonitor(SafetyLimits.from_description(DESCRIPTION))
    with pytest.raises(ConfigurationError, match="overrun_limit"):
        ControlLoop(hal, monitor, FixedSupervisor(None), LockStepClock(DT), overrun_limit=0)
    with pytest.raises(ConfigurationError, match="max_stall_periods"):
        ControlLoop(hal, monitor, FixedSupervisor(None), LockStepClock(DT), max_stall_periods=-1)


def test_a_clock_that_reports_overruns_without_missed_deadlines_still_faults() -> None:
    """``tests/daror_runtime/session/test_session_loop.py``'s OverrunClock: lock-step time whose timing says overrun (no missed count)."""

    class OverrunClock(LockStepClock):
        run = 0

        def wait(self) -> TickTiming:
            timing = super().wait()
            if timing.index < 50:
                return timing
            self.run += 1
            return timing._replace(lateness_s=1.5 * self.period_s, overrun=True, consecutive_overruns=self.run)

    hal, loop = build(clock=OverrunClock(DT))
    settle(loop, 50)
    result = run_until_fault(hal, loop, 10)
    assert result.timing.consecutive_overruns == DEFAULT_OVERRUN_LIMIT
    assert overrun_faults(result)


def test_lock_step_stats_report_zero_lateness_and_the_work_of_a_tick() -> None:
    _hal, loop = build()
    loop.start()
    settle(loop, 300)
    stats = loop.stats
    assert (stats.ticks, stats.overruns, stats.missed_deadlines, stats.worst_lateness_s) == (300, 0, 0, 0.0)
    assert 0.0 < stats.mean_work_s <= stats.worst_work_s < 1.0


# A tick starts on time (0) or late by m + u periods; u keeps clear of the grid's boundaries.
lateness = st.one_of(
    st.just(0.0),
    st.builds(lambda m, u: m + u, st.integers(0, 30), st.floats(0.05, 0.95)),
)


@settings(max_examples=300, deadline=None)
@given(
    schedule=st.lists(lateness, min_size=1, max_size=40),
    overrun_limit=st.integers(1, 8),
    max_stall=st.integers(0, 8),
)
def test_the_watchdog_fires_exactly_when_the_rule_says(
    schedule: list[float], overrun_limit: int, max_stall: int
) -> None:
    """Rule: fault in the first tick where one stall missed more than ``max_stall`` deadlines or the
    deadlines missed in a row reach ``overrun_limit``; a tick L periods late missed floor(L) + 1."""
    paced = Paced(overrun_limit, max_stall)
    in_a_row = 0
    for late in schedule:
        missed = int(late) + 1 if late > 0 else 0
        in_a_row = in_a_row + missed if missed else 0
        stall = missed > max_stall
        expected = stall or in_a_row >= overrun_limit
        result = paced.tick(late)
        assert result.timing.missed_deadlines == missed
        assert result.timing.consecutive_overruns == in_a_row
        assert result.timing.lateness_s == pytest.approx(late * DT, abs=1e-6)
        messages = overrun_faults(result)
        if not expected:
            assert messages == []
            assert result.command.enable
            continue
        [message] = messages
        assert message.startswith("the loop stalled" if stall else f"{in_a_row} consecutive deadlines")
        assert result.command.enable is False
        return


# --- defect 6: the request queue -------------------------------------------------------------


def fsm(**queue: int) -> FsmInTheTick:
    """The real FSM, monitor and loop over the scripted HAL (``tests/daror_runtime/fsm/test_fsm_properties.py``), in state 1."""
    machine = FsmInTheTick()
    if queue:
        old = machine.supervisor
        machine.supervisor = FsmSupervisor(
            old.spec, old.monitor, old.device_limits, old.controllers, old.signals, old._isb_function, **queue
        )
        machine.loop.supervisor = machine.supervisor
    machine.tick()
    return machine


def flood_refused(ticket: Ticket) -> bool:
    response = ticket.response
    return response is not None and not response.accepted and "too many requests waiting" in response.reason


@pytest.fixture
def warnings_reach_capture() -> Iterator[None]:
    """Let warnings reach ``structlog.testing.capture_logs`` (the suite's default level drops them early)."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    yield
    configure_logging("critical")


@pytest.mark.slow
@pytest.mark.usefixtures("warnings_reach_capture")
def test_a_flood_of_advances_is_applied_a_few_per_tick_and_every_ticket_is_resolved() -> None:
    machine = fsm()
    supervisor = machine.supervisor
    limit, per_tick = DEFAULT_MAX_PENDING_REQUESTS, DEFAULT_MAX_REQUESTS_PER_TICK
    with structlog.testing.capture_logs() as logs:
        tickets = [supervisor.post_event(Event.ADVANCE) for _ in range(FLOOD)]
        queued, refused = tickets[:limit], tickets[limit:]
        assert supervisor.waiting_requests == limit
        assert all(flood_refused(t) for t in refused)  # resolved at the post, never reach a tick
        assert refused[0].response == Response(
            "advance", False, "startup", f"too many requests waiting for the loop ({limit}); this one was refused"
        )
        assert not any(t.done for t in queued)
        resolved_per_tick = []
        while supervisor.pending_requests:
            before = sum(t.done for t in queued)
            machine.tick()
            resolved_per_tick.append(sum(t.done for t in queued) - before)
            done = [t.done for t in queued]
            assert done == sorted(done, reverse=True), "requests must be applied in the order posted"
        machine.tick()  # the first tick with nothing waiting ends the burst in the log
    # 1st tick: the first advance (accepted) and nothing after a state change; then 4 refusals a tick
    assert resolved_per_tick == [1] + [per_tick] * ((limit - 1) // per_tick) + [(limit - 1) % per_tick]
    assert queued[0].response is not None
    assert queued[0].response.accepted
    assert supervisor.state_name == "safety_check"
    assert all(t.response is not None and not t.response.accepted and t.response.unmet for t in queued[1:])
    assert supervisor.refused_requests == FLOOD - limit
    flood_log = [e for e in logs if "too many" in e["event"]]
    assert [e["event"] for e in flood_log] == (
        ["requests refused: too many waiting for the loop"]
        + ["requests still refused: too many waiting for the loop"] * ((FLOOD - limit) // 10_000)
        + ["requests refused: too many were waiting for the loop"]
    )
    assert flood_log[-1]["refused"] == FLOOD - limit


def test_requests_beyond_the_per_tick_bound_wait_in_order() -> None:
    machine = fsm(max_pending_requests=10, max_requests_per_tick=3)
    supervisor = machine.supervisor
    applied: list[int] = []

    def action(i: int) -> Callable[[FsmSupervisor], Response]:
        def apply(s: FsmSupervisor) -> Response:
            applied.append(i)
            return Response(f"r{i}", True, s.state_name)

        return apply

    tickets = [supervisor.post(f"r{i}", action(i)) for i in range(12)]
    assert [flood_refused(t) for t in tickets] == [False] * 10 + [True] * 2
    assert "(10)" in tickets[10].response.reason  # type: ignore[union-attr]
    for expected in ([0, 1, 2], [3, 4, 5], [6, 7, 8], [9]):
        machine.tick()
        assert applied[-len(expected) :] == expected
    assert all(t.done for t in tickets)
    assert supervisor.post("r12", action(12)).done is False  # room again


def test_one_state_change_per_tick() -> None:
    """After a transition the next request is decided in the next tick, in the new state."""
    machine = fsm()
    supervisor = machine.supervisor
    first, second = supervisor.post_event(Event.ADVANCE), supervisor.post_event(Event.REVERT)
    machine.tick()
    assert first.response is not None
    assert first.response.state == "safety_check"
    assert not second.done
    machine.tick()
    assert second.response is not None
    assert second.response.accepted
    assert second.response.state == "startup"


@pytest.mark.slow
def test_a_flood_never_stops_a_fault_from_failing_the_robot_in_the_same_tick() -> None:
    machine = FsmInTheTick()
    machine.walk_to("pilot_installation")  # torque on, fails on a fault
    assert machine.tick().command.enable
    supervisor = machine.supervisor
    tickets = [supervisor.post_event(Event.REVERT) for _ in range(FLOOD)]
    machine.hal.drive_fault = True
    result = machine.tick()
    assert supervisor.state_name == FAIL
    assert result.command.enable is False
    assert FaultKind.DRIVE in {f.kind for f in result.faults}
    while supervisor.pending_requests:
        machine.tick()
    assert all(t.done for t in tickets)
    assert supervisor.state_name == FAIL  # every revert was refused in FAIL


def test_essential_requests_are_queued_beyond_the_bound_in_order() -> None:
    machine = fsm(max_pending_requests=2)
    supervisor = machine.supervisor
    order: list[str] = []

    def note(name: str) -> Callable[[FsmSupervisor], Response]:
        def apply(s: FsmSupervisor) -> Response:
            order.append(name)
            return Response(name, True, s.state_name)

        return apply

    tickets = [supervisor.post(n, note(n)) for n in ("a", "b", "c")]
    saved = supervisor.post("identification saved", note("saved"), essential=True)
    assert flood_refused(tickets[2])
    assert not saved.done
    machine.tick()
    assert order == ["a", "b", "saved"]


def test_posting_from_another_thread_keeps_the_bound_and_the_order() -> None:
    machine = fsm(max_pending_requests=16)
    supervisor = machine.supervisor
    applied: list[int] = []
    seen_waiting: list[int] = []
    tickets: list[Ticket] = []

    def action(i: int) -> Callable[[FsmSupervisor], Response]:
        def apply(s: FsmSupervisor) -> Response:
            applied.append(i)
            return Response(f"r{i}", True, s.state_name)

        return apply

    def poster() -> None:
        for i in range(20_000):
            tickets.append(supervisor.post(f"r{i}", action(i)))
            seen_waiting.append(supervisor.waiting_requests)

    thread = threading.Thread(target=poster)
    thread.start()
    ticks = 0
    while thread.is_alive() or supervisor.pending_requests:
        machine.tick()
        ticks += 1
        seen_waiting.append(supervisor.waiting_requests)
    thread.join()
    assert max(seen_waiting) <= 16
    assert all(t.done for t in tickets)
    assert applied == sorted(applied)  # in the order posted
    assert applied == [i for i, t in enumerate(tickets) if not flood_refused(t)]
    assert len(applied) <= ticks * DEFAULT_MAX_REQUESTS_PER_TICK


def test_queue_bounds_are_checked() -> None:
    old = FsmInTheTick().supervisor
    for bad in ({"max_pending_requests": 0}, {"max_requests_per_tick": 0}):
        with pytest.raises(ConfigurationError, match="request queue"):
            FsmSupervisor(old.spec, old.monitor, old.device_limits, old.controllers, old.signals, **bad)
