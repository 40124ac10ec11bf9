"""Compiled kernels called through resolved entry points: the numba types of the tick's data.

numba's dispatcher works out the type of every argument at every call (~35 ns an array, 0.1-0.35 us
a call of the tick's kernels). A kernel's *entry point* for one signature, resolved once before the
loop runs (:func:`entry_point`), skips that work, and checks nothing but that each array argument
is an ndarray of 8-byte items: an array of another dimension overwrites memory, one of another
dtype is misread. An entry point is therefore called only with arguments whose types are
guaranteed, and falls back to the dispatcher otherwise:

* arrays the caller made itself with the types of the signature (its own state, gains, scratch);
* the four arrays of a :class:`hal.interface.CheckedSample` (float64, shape (4,), checked when the
  sample was made): :data:`SAMPLE_VECTOR`;
* anything else only after the caller checked it (``hal.sim.backend.SimHal.write`` checks the
  commanded torque, as it did before it reached the kernel).

Tests check that what the tick passes fits the signature it was resolved for (:func:`misfits`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numba
from numba import types
from numba.core.typing.templates import Signature
from numba.experimental.function_type import _get_wrapper_address
from numba.types import WrapperAddressProtocol

__all__ = [
    "BACKEND_STEP",
    "READING_ROWS",
    "SAMPLE_VECTOR",
    "CompiledFunction",
    "entry_point",
    "misfits",
]

#: How a kernel takes a float64 vector it only reads (a sample's array, a commanded torque):
#: read-only and of any strides, so every float64 vector fits, writable or not, a view or not
#: (numba refuses to compile a kernel that would write into an argument of this type).
SAMPLE_VECTOR = types.Array(types.float64, 1, "A", readonly=True)


def entry_point(kernel: Any, signature: Sequence[types.Type]) -> Callable[..., Any]:
    """``kernel``'s compiled entry point for ``signature`` (numba types, one per argument).

    Loaded from numba's on-disk cache when it is there, compiled once otherwise (a kernel with
    ``cache=True`` stores it for the next process). Call it outside the tick: loading takes
    milliseconds, compiling seconds.
    """
    return kernel.compile(tuple(signature))


def misfits(signature: Sequence[types.Type], args: Sequence[object]) -> list[str]:
    """Which of ``args`` an entry point for ``signature`` must not be given (empty: all fit); for tests.

    An array fits an array type of the same dtype and dimension whose layout is ``A`` or its own,
    and which is read-only or the array writable; anything else fits its exact numba type.
    """
    if len(args) != len(signature):
        return [f"{len(args)} arguments for a signature of {len(signature)}"]
    wrong = []
    for n, (expected, value) in enumerate(zip(signature, args, strict=True)):
        actual = numba.typeof(value)
        if isinstance(expected, types.Array):
            fits = (
                isinstance(actual, types.Array)
                and actual.dtype == expected.dtype
                and actual.ndim == expected.ndim
                and expected.layout in ("A", actual.layout)
                and (not expected.mutable or actual.mutable)
            )
        else:
            fits = actual == expected
        if not fits:
            wrong.append(f"argument {n}: {actual} does not fit {expected}")
    return wrong


class CompiledFunction(WrapperAddressProtocol):
    """A compiled kernel handed to other compiled code as a value (a numba first-class function).

    A component offers its tick as one of these so that a compiled caller can run it without
    importing the component's module (a backend's tick, for instance, is called by the runtime's
    lock-step batches, and the runtime never imports a backend: ``docs/architecture.md``). The
    kernel's address for ``signature`` is resolved once here (loaded from numba's cache when it is
    there, compiled otherwise), outside any tick; passing the value to a compiled function costs
    about 3 us a call, calling it from compiled code a few ns.

    Args:
        kernel: an ``njit`` dispatcher.
        signature: the numba signature the caller's :class:`numba.types.FunctionType` declares
            (``return_type(arg types...)``); the kernel is compiled for exactly these argument types.
    """

    def __init__(self, kernel: Any, signature: Signature) -> None:
        self.kernel = kernel  # keeps the compiled code (and so the address) alive
        self._signature = signature
        kernel.compile(signature.args)
        self._address = int(_get_wrapper_address(kernel, signature))

    def __wrapper_address__(self) -> int:
        return self._address

    def signature(self) -> Signature:
        return self._signature

    @property
    def function_type(self) -> types.FunctionType:
        """The numba type a compiled caller declares for this value."""
        return types.FunctionType(self._signature)


#: A backend's compiled tick for lock-step batches (:class:`hal.capabilities.LockStepBatches`):
#: ``step(x, p, work, s, torque, enable, readings, row) -> status``. The first four arrays are the
#: backend's own state (what they hold is its business), ``torque`` the commanded motor torque
#: (4,), ``enable`` the command's flag; the step writes the readings of the new tick into rows
#: ``row .. row + 3`` of ``readings`` (in the order of :data:`READING_ROWS`) and returns 0 (drives
#: enabled), 1 (disabled) or a negative status (the tick failed: the backend says why when the
#: batch ends).
BACKEND_STEP = types.intp(
    types.float64[::1],
    types.float64[::1],
    types.float64[::1],
    types.float64[::1],
    types.float64[::1],
    types.boolean,
    types.float64[:, ::1],
    types.intp,
)

#: What the four rows of one tick's readings hold, in order (each (4,), joints 1-4): the link
#: angles (rad), the link velocities (rad/s), the motor angles (rad), the spring torques (Nm).
READING_ROWS = ("q_rad", "dq_rad_s", "theta_rad", "tau_nm")
