"""A training or validation file that is itself a raw log is its own path (the hysteresis's history).

``load_pair`` reduces a raw log to its stationary points; the joints' path to those points is then
that raw log's samples (``PointHistory.from_raw``), not the points in order. A raw log named
explicitly (``raw_paths``, ``--raw``) still wins, and the file is read once.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import daror_runtime.residual.data as residual_data
from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import RawLog
from daror_runtime.errors import DataError
from daror_runtime.models.penn_residual import PennResidualModel
from daror_runtime.residual.data import load_pair, prediction_signal, read_residual_file
from daror_runtime.residual.hysteresis import PointHistory
from daror_runtime.residual.model import AugmentedModel
from hal.robot import load_description
from hal.sim.quasi_static import QuasiStaticSettings, quasi_static_log
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import STREAM_RAW_LOG, generate_stationary, scenario_stops, stream
from tests.conftest import as_dataset

TRAVEL_RAD = np.array([0.005, 0.01, 0.02, 0.005])


def _raw_log(trajectory: str, seed_offset: int = 0) -> RawLog:
    """A quasi-static run of the direction-offset scenario (moves and dwells at 100 Hz, ~2 minutes)."""
    scenario = load_scenario("residual_direction_offset")
    stops = scenario_stops(scenario, trajectory, n_waypoints=30, sub_steps=3)  # type: ignore[arg-type]
    log = quasi_static_log(scenario, stops, stream(scenario.seed + seed_offset, STREAM_RAW_LOG), QuasiStaticSettings())
    return RawLog(log.t_s, log.q_rad, log.dq_rad_s, log.tau_nm, source="memory")


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Raw logs of a training and a validation run, and a stationary validation file."""
    folder = tmp_path_factory.mktemp("raw_as_data")
    paths = {
        "train_raw": folder / "train_log.npz",
        "validate_raw": folder / "validate_log.csv",
        "validate": folder / "validate.csv",
    }
    write_dataset(paths["train_raw"], _raw_log("training"))
    write_dataset(paths["validate_raw"], _raw_log("validation"))
    scenario = load_scenario("residual_direction_offset")
    write_dataset(paths["validate"], as_dataset(generate_stationary(scenario, "validation")))
    return paths


def test_the_reduced_points_keep_their_times_and_the_raw_log_comes_back(files: dict[str, Path]) -> None:
    points, raw = read_residual_file(files["train_raw"])
    assert isinstance(raw, RawLog)
    assert raw.source == str(files["train_raw"])
    assert points.t_s is not None
    assert len(points) > 20
    assert np.all((points.t_s >= raw.t_s[0]) & (points.t_s <= raw.t_s[-1]))
    stationary, none = read_residual_file(files["validate"])
    assert none is None
    assert len(stationary) == 165


def test_a_raw_log_given_as_training_data_is_its_own_path(files: dict[str, Path]) -> None:
    pair = load_pair(files["train_raw"], files["validate"])
    history = pair.train_history
    assert history is not None
    assert history.from_raw_log
    assert history.source == str(files["train_raw"])
    _, raw = read_residual_file(files["train_raw"])
    assert raw is not None
    assert len(history.path_q_rad) == len(raw) > len(pair.train)  # every sample, the moves included
    assert np.all(raw.t_s[history.point_index] <= pair.train.t_s)  # each point's sample, at or before its time
    assert history.half_window > 0
    # the stationary validation file has no raw log beside it: its points in order
    assert pair.validate_history is not None
    assert not pair.validate_history.from_raw_log


def test_its_states_equal_those_of_the_same_raw_log_given_explicitly(files: dict[str, Path]) -> None:
    own = load_pair(files["train_raw"], files["validate"])
    given = load_pair(files["train_raw"], files["validate"], raw_paths=(files["train_raw"], None))
    assert own.train_history is not None
    assert given.train_history is not None
    assert given.train_history.source == own.train_history.source
    np.testing.assert_array_equal(own.train_history.states(TRAVEL_RAD), given.train_history.states(TRAVEL_RAD))
    # and both are the raw log's own history of the reduced points
    points, raw = read_residual_file(files["train_raw"])
    assert raw is not None
    direct = PointHistory.from_raw(raw, points).states(TRAVEL_RAD)
    np.testing.assert_array_equal(own.train_history.states(TRAVEL_RAD), direct)


def test_a_raw_log_given_as_validation_data_is_its_own_path(files: dict[str, Path]) -> None:
    pair = load_pair(files["train_raw"], files["validate_raw"])
    assert pair.validate_history is not None
    assert pair.validate_history.from_raw_log
    assert pair.validate_history.source == str(files["validate_raw"])
    assert pair.train_history is not None
    assert pair.train_history.source == str(files["train_raw"])


def test_an_explicit_raw_log_still_wins(files: dict[str, Path], tmp_path: Path) -> None:
    # another run's log (one second, standing still): named explicitly, it is used, and refused
    t = np.arange(0.0, 1.0, 0.01)
    q = np.zeros((len(t), 4))
    other = tmp_path / "other.raw.npz"
    write_dataset(other, RawLog(t, q, np.zeros_like(q), np.zeros_like(q)))
    with pytest.raises(DataError, match=rf"^{other}: the point at t = .* outside this raw log"):
        load_pair(files["train_raw"], files["validate"], raw_paths=(other, None))


def test_its_own_samples_win_over_a_raw_log_beside_it(files: dict[str, Path], tmp_path: Path) -> None:
    # a data file that is a raw log, with a NAME.raw.* beside it that is not this run's:
    # the file's own samples are the path (the one beside it is not even read)
    train = tmp_path / "train.npz"
    train.write_bytes(files["train_raw"].read_bytes())
    t = np.arange(0.0, 1.0, 0.01)
    q = np.zeros((len(t), 4))
    write_dataset(tmp_path / "train.raw.npz", RawLog(t, q, np.zeros_like(q), np.zeros_like(q)))
    pair = load_pair(train, files["validate"])
    assert pair.train_history is not None
    assert pair.train_history.source == str(train)


def test_each_file_is_read_once(files: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    read: list[str] = []
    real = residual_data.read_table

    def counting(path: Path | str) -> object:
        read.append(str(path))
        return real(path)

    monkeypatch.setattr(residual_data, "read_table", counting)
    pair = load_pair(files["train_raw"], files["validate_raw"])
    assert pair.train_history is not None
    assert pair.train_history.from_raw_log
    assert sorted(read) == sorted([str(files["train_raw"]), str(files["validate_raw"])])


def _with_hysteresis(travel_rad: list[float] | None) -> AugmentedModel:
    parameters: dict[str, object] = {"base_kind": "plf+", "theta": [0.0] * 12, "hysteresis_nm": [0.0, 0.5, 0.0, 0.0]}
    if travel_rad is not None:
        parameters["hysteresis_travel_rad"] = travel_rad
    return AugmentedModel.from_parameters(load_description(), parameters)


def test_a_model_is_judged_with_the_signal_its_reading_needs(files: dict[str, Path], tmp_path: Path) -> None:
    """A sign model predicts with ``dir``; a hysteresis model with its state along the run's raw log
    beside the file (else the points in order); a PENN residual on it with its base's."""
    points, raw = read_residual_file(files["train_raw"])
    assert raw is not None
    stationary = tmp_path / "run.csv"
    write_dataset(stationary, points)
    sign_model = _with_hysteresis(None)
    assert sign_model.path_travel_rad() is None
    assert prediction_signal(sign_model, points, stationary) is points.direction
    model = _with_hysteresis([0.005] * 4)
    in_order = prediction_signal(model, points, stationary)  # no raw log beside it yet
    assert in_order == pytest.approx(PointHistory.from_points(points).states(0.005))
    write_dataset(tmp_path / "run.raw.npz", raw)
    along_the_log = prediction_signal(model, points, stationary)
    assert along_the_log == pytest.approx(PointHistory.from_raw(raw, points).states(0.005))
    assert not np.allclose(along_the_log, in_order)  # the log sees the settling the points do not
    assert np.all(np.abs(along_the_log) <= 1.0)
    learned = object.__new__(PennResidualModel)  # the delegation alone: no network needed
    learned.base = model
    assert learned.path_travel_rad() == pytest.approx([0.005] * 4)
    assert learned.reading_error_tracker() is not None
