"""The ``daror`` command in-process: bad input is refused with exit code 2, one line on stderr
naming the file, and nothing written; the success paths write exactly the documented JSON.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.cli import main
from daror_runtime.data.load import load_dataset, load_stationary, write_dataset
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.stationary import reduce_to_stationary
from daror_runtime.models.files import load_model
from daror_runtime.models.linear import fit_plf, fit_plf_plus
from hal.robot import RobotDescription

SCENARIO = "exo_dummy_arm"


@dataclass(frozen=True)
class Files:
    """Good inputs written once by the CLI itself."""

    folder: Path
    train: Path  # dataset B, training trajectory (1,313 points)
    validation: Path  # dataset B, validation trajectory (165 points)
    small: Path  # a shorter training trajectory, with its raw log beside it
    small_raw: Path
    plf: Path  # model files fitted on ``train``
    plf_plus: Path


def run(*argv: str) -> int:
    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Files:
    folder = tmp_path_factory.mktemp("cli")
    f = Files(
        folder=folder,
        train=folder / "B.csv",
        validation=folder / "B_val.csv",
        small=folder / "S.csv",
        small_raw=folder / "S.raw.csv",
        plf=folder / "plf.json",
        plf_plus=folder / "plf_plus.json",
    )
    common = ("simulate", "static", "--scenario", SCENARIO)
    assert run(*common, "--trajectory", "training", "--out", f.train) == 0
    assert run(*common, "--trajectory", "validation", "--out", f.validation) == 0
    small = ("--waypoints", "20", "--sub-steps", "3", "--with-raw")
    assert run(*common, "--trajectory", "training", "--out", f.small, *small) == 0
    assert run("fit", "plf", "--train", f.train, "--out", f.plf) == 0
    assert run("fit", "plf+", "--train", f.train, "--out", f.plf_plus) == 0
    for path in (f.train, f.validation, f.small, f.small_raw, f.plf, f.plf_plus):
        assert path.is_file(), path
    return f


def refused(capsys: pytest.CaptureFixture[str], argv: list[object], names: str, output: Path) -> str:
    """Run ``argv``; assert exit code 2, exactly one stderr line naming ``names``, and no ``output``."""
    capsys.readouterr()
    code = run(*map(str, argv))
    err = capsys.readouterr().err
    assert code == 2, f"exit code {code}; stderr: {err!r}"
    assert err.endswith("\n")
    lines = err.rstrip("\n").split("\n")
    assert len(lines) == 1, f"stderr is not one line: {err!r}"
    line = lines[0].strip()
    assert line.startswith(f"daror {argv[0]}: error: "), line
    assert names in line, f"{names!r} not named in: {line}"
    assert not output.exists(), f"{output} was written despite the refusal"
    return line


def stationary_csv(path: Path, data: StationaryDataset) -> Path:
    write_dataset(path, data)
    return path


# --- fit: bad training data ------------------------------------------------------------------


def test_fit_missing_column(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = files.train.read_text().splitlines()
    header = lines[0].split(",")
    drop = header.index("tau3")
    text = "\n".join(",".join(c for i, c in enumerate(row.split(",")) if i != drop) for row in lines) + "\n"
    bad = tmp_path / "no_tau3.csv"
    bad.write_text(text)
    out = tmp_path / "model.json"
    line = refused(capsys, ["fit", "plf", "--train", bad, "--out", out], str(bad), out)
    assert "missing column(s) tau3" in line


def test_fit_nan(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = files.train.read_text().splitlines()
    header = lines[0].split(",")
    row = lines[9].split(",")  # the 9th data row: line 10 of the file
    row[header.index("tau2")] = "nan"
    lines[9] = ",".join(row)
    bad = tmp_path / "nan.csv"
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "model.json"
    line = refused(capsys, ["fit", "plf+", "--train", bad, "--out", out], str(bad), out)
    assert "line 10, column tau2: NaN" in line


def test_fit_empty_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "empty.csv"
    bad.write_text("")
    out = tmp_path / "model.json"
    line = refused(capsys, ["fit", "plf", "--train", bad, "--out", out], str(bad), out)
    assert "file is empty" in line


def test_fit_angles_in_degrees(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = load_stationary(files.train)
    bad = stationary_csv(
        tmp_path / "degrees.csv", StationaryDataset(np.degrees(data.q_rad), data.tau_nm, data.direction, data.t_s)
    )
    out = tmp_path / "model.json"
    line = refused(capsys, ["fit", "plf", "--train", bad, "--out", out], str(bad), out)
    assert "degrees" in line
    assert re.search(r"line \d+, column q\d", line), line


def test_fit_npy_array_named_npz(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "array.npz"
    with open(bad, "wb") as handle:
        np.save(handle, np.zeros((20, 8)))
    out = tmp_path / "model.json"
    line = refused(capsys, ["fit", "plf", "--train", bad, "--out", out], str(bad), out)
    assert "not a readable .npz archive" in line


def test_fit_missing_training_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nowhere.csv"
    out = tmp_path / "model.json"
    line = refused(capsys, ["fit", "plf", "--train", missing, "--out", out], str(missing), out)
    assert "file not found" in line


@pytest.mark.parametrize(("kind", "n_points", "rank"), [("plf+", 2, 8), ("plf", 1, 4)])
def test_fit_too_few_points_for_the_rank(
    files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str, n_points: int, rank: int
) -> None:
    """N points give 4N equations: 2 points cannot reach PLF+'s 14, 1 point cannot reach PLF's 8."""
    bad = stationary_csv(tmp_path / "few.csv", load_stationary(files.train).subset(slice(0, n_points)))
    out = tmp_path / "model.json"
    line = refused(capsys, ["fit", kind, "--train", bad, "--out", out], str(bad), out)
    expected = 14 if kind == "plf+" else 8
    assert f"{n_points} stationary points identify only {rank} of the {expected}" in line


def test_fit_plf_refuses_two_points(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = stationary_csv(tmp_path / "two.csv", load_stationary(files.train).subset(slice(0, 2)))
    out = tmp_path / "model.json"
    refused(capsys, ["fit", "plf", "--train", bad, "--out", out], str(bad), out)


def test_fit_plf_plus_with_three_elbow_angles(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """30 points, q4 in {0.5, 1.0, 1.5}: the gravity part (8) plus 3 of the 6 elbow-polynomial terms."""
    data = load_stationary(files.train)
    pick = np.random.default_rng(0).choice(len(data), 30, replace=False)
    subset = data.subset(pick)
    q = subset.q_rad.copy()
    q[:, 3] = np.array([0.5, 1.0, 1.5])[np.arange(30) % 3]
    bad = stationary_csv(tmp_path / "elbow3.csv", StationaryDataset(q, subset.tau_nm, subset.direction, subset.t_s))
    out = tmp_path / "model.json"
    line = refused(capsys, ["fit", "plf+", "--train", bad, "--out", out], str(bad), out)
    assert "30 stationary points identify only 11 of the 14" in line
    assert "at least 6 distinct elbow angles" in line
    # the same points are enough for PLF, which has no elbow polynomial
    assert run("fit", "plf", "--train", bad, "--out", out) == 0
    assert out.is_file()


def test_fit_unknown_model_kind(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "model.json"
    line = refused(capsys, ["fit", "foo", "--train", files.train, "--out", out], "'foo'", out)
    assert "unknown model kind 'foo'; expected one of ap, plf, plf+" in line


@pytest.mark.parametrize(
    ("kind", "flags", "named"),
    [
        ("plf", ["--dummy-arm"], "model kind plf does not take --dummy-arm; its options: --name"),
        ("plf+", ["--no-elbow-stiffness"], "model kind plf+ does not take --elbow-stiffness/--no-elbow-stiffness"),
        ("augmented", ["--seed", "3"], "model kind augmented does not take --seed"),
        ("ap", ["--seed", "3"], "model kind ap does not take --seed; its options: --name, --dummy-arm"),
    ],
)
def test_fit_refuses_an_option_the_kind_does_not_take(
    files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str, flags: list[str], named: str
) -> None:
    """Issue 11: each kind has its own options; one it does not take is refused, not ignored."""
    out = tmp_path / "model.json"
    refused(capsys, ["fit", kind, "--train", files.train, "--out", out, *flags], named, out)


def test_fit_passes_the_options_the_kind_takes(files: Files, tmp_path: Path) -> None:
    out = tmp_path / "ap.json"
    assert run("fit", "ap", "--dummy-arm", "--no-elbow-stiffness", "--name", "AP0", "--out", out) == 0
    model, contents = load_model(out)
    assert (model.name, contents.parameters["includes_dummy_arm"]) == ("AP0", True)
    assert contents.parameters["includes_elbow_stiffness"] is False
    assert run("fit", "plf", "--name", "mine", "--train", files.train, "--out", tmp_path / "plf.json") == 0
    assert load_model(tmp_path / "plf.json")[0].name == "mine"


def test_fit_refuses_to_overwrite_its_training_file(
    files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    train = tmp_path / "B.csv"
    train.write_bytes(files.train.read_bytes())
    before = train.read_bytes()
    capsys.readouterr()
    code = run("fit", "plf", "--train", train, "--out", train)
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1
    assert str(train) in err
    assert "refusing to overwrite an input file" in err
    assert train.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["B.csv"]


def test_fit_refuses_to_overwrite_its_training_file_by_another_spelling(
    files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    train = tmp_path / "B.csv"
    train.write_bytes(files.train.read_bytes())
    before = train.read_bytes()
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path / "sub")
    capsys.readouterr()
    assert run("fit", "plf", "--train", str(train), "--out", "../B.csv") == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert train.read_bytes() == before


# --- evaluate: bad model files -----------------------------------------------------------------


def test_evaluate_truncated_model_file(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = files.plf.read_text()
    bad = tmp_path / "truncated.json"
    bad.write_text(text[: len(text) // 2])
    out = tmp_path / "errors.json"
    line = refused(capsys, ["evaluate", bad, "--data", files.validation, "--json", out], str(bad), out)
    assert "not valid JSON" in line
    assert "corrupted" in line


def test_evaluate_altered_parameter(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    document = json.loads(files.plf.read_text())
    document["parameters"]["theta"][4] += 0.001  # one number changed, checksum left as written
    bad = tmp_path / "altered.json"
    bad.write_text(json.dumps(document, indent=2))
    out = tmp_path / "errors.json"
    line = refused(capsys, ["evaluate", bad, "--data", files.validation, "--json", out], str(bad), out)
    assert "checksum mismatch" in line


def test_evaluate_altered_number_in_the_text(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A hand edit of one digit in the file (not a re-serialisation) is caught too."""
    document = json.loads(files.plf.read_text())
    value = document["parameters"]["theta"][2]
    text = files.plf.read_text()
    assert text.count(repr(value)) == 1
    bad = tmp_path / "edited.json"
    bad.write_text(text.replace(repr(value), repr(value + 1.0)))
    out = tmp_path / "errors.json"
    assert "checksum mismatch" in refused(
        capsys, ["evaluate", bad, "--data", files.validation, "--json", out], str(bad), out
    )


def test_evaluate_bad_data_file(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "val.csv"
    bad.write_text("q1,q2,q3,q4,tau1,tau2,tau3,tau4\n")
    out = tmp_path / "errors.json"
    line = refused(capsys, ["evaluate", files.plf, "--data", bad, "--json", out], str(bad), out)
    assert "no data rows" in line


def test_evaluate_refuses_to_overwrite_its_data(
    files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "val.csv"
    data.write_bytes(files.validation.read_bytes())
    before = data.read_bytes()
    capsys.readouterr()
    assert run("evaluate", files.plf, "--data", data, "--json", data) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert str(data) in err
    assert data.read_bytes() == before


def test_cvf_truncated_model_file(files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "truncated.json"
    bad.write_text(files.plf_plus.read_text()[:100])
    out = tmp_path / "cvf.json"
    assert "not valid JSON" in refused(capsys, ["cvf", bad, "--json", out], str(bad), out)


# --- success paths -----------------------------------------------------------------------------


def _is_number(value: object) -> bool:
    return isinstance(value, float) and math.isfinite(value)


def test_fit_then_evaluate_writes_the_documented_json(
    files: Files, tmp_path: Path, capsys: pytest.CaptureFixture[str], description: RobotDescription
) -> None:
    model_path = tmp_path / "model.json"
    out = tmp_path / "out.json"
    assert run("fit", "plf", "--train", files.train, "--out", model_path) == 0
    capsys.readouterr()
    assert run("evaluate", model_path, "--data", files.validation, "--json", out) == 0
    assert capsys.readouterr().err == ""
    document = json.loads(out.read_text())
    assert set(document) == {"models"}
    assert len(document["models"]) == 1
    entry = document["models"][0]
    assert set(entry) == {"name", "kind", "rmse", "nrmse", "rmse_per_joint", "training_range"}
    assert entry["name"] == "PLF"
    assert entry["kind"] == "plf"
    assert _is_number(entry["rmse"])
    assert _is_number(entry["nrmse"])
    assert len(entry["rmse_per_joint"]) == 4
    assert all(_is_number(v) for v in entry["rmse_per_joint"])
    # the numbers, recomputed here from Eq. 4.31-4.32 with the model fitted in memory
    model = fit_plf(load_stationary(files.train), description).model
    validation = load_stationary(files.validation)
    error = validation.tau_nm - model.torque_batch(validation.q_rad)
    np.testing.assert_allclose(entry["rmse"], np.sqrt(np.mean(error**2)), rtol=1e-12)
    np.testing.assert_allclose(entry["rmse_per_joint"], np.sqrt(np.mean(error**2, axis=0)), rtol=1e-12)
    peak = np.abs(validation.tau_nm).max(axis=0)
    np.testing.assert_allclose(entry["nrmse"], np.sqrt(np.sum((error / peak) ** 2) / len(validation)), rtol=1e-12)
    assert entry["rmse"] ** 2 == pytest.approx(np.mean(np.square(entry["rmse_per_joint"])), rel=1e-12)
    assert 0.3 < entry["rmse"] < 3.0  # dataset B: the thesis reports 1.24 Nm for PLF
    # issue 24: the points outside the training data's range (beyond 1e-3 rad), and the RMSE on each side
    q_train = load_stationary(files.train).q_rad
    low, high = q_train.min(axis=0), q_train.max(axis=0)
    outside = ((validation.q_rad < low - 1e-3) | (validation.q_rad > high + 1e-3)).any(axis=1)
    extrapolated = entry["training_range"]
    assert extrapolated["points"] == len(validation)
    assert extrapolated["outside"] == int(outside.sum())
    assert extrapolated["q_min"] == low.tolist()
    assert extrapolated["q_max"] == high.tolist()
    for side, points in (("rmse_inside", ~outside), ("rmse_outside", outside)):
        expected = np.sqrt(np.mean(error[points] ** 2)) if points.any() else None
        assert extrapolated[side] == (None if expected is None else pytest.approx(expected, rel=1e-12)), side


def test_evaluate_two_models_keeps_their_order(files: Files, tmp_path: Path) -> None:
    out = tmp_path / "out.json"
    assert run("evaluate", files.plf, files.plf_plus, "--data", files.validation, "--json", out) == 0
    models = json.loads(out.read_text())["models"]
    assert [m["kind"] for m in models] == ["plf", "plf+"]
    assert [m["name"] for m in models] == ["PLF", "PLF+"]
    assert models[1]["rmse"] < models[0]["rmse"]  # the elbow polynomial pays off on dataset B (Table III)


@pytest.mark.parametrize("which", ["plf", "plf_plus"])
def test_cvf_writes_the_documented_json(files: Files, tmp_path: Path, which: str) -> None:
    out = tmp_path / "c.json"
    assert run("cvf", getattr(files, which), "--json", out) == 0
    document = json.loads(out.read_text())
    assert set(document) == {"models"}
    assert len(document["models"]) == 1
    entry = document["models"][0]
    assert set(entry) == {"name", "kind", "steps", "conservative"}
    assert entry["kind"] == {"plf": "plf", "plf_plus": "plf+"}[which]
    assert entry["conservative"] is True
    assert len(entry["steps"]) == 3
    for step in entry["steps"]:
        assert set(step) == {"dq", "dV"}
        assert _is_number(step["dq"])
        assert _is_number(step["dV"])
    assert [s["dq"] for s in entry["steps"]] == pytest.approx([np.pi / 400, np.pi / 4000, np.pi / 40000], rel=1e-15)
    energies = [abs(s["dV"]) for s in entry["steps"]]
    # a conservative field: the closed-path sum shrinks with the step (first order: tenfold)
    assert energies[1] < energies[0] / 5
    assert energies[2] < energies[1] / 5


def test_evaluate_accepts_a_raw_log(files: Files, tmp_path: Path) -> None:
    raw = load_dataset(files.small_raw)
    assert isinstance(raw, RawLog)
    raw_json, stationary_json = tmp_path / "raw.json", tmp_path / "stationary.json"
    assert run("evaluate", files.plf, "--data", files.small_raw, "--json", raw_json) == 0
    assert run("evaluate", files.plf, "--data", files.small, "--json", stationary_json) == 0
    rmse_raw = json.loads(raw_json.read_text())["models"][0]["rmse"]
    rmse_stationary = json.loads(stationary_json.read_text())["models"][0]["rmse"]
    assert abs(rmse_raw - rmse_stationary) <= 0.3 * rmse_stationary
    # and it did reduce the log: far fewer points than samples, more than stops
    n_points = len(reduce_to_stationary(raw))
    assert len(load_stationary(files.small)) < n_points < 0.8 * len(raw)


def test_model_file_predicts_exactly_what_the_fitted_model_does(files: Files, description: RobotDescription) -> None:
    validation = load_stationary(files.validation)
    train = load_stationary(files.train)
    for path, fit in ((files.plf, fit_plf), (files.plf_plus, fit_plf_plus)):
        loaded, contents = load_model(path)
        in_memory = fit(train, description).model
        assert loaded.kind == in_memory.kind
        assert np.array_equal(loaded.torque_batch(validation.q_rad), in_memory.torque_batch(validation.q_rad))
        for q in validation.q_rad[:5]:
            assert np.array_equal(loaded.torque(q), in_memory.torque(q))
        assert contents.training is not None
        assert contents.training.n_points == len(train) == 1313
        assert contents.training.source == str(files.train)
        assert contents.training.has_direction is True


def test_simulate_writes_the_promised_sizes(files: Files) -> None:
    assert len(load_stationary(files.train)) == 1313
    assert len(load_stationary(files.validation)) == 165
    assert len(load_stationary(files.small)) == 153  # 20 waypoints, 3 sub-steps, there and back


@pytest.mark.parametrize(("rate", "expected"), [("0", "greater than 0"), ("20000", "less than or equal to 10000")])
def test_identify_refuses_an_impossible_loop_rate_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], rate: str, expected: str
) -> None:
    out = tmp_path / "identified.csv"
    argv = ["identify", "--scenario", "exo", "--trajectory", "validation", "--rate-hz", rate, "--out", out]
    line = refused(capsys, argv, "--rate-hz", out)
    assert expected in line
