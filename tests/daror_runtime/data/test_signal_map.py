"""Issue 27: a dataset's signal map judged from physics (daror_runtime/data/signal_map.py, `daror data check`).

The thesis's mistake (Sec. 6.7: the joint angle and the gearbox angle exchanged, the joint torque
and the motor torque exchanged), names shifted by one column, two joints exchanged: each is refused
with its mix-up named, from a raw log of a closed-loop identification run written as a user's file
would be (every column there, only the names wrong). No clean dataset the project makes or ships is
refused.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from daror_runtime.cli import main
from daror_runtime.data.load import load_dataset, write_dataset
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.signal_map import SignalMapError, check_signal_map
from hal.robot import RobotDescription, load_description
from hal.sim.scenario import load_scenario, scenario_names
from hal.sim.static_dataset import generate_stationary
from tests.conftest import as_dataset

ROOT = Path(__file__).resolve().parents[3]
GROUPS = ("q", "dq", "tau", "theta", "tau_cmd")
THESIS = "q and theta exchanged, and tau and tau_cmd exchanged"


@pytest.fixture(scope="module")
def raw_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The raw log of a closed-loop identification run (validation trajectory through every fifth
    waypoint, enough elbow angles for PLF+ to be fitted to it; the Dummy Arm installed)."""
    folder = tmp_path_factory.mktemp("signal_map")
    out = folder / "run.npz"
    waypoints = _shipped_waypoints_every(5, folder)
    command = ["identify", "--scenario", "exo_dummy_arm", "--dummy-arm", "--trajectory", "validation"]
    assert main([*command, "--waypoints", str(waypoints), "--out", str(out)]) == 0
    return folder / "run.raw.npz"


def _renamed(source: Path, target: Path, rename: dict[str, str]) -> Path:
    """``source``'s columns written to ``target``, the column named ``a`` under the name ``rename[a]``."""
    columns = dict(np.load(source))
    np.savez(target, **{rename.get(name, name): values for name, values in columns.items()})
    return target


def _every_joint(pairs: tuple[tuple[str, str], ...]) -> dict[str, str]:
    rename = {}
    for a, b in pairs:
        for j in range(1, 5):
            rename[f"{a}{j}"], rename[f"{b}{j}"] = f"{b}{j}", f"{a}{j}"
    return rename


def _data_check(path: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[int, str]:
    code = main(["data", "check", str(path), *extra])
    captured = capsys.readouterr()
    return code, captured.out + captured.err


@pytest.mark.slow
def test_the_closed_loop_run_s_raw_log_holds_every_relation(raw_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    report = check_signal_map(load_dataset(raw_file), load_description())
    assert report.passed
    held = {(r.joint, r.name) for r in report.relations if r.held}
    # every relation judged on every joint of a run that moves every joint; the A Priori torque of
    # the bare robot (the Dummy Arm is not assumed) barely changes at the elbow: not judged there
    judged = {(j, n) for j in range(1, 5) for n in ("spring", "deflection", "command", "velocity", "a priori")}
    assert held == judged - {(4, "a priori")}
    code, out = _data_check(raw_file, capsys)
    assert code == 0
    assert "signal map consistent" in out
    assert out.count(" ok ") == 19


@pytest.mark.slow
def test_the_thesis_s_mistake_is_refused_and_named(
    raw_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    wrong = _renamed(raw_file, tmp_path / "thesis.npz", _every_joint((("q", "theta"), ("tau", "tau_cmd"))))
    report = check_signal_map(load_dataset(wrong), load_description())
    assert {(r.joint, r.name) for r in report.failures} >= {(j, "spring") for j in range(1, 5)}
    assert report.mix_up is not None
    assert report.mix_up.startswith(THESIS)
    code, out = _data_check(wrong, capsys)
    assert code == 2
    last = out.strip().splitlines()[-1]
    assert last.startswith(
        f"daror data check: error: {wrong}: the signal map looks wrong: spring relation fails on joints 1, 2, 3, 4"
    )
    assert f"most likely {THESIS}" in last
    # q and theta alone exchanged is named as such (tau is the springs' torque, and says so)
    alone = _renamed(raw_file, tmp_path / "q_theta.npz", _every_joint((("q", "theta"),)))
    assert check_signal_map(load_dataset(alone), load_description()).mix_up == (
        "q and theta exchanged (the gearbox angle read as the joint angle)"
    )


@pytest.mark.slow
@pytest.mark.parametrize(("shift", "said"), [(1, "later"), (-1, "earlier")])
def test_names_shifted_by_one_column_are_refused_and_named(
    raw_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], shift: int, said: str
) -> None:
    names = [f"{g}{j}" for g in GROUPS for j in range(1, 5)]  # the file's column order after t
    # each data column under the name ``shift`` columns away: a torque then sits under an angle's name
    rename = {names[(i + shift) % len(names)]: names[i] for i in range(len(names))}
    wrong = _renamed(raw_file, tmp_path / f"shift{shift}.npz", rename)
    with pytest.raises(
        SignalMapError, match=f"most likely the column names shifted by 1 .each name 1 column.s. {said}"
    ):
        load_dataset(wrong)
    code, out = _data_check(wrong, capsys)
    assert code == 2
    assert len(out.strip().splitlines()) == 1  # refused as it was read: one line, no report
    assert "the column names shifted by 1" in out


@pytest.mark.slow
def test_two_joints_exchanged_are_refused_and_named(
    raw_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rename = {f"{g}{a}": f"{g}{b}" for g in GROUPS for a, b in ((2, 3), (3, 2))}
    wrong = _renamed(raw_file, tmp_path / "joints.npz", rename)
    report = check_signal_map(load_dataset(wrong), load_description())
    # each joint's own springs still hold; the geometry's gravity torque tells the joints apart
    assert {r.name for r in report.failures} == {"a priori"}
    assert report.mix_up == "joints 2 and 3 exchanged (every column of the two)"
    code, out = _data_check(wrong, capsys)
    assert code == 2
    assert "most likely joints 2 and 3 exchanged" in out


def _stationary(description: RobotDescription, scenario: str, trajectory: str) -> StationaryDataset:
    return as_dataset(generate_stationary(load_scenario(scenario), trajectory), f"{scenario}-{trajectory}")


@pytest.mark.parametrize("scenario", scenario_names())
def test_no_scenario_s_stationary_data_is_refused(description: RobotDescription, scenario: str) -> None:
    for trajectory in ("training", "validation"):
        data = _stationary(description, scenario, trajectory)
        for dummy_arm in (False, True):  # whatever the user says of the Dummy Arm
            report = check_signal_map(data, description, dummy_arm=dummy_arm)
            assert report.passed, report.lines()
            assert sum(r.held is True for r in report.relations) >= 3  # judged, not waved through


#: The plants most likely to trip a relation: the bare robot (little torque at the elbow: the false
#: alarm D205 fixed), a heavier arm, a wider hysteresis, and the undeclared effects that touch the
#: relations' own signals (a stiffer spring, a wrong encoder zero, a drifting torque). docs/data.md
#: has all 11 scenarios, both trajectories, every waypoint (0 of 44 refused).
RAW_LOG_SCENARIOS = (
    "exo",
    "exo_heavy_arm",
    "exo_wide_hysteresis",
    "residual_torque_gain",
    "residual_encoder_offset",
    "residual_drift",
)


def _shipped_waypoints_every(step: int, folder: Path) -> Path:
    """The shipped waypoints 1, 1 + step, ...: a shorter protocol of the same workspace (a waypoint file)."""
    shipped = yaml.safe_load((ROOT / "daror_runtime/identification/waypoints.yaml").read_text(encoding="utf-8"))
    waypoints = shipped["waypoints"][::step]
    n = len(waypoints)
    path = folder / f"every_{step}.yaml"
    document = {
        "description": f"every {step}th shipped waypoint",
        "waypoints": waypoints,
        "training_order": list(range(1, n + 1)),
        "validation_order": [1, *range(n, 1, -1)],
    }
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def every_tenth_waypoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped waypoints 1, 11, ..., 81: a validation run of 92 s of robot time (~0.5 CPU-s)."""
    return _shipped_waypoints_every(10, tmp_path_factory.mktemp("waypoints"))


@pytest.mark.slow
@pytest.mark.parametrize("scenario", RAW_LOG_SCENARIOS)
def test_no_scenario_s_closed_loop_raw_log_is_refused(
    description: RobotDescription, scenario: str, every_tenth_waypoint: Path, tmp_path: Path
) -> None:
    """The false-alarm rate over the scenarios' closed-loop runs (issue 27: 0 of N clean runs refused).

    Each scenario's validation run through every tenth waypoint: the bare robot's elbow carries
    too little torque for the command relation (spread 0.18 Nm; judged, it fails at gain 0.15 and
    correlation 0.39), which is then not judged rather than failed (D205).
    """
    dummy_arm = ["--dummy-arm"] if load_scenario(scenario).dummy_arm is not None else []
    out = tmp_path / "run.npz"
    command = ["identify", "--scenario", scenario, *dummy_arm, "--trajectory", "validation"]
    assert main([*command, "--waypoints", str(every_tenth_waypoint), "--out", str(out)]) == 0
    report = check_signal_map(load_dataset(tmp_path / "run.raw.npz"), description, dummy_arm=bool(dummy_arm))
    assert report.passed, report.lines()
    judged = {(r.joint, r.name) for r in report.relations if r.held is True}
    assert {(j, "spring") for j in range(1, 5)} <= judged  # the springs, on every joint, judged and held
    assert {(j, "velocity") for j in range(1, 5)} <= judged


@pytest.mark.parametrize(
    ("columns", "named"),
    [
        ([1, 0, 2, 3], "joints 1 and 2 exchanged"),
        ([0, 1, 3, 2], "joints 3 and 4 exchanged"),
    ],
)
def test_stationary_points_with_two_joints_exchanged_are_named(
    description: RobotDescription, columns: list[int], named: str
) -> None:
    data = _stationary(description, "exo_dummy_arm", "training")
    wrong = replace(data, q_rad=data.q_rad[:, columns], tau_nm=data.tau_nm[:, columns])
    report = check_signal_map(wrong, description, dummy_arm=True)
    assert not report.passed
    assert report.mix_up is not None
    assert report.mix_up.startswith(named)


def test_a_torque_of_the_wrong_sign_is_refused_and_no_mix_up_invented(description: RobotDescription) -> None:
    data = _stationary(description, "exo_dummy_arm", "training")
    report = check_signal_map(replace(data, tau_nm=-data.tau_nm), description, dummy_arm=True)
    assert {r.joint for r in report.failures} >= {1, 2, 3}
    assert report.mix_up is None
    assert report.failure_line().endswith("(no exchange or shift of its columns explains it)")


@pytest.mark.parametrize("name", ["external_train.csv", "external_validate.mat"])
def test_the_shipped_external_datasets_are_not_refused(
    name: str, capsys: pytest.CaptureFixture[str], description: RobotDescription
) -> None:
    path = ROOT / "examples" / "residual" / name
    assert check_signal_map(load_dataset(path), description).passed
    code, _ = _data_check(path, capsys)
    assert code == 0


def test_a_robot_standing_still_is_not_judged_rather_than_refused(description: RobotDescription) -> None:
    """Relations the data cannot judge (no motion, no change of torque) are never failures."""
    n = 2000
    t = np.arange(n) * 1e-3
    q = np.tile([0.3, 0.8, 0.2, 1.0], (n, 1))
    deflection = np.tile([0.005, 0.02, 0.008, 0.003], (n, 1))
    tau = description.sea.spring_stiffness_nm_per_rad * deflection
    raw = RawLog(t, q, np.zeros_like(q), tau, theta_rad=q + deflection, tau_cmd_nm=tau.copy(), source="still")
    report = check_signal_map(raw, description)
    assert report.passed
    by_name = {(r.joint, r.name): r.held for r in report.relations}
    assert all(by_name[(j, "velocity")] is None and by_name[(j, "command")] is None for j in range(1, 5))
    assert all(by_name[(j, "spring")] is True for j in range(1, 5))  # its mean still says k (theta - q)
    flipped = replace(raw, theta_rad=q - deflection)  # the spring's sign wrong, even standing still
    assert {r.name for r in check_signal_map(flipped, description).failures} == {"spring"}


@pytest.mark.slow
def test_fit_and_evaluate_refuse_the_thesis_s_mistake_unless_trusted_and_then_say_so(
    raw_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    wrong = _renamed(raw_file, tmp_path / "thesis.npz", _every_joint((("q", "theta"), ("tau", "tau_cmd"))))
    model = tmp_path / "m.json"
    assert main(["fit", "plf+", "--train", str(wrong), "--out", str(model)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith(f"daror fit: error: {wrong}: the signal map looks wrong: spring relation fails")
    assert err[0].endswith("--trust-signal-map accepts the file anyway")
    assert not model.exists()  # nothing written
    # trusted: the model is fitted and its file says on what
    assert main(["fit", "plf+", "--train", str(wrong), "--out", str(model), "--trust-signal-map"]) == 0
    said = json.loads(model.read_text(encoding="utf-8"))["training"]["signal_map"]
    assert said.startswith(f"accepted with --trust-signal-map although {wrong}: the signal map looks wrong")
    assert THESIS in said
    table = tmp_path / "errors.json"
    assert main(["evaluate", str(model), "--data", str(wrong), "--json", str(table)]) == 2
    assert not table.exists()
    assert main(["evaluate", str(model), "--data", str(wrong), "--json", str(table), "--trust-signal-map"]) == 0
    assert json.loads(table.read_text(encoding="utf-8"))["signal_map"] == said
    # clean data: the files are as before (no signal_map key)
    clean_model, clean_table = tmp_path / "clean.json", tmp_path / "clean_errors.json"
    assert main(["fit", "plf+", "--train", str(raw_file), "--out", str(clean_model)]) == 0
    assert "signal_map" not in json.loads(clean_model.read_text(encoding="utf-8"))["training"]
    assert main(["evaluate", str(clean_model), "--data", str(raw_file), "--json", str(clean_table)]) == 0
    assert "signal_map" not in json.loads(clean_table.read_text(encoding="utf-8"))


@pytest.mark.slow
def test_residual_refuses_the_thesis_s_mistake_unless_trusted_and_then_its_report_says_so(
    raw_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    wrong = _renamed(raw_file, tmp_path / "thesis.npz", _every_joint((("q", "theta"), ("tau", "tau_cmd"))))
    validate = raw_file.parent / "run.npz"  # the run's stationary points, under their right names
    out = tmp_path / "residual"
    argv = ["residual", "--train", str(wrong), "--validate", str(validate), "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert f"{wrong}: the signal map looks wrong: spring relation fails" in err[0]
    assert not out.exists()
    assert main([*argv, "--trust-signal-map"]) == 0
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert len(summary["signal_map"]) == 1  # the training file only: the validation file's map held
    assert summary["signal_map"][0].startswith(f"accepted with --trust-signal-map although {wrong}")
    model = json.loads((out / "model.json").read_text(encoding="utf-8"))
    assert model["training"]["signal_map"] == summary["signal_map"][0]


@pytest.mark.slow
def test_the_data_efficiency_study_refuses_a_mix_up_unless_trusted_and_then_says_so(
    tmp_path: Path, description: RobotDescription, capsys: pytest.CaptureFixture[str]
) -> None:
    train, validate = (_stationary(description, "exo_dummy_arm", t) for t in ("training", "validation"))
    swapped = tmp_path / "swapped.csv"  # joints 1 and 2 exchanged in every column
    write_dataset(swapped, replace(train, q_rad=train.q_rad[:, [1, 0, 2, 3]], tau_nm=train.tau_nm[:, [1, 0, 2, 3]]))
    clean = tmp_path / "validate.csv"
    write_dataset(clean, validate)
    out = tmp_path / "study"
    argv = ["study", "data-efficiency", "--train", str(swapped), "--validate", str(clean), "--out", str(out)]
    assert main([*argv, "--sizes", "40,80", "--draws", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "most likely joints 1 and 2 exchanged" in err[0]
    assert not out.exists()
    assert main([*argv, "--sizes", "40,80", "--draws", "2", "--trust-signal-map"]) == 0
    document = json.loads((out / "data_efficiency.json").read_text(encoding="utf-8"))
    assert len(document["signal_map"]) == 1
    assert "most likely joints 1 and 2 exchanged" in document["signal_map"][0]
    assert document["signal_map"][0] in (out / "data_efficiency.md").read_text(encoding="utf-8")


@pytest.mark.slow
@pytest.mark.parametrize("mixed_up", [False, True], ids=["clean", "q-theta-exchanged"])
def test_a_session_s_own_recording_with_a_wrong_map_is_kept_as_evidence_and_never_trained_on(
    raw_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mixed_up: bool
) -> None:
    """The drives' readings mapped to the wrong signals (here each joint's two encoders exchanged,
    as a wrong PDO mapping or a swapped cable would) make a recording the session would train on; it
    is judged as it is saved, kept, and refused for a model, with the mix-up named to the operator."""
    from types import SimpleNamespace

    from daror_runtime.identification.protocol import RunData
    from daror_runtime.runtime import Runtime
    from daror_runtime.session import identification, requests
    from daror_runtime.session.events import AnnouncementKind
    from daror_runtime.session.settings import SessionSettings
    from daror_runtime.testing import session_core
    from hal.sim.backend import SimHal

    raw = load_dataset(raw_file)
    assert isinstance(raw, RawLog)
    assert raw.theta_rad is not None
    if mixed_up:
        raw = replace(raw, q_rad=raw.theta_rad, theta_rad=raw.q_rad)
    stationary = load_dataset(raw_file.parent / "run.npz")
    assert isinstance(stationary, StationaryDataset)
    recorded = RunData(raw, stationary, np.zeros(4), np.zeros(4))
    monkeypatch.setattr(identification, "finish_recording", lambda run: recorded)

    runtime = Runtime(SimHal("exo_dummy_arm"), tmp_path / "session", settings=SessionSettings(dummy_arm=True))
    runtime.open()
    try:
        core = session_core(runtime)
        dataset = tmp_path / "session" / "identification_training.csv"
        run = SimpleNamespace(kind="training", dataset_path=dataset, recorder=SimpleNamespace(path=tmp_path / "rec"))
        requests._collect(core, run)  # type: ignore[arg-type]  # what the tick boundary does when a run ends
        core.jobs.run_pending()
        runtime.runner.run_ticks(2)  # the job's outcome is applied at a tick boundary
        said = [(a.kind, a.text) for a in core.announcements.drain()]
    finally:
        runtime.close()
    # the files are written either way: a recording is evidence
    assert dataset.is_file()
    assert (tmp_path / "session" / "identification_training.raw.npz").is_file()
    if not mixed_up:
        assert core.progress.last_error is None
        assert core.signals.identification_saved == {"training": dataset}
        return
    assert "training" not in core.signals.identification_saved  # nothing to train on: train is refused
    error = core.progress.last_error
    assert error is not None
    assert error.startswith(f"identification training: {tmp_path / 'session' / 'identification_training.raw.npz'}: ")
    assert "the signal map looks wrong: spring relation fails on joints 1, 2, 3, 4" in error
    assert "most likely q and theta exchanged" in error
    assert "kept as evidence, not used for a model" in error
    assert any(
        kind is AnnouncementKind.JOB_FAILED
        and text.startswith("save identification training failed: ")
        and "q and theta exchanged" in text
        for kind, text in said
    ), said


@pytest.mark.slow
def test_a_joint_carrying_little_torque_in_a_short_run_is_judged_on_its_sign_not_refused(tmp_path: Path) -> None:
    """The bare robot's joint 2 through every 12th waypoint (a session's short protocol): its torque
    spreads 0.5-0.8 Nm, the size of the direction error across its spring (0.75 Nm), which leaves
    R^2 0.2 and biases the gains (1.3 on the spring, 0.6 on the command). Refused before D209; the
    same run with q and theta exchanged is still refused on every joint's sign."""
    out = tmp_path / "short.npz"
    waypoints = _shipped_waypoints_every(12, tmp_path)
    argv = ["identify", "--scenario", "exo", "--trajectory", "validation", "--waypoints", str(waypoints)]
    assert main([*argv, "--out", str(out)]) == 0
    raw = load_dataset(tmp_path / "short.raw.npz")
    assert isinstance(raw, RawLog)
    assert raw.theta_rad is not None
    report = check_signal_map(raw, load_description())
    assert report.passed, report.lines()
    joint_2 = {r.name: r for r in report.relations if r.joint == 2}
    assert joint_2["spring"].held
    assert "little spread: its sign judged" in joint_2["spring"].figure
    assert joint_2["command"].held
    assert "little spread: its sign judged" in joint_2["command"].figure
    exchanged = check_signal_map(replace(raw, q_rad=raw.theta_rad, theta_rad=raw.q_rad), load_description())
    assert {(r.joint, r.name) for r in exchanged.failures} >= {(j, "spring") for j in range(1, 5)}
    assert exchanged.mix_up == "q and theta exchanged (the gearbox angle read as the joint angle)"
