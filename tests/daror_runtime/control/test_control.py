"""Controllers (issue 3, item 5): filters, the SEA torque loop with its observer, the modes, link bounds.

The plant here is a small explicit model of four independent single-joint SEAs, with the as-built
drive train of scenario ``exo_dummy_arm`` (inertia, viscous and Coulomb friction, spring damping),
quantised noisy encoders, the drives' 50 Hz velocity filter and the one-tick command delay. The
4-DoF dynamic simulator (written in parallel) is for the integration tests.
"""

from __future__ import annotations

import math
import tracemalloc
from collections.abc import Callable

import numpy as np
import pytest
from scipy import signal

from daror_runtime.control import (
    Compensation,
    ControlDesignError,
    ControlError,
    Controller,
    ControlSettingError,
    LinkBounds,
    MinimalImpedance,
    SeaTorqueController,
    SeaTorqueDesign,
    TorqueOff,
)
from daror_runtime.control.filters import DiscreteTransferFunction, FilterBank
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.sea_torque import _W_DHAT
from daror_runtime.control.sea_torque_design import design_inner_loop, inner_loop_gains
from daror_runtime.errors import InputError, ShapeError
from daror_runtime.models.base import CompensationModel
from hal.interface import Command, DriveState, Sample
from hal.robot import FloatArray, RobotDescription, load_description
from hal.sim.scenario import load_scenario

PERIOD_S = 1e-3
RESOLUTION_NM = 289.0 * 1e-4  # torque resolution of one encoder count


# --- a small explicit plant ----------------------------------------------------------------------


class JointSim:
    """Four independent single-joint SEAs (as-built drive train of ``exo_dummy_arm``), 1 kHz ticks.

    ``link``: "locked" (q = 0), "driven" (the pilot imposes ``motion(t) -> (q, dq)``) or "free"
    (inertia ``I``, gravity ``mgl sin q``, link viscous friction). Motor side reflected to the
    gearbox output: ``J theta'' = tau_m - tau_s - b theta' - tau_c tanh(theta' / eps)``,
    ``tau_s = k (theta - q) + d_s (theta' - q')``. Semi-implicit Euler with ``substeps`` per tick.
    """

    def __init__(
        self,
        link: str,
        *,
        inertia_kgm2: FloatArray | None = None,
        mgl_nm: FloatArray | None = None,
        motion: Callable[[float], tuple[FloatArray, FloatArray]] | None = None,
        noise: bool = True,
        coulomb: bool = True,
        substeps: int = 10,
        seed: int = 3,
    ) -> None:
        truth = load_scenario("exo_dummy_arm").drive_train
        assert truth is not None
        self.j = np.array(truth.gearbox_inertia_kgm2)
        self.b = np.array(truth.gearbox_viscous_nms_per_rad)
        self.tau_c = np.array(truth.gearbox_coulomb_nm) if coulomb else np.zeros(4)
        self.eps = truth.coulomb_smoothing_rad_s
        self.ds = np.array(truth.spring_damping_nms_per_rad)
        self.bl = np.array(truth.link_viscous_nms_per_rad)
        self.k = 289.0
        self.link, self.motion, self.substeps = link, motion, substeps
        self.inertia = None if inertia_kgm2 is None else np.broadcast_to(inertia_kgm2, (4,)).astype(float)
        self.mgl = np.zeros(4) if mgl_nm is None else np.broadcast_to(mgl_nm, (4,)).astype(float)
        self.noise = 0.5e-4 if noise else 0.0
        self.quantise = noise
        self.rng = np.random.default_rng(seed)
        self.theta, self.dtheta, self.q, self.dq = (np.zeros(4) for _ in range(4))
        self.queue = [np.zeros(4)]  # one tick of command delay
        self.t, self.seq = 0.0, 0
        self.q_prev: FloatArray | None = None
        self.v_est = np.zeros(4)
        self.beta = math.exp(-2.0 * math.pi * 50.0 * PERIOD_S)
        if motion is not None:
            self.q, self.dq = motion(0.0)
            self.theta = self.q.copy()
            self.dtheta = self.dq.copy()

    def hold(self, q: FloatArray) -> None:
        """Start at rest at ``q`` with the spring carrying gravity."""
        self.q = np.array(q, dtype=float)
        self.theta = self.q + self.mgl * np.sin(self.q) / self.k

    def spring(self) -> FloatArray:
        return self.k * (self.theta - self.q) + self.ds * (self.dtheta - self.dq)

    def read(self) -> Sample:
        q = self.q + self.rng.normal(0.0, self.noise, 4) if self.noise else self.q.copy()
        theta = self.theta + self.rng.normal(0.0, self.noise, 4) if self.noise else self.theta.copy()
        if self.quantise:
            q, theta = np.round(q / 1e-4) * 1e-4, np.round(theta / 1e-4) * 1e-4
        if self.q_prev is not None:
            self.v_est = self.beta * self.v_est + (1.0 - self.beta) * (q - self.q_prev) / PERIOD_S
        self.q_prev = q
        self.seq += 1
        return Sample(
            self.seq,
            self.t,
            q,
            self.v_est.copy(),
            theta,
            self.k * (theta - q),
            (False, False),
            (DriveState.ENABLED,) * 4,
        )

    def step(self, command: Command, on_substep: Callable[[float], None] | None = None) -> None:
        """Advance one tick; ``on_substep(t)`` (if given) sees the state after every substep."""
        self.queue.append(np.asarray(command.motor_torque_nm, dtype=float))
        tau_m = self.queue.pop(0)
        h = PERIOD_S / self.substeps
        for i in range(self.substeps):
            friction = self.b * self.dtheta + self.tau_c * np.tanh(self.dtheta / self.eps)
            self.dtheta += h * (tau_m - self.spring() - friction) / self.j
            self.theta += h * self.dtheta
            if self.link == "free":
                assert self.inertia is not None
                self.dq += h * (self.spring() - self.bl * self.dq - self.mgl * np.sin(self.q)) / self.inertia
                self.q += h * self.dq
            elif self.link == "driven":
                assert self.motion is not None
                self.q, self.dq = self.motion(self.t + (i + 1) * h)
            if on_substep is not None:
                on_substep(self.t + (i + 1) * h)
        self.t += PERIOD_S


def run(sim: JointSim, controller: Controller, ticks: int, record: Callable[[Sample], object] | None = None) -> list:
    """Reset the controller on the first sample, then run ``ticks`` ticks; returns what ``record`` returned."""
    controller.reset(sim.read())
    out = []
    for _ in range(ticks):
        sample = sim.read()
        sim.step(controller.update(sample, PERIOD_S))
        if record is not None:
            out.append(record(sample))
    return out


class StepTorque:
    """A controller that asks the torque loop for ``reference(t)``: the locked-link tests' driver."""

    def __init__(self, torque: SeaTorqueController, reference: Callable[[float], FloatArray]) -> None:
        self.torque, self.reference = torque, reference

    def reset(self, sample: Sample) -> None:
        self.torque.reset(sample)

    def update(self, sample: Sample, dt_s: float) -> Command:
        return Command(self.torque.motor_torque(self.reference(sample.t_s), sample, dt_s), True)


class Gravity(CompensationModel):
    """``mgl sin q`` per joint: the single-joint link's holding torque (times ``1 + error``)."""

    kind = "test-gravity"
    display_name = "test gravity"
    conservative_by_construction = True

    def __init__(self, description: RobotDescription, mgl_nm: FloatArray, error: float = 0.0) -> None:
        super().__init__(description)
        self.mgl = np.asarray(mgl_nm, dtype=float) * (1.0 + error)

    def torque(self, q: FloatArray) -> np.ndarray:
        return self.mgl * np.sin(q)

    def torque_batch(self, q: FloatArray) -> FloatArray:
        return self.mgl * np.sin(q)

    def parameters(self) -> dict:
        return {"mgl": self.mgl.tolist()}

    @classmethod
    def from_parameters(cls, description, parameters, name=None):  # type: ignore[no-untyped-def]
        return cls(description, np.asarray(parameters["mgl"]))


class ConstantModel(Gravity):
    """Returns a fixed torque (or NaN) whatever ``q``."""

    def __init__(self, description: RobotDescription, value: FloatArray) -> None:
        super().__init__(description, np.zeros(4))
        self.value = np.asarray(value, dtype=float)

    def torque(self, q: FloatArray) -> np.ndarray:
        return self.value.copy()


def still_sample(tau_nm: float = 0.0, theta_rad: float = 0.0, t_s: float = 0.0) -> Sample:
    return Sample(
        0,
        t_s,
        np.zeros(4),
        np.zeros(4),
        np.full(4, theta_rad),
        np.full(4, tau_nm),
        (False, False),
        (DriveState.ENABLED,) * 4,
    )


@pytest.fixture
def torque(description: RobotDescription) -> SeaTorqueController:
    return SeaTorqueController(description.sea)


def d_hat_nm(torque: SeaTorqueController) -> FloatArray:
    """The observer's disturbance estimate of the last tick (Nm), a copy (the kernel's diagnostics row)."""
    return torque._work[_W_DHAT].copy()


def hold(q_rad: FloatArray) -> Callable[[float], tuple[FloatArray, FloatArray]]:
    """A position reference that holds ``q_rad`` (no allocation per call)."""
    q, dq = np.array(q_rad, dtype=float), np.zeros(len(q_rad))
    return lambda t_s: (q, dq)


# --- filters -------------------------------------------------------------------------------------


def test_tustin_filter_matches_scipy_and_steps_like_lfilter() -> None:
    num_s, den_s = [0.0, 1.0], [0.01, 1.0]  # 1 / (0.01 s + 1)
    tf = DiscreteTransferFunction.from_continuous(num_s, den_s, PERIOD_S)
    f = np.array([0.5, 5.0, 50.0, 200.0])
    _, expected = signal.freqz(tf.num, tf.den, worN=2 * np.pi * f * PERIOD_S)
    np.testing.assert_allclose(tf.response(f), expected, rtol=1e-12)
    # Tustin keeps the continuous response at low frequency.
    assert abs(tf.response(np.array([1.0]))[0] - 1 / (1 + 0.01j * 2 * np.pi)) < 1e-4
    bank = FilterBank.replicate(tf, 4)
    u = np.random.default_rng(0).normal(size=(200, 4))
    y = np.array([bank.step(row) for row in u])
    np.testing.assert_allclose(y, signal.lfilter(tf.num, tf.den, u, axis=0), atol=1e-12)


def test_filter_bank_reset_starts_in_steady_state_and_pads_orders() -> None:
    lowpass = DiscreteTransferFunction.from_continuous([1.0], [0.05, 1.0], PERIOD_S)
    second = DiscreteTransferFunction.from_continuous([1.0], [1e-4, 0.02, 1.0], PERIOD_S)
    bank = FilterBank([lowpass, second, DiscreteTransferFunction.gain(3.0, PERIOD_S), lowpass])
    assert bank.order == 2
    bank.reset(np.array([1.0, -2.0, 0.5, 4.0]))
    for _ in range(5):
        y = bank.step(np.array([1.0, -2.0, 0.5, 4.0]))
    np.testing.assert_allclose(y, [1.0, -2.0, 1.5, 4.0], atol=1e-12)
    f = np.array([1.0, 30.0])
    np.testing.assert_allclose(bank.response(f)[1], second.response(f), rtol=1e-10)


def test_improper_and_invalid_filters_are_refused() -> None:
    with pytest.raises(ControlDesignError, match="improper"):
        DiscreteTransferFunction(np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.5]), PERIOD_S)
    with pytest.raises(ControlDesignError, match="improper"):
        DiscreteTransferFunction.from_continuous([1.0, 0.0], [1.0], PERIOD_S)
    with pytest.raises(ControlDesignError, match="method"):
        DiscreteTransferFunction.from_continuous([1.0], [1.0, 1.0], PERIOD_S, "euler")
    with pytest.raises(ControlDesignError):
        DiscreteTransferFunction.delay(-1, PERIOD_S)
    with pytest.raises(ControlDesignError, match="period"):
        DiscreteTransferFunction.gain(1.0, PERIOD_S) * DiscreteTransferFunction.gain(1.0, 2e-3)


# --- design of the torque loop ----------------------------------------------------------------------


def test_inner_gains_place_the_nominal_locked_link_poles(description: RobotDescription) -> None:
    design = SeaTorqueDesign()
    kp, kd = inner_loop_gains(description.sea, design)
    sea = description.sea
    # J s^2 + (b + k Kd) s + k (1 + Kp) = J (s^2 + 2 zeta w s + w^2); coefficients (a double root is ill-conditioned)
    w = 2 * np.pi * design.bandwidth_hz
    j = sea.gearbox_inertia_kgm2
    assert 289.0 * (1 + kp) / j == pytest.approx(w**2, rel=1e-12)
    assert (sea.gearbox_viscous_nms_per_rad + 289.0 * kd) / j == pytest.approx(2 * design.damping_ratio * w, rel=1e-12)
    with pytest.raises(ControlDesignError, match="natural frequency"):
        inner_loop_gains(sea, SeaTorqueDesign(bandwidth_hz=3.0))


def test_nominal_model_observer_filters_are_proper_and_stable(description: RobotDescription) -> None:
    loop = design_inner_loop(description.sea, SeaTorqueDesign())
    assert loop.nominal_loop.relative_degree == 2  # ZOH + one tick of command delay
    assert loop.q_filter.relative_degree >= loop.nominal_loop.relative_degree
    assert loop.q_inverse_model.relative_degree == 0  # Q H_n^-1 proper, with direct feedthrough
    assert abs(loop.nominal_loop.dc_gain - 1.0) < 1e-6
    assert abs(loop.q_filter.dc_gain - 1.0) < 1e-9
    for tf in (loop.nominal_loop, loop.q_filter, loop.q_inverse_model):
        assert tf.is_stable
    assert np.all(np.abs(loop.nominal_loop.zeros) < 1.0)  # minimum phase: H_n^-1 stable
    # The ZOH sampling zero is cancelled: Q H_n^-1 has no lightly damped pole near z = -1.
    assert np.min(np.abs(loop.q_inverse_model.poles + 1.0)) > 0.5


def test_linear_model_is_exactly_the_kernel(description: RobotDescription) -> None:
    """The state-space model the analysis uses reproduces the compiled controller tick by tick."""
    controller = SeaTorqueController(description.sea, SeaTorqueDesign(motor_damping_nms_per_rad=0.5))
    controller.reset(None)
    a, b, c, d = controller.linear_model(2)
    x = np.zeros(a.shape[0])
    rng = np.random.default_rng(1)
    for k in range(300):
        t = k * PERIOD_S  # a smooth reference (the slew limiter is not part of the linear model) and noisy readings
        inputs = np.array(
            [2.0 * np.sin(7.0 * t), np.sin(5.0 * t) + rng.normal(0, 0.05), 0.001 * k + rng.normal(0, 1e-4)]
        )
        q = inputs[2] - inputs[1] / 289.0  # the linear model's tau_meas is the deflection k (theta - q)
        sample = Sample(
            k, k * PERIOD_S, np.full(4, q), np.zeros(4), np.full(4, inputs[2]), np.full(4, inputs[1]), (), ()
        )
        out = controller.motor_torque(np.full(4, inputs[0]), sample, PERIOD_S)
        expected = float(c[0] @ x + d[0] @ inputs)
        x = a @ x + b @ inputs
        assert abs(out[1] - expected) < 1e-9 * max(1.0, abs(expected))
        assert np.all(np.abs(out) < description.sea.max_motor_torque_nm)  # the comparison assumes no saturation


# --- the torque loop on a locked link ---------------------------------------------------------------


def test_torque_step_on_locked_link(torque: SeaTorqueController) -> None:
    """A 5 Nm step: rise time, overshoot, and steady-state error within one encoder count."""
    step_at_s, target = 0.1, 5.0
    controller = StepTorque(torque, lambda t: np.full(4, target if t >= step_at_s - 1e-9 else 0.0))
    sim = JointSim("locked")
    spring = np.array(run(sim, controller, 1000, lambda s: sim.spring()))
    t = np.arange(1000) * PERIOD_S
    after = t >= step_at_s
    for j in range(4):
        y = spring[after, j]
        rise_s = (np.argmax(y >= 0.9 * target) - np.argmax(y >= 0.1 * target)) * PERIOD_S
        overshoot = (y.max() - target) / target
        settled = y[-300:].mean() - target
        assert rise_s < 0.020, f"joint {j + 1}: rise time {rise_s * 1e3:.0f} ms"
        assert overshoot < 0.10, f"joint {j + 1}: overshoot {overshoot:.1%}"
        assert abs(settled) < RESOLUTION_NM, f"joint {j + 1}: steady-state error {settled:.4f} Nm"


def test_reference_limit_saturation_and_no_windup(torque: SeaTorqueController, description: RobotDescription) -> None:
    """Asked for 80 Nm: the reference is cut to what the spring can carry, the motor never exceeds its
    limit, the loop keeps damping; back to 5 Nm it recovers like a plain step (no wind-up)."""
    sea = description.sea
    spring_limit = sea.spring_stiffness_nm_per_rad * sea.max_spring_deflection_rad
    controller = StepTorque(torque, lambda t: np.full(4, 80.0 if t < 0.5 else 5.0))
    sim = JointSim("locked")
    rows = run(sim, controller, 800, lambda s: (np.array(sim.queue[-1]), sim.spring().copy(), d_hat_nm(torque)))
    commands, spring = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
    assert np.max(np.abs(commands)) <= sea.max_motor_torque_nm
    assert np.max(spring[:500]) < 1.05 * spring_limit  # no ringing past the end stop
    assert np.all(np.abs(spring[400:500].mean(axis=0) - spring_limit) < 0.05)
    # Down 30 Nm at the slew limit: no undershoot worth the name, settled to 1 % of the step in 100 ms.
    back = spring[500:]
    assert np.all(back.min(axis=0) > 5.0 - 0.6), f"undershoot to {back.min(axis=0).round(2)} Nm"
    outside = np.abs(back - 5.0) > 0.3
    settle_ms = np.array([np.flatnonzero(outside[:, j])[-1] + 1 for j in range(4)])  # last tick outside the band
    assert np.all(settle_ms < 100), f"settling after saturation took {settle_ms} ms"
    assert np.max(np.abs(np.array([r[2] for r in rows]))) < sea.max_motor_torque_nm  # the observer stayed bounded


def test_mode_entry_under_load_does_not_kick(description: RobotDescription) -> None:
    """Taking over a joint whose spring carries 5 Nm, asked to keep 5 Nm: the motor just holds 5 Nm."""
    for mode_design in (SeaTorqueDesign(), SeaTorqueDesign(torque_from_encoders=False)):
        torque = SeaTorqueController(description.sea, mode_design)
        loaded = Sample(0, 0.0, np.zeros(4), np.zeros(4), np.full(4, 5.0 / 289.0), np.full(4, 5.0), (), ())
        torque.reset(loaded)
        first = torque.motor_torque(np.full(4, 5.0), loaded, PERIOD_S)
        np.testing.assert_allclose(first, 5.0, atol=1e-9)


def test_direction_error_of_the_reading_is_not_fed_back(description: RobotDescription) -> None:
    """The reading's direction-dependent error (Sec. 2.2.2) switches with the motion; the loop regulates
    the encoders' deflection k (theta - q), so the switching offset never reaches the motor."""
    torque = SeaTorqueController(description.sea)
    flipped = [
        Sample(
            k,
            k * PERIOD_S,
            np.zeros(4),
            np.zeros(4),
            np.full(4, 1.0 / 289.0),
            np.full(4, 1.0 + 0.75 * (-1) ** k),
            (),
            (),
        )
        for k in range(50)
    ]
    torque.reset(flipped[0])
    commands = np.array([torque.motor_torque(np.full(4, 1.0), sample, PERIOD_S) for sample in flipped])
    np.testing.assert_allclose(commands, 1.0, atol=1e-9)
    reading = SeaTorqueController(description.sea, SeaTorqueDesign(torque_from_encoders=False))
    reading.reset(flipped[0])
    chased = np.array([reading.motor_torque(np.full(4, 1.0), sample, PERIOD_S) for sample in flipped])
    assert np.ptp(chased) > 10.0  # the reading-based loop chases the flips with ~10 Nm swings


def test_non_finite_input_is_refused_and_state_is_kept(
    torque: SeaTorqueController, description: RobotDescription
) -> None:
    twin = SeaTorqueController(description.sea)
    torque.reset(still_sample(1.0))
    twin.reset(still_sample(1.0))
    good = still_sample(1.2)
    for bad in (still_sample(float("nan")), still_sample(1.0, float("inf"))):
        with pytest.raises(ControlError, match="joint 1"):
            torque.motor_torque(np.zeros(4), bad, PERIOD_S)
    with pytest.raises(ControlError, match="joint 3"):
        torque.motor_torque(np.array([0.0, 0.0, np.nan, 0.0]), good, PERIOD_S)
    with pytest.raises(ControlError, match="period"):
        torque.motor_torque(np.zeros(4), good, float("nan"))
    np.testing.assert_array_equal(
        torque.motor_torque(np.zeros(4), good, PERIOD_S), twin.motor_torque(np.zeros(4), good, PERIOD_S)
    )


def test_wrong_shapes_are_refused(torque: SeaTorqueController) -> None:
    torque.reset(still_sample())
    with pytest.raises(ShapeError):
        torque.motor_torque(np.zeros(3), still_sample(), PERIOD_S)
    with pytest.raises(ShapeError):
        torque.motor_torque(np.zeros((2, 4)), still_sample(), PERIOD_S)
    with pytest.raises(ShapeError):
        torque.motor_torque(["a"] * 4, still_sample(), PERIOD_S)  # type: ignore[arg-type]
    # Lists and read-only arrays are fine (a HAL may hand out frozen arrays).
    frozen = np.zeros(4)
    frozen.flags.writeable = False
    assert torque.motor_torque([0.0] * 4, still_sample(), PERIOD_S).shape == (4,)  # type: ignore[arg-type]
    assert torque.motor_torque(frozen, still_sample(), PERIOD_S).shape == (4,)


# --- the observer against the pilot ----------------------------------------------------------------


@pytest.mark.parametrize(("frequency_hz", "amplitude_rad"), [(0.5, 0.3), (1.0, 0.2)])
def test_dob_rejects_the_pilots_motion(
    description: RobotDescription, frequency_hz: float, amplitude_rad: float
) -> None:
    """The pilot swings the link; with the observer the spring torque they feel is at most half."""
    w = 2 * np.pi * frequency_hz

    def pilot(t: float) -> tuple[FloatArray, FloatArray]:
        return np.full(4, amplitude_rad * np.sin(w * t)), np.full(4, amplitude_rad * w * np.cos(w * t))

    ticks, settle = int(3.0 / frequency_hz * 1000), int(1.0 / frequency_hz * 1000)
    rms = {}
    for alpha in (0.0, SeaTorqueDesign().alpha):
        sim = JointSim("driven", motion=pilot)
        mode = MinimalImpedance(SeaTorqueController(description.sea, SeaTorqueDesign(alpha=alpha)))
        spring = np.array(run(sim, mode, ticks, lambda s, sim=sim: sim.spring().copy()))[settle:]
        rms[alpha] = np.sqrt(np.mean(spring**2, axis=0))
    ratio = rms[SeaTorqueDesign().alpha] / rms[0.0]
    assert np.all(ratio <= 0.5), f"RMS spring torque with/without observer: {ratio.round(3)}"
    assert np.all(ratio >= 0.2)  # it is the 1 - alpha of the design, not a fluke (alpha 0.61 -> ~0.39)


def test_observer_adds_no_motor_torque_noise(description: RobotDescription) -> None:
    """At rest the encoders' noise and quantisation reach the motor through C and the observer; Q rolls
    off fast enough that the observer adds (almost) nothing to what C alone passes (~0.8 Nm RMS)."""
    std = {}
    for alpha in (0.0, SeaTorqueDesign().alpha):
        sim = JointSim("locked")
        mode = MinimalImpedance(SeaTorqueController(description.sea, SeaTorqueDesign(alpha=alpha)))
        rows = np.array(run(sim, mode, 2000, lambda s, sim=sim: (np.array(sim.queue[-1]), sim.spring().copy())))
        std[alpha] = (rows[500:, 0].std(axis=0), rows[500:, 1].std(axis=0))
    motor_without, motor_with = std[0.0][0], std[SeaTorqueDesign().alpha][0]
    assert np.all(motor_with < 1.1 * motor_without), (
        f"motor torque noise {motor_with.round(2)} vs {motor_without.round(2)} Nm"
    )
    assert np.all(motor_with < 1.0)
    assert np.all(std[SeaTorqueDesign().alpha][1] < RESOLUTION_NM)  # what the pilot gets: below one count


# --- modes ---------------------------------------------------------------------------------------


def test_modes_satisfy_the_controller_protocol(torque: SeaTorqueController, description: RobotDescription) -> None:
    model = ConstantModel(description, np.ones(4))
    modes = [
        TorqueOff(),
        MinimalImpedance(torque),
        Compensation(torque, model),
        MotorPositionPD(description, hold(np.zeros(4)), BOUNDS),
    ]
    for mode in modes:
        assert isinstance(mode, Controller)
    off = TorqueOff().update(still_sample(), PERIOD_S)
    assert not off.enable
    np.testing.assert_array_equal(off.motor_torque_nm, 0.0)
    minimal = MinimalImpedance(torque)
    minimal.reset(still_sample())
    command = minimal.update(still_sample(), PERIOD_S)
    assert command.enable
    np.testing.assert_array_equal(minimal.last_reference_nm, 0.0)
    np.testing.assert_allclose(command.motor_torque_nm, 0.0, atol=1e-12)  # at rest with zero torque: nothing to do


def holding_sample(spring_nm: FloatArray, enabled: bool = True) -> Sample:
    """At rest at q = 0 with the springs carrying ``spring_nm`` (motor angles ``spring / k``)."""
    theta = np.asarray(spring_nm, dtype=float) / load_description().sea.spring_stiffness_nm_per_rad
    drives = (DriveState.ENABLED if enabled else DriveState.DISABLED,) * 4
    return Sample(0, 0.0, np.zeros(4), np.zeros(4), theta, np.asarray(spring_nm, dtype=float), (False, False), drives)


def test_compensation_gives_support_times_model_torque(
    torque: SeaTorqueController, description: RobotDescription
) -> None:
    model_torque = np.array([2.0, -4.0, 1.5, 0.8])
    mode = Compensation(torque, ConstantModel(description, model_torque), support_level=0.5, ramp_per_s=None)
    mode.reset(holding_sample(0.5 * model_torque))  # the springs already carry the support: nothing to hand over
    assert not mode.handover.active
    mode.update(still_sample(), PERIOD_S)
    np.testing.assert_allclose(mode.last_reference_nm, 0.5 * model_torque)
    mode.support_level = 1.0
    mode.update(still_sample(), PERIOD_S)
    np.testing.assert_allclose(mode.last_reference_nm, model_torque)


def test_compensation_ramps_in_and_refuses_bad_levels(
    torque: SeaTorqueController, description: RobotDescription
) -> None:
    model_torque = np.array([2.0, -4.0, 1.5, 0.8])
    mode = Compensation(
        torque, ConstantModel(description, model_torque), support_level=0.5, ramp_per_s=0.5, handover_tolerance_nm=0.0
    )
    mode.reset(holding_sample(np.zeros(4), enabled=False))  # torque was off: all the support is missing
    mode.update(still_sample(), PERIOD_S)
    np.testing.assert_allclose(mode.last_reference_nm, 0.0005 * 0.5 * model_torque)  # 0.5/s of the gap for 1 ms
    for _ in range(999):
        mode.update(still_sample(), PERIOD_S)
    np.testing.assert_allclose(mode.last_reference_nm, 0.5 * 0.5 * model_torque)  # 1 s at 0.5/s: half the gap
    for _ in range(1000):
        mode.update(still_sample(), PERIOD_S)
    np.testing.assert_allclose(mode.last_reference_nm, 0.5 * model_torque)  # 2 s: all of it
    mode.update(still_sample(), 5.0)  # a stalled tick counts as at most 10 ms
    for bad in (float("nan"), float("inf"), -0.1, 1.01, "half", True, None):
        with pytest.raises(ControlSettingError):
            mode.support_level = bad  # type: ignore[assignment]
    assert mode.support_level == 0.5
    assert issubclass(ControlSettingError, InputError)
    with pytest.raises(ControlSettingError):
        Compensation(torque, ConstantModel(description, model_torque), support_level=float("nan"))
    mode.support_level = 0.0
    mode.update(still_sample(), 1e-3)
    assert mode.delivered_support_level == pytest.approx(0.5 - 0.0005)  # ramps down too


def test_compensation_refuses_a_non_finite_model_torque(
    torque: SeaTorqueController, description: RobotDescription
) -> None:
    mode = Compensation(torque, ConstantModel(description, np.array([1.0, np.nan, 0.0, 0.0])), ramp_per_s=None)
    with pytest.raises(ControlError, match="entry pose"):  # refused before it starts
        mode.reset(still_sample())
    mode.handover.clear()
    with pytest.raises(ControlError, match="non-finite"):
        mode.update(still_sample(), PERIOD_S)
    wrong = Compensation(torque, ConstantModel(description, np.ones(3)), ramp_per_s=None)
    with pytest.raises(ShapeError):
        wrong.update(still_sample(), PERIOD_S)
    with pytest.raises(ControlError, match="no compensation model"):
        Compensation(torque, None).reset(still_sample())


# --- link bounds (what the position gains are checked over) ------------------------------------------

LINK_INERTIA = np.array([0.03, 0.1, 0.3, 0.1])  # kg m^2, one single-joint link per "joint"
LINK_MGL = np.array([1.5, 3.0, 6.0, 3.0])  # Nm: gravity torque at 90 degrees
BOUNDS = LinkBounds(LINK_INERTIA / 2, LINK_INERTIA * 2, LINK_MGL)


def test_link_bounds_refuse_a_load_outside_zero_to_one(description: RobotDescription) -> None:
    with pytest.raises(ControlSettingError):
        LinkBounds.from_description(description, load_in_minimum=1.5)


# --- per-tick cost: small arrays only ------------------------------------------------------------------


def test_updates_allocate_only_small_arrays(torque: SeaTorqueController, description: RobotDescription) -> None:
    modes: list[Controller] = [
        MinimalImpedance(torque),
        Compensation(torque, Gravity(description, LINK_MGL), ramp_per_s=None),
        MotorPositionPD(description, hold(np.zeros(4)), BOUNDS),
    ]
    sample = still_sample()
    for mode in modes:
        mode.reset(sample)
        for _ in range(10):  # warm-up: caches, first-touch
            mode.update(sample, PERIOD_S)
        tracemalloc.start()
        try:
            before, _ = tracemalloc.get_traced_memory()
            tracemalloc.reset_peak()
            kept = [mode.update(sample, PERIOD_S) for _ in range(200)]
            during, peak = tracemalloc.get_traced_memory()
            del kept
            after, _ = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        per_tick = (during - before) / 200  # what each returned Command holds on to
        assert per_tick < 600, f"{type(mode).__name__}: {per_tick:.0f} bytes kept per tick"
        assert after - before < 2048, f"{type(mode).__name__}: {after - before} bytes leaked"
        assert peak - during < 4096  # transient work per tick is small arrays only
