"""Issue 29, part 2: the drift test on the simulated plant, against the model's true error.

A lock-step session on the Dummy Arm scenario reaches compensation with a fitted PLF+ model; at
four poses the pilot holds his arm, the drift test starts and he relaxes at once; the session
catches the arm and measures the torque the model missed; then the same under the model with a
known error added (bench/online_harness.py).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from bench.online_harness import DriftCheck, SimulatedSession, fitted_model
from daror_runtime.online.drift import DRIFT_MAX_DEG, DRIFT_MAX_S

KNOWN_ERROR_NM = np.array([0.3, -0.5, 0.2, 0.4])


@pytest.fixture(scope="module")
def drifted(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[tuple[SimulatedSession, list[DriftCheck], list[DriftCheck]]]:
    folder = tmp_path_factory.mktemp("drift")
    model, validation = fitted_model("exo_dummy_arm", folder)
    session = SimulatedSession("exo_dummy_arm", folder / "session", model, validation)
    session.run(0.5)
    plain = session.drift_tests()
    session.use_offset(KNOWN_ERROR_NM)
    offset = session.drift_tests()
    yield session, plain, offset
    session.close()


def test_the_unsupported_torque_is_the_model_s_error_where_the_arm_was_caught(
    drifted: tuple[SimulatedSession, list[DriftCheck], list[DriftCheck]],
) -> None:
    _, plain, offset = drifted
    assert len(plain) == len(offset) == 4
    for check in [*plain, *offset]:
        true = check.model_error_nm
        # against the model's true error at the pose it was caught: within 25 % (and 0.01 Nm)
        assert np.all(np.abs(check.error_nm) <= 0.25 * np.abs(true) + 0.01), (check.result.unsupported_nm, true)
    for check in offset:  # the known error shows: within 25 % of it on every joint (PLF+'s own error beside it)
        unsupported = np.array(check.result.unsupported_nm)
        assert np.all(np.abs(unsupported - KNOWN_ERROR_NM) <= 0.25 * np.abs(KNOWN_ERROR_NM)), unsupported


def test_the_drift_is_caught_at_its_limits_and_the_catch_is_bumpless(
    drifted: tuple[SimulatedSession, list[DriftCheck], list[DriftCheck]],
) -> None:
    _, plain, offset = drifted
    for check in plain:  # a good model: the relaxed arm drifts under a degree in the whole second
        assert check.result.why_caught == f"{DRIFT_MAX_S:g} s passed"
        assert max(abs(v) for v in check.result.drift_deg) < 1.0
    for check in offset:  # 0.4 Nm missing at the elbow: caught at the drift limit, well before the second
        assert check.result.why_caught.startswith("joint 4 drifted 3.0 deg")
        assert check.result.drift_s < 0.5
        assert max(abs(v) for v in check.result.drift_deg) < DRIFT_MAX_DEG + 0.2
    for check in [*plain, *offset]:  # once held, the arm stays where it was caught (issue 9's 1 deg)
        assert check.held_drift_deg < 1.0


def test_the_drift_tests_are_in_the_status(
    drifted: tuple[SimulatedSession, list[DriftCheck], list[DriftCheck]],
) -> None:
    session, plain, offset = drifted
    online = {entry["model"]: entry for entry in session.runtime.status()["online"]}
    tests = online["PLF+ (model_plf_plus.json)"]["drift_tests"]
    assert [t["unsupported_nm"] for t in tests] == [[round(v, 4) for v in c.result.unsupported_nm] for c in plain]
    assert len(online["PLF+ + known error (model_plf_plus.json)"]["drift_tests"]) == len(offset)


def test_a_drift_test_is_refused_where_it_cannot_be_made(
    drifted: tuple[SimulatedSession, list[DriftCheck], list[DriftCheck]],
) -> None:
    session, _, _ = drifted
    runtime = session.runtime
    assert runtime.state_name == "compensation"
    runtime.wait(runtime.set_support(0.5))
    session.run(0.2)
    refused = runtime.wait(runtime.drift_test())
    assert not refused.accepted
    assert "set support 1.0" in refused.reason
    runtime.wait(runtime.set_support(1.0))
    session.run(3.0)
    session.world.pilot_move(runtime.last_sample.q_rad + np.array([0.0, 0.0, 0.0, 0.5]), 1.0)
    session.run(0.5)
    moving = runtime.wait(runtime.drift_test())
    assert not moving.accepted
    assert "must be still" in moving.reason
    session.run(1.5)
    runtime.wait(runtime.revert())
    session.run(0.3)
    assert runtime.state_name == "training"
    outside = runtime.wait(runtime.drift_test())
    assert not outside.accepted
    assert "compensation state" in outside.reason
