"""Issue 16: the SEA reading's hysteresis, closed on the robot's own closed-loop identification data.

``daror identify`` runs the protocol (training and validation) on two plants with different
hysteresis: ``exo_dummy_arm`` (dataset B: 0.25 / 0.75 / 0.35 / 0.15 Nm over 5 mrad) and
``exo_wide_hysteresis`` (0.15 / 0.55 / 0.60 / 0 Nm over 15 mrad). ``daror residual`` finds each
run's raw log beside its dataset and must name the hysteresis on the joints that carry it, with
the plant's amplitudes and travel, and leave nothing unexplained.

Two floors (D109, D111). The noise floor of the same runs: PLF+ on these very runs with the
plant's own hysteresis (its true amplitudes and travel) taken out, its state computed from the
measured angles as the analysis computes it: what the measured data allow a model that lacks
nothing. The stricter floor without the effect: the same protocol on the same plant (same seed,
so the same noise) with the direction error removed, fitted by PLF+ alone; it does not pay for
the encoders' noise in the hysteresis state. On static data with a pure direction offset the
sign stays the answer.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.control.sea_torque_design import SeaTorqueDesign
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.identification.protocol import run_protocol
from daror_runtime.identification.trajectory import ReferenceTrajectory
from daror_runtime.identification.trajectory_planning import build_trajectory
from daror_runtime.identification.waypoints import load_waypoints
from daror_runtime.models.files import load_model
from daror_runtime.models.linear import APModel
from daror_runtime.residual.data import load_pair
from daror_runtime.residual.diagnosis import closure, diagnose
from daror_runtime.residual.evidence import DiagnosisSettings
from daror_runtime.residual.floor import floor_of_the_same_runs
from daror_runtime.residual.hysteresis import PointHistory
from daror_runtime.residual.model import AugmentedModel
from daror_runtime.residual.travel import choose_direction_signal
from daror_runtime.session.settings import load_session_settings
from daror_runtime.session.training import read_model_candidate, validate_candidate
from hal.config import hal_config
from hal.interface import open_hal
from hal.isb import IsbLimits
from hal.robot import load_description
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary
from tests.conftest import as_dataset
from tests.daror_runtime.residual.test_residual_loop import pilot_torque_on_a_path

DAROR = str(Path(sys.executable).with_name("daror"))


def _daror(*args: str) -> str:
    run = subprocess.run([DAROR, *args], capture_output=True, text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr
    return run.stdout


def _identify(scenario: str, folder: Path) -> tuple[Path, Path]:
    paths = []
    for run in ("training", "validation"):
        out = folder / f"{Path(scenario).stem}_{run}.csv"
        _daror("identify", "--scenario", scenario, "--dummy-arm", "--trajectory", run, "--out", str(out))
        assert out.with_name(f"{out.stem}.raw.npz").exists()  # the raw log the analysis will find
        paths.append(out)
    return paths[0], paths[1]


def _residual(train: Path, validate: Path, out: Path, *extra: str) -> tuple[dict, dict]:
    _daror("residual", "--train", str(train), "--validate", str(validate), "--out", str(out), *extra)
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    evidence = json.loads((out / "diagnosis.json").read_text(encoding="utf-8"))
    return summary, evidence


#: The shipped protocol's trajectories by run and robot description (JSON), planned once per module.
Planned = dict[tuple[str, str], ReferenceTrajectory]


@pytest.fixture(scope="module")
def planned() -> Planned:
    """Where the floors' runs keep their trajectories: both plants are the same robot, so they share them."""
    return {}


def _identify_here(scenario: Path, run: str, folder: Path, planned: Planned) -> StationaryDataset:
    """The stationary points of ``daror identify --scenario SCENARIO --dummy-arm --trajectory RUN``, run here.

    The command's own pieces in its order (backend, AP feed-forward, trajectory, protocol), so the
    very points its dataset file holds (the CSV reads back bit for bit, D130); without the process
    and without writing files: these runs only give a reference figure, the command is tested above.
    """
    settings = load_session_settings(None).identification
    hal = open_hal(hal_config("sim", "--scenario/--rate-hz", scenario=str(scenario), rate_hz=1000.0))
    feedforward = APModel.from_description(hal.description, True, True)
    key = (run, hal.description.model_dump_json())
    if key not in planned:
        waypoints = load_waypoints(settings.waypoints_file)
        planned[key] = build_trajectory(waypoints, run, limits=IsbLimits(), description=hal.description)  # type: ignore[arg-type]
    trajectory = planned[key]
    hal.open()
    recording, dataset = folder / f"{scenario.stem}_{run}.rec", folder / f"{scenario.stem}_{run}.csv"
    try:
        result = run_protocol(hal, trajectory, recording, dataset, settings=settings, feedforward=feedforward)
    finally:
        hal.close()
        recording.unlink(missing_ok=True)
    return result.stationary


def _floor(scenario: str, folder: Path, planned: Planned) -> float:
    """PLF+ alone on the same runs of the same plant without the direction error.

    What ``daror residual --effects none`` reports as ``rmse_after`` on the two ``daror identify``
    runs of that plant (the same figure, bit for bit), computed in this process.
    """
    folder.mkdir(parents=True, exist_ok=True)
    plain = folder / f"{Path(scenario).stem}_no_hysteresis.yaml"
    plain.write_text(
        f"extends: {scenario}\nname: {plain.stem}\nsummary: the floor's runs\n"
        "sensors:\n  direction_error_nm: [0.0, 0.0, 0.0, 0.0]\n",
        encoding="utf-8",
    )
    train, validate = (_identify_here(plain, run, folder, planned) for run in ("training", "validation"))
    plain_fit = diagnose(train, load_description(), settings=DiagnosisSettings(families=()))
    return closure(plain_fit, validate).after.rmse_nm


def _floor_of_the_same_runs(train: Path, validate: Path, amplitudes: tuple[float, ...], travel: float) -> float:
    """PLF+ alone on these runs with the plant's true hysteresis, through the measured path, taken out."""
    return floor_of_the_same_runs(
        load_pair(train, validate), np.asarray(amplitudes), travel, load_description()
    ).after.rmse_nm


PLANTS = [
    # scenario, amplitudes (Nm), travel (rad), the largest ratio to the stricter floor (measured 1.73 and 1.18)
    ("exo_dummy_arm", (0.25, 0.75, 0.35, 0.15), 5e-3, 2.0),
    ("exo_wide_hysteresis", (0.15, 0.55, 0.60, 0.0), 15e-3, 1.5),
]


@pytest.mark.subprocess
@pytest.mark.slow
@pytest.mark.parametrize(("scenario", "amplitudes", "travel", "floor_ratio"), PLANTS)
def test_the_closed_loop_runs_hysteresis_is_named_and_closed(
    scenario: str, amplitudes: tuple[float, ...], travel: float, floor_ratio: float, tmp_path: Path, planned: Planned
) -> None:
    train, validate = _identify(scenario, tmp_path)
    summary, evidence = _residual(train, validate, tmp_path / "residual")
    found = {e["joints"][0]: e for e in summary["effects"] if e["name"] == "hysteresis"}
    carrying = {j + 1 for j, a in enumerate(amplitudes) if a > 0}
    assert set(found) == carrying  # on the joints that carry it, and only there
    assert all(e["name"] == "hysteresis" for e in summary["effects"])  # nothing else invented
    for joint in carrying:
        assert found[joint]["parameters"]["amplitude_nm"] == pytest.approx(amplitudes[joint - 1], rel=0.05)
        assert found[joint]["parameters"]["travel_rad"] == pytest.approx(travel, rel=0.05)
    assert evidence["direction_signal"]["chosen"] == "hysteresis"
    assert evidence["direction_signal"]["path"] == "raw log"
    assert summary["unexplained"] is False
    # Issue 16's acceptance: within 1.5x the noise floor of the same runs (measured 1.04x and 1.09x).
    assert summary["rmse_after"] <= 1.5 * _floor_of_the_same_runs(train, validate, amplitudes, travel)
    floor = _floor(scenario, tmp_path / "floor_runs", planned)
    assert summary["rmse_before"] > 100 * floor
    # Against the stricter floor, exo_dummy_arm's 5 mrad travel pays for the encoders' noise at
    # every turning point (docs/residual.md): this bound says what is reached.
    assert summary["rmse_after"] <= floor_ratio * floor
    # The session's validation gate and `daror evaluate` judge the model as the analysis did: with
    # its state along the validation run's raw log, not with the sign.
    fitted, _ = load_model(tmp_path / "residual" / "model.json")
    candidate = read_model_candidate(tmp_path / "residual" / "model.json", validate, load_description())
    gate = validate_candidate(candidate, max_rmse_nm=0.5)
    assert gate.validation.rmse_nm == pytest.approx(summary["rmse_after"], rel=1e-9)
    table = tmp_path / "evaluate.json"
    _daror("evaluate", str(tmp_path / "residual" / "model.json"), "--data", str(validate), "--json", str(table))
    evaluated = json.loads(table.read_text(encoding="utf-8"))["models"][0]["rmse"]
    assert evaluated == pytest.approx(summary["rmse_after"], rel=1e-9)
    # The fitted model in the loop (regulating the drive's reading, which carries the error): the
    # tracked hysteresis takes the reading's error off the pilot's arm.
    assert isinstance(fitted, AugmentedModel)
    untracked = AugmentedModel(fitted.description, fitted.spec.model_copy(update={"hysteresis_nm": [0.0] * 4}))
    plant = load_scenario(scenario)
    pose = generate_stationary(plant, "validation", noise_free=True).q_rad[10]
    design = SeaTorqueDesign(torque_from_encoders=False)
    carried_untracked, _ = pilot_torque_on_a_path(plant, untracked, pose, design)
    carried_tracked, _ = pilot_torque_on_a_path(plant, fitted, pose, design)
    # The reading's error flips with the approach; the model's own error at the pose does not.
    flip_tracked = np.abs(carried_tracked[1] - carried_tracked[0])
    flip_untracked = np.abs(carried_untracked[1] - carried_untracked[0])
    for joint in carrying:
        assert flip_tracked[joint - 1] < 0.25 * flip_untracked[joint - 1]
    assert np.linalg.norm(carried_tracked) < np.linalg.norm(carried_untracked)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["residual_direction_offset", "exo_dummy_arm"])
def test_a_static_direction_offset_stays_a_direction_offset(scenario: str) -> None:
    """Static data (every stop reverses the error fully): the sign of the last motion is the truth."""
    train = as_dataset(generate_stationary(load_scenario(scenario), "training"), f"{scenario}-training")
    description = load_description()
    first = diagnose(train, description)
    choice = choose_direction_signal(first, train, PointHistory.from_points(train), description, DiagnosisSettings())
    assert choice is not None
    assert not choice.hysteresis
    assert choice.bic_hysteresis > choice.bic_direction
    assert {f.effect.family for f in choice.diagnosis.found} >= {"direction_offset"}
    assert "hysteresis" not in {f.effect.family for f in choice.diagnosis.found}
    assert np.all(choice.travel_rad > 0)
