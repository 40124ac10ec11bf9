"""The simulator's own gravity path (CoM Jacobians) and its agreement with the PLF regressor.

docs/architecture.md: the plant computes gravity from link CoM Jacobians, not from the regressor,
and a test checks the two agree on noise-free data (thesis Sec. 3.4 / 4.4.2).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from daror_runtime.models.regressor import gravity_regressor
from hal.robot import load_description
from hal.sim.scenario import Scenario, load_scenario
from hal.sim.statics import PointMass, PullSpring, StaticPlant

configurations = arrays(np.float64, (5, 4), elements=st.floats(-2.5, 2.5))
DESCRIPTION = load_description()
SCENARIOS = {name: load_scenario(name) for name in ("exo", "exo_dummy_arm")}


def truth_theta(scenario: Scenario) -> np.ndarray:
    """Eq. 4.20 from the scenario's as-built truth (only tests may read the truth)."""
    g = scenario.gravity_mps2
    theta = np.concatenate([link.mass_kg * g * np.asarray(link.com_m) for link in scenario.links])
    delta = np.asarray(DESCRIPTION.geometry.elbow_offset_m)
    theta[6:9] += scenario.links[3].mass_kg * g * delta
    if scenario.dummy_arm is not None:
        upper, lower = scenario.dummy_arm.upper_arm, scenario.dummy_arm.lower_arm
        theta[6:9] += upper.mass_kg * g * np.asarray(upper.com_m) + lower.mass_kg * g * delta
        theta[9:12] += lower.mass_kg * g * np.asarray(lower.com_m)
    return theta


@pytest.mark.parametrize("name", ["exo", "exo_dummy_arm"])
@given(q=configurations)
def test_holding_torque_is_the_gradient_of_the_potential(name: str, q: np.ndarray) -> None:
    plant = SCENARIOS[name].static_plant(DESCRIPTION)
    h = 1e-6
    numeric = np.empty_like(q)
    for j in range(4):
        step = np.zeros(4)
        step[j] = h
        numeric[:, j] = (plant.potential_energy_j(q + step) - plant.potential_energy_j(q - step)) / (2 * h)
    assert plant.holding_torque_nm(q) == pytest.approx(numeric, abs=1e-6)


@pytest.mark.parametrize("name", ["exo", "exo_dummy_arm"])
@given(q=configurations)
def test_regressor_reproduces_the_independent_gravity_path(name: str, q: np.ndarray) -> None:
    scenario = SCENARIOS[name]
    plant = scenario.static_plant(DESCRIPTION)
    via_regressor = gravity_regressor(DESCRIPTION.kinematics(), q) @ truth_theta(scenario)
    assert via_regressor == pytest.approx(plant.gravity_torque_nm(q), abs=1e-12)


def test_mass_in_the_centre_of_rotation_or_on_joint_one_axis_needs_no_torque(rng: np.random.Generator) -> None:
    kin = DESCRIPTION.kinematics()
    plant = StaticPlant(kin, [PointMass(3, 2.0, (0.0, 0.0, 0.0)), PointMass(1, 1.0, (0.0, 0.0, 0.3))])
    q = rng.uniform(-2, 2, (50, 4))
    assert plant.holding_torque_nm(q) == pytest.approx(np.zeros((50, 4)), abs=1e-12)


def test_pendulum_on_the_elbow_matches_m_g_l_sin() -> None:
    # Only the forearm mass: joint 4's holding torque is m g l times the sine of the angle between
    # the forearm and the downward vertical, projected on the (tilted) elbow axis.
    kin = DESCRIPTION.kinematics()
    m, length = 1.0, 0.2
    plant = StaticPlant(kin, [PointMass(4, m, (length, 0.0, 0.0))])
    q = np.array([[0.2, 0.4, -0.3, 0.9]])
    forearm = kin.rotor_rotations(q)[0, 3] @ [length, 0, 0]
    axis = kin.joint_axes(q)[0, 3]
    expected = np.dot(np.cross(axis, forearm), [0.0, m * 9.81, 0.0])
    assert plant.holding_torque_nm(q)[0, 3] == pytest.approx(expected)
    assert plant.holding_torque_nm(q)[0, :3] != pytest.approx(np.zeros(3))  # the shoulder carries it too


def test_pull_only_springs() -> None:
    kin = DESCRIPTION.kinematics()
    flexion = PullSpring(4, 2.0, 0.5, "flexion")
    extension = PullSpring(4, 3.0, 0.2, "extension")
    plant = StaticPlant(kin, [], [flexion, extension])
    q4 = np.array([0.0, 0.2, 0.3, 0.5, 0.9])
    q = np.column_stack([np.zeros((5, 3)), q4])
    # below 0.2 the extension spring pulls towards flexion (negative holding torque); above 0.5 the flexion one.
    assert plant.spring_torque_nm(q)[:, 3] == pytest.approx([-0.6, 0.0, 0.0, 0.0, 0.8])
    assert plant.potential_energy_j(q) == pytest.approx([0.06, 0.0, 0.0, 0.0, 0.16])


def test_dummy_arm_loads_the_shoulder(rng: np.random.Generator) -> None:
    q = rng.uniform(-0.5, 0.5, (200, 4))
    alone = SCENARIOS["exo"].static_plant(DESCRIPTION).holding_torque_nm(q)
    loaded = SCENARIOS["exo_dummy_arm"].static_plant(DESCRIPTION).holding_torque_nm(q)
    assert np.sqrt(np.mean((loaded - alone) ** 2)) > 1.0  # several Nm of arm on the shoulder
