"""Joint position control through the motor: a collocated PD on the motor angle of each SEA.

The motor (gearbox output) angle ``theta`` is where the actuator acts, so a PD on it is
collocated and stays stable at high gains; the link follows through the spring. With a
gravity feed-forward ``tau_ff`` (a compensation model at the reference) the motor reference is
``theta_ref = q_ref + tau_ff / k``, the angle at which the spring carries ``tau_ff`` when the
link is on its reference::

    tau_m = tau_ff + Kp (theta_ref - theta) + Kd (dq_ref - theta'_filtered)

The link's static error is the feed-forward's error divided by the series stiffness of the
position loop and the spring (``1 / (1/Kp + 1/k)``, about 200 Nm/rad with Kp = 700).

Gains: ``Kp = 700 Nm/rad`` is the thesis's (Sec. 2.2.4); ``Kd = 20 Nms/rad`` is ours. The thesis's
``Kd = 175 Nms/rad`` is stable here too, but it turns the 1e-4 rad quantisation of the motor
encoder at 1 kHz into 17-33 Nm RMS of motor-torque noise (docs/control.md). ``Kd = 20`` damps the
motor loop at about 0.76 of critical on the nominal 0.25 kg m^2 gearbox inertia with 0.4 Nm of
noise and the same tracking. Every gain set is checked at construction: the discrete-time loop
(one tick of command delay, the velocity filter, motor, spring, the lightest and heaviest link,
the gravity that pulls away) must have a spectral radius below one with the given margin.

Compared with a PD on the link angle whose output is the torque reference of the SEA torque loop
(the thesis's cascade, Sec. 2.2.4; built and removed in issue 11, docs/control.md section 5),
this controller is 40 times stiffer at the link for the same stability; it is what the
identification protocol uses.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import scipy.linalg
from numba import njit, types

from daror_runtime.control.base import (
    CONTROLLER_STEP,
    CompiledControllerTick,
    ControlDesignError,
    ControlError,
    ControlSettingError,
)
from daror_runtime.control.position import LinkBounds, Reference
from daror_runtime.models.base import Feedforward
from daror_runtime.models.regressor import linear_torque
from hal.interface import CheckedCommand, CheckedSample, Command, Sample
from hal.kernels import SAMPLE_VECTOR, CompiledFunction, entry_point
from hal.robot import N_JOINTS, FloatArray, RobotDescription

_new_tuple = tuple.__new__

#: The thesis's proportional gain (Sec. 2.2.4), Nm/rad, here on the motor angle.
DEFAULT_KP_NM_PER_RAD = 700.0
#: Our derivative gain (the thesis's 175 amplifies encoder quantisation into 17-33 Nm of noise).
DEFAULT_KD_NMS_PER_RAD = 20.0
DEFAULT_VELOCITY_FILTER_HZ = 50.0


@njit(cache=True)
def _motor_pd(
    q_ref: np.ndarray,
    dq_ref: np.ndarray,
    feedforward: np.ndarray,
    theta: np.ndarray,
    state: np.ndarray,
    gains: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """One tick for every joint. ``state`` rows: previous theta, filtered velocity;
    ``gains`` rows: kp, kd, 1/k, filter alpha, 1/dt, torque limit."""
    for j in range(q_ref.shape[0]):
        rate = (theta[j] - state[0, j]) * gains[4, j]
        state[0, j] = theta[j]
        state[1, j] += gains[3, j] * (rate - state[1, j])
        theta_ref = q_ref[j] + feedforward[j] * gains[2, j]
        torque = feedforward[j] + gains[0, j] * (theta_ref - theta[j]) + gains[1, j] * (dq_ref[j] - state[1, j])
        limit = gains[5, j]
        out[j] = min(max(torque, -limit), limit)


@njit(cache=True)
def _motor_pd_linear_feedforward(
    q_ref: np.ndarray,
    dq_ref: np.ndarray,
    theta: np.ndarray,
    state: np.ndarray,
    gains: np.ndarray,
    model: np.ndarray,
    feedforward: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """:func:`_motor_pd` with a linear model's torque at ``q_ref`` as feed-forward, in one compiled call."""
    linear_torque(q_ref, model, feedforward)
    _motor_pd(q_ref, dq_ref, feedforward, theta, state, gains, out)


@njit(cache=True)
def _motor_pd_table(
    t: float,
    starts: np.ndarray,
    coefficients: np.ndarray,
    cursor: np.ndarray,
    theta: np.ndarray,
    state: np.ndarray,
    gains: np.ndarray,
    model: np.ndarray,
    scratch: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The whole controller for a piecewise-cubic reference, in one compiled call.

    Finds the piece of time ``t`` (advancing ``cursor[0]`` from the last tick's piece: O(1) per
    tick), evaluates q_ref and dq_ref, the linear model's feed-forward at q_ref (when
    ``model.size > 0``) and the PD. ``scratch`` (12,): q_ref, dq_ref, feed-forward.
    """
    n = starts.shape[0]
    k = int(cursor[0])
    if t < starts[k]:
        k = max(int(np.searchsorted(starts, t, side="right")) - 1, 0)
    while k + 1 < n and t >= starts[k + 1]:
        k += 1
    cursor[0] = k
    tau = max(t - starts[k], 0.0)
    for r in range(8):
        scratch[r] = coefficients[k, r, 0] + tau * (
            coefficients[k, r, 1] + tau * (coefficients[k, r, 2] + tau * coefficients[k, r, 3])
        )
    if model.size > 0:
        linear_torque(scratch[0:4], model, scratch[8:12])
    else:
        scratch[8:12] = 0.0
    _motor_pd(scratch[0:4], scratch[4:8], scratch[8:12], theta, state, gains, out)


# The controller's memory (MotorPositionPD._memory): its reference time, the piece cursor, the
# filter state (2 x 4), the gains (6 x 4), the scratch (12) and the linear model's parameters.
_MEMORY_T0 = 0
_MEMORY_CURSOR = 1
_MEMORY_STATE = 2
_MEMORY_GAINS = _MEMORY_STATE + 2 * N_JOINTS
_MEMORY_SCRATCH = _MEMORY_GAINS + 6 * N_JOINTS
_MEMORY_MODEL = _MEMORY_SCRATCH + 3 * N_JOINTS


@njit(cache=True)
def _motor_pd_batch_step(
    t_s: float,
    readings: np.ndarray,
    row: int,
    memory: np.ndarray,
    knots: np.ndarray,
    table: np.ndarray,
    out: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """:meth:`MotorPositionPD.update` on a batch's readings (:data:`~daror_runtime.control.base.CONTROLLER_STEP`).

    The sample's theta is row ``row + 2`` of ``readings`` (:data:`hal.kernels.READING_ROWS`); the
    controller's arrays are the slices of ``memory`` its views are.
    """
    _motor_pd_table(
        t_s - memory[_MEMORY_T0],
        knots,
        table,
        memory[_MEMORY_CURSOR : _MEMORY_CURSOR + 1],
        readings[row + 2],
        memory[_MEMORY_STATE:_MEMORY_GAINS].reshape((2, N_JOINTS)),
        memory[_MEMORY_GAINS:_MEMORY_SCRATCH].reshape((6, N_JOINTS)),
        memory[_MEMORY_MODEL:],
        memory[_MEMORY_SCRATCH:_MEMORY_MODEL],
        out,
    )
    return 0


#: What :func:`_motor_pd_table` is resolved for: the time, the reference table (its knots and
#: coefficients), the controller's own arrays (cursor, state, gains, model, scratch, output), all
#: float64 arrays it makes itself, and a checked sample's theta (:data:`hal.kernels.SAMPLE_VECTOR`).
TABLE_SIGNATURE = (
    types.float64,
    types.float64[::1],
    types.float64[:, :, ::1],
    types.float64[::1],
    SAMPLE_VECTOR,
    types.float64[:, ::1],
    types.float64[:, ::1],
    types.float64[::1],
    types.float64[::1],
    types.float64[::1],
)


# Memoised: a pure function of its numbers, evaluated 192 times by every session's start-up (the gains of each
# position controller checked over the inertia, gravity and margin cases), ~33 distinct cases in all. The
# scipy expm of a 5 x 5 matrix costs 0.1 ms alone and up to 10 ms when OpenBLAS threads compete for a busy
# machine's cores: 0.2-2 s a session built, now once a process.
@functools.lru_cache(maxsize=1024)
def motor_loop_spectral_radius(
    kp: float,
    kd: float,
    motor_inertia_kgm2: float,
    motor_viscous_nms_per_rad: float,
    spring_nm_per_rad: float,
    link_inertia_kgm2: float,
    gravity_stiffness_nm_per_rad: float,
    velocity_filter_hz: float,
    dt_s: float,
    delay_ticks: int = 1,
    spring_damping_nms_per_rad: float = 0.0,
) -> float:
    """Spectral radius of one joint's closed loop in discrete time (below 1: stable).

    Continuous mechanics (motor on the spring, the link on the spring with a gravity stiffness
    that pulls away from the reference: ``-g_s q``), sampled with zero-order hold; the controller
    sees theta at the tick, filters the backward difference, and its command acts
    ``delay_ticks`` ticks later.
    """
    k, j_m, b_m, i_l = spring_nm_per_rad, motor_inertia_kgm2, motor_viscous_nms_per_rad, link_inertia_kgm2
    d = spring_damping_nms_per_rad
    # state x = [theta, theta', q, q'], input u = motor torque
    a = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-k / j_m, -(b_m + d) / j_m, k / j_m, d / j_m],
            [0.0, 0.0, 0.0, 1.0],
            [k / i_l, d / i_l, (gravity_stiffness_nm_per_rad - k) / i_l, -d / i_l],
        ]
    )
    b = np.array([[0.0], [1.0 / j_m], [0.0], [0.0]])
    m = scipy.linalg.expm(np.block([[a, b], [np.zeros((1, 5))]]) * dt_s)
    ad, bd = m[:4, :4], m[:4, 4:]
    alpha = 1.0 - math.exp(-2.0 * math.pi * velocity_filter_hz * dt_s)
    # discrete state z = [x (4), previous theta, filtered velocity, queued commands (delay_ticks)]
    n = 6 + delay_ticks
    big = np.zeros((n, n))
    big[:4, :4] = ad
    big[:4, 6:7] = bd  # the oldest queued command acts now
    big[4, 0] = 1.0  # previous theta <- theta
    # filtered velocity <- v + alpha ((theta - theta_prev)/dt - v)
    big[5, 0] = alpha / dt_s
    big[5, 4] = -alpha / dt_s
    big[5, 5] = 1.0 - alpha
    # the new command (from this tick's readings, after the filter update) enters the queue's end
    row = np.zeros(n)
    row[0] = -kp - kd * alpha / dt_s
    row[4] = kd * alpha / dt_s
    row[5] = -kd * (1.0 - alpha)
    for d in range(delay_ticks - 1):
        big[6 + d, 7 + d] = 1.0
    big[6 + delay_ticks - 1] = row
    return float(np.max(np.abs(np.linalg.eigvals(big))))


class MotorPositionPD:
    """Collocated joint position PD on the motor angle, with gravity feed-forward; a :class:`Controller`.

    Args:
        description: the robot (spring stiffness, nominal gearbox inertia and friction, saturation).
        reference: ``t_s -> (q_ref (4,), dq_ref (4,))``, ``t_s`` counted from the reset sample. A
            reference with a ``piecewise_table`` (a ReferenceTrajectory) is evaluated inside the
            compiled controller (with no feed-forward or a linear one): the identification's fast path.
        bounds: link inertia and gravity-stiffness ranges the gains are checked over.
        kp_nm_per_rad, kd_nms_per_rad: gains (scalar or per joint).
        feedforward: compensation model (or a hold's held torque) evaluated at the reference (None: none).
        velocity_filter_hz: first-order low-pass of the motor velocity estimate.
        delay_ticks: command delay of the drives the gains are checked for.
        slowest_decay_s: every mode must decay with a time constant below this (nominal gains).
        gain_margin: the gains multiplied by this must still give a stable loop.
        inertia_tolerance: the nominal gearbox inertia is checked at (1 -+ this).
        spring_damping_nms_per_rad: the least internal damping of the torsion springs assumed (the
            same lower bound the torque controller's passivity design assumes, docs/control.md).
        max_start_error_rad: :meth:`reset` refuses a reference that starts this far from the robot.

    Raises:
        ControlSettingError: gains not positive and finite.
        ControlDesignError: the gains make a checked case unstable (the message names joint and case).
    """

    def __init__(
        self,
        description: RobotDescription,
        reference: Reference,
        bounds: LinkBounds,
        kp_nm_per_rad: float | FloatArray = DEFAULT_KP_NM_PER_RAD,
        kd_nms_per_rad: float | FloatArray = DEFAULT_KD_NMS_PER_RAD,
        *,
        feedforward: Feedforward | None = None,
        velocity_filter_hz: float = DEFAULT_VELOCITY_FILTER_HZ,
        dt_s: float = 1e-3,
        delay_ticks: int = 1,
        slowest_decay_s: float = 2.0,
        gain_margin: float = 1.5,
        inertia_tolerance: float = 0.2,
        spring_damping_nms_per_rad: float = 0.05,
        max_start_error_rad: float = 0.05,
    ) -> None:
        kp = np.broadcast_to(np.asarray(kp_nm_per_rad, dtype=float), (N_JOINTS,)).copy()
        kd = np.broadcast_to(np.asarray(kd_nms_per_rad, dtype=float), (N_JOINTS,)).copy()
        if not (np.all(np.isfinite(kp)) and np.all(np.isfinite(kd)) and np.all(kp > 0) and np.all(kd >= 0)):
            raise ControlSettingError(f"motor position gains must be finite, K_p > 0, K_d >= 0; got {kp}, {kd}")
        sea = description.sea
        self.reference = reference
        self.feedforward = feedforward
        self.max_start_error_rad = max_start_error_rad
        self.spring_nm_per_rad = sea.spring_stiffness_nm_per_rad
        limit = math.exp(-dt_s / slowest_decay_s)  # spectral radius of a mode decaying with that time constant
        radius = np.zeros(N_JOINTS)
        for j in range(N_JOINTS):
            for inertia in (
                sea.gearbox_inertia_kgm2 * (1 - inertia_tolerance),
                sea.gearbox_inertia_kgm2 * (1 + inertia_tolerance),
            ):
                for link in (bounds.inertia_min_kgm2[j], bounds.inertia_max_kgm2[j]):
                    for gravity in (0.0, bounds.gravity_stiffness_nm_per_rad[j]):
                        for scale, bound, what in (
                            (1.0, limit, "decays too slowly"),
                            (gain_margin, 1.0, "is unstable"),
                        ):
                            r = motor_loop_spectral_radius(
                                scale * kp[j], scale * kd[j], inertia, 0.0, sea.spring_stiffness_nm_per_rad, link,
                                gravity, velocity_filter_hz, dt_s, delay_ticks, spring_damping_nms_per_rad,
                            )  # fmt: skip
                            if r >= bound:
                                what = "is unstable" if r >= 1.0 else what
                                raise ControlDesignError(
                                    f"joint {j + 1}: with motor position gains {scale:g} x (K_p {kp[j]:g}, K_d {kd[j]:g}) the "
                                    f"loop {what} (spectral radius {r:.5f}, limit {bound:.5f}) with gearbox inertia "
                                    f"{inertia:.3g} kg m^2, link inertia {link:.3g} kg m^2, gravity stiffness "
                                    f"{gravity:.3g} Nm/rad"
                                )
                            if scale == 1.0:
                                radius[j] = max(radius[j], r)
        self.kp_nm_per_rad, self.kd_nms_per_rad = kp, kd
        self.spectral_radius = radius
        alpha = 1.0 - math.exp(-2.0 * math.pi * velocity_filter_hz * dt_s)
        self._zero = np.zeros(N_JOINTS)
        self._feedforward = np.zeros(N_JOINTS)
        # The compiled paths are compiled with linear_torque: a model offering that kernel (AP, PLF,
        # PLF+) runs inside them; any other feed-forward (a hold's held torque offers none) runs
        # through its torque().
        kernel = feedforward.tick_kernel() if feedforward is not None else None
        self._linear = kernel.parameters if kernel is not None and kernel.function is linear_torque else None
        # Every number the controller keeps between ticks, in one array (MEMORY_* layout): the
        # arrays below are views of it, so the compiled batch tick (_motor_pd_batch_step) and update
        # work on the very same state.
        n_model = 0 if self._linear is None else int(np.asarray(self._linear).size)
        self._memory = np.zeros(_MEMORY_MODEL + n_model)
        self._cursor = self._memory[_MEMORY_CURSOR : _MEMORY_CURSOR + 1]
        self._state = self._memory[_MEMORY_STATE:_MEMORY_GAINS].reshape(2, N_JOINTS)
        self._gains = self._memory[_MEMORY_GAINS:_MEMORY_SCRATCH].reshape(6, N_JOINTS)
        self._scratch = self._memory[_MEMORY_SCRATCH:_MEMORY_MODEL]
        self._gains[:] = (
            kp,
            kd,
            np.full(N_JOINTS, 1.0 / sea.spring_stiffness_nm_per_rad),
            np.full(N_JOINTS, alpha),
            np.full(N_JOINTS, 1.0 / dt_s),
            np.full(N_JOINTS, sea.max_motor_torque_nm),
        )
        table = getattr(reference, "piecewise_table", None)
        # The compiled path needs the feed-forward compiled too: none, or a model offering linear_torque.
        # Its arrays as float64 C-contiguous arrays (no copy when they are already: the types the
        # kernel's entry point is resolved for).
        self._table = (
            (np.ascontiguousarray(table[0], dtype=np.float64), np.ascontiguousarray(table[1], dtype=np.float64))
            if table is not None and (feedforward is None or self._linear is not None)
            else None
        )
        self._model_or_empty = self._memory[_MEMORY_MODEL:]
        if self._linear is not None:
            self._model_or_empty[:] = np.asarray(self._linear, dtype=np.float64).ravel()
        # A CheckedSample's theta goes to this entry point (no type dispatch); any other through the dispatcher.
        self._table_checked = entry_point(_motor_pd_table, TABLE_SIGNATURE) if self._table is not None else None
        self._t0_s = 0.0
        self._compiled_tick: CompiledControllerTick | None = None

    def reset(self, sample: Sample) -> None:
        """Start the reference clock at this sample; the filter starts at rest.

        Raises:
            ControlError: the reference starts farther than ``max_start_error_rad`` from the robot.
        """
        q_ref, _ = self.reference(0.0)
        error = np.abs(np.asarray(q_ref) - sample.q_rad)
        if np.any(error > self.max_start_error_rad):
            j = int(np.argmax(error))
            raise ControlError(
                f"the reference starts {error[j]:.3f} rad from joint {j + 1} (limit {self.max_start_error_rad} rad); "
                "move the robot to the start first"
            )
        self._t0_s = sample.t_s
        self._memory[_MEMORY_T0] = sample.t_s
        self._state[0] = sample.theta_rad
        self._state[1] = 0.0
        self._cursor[0] = 0.0

    def compiled_tick(self) -> CompiledControllerTick | None:
        """The controller's tick for lock-step batches (with a tabulated reference), or None.

        The batch tick is :meth:`update` on a sample at the batch's readings: the same compiled
        arithmetic (:func:`_motor_pd_table`) on the same memory. Loaded once, outside any tick.
        """
        if self._table is None:
            return None
        if self._compiled_tick is None:
            step = CompiledFunction(_motor_pd_batch_step, CONTROLLER_STEP)
            self._compiled_tick = CompiledControllerTick(step, self._memory, self._table[0], self._table[1])
        return self._compiled_tick

    def update(self, sample: Sample, dt_s: float) -> Command:
        out = np.empty(N_JOINTS)  # a new array each tick: a command is a record, nobody changes it later
        table = self._table
        if table is not None:  # a piecewise-cubic reference: one compiled call does everything
            (self._table_checked if type(sample) is CheckedSample else _motor_pd_table)(
                sample.t_s - self._t0_s, table[0], table[1], self._cursor, sample.theta_rad, self._state,
                self._gains, self._model_or_empty, self._scratch, out,
            )  # fmt: skip
            return _new_tuple(CheckedCommand, (out, True, ()))  # out: float64 (4,), so a CheckedCommand as it is
        q_ref, dq_ref = self.reference(sample.t_s - self._t0_s)
        if self._linear is not None:  # AP, PLF, PLF+: the model runs inside the compiled controller
            _motor_pd_linear_feedforward(
                q_ref, dq_ref, sample.theta_rad, self._state, self._gains, self._linear, self._feedforward, out
            )
        else:
            feedforward = self._zero if self.feedforward is None else self.feedforward.torque(q_ref)
            _motor_pd(q_ref, dq_ref, feedforward, sample.theta_rad, self._state, self._gains, out)
        return _new_tuple(CheckedCommand, (out, True, ()))
