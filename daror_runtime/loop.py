"""The fixed-rate control loop: one tick is read, check, decide, update, filter, write, record.

docs/loop.md::

    sample = hal.read()                      # q, dq, motor angles, spring torque, e-stop, drives
    faults = safety.check(sample)            # limits, plausibility, staleness, e-stop, drives
    controller = supervisor.on_tick(...)     # the FSM applies requests and faults here (issue 4)
    command = controller.update(sample, dt)  # the controllers never touch hardware
    command = safety.filter(command)         # only the torque the fault's reaction permits
    recorder.push(sample, command); hal.write(command)

Rules kept here: nothing inside the tick blocks (the recorder hands blocks to a writer thread);
every fault is acted on in the tick it is found (the supervisor puts the reaction the spec
declares in force and runs its controller in the same tick; the filter runs after the faults of
this tick are latched; a HAL or software error is itself a fault); errors are never swallowed:
an exception from the controller or the recorder is reported as a ``software`` fault with its
message, logged, and the loop goes on under that fault's reaction.

The overrun watchdog counts missed deadlines, not late wake-ups: ``overrun_limit`` deadlines
missed in a row, or one stall that missed more than ``max_stall_periods`` deadlines at once, is an
``overrun`` fault in the tick that finds it (the first tick after the stall), met by its reaction.
The clock decides what a late tick is: the real-time clock reports it as an overrun (the drives
held the last command through it) and the watchdog judges it; a paced clock (virtual time paced
to the wall clock, a simulated backend only) never does, since the simulated world stalled with
the process: it counts the stall itself (``Clock.pacing``), and the tick's lateness is recorded.
"""

from __future__ import annotations

import gc
import time
from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np
import structlog
from numba import types

from daror_runtime.clocks import Clock, TickTiming
from daror_runtime.data.recorder import Recorder
from daror_runtime.data.tick_row import N_RECORD_COLUMNS, fill_tick_row_at
from daror_runtime.errors import ConfigurationError, DarorError
from daror_runtime.loop_batch import MONITOR_MEMORY as _MONITOR_MEMORY
from daror_runtime.loop_batch import STOP_BUDGET, STOP_MONITOR, run_ticks_entry
from daror_runtime.safety.faults import Fault, FaultKind
from daror_runtime.safety.monitor import SafetyMonitor
from hal.errors import HalError
from hal.interface import TORQUE_OFF, CheckedCommand, CheckedSample, Command, Hal, HalBusFaultError, Sample
from hal.kernels import SAMPLE_VECTOR, entry_point

log = structlog.get_logger(__name__)

_perf_counter = time.perf_counter
_new_tuple = tuple.__new__
_fill_tick_row_at = fill_tick_row_at

#: What :func:`~daror_runtime.data.tick_row.fill_tick_row_at` is resolved for: a recorder's block
#: (float64, C order: ``Recorder`` makes it so) and the row's index, the time, the sample's four
#: arrays and the commanded torque (float64 vectors: :data:`hal.kernels.SAMPLE_VECTOR`), and
#: enable, faulted and lateness.
FILL_SIGNATURE = (
    types.float64[:, ::1],
    types.intp,
    types.float64,
    *(SAMPLE_VECTOR,) * 5,
    types.float64,
    types.float64,
    types.float64,
)

#: Deadlines missed in a row that make a fault (a 1 kHz loop that misses 5 ms in a row is not in control).
DEFAULT_OVERRUN_LIMIT = 5

#: Deadlines one stall may miss before it is a fault by itself. While the loop stalls, the drives
#: hold the last torque command: the SEA torque loop runs open. The worst case is a command at a
#: state's 30 Nm limit with the spring unloaded: it accelerates the motor side (0.25 kg m^2 at the
#: gearbox output) at 120 rad/s^2, so after N ms the motor moved 0.06 N^2 mrad and gained
#: 0.12 N rad/s. A stall that missed 3 deadlines started the next tick under 3 ms late, so the last
#: command stood under 4 ms: at most 1 mrad (0.28 Nm on the 289 Nm/rad spring) and 0.48 rad/s (a
#: quarter of the device's 2 rad/s). A 20 ms stall gives 24 mrad (7 Nm) and 2.4 rad/s, past the
#: device's velocity limit. 3 periods is also 4x the worst lateness measured with SCHED_FIFO
#: (0.75 ms, docs/performance.md), so a real-time run does not trip on jitter.
DEFAULT_MAX_STALL_PERIODS = 3


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

    # Optional: ``batch_controller() -> TickController | None``, the controller every coming tick
    # runs whatever happens (no request pending, nothing decided per tick), which lets a lock-step
    # loop run ticks in compiled batches (daror_runtime/loop_batch.py). A supervisor without it
    # (the FSM's: it applies requests at every tick boundary) always gets Python ticks.


class FixedSupervisor:
    """One controller until told otherwise; changes take effect at the next tick boundary."""

    def __init__(self, controller: TickController | None = None) -> None:
        self._controller = controller
        self._pending: list[TickController | None] = []

    def use(self, controller: TickController | None) -> None:
        self._pending.append(controller)

    def batch_controller(self) -> TickController | None:
        """The controller every coming tick runs, when no change is pending (lock-step batches may run it)."""
        return None if self._pending else self._controller

    def on_tick(self, sample: Sample | None, faults: list[Fault], monitor: SafetyMonitor) -> TickController | None:
        while self._pending:
            self._controller = self._pending.pop(0)
        return self._controller

    def on_late_faults(self, sample: Sample | None, faults: list[Fault]) -> None:
        """Nothing to decide: the filter already removed torque."""


class Recording(Protocol):
    """What the loop needs of a recorder (``daror_runtime.data.recorder.Recorder``).

    ``push(row)`` takes the loop's row; a recorder that also offers ``push_into(fill, n_values,
    *args)`` (as ``Recorder`` does) gets the row written straight into its own memory instead.
    """

    def push(self, row: np.ndarray) -> bool: ...


class _Batches:
    """What a lock-step loop keeps for its compiled batches (:mod:`daror_runtime.loop_batch`)."""

    def __init__(self) -> None:
        self.run_ticks = run_ticks_entry()
        self.torque = np.zeros(4)
        self.backup = np.zeros(64)
        self.outcome = np.zeros(2, dtype=np.intp)
        # Rows a batch fills when the loop has no recorder (nobody reads them).
        self.scratch_rows = np.zeros((256, N_RECORD_COLUMNS))


class TickResult(NamedTuple):
    timing: TickTiming
    sample: Sample | None
    command: Command  # as written to the hardware
    faults: list[Fault]  # new in this tick


class LoopStats(NamedTuple):
    """Totals of a loop since it started (a read-only snapshot for a status view).

    Attributes:
        ticks: ticks run.
        overruns: ticks that started after the deadline they were due at (the clock's count).
        missed_deadlines: deadlines missed in all, skipped ones included (the clock's count).
        worst_lateness_s: the latest start of a tick after its deadline, in s (0 in lock-step).
        worst_work_s: the longest a tick's own work took (everything after the clock's wait), in s.
        mean_work_s: the mean of a tick's own work, in s (0 before the first tick).
    """

    ticks: int
    overruns: int
    missed_deadlines: int
    worst_lateness_s: float
    worst_work_s: float
    mean_work_s: float


class ControlLoop:
    """Runs ticks at the clock's rate over one HAL.

    Args:
        hal: an opened backend.
        monitor: the safety monitor (owns the latched faults).
        supervisor: decides the controller per tick.
        clock: real-time or lock-step.
        recorder: receives one row of :data:`~daror_runtime.data.tick_row.RECORD_COLUMNS` per tick
            (optional).
        overrun_limit: deadlines missed in a row that make an ``overrun`` fault (at least 1).
        max_stall_periods: deadlines one stall may miss; a stall that missed more is an
            ``overrun`` fault by itself (at least 0; see :data:`DEFAULT_MAX_STALL_PERIODS`).
        compiled_batches: on virtual time, let :meth:`run` run ticks in compiled batches where
            every part offers its compiled form (:mod:`daror_runtime.loop_batch`); False: every
            tick through :meth:`tick` (the reference the batches are tested against).

    Raises:
        ConfigurationError: ``overrun_limit`` below 1 or ``max_stall_periods`` below 0.
    """

    def __init__(
        self,
        hal: Hal,
        monitor: SafetyMonitor,
        supervisor: Supervisor,
        clock: Clock,
        recorder: Recording | None = None,
        overrun_limit: int = DEFAULT_OVERRUN_LIMIT,
        max_stall_periods: int = DEFAULT_MAX_STALL_PERIODS,
        compiled_batches: bool = True,
    ) -> None:
        if overrun_limit < 1:
            raise ConfigurationError(f"overrun_limit must be at least 1 missed deadline, got {overrun_limit}")
        if max_stall_periods < 0:
            raise ConfigurationError(f"max_stall_periods must be at least 0, got {max_stall_periods}")
        self.hal = hal
        self.monitor = monitor
        self.supervisor = supervisor
        self.clock = clock
        self.recorder = recorder
        self.overrun_limit = overrun_limit
        self.max_stall_periods = max_stall_periods
        self.dt_s = clock.period_s
        self._rows = np.zeros((1, N_RECORD_COLUMNS))  # the row a recorder without push_into gets
        # The sample's part of the row in a tick without a reading; read-only like a HAL's arrays, so
        # the row kernel runs the variant the warm-up below loaded.
        self._no_reading = np.full(4, np.nan)
        self._no_reading.flags.writeable = False
        self._last_t_s = 0.0
        self._started = False
        self.dropped_rows = 0
        self.last_command: Command = TORQUE_OFF  # as written to the hardware in the last tick
        # Load the row kernel now, not in the tick a recording starts in (5 ms the first time), for
        # both kinds of sample and command array (numba compiles per type: a HAL's read-only arrays
        # and plain ones; the shared torque-off command is read-only, a controller's is not).
        for readonly in (True, False):
            zeros = np.zeros(4)
            zeros.flags.writeable = not readonly
            for command_torque in (np.zeros(4), TORQUE_OFF.motor_torque_nm):
                fill_tick_row_at(self._rows, 0, 0.0, zeros, zeros, zeros, zeros, command_torque, 0.0, 0.0, 0.0)
        self._fill_checked = entry_point(fill_tick_row_at, FILL_SIGNATURE)
        # Compiled batches of lock-step ticks (loop_batch.py): only on virtual time, made at the first batch.
        self._batch_capable = compiled_batches and clock.virtual and hal.virtual_time
        self._batches: _Batches | None = None
        #: Ticks run inside compiled batches since the loop was made (the rest went through :meth:`tick`).
        self.batched_ticks = 0
        self._ticks = 0
        self._work_total_s = 0.0
        self._work_worst_s = 0.0

    @property
    def stats(self) -> LoopStats:
        """Totals since :meth:`start`: ticks, the clock's overruns and lateness, the tick's own work."""
        clock = self.clock.stats
        ticks = self._ticks
        return LoopStats(
            ticks,
            clock.overruns,
            clock.missed_deadlines,
            clock.worst_lateness_s,
            self._work_worst_s,
            self._work_total_s / ticks if ticks else 0.0,
        )

    def start(self) -> None:
        """Start the clock (and the totals of :attr:`stats`); the HAL must be open."""
        self.monitor.reset_history()
        self.clock.start()
        self._ticks = 0
        self._work_total_s = 0.0
        self._work_worst_s = 0.0
        self._started = True

    def tick(self) -> TickResult:
        """One tick. Never raises for hardware, controller or recorder errors: they become faults."""
        timing = self.clock.wait()
        began = _perf_counter()
        monitor = self.monitor
        monitor.begin_tick()
        hal = self.hal
        try:
            sample: Sample | None = hal.read()
        except HalError as exc:
            sample = None
            faults: list[Fault] = []
            # the bus itself failed (bus-off, error-passive): its own reaction, not a failed read's
            kind = FaultKind.BUS if isinstance(exc, HalBusFaultError) else FaultKind.HAL
            self._report(faults, kind, f"reading the hardware failed: {exc}")
        else:
            self._last_t_s = sample.t_s
            faults = monitor.check(sample)
        if timing.overrun:  # a deadline the drives depended on passed (real time; a paced clock reports none)
            self._watchdog(faults, timing)
        supervisor = self.supervisor
        controller = supervisor.on_tick(sample, faults, monitor)
        decided = len(faults)  # the supervisor saw these; later ones are passed to it at the end of the tick
        command = self._command(controller, sample, faults)
        if len(faults) > decided:
            # Found while computing the command (the controller failed, or asked for a non-finite torque):
            # the supervisor decides the reaction now, and a reaction that holds the arm runs in this tick.
            supervisor.on_late_faults(sample, faults[decided:])
            decided = len(faults)
            reaction = getattr(supervisor, "controller", None)
            if reaction is not None and reaction is not controller:
                command = self._command(reaction, sample, faults)
        recorder = self.recorder
        if recorder is not None:
            try:
                if type(recorder) is Recorder and type(sample) is CheckedSample and type(command) is CheckedCommand:
                    # The common case, inline: every array of the type the fill's entry point takes.
                    recorded = recorder.push_into(
                        self._fill_checked, N_RECORD_COLUMNS, sample.t_s, sample.q_rad, sample.dq_rad_s,
                        sample.tau_nm, sample.theta_rad, command.motor_torque_nm, 1.0 if command.enable else 0.0,
                        1.0 if monitor.faulted else 0.0, timing.lateness_s,
                    )  # fmt: skip
                else:
                    recorded = self._record(recorder, sample, command, timing)
                if not recorded:
                    self.dropped_rows += 1
                    if self.dropped_rows == 1:  # a dropped row is data loss, not danger: say so once, count all
                        log.warning("recorder dropped a row: the disk cannot keep up", t_s=self._last_t_s)
            except DarorError as exc:
                self._report(faults, FaultKind.SOFTWARE, f"recorder failed: {exc}")
                supervisor.on_late_faults(sample, faults[decided:])
                decided = len(faults)
                if not monitor.torque_permitted:  # the reaction to it is off: nothing is written with torque
                    command = TORQUE_OFF
        try:
            hal.write(command)
        except HalError as exc:
            self._report(faults, FaultKind.HAL, f"writing the hardware failed: {exc}")
        if len(faults) > decided:
            supervisor.on_late_faults(sample, faults[decided:])
        self.last_command = command
        work = _perf_counter() - began
        self._ticks += 1
        self._work_total_s += work
        if work > self._work_worst_s:
            self._work_worst_s = work
        # TickResult(timing, sample, command, faults), every field in order, without the NamedTuple's
        # Python-level __new__ (this runs every tick).
        return _new_tuple(TickResult, (timing, sample, command, faults))

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
            if on_tick is None and stop is None and self._batch_capable:
                result = self._run_batched(ticks, stop_on_fault)
            elif on_tick is None and stop is None:  # nothing but ticks
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

    def _run_batched(self, ticks: int, stop_on_fault: bool) -> TickResult | None:
        """:meth:`run`'s ticks in lock-step: compiled batches where every part allows, Python ticks elsewhere.

        The last tick is always a Python tick (its result is what :meth:`run` returns); so is the
        tick after a batch that stopped because the next tick is not the common case.
        """
        result = None
        remaining = ticks
        tick = self.tick
        while remaining > 0:
            if remaining > 1:
                ran, reason, failed = self._batch(remaining - 1)
                remaining -= ran
                if failed is not None:
                    result = failed
                    if stop_on_fault:
                        break
                    continue
                if ran > 0 and reason == STOP_BUDGET:
                    continue  # the backend's budget ran out (a block of noise or readings): next batch
            result = tick()
            remaining -= 1
            if stop_on_fault and result.faults:
                break
        return result

    def _batch(self, limit: int) -> tuple[int, int, TickResult | None]:
        """One compiled batch of at most ``limit`` ticks: ``(ticks run, why it stopped, a failed tick's result)``.

        Runs nothing (0 ticks) unless every part offers its compiled form now. See
        :mod:`daror_runtime.loop_batch`.
        """
        if self.monitor.faulted:
            return 0, STOP_MONITOR, None
        batch_controller = getattr(self.supervisor, "batch_controller", None)
        controller = batch_controller() if batch_controller is not None else None
        compiled_tick = getattr(controller, "compiled_tick", None)
        controller_tick = compiled_tick() if compiled_tick is not None else None
        backend = self.hal.lockstep_batches
        monitor_arrays = self.monitor.batch_arrays()
        recorder = self.recorder
        if controller_tick is None or backend is None or monitor_arrays is None:
            return 0, STOP_MONITOR, None
        batches = self._batches
        if batches is None:
            batches = self._batches = _Batches()
        if recorder is None:
            slot: tuple[np.ndarray, int, int] | None = (batches.scratch_rows, 0, batches.scratch_rows.shape[0])
        elif type(recorder) is Recorder:
            slot = recorder.batch_slot()
        else:  # another recorder takes rows through push only
            slot = None
        if slot is None:
            return 0, STOP_MONITOR, None
        begun = backend.begin()
        if begun is None:
            return 0, STOP_MONITOR, None
        block, index, free = slot
        n = min(limit, begun.ticks, free)
        memory = controller_tick.memory
        if batches.backup.shape[0] < _MONITOR_MEMORY + memory.shape[0]:
            batches.backup = np.zeros(_MONITOR_MEMORY + memory.shape[0])
        previous, lower, upper, command_limit = monitor_arrays
        x, p, work, s = begun.state
        torque = batches.torque
        outcome = batches.outcome
        began = _perf_counter()
        ran = batches.run_ticks(
            n, begun.seq, begun.period_s, begun.step, x, p, work, s, begun.readings, begun.row,
            controller_tick.step, memory, controller_tick.knots, controller_tick.table,
            previous, lower, upper, command_limit, block, index, torque, batches.backup, outcome,
        )  # fmt: skip
        work_s = _perf_counter() - began
        reason = int(outcome[0])
        if ran == 0:
            return 0, reason, None
        last_seq = begun.seq + ran - 1
        if recorder is not None:
            recorder.commit_batch(ran)
        self.clock.advance(ran)
        self.monitor.after_batch(last_seq)
        self._ticks += ran
        self.batched_ticks += ran
        self._work_total_s += work_s
        if work_s / ran > self._work_worst_s:
            self._work_worst_s = work_s / ran
        self._last_t_s = last_seq * begun.period_s
        command = _new_tuple(CheckedCommand, (torque.copy(), True, ()))
        self.last_command = command
        try:
            backend.end(ran, int(outcome[1]))
        except HalError as exc:
            # The batch's last tick failed in the backend's step: reported as the Python tick reports
            # a failed write (its row is recorded, with the monitor not yet faulted).
            faults: list[Fault] = []
            self._report(faults, FaultKind.HAL, f"writing the hardware failed: {exc}")
            try:
                sample: Sample | None = self.hal.read()
            except HalError:
                sample = None
            self.supervisor.on_late_faults(sample, faults)
            index = self.clock.ticks - 1
            timing = _new_tuple(TickTiming, (index, index * self.dt_s, 0.0, False, 0, 0))
            return ran, reason, _new_tuple(TickResult, (timing, sample, command, faults))
        return ran, reason, None

    def _command(self, controller: TickController | None, sample: Sample | None, faults: list[Fault]) -> Command:
        """What the tick writes: the controller's command through the safety filter (faults it finds go to ``faults``).

        Without a reading the last command written is handed to the filter, which keeps it only
        under a reaction that holds the arm, for a few ticks (the drives' own behaviour between
        frames); otherwise torque off.
        """
        monitor = self.monitor
        command = TORQUE_OFF
        if sample is None:
            command = self.last_command
        elif controller is not None and monitor.torque_permitted:
            try:
                command = controller.update(sample, self.dt_s)
            except DarorError as exc:
                self._report(faults, FaultKind.SOFTWARE, f"{type(controller).__name__} failed: {exc}")
            except Exception as exc:  # a bug in a controller must stop the robot, not the loop
                log.exception("controller raised", controller=type(controller).__name__)
                self._report(faults, FaultKind.SOFTWARE, f"{type(controller).__name__} raised {exc!r}")
        command = monitor.filter(command, sample)
        refused = monitor.filter_fault
        if refused is not None:  # a non-finite command, found by the filter: one of this tick's faults like any other
            monitor.filter_fault = None
            faults.append(refused)
        return command

    def _watchdog(self, faults: list[Fault], timing: TickTiming) -> None:
        """The overrun rules, for a tick that started late (a stall is named in ms and periods)."""
        missed = timing.missed_deadlines
        period_ms = self.dt_s * 1e3
        late_ms = timing.lateness_s * 1e3
        if missed > self.max_stall_periods:
            self._report(
                faults,
                FaultKind.OVERRUN,
                f"the loop stalled {late_ms:.1f} ms past a deadline: {missed} deadlines of {period_ms:g} ms missed "
                f"at once (more than {self.max_stall_periods} periods); the torque loop ran open that long",
            )
        elif timing.consecutive_overruns >= self.overrun_limit:
            self._report(
                faults,
                FaultKind.OVERRUN,
                f"{timing.consecutive_overruns} consecutive deadlines of {period_ms:g} ms missed "
                f"(limit {self.overrun_limit}); this tick started {late_ms:.1f} ms "
                f"({late_ms / period_ms:.1f} periods) late",
            )

    def _report(self, faults: list[Fault], kind: FaultKind, message: str) -> None:
        fault = self.monitor.report(kind, self._last_t_s, message)
        if fault is not None:
            faults.append(fault)

    def _record(self, recorder: Recording, sample: Sample | None, command: Command, timing: TickTiming) -> bool:
        """Record the tick's row (:data:`~daror_runtime.data.tick_row.RECORD_COLUMNS`); False if it was dropped.

        A :class:`~daror_runtime.data.recorder.Recorder` has the row filled straight into its block
        (``push_into``): by the fill's entry point when every array is of the type it was resolved
        for (a :class:`~hal.interface.CheckedSample`'s or the loop's NaN row, and a
        :class:`~hal.interface.CheckedCommand`'s torque), else through numba's dispatcher. Any
        other recorder gets the loop's own row through ``push``.
        """
        faulted = 1.0 if self.monitor.faulted else 0.0
        enable = 1.0 if command.enable else 0.0
        torque = command.motor_torque_nm
        if sample is None:  # no reading this tick: NaN, which recording_to_raw_log(drop_nan_rows=True) skips
            t_s = self._last_t_s
            q = dq = tau = theta = self._no_reading
        else:
            t_s, q, dq, tau, theta = sample.t_s, sample.q_rad, sample.dq_rad_s, sample.tau_nm, sample.theta_rad
        if type(recorder) is Recorder:
            fill = (
                self._fill_checked
                if type(command) is CheckedCommand and (type(sample) is CheckedSample or sample is None)
                else _fill_tick_row_at
            )
            return recorder.push_into(
                fill, N_RECORD_COLUMNS, t_s, q, dq, tau, theta, torque, enable, faulted, timing.lateness_s
            )
        rows = self._rows
        _fill_tick_row_at(rows, 0, t_s, q, dq, tau, theta, torque, enable, faulted, timing.lateness_s)
        return recorder.push(rows[0])
