"""``daror rt-check``: can this PC run the robot's loop at its rate? Measured with the real loop.

The check runs :class:`~daror_runtime.loop.ControlLoop` on the real-time clock, with the overrun
watchdog of a session (:data:`~daror_runtime.loop.DEFAULT_OVERRUN_LIMIT`,
:data:`~daror_runtime.loop.DEFAULT_MAX_STALL_PERIODS`), ``SCHED_FIFO`` and ``mlockall`` when the
OS grants them (:mod:`daror_runtime.realtime`), the interpreter set up as a session's background
loop (switch interval 0.1 ms, no cyclic garbage collection), the recorder on, for N seconds at the
backend's rate. What ticks is the simulated plant with the Dummy Arm, its pose held by the motor
position controller (never the robot: a ``can`` configuration only gives its rate). Each tick's
lateness against the deadline it was due at is kept; a fault the watchdog raises is counted, and
then cleared so that every tick does the same work (a session would have gone to FAIL).

The verdict (:func:`judge`, D141): the PC can run the robot when the watchdog would not have
faulted once and the worst tick started at most half as late as the stall the watchdog faults
(``max_stall_periods`` periods): a 30 s check sees less of the tail than a 45-minute session.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from daror_runtime.clocks import RealTimeClock
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.position import LinkBounds
from daror_runtime.data.recorder import Recorder
from daror_runtime.data.tick_row import RECORD_COLUMNS
from daror_runtime.errors import UsageError
from daror_runtime.loop import (
    DEFAULT_MAX_STALL_PERIODS,
    DEFAULT_OVERRUN_LIMIT,
    ControlLoop,
    FixedSupervisor,
    TickResult,
)
from daror_runtime.models.linear import APModel
from daror_runtime.realtime import release_realtime, request_realtime
from daror_runtime.safety.faults import FaultKind
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from hal.config import AnyHalConfig, hal_config
from hal.interface import Hal, open_hal

log = structlog.get_logger(__name__)

#: The longest check, s (a longer one is a soak test: run a session).
MAX_SECONDS = 3600.0
#: The worst lateness a PC may show, as a fraction of the stall the watchdog faults (D141).
LATENESS_MARGIN = 0.5
#: The interpreter's thread switch interval while the check runs, s (the runtime's in real time).
SWITCH_INTERVAL_S = 1e-4
#: Watchdog messages kept in the report (the first ones).
KEPT_MESSAGES = 5


@dataclass(frozen=True)
class Lateness:
    """Percentiles of the ticks' lateness against the deadline each was due at, in us (ticks 0 and 1 left out)."""

    p50_us: float
    p99_us: float
    p99_9_us: float
    max_us: float


@dataclass(frozen=True)
class RtFigures:
    """What the verdict is judged on.

    Attributes:
        rate_hz: the loop's rate, Hz.
        duration_s: wall-clock time of the run, s.
        ticks: ticks run.
        lateness: the ticks' lateness percentiles.
        overruns: ticks that started after their deadline.
        missed_deadlines: deadlines missed in all (skipped ones included).
        watchdog_faults: ``overrun`` faults the watchdog raised (each would have sent a session to FAIL).
        first_fault_s: wall-clock time of the first, s after the run's start (None: none).
        scheduling: how the loop was scheduled (``SCHED_FIFO 50, memory locked``, ...).
        load_average: the 1, 5 and 15 min load averages when the run ended (the 1 min one covers
            the run; at its start it still showed the minute before).
        cpus: the CPUs this process may run on.
        overrun_limit: deadlines missed in a row that fault.
        max_stall_periods: deadlines one stall may miss before it faults.
    """

    rate_hz: float
    duration_s: float
    ticks: int
    lateness: Lateness
    overruns: int
    missed_deadlines: int
    watchdog_faults: int
    first_fault_s: float | None
    scheduling: str
    load_average: tuple[float, float, float]
    cpus: int
    overrun_limit: int = DEFAULT_OVERRUN_LIMIT
    max_stall_periods: int = DEFAULT_MAX_STALL_PERIODS

    @property
    def stall_limit_ms(self) -> float:
        """The lateness at which one stall faults, ms (``max_stall_periods`` periods)."""
        return self.max_stall_periods * 1e3 / self.rate_hz


@dataclass(frozen=True)
class Verdict:
    can_run: bool
    line: str  # one sentence with the figures it rests on


def _times(n: int) -> str:
    return "once" if n == 1 else f"{n} times"


def judge(figures: RtFigures) -> Verdict:
    """Whether the PC can run the loop at ``figures.rate_hz`` (D141), in one sentence with the figures."""
    f = figures
    late = f.lateness
    worst_ms = late.max_us / 1e3
    limit_ms = f.stall_limit_ms
    load = " ".join(f"{x:.2f}" for x in f.load_average)
    context = (
        f"p99.9 {late.p99_9_us:.1f} us, {f.missed_deadlines} missed deadlines in {f.ticks} ticks; "
        f"{f.scheduling}; load {load} on {f.cpus} CPUs"
    )
    hint = "" if f.scheduling.startswith("SCHED_FIFO") else "; check again where SCHED_FIFO is granted"
    robot = f"the robot at {f.rate_hz:g} Hz"
    if f.watchdog_faults:
        first = "" if f.first_fault_s is None else f", the first after {f.first_fault_s:.1f} s (a session fails then)"
        return Verdict(
            False,
            f"this PC cannot run {robot}: the overrun watchdog faulted {_times(f.watchdog_faults)} in "
            f"{f.duration_s:.1f} s{first}; worst tick {worst_ms:.2f} ms late (a stall of {limit_ms:g} ms faults), "
            f"{context}{hint}",
        )
    if worst_ms > LATENESS_MARGIN * limit_ms:
        return Verdict(
            False,
            f"this PC cannot run {robot} with a margin: no overrun fault in {f.duration_s:.1f} s, but the worst "
            f"tick was {worst_ms:.2f} ms late, more than half the {limit_ms:g} ms stall the watchdog faults; "
            f"{context}{hint}",
        )
    return Verdict(
        True,
        f"this PC can run {robot}: no overrun fault in {f.duration_s:.1f} s, worst tick {worst_ms:.2f} ms late "
        f"(a stall of {limit_ms:g} ms faults), {context}",
    )


@dataclass(frozen=True)
class RtCheckReport:
    """One check: what ran, the figures, the verdict (``--json``: :meth:`as_dict`).

    Attributes:
        backend: the backend whose rate was checked (``sim``, ``can-sim``, ``can``).
        plant: what ticked.
        seconds: the run's length asked for, s.
        deadlines: the deadline grid's slots the run covered (``ticks`` plus the skipped ones).
        figures: what the verdict is judged on.
        watchdog_messages: the first watchdog faults' messages.
        other_faults: any other fault of the run (none on a sound plant), as ``kind: message``.
        tick_work_mean_us: the mean of a tick's own work, us.
        tick_work_max_us: the longest tick's own work, us.
        fifo_priority: the ``SCHED_FIFO`` priority obtained (None: refused).
        memory_locked: ``mlockall`` granted.
        refusals: what the OS refused, and why.
        load_average_start: the load averages when the run started.
        verdict: the judgement.
    """

    backend: str
    plant: str
    seconds: float
    deadlines: int
    figures: RtFigures
    watchdog_messages: tuple[str, ...]
    other_faults: tuple[str, ...]
    tick_work_mean_us: float
    tick_work_max_us: float
    fifo_priority: int | None
    memory_locked: bool
    refusals: tuple[str, ...]
    load_average_start: tuple[float, float, float]
    verdict: Verdict

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, with the date and the machine."""
        from daror_runtime.bench import machine

        return dataclasses.asdict(self) | {"machine": machine()}


def check_seconds(seconds: float) -> float:
    """``seconds`` if it is a run length the check takes.

    Raises:
        UsageError: not finite, not positive, or over :data:`MAX_SECONDS`.
    """
    if not (math.isfinite(seconds) and 0.0 < seconds <= MAX_SECONDS):
        raise UsageError(f"--seconds {seconds:g}: expected a duration in s, more than 0 and at most {MAX_SECONDS:g}")
    return seconds


def measured_backend(config: AnyHalConfig) -> tuple[Hal, Hal]:
    """``(the configured backend, the plant the check ticks)``, neither opened.

    The configured backend (which may drive hardware) is only built, for its rate; the check
    ticks the simulated plant at that rate, with the Dummy Arm.

    Raises:
        HalConfigError: the configuration does not make a backend, or the plant cannot run at its rate.
        BackendUnavailableError: the backend needs a package that is not installed.
    """
    backend = open_hal(config)
    plant = open_hal(hal_config("sim", f"the {config.backend} backend's rate", rate_hz=backend.rate_hz))
    return backend, plant


def _load_average() -> tuple[float, float, float]:
    one, five, fifteen = os.getloadavg()
    return one, five, fifteen


def _cpus() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _scheduling(requested: bool, fifo_priority: int | None, memory_locked: bool) -> str:
    if not requested:
        return "ordinary scheduling (SCHED_FIFO not asked for)"
    if fifo_priority is None:
        return "ordinary scheduling (SCHED_FIFO refused)"
    return f"SCHED_FIFO {fifo_priority}" + (", memory locked" if memory_locked else ", memory not locked")


def run_rt_check(backend: Hal, plant: Hal, seconds: float, realtime: bool = True) -> RtCheckReport:
    """Run the loop on ``plant`` at its rate for ``seconds`` of wall-clock time and judge the figures.

    Args:
        backend: the backend whose rate is checked (named in the report; never opened).
        plant: a simulated backend at that rate, not opened (:func:`measured_backend`); closed at the end.
        seconds: how long, s.
        realtime: ask the OS for ``SCHED_FIFO`` and ``mlockall`` (released at the end).

    Raises:
        UsageError: ``seconds`` out of range (:func:`check_seconds`).
        HalError: the plant failed to open.
    """
    check_seconds(seconds)
    rate = plant.rate_hz
    period = 1.0 / rate
    deadlines = max(3, round(seconds * rate))  # ticks 0 and 1 anchor the grid; at least one tick is measured
    lateness = np.full(deadlines, np.nan)
    watchdog: list[tuple[float, str]] = []
    other: list[str] = []
    plant.open()
    try:
        first = plant.read()
        description = plant.description
        hold = first.q_rad.copy()
        controller = MotorPositionPD(
            description,
            lambda _t: (hold, np.zeros(4)),
            LinkBounds.from_description(description),
            feedforward=APModel.from_description(description, dummy_arm=True, elbow_stiffness=True),
        )
        controller.reset(first)
        monitor = SafetyMonitor(SafetyLimits.from_description(description))
        with tempfile.TemporaryDirectory(prefix="daror-rt-check-") as folder:
            recorder = Recorder(Path(folder) / "rt.rec", RECORD_COLUMNS)
            recorder.start()
            loop = ControlLoop(plant, monitor, FixedSupervisor(controller), RealTimeClock(period), recorder)

            def on_tick(result: TickResult) -> None:
                timing = result.timing
                if timing.index < deadlines:
                    lateness[timing.index] = timing.lateness_s
                for fault in result.faults:
                    if fault.kind is FaultKind.OVERRUN:
                        watchdog.append((timing.index * period, fault.message))
                    else:
                        other.append(f"{fault.kind.value}: {fault.message}")
                if monitor.faulted:  # the same work in every tick: a session would have failed here
                    monitor.clear()

            load_start = _load_average()
            switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(SWITCH_INTERVAL_S)
            grant = request_realtime() if realtime else None
            began = time.perf_counter()
            try:
                loop.run(deadlines, on_tick=on_tick, stop=lambda result: result.timing.index >= deadlines - 1)
            finally:
                duration = time.perf_counter() - began
                if grant is not None:
                    release_realtime()
                sys.setswitchinterval(switch_interval)
                recorder.close()
        load_end = _load_average()
    finally:
        plant.close()
    late_us = lateness[2:][~np.isnan(lateness[2:])] * 1e6
    stats = loop.stats
    fifo = None if grant is None else grant.fifo_priority
    locked = grant is not None and grant.memory_locked
    figures = RtFigures(
        rate_hz=rate,
        duration_s=duration,
        ticks=stats.ticks,
        lateness=Lateness(*(float(np.percentile(late_us, q)) for q in (50.0, 99.0, 99.9)), float(late_us.max())),
        overruns=stats.overruns,
        missed_deadlines=stats.missed_deadlines,
        watchdog_faults=len(watchdog),
        first_fault_s=watchdog[0][0] if watchdog else None,
        scheduling=_scheduling(grant is not None, fifo, locked),
        load_average=load_end,
        cpus=_cpus(),
        overrun_limit=loop.overrun_limit,
        max_stall_periods=loop.max_stall_periods,
    )
    verdict = judge(figures)
    report = RtCheckReport(
        backend=backend.kind,
        plant=f"the simulated plant ({plant.kind}) with the Dummy Arm, held by the motor position controller",
        seconds=seconds,
        deadlines=stats.ticks + loop.clock.stats.skipped_deadlines,
        figures=figures,
        watchdog_messages=tuple(message for _, message in watchdog[:KEPT_MESSAGES]),
        other_faults=tuple(other[:KEPT_MESSAGES]),
        tick_work_mean_us=stats.mean_work_s * 1e6,
        tick_work_max_us=stats.worst_work_s * 1e6,
        fifo_priority=fifo,
        memory_locked=locked,
        refusals=() if grant is None else grant.refusals,
        load_average_start=load_start,
        verdict=verdict,
    )
    log.info("rt-check", rate_hz=rate, seconds=seconds, can_run=verdict.can_run, verdict=verdict.line)
    return report
