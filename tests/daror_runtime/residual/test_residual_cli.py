"""``daror residual`` end to end: the files it writes, data from elsewhere, and bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.cli import main
from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.tables import read_table, write_table
from daror_runtime.models.files import load_model
from daror_runtime.residual.report import SUMMARY_KEYS
from hal.sim.quasi_static import QuasiStaticSettings, quasi_static_log
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import STREAM_RAW_LOG, generate_stationary, scenario_stops, stream
from tests.conftest import as_dataset

#: Slow tier as a whole (docs/testing.md): the module's residual runs take ~9 s before the first test.
pytestmark = pytest.mark.slow

EXAMPLES = Path(__file__).resolve().parents[3] / "examples" / "residual"


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Training and validation files of the direction-offset scenario (CSV)."""
    folder = tmp_path_factory.mktemp("residual")
    scenario = load_scenario("residual_direction_offset")
    train, validate = folder / "train.csv", folder / "validate.csv"
    write_dataset(train, as_dataset(generate_stationary(scenario, "training")))
    write_dataset(validate, as_dataset(generate_stationary(scenario, "validation")))
    return train, validate


@pytest.fixture(scope="module")
def run(files: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("out") / "report"
    assert main(["residual", "--train", str(files[0]), "--validate", str(files[1]), "--out", str(out)]) == 0
    return out


@pytest.mark.slow
def test_summary_json_is_exactly_the_design_contract(run: Path) -> None:
    summary = json.loads((run / "summary.json").read_text())
    assert tuple(summary) == SUMMARY_KEYS
    assert summary["base_model"] == "plf+"
    assert len(summary["rmse_per_joint_before"]) == len(summary["rmse_per_joint_after"]) == 4
    assert summary["rmse_after"] < 0.1 * summary["rmse_before"]
    assert summary["nrmse_after"] < summary["nrmse_before"]
    assert summary["unexplained"] is False
    (effect,) = summary["effects"]
    assert set(effect) == {"name", "joints", "parameters", "rmse_gain"}
    assert (effect["name"], effect["joints"]) == ("direction_offset", [2])
    assert effect["parameters"]["offset_nm"] == pytest.approx(0.6, abs=0.01)
    assert effect["rmse_gain"] == pytest.approx(summary["rmse_before"] - summary["rmse_after"])


def test_report_files_are_all_there_and_readable(run: Path) -> None:
    report = (run / "report.md").read_text()
    assert "joint 2 direction offset 0.6" in report
    assert "| joint 2 |" in report
    for plot in ("residual_signals.png", "before_after.png"):
        assert (run / plot).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"]({plot})" in report
    diagnosis = json.loads((run / "diagnosis.json").read_text())
    assert diagnosis["found"][0]["verdict"] == "found"
    assert {e["verdict"] for e in diagnosis["rounds"][-1]} <= {
        "absorbed",
        "not significant",
        "too small",
        "does not generalise",
    }
    assert not list(run.parent.glob(".report.*")), "the staging folder must be gone"


def test_the_written_model_is_an_ordinary_model_file(run: Path, files: tuple[Path, Path], tmp_path: Path) -> None:
    _model, contents = load_model(run / "model.json")
    assert contents.kind == "augmented"
    assert contents.parameters["effects"] == ["direction_offset (joint 2)"]
    out = tmp_path / "evaluation.json"
    assert main(["evaluate", str(run / "model.json"), "--data", str(files[1]), "--json", str(out)]) == 0
    evaluated = json.loads(out.read_text())["models"][0]
    summary = json.loads((run / "summary.json").read_text())
    assert evaluated["rmse"] == pytest.approx(summary["rmse_after"], rel=1e-9)


def test_the_a_priori_base_is_augmented(files: tuple[Path, Path], tmp_path: Path) -> None:
    # AP has no fitted parameters: before issue 10 its first round failed on an empty design.
    out = tmp_path / "ap"
    args = ["--train", str(files[0]), "--validate", str(files[1]), "--base", "ap", "--dummy-arm"]
    assert main(["residual", *args, "--effects", "direction_offset,torque_gain", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["base_model"] == "ap"
    assert ("direction_offset", [2]) in [(e["name"], e["joints"]) for e in summary["effects"]]
    assert summary["rmse_after"] < summary["rmse_before"]


@pytest.mark.slow
def test_data_from_another_source_works(tmp_path: Path) -> None:
    # The example files do not come from hal.sim: own column order, extra columns, no t, a .mat file.
    out = tmp_path / "external"
    train, validate = EXAMPLES / "external_train.csv", EXAMPLES / "external_validate.mat"
    assert main(["residual", "--train", str(train), "--validate", str(validate), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [(e["name"], e["joints"]) for e in summary["effects"]] == [("direction_offset", [2])]
    assert summary["effects"][0]["parameters"]["offset_nm"] == pytest.approx(0.4, abs=0.02)
    assert summary["rmse_after"] == pytest.approx(0.03, abs=0.005)  # the generator's noise


@pytest.mark.slow
def test_a_raw_log_is_reduced_first(tmp_path: Path) -> None:
    scenario = load_scenario("residual_clean")
    stops = scenario_stops(scenario, "training", n_waypoints=30, sub_steps=3)
    raw = quasi_static_log(scenario, stops, stream(scenario.seed, STREAM_RAW_LOG), QuasiStaticSettings())
    raw_log = RawLog(raw.t_s, raw.q_rad, raw.dq_rad_s, raw.tau_nm, source="raw")
    write_dataset(tmp_path / "train.raw.csv", raw_log)
    write_dataset(tmp_path / "validate.csv", as_dataset(generate_stationary(scenario, "validation")))
    out = tmp_path / "out"
    code = main(
        [
            "residual",
            "--train",
            str(tmp_path / "train.raw.csv"),
            "--validate",
            str(tmp_path / "validate.csv"),
            "--out",
            str(out),
        ]
    )
    assert code == 0
    assert json.loads((out / "summary.json").read_text())["effects"] == []


# --- bad input: one clear line, exit code 2, nothing written ------------------------------------


def _columns(path: Path) -> dict[str, np.ndarray]:
    return dict(read_table(path).columns)


def _refused(args: list[str], out: Path, capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    assert main(["residual", *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    for needle in needles:
        assert needle in err, err
    assert not out.exists()
    assert not list(out.parent.glob(f".{out.name}.*"))


def test_validation_without_dir_while_training_has_it(
    files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    validate = tmp_path / "validate_no_dir.csv"
    write_table(validate, {k: v for k, v in _columns(files[1]).items() if not k.startswith("dir")})
    _refused(
        ["--train", str(files[0]), "--validate", str(validate)],
        tmp_path / "out",
        capsys,
        str(validate),
        "dir1..dir4",
        "same columns",
    )


def test_files_of_another_robot(files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    validate = tmp_path / "five_joints.csv"
    columns = _columns(files[1])
    columns["q5"], columns["tau5"] = columns["q4"], columns["tau4"]
    write_table(validate, columns)
    _refused(
        ["--train", str(files[0]), "--validate", str(validate)], tmp_path / "out", capsys, str(validate), "q5", "tau5"
    )


def test_validation_file_too_small(
    files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    validate = tmp_path / "tiny.csv"
    write_table(validate, {k: v[:12] for k, v in _columns(files[1]).items()})
    _refused(
        ["--train", str(files[0]), "--validate", str(validate)],
        tmp_path / "out",
        capsys,
        str(validate),
        "12 validation points",
        "at least 20",
    )


def test_direction_effect_asked_without_dir(
    files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    stripped = []
    for name, source in (("train.csv", files[0]), ("validate.csv", files[1])):
        target = tmp_path / name
        write_table(target, {k: v for k, v in _columns(source).items() if not k.startswith("dir")})
        stripped.append(target)
    args = ["--train", str(stripped[0]), "--validate", str(stripped[1]), "--effects", "gravity_tilt,direction_offset"]
    _refused(args, tmp_path / "out", capsys, str(stripped[0]), "direction_offset", "dir1..dir4")


def test_without_dir_the_other_families_still_run(files: tuple[Path, Path], tmp_path: Path) -> None:
    stripped = []
    for name, source in (("train.csv", files[0]), ("validate.csv", files[1])):
        target = tmp_path / name
        write_table(target, {k: v for k, v in _columns(source).items() if not k.startswith("dir")})
        stripped.append(target)
    out = tmp_path / "out"
    assert main(["residual", "--train", str(stripped[0]), "--validate", str(stripped[1]), "--out", str(out)]) == 0
    diagnosis = json.loads((out / "diagnosis.json").read_text())
    assert any("direction_offset: not tested" in n for n in diagnosis["notes"])
    # the direction error is still in the data, unexplained by any configuration effect
    assert json.loads((out / "summary.json").read_text())["unexplained"] is True


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--effects", "gravity_tilt,magic"], "unknown effect family 'magic'"),
        (["--effects", "gravity_tilt,gravity_tilt"], "named twice"),
        (["--base", "penn"], "--base penn"),
        (["--base", "plf", "--dummy-arm"], "--dummy-arm: the base model plf takes no Dummy Arm"),
        (["--dummy-arm"], "only --base ap does"),  # the default base, plf+
    ],
)
def test_bad_options(
    files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], needle: str
) -> None:
    _refused(["--train", str(files[0]), "--validate", str(files[1]), *extra], tmp_path / "out", capsys, needle)


def test_a_failed_run_leaves_an_earlier_report_untouched(
    files: tuple[Path, Path], run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "kept"
    shutil.copytree(run, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    tiny = tmp_path / "tiny.csv"
    write_table(tiny, {k: v[:5] for k, v in _columns(files[1]).items()})
    assert main(["residual", "--train", str(files[0]), "--validate", str(tiny), "--out", str(out)]) == 2
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.slow
def test_identical_inputs_give_identical_summaries(files: tuple[Path, Path], run: Path, tmp_path: Path) -> None:
    out = tmp_path / "again"
    assert main(["residual", "--train", str(files[0]), "--validate", str(files[1]), "--out", str(out)]) == 0
    assert (out / "summary.json").read_text() == (run / "summary.json").read_text()


def test_dataset_type_is_what_the_loader_gives(files: tuple[Path, Path]) -> None:
    from daror_runtime.residual.data import load_pair

    pair = load_pair(*files)
    assert isinstance(pair.train, StationaryDataset)
    assert pair.has_direction
    assert pair.train.t_s is not None


def test_fit_augmented_diagnoses_the_training_data_alone(files: tuple[Path, Path], tmp_path: Path) -> None:
    out = tmp_path / "augmented.json"
    assert main(["fit", "augmented", "--train", str(files[0]), "--out", str(out)]) == 0
    model, contents = load_model(out)
    assert contents.kind == "augmented"
    assert contents.parameters["effects"] == ["direction_offset (joint 2)"]
    assert contents.parameters["direction_offset_nm"][1] == pytest.approx(0.6, abs=0.01)
    assert contents.fit["training"]["rmse"] < 0.03
    assert model.torque(np.zeros(4)).shape == (4,)


def test_raw_names_at_most_two_logs_and_only_raw_logs(
    files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--raw TRAIN [VALIDATE]``: a third file, a stationary dataset, or another run's log: one line, exit 2."""
    args = ["--train", str(files[0]), "--validate", str(files[1])]
    _refused([*args, "--raw", str(files[0]), str(files[1]), str(files[1])], tmp_path / "a", capsys, "--raw: 3 files")
    _refused([*args, "--raw", str(files[1])], tmp_path / "b", capsys, str(files[1]), "expected the raw log")
    t = np.arange(0.0, 1.0, 0.001)
    q = np.zeros((len(t), 4))
    other = tmp_path / "other.raw.npz"
    write_dataset(other, RawLog(t, q, np.zeros_like(q), np.zeros_like(q)))  # one second: not this run's
    _refused([*args, "--raw", str(other)], tmp_path / "c", capsys, str(other), "outside this raw log")


@pytest.mark.slow
def test_a_raw_log_given_as_training_data_is_the_hysteresis_path(tmp_path: Path) -> None:
    """``--train`` a raw log: its own samples are the joints' path when the direction error is weighed."""
    scenario = load_scenario("residual_direction_offset")
    stops = scenario_stops(scenario, "training", n_waypoints=12, sub_steps=2)
    settings = QuasiStaticSettings(dwell_s=0.3)  # short stops: few points, a fast analysis
    raw = quasi_static_log(scenario, stops, stream(scenario.seed, STREAM_RAW_LOG), settings)
    train = tmp_path / "train_log.npz"  # no NAME.raw.* beside it: the file itself is the raw log
    write_dataset(train, RawLog(raw.t_s, raw.q_rad, raw.dq_rad_s, raw.tau_nm))
    validate = tmp_path / "validate.csv"
    write_dataset(validate, as_dataset(generate_stationary(scenario, "validation")))
    out = tmp_path / "out"
    assert main(["residual", "--train", str(train), "--validate", str(validate), "--out", str(out)]) == 0
    evidence = json.loads((out / "diagnosis.json").read_text())
    assert evidence["train"]["source"] == str(train)
    assert evidence["direction_signal"]["path"] == "raw log"
    assert ("direction_offset", 2) in [(f["effect"], f["joint"]) for f in evidence["found"]]
