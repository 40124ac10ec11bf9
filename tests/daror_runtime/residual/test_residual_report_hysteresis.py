"""``hysteresis.png``: the fitted hysteresis drawn against the data, written only when the model has one.

The data: the clean Dummy Arm scenario (sensor noise only, ~0.024 Nm RMS) with a known hysteresis
added to the torque reading of joints 2 and 4 (play operator over the points in their order, one
travel constant). The real pipeline (:func:`run_residual`, no subprocess) must choose the hysteresis,
draw it, and the numbers the plot is drawn from must be the injected error to the noise.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DataError
from daror_runtime.residual.hysteresis import PointHistory
from daror_runtime.residual.model import AugmentedModel
from daror_runtime.residual.pipeline import ResidualRun, run_residual
from daror_runtime.residual.report import (
    HYSTERESIS_PLOT_FILE,
    REPORT_FILES,
    carries_hysteresis,
    hysteresis_curve_data,
)
from daror_runtime.residual.travel import with_signal
from hal.robot import load_description
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary
from tests.conftest import as_dataset

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
AMPLITUDE_NM = np.array([0.0, 0.5, 0.0, 0.3])  # the injected d_j
TRAVEL_RAD = 0.03  # the injected r_j (all joints)
NOISE_NM = 0.05  # about twice the scenario's sensor noise (0.024 Nm RMS)


@dataclass(frozen=True)
class Case:
    folder: Path
    run: ResidualRun
    train: StationaryDataset  # as written, the hysteresis added
    validate: StationaryDataset
    injected_train_nm: np.ndarray  # d_j * s_j(true travel) per point
    injected_validate_nm: np.ndarray


def _with_hysteresis(data: StationaryDataset) -> tuple[StationaryDataset, np.ndarray]:
    injected = AMPLITUDE_NM * PointHistory.from_points(data).states(TRAVEL_RAD)
    return dataclasses.replace(data, tau_nm=data.tau_nm + injected), injected


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> Case:
    folder = tmp_path_factory.mktemp("hysteresis_report")
    scenario = load_scenario("residual_clean")
    train, injected_train = _with_hysteresis(as_dataset(generate_stationary(scenario, "training"), "train"))
    validate, injected_validate = _with_hysteresis(as_dataset(generate_stationary(scenario, "validation"), "val"))
    write_dataset(folder / "train.csv", train)
    write_dataset(folder / "validate.csv", validate)
    run = run_residual(folder / "train.csv", folder / "validate.csv", folder / "report", load_description())
    return Case(folder, run, train, validate, injected_train, injected_validate)


@pytest.fixture(scope="module")
def without(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Training and validation files of a pure direction offset (the sign stays the answer)."""
    folder = tmp_path_factory.mktemp("direction_offset")
    scenario = load_scenario("residual_direction_offset")
    write_dataset(folder / "train.csv", as_dataset(generate_stationary(scenario, "training")))
    write_dataset(folder / "validate.csv", as_dataset(generate_stationary(scenario, "validation")))
    return folder / "train.csv", folder / "validate.csv"


def _states(case: Case) -> tuple[StationaryDataset, StationaryDataset]:
    """The datasets as the report saw them: the direction column replaced by the fitted travel's states."""
    run = case.run
    assert run.travel is not None
    assert run.inputs.train_history is not None
    assert run.inputs.validate_history is not None
    train = with_signal(run.inputs.train, run.inputs.train_history, run.travel.travel_rad)
    validate = with_signal(run.inputs.validate, run.inputs.validate_history, run.travel.travel_rad)
    return train, validate


@pytest.mark.slow
def test_the_pipeline_chose_the_injected_hysteresis(case: Case) -> None:
    """The premise of the other tests: the model carries the hysteresis on joints 2 and 4 only."""
    spec = case.run.model.spec
    assert case.run.travel is not None
    assert case.run.travel.hysteresis
    assert carries_hysteresis(case.run.model)
    assert [j for j, d in enumerate(spec.hysteresis_nm) if d != 0.0] == [1, 3]
    assert spec.hysteresis_travel_rad is not None


def test_the_plot_is_written_and_named_in_the_report(case: Case) -> None:
    out = case.folder / "report"
    assert case.run.files[HYSTERESIS_PLOT_FILE] == out / HYSTERESIS_PLOT_FILE
    assert set(case.run.files) == {HYSTERESIS_PLOT_FILE, *REPORT_FILES}
    png = (out / HYSTERESIS_PLOT_FILE).read_bytes()
    assert png[:8] == PNG_MAGIC
    import matplotlib.image

    height, width, _ = matplotlib.image.imread(out / HYSTERESIS_PLOT_FILE).shape
    assert width > 2 * height  # two panels side by side: joints 2 and 4
    report = (out / "report.md").read_text(encoding="utf-8")
    effects = report[report.index("## Effects found") : report.index("## Candidates of the last round")]
    assert "hysteresis" in effects
    assert f"]({HYSTERESIS_PLOT_FILE})" in effects
    assert f"![{HYSTERESIS_PLOT_FILE}]({HYSTERESIS_PLOT_FILE})" in report[report.index("## Plots") :]
    assert not list(out.parent.glob(".report.*")), "the staging folder must be gone"


def test_the_plotted_residual_is_the_injected_hysteresis(case: Case) -> None:
    """residual = tau - model without its direction term = d_j s_j + noise, on both files."""
    train, validate = _states(case)
    for data, injected in ((train, case.injected_train_nm), (validate, case.injected_validate_nm)):
        curves = hysteresis_curve_data(case.run.model, data)
        assert [c.joint for c in curves] == [2, 4]
        for curve in curves:
            j = curve.joint - 1
            np.testing.assert_array_equal(curve.states, data.direction[:, j])
            truth = injected[:, j]
            assert np.sqrt(np.mean(truth**2)) > 5 * NOISE_NM  # the injected error is far above the noise
            assert np.sqrt(np.mean((curve.residual_nm - truth) ** 2)) < NOISE_NM
            # the model's own term predicts the residual as well as the truth does
            fitted = curve.gain * curve.amplitude_nm * curve.states
            assert np.sqrt(np.mean((curve.residual_nm - fitted) ** 2)) < NOISE_NM


def test_the_plotted_line_is_the_fitted_amplitude_over_the_fitted_travel(case: Case) -> None:
    train, _ = _states(case)
    spec = case.run.model.spec
    for curve in hysteresis_curve_data(case.run.model, train):
        j = curve.joint - 1
        assert curve.line_states[0] == -1.0
        assert curve.line_states[-1] == 1.0
        assert curve.line_nm[-1] == pytest.approx(spec.torque_gain[j] * spec.hysteresis_nm[j])
        assert curve.line_nm[-1] == pytest.approx(AMPLITUDE_NM[j], rel=0.05)
        np.testing.assert_allclose(curve.line_nm, -curve.line_nm[::-1], atol=1e-12)
        assert curve.amplitude_nm == spec.hysteresis_nm[j]
        assert curve.travel_rad == pytest.approx(TRAVEL_RAD, rel=0.2)


def test_the_curve_data_exact_on_a_model_it_was_made_from(case: Case) -> None:
    """Data the model itself reads (gain != 1): the residual is gain d s to rounding, joint by joint."""
    spec = case.run.model.spec.model_copy(
        update={"torque_gain": [1.0, 0.9, 1.0, 1.2], "hysteresis_nm": [0.0, 0.4, 0.0, -0.2]}
    )
    model = AugmentedModel(load_description(), spec)
    train, _ = _states(case)
    exact = dataclasses.replace(train, tau_nm=model.predict(train.q_rad, train.direction))
    curves = hysteresis_curve_data(model, exact)
    assert [c.joint for c in curves] == [2, 4]
    for curve, gain, amplitude in zip(curves, (0.9, 1.2), (0.4, -0.2), strict=True):
        np.testing.assert_allclose(curve.residual_nm, gain * amplitude * curve.states, atol=1e-9)
        assert curve.line_nm[-1] == pytest.approx(gain * amplitude)


def test_curve_data_refuses_a_dataset_without_states(case: Case) -> None:
    no_signal = dataclasses.replace(case.train, direction=None, source="nodir.csv")
    with pytest.raises(DataError, match=r"^nodir\.csv: no direction signal"):
        hysteresis_curve_data(case.run.model, no_signal)
    outside = dataclasses.replace(case.train, direction=2.0 * np.ones_like(case.train.q_rad), source="big.csv")
    with pytest.raises(DataError, match=r"^big\.csv: .*outside \[-1, 1\]"):
        hysteresis_curve_data(case.run.model, outside)


@pytest.mark.slow
def test_a_run_without_hysteresis_writes_none_and_removes_an_earlier_one(
    case: Case, without: tuple[Path, Path], tmp_path: Path
) -> None:
    out = tmp_path / "reused"
    shutil.copytree(case.folder / "report", out)
    assert (out / HYSTERESIS_PLOT_FILE).exists()
    run = run_residual(*without, out, load_description())
    assert not carries_hysteresis(run.model)
    assert run.travel is not None
    assert not run.travel.hysteresis
    assert hysteresis_curve_data(run.model, run.inputs.train) == []
    assert HYSTERESIS_PLOT_FILE not in run.files
    assert not (out / HYSTERESIS_PLOT_FILE).exists(), "a stale hysteresis.png from the earlier run"
    assert sorted(p.name for p in out.iterdir()) == sorted(REPORT_FILES)
    assert HYSTERESIS_PLOT_FILE not in (out / "report.md").read_text(encoding="utf-8")
