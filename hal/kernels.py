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

__all__ = ["SAMPLE_VECTOR", "entry_point", "misfits"]

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
