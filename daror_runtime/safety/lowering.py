"""Planning a controlled lowering: from where a fault found the arm to the session's rest pose.

A ``lower`` reaction (category 1, docs/safety.md "Fault reactions") first holds the arm where the
fault found it; meanwhile this module plans, outside the tick (a job), the path the arm then
follows down to the rest pose of the session settings (where it lies on the pilot's lap, an
armrest or the robot's lower stops). The path:

* moves the shoulder about one fixed axis (the shortest rotation of the upper arm, as every move
  of the identification protocol does: :func:`~daror_runtime.identification.trajectory_planning.integrate_move`)
  and the elbow linearly, with minimum-jerk timing (no step in speed at either end); when a shoulder
  joint's torque is off (a fault took it), the shoulder cannot follow a rotation, and the joints
  still driven go straight to their rest angles in joint space instead;
* is timed so that no driven joint moves faster than ``speed_rad_s`` (0.12 rad/s by default: a
  fifth of the pilot's own pace, well under the 0.2 rad/s a limp arm may ever reach);
* is checked before it is used: inside the device's joint limits, away from the shoulder's
  singularity, and inside the pilot's ISB limits plus the monitor's margin (an arm that starts
  outside them, after an ISB fault, must only come back in). A path that fails a check is refused
  with the reason (:class:`LoweringError`): the reaction then holds the arm (category 2) and the
  operator is told why.

The result, :class:`LoweringPath`, is what the tick samples: cubic Hermite pieces between knots
at ``knot_rate_hz``, one compiled evaluation per tick.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from daror_runtime.errors import DarorError
from daror_runtime.identification.trajectory import evaluate_piece
from daror_runtime.identification.trajectory_planning import (
    MIN_JERK_PEAK,
    hermite_pieces,
    integrate_move,
    minimum_jerk,
)
from hal.isb import IsbLimits, Shoulder
from hal.robot import N_JOINTS, FloatArray

__all__ = ["DEFAULT_LOWERING_SPEED_RAD_S", "LoweringError", "LoweringPath", "plan_lowering"]

#: Peak joint speed of a lowering (rad/s).
DEFAULT_LOWERING_SPEED_RAD_S = 0.15
#: Knots of the stored path per second (cubic Hermite in between).
KNOT_RATE_HZ = 50.0
#: Rate the shoulder's rotation is integrated and every sample checked at (Hz).
CHECK_RATE_HZ = 500.0
#: Feedback gain of the rotation integrator (1/s), as the identification protocol's.
FEEDBACK_GAIN_PER_S = 20.0
#: Smallest singular value of the shoulder Jacobian a path may pass (as the identification protocol's).
MIN_SIGMA = 0.3
#: Shortest lowering (s): even a few degrees are moved gently.
MIN_DURATION_S = 1.0
#: A rest pose this close to the start (every driven joint, rad) needs no motion at all.
AT_REST_RAD = 1e-4


class LoweringError(DarorError):
    """No safe lowering from where the arm is: the reason (the reaction holds the arm instead)."""


class LoweringPath:
    """The reference of a lowering: ``reference(t_s) -> (q_ref (4,), dq_ref (4,))``, t from its start.

    Before 0 it holds the first pose, after ``duration_s`` the rest pose. Increasing times advance
    a cursor (O(1) per tick).
    """

    def __init__(self, starts_s: FloatArray, coefficients: FloatArray, duration_s: float, method: str) -> None:
        self._starts = [float(t) for t in starts_s]
        self._ends = [*self._starts[1:], math.inf]
        self._coefficients = np.ascontiguousarray(coefficients, dtype=float)
        self.duration_s = float(duration_s)
        #: how the shoulder moves: "shoulder rotation" or "joint space" (for the audit log)
        self.method = method
        self._cursor = 0
        self.q_start_rad = self._coefficients[0, :N_JOINTS, 0].copy()
        self.q_end_rad = self.reference(self.duration_s)[0].copy()
        self._cursor = 0

    def reference(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        """Joint angles (4,) rad and velocities (4,) rad/s at ``t_s`` seconds into the lowering."""
        k = self._cursor
        if not self._starts[k] <= t_s < self._ends[k]:
            k = self._cursor = max(bisect.bisect_right(self._starts, t_s) - 1, 0)
        out = evaluate_piece(self._coefficients, k, max(t_s - self._starts[k], 0.0))
        return out[:N_JOINTS], out[N_JOINTS:]

    def sample(self, t_s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """:meth:`reference` at many times: (N, 4) angles and (N, 4) velocities (offline checks, reports)."""
        rows = [self.reference(float(t)) for t in np.atleast_1d(t_s)]
        self._cursor = 0
        return np.array([r[0] for r in rows]), np.array([r[1] for r in rows])


def _joint_space(
    q_start: FloatArray, q_end: FloatArray, speed_rad_s: float, rate_hz: float
) -> tuple[FloatArray, FloatArray, float]:
    """A minimum-jerk straight line in joint space, sampled at ``rate_hz``: (q, dq, duration)."""
    distance = float(np.max(np.abs(q_end - q_start)))
    duration = max(MIN_DURATION_S, MIN_JERK_PEAK * distance / speed_rad_s)
    steps = max(math.ceil(duration * rate_hz), 1)
    duration = steps / rate_hz
    s, ds = minimum_jerk(np.arange(steps + 1) / steps)
    q = q_start + s[:, None] * (q_end - q_start)
    dq = ds[:, None] * (q_end - q_start) / duration
    return q, dq, duration


def _shoulder_rotation(
    shoulder: Shoulder, q_start: FloatArray, q_end: FloatArray, speed_rad_s: float, rate_hz: float
) -> tuple[FloatArray, FloatArray, float]:
    """The shoulder about one axis, the elbow linearly, timed for ``speed_rad_s``: (q, dq, duration)."""
    r3_start, r3_end = shoulder.rotor3(q_start), shoulder.rotor3(q_end)
    # A first guess from the joint-space distance, then stretched once to the fastest joint's speed
    # (joint speeds scale with 1/duration along the same path).
    duration = max(MIN_DURATION_S, MIN_JERK_PEAK * float(np.max(np.abs(q_end - q_start))) / speed_rad_s)
    for _ in range(2):
        duration = math.ceil(duration * rate_hz) / rate_hz
        q, dq = integrate_move(
            shoulder, q_start, r3_start, r3_end, float(q_end[3]), duration, rate_hz, FEEDBACK_GAIN_PER_S
        )
        ratio = float(np.max(np.abs(dq))) / speed_rad_s
        if ratio <= 1.0:
            break
        duration *= ratio * 1.01
    return q, dq, duration


def plan_lowering(
    q_start_rad: FloatArray,
    q_rest_rad: FloatArray,
    shoulder: Shoulder,
    joints_off: tuple[int, ...] = (),
    isb_limits: IsbLimits | None = None,
    isb_margin_rad: float = 0.0,
    speed_rad_s: float = DEFAULT_LOWERING_SPEED_RAD_S,
) -> LoweringPath:
    """The lowering from ``q_start_rad`` (where the arm is held) to ``q_rest_rad`` (4,) rad, checked.

    Joints in ``joints_off`` (1-4) are not driven: they stay at their start angle in the plan (the
    arm moves them as it will). Design time: milliseconds to tens of milliseconds, never in the tick.

    Raises:
        LoweringError: the rest pose or the path leaves the joint limits, passes near the shoulder's
            singularity, leaves the pilot's ISB limits (plus ``isb_margin_rad``) beyond where the
            arm already is, or the inputs are not finite: the message says which and where.
    """
    q_start = np.asarray(q_start_rad, dtype=float).reshape(N_JOINTS).copy()
    q_end = np.asarray(q_rest_rad, dtype=float).reshape(N_JOINTS).copy()
    if not (np.all(np.isfinite(q_start)) and np.all(np.isfinite(q_end))):
        raise LoweringError(f"the arm's pose {q_start.tolist()} or the rest pose {q_end.tolist()} is not finite")
    if not (math.isfinite(speed_rad_s) and speed_rad_s > 0.0):
        raise LoweringError(f"the lowering speed must be a positive number of rad/s, got {speed_rad_s}")
    off = [j - 1 for j in joints_off]
    q_end[off] = q_start[off]
    if float(np.max(np.abs(q_end - q_start))) < AT_REST_RAD:
        block = np.zeros((1, 2 * N_JOINTS, 4))
        block[0, :N_JOINTS, 0] = q_end
        return LoweringPath(np.zeros(1), block, 0.0, "none: the arm is at its rest pose")
    rate = CHECK_RATE_HZ
    shoulder_off = any(j < 3 for j in off)
    if not shoulder_off and float(shoulder.sigma_min(q_start)) < MIN_SIGMA:
        raise LoweringError(
            f"the arm is held near the shoulder's singularity (q2 = {np.degrees(q_start[1]):.1f} deg): a rotation "
            "of the upper arm cannot be followed from there"
        )
    if shoulder_off:
        q, dq, duration = _joint_space(q_start, q_end, speed_rad_s, rate)
        method = "joint space (a shoulder joint's torque is off)"
    else:
        q, dq, duration = _shoulder_rotation(shoulder, q_start, q_end, speed_rad_s, rate)
        method = "shoulder rotation"
        if float(np.max(np.abs(q[-1] - q_end))) > 1e-3:  # the rotation reached the rest on the other IK branch
            q, dq, duration = _joint_space(q_start, q_end, speed_rad_s, rate)
            method = "joint space (the rest pose is on the other branch of the shoulder)"
        elif _leaves_joint_limits(q, shoulder):
            # From an arm held near a joint limit the rotation's path may pass it (q2 at 119.8 of 120 deg went
            # to 120.0): a straight line in joint space between two poses inside the limits stays inside them.
            # It is checked below like the rotation (singularity, the pilot's ISB limits); refused if it fails.
            q, dq, duration = _joint_space(q_start, q_end, speed_rad_s, rate)
            method = "joint space (the shoulder rotation would pass a joint limit)"
    _check(q, dq, shoulder, off, isb_limits, isb_margin_rad, speed_rad_s)
    every = round(rate / KNOT_RATE_HZ)
    qk, dqk = q[::every], dq[::every]
    if (q.shape[0] - 1) % every:
        qk, dqk = np.vstack([qk, q[-1:]]), np.vstack([dqk, dq[-1:]])
    h = every / rate
    times = np.minimum(np.arange(qk.shape[0]) * h, duration)
    pieces = hermite_pieces(qk, dqk, h)
    hold = np.zeros((1, 2 * N_JOINTS, 4))
    hold[0, :N_JOINTS, 0] = q[-1]  # after the end: the rest pose, still
    return LoweringPath(np.concatenate([times[:-1], [duration]]), np.concatenate([pieces, hold]), duration, method)


def _leaves_joint_limits(q: FloatArray, shoulder: Shoulder) -> bool:
    """True if a sample of ``q`` (N, 4) rad is outside the joint limits (the tolerance :func:`_check` allows)."""
    return bool(np.any((q < shoulder.lower_rad - 1e-9) | (q > shoulder.upper_rad + 1e-9)))


def _check(
    q: FloatArray,
    dq: FloatArray,
    shoulder: Shoulder,
    off: list[int],
    isb_limits: IsbLimits | None,
    isb_margin_rad: float,
    speed_rad_s: float,
) -> None:
    """Every sample of a lowering: joint limits, singularity, ISB limits (never farther out), speed."""
    driven = [j for j in range(N_JOINTS) if j not in off]
    lo, hi = shoulder.lower_rad - 1e-9, shoulder.upper_rad + 1e-9
    outside = (q[:, driven] < lo[driven]) | (q[:, driven] > hi[driven])
    if np.any(outside):
        n, k = (int(i[0]) for i in np.nonzero(outside))
        j = driven[k]
        raise LoweringError(
            f"the lowering would take joint {j + 1} to {np.degrees(q[n, j]):.1f} deg, outside its limits "
            f"[{np.degrees(shoulder.lower_rad[j]):g}, {np.degrees(shoulder.upper_rad[j]):g}] deg"
        )
    if not any(j < 3 for j in off):
        sigma = shoulder.sigma_min(q)
        if np.any(sigma < MIN_SIGMA):
            n = int(np.argmax(sigma < MIN_SIGMA))
            raise LoweringError(
                f"the lowering passes near the shoulder's singularity (q2 = {np.degrees(q[n, 1]):.1f} deg, "
                f"smallest singular value {sigma[n]:.2f} < {MIN_SIGMA})"
            )
    if float(np.max(np.abs(dq[:, driven]))) > speed_rad_s * 1.02:
        raise LoweringError(f"the lowering would move a joint at {np.max(np.abs(dq)):.3f} rad/s (limit {speed_rad_s})")
    if isb_limits is None:
        return
    boxed = isb_limits.for_box_check(shoulder.isb_from_q(q))
    lower, upper = isb_limits.lower_rad - isb_margin_rad, isb_limits.upper_rad + isb_margin_rad
    if off:  # an angle that depends on an undriven joint is not the plan's to keep
        free = {3} if 3 in off else set()
        if any(j < 3 for j in off):
            free |= {0, 1, 2}
        keep = [i for i in range(N_JOINTS) if i not in free]
    else:
        keep = list(range(N_JOINTS))
    excess = np.maximum(lower - boxed, boxed - upper).clip(min=0.0)[:, keep]
    # An arm that starts outside (an ISB fault) may only come back in: no sample farther out than the start.
    allowed = excess[0] + 1e-6
    worse = np.any(excess > allowed, axis=1)
    if np.any(worse):
        n = int(np.argmax(worse))
        raise LoweringError(
            f"the lowering would leave the pilot's ISB limits at {100.0 * n / max(q.shape[0] - 1, 1):.0f}% of the "
            "way: " + "; ".join(isb_limits.violations(shoulder.isb_from_q(q[n])) or ["beyond the margin"])
        )
