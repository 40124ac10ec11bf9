"""Residual analysis on simulated data carrying effects no model declares (issue 5 acceptance).

One scenario per family (``hal/sim/scenarios/residual_*.yaml``), a clean one and one outside
every family (a slow drift). One configuration (the defaults) must pass them all: the right
family and joint named, the validation RMSE after closure within 1.3x of the scenario's sensor
noise floor, nothing added on the clean data, ``unexplained`` on the drift.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
import pytest

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.compare import evaluate_models
from daror_runtime.models.files import load_model, save_model
from daror_runtime.residual.diagnosis import Closure, Diagnosis, closure, diagnose
from daror_runtime.residual.effects import Effect
from daror_runtime.residual.evidence import DiagnosisSettings
from daror_runtime.residual.model import AugmentedModel, augmented_model
from hal.robot import load_description
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary, noise_floor_rmse_nm
from tests.conftest import as_dataset

#: Slow tier as a whole (docs/testing.md): a diagnosis of each scenario (~4 s each) feeds every test here.
pytestmark = pytest.mark.slow

NOISE_FLOOR_FACTOR = 1.3


@dataclass(frozen=True)
class Case:
    train: StationaryDataset
    validate: StationaryDataset
    floor_nm: float
    diagnosis: Diagnosis
    closure: Closure


@cache
def case(name: str, base: str = "plf+") -> Case:
    """Training and validation data of a scenario, its noise floor, and the default diagnosis."""
    scenario = load_scenario(name)
    train = as_dataset(generate_stationary(scenario, "training"), f"{name}:training")
    measured = generate_stationary(scenario, "validation")
    floor = noise_floor_rmse_nm(measured, generate_stationary(scenario, "validation", systematic_only=True))
    validate = as_dataset(measured, f"{name}:validation")
    diagnosis = diagnose(train, load_description(), base)
    return Case(train, validate, floor, diagnosis, closure(diagnosis, validate))


FAMILY_CASES = [
    ("residual_direction_offset", Effect("direction_offset", 2)),
    ("residual_joint_stiffness", Effect("joint_stiffness", 1)),
    ("residual_gravity_tilt", Effect("gravity_tilt")),
    ("residual_encoder_offset", Effect("encoder_offset", 2)),
    ("residual_torque_gain", Effect("torque_gain", 3)),
]


@pytest.mark.slow
@pytest.mark.parametrize(("scenario", "expected"), FAMILY_CASES, ids=[c[0] for c in FAMILY_CASES])
def test_each_family_is_named_and_closes_to_the_noise_floor(scenario: str, expected: Effect) -> None:
    c = case(scenario)
    sites = [f.effect.site for f in c.diagnosis.found]
    assert sites == [expected.site], f"expected exactly {expected.label}, found {sites}"
    assert c.closure.before.rmse_nm > 1.3 * c.floor_nm, "the scenario's effect must be visible in the base model"
    assert c.closure.after.rmse_nm <= NOISE_FLOOR_FACTOR * c.floor_nm
    assert not c.diagnosis.unexplained
    assert c.closure.rmse_gain_nm(0) > 0


def _parameters(scenario: str) -> dict[str, object]:
    return case(scenario).diagnosis.found[0].parameters


def test_physical_parameters_match_the_injected_truth() -> None:
    # The scenario files declare: 0.6 Nm; 2.0 Nm/rad about 10 deg; 1.5 / -2.0 deg; 1.5 deg; 1.12x spring.
    assert _parameters("residual_direction_offset")["offset_nm"] == pytest.approx(0.6, abs=0.01)
    stiffness = _parameters("residual_joint_stiffness")
    assert stiffness["stiffness_nm_per_rad"] == pytest.approx(2.0, abs=0.1)
    assert stiffness["rest_angle_deg"] == pytest.approx(10.0, abs=1.0)
    tilt = _parameters("residual_gravity_tilt")
    assert tilt["about_x_deg"] == pytest.approx(1.5, abs=0.05)
    assert tilt["about_z_deg"] == pytest.approx(-2.0, abs=0.05)
    assert _parameters("residual_encoder_offset")["offset_deg"] == pytest.approx(1.5, abs=0.05)
    gain = _parameters("residual_torque_gain")
    assert gain["gain"] == pytest.approx(1 / 1.12, abs=0.003)
    assert gain["spring_nm_per_rad"] == pytest.approx(289 * 1.12, rel=0.005)


def test_parameter_standard_errors_cover_the_truth() -> None:
    p = _parameters("residual_direction_offset")
    assert 0 < p["offset_std_error_nm"] < 0.01  # type: ignore[operator]
    assert abs(p["offset_nm"] - 0.6) < 5 * p["offset_std_error_nm"]  # type: ignore[operator]


def test_clean_data_add_nothing() -> None:
    c = case("residual_clean")
    assert c.diagnosis.found == []
    assert c.closure.after.rmse_nm == pytest.approx(c.closure.before.rmse_nm, rel=1e-9)
    assert c.closure.after.rmse_nm <= NOISE_FLOOR_FACTOR * c.floor_nm
    assert not c.diagnosis.unexplained
    verdicts = {e.verdict for e in c.diagnosis.rounds[0]}
    assert "found" not in verdicts


def test_an_effect_outside_every_family_is_reported_unexplained() -> None:
    c = case("residual_drift")
    assert c.diagnosis.unexplained
    strongest = c.diagnosis.structured_correlates[0]
    assert (strongest.joint, strongest.signal) == (2, "t")
    assert strongest.r2 > 0.5
    # No configuration effect can close it: the validation error stays far above the floor.
    assert c.closure.after.rmse_nm > 3 * c.floor_nm


def test_effects_the_base_model_already_holds_are_absorbed_not_found() -> None:
    # PLF+ holds a rotated theta (an encoder offset on joints 3 and 4) and the elbow polynomial.
    verdicts = {(e.effect.family, e.effect.joint): e for e in case("residual_clean").diagnosis.rounds[0]}
    for site in (("encoder_offset", 3), ("encoder_offset", 4), ("joint_stiffness", 4)):
        assert verdicts[site].verdict == "absorbed"
        assert verdicts[site].orthogonal_fraction < 1e-6
    assert verdicts[("encoder_offset", 2)].orthogonal_fraction > 0.01


def test_plf_base_finds_the_elbow_stiffness_plf_plus_adds() -> None:
    # The Dummy Arm's elbow spring is what PLF+ adds to PLF (Sec. 4.2.2): on a PLF base the
    # diagnosis must rediscover it as joint 4 stiffness.
    c = case("residual_clean", "plf")
    sites = [f.effect.site for f in c.diagnosis.found]
    assert ("joint_stiffness", 4) in sites
    spring = next(f for f in c.diagnosis.found if f.effect.site == ("joint_stiffness", 4)).parameters
    assert spring["stiffness_nm_per_rad"] == pytest.approx(2.84, rel=0.1)  # the flexion spring
    assert c.closure.after.rmse_nm <= NOISE_FLOOR_FACTOR * c.floor_nm


@pytest.mark.slow
def test_dataset_b_names_joint_2_direction_error_first(dataset_b: tuple[StationaryDataset, StationaryDataset]) -> None:
    train, validate = dataset_b
    diagnosis = diagnose(train, load_description())
    first = diagnosis.found[0]
    assert (first.effect.family, first.effect.joint) == ("direction_offset", 2)
    assert first.parameters["offset_nm"] == pytest.approx(0.75, abs=0.02)
    result = closure(diagnosis, validate)
    assert result.after.rmse_nm < 0.1 * result.before.rmse_nm


def test_one_configuration_for_all_scenarios() -> None:
    # The cases above all ran with the defaults: nothing per scenario to tune.
    assert all(case(name).diagnosis.settings == DiagnosisSettings() for name, _ in FAMILY_CASES)


# --- closure: an ordinary model the runtime runs ----------------------------------------------


def test_augmented_model_round_trips_through_a_model_file(tmp_path) -> None:  # type: ignore[no-untyped-def]
    c = case("residual_gravity_tilt")
    model = augmented_model(c.diagnosis.final_fit)
    path = tmp_path / "augmented.json"
    save_model(path, model)
    loaded, contents = load_model(path)
    assert isinstance(loaded, AugmentedModel)
    assert contents.kind == "augmented"
    q = c.validate.q_rad
    np.testing.assert_allclose(loaded.torque_batch(q), model.torque_batch(q), atol=1e-12)
    np.testing.assert_allclose(
        loaded.predict(q, c.validate.direction), c.diagnosis.final_fit.predict(c.validate), atol=1e-9
    )
    for row in q[:20]:
        np.testing.assert_allclose(loaded.torque(row), loaded.torque_batch(row[None, :])[0], atol=1e-12)
    evaluation = evaluate_models([loaded], c.validate)[0]
    assert evaluation.metrics.rmse_nm == pytest.approx(c.closure.after.rmse_nm, rel=1e-9)


def test_direction_term_is_in_the_prediction_but_not_in_the_loop_torque() -> None:
    c = case("residual_direction_offset")
    model = augmented_model(c.diagnosis.final_fit)
    q, direction = c.validate.q_rad, c.validate.direction
    difference = model.predict(q, direction) - model.torque_batch(q)
    np.testing.assert_allclose(difference[:, [0, 2, 3]], 0.0, atol=1e-12)
    np.testing.assert_allclose(difference[:, 1], 0.6 * direction[:, 1], atol=0.01)  # type: ignore[index]


def test_augmented_model_compensates_the_true_gravity_better_than_the_base() -> None:
    # Against the simulator's truth (what the robot must hold), not the readings.
    scenario = load_scenario("residual_gravity_tilt")
    truth = generate_stationary(scenario, "validation")
    c = case("residual_gravity_tilt")
    model = augmented_model(c.diagnosis.final_fit)
    base = c.diagnosis.base_fit.predict(c.validate)
    error_base = math.sqrt(np.mean((base - truth.tau_true_nm) ** 2))
    error_augmented = math.sqrt(np.mean((model.torque_batch(truth.q_rad) - truth.tau_true_nm) ** 2))
    assert error_augmented < 0.1 * error_base
