"""The operator's console (issue 9): what the status view costs, what a console thread does to the
1 kHz loop in real time, and the whole ``daror console`` command from process start to exit.

* **status view**: ``Runtime.snapshot()`` + the next steps + the text, as ``status`` and the prompt's
  bottom line build it (target: well under a tick's budget is not needed, it runs outside the loop;
  the figure says what the console thread holds the interpreter for).
* **real time with a console**: the loop at 1 kHz on its thread (SCHED_FIFO when granted) while a
  console thread builds the status view every 100 ms, with the interpreter's switch interval at the
  runtime's 0.1 ms and at Python's default 5 ms, compared in one run: missed deadlines, overruns and
  the worst lateness. Target: no missed deadline past the watchdog's stall limit (3 periods).
* **whole commands**: ``daror console --script`` of the shipped rehearsal (every third waypoint),
  and the unguided operator's transcript piped in (default settings: the full 83-waypoint protocol),
  process start to exit.
"""

from __future__ import annotations

import io
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from rich.console import Console

import daror_runtime.runner as runner_module
from daror_runtime.bench import BenchFigure, time_calls
from daror_runtime.clocks import RealTimeClock
from daror_runtime.console.guide import next_steps
from daror_runtime.console.run import make_session
from daror_runtime.console.view import render_status
from daror_runtime.demo.rehearsal import session_script
from daror_runtime.logs import configure_logging
from daror_runtime.runtime import Runtime
from hal.sim.backend import SimHal

DAROR = Path(sys.executable).with_name("daror")
ROOT = Path(__file__).resolve().parents[1]


def bench_console_status_view(quick: bool) -> BenchFigure:
    with tempfile.TemporaryDirectory() as directory:
        runtime = Runtime(SimHal("exo_dummy_arm"), Path(directory))
        runtime.open()
        runtime.runner.run_ticks(10)
        repeats = 20 if quick else 200
        median, p90 = time_calls(
            lambda: render_status(runtime.snapshot(), next_steps(runtime.snapshot(), True)),
            repeats=repeats,
            per_call=20,
            scale=1e6,
        )
        runtime.shutdown("bench")
        runtime.close()
    return BenchFigure("status view: snapshot, next steps, text", median, p90, "us", repeats)


def _real_time_with_console(seconds: float, switch_interval_s: float, busy: bool = True) -> tuple[int, int, int, float]:
    """(ticks, overruns, missed deadlines, worst lateness ms) of ``seconds`` at 1 kHz beside a console thread
    that builds the status view every 100 ms (``busy``) or only wakes up (the VM's own stalls)."""
    configure_logging("critical")
    saved = runner_module.REALTIME_SWITCH_INTERVAL_S
    runner_module.REALTIME_SWITCH_INTERVAL_S = switch_interval_s
    try:
        with tempfile.TemporaryDirectory() as directory:
            runtime = Runtime(SimHal("exo_dummy_arm"), Path(directory), clock=RealTimeClock(1e-3))
            runtime.open()
            buffer = io.StringIO()
            session = make_session(runtime, Console(file=buffer, width=160))
            runtime.runner.start()
            stop = threading.Event()

            def console() -> None:  # what an operator's terminal asks of the runtime, and more
                while not stop.wait(0.1):
                    if busy:
                        session.execute("status")
                        buffer.seek(0)
                        buffer.truncate()

            thread = threading.Thread(target=console)
            thread.start()
            time.sleep(seconds)
            stop.set()
            thread.join()
            stats = runtime.runner.stats
            runtime.shutdown("bench")
            runtime.close()
    finally:
        runner_module.REALTIME_SWITCH_INTERVAL_S = saved
    return stats.ticks, stats.overruns, stats.missed_deadlines, stats.worst_lateness_s * 1e3


def bench_console_real_time_loop(quick: bool) -> list[BenchFigure]:
    seconds = 5.0 if quick else 30.0
    figures = []
    cases = (
        ("console status every 100 ms, switch interval runtime's 0.1 ms", 1e-4, True),
        ("console status every 100 ms, switch interval Python's default 5 ms", sys.getswitchinterval(), True),
        ("an idle console thread (the VM's own stalls)", 1e-4, False),
    )
    for label, interval, busy in cases:
        ticks, overruns, missed, worst_ms = _real_time_with_console(seconds, interval, busy)
        figures.append(
            BenchFigure(
                f"1 kHz real time, {label}: worst lateness",
                worst_ms,
                worst_ms,
                "ms",
                1,
                target=3.0,
                note=f"{seconds:g} s, {ticks} ticks: {overruns} overruns, {missed} missed deadlines",
            )
        )
    return figures


def _whole_command(arguments: list[str], stdin: str | None = None) -> float:
    start = time.perf_counter()
    run = subprocess.run(
        [str(DAROR), *arguments], input=stdin, capture_output=True, text=True, timeout=1800, check=False
    )
    elapsed = time.perf_counter() - start
    if run.returncode != 0:
        raise RuntimeError(f"daror {' '.join(arguments)} exited {run.returncode}: {run.stderr[-500:]}")
    return elapsed


def bench_console_whole_commands(quick: bool) -> list[BenchFigure]:
    with tempfile.TemporaryDirectory() as directory:
        folder = Path(directory)
        settings = folder / "settings.yaml"
        settings.write_text("dummy_arm: true\nidentification:\n  waypoint_stride: 3\n", encoding="utf-8")
        repeats = 1 if quick else 3
        script = [
            _whole_command(
                [
                    "console",
                    "--script",
                    str(session_script()),
                    "--settings",
                    str(settings),
                    "--out",
                    str(folder / f"s{i}"),
                ]
            )
            for i in range(repeats)
        ]
        figures = [
            BenchFigure(
                "daror console --script (the rehearsal, 660 s robot time), process start to exit",
                float(np.median(script)),
                float(max(script)),
                "s",
                repeats,
                note=f"runs: {', '.join(f'{s:.1f}' for s in script)} s",
            )
        ]
        if not quick:
            transcript = (ROOT / "tests" / "data" / "unguided_operator.txt").read_text(encoding="utf-8")
            unguided = _whole_command(["console", "--out", str(folder / "unguided")], stdin=transcript)
            figures.append(
                BenchFigure(
                    "daror console, the unguided operator's lines piped in (default settings, full protocol)",
                    unguided,
                    unguided,
                    "s",
                    1,
                )
            )
    return figures


BENCHMARKS = [bench_console_status_view, bench_console_real_time_loop, bench_console_whole_commands]
