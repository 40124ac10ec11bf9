"""Apparent impedance of one SEA joint in minimal-impedance mode, its passivity, and the choice of alpha.

The pilot moves the link with velocity ``q'``; the actuator answers with the spring torque
``tau_s = k (theta - q) + d_s (theta' - q')`` on the link. The apparent impedance is
``Z = -tau_s / q'`` (Nms/rad): what the pilot's arm feels. The joint is *passive* when
``Re Z >= 0`` at every frequency: then it can only absorb energy from the pilot, and coupled with
any passive environment (an arm, a hand, an end stop) it stays stable.

How Z is computed (per joint, ``tau_ref = 0``, saturation ignored):

* the mechanics (motor-side inertia ``J``, viscous ``b``, spring ``k``, spring damping ``d_s``)
  in continuous time, evaluated exactly at ``s = j w``, with the link velocity as the input;
* the two encoders sampled at the tick: the controller sees ``tau(kT)`` and ``theta(kT)``;
* the controller exactly as it runs: the discrete state-space model of
  :meth:`SeaTorqueController.linear_model` (C, C_ff, the DOB with H_n, Q and alpha), at
  ``z = exp(j w T)``;
* the command delay ``z^-d`` and the zero-order hold back into continuous time.

A sinusoidal link velocity ``q' = V exp(j w t)`` then gives a spring torque whose component at ``w``
is ``-Z(j w) V`` (the hold also creates components at ``w + n 2 pi / T``; with the velocity at
``w`` only, they carry no average power). ``Re Z(j w) V^2 / 2`` is the exact average power the
pilot puts in: this *sampled-data fundamental-harmonic* impedance is what an impedance
measurement on the real joint would show.

Why not the all-discrete model with the link velocity held over a tick: it misplaces the velocity
by half a tick against the sampled torque, so that even a bare spring ``Z = k / s`` appears as
``Z(z) = k T / (z - 1)`` with ``Re Z = -k T / 2 = -0.14 Nms/rad``: non-passive at every frequency,
for no physical reason.

Two limits the analysis shows (docs/control.md):

* With *no* spring damping, no torque feedback through a sampled, delayed loop is passive: the
  hold and the delay make any gain inject a little energy near 20-150 Hz (a proportional gain of
  0.02 already gives ``Re Z = -3e-5 Nms/rad``). Physical springs dissipate; the plant set therefore
  starts at the smallest spring damping for which the inner loop alone is passive
  (:func:`spring_damping_floor`).
* The observer lowers the impedance at low frequency by ``1 - alpha``, but lags the disturbance, which
  turns the lowered impedance non-passive for a large alpha; :func:`choose_alpha` finds the largest
  alpha that stays passive for the whole plant set and keeps a margin below it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import signal

from daror_runtime.control.base import ControlDesignError
from daror_runtime.control.filters import ComplexArray
from daror_runtime.control.sea_torque import SeaTorqueController
from daror_runtime.control.sea_torque_design import SeaPlant, SeaTorqueDesign
from hal.robot import FloatArray, SeaConstants

#: Spring damping (Nms/rad) of the nominal plant in the passivity analysis. ``description.sea`` has
#: no such field (the controller's model H_n uses 0); 0.2 is the order of the internal damping of
#: the torsion springs the simulated as-built drive train has.
NOMINAL_SPRING_DAMPING_NMS_PER_RAD = 0.2

#: Perturbations of the plant set, as factors of the nominal values (the brief's set).
INERTIA_FACTORS = (0.8, 1.0, 1.2)
VISCOUS_FACTORS = (0.5, 1.0, 1.5)
SPRING_DAMPING_FACTORS = (1.0, 2.0)  # plus the floor, see spring_damping_floor()

#: Chosen alpha = this x the largest passive alpha.
DEFAULT_MARGIN_FACTOR = 0.85


def frequency_grid(period_s: float = 1e-3, points: int = 3000, lowest_hz: float = 0.01) -> FloatArray:
    """Logarithmic grid from ``lowest_hz`` up to and including the Nyquist frequency (Hz)."""
    nyquist = 0.5 / period_s
    return np.logspace(np.log10(lowest_hz), np.log10(nyquist), points)


@dataclass(frozen=True)
class ImpedanceResponse:
    """Apparent impedance ``Z = -tau_s / q'`` (Nms/rad) of one joint over ``frequencies_hz``.

    ``stable`` is False when the torque loop itself is unstable on this plant (link held still):
    Z then means nothing and the joint counts as not passive.
    """

    plant: SeaPlant
    frequencies_hz: FloatArray
    impedance: ComplexArray
    spectral_radius: float

    @property
    def stable(self) -> bool:
        return self.spectral_radius < 1.0

    @property
    def min_real_part(self) -> float:
        """Smallest ``Re Z`` over the grid (Nms/rad); negative means energy flows to the pilot."""
        return float(np.min(self.impedance.real))

    @property
    def frequency_of_min_real_part_hz(self) -> float:
        return float(self.frequencies_hz[int(np.argmin(self.impedance.real))])

    @property
    def passive(self) -> bool:
        return self.stable and self.min_real_part >= 0.0


def _controller_response(
    controller: SeaTorqueController, z: ComplexArray, joint: int
) -> tuple[ComplexArray, ComplexArray]:
    """``(K_tau(z), K_theta(z))``: command per measured torque and per motor angle, ``tau_ref = 0``."""
    a, b, c, d = controller.linear_model(joint)
    n = a.shape[0]
    resolvent = np.linalg.solve(z[:, None, None] * np.eye(n)[None] - a[None], np.broadcast_to(b[:, 1:], (z.size, n, 2)))
    k = np.einsum("n,fnm->fm", c[0], resolvent) + d[0, 1:]
    return k[:, 0], k[:, 1]


def _plant_matrices(plant: SeaPlant) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Continuous ``A``, ``B_motor``, ``B_link`` of the state ``[delta = theta - q, theta']``."""
    j, b, k, ds = (
        plant.inertia_kgm2,
        plant.viscous_nms_per_rad,
        plant.stiffness_nm_per_rad,
        plant.spring_damping_nms_per_rad,
    )
    a = np.array([[0.0, 1.0], [-k / j, -(b + ds) / j]])
    b_motor = np.array([0.0, 1.0 / j])
    b_link = np.array([-1.0, ds / j])  # delta' = theta' - q', spring damping pulls on theta'
    return a, b_motor, b_link


def torque_loop_spectral_radius(controller: SeaTorqueController, plant: SeaPlant, joint: int = 1) -> float:
    """Largest closed-loop eigenvalue magnitude of the sampled torque loop, link held still.

    The discrete model: ZOH-discretised mechanics, ``delay_ticks`` of command delay, the
    controller's state-space model. Below 1: stable.
    """
    a_c, b_c, c_c, d_c = controller.linear_model(joint)
    a, b_motor, _ = _plant_matrices(plant)
    ad, bd, *_ = signal.cont2discrete(
        (a, b_motor[:, None], np.eye(2), np.zeros((2, 1))), controller.design.period_s, "zoh"
    )
    k = plant.stiffness_nm_per_rad
    delay = plant.delay_ticks
    n_c = a_c.shape[0]
    n = 2 + delay + n_c
    p, w0, c0 = slice(0, 2), 2, 2 + delay
    # Measured torque k delta and motor angle (delta + a constant link angle: the constant does not
    # matter, the motor-velocity filter does not pass it).
    meas = np.zeros((2, n))
    meas[0, 0] = k
    meas[1, 0] = 1.0
    command = c_c[0] @ np.eye(n_c, n, c0) + d_c[0, 1:] @ meas
    m = np.zeros((n, n))
    m[p, p] = ad
    if delay == 0:
        m[p] += np.outer(bd[:, 0], command)
    else:
        m[p, w0 + delay - 1] += bd[:, 0]
        m[w0] = command
        for i in range(1, delay):
            m[w0 + i, w0 + i - 1] = 1.0
    m[c0:, c0:] = a_c
    m[c0:] += b_c[:, 1:] @ meas
    return float(np.max(np.abs(np.linalg.eigvals(m))))


@dataclass(frozen=True)
class _PlantResponse:
    """Everything about one plant on one frequency grid that does not depend on the controller."""

    plant: SeaPlant
    frequencies_hz: FloatArray
    tau_meas_v: ComplexArray  # measured torque per unit link velocity (continuous, at w)
    theta_v: ComplexArray  # motor angle per unit link velocity
    tau_s_v: ComplexArray  # spring torque on the link per unit link velocity, motor torque held at 0
    tau_s_m: ComplexArray  # spring torque per unit motor torque
    p_tau: ComplexArray  # sampled loop: command -> measured torque (ZOH, delay)
    p_theta: ComplexArray  # sampled loop: command -> motor angle
    hold: ComplexArray  # fundamental of the ZOH with the command delay


def _plant_response(plant: SeaPlant, f: FloatArray, period: float) -> _PlantResponse:
    s = 2j * np.pi * f
    z = np.exp(s * period)
    a, b_motor, b_link = _plant_matrices(plant)
    k, ds = plant.stiffness_nm_per_rad, plant.spring_damping_nms_per_rad
    resolvent = np.linalg.inv(s[:, None, None] * np.eye(2)[None] - a[None])
    x_motor = resolvent @ b_motor  # (F, 2): state per unit motor torque
    x_link = resolvent @ b_link  # (F, 2): state per unit link velocity
    ad, bd, *_ = signal.cont2discrete((a, b_motor[:, None], np.eye(2), np.zeros((2, 1))), period, "zoh")
    x_d = np.linalg.solve(z[:, None, None] * np.eye(2)[None] - ad[None], np.broadcast_to(bd, (z.size, 2, 1)))[..., 0]
    delay = z ** (-plant.delay_ticks)
    return _PlantResponse(
        plant=plant,
        frequencies_hz=f,
        tau_meas_v=k * x_link[:, 0],
        theta_v=x_link[:, 0] + 1.0 / s,  # link angle = velocity / s
        tau_s_v=k * x_link[:, 0] + ds * x_link[:, 1] - ds,
        tau_s_m=k * x_motor[:, 0] + ds * x_motor[:, 1],
        p_tau=k * x_d[:, 0] * delay,
        p_theta=x_d[:, 0] * delay,
        hold=(1.0 - np.exp(-s * period)) / (s * period) * np.exp(-s * period * plant.delay_ticks),
    )


def _impedance(k_tau: ComplexArray, k_theta: ComplexArray, pr: _PlantResponse) -> ComplexArray:
    # The sampled loop closed around the sinusoidal disturbance, then held back into continuous time.
    command = (k_tau * pr.tau_meas_v + k_theta * pr.theta_v) / (1.0 - k_tau * pr.p_tau - k_theta * pr.p_theta)
    return -(pr.tau_s_v + pr.tau_s_m * pr.hold * command)


def _grid(controller: SeaTorqueController, frequencies_hz: FloatArray | None) -> FloatArray:
    period = controller.design.period_s
    f = frequency_grid(period) if frequencies_hz is None else np.asarray(frequencies_hz, dtype=float)
    if f.ndim != 1 or f.size == 0 or np.any(f <= 0.0) or np.any(f > 0.5 / period * (1 + 1e-9)):
        raise ControlDesignError("impedance frequencies must be a non-empty 1-D array in (0, Nyquist]")
    return f


def apparent_impedance(
    controller: SeaTorqueController,
    plant: SeaPlant | None = None,
    frequencies_hz: FloatArray | None = None,
    joint: int = 1,
) -> ImpedanceResponse:
    """The sampled-data apparent impedance of ``joint`` in minimal-impedance mode (``tau_ref = 0``).

    Args:
        controller: the torque controller (its design, alpha included, is what is analysed).
        plant: the drive train; default the controller's nominal SEA with
            :data:`NOMINAL_SPRING_DAMPING_NMS_PER_RAD` and the design's command delay.
        frequencies_hz: default :func:`frequency_grid` of the controller's period.
        joint: 1-based joint whose controller filters are used.

    Raises:
        ShapeError: ``joint`` out of range.
        ControlDesignError: frequencies outside (0, Nyquist].
    """
    if plant is None:
        plant = analysis_nominal_plant(controller.sea, controller.design)
    f = _grid(controller, frequencies_hz)
    period = controller.design.period_s
    k_tau, k_theta = _controller_response(controller, np.exp(2j * np.pi * f * period), joint)
    impedance = _impedance(k_tau, k_theta, _plant_response(plant, f, period))
    return ImpedanceResponse(plant, f, impedance, torque_loop_spectral_radius(controller, plant, joint))


def _responses(controller: SeaTorqueController, plant_responses: Sequence[_PlantResponse]) -> list[ImpedanceResponse]:
    """Impedances of one controller on many plants sharing one grid (the controller evaluated once)."""
    f = plant_responses[0].frequencies_hz
    k_tau, k_theta = _controller_response(controller, np.exp(2j * np.pi * f * controller.design.period_s), 1)
    return [
        ImpedanceResponse(
            pr.plant, f, _impedance(k_tau, k_theta, pr), torque_loop_spectral_radius(controller, pr.plant)
        )
        for pr in plant_responses
    ]


def analysis_nominal_plant(sea: SeaConstants, design: SeaTorqueDesign) -> SeaPlant:
    """The nominal plant of the passivity analysis: ``description.sea`` plus the nominal spring damping."""
    return replace(
        SeaPlant.nominal(sea, design.delay_ticks), spring_damping_nms_per_rad=NOMINAL_SPRING_DAMPING_NMS_PER_RAD
    )


def spring_damping_floor(
    sea: SeaConstants,
    design: SeaTorqueDesign,
    candidates_nms_per_rad: Sequence[float] = (0.0, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.15, 0.2),
    frequencies_hz: FloatArray | None = None,
) -> float:
    """Smallest candidate spring damping (Nms/rad) for which the inner loop alone (alpha = 0) is passive
    for every inertia and viscous perturbation.

    Raises:
        ControlDesignError: the inner loop is not passive even at the largest candidate.
    """
    controller = SeaTorqueController(sea, design.with_alpha(0.0), n_joints=1)
    nominal = analysis_nominal_plant(sea, design)
    f = _grid(controller, frequencies_hz)
    for ds in candidates_nms_per_rad:
        plants = [_plant_response(p, f, design.period_s) for p in _perturbations(nominal, (ds,))]
        if all(r.passive for r in _responses(controller, plants)):
            return float(ds)
    raise ControlDesignError(
        f"the torque loop without observer is not passive even with {candidates_nms_per_rad[-1]} Nms/rad of spring damping"
    )


def _perturbations(nominal: SeaPlant, spring_dampings: Sequence[float]) -> list[SeaPlant]:
    return [
        replace(
            nominal,
            inertia_kgm2=nominal.inertia_kgm2 * fj,
            viscous_nms_per_rad=nominal.viscous_nms_per_rad * fb,
            spring_damping_nms_per_rad=float(ds),
        )
        for fj in INERTIA_FACTORS
        for fb in VISCOUS_FACTORS
        for ds in spring_dampings
    ]


def perturbed_plants(
    sea: SeaConstants, design: SeaTorqueDesign, spring_damping_floor_nms_per_rad: float
) -> list[SeaPlant]:
    """The plant set: inertia x0.8/1/1.2, viscous x0.5/1/1.5, spring damping floor/x1/x2 of nominal (27 plants)."""
    nominal = analysis_nominal_plant(sea, design)
    dampings = (
        spring_damping_floor_nms_per_rad,
        *(f * nominal.spring_damping_nms_per_rad for f in SPRING_DAMPING_FACTORS),
    )
    return _perturbations(nominal, dampings)


@dataclass(frozen=True)
class PassivityCheck:
    """Passivity of one alpha over a plant set; ``worst`` is the response with the smallest Re Z."""

    alpha: float
    passive: bool
    worst: ImpedanceResponse


def check_passivity(
    sea: SeaConstants, design: SeaTorqueDesign, plants: Sequence[SeaPlant], frequencies_hz: FloatArray | None = None
) -> PassivityCheck:
    """Is ``design`` passive on every plant of ``plants``? (the design's alpha is the one checked)

    Raises:
        ControlDesignError: an empty plant set or frequencies outside (0, Nyquist].
    """
    if not plants:
        raise ControlDesignError("passivity needs at least one plant")
    controller = SeaTorqueController(sea, design, n_joints=1)
    f = _grid(controller, frequencies_hz)
    return _check(controller, [_plant_response(p, f, design.period_s) for p in plants])


def _check(controller: SeaTorqueController, plant_responses: Sequence[_PlantResponse]) -> PassivityCheck:
    responses = _responses(controller, plant_responses)
    unstable = [r for r in responses if not r.stable]
    worst = unstable[0] if unstable else min(responses, key=lambda r: r.min_real_part)
    return PassivityCheck(controller.design.alpha, not unstable and worst.min_real_part >= 0.0, worst)


@dataclass(frozen=True)
class AlphaChoice:
    """The result of :func:`choose_alpha`; impedances in Nms/rad, frequencies in Hz."""

    alpha: float  # chosen: margin_factor x alpha_limit
    alpha_limit: float  # largest passive alpha found (to the bisection resolution)
    margin_factor: float
    spring_damping_floor_nms_per_rad: float
    plants: tuple[SeaPlant, ...]
    at_alpha: PassivityCheck  # worst plant at the chosen alpha (min Re Z is the passivity margin)
    beyond_limit: PassivityCheck | None  # the first failure just above alpha_limit (None if alpha 1 passes)


def choose_alpha(
    sea: SeaConstants,
    design: SeaTorqueDesign | None = None,
    margin_factor: float = DEFAULT_MARGIN_FACTOR,
    plants: Sequence[SeaPlant] | None = None,
    resolution: float = 1.0 / 512.0,
    frequencies_hz: FloatArray | None = None,
) -> AlphaChoice:
    """The largest alpha in [0, 1] passive on the nominal and perturbed plants, times ``margin_factor``.

    A coarse scan (steps of 0.05) finds the first alpha that is not passive; bisection then narrows
    the boundary to ``resolution``. The scan guards against a passive region that is not one
    interval starting at 0 (it stops at the first failure).

    Raises:
        ControlDesignError: the design is not passive even without the observer (alpha = 0), or
            ``margin_factor`` is not in (0, 1].
    """
    design = design or SeaTorqueDesign()
    if not 0.0 < margin_factor <= 1.0:
        raise ControlDesignError(f"margin factor must be in (0, 1], got {margin_factor}")
    floor = spring_damping_floor(sea, design, frequencies_hz=frequencies_hz)
    plant_set = tuple(plants) if plants is not None else tuple(perturbed_plants(sea, design, floor))

    f = frequency_grid(design.period_s) if frequencies_hz is None else np.asarray(frequencies_hz, dtype=float)
    plant_responses = [_plant_response(p, f, design.period_s) for p in plant_set]

    def check(alpha: float) -> PassivityCheck:
        return _check(SeaTorqueController(sea, design.with_alpha(alpha), n_joints=1), plant_responses)

    if not check(0.0).passive:
        raise ControlDesignError("the torque loop is not passive on the plant set even without the observer")
    passing, failing = 0.0, None
    for alpha in np.arange(0.05, 1.0 + 1e-9, 0.05):
        result = check(float(alpha))
        if not result.passive:
            failing = (float(alpha), result)
            break
        passing = float(alpha)
    beyond = None
    if failing is not None:
        hi, beyond = failing
        while hi - passing > resolution:
            mid = 0.5 * (passing + hi)
            result = check(mid)
            if result.passive:
                passing = mid
            else:
                hi, beyond = mid, result
    alpha = margin_factor * passing
    return AlphaChoice(alpha, passing, margin_factor, floor, plant_set, check(alpha), beyond)
