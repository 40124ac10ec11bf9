"""Stationary datasets of a scenario, generated without running the control loop.

Mirrors the data acquisition of Sec. 4.3.2 at the level of stops: waypoints drawn in the
scenario's workspace are joined by straight joint-space segments cut into sub-waypoints; the
robot stops at each; the whole path runs forward, then in reverse, so every joint arrives at
most configurations from both sides (which is what exposes the direction-dependent torque error
of Sec. 2.2.2). A training set stops at every sub-waypoint; a validation set visits the same
waypoints in another order and keeps one point per waypoint (the thesis's 166 points).

The closed-loop identification protocol on the dynamic plant replaces this generator for
``daror identify``; this one stays as the fast source of static data for model tests.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Literal

import numpy as np

from hal.errors import InputError, ShapeError
from hal.robot import N_JOINTS, FloatArray
from hal.signals import last_motion_sign
from hal.sim.scenario import Scenario, SensorTruth, WorkspaceBox
from hal.sim.sensors import read_encoders

TrajectoryKind = Literal["training", "validation"]

#: Independent random streams of one scenario seed, so changing one never shifts another.
STREAM_WAYPOINTS, STREAM_TRAINING, STREAM_VALIDATION, STREAM_ORDER, STREAM_RAW_LOG = 1, 2, 3, 4, 5


@dataclass(frozen=True)
class StationarySet:
    """Measured stationary points plus the truth behind them (truth is for tests, never written)."""

    t_s: FloatArray
    q_rad: FloatArray
    tau_nm: FloatArray
    direction: FloatArray
    q_true_rad: FloatArray
    tau_true_nm: FloatArray

    def __len__(self) -> int:
        return int(self.q_rad.shape[0])


def stream(seed: int, stream_id: int) -> np.random.Generator:
    """The random generator of one named stream of a scenario seed."""
    return np.random.default_rng([seed, stream_id])


def random_waypoints(workspace: WorkspaceBox, count: int, rng: np.random.Generator) -> FloatArray:
    """``count`` configurations drawn uniformly in the workspace box; (count, 4) rad."""
    return rng.uniform(workspace.lower_rad, workspace.upper_rad, size=(count, N_JOINTS))


def path_through(waypoints: FloatArray, sub_steps: int) -> FloatArray:
    """Stops along straight segments: each waypoint, plus ``sub_steps`` evenly spaced between."""
    if sub_steps < 0:
        raise ValueError("sub_steps must be >= 0")
    stops = [waypoints[:1]]
    fractions = np.linspace(0.0, 1.0, sub_steps + 2)[1:, None]
    for start, end in itertools.pairwise(waypoints):
        stops.append(start + fractions * (end - start))
    return np.concatenate(stops)


def there_and_back(stops: FloatArray) -> FloatArray:
    """The path forward, then in reverse (the turning stop is not repeated)."""
    return np.concatenate([stops, stops[-2::-1]])


def last_motion_signs(stops: FloatArray) -> FloatArray:
    """Sign of each joint's last motion before each stop; 0 until a joint has moved."""
    return np.concatenate([np.zeros((1, stops.shape[1])), last_motion_sign(np.diff(stops, axis=0))])


def stop_times_s(stops: FloatArray, joint_speed_rad_s: float = 0.2, dwell_s: float = 1.0) -> FloatArray:
    """Robot time at each stop: moves at ``joint_speed_rad_s`` on the slowest joint, then a dwell."""
    move_s = np.abs(np.diff(stops, axis=0)).max(axis=1) / joint_speed_rad_s
    return np.concatenate([[dwell_s], dwell_s + np.cumsum(move_s + dwell_s)])


def _sensors_for(scenario: Scenario, noise_free: bool, systematic_only: bool) -> SensorTruth:
    """The scenario's sensors with the parts a caller asked to leave out removed.

    Raises:
        InputError: both ``noise_free`` and ``systematic_only``.
    """
    if noise_free and systematic_only:
        raise InputError("noise_free and systematic_only are different readings; ask for one")
    if noise_free:
        # As before the undeclared effects existed: no noise, no quantisation, no direction
        # error. The angle offset and the torque drift stay: like an as-built mass they are what
        # the robot is, and a model fitted to this "truth" is meant to show them as residual.
        return scenario.sensors.model_copy(
            update={"encoder_noise_rad": 0.0, "quantise": False, "direction_error_nm": [0.0] * N_JOINTS}
        )
    if systematic_only:
        return scenario.sensors.model_copy(update={"encoder_noise_rad": 0.0, "quantise": False})
    return scenario.sensors


def measure_stops(
    scenario: Scenario,
    stops: FloatArray,
    rng: np.random.Generator,
    samples_per_stop: int = 1,
    noise_free: bool = False,
    systematic_only: bool = False,
) -> StationarySet:
    """Hold still at each stop and read the sensors ``samples_per_stop`` times.

    The plant is the scenario's as-built truth, undeclared effects included (mounting tilt,
    joint springs, SEA stiffness scale; angle offset and torque drift in the sensors). Sample
    ``n`` of a stop is taken ``n`` ms after the robot arrived, at the robot time
    :func:`stop_times_s` gives; the torque drift grows with that time.

    Args:
        scenario: the as-built truth.
        stops: (K, 4) rad, in the order the robot visits them.
        rng: random generator of the encoder noise (not drawn from without noise).
        samples_per_stop: readings per stop.
        noise_free: no encoder noise, no quantisation and no direction-dependent error; the
            undeclared effects (offset, drift, gain, tilt, springs) stay, they are physics.
        systematic_only: no encoder noise and no quantisation, but every systematic effect,
            the direction-dependent error included: what the sensors read without their noise.
            Measured minus this is pure sensor noise (:func:`noise_floor_rmse_nm`).

    Raises:
        InputError: both ``noise_free`` and ``systematic_only``.
    """
    sensors = _sensors_for(scenario, noise_free, systematic_only)
    description = scenario.description()
    plant = scenario.static_plant(description)
    direction = last_motion_signs(stops)
    times = stop_times_s(stops)
    q_true = np.repeat(stops, samples_per_stop, axis=0)
    direction = np.repeat(direction, samples_per_stop, axis=0)
    t = np.repeat(times, samples_per_stop) + np.tile(np.arange(samples_per_stop) * 1e-3, len(stops))
    tau_true = plant.holding_torque_nm(q_true)
    readings = read_encoders(
        q_true,
        tau_true,
        direction,
        sensors,
        description.sea,
        rng,
        stiffness_nm_per_rad=scenario.stiffness_nm_per_rad(description),
        t_s=t,
    )
    return StationarySet(t, readings.q_rad, readings.torque_nm, direction, q_true, tau_true)


def noise_floor_rmse_nm(measured: StationarySet, systematic: StationarySet) -> float:
    """RMSE (Nm) of ``measured`` torque minus the ``systematic_only`` torque at the same stops.

    What is left is the encoder noise and quantisation alone: no model of the robot, however
    complete, can predict it, so this is the lowest RMSE a model can reach on ``measured``
    (about ``k sqrt(2) sqrt(noise^2 + resolution^2 / 12)`` = 0.024 Nm for the DAROR-01).
    Over every joint and point, like the evaluation's overall RMSE.

    Args:
        measured: a set as measured (noise and quantisation on).
        systematic: the same stops measured with ``systematic_only=True``.

    Raises:
        ShapeError: the two sets are not of the same size.
        InputError: they were not taken at the same true configurations and times.
    """
    if measured.tau_nm.shape != systematic.tau_nm.shape:
        raise ShapeError(
            f"measured {measured.tau_nm.shape} and systematic {systematic.tau_nm.shape} sets differ in size"
        )
    if not (
        np.array_equal(measured.q_true_rad, systematic.q_true_rad) and np.array_equal(measured.t_s, systematic.t_s)
    ):
        raise InputError("measured and systematic sets were not taken at the same stops and times")
    return float(np.sqrt(np.mean((measured.tau_nm - systematic.tau_nm) ** 2)))


def scenario_stops(
    scenario: Scenario, trajectory: TrajectoryKind, n_waypoints: int = 83, sub_steps: int = 7
) -> FloatArray:
    """Stops of the training or validation trajectory of a scenario (deterministic in its seed).

    Both visit the same ``n_waypoints`` waypoints, in different orders, forward then reverse.
    Training stops at ``sub_steps`` sub-waypoints per segment too; validation only at waypoints.
    The defaults give the thesis's sizes: about 1,300 training and 165 validation points.
    """
    waypoints = random_waypoints(scenario.workspace, n_waypoints, stream(scenario.seed, STREAM_WAYPOINTS))
    if trajectory == "training":
        return there_and_back(path_through(waypoints, sub_steps))
    order = stream(scenario.seed, STREAM_ORDER).permutation(n_waypoints)
    return there_and_back(waypoints[order])


def generate_stationary(
    scenario: Scenario,
    trajectory: TrajectoryKind,
    n_waypoints: int = 83,
    sub_steps: int = 7,
    samples_per_stop: int = 1,
    noise_free: bool = False,
    systematic_only: bool = False,
) -> StationarySet:
    """A stationary dataset of ``scenario`` along its training or validation trajectory.

    ``noise_free`` and ``systematic_only`` as in :func:`measure_stops`; the stops and times are
    the same whichever is chosen, so sets of one scenario and trajectory compare point by point.

    Raises:
        InputError: both ``noise_free`` and ``systematic_only``.
    """
    stops = scenario_stops(scenario, trajectory, n_waypoints, sub_steps)
    stream_id = STREAM_TRAINING if trajectory == "training" else STREAM_VALIDATION
    return measure_stops(
        scenario, stops, stream(scenario.seed, stream_id), samples_per_stop, noise_free, systematic_only
    )
