"""The SEA torque reading's hysteresis, tracked in the tick (issue 16): what the sensors read beyond the springs' torque.

The torque reading of each joint carries an error that depends on the joint's path: a play
operator (a Jenkins element) over the joint's travel, ``error_j = d_j s_j`` with

    s_j <- clip(s_j + dq_j / r_j, -1, 1)

(``d_j`` the amplitude in Nm, ``r_j`` the travel constant in rad; the design-time side, which
fits them from a run's raw log, is :mod:`daror_runtime.residual.hysteresis`). The SEA torque loop
drives the *reading* to its reference, so without this term the springs carry the reference
minus ``d_j s_j`` and the pilot holds the difference. :class:`HysteresisTracker` carries the
state from one sample to the next in O(1), without allocating, and gives the error to add to
the reference (:class:`daror_runtime.control.modes.Compensation`).

The measured angle is low-passed first (:data:`PATH_FILTER_HZ`, first order): the friction acts
on the true angle, and the encoders' noise would otherwise walk a held joint's state. The offline
analysis low-passes the raw log at the same cut-off without lag (it can look ahead:
:func:`daror_runtime.residual.hysteresis.estimate_path`); the tick's causal filter turns ~8 ms
late, while a joint moves less than its travel constant (measured in closed loop: the tracked
state within 0.005 of the plant's, docs/residual.md).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from daror_runtime.errors import ShapeError, UsageError
from hal.robot import FloatArray

__all__ = ["PATH_FILTER_HZ", "HysteresisTracker", "checked_travel", "path_filter_gain"]

#: The measured path is low-passed at this frequency before the operator (here first order and
#: causal; offline zero-phase). Measured on dataset B: 20 Hz recovers the plant's travel constants
#: to 1 % and its amplitudes to 0.5 % (5 Hz smears real moves; 80 Hz lets the noise in).
PATH_FILTER_HZ = 20.0


def path_filter_gain(dt_s: float, cutoff_hz: float = PATH_FILTER_HZ) -> float:
    """The first-order low-pass's gain per sample of ``dt_s`` (s) at ``cutoff_hz`` (Hz), in [0, 1]."""
    if not math.isfinite(dt_s) or dt_s <= 0.0:
        return 0.0  # no time passed (or none that can be counted): the filter does not move
    return 1.0 - math.exp(-2.0 * math.pi * cutoff_hz * dt_s)


#: The angles: any layout, read-only accepted (a sample's arrays may be frozen); writable ones match too.
_ANGLES = numba.types.Array(numba.float64, 1, "A", readonly=True)
_OWN = numba.float64[::1]
_FROZEN = numba.types.Array(numba.float64, 1, "C", readonly=True)  # the amplitudes, never written


@numba.njit(numba.int64(_ANGLES, numba.float64, _OWN, _FROZEN, _OWN, _OWN, _OWN), cache=True, nogil=True)
def _track(
    q_rad: np.ndarray,
    gain: float,
    inverse_travel: np.ndarray,
    amplitude_nm: np.ndarray,
    filtered: np.ndarray,
    state: np.ndarray,
    error_nm: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """One tick of every joint: filter the angle, move the state, write the error; a non-finite angle moves nothing.

    Returns 0, or -1 (nothing done) when ``q_rad`` is not one angle per joint.
    """
    n = state.shape[0]
    if q_rad.shape[0] != n:
        return -1
    for j in range(n):
        if not math.isfinite(q_rad[j]):
            for k in range(n):
                error_nm[k] = amplitude_nm[k] * state[k]
            return 0
    for j in range(n):
        step = gain * (q_rad[j] - filtered[j])
        filtered[j] += step
        s = state[j] + step * inverse_travel[j]
        state[j] = 1.0 if s > 1.0 else (-1.0 if s < -1.0 else s)
        error_nm[j] = amplitude_nm[j] * state[j]
    return 0


#: The shortest travel constant a play operator takes, rad: the DAROR-01 encoders' resolution
#: (hal/daror01.yaml). A shorter one turns the state over within a count of the encoder: a relay, the
#: hysteresis's full step at every reversal (hazard H20). The analysis fits travels from 2e-4 rad up
#: (:data:`daror_runtime.residual.travel.TRAVEL_GRID_RAD`).
MIN_TRAVEL_RAD = 1e-4


def checked_travel(travel_rad: FloatArray | float, joints: int) -> FloatArray:
    """Travel constants (rad) broadcast to ``joints``.

    Raises:
        UsageError: one that is not finite or is shorter than :data:`MIN_TRAVEL_RAD`.
    """
    travel = np.broadcast_to(np.asarray(travel_rad, dtype=float), (joints,)).copy()
    if not np.all(np.isfinite(travel)) or np.any(travel < MIN_TRAVEL_RAD):
        raise UsageError(
            f"a hysteresis travel constant must be finite and at least {MIN_TRAVEL_RAD:g} rad (the encoders' "
            f"resolution; a shorter one is a relay: a torque step at every reversal), got {travel.tolist()}"
        )
    return travel


class HysteresisTracker:
    """The play operator's state carried from tick to tick, and the reading's error it gives (Nm).

    Args:
        travel_rad: travel constant per joint, rad (positive).
        amplitude_nm: the error's amplitude per joint, Nm (0 where a joint has none).

    The state starts at 0 (unknown: half way) at :meth:`reset`; any move longer than twice a
    joint's travel saturates it, and from then on it is exact whatever it started at.

    Raises:
        UsageError: a travel constant that is not positive and finite, or an amplitude that is not finite.
    """

    def __init__(self, travel_rad: FloatArray, amplitude_nm: FloatArray) -> None:
        amplitude = np.array(amplitude_nm, dtype=float)
        if amplitude.ndim != 1 or not np.all(np.isfinite(amplitude)):
            raise UsageError(f"a hysteresis amplitude must be finite (Nm, one per joint), got {amplitude.tolist()}")
        self._inverse_travel = 1.0 / checked_travel(travel_rad, amplitude.shape[0])
        amplitude.flags.writeable = False
        self.amplitude_nm = amplitude
        joints = amplitude.shape[0]
        self.state = np.zeros(joints)
        self._filtered = np.zeros(joints)
        self._error = np.zeros(joints)
        self._started = False
        self._dt_s = math.nan
        self._gain = 0.0

    def reset(self, q_rad: FloatArray, state: FloatArray | None = None) -> None:
        """Start from the pose ``q_rad`` (rad) with ``state`` (None: 0, unknown)."""
        self._filtered[:] = q_rad
        self.state[:] = 0.0 if state is None else np.clip(np.asarray(state, dtype=float), -1.0, 1.0)
        self._started = True

    def update(self, q_rad: FloatArray, dt_s: float) -> FloatArray:
        """Move the state with the (filtered) travel since the last call; the reading's error now (Nm, per joint).

        ``dt_s``: time since the last call (s). A sample that is not finite moves nothing (the
        torque loop refuses it). One compiled call, nothing allocated. The returned array is the
        tracker's own: valid until the next call.

        Raises:
            ShapeError: ``q_rad`` is not one angle per joint.
        """
        if not self._started:
            self.reset(q_rad)
        if dt_s != self._dt_s:  # the gain's exp once per period, not per tick
            self._dt_s = dt_s
            self._gain = path_filter_gain(dt_s)
        try:
            status = _track(
                q_rad, self._gain, self._inverse_travel, self.amplitude_nm, self._filtered, self.state, self._error
            )
        except TypeError:  # not a float64 vector: convert (or refuse), then the same kernel
            q = np.asarray(q_rad, dtype=float)
            status = (
                -1
                if q.ndim != 1
                else _track(
                    q, self._gain, self._inverse_travel, self.amplitude_nm, self._filtered, self.state, self._error
                )
            )
        if status:
            raise ShapeError(f"the hysteresis tracker takes {self.state.shape[0]} angles, got shape {np.shape(q_rad)}")
        return self._error
