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
:class:`PointHistory` holds either for a dataset. This module is the design-time side; in the
tick, :class:`daror_runtime.control.reading_error.HysteresisTracker` carries the same state from one
sample to the next in O(1), on the measured angles low-passed at the same cut-off (causally there,
without lag here: :func:`estimate_path`).

Everything here is a pure function of its arguments.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from daror_runtime.control.reading_error import PATH_FILTER_HZ, checked_travel
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.errors import DataError, UsageError
from hal.robot import FloatArray

#: A point averages the readings of a hold: its state is the state averaged over this long around
#: the point's time (s; well inside the shortest window a point averages, 0.2 s of a 3-point stop).
#: Measured on dataset B: 0.0034 Nm with the state at the point's time, 0.0019 Nm averaged over
#: +-0.1 s, the same over +-0.3 s (the noise's walk of the state averages out).
POINT_WINDOW_S = 0.1

_PAD_SAMPLES = 50  # the forward-backward filter's padding at each end (a log shorter than 4x is not filtered)


def estimate_path(q_rad: FloatArray, dt_s: float, cutoff_hz: float = PATH_FILTER_HZ) -> FloatArray:
    """The joints' true path estimated from a raw log's measured angles: low-passed without lag.

    A second-order Butterworth low-pass at ``cutoff_hz`` (Hz), run forward and backward
    (zero-phase): offline the analysis can look ahead, which the tick cannot (its tracker's
    filter is causal, :class:`~daror_runtime.control.reading_error.HysteresisTracker`). The state
    turns at the path's extremes, so the estimate must not lag or overshoot them: measured on
    dataset B, the validation error after the closure falls from 0.00189 Nm (the tick's causal
    filter) to 0.00155 Nm (no change on exo_wide_hysteresis, whose travel is 3x longer).
    A log too short or too slowly sampled for the filter is returned as measured.

    Args:
        q_rad: (samples, joints) measured joint angles in rad, in time order.
        dt_s: the log's sampling period (s).
    """
    q = np.ascontiguousarray(q_rad, dtype=float)
    if not (math.isfinite(dt_s) and dt_s > 0.0) or cutoff_hz >= 0.45 / dt_s or len(q) < 4 * _PAD_SAMPLES:
        return q
    import scipy.signal  # here: importing it costs 0.5 s, and a session that trains a model needs only the readers

    sos = scipy.signal.butter(2, cutoff_hz, fs=1.0 / dt_s, output="sos")
    return np.ascontiguousarray(scipy.signal.sosfiltfilt(sos, q, axis=0, padlen=_PAD_SAMPLES))


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


@njit(cache=True)
def _play_sums(q_rad: np.ndarray, inverse_travel: np.ndarray, initial: np.ndarray) -> np.ndarray:  # pragma: no cover
    """``sums[k]``: the sum of :func:`_play`'s states over samples ``0 .. k - 1`` (``sums[0] = 0``).

    One pass, without the states themselves: each state as :func:`_play` computes it, added in
    time order as ``numpy.cumsum`` adds them (the first copied, then one addition per sample), so
    the sums are the very numbers ``cumsum`` gives.
    """
    samples, joints = q_rad.shape
    sums = np.empty((samples + 1, joints))
    for j in range(joints):
        sums[0, j] = 0.0
        if samples == 0:
            continue
        state = initial[j]
        previous = q_rad[0, j]
        gain = inverse_travel[j]
        total = 0.0
        for k in range(samples):
            q = q_rad[k, j]
            state += (q - previous) * gain
            if state > 1.0:
                state = 1.0
            elif state < -1.0:
                state = -1.0
            total = state if k == 0 else total + state
            sums[k + 1, j] = total
            previous = q
    return sums


@njit(cache=True)
def _first_determined(q_rad: np.ndarray, inverse_travel: np.ndarray) -> np.ndarray:  # pragma: no cover
    """Per joint, the first sample whose state no longer depends on the state before the path (``samples``: none).

    The operator run from both extreme initial states at once, in :func:`_play`'s arithmetic: once
    one of them clips, the two meet exactly and move as one from then on.
    """
    samples, joints = q_rad.shape
    first = np.full(joints, samples)
    for j in range(joints):
        low = -1.0
        high = 1.0
        previous = q_rad[0, j] if samples > 0 else 0.0
        gain = inverse_travel[j]
        for k in range(samples):
            q = q_rad[k, j]
            low = min(max(low + (q - previous) * gain, -1.0), 1.0)
            high = min(max(high + (q - previous) * gain, -1.0), 1.0)
            previous = q
            if low == high:
                first[j] = k
                break
    return first


def _play_arguments(
    q_rad: FloatArray, travel_rad: FloatArray | float, initial: FloatArray | float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The path (contiguous), the inverse travel constants and the clipped initial state of :func:`play_states`.

    Raises:
        UsageError: see :func:`play_states`.
    """
    q = np.ascontiguousarray(q_rad, dtype=float)
    if q.ndim != 2:
        raise UsageError(f"a path of joint angles is (samples, joints), got shape {q.shape}")
    joints = q.shape[1]
    travel = checked_travel(travel_rad, joints)
    start = np.broadcast_to(np.asarray(initial, dtype=float), (joints,)).copy()
    return q, 1.0 / travel, np.clip(start, -1.0, 1.0)


def play_states(q_rad: FloatArray, travel_rad: FloatArray | float, initial: FloatArray | float = 0.0) -> FloatArray:
    """The play operator's state (in [-1, 1]) after each sample of a path of joint angles.

    Args:
        q_rad: (samples, joints) joint angles in rad, in time order.
        travel_rad: travel constant per joint (or one for all), rad, positive.
        initial: the state before the first sample (0: unknown, half way).

    Raises:
        UsageError: a travel constant that is not positive and finite, or a path that is not 2-D.
    """
    q, inverse_travel, start = _play_arguments(q_rad, travel_rad, initial)
    if q.shape[0] == 0:
        return np.zeros((0, q.shape[1]))
    return _play(q, inverse_travel, start)


@dataclass(frozen=True)
class PointHistory:
    """The path the joints took up to each stationary point of a dataset: what the hysteresis state needs.

    ``path_q_rad`` is the raw log's every sample, low-passed (:func:`estimate_path`), or, without a
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
        return cls(estimate_path(raw.q_rad, dt_s), index, True, raw.source, round(POINT_WINDOW_S / dt_s))

    @classmethod
    def from_points(cls, points: StationaryDataset) -> PointHistory:
        """Without a raw log: the points in their order (moves between stops taken as straight)."""
        return cls(np.ascontiguousarray(points.q_rad, dtype=float), np.arange(len(points)), False, points.source)

    def states(self, travel_rad: FloatArray | float) -> FloatArray:
        """The hysteresis state (in [-1, 1]) of every joint at every point (averaged over the point's window)."""
        if self.half_window == 0:
            return play_states(self.path_q_rad, travel_rad)[self.point_index]
        # The states' running sums straight from the path (one compiled pass, no array of states): the
        # fit of the travel constants asks for the states of a ~750,000-sample raw log some 60 times.
        sums = _play_sums(*_play_arguments(self.path_q_rad, travel_rad, 0.0))
        samples = sums.shape[0] - 1
        lo = np.clip(self.point_index - self.half_window, 0, samples)
        hi = np.clip(self.point_index + self.half_window + 1, 0, samples)
        return (sums[hi] - sums[lo]) / (hi - lo)[:, None]

    def undetermined(self, travel_rad: FloatArray | float) -> np.ndarray:
        """(points, joints) True where the point's state depends on the state before the path began.

        The path settles the state only once the joint has moved far enough one way after its
        start (a travel constant or two): a run that begins at rest at its first stop holds
        nothing that says which way the joint moved last, so no model can know the state there
        (:meth:`states` takes it as halfway, 0), and even one that lacks nothing errs by up to
        the hysteresis's amplitude at that point.

        Raises:
            UsageError: see :func:`play_states`.
        """
        q, inverse_travel, _ = _play_arguments(self.path_q_rad, travel_rad, 0.0)
        first = _first_determined(q, inverse_travel)
        window_start = np.clip(self.point_index - self.half_window, 0, None)
        return window_start[:, None] < first[None, :]

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
