"""Soft walls: spring-damper torques a few degrees inside the device's joint limits and the pilot's ISB limits.

In compensation (SEA torque control, transparent to the pilot) a limp arm drifts with the model's
error. Without a wall it drifts until the safety monitor faults at the pilot's ISB limit plus its
margin (or at a device joint limit), and the arm may drop with the torque. A soft wall is a
potential added to the torque reference: zero until the arm is ``onset`` inside a limit, then a
spring from there, so a drifting arm slows and stops before the limit; the monitor's fault stays as
the last line. Per tick it is one compiled call (:meth:`SoftWalls.torque`).

Every wall is a distance ``d(q)`` (rad, positive inside the allowed range) and the potential
``V = k/2 (onset - d)^2`` where ``d < onset``. The torque on the joints is ``-dV/dq`` plus a damper
along the same direction::

    p   = onset - d                                  penetration into the wall, rad (> 0: the wall acts)
    tau = (k p + c w(p) max(-d', 0)) grad_q d        Nm on the joints;  d' = grad_q d . dq
    w(p) = min(p / fade, 1)                          the damper fades in with the penetration

so the force is continuous at the onset (zero there, spring and damper alike) and the damper only
resists motion *toward* the limit (``d' < 0``), never an arm leaving the wall.

The walls:

* **device joint limits**, per joint: ``d = q - lower`` and ``d = upper - q``;
* **ISB angles** (after :meth:`SoftWalls.set_limits`), their gradients ``d isb / dq`` analytic
  (``dS/dq_j = [w_j]x S`` for the shoulder rotation ``S`` in thorax coordinates and ``w_j`` joint
  ``j``'s axis there), computed only when an ISB wall is near:

  - elevation: the upper limit; the lower limit only when it is above the onset (elevation is >= 0
    by definition, and a recorded range starts at the hanging arm, 0.001 deg: a wall there would push
    an arm resting by the pilot's side up);
  - axial rotation: both limits, as angular distances (wrapping at +-180 deg); elbow: both limits;
  - horizontal rotation, limited only at or above ``e_free = horizontal_free_below_deg`` of
    elevation: the forbidden region ``{e >= e_free, h outside [h_lo, h_hi]}``. Its distance is
    taken in the plane ``(x, y) = (e_free - e, s v)``, with ``v`` the angular distance of ``h``
    inside its limit and ``s = sin(e_free)`` (the arc the horizontal rotation sweeps there, so a
    degree of ``y`` is about a degree of the arm's motion). The region is the quadrant
    ``x <= 0, y <= 0``: distance to its edge ``y`` above ``e_free`` (a horizontal-rotation wall),
    to its edge ``x`` when ``h`` is out of range below ``e_free`` (an elevation wall that pushes
    the arm *down*: a limp arm rising behind the body), to its (rounded) corner when both are
    outside. One such region per limit, each covering the half of the forbidden arc nearest to its
    limit. Above ``e_free`` the wall therefore starts ``onset / s`` inside the horizontal limit
    (23 deg at the defaults: 8 deg of arm motion at ``e_free``, more higher up). ``s`` is floored
    at :data:`MIN_FREE_SCALE`; with ``e_free`` below the onset the region's wall reaches the
    hanging arm, where the horizontal rotation has no meaning: only the cap bounds it there.

**Continuity.** The SEA torque loop (10 Hz) would chatter on a force step, so the force is
continuous in ``q``:

* at the onset (``p = 0``) by construction;
* across the branches of the horizontal-rotation field: the distance to a convex region is C1
  outside it. The quadrant's corner is rounded with radius ``rho`` (:data:`CORNER_ROUNDING` of the
  onset: the distance is taken to the quadrant shifted ``rho`` inward, minus ``rho``), and inside
  that inner quadrant the depth is the soft minimum ``A B / (A + B)`` of the two penetrations,
  whose gradient meets the outside's continuously on its edges. The one point left where the
  direction of the force is undefined is the corner of the *inner* quadrant (``rho`` beyond both
  edges: at the defaults 4 deg above ``e_free`` and 4 deg / sin(20 deg) = 11.7 deg beyond the
  horizontal limit, past the monitor's 5 deg margin);
* two limits of one angle are two walls whose forces add, so a narrow range has no ridge in its
  middle. What remains discontinuous lies far beyond a limit: the antipode of an angular range's
  middle (a wrapped angle switches which limit is "nearest": 87.5 deg beyond the default
  horizontal limits) and the pole of the elevation (the hanging arm) for an elevation lower limit
  above 0, where the elevation's gradient has no direction.

**Torque cap.** Near the shoulder's singularities (and near the pole, for the horizontal rotation,
whose gradient grows like ``1 / sin(e)``) a few degrees of ISB penetration would map to tens of Nm
on the shoulder joints. The wall torque is therefore clipped per joint to ``max_torque_nm``
(default 5 Nm): above what a wall needs at the monitor's fault (``k (onset + 5 deg)`` = 3.4 Nm at
the defaults), far below the springs' limits (20-30 Nm) and the torque loop's reference limit
(34.7 Nm), so a bad Jacobian can add at most 5 Nm a joint. The clip is continuous; where it acts
the torque is no longer the potential's gradient.

**Stiffness and damping** (the defaults; docs: issue 23, point 5). The walls start ``onset`` = 8 deg
inside the *recorded* limits; the monitor faults at limit + 5 deg.

* A limp arm pushed by a constant model error ``F`` = 1 Nm comes to rest at ``p = F / k``. It must
  rest before the limit + half the margin: ``F / k < 8 + 2.5 deg = 0.183 rad``, so ``k > 5.5 Nm/rad``.
  To keep room for the overshoot of an arm arriving at speed we want it at rest by half the onset:
  ``k >= 1 Nm / 4 deg = 14.3 Nm/rad``.
* The torque loop cannot render a spring whose natural frequency with the link is above ~5 Hz;
  keep ``sqrt(k / I) <= 2 pi 4 Hz = 25.1 rad/s`` for the lightest link (the elbow with the Dummy
  Arm, ``I`` = 0.03 kg m^2): ``k <= 0.03 x 25.1^2 = 18.9 Nm/rad``.
* **k = 15 Nm/rad**: 22.4 rad/s (3.6 Hz) on the elbow, 17.3-7.1 rad/s (2.8-1.1 Hz) on the shoulder
  joints (0.05-0.3 kg m^2). A 1 Nm error rests 3.8 deg into the wall, 4.2 deg before the limit.
* **c = 1.3 Nms/rad**: critical on the elbow, ``2 sqrt(k I) = 2 sqrt(15 x 0.03) = 1.34``; on the
  shoulder joints ``zeta = 1.3 / (2 sqrt(15 I))`` = 0.75-0.31 (a step's overshoot at most 36 %,
  5.2 deg for 1 Nm: still inside the limit), the pilot's own arm and the torque loop's apparent
  impedance damp them further.
* The damper is at full strength 4 deg into the wall (``fade`` = half the onset): where a 1 Nm
  error comes to rest.

On the simulated plant (exo_dummy_arm, limp pilot, tests/daror_runtime/control/test_soft_walls.py) a -1 Nm error on the
elbow brings the arm into the wall at its free drift of 0.59 rad/s; it rests 4.2 deg before the
pilot's limit (the monitor faults without the walls). A 1 Nm error lifting the arm behind the body
stops 4.9 deg below ``e_free`` (without walls: the fault "horizontal rotation -118 deg" at 20 deg).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from daror_runtime.control.base import ControlError, ControlSettingError
from daror_runtime.errors import ConfigurationError, ShapeError
from hal.interface import CheckedSample, Sample
from hal.isb import NEUTRAL_ROTOR3_IN_THORAX, POLE_SIN, IsbLimits, Shoulder
from hal.robot import N_JOINTS, FloatArray, RobotDescription

__all__ = [
    "CORNER_ROUNDING",
    "DEFAULT_DAMPING_NMS_PER_RAD",
    "DEFAULT_MAX_TORQUE_NM",
    "DEFAULT_ONSET_DEG",
    "DEFAULT_STIFFNESS_NM_PER_RAD",
    "MIN_FREE_SCALE",
    "SoftWalls",
]

#: How far inside a limit the walls start (deg).
DEFAULT_ONSET_DEG = 8.0
#: Wall stiffness (Nm/rad) and damping (Nms/rad): see the module's docstring for the arithmetic.
DEFAULT_STIFFNESS_NM_PER_RAD = 15.0
DEFAULT_DAMPING_NMS_PER_RAD = 1.3
#: Largest wall torque per joint (Nm): see "Torque cap" in the module's docstring.
DEFAULT_MAX_TORQUE_NM = 5.0
#: The damper reaches full strength this fraction of the onset into a wall.
DAMPING_FADE = 0.5
#: Radius of the rounded corner of the horizontal-rotation region, as a fraction of the onset.
CORNER_ROUNDING = 0.5
#: Floor of ``s = sin(e_free)``: with a threshold near 0 the horizontal distance would vanish and the
#: region would become an elevation wall at any horizontal rotation.
MIN_FREE_SCALE = math.sin(math.radians(10.0))

# --- layout of the parameter vector the kernel reads (set before the loop, between ticks) ---------
_K, _C, _ONSET, _FADE, _CAP, _ISB_ON, _ROUND = 0, 1, 2, 3, 4, 5, 6
_J_LO = 7  # [7:11] device lower joint limits, rad
_J_HI = 11  # [11:15] device upper joint limits, rad
_E_LO_ON, _E_LO, _E_HI = 15, 16, 17  # elevation: lower wall on (1/0), lower, upper, rad
_A_ON, _A_MID, _A_HALF = 18, 19, 20  # axial rotation: walls on, middle and half-width of the range, rad
_B_LO, _B_HI = 21, 22  # elbow (ISB), rad
_H_ON, _H_MID, _H_HALF, _E_FREE, _SCALE = 23, 24, 25, 26, 27  # the horizontal-rotation region
_N_PARAMS = 28

# --- the vector of results and scratch the kernel writes ----------------------------------------
_ISB = 0  # [0:4] ISB angles of the last call, rad
_GRAD = 4  # [4:13] d(elevation, horizontal, axial)/d(q1, q2, q3), row-major (angle, joint)
_ENERGY = 13  # the walls' potential energy, J
_N_VEC = 14

#: The matrices the kernel works in: base, inter, left, right (constants), then scratch.
_BASE, _INTER, _LEFT, _RIGHT, _M0, _M1, _R3, _AXES, _S = 0, 1, 2, 3, 4, 5, 6, 7, 8
_N_MATS = 9

_TWO_PI = 2.0 * math.pi

_READ_VECTOR = numba.types.Array(numba.float64, 1, "A", readonly=True)
_F1 = numba.float64[::1]
_F3 = numba.float64[:, :, ::1]
#: The kernel's one signature: a sample's q and dq, then the walls' own arrays.
_WALLS_SIGNATURE = (_READ_VECTOR, _READ_VECTOR, _F1, _F3, _F1, _F1)


# --- compiled kernels -----------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _wrap(angle: float) -> float:  # pragma: no cover - compiled
    """``angle`` wrapped to (-pi, pi]."""
    return math.pi - ((math.pi - angle) % _TWO_PI)


@numba.njit(cache=True, inline="always")
def _times_rz(a: FloatArray, angle: float, out: FloatArray) -> None:  # pragma: no cover - compiled
    """out = a @ Rz(angle) for 3x3; ``out`` must not alias ``a``."""
    c, s = math.cos(angle), math.sin(angle)
    for r in range(3):
        out[r, 0] = c * a[r, 0] + s * a[r, 1]
        out[r, 1] = -s * a[r, 0] + c * a[r, 1]
        out[r, 2] = a[r, 2]


@numba.njit(cache=True, inline="always")
def _times(a: FloatArray, b: FloatArray, out: FloatArray) -> None:  # pragma: no cover - compiled
    """out = a @ b for 3x3; ``out`` must not alias ``a`` or ``b``."""
    for r in range(3):
        for c in range(3):
            out[r, c] = a[r, 0] * b[0, c] + a[r, 1] * b[1, c] + a[r, 2] * b[2, c]


@numba.njit(cache=True)
def _isb_angles(q: FloatArray, mats: FloatArray, vec: FloatArray) -> None:  # pragma: no cover - compiled
    """ISB angles of ``q`` into ``vec[_ISB:_ISB+4]``; leaves S and the world joint axes in ``mats``.

    The chain of :class:`hal.isb.Shoulder` (``R3 = B Rz(q1) Ry(60) Rz(q2) Ry(60) Rz(q3)``,
    ``S = left R3 right``), written here into preallocated matrices: the shoulder's own kernel
    allocates its scratch, and the tick must not. Equal to ``Shoulder.isb_single`` to round-off
    (checked when a :class:`SoftWalls` is built, and by the tests).
    """
    m0, m1, axes = mats[_M0], mats[_M1], mats[_AXES]
    _times_rz(mats[_BASE], q[0], m0)  # rotor 1
    for r in range(3):
        axes[r, 0] = m0[r, 2]
    _times(m0, mats[_INTER], m1)  # stator 2
    for r in range(3):
        axes[r, 1] = m1[r, 2]
    _times_rz(m1, q[1], m0)  # rotor 2
    _times(m0, mats[_INTER], m1)  # stator 3
    for r in range(3):
        axes[r, 2] = m1[r, 2]
    _times_rz(m1, q[2], mats[_R3])  # rotor 3
    _times(mats[_LEFT], mats[_R3], m0)
    s = mats[_S]
    _times(m0, mats[_RIGHT], s)
    sin_e = math.sqrt(s[0, 1] * s[0, 1] + s[2, 1] * s[2, 1])
    vec[_ISB] = math.atan2(sin_e, s[1, 1])
    vec[_ISB + 1] = math.atan2(-s[0, 1], -s[2, 1]) if sin_e > POLE_SIN else 0.0
    vec[_ISB + 2] = -math.atan2(s[0, 2] - s[2, 0], s[0, 0] + s[2, 2])
    vec[_ISB + 3] = q[3]


@numba.njit(cache=True)
def _isb_gradients(mats: FloatArray, vec: FloatArray) -> None:  # pragma: no cover - compiled
    """d(elevation, horizontal, axial)/d(q1, q2, q3) into ``vec[_GRAD:_GRAD+9]``, after :func:`_isb_angles`.

    ``dR3/dq_j = [z_j]x R3`` (z_j the world axis of joint j), so ``dS/dq_j = [w_j]x S`` with
    ``w_j = left z_j``; the angles' derivatives follow from their atan2 forms. At the pole (the
    arm straight down) elevation and horizontal rotation have no gradient: 0 there.
    """
    s, axes, left = mats[_S], mats[_AXES], mats[_LEFT]
    v0, v1, v2 = s[0, 1], s[1, 1], s[2, 1]  # S's column 1: the elevation and horizontal rotation
    rho2 = v0 * v0 + v2 * v2
    rho = math.sqrt(rho2)
    n = s[0, 2] - s[2, 0]  # axial rotation = -atan2(n, m)
    m = s[0, 0] + s[2, 2]
    nm2 = n * n + m * m
    for j in range(3):
        w0 = left[0, 0] * axes[0, j] + left[0, 1] * axes[1, j] + left[0, 2] * axes[2, j]
        w1 = left[1, 0] * axes[0, j] + left[1, 1] * axes[1, j] + left[1, 2] * axes[2, j]
        w2 = left[2, 0] * axes[0, j] + left[2, 1] * axes[1, j] + left[2, 2] * axes[2, j]
        # d(column 1) = w x column 1
        dv0 = w1 * v2 - w2 * v1
        dv1 = w2 * v0 - w0 * v2
        dv2 = w0 * v1 - w1 * v0
        if rho > POLE_SIN:
            # e = atan2(rho, v1) with rho^2 + v1^2 = 1; h = atan2(-v0, -v2)
            vec[_GRAD + j] = (v1 * (v0 * dv0 + v2 * dv2) / rho - rho * dv1) / (rho2 + v1 * v1)
            vec[_GRAD + 3 + j] = (v2 * dv0 - v0 * dv2) / rho2
        else:
            vec[_GRAD + j] = 0.0
            vec[_GRAD + 3 + j] = 0.0
        # rows of [w]x S: row 0 = -w2 S[1] + w1 S[2], row 2 = -w1 S[0] + w0 S[1]
        ds00 = -w2 * s[1, 0] + w1 * s[2, 0]
        ds02 = -w2 * s[1, 2] + w1 * s[2, 2]
        ds20 = -w1 * s[0, 0] + w0 * s[1, 0]
        ds22 = -w1 * s[0, 2] + w0 * s[1, 2]
        dn = ds02 - ds20
        dm = ds00 + ds22
        vec[_GRAD + 6 + j] = -(m * dn - n * dm) / nm2 if nm2 > 0.0 else 0.0


@numba.njit(cache=True, inline="always")
def _push(
    d: float, g0: float, g1: float, g2: float, g3: float, dq: FloatArray, params: FloatArray, out: FloatArray
) -> float:  # pragma: no cover - compiled
    """One wall of distance ``d`` (rad) and gradient ``g`` (4 numbers): adds its torque to ``out``.

    Returns its potential energy (J); 0 and nothing added when ``d >= onset``.
    """
    p = params[_ONSET] - d
    if p <= 0.0:
        return 0.0
    rate = g0 * dq[0] + g1 * dq[1] + g2 * dq[2] + g3 * dq[3]  # d', rad/s
    force = params[_K] * p
    if rate < 0.0:  # moving toward the limit: the damper resists, faded in with the penetration
        force -= params[_C] * min(p / params[_FADE], 1.0) * rate
    out[0] += force * g0
    out[1] += force * g1
    out[2] += force * g2
    out[3] += force * g3
    return 0.5 * params[_K] * p * p


@numba.njit(cache=True, inline="always")
def _push_joint(
    d: float, joint: int, sign: float, dq: FloatArray, params: FloatArray, out: FloatArray
) -> float:  # pragma: no cover - compiled
    """A wall on one joint's angle (gradient ``sign`` on ``joint``); see :func:`_push`."""
    p = params[_ONSET] - d
    if p <= 0.0:
        return 0.0
    rate = sign * dq[joint]
    force = params[_K] * p
    if rate < 0.0:
        force -= params[_C] * min(p / params[_FADE], 1.0) * rate
    out[joint] += force * sign
    return 0.5 * params[_K] * p * p


@numba.njit(cache=True, inline="always")
def _region_distance(x: float, y: float, rho: float) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """Signed distance (rad) to the quadrant ``x <= 0, y <= 0`` with its corner rounded by ``rho``, and its gradient.

    Outside the inner quadrant ``x, y <= -rho``: Euclidean distance to it, minus ``rho`` (C1).
    Inside it: ``-rho`` minus the soft minimum ``A B / (A + B)`` of the two depths, whose gradient
    ``(B^2, A^2) / (A + B)^2`` meets the outside's on each edge.
    """
    a = x + rho
    b = y + rho
    if a > 0.0 or b > 0.0:
        ap = a if a > 0.0 else 0.0
        bp = b if b > 0.0 else 0.0
        dist = math.sqrt(ap * ap + bp * bp)
        return dist - rho, ap / dist, bp / dist
    depth_a, depth_b = -a, -b
    total = depth_a + depth_b
    if total <= 0.0:  # exactly on the inner corner: no direction; take the diagonal
        return -rho, 0.25, 0.25
    return -rho - depth_a * depth_b / total, (depth_b / total) ** 2, (depth_a / total) ** 2


@numba.njit(cache=True)
def _region(
    side: float, h_dist: float, dq: FloatArray, params: FloatArray, vec: FloatArray, out: FloatArray
) -> float:  # pragma: no cover - compiled
    """The horizontal-rotation region of one limit (``side`` +1 lower, -1 upper); ``h_dist`` the
    angular distance of h inside that limit (rad). Adds its torque to ``out``; returns its energy (J)."""
    scale = params[_SCALE]
    x = params[_E_FREE] - vec[_ISB]
    d, gx, gy = _region_distance(x, scale * h_dist, params[_ROUND])
    if d >= params[_ONSET]:
        return 0.0
    # grad_q d = gx grad(e_free - e) + gy s grad(side h)
    hy = gy * scale * side
    g0 = -gx * vec[_GRAD] + hy * vec[_GRAD + 3]
    g1 = -gx * vec[_GRAD + 1] + hy * vec[_GRAD + 4]
    g2 = -gx * vec[_GRAD + 2] + hy * vec[_GRAD + 5]
    return _push(d, g0, g1, g2, 0.0, dq, params, out)


@numba.njit(
    numba.int64(*_WALLS_SIGNATURE),
    cache=True,
    nogil=True,
)
def _walls_kernel(
    q: FloatArray, dq: FloatArray, params: FloatArray, mats: FloatArray, vec: FloatArray, out: FloatArray
) -> int:  # pragma: no cover - compiled
    """The walls' torque (4,) Nm into ``out``; returns 1 if a wall acts (some penetration > 0), 0 if
    none, -1 for a wrong shape, -2 for a non-finite input (``out`` untouched then). Allocates nothing."""
    if q.shape[0] != 4 or dq.shape[0] != 4 or out.shape[0] != 4:
        return -1
    for j in range(4):
        if not (math.isfinite(q[j]) and math.isfinite(dq[j])):
            return -2
    onset = params[_ONSET]
    near = False
    for j in range(4):
        if q[j] - params[_J_LO + j] < onset or params[_J_HI + j] - q[j] < onset:
            near = True
    isb_near = False
    a_mid = 0.0
    h_mid = 0.0
    if params[_ISB_ON] > 0.0:
        _isb_angles(q, mats, vec)
        e = vec[_ISB]
        if params[_E_HI] - e < onset or (params[_E_LO_ON] > 0.0 and e - params[_E_LO] < onset):
            isb_near = True
        if params[_A_ON] > 0.0:
            a_mid = _wrap(vec[_ISB + 2] - params[_A_MID])
            if params[_A_HALF] - abs(a_mid) < onset:
                isb_near = True
        if q[3] - params[_B_LO] < onset or params[_B_HI] - q[3] < onset:
            isb_near = True
        if params[_H_ON] > 0.0:
            h_mid = _wrap(vec[_ISB + 1] - params[_H_MID])
            # quick test before any gradient: a region's distance is at least x and at least its y
            # (d >= max(x, y) outside the inner quadrant, and y >= s v for both limits' regions)
            if params[_E_FREE] - e < onset and params[_SCALE] * (params[_H_HALF] - abs(h_mid)) < onset:
                isb_near = True
    if not (near or isb_near):
        for j in range(4):
            out[j] = 0.0
        vec[_ENERGY] = 0.0
        return 0
    for j in range(4):
        out[j] = 0.0
    energy = 0.0
    for j in range(4):
        energy += _push_joint(q[j] - params[_J_LO + j], j, 1.0, dq, params, out)
        energy += _push_joint(params[_J_HI + j] - q[j], j, -1.0, dq, params, out)
    if isb_near:
        _isb_gradients(mats, vec)
        e = vec[_ISB]
        ge0, ge1, ge2 = vec[_GRAD], vec[_GRAD + 1], vec[_GRAD + 2]
        energy += _push(params[_E_HI] - e, -ge0, -ge1, -ge2, 0.0, dq, params, out)
        if params[_E_LO_ON] > 0.0:
            energy += _push(e - params[_E_LO], ge0, ge1, ge2, 0.0, dq, params, out)
        if params[_A_ON] > 0.0:
            ga0, ga1, ga2 = vec[_GRAD + 6], vec[_GRAD + 7], vec[_GRAD + 8]
            energy += _push(a_mid + params[_A_HALF], ga0, ga1, ga2, 0.0, dq, params, out)
            energy += _push(params[_A_HALF] - a_mid, -ga0, -ga1, -ga2, 0.0, dq, params, out)
        energy += _push(q[3] - params[_B_LO], 0.0, 0.0, 0.0, 1.0, dq, params, out)
        energy += _push(params[_B_HI] - q[3], 0.0, 0.0, 0.0, -1.0, dq, params, out)
        if params[_H_ON] > 0.0:
            # one region per limit, each the half of the forbidden arc nearest to it
            energy += _region(1.0, h_mid + params[_H_HALF], dq, params, vec, out)
            energy += _region(-1.0, params[_H_HALF] - h_mid, dq, params, vec, out)
    cap = params[_CAP]
    for j in range(4):
        out[j] = min(max(out[j], -cap), cap)
    vec[_ENERGY] = energy
    return 1 if energy > 0.0 else 0


@numba.njit(cache=True)
def _isb_and_gradients(q: FloatArray, mats: FloatArray, vec: FloatArray) -> None:  # pragma: no cover - compiled
    _isb_angles(q, mats, vec)
    _isb_gradients(mats, vec)


# --- the object the modes own -----------------------------------------------------------------------


def _setting(name: str, value: float, zero_allowed: bool = False) -> float:
    """``value`` as a float, refused unless finite and positive (or zero, if ``zero_allowed``)."""
    wanted = "a finite number >= 0" if zero_allowed else "a positive finite number"
    if isinstance(value, bool):  # True would pass float() as 1.0
        raise ControlSettingError(f"soft walls: {name} must be {wanted}, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ControlSettingError(f"soft walls: {name} must be {wanted}, got {value!r}") from None
    if not (math.isfinite(number) and (number > 0.0 or (zero_allowed and number == 0.0))):
        raise ControlSettingError(f"soft walls: {name} must be {wanted}, got {value!r}")
    return number


class SoftWalls:
    """Spring-damper walls a few degrees inside the device's joint limits and the pilot's ISB limits.

    Built once before the loop; :meth:`set_limits` between ticks; :meth:`torque` in the tick (one
    compiled call, nothing allocated). The module's docstring has the walls, their continuity,
    the cap and the arithmetic behind the defaults.

    Args:
        description: the robot (its device joint limits, ``lower_limits_rad``/``upper_limits_rad``).
        shoulder: the shoulder's kinematics and ISB convention (``hal.isb.Shoulder``) of that robot.
        onset_deg: how far inside each limit a wall starts, deg.
        stiffness_nm_per_rad: the walls' spring, Nm per rad of penetration.
        damping_nms_per_rad: the walls' damper at full strength (``DAMPING_FADE`` of the onset in), Nms/rad.
        max_torque_nm: the wall torque is clipped to this per joint, Nm.

    Raises:
        ControlSettingError: a setting that is not a positive finite number.
        ConfigurationError: the walls' kinematics disagree with ``shoulder.isb_single`` (the ISB
            convention changed under this module).
    """

    def __init__(
        self,
        description: RobotDescription,
        shoulder: Shoulder,
        onset_deg: float = DEFAULT_ONSET_DEG,
        stiffness_nm_per_rad: float = DEFAULT_STIFFNESS_NM_PER_RAD,
        damping_nms_per_rad: float = DEFAULT_DAMPING_NMS_PER_RAD,
        max_torque_nm: float = DEFAULT_MAX_TORQUE_NM,
    ) -> None:
        onset_rad = math.radians(_setting("onset", onset_deg))
        self.onset_rad = onset_rad
        self.stiffness_nm_per_rad = _setting("stiffness", stiffness_nm_per_rad)
        self.damping_nms_per_rad = _setting("damping", damping_nms_per_rad, zero_allowed=True)  # 0: a pure spring
        self.max_torque_nm = _setting("torque cap", max_torque_nm)
        self._params = np.zeros(_N_PARAMS)
        p = self._params
        p[_K] = self.stiffness_nm_per_rad
        p[_C] = self.damping_nms_per_rad
        p[_ONSET] = onset_rad
        p[_FADE] = DAMPING_FADE * onset_rad
        p[_CAP] = self.max_torque_nm
        p[_ROUND] = CORNER_ROUNDING * onset_rad
        p[_J_LO : _J_LO + N_JOINTS] = description.lower_limits_rad
        p[_J_HI : _J_HI + N_JOINTS] = description.upper_limits_rad
        self._mats = np.zeros((_N_MATS, 3, 3))
        self._mats[_BASE] = shoulder.kinematics.base_rotation
        self._mats[_INTER] = shoulder.kinematics.inter_rotation
        self._mats[_LEFT] = shoulder.thorax_in_world.T
        self._mats[_RIGHT] = NEUTRAL_ROTOR3_IN_THORAX.T
        self._vec = np.zeros(_N_VEC)
        self._scratch = np.zeros(N_JOINTS)
        self.limits: IsbLimits | None = None
        self._check_convention(shoulder)
        # Load the compiled kernel now (from numba's cache), not in the first tick.
        zeros = np.zeros(N_JOINTS)
        _walls_kernel(shoulder.q_neutral, zeros, self._params, self._mats, self._vec, self._scratch)
        #: The tick's walls torque (:meth:`torque_for`), Nm; overwritten by every call.
        self._tick_out = np.zeros(N_JOINTS)
        # A CheckedSample's arrays go to this entry point (no type dispatch: hal.kernels); the rest
        # of the arguments are the walls' own arrays, of the signature's types by construction. The
        # kernel is compiled eagerly for its one signature (numba then refuses Dispatcher.compile).
        self._entry = _walls_kernel.overloads[_WALLS_SIGNATURE].entry_point

    def _check_convention(self, shoulder: Shoulder) -> None:
        """The walls' own kinematics (allocation-free) must give the shoulder's ISB angles."""
        poses = [
            shoulder.q_neutral + np.radians(offset) for offset in ([0.0] * 4, [20, -30, 40, 10], [-30, 20, -50, 60])
        ]
        for q in poses:
            _isb_and_gradients(np.ascontiguousarray(q, dtype=float), self._mats, self._vec)
            expected = shoulder.isb_single(np.ascontiguousarray(q, dtype=float))
            error = np.abs(_wrapped(self._vec[_ISB : _ISB + N_JOINTS] - expected))
            # the horizontal rotation is arbitrary at the pole: compare it only where it is defined
            if expected[0] < 1e-6:
                error[1] = 0.0
            if not np.all(error < 1e-9):
                raise ConfigurationError(
                    f"soft walls: ISB angles {self._vec[_ISB : _ISB + N_JOINTS].tolist()} differ from the "
                    f"shoulder's {expected.tolist()} at q = {q.tolist()}"
                )

    def set_limits(self, isb: IsbLimits | None) -> None:
        """Walls at the pilot's ISB limits from the next tick on (call between ticks); None: device joint limits only.

        The new parameters are built aside and swapped in with one assignment: a tick never sees
        half of them.

        Args:
            isb: the pilot's recorded limits; the walls start ``onset`` inside them.
        """
        p = self._params.copy()
        if isb is None:
            p[_ISB_ON] = 0.0
        else:
            # A lower elevation limit within the onset of 0 is the hanging arm's (a recorded range starts at
            # 0.001 deg): a wall there would push an arm resting by the pilot's side up. Only a limit clear of
            # the pole (a shoulder that cannot hang straight) gets a wall.
            p[_E_LO_ON] = 1.0 if isb.elevation.lower_rad > p[_ONSET] else 0.0
            p[_E_LO] = isb.elevation.lower_rad
            p[_E_HI] = isb.elevation.upper_rad
            a_lo, a_hi = isb.axial_rotation.lower_rad, isb.axial_rotation.upper_rad
            # A range of the whole circle has no limit to wall (and no forbidden arc to halve).
            p[_A_ON] = 1.0 if a_hi - a_lo < 2.0 * math.pi - 1e-9 else 0.0
            p[_A_MID] = 0.5 * (a_lo + a_hi)
            p[_A_HALF] = 0.5 * (a_hi - a_lo)
            p[_B_LO] = isb.elbow.lower_rad
            p[_B_HI] = isb.elbow.upper_rad
            h_lo, h_hi = isb.horizontal_rotation.lower_rad, isb.horizontal_rotation.upper_rad
            p[_H_ON] = 1.0 if h_hi - h_lo < 2.0 * math.pi - 1e-9 else 0.0
            p[_H_MID] = 0.5 * (h_lo + h_hi)
            p[_H_HALF] = 0.5 * (h_hi - h_lo)
            p[_E_FREE] = isb.horizontal_free_below_rad
            p[_SCALE] = max(math.sin(isb.horizontal_free_below_rad), MIN_FREE_SCALE)
            p[_ISB_ON] = 1.0
        self._params = p
        self.limits = isb

    def torque(self, q_rad: FloatArray, dq_rad_s: FloatArray, out: FloatArray) -> bool:
        """The walls' torque (4,) Nm on the joints, written into ``out``; True if any wall acts.

        One compiled call, measured by the tests: about 0.7 us when no wall is near (the common
        case), 1 us near one. The kernel allocates nothing (numba's unboxing of the array arguments
        makes the memory records every compiled call makes). ``out`` is all zeros when no wall acts.

        Args:
            q_rad: joint angles (4,) float64, rad.
            dq_rad_s: joint velocities (4,) float64, rad/s.
            out: where the torque goes, (4,) float64 C-contiguous, Nm.

        Raises:
            ShapeError: an array without four elements, or not a float64 vector.
            ControlError: a non-finite angle or velocity (``out`` is left as it was).
        """
        try:
            status = _walls_kernel(q_rad, dq_rad_s, self._params, self._mats, self._vec, out)
        except TypeError:  # numba found no match: not float64 vectors, or ``out`` not writable and contiguous
            raise ShapeError(
                f"soft walls need float64 vectors (out writable and contiguous), got "
                f"{type(q_rad).__name__}, {type(dq_rad_s).__name__}, {type(out).__name__}"
            ) from None
        if status == 1:
            return True
        if status == 0:
            return False
        if status == -1:
            raise ShapeError(
                f"soft walls need q, dq and out of shape ({N_JOINTS},), got "
                f"{np.shape(q_rad)}, {np.shape(dq_rad_s)}, {np.shape(out)}"
            )
        raise ControlError(f"soft walls: non-finite input q = {list(q_rad)}, dq = {list(dq_rad_s)}")

    def torque_for(self, sample: Sample) -> FloatArray | None:
        """The walls' torque (4,) Nm for ``sample``'s angles and speeds; None if no wall acts (the common case).

        The tick's call: a :class:`~hal.interface.CheckedSample` goes straight to the compiled entry
        point (about 0.3 us less than :meth:`torque`). The array returned is the walls' own, overwritten
        by the next call: add it, do not keep it.

        Raises:
            ShapeError, ControlError: as :meth:`torque`.
        """
        out = self._tick_out
        if type(sample) is CheckedSample:
            status = self._entry(sample.q_rad, sample.dq_rad_s, self._params, self._mats, self._vec, out)
            if status == 0:
                return None
            if status == 1:
                return out
        # anything else (or a non-finite reading): the checked path says what is wrong
        return out if self.torque(sample.q_rad, sample.dq_rad_s, out) else None

    # --- analysis and tests (not for the tick: these allocate, and use scratch of their own) --------

    def energy_j(self, q_rad: FloatArray) -> float:
        """The walls' potential energy at ``q_rad`` (4,) rad, J (the spring part of :meth:`torque` is its negative gradient).

        Raises:
            ShapeError: ``q_rad`` is not four finite angles.
        """
        q = np.ascontiguousarray(q_rad, dtype=float)
        vec = np.zeros(_N_VEC)
        if (
            q.shape != (N_JOINTS,)
            or _walls_kernel(q, np.zeros(N_JOINTS), self._params, self._mats.copy(), vec, np.zeros(N_JOINTS)) < 0
        ):
            raise ShapeError(f"soft walls need four finite angles, got {q.tolist()}")
        return float(vec[_ENERGY])

    def isb_and_jacobian(self, q_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The ISB angles (4,) rad at ``q_rad`` and their Jacobian d(isb)/dq (4, 4), as the walls compute them.

        Raises:
            ShapeError: ``q_rad`` is not of shape (4,).
        """
        q = np.ascontiguousarray(q_rad, dtype=float)
        if q.shape != (N_JOINTS,):
            raise ShapeError(f"expected q of shape ({N_JOINTS},), got {q.shape}")
        vec = np.zeros(_N_VEC)
        _isb_and_gradients(q, self._mats.copy(), vec)
        jac = np.zeros((N_JOINTS, N_JOINTS))
        jac[:3, :3] = vec[_GRAD : _GRAD + 9].reshape(3, 3)
        jac[3, 3] = 1.0
        return vec[_ISB : _ISB + N_JOINTS].copy(), jac


def _wrapped(angle: FloatArray) -> FloatArray:
    """Angles wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - angle, 2.0 * np.pi)
