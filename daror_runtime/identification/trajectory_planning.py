"""Planning identification trajectories: ISB waypoints to joint references (thesis Sec. 4.3.1-4.3.2, Eq. 4.30).

From waypoint ``i`` to ``i + 1`` the shoulder turns about one fixed axis (Euler's rotation
theorem): ``R_{i+1} = exp([omega] theta) R_i``. Along a move the reference shoulder rotation is
``R_ref(t) = exp([omega] theta s(t)) R_i`` with a minimum-jerk timing ``s`` (zero velocity and
acceleration at both ends), and the joint velocities are Eq. 4.30 with the feedback correction the
thesis mentions and omits::

    q_dot[:3] = J(q)^-1 (omega theta s_dot + K_fb e),   e = vee(R_ref R(q)^T - R(q) R_ref^T) / 2
    q_dot[3]  = (elbow_{i+1} - elbow_i) s_dot

integrated with RK4 at the loop rate. ``e`` is the small rotation from where the integrated joints
put rotor 3 to where the reference is, so integration error does not accumulate over the hundreds
of moves of a protocol: every stop lies on the exact waypoint rotation (to ~1e-12 rad).

Training trajectory: each segment is cut into sub-waypoints no more than
``sub_waypoint_spacing_deg`` apart (shoulder rotation angle and elbow angle) and the robot stops at
each (Sec. 4.3.2). Validation trajectory: the same waypoints in another order, one move per
segment, stops only at waypoints (one validation point per waypoint, Sec. 4.3.2). Both run the
order forward and then in reverse (Sec. 4.3.1), so they end where they started; the turning
waypoint gets one stop for each run.

Before anything runs, every pose and every sample of the path (at the integration rate) is
checked: reachable, inside the joint limits, inside the pilot's ISB limits, away from a shoulder
singularity, joint speeds within the limit. A failure is a :class:`TrajectoryError` naming the
waypoint (and its line in the waypoint file).

The result is a :class:`~daror_runtime.identification.trajectory.ReferenceTrajectory`, the table
the tick samples; :func:`prepend_approach` puts the move from where the robot stands in front of
it. Everything here runs before the loop starts, never in the tick.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numba import njit

from daror_runtime.identification.trajectory import ReferenceTrajectory, Stop
from daror_runtime.identification.trajectory_settings import TrajectoryError, TrajectoryKind, TrajectorySettings
from daror_runtime.identification.waypoints import WaypointSet
from hal.isb import AngleRange, IsbLimits, Shoulder, UnreachablePoseError, default_shoulder, shoulder_fk_kernel
from hal.robot import N_JOINTS, FloatArray, RobotDescription, load_description

__all__ = [
    "APPROACH_SLACK_DEG",
    "MIN_JERK_PEAK",
    "ApproachCheck",
    "MoveError",
    "TrajectoryError",
    "TrajectorySettings",
    "approach_limits",
    "build_trajectory",
    "build_visit_trajectory",
    "check_approach",
    "hermite_pieces",
    "integrate_move",
    "minimum_jerk",
    "prepend_approach",
]

#: Peak of the minimum-jerk velocity profile relative to the mean: max s_dot = 1.875 / T.
MIN_JERK_PEAK = 1.875

#: Fraction of the joint-speed limit a move is timed for (the feedback adds a little on top).
_SPEED_HEADROOM = 0.95


class MoveError(TrajectoryError):
    """A visit or a move of a visit sequence fails a check; ``from_visit``/``to_visit`` number the
    move's ends, or the visit twice (from 1)."""

    def __init__(self, message: str, from_visit: int, to_visit: int) -> None:
        super().__init__(message)
        self.from_visit = from_visit
        self.to_visit = to_visit


# --- the move integrator -------------------------------------------------------------------


def minimum_jerk(tau: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Minimum-jerk path parameter ``s`` and ``ds/dtau`` at normalised time ``tau`` in [0, 1]."""
    tau = np.asarray(tau, dtype=float)
    return tau**3 * (10 - 15 * tau + 6 * tau**2), 30 * tau**2 * (1 - tau) ** 2


@njit(cache=True)
def _rhs(
    t: float,
    q: FloatArray,
    r3_start: FloatArray,
    axis: FloatArray,
    angle: float,
    duration: float,
    k_fb: float,
    base: FloatArray,
    inter: FloatArray,
    scratch: FloatArray,
    out: FloatArray,
) -> None:
    """Eq. 4.30 with feedback: shoulder joint velocities (3,) into ``out``; ``scratch`` (5, 3, 3)."""
    tau = min(max(t / duration, 0.0), 1.0)
    s = tau * tau * tau * (10.0 - 15.0 * tau + 6.0 * tau * tau)
    s_dot = 30.0 * tau * tau * (1.0 - tau) * (1.0 - tau) / duration
    # R_ref = Rodrigues(axis, angle s) @ r3_start
    phi = angle * s
    c, sn = np.cos(phi), np.sin(phi)
    x, y, z = axis[0], axis[1], axis[2]
    rot, ref, err, r3, jac = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4]
    rot[0, 0] = c + x * x * (1 - c)
    rot[0, 1] = x * y * (1 - c) - z * sn
    rot[0, 2] = x * z * (1 - c) + y * sn
    rot[1, 0] = y * x * (1 - c) + z * sn
    rot[1, 1] = c + y * y * (1 - c)
    rot[1, 2] = y * z * (1 - c) - x * sn
    rot[2, 0] = z * x * (1 - c) - y * sn
    rot[2, 1] = z * y * (1 - c) + x * sn
    rot[2, 2] = c + z * z * (1 - c)
    for i in range(3):
        for j in range(3):
            ref[i, j] = rot[i, 0] * r3_start[0, j] + rot[i, 1] * r3_start[1, j] + rot[i, 2] * r3_start[2, j]
    shoulder_fk_kernel(q, base, inter, r3, jac)
    # err = R_ref R^T
    for i in range(3):
        for j in range(3):
            err[i, j] = ref[i, 0] * r3[j, 0] + ref[i, 1] * r3[j, 1] + ref[i, 2] * r3[j, 2]
    v0 = angle * s_dot * x + k_fb * 0.5 * (err[2, 1] - err[1, 2])
    v1 = angle * s_dot * y + k_fb * 0.5 * (err[0, 2] - err[2, 0])
    v2 = angle * s_dot * z + k_fb * 0.5 * (err[1, 0] - err[0, 1])
    # J x = v by Cramer's rule (J is 3x3 and, by the path checks, far from singular)
    a, b, cc = jac[0], jac[1], jac[2]
    det = (
        a[0] * (b[1] * cc[2] - b[2] * cc[1])
        - a[1] * (b[0] * cc[2] - b[2] * cc[0])
        + a[2] * (b[0] * cc[1] - b[1] * cc[0])
    )
    out[0] = (
        v0 * (b[1] * cc[2] - b[2] * cc[1]) - a[1] * (v1 * cc[2] - b[2] * v2) + a[2] * (v1 * cc[1] - b[1] * v2)
    ) / det
    out[1] = (
        a[0] * (v1 * cc[2] - b[2] * v2) - v0 * (b[0] * cc[2] - b[2] * cc[0]) + a[2] * (b[0] * v2 - v1 * cc[0])
    ) / det
    out[2] = (
        a[0] * (b[1] * v2 - v1 * cc[1]) - a[1] * (b[0] * v2 - v1 * cc[0]) + v0 * (b[0] * cc[1] - b[1] * cc[0])
    ) / det


@njit(cache=True)
def _integrate(
    q0: FloatArray,
    r3_start: FloatArray,
    axis: FloatArray,
    angle: float,
    duration: float,
    steps: int,
    k_fb: float,
    base: FloatArray,
    inter: FloatArray,
    q_out: FloatArray,
    dq_out: FloatArray,
) -> None:
    """RK4 of the shoulder joints over one move; q_out, dq_out (steps + 1, 3)."""
    dt = duration / steps
    scratch = np.empty((5, 3, 3))
    k1, k2, k3, k4 = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    q = q0[:3].copy()
    tmp = np.empty(3)
    for n in range(steps + 1):
        t = n * dt
        _rhs(t, q, r3_start, axis, angle, duration, k_fb, base, inter, scratch, k1)
        q_out[n] = q
        dq_out[n] = k1
        if n == steps:
            break
        for i in range(3):
            tmp[i] = q[i] + 0.5 * dt * k1[i]
        _rhs(t + 0.5 * dt, tmp, r3_start, axis, angle, duration, k_fb, base, inter, scratch, k2)
        for i in range(3):
            tmp[i] = q[i] + 0.5 * dt * k2[i]
        _rhs(t + 0.5 * dt, tmp, r3_start, axis, angle, duration, k_fb, base, inter, scratch, k3)
        for i in range(3):
            tmp[i] = q[i] + dt * k3[i]
        _rhs(t + dt, tmp, r3_start, axis, angle, duration, k_fb, base, inter, scratch, k4)
        for i in range(3):
            q[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])


def integrate_move(
    shoulder: Shoulder,
    q_start: FloatArray,
    r3_start: FloatArray,
    r3_end: FloatArray,
    elbow_end_rad: float,
    duration_s: float,
    rate_hz: float,
    feedback_gain_per_s: float,
) -> tuple[FloatArray, FloatArray]:
    """Joint path of one minimum-jerk move from ``q_start`` towards rotor-3 orientation ``r3_end``.

    The shoulder follows ``exp([omega] theta s) r3_start`` (Eq. 4.30 with feedback); the elbow
    goes linearly in ``s`` from ``q_start[3]`` to ``elbow_end_rad``. ``r3_start`` is the exact
    rotation the move starts from (the previous waypoint's), so an error in ``q_start`` is pulled
    out by the feedback rather than carried along.

    Returns:
        q (steps + 1, 4) rad and dq (steps + 1, 4) rad/s at ``rate_hz``; ``steps = round(duration_s * rate_hz)``.
    """
    steps = max(round(duration_s * rate_hz), 1)
    duration = steps / rate_hz
    relative = np.asarray(r3_end) @ np.asarray(r3_start).T
    axis, angle = _axis_angle(relative)
    q_out = np.empty((steps + 1, N_JOINTS))
    dq_out = np.empty((steps + 1, N_JOINTS))
    q3 = np.empty((steps + 1, 3))
    dq3 = np.empty((steps + 1, 3))
    _integrate(
        np.ascontiguousarray(q_start, dtype=float),
        np.ascontiguousarray(r3_start, dtype=float),
        axis,
        angle,
        duration,
        steps,
        float(feedback_gain_per_s),
        np.ascontiguousarray(shoulder.kinematics.base_rotation),
        np.ascontiguousarray(shoulder.kinematics.inter_rotation),
        q3,
        dq3,
    )
    s, ds = minimum_jerk(np.arange(steps + 1) / steps)
    q_out[:, :3], dq_out[:, :3] = q3, dq3
    q_out[:, 3] = q_start[3] + (elbow_end_rad - q_start[3]) * s
    dq_out[:, 3] = (elbow_end_rad - q_start[3]) * ds / duration
    return q_out, dq_out


def _axis_angle(rotation: FloatArray) -> tuple[FloatArray, float]:
    """Euler axis (3,) and angle [0, pi] of a rotation matrix, robust near 0 and pi."""
    # Quaternion route (Shepperd): stable for every angle, unlike acos of the trace near 0.
    m = rotation
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = np.array([trace, m[0, 0], m[1, 1], m[2, 2]])
    i = int(np.argmax(candidates))
    if i == 0:
        w = math.sqrt(1.0 + trace) / 2
        x, y, z = (m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w)
    elif i == 1:
        x = math.sqrt(1.0 + 2 * m[0, 0] - trace) / 2
        w, y, z = (m[2, 1] - m[1, 2]) / (4 * x), (m[0, 1] + m[1, 0]) / (4 * x), (m[0, 2] + m[2, 0]) / (4 * x)
    elif i == 2:
        y = math.sqrt(1.0 + 2 * m[1, 1] - trace) / 2
        w, x, z = (m[0, 2] - m[2, 0]) / (4 * y), (m[0, 1] + m[1, 0]) / (4 * y), (m[1, 2] + m[2, 1]) / (4 * y)
    else:
        z = math.sqrt(1.0 + 2 * m[2, 2] - trace) / 2
        w, x, y = (m[1, 0] - m[0, 1]) / (4 * z), (m[0, 2] + m[2, 0]) / (4 * z), (m[1, 2] + m[2, 1]) / (4 * z)
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    vector = np.array([x, y, z])
    norm = float(np.linalg.norm(vector))
    if norm < 1e-15:
        return np.array([1.0, 0.0, 0.0]), 0.0
    return vector / norm, 2.0 * math.atan2(norm, w)


def _rodrigues(axis: FloatArray, angle: float) -> FloatArray:
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


# --- cubic Hermite pieces ----------------------------------------------------------------------


def hermite_pieces(qk: FloatArray, dqk: FloatArray, h: float) -> FloatArray:
    """Pieces (n, 8, 4) between ``n + 1`` knots ``qk`` (rad) and ``dqk`` (rad/s), ``h`` s apart.

    Row ``r`` of a piece holds the cubic's coefficients ``c0..c3`` in the local time: rows q1..q4
    are the Hermite interpolant of the knots, rows dq1..dq4 its exact derivative.
    """
    n = qk.shape[0] - 1
    block = np.zeros((n, 2 * N_JOINTS, 4))
    q0, q1, d0, d1 = qk[:-1], qk[1:], dqk[:-1], dqk[1:]
    c2 = (3 * (q1 - q0) / h - 2 * d0 - d1) / h
    c3 = (2 * (q0 - q1) / h + d0 + d1) / (h * h)
    block[:, :N_JOINTS, 0], block[:, :N_JOINTS, 1] = q0, d0
    block[:, :N_JOINTS, 2], block[:, :N_JOINTS, 3] = c2, c3
    block[:, N_JOINTS:, 0], block[:, N_JOINTS:, 1], block[:, N_JOINTS:, 2] = d0, 2 * c2, 3 * c3
    return block


def prepend_approach(
    trajectory: ReferenceTrajectory, q_from_rad: FloatArray, approach_s: float, settle_s: float
) -> ReferenceTrajectory:
    """``trajectory`` preceded by a minimum-jerk move from ``q_from_rad`` and a hold at its start.

    The approach is stored like every move (cubic Hermite pieces between knots of the exact
    minimum-jerk profile at ``knot_rate_hz``), so the whole run stays one piecewise table.
    The result's ``time_offset_s`` is when ``trajectory``'s own clock reads zero; its stops and
    times are shifted by it. Robot time in s, angles in rad.

    Raises:
        TrajectoryError: a non-positive approach duration or a negative settle time.
    """
    if not (approach_s > 0 and settle_s >= 0):
        raise TrajectoryError(f"approach_s must be > 0 and settle_s >= 0, got {approach_s}, {settle_s}")
    q_from = np.asarray(q_from_rad, dtype=float)
    delta = trajectory.start_q_rad - q_from
    h = 1.0 / trajectory.settings.knot_rate_hz
    n = max(round(approach_s / h), 1)
    h = approach_s / n
    fraction = np.arange(n + 1) / n
    position, velocity = minimum_jerk(fraction)
    qk = q_from + position[:, None] * delta
    dqk = velocity[:, None] * delta / approach_s
    hold = np.zeros((1, 2 * N_JOINTS, 4))
    hold[0, :N_JOINTS, 0] = trajectory.start_q_rad  # the settle hold
    offset = approach_s + settle_s
    starts, coefficients = trajectory.piecewise_table
    shifted = tuple(
        dataclasses.replace(s, start_s=s.start_s + offset, end_s=s.end_s + offset) for s in trajectory.stops
    )
    combined = ReferenceTrajectory(
        trajectory.kind,
        np.concatenate([h * np.arange(n), [approach_s], starts + offset]),
        np.concatenate([hermite_pieces(qk, dqk, h), hold, coefficients]),
        trajectory.duration_s + offset,
        shifted,
        trajectory.order,
        trajectory.settings,
    )
    combined.time_offset_s = trajectory.time_offset_s + offset
    return combined


# --- the approach and the pilot's limits ---------------------------------------------------------

#: How far beyond its start pose an approach from outside the pilot's ISB limits may go before it
#: has entered them, degrees: the arm at rest reads a little noise and sags in the position
#: control's first ticks (the monitor holds the approach to this, :func:`check_approach`).
APPROACH_SLACK_DEG = 1.0
#: The approach's straight joint path is checked at joint steps no longer than this, rad.
_APPROACH_STEP_RAD = 1e-3


@dataclass(frozen=True)
class ApproachCheck:
    """How the approach from where the robot stands meets the pilot's ISB limits (:func:`check_approach`).

    Attributes:
        entry_fraction: share of the approach's path (0 to 1) from which on every pose is inside the
            limits; 0 when it starts inside.
        outside: what the start pose violates, one phrase per angle; empty when it starts inside.
        on_the_way: the limits the approach is held to until the arm has entered the pilot's: theirs,
            widened on each side the start pose lies beyond to that pose plus :data:`APPROACH_SLACK_DEG`;
            the pilot's own when it starts inside.
    """

    entry_fraction: float
    outside: tuple[str, ...]
    on_the_way: IsbLimits

    @property
    def starts_inside(self) -> bool:
        return not self.outside


def approach_limits(limits: IsbLimits, start_isb_rad: FloatArray) -> IsbLimits:
    """``limits`` widened just enough to hold a start pose (4,) rad outside them, plus :data:`APPROACH_SLACK_DEG`.

    Only the sides the start pose lies beyond move; a start inside gives ``limits`` back.
    """
    boxed = np.degrees(limits.for_box_check(np.asarray(start_isb_rad, dtype=float)))
    ranges = []
    for value, r in zip(boxed, limits.ranges, strict=True):
        lower = max(value - APPROACH_SLACK_DEG, -180.0) if value < r.lower_deg else r.lower_deg
        upper = min(value + APPROACH_SLACK_DEG, 180.0) if value > r.upper_deg else r.upper_deg
        ranges.append(AngleRange(lower_deg=lower, upper_deg=upper))
    if all(a == b for a, b in zip(ranges, limits.ranges, strict=True)):
        return limits
    return IsbLimits(
        elevation=ranges[0],
        horizontal_rotation=ranges[1],
        axial_rotation=ranges[2],
        elbow=ranges[3],
        horizontal_free_below_deg=limits.horizontal_free_below_deg,
    )


def check_approach(
    shoulder: Shoulder, limits: IsbLimits, q_from_rad: FloatArray, q_to_rad: FloatArray, what: str = "the approach"
) -> ApproachCheck:
    """Check the approach (the straight joint path of :func:`prepend_approach`) against the pilot's ISB limits.

    An approach that starts inside the limits must stay inside. One that starts outside (a pilot who
    cannot reach the robot's home pose) must enter them once and for all: outside them only on its
    way in, and there inside :attr:`ApproachCheck.on_the_way`; from the first pose inside, inside to
    the end. Angles in rad; the path is checked at joint steps of at most 1 mrad.

    Raises:
        TrajectoryError: the approach ends outside the limits, leaves them after it was inside, or
            strays further out than its start on the way in (one line naming where and what).
    """
    q_from = np.asarray(q_from_rad, dtype=float)
    q_to = np.asarray(q_to_rad, dtype=float)
    start_isb = shoulder.isb_from_q(q_from)
    outside = tuple(limits.violations(start_isb))
    on_the_way = approach_limits(limits, start_isb) if outside else limits
    steps = max(math.ceil(float(np.abs(q_to - q_from).max()) / _APPROACH_STEP_RAD), 1)
    fraction = np.arange(steps + 1) / steps
    isb = shoulder.isb_from_q(q_from + fraction[:, None] * (q_to - q_from))
    inside = np.asarray(limits.contains(isb))
    if not inside[-1]:
        raise TrajectoryError(f"{what} ends outside the pilot's ISB limits: " + "; ".join(limits.violations(isb[-1])))
    entry = int(np.argmax(inside))
    if not inside[entry:].all():
        n = entry + int(np.argmin(inside[entry:]))
        raise TrajectoryError(
            f"{what} leaves the pilot's ISB limits at {100.0 * fraction[n]:.0f}% of the way after it was inside them: "
            + "; ".join(limits.violations(isb[n]))
        )
    if outside:
        strayed = np.flatnonzero(~np.asarray(on_the_way.contains(isb[:entry])))
        if strayed.size:
            n = int(strayed[0])
            raise TrajectoryError(
                f"{what} from outside the pilot's ISB limits ({'; '.join(outside)}) goes further out on its way in, "
                f"at {100.0 * fraction[n]:.0f}% of the way: " + "; ".join(on_the_way.violations(isb[n]))
            )
    return ApproachCheck(float(fraction[entry]), outside, on_the_way)


# --- building a trajectory -----------------------------------------------------------------


@dataclass
class _Builder:
    """Accumulates pieces and stops while walking the order; runs every check on the way."""

    kind: TrajectoryKind
    waypoints: WaypointSet
    settings: TrajectorySettings
    limits: IsbLimits
    shoulder: Shoulder
    max_speed: FloatArray
    t_s: float = 0.0
    starts: list[FloatArray] = field(default_factory=list)
    coefficients: list[FloatArray] = field(default_factory=list)
    stops: list[Stop] = field(default_factory=list)

    def error(self, what: str) -> TrajectoryError:
        return TrajectoryError(f"{self.kind} trajectory, {what}")

    def add_stop(
        self, q: FloatArray, waypoint: int | None, run: Literal["forward", "reverse"], stop_s: float | None = None
    ) -> None:
        """Stand still at ``q`` for ``stop_s`` (default the settings' ``stop_s``), seconds."""
        block = np.zeros((1, 2 * N_JOINTS, 4))
        block[0, :N_JOINTS, 0] = q
        self.starts.append(np.array([self.t_s]))
        self.coefficients.append(block)
        end = self.t_s + (self.settings.stop_s if stop_s is None else stop_s)
        self.stops.append(Stop(self.t_s, end, waypoint, run, (float(q[0]), float(q[1]), float(q[2]), float(q[3]))))
        self.t_s = end

    def add_move(self, q: FloatArray, dq: FloatArray) -> None:
        """Hermite pieces between the knots of an integrated move (samples at rate_hz)."""
        every = round(self.settings.rate_hz / self.settings.knot_rate_hz)
        qk, dqk = q[::every], dq[::every]
        h = every / self.settings.rate_hz
        n = qk.shape[0] - 1
        self.starts.append(self.t_s + h * np.arange(n))
        self.coefficients.append(hermite_pieces(qk, dqk, h))
        self.t_s += h * n

    def check_waypoint(self, number: int) -> FloatArray:
        """Reachability, ISB limits and distance from singularities of one waypoint; its q."""
        isb = self.waypoints.waypoints[number - 1].isb_rad
        name = self.waypoints.describe(number)
        outside = self.limits.violations(isb)
        if outside:
            raise self.error(f"{name} is outside the pilot's ISB limits: {'; '.join(outside)}")
        try:
            q = self.shoulder.q_from_isb(isb)
        except UnreachablePoseError as exc:
            raise self.error(f"{name}: {exc}") from None
        sigma = self.shoulder.sigma_min(q)
        if sigma < self.settings.min_sigma:
            raise self.error(
                f"{name} is too near a shoulder singularity (smallest singular value of J {sigma:.3f} < {self.settings.min_sigma:.3f})"
            )
        return q

    def check_path(self, q: FloatArray, dq: FloatArray, what: str) -> None:
        """Every sample of a move: joint limits, singularity, ISB limits, joint speed."""
        sh = self.shoulder
        lo, hi = sh.lower_rad - 1e-9, sh.upper_rad + 1e-9
        outside = np.flatnonzero(np.any((q < lo) | (q > hi), axis=1))
        if outside.size:
            n = outside[0]
            joint = int(np.flatnonzero((q[n] < lo) | (q[n] > hi))[0])
            raise self.error(
                f"{what}: joint {joint + 1} reaches {np.degrees(q[n, joint]):.1f} deg at {self._percent(n, q)}, "
                f"outside its limits [{np.degrees(sh.lower_rad[joint]):g}, {np.degrees(sh.upper_rad[joint]):g}] deg"
            )
        sigma = sh.sigma_min(q)
        low = np.flatnonzero(sigma < self.settings.min_sigma)
        if low.size:
            n = low[0]
            raise self.error(
                f"{what}: the path passes near a shoulder singularity (q2 = {np.degrees(q[n, 1]):.1f} deg, "
                f"smallest singular value of J {sigma[n]:.3f} < {self.settings.min_sigma:.3f}) at {self._percent(n, q)}"
            )
        isb = sh.isb_from_q(q)
        inside = self.limits.contains(isb)
        if not np.all(inside):
            n = int(np.flatnonzero(~inside)[0])
            # Where it leaves, and how far out it gets (the first sample outside is barely outside).
            boxed = self.limits.for_box_check(isb)
            excess = np.maximum(self.limits.lower_rad - boxed, boxed - self.limits.upper_rad).clip(min=0).sum(axis=1)
            worst = int(np.argmax(excess))
            raise self.error(
                f"{what}: the path leaves the pilot's ISB limits at {self._percent(n, q)}, "
                f"worst at {self._percent(worst, q)}: " + "; ".join(self.limits.violations(isb[worst]))
            )
        fast = np.abs(dq) > self.max_speed * (1 + 1e-9)
        if np.any(fast):
            n, joint = (int(i[0]) for i in np.nonzero(fast))
            raise self.error(
                f"{what}: joint {joint + 1} would move at {abs(dq[n, joint]):.3f} rad/s, "
                f"above the limit {self.max_speed[joint]:.3f} rad/s"
            )

    @staticmethod
    def _percent(n: int, q: FloatArray) -> str:
        return f"{100.0 * n / max(q.shape[0] - 1, 1):.0f}% of the way"

    def move(
        self, q_start: FloatArray, r3_start: FloatArray, r3_end: FloatArray, elbow_end: float, what: str
    ) -> tuple[FloatArray, FloatArray]:
        """Time, integrate and check one move; stretched once if a joint would be too fast."""
        st = self.settings
        angle = _axis_angle(r3_end @ r3_start.T)[1]
        elbow_change = abs(elbow_end - q_start[3])
        duration = max(
            st.min_move_s,
            MIN_JERK_PEAK * angle / st.shoulder_speed_rad_s,
            MIN_JERK_PEAK * elbow_change / st.elbow_speed_rad_s,
        )
        for _ in range(2):
            duration = math.ceil(duration * st.knot_rate_hz - 1e-9) / st.knot_rate_hz  # whole knot intervals
            q, dq = integrate_move(
                self.shoulder, q_start, r3_start, r3_end, elbow_end, duration, st.rate_hz, st.feedback_gain_per_s
            )
            # Joint speeds scale with 1/duration along the same path: one stretch is enough.
            ratio = float(np.max(np.abs(dq) / (self.max_speed * _SPEED_HEADROOM)))
            if ratio <= 1.0:
                break
            duration *= ratio
        self.check_path(q, dq, what)
        return q, dq


def build_trajectory(
    waypoints: WaypointSet,
    kind: TrajectoryKind,
    settings: TrajectorySettings | None = None,
    limits: IsbLimits | None = None,
    description: RobotDescription | None = None,
) -> ReferenceTrajectory:
    """The training or validation trajectory through ``waypoints``, checked end to end.

    Args:
        waypoints: the waypoint set; its ``training_order`` or ``validation_order`` is used.
        kind: "training" (stops at sub-waypoints) or "validation" (stops at waypoints only).
        settings: default :meth:`TrajectorySettings.for_kind`.
        limits: the pilot's ISB limits; default :class:`hal.isb.IsbLimits` ().
        description: the robot; default the packaged ``hal/daror01.yaml``.

    Raises:
        TrajectoryError: a waypoint is unreachable, outside the joint or ISB limits, or too near a
            singularity, or the path between two waypoints is; the message names the waypoint(s)
            and, for a set read from a file, their lines.
        hal.errors.DescriptionError: the description's neutral pose is unusable.
    """
    settings = TrajectorySettings.for_kind(kind) if settings is None else settings
    limits = IsbLimits() if limits is None else limits
    if description is None:
        description, shoulder = load_description(), default_shoulder()
    else:
        shoulder = Shoulder.from_description(description)
    device_speed = np.asarray(description.limits.max_velocity_rad_s, dtype=float)
    max_speed = np.minimum(device_speed, settings.max_joint_speed_rad_s)
    order = waypoints.order(kind)
    b = _Builder(kind, waypoints, settings, limits, shoulder, max_speed)

    q_of = {number: b.check_waypoint(number) for number in order}  # every pose first: fail before any path work
    r3_of = {
        number: shoulder.shoulder_rotation(waypoints.waypoints[number - 1].isb_rad) @ shoulder.r3_neutral
        for number in order
    }
    elbow_of = {number: waypoints.waypoints[number - 1].isb_rad[3] for number in order}

    q = q_of[order[0]]
    runs: tuple[tuple[Literal["forward", "reverse"], tuple[int, ...]], ...] = (
        ("forward", order),
        ("reverse", order[::-1]),
    )
    for run, sequence in runs:
        b.add_stop(q, sequence[0], run)
        for a, z in itertools.pairwise(sequence):
            parts = _parts(r3_of[a], r3_of[z], elbow_of[a], elbow_of[z], settings.sub_waypoint_spacing_deg)
            axis, angle = _axis_angle(r3_of[z] @ r3_of[a].T)
            r3_from = r3_of[a]
            what = f"{run} run, move from {waypoints.describe(a)} to {waypoints.describe(z)}"
            for k in range(1, parts + 1):
                r3_to = r3_of[z] if k == parts else _rodrigues(axis, angle * k / parts) @ r3_of[a]
                elbow_to = elbow_of[a] + (elbow_of[z] - elbow_of[a]) * k / parts
                step = what if parts == 1 else f"{what} (step {k} of {parts})"
                path, velocity = b.move(q, r3_from, r3_to, elbow_to, step)
                b.add_move(path, velocity)
                q = path[-1].copy()
                b.add_stop(q, z if k == parts else None, run)
                r3_from = r3_to
    return ReferenceTrajectory(
        kind,
        np.concatenate(b.starts),
        np.concatenate(b.coefficients),
        b.t_s,
        tuple(b.stops),
        order,
        settings,
    )


def build_visit_trajectory(
    visits: WaypointSet,
    stops_s: Sequence[float],
    settings: TrajectorySettings,
    limits: IsbLimits | None = None,
    description: RobotDescription | None = None,
) -> ReferenceTrajectory:
    """One run through ``visits`` in their file order, with a stop of ``stops_s[i]`` s at visit ``i + 1``.

    A designed protocol (:mod:`daror_runtime.identification.design`) is a sequence of visits: the
    same pose may appear several times, and a visit with a stop of 0 s is passed through (the
    move ends at rest there and the next one starts: a via pose that sets the direction the
    robot arrives from). Unlike :func:`build_trajectory` there are no sub-waypoints and no reverse
    run. Moves are timed, integrated and checked exactly as there. The trajectory's kind is
    ``training``: every stop gives data (:func:`~daror_runtime.identification.protocol.stationary_points_of_run`);
    a stop's ``waypoint`` is its visit number.

    Raises:
        MoveError: a move leaves the joint or ISB limits, passes near a singularity or is too
            fast; it names both visits (and their lines, for a set read from a file).
        TrajectoryError: a visit is unreachable, outside the limits or near a singularity; fewer
            than two visits; a negative or non-finite stop; no stop at all.
    """
    limits = IsbLimits() if limits is None else limits
    if description is None:
        description, shoulder = load_description(), default_shoulder()
    else:
        shoulder = Shoulder.from_description(description)
    n = len(visits)
    durations = [float(v) for v in stops_s]
    if len(durations) != n:
        raise TrajectoryError(f"{n} visits need {n} stop durations, got {len(durations)}")
    bad = [i + 1 for i, v in enumerate(durations) if not (math.isfinite(v) and v >= 0.0)]
    if bad:
        raise TrajectoryError(f"protocol, visits {bad}: a stop must last 0 s or more")
    if not any(v > 0.0 for v in durations):
        raise TrajectoryError("protocol: no visit has a stop, so the run would give no data")
    device_speed = np.asarray(description.limits.max_velocity_rad_s, dtype=float)
    max_speed = np.minimum(device_speed, settings.max_joint_speed_rad_s)
    b = _Builder("training", visits, settings, limits, shoulder, max_speed)
    q_of = []
    for k in range(1, n + 1):
        try:
            q_of.append(b.check_waypoint(k))
        except TrajectoryError as exc:
            raise MoveError(str(exc), k, k) from None
    r3_of = [shoulder.shoulder_rotation(w.isb_rad) @ shoulder.r3_neutral for w in visits.waypoints]
    q = q_of[0]
    if durations[0] > 0.0:
        b.add_stop(q, 1, "forward", durations[0])
    for k in range(1, n):
        what = f"move from {visits.describe(k)} to {visits.describe(k + 1)}"
        try:
            path, velocity = b.move(q, r3_of[k - 1], r3_of[k], visits.waypoints[k].isb_rad[3], what)
        except TrajectoryError as exc:
            raise MoveError(str(exc), k, k + 1) from None
        b.add_move(path, velocity)
        q = path[-1].copy()
        if durations[k] > 0.0:
            b.add_stop(q, k + 1, "forward", durations[k])
    return ReferenceTrajectory(
        "training",
        np.concatenate(b.starts),
        np.concatenate(b.coefficients),
        b.t_s,
        tuple(b.stops),
        tuple(range(1, n + 1)),
        settings,
    )


def _parts(r3_a: FloatArray, r3_z: FloatArray, elbow_a: float, elbow_z: float, spacing_deg: float | None) -> int:
    """Number of moves a segment is cut into: sub-waypoints at most ``spacing_deg`` apart."""
    if spacing_deg is None:
        return 1
    angle = _axis_angle(r3_z @ r3_a.T)[1]
    largest = max(np.degrees(angle), np.degrees(abs(elbow_z - elbow_a)))
    return max(math.ceil(largest / spacing_deg - 1e-9), 1)
