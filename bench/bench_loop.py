"""Benchmarks of the control loop (issues 3 and 11).

* The whole ``daror identify --trajectory training`` command (752 s of robot time) in a fresh
  interpreter, as a user runs it, from the process's start to its exit: at least 100x faster than
  real time, and its own peak memory (the child's ``VmHWM``) below 400 MB (issue 11).
* The identification loop alone (training, 752 s of robot time) in lock-step time on the
  simulated plant, full tick (safety, controller, recorder): at least 200x faster than real time,
  5 us a tick (issue 11; 50x in issue 3).
* Real-time mode at 1 kHz for 30 s (the same tick, recorder on): tick lateness p50/p99/max (against
  the deadline each tick was due at, so a stall counts in full), overruns and missed deadlines
  (``ControlLoop.stats``), and the tick's own work (mean and worst); p99 below 200 us.
* Peak memory of the protocol run (a fresh process): below 400 MB.

``daror bench`` prints the load average beside every figure: these share a machine.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from daror_runtime.bench import BenchFigure, command_in_child
from daror_runtime.clocks import LockStepClock, RealTimeClock
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.position import LinkBounds
from daror_runtime.data.load import raw_log_path
from daror_runtime.data.recorder import Recorder
from daror_runtime.data.tick_row import RECORD_COLUMNS
from daror_runtime.identification.protocol import let_the_writer_catch_up, plan_run, run_protocol
from daror_runtime.identification.settings import IdentificationSettings
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


def _python_ticks_once(seconds: float) -> float:
    """us per tick of the identification loop with every tick through ``ControlLoop.tick`` (no batches).

    The path every tick takes in a session and in real time (the FSM's supervisor decides each
    tick), measured on the same protocol as :func:`_protocol_once` for its first ``seconds``.
    """
    hal = SimHal("exo_dummy_arm")
    hal.open()
    trajectory = build_trajectory(load_waypoints(), "training")
    feedforward = APModel.from_description(hal.description, dummy_arm=True, elbow_stiffness=True)
    first = hal.read()
    with tempfile.TemporaryDirectory() as tmp:
        run = plan_run(trajectory, hal.description, first.q_rad, IdentificationSettings(), feedforward, 1e-3,
                       Path(tmp) / "run.rec", Path(tmp) / "run.csv")  # fmt: skip
        run.controller.reset(first)
        monitor = SafetyMonitor(SafetyLimits.from_description(hal.description))
        loop = ControlLoop(hal, monitor, FixedSupervisor(run.controller), LockStepClock(1e-3), run.recorder,
                           compiled_batches=False)  # fmt: skip
        chunks = int(seconds)
        began = time.perf_counter()
        for _ in range(chunks):
            loop.run(1000, stop_on_fault=True)
            let_the_writer_catch_up(run.recorder)
        wall = time.perf_counter() - began
        run.recorder.close()
    return wall / (chunks * 1000) * 1e6


def bench_identification_lock_step(quick: bool) -> list[BenchFigure]:
    """The loop alone: ``run_protocol``'s wall time covers the ticks, not the planning or the data after.

    ``run_protocol`` runs its ticks in compiled batches (daror_runtime/loop_batch.py); the last
    figure is the same loop with every tick in Python, the path of a session and of real time.
    """
    runs = [_protocol_once() for _ in range(1 if quick else 3)]
    factors = np.array([r[0] for r in runs])
    ticks_us = np.array([r[1] for r in runs])
    spread = ", ".join(f"{f:.0f}x" for f in sorted(factors))
    seconds = 20.0 if quick else 100.0
    python_us = np.array([_python_ticks_once(seconds) for _ in range(1 if quick else 3)])
    return [
        BenchFigure(
            "identification loop alone, lock-step (training, 752 s robot time)",
            float(np.median(factors)),
            float(np.percentile(factors, 10)),
            "x real time",
            len(runs),
            target=200.0,
            at_least=True,
            note=f"p90 column: the slowest-tenth figure; runs {spread}",
        ),
        BenchFigure("  its full tick (safety, controller, recorder, plant)", float(np.median(ticks_us)),
                    float(np.percentile(ticks_us, 90)), "us", len(runs), target=5.0),
        BenchFigure("  the same tick through ControlLoop.tick (no batches: sessions, real time)",
                    float(np.median(python_us)), float(np.percentile(python_us, 90)), "us", len(python_us),
                    note=f"first {seconds:g} s of the protocol per run"),
    ]  # fmt: skip


#: The command measured: what a user types (``--out`` added per run).
IDENTIFY_ARGV = ("identify", "--scenario", "exo_dummy_arm", "--trajectory", "training")


def bench_identify_command(quick: bool) -> list[BenchFigure]:
    """The whole ``daror identify --trajectory training``: a fresh interpreter, start to exit.

    Everything the command does is in the figure: interpreter start and imports, loading the
    compiled kernels, planning the trajectory, the loop, reading the recording back, the stationary
    reduction, writing the dataset and the raw log, and the interpreter's exit. Robot time is the
    length of the raw log the command wrote (one sample a tick at 1 kHz).
    """
    runs: list[tuple[float, float, float]] = []  # robot s, wall s, peak MB
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for n in range(1 if quick else 3):
            out = folder / f"train{n}.csv"
            run = command_in_child([*IDENTIFY_ARGV, "--out", str(out)], folder)
            if run.code != 0 or run.peak_mb is None:
                raise RuntimeError(f"daror {' '.join(IDENTIFY_ARGV)}: exit code {run.code}: {run.stderr[-2000:]}")
            with np.load(raw_log_path(out, ".npz")) as raw:
                robot_s = raw["t"].size / 1000.0
            runs.append((robot_s, run.wall_s, run.peak_mb))
            for produced in folder.glob(f"train{n}*"):
                produced.unlink()  # one run's outputs at a time on the disk
    robot = runs[0][0]
    walls = np.array([r[1] for r in runs])
    factors = robot / walls
    peaks = np.array([r[2] for r in runs])
    walls_text = ", ".join(f"{w:.2f}" for w in sorted(walls))
    return [
        BenchFigure(
            "daror identify --trajectory training, whole command (fresh process, start to exit)",
            float(np.median(factors)),
            float(np.percentile(factors, 10)),
            "x real time",
            len(runs),
            target=100.0,
            at_least=True,
            note=f"{robot:.0f} s of robot time; wall {walls_text} s; p90 column: the slowest-tenth figure",
        ),
        BenchFigure("  its wall time, start to exit", float(np.median(walls)), float(np.percentile(walls, 90)), "s",
                    len(runs), target=robot / 100.0),
        BenchFigure("  its peak memory (the child's own VmHWM)", float(np.median(peaks)), float(peaks.max()), "MB",
                    len(runs), target=400.0, note="p90 column: the largest of the runs"),
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
                    "MB", 1, target=400.0, note=note),
        BenchFigure("  the same, first run (may include JIT compilation)", first["peak_mb"], first["peak_mb"], "MB", 1),
    ]  # fmt: skip


BENCHMARKS = [bench_identify_command, bench_identification_lock_step, bench_real_time_1khz, bench_protocol_peak_memory]
