"""Lock-step ticks in compiled batches: the loop's tick, run many times in one compiled call.

In lock-step (virtual time, a simulating backend) nothing waits between ticks, so the cost of a
tick is its own work, and most of that work is the Python between the compiled kernels (about
6 us of 7.5, docs/performance.md). When every part of the tick offers its compiled form, the
loop runs a batch of ticks in :func:`run_ticks` instead; each batch tick is the loop's tick with
the same parts in the same order, on the same memory::

    readings of the tick (the backend's block)   # hal.read()
    signals_in_bounds(...)                       # monitor.check(): the common case, else stop
    controller step                              # controller.update()
    command_status(...)                          # monitor.filter(): the common case, else stop
    fill_tick_row_at(...)                        # recorder.push_into()
    backend step                                 # hal.write()

The parts: the backend's step (:class:`hal.capabilities.LockStepBatches`, handed over as a
compiled value, so the runtime imports no backend), the controller's step
(:class:`~daror_runtime.control.base.CompiledControllerTick`), the monitor's arrays
(:meth:`~daror_runtime.safety.monitor.SafetyMonitor.batch_arrays`) and the recorder's block
(:meth:`~daror_runtime.data.recorder.Recorder.batch_slot`). A tick that is not the common case (a
signal out of bounds, a torque to clip or not finite) is put back as it was before the tick
(the monitor's memory, the controller's memory) and the batch ends before it: the loop's Python
tick then runs it, names the fault and removes the torque as always. A backend step that fails
ends the batch after it, and the loop reports it as the Python tick reports a failed write.

What the loop gives up inside a batch: the per-tick work time (a batch's ticks share its mean),
and nothing else: ``tests/daror_runtime/test_loop_batch.py`` checks that a protocol run records the very same
rows, bit for bit, with and without batches, and that a fault mid-batch is found at the same tick.

A batch never runs on a real-time clock or on a backend that drives hardware: only a backend on
virtual time offers :attr:`hal.interface.Hal.lockstep_batches`, and the loop asks only when its
clock is virtual.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numba import njit, types

from daror_runtime.control.base import CONTROLLER_STEP
from daror_runtime.data.tick_row import fill_tick_row_at
from daror_runtime.safety.kernels import command_status, signals_in_bounds
from hal.kernels import BACKEND_STEP, entry_point

__all__ = [
    "MONITOR_MEMORY",
    "STOP_BACKEND",
    "STOP_BUDGET",
    "STOP_FILTER",
    "STOP_MONITOR",
    "run_ticks",
    "run_ticks_entry",
]

#: Why a batch ended (``result[0]``): it ran every tick it was given.
STOP_BUDGET = 0
#: The next tick's sample is not the monitor's common case (a signal out of bounds): not run.
STOP_MONITOR = 1
#: The next tick's torque is not the filter's common case (beyond the limit, or not finite): not run.
STOP_FILTER = 2
#: The last tick's backend step failed (``result[1]`` is its status): it ran, and failed.
STOP_BACKEND = 3

#: Values of the monitor's memory (``SafetyMonitor._previous``; see ``signals_in_bounds``).
MONITOR_MEMORY = 10


@njit(cache=True)
def run_ticks(
    ticks: int,
    seq0: int,
    period_s: float,
    backend_step: types.FunctionType,
    x: np.ndarray,
    p: np.ndarray,
    work: np.ndarray,
    s: np.ndarray,
    readings: np.ndarray,
    row: int,
    controller_step: types.FunctionType,
    memory: np.ndarray,
    knots: np.ndarray,
    table: np.ndarray,
    previous: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    command_limit: np.ndarray,
    block: np.ndarray,
    block_index: int,
    torque: np.ndarray,
    backup: np.ndarray,
    result: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Run up to ``ticks`` lock-step ticks; returns how many ran (``result``: why it ended, last status).

    Tick ``i`` reads the sample ``seq0 + i`` (time ``(seq0 + i) * period_s``, the product the
    backend stamps its samples with) from rows ``row + 4 i ..`` of ``readings``, and records into
    row ``block_index + i`` of ``block``. ``torque`` (4,) receives each tick's command; ``backup``
    holds the monitor's and the controller's memory while a tick runs (at least
    ``10 + memory.size`` values).
    """
    n_memory = memory.shape[0]
    result[0] = STOP_BUDGET
    for i in range(ticks):
        t_s = (seq0 + i) * period_s
        q = readings[row]
        dq = readings[row + 1]
        theta = readings[row + 2]
        tau = readings[row + 3]
        for k in range(MONITOR_MEMORY):
            backup[k] = previous[k]
        if not signals_in_bounds(q, dq, tau, theta, previous, lower, upper):
            for k in range(MONITOR_MEMORY):
                previous[k] = backup[k]
            result[0] = STOP_MONITOR
            return i
        for k in range(n_memory):
            backup[MONITOR_MEMORY + k] = memory[k]
        controller_step(t_s, readings, row, memory, knots, table, torque)
        if command_status(torque, command_limit) != 0:
            for k in range(n_memory):
                memory[k] = backup[MONITOR_MEMORY + k]
            for k in range(MONITOR_MEMORY):
                previous[k] = backup[k]
            result[0] = STOP_FILTER
            return i
        fill_tick_row_at(block, block_index + i, t_s, q, dq, tau, theta, torque, 1.0, 0.0, 0.0)
        status = backend_step(x, p, work, s, torque, True, readings, row + 4)
        result[1] = status
        if status < 0:
            result[0] = STOP_BACKEND
            return i + 1
        row += 4
    return ticks


_F8 = types.float64[::1]

#: What :func:`run_ticks` is resolved for (its entry point, :func:`run_ticks_entry`).
RUN_TICKS_SIGNATURE = types.intp(
    types.intp,
    types.intp,
    types.float64,
    types.FunctionType(BACKEND_STEP),
    _F8,
    _F8,
    _F8,
    _F8,
    types.float64[:, ::1],
    types.intp,
    types.FunctionType(CONTROLLER_STEP),
    _F8,
    _F8,
    types.float64[:, :, ::1],
    _F8,
    _F8,
    _F8,
    _F8,
    types.float64[:, ::1],
    types.intp,
    _F8,
    _F8,
    types.intp[::1],
)


def run_ticks_entry() -> Callable[..., int]:
    """:func:`run_ticks`'s compiled entry point (loaded from numba's cache, or compiled once; outside the tick)."""
    return entry_point(run_ticks, RUN_TICKS_SIGNATURE.args)
