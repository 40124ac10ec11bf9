"""Reduce a raw log to stationary points (thesis Sec. 4.3.2).

Only points where the robot stands still carry nothing but gravity and stiffness torque. The
logged joint velocity is noisy (it is differentiated from 1e-4 rad encoders), so it is low-pass
filtered first (zero-phase Butterworth, ``scipy.signal.sosfiltfilt``; order 2 computed to the bit
by :mod:`daror_runtime.data.lowpass` without importing scipy.signal) and a sample counts as
stationary when the norm of the filtered velocity is below a threshold.

Runs of stationary samples are then grouped into *stops* by position: the filter's ringing
around a short, fast move can break one dwell into several runs, and runs whose positions agree
within ``same_position_rad`` are the same stop. The first and last ``edge_trim_s`` of each stop
are dropped where they border a move (the slow ends of the moves on either side).

``dir``, the direction of each joint's last motion before a stop, comes from the move into the
stop (the samples since the previous stop): a joint that travelled more than
``same_position_rad`` gets the sign of its filtered velocity at the last point where that velocity
exceeded half its peak in the move (a move that reverses counts by its last lobe); a joint that did
not move keeps its previous ``dir`` (0 before it first moves).

The thesis used a 0.1 Hz cut-off and ``||dq|| < 0.0002 rad/s`` for its protocol of long stops;
the defaults here are set for this runtime's protocol and documented in ``docs/data.md``. All are
settings, so the thesis values can be reproduced.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from daror_runtime.data import lowpass
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.errors import DataError

StopReduction = Literal["all", "mean"]


@dataclass(frozen=True)
class ReductionSettings:
    """How a raw log becomes stationary points."""

    cutoff_hz: float = 2.0
    filter_order: int = 2
    threshold_rad_s: float = 0.01
    same_position_rad: float = 1e-3
    edge_trim_s: float = 0.1
    per_stop: StopReduction = "all"
    points_per_stop: int = 1  # with per_stop="mean": each stop split into this many averaged parts
    min_stop_samples: int = 1


def _stop_segments(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index ranges of consecutive True runs."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def filtered_velocity(raw: RawLog, settings: ReductionSettings) -> np.ndarray:
    """Zero-phase Butterworth low-pass of the logged joint velocity; (N, 4) rad/s.

    Raises:
        DataError: the sample rate cannot be determined or the cut-off is above Nyquist, or the
            log is too short for the filter.
    """
    dt = np.diff(raw.t_s)
    if dt.size == 0:
        raise DataError(f"{raw.source}: a raw log needs at least two samples to reduce to stationary points")
    rate_hz = 1.0 / float(np.median(dt))
    if not 0 < settings.cutoff_hz < rate_hz / 2:
        raise DataError(
            f"{raw.source}: low-pass cut-off {settings.cutoff_hz} Hz must be below half the sample rate ({rate_hz:.4g} Hz)"
        )
    # Order 2 (the default) by lowpass: scipy.signal's butter and sosfiltfilt to the bit, without
    # importing scipy.signal (~0.5 s, ~50 MB); any other order by scipy.signal itself.
    if settings.filter_order == lowpass.ORDER:
        sos = lowpass.butter2_lowpass_sos(settings.cutoff_hz, rate_hz)
    else:
        import scipy.signal

        sos = scipy.signal.butter(settings.filter_order, settings.cutoff_hz, fs=rate_hz, output="sos")
    pad = 3 * (2 * len(sos) + 1)
    if len(raw) <= pad:
        raise DataError(f"{raw.source}: {len(raw)} samples are too few to filter; expected more than {pad}")
    # "even" padding: the default "odd" extension pins the output at each end of the log to the
    # raw (unfiltered) end sample, so one noisy first sample read as a motion before the first stop.
    if settings.filter_order == lowpass.ORDER:
        return lowpass.sosfiltfilt_even(sos, raw.dq_rad_s)
    import scipy.signal

    return scipy.signal.sosfiltfilt(sos, raw.dq_rad_s, axis=0, padtype="even")


def _group_stops(runs: list[tuple[int, int]], q: np.ndarray, tolerance: float) -> list[list[tuple[int, int]]]:
    """Consecutive stationary runs at the same position (every joint within ``tolerance``) form one stop."""
    stops: list[list[tuple[int, int]]] = []
    previous = None  # the median of the previous run, which is always the last run of stops[-1]
    for a, b in runs:
        here = np.median(q[a:b], axis=0)
        if stops and np.max(np.abs(here - previous)) <= tolerance:
            stops[-1].append((a, b))
        else:
            stops.append([(a, b)])
        previous = here
    return stops


def _move_direction(q: np.ndarray, dq_f: np.ndarray, previous: np.ndarray, tolerance: float) -> np.ndarray:
    """``dir`` after the move ``q``/``dq_f`` (samples between two stops), given the ``dir`` before it."""
    direction = previous.copy()
    if q.shape[0] == 0:
        return direction
    travel = q.max(axis=0) - q.min(axis=0)
    for j in np.flatnonzero(travel > tolerance):
        speed = np.abs(dq_f[:, j])
        last = np.flatnonzero(speed >= 0.5 * speed.max())[-1]
        direction[j] = np.sign(dq_f[last, j]) or direction[j]
    return direction


#: Rows per block of :func:`_norm_below` (2 MB of temporaries at 4 joints).
_NORM_BLOCK_ROWS = 1 << 16


def _norm_below(values: np.ndarray, threshold: float) -> np.ndarray:
    """``np.linalg.norm(values, axis=1) < threshold``, a block of rows at a time.

    The same values (a row's norm depends on that row alone, and a block keeps the array's layout,
    so numpy adds each row in the same order), without two temporaries the size of the whole log.
    """
    below = np.empty(len(values), dtype=bool)
    for start in range(0, len(values), _NORM_BLOCK_ROWS):
        block = values[start : start + _NORM_BLOCK_ROWS]
        below[start : start + len(block)] = np.linalg.norm(block, axis=1) < threshold
    return below


def reduce_to_stationary(raw: RawLog, settings: ReductionSettings | None = None) -> StationaryDataset:
    """The stationary points of a raw log, with ``dir`` and ``t`` kept.

    Raises:
        DataError: the log cannot be filtered, or holds no stationary sample.
    """
    settings = settings or ReductionSettings()
    dq_f = filtered_velocity(raw, settings)
    still = _norm_below(dq_f, settings.threshold_rad_s)
    trim = round(settings.edge_trim_s / float(np.median(np.diff(raw.t_s))))
    indices, directions, stop_of_sample = [], [], []
    direction = np.zeros(raw.q_rad.shape[1])
    previous_end = 0
    for stop in _group_stops(_stop_segments(still), raw.q_rad, settings.same_position_rad):
        start, end = stop[0][0], stop[-1][1]
        move = slice(previous_end, start)
        direction = _move_direction(raw.q_rad[move], dq_f[move], direction, settings.same_position_rad)
        previous_end = end
        # trim only the sides that border a move, not the start or end of the log
        first = start + trim if start > 0 else start
        last = end - trim if end < len(raw) else end
        kept = np.concatenate([np.arange(max(a, first), min(b, last)) for a, b in stop])
        if kept.size < max(settings.min_stop_samples, 1):
            continue
        indices.append(kept)
        directions.append(direction.copy())
        stop_of_sample.append(np.full(kept.size, len(indices) - 1))
    del dq_f, still  # not needed below: 30 MB of a 15-minute log less while the points are built
    if not indices:
        raise DataError(
            f"{raw.source}: no stationary samples (filtered |dq| below {settings.threshold_rad_s} rad/s); "
            "expected a log with stops"
        )
    if settings.per_stop == "mean":
        if settings.points_per_stop < 1:
            raise DataError(f"{raw.source}: points_per_stop must be at least 1, got {settings.points_per_stop}")
        parts = [
            (part, direction)
            for kept, direction in zip(indices, directions, strict=True)
            for part in np.array_split(kept, min(settings.points_per_stop, kept.size))
        ]
        return StationaryDataset(
            np.array([raw.q_rad[i].mean(axis=0) for i, _ in parts]),
            np.array([raw.tau_nm[i].mean(axis=0) for i, _ in parts]),
            np.array([d for _, d in parts]),
            np.array([raw.t_s[i].mean() for i, _ in parts]),
            raw.source,
        )
    index = np.concatenate(indices)
    per_sample_dir = np.array(directions)[np.concatenate(stop_of_sample)]
    return StationaryDataset(raw.q_rad[index], raw.tau_nm[index], per_sample_dir, raw.t_s[index], raw.source)
