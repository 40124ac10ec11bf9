"""Undeclared effects of the simulated plant (docs/simulation.md, "Undeclared effects").

Each effect is checked against its physics, on both code paths: the static one
(``Scenario.static_plant``, ``read_encoders``, ``measure_stops``) and the dynamic one
(``DynamicPlant``, the drive kernels behind ``SimHal``). Also: ``extends`` in scenario files,
``systematic_only`` readings and the sensor-noise floor.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hal.errors import DescriptionError, InputError, ShapeError
from hal.interface import Command
from hal.robot import N_JOINTS, load_description, rot_x
from hal.sim.backend import SimHal
from hal.sim.plant import DynamicPlant
from hal.sim.scenario import Scenario, deep_merge, load_scenario, scenario_names
from hal.sim.sensors import read_encoders
from hal.sim.static_dataset import (
    STREAM_VALIDATION,
    generate_stationary,
    measure_stops,
    noise_floor_rmse_nm,
    scenario_stops,
    stream,
)
from hal.sim.statics import StaticPlant

DESCRIPTION = load_description()
K_NOMINAL = DESCRIPTION.sea.spring_stiffness_nm_per_rad
RESIDUAL_SCENARIOS = (
    "residual_clean",
    "residual_direction_offset",
    "residual_joint_stiffness",
    "residual_gravity_tilt",
    "residual_encoder_offset",
    "residual_torque_gain",
    "residual_drift",
)
#: Configurations inside the device's range of motion (beyond it the dynamic plant's end stops push).
CONFIGURATIONS = np.random.default_rng(20261122).uniform(
    DESCRIPTION.lower_limits_rad, DESCRIPTION.upper_limits_rad, size=(25, N_JOINTS)
)


def without(scenario: Scenario, **defaults: object) -> Scenario:
    """``scenario`` with the named top-level or ``sensors.*`` fields set (to their absent values)."""
    sensor_fields = {k: v for k, v in defaults.items() if k in type(scenario.sensors).model_fields}
    top = {k: v for k, v in defaults.items() if k not in sensor_fields}
    return scenario.model_copy(update={**top, "sensors": scenario.sensors.model_copy(update=sensor_fields)})


def quiet(scenario: Scenario) -> Scenario:
    """No encoder noise, no quantisation, no command delay: readings are exact functions of the truth."""
    assert scenario.drive_train is not None
    return scenario.model_copy(
        update={
            "sensors": scenario.sensors.model_copy(update={"encoder_noise_rad": 0.0, "quantise": False}),
            "drive_train": scenario.drive_train.model_copy(update={"command_delay_ticks": 0}),
        }
    )


def every_effect() -> Scenario:
    """One scenario with every undeclared effect at once, four joint springs included."""
    base = load_scenario("exo_dummy_arm")
    data = base.model_dump()
    data.update(
        mounting_tilt_deg=[-2.5, 3.0],
        joint_springs=[
            {"joint": j, "stiffness_nm_per_rad": 1.0 + j, "rest_angle_deg": 5.0 * j} for j in range(1, N_JOINTS + 1)
        ],
        sea_stiffness_scale=[0.9, 1.05, 1.12, 0.95],
    )
    data["sensors"].update(angle_offset_deg=[0.3, -1.5, 0.7, 2.0], torque_drift_nm_per_min=[0.01, 0.03, -0.02, 0.0])
    return Scenario.model_validate(data)


# --- the shipped scenarios ----------------------------------------------------------------------


def test_residual_scenarios_are_shipped_extend_the_dummy_arm_and_have_distinct_seeds() -> None:
    base = load_scenario("exo_dummy_arm")
    seeds = set()
    for name in RESIDUAL_SCENARIOS:
        assert name in scenario_names()
        scenario = load_scenario(name)
        assert scenario.name == name
        assert scenario.summary
        assert scenario.links == base.links
        assert scenario.dummy_arm == base.dummy_arm
        assert scenario.drive_train == base.drive_train
        seeds.add(scenario.seed)
    assert len(seeds | {base.seed, load_scenario("exo").seed}) == len(RESIDUAL_SCENARIOS) + 2


@pytest.mark.parametrize("name", ["exo", "exo_dummy_arm"])
def test_the_original_scenarios_declare_no_undeclared_effect(name: str) -> None:
    scenario = load_scenario(name)
    assert scenario.mounting_tilt_deg == [0.0, 0.0]
    assert scenario.joint_springs == []
    assert scenario.sea_stiffness_scale == [1.0] * N_JOINTS
    assert scenario.sensors.angle_offset_deg == [0.0] * N_JOINTS
    assert scenario.sensors.torque_drift_nm_per_min == [0.0] * N_JOINTS
    # Absent means the very same floats: the chain and the stiffness the plants are built from.
    np.testing.assert_array_equal(
        scenario.true_kinematics(DESCRIPTION).base_rotation, DESCRIPTION.kinematics().base_rotation
    )
    np.testing.assert_array_equal(scenario.stiffness_nm_per_rad(DESCRIPTION), np.full(N_JOINTS, K_NOMINAL))


def test_without_effects_the_static_readings_are_those_of_the_plain_sensor_model() -> None:
    """Regression: the effect parameters, when absent, change no bit of a generated dataset."""
    scenario = load_scenario("exo_dummy_arm")
    points = generate_stationary(scenario, "validation")
    stops = scenario_stops(scenario, "validation")
    assert np.array_equal(points.q_true_rad, stops)
    plain = read_encoders(
        points.q_true_rad,
        scenario.static_plant(DESCRIPTION).holding_torque_nm(stops),
        points.direction,
        scenario.sensors,
        DESCRIPTION.sea,
        stream(scenario.seed, STREAM_VALIDATION),
    )
    np.testing.assert_array_equal(points.q_rad, plain.q_rad)
    np.testing.assert_array_equal(points.tau_nm, plain.torque_nm)


# --- static and dynamic agree ---------------------------------------------------------------------


@pytest.mark.parametrize("name", [*RESIDUAL_SCENARIOS, "every_effect"])
def test_dynamic_holding_torque_equals_the_static_one(name: str) -> None:
    scenario = every_effect() if name == "every_effect" else load_scenario(name)
    plant = DynamicPlant(scenario, DESCRIPTION)
    expected = scenario.static_plant(DESCRIPTION).holding_torque_nm(CONFIGURATIONS)
    for q, tau in zip(CONFIGURATIONS, expected, strict=True):
        assert np.abs(plant.holding_torque_nm(q) - tau).max() < 1e-10


# --- mounting tilt --------------------------------------------------------------------------------


def test_mounting_rotation_is_rx_then_rz_in_the_world_frame() -> None:
    scenario = load_scenario("residual_gravity_tilt")
    ax, az = np.deg2rad(1.5), np.deg2rad(-2.0)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    np.testing.assert_allclose(scenario.mounting_rotation(), rx @ rz, rtol=0, atol=1e-15)
    nominal = DESCRIPTION.kinematics().base_rotation
    np.testing.assert_allclose(
        scenario.true_kinematics(DESCRIPTION).base_rotation, rx @ rz @ nominal, rtol=0, atol=1e-15
    )


@pytest.mark.parametrize("name", ["residual_gravity_tilt", "every_effect"])
def test_a_tilted_base_holds_the_torque_of_gravity_rotated_into_the_nominal_base(name: str) -> None:
    """Rotating the whole chain by R maps every CoM p to R p and every axis z to R z, so

    ``tau_j = (R z_j x R (p - o_j)) . (-m g) = (z_j x (p - o_j)) . (-m R^T g)``:
    the tilted robot under ``g`` holds what the nominal robot holds under ``R^T g``.
    """
    scenario = every_effect() if name == "every_effect" else load_scenario(name)
    tilted = scenario.static_plant(DESCRIPTION)
    gravity = np.array([0.0, -scenario.gravity_mps2, 0.0])
    rotated = StaticPlant(
        DESCRIPTION.kinematics(), tilted.masses, tilted.springs, scenario.mounting_rotation().T @ gravity
    )
    np.testing.assert_allclose(
        tilted.holding_torque_nm(CONFIGURATIONS), rotated.holding_torque_nm(CONFIGURATIONS), rtol=0, atol=1e-12
    )
    level = without(scenario, mounting_tilt_deg=[0.0, 0.0]).static_plant(DESCRIPTION)
    change = tilted.holding_torque_nm(CONFIGURATIONS) - level.holding_torque_nm(CONFIGURATIONS)
    assert np.abs(change).max() > 0.1  # a couple of degrees is visible above the 0.024 Nm noise


def test_with_base_rotation_refuses_what_is_not_a_rotation() -> None:
    kinematics = DESCRIPTION.kinematics()
    with pytest.raises(ShapeError, match="shape"):
        kinematics.with_base_rotation(np.eye(2))
    with pytest.raises(ShapeError, match="rotation"):
        kinematics.with_base_rotation(2.0 * np.eye(3))
    with pytest.raises(ShapeError, match="rotation"):
        kinematics.with_base_rotation(np.diag([1.0, 1.0, -1.0]))  # a reflection
    tilted = kinematics.with_base_rotation(rot_x(0.1) @ kinematics.base_rotation)
    q = CONFIGURATIONS[:3]
    np.testing.assert_allclose(
        tilted.rotor_rotations(q), rot_x(0.1) @ kinematics.rotor_rotations(q), rtol=0, atol=1e-14
    )
    np.testing.assert_array_equal(kinematics.base_rotation, DESCRIPTION.kinematics().base_rotation)  # untouched


# --- joint springs ----------------------------------------------------------------------------------


def test_a_joint_spring_adds_k_times_q_minus_rest_on_its_joint_only() -> None:
    scenario = load_scenario("residual_joint_stiffness")
    spring = scenario.joint_springs[0]
    k, rest = spring.stiffness_nm_per_rad, np.deg2rad(spring.rest_angle_deg)
    assert (spring.joint, k, spring.rest_angle_deg) == (1, 2.0, 10.0)
    bare = without(scenario, joint_springs=[])
    q = CONFIGURATIONS.copy()
    q[:3, 0] = [rest - 0.3, rest, rest + 0.4]  # both sides of the rest angle, and on it
    assert np.any(q[:, 0] < rest)
    assert np.any(q[:, 0] > rest)
    expected = np.zeros_like(q)
    expected[:, 0] = k * (q[:, 0] - rest)
    static = scenario.static_plant(DESCRIPTION).holding_torque_nm(q) - bare.static_plant(DESCRIPTION).holding_torque_nm(
        q
    )
    np.testing.assert_allclose(static, expected, rtol=0, atol=1e-12)
    with_spring, without_spring = DynamicPlant(scenario, DESCRIPTION), DynamicPlant(bare, DESCRIPTION)
    for qi, tau in zip(q, expected, strict=True):
        np.testing.assert_allclose(
            with_spring.holding_torque_nm(qi) - without_spring.holding_torque_nm(qi), tau, rtol=0, atol=1e-12
        )
    # The dynamic plant stores its energy: 1/2 k (q1 - rest)^2 at the start pose.
    q0 = with_spring.q_rad
    extra = (
        with_spring.energy_components_j()["joint_spring_potential"]
        - without_spring.energy_components_j()["joint_spring_potential"]
    )
    assert extra == pytest.approx(0.5 * k * (q0[0] - rest) ** 2, rel=1e-12)


# --- SEA stiffness scale (torque gain) -------------------------------------------------------------


def test_a_stiffer_sea_spring_reads_true_torque_over_scale_in_the_static_data() -> None:
    scenario = load_scenario("residual_torque_gain")
    scale = np.asarray(scenario.sea_stiffness_scale)
    assert scale.tolist() == [1.0, 1.0, 1.12, 1.0]
    points = generate_stationary(scenario, "validation", systematic_only=True)
    np.testing.assert_allclose(points.tau_nm, points.tau_true_nm / scale, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(points.q_rad, points.q_true_rad)
    # Joint 3 carries real torque here, so the gain error is a real error (> 0.1 Nm somewhere).
    assert np.abs(points.tau_nm[:, 2] - points.tau_true_nm[:, 2]).max() > 0.1


def test_a_stiffer_sea_spring_reads_true_torque_over_scale_on_the_sim_hal() -> None:
    scenario = quiet(load_scenario("residual_torque_gain"))
    scale = np.asarray(scenario.sea_stiffness_scale)
    hal = SimHal(scenario, 1000.0, DESCRIPTION)
    np.testing.assert_allclose(hal.plant.stiffness_nm_per_rad, K_NOMINAL * scale, rtol=1e-15)
    hal.open()
    torque = hal.plant.holding_torque_nm(hal.truth().q_rad)
    for _ in range(200):
        hal.write(Command(torque, True))
    truth, sample = hal.truth(), hal.read()
    assert np.abs(truth.dq_rad_s).max() < 1e-9  # at rest: the as-built spring carries the holding torque
    np.testing.assert_allclose(truth.tau_spring_nm, torque, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(sample.tau_nm, truth.tau_spring_nm / scale, rtol=1e-9, atol=1e-9)
    # The drive divides by nothing: it multiplies the deflection by the nominal constant.
    np.testing.assert_allclose(sample.tau_nm, K_NOMINAL * (sample.theta_rad - sample.q_rad), rtol=0, atol=1e-12)


# --- angle offset -----------------------------------------------------------------------------------


def test_an_angle_offset_shifts_q_and_leaves_the_static_torque_untouched() -> None:
    scenario = load_scenario("residual_encoder_offset")
    offset = np.deg2rad(scenario.sensors.angle_offset_deg)
    assert offset[1] == pytest.approx(np.deg2rad(1.5))
    # With noise: the same random stream, so the torque is the same to the bit.
    shifted = generate_stationary(scenario, "validation")
    plain = generate_stationary(without(scenario, angle_offset_deg=[0.0] * N_JOINTS), "validation")
    np.testing.assert_array_equal(shifted.tau_nm, plain.tau_nm)
    np.testing.assert_allclose(shifted.q_rad - plain.q_rad, np.broadcast_to(offset, plain.q_rad.shape), atol=1e-15)
    systematic = generate_stationary(scenario, "validation", systematic_only=True)
    np.testing.assert_allclose(systematic.q_rad, systematic.q_true_rad + offset, rtol=0, atol=1e-15)
    np.testing.assert_allclose(systematic.tau_nm, systematic.tau_true_nm, rtol=0, atol=1e-9)


def test_an_angle_offset_shifts_both_encoders_and_nothing_else_on_the_sim_hal() -> None:
    scenario = load_scenario("residual_encoder_offset")  # with noise and quantisation
    offset = np.deg2rad(scenario.sensors.angle_offset_deg)
    shifted = SimHal(scenario, 1000.0, DESCRIPTION)
    plain = SimHal(without(scenario, angle_offset_deg=[0.0] * N_JOINTS), 1000.0, DESCRIPTION)
    for hal in (shifted, plain):
        hal.open()
    torque = plain.plant.holding_torque_nm(plain.truth().q_rad)
    for tick in range(600):
        command = Command(torque, True) if tick < 300 else Command.torque_off()  # then it falls: q moves
        for hal in (shifted, plain):
            hal.write(command)
        a, b = shifted.read(), plain.read()
        np.testing.assert_allclose(a.q_rad - b.q_rad, offset, rtol=0, atol=1e-15)
        np.testing.assert_allclose(a.theta_rad - b.theta_rad, offset, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(a.tau_nm, b.tau_nm)
        np.testing.assert_array_equal(a.dq_rad_s, b.dq_rad_s)
    np.testing.assert_array_equal(shifted.truth().q_rad, plain.truth().q_rad)  # a measurement error only
    assert np.abs(plain.truth().dq_rad_s).max() > 0.1
    shifted.clear_faults()  # a calibration constant, not a fault
    shifted.write(Command.torque_off())
    plain.write(Command.torque_off())
    np.testing.assert_allclose(shifted.read().q_rad - plain.read().q_rad, offset, rtol=0, atol=1e-15)


# --- torque drift -----------------------------------------------------------------------------------


def test_torque_drift_grows_linearly_with_the_stop_times() -> None:
    scenario = load_scenario("residual_drift")
    rate_nm_per_s = np.asarray(scenario.sensors.torque_drift_nm_per_min) / 60.0
    assert rate_nm_per_s[1] == pytest.approx(0.03 / 60.0)
    points = generate_stationary(scenario, "training", systematic_only=True)
    np.testing.assert_allclose(points.tau_nm - points.tau_true_nm, np.outer(points.t_s, rate_nm_per_s), atol=1e-9)
    assert points.t_s[-1] > 600.0  # over ten minutes of robot time: 0.3 Nm of drift, 12x the noise
    # With noise: a straight-line fit of the error on joint 2 against time recovers the rate.
    noisy = generate_stationary(scenario, "training")
    slope, intercept = np.polyfit(noisy.t_s, noisy.tau_nm[:, 1] - noisy.tau_true_nm[:, 1], 1)
    assert slope == pytest.approx(rate_nm_per_s[1], rel=0.03)
    assert abs(intercept) < 0.01


def test_torque_drift_grows_linearly_with_robot_time_on_the_sim_hal() -> None:
    scenario = quiet(load_scenario("residual_drift"))
    rate_nm_per_s = np.asarray(scenario.sensors.torque_drift_nm_per_min) / 60.0
    hal = SimHal(scenario, 1000.0, DESCRIPTION)
    hal.open()
    first = hal.read()
    assert first.t_s == 0.0
    np.testing.assert_allclose(first.tau_nm, hal.plant.holding_torque_nm(first.q_rad), rtol=0, atol=1e-9)
    torque = hal.plant.holding_torque_nm(hal.truth().q_rad)
    times, drift = [], []
    for _ in range(3000):  # 3 s of robot time, lock-step
        hal.write(Command(torque, True))
        sample, truth = hal.read(), hal.truth()
        times.append(sample.t_s)
        drift.append(sample.tau_nm - K_NOMINAL * (truth.theta_rad - truth.q_rad))
    times_s, drift_nm = np.array(times), np.array(drift)
    assert times_s[-1] == pytest.approx(3.0)
    np.testing.assert_allclose(drift_nm, np.outer(times_s, rate_nm_per_s), rtol=0, atol=1e-12)
    # Restarting the session restarts the clock: the drift is since the session started.
    hal.open()
    np.testing.assert_allclose(hal.read().tau_nm, first.tau_nm, rtol=0, atol=0)


# --- systematic-only readings and the noise floor ------------------------------------------------


def test_systematic_only_keeps_the_direction_error_and_noise_free_drops_it() -> None:
    scenario = load_scenario("residual_direction_offset")
    systematic = generate_stationary(scenario, "validation", systematic_only=True)
    noise_free = generate_stationary(scenario, "validation", noise_free=True)
    error = np.asarray(scenario.sensors.direction_error_nm)
    np.testing.assert_allclose(systematic.tau_nm - noise_free.tau_nm, error * systematic.direction, atol=1e-12)
    np.testing.assert_allclose(noise_free.tau_nm, noise_free.tau_true_nm, atol=1e-9)
    with pytest.raises(InputError, match="one"):
        generate_stationary(scenario, "validation", noise_free=True, systematic_only=True)


def test_noise_free_keeps_the_undeclared_effects() -> None:
    scenario = every_effect()
    points = generate_stationary(scenario, "validation", noise_free=True)
    offset = np.deg2rad(scenario.sensors.angle_offset_deg)
    rate = np.asarray(scenario.sensors.torque_drift_nm_per_min) / 60.0
    scale = np.asarray(scenario.sea_stiffness_scale)
    np.testing.assert_allclose(points.q_rad, points.q_true_rad + offset, rtol=0, atol=1e-15)
    expected = points.tau_true_nm / scale + np.outer(points.t_s, rate)
    np.testing.assert_allclose(points.tau_nm, expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["residual_clean", "residual_direction_offset", "residual_drift"])
def test_the_noise_floor_is_the_encoder_noise_alone(name: str) -> None:
    """``k sqrt(2) sqrt(noise^2 + resolution^2 / 12)``: two encoders, each with white noise and rounding."""
    scenario = load_scenario(name)
    floor = noise_floor_rmse_nm(
        generate_stationary(scenario, "training"), generate_stationary(scenario, "training", systematic_only=True)
    )
    noise, resolution = scenario.sensors.encoder_noise_rad, DESCRIPTION.sea.encoder_resolution_rad
    expected = K_NOMINAL * np.sqrt(2.0) * np.sqrt(noise**2 + resolution**2 / 12.0)
    assert expected == pytest.approx(0.0236, abs=5e-4)
    assert floor == pytest.approx(expected, rel=0.2)


def test_the_noise_floor_refuses_sets_of_different_stops() -> None:
    scenario = load_scenario("residual_clean")
    training = generate_stationary(scenario, "training", systematic_only=True)
    validation = generate_stationary(scenario, "validation")
    with pytest.raises(ShapeError):
        noise_floor_rmse_nm(validation, training)
    stops = scenario_stops(scenario, "validation")
    moved = measure_stops(scenario, stops + 0.01, np.random.default_rng(1), systematic_only=True)
    with pytest.raises(InputError, match="same stops"):
        noise_floor_rmse_nm(validation, moved)


# --- schema -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"sea_stiffness_scale": [1.0, 0.0, 1.0, 1.0]}, "sea_stiffness_scale"),
        ({"sea_stiffness_scale": [1.0, -1.0, 1.0, 1.0]}, "sea_stiffness_scale"),
        ({"sea_stiffness_scale": [1.0, 1.0, 1.0]}, "sea_stiffness_scale"),
        ({"mounting_tilt_deg": [1.0]}, "mounting_tilt_deg"),
        ({"mounting_tilt_deg": [float("nan"), 0.0]}, "mounting_tilt_deg"),
        ({"joint_springs": [{"joint": 5, "stiffness_nm_per_rad": 1.0, "rest_angle_deg": 0.0}]}, "joint_springs"),
        ({"joint_springs": [{"joint": 1, "stiffness_nm_per_rad": 0.0, "rest_angle_deg": 0.0}]}, "joint_springs"),
        ({"sensors": {"angle_offset_deg": [0.0, float("inf"), 0.0, 0.0]}}, "angle_offset_deg"),
        ({"sensors": {"torque_drift_nm_per_min": [0.0, float("nan"), 0.0, 0.0]}}, "torque_drift_nm_per_min"),
    ],
)
def test_unphysical_effects_are_refused(tmp_path: Path, changes: dict[str, object], field: str) -> None:
    import yaml

    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"extends": "exo_dummy_arm", "name": "bad", **changes}), encoding="utf-8")
    with pytest.raises(DescriptionError, match=field) as caught:
        load_scenario(path)
    assert str(path) in str(caught.value)


# --- extends ----------------------------------------------------------------------------------------


def test_deep_merge_merges_mappings_and_replaces_lists_and_scalars() -> None:
    base = {"a": 1, "m": {"x": 1, "y": [1, 2], "n": {"p": 1, "q": 2}}, "l": [1, 2, 3]}
    override = {"m": {"y": [9], "n": {"q": 5}}, "l": [4], "b": 2}
    merged = deep_merge(base, override)
    assert merged == {"a": 1, "m": {"x": 1, "y": [9], "n": {"p": 1, "q": 5}}, "l": [4], "b": 2}
    assert base == {"a": 1, "m": {"x": 1, "y": [1, 2], "n": {"p": 1, "q": 2}}, "l": [1, 2, 3]}  # untouched
    assert deep_merge({"m": {"x": 1}}, {"m": None}) == {"m": None}  # a scalar replaces a mapping


def test_extends_a_shipped_scenario_deep_merges_under_the_file(tmp_path: Path) -> None:
    path = tmp_path / "child.yaml"
    path.write_text(
        "extends: exo_dummy_arm\nname: child\nseed: 7\nsensors:\n  direction_error_nm: [0.0, 0.1, 0.0, 0.0]\n",
        encoding="utf-8",
    )
    child, base = load_scenario(path), load_scenario("exo_dummy_arm")
    assert (child.name, child.seed) == ("child", 7)
    assert child.sensors.direction_error_nm == [0.0, 0.1, 0.0, 0.0]
    assert child.sensors.encoder_noise_rad == base.sensors.encoder_noise_rad  # merged, not replaced
    assert child.sensors.velocity_filter_hz == base.sensors.velocity_filter_hz
    assert child.model_dump(exclude={"name", "seed", "sensors"}) == base.model_dump(exclude={"name", "seed", "sensors"})


def test_extends_a_relative_path_and_a_chain(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "middle.yaml").write_text(
        "extends: exo\nname: middle\nmounting_tilt_deg: [1.0, 0.0]\n", encoding="utf-8"
    )
    (tmp_path / "top.yaml").write_text(
        "extends: sub/middle.yaml\nname: top\nsensors:\n  angle_offset_deg: [0.0, 0.0, 2.0, 0.0]\n", encoding="utf-8"
    )
    top = load_scenario(tmp_path / "top.yaml")
    assert top.name == "top"
    assert top.mounting_tilt_deg == [1.0, 0.0]  # from the middle
    assert top.links == load_scenario("exo").links  # from the shipped root
    assert top.dummy_arm is None
    assert top.sensors.angle_offset_deg == [0.0, 0.0, 2.0, 0.0]


def test_extends_cycles_are_refused_naming_the_file(tmp_path: Path) -> None:
    (tmp_path / "a.yaml").write_text("extends: b.yaml\nname: a\n", encoding="utf-8")
    (tmp_path / "b.yaml").write_text("extends: a.yaml\nname: b\n", encoding="utf-8")
    with pytest.raises(DescriptionError, match="cycle") as caught:
        load_scenario(tmp_path / "a.yaml")
    # Raised where the cycle closes (b.yaml's extends), with the whole chain a -> b -> a.
    assert str(caught.value).startswith(f"{tmp_path / 'b.yaml'}: line 1, field extends: 'a.yaml' forms a cycle")
    assert str(caught.value).endswith(f"{tmp_path / 'a.yaml'} -> {tmp_path / 'b.yaml'} -> {tmp_path / 'a.yaml'}")
    (tmp_path / "self.yaml").write_text("name: self\nextends: self.yaml\n", encoding="utf-8")
    with pytest.raises(DescriptionError, match=r"self\.yaml: line 2, field extends: 'self.yaml' forms a cycle"):
        load_scenario(tmp_path / "self.yaml")


@pytest.mark.parametrize(
    ("extends", "message"),
    [
        ("no_such_scenario", "unknown scenario 'no_such_scenario'"),
        ("missing.yaml", "not found"),
        ("[1, 2]", "expected the name of a shipped scenario"),
    ],
)
def test_a_bad_base_is_refused_naming_the_file(tmp_path: Path, extends: str, message: str) -> None:
    path = tmp_path / "child.yaml"
    path.write_text(f"name: child\nextends: {extends}\n", encoding="utf-8")
    with pytest.raises(DescriptionError, match=message) as caught:
        load_scenario(path)
    assert str(caught.value).startswith(f"{path}: line 2, field extends")


def test_a_problem_in_an_inherited_value_names_both_files(tmp_path: Path) -> None:
    (tmp_path / "base.yaml").write_text("extends: exo\nname: base\ngravity_mps2: -1.0\n", encoding="utf-8")
    (tmp_path / "child.yaml").write_text("extends: base.yaml\nname: child\nseed: -x\n", encoding="utf-8")
    with pytest.raises(DescriptionError) as caught:
        load_scenario(tmp_path / "child.yaml")
    text = str(caught.value)
    assert f"{tmp_path / 'child.yaml'}: line 3, field seed" in text
    assert f"{tmp_path / 'child.yaml'}: inherited from {tmp_path / 'base.yaml'}" in text
    assert "field gravity_mps2" in text
