"""Compiled fast paths of the safety monitor (numba): the common case of every tick.

Kept tiny and obvious on purpose: one bounds test over all checked signals and one finite-and-clip
of the command. Everything that names a fault (messages, joints, limits) is plain Python in
:mod:`daror_runtime.safety.monitor`, which only runs when these report a problem.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_kernel = njit(cache=True)


@_kernel
def signals_in_bounds(
    q: np.ndarray,
    dq: np.ndarray,
    tau: np.ndarray,
    theta: np.ndarray,
    previous: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
) -> bool:
    """True when every checked signal of one sample lies inside ``[lower, upper]`` (20 values each).

    Signal order: q (4), dq (4), tau (4), theta - q (4), q - previous q (4; zero before the first
    finite sample). A NaN fails every comparison, so it is never "in bounds".

    ``previous`` (10,) is the monitor's memory, updated in place: [0:4] the angles of the last
    finite sample and [4] a flag that they exist; [5:10] keep the values [0:5] had before this
    call, so a failed check can still name the jump it saw.
    """
    for i in range(5):
        previous[5 + i] = previous[i]
    has_previous = previous[4] > 0.0
    ok = True
    finite = True
    for j in range(4):
        jump = q[j] - previous[j] if has_previous else 0.0
        values = (q[j], dq[j], tau[j], theta[j] - q[j], jump)
        if not math.isfinite(q[j]):
            finite = False
        for g in range(5):
            i = 4 * g + j
            v = values[g]
            if not (lower[i] <= v <= upper[i]):
                ok = False
    if finite:
        for j in range(4):
            previous[j] = q[j]
        previous[4] = 1.0
    return ok


@_kernel
def command_status(torque: np.ndarray, limit: np.ndarray) -> int:
    """0: every torque finite and within ``+-limit``; 1: finite but some beyond; -1: not finite."""
    status = 0
    for j in range(torque.shape[0]):
        t = torque[j]
        if not math.isfinite(t):
            return -1
        if t > limit[j] or t < -limit[j]:
            status = 1
    return status
