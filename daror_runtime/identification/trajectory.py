"""Identification trajectories as the tick samples them (thesis Sec. 4.3.1-4.3.2).

A :class:`ReferenceTrajectory` is a built, checked trajectory: a table of cubic Hermite pieces
(knots at ``knot_rate_hz`` on moves, one constant piece per stop) that the position controller
samples once per tick with :meth:`ReferenceTrajectory.reference` in O(1), or reads whole through
:attr:`ReferenceTrajectory.piecewise_table` inside its compiled kernel. Its stops (:class:`Stop`)
say when the robot stands still, where, and at which waypoint.

Building one (waypoints to joint paths, the checks against the joint and ISB limits, the approach
move) is planning, done before anything moves: :mod:`daror_runtime.identification.trajectory_planning`.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit

from daror_runtime.errors import DarorError
from daror_runtime.identification.trajectory_settings import TrajectoryKind, TrajectorySettings
from hal.robot import N_JOINTS, FloatArray

__all__ = ["ReferenceTimeError", "ReferenceTrajectory", "Stop", "TrajectoryKind", "evaluate_piece"]


class ReferenceTimeError(DarorError, ValueError):
    """A non-finite time reached :meth:`ReferenceTrajectory.reference`: a programming error."""


@dataclass(frozen=True)
class Stop:
    """One period the robot stands still.

    Attributes:
        start_s, end_s: robot time, seconds from the start of the trajectory.
        waypoint: the waypoint number (from 1, as in the waypoint file), ``None`` at a sub-waypoint.
        run: "forward" or "reverse".
        q_rad: the joint angles held (4,).
    """

    start_s: float
    end_s: float
    waypoint: int | None
    run: Literal["forward", "reverse"]
    q_rad: tuple[float, float, float, float]

    @property
    def is_waypoint(self) -> bool:
        return self.waypoint is not None


class ReferenceTrajectory:
    """Joint reference of one identification run, sampled per tick.

    ``reference(t_s)`` returns ``(q_ref (4,), dq_ref (4,))``: on a move a cubic Hermite
    interpolant of the integrated path (``dq_ref`` is its exact derivative), at a stop the held
    angles and zero velocity. Before the start it holds the first pose, after the end the last.
    Calls with increasing ``t_s`` advance a cursor (O(1)); a jump anywhere else is a C-level
    binary search.
    """

    def __init__(
        self,
        kind: TrajectoryKind,
        starts_s: FloatArray,
        coefficients: FloatArray,
        duration_s: float,
        stops: tuple[Stop, ...],
        order: tuple[int, ...],
        settings: TrajectorySettings,
    ) -> None:
        self.kind = kind
        self.duration_s = float(duration_s)
        self.stops = stops
        #: waypoint numbers in the order of the forward run; the reverse run is the same backwards
        self.order = order
        self.settings = settings
        self._coefficients = np.ascontiguousarray(coefficients)
        self._starts = [float(t) for t in starts_s]  # Python floats: the per-tick comparisons stay cheap
        self._starts_array = np.ascontiguousarray(starts_s, dtype=float)
        #: Robot time at which the planned trajectory (its first stop) begins; non-zero after an approach.
        self.time_offset_s = 0.0
        self._ends = [*self._starts[1:], math.inf]
        self._cursor = 0
        evaluate_piece(self._coefficients, 0, 0.0)  # compile (or load from the cache) before the first tick

    # --- per tick ---------------------------------------------------------------------------

    def reference(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        """Reference joint angles (4,) rad and velocities (4,) rad/s at robot time ``t_s`` (s).

        Raises:
            ReferenceTimeError: ``t_s`` is NaN or infinite (a bug in the caller's clock).
        """
        k = self._cursor
        if not self._starts[k] <= t_s < self._ends[k]:
            if not math.isfinite(t_s):  # NaN fails the test above; never hand the loop a made-up pose
                raise ReferenceTimeError(f"reference() needs a finite robot time, got {t_s}")
            k = self._cursor = max(bisect.bisect_right(self._starts, t_s) - 1, 0)
        out = evaluate_piece(self._coefficients, k, t_s - self._starts[k])
        return out[:N_JOINTS], out[N_JOINTS:]

    def __call__(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        """A trajectory is a reference: ``t_s -> (q_ref, dq_ref)`` (the controllers' contract)."""
        return self.reference(t_s)

    # --- offline ------------------------------------------------------------------------------

    def sample(self, t_s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Vectorised :meth:`reference`: (N, 4) angles and (N, 4) velocities at times ``t_s`` (N,)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        starts = self._starts_array  # the same float64 values as the list ``_starts``, already an array
        k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, starts.shape[0] - 1)
        tau = t - starts[k]
        basis = np.stack([np.ones_like(tau), tau, tau * tau, tau * tau * tau], axis=-1)
        out = np.einsum("nrc,nc->nr", self._coefficients[k], basis)
        return out[:, :N_JOINTS], out[:, N_JOINTS:]

    @property
    def piecewise_table(self) -> tuple[FloatArray, FloatArray]:
        """``(starts (P,), coefficients (P, 8, 4))`` for compiled consumers: piece ``k`` starts at
        ``starts[k]`` and row ``r`` is ``c0 + c1 tau + c2 tau^2 + c3 tau^3`` (rows q1..q4, dq1..dq4)."""
        return self._starts_array, self._coefficients

    @property
    def start_q_rad(self) -> FloatArray:
        """Where the robot must be before the trajectory starts (4,) rad: where its first piece begins."""
        return self._coefficients[0, :N_JOINTS, 0].copy()

    @property
    def waypoint_stops(self) -> tuple[Stop, ...]:
        return tuple(s for s in self.stops if s.is_waypoint)


@njit(cache=True)
def evaluate_piece(coefficients: FloatArray, k: int, tau: float) -> FloatArray:
    """Rows of piece ``k`` (8 cubics: q then dq) at local time ``tau``; numba halves the per-tick cost."""
    out = np.empty(2 * N_JOINTS)
    for r in range(2 * N_JOINTS):
        out[r] = coefficients[k, r, 0] + tau * (
            coefficients[k, r, 1] + tau * (coefficients[k, r, 2] + tau * coefficients[k, r, 3])
        )
    return out
