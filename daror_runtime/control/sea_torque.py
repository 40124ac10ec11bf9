"""SEA torque control with a disturbance observer (thesis Sec. 2.2.3, Fig. 2.5, after Rampeltshammer et al.).

Per joint, with ``tau = k (theta - q)`` the spring torque from the two encoders and ``theta`` the
motor-side angle::

                 +---------------------- DOB: d_hat = [Q H_n^-1] tau - [Q] u ----------------------+
                 |                                                                                ^ tau
    tau_ref -> [limit] -> [slew] -(+)-> u -+-> C_ff = 1 - (1 - w) D -(+)-> [sat] -> [1 tick] -> SEA -+
                       - alpha d_hat       +-> C = K_p + D on (u - tau) -^   (anti-windup on u; optional
                                                                              motor damping -K_v D(z) theta)

* **C** (feedback): PD on the torque error with a first-order filtered derivative,
  ``C(s) = K_p + K_d s / (tau_f s + 1)``, discretised with Tustin. The gains come from the tuning
  of Rampeltshammer et al.: on the nominal locked-link SEA ``J s^2 + b s + k`` the loop's
  characteristic polynomial is ``J s^2 + (b + k K_d) s + k (1 + K_p)``, so a chosen natural
  frequency ``w`` and damping ratio ``zeta`` give ``K_p = J w^2 / k - 1`` and
  ``K_d = (2 zeta w J - b) / k`` independently.
* **C_ff = 1 - (1 - w) D(z)** (setpoint weighting of C's derivative, ``derivative_weight`` w):
  the reference reaches the motor through ``1 + K_p + w D``. The ``1``: with the link locked the
  spring torque equals the motor torque at steady state. The ``- (1 - w) D``: with ``C_ff = 1``
  the zero of ``C_ff + C = 1 + K_p + K_d s`` (~5 Hz, slower than the loop's poles) makes a torque
  step overshoot by ~25 %; without any D in the reference path the step takes 60 ms. ``w = 0.75``
  sits between (docs/control.md has the figures).
* **H_n**: the nominal inner closed loop from ``u`` to the measured spring torque, link locked,
  computed *exactly in discrete time*: zero-order-hold SEA model of ``description.sea`` (spring
  damping 0), the command delay, and the discretised C. On the nominal plant the observer
  therefore estimates exactly zero when nothing disturbs the joint.
* **Q**: a binomial low-pass ``1 / (tau s + 1)^N`` (Tustin; default N = 4 at 35 Hz) times ``z^-r``
  with ``r`` the relative degree of H_n (the loop's delay in ticks), so ``Q H_n^-1`` is proper and
  causal. The observer's lag behind the disturbance (Q's low-frequency group delay) is what limits
  the passive alpha, so the cut-off sits well above the torque loop; the order keeps
  ``Q P_n^-1`` rolling off, which is what the observer adds to the motor-torque noise (an optional
  numerator zero, ``dob_lead``, cancels the group delay instead: higher alpha, four times the
  noise). One zero of Q sits on H_n's sampling zero (ZOH, near ``z = -1``) so that ``Q H_n^-1`` has
  no ringing pole there.
* **alpha** in [0, 1] scales the observer's correction. With the nominal plant the apparent
  impedance the pilot feels becomes ``(1 - alpha Q) Z_inner``: at low frequency it is lowered by
  the factor ``1 - alpha``. The largest alpha that keeps the impedance passive for the nominal
  and perturbed plants is chosen by :func:`daror_runtime.control.passivity.choose_alpha`.

The regulated torque is ``k (theta - q)`` from the sample's encoders (``torque_from_encoders``):
the same as the drive's reading on hardware that computes it from those encoders, but free of a
reading error that switches with the direction of motion (Sec. 2.2.2), which fed back drives a
~30 Hz limit cycle (docs/control.md).

Limits: the reference is clipped to what the spring carries before its end stop and slew-limited
(500 Nm/s); the observer's correction to the motor limit; the motor torque to
``description.sea.max_motor_torque_nm``. Anti-windup: the ``u`` fed to the observer and to D is
recomputed as the value that would have produced exactly the clipped torque (back-calculation
through the direct feedthrough ``1 + K_p + w D``), so no state winds up while saturated.

The per-tick work of all four joints runs in one compiled kernel (:mod:`numba`, compiled when
this module is imported, never inside the tick) on the filter matrices of
:class:`~daror_runtime.control.filters.FilterBank`. :meth:`SeaTorqueController.linear_model`
returns the same filters as one state-space system for the analysis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numba
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from daror_runtime.control.base import ControlDesignError, ControlError
from daror_runtime.control.filters import DiscreteTransferFunction, FilterBank
from daror_runtime.errors import ShapeError
from hal.interface import Sample
from hal.robot import N_JOINTS, FloatArray, SeaConstants

#: The observer gain chosen with ``daror_runtime.control.passivity.choose_alpha`` for the default
#: design (docs/control.md: largest passive alpha over the nominal and perturbed plants, times the
#: margin factor). A test re-derives it so this number cannot drift from the analysis.
DEFAULT_ALPHA = 0.58


class SeaTorqueDesign(BaseModel):
    """Tuning of the SEA torque controller; the nominal plant comes from ``description.sea``.

    Frequencies in Hz, damping in Nms/rad, the period in seconds.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    period_s: Annotated[float, Field(gt=0, le=0.01)] = 1e-3
    bandwidth_hz: Annotated[float, Field(gt=0)] = Field(
        10.0, description="natural frequency of the locked-link torque loop on the nominal SEA"
    )
    damping_ratio: Annotated[float, Field(gt=0, le=3)] = 1.0
    derivative_filter_hz: Annotated[float, Field(gt=0)] = Field(50.0, description="first-order filter of C's D part")
    dob_cutoff_hz: Annotated[float, Field(gt=0)] = Field(35.0, description="cut-off of the observer low-pass Q")
    dob_order: Annotated[int, Field(ge=1, le=4)] = Field(4, description="order of the binomial low-pass of Q")
    dob_lead: bool = Field(
        False, description="cancel Q's low-frequency group delay with a numerator zero (raises alpha, and noise x4)"
    )
    alpha: Annotated[float, Field(ge=0, le=1)] = Field(DEFAULT_ALPHA, description="observer gain")
    delay_ticks: Annotated[int, Field(ge=0, le=5)] = Field(1, description="command delay the nominal model assumes")
    derivative_weight: Annotated[float, Field(ge=0, le=1)] = Field(
        0.75, description="share of the reference in the input of C's D part (setpoint weighting): C_ff = 1 - (1 - w) D"
    )
    reference_slew_nm_per_s: Annotated[float, Field(gt=0)] = Field(
        500.0, description="largest rate of change of the torque reference (the observer's correction is not limited)"
    )
    torque_from_encoders: bool = Field(
        True,
        description="regulate k (theta - q) from the sample's two encoders rather than the drive's torque reading",
    )
    motor_damping_nms_per_rad: Annotated[float, Field(ge=0)] = Field(
        0.0, description="K_v: extra damping on the motor-side velocity (from theta); 0 disables it"
    )
    motor_velocity_filter_hz: Annotated[float, Field(gt=0)] = Field(
        100.0, description="filter of the differentiated motor angle for K_v"
    )

    @model_validator(mode="after")
    def _below_nyquist(self) -> SeaTorqueDesign:
        nyquist = 0.5 / self.period_s
        for name in ("bandwidth_hz", "derivative_filter_hz", "dob_cutoff_hz", "motor_velocity_filter_hz"):
            if getattr(self, name) >= nyquist:
                raise ValueError(f"{name} must be below the Nyquist frequency {nyquist:g} Hz")
        return self

    def with_alpha(self, alpha: float) -> SeaTorqueDesign:
        """A copy with another observer gain (validated)."""
        return SeaTorqueDesign.model_validate(self.model_dump() | {"alpha": alpha})


@dataclass(frozen=True)
class SeaPlant:
    """Linear single-joint SEA drive train, reflected to the gearbox output.

    ``J theta'' = tau_m - tau_s - b theta'``, ``tau_s = k (theta - q) + d_s (theta' - q')``; the
    command acts ``delay_ticks`` ticks after it is written. Coulomb friction has no linearisation
    at rest and is left out (it only dissipates).
    """

    inertia_kgm2: float
    viscous_nms_per_rad: float
    stiffness_nm_per_rad: float
    spring_damping_nms_per_rad: float = 0.0
    delay_ticks: int = 1

    @classmethod
    def nominal(cls, sea: SeaConstants, delay_ticks: int = 1) -> SeaPlant:
        """The model the controller is designed on: ``description.sea``, spring damping 0."""
        return cls(
            sea.gearbox_inertia_kgm2, sea.gearbox_viscous_nms_per_rad, sea.spring_stiffness_nm_per_rad, 0.0, delay_ticks
        )

    def locked_link_state_space(self) -> tuple[FloatArray, FloatArray]:
        """Continuous ``(A, B)`` of the locked-link SEA, state ``[theta, theta']``, input ``tau_m``."""
        j, b, k, ds = (
            self.inertia_kgm2,
            self.viscous_nms_per_rad,
            self.stiffness_nm_per_rad,
            self.spring_damping_nms_per_rad,
        )
        return np.array([[0.0, 1.0], [-k / j, -(b + ds) / j]]), np.array([[0.0], [1.0 / j]])


@dataclass(frozen=True)
class InnerLoopDesign:
    """The designed filters (transfer functions in z) and gains of one joint's torque controller."""

    kp: float  # torque-error gain (Nm/Nm)
    kd_s: float  # torque-error derivative gain (s)
    feedback: DiscreteTransferFunction  # C(z) = kp + D(z): torque error -> motor torque
    derivative: DiscreteTransferFunction  # D(z): the filtered derivative part of C
    derivative_weight: float  # 1: D acts on the error; 0: on the measurement (C_ff = 1 - D)
    motor_velocity: DiscreteTransferFunction  # D(z): theta -> filtered theta'
    plant: DiscreteTransferFunction  # nominal ZOH SEA, locked link, tau_m -> tau (no delay)
    nominal_loop: DiscreteTransferFunction  # H_n(z): u -> tau, link locked, with the delay
    q_filter: DiscreteTransferFunction  # Q(z), relative degree = that of H_n
    q_inverse_model: DiscreteTransferFunction  # Q(z) H_n(z)^-1, proper


def zoh_locked_plant(plant: SeaPlant, period_s: float) -> DiscreteTransferFunction:
    """Zero-order-hold discretisation of the locked-link SEA, ``tau_m -> tau_meas = k theta``."""
    a, b = plant.locked_link_state_space()
    c = np.array([[plant.stiffness_nm_per_rad, 0.0]])
    num, den = _ss_to_tf_zoh(a, b, c, period_s)
    return DiscreteTransferFunction(num, den, period_s)


def _ss_to_tf_zoh(a: FloatArray, b: FloatArray, c: FloatArray, period_s: float) -> tuple[FloatArray, FloatArray]:
    from scipy import signal

    ad, bd, cd, dd, _ = signal.cont2discrete((a, b, c, np.zeros((c.shape[0], b.shape[1]))), period_s, method="zoh")
    num, den = signal.ss2tf(ad, bd, cd, dd)
    return np.asarray(num, dtype=float).ravel(), np.asarray(den, dtype=float).ravel()


def _tustin_root(time_constant_s: float, period_s: float) -> float:
    """Where Tustin maps the root ``s = -1 / time_constant_s``: ``(2 tau / T - 1) / (2 tau / T + 1)``."""
    ratio = 2.0 * time_constant_s / period_s
    return (ratio - 1.0) / (ratio + 1.0)


def dob_lowpass_zpk(
    order: int, cutoff_hz: float, period_s: float, lead_s: float = 0.0
) -> tuple[list[float], list[float]]:
    """Zeros and poles of ``Q_0(s) = (1 + lead_s s) / (tau s + 1)^order`` after Tustin.

    A binomial low-pass (the usual DOB Q-filter), ``tau = 1 / (2 pi cutoff_hz)``: ``order`` poles at
    the Tustin image of ``-1 / tau``, zeros at ``z = -1`` (Tustin's image of infinity), and the lead
    zero if ``lead_s`` > 0. The lead cancels part of the filter's low-frequency group delay: higher
    passive alpha, but Q then rolls off one order slower (more motor-torque noise).

    Raises:
        ControlDesignError: a cut-off outside (0, Nyquist) or a negative lead.
    """
    if not 0.0 < cutoff_hz < 0.5 / period_s:
        raise ControlDesignError(f"low-pass cut-off {cutoff_hz} Hz must be in (0, {0.5 / period_s:g}) Hz")
    if lead_s < 0.0:
        raise ControlDesignError(f"the Q-filter lead must not be negative, got {lead_s} s")
    tau = 1.0 / (2.0 * np.pi * cutoff_hz)
    poles = [_tustin_root(tau, period_s)] * order
    zeros = [-1.0] * order
    if lead_s > 0.0:
        zeros[0] = _tustin_root(lead_s, period_s)
    return zeros, poles


def dob_lowpass(order: int, cutoff_hz: float, period_s: float, lead_s: float = 0.0) -> DiscreteTransferFunction:
    """``Q_0`` of :func:`dob_lowpass_zpk` as a transfer function of unit DC gain."""
    zeros, poles = dob_lowpass_zpk(order, cutoff_hz, period_s, lead_s)
    return DiscreteTransferFunction.from_zpk(zeros, poles, 1.0, period_s)


def inner_loop_gains(sea: SeaConstants, design: SeaTorqueDesign) -> tuple[float, float]:
    """``(K_p, K_d)`` placing the nominal locked-link loop at ``bandwidth_hz`` with ``damping_ratio``.

    Raises:
        ControlDesignError: the requested bandwidth is below the SEA's own natural frequency
            (negative K_p) or the damping is below what friction already gives (negative K_d).
    """
    j, b, k = sea.gearbox_inertia_kgm2, sea.gearbox_viscous_nms_per_rad, sea.spring_stiffness_nm_per_rad
    w = 2.0 * np.pi * design.bandwidth_hz
    kp = j * w * w / k - 1.0
    kd = (2.0 * design.damping_ratio * w * j - b - design.motor_damping_nms_per_rad) / k
    if kp < 0.0:
        raise ControlDesignError(
            f"torque-loop bandwidth {design.bandwidth_hz} Hz is below the SEA's natural frequency "
            f"{np.sqrt(k / j) / (2 * np.pi):.2f} Hz"
        )
    if kd < 0.0:
        raise ControlDesignError("damping ratio too low for the SEA's friction: the derivative gain would be negative")
    return float(kp), float(kd)


def _cancel_common(tf: DiscreteTransferFunction, tolerance: float = 1e-7) -> DiscreteTransferFunction:
    """Cancel pole-zero pairs closer than ``tolerance`` (round-off leaves them after the algebra)."""
    zeros = list(np.roots(tf.num)) if len(tf.num) > 1 else []
    poles = list(np.roots(tf.den)) if len(tf.den) > 1 else []
    kept_zeros = []
    for z in zeros:
        distances = [abs(z - p) for p in poles]
        if distances and min(distances) < tolerance * max(1.0, abs(z)):
            poles.pop(int(np.argmin(distances)))
        else:
            kept_zeros.append(z)
    gain = tf.num[0]
    num = gain * np.real(np.poly(kept_zeros)) if kept_zeros else np.array([gain])
    den = np.real(np.poly(poles)) if poles else np.ones(1)
    return DiscreteTransferFunction(num, den, tf.dt_s)


def design_inner_loop(sea: SeaConstants, design: SeaTorqueDesign) -> InnerLoopDesign:
    """C, D, H_n, Q and Q H_n^-1 of one joint, on the nominal SEA of ``sea``.

    Raises:
        ControlDesignError: invalid gains, an unstable nominal loop or a non-minimum-phase H_n
            (its inverse would be unstable).
    """
    dt = design.period_s
    kp, kd = inner_loop_gains(sea, design)
    tau_f = 1.0 / (2.0 * np.pi * design.derivative_filter_hz)
    # C(s) = kp + kd s / (tau_f s + 1) = ((kp tau_f + kd) s + kp) / (tau_f s + 1)
    derivative = DiscreteTransferFunction.from_continuous([kd, 0.0], [tau_f, 1.0], dt, "bilinear")
    feedback = DiscreteTransferFunction.gain(kp, dt) + derivative
    # Setpoint weighting: C_ff = 1 - (1 - w) D, so the reference path is 1 + kp + w D. w = 1 leaves the
    # slow zero of C_ff + C (~25 % overshoot on a torque step), w = 0 removes it (but triples the rise time).
    weight = design.derivative_weight
    reference_path = DiscreteTransferFunction.gain(1.0 + kp, dt) + derivative * DiscreteTransferFunction.gain(
        weight, dt
    )
    tau_v = 1.0 / (2.0 * np.pi * design.motor_velocity_filter_hz)
    motor_velocity = DiscreteTransferFunction.from_continuous([1.0, 0.0], [tau_v, 1.0], dt, "bilinear")

    nominal = SeaPlant.nominal(sea, design.delay_ticks)
    plant = zoh_locked_plant(nominal, dt)
    delayed_plant = plant * DiscreteTransferFunction.delay(design.delay_ticks, dt)
    # Locked link: theta = tau / k, so motor damping is feedback on tau through K_v D(z) / k.
    total_feedback = feedback + motor_velocity * DiscreteTransferFunction.gain(
        design.motor_damping_nms_per_rad / sea.spring_stiffness_nm_per_rad, dt
    )
    nominal_loop = _cancel_common(delayed_plant.feedback(total_feedback) * reference_path)
    if not nominal_loop.is_stable:
        raise ControlDesignError("the nominal torque loop is unstable with this design")
    if np.any(np.abs(nominal_loop.zeros) >= 1.0):
        raise ControlDesignError("the nominal torque loop has zeros outside the unit circle: H_n^-1 would be unstable")
    delay = nominal_loop.relative_degree
    tau_q = 1.0 / (2.0 * np.pi * design.dob_cutoff_hz)
    # The lead cancels the DC group delay of the binomial filter and of the z^-r alignment.
    lead_s = design.dob_order * tau_q + delay * dt if design.dob_lead else 0.0
    q_zeros, q_poles = dob_lowpass_zpk(design.dob_order, design.dob_cutoff_hz, dt, lead_s)
    q_poles += [0.0] * delay  # z^-r
    # The ZOH puts a zero of H_n at about -0.9987; in Q H_n^-1 it would be a pole ringing at Nyquist
    # for ~750 ticks. Q has zeros at exactly -1 next to it: moving one onto it cancels it exactly.
    h_zeros, h_poles = list(np.roots(nominal_loop.num)), list(np.roots(nominal_loop.den))
    inverse_zeros = list(q_zeros)  # Q H_n^-1: zeros of Q and poles of H_n over poles of Q and zeros of H_n
    for z_s in [z for z in h_zeros if abs(z.imag) < 1e-9 and abs(z.real + 1.0) < 0.05]:
        if -1.0 not in q_zeros:
            break
        q_zeros[q_zeros.index(-1.0)] = z_s.real
        inverse_zeros.remove(-1.0)
        h_zeros.remove(z_s)
    q_filter = DiscreteTransferFunction.from_zpk(q_zeros, q_poles, 1.0, dt)
    q_inverse_model = DiscreteTransferFunction.from_zpk(
        inverse_zeros + h_poles, q_poles + h_zeros, 1.0 / nominal_loop.dc_gain, dt
    )
    if q_inverse_model.relative_degree < 0:
        raise ControlDesignError("Q H_n^-1 is improper: Q's relative degree is below H_n's")
    return InnerLoopDesign(
        kp, kd, feedback, derivative, weight, motor_velocity, plant, nominal_loop, q_filter, q_inverse_model
    )


# --- the per-tick kernel ---------------------------------------------------------------------

#: Inputs: any layout, read-only accepted (a sample's arrays may be frozen); writable arrays match too.
_VEC = numba.types.Array(numba.float64, 1, "A", readonly=True)
_F1 = numba.float64[::1]
_F2 = numba.float64[:, ::1]
_F3 = numba.float64[:, :, ::1]
_F4 = numba.float64[:, :, :, ::1]

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

    @property
    def _banks(self) -> tuple[FilterBank, ...]:
        return (self._dob_model, self._dob_q, self._derivative, self._motor_velocity)

    @property
    def alpha(self) -> float:
        return self.design.alpha

    @property
    def d_hat_nm(self) -> FloatArray:
        """The observer's disturbance estimate of the last tick (Nm), a copy."""
        return self._work[_W_DHAT].copy()

    @property
    def u_nm(self) -> FloatArray:
        """The inner loop's reference actually applied in the last tick (Nm), a copy."""
        return self._work[_W_U].copy()

    @property
    def kp(self) -> float:
        return self.loop.kp

    @property
    def kd_s(self) -> float:
        return self.loop.kd_s

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
