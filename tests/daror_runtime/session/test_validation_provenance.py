"""Issue 24, defect 1: a session validates a model only on data of this pilot, and a non-conservative model needs the operator's word.

* ``model FILE VALIDATION`` with data that is not a recording of this session's pilot on its robot is
  refused when named, with the reason: synthetic points of ``daror simulate static``, a file without
  provenance, a recording of another pilot, a provenance file moved beside other data;
* a recording of this pilot (an earlier session's run, its provenance naming the pilot and robot) is
  accepted, and the status says where the validation data came from;
* a model the closed-path test finds not conservative (an NNN) is refused with its energy figure, and
  used only when the operator confirms it (``nonconservative``); the status then says so.
"""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from daror_runtime.cli import main
from daror_runtime.console.commands import ConsoleSession
from daror_runtime.console.view import render_status
from daror_runtime.data.load import load_stationary, write_dataset
from daror_runtime.data.provenance import (
    provenance_path,
    read_provenance,
    simulated_pilot,
    simulated_robot,
    write_provenance,
)
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.data.signal_map import SignalMapError
from daror_runtime.errors import DataError
from daror_runtime.models.files import load_model, save_model
from daror_runtime.models.neural import Network, NetworkSpec, NnnModel
from daror_runtime.session.core import RequestRefusedError
from daror_runtime.session.settings import SessionSettings
from daror_runtime.testing import session_core
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary
from tests.conftest import Models, recorded_by_an_earlier_session
from tests.daror_runtime.session.test_session_safety import Session

SCENARIO = load_scenario("exo_dummy_arm")
ROBOT = simulated_robot(SCENARIO.description().name, SCENARIO.name)


@pytest.fixture
def session(tmp_path: Path) -> Iterator[Session]:
    s = Session(tmp_path / "session")
    yield s
    s.close()


def _held_out(path: Path) -> Path:
    points = generate_stationary(SCENARIO, "validation")
    write_dataset(path, StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s))
    return path


def _refused(session: Session, model: Path, validation: Path) -> str:
    with pytest.raises(RequestRefusedError) as refusal:
        session.runtime.select_model(model, validation)
    assert not session_core(session.runtime).jobs.pending  # refused when named: nothing queued
    assert session_core(session.runtime).modes.compensation.model is None
    return str(refusal.value)


def test_synthetic_points_of_daror_simulate_static_do_not_validate_a_model(
    session: Session, models: Models, tmp_path: Path
) -> None:
    """The issue's case: B_val.csv from `daror simulate static` is another 'robot', not this pilot."""
    data = tmp_path / "B_val.csv"
    args = ["simulate", "static", "--scenario", "exo_dummy_arm", "--trajectory", "validation", "--out", str(data)]
    assert main(args) == 0
    provenance = read_provenance(data)
    assert provenance is not None
    assert provenance.source == "simulate"
    assert provenance.robot == ROBOT
    assert provenance.run == "validation"
    reason = _refused(session, models.good, data)
    assert "synthetic points of the simulator (daror simulate static)" in reason
    assert "not a recording of the pilot" in reason


def test_a_model_file_carries_the_provenance_of_its_training_data(tmp_path: Path) -> None:
    train, model = tmp_path / "B_train.csv", tmp_path / "plf_plus.json"
    args = ["simulate", "static", "--scenario", "exo_dummy_arm", "--trajectory", "training", "--out", str(train)]
    assert main(args) == 0
    assert main(["fit", "plf+", "--train", str(train), "--out", str(model)]) == 0
    _, document = load_model(model)
    assert document.training is not None
    assert document.training.provenance == read_provenance(train)
    assert document.training.provenance is not None
    assert document.training.provenance.source == "simulate"
    assert document.training.provenance.pilot == simulated_pilot("exo_dummy_arm")


def test_data_without_provenance_does_not_validate_a_model(session: Session, models: Models, tmp_path: Path) -> None:
    data = _held_out(tmp_path / "from_elsewhere.csv")
    reason = _refused(session, models.good, data)
    assert "no provenance file beside it (from_elsewhere.csv.provenance.json)" in reason


def test_a_recording_of_another_pilot_is_refused_and_one_of_this_pilot_is_accepted(
    tmp_path: Path, models: Models
) -> None:
    session = Session(tmp_path / "session", SessionSettings(dummy_arm=True, pilot="P-001"))
    try:
        other = _held_out(tmp_path / "other_pilot.csv")
        write_provenance(other, "session", ROBOT, "P-002", "s-earlier", "validation", SCENARIO.name)
        reason = _refused(session, models.good, other)
        assert "pilot P-002" in reason
        assert "this session is pilot P-001" in reason
        other_robot = _held_out(tmp_path / "other_robot.csv")
        write_provenance(other_robot, "session", "DAROR-01", "P-001", "s-lab", "validation")
        assert "robot DAROR-01," in _refused(session, models.good, other_robot)

        mine = _held_out(tmp_path / "p001_validation.csv")
        write_provenance(mine, "session", ROBOT, "P-001", "s-0925", "validation", SCENARIO.name)
        session.select(models.good, mine)
        status = session.runtime.snapshot()
        assert status.model is not None
        assert status.model.validated
        assert status.model.validation_data == (
            f"recorded in session s-0925 (validation run): pilot P-001, robot {ROBOT}, "
            f"{read_provenance(mine).recorded_utc}"  # type: ignore[union-attr]
        )
        assert status.model.conservative is True
        assert "validation data: recorded in session s-0925" in render_status(status, [], [])
        summary = session_core(session.runtime).progress.last_model
        assert summary["validation_data"]["pilot"] == "P-001"
        assert summary["validation_data"]["origin"] == "earlier recording"
    finally:
        session.close()


def test_a_provenance_file_beside_other_data_is_an_error_naming_it(
    session: Session, models: Models, tmp_path: Path
) -> None:
    data = _held_out(tmp_path / "val.csv")
    write_provenance(data, "session", ROBOT, simulated_pilot(SCENARIO.name), "s1", "validation")
    other = _held_out(tmp_path / "copied.csv")
    with other.open("a", encoding="utf-8") as handle:  # the same pilot's file, then edited by hand
        handle.write("0.1,0.2,0.3,0.4,1,1,1,1\n")
    provenance_path(other).write_bytes(provenance_path(data).read_bytes())
    with pytest.raises(DataError, match=r"copied\.csv\.provenance\.json: belongs to other data than copied\.csv"):
        session.runtime.select_model(models.good, other)
    provenance_path(other).write_text('{"format": "daror-provenance", "source": "lab"}', encoding="utf-8")
    with pytest.raises(DataError, match=r"not a provenance file: .*copied\.csv\.provenance\.json"):
        session.runtime.select_model(models.good, other)


def test_the_console_names_the_refusal_in_one_line(session: Session, models: Models, tmp_path: Path) -> None:
    data = _held_out(tmp_path / "B_val.csv")
    buffer = io.StringIO()
    console = ConsoleSession(session.runtime, Console(file=buffer, width=300, color_system=None), session.world)
    with pytest.raises(RequestRefusedError, match="no provenance file beside it"):
        console.execute(f"model {models.good} {data}")


# --- a model that is not conservative ---------------------------------------------------------------


def _small_nnn(path: Path) -> Path:
    """An NNN of small torques (<= 0.05 Nm a joint): harmless, and, like every NNN, not a gradient."""
    spec = NetworkSpec(model="nnn", layers=1, width=8, activation="tanh", inputs="q")
    rng = np.random.default_rng(3)
    network = Network.checked(spec, np.zeros(4), np.ones(4), np.full(4, 0.05), rng.normal(0.0, 1.0, spec.n_weights))
    save_model(path, NnnModel(SCENARIO.description(), network))
    return path


def test_a_non_conservative_model_needs_the_operator_s_confirmation_with_its_energy_shown(
    tmp_path: Path, models: Models
) -> None:
    # the NNN's torques are small: its validation RMSE is about the data's own size; the limit lets it pass,
    # so that what refuses it is the closed-path test alone
    session = Session(tmp_path / "session", SessionSettings(dummy_arm=True, max_validation_rmse_nm=20.0))
    try:
        runtime = session.runtime
        nnn = _small_nnn(tmp_path / "nnn.json")
        session.select(nnn, models.validation)
        refused = runtime.snapshot().model_refused
        assert refused is not None
        assert refused["validated"]  # it passed validation ...
        assert refused["conservative"] is False  # ... and the closed-path test refused it
        energies = refused["closed_path_energy_j"]
        assert len(energies) == 3
        assert abs(energies[-1]) > 1e-6  # it does not vanish with the step: energy along a closed path
        assert abs(energies[-1]) * 5.0 > abs(energies[-2])
        assert session_core(runtime).modes.compensation.model is None
        said = [a.text for a in runtime.drain_announcements() if a.kind.value == "model"]
        assert any(
            "is not conservative: the closed-path test leaves" in text
            and f"{energies[-1]:.3g} J" in text
            and f"model {nnn} {models.validation} nonconservative" in text
            for text in said
        ), said
        view = render_status(runtime.snapshot(), [], [])
        assert "is not conservative" in view

        buffer = io.StringIO()
        console = ConsoleSession(runtime, Console(file=buffer, width=300, color_system=None), session.world)
        console.execute(f"model {nnn} {models.validation} nonconservative")
        assert runtime.runner.run_until(lambda: not runtime.busy, 5.0)
        status = runtime.snapshot()
        assert status.model is not None
        assert status.model.kind == "nnn"
        assert status.model.nonconservative_confirmed
        assert status.model.conservative is False
        assert "NOT conservative" in render_status(status, [], [])
        assert session_core(runtime).modes.compensation.model is not None
        document = json.loads(json.dumps(runtime.status(), default=str))
        assert document["model"]["nonconservative_confirmed"] is True
    finally:
        session.close()


def test_a_conservative_model_is_not_asked_for_confirmation(session: Session, models: Models) -> None:
    session.select(models.good, models.validation)
    status = session.runtime.snapshot()
    assert status.model is not None
    assert status.model.conservative is True
    assert not status.model.nonconservative_confirmed
    assert status.model_refused is None


def test_the_gate_says_how_many_validation_points_the_model_extrapolates_to(session: Session, models: Models) -> None:
    """Issue 24, defect 7, in the session: points outside the model's training range, and the RMSE on each side."""
    session.select(models.good, models.validation)
    _, document = load_model(models.good)
    assert document.training is not None
    validation = load_stationary(models.validation)
    low, high = np.array(document.training.q_min_rad), np.array(document.training.q_max_rad)
    outside = np.any((validation.q_rad < low - 1e-3) | (validation.q_rad > high + 1e-3), axis=1)
    summary = session_core(session.runtime).progress.last_model["extrapolation"]
    assert summary["points"] == len(validation)
    assert summary["outside"] == int(outside.sum())
    text = session.runtime.snapshot().model.validation_extrapolation  # type: ignore[union-attr]
    assert text is not None
    assert text.startswith(f"{int(outside.sum())} of {len(validation)} validation points outside the model's")
    assert text in render_status(session.runtime.snapshot(), [], [])


def test_validation_data_whose_columns_are_not_what_their_names_say_is_refused_naming_the_mix_up(
    session: Session, models: Models, tmp_path: Path
) -> None:
    """Issue 27: the gate judges the validation file's signal map, and has no trust flag."""
    points = generate_stationary(SCENARIO, "validation")
    swapped = tmp_path / "swapped_validation.csv"  # joints 1 and 2 exchanged in every column
    order = [1, 0, 2, 3]
    write_dataset(
        swapped, StationaryDataset(points.q_rad[:, order], points.tau_nm[:, order], points.direction[:, order])
    )
    recorded_by_an_earlier_session(swapped, SCENARIO, "validation")  # this pilot's: only the columns are wrong
    with pytest.raises(SignalMapError) as refusal:  # refused when named, as a malformed file is
        session.runtime.select_model(models.good, swapped)
    reason = str(refusal.value)
    assert "the signal map looks wrong" in reason
    assert "most likely joints 1 and 2 exchanged" in reason
    assert reason.endswith("a session validates a model only on data whose columns are what they say")
    assert not session_core(session.runtime).jobs.pending
    assert session_core(session.runtime).modes.compensation.model is None
