"""The closed-path energy test (Sec. 4.4.4, 5.2, Table IV)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from daror_runtime.errors import UsageError
from daror_runtime.models.cvf import THESIS_STEPS_RAD, closed_path, cvf_test
from daror_runtime.models.linear import fit_plf, fit_plf_plus
from hal.robot import RobotDescription


def test_path_is_closed_and_steps_pi_over_4_in_each_joint() -> None:
    start = np.array([0.1, -0.2, 0.3, 0.4])
    path = closed_path(start, np.pi / 400)
    assert path.shape == (8 * 100 + 1, 4)
    assert np.array_equal(path[0], start)
    assert path[-1] == pytest.approx(start, abs=1e-12)
    assert path.max(axis=0) - start == pytest.approx(np.full(4, np.pi / 4))
    assert path.min(axis=0) == pytest.approx(start)
    # one joint at a time
    assert np.all(np.count_nonzero(np.abs(np.diff(path, axis=0)) > 1e-15, axis=1) == 1)


@pytest.mark.parametrize("fit", [fit_plf, fit_plf_plus])
def test_plf_models_are_conservative(fit, dataset_b, description: RobotDescription) -> None:
    model = fit(dataset_b[0], description).model
    result = cvf_test(model.torque_batch, [0.0, 0.2, 0.0, 0.5])
    assert result.conservative
    energies = [abs(s.energy_j) for s in result.steps]
    # first-order convergence: about tenfold smaller dV for each tenfold smaller dq
    for coarse, fine in itertools.pairwise(energies):
        assert 8.0 < coarse / fine < 12.5


def test_a_curl_field_is_not_conservative() -> None:
    """tau = (-q2, q1, 0, 0) has curl 2: the square the path walks (counter-clockwise) in (q1, q2) keeps 2 (pi/4)^2."""

    def curl(q: np.ndarray) -> np.ndarray:
        return np.column_stack([-q[:, 1], q[:, 0], np.zeros(len(q)), np.zeros(len(q))])

    result = cvf_test(curl, [0.0, 0.0, 0.0, 0.0], THESIS_STEPS_RAD)
    assert not result.conservative
    assert result.steps[-1].energy_j == pytest.approx(2 * (np.pi / 4) ** 2, rel=1e-3)


def test_an_exactly_conservative_field_under_the_floor_passes() -> None:
    result = cvf_test(lambda q: np.zeros_like(q), [0.0] * 4)
    assert result.conservative
    assert all(s.energy_j == 0.0 for s in result.steps)


def test_step_larger_than_the_path_is_refused() -> None:
    with pytest.raises(UsageError, match="at most the path amplitude"):
        closed_path([0.0] * 4, 1.0)
    with pytest.raises(UsageError, match="positive"):
        closed_path([0.0] * 4, 0.0)
