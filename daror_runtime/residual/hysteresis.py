"""The SEA torque reading's hysteresis: a play operator over each joint's travel (issue 16).

The torque a series elastic actuator reads carries a direction-dependent error (Sec. 2.2.2, worst
on joint 2): friction across the spring, or an encoder that shifts with the rotor. It does not
flip with the sign of the velocity: it builds up over the joint's travel after a reversal and
saturates. A Jenkins element (a spring in series with Coulomb friction) behaves exactly so, and its
force is the play operator::

    s_j <- clip(s_j + dq_j / r_j, -1, 1)        error_j = d_j s_j

with ``d_j`` the amplitude (Nm: the friction level) and ``r_j`` the travel constant (rad: the
travel after a reversal over which the error goes from -d_j to +d_j, the friction level over the
pre-sliding stiffness). As ``r_j -> 0`` it is the sign of the last motion, the
``direction_offset`` family: a direction offset is a hysteresis whose travel nobody can see.

The state depends on the path, not on the pose, so it is computed from the joint's history: the
raw log of a run (every tick's measured angle) when there is one, else the sequence of the
stationary points (moves between stops, without what happened during them): a
:class:`PointHistory` holds either for a dataset. In the tick, :class:`HysteresisTracker` carries the same state from one sample to
the next in O(1).

Everything here is a pure function of its arguments except :class:`HysteresisTracker`, whose
state is explicit.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.signal
from numba import njit

from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.errors import DataError, UsageError
from hal.robot import FloatArray

#: A point averages the readings of a hold: its state is the state averaged over this long around
#: the point's time (s; well inside the shortest window a point averages, 0.2 s of a 3-point stop).
#: Measured on dataset B: 0.0034 Nm with the state at the point's time, 0.0019 Nm averaged over
#: +-0.1 s, the same over +-0.3 s (the noise's walk of the state averages out).
POINT_WINDOW_S = 0.1

#: The measured path is low-passed (first order, causal) at this frequency before the operator:
#: the plant's friction acts on the true angle, and the encoders' noise (a few 1e-5 rad a tick)
#: would walk the state of a held joint. Measured on dataset B: 20 Hz recovers the plant's
#: travel constants to 2-4 % and its amplitudes to 0.5 % (5 Hz lags real moves, none lets noise in).
PATH_FILTER_HZ = 20.0


def path_filter_gain(dt_s: float, cutoff_hz: float = PATH_FILTER_HZ) -> float:
    """The first-order low-pass's gain per sample of ``dt_s`` (s) at ``cutoff_hz`` (Hz)."""
    return 1.0 - math.exp(-2.0 * math.pi * cutoff_hz * dt_s)


def smooth_path(q_rad: FloatArray, dt_s: float, cutoff_hz: float = PATH_FILTER_HZ) -> FloatArray:
    """The measured path low-passed as the tick's tracker does it (causal, first order, from the first sample)."""
    q = np.asarray(q_rad, dtype=float)
    a = path_filter_gain(dt_s, cutoff_hz)
    return np.ascontiguousarray(scipy.signal.lfilter([a], [1.0, a - 1.0], q - q[:1], axis=0) + q[:1])


@njit(cache=True)
def _play(q_rad: np.ndarray, inverse_travel: np.ndarray, initial: np.ndarray) -> np.ndarray:  # pragma: no cover
    samples, joints = q_rad.shape
    states = np.empty((samples, joints))
    for j in range(joints):
        state = initial[j]
        previous = q_rad[0, j]
        gain = inverse_travel[j]
        for k in range(samples):
            q = q_rad[k, j]
            state += (q - previous) * gain
            if state > 1.0:
                state = 1.0
            elif state < -1.0:
                state = -1.0
            states[k, j] = state
            previous = q
    return states


def _checked_travel(travel_rad: FloatArray | float, joints: int) -> FloatArray:
    travel = np.broadcast_to(np.asarray(travel_rad, dtype=float), (joints,)).copy()
    if not np.all(np.isfinite(travel)) or np.any(travel <= 0.0):
        raise UsageError(f"a hysteresis travel constant must be positive and finite (rad), got {travel.tolist()}")
    return travel


def play_states(q_rad: FloatArray, travel_rad: FloatArray | float, initial: FloatArray | float = 0.0) -> FloatArray:
    """The play operator's state (in [-1, 1]) after each sample of a path of joint angles.

    Args:
        q_rad: (samples, joints) joint angles in rad, in time order.
        travel_rad: travel constant per joint (or one for all), rad, positive.
        initial: the state before the first sample (0: unknown, half way).

    Raises:
        UsageError: a travel constant that is not positive and finite, or a path that is not 2-D.
    """
    q = np.ascontiguousarray(q_rad, dtype=float)
    if q.ndim != 2:
        raise UsageError(f"a path of joint angles is (samples, joints), got shape {q.shape}")
    joints = q.shape[1]
    travel = _checked_travel(travel_rad, joints)
    start = np.broadcast_to(np.asarray(initial, dtype=float), (joints,)).copy()
    if q.shape[0] == 0:
        return np.zeros((0, joints))
    return _play(q, 1.0 / travel, np.clip(start, -1.0, 1.0))


class HysteresisTracker:
    """The play operator's state carried from tick to tick (the controller's side of the closure).

    The measured angle is low-passed as the offline path is (:func:`smooth_path`), then moves the
    state: what the tick adds is the very error the analysis fitted.

    Args:
        travel_rad: travel constant per joint, rad (positive).
        amplitude_nm: the error's amplitude per joint, Nm.
        dt_s: the loop's period, s.

    Raises:
        UsageError: a travel constant that is not positive and finite, or an amplitude that is not finite.
    """

    def __init__(self, travel_rad: FloatArray, amplitude_nm: FloatArray, dt_s: float) -> None:
        amplitude = np.asarray(amplitude_nm, dtype=float)
        self._inverse_travel = 1.0 / _checked_travel(travel_rad, amplitude.shape[0])
        if not np.all(np.isfinite(amplitude)):
            raise UsageError(f"a hysteresis amplitude must be finite (Nm), got {amplitude.tolist()}")
        self.amplitude_nm = amplitude
        self._gain = path_filter_gain(dt_s)
        self.state = np.zeros(amplitude.shape[0])
        self._filtered: FloatArray | None = None

    def reset(self, q_rad: FloatArray, state: FloatArray | None = None) -> None:
        """Start from the pose ``q_rad`` with ``state`` (None: 0, unknown)."""
        self._filtered = np.array(q_rad, dtype=float)
        self.state = np.zeros_like(self.amplitude_nm) if state is None else np.clip(np.asarray(state, float), -1, 1)

    def update(self, q_rad: FloatArray) -> FloatArray:
        """Move the state with the (filtered) travel since the last call; the reading's error now (Nm, per joint)."""
        q = np.asarray(q_rad, dtype=float)
        previous = q.copy() if self._filtered is None else self._filtered
        filtered = previous + self._gain * (q - previous)
        state = self.state + (filtered - previous) * self._inverse_travel
        np.clip(state, -1.0, 1.0, out=state)
        self.state = state
        self._filtered = filtered
        return self.amplitude_nm * state


@dataclass(frozen=True)
class PointHistory:
    """The path the joints took up to each stationary point of a dataset: what the hysteresis state needs.

    ``path_q_rad`` is the raw log's every sample, low-passed (:func:`smooth_path`), or, without a
    raw log, the points themselves in their order; ``point_index`` the sample each point was taken
    at (the last at or before its ``t``).
    """

    path_q_rad: FloatArray  # (samples, joints), time order
    point_index: np.ndarray  # (points,) indices into path_q_rad
    from_raw_log: bool
    source: str = "<memory>"
    half_window: int = 0  # samples each side of a point its state is averaged over

    @classmethod
    def from_raw(cls, raw: RawLog, points: StationaryDataset) -> PointHistory:
        """The raw log of the run the points were reduced from.

        Raises:
            DataError: the points have no ``t``, or one lies outside the raw log (another run's log).
        """
        if points.t_s is None:
            raise DataError(f"{points.source}: no t column; expected the points' times to find them in {raw.source}")
        t_raw = np.asarray(raw.t_s, dtype=float)
        t_points = np.asarray(points.t_s, dtype=float)
        outside = (t_points < t_raw[0]) | (t_points > t_raw[-1])
        if np.any(outside):
            first = float(t_points[np.argmax(outside)])
            raise DataError(
                f"{raw.source}: the point at t = {first:.3f} s of {points.source} lies outside this raw log "
                f"({t_raw[0]:.3f}-{t_raw[-1]:.3f} s); expected the raw log of the same run"
            )
        index = np.searchsorted(t_raw, t_points, side="right") - 1
        dt_s = float(np.median(np.diff(t_raw)))
        return cls(smooth_path(raw.q_rad, dt_s), index, True, raw.source, round(POINT_WINDOW_S / dt_s))

    @classmethod
    def from_points(cls, points: StationaryDataset) -> PointHistory:
        """Without a raw log: the points in their order (moves between stops taken as straight)."""
        return cls(np.ascontiguousarray(points.q_rad, dtype=float), np.arange(len(points)), False, points.source)

    def states(self, travel_rad: FloatArray | float) -> FloatArray:
        """The hysteresis state (in [-1, 1]) of every joint at every point (averaged over the point's window)."""
        states = play_states(self.path_q_rad, travel_rad)
        if self.half_window == 0:
            return states[self.point_index]
        sums = np.vstack([np.zeros((1, states.shape[1])), np.cumsum(states, axis=0)])
        lo = np.clip(self.point_index - self.half_window, 0, len(states))
        hi = np.clip(self.point_index + self.half_window + 1, 0, len(states))
        return (sums[hi] - sums[lo]) / (hi - lo)[:, None]

    def subset(self, index: np.ndarray | slice) -> PointHistory:
        """The history of the points selected by ``index`` (the path is shared)."""
        return dataclasses.replace(self, point_index=self.point_index[index])


def find_raw_log(dataset_path: Path | str) -> Path | None:
    """The raw log written beside a dataset (``NAME.raw.npz``, ``.csv`` or ``.mat``), None when there is none."""
    path = Path(dataset_path)
    for suffix in (".npz", ".csv", ".mat"):
        candidate = path.with_name(f"{path.stem}.raw{suffix}")
        if candidate.is_file():
            return candidate
    return None
