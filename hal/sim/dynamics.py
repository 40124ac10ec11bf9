"""Numba kernels of the dynamic plant: a 4-DoF rigid-body chain with a series elastic actuator per joint.

Link side (joint space, gearbox output)::

    M(q) q'' + c(q, q') + g(q) = tau_s + tau_ext - b_l q'
    tau_s = k (theta - q) + d_s (theta' - q')                 spring torque acting on the link

Motor side, reflected to the gearbox output::

    J_m theta'' = sat(tau_m) - tau_s - b_m theta' - tau_c tanh(theta' / eps)

``g(q) = dV/dq`` is the holding torque: gravity of every body (links and Dummy Arm segments) plus
the pull-only elbow springs. ``c(q, q')`` (Coriolis and centrifugal) comes from a recursive
Newton-Euler pass with ``q'' = 0`` in the world frame; ``M(q)`` from the bodies' CoM linear
Jacobians ``z_j x (p - o_j)`` and angular Jacobians ``z_j``. Joints 1-3 turn about axes through
the shoulder's centre of rotation (the world origin), joint 4 about an axis through the elbow
``o_4 = 0R_3r delta``. Gravity is ``(0, -g, 0)`` in the world frame (``y`` up).

Everything a kernel needs is packed into flat ``float64`` arrays, because every array argument
of a numba call costs ~0.1 us of dispatch and one RK4 step must take a few microseconds:

* the parameter vector ``p`` (layout ``P_*`` below, built by :func:`pack_parameters`),
* the state ``x = [q, theta, q', theta']`` of shape (16,),
* the inputs ``u = [tau_m, tau_ext]`` of shape (8,), held constant over a step,
* a scratch array ``work`` of :data:`WORK_SIZE` (allocating inside a kernel costs more than the
  arithmetic).

Bodies are one composite rigid body per rotor frame (mass, CoM and full inertia tensor about
the CoM in that rotor frame); :mod:`hal.sim.plant` combines links and Dummy Arm segments.

The kernels of the simulated drives (command FIFO, encoders, velocity filter; used by
:mod:`hal.sim.backend`) and of the simulated pilot (:mod:`hal.sim.pilot`) are at the end of
this file, for the reason given there.
Units: rad, rad/s, Nm, kg, m, kg m^2, s.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numba import njit, types

from hal.errors import DescriptionError, ShapeError
from hal.robot import N_JOINTS, FloatArray

#: How every kernel is compiled: cached on disk; division by zero gives inf/nan (numpy's error
#: model) instead of a Python exception check in the inner loop, and the step's finiteness check
#: catches it. No fast-math flag at all, not even fused multiply-add: where LLVM fuses depends on
#: what it inlined, which differs between a kernel compiled in this process and one loaded from
#: numba's cache, so a contracted plant recorded different rows in a fresh and a cached run
#: (docs/simulation.md S17); "no NaN/inf" would also delete the finiteness checks.
_kernel = njit(cache=True, error_model="numpy")

#: Length of the state vector ``[q, theta, q', theta']``.
N_STATE = 4 * N_JOINTS
#: Length of the input vector ``[tau_m, tau_ext]``.
N_INPUT = 2 * N_JOINTS

# --- parameter vector layout --------------------------------------------------------------------
P_BASE_ROTATION = 0  # 0R_1s, 3x3 row-major
P_INTER_ROTATION = 9  # Ry(60 deg): rotor 1 -> stator 2 and rotor 2 -> stator 3, 3x3 row-major
P_ELBOW_OFFSET = 18  # delta in rotor-3 coordinates, 3
P_GRAVITY = 21  # g, m/s^2 (gravity points along -y)
P_BODIES = 22  # 4 bodies of BODY_SIZE each
BODY_SIZE = 13  # mass, CoM (3, rotor frame), inertia about the CoM (9, rotor frame, row-major)
P_STIFFNESS = P_BODIES + N_JOINTS * BODY_SIZE  # k, 4
P_SPRING_DAMPING = P_STIFFNESS + N_JOINTS  # d_s, 4
P_LINK_VISCOUS = P_SPRING_DAMPING + N_JOINTS  # b_l, 4
P_MOTOR_INERTIA = P_LINK_VISCOUS + N_JOINTS  # J_m, 4
P_MOTOR_VISCOUS = P_MOTOR_INERTIA + N_JOINTS  # b_m, 4
P_MOTOR_COULOMB = P_MOTOR_VISCOUS + N_JOINTS  # tau_c, 4
P_MAX_MOTOR_TORQUE = P_MOTOR_COULOMB + N_JOINTS  # saturation, 4
P_COULOMB_SMOOTHING = P_MAX_MOTOR_TORQUE + N_JOINTS  # eps, rad/s
P_INVERSE_MOTOR_INERTIA = P_COULOMB_SMOOTHING + 1  # 1 / J_m, 4 (multiplying is cheaper than dividing)
P_INVERSE_SMOOTHING = P_INVERSE_MOTOR_INERTIA + N_JOINTS  # 1 / eps
P_N_SPRINGS = P_INVERSE_SMOOTHING + 1
P_SPRINGS = P_N_SPRINGS + 1  # MAX_SPRINGS of SPRING_SIZE each
SPRING_SIZE = 5  # joint index 0-3, stiffness, slack angle, +1 resists flexion / -1 extension, damping
# The Dummy Arm's elbow springs (2), an end stop at each end of every joint (8), a pair per
# undeclared two-sided joint spring (up to 4 pairs) and the arm's rest support when one is placed
# (up to 4: a pilot's lap, an armrest); unused slots cost nothing (the kernels loop over
# P_N_SPRINGS), and springs are the last block, so no other offset moves.
MAX_SPRINGS = 24
PARAM_SIZE = P_SPRINGS + MAX_SPRINGS * SPRING_SIZE

# --- scratch layout -----------------------------------------------------------------------------
W_ROT = 0  # rotor rotations, 4x3x3
W_ELBOW = 36  # o_4, 3
W_COM = 39  # world CoM of each body, 4x3
W_INERTIA = 51  # world inertia tensor of each body about its CoM, 4x3x3
W_MASS = 87  # M(q), 4x4
W_BIAS = 103  # c + g, 4
W_RHS = 107  # right-hand side, then q'', 4
W_CHOL = 111  # Cholesky factor, 4x4
W_FORCE = 127  # m (a - gravity) of each body, 4x3
W_MOMENT = 139  # I alpha + w x I w of each body, 4x3
W_TEMP = 151  # 3x3 scratch and a 3-vector, 12
W_K1 = 163  # RK4 stage derivatives, 4 x 16
W_K2 = W_K1 + N_STATE
W_K3 = W_K2 + N_STATE
W_K4 = W_K3 + N_STATE
W_XT = W_K4 + N_STATE  # RK4 stage state, 16
WORK_SIZE = W_XT + N_STATE


def new_work() -> FloatArray:
    """A scratch array for the kernels (one per plant; kernels are not re-entrant on it)."""
    return np.zeros(WORK_SIZE)


def pack_parameters(
    base_rotation: FloatArray,
    inter_rotation: FloatArray,
    elbow_offset_m: FloatArray,
    gravity_mps2: float,
    body_mass_kg: FloatArray,
    body_com_m: FloatArray,
    body_inertia_kgm2: FloatArray,
    stiffness_nm_per_rad: FloatArray,
    spring_damping_nms_per_rad: FloatArray,
    link_viscous_nms_per_rad: FloatArray,
    motor_inertia_kgm2: FloatArray,
    motor_viscous_nms_per_rad: FloatArray,
    motor_coulomb_nm: FloatArray,
    max_motor_torque_nm: FloatArray,
    coulomb_smoothing_rad_s: float,
    springs: list[tuple[float, ...]],
) -> FloatArray:
    """The parameter vector ``p`` of the kernels.

    Args:
        base_rotation, inter_rotation: (3, 3) constant rotations of the chain (Eq. 2.9, 2.14).
        elbow_offset_m: (3,) delta, rotor 3 to the elbow axis (Eq. 2.15).
        gravity_mps2: magnitude of gravity; it points along world -y.
        body_mass_kg: (4,) composite mass per rotor frame.
        body_com_m: (4, 3) composite CoM in its rotor frame (from that frame's origin).
        body_inertia_kgm2: (4, 3, 3) inertia tensor about the composite CoM, rotor-frame axes.
        stiffness_nm_per_rad .. max_motor_torque_nm: (4,) drive-train constants per joint.
        coulomb_smoothing_rad_s: ``eps`` of ``tau_c tanh(theta' / eps)``.
        springs: pull-only joint springs as (joint index 0-3, stiffness, slack angle rad,
            +1 resists flexion / -1 resists extension[, damping Nms/rad]); the damping acts only
            while the spring is stretched and never pulls (mechanical end stops are such springs).

    Raises:
        ShapeError: an array of the wrong shape.
        DescriptionError: more than :data:`MAX_SPRINGS` springs, or a spring on a joint outside 0-3.
    """
    expected = {
        "base_rotation": (base_rotation, (3, 3)),
        "inter_rotation": (inter_rotation, (3, 3)),
        "elbow_offset_m": (elbow_offset_m, (3,)),
        "body_mass_kg": (body_mass_kg, (N_JOINTS,)),
        "body_com_m": (body_com_m, (N_JOINTS, 3)),
        "body_inertia_kgm2": (body_inertia_kgm2, (N_JOINTS, 3, 3)),
        "stiffness_nm_per_rad": (stiffness_nm_per_rad, (N_JOINTS,)),
        "spring_damping_nms_per_rad": (spring_damping_nms_per_rad, (N_JOINTS,)),
        "link_viscous_nms_per_rad": (link_viscous_nms_per_rad, (N_JOINTS,)),
        "motor_inertia_kgm2": (motor_inertia_kgm2, (N_JOINTS,)),
        "motor_viscous_nms_per_rad": (motor_viscous_nms_per_rad, (N_JOINTS,)),
        "motor_coulomb_nm": (motor_coulomb_nm, (N_JOINTS,)),
        "max_motor_torque_nm": (max_motor_torque_nm, (N_JOINTS,)),
    }
    for name, (value, shape) in expected.items():
        if np.shape(value) != shape:
            raise ShapeError(f"{name}: expected shape {shape}, got {np.shape(value)}")
    if len(springs) > MAX_SPRINGS:
        raise DescriptionError(f"{len(springs)} joint springs; the dynamic plant supports at most {MAX_SPRINGS}")
    p = np.zeros(PARAM_SIZE)
    p[P_BASE_ROTATION : P_BASE_ROTATION + 9] = np.asarray(base_rotation, dtype=float).ravel()
    p[P_INTER_ROTATION : P_INTER_ROTATION + 9] = np.asarray(inter_rotation, dtype=float).ravel()
    p[P_ELBOW_OFFSET : P_ELBOW_OFFSET + 3] = elbow_offset_m
    p[P_GRAVITY] = gravity_mps2
    for i in range(N_JOINTS):
        base = P_BODIES + i * BODY_SIZE
        p[base] = body_mass_kg[i]
        p[base + 1 : base + 4] = body_com_m[i]
        p[base + 4 : base + 13] = np.asarray(body_inertia_kgm2[i], dtype=float).ravel()
    p[P_STIFFNESS : P_STIFFNESS + N_JOINTS] = stiffness_nm_per_rad
    p[P_SPRING_DAMPING : P_SPRING_DAMPING + N_JOINTS] = spring_damping_nms_per_rad
    p[P_LINK_VISCOUS : P_LINK_VISCOUS + N_JOINTS] = link_viscous_nms_per_rad
    p[P_MOTOR_INERTIA : P_MOTOR_INERTIA + N_JOINTS] = motor_inertia_kgm2
    p[P_MOTOR_VISCOUS : P_MOTOR_VISCOUS + N_JOINTS] = motor_viscous_nms_per_rad
    p[P_MOTOR_COULOMB : P_MOTOR_COULOMB + N_JOINTS] = motor_coulomb_nm
    p[P_MAX_MOTOR_TORQUE : P_MAX_MOTOR_TORQUE + N_JOINTS] = max_motor_torque_nm
    p[P_COULOMB_SMOOTHING] = coulomb_smoothing_rad_s
    p[P_INVERSE_MOTOR_INERTIA : P_INVERSE_MOTOR_INERTIA + N_JOINTS] = 1.0 / np.asarray(motor_inertia_kgm2, dtype=float)
    p[P_INVERSE_SMOOTHING] = 1.0 / coulomb_smoothing_rad_s
    p[P_N_SPRINGS] = len(springs)
    for s, spring in enumerate(springs):
        joint, stiffness, slack_rad, sign = spring[:4]
        damping = spring[4] if len(spring) > 4 else 0.0
        if not 0 <= joint < N_JOINTS:
            raise DescriptionError(f"joint spring on joint index {joint}; joint indices are 0-{N_JOINTS - 1}")
        base = P_SPRINGS + s * SPRING_SIZE
        p[base : base + SPRING_SIZE] = (joint, stiffness, slack_rad, 1.0 if sign > 0 else -1.0, damping)
    return p


# --- kinematics -----------------------------------------------------------------------------------


@_kernel
def kinematics(x: FloatArray, p: FloatArray, work: FloatArray) -> None:
    """Rotor rotations, elbow position, world CoMs and world inertias for ``q = x[0:4]`` into ``work``.

    Same chain as :class:`hal.robot.Kinematics`: ``0R_1r = 0R_1s Rz(q1)``, ``0R_ir = 0R_(i-1)r
    Ry(60 deg) Rz(qi)`` for i = 2, 3, ``0R_4r = 0R_3r Rz(q4)``.
    """
    # Indices instead of slices throughout: a view costs reference counting in the inner loop.
    rot = W_ROT
    for i in range(N_JOINTS):
        cq = math.cos(x[i])
        sq = math.sin(x[i])
        for r in range(3):
            # Row r of the stator rotation (world orientation before the joint turns).
            if i == 0:
                s0 = p[P_BASE_ROTATION + 3 * r]
                s1 = p[P_BASE_ROTATION + 3 * r + 1]
                s2 = p[P_BASE_ROTATION + 3 * r + 2]
            elif i == 3:
                s0 = work[rot + 18 + 3 * r]
                s1 = work[rot + 18 + 3 * r + 1]
                s2 = work[rot + 18 + 3 * r + 2]
            else:
                prev = rot + 9 * (i - 1) + 3 * r
                a0 = work[prev]
                a1 = work[prev + 1]
                a2 = work[prev + 2]
                s0 = a0 * p[P_INTER_ROTATION] + a1 * p[P_INTER_ROTATION + 3] + a2 * p[P_INTER_ROTATION + 6]
                s1 = a0 * p[P_INTER_ROTATION + 1] + a1 * p[P_INTER_ROTATION + 4] + a2 * p[P_INTER_ROTATION + 7]
                s2 = a0 * p[P_INTER_ROTATION + 2] + a1 * p[P_INTER_ROTATION + 5] + a2 * p[P_INTER_ROTATION + 8]
            out = rot + 9 * i + 3 * r
            work[out] = s0 * cq + s1 * sq
            work[out + 1] = -s0 * sq + s1 * cq
            work[out + 2] = s2
    # Elbow axis point o_4 = 0R_3r delta.
    for r in range(3):
        work[W_ELBOW + r] = (
            work[rot + 18 + 3 * r] * p[P_ELBOW_OFFSET]
            + work[rot + 18 + 3 * r + 1] * p[P_ELBOW_OFFSET + 1]
            + work[rot + 18 + 3 * r + 2] * p[P_ELBOW_OFFSET + 2]
        )
    for i in range(N_JOINTS):
        base = P_BODIES + i * BODY_SIZE
        rot_i = W_ROT + 9 * i
        for r in range(3):
            work[W_COM + 3 * i + r] = (
                work[rot_i + 3 * r] * p[base + 1]
                + work[rot_i + 3 * r + 1] * p[base + 2]
                + work[rot_i + 3 * r + 2] * p[base + 3]
                + (work[W_ELBOW + r] if i == 3 else 0.0)
            )
        # World inertia R I R^T about the CoM, in two 3x3 products (T = R I, then T R^T, symmetric).
        for r in range(3):
            for c in range(3):
                work[W_TEMP + 3 * r + c] = (
                    work[rot_i + 3 * r] * p[base + 4 + c]
                    + work[rot_i + 3 * r + 1] * p[base + 7 + c]
                    + work[rot_i + 3 * r + 2] * p[base + 10 + c]
                )
        inertia = W_INERTIA + 9 * i
        for r in range(3):
            for c in range(r, 3):
                value = (
                    work[W_TEMP + 3 * r] * work[rot_i + 3 * c]
                    + work[W_TEMP + 3 * r + 1] * work[rot_i + 3 * c + 1]
                    + work[W_TEMP + 3 * r + 2] * work[rot_i + 3 * c + 2]
                )
                work[inertia + 3 * r + c] = value
                work[inertia + 3 * c + r] = value


@_kernel
def _axis(work: FloatArray, j: int, r: int) -> float:
    """Component r of joint j's world axis z_j (rotor j's third column)."""
    return work[W_ROT + 9 * j + 3 * r + 2]


@_kernel
def _axis_point(work: FloatArray, j: int, r: int) -> float:
    """Component r of a point on joint j's axis: the origin for joints 1-3, the elbow for joint 4."""
    return work[W_ELBOW + r] if j == 3 else 0.0


@_kernel
def _times_axis(work: FloatArray, matrix: int, k: int, out: int) -> None:
    """``work[out:out + 3] = A z_k`` for the 3x3 matrix stored at ``work[matrix:]``."""
    z0 = _axis(work, k, 0)
    z1 = _axis(work, k, 1)
    z2 = _axis(work, k, 2)
    for r in range(3):
        work[out + r] = work[matrix + 3 * r] * z0 + work[matrix + 3 * r + 1] * z1 + work[matrix + 3 * r + 2] * z2


@_kernel
def _axis_dot(work: FloatArray, j: int, at: int) -> float:
    """``z_j . work[at:at + 3]``."""
    return _axis(work, j, 0) * work[at] + _axis(work, j, 1) * work[at + 1] + _axis(work, j, 2) * work[at + 2]


@_kernel
def mass_matrix_from_kinematics(p: FloatArray, work: FloatArray) -> None:
    """``M(q)`` into ``work[W_MASS:]`` from the kinematics already in ``work``.

    ``M = sum_i m_i Jv_i^T Jv_i + Jw_i^T I_i Jw_i`` with columns ``z_j x (c_i - o_j)`` and
    ``z_j`` (j <= i). Joints 1-3 turn about axes through the origin, so for them the sum over
    bodies i >= max(j, k) is ``z_j^T C z_k`` with ``C`` the composite inertia of those bodies
    about the origin (parallel-axis theorem). Joint 4 moves body 4 only, about the elbow.
    """
    composite = W_TEMP  # running sum of inertias about the origin, bodies i..4 (9), then C z_i (3)
    product = W_TEMP + 9
    for n in range(9):
        work[composite + n] = 0.0
    for i in range(N_JOINTS - 1, -1, -1):
        mass = p[P_BODIES + i * BODY_SIZE]
        c0 = work[W_COM + 3 * i]
        c1 = work[W_COM + 3 * i + 1]
        c2 = work[W_COM + 3 * i + 2]
        cc = mass * (c0 * c0 + c1 * c1 + c2 * c2)
        inertia = W_INERTIA + 9 * i
        for r in range(3):
            cr = mass * work[W_COM + 3 * i + r]
            for c in range(3):
                work[composite + 3 * r + c] += work[inertia + 3 * r + c] - cr * work[W_COM + 3 * i + c]
            work[composite + 4 * r] += cc
        if i < 3:
            # Entries (j, i), j <= i <= joint 3: bodies i..4 are exactly those both joints move.
            _times_axis(work, composite, i, product)
            for j in range(i + 1):
                value = _axis_dot(work, j, product)
                work[W_MASS + 4 * j + i] = value
                work[W_MASS + 4 * i + j] = value
    # Joint 4 with itself and with joints 1-3: body 4 alone.
    mass = p[P_BODIES + 3 * BODY_SIZE]
    _times_axis(work, W_INERTIA + 27, 3, product)
    r0 = work[W_COM + 9] - work[W_ELBOW]
    r1 = work[W_COM + 10] - work[W_ELBOW + 1]
    r2 = work[W_COM + 11] - work[W_ELBOW + 2]
    z0 = _axis(work, 3, 0)
    z1 = _axis(work, 3, 1)
    z2 = _axis(work, 3, 2)
    jv0 = mass * (z1 * r2 - z2 * r1)  # m z_4 x (c_4 - o_4)
    jv1 = mass * (z2 * r0 - z0 * r2)
    jv2 = mass * (z0 * r1 - z1 * r0)
    for j in range(N_JOINTS):
        c0 = work[W_COM + 9] - _axis_point(work, j, 0)
        c1 = work[W_COM + 10] - _axis_point(work, j, 1)
        c2 = work[W_COM + 11] - _axis_point(work, j, 2)
        a0 = _axis(work, j, 0)
        a1 = _axis(work, j, 1)
        a2 = _axis(work, j, 2)
        value = (
            (a1 * c2 - a2 * c1) * jv0
            + (a2 * c0 - a0 * c2) * jv1
            + (a0 * c1 - a1 * c0) * jv2
            + _axis_dot(work, j, product)
        )
        work[W_MASS + 4 * j + 3] = value
        work[W_MASS + 12 + j] = value


@_kernel
def joint_spring_torque(x: FloatArray, p: FloatArray, out: FloatArray, at: int) -> None:
    """Add the holding torque of the pull-only joint springs at state ``x`` to ``out[at:at + 4]``.

    While stretched a spring pushes back with ``k stretch + d stretch'``, never negative: the
    damping of an end stop brakes a joint running into it but does not hold it when it leaves.
    """
    for s in range(int(p[P_N_SPRINGS])):
        base = P_SPRINGS + s * SPRING_SIZE
        joint = int(p[base])
        sign = p[base + 3]
        stretch = sign * (x[joint] - p[base + 2])
        if stretch > 0.0:
            push = p[base + 1] * stretch + p[base + 4] * sign * x[2 * N_JOINTS + joint]
            if push > 0.0:
                out[at + joint] += sign * push


@_kernel
def bias_from_kinematics(x: FloatArray, p: FloatArray, work: FloatArray, with_gravity: bool) -> None:
    """``c(q, q') (+ gravity)`` into ``work[W_BIAS:]``: Newton-Euler with ``q'' = 0``, ``q' = x[8:12]``.

    Forward pass in the world frame: ``w_i = w_(i-1) + z_i q'_i``, ``alpha_i = alpha_(i-1) +
    w_(i-1) x z_i q'_i`` (z_i is fixed in body i-1), CoM acceleration ``a_o + alpha x r + w x (w
    x r)`` with ``a_o`` zero for joints 1-3 (the fixed shoulder CoR) and that of the elbow point
    of body 3 for joint 4. Backward: ``tau_j = z_j . sum_(i >= j) (N_i + (c_i - o_j) x F_i)``.
    Joint springs are not included (see :func:`joint_spring_torque`).
    """
    g = p[P_GRAVITY] if with_gravity else 0.0
    # w and alpha of the previous body, carried in registers.
    w0 = w1 = w2 = 0.0
    al0 = al1 = al2 = 0.0
    for i in range(N_JOINTS):
        z0 = _axis(work, i, 0)
        z1 = _axis(work, i, 1)
        z2 = _axis(work, i, 2)
        wp0 = w0
        wp1 = w1
        wp2 = w2
        ap0 = al0
        ap1 = al1
        ap2 = al2
        v = x[2 * N_JOINTS + i]
        w0 = wp0 + z0 * v
        w1 = wp1 + z1 * v
        w2 = wp2 + z2 * v
        al0 = ap0 + (wp1 * z2 - wp2 * z1) * v
        al1 = ap1 + (wp2 * z0 - wp0 * z2) * v
        al2 = ap2 + (wp0 * z1 - wp1 * z0) * v
        # Acceleration of the axis point o_i (moves only for the elbow, a point of body 3).
        ao0 = ao1 = ao2 = 0.0
        if i == 3:
            e0 = work[W_ELBOW]
            e1 = work[W_ELBOW + 1]
            e2 = work[W_ELBOW + 2]
            u0 = wp1 * e2 - wp2 * e1
            u1 = wp2 * e0 - wp0 * e2
            u2 = wp0 * e1 - wp1 * e0
            ao0 = ap1 * e2 - ap2 * e1 + wp1 * u2 - wp2 * u1
            ao1 = ap2 * e0 - ap0 * e2 + wp2 * u0 - wp0 * u2
            ao2 = ap0 * e1 - ap1 * e0 + wp0 * u1 - wp1 * u0
        r0 = work[W_COM + 3 * i] - _axis_point(work, i, 0)
        r1 = work[W_COM + 3 * i + 1] - _axis_point(work, i, 1)
        r2 = work[W_COM + 3 * i + 2] - _axis_point(work, i, 2)
        u0 = w1 * r2 - w2 * r1
        u1 = w2 * r0 - w0 * r2
        u2 = w0 * r1 - w1 * r0
        a0 = ao0 + al1 * r2 - al2 * r1 + w1 * u2 - w2 * u1
        a1 = ao1 + al2 * r0 - al0 * r2 + w2 * u0 - w0 * u2
        a2 = ao2 + al0 * r1 - al1 * r0 + w0 * u1 - w1 * u0
        mass = p[P_BODIES + i * BODY_SIZE]
        work[W_FORCE + 3 * i] = mass * a0
        work[W_FORCE + 3 * i + 1] = mass * (a1 + g)  # m (a - gravity), gravity = (0, -g, 0)
        work[W_FORCE + 3 * i + 2] = mass * a2
        inertia = W_INERTIA + 9 * i
        iw0 = work[inertia] * w0 + work[inertia + 1] * w1 + work[inertia + 2] * w2
        iw1 = work[inertia + 3] * w0 + work[inertia + 4] * w1 + work[inertia + 5] * w2
        iw2 = work[inertia + 6] * w0 + work[inertia + 7] * w1 + work[inertia + 8] * w2
        ia0 = work[inertia] * al0 + work[inertia + 1] * al1 + work[inertia + 2] * al2
        ia1 = work[inertia + 3] * al0 + work[inertia + 4] * al1 + work[inertia + 5] * al2
        ia2 = work[inertia + 6] * al0 + work[inertia + 7] * al1 + work[inertia + 8] * al2
        work[W_MOMENT + 3 * i] = ia0 + w1 * iw2 - w2 * iw1
        work[W_MOMENT + 3 * i + 1] = ia1 + w2 * iw0 - w0 * iw2
        work[W_MOMENT + 3 * i + 2] = ia2 + w0 * iw1 - w1 * iw0
    # Backward pass. Joints 1-3 share the axis point (origin), so their moments accumulate.
    s0 = s1 = s2 = 0.0
    for i in range(N_JOINTS - 1, -1, -1):
        c0 = work[W_COM + 3 * i]
        c1 = work[W_COM + 3 * i + 1]
        c2 = work[W_COM + 3 * i + 2]
        f0 = work[W_FORCE + 3 * i]
        f1 = work[W_FORCE + 3 * i + 1]
        f2 = work[W_FORCE + 3 * i + 2]
        n0 = work[W_MOMENT + 3 * i]
        n1 = work[W_MOMENT + 3 * i + 1]
        n2 = work[W_MOMENT + 3 * i + 2]
        s0 += n0 + c1 * f2 - c2 * f1
        s1 += n1 + c2 * f0 - c0 * f2
        s2 += n2 + c0 * f1 - c1 * f0
        if i == 3:
            # Joint 4: moment about the elbow of body 4 alone.
            r0 = c0 - work[W_ELBOW]
            r1 = c1 - work[W_ELBOW + 1]
            r2 = c2 - work[W_ELBOW + 2]
            m0 = n0 + r1 * f2 - r2 * f1
            m1 = n1 + r2 * f0 - r0 * f2
            m2 = n2 + r0 * f1 - r1 * f0
            work[W_BIAS + 3] = _axis(work, 3, 0) * m0 + _axis(work, 3, 1) * m1 + _axis(work, 3, 2) * m2
        else:
            work[W_BIAS + i] = _axis(work, i, 0) * s0 + _axis(work, i, 1) * s1 + _axis(work, i, 2) * s2


@_kernel
def _solve_spd(work: FloatArray) -> bool:
    """Solve ``M x = rhs`` in place of ``work[W_RHS:]`` by Cholesky; False if M is not positive definite.

    The diagonal of the factor is stored inverted: one division per column instead of one per
    element (the factorisation is a chain of dependent operations, divisions are its slowest).
    """
    for j in range(N_JOINTS):
        acc = work[W_MASS + 5 * j]
        for k in range(j):
            acc -= work[W_CHOL + 4 * j + k] ** 2
        if not acc > 0.0:
            return False
        inverse = 1.0 / math.sqrt(acc)
        work[W_CHOL + 5 * j] = inverse
        for i in range(j + 1, N_JOINTS):
            acc = work[W_MASS + 4 * i + j]
            for k in range(j):
                acc -= work[W_CHOL + 4 * i + k] * work[W_CHOL + 4 * j + k]
            work[W_CHOL + 4 * i + j] = acc * inverse
    for i in range(N_JOINTS):  # forward substitution L y = b
        acc = work[W_RHS + i]
        for k in range(i):
            acc -= work[W_CHOL + 4 * i + k] * work[W_RHS + k]
        work[W_RHS + i] = acc * work[W_CHOL + 5 * i]
    for i in range(N_JOINTS - 1, -1, -1):  # back substitution L^T x = y
        acc = work[W_RHS + i]
        for k in range(i + 1, N_JOINTS):
            acc -= work[W_CHOL + 4 * k + i] * work[W_RHS + k]
        work[W_RHS + i] = acc * work[W_CHOL + 5 * i]
    return True


# --- public kernels -------------------------------------------------------------------------------


@_kernel
def derivative(x: FloatArray, u: FloatArray, p: FloatArray, work: FloatArray, out: FloatArray) -> bool:
    """``out = dx/dt`` for state ``x`` (16,) and inputs ``u = [tau_m, tau_ext]`` (8,).

    Returns False (``out`` undefined) if ``M(q)`` is not numerically positive definite.
    """
    kinematics(x, p, work)
    mass_matrix_from_kinematics(p, work)
    bias_from_kinematics(x, p, work, True)
    joint_spring_torque(x, p, work, W_BIAS)
    inverse_eps = p[P_INVERSE_SMOOTHING]
    for j in range(N_JOINTS):
        qj = x[j]
        th = x[N_JOINTS + j]
        v = x[2 * N_JOINTS + j]
        dth = x[3 * N_JOINTS + j]
        tau_s = p[P_STIFFNESS + j] * (th - qj) + p[P_SPRING_DAMPING + j] * (dth - v)
        work[W_RHS + j] = tau_s + u[N_JOINTS + j] - p[P_LINK_VISCOUS + j] * v - work[W_BIAS + j]
        limit = p[P_MAX_MOTOR_TORQUE + j]
        tau_m = min(max(u[j], -limit), limit)
        friction = p[P_MOTOR_VISCOUS + j] * dth
        if p[P_MOTOR_COULOMB + j] != 0.0:
            friction += p[P_MOTOR_COULOMB + j] * math.tanh(dth * inverse_eps)
        out[j] = v
        out[N_JOINTS + j] = dth
        out[3 * N_JOINTS + j] = (tau_m - tau_s - friction) * p[P_INVERSE_MOTOR_INERTIA + j]
    if not _solve_spd(work):
        return False
    for j in range(N_JOINTS):
        out[2 * N_JOINTS + j] = work[W_RHS + j]
    return True


@_kernel
def rk4_step(x: FloatArray, u: FloatArray, dt: float, p: FloatArray, work: FloatArray) -> bool:
    """Advance ``x`` in place by one classical RK4 step of ``dt`` seconds, inputs held constant.

    Returns False and leaves ``x`` unchanged if the step produced a non-finite state or met a
    mass matrix that is not positive definite (the plant diverged; the caller raises).
    """
    k1 = work[W_K1 : W_K1 + N_STATE]
    k2 = work[W_K2 : W_K2 + N_STATE]
    k3 = work[W_K3 : W_K3 + N_STATE]
    k4 = work[W_K4 : W_K4 + N_STATE]
    xt = work[W_XT : W_XT + N_STATE]
    ok = derivative(x, u, p, work, k1)
    for n in range(N_STATE):
        xt[n] = x[n] + 0.5 * dt * k1[n]
    ok = ok and derivative(xt, u, p, work, k2)
    for n in range(N_STATE):
        xt[n] = x[n] + 0.5 * dt * k2[n]
    ok = ok and derivative(xt, u, p, work, k3)
    for n in range(N_STATE):
        xt[n] = x[n] + dt * k3[n]
    ok = ok and derivative(xt, u, p, work, k4)
    if not ok:
        return False
    sixth = dt / 6.0
    for n in range(N_STATE):
        value = x[n] + sixth * (k1[n] + 2.0 * k2[n] + 2.0 * k3[n] + k4[n])
        if not math.isfinite(value):
            return False
        xt[n] = value
    for n in range(N_STATE):
        x[n] = xt[n]
    return True


@_kernel
def simulate(x: FloatArray, u: FloatArray, dt: float, steps: int, p: FloatArray, work: FloatArray) -> int:
    """``steps`` RK4 steps with constant inputs; returns the number of steps completed."""
    for n in range(steps):
        if not rk4_step(x, u, dt, p, work):
            return n
    return steps


@_kernel
def mass_matrix(q: FloatArray, p: FloatArray, work: FloatArray, out: FloatArray) -> None:
    """``M(q)`` into ``out`` (4, 4)."""
    x = np.zeros(N_STATE)
    x[0:N_JOINTS] = q
    kinematics(x, p, work)
    mass_matrix_from_kinematics(p, work)
    for j in range(N_JOINTS):
        for k in range(N_JOINTS):
            out[j, k] = work[W_MASS + 4 * j + k]


@_kernel
def bias_torque(q: FloatArray, dq: FloatArray, p: FloatArray, work: FloatArray, out: FloatArray) -> None:
    """``c(q, q') + g(q)`` into ``out`` (4,); ``g`` includes gravity and the joint springs."""
    x = np.zeros(N_STATE)
    x[0:N_JOINTS] = q
    x[2 * N_JOINTS : 3 * N_JOINTS] = dq
    kinematics(x, p, work)
    bias_from_kinematics(x, p, work, True)
    for j in range(N_JOINTS):
        out[j] = work[W_BIAS + j]
    joint_spring_torque(x, p, out, 0)


@_kernel
def energy_components(x: FloatArray, p: FloatArray, work: FloatArray, out: FloatArray) -> None:
    """Mechanical energy terms (J) into ``out`` (5,).

    ``[link kinetic, motor kinetic, gravity potential, SEA spring potential, joint spring
    potential]``; gravity potential is ``m g y`` of every body (zero at the height of the CoR).
    """
    kinematics(x, p, work)
    mass_matrix_from_kinematics(p, work)
    link = 0.0
    for j in range(N_JOINTS):
        for k in range(N_JOINTS):
            link += x[2 * N_JOINTS + j] * work[W_MASS + 4 * j + k] * x[2 * N_JOINTS + k]
    motor = 0.0
    sea = 0.0
    for j in range(N_JOINTS):
        motor += p[P_MOTOR_INERTIA + j] * x[3 * N_JOINTS + j] ** 2
        sea += p[P_STIFFNESS + j] * (x[N_JOINTS + j] - x[j]) ** 2
    gravity = 0.0
    for i in range(N_JOINTS):
        gravity += p[P_BODIES + i * BODY_SIZE] * p[P_GRAVITY] * work[W_COM + 3 * i + 1]
    springs = 0.0
    for s in range(int(p[P_N_SPRINGS])):
        base = P_SPRINGS + s * SPRING_SIZE
        stretch = p[base + 3] * (x[int(p[base])] - p[base + 2])
        if stretch > 0.0:
            springs += 0.5 * p[base + 1] * stretch * stretch
    out[0] = 0.5 * link
    out[1] = 0.5 * motor
    out[2] = gravity
    out[3] = 0.5 * sea
    out[4] = springs


# --- the simulated drives (hal.sim.backend) --------------------------------------------------------
# They live here, not in backend.py, because numba's on-disk cache notices changes to a kernel's
# own file only: a cached kernel in another module that calls rk4_step would keep running the old
# physics after an edit of this file.

# Drive vector ``s`` layout: sensor parameters, the drives' sensor state, the command path, and a
# block of pre-drawn encoder noise (all in one array: each array argument of a kernel call costs).
S_STIFFNESS = 0  # k used by the drive to compute torque, 4
S_RESOLUTION = 4  # encoder resolution, rad
S_QUANTISE = 5  # 1.0: round readings to the resolution
S_NOISE = 6  # encoder noise std, rad
S_DIRECTION_ERROR = 7  # Sec. 2.2.2 error per joint, 4
S_FILTER_ALPHA = 11  # velocity low-pass gain per tick
S_INVERSE_PLAY = 12  # 1 / travel after which the direction-dependent error has reversed, 1/rad
S_DT = 13  # the tick, s
S_JUMP = 14  # injected offset of each q reading, 4
S_PREVIOUS_Q = 18  # previous q reading, 4
S_VELOCITY = 22  # the drives' velocity estimate, 4
S_DIRECTION = 26  # play-operator state of each joint in [-1, 1]: where its last motion went, 4
S_STARTED = 30  # 1.0 once a first reading exists
S_TICK = 31  # ticks since the session started (exact as a float up to 2^53)
MAX_FIFO = 11  # command_delay_ticks <= 10 (scenario schema)
S_FIFO_LENGTH = 32  # command_delay_ticks + 1
S_FIFO_ENABLE = 33  # 1.0 where a queued command is enabled, MAX_FIFO
S_FIFO_TORQUE = S_FIFO_ENABLE + MAX_FIFO  # queued motor torques, MAX_FIFO x 4
S_INPUTS = S_FIFO_TORQUE + MAX_FIFO * N_JOINTS  # [motor torque applied this tick, external torque], 8
S_FAULTED = S_INPUTS + 2 * N_JOINTS  # 1.0 where the drive has a fault, 4
S_NOISE_INDEX = S_FAULTED + N_JOINTS  # next unused number of the noise block
NOISE_PER_TICK = 2 * N_JOINTS  # one standard normal per encoder
NOISE_BLOCK_TICKS = 256  # one refill draws 2,048 normals: ~25-50 us, no spike in a real-time tick
S_NOISE_BLOCK = S_NOISE_INDEX + 1  # standard normals, NOISE_BLOCK_TICKS x NOISE_PER_TICK
NOISE_BLOCK_SIZE = NOISE_BLOCK_TICKS * NOISE_PER_TICK
S_SUBSTEPS = S_NOISE_BLOCK + NOISE_BLOCK_SIZE  # RK4 steps per tick (>= 1)
S_PREVIOUS_TRUE_Q = S_SUBSTEPS + 1  # true link angles at the previous reading (play operator), 4
# Undeclared sensor effects (scenario sensors.*; docs/simulation.md "Undeclared effects"). Appended
# at the end so that no index above moves. Zero means absent: sense skips them then.
S_ANGLE_OFFSET = S_PREVIOUS_TRUE_Q + N_JOINTS  # calibration error of each joint's zero, both encoders, rad, 4
S_TORQUE_DRIFT = S_ANGLE_OFFSET + N_JOINTS  # drift of the measured torque, Nm per second of robot time, 4
# 1.0 where the command disables this joint's drive (Command.joints_off): no torque from this tick
# on, whatever the FIFO holds (a power stage switches off at once), while the others follow the command.
S_JOINT_OFF = S_TORQUE_DRIFT + N_JOINTS
# 1.0 while the e-stop circuit has cut every drive's power stage (safe torque off: at once with an sto
# wiring, when the safety relay's delay has run out with ss1; set by the caller before the call).
S_POWER_CUT = S_JOINT_OFF + N_JOINTS
DRIVE_VECTOR_SIZE = S_POWER_CUT + 1

#: What the tick kernel returns.
TICK_ENABLED, TICK_DISABLED, TICK_BAD_COMMAND, TICK_DIVERGED, TICK_NO_NOISE = 0, 1, -1, -2, -3


@_kernel
def noise_left(s: FloatArray) -> bool:
    """True if the noise block holds the numbers of one more tick (kernels never read past it)."""
    return s[S_NOISE_INDEX] + NOISE_PER_TICK <= NOISE_BLOCK_TICKS * NOISE_PER_TICK


@_kernel
def sense(x: FloatArray, s: FloatArray, out: FloatArray, row: int) -> bool:
    """Read both encoders of every joint; update the drives' state in ``s``; readings into ``out``.

    ``out[row:row + 4]`` (4 rows of 4): q, velocity estimate, theta, measured torque (``out`` is
    a block of readings, so the backend needs no new array per tick). Uses the next
    NOISE_PER_TICK numbers of the noise block; returns False (nothing read) if it is used up.
    The reading is taken at robot time ``s[S_TICK] * s[S_DT]`` (the torque drift grows with it).

    The undeclared effects match :func:`hal.sim.sensors.read_encoders`: the torque uses the
    drive's (nominal) ``S_STIFFNESS``, whatever the plant's spring is; ``S_ANGLE_OFFSET`` is
    added to both reported angles after quantisation and after the torque and velocity (a
    common offset cancels in both); ``S_TORQUE_DRIFT`` times the robot time is added to the torque.
    """
    if not noise_left(s):
        return False
    std = s[S_NOISE]
    step = s[S_RESOLUTION]
    started = s[S_STARTED] > 0.0
    alpha = s[S_FILTER_ALPHA]
    inverse_dt = 1.0 / s[S_DT]
    t = s[S_TICK] * s[S_DT]  # the same product as the sample's t_s in hal.sim.backend
    noise = S_NOISE_BLOCK + int(s[S_NOISE_INDEX])
    for j in range(N_JOINTS):
        q = x[j] + std * s[noise + j]
        theta = x[N_JOINTS + j] + std * s[noise + N_JOINTS + j]
        if s[S_QUANTISE] > 0.0:
            q = np.rint(q / step) * step
            theta = np.rint(theta / step) * step
        q += s[S_JUMP + j]
        # Direction-dependent error as hysteresis (a play operator): the state moves with the true
        # travel and saturates at +-1 after 1 / S_INVERSE_PLAY rad; the vibration of a held joint
        # does not flip it, a real move in the other direction does.
        if started:
            travel = x[j] - s[S_PREVIOUS_TRUE_Q + j]
            s[S_DIRECTION + j] = min(max(s[S_DIRECTION + j] + travel * s[S_INVERSE_PLAY], -1.0), 1.0)
        s[S_PREVIOUS_TRUE_Q + j] = x[j]
        if started:
            raw = (q - s[S_PREVIOUS_Q + j]) * inverse_dt
            s[S_VELOCITY + j] += alpha * (raw - s[S_VELOCITY + j])
        else:
            s[S_VELOCITY + j] = 0.0
        s[S_PREVIOUS_Q + j] = q
        tau = s[S_STIFFNESS + j] * (theta - q) + s[S_DIRECTION_ERROR + j] * s[S_DIRECTION + j]
        # Each undeclared effect only where declared: a scenario without it reads the very same
        # floats as before the effect existed (adding 0.0 would turn a -0.0 reading into +0.0).
        drift = s[S_TORQUE_DRIFT + j]
        if drift != 0.0:
            tau += drift * t
        offset = s[S_ANGLE_OFFSET + j]
        if offset != 0.0:
            q += offset
            theta += offset
        out[row, j] = q
        out[row + 1, j] = s[S_VELOCITY + j]
        out[row + 2, j] = theta
        out[row + 3, j] = tau
    s[S_STARTED] = 1.0
    s[S_NOISE_INDEX] += NOISE_PER_TICK
    return True


@_kernel
def flush_commands(s: FloatArray) -> None:
    """Empty the command FIFO: every queued command becomes torque off."""
    for n in range(MAX_FIFO):
        s[S_FIFO_ENABLE + n] = 0.0
    for n in range(MAX_FIFO * N_JOINTS):
        s[S_FIFO_TORQUE + n] = 0.0
    for j in range(N_JOINTS):
        s[S_INPUTS + j] = 0.0


@_kernel
def hal_tick(
    x: FloatArray,
    p: FloatArray,
    work: FloatArray,
    s: FloatArray,
    torque: FloatArray,
    enable: bool,
    out: FloatArray,
    row: int,
) -> int:
    """One tick of the drives and the plant; readings of the new plant time into ``out[row:row + 4]``.

    Queues the command (an enabled one acts ``fifo length - 1`` ticks later; a disabled one
    empties the FIFO and acts now), removes the torque of faulted drives and of drives the command
    switched off (``S_JOINT_OFF``) or whose power the e-stop circuit cut (``S_POWER_CUT``; both set by
    the caller before the call), integrates one RK4
    step (split into ``s[S_SUBSTEPS]`` RK4 substeps), counts the tick, reads the encoders
    (stamped with the new tick count). Returns TICK_ENABLED or TICK_DISABLED (what the
    power stages did), TICK_BAD_COMMAND (non-finite torque: FIFO emptied, no step) or
    TICK_DIVERGED (FIFO emptied, state as after the last good RK4 substep), or TICK_NO_NOISE (nothing done:
    refill the noise block and call again).
    """
    if not noise_left(s):
        return TICK_NO_NOISE
    length = int(s[S_FIFO_LENGTH])
    tick = int(s[S_TICK])
    slot = tick % length
    if enable:
        for j in range(N_JOINTS):
            if not math.isfinite(torque[j]):
                flush_commands(s)
                return TICK_BAD_COMMAND
        for j in range(N_JOINTS):
            s[S_FIFO_TORQUE + N_JOINTS * slot + j] = torque[j]
        s[S_FIFO_ENABLE + slot] = 1.0
        active = (tick + 1) % length  # the command written length - 1 ticks ago
    else:
        flush_commands(s)
        active = slot
    on = s[S_FIFO_ENABLE + active] > 0.0
    for j in range(N_JOINTS):
        applied = on and s[S_FAULTED + j] == 0.0 and s[S_JOINT_OFF + j] == 0.0 and s[S_POWER_CUT] == 0.0
        s[S_INPUTS + j] = s[S_FIFO_TORQUE + N_JOINTS * active + j] if applied else 0.0
    substeps = max(int(s[S_SUBSTEPS]), 1)
    h = s[S_DT] / substeps
    inputs = s[S_INPUTS : S_INPUTS + 2 * N_JOINTS]
    for _ in range(substeps):
        if not rk4_step(x, inputs, h, p, work):
            flush_commands(s)
            return TICK_DIVERGED
    # Counted before reading: the reading belongs to the new plant time, tick + 1 ticks in
    # (sense takes its time stamp from S_TICK; the backend's sample says t_s = (tick + 1) dt).
    s[S_TICK] = tick + 1
    sense(x, s, out, row)
    return TICK_ENABLED if on else TICK_DISABLED


#: The numba types :func:`hal_tick` is resolved for (:func:`hal_tick_entry`): the plant's and the
#: drives' own arrays (float64, 1-D, C order, written by the kernel), the commanded torque as any
#: read-only float64 vector (the kernel never writes it: a read-only view of any 1-D float64 array,
#: whatever its strides, is an instance of this type), the enable flag, the block of readings and
#: the first row of this tick's four.
HAL_TICK_SIGNATURE = (
    types.float64[::1],
    types.float64[::1],
    types.float64[::1],
    types.float64[::1],
    types.Array(types.float64, 1, "A", readonly=True),
    types.boolean,
    types.float64[:, ::1],
    types.intp,
)


def hal_tick_entry() -> Callable[..., int]:
    """:func:`hal_tick`'s compiled entry point for :data:`HAL_TICK_SIGNATURE` (loaded or compiled once).

    Calling the entry point skips the dispatcher's type resolution (7 arrays: ~0.25 us a tick) and,
    unlike the dispatcher, checks no argument type: numba only checks that each array argument is
    an ndarray of 8-byte items. The caller therefore guarantees the types: its own arrays are
    made with them, and the commanded torque is checked to be a float64 ndarray of shape (4,)
    before the call (``hal.sim.backend.SimHal.write``; ``tests/daror_runtime/test_kernel_entry_points.py`` checks both).
    """
    return hal_tick.compile(HAL_TICK_SIGNATURE)


# --- the simulated pilot (hal.sim.pilot) ------------------------------------------------------------
# Here for the same reason as the drives' kernels: it calls bias_torque.

# Pilot vector ``v`` layout: the pilot's impedance, the support it feels and its scratch.
PILOT_STIFFNESS = 0  # K, Nm/rad, 4
PILOT_DAMPING = 4  # D, Nms/rad, 4
PILOT_FELT_SUPPORT = 8  # the spring torque the pilot feels (low-passed), Nm, 4
PILOT_ZERO = 12  # zeros: the joint speeds of g(q) = bias_torque(q, 0), 4
PILOT_GRAVITY = 16  # g(q), Nm, 4
PILOT_TORQUE = 20  # the torque of the last evaluation, finite or not, Nm, 4
PILOT_VECTOR_SIZE = 24


@_kernel
def pilot_torque(
    q: FloatArray,
    dq: FloatArray,
    x: FloatArray,
    p: FloatArray,
    work: FloatArray,
    v: FloatArray,
    q_from: FloatArray,
    q_to: FloatArray,
    moving: bool,
    shape: float,
    adapt: bool,
    alpha: float,
    carried: float,
    out: FloatArray,
) -> bool:
    """The pilot's torque on the links (Nm) into ``v[PILOT_TORQUE:]``, and into ``out`` (4,) if finite.

    ``tau = K (q_target - q) - D q' + carried (g(q) - clip(s, min(g, 0), max(g, 0)))`` with
    ``q_target = q_from + (q_to - q_from) shape`` while ``moving``, else ``q_from``; the felt
    support ``s`` (Nm) first moves by ``alpha`` of the way to the plant's spring torque
    ``k (theta - q) + d_s (theta' - q')`` at state ``x`` (``k``, ``d_s`` from ``p``: the values
    ``DynamicPlant.spring_torque_nm`` multiplies with) when ``adapt``; the last term only where
    ``carried > 0``. The same IEEE operations in the same order as the pilot's numpy formula on
    arrays (kept in ``tests/hal/sim/test_pilot_fast_path.py``), no fast-math: the torque is numpy's to the
    bit. Returns False, ``out`` untouched, if an element is not finite.
    """
    for j in range(N_JOINTS):
        target = q_from[j] + (q_to[j] - q_from[j]) * shape if moving else q_from[j]
        v[PILOT_TORQUE + j] = v[PILOT_STIFFNESS + j] * (target - q[j]) - v[PILOT_DAMPING + j] * dq[j]
    if adapt:
        for j in range(N_JOINTS):
            spring = p[P_STIFFNESS + j] * (x[N_JOINTS + j] - x[j]) + p[P_SPRING_DAMPING + j] * (
                x[3 * N_JOINTS + j] - x[2 * N_JOINTS + j]
            )
            v[PILOT_FELT_SUPPORT + j] += alpha * (spring - v[PILOT_FELT_SUPPORT + j])
    if carried > 0.0:
        gravity = v[PILOT_GRAVITY : PILOT_GRAVITY + N_JOINTS]
        bias_torque(q, v[PILOT_ZERO : PILOT_ZERO + N_JOINTS], p, work, gravity)
        for j in range(N_JOINTS):
            g = gravity[j]
            # np.minimum(g, 0.0) and np.maximum(g, 0.0): a NaN propagates, a tie (g = -0.0) gives the 0.0.
            low = g if g < 0.0 or g != g else 0.0
            high = g if g > 0.0 or g != g else 0.0
            # np.clip(s, low, high), i.e. np.minimum(np.maximum(s, low), high) elementwise: a NaN
            # propagates, a tie (signed zeros) gives the bound, as numpy's SIMD loops do.
            felt = v[PILOT_FELT_SUPPORT + j]
            felt = felt if felt > low or felt != felt else low
            felt = felt if felt < high or felt != felt else high
            v[PILOT_TORQUE + j] += carried * (g - felt)
    for j in range(N_JOINTS):
        if not math.isfinite(v[PILOT_TORQUE + j]):
            return False
    for j in range(N_JOINTS):
        out[j] = v[PILOT_TORQUE + j]
    return True


#: The numba types :func:`pilot_torque` is resolved for (:func:`pilot_torque_entry`): ``q``,
#: ``dq``, ``q_from`` and ``q_to`` as read-only float64 vectors of any strides (a view of the
#: plant's state fits, and so does any float64 (4,) array the caller checked), the plant's state,
#: parameters, the pilot's scratch and its vector (float64, C order), the flags and scalars, and
#: ``out`` as a writable float64 vector in C order (a slice of the drive vector fits).
PILOT_TORQUE_SIGNATURE = (
    types.Array(types.float64, 1, "A", readonly=True),
    types.Array(types.float64, 1, "A", readonly=True),
    types.float64[::1],
    types.float64[::1],
    types.float64[::1],
    types.float64[::1],
    types.Array(types.float64, 1, "A", readonly=True),
    types.Array(types.float64, 1, "A", readonly=True),
    types.boolean,
    types.float64,
    types.boolean,
    types.float64,
    types.float64,
    types.float64[::1],
)


def pilot_torque_entry() -> Callable[..., bool]:
    """:func:`pilot_torque`'s compiled entry point for :data:`PILOT_TORQUE_SIGNATURE` (loaded or compiled once).

    Like :func:`hal_tick_entry`'s, it checks no argument type: the caller passes arrays made with
    these types (``hal.sim.pilot.SimulatedPilot`` checks ``q`` and ``dq`` unless they are the
    backend's views of the plant's state).
    """
    return pilot_torque.compile(PILOT_TORQUE_SIGNATURE)
