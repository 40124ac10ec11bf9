"""The controller contract: small objects that turn a sample into a command, nothing else.

A controller does no I/O, owns no thread and never blocks (docs/architecture.md, docs/loop.md). The FSM decides
which controller runs; the controller obeys: it computes the motor torque of its mode and returns
a :class:`hal.interface.Command` with ``enable=True``. Limits per state and the e-stop are applied
after it by the safety filter, which may lower or remove any torque a controller asks for.

Per tick the loop calls :meth:`Controller.update` once. When the FSM switches to a controller it
calls :meth:`Controller.reset` first with the current sample, so filters and observers start
from the robot's present state instead of from zero (no torque jump on a mode change).

Errors: settings a person hands in (a support level, a gain) are refused with
:class:`ControlSettingError` (an :class:`~daror_runtime.errors.InputError`); anything that goes
wrong inside the tick (a non-finite reading or reference) raises :class:`ControlError`, which the
loop turns into a ``software`` fault met by its reaction in the same tick.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol, runtime_checkable

from numba import types

from daror_runtime.errors import DarorError, InputError
from hal.interface import Command, Sample
from hal.kernels import CompiledFunction
from hal.robot import FloatArray

__all__ = [
    "CONTROLLER_STEP",
    "CompiledControllerTick",
    "ControlDesignError",
    "ControlError",
    "ControlSettingError",
    "Controller",
]


class ControlError(DarorError):
    """The controller cannot produce a safe command this tick (e.g. a NaN in the sample).

    The controller's state is not advanced when this is raised; call ``reset`` before using it again.
    """


class ControlSettingError(InputError):
    """A controller setting (support level, gain, reference) was refused: out of range or not finite."""


class ControlDesignError(DarorError):
    """A controller or filter design is invalid (improper filter, unstable nominal loop, bad period)."""


@runtime_checkable
class Controller(Protocol):
    """What every control mode implements: a :class:`hal.interface.Command` (motor torques and enable) per tick.

    A controller never touches the hardware: the loop writes what it returns, after the safety
    filter. (It declares nothing else it commands: the HAL takes one kind of command, D187.)
    """

    def reset(self, sample: Sample) -> None:
        """Re-initialise internal state from ``sample``; called when the controller is selected.

        Raises:
            ControlError: the sample is not finite.
        """
        ...

    def update(self, sample: Sample, dt_s: float) -> Command:
        """The command for this tick; ``dt_s`` is the time since the previous tick in seconds.

        Raises:
            ControlError: a non-finite input or reference; the controller's state is unchanged.
        """
        ...


#: A controller's compiled tick for lock-step batches (``daror_runtime/loop_batch.py``):
#: ``step(t_s, readings, row, memory, knots, table, out) -> 0``. ``t_s`` is the sample's time (s),
#: the sample's readings are rows ``row .. row + 3`` of ``readings`` (:data:`hal.kernels.READING_ROWS`),
#: ``memory`` holds every number the controller keeps between ticks (its state, gains, its own
#: reference time), ``knots`` and ``table`` a tabulated reference (empty when it has none), and
#: the step writes the motor torque (4,) into ``out``. The same arithmetic as ``update`` on the
#: same state: a batch tick and a Python tick give the same floats.
CONTROLLER_STEP = types.intp(
    types.float64,
    types.float64[:, ::1],
    types.intp,
    types.float64[::1],
    types.float64[::1],
    types.float64[:, :, ::1],
    types.float64[::1],
)


class CompiledControllerTick(NamedTuple):
    """What a controller hands a lock-step batch: its compiled tick and the arrays it works on.

    ``memory`` is the controller's own state (the same memory ``update`` uses, so a batch and the
    Python ticks around it continue each other); the batch copies it before each tick and puts it
    back when the tick cannot finish in compiled code.
    """

    step: CompiledFunction  # of CONTROLLER_STEP
    memory: FloatArray
    knots: FloatArray
    table: FloatArray
