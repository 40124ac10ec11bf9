"""The PLF regressor (Eq. 4.21-4.27) and the fast evaluator used in the tick."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from daror_runtime.models.least_squares import min_norm_least_squares
from daror_runtime.models.regressor import (
    GRAVITY_PARAMETER_NAMES,
    N_GRAVITY_PARAMETERS,
    LinearTorqueEvaluator,
    gravity_regressor,
    linear_torque,
    regressor_parameter_major,
)
from hal.errors import ShapeError
from hal.robot import N_JOINTS, FloatArray, Kinematics, as_configurations, load_description

KIN = load_description().kinematics()
configurations = arrays(np.float64, (6, 4), elements=st.floats(-3.0, 3.0))
parameters = arrays(np.float64, (12,), elements=st.floats(-5.0, 5.0))
polynomials = arrays(np.float64, (6,), elements=st.floats(-2.0, 2.0))


def potential_regressor(kinematics: Kinematics, q: FloatArray) -> FloatArray:
    """``Kbar_y(q)`` of Eq. 4.19 with Eq. 4.3: ``V_y = Kbar_y theta``; shape (N, 12)."""
    rotors = kinematics.rotor_rotations_component_major(q)  # (4, 3, 3, N)
    return rotors[:, 1, :, :].reshape(N_GRAVITY_PARAMETERS, -1).T


def elbow_polynomial_regressor(q: FloatArray, order: int) -> FloatArray:
    """``K_s(q4)`` of Eq. 4.26 placed on the elbow row; shape (N, 4, order + 1)."""
    q = as_configurations(q)
    regressor = np.zeros((q.shape[0], N_JOINTS, order + 1))
    regressor[:, 3, 0] = 1.0
    # successive products, exactly as regressor_parameter_major builds them
    regressor[:, 3, 1:] = np.cumprod(np.repeat(q[:, 3:4], order, axis=1), axis=1)
    return regressor


@given(q=configurations, theta=parameters, mu=polynomials)
def test_evaluator_equals_regressor_times_parameters(q: np.ndarray, theta: np.ndarray, mu: np.ndarray) -> None:
    evaluator = LinearTorqueEvaluator(KIN, theta, mu)
    via_regressor = gravity_regressor(KIN, q) @ theta + elbow_polynomial_regressor(q, 5) @ mu
    batch = evaluator.torque_batch(q)
    assert batch == pytest.approx(via_regressor, abs=1e-10)
    for n in range(q.shape[0]):
        assert evaluator.torque(q[n]) == pytest.approx(batch[n], abs=1e-12)
        interpreted = np.empty(4)  # the same source run by Python, not by numba
        linear_torque.py_func(q[n], evaluator.packed_parameters, interpreted)
        assert interpreted == pytest.approx(batch[n], abs=1e-12)


@given(q=configurations, theta=parameters, mu=polynomials)
def test_torque_is_the_gradient_of_the_potential(q: np.ndarray, theta: np.ndarray, mu: np.ndarray) -> None:
    evaluator = LinearTorqueEvaluator(KIN, theta, mu)
    h = 1e-6
    for j in range(4):
        step = np.zeros(4)
        step[j] = h
        numeric = (evaluator.potential_batch(q + step) - evaluator.potential_batch(q - step)) / (2 * h)
        assert evaluator.torque_batch(q)[:, j] == pytest.approx(numeric, abs=1e-5)


@given(q=configurations, theta=parameters)
def test_potential_regressor_is_eq_4_19(q: np.ndarray, theta: np.ndarray) -> None:
    rotors = KIN.rotor_rotations(q)
    expected = sum(rotors[:, i, 1, :] @ theta[3 * i : 3 * i + 3] for i in range(4))
    assert potential_regressor(KIN, q) @ theta == pytest.approx(expected, abs=1e-12)


def test_regressor_is_block_upper_triangular_eq_4_22(rng: np.random.Generator) -> None:
    k = gravity_regressor(KIN, rng.uniform(-2, 2, (30, 4)))
    for j in range(4):
        for i in range(j):
            assert np.all(k[:, j, 3 * i : 3 * i + 3] == 0.0), f"row {j + 1} must not see link {i + 1}"


def test_rank_is_8_of_12_and_14_of_18(rng: np.random.Generator) -> None:
    """Sec. 4.2.1: Matlab's rank() of the stacked regressor returns 8; PLF+ adds six."""
    q = rng.uniform(-np.pi, np.pi, (200, 4))
    for order, expected, columns in ((None, 8, 12), (5, 14, 18)):
        kt = regressor_parameter_major(KIN, q, order).reshape(columns, -1)
        assert np.linalg.matrix_rank(kt.T) == expected
        assert min_norm_least_squares(kt, np.zeros(kt.shape[1])).rank == expected
    # theta1z never moves: its column is identically zero.
    assert np.all(gravity_regressor(KIN, q)[:, :, GRAVITY_PARAMETER_NAMES.index("theta1z")] == 0.0)


def test_parameter_major_layout_is_a_transpose_of_the_documented_one(rng: np.random.Generator) -> None:
    q = rng.uniform(-2, 2, (9, 4))
    pm = regressor_parameter_major(KIN, q, 5)
    assert pm.shape == (18, 4, 9)
    assert np.array_equal(np.transpose(pm[:12], (2, 1, 0)), gravity_regressor(KIN, q))
    assert np.array_equal(np.transpose(pm[12:], (2, 1, 0)), elbow_polynomial_regressor(q, 5))


def test_evaluator_refuses_wrong_parameter_count() -> None:
    with pytest.raises(ShapeError, match="12"):
        LinearTorqueEvaluator(KIN, np.zeros(11))
