"""Issue 24, defect 7 and the labels of defect 9: ``daror evaluate`` says where a model extrapolates, and tells
two files of one name apart.

A model file records the range of joint angles it was trained on; a point with any joint more than
``TOLERANCE_RAD`` beyond it is outside. The figures per model: the points outside, the RMSE inside
and outside (Eq. 4.31 over those points), in the table and in ``--json``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.cli import main
from daror_runtime.data.load import load_stationary, write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.compare import distinct_labels, evaluate_models
from daror_runtime.models.extrapolation import TOLERANCE_RAD, extrapolation, model_extrapolation, outside_range
from daror_runtime.models.files import TrainingSummary, load_model, save_model, training_summary
from daror_runtime.models.linear import build_ap, fit_plf_plus
from hal.robot import RobotDescription


def _summary(low: list[float], high: list[float]) -> TrainingSummary:
    return TrainingSummary(source="x", n_points=2, has_direction=False, q_min_rad=low, q_max_rad=high)


def test_points_beyond_the_tolerance_are_outside_and_each_side_has_its_rmse() -> None:
    training = _summary([0.0, -1.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0])
    q = np.array(
        [
            [0.5, 0.0, 0.5, 0.5],  # inside
            [1.0 + 0.9 * TOLERANCE_RAD, 0.0, 0.5, 0.5],  # within the tolerance: inside
            [1.0 + 1.1 * TOLERANCE_RAD, 0.0, 0.5, 0.5],  # joint 1 just beyond its maximum
            [0.5, -1.5, 0.5, 2.0],  # joints 2 and 4 outside: one point
        ]
    )
    measured = np.zeros((4, 4))
    model = np.array([[1.0, 0, 0, 0], [1.0, 1.0, 0, 0], [2.0, 0, 0, 0], [0, 0, 0, 4.0]])
    x = extrapolation(training, q, measured, model)
    assert x is not None
    assert (x.n_points, x.n_outside, x.n_inside) == (4, 2, 2)
    assert x.outside_per_joint == (1, 1, 0, 1)
    assert x.rmse_inside_nm == pytest.approx(np.sqrt((1 + 1 + 1) / 8))
    assert x.rmse_outside_nm == pytest.approx(np.sqrt((4 + 16) / 8))
    assert x.to_dict()["outside"] == 2
    assert outside_range(q, training.q_min_rad, training.q_max_rad).sum() == 3


def test_an_empty_side_has_no_rmse_and_a_model_without_a_range_has_no_figures() -> None:
    training = _summary([-1.0] * 4, [1.0] * 4)
    q = np.zeros((3, 4))
    x = extrapolation(training, q, np.ones((3, 4)), np.zeros((3, 4)))
    assert x is not None
    assert (x.n_outside, x.rmse_inside_nm, x.rmse_outside_nm) == (0, 1.0, None)
    far = extrapolation(training, q + 2.0, np.ones((3, 4)), np.zeros((3, 4)))
    assert far is not None
    assert (far.n_outside, far.rmse_inside_nm, far.rmse_outside_nm) == (3, None, 1.0)
    assert extrapolation(None, q, np.ones((3, 4)), np.zeros((3, 4))) is None


@pytest.fixture(scope="module")
def narrow(
    tmp_path_factory: pytest.TempPathFactory,
    dataset_b: tuple[StationaryDataset, StationaryDataset],
    description: RobotDescription,
) -> tuple[Path, Path, Path]:
    """A PLF+ trained on the half of dataset B's training set with q2 below its median (so part of B's
    validation set lies outside its range), an A Priori model file (no training range), the validation CSV."""
    folder = tmp_path_factory.mktemp("narrow")
    train, validation = dataset_b
    keep = train.q_rad[:, 1] < np.median(train.q_rad[:, 1])
    half = StationaryDataset(train.q_rad[keep], train.tau_nm[keep], train.direction[keep], None, "half")
    train_path = folder / "half.csv"
    write_dataset(train_path, half)
    half = load_stationary(train_path)
    model = folder / "plf_plus.json"
    result = fit_plf_plus(half, description)
    save_model(model, result.model, training_summary(half, train_path), result.report)
    ap = folder / "ap.json"
    save_model(ap, build_ap(description, None, True, True).model)
    data = folder / "validation.csv"
    write_dataset(data, validation)
    return model, ap, data


def test_evaluate_reports_the_points_outside_each_models_range_and_the_rmse_on_each_side(
    narrow: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model_path, ap_path, data_path = narrow
    out = tmp_path / "errors.json"
    assert main(["evaluate", str(model_path), str(ap_path), "--data", str(data_path), "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    plf_plus, ap = json.loads(out.read_text())["models"]
    # the expected figures, computed here from the file's range and the model's torque
    model, contents = load_model(model_path)
    assert contents.training is not None
    data = load_stationary(data_path)
    low, high = np.array(contents.training.q_min_rad), np.array(contents.training.q_max_rad)
    outside = ((data.q_rad < low - 1e-3) | (data.q_rad > high + 1e-3)).any(axis=1)
    error = data.tau_nm - model.torque_batch(data.q_rad)
    assert 0 < outside.sum() < len(data)  # the fixture's point: some inside, some outside
    figures = plf_plus["training_range"]
    assert figures["points"] == len(data)
    assert figures["outside"] == int(outside.sum())
    assert figures["rmse_inside"] == pytest.approx(np.sqrt(np.mean(error[~outside] ** 2)), rel=1e-12)
    assert figures["rmse_outside"] == pytest.approx(np.sqrt(np.mean(error[outside] ** 2)), rel=1e-12)
    assert figures["q_min"] == low.tolist()
    assert figures["tolerance_rad"] == TOLERANCE_RAD
    assert ap["training_range"] is None  # built from the design values: never trained, nothing extrapolated
    # the table and the sentence
    assert f"{int(outside.sum())}/{len(data)}" in stdout
    assert f"PLF+: {int(outside.sum())} of {len(data)} points outside its training range" in stdout
    # the same through the library, for the session's validation gate
    again = model_extrapolation(model, contents.training, data)
    assert again is not None
    assert again.n_outside == figures["outside"]
    evaluated = evaluate_models([model], data, None, [contents.training])[0]
    assert evaluated.extrapolation == again


def test_two_files_of_one_kind_and_name_get_labels_that_tell_them_apart(
    narrow: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model_path, _, data_path = narrow
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        shutil.copy(model_path, tmp_path / folder / "model_plf_plus.json")
    out = tmp_path / "errors.json"
    paths = [str(tmp_path / f / "model_plf_plus.json") for f in ("a", "b")]
    assert main(["evaluate", *paths, "--data", str(data_path), "--json", str(out)]) == 0
    names = [m["name"] for m in json.loads(out.read_text())["models"]]
    assert names == ["PLF+ (a/model_plf_plus.json)", "PLF+ (b/model_plf_plus.json)"]
    stdout = capsys.readouterr().out
    assert "a/model_plf_plus.json" in stdout
    assert "b/model_plf_plus.json" in stdout


def test_distinct_labels_use_the_shortest_distinguishing_end_of_the_path() -> None:
    assert distinct_labels(["PLF+", "PENN"], ["x/m.json", "y/m.json"]) == ["PLF+", "PENN"]
    assert distinct_labels(["PLF+", "PLF+"], ["a.json", "b.json"]) == ["PLF+ (a.json)", "PLF+ (b.json)"]
    assert distinct_labels(["PLF+", "PLF+", "PLF+"], ["s1/a/m.json", "s2/a/m.json", "b/m.json"]) == [
        "PLF+ (s1/a/m.json)",
        "PLF+ (s2/a/m.json)",
        "PLF+ (b/m.json)",
    ]
    assert distinct_labels(["PLF+", "PLF+"], ["a/m.json", "x/a/m.json"]) == ["PLF+ (a/m.json)", "PLF+ (x/a/m.json)"]
    # the very same file twice: its path and its place in the list
    assert distinct_labels(["PLF+", "PLF+"], ["a/m.json", "a/m.json"]) == ["PLF+ (a/m.json #1)", "PLF+ (a/m.json #2)"]
