"""The fixed-rate control loop: one tick is read, check, decide, update, filter, write, record.

DESIGN.md section 3::

    sample = hal.read()                      # q, dq, motor angles, spring torque, e-stop, drives
    faults = safety.check(sample)            # limits, plausibility, staleness, e-stop, drives
    controller = supervisor.on_tick(...)     # the FSM applies requests and faults here (issue 4)
    command = controller.update(sample, dt)  # the controllers never touch hardware
    command = safety.filter(command)         # torque off while faulted or an e-stop is pressed
    recorder.push(sample, command); hal.write(command)

Rules kept here: nothing inside the tick blocks (the recorder hands blocks to a writer thread);
every fault removes torque in the tick it is found (the filter runs after the faults of this
tick are latched, and a HAL or software error is itself a fault); errors are never swallowed:
an exception from the controller or the recorder is reported as a ``software`` fault with its
message, logged, and the loop goes on with torque off.
"""

from __future__ import annotations

import gc
from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np
import structlog
from numba import njit

from daror_runtime.clocks import Clock, TickTiming
from daror_runtime.data.recorder import recording_columns
from daror_runtime.errors import DarorError
from daror_runtime.safety.faults import Fault, FaultKind
from daror_runtime.safety.monitor import SafetyMonitor
from hal.errors import HalError
from hal.interface import TORQUE_OFF, Command, Hal, Sample

log = structlog.get_logger(__name__)

#: Columns of the loop's recording, one row per tick: the raw-log columns (t, q, dq, tau, theta,
#: tau_cmd), then whether the drives were enabled, whether a fault was latched, and the lateness.
RECORD_COLUMNS: tuple[str, ...] = recording_columns(theta=True, tau_cmd=True, extra=("enable", "faulted", "lateness_s"))

#: Consecutive overruns that make a fault (a 1 kHz loop that misses 5 ms in a row is not in control).
DEFAULT_OVERRUN_LIMIT = 5


class TickController(Protocol):
    """What the loop needs of a controller (``daror_runtime.control.base.Controller``)."""

    def update(self, sample: Sample, dt_s: float) -> Command: ...


class Supervisor(Protocol):
    """Decides, once per tick, which controller runs (issue 4: the FSM).

    Called after the safety check with the new faults of the tick; returns the controller for
    this tick, or None for torque off.
    """

    def on_tick(self, sample: Sample | None, faults: list[Fault], monitor: SafetyMonitor) -> TickController | None: ...

    def on_late_faults(self, sample: Sample | None, faults: list[Fault]) -> None:
        """Faults found after :meth:`on_tick` in the same tick (controller, recorder, HAL write)."""
        ...


class FixedSupervisor:
    """One controller until told otherwise; changes take effect at the next tick boundary."""

    def __init__(self, controller: TickController | None = None) -> None:
        self._controller = controller
        self._pending: list[TickController | None] = []

    def use(self, controller: TickController | None) -> None:
        self._pending.append(controller)

    def on_tick(self, sample: Sample | None, faults: list[Fault], monitor: SafetyMonitor) -> TickController | None:
        while self._pending:
            self._controller = self._pending.pop(0)
        return self._controller

    def on_late_faults(self, sample: Sample | None, faults: list[Fault]) -> None:
        """Nothing to decide: the filter already removed torque."""


class Recording(Protocol):
    """What the loop needs of a recorder (``daror_runtime.data.recorder.Recorder``)."""

    def push(self, row: np.ndarray) -> bool: ...


class TickResult(NamedTuple):
    timing: TickTiming
    sample: Sample | None
    command: Command  # as written to the hardware
    faults: list[Fault]  # new in this tick


class ControlLoop:
    """Runs ticks at the clock's rate over one HAL.

    Args:
        hal: an opened backend.
        monitor: the safety monitor (owns the latched faults).
        supervisor: decides the controller per tick.
        clock: real-time or lock-step.
        recorder: receives one row of :data:`RECORD_COLUMNS` per tick (optional).
        overrun_limit: consecutive overruns that make an ``overrun`` fault.
    """

    def __init__(
        self,
        hal: Hal,
        monitor: SafetyMonitor,
        supervisor: Supervisor,
        clock: Clock,
        recorder: Recording | None = None,
        overrun_limit: int = DEFAULT_OVERRUN_LIMIT,
    ) -> None:
        self.hal = hal
        self.monitor = monitor
        self.supervisor = supervisor
        self.clock = clock
        self.recorder = recorder
        self.overrun_limit = overrun_limit
        self.dt_s = clock.period_s
        self._row = np.zeros(len(RECORD_COLUMNS))
        self._last_t_s = 0.0
        self._started = False
        self.dropped_rows = 0

    def start(self) -> None:
        """Start the clock; the HAL must be open."""
        self.monitor.reset_history()
        self.clock.start()
        self._started = True

    def tick(self) -> TickResult:
        """One tick. Never raises for hardware, controller or recorder errors: they become faults."""
        timing = self.clock.wait()
        monitor = self.monitor
        monitor.begin_tick()
        try:
            sample: Sample | None = self.hal.read()
        except HalError as exc:
            sample = None
            faults: list[Fault] = []
            self._report(faults, FaultKind.HAL, f"reading the hardware failed: {exc}")
        else:
            self._last_t_s = sample.t_s
            faults = monitor.check(sample)
        if timing.consecutive_overruns >= self.overrun_limit:
            self._report(
                faults, FaultKind.OVERRUN, f"{timing.consecutive_overruns} consecutive ticks missed their deadline"
            )
        controller = self.supervisor.on_tick(sample, faults, monitor)
        decided = len(faults)  # the supervisor saw these; later ones are passed to it at the end of the tick
        command = TORQUE_OFF
        if sample is not None and controller is not None and not monitor.faulted:
            try:
                command = controller.update(sample, self.dt_s)
            except DarorError as exc:
                self._report(faults, FaultKind.SOFTWARE, f"{type(controller).__name__} failed: {exc}")
            except Exception as exc:  # a bug in a controller must stop the robot, not the loop
                log.exception("controller raised", controller=type(controller).__name__)
                self._report(faults, FaultKind.SOFTWARE, f"{type(controller).__name__} raised {exc!r}")
        command = monitor.filter(command, sample)
        recorder = self.recorder
        if recorder is not None:
            try:
                if not recorder.push(self._fill_row(sample, command, timing)):
                    self.dropped_rows += 1
                    if self.dropped_rows == 1:  # a dropped row is data loss, not danger: say so once, count all
                        log.warning("recorder dropped a row: the disk cannot keep up", t_s=self._last_t_s)
            except DarorError as exc:
                self._report(faults, FaultKind.SOFTWARE, f"recorder failed: {exc}")
                command = TORQUE_OFF
        try:
            self.hal.write(command)
        except HalError as exc:
            self._report(faults, FaultKind.HAL, f"writing the hardware failed: {exc}")
        if len(faults) > decided:
            self.supervisor.on_late_faults(sample, faults[decided:])
        return TickResult(timing, sample, command, faults)

    def run(
        self,
        ticks: int,
        on_tick: Callable[[TickResult], None] | None = None,
        stop: Callable[[TickResult], bool] | None = None,
        disable_gc: bool = True,
        stop_on_fault: bool = False,
    ) -> TickResult | None:
        """Run up to ``ticks`` ticks; returns the last tick's result.

        ``stop`` ends the run after a tick for which it returns True; ``stop_on_fault`` ends it
        after the first tick that reports a fault (torque is already off in that tick). The
        cyclic garbage collector is paused during the run (its pauses are the main source of tick
        jitter in CPython); reference counting still frees everything a tick allocates.
        """
        if not self._started:
            self.start()
        was_enabled = gc.isenabled()
        if disable_gc:
            gc.disable()
        result = None
        tick = self.tick
        try:
            if on_tick is None and stop is None:  # the lock-step fast path: nothing but ticks
                for _ in range(ticks):
                    result = tick()
                    if stop_on_fault and result.faults:
                        break
            else:
                for _ in range(ticks):
                    result = tick()
                    if on_tick is not None:
                        on_tick(result)
                    if (stop is not None and stop(result)) or (stop_on_fault and result.faults):
                        break
        finally:
            if disable_gc and was_enabled:
                gc.enable()
        return result

    def _report(self, faults: list[Fault], kind: FaultKind, message: str) -> None:
        fault = self.monitor.report(kind, self._last_t_s, message)
        if fault is not None:
            faults.append(fault)

    def _fill_row(self, sample: Sample | None, command: Command, timing: TickTiming) -> np.ndarray:
        row = self._row
        faulted = 1.0 if self.monitor.faulted else 0.0
        enable = 1.0 if command.enable else 0.0
        if sample is None:  # no reading this tick: NaN, which recording_to_raw_log(drop_nan_rows=True) skips
            row[:17] = np.nan
            row[0] = self._last_t_s
            row[17:21] = command.motor_torque_nm
            row[21:24] = (enable, faulted, timing.lateness_s)
        else:
            _fill_tick_row(
                row, sample.t_s, sample.q_rad, sample.dq_rad_s, sample.tau_nm, sample.theta_rad,
                command.motor_torque_nm, enable, faulted, timing.lateness_s,
            )  # fmt: skip
        return row


@njit(cache=True)
def _fill_tick_row(row, t, q, dq, tau, theta, torque, enable, faulted, lateness):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The whole row of :data:`RECORD_COLUMNS` in one compiled call (it runs every tick)."""
    row[0] = t
    for j in range(4):
        row[1 + j] = q[j]
        row[5 + j] = dq[j]
        row[9 + j] = tau[j]
        row[13 + j] = theta[j]
        row[17 + j] = torque[j]
    row[21] = enable
    row[22] = faulted
    row[23] = lateness
