"""Reduce a raw log to stationary points (thesis Sec. 4.3.2).

Only points where the robot stands still carry nothing but gravity and stiffness torque. The
logged joint velocity is noisy (it is differentiated from 1e-4 rad encoders), so it is low-pass
filtered first (zero-phase Butterworth, ``scipy.signal.sosfiltfilt``) and a sample counts as
stationary when the norm of the filtered velocity is below a threshold.

The thesis used a 0.1 Hz cut-off and ``||dq|| < 0.0002 rad/s`` for its protocol of long stops;
the defaults here are set for this runtime's protocol and documented in ``docs/data.md``. Both
are settings, so the thesis values can be reproduced.

The direction of each joint's last motion before a stop (``dir``) is the sign of the filtered
velocity the last time that joint moved faster than ``motion_threshold_rad_s``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.signal

from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.errors import DataError
from hal.signals import last_motion_sign

StopReduction = Literal["all", "mean"]


@dataclass(frozen=True)
class ReductionSettings:
    """How a raw log becomes stationary points."""

    cutoff_hz: float = 2.0
    filter_order: int = 2
    threshold_rad_s: float = 0.01
    motion_threshold_rad_s: float = 0.02
    per_stop: StopReduction = "all"
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
    sos = scipy.signal.butter(settings.filter_order, settings.cutoff_hz, fs=rate_hz, output="sos")
    pad = 3 * (2 * len(sos) + 1)
    if len(raw) <= pad:
        raise DataError(f"{raw.source}: {len(raw)} samples are too few to filter; expected more than {pad}")
    return scipy.signal.sosfiltfilt(sos, raw.dq_rad_s, axis=0)


def reduce_to_stationary(raw: RawLog, settings: ReductionSettings | None = None) -> StationaryDataset:
    """The stationary points of a raw log, with ``dir`` and ``t`` kept.

    Raises:
        DataError: the log cannot be filtered, or holds no stationary sample.
    """
    settings = settings or ReductionSettings()
    dq_f = filtered_velocity(raw, settings)
    still = np.linalg.norm(dq_f, axis=1) < settings.threshold_rad_s
    direction = last_motion_sign(dq_f, settings.motion_threshold_rad_s)
    stops = [(a, b) for a, b in _stop_segments(still) if b - a >= settings.min_stop_samples]
    if not stops:
        raise DataError(
            f"{raw.source}: no stationary samples (filtered |dq| below {settings.threshold_rad_s} rad/s); "
            "expected a log with stops"
        )
    if settings.per_stop == "all":
        index = np.concatenate([np.arange(a, b) for a, b in stops])
        return StationaryDataset(raw.q_rad[index], raw.tau_nm[index], direction[index], raw.t_s[index], raw.source)
    q = np.array([raw.q_rad[a:b].mean(axis=0) for a, b in stops])
    tau = np.array([raw.tau_nm[a:b].mean(axis=0) for a, b in stops])
    t = np.array([raw.t_s[a:b].mean() for a, b in stops])
    return StationaryDataset(q, tau, direction[[a for a, _ in stops]], t, raw.source)
