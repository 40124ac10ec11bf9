"""Lock-step ticks in compiled batches (daror_runtime/loop_batch.py) are the loop's ticks, bit for bit.

Every test runs the same closed loop twice from the same start, once with ``compiled_batches``
(the default) and once with every tick through ``ControlLoop.tick``, and compares what a user
can see: the recorded rows (bytes), the plant's true state, the faults (kind, time, message), the
loop's and the clock's counts, the last command. Where the common case ends (a signal out of
bounds, a torque clipped, a fault injected, an e-stop), the batch must hand the tick to Python at
exactly that tick.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import event as statistics_event
from hypothesis import strategies as st
from numba import njit

from daror_runtime.clocks import LockStepClock, RealTimeClock
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.data.recorder import Recorder
from daror_runtime.data.recording_reader import read_recording
from daror_runtime.data.tick_row import RECORD_COLUMNS
from daror_runtime.identification.protocol import plan_run
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.identification.trajectory_planning import build_trajectory
from daror_runtime.identification.waypoints import WaypointSet, load_waypoints
from daror_runtime.loop import ControlLoop, FixedSupervisor, TickResult
from daror_runtime.models.linear import APModel
from daror_runtime.safety.faults import FaultKind
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from hal.capabilities import BackendBatch
from hal.interface import DriveState
from hal.kernels import BACKEND_STEP, CompiledFunction
from hal.sim import dynamics
from hal.sim.backend import SimHal

PERIOD_S = 0.001
FOUR = (1, 14, 30, 50)


def _short_trajectory_set() -> WaypointSet:
    full = load_waypoints()
    return WaypointSet(
        waypoints=[full.waypoints[n - 1] for n in FOUR], training_order=[1, 2, 3, 4], validation_order=[1, 3, 2, 4]
    )


@dataclass
class Rig:
    """One identification loop on the simulated plant, recorded to ``path``."""

    hal: SimHal
    loop: ControlLoop
    monitor: SafetyMonitor
    controller: MotorPositionPD
    recorder: Recorder
    path: Path

    def rows(self) -> np.ndarray:
        self.recorder.close()
        columns, rows = read_recording(self.path)
        assert columns == RECORD_COLUMNS
        return rows


def make_rig(
    tmp_path: Path,
    name: str,
    *,
    batches: bool,
    limits: Callable[[SafetyLimits], SafetyLimits] | None = None,
    hal: SimHal | None = None,
) -> Rig:
    hal = hal or SimHal("exo_dummy_arm")
    hal.open()
    trajectory = build_trajectory(_short_trajectory_set(), "training")
    feedforward = APModel.from_description(hal.description, dummy_arm=True, elbow_stiffness=True)
    first = hal.read()
    run = plan_run(
        trajectory, hal.description, first.q_rad, IdentificationSettings(), feedforward, PERIOD_S,
        tmp_path / f"{name}.rec", tmp_path / f"{name}.csv",
    )  # fmt: skip
    run.controller.reset(first)
    safety = SafetyLimits.from_description(hal.description)
    monitor = SafetyMonitor(limits(safety) if limits else safety)
    loop = ControlLoop(
        hal, monitor, FixedSupervisor(run.controller), LockStepClock(PERIOD_S), run.recorder, compiled_batches=batches
    )
    return Rig(hal, loop, monitor, run.controller, run.recorder, tmp_path / f"{name}.rec")


def fault_log(results: list[TickResult | None]) -> list[tuple[str, float, str]]:
    return [(f.kind.value, f.t_s, f.message) for r in results if r is not None for f in r.faults]


def assert_same_run(python: Rig, batched: Rig) -> None:
    """Everything a user sees of the two runs is the same, to the bit."""
    assert batched.loop.clock.ticks == python.loop.clock.ticks
    assert batched.loop.stats.ticks == python.loop.stats.ticks
    assert batched.hal.read_without_faults().seq == python.hal.read_without_faults().seq
    for got, expected in zip(batched.hal.truth(), python.hal.truth(), strict=True):
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(batched.loop.last_command.motor_torque_nm, python.loop.last_command.motor_torque_nm)
    assert batched.loop.last_command.enable == python.loop.last_command.enable
    assert [(f.kind, f.t_s) for f in batched.monitor.latched] == [(f.kind, f.t_s) for f in python.monitor.latched]
    python_rows, batched_rows = python.rows(), batched.rows()
    assert batched_rows.shape == python_rows.shape
    assert batched_rows.tobytes() == python_rows.tobytes()


def test_a_protocol_records_the_same_bytes_with_and_without_batches(tmp_path: Path) -> None:
    python, batched = make_rig(tmp_path, "python", batches=False), make_rig(tmp_path, "batched", batches=True)
    for _ in range(12):  # 12,000 ticks: many blocks of readings, noise and recorder rows
        assert python.loop.run(1000, stop_on_fault=True).faults == []
        assert batched.loop.run(1000, stop_on_fault=True).faults == []
    assert_same_run(python, batched)
    assert python.loop.batched_ticks == 0
    # the batches did the work: every tick but the last of each run() and those after a block ran out
    assert batched.loop.batched_ticks > 0.9 * 12_000


def test_a_signal_leaving_its_bounds_mid_batch_is_found_at_the_same_tick(tmp_path: Path) -> None:
    """A joint limit the trajectory crosses: the batch stops before that tick and the Python tick names the fault."""

    def tight(limits: SafetyLimits) -> SafetyLimits:
        upper = limits.joint_upper_rad.copy()
        upper[1] = 1.50  # joint 2 passes 1.50 rad on the way to the second waypoint
        return replace(limits, joint_upper_rad=upper)

    python = make_rig(tmp_path, "python", batches=False, limits=tight)
    batched = make_rig(tmp_path, "batched", batches=True, limits=tight)
    found = []
    for rig in (python, batched):
        result = rig.loop.run(20_000, stop_on_fault=True)
        assert result is not None
        found.append(fault_log([result]))
    assert found[0] == found[1]
    assert found[0], "the trajectory never crossed the tightened limit"
    assert found[0][0][0] == FaultKind.JOINT_LIMIT.value
    assert 0.5 < found[0][0][1] < 20.0
    assert_same_run(python, batched)


def test_a_clipped_torque_is_clipped_by_the_filter_at_the_same_ticks(tmp_path: Path) -> None:
    """A command limit below what the PD asks for: every clipped tick runs through the Python filter."""

    def low(limits: SafetyLimits) -> SafetyLimits:
        return replace(limits, command_limit_nm=np.full(4, 3.5))

    python = make_rig(tmp_path, "python", batches=False, limits=low)
    batched = make_rig(tmp_path, "batched", batches=True, limits=low)
    for rig in (python, batched):
        for _ in range(5):
            rig.loop.run(1000, stop_on_fault=True)
    assert_same_run(python, batched)
    rows = python.rows()
    torque = rows[:, RECORD_COLUMNS.index("tau_cmd1") : RECORD_COLUMNS.index("tau_cmd4") + 1]
    assert np.abs(torque).max() == 3.5  # the limit was reached: clipped ticks happened


WORLD_EVENTS = st.sampled_from(
    ["nan", "jump", "stale", "drive_fault", "bus", "estop", "release", "clear", "push", "no push", "ack", "ack"]
)


@pytest.mark.slow
@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(chunks=st.lists(st.tuples(st.integers(1, 700), WORLD_EVENTS), min_size=1, max_size=8))
def test_random_runs_with_world_events_match_tick_for_tick(
    tmp_path_factory: pytest.TempPathFactory, chunks: list[tuple[int, str]]
) -> None:
    """Random chunk lengths with faults, e-stops, pushes and acknowledgements between them: the same rows,
    faults and state (batches resume once the faults are acknowledged)."""
    tmp_path = tmp_path_factory.mktemp("batches")
    python, batched = make_rig(tmp_path, "python", batches=False), make_rig(tmp_path, "batched", batches=True)
    logs: list[list[tuple[str, float, str]]] = [[], []]
    for ticks, event in chunks:
        for n, rig in enumerate((python, batched)):
            logs[n] += fault_log([rig.loop.run(ticks)])
            world = rig.hal.world
            if event in {"nan", "jump", "stale", "drive_fault", "bus"}:
                value = 0.2 if event == "jump" else None
                world.inject_fault(event, 2, value)  # type: ignore[arg-type]
            elif event == "estop":
                world.press_estop(0, True)
            elif event == "release":
                world.press_estop(0, False)
            elif event == "clear":
                world.clear_faults()
            elif event == "ack":  # the operator acknowledges: faults whose condition is gone unlatch
                rig.monitor.clear()
            elif event == "push":
                rig.hal.set_external_torque(np.array([0.0, 1.5, 0.0, 0.0]))
            else:
                rig.hal.set_external_torque(None)
    assert logs[0] == logs[1]
    statistics_event(f"ticks in batches: {'some' if batched.loop.batched_ticks else 'none'}")
    assert_same_run(python, batched)


@njit(cache=True)
def _diverging_step(x, p, work, s, torque, enable, readings, row):  # type: ignore[no-untyped-def]
    """The plant's tick, failing as a diverged plant fails from robot time 0.5 s on (a test double)."""
    if s[dynamics.S_TICK] >= 500:
        dynamics.flush_commands(s)
        return dynamics.TICK_DIVERGED
    return dynamics.hal_tick(x, p, work, s, torque, enable, readings, row)


class _DivergingBatches:
    """SimHal's batches with a step that fails at 0.5 s (the Python ticks before it are real)."""

    def __init__(self, hal: SimHal) -> None:
        self.inner = SimHal.lockstep_batches.fget(hal)  # type: ignore[attr-defined]
        self.step = CompiledFunction(_diverging_step, BACKEND_STEP)

    def begin(self) -> BackendBatch | None:
        begun = self.inner.begin()
        return None if begun is None else begun._replace(step=self.step)

    def end(self, ticks: int, status: int) -> None:
        self.inner.end(ticks, status)


class _DivergingSimHal(SimHal):
    @property
    def lockstep_batches(self) -> _DivergingBatches:  # type: ignore[override]
        if not hasattr(self, "_diverging"):
            self._diverging = _DivergingBatches(self)
        return self._diverging


def test_a_backend_step_that_fails_mid_batch_is_a_hal_fault_with_torque_off(tmp_path: Path) -> None:
    rig = make_rig(tmp_path, "diverging", batches=True, hal=_DivergingSimHal("exo_dummy_arm"))
    result = rig.loop.run(5000, stop_on_fault=True)
    assert result is not None
    assert [f.kind for f in result.faults] == [FaultKind.HAL]
    assert "diverged" in result.faults[0].message
    assert "writing the hardware failed" in result.faults[0].message
    assert rig.monitor.faulted
    # 500 ticks wrote (samples 0..499); the tick of sample 500 failed in its write: it counts for
    # the loop (and its row is recorded, as a Python tick records it), not for the plant
    assert rig.loop.stats.ticks == 501
    assert rig.hal.read().seq == 500
    assert rig.hal.read().drives == (DriveState.DISABLED,) * 4  # torque removed
    assert result.sample is not None
    assert result.sample.seq == 500
    assert result.faults[0].t_s == pytest.approx(0.5)
    rows = rig.rows()
    assert len(rows) == 501
    assert rows[-1, RECORD_COLUMNS.index("t")] == pytest.approx(0.5)
    # the loop goes on with torque off: no batch while faulted
    after = rig.loop.run(3)
    assert after is not None
    assert after.command.enable is False


def test_no_batches_on_a_real_time_clock(tmp_path: Path) -> None:
    """Wall-clock time never runs ticks ahead: every tick goes through the Python tick and waits."""
    hal = SimHal("exo_dummy_arm")
    hal.open()
    calls: list[int] = []
    inner = hal.lockstep_batches

    class Spy:
        def begin(self) -> BackendBatch | None:
            calls.append(1)
            return inner.begin()

        def end(self, ticks: int, status: int) -> None:
            inner.end(ticks, status)

    spy = Spy()
    type(hal).lockstep_batches = property(lambda self: spy)  # type: ignore[assignment]
    try:
        rig = make_rig(tmp_path, "rt", batches=True, hal=hal)
        loop = ControlLoop(hal, rig.monitor, FixedSupervisor(rig.controller), RealTimeClock(PERIOD_S), rig.recorder)
        loop.run(20)
        assert calls == []
        # A monitor of its own: the wall-clock run may overrun on a loaded machine, and a faulted
        # monitor rightly keeps a loop from batching (it failed so in make check once).
        unfaulted = SafetyMonitor(SafetyLimits.from_description(hal.description))
        lock_step = ControlLoop(hal, unfaulted, FixedSupervisor(rig.controller), LockStepClock(PERIOD_S), None)
        lock_step.run(20)
        assert calls, "the lock-step loop did not ask for a batch"
    finally:
        del type(hal).lockstep_batches
