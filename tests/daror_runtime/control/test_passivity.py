"""Apparent impedance and passivity of the SEA torque loop in minimal-impedance mode; the choice of alpha."""

from __future__ import annotations

import inspect
from dataclasses import replace

import numpy as np
import pytest

from daror_runtime.control import MinimalImpedance, SeaTorqueController, SeaTorqueDesign
from daror_runtime.control.base import ControlDesignError
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.passivity import (
    AlphaChoice,
    analysis_nominal_plant,
    apparent_impedance,
    check_passivity,
    choose_alpha,
    frequency_grid,
    perturbed_plants,
    spring_damping_floor,
    torque_loop_spectral_radius,
)
from daror_runtime.control.sea_torque_design import DEFAULT_ALPHA, SeaPlant
from hal.robot import RobotDescription, SeaConstants
from tests.daror_runtime.control.test_control import PERIOD_S, JointSim


@pytest.fixture(scope="module")
def sea() -> SeaConstants:
    from hal.robot import load_description

    return load_description().sea


@pytest.fixture(scope="module")
def choice(sea: SeaConstants) -> AlphaChoice:
    return choose_alpha(sea)


def test_chosen_alpha_is_the_default_and_keeps_a_margin(choice: AlphaChoice) -> None:
    """The analysis reproduces the shipped alpha; the margin is 15 % of the passive limit."""
    assert 0.5 < choice.alpha_limit < 1.0
    assert choice.alpha == pytest.approx(0.85 * choice.alpha_limit)
    assert choice.alpha + 1e-9 >= DEFAULT_ALPHA
    assert choice.alpha - DEFAULT_ALPHA < 0.01  # the constant was rounded down, not guessed
    assert choice.beyond_limit is not None
    assert not choice.beyond_limit.passive


def test_chosen_alpha_is_passive_on_nominal_and_perturbed_plants(sea: SeaConstants, choice: AlphaChoice) -> None:
    design = SeaTorqueDesign(alpha=DEFAULT_ALPHA)
    controller = SeaTorqueController(sea, design, n_joints=1)
    plants = [analysis_nominal_plant(sea, design), *choice.plants]
    assert len(choice.plants) == 27  # inertia x3, viscous x3, spring damping x3
    inertias = {p.inertia_kgm2 for p in plants}
    assert min(inertias) == pytest.approx(0.8 * 0.25)
    assert max(inertias) == pytest.approx(1.2 * 0.25)
    assert sorted({round(p.viscous_nms_per_rad, 9) for p in plants}) == [0.5, 1.0, 1.5]
    f = frequency_grid(PERIOD_S)
    assert f[-1] == pytest.approx(500.0)  # up to Nyquist
    worst = np.inf
    for plant in plants:
        response = apparent_impedance(controller, plant, f)
        assert response.stable
        assert response.min_real_part >= 0.0, (
            f"{plant}: Re Z = {response.min_real_part:.4f} at {response.frequency_of_min_real_part_hz:.1f} Hz"
        )
        worst = min(worst, response.min_real_part)
    assert worst > 0.01  # Nms/rad: the margin left at the chosen alpha


def test_too_large_alpha_is_detected_as_not_passive(sea: SeaConstants, choice: AlphaChoice) -> None:
    """The check can fail: full observer gain, and 5 % above the limit, are refused."""
    for alpha in (1.0, min(1.0, 1.05 * choice.alpha_limit)):
        result = check_passivity(sea, SeaTorqueDesign(alpha=alpha), choice.plants)
        assert not result.passive
        assert result.worst.min_real_part < 0.0
    heavy_low_friction = SeaPlant(0.3, 0.5, 289.0, 0.4, 1)  # where the limit sits (docs/control.md)
    assert (
        apparent_impedance(SeaTorqueController(sea, SeaTorqueDesign(alpha=1.0), 1), heavy_low_friction).min_real_part
        < 0
    )


def test_model_mismatch_is_detected(sea: SeaConstants, choice: AlphaChoice) -> None:
    """Drive trains outside the set: more command delay than designed for, or a lossless spring."""
    controller = SeaTorqueController(sea, SeaTorqueDesign(), n_joints=1)
    floor = replace(analysis_nominal_plant(sea, SeaTorqueDesign()), spring_damping_nms_per_rad=0.05)
    assert apparent_impedance(controller, floor).passive
    for mismatch in (
        replace(floor, delay_ticks=2),
        replace(floor, delay_ticks=5),
        replace(floor, spring_damping_nms_per_rad=0.0),
    ):
        response = apparent_impedance(controller, mismatch)
        assert not response.passive, mismatch
    # Five ticks is gross: the pilot would meet a strongly active joint near 27 Hz.
    assert apparent_impedance(controller, replace(floor, delay_ticks=5)).min_real_part < -1.0


def test_no_spring_damping_no_passive_sampled_torque_loop(sea: SeaConstants, choice: AlphaChoice) -> None:
    """Why the plant set starts at a spring-damping floor: at zero, even the observer-free loop leaks energy."""
    design = SeaTorqueDesign(alpha=0.0)
    controller = SeaTorqueController(sea, design, n_joints=1)
    bare = SeaPlant(0.2, 0.5, 289.0, 0.0, 1)
    response = apparent_impedance(controller, bare)
    assert response.stable
    assert response.min_real_part < 0.0
    assert 20.0 < response.frequency_of_min_real_part_hz < 300.0  # the delay's band, not the pilot's
    assert choice.spring_damping_floor_nms_per_rad == spring_damping_floor(sea, design)
    assert choice.spring_damping_floor_nms_per_rad <= 0.05  # a quarter of the as-built springs' 0.15-0.2
    assert apparent_impedance(controller, replace(bare, spring_damping_nms_per_rad=0.05)).passive


def test_motor_position_check_uses_the_passivity_floor(sea: SeaConstants, choice: AlphaChoice) -> None:
    """The position controller's stability check assumes the same spring-damping floor as the torque loop's."""
    default = inspect.signature(MotorPositionPD).parameters["spring_damping_nms_per_rad"].default
    assert choice.spring_damping_floor_nms_per_rad == default


def test_observer_lowers_the_low_frequency_impedance(sea: SeaConstants) -> None:
    """|Z| with the observer is about (1 - alpha) of |Z| without, below the observer's band."""
    f = np.array([0.1, 0.3, 0.5, 1.0])
    without = apparent_impedance(SeaTorqueController(sea, SeaTorqueDesign(alpha=0.0), 1), None, f)
    with_dob = apparent_impedance(SeaTorqueController(sea, SeaTorqueDesign(), 1), None, f)
    ratio = np.abs(with_dob.impedance) / np.abs(without.impedance)
    assert np.all(ratio < 0.45), ratio
    assert ratio[0] == pytest.approx(1.0 - DEFAULT_ALPHA, abs=0.03)
    # At DC the pilot feels the gearbox viscous friction divided by the loop gain (1 + K_p), times 1 - alpha.
    kp = SeaTorqueController(sea).loop.kp
    dc = apparent_impedance(SeaTorqueController(sea, SeaTorqueDesign(), 1), None, np.array([1e-3])).impedance[0]
    assert dc.real == pytest.approx((1 - DEFAULT_ALPHA) * sea.gearbox_viscous_nms_per_rad / (1 + kp), rel=0.01)


@pytest.mark.parametrize("frequency_hz", [2.0, 20.0, 60.0])
def test_impedance_matches_a_time_domain_simulation(description: RobotDescription, frequency_hz: float) -> None:
    """The sampled-data analysis against the pilot actually swinging the (linear) joint."""
    w, speed = 2 * np.pi * frequency_hz, 0.05

    def pilot(t: float) -> tuple[np.ndarray, np.ndarray]:
        return np.full(4, speed / w * np.sin(w * t)), np.full(4, speed * np.cos(w * t))

    sim = JointSim("driven", motion=pilot, noise=False, coulomb=False, substeps=20)
    mode = MinimalImpedance(SeaTorqueController(description.sea))
    ticks = int(max(6.0, 4.0 * frequency_hz) / frequency_hz * 1000)
    mode.reset(sim.read())
    lock_in = {"sum": np.zeros(4, complex), "count": 0}

    def accumulate(t: float) -> None:  # the continuous spring torque, at every substep
        lock_in["sum"] += sim.spring() * np.exp(-1j * w * t)
        lock_in["count"] += 1

    for k in range(ticks):  # the second half spans a whole number of periods
        sim.step(mode.update(sim.read(), PERIOD_S), accumulate if k >= ticks // 2 else None)
    z_sim = -2.0 * lock_in["sum"] / lock_in["count"] / speed
    controller = SeaTorqueController(description.sea, n_joints=1)
    for j in range(4):
        plant = SeaPlant(sim.j[j], sim.b[j], 289.0, sim.ds[j], 1)
        z = apparent_impedance(controller, plant, np.array([frequency_hz])).impedance[0]
        assert abs(z_sim[j] - z) < 0.02 * abs(z) + 2e-3, f"joint {j + 1}: simulated {z_sim[j]:.4f}, analysed {z:.4f}"


def test_inputs_are_checked(sea: SeaConstants) -> None:
    controller = SeaTorqueController(sea, n_joints=1)
    with pytest.raises(ControlDesignError):
        apparent_impedance(controller, None, np.array([0.0, 1.0]))
    with pytest.raises(ControlDesignError):
        apparent_impedance(controller, None, np.array([600.0]))
    with pytest.raises(ControlDesignError):
        choose_alpha(sea, margin_factor=1.5)
    with pytest.raises(ControlDesignError):
        check_passivity(sea, SeaTorqueDesign(), [])
    assert torque_loop_spectral_radius(controller, SeaPlant.nominal(sea)) < 1.0
    assert len(perturbed_plants(sea, SeaTorqueDesign(), 0.05)) == 27
