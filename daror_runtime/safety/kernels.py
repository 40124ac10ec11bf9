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
    previous_q: np.ndarray,
    has_previous: bool,
    lower: np.ndarray,
    upper: np.ndarray,
) -> bool:
    """True when every checked signal of one sample lies inside ``[lower, upper]`` (20 values each).

    Signal order: q (4), dq (4), tau (4), theta - q (4), q - previous q (4, zero without a previous
    sample). A NaN fails every comparison, so it is never "in bounds".
    """
    for j in range(4):
        values = (q[j], dq[j], tau[j], theta[j] - q[j], q[j] - previous_q[j] if has_previous else 0.0)
        for g in range(5):
            i = 4 * g + j
            v = values[g]
            if not (lower[i] <= v <= upper[i]):
                return False
    return True


@_kernel
def clip_finite(torque: np.ndarray, limit: np.ndarray, out: np.ndarray) -> bool:
    """``out = clip(torque, -limit, limit)``; False (``out`` undefined) if any torque is not finite."""
    for j in range(torque.shape[0]):
        t = torque[j]
        if not math.isfinite(t):
            return False
        out[j] = min(max(t, -limit[j]), limit[j])
    return True
