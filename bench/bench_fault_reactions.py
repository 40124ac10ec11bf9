"""Fault reactions (issue 23): what they cost in the tick, and what each fault does to a limp arm.

* The session's tick in compensation (the common path: no fault, the soft walls far away): the whole
  ``ControlLoop.tick`` of a lock-step session with the simulated pilot, as the operator's session runs
  it. The reactions must not make it dearer (docs/performance.md compares it with the code before).
* ``Compensation.update`` with the soft walls: far from every wall (the common case) and inside an
  ISB wall (the walls' gradient computed every tick); target 12 us, as compensation's.
* ``SafeStop.update``: holding, and following a lowering path.
* Per fault kind, in compensation, the pilot limp with his arm raised (40 deg forward, elbow 70 deg),
  nothing under the arm: the reaction, the largest displacement of any joint in the 3 s after the
  fault and its peak speed. The table of docs/safety.md ("Fault reactions, measured").
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from daror_runtime.bench import BenchFigure, time_calls
from daror_runtime.control import Compensation, SeaTorqueController
from daror_runtime.control.position import LinkBounds
from daror_runtime.control.safe_stop import SafeStop
from daror_runtime.control.soft_walls import SoftWalls
from daror_runtime.logs import configure_logging
from daror_runtime.models.linear import APModel
from daror_runtime.runtime import Runtime
from daror_runtime.safety.faults import FaultKind
from daror_runtime.safety.lowering import plan_lowering
from daror_runtime.testing import session_core
from hal.isb import IsbLimits, default_shoulder
from hal.robot import load_description
from hal.sim.backend import SimHal

TICK_S = 1e-3
# the session walk is shared with compare_tick.py (a sibling module: `daror bench` loads scripts by path)
sys.path.insert(0, str(Path(__file__).parent))
import session_walk  # noqa: E402
from bench_control import plf_plus, samples_near, time_update  # noqa: E402

sys.path.insert(0, str(Path(__file__).parents[1]))  # the checkout: the tests' way of provoking a fault
from tests.provoke import LIMIT_KINDS, PLANT_KINDS, inject_in_plant, narrowed_limits  # noqa: E402

POSE_ISB_DEG = session_walk.POSE_ISB_DEG
_session_in_compensation = session_walk.session_in_compensation


def _compensation_with_walls(near: bool, quick: bool) -> BenchFigure:
    description = load_description()
    shoulder = default_shoulder()
    walls = SoftWalls(description, shoulder)
    walls.set_limits(IsbLimits())
    # far: the middle of the range; near: the elbow 3 deg inside its recorded limit (5 deg), in its wall
    isb = (30.0, 60.0, 0.0, 8.0 if near else 60.0)
    q0 = shoulder.q_from_isb(np.deg2rad(isb))
    controller = Compensation(SeaTorqueController(description.sea), plf_plus(), 0.8, None, walls=walls)
    samples = samples_near(q0, checked=True)
    out = np.zeros(4)
    assert walls.torque(samples[0].q_rad, samples[0].dq_rad_s, out) == near
    median, p90, repeats = time_update(controller, quick, samples)
    where = "inside the elbow's wall (ISB gradient every tick)" if near else "far from every wall (the common case)"
    return BenchFigure(f"Compensation(PLF+) with soft walls, {where}", median, p90, "us", repeats, 12.0)


def bench_compensation_walls_far(quick: bool) -> BenchFigure:
    return _compensation_with_walls(False, quick)


def bench_compensation_walls_near(quick: bool) -> BenchFigure:
    return _compensation_with_walls(True, quick)


def _safe_stop(lowering: bool, quick: bool) -> BenchFigure:
    description = load_description()
    shoulder = default_shoulder()
    a_priori = APModel.from_description(description, True, True)
    stop = SafeStop(description, LinkBounds.from_description(description), TICK_S, a_priori, hold_s=0.0)
    q0 = shoulder.q_from_isb(np.deg2rad(POSE_ISB_DEG))
    samples = samples_near(q0, checked=True)
    stop.arm(lowering, (), plf_plus())
    stop.reset(samples[0])
    if lowering:
        rest = shoulder.q_from_isb(np.deg2rad((0.0, 0.0, 0.0, 30.0)))
        stop.install_path(plan_lowering(stop.hold_pose_rad, rest, shoulder))
    median, p90, repeats = time_update(stop, quick, samples, reset=False)
    what = "following a lowering path" if lowering else "holding the pose"
    return BenchFigure(f"SafeStop.update, {what}", median, p90, "us", repeats, 20.0, note="PLF+ support along the path")


def bench_safe_stop_hold(quick: bool) -> BenchFigure:
    return _safe_stop(False, quick)


def bench_safe_stop_lower(quick: bool) -> BenchFigure:
    return _safe_stop(True, quick)


def bench_session_tick_in_compensation(quick: bool) -> BenchFigure:
    """The whole tick of a lock-step session in compensation (pilot limp, no fault, far from the walls)."""
    configure_logging("critical")
    with tempfile.TemporaryDirectory() as directory:
        runtime, _ = _session_in_compensation(Path(directory))
        tick = session_core(runtime).loop.tick
        repeats = 10 if quick else 60
        median, p90 = time_calls(tick, repeats=repeats, per_call=500, scale=1e6)
        runtime.close()
    return BenchFigure(
        "session tick in compensation (ControlLoop.tick: HAL, monitor, FSM, Compensation with walls, pilot)",
        median, p90, "us", repeats, note="lock-step; the simulated pilot's torque every tick",
    )  # fmt: skip


def _provoke(runtime: Runtime, hal: SimHal, kind: FaultKind) -> None:
    """As tests/daror_runtime/safety/test_fault_reactions.py provokes each kind (a narrowed limit where the monitor must see a reading)."""
    core = session_core(runtime)
    monitor = core.monitor
    limits = monitor.limits
    sample = runtime.last_sample
    assert sample is not None
    if kind == FaultKind.ESTOP:
        hal.press_estop(0, True)
    elif kind in PLANT_KINDS:
        inject_in_plant(hal, kind, stale_ticks=5000)
    elif kind in LIMIT_KINDS:
        monitor.set_limits(narrowed_limits(limits, sample, kind))
    elif kind == FaultKind.OVERRUN:
        core.loop._report([], FaultKind.OVERRUN, "the loop stalled (bench)")
        core.supervisor.on_late_faults(sample, monitor.latched)
    else:
        controller = core.supervisor.controller

        def update(sample: Any, dt_s: float) -> Any:
            raise ZeroDivisionError("division by zero (bench)")

        controller.update = update
        runtime.runner.run_ticks(1)
        del controller.update


def _drop(kind: FaultKind) -> BenchFigure:
    with tempfile.TemporaryDirectory() as directory:
        runtime, hal = _session_in_compensation(Path(directory))
        q0 = hal.truth().q_rad
        _provoke(runtime, hal, kind)
        q, dq = [], []

        def row(result: Any) -> bool:
            truth = hal.truth()
            q.append(truth.q_rad)
            dq.append(truth.dq_rad_s)
            return False

        runtime.runner.run_ticks(3000, stop=row)
        plan = session_core(runtime).supervisor.reaction
        runtime.close()
    moved = np.degrees(np.abs(np.array(q) - q0).max(axis=0))
    speed = np.abs(np.array(dq)).max(axis=0)
    reaction = (
        "none" if plan is None else f"{plan.reaction}" + (f", joint {plan.joints_off} off" if plan.joints_off else "")
    )
    note = (
        f"{reaction}; per joint: moved {', '.join(f'{m:.1f}' for m in moved)} deg, peak "
        f"{', '.join(f'{v:.2f}' for v in speed)} rad/s"
    )
    # Lock-step and seeded: one run is the figure (median and p90 alike); the peak speed is in the note.
    largest = float(moved.max())
    return BenchFigure(f"{kind.value}: largest move in 3 s (limp arm, nothing under it)", largest, largest, "deg", 1,
                       note=note)  # fmt: skip


def _drop_bench(kind: FaultKind) -> Any:
    def bench(quick: bool) -> BenchFigure:
        configure_logging("critical")
        return _drop(kind)

    bench.__name__ = f"bench_drop_{kind.value}"
    return bench


BENCHMARKS = [
    bench_compensation_walls_far,
    bench_compensation_walls_near,
    bench_safe_stop_hold,
    bench_safe_stop_lower,
    bench_session_tick_in_compensation,
    *(_drop_bench(kind) for kind in FaultKind),
]
