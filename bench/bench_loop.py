"""Benchmarks of the control loop (issue 3).

* The full identification protocol (training, ~12.5 min of robot time) in lock-step time on the
  simulated plant, full tick (safety, controller, recorder): at least 50x faster than real time.
* Real-time mode at 1 kHz for 30 s (the same tick, recorder on): tick lateness p50/p99/max (against
  the deadline each tick was due at, so a stall counts in full), overruns and missed deadlines
  (``ControlLoop.stats``), and the tick's own work (mean and worst); p99 below 200 us.
* Peak memory of the protocol run (a fresh process): below 500 MB.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from daror_runtime.bench import BenchFigure
from daror_runtime.clocks import RealTimeClock
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.position import LinkBounds
from daror_runtime.data.recorder import Recorder
from daror_runtime.data.tick_row import RECORD_COLUMNS
from daror_runtime.identification.protocol import run_protocol
from daror_runtime.identification.trajectory_planning import build_trajectory
from daror_runtime.identification.waypoints import load_waypoints
from daror_runtime.loop import ControlLoop, FixedSupervisor
from daror_runtime.models.linear import APModel
from daror_runtime.realtime import release_realtime, request_realtime
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from hal.sim.backend import SimHal


def _protocol_once(kind: str = "training") -> tuple[float, float, int]:
    hal = SimHal("exo_dummy_arm")
    hal.open()
    trajectory = build_trajectory(load_waypoints(), kind)  # type: ignore[arg-type]
    feedforward = APModel.from_description(hal.description, dummy_arm=True, elbow_stiffness=True)
    with tempfile.TemporaryDirectory() as tmp:
        result = run_protocol(hal, trajectory, Path(tmp) / "run.rec", Path(tmp) / "run.csv", feedforward=feedforward)
    return result.real_time_factor, result.wall_time_s / result.ticks * 1e6, result.ticks


def bench_identification_lock_step(quick: bool) -> list[BenchFigure]:
    runs = [_protocol_once() for _ in range(1 if quick else 3)]
    factors = np.array([r[0] for r in runs])
    ticks_us = np.array([r[1] for r in runs])
    return [
        BenchFigure(
            "identification protocol, lock-step (training, 752 s robot time)",
            float(np.median(factors)),
            float(np.percentile(factors, 10)),
            "x real time",
            len(runs),
            target=50.0,
            at_least=True,
            note="p90 column: the slowest-tenth figure",
        ),
        BenchFigure("  its full tick (safety, controller, recorder, plant)", float(np.median(ticks_us)),
                    float(np.percentile(ticks_us, 90)), "us", len(runs)),
    ]  # fmt: skip


def bench_real_time_1khz(quick: bool) -> list[BenchFigure]:
    seconds = 5.0 if quick else 30.0
    hal = SimHal("exo_dummy_arm")
    hal.open()
    first = hal.read()
    hold = first.q_rad.copy()
    feedforward = APModel.from_description(hal.description, dummy_arm=True, elbow_stiffness=True)
    controller = MotorPositionPD(
        hal.description,
        lambda t: (hold, np.zeros(4)),
        LinkBounds.from_description(hal.description),
        feedforward=feedforward,
    )
    controller.reset(first)
    lateness: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        recorder = Recorder(Path(tmp) / "rt.rec", RECORD_COLUMNS)
        recorder.start()
        clock = RealTimeClock(1e-3)
        loop = ControlLoop(hal, SafetyMonitor(SafetyLimits.from_description(hal.description)),
                           FixedSupervisor(controller), clock, recorder)  # fmt: skip
        grant = request_realtime()
        try:
            loop.run(int(seconds * 1000), on_tick=lambda r: lateness.append(r.timing.lateness_s))
        finally:
            release_realtime()
        recorder.close()
    late_us = np.array(lateness[1:]) * 1e6
    stats = loop.stats
    scheduling = f"SCHED_FIFO {grant.fifo_priority}" if grant.fifo_priority else "ordinary scheduling"
    note = (
        f"{seconds:g} s, {scheduling}, {stats.overruns} overruns, {stats.missed_deadlines} missed deadlines, "
        f"worst lateness {stats.worst_lateness_s * 1e3:.2f} ms"
    )
    return [
        BenchFigure("real time 1 kHz: tick lateness p50", float(np.percentile(late_us, 50)),
                    float(np.percentile(late_us, 90)), "us", len(late_us), note=note),
        BenchFigure("real time 1 kHz: tick lateness p99", float(np.percentile(late_us, 99)),
                    float(np.percentile(late_us, 99.9)), "us", len(late_us), target=200.0, note="p90 column: p99.9"),
        BenchFigure("real time 1 kHz: tick lateness max", float(late_us.max()), float(late_us.max()), "us",
                    len(late_us)),
        BenchFigure("real time 1 kHz: overruns", float(stats.overruns), float(stats.overruns), "ticks", len(late_us)),
        BenchFigure("real time 1 kHz: missed deadlines", float(stats.missed_deadlines), float(stats.missed_deadlines),
                    "deadlines", len(late_us)),
        BenchFigure("real time 1 kHz: a tick's own work, mean (p90 column: worst)", stats.mean_work_s * 1e6,
                    stats.worst_work_s * 1e6, "us", stats.ticks),
    ]  # fmt: skip


_MEMORY_SCRIPT = """
import json, sys
sys.path.insert(0, {bench!r})
from bench_loop import _protocol_once
from daror_runtime.bench import high_water_mark_mb
factor, tick_us, ticks = _protocol_once()
print(json.dumps({{"peak_mb": high_water_mark_mb(), "ticks": ticks}}))
"""


def _peak_memory_of_a_protocol_run() -> dict[str, float]:
    script = _MEMORY_SCRIPT.format(bench=str(Path(__file__).parent))
    output = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def bench_protocol_peak_memory(quick: bool) -> list[BenchFigure]:
    """Peak resident memory of a fresh process running the training protocol.

    The first run after numba's on-disk cache was emptied also compiles every kernel, and LLVM's
    compile-time memory lands in the peak; the second run is the protocol alone.
    """
    start = time.perf_counter()
    first = _peak_memory_of_a_protocol_run()  # compiles whatever the cache lacks
    second = _peak_memory_of_a_protocol_run()
    note = f"{second['ticks']:.0f} ticks, {time.perf_counter() - start:.0f} s for both runs"
    return [
        BenchFigure("identification protocol: peak memory (whole process)", second["peak_mb"], second["peak_mb"],
                    "MB", 1, target=500.0, note=note),
        BenchFigure("  the same, first run (may include JIT compilation)", first["peak_mb"], first["peak_mb"], "MB", 1),
    ]  # fmt: skip


BENCHMARKS = [bench_identification_lock_step, bench_real_time_1khz, bench_protocol_peak_memory]
