"""SEA torque control with a disturbance observer, as it runs in the tick (thesis Sec. 2.2.3, Fig. 2.5).

Per joint, with ``tau = k (theta - q)`` the spring torque from the two encoders and ``theta`` the
motor-side angle::

                 +---------------------- DOB: d_hat = [Q H_n^-1] tau - [Q] u ----------------------+
                 |                                                                                ^ tau
    tau_ref -> [limit] -> [slew] -(+)-> u -+-> C_ff = 1 - (1 - w) D -(+)-> [sat] -> [1 tick] -> SEA -+
                       - alpha d_hat       +-> C = K_p + D on (u - tau) -^   (anti-windup on u; optional
                                                                              motor damping -K_v D(z) theta)

The filters C, D, H_n, Q and the gain alpha are designed once, before the loop, by
:mod:`daror_runtime.control.sea_torque_design` (which explains each); this module holds what runs
every tick: the controller's state and its compiled kernel.

The regulated torque is ``k (theta - q)`` from the sample's encoders (``torque_from_encoders``):
the same as the drive's reading on hardware that computes it from those encoders, but free of a
reading error that switches with the direction of motion (Sec. 2.2.2), which fed back drives a
~30 Hz limit cycle (docs/control.md).

Limits: the reference is clipped to what the spring carries before its end stop and slew-limited
(500 Nm/s); the observer's correction to the motor limit; the motor torque to
``description.sea.max_motor_torque_nm``.

**Soft start.** A joint whose drive was not enabled when the controller was reset (torque comes back
after an e-stop, a fault, a disabled start) has a motor that coasts on the spring: its filters start
at rest but the motor does not, and the first commands would answer that motion with a step of
several Nm. Such a joint's command is brought in over :data:`SOFT_START_S` (a weight from 0 to 1):
the first command is near zero, like the torque the disabled drive applied. Anti-windup: the ``u`` fed to the observer and to D is
recomputed as the value that would have produced exactly the clipped torque (back-calculation
through the direct feedthrough ``1 + K_p + w D``), so no state winds up while saturated.

The per-tick work of all four joints runs in one compiled kernel (:mod:`numba`, compiled when
this module is imported, never inside the tick) on the filter matrices of
:class:`~daror_runtime.control.filters.FilterBank`. :meth:`SeaTorqueController.linear_model`
returns the same filters as one state-space system for the analysis.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from daror_runtime.control.base import ControlDesignError, ControlError
from daror_runtime.control.filters import FilterBank
from daror_runtime.control.sea_torque_design import SeaTorqueDesign, design_inner_loop
from daror_runtime.errors import ShapeError
from hal.interface import DriveState, Sample
from hal.robot import N_JOINTS, FloatArray, SeaConstants

# --- the per-tick kernel ---------------------------------------------------------------------

#: Inputs: any layout, read-only accepted (a sample's arrays may be frozen); writable arrays match too.
_VEC = numba.types.Array(numba.float64, 1, "A", readonly=True)
_F1 = numba.float64[::1]
_F2 = numba.float64[:, ::1]
_F3 = numba.float64[:, :, ::1]
_F4 = numba.float64[:, :, :, ::1]

#: How long a joint whose drive was off at the reset takes to get its whole command (s): the soft start.
SOFT_START_S = 0.05

#: Bank order in the stacked arrays the kernel reads.
_BANK_MODEL, _BANK_Q, _BANK_C, _BANK_D = 0, 1, 2, 3


#: Rows of the ``work`` array: alpha, K_v, torque limit, the direct feedthrough D of each bank, and
#: the diagnostics written every tick (observer estimate d_hat, inner-loop reference u applied).
#: Then C's proportional gain, the weight of u in the derivative's input (1 on the error, 0 on the
#: measurement), the limit of the torque reference, its largest change per tick, and the reference
#: applied in the previous tick (the slew limiter's state).
_W_ALPHA, _W_KV, _W_LIMIT, _W_D = 0, 1, 2, 3  # _W_D .. _W_D + 3: one row per bank
_W_DHAT, _W_U, _W_KP, _W_WU, _W_REF, _W_SLEW, _W_PREV = 7, 8, 9, 10, 11, 12, 13
#: Spring stiffness, and 1 where the loop regulates the encoders' deflection torque k (theta - q)
#: instead of the drive's torque reading.
_W_K, _W_DEFLECTION = 14, 15
_W_ROWS = 16
#: ``abcx[bank, joint]`` is one filter: columns ``[:n]`` its A, then one column each for B, C and the state x.
#: One array instead of four keeps the kernel's argument count (numba's call overhead) low.


@numba.njit(cache=True, inline="always")
def _advance(abcx, bank, j, u, scratch):  # pragma: no cover - compiled
    n = abcx.shape[2]
    for m in range(n):
        acc = abcx[bank, j, m, n] * u
        for i in range(n):
            acc += abcx[bank, j, m, i] * abcx[bank, j, i, n + 2]
        scratch[m] = acc
    for m in range(n):
        abcx[bank, j, m, n + 2] = scratch[m]


@numba.njit(cache=True, inline="always")
def _output(work, abcx, bank, j, u):  # pragma: no cover - compiled
    n = abcx.shape[2]
    y = work[_W_D + bank, j] * u
    for m in range(n):
        y += abcx[bank, j, m, n + 1] * abcx[bank, j, m, n + 2]
    return y


@numba.njit(numba.int64(_VEC, _VEC, _VEC, _VEC, _F2, _F4, _F1), cache=True, nogil=True)
def _torque_kernel(tau_ref, tau_meas, theta, q, work, abcx, command):  # pragma: no cover - compiled
    """One tick of every joint: writes ``command`` and the diagnostics rows of ``work``.

    Returns 0; -1 when an input does not have one value per joint; or the 1-based joint whose
    inputs are not finite. Nothing is changed unless it returns 0.
    """
    n_joints = work.shape[1]
    # numba does not check bounds: a short array must be refused here, before any indexing.
    if tau_ref.shape[0] != n_joints or tau_meas.shape[0] != n_joints or theta.shape[0] != n_joints:
        return -1
    if q.shape[0] != n_joints:
        return -1
    if command.shape[0] != n_joints:
        return -1
    # Validate everything before touching any state: a bad sample must leave the controller intact.
    for j in range(n_joints):
        if not (np.isfinite(tau_ref[j]) and np.isfinite(tau_meas[j]) and np.isfinite(theta[j])):
            return j + 1
        if not np.isfinite(q[j]):
            return j + 1
    scratch = np.empty(abcx.shape[2])
    for j in range(n_joints):
        alpha, k_v, limit = work[_W_ALPHA, j], work[_W_KV, j], work[_W_LIMIT, j]
        kp, w_u = work[_W_KP, j], work[_W_WU, j]
        # A reference the spring cannot carry would pin the motor at its limit, where the loop can no
        # longer damp the motor against the spring: it would ring up to twice the limit.
        reference = min(max(tau_ref[j], -work[_W_REF, j]), work[_W_REF, j])
        # Slew limit: a reference step would pin the motor at its limit for tens of ticks, unable to
        # brake the motor inertia: the spring torque then overshoots by a third of the step.
        previous, slew = work[_W_PREV, j], work[_W_SLEW, j]
        reference = min(max(reference, previous - slew), previous + slew)
        # The torque the loop regulates: the encoders' deflection k (theta - q), or the drive's reading.
        # On a drive that computes its reading from these encoders they are the same; a reading error
        # that switches with the direction of motion (Sec. 2.2.2) is not: fed back, it drives a
        # ~30 Hz limit cycle (the reaction to each switch reverses the motion again).
        use_encoders = work[_W_DEFLECTION, j]
        measured = use_encoders * work[_W_K, j] * (theta[j] - q[j]) + (1.0 - use_encoders) * tau_meas[j]
        d_hat = _output(work, abcx, _BANK_MODEL, j, measured) - _output(work, abcx, _BANK_Q, j, 0.0)
        # The observer may never ask for more than the motor can give (e.g. a link held at an end stop).
        correction = min(max(alpha * d_hat, -limit), limit)
        u = reference - correction
        derivative = _output(work, abcx, _BANK_C, j, w_u * u - measured)
        raw = u + kp * (u - measured) + derivative - k_v * _output(work, abcx, _BANK_D, j, theta[j])
        clipped = min(max(raw, -limit), limit)
        # Back-calculation: the u that would have produced exactly the clipped torque.
        u_applied = u - (raw - clipped) / (1.0 + kp + w_u * work[_W_D + _BANK_C, j])
        _advance(abcx, _BANK_MODEL, j, measured, scratch)
        _advance(abcx, _BANK_Q, j, u_applied, scratch)
        _advance(abcx, _BANK_C, j, w_u * u_applied - measured, scratch)
        _advance(abcx, _BANK_D, j, theta[j], scratch)
        command[j] = clipped
        work[_W_PREV, j] = reference
        work[_W_DHAT, j] = d_hat
        work[_W_U, j] = u_applied
    return 0


def _stack(banks: tuple[FilterBank, ...]) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Stack banks into (bank, joint, ...) arrays padded to one order (padding states are inert)."""
    n_banks, n_joints = len(banks), banks[0].channels
    order = max(bank.order for bank in banks)
    a = np.zeros((n_banks, n_joints, order, order))
    b = np.zeros((n_banks, n_joints, order))
    c = np.zeros((n_banks, n_joints, order))
    d = np.zeros((n_banks, n_joints))
    for i, bank in enumerate(banks):
        m = bank.order
        a[i, :, :m, :m] = bank.a
        b[i, :, :m] = bank.b
        c[i, :, :m] = bank.c
        d[i] = bank.d
    return a, b, c, d


class SeaTorqueController:
    """Torque control of the four SEAs: ``motor_torque(tau_ref, sample, dt_s) -> (4,)`` in Nm.

    Not a :class:`~daror_runtime.control.base.Controller` itself: the modes of
    :mod:`daror_runtime.control.modes` own one and give it their torque reference.

    Args:
        sea: the nominal SEA model (``description.sea``) the filters are designed on; its
            ``max_motor_torque_nm`` is the saturation.
        design: the tuning; default :class:`SeaTorqueDesign` ().
        n_joints: joints controlled (4 for the DAROR-01; 1 for single-joint analysis).

    Raises:
        ControlDesignError: the design is invalid for this SEA.
    """

    def __init__(self, sea: SeaConstants, design: SeaTorqueDesign | None = None, n_joints: int = N_JOINTS) -> None:
        self.sea = sea
        self.design = design or SeaTorqueDesign()
        self.n_joints = n_joints
        self.loop = design_inner_loop(sea, self.design)
        self._dob_model = FilterBank.replicate(self.loop.q_inverse_model, n_joints)
        self._dob_q = FilterBank.replicate(self.loop.q_filter, n_joints)
        if np.any(self._dob_q.d != 0.0):
            raise ControlDesignError("Q must be strictly proper so the observer has no algebraic loop")
        self._derivative = FilterBank.replicate(self.loop.derivative, n_joints)
        self._motor_velocity = FilterBank.replicate(self.loop.motor_velocity, n_joints)
        a, b, c, d = _stack(self._banks)
        self._work = np.zeros((_W_ROWS, n_joints))
        self._work[_W_ALPHA] = self.design.alpha
        self._work[_W_KV] = self.design.motor_damping_nms_per_rad
        self._work[_W_LIMIT] = sea.max_motor_torque_nm
        self._work[_W_D : _W_D + 4] = d
        self._work[_W_KP] = self.loop.kp
        self._work[_W_WU] = self.loop.derivative_weight
        self._work[_W_REF] = min(
            sea.max_motor_torque_nm, sea.spring_stiffness_nm_per_rad * sea.max_spring_deflection_rad
        )
        self._work[_W_SLEW] = self.design.reference_slew_nm_per_s * self.design.period_s
        self._work[_W_K] = sea.spring_stiffness_nm_per_rad
        self._work[_W_DEFLECTION] = 1.0 if self.design.torque_from_encoders else 0.0
        self._abcx = np.ascontiguousarray(
            np.concatenate([a, b[..., None], c[..., None], np.zeros_like(b)[..., None]], -1)
        )
        self._soft = np.ones(n_joints)  # the soft start's weight per joint (1: the whole command)
        self._softening = False

    @property
    def _banks(self) -> tuple[FilterBank, ...]:
        return (self._dob_model, self._dob_q, self._derivative, self._motor_velocity)

    def reset(self, sample: Sample | None = None) -> None:
        """Start every filter at rest at the sample's torque and motor angle (zeros if None).

        Every filter starts as if the present torque had been commanded forever: the observer's
        estimate starts at zero and nothing kicks the motor when a mode takes over.

        Raises:
            ControlError: the sample holds non-finite values.
        """
        if sample is None:
            tau0, theta0 = np.zeros(self.n_joints), np.zeros(self.n_joints)
        else:
            theta0 = np.asarray(sample.theta_rad, dtype=float)
            tau0 = self.spring_torque_nm(sample)
            if not (np.all(np.isfinite(tau0)) and np.all(np.isfinite(theta0))):
                raise ControlError("cannot start the torque controller from a sample with non-finite torque or angle")
        # Every filter in the steady state of "this torque, commanded forever": the derivative's input
        # is then w u - tau = (w - 1) tau0, and a filter left at zero would kick the motor on entry.
        inputs = (tau0, tau0, (self.loop.derivative_weight - 1.0) * tau0, theta0)
        for i, (bank, u0) in enumerate(zip(self._banks, inputs, strict=True)):
            bank.reset(u0)
            n = self._abcx.shape[2]
            self._abcx[i, :, :, n + 2] = 0.0
            self._abcx[i, :, : bank.order, n + 2] = bank.x
        self._work[_W_DHAT] = 0.0
        self._work[_W_U] = tau0
        self._work[_W_PREV] = tau0  # the reference slews from the torque the springs carry now
        self._soft[:] = 1.0
        if sample is not None:
            for j, drive in enumerate(sample.drives[: self.n_joints]):
                if drive != DriveState.ENABLED:  # its motor coasts on the spring: bring the command in softly
                    self._soft[j] = 0.0
        self._softening = bool(np.any(self._soft < 1.0))

    @property
    def regulates_reading_error(self) -> bool:
        """True when the torque this loop regulates carries the torque reading's hysteresis.

        The drive's reading carries it (the residual analysis measured it there); ``k (theta - q)``
        from the encoders only when the design says the error is in the encoders themselves
        (``reading_error_in_encoders``). A model's reading error is corrected exactly when this is True.
        """
        return not self.design.torque_from_encoders or self.design.reading_error_in_encoders

    def spring_torque_nm(self, sample: Sample) -> FloatArray:
        """The spring torque (n_joints,) in Nm this controller regulates, read from ``sample``.

        ``k (theta - q)`` from the two encoders (``torque_from_encoders``) or the drive's reading.
        """
        if self.design.torque_from_encoders:
            return self.sea.spring_stiffness_nm_per_rad * (
                np.asarray(sample.theta_rad, dtype=float) - np.asarray(sample.q_rad, dtype=float)
            )
        return np.array(sample.tau_nm, dtype=float)

    def motor_torque(self, tau_ref_nm: FloatArray, sample: Sample, dt_s: float) -> FloatArray:
        """Motor torque (n_joints,) in Nm at the gearbox output, within +-``max_motor_torque_nm``.

        The reference is first limited to what the spring can carry before its end stop
        (``k x max_spring_deflection_rad``, 34.7 Nm), which leaves the loop headroom to damp.

        The filters run at the design period; ``dt_s`` (s) is checked, not used: an overrun is the
        loop watchdog's business, the discrete filters stay consistent through it.

        Raises:
            ShapeError: ``tau_ref_nm`` or the sample arrays are not of shape (n_joints,).
            ControlError: ``dt_s`` is not a positive finite number, or a non-finite reference or
                reading (joint named); the controller's state is not changed.
        """
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ControlError(f"tick period must be a positive finite number of seconds, got {dt_s!r}")
        command = np.empty(self.n_joints)
        tau_ref, tau_meas, theta, q = tau_ref_nm, sample.tau_nm, sample.theta_rad, sample.q_rad
        try:
            status = _torque_kernel(tau_ref, tau_meas, theta, q, self._work, self._abcx, command)
        except TypeError:  # not float64 vectors: convert (or refuse), then the same kernel
            tau_ref = _vector(tau_ref_nm, self.n_joints, "torque reference")
            tau_meas = _vector(sample.tau_nm, self.n_joints, "measured torque")
            theta = _vector(sample.theta_rad, self.n_joints, "motor angle")
            q = _vector(sample.q_rad, self.n_joints, "link angle")
            status = _torque_kernel(tau_ref, tau_meas, theta, q, self._work, self._abcx, command)
        if status == -1:
            named = (
                (tau_ref, "torque reference"),
                (tau_meas, "measured torque"),
                (theta, "motor angle"),
                (q, "link angle"),
            )
            for values, what in named:
                _vector(values, self.n_joints, what)
        if status:
            j = status - 1
            raise ControlError(
                f"joint {status}: non-finite torque reference ({tau_ref[j]}), measured torque ({tau_meas[j]}), "
                f"motor angle ({theta[j]}) or link angle ({q[j]}); torque controller not advanced"
            )
        if self._softening:
            soft = self._soft
            command *= soft
            np.minimum(soft + self.design.period_s / SOFT_START_S, 1.0, out=soft)
            self._softening = bool(np.any(soft < 1.0))
        return command

    def linear_model(self, joint: int = 1) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The controller of ``joint`` (1-based) as one discrete state-space system, saturation ignored.

        Inputs ``[tau_ref, tau_meas, theta]``, output the motor torque command; returns
        ``(A, B (n, 3), C (1, n), D (1, 3))``. Built from the very filter matrices the kernel runs.
        ``tau_meas`` stands for the regulated torque: with ``torque_from_encoders`` that is
        ``k (theta - q)``, the same signal in the linear (error-free) plant. The reference limit
        and slew limiter are not part of it (they act only on large, fast references).

        Raises:
            ShapeError: ``joint`` out of range.
        """
        if not 1 <= joint <= self.n_joints:
            raise ShapeError(f"joint must be 1..{self.n_joints}, got {joint}")
        j = joint - 1
        alpha, k_v, kp, w_u = (self._work[row, j] for row in (_W_ALPHA, _W_KV, _W_KP, _W_WU))
        blocks = [(bank.a[j], bank.b[j], bank.c[j], bank.d[j]) for bank in self._banks]
        sizes = [blk[0].shape[0] for blk in blocks]
        n = sum(sizes)
        offsets = np.cumsum([0, *sizes])
        s1, s2, sc, sv = (slice(offsets[i], offsets[i + 1]) for i in range(4))
        (a1, b1, c1, d1), (a2, b2, c2, _), (ac, bc, cc, dc), (av, bv, cv, dv) = blocks
        # Each signal as (row over the state, row over the inputs [ref, meas, theta]).
        d_hat_x = np.zeros(n)
        d_hat_x[s1], d_hat_x[s2] = c1, -c2
        d_hat_u = np.array([0.0, d1, 0.0])
        u_x, u_u = -alpha * d_hat_x, np.array([1.0, 0.0, 0.0]) - alpha * d_hat_u
        e_x, e_u = u_x, u_u - np.array([0.0, 1.0, 0.0])  # torque error
        din_x, din_u = w_u * u_x, w_u * u_u - np.array([0.0, 1.0, 0.0])  # the derivative's input
        yc_x, yc_u = kp * e_x + dc * din_x, kp * e_u + dc * din_u
        yc_x[sc] += cc
        w_x, w_u = np.zeros(n), np.array([0.0, 0.0, dv])
        w_x[sv] = cv
        out_x, out_u = u_x + yc_x - k_v * w_x, u_u + yc_u - k_v * w_u
        a = np.zeros((n, n))
        b = np.zeros((n, 3))
        a[s1, s1], b[s1, 1] = a1, b1
        a[s2, s2] = a2
        a[s2] += np.outer(b2, u_x)
        b[s2] += np.outer(b2, u_u)
        a[sc, sc] = ac
        a[sc] += np.outer(bc, din_x)
        b[sc] += np.outer(bc, din_u)
        a[sv, sv], b[sv, 2] = av, bv
        return a, b, out_x[None, :], out_u[None, :]


def _vector(values: FloatArray, n: int, what: str) -> FloatArray:
    """``values`` as a float64 (n,) array.

    Raises:
        ShapeError: not convertible to, or not of, shape (n,).
    """
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ShapeError(f"{what} must be {n} numbers, got {values!r}") from None
    if array.shape != (n,):
        raise ShapeError(f"{what} must have shape ({n},), got {array.shape}")
    return array
