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


def measure_stops(
    scenario: Scenario,
    stops: FloatArray,
    rng: np.random.Generator,
    samples_per_stop: int = 1,
    noise_free: bool = False,
) -> StationarySet:
    """Hold still at each stop and read the sensors ``samples_per_stop`` times."""
    description = scenario.description()
    plant = scenario.static_plant(description)
    direction = last_motion_signs(stops)
    times = stop_times_s(stops)
    q_true = np.repeat(stops, samples_per_stop, axis=0)
    direction = np.repeat(direction, samples_per_stop, axis=0)
    t = np.repeat(times, samples_per_stop) + np.tile(np.arange(samples_per_stop) * 1e-3, len(stops))
    tau_true = plant.holding_torque_nm(q_true)
    sensors = SensorTruth(encoder_noise_rad=0.0, quantise=False) if noise_free else scenario.sensors
    readings = read_encoders(q_true, tau_true, direction, sensors, description.sea, rng)
    return StationarySet(t, readings.q_rad, readings.torque_nm, direction, q_true, tau_true)


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
) -> StationarySet:
    """A stationary dataset of ``scenario`` along its training or validation trajectory."""
    stops = scenario_stops(scenario, trajectory, n_waypoints, sub_steps)
    stream_id = STREAM_TRAINING if trajectory == "training" else STREAM_VALIDATION
    return measure_stops(scenario, stops, stream(scenario.seed, stream_id), samples_per_stop, noise_free)
