"""Costs of the safety FSM in the tick (issue 4): per-tick work without a transition, a transition,
and the ticks while a flood of requests waits.

Targets: the FSM's work in a tick with no request and no fault below 10 us; a transition below
1 ms; a tick while 10^5 requests are posted below 1 ms (the queue bounds what one tick applies). A transition is measured as the supervisor does it inside the tick: the machine's guards,
the ``transitions`` library's trigger, the new state's limits in the safety monitor, the reset of
the new state's controller (the real controllers of a session) and the audit log events
(rendered to JSON, handed to the log writer thread). Every transition of ``fsm_spec.yaml`` is
timed, many times each; the figure is over all of them.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from daror_runtime.bench import BenchFigure, time_calls
from daror_runtime.fsm.machine import Event
from daror_runtime.logs import configure_logging, flush_logs
from daror_runtime.runtime import Runtime
from daror_runtime.session.settings import SessionSettings
from daror_runtime.testing import session_core
from hal.isb import IsbLimits
from hal.sim.backend import SimHal
from hal.sim.pilot import SimulatedPilot


def _session(directory: Path) -> tuple[Runtime, SimHal]:
    hal = SimHal("exo_dummy_arm")
    runtime = Runtime(hal, directory, settings=SessionSettings(dummy_arm=True))
    runtime.open()
    pilot = SimulatedPilot(hal.plant, hal.read_without_faults().q_rad)
    hal.set_external_torque(pilot)

    def relax_when_supported(
        state: object, outcome: object
    ) -> None:  # the pilot rests on the robot when it carries the arm
        pilot.carried = 0.0 if getattr(state, "mode", "") in ("compensation", "hold", "identification") else 1.0

    session_core(runtime).supervisor.listeners.append(relax_when_supported)
    runtime.runner.run_ticks(10)
    return runtime, hal


def bench_fsm_tick(quick: bool) -> BenchFigure:
    """``FsmSupervisor.on_tick`` with no request and no fault, in compensation (the common tick)."""
    with tempfile.TemporaryDirectory() as directory:
        runtime, _ = _session(Path(directory))
        supervisor, monitor = session_core(runtime).supervisor, session_core(runtime).monitor
        _force_to(runtime, "compensation")
        sample = runtime.last_sample
        no_faults: list = []
        repeats = 20 if quick else 200
        median, p90 = time_calls(
            lambda: supervisor.on_tick(sample, no_faults, monitor), repeats=repeats, per_call=2000, scale=1e6
        )
        runtime.close()
    return BenchFigure("FSM work per tick, no transition (supervisor.on_tick)", median, p90, "us", repeats, target=10.0)


def bench_fsm_transition(quick: bool) -> BenchFigure:
    """Every transition of the spec (advance 1->10, revert, fail, acknowledge, reset), each timed in the tick."""
    with tempfile.TemporaryDirectory() as directory:
        configure_logging("critical", json_path=Path(directory) / "audit.jsonl", json_level="info")
        runtime, hal = _session(Path(directory) / "session")
        supervisor = session_core(runtime).supervisor
        rounds = 5 if quick else 40
        samples: list[float] = []
        worst = ("", 0.0)
        for _ in range(rounds):
            _force_guards(runtime)
            for event in [Event.ADVANCE] * 9 + [Event.REVERT, Event.ADVANCE]:
                _force_guards(runtime)
                _settle(runtime)
                source = supervisor.state_name
                start = time.perf_counter()
                response = supervisor.fire(event)
                elapsed = (time.perf_counter() - start) * 1e3
                if not response.accepted:
                    raise RuntimeError(f"benchmark walk refused {event} in {source}: {response.reason}")
                samples.append(elapsed)
                if elapsed > worst[1]:
                    worst = (f"{event.value} {source}", elapsed)
                runtime.runner.run_ticks(2)
            hal.press_estop(0, True)
            start = time.perf_counter()
            runtime.runner.run_ticks(1)  # the tick that fails (read, check, fail transition, filter, write)
            samples.append((time.perf_counter() - start) * 1e3)
            hal.press_estop(0, False)
            runtime.runner.run_ticks(2)
            for event in (Event.ACKNOWLEDGE, Event.RESET):
                start = time.perf_counter()
                supervisor.fire(event)
                samples.append((time.perf_counter() - start) * 1e3)
            runtime.runner.run_ticks(2)
        runtime.close()
        flush_logs()
        configure_logging("warning")
    note = f"{len(samples)} transitions over the whole spec; slowest {worst[0]} {worst[1]:.3f} ms; max {max(samples):.3f} ms"
    return BenchFigure(
        "FSM transition in the tick (guards, trigger, limits, controller reset, audit log)",
        float(np.median(samples)),
        float(np.percentile(samples, 90)),
        "ms",
        len(samples),
        target=1.0,
        note=note,
    )


def _force_guards(runtime: Runtime) -> None:
    """Every advance guard true (the session's evidence, set directly: the benchmark times transitions)."""
    from daror_runtime.fsm.signals import Checklist, EstopButton, SelectedModel

    signals = session_core(runtime).signals
    signals.estop_tested.update(EstopButton)
    signals.confirmed.update(Checklist)
    signals.isb_limits = signals.isb_limits or IsbLimits()
    signals.model = SelectedModel("AP", "ap", None, 0.5, 1.5)
    session_core(runtime).modes.compensation.model = session_core(
        runtime
    ).a_priori  # what the runtime installs with an approved model


def _settle(runtime: Runtime) -> None:
    """Let the arm come to rest (the robot_at_rest guard) before a transition that needs it."""
    runtime.runner.run_until(lambda: runtime.at_rest, 5.0)


def _force_to(runtime: Runtime, name: str) -> None:
    supervisor = session_core(runtime).supervisor
    while supervisor.state_name != name:
        _force_guards(runtime)
        _settle(runtime)
        response = supervisor.fire(Event.ADVANCE)
        if not response.accepted:
            raise RuntimeError(f"cannot reach {name}: {response.reason}")
        runtime.runner.run_ticks(2)


def bench_fsm_request_flood(quick: bool) -> list[BenchFigure]:
    """The loop's ticks while 10^5 ``advance`` requests are posted at once (1e4 with ``quick``).

    In 2 safety_check (one posted advance took the loop there first, so the transition's code is
    warm), with the audit log on, the requests are posted from this thread before the next tick
    (the worst case: all of them wait for the same tick); every one is refused (the e-stops were
    not tested). Then ticks run until none waits. The figures are the whole tick
    (``ControlLoop.tick``: read, check, FSM, controller, filter, write) in ms: the slowest and the
    median tick while requests waited, and a quiet tick after. Before the queue was bounded one
    tick applied all of them: 7 s for 10^5 on the reference VM.
    """
    count = 10_000 if quick else 100_000
    with tempfile.TemporaryDirectory() as directory:
        configure_logging("critical", json_path=Path(directory) / "audit.jsonl", json_level="info")
        runtime, _ = _session(Path(directory) / "session")
        supervisor, tick = session_core(runtime).supervisor, session_core(runtime).loop.tick
        supervisor.post_event(Event.ADVANCE)
        for _ in range(200):
            tick()
        if supervisor.state_name != "safety_check":
            raise RuntimeError(f"benchmark setup: expected safety_check, in {supervisor.state_name}")
        start = time.perf_counter()
        tickets = [supervisor.post_event(Event.ADVANCE) for _ in range(count)]
        post_us = (time.perf_counter() - start) / count * 1e6
        flooded: list[float] = []
        while supervisor.pending_requests and len(flooded) < count + 10:
            start = time.perf_counter()
            tick()
            flooded.append((time.perf_counter() - start) * 1e3)
        quiet: list[float] = []
        for _ in range(200):
            start = time.perf_counter()
            tick()
            quiet.append((time.perf_counter() - start) * 1e3)
        responses = [t.response for t in tickets]
        runtime.close()
        flush_logs()
        configure_logging("warning")
    accepted = sum(1 for r in responses if r is not None and r.accepted)
    unresolved = sum(1 for r in responses if r is None)
    flood = sum(1 for r in responses if r is not None and not r.accepted and "too many requests" in r.reason)
    note = (
        f"{count} posted ({post_us:.1f} us per post): {accepted} accepted, {flood} refused as a flood, "
        f"{count - accepted - flood - unresolved} refused by the FSM, {unresolved} unresolved; "
        f"{len(flooded)} ticks until none waited"
    )
    return [
        BenchFigure(
            f"tick while {count} requests are posted: slowest tick",
            float(max(flooded)),
            float(max(flooded)),
            "ms",
            len(flooded),
            target=1.0,
            note=note,
        ),
        BenchFigure(
            "  median tick while requests waited",
            float(np.median(flooded)),
            float(np.percentile(flooded, 90)),
            "ms",
            len(flooded),
        ),
        BenchFigure("  quiet tick after (no request)", float(np.median(quiet)), float(np.percentile(quiet, 90)), "ms",
                    len(quiet)),
    ]  # fmt: skip


BENCHMARKS = [bench_fsm_tick, bench_fsm_transition, bench_fsm_request_flood]
