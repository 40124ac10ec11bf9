"""Design of the SEA torque controller, done once before the loop (thesis Sec. 2.2.3, after Rampeltshammer et al.).

:class:`SeaTorqueDesign` is the tuning; :func:`design_inner_loop` turns it and the nominal SEA of
``description.sea`` into the per-joint filters the tick runs
(:class:`~daror_runtime.control.sea_torque.SeaTorqueController` builds them at construction, never
in the tick). Per joint, with ``tau = k (theta - q)`` the spring torque and ``u`` the inner loop's
reference (the signal flow is drawn in :mod:`daror_runtime.control.sea_torque`):

* **C** (feedback): PD on the torque error with a first-order filtered derivative,
  ``C(s) = K_p + K_d s / (tau_f s + 1)``, discretised with Tustin. The gains come from the tuning
  of Rampeltshammer et al.: on the nominal locked-link SEA ``J s^2 + b s + k`` the loop's
  characteristic polynomial is ``J s^2 + (b + k K_d) s + k (1 + K_p)``, so a chosen natural
  frequency ``w`` and damping ratio ``zeta`` give ``K_p = J w^2 / k - 1`` and
  ``K_d = (2 zeta w J - b) / k`` independently (:func:`inner_loop_gains`).
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
  and perturbed plants is chosen by :func:`daror_runtime.control.passivity.choose_alpha`
  (:data:`DEFAULT_ALPHA`).

:class:`SeaPlant` is the linear single-joint drive train the design and the analysis
(:mod:`daror_runtime.control.passivity`) use. Nothing here runs in the tick.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

import daror_runtime.control.lti_conversion as lti_conversion
from daror_runtime.control.base import ControlDesignError
from daror_runtime.control.filters import DiscreteTransferFunction
from hal.robot import FloatArray, SeaConstants

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
    reading_error_in_encoders: bool = Field(
        False,
        description="the torque reading's hysteresis (Sec. 2.2.2) is in the encoders' deflection itself (an encoder "
        "that moves with the rotor), so k (theta - q) carries it too; False: only the drive's reading carries it "
        "(as in the simulator). A bench test on the robot decides (docs/control.md, section 10)",
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
    # scipy.signal's cont2discrete and ss2tf, to the bit, without importing scipy.signal (~0.5 s)
    ad, bd, cd, dd, _ = lti_conversion.cont2discrete_ss(
        a, b, c, np.zeros((c.shape[0], b.shape[1])), period_s, method="zoh"
    )
    num, den = lti_conversion.ss2tf(ad, bd, cd, dd)
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
