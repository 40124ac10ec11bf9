"""RMSE (Eq. 4.31) and nRMSE (Eq. 4.32)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from daror_runtime.models.metrics import error_metrics
from hal.errors import ShapeError

torques = arrays(np.float64, (8, 4), elements=st.floats(-20, 20)).filter(lambda a: np.all(np.abs(a).max(axis=0) > 0.1))


def test_hand_computed_example() -> None:
    measured = np.array([[1.0, -4.0, 2.0, 0.5], [3.0, -2.0, -2.0, 1.0]])
    model = np.array([[1.0, -3.0, 2.0, 0.0], [2.0, -2.0, -1.0, 1.0]])
    m = error_metrics(measured, model)
    # errors: [0, -1, 0, 0.5], [1, 0, -1, 0]
    assert m.rmse_nm == pytest.approx(np.sqrt((0 + 1 + 0 + 0.25 + 1 + 0 + 1 + 0) / 8))
    assert m.rmse_per_joint_nm == pytest.approx((np.sqrt(0.5), np.sqrt(0.5), np.sqrt(0.5), np.sqrt(0.125)))
    # Eq. 4.32: divide by the peak magnitude per joint (3, 4, 2, 1), sum over joints, mean over N = 2.
    expected = np.sqrt(((1 / 3) ** 2 + (1 / 4) ** 2 + (1 / 2) ** 2 + 0.5**2) / 2)
    assert m.nrmse == pytest.approx(expected)
    assert m.n_points == 2


@given(measured=torques, model=torques, scale=st.floats(0.1, 10))
def test_scaling(measured: np.ndarray, model: np.ndarray, scale: float) -> None:
    m = error_metrics(measured, model)
    scaled = error_metrics(scale * measured, scale * model)
    assert scaled.rmse_nm == pytest.approx(scale * m.rmse_nm, rel=1e-9, abs=1e-12)
    assert scaled.nrmse == pytest.approx(m.nrmse, rel=1e-9, abs=1e-12)  # the point of normalising
    assert error_metrics(measured, measured).rmse_nm == 0.0


@given(measured=torques, model=torques)
def test_overall_rmse_is_the_quadratic_mean_of_the_joints(measured: np.ndarray, model: np.ndarray) -> None:
    m = error_metrics(measured, model)
    assert m.rmse_nm == pytest.approx(np.sqrt(np.mean(np.square(m.rmse_per_joint_nm))))


def test_shapes_are_checked() -> None:
    with pytest.raises(ShapeError):
        error_metrics(np.zeros((3, 4)), np.zeros((3, 3)))
    with pytest.raises(ShapeError):
        error_metrics(np.zeros((0, 4)), np.zeros((0, 4)))
