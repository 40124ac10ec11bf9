"""The web console (issue 15): what serving a browser does to the 1 kHz loop in real time.

The loop at 1 kHz on its thread (SCHED_FIFO when granted), on the simulated plant, in its first
state, for the same time without and with the web console: the server (its own process), the
bridge in the runtime's process (a row into the shared ring every 20 ms and the status on a
change or every 400 ms, from the service thread), two browsers' worth of websocket clients reading the live
stream (20 messages/s each) and a button press (a console line, ``status``) every 2 s.
Every tick's lateness is kept (a clock that records what the real-time clock returns); the figures
are the mean, the 99th and 99.9th percentiles and the worst, and the ratios with/without
(target: within 5 %).
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
from daror_runtime.clocks import RealTimeClock, TickTiming
from daror_runtime.console.world import SimWorld
from daror_runtime.logs import configure_logging
from daror_runtime.runtime import Runtime
from hal.sim.backend import SimHal


class _RecordingClock(RealTimeClock):
    """The real-time clock, keeping every tick's lateness (s) in a preallocated array."""

    def __init__(self, period_s: float, capacity: int) -> None:
        super().__init__(period_s)
        self.lateness = np.zeros(capacity)
        self.n = 0

    def wait(self) -> TickTiming:
        timing = super().wait()
        if self.n < len(self.lateness):
            self.lateness[self.n] = timing.lateness_s
            self.n += 1
        return timing


#: Browsers are other processes: the clients run in one (their JSON parsing must not share the
#: loop's interpreter). argv: clients, seconds, press|nopress; the URL on standard input when they
#: should start; prints the rows each client received.
_CLIENTS = """
import json, sys, threading, time, urllib.request
from websockets.sync.client import connect
count, seconds = int(sys.argv[1]), float(sys.argv[2])
url = sys.stdin.readline().strip()  # started before the loop runs (a fork beside it stalls it); go when told
received = [0] * count
end = time.monotonic() + seconds
def read(slot):
    with connect(url.replace("http", "ws") + "/ws") as socket:
        while time.monotonic() < end:
            received[slot] += len(json.loads(socket.recv(timeout=5.0))["rows"])
def press():
    while time.monotonic() < end:
        time.sleep(2.0)
        body = json.dumps({"line": "status"}).encode()
        request = urllib.request.Request(url + "/api/command", data=body, headers={"Content-Type": "application/json"})
        urllib.request.urlopen(request, timeout=5.0).read()
threads = [threading.Thread(target=read, args=(i,)) for i in range(count)] + ([threading.Thread(target=press)] if "nopress" not in sys.argv else [])
for t in threads: t.start()
for t in threads: t.join()
print(json.dumps(received))
"""


def measure(seconds: float, web: bool, clients: int = 2, press: bool = True) -> dict[str, float]:
    """Lateness figures (ms) and fault counts of ``seconds`` at 1 kHz, with or without the web console."""
    configure_logging("critical")
    with tempfile.TemporaryDirectory() as directory:
        clock = _RecordingClock(1e-3, int(seconds * 1000) + 2000)
        runtime = Runtime(SimHal("exo_dummy_arm"), Path(directory), clock=clock)
        runtime.open()
        server = None
        received = [0] * max(clients, 1)
        world = SimWorld(runtime.world)  # the pilot seated in both runs (the same plant, the same state)
        browsers = None
        if web:
            from daror_runtime.console.web.serve import start_web

            server = start_web(runtime, world, port=0, require_token=False)  # loopback; the cost, not the access
            if clients:  # forked before the loop runs: a fork of this process beside the loop stalls it
                browsers = subprocess.Popen(
                    [sys.executable, "-c", _CLIENTS, str(clients), str(seconds), "press" if press else "nopress"],
                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                )  # fmt: skip
        runtime.runner.start()
        time.sleep(1.0)  # the first second (the grid's start) is not measured
        skip = clock.n
        if browsers is not None and server is not None:
            out, _ = browsers.communicate(server.url + "\n", timeout=seconds + 30)
            received = json.loads(out)
        else:
            time.sleep(seconds)
        late = clock.lateness[skip : clock.n] * 1e3
        status = runtime.snapshot()
        if server is not None:
            server.stop()
        runtime.shutdown("bench")
        runtime.close()
    return {
        "ticks": float(len(late)),
        "mean_ms": float(late.mean()),
        "p99_ms": float(np.percentile(late, 99)),
        "p999_ms": float(np.percentile(late, 99.9)),
        "worst_ms": float(late.max()),
        "worst_at_s": float(np.argmax(late)) / 1000.0,
        "overruns": float(status.loop.overruns),
        "missed": float(status.loop.missed_deadlines),
        "faults": float(len(status.faults)),
        "rows_per_s": sum(received) / len(received) / seconds,
    }


def _median(runs: list[dict[str, float]], key: str) -> float:
    return float(np.median([run[key] for run in runs]))


def _spread(runs: list[dict[str, float]], key: str, scale: float = 1e3) -> str:
    values = [run[key] * scale for run in runs]
    return f"{min(values):.2f}-{max(values):.2f}"


def bench_web_tick_lateness(quick: bool) -> list[BenchFigure]:
    """Rounds of without (A), with (B) and without again (A'), interleaved, the order rotating: the VM drifts.

    The mean lateness of a 1 kHz loop is well under a microsecond and dominated by a handful of
    scheduler stalls per run, which come and go with the machine's other tenants: one run each
    way cannot tell 5 %. So the figures are medians over rounds of each run's mean, 99th and
    99.9th percentile; the ratios are of those medians, B/A, and A'/A beside them: what the same
    loop without a web console scores against itself, the resolution of the comparison.
    """
    rounds, seconds = (2, 5.0) if quick else (6, 10.0)
    runs: dict[str, list[dict[str, float]]] = {"A": [], "B": [], "A'": []}
    orders = (("A", "B", "A'"), ("B", "A'", "A"), ("A'", "A", "B"))
    for k in range(rounds):
        for label in orders[k % 3]:
            runs[label].append(measure(seconds, web=label == "B"))
    figures = []
    for label, what in (
        ("A", "without the web console"),
        ("B", "with the web console streaming"),
        ("A'", "without it again (control)"),
    ):
        group = runs[label]
        note = (
            f"{rounds} runs of {seconds:g} s interleaved; per-run mean {_spread(group, 'mean_ms')} us,"
            f" p99 {_spread(group, 'p99_ms')} us; median p99.9 {_median(group, 'p999_ms'):.3f} ms, worst"
            f" {max(run['worst_ms'] for run in group):.3f} ms, {sum(run['overruns'] for run in group):.0f} overruns,"
            f" {sum(run['faults'] for run in group):.0f} faults"
        )
        if label == "B":
            note += f"; {min(run['rows_per_s'] for run in group):.0f}+ rows/s to each of 2 browsers"
        figures.append(
            BenchFigure(
                f"1 kHz real time, {what} ({label}): tick lateness mean (p99), median of runs",
                _median(group, "mean_ms"),
                _median(group, "p99_ms"),
                "ms",
                len(group),
                note=note,
            )
        )
    for what, key in (("mean", "mean_ms"), ("p99", "p99_ms"), ("p99.9", "p999_ms")):
        base = _median(runs["A"], key)
        control = _median(runs["A'"], key) / base
        figures.append(
            BenchFigure(
                f"web console: tick lateness {what}, B/A (median of runs)",
                _median(runs["B"], key) / base,
                _median(runs["B"], key) / base,
                "ratio",
                rounds,
                target=1.05,
                note=f"control A'/A: {control:.2f}",
            )
        )
    return figures


BENCHMARKS = [bench_web_tick_lateness]
