"""From a raw log to stationary points (``daror_runtime.data.stationary``, thesis Sec. 4.3.2).

The raw logs come from ``hal.sim.quasi_static``: minimum-jerk moves between stops, a dwell at
each stop, and a truth array ``moving`` telling which samples belong to a move. Kept samples are
mapped back to the log through their time ``t`` (the reducer keeps ``t`` exactly).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from daror_runtime.data.load import load_dataset, load_stationary, write_dataset
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.stationary import ReductionSettings, reduce_to_stationary
from daror_runtime.errors import DataError
from daror_runtime.models.linear import fit_plf_plus
from daror_runtime.models.metrics import error_metrics
from hal.robot import RobotDescription
from hal.sim.quasi_static import QuasiStaticLog, QuasiStaticSettings, quasi_static_log
from hal.sim.scenario import Scenario
from hal.sim.static_dataset import (
    generate_stationary,
    last_motion_signs,
    path_through,
    random_waypoints,
    scenario_stops,
)
from tests.conftest import as_dataset

#: Hand-picked stops (rad). Every move turns its leading joint by at least 0.5 rad; joint 3 never
#: moves; joint 4 first moves into stop 3. Each joint moves both ways.
STOPS = np.array(
    [
        [0.0, 0.3, 0.2, 1.0],
        [0.5, 0.3, 0.2, 1.0],  # j1 +
        [0.5, 0.8, 0.2, 1.0],  # j2 +
        [0.0, 0.4, 0.2, 1.5],  # j1 -, j2 -, j4 +
        [0.0, 0.4, 0.2, 0.9],  # j4 -
        [0.6, 0.4, 0.2, 0.9],  # j1 +
        [0.6, 0.9, 0.2, 1.4],  # j2 +, j4 +
        [-0.1, 0.9, 0.2, 1.4],  # j1 -
    ]
)
#: Sign of each joint's last motion into each stop, worked out by hand from STOPS.
EXPECTED_DIR = np.array(
    [
        [0, 0, 0, 0],
        [1, 0, 0, 0],
        [1, 1, 0, 0],
        [-1, -1, 0, 1],
        [-1, -1, 0, -1],
        [1, -1, 0, -1],
        [1, 1, 0, 1],
        [-1, 1, 0, 1],
    ],
    dtype=float,
)


def as_raw(log: QuasiStaticLog, source: str = "<quasi-static>") -> RawLog:
    return RawLog(log.t_s, log.q_rad, log.dq_rad_s, log.tau_nm, log.theta_rad, source=source)


def kept_indices(log: QuasiStaticLog, reduced: StationaryDataset) -> np.ndarray:
    """Indices into the log of the samples the reducer kept, found by their time."""
    index = np.searchsorted(log.t_s, reduced.t_s)
    assert np.all(index < len(log.t_s))
    assert np.array_equal(log.t_s[index], reduced.t_s), "kept times are not times of the log"
    assert np.all(np.diff(index) > 0), "kept samples are not in log order or repeat"
    return index


def runs(index: np.ndarray) -> list[np.ndarray]:
    """Runs of consecutive log indices."""
    return np.split(index, np.flatnonzero(np.diff(index) > 1) + 1)


def dwell_number(log: QuasiStaticLog) -> np.ndarray:
    """For every sample, the number of the dwell it is in or last left (0 for the first stop)."""
    dwell_starts = np.flatnonzero(np.diff(log.moving.astype(np.int8)) == -1) + 1
    return np.searchsorted(dwell_starts, np.arange(len(log.t_s)), side="right")


@pytest.fixture(scope="module")
def stop_log(exo_dummy_arm: Scenario) -> QuasiStaticLog:
    return quasi_static_log(exo_dummy_arm, STOPS, np.random.default_rng(20261121))


@pytest.fixture(scope="module")
def reduced(stop_log: QuasiStaticLog) -> StationaryDataset:
    return reduce_to_stationary(as_raw(stop_log))


def test_simulated_log_has_what_the_tests_rely_on(stop_log: QuasiStaticLog) -> None:
    assert np.all(np.diff(stop_log.t_s) > 0)
    assert stop_log.q_rad.shape == stop_log.dq_rad_s.shape == stop_log.tau_nm.shape == (len(stop_log.t_s), 4)
    assert not stop_log.moving[0]
    assert not stop_log.moving[-1]
    assert dwell_number(stop_log)[-1] == len(STOPS) - 1
    dwell_lengths = np.bincount(dwell_number(stop_log)[~stop_log.moving])
    assert dwell_lengths.tolist() == [150] * len(STOPS)  # 1.5 s at 100 Hz


def test_reduced_set_keeps_t_and_dir_and_the_samples_values(
    stop_log: QuasiStaticLog, reduced: StationaryDataset
) -> None:
    index = kept_indices(stop_log, reduced)
    assert reduced.direction is not None
    assert reduced.source == "<quasi-static>"
    assert np.array_equal(reduced.q_rad, stop_log.q_rad[index])
    assert np.array_equal(reduced.tau_nm, stop_log.tau_nm[index])
    assert set(np.unique(reduced.direction)) <= {-1.0, 0.0, 1.0}
    # most of every dwell survives: 150 samples per stop, minus the filter's smear at its edges
    per_dwell = np.bincount(dwell_number(stop_log)[index], minlength=len(STOPS))
    assert per_dwell.min() >= 110, per_dwell


def test_every_kept_sample_is_a_dwell_sample(stop_log: QuasiStaticLog, reduced: StationaryDataset) -> None:
    index = kept_indices(stop_log, reduced)
    moving_kept = index[stop_log.moving[index]]
    assert moving_kept.size == 0, f"{moving_kept.size} kept samples are moving: {moving_kept[:10]}"


def test_one_run_of_kept_samples_per_stop(stop_log: QuasiStaticLog, reduced: StationaryDataset) -> None:
    index = kept_indices(stop_log, reduced)
    found = runs(index)
    assert len(found) == len(STOPS)
    # run k lies (almost entirely) in dwell k: the first stop is a stop too
    dwell = dwell_number(stop_log)
    for k, run in enumerate(found):
        assert np.bincount(dwell[run]).argmax() == k


def test_dir_is_the_sign_of_each_joints_last_motion_into_the_stop(
    stop_log: QuasiStaticLog, reduced: StationaryDataset
) -> None:
    index = kept_indices(stop_log, reduced)
    start = 0
    for k, run in enumerate(runs(index)):
        direction = reduced.direction[start : start + run.size]
        start += run.size
        assert np.all(direction == EXPECTED_DIR[k]), f"stop {k}: {np.unique(direction, axis=0)} != {EXPECTED_DIR[k]}"


def test_per_stop_mean_gives_one_point_per_stop(stop_log: QuasiStaticLog) -> None:
    mean = reduce_to_stationary(as_raw(stop_log), ReductionSettings(per_stop="mean"))
    assert len(mean) == len(STOPS)
    assert np.abs(mean.q_rad - STOPS).max() < 2e-4
    assert np.array_equal(mean.direction, EXPECTED_DIR)
    # time of each point: the middle of its dwell
    dwell = dwell_number(stop_log)
    for k in range(len(STOPS)):
        t_dwell = stop_log.t_s[(dwell == k) & ~stop_log.moving]
        assert t_dwell[0] < mean.t_s[k] < t_dwell[-1]
    assert np.all(np.diff(mean.t_s) > 0)


def test_per_stop_mean_averages_the_kept_samples(stop_log: QuasiStaticLog, reduced: StationaryDataset) -> None:
    mean = reduce_to_stationary(as_raw(stop_log), ReductionSettings(per_stop="mean"))
    index = kept_indices(stop_log, reduced)
    start = 0
    for k, run in enumerate(runs(index)):
        block = slice(start, start + run.size)
        start += run.size
        np.testing.assert_allclose(mean.q_rad[k], reduced.q_rad[block].mean(axis=0), rtol=0, atol=1e-15)
        np.testing.assert_allclose(mean.tau_nm[k], reduced.tau_nm[block].mean(axis=0), rtol=0, atol=1e-12)


def test_min_stop_samples_drops_short_stops(stop_log: QuasiStaticLog) -> None:
    raw = as_raw(stop_log)
    everything = reduce_to_stationary(raw)
    assert len(reduce_to_stationary(raw, ReductionSettings(min_stop_samples=100))) == len(everything)
    with pytest.raises(DataError, match="no stationary samples"):
        reduce_to_stationary(raw, ReductionSettings(min_stop_samples=400))


@pytest.mark.parametrize("waypoint_seed", range(12))
def test_random_paths_give_every_stop_and_its_dir(exo_dummy_arm: Scenario, waypoint_seed: int) -> None:
    """Stops from path_through on random waypoints, small and large moves alike."""
    stops = path_through(random_waypoints(exo_dummy_arm.workspace, 4, np.random.default_rng(waypoint_seed)), 1)
    log = quasi_static_log(exo_dummy_arm, stops, np.random.default_rng(100 + waypoint_seed))
    mean = reduce_to_stationary(as_raw(log), ReductionSettings(per_stop="mean"))
    assert len(mean) == len(stops)
    assert np.abs(mean.q_rad - stops).max() < 2e-4
    assert np.array_equal(mean.direction, last_motion_signs(stops))


def test_noise_at_the_start_of_the_log_is_no_motion(exo_dummy_arm: Scenario) -> None:
    """Regression: the filter's ends are filtered too, so encoder noise in the first sample neither
    reads as a motion before the first stop (dir must stay 0) nor drops the first samples."""
    stops = STOPS[:2]
    for seed in range(40):
        log = quasi_static_log(exo_dummy_arm, stops, np.random.default_rng(seed))
        reduced = reduce_to_stationary(as_raw(log))
        assert reduced.t_s[0] == log.t_s[0], f"seed {seed}: the first sample was dropped"
        first_stop = reduced.t_s < log.t_s[np.argmax(log.moving)]
        assert first_stop.sum() >= 140, f"seed {seed}"
        assert np.all(reduced.direction[first_stop] == 0), (
            f"seed {seed}: {np.unique(reduced.direction[first_stop], axis=0)}"
        )


def test_a_short_move_does_not_split_the_dwells_beside_it(exo_dummy_arm: Scenario) -> None:
    stops = np.array([[0.0, 0.3, 0.2, 1.0], [0.25, 0.3, 0.2, 1.0], [0.25, 0.3, 0.2, 1.5]])
    log = quasi_static_log(exo_dummy_arm, stops, np.random.default_rng(5))
    mean = reduce_to_stationary(as_raw(log), ReductionSettings(per_stop="mean"))
    assert len(mean) == len(stops)


def test_dir_of_a_joint_that_moves_a_little(exo_dummy_arm: Scenario) -> None:
    stops = np.array([[0.0, 0.3, 0.2, 1.0], [0.5, 0.3, 0.2, 1.0], [0.49, 0.3, 0.2, 1.5]])
    log = quasi_static_log(exo_dummy_arm, stops, np.random.default_rng(6))
    mean = reduce_to_stationary(as_raw(log), ReductionSettings(per_stop="mean"))
    assert len(mean) == 3
    assert mean.direction[2].tolist() == [-1.0, 0.0, 0.0, 1.0]


# --- the reduction matters for a fit ---------------------------------------------------------


def test_reduced_log_fits_plf_plus_better_than_all_samples(
    exo_dummy_arm: Scenario, description: RobotDescription
) -> None:
    stops = scenario_stops(exo_dummy_arm, "training", n_waypoints=20, sub_steps=3)
    log = quasi_static_log(exo_dummy_arm, stops, np.random.default_rng(3))
    raw = as_raw(log, "B-raw")
    assert log.moving.mean() > 0.3  # a third of the log or more is moving: keeping it should hurt
    validation = as_dataset(generate_stationary(exo_dummy_arm, "validation"), "B-validation")

    def validation_rmse(train: StationaryDataset) -> float:
        model = fit_plf_plus(train, description).model
        return error_metrics(validation.tau_nm, model.torque_batch(validation.q_rad)).rmse_nm

    reduced = reduce_to_stationary(raw)
    every_sample = StationaryDataset(raw.q_rad, raw.tau_nm, source="B-raw (all samples)")
    true_dwells = StationaryDataset(raw.q_rad[~log.moving], raw.tau_nm[~log.moving], source="B-raw (dwells)")
    rmse_reduced = validation_rmse(reduced)
    rmse_all = validation_rmse(every_sample)
    rmse_truth = validation_rmse(true_dwells)
    assert rmse_reduced < rmse_all
    assert rmse_all > 1.01 * rmse_reduced  # not a rounding-level difference
    assert rmse_reduced < 1.01 * rmse_truth  # as good as knowing which samples were still


# --- errors ------------------------------------------------------------------------------------


def _ramp_log(n: int, rate_hz: float = 100.0, speed: float = 0.1) -> RawLog:
    t = np.arange(n) / rate_hz
    q = np.zeros((n, 4))
    q[:, 0] = speed * t
    dq = np.zeros((n, 4))
    dq[:, 0] = speed
    return RawLog(t, q, dq, np.ones((n, 4)), source="ramp.csv")


def test_constant_velocity_has_no_stationary_sample() -> None:
    with pytest.raises(DataError, match="no stationary") as caught:
        reduce_to_stationary(_ramp_log(500))
    assert str(caught.value).startswith("ramp.csv: ")


@pytest.mark.parametrize("cutoff_hz", [50.0, 60.0, 0.0, -1.0])
def test_cutoff_must_be_below_nyquist_and_positive(cutoff_hz: float) -> None:
    with pytest.raises(DataError, match=r"ramp\.csv: low-pass cut-off .* below half the sample rate \(100 Hz\)"):
        reduce_to_stationary(_ramp_log(500, speed=0.0), ReductionSettings(cutoff_hz=cutoff_hz))


def test_cutoff_just_below_nyquist_is_accepted() -> None:
    reduced = reduce_to_stationary(_ramp_log(500, speed=0.0), ReductionSettings(cutoff_hz=49.0))
    assert len(reduced) == 500


def test_too_few_samples_to_filter() -> None:
    with pytest.raises(DataError, match="9 samples are too few to filter; expected more than 9"):
        reduce_to_stationary(_ramp_log(9, speed=0.0))
    assert len(reduce_to_stationary(_ramp_log(10, speed=0.0))) == 10


def test_a_single_sample_cannot_be_reduced() -> None:
    with pytest.raises(DataError, match="at least two samples"):
        reduce_to_stationary(_ramp_log(1, speed=0.0))


# --- load_stationary ---------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".csv", ".npz", ".mat"])
def test_load_stationary_reduces_a_raw_log_file(tmp_path: Path, stop_log: QuasiStaticLog, suffix: str) -> None:
    raw = as_raw(stop_log)
    path = tmp_path / f"run.raw{suffix}"
    write_dataset(path, raw)
    assert isinstance(load_dataset(path), RawLog)
    loaded = load_stationary(path)
    expected = reduce_to_stationary(raw)
    assert isinstance(loaded, StationaryDataset)
    assert loaded.source == str(path)
    assert loaded.direction is not None
    assert loaded.t_s is not None
    assert np.array_equal(loaded.q_rad, expected.q_rad)
    assert np.array_equal(loaded.tau_nm, expected.tau_nm)
    assert np.array_equal(loaded.direction, expected.direction)
    assert np.array_equal(loaded.t_s, expected.t_s)
    mean = load_stationary(path, ReductionSettings(per_stop="mean"))
    assert len(mean) == len(STOPS)


def test_load_stationary_of_a_raw_log_without_stops_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "moving.raw.csv"
    write_dataset(path, _ramp_log(300))
    with pytest.raises(DataError, match="no stationary") as caught:
        load_stationary(path)
    assert str(caught.value).startswith(f"{path}: ")


def test_load_stationary_returns_a_stationary_file_unchanged(tmp_path: Path, exo_dummy_arm: Scenario) -> None:
    points = as_dataset(generate_stationary(exo_dummy_arm, "validation", n_waypoints=10))
    path = tmp_path / "val.csv"
    write_dataset(path, points)
    loaded = load_stationary(path)
    assert isinstance(loaded, StationaryDataset)
    for name in ("q_rad", "tau_nm", "direction", "t_s"):
        assert np.array_equal(getattr(loaded, name), getattr(points, name)), name
    assert len(loaded) == len(points) == 19  # 10 waypoints there and back, the turn not repeated


def test_quasi_static_settings_rate_changes_nothing_of_the_stops(exo_dummy_arm: Scenario) -> None:
    """The reducer works off the log's own sample rate: a 200 Hz log gives the same stops."""
    log = quasi_static_log(exo_dummy_arm, STOPS, np.random.default_rng(9), QuasiStaticSettings(rate_hz=200.0))
    mean = reduce_to_stationary(as_raw(log), ReductionSettings(per_stop="mean"))
    assert len(mean) == len(STOPS)
    assert np.abs(mean.q_rad - STOPS).max() < 2e-4
    assert np.array_equal(mean.direction, EXPECTED_DIR)


def test_points_per_stop_splits_each_stop_into_averaged_parts(stop_log: QuasiStaticLog) -> None:
    one = reduce_to_stationary(as_raw(stop_log), ReductionSettings(per_stop="mean"))
    three = reduce_to_stationary(as_raw(stop_log), ReductionSettings(per_stop="mean", points_per_stop=3))
    assert len(three) == 3 * len(one)
    # the parts of a stop share its direction, follow each other in time and average to the stop's mean
    assert np.array_equal(three.direction[::3], one.direction)
    assert np.all(np.diff(three.t_s) > 0)
    assert three.q_rad.reshape(-1, 3, 4).mean(axis=1) == pytest.approx(one.q_rad, abs=2e-5)
    with pytest.raises(DataError, match="points_per_stop must be at least 1"):
        reduce_to_stationary(as_raw(stop_log), ReductionSettings(per_stop="mean", points_per_stop=0))
