"""The data-efficiency study of thesis Sec. 5.3.1 (Fig. 5.4): numbers, rules, files and the CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.cli import main
from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DataError, UnknownModelKindError, UsageError
from daror_runtime.models.linear import fit_plf_plus
from daror_runtime.models.metrics import error_metrics
from daror_runtime.studies import data_efficiency_report as report
from daror_runtime.studies.data_efficiency import (
    DataEfficiencyResult,
    SizeResult,
    check_kind,
    default_sizes,
    enough_points,
    minimum_identifiable_size,
    parse_sizes,
    run_data_efficiency,
)
from hal.robot import RobotDescription

Datasets = tuple[StationaryDataset, StationaryDataset]

#: Draws per size in these tests: enough for a stable mean and spread, few enough to stay fast.
#: Slow tier as a whole (docs/testing.md): the module's study takes ~8 s before the first test.
pytestmark = pytest.mark.slow

DRAWS = 16
SIZE_KEYS = {
    "n", "fitted", "refused", "rmse_mean", "rmse_std", "rmse_min", "rmse_p5",
    "rmse_median", "rmse_p95", "rmse_max", "nrmse_mean",
}  # fmt: skip
TOP_KEYS = {"kind", "train", "validate", "draws", "seed", "full_data_rmse", "sizes", "enough_points"}


@pytest.fixture(scope="module")
def study(dataset_b: Datasets, description: RobotDescription) -> DataEfficiencyResult:
    """PLF+ on dataset B with the default ladder (the command's default run, fewer draws)."""
    train, validation = dataset_b
    return run_data_efficiency(train, validation, description, draws=DRAWS, seed=0)


# --- the numbers --------------------------------------------------------------------------


def test_full_data_rmse_is_the_plain_plf_plus_fit(
    study: DataEfficiencyResult, dataset_b: Datasets, description: RobotDescription
) -> None:
    train, validation = dataset_b
    model = fit_plf_plus(train, description).model
    expected = error_metrics(validation.tau_nm, model.torque_batch(validation.q_rad))
    assert study.full_data_rmse == pytest.approx(expected.rmse_nm, rel=1e-12)
    assert study.full_data.nrmse == pytest.approx(expected.nrmse, rel=1e-12)
    # dataset B's PLF+ sits near 0.42 Nm (docs/data_efficiency.md); a gross change is a regression
    assert 0.3 < study.full_data_rmse < 0.6


def test_default_ladder_spans_smallest_identifiable_size_to_all_points(
    study: DataEfficiencyResult, dataset_b: Datasets
) -> None:
    n = [s.n for s in study.sizes]
    assert study.rank == 14  # PLF+: 8 gravity combinations + 6 elbow polynomial coefficients
    assert n[0] == 7  # ceil(2 * 14 / 4): as many spare equations as unknowns
    assert n[-1] == len(dataset_b[0]) == study.train_points
    assert n == sorted(set(n))
    assert 15 <= len(n) <= 20
    ratios = np.diff(np.log(n))
    assert np.ptp(ratios[3:]) < 0.1  # geometric once rounding no longer matters


def test_every_draw_is_fitted_or_refused(study: DataEfficiencyResult) -> None:
    for s in study.sizes:
        assert s.fitted + s.refused == DRAWS
    # from a few times the minimum on, random subsets always identify PLF+
    assert all(s.refused == 0 for s in study.sizes if s.n >= 20)


def test_largest_sizes_reach_the_full_data_rmse(study: DataEfficiencyResult) -> None:
    full = study.full_data_rmse
    largest = study.sizes[-1]
    assert largest.rmse_mean == pytest.approx(full, rel=1e-9)  # n = N: every draw is the whole set
    assert largest.rmse_std == pytest.approx(0.0, abs=1e-9)
    for s in study.sizes:
        if s.n >= study.train_points // 2:
            assert s.rmse_mean == pytest.approx(full, rel=0.02), s


def test_error_and_spread_shrink_as_n_grows(study: DataEfficiencyResult) -> None:
    """Fig. 5.4: the mean and the spread fall with n.

    Compares sizes far apart: neighbouring sizes differ by less than the noise of 16 draws.
    """
    by_n = {s.n: s for s in study.sizes}
    n = sorted(by_n)
    small, middle, large = by_n[n[0]], by_n[n[len(n) // 2]], by_n[n[-2]]
    assert small.rmse_mean > 5 * large.rmse_mean
    # the spread falls by orders of magnitude from the smallest size, then still severalfold
    assert small.rmse_std > 100 * middle.rmse_std
    assert middle.rmse_std > 2 * large.rmse_std
    assert small.rmse_p95 - small.rmse_p5 > middle.rmse_p95 - middle.rmse_p5 > large.rmse_p95 - large.rmse_p5
    # trend over the whole ladder: each third's mean RMSE below the previous third's
    means = np.array([by_n[k].rmse_mean for k in n])
    thirds = [float(np.mean(part)) for part in np.array_split(means, 3)]
    assert thirds[0] > thirds[1] > thirds[2]
    # the statistics are ordered as their names say
    for s in study.sizes:
        assert s.rmse_min <= s.rmse_p5 <= s.rmse_median <= s.rmse_p95 <= s.rmse_max
        assert s.rmse_min <= s.rmse_mean <= s.rmse_max


def test_enough_points_follows_the_documented_rule(study: DataEfficiencyResult) -> None:
    limit = 1.05 * study.full_data_rmse
    assert study.enough_points is not None
    tail = [s for s in study.sizes if s.n >= study.enough_points]
    assert all(s.rmse_mean <= limit for s in tail)
    before = [s for s in study.sizes if s.n < study.enough_points]
    assert before
    assert before[-1].rmse_mean > limit
    assert 20 <= study.enough_points <= 300  # dataset B: tens of points, far below N = 1313


def test_enough_points_ignores_a_lucky_dip() -> None:
    def size(n: int, mean: float | None) -> SizeResult:
        if mean is None:
            return SizeResult.from_draws(n, 5, [], [])
        return SizeResult.from_draws(n, 0, [mean], [0.1])

    full = 1.0
    dip = [size(10, 1.02), size(20, 1.2), size(40, 1.04), size(80, 1.0)]
    assert enough_points(dip, full, 0.05) == 40
    assert enough_points([size(10, 0.9), size(20, 1.049)], full, 0.05) == 10  # below full counts as within
    assert enough_points([size(10, 1.0), size(20, None), size(40, 1.0)], full, 0.05) == 40
    assert enough_points([size(10, 1.0), size(20, 1.06)], full, 0.05) is None


def test_deterministic_for_a_seed_and_each_size_has_its_own_stream(
    dataset_b: Datasets, description: RobotDescription
) -> None:
    train, validation = dataset_b
    first = run_data_efficiency(train, validation, description, sizes=[10, 40], draws=8, seed=3)
    again = run_data_efficiency(train, validation, description, sizes=[40, 10], draws=8, seed=3)
    alone = run_data_efficiency(train, validation, description, sizes=[40], draws=8, seed=3)
    other = run_data_efficiency(train, validation, description, sizes=[10, 40], draws=8, seed=4)
    assert first.to_dict() == again.to_dict()
    assert alone.sizes[0] == first.sizes[1]  # size 40 draws the same subsets with or without size 10
    assert other.sizes[1].rmse_mean != first.sizes[1].rmse_mean


def test_unidentifiable_sizes_are_counted_not_fatal(dataset_b: Datasets, description: RobotDescription) -> None:
    train, validation = dataset_b
    result = run_data_efficiency(train, validation, description, sizes=[1, 6, 7], draws=5)
    one, six, seven = result.sizes
    for s in (one, six):
        assert (s.fitted, s.refused) == (0, 5)
        assert s.rmse_mean is None
        assert s.rmse_std is None
        assert s.nrmse_mean is None
    assert seven.fitted + seven.refused == 5
    assert seven.fitted > 0
    json.dumps(result.to_dict(), allow_nan=False)  # None, never NaN, in the document


def test_plf_starts_at_its_own_minimum(dataset_b: Datasets, description: RobotDescription) -> None:
    train, validation = dataset_b
    result = run_data_efficiency(train, validation, description, kind="plf", sizes=None, draws=2)
    assert result.rank == 8
    assert result.sizes[0].n == minimum_identifiable_size(8) == 4


# --- inputs the library refuses -------------------------------------------------------------


def test_sizes_and_kinds_are_checked() -> None:
    assert parse_sizes("10, 50,200") == [10, 50, 200]
    with pytest.raises(UsageError, match="--sizes: 'ten'"):
        parse_sizes("ten,50")
    with pytest.raises(UsageError, match="--sizes: ''"):
        parse_sizes("10,,50")
    assert check_kind("PLF+") == "plf+"
    with pytest.raises(UsageError, match="nothing to learn"):
        check_kind("ap")
    with pytest.raises(UnknownModelKindError, match="gp"):
        check_kind("gp")
    for neural in ("penn", "nnn", "penn-residual"):
        with pytest.raises(UsageError, match=f"--kind {neural}: the study refits .* 'daror hpsearch'"):
            check_kind(neural)


def test_default_sizes_is_a_geometric_ladder() -> None:
    ladder = default_sizes(7, 1313)
    assert ladder[0] == 7
    assert ladder[-1] == 1313
    assert len(ladder) == 18
    assert default_sizes(5, 5) == [5]
    with pytest.raises(UsageError):
        default_sizes(0, 10)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"draws": 0}, "--draws 0"),
        ({"seed": -1}, "--seed -1"),
        ({"sizes": [0, 10]}, "--sizes: 0 is out of range; expected sizes from 1 to 1313"),
        ({"sizes": [1314]}, "--sizes: 1314 is out of range"),
        ({"sizes": []}, "--sizes: no sizes"),
        ({"kind": "ap"}, "--kind ap"),
    ],
)
def test_bad_settings_are_refused(
    dataset_b: Datasets, description: RobotDescription, kwargs: dict[str, object], message: str
) -> None:
    train, validation = dataset_b
    with pytest.raises(UsageError, match=message.replace("+", r"\+")):
        run_data_efficiency(train, validation, description, **kwargs)  # type: ignore[arg-type]


def test_too_few_validation_points_are_refused(dataset_b: Datasets, description: RobotDescription) -> None:
    train, validation = dataset_b
    with pytest.raises(DataError, match="B-validation: 19 stationary points; expected at least 20"):
        run_data_efficiency(train, validation.subset(slice(0, 19)), description, sizes=[10], draws=1)


# --- files ------------------------------------------------------------------------------------


def test_outputs_hold_the_documented_contract(study: DataEfficiencyResult, dataset_b: Datasets, tmp_path: Path) -> None:
    out = tmp_path / "new" / "study"
    json_path, png_path, md_path = report.write_outputs(study, out)
    document = json.loads(json_path.read_text(encoding="utf-8"))
    assert set(document) >= TOP_KEYS
    assert document["kind"] == "plf+"
    assert document["train"] == {"source": "B-training", "n_points": 1313}
    assert document["validate"] == {"source": "B-validation", "n_points": len(dataset_b[1])}
    assert (document["draws"], document["seed"]) == (DRAWS, 0)
    assert document["full_data_rmse"] == study.full_data_rmse
    assert document["enough_points"] == study.enough_points
    assert len(document["sizes"]) == len(study.sizes)
    for entry, size in zip(document["sizes"], study.sizes, strict=True):
        assert set(entry) == SIZE_KEYS
        assert entry["n"] == size.n
        assert entry["rmse_mean"] == size.rmse_mean
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png_path.stat().st_size > 10_000
    markdown = md_path.read_text(encoding="utf-8")
    rows = [line for line in markdown.splitlines() if line.startswith("| ") and line[2].isdigit()]
    assert len(rows) == len(study.sizes)
    assert f"**n = {study.enough_points}**" in markdown
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in report.output_paths(out))


def test_a_rendering_failure_writes_nothing(
    study: DataEfficiencyResult, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(result: DataEfficiencyResult, dpi: int = 120) -> bytes:
        raise RuntimeError("renderer broke")

    monkeypatch.setattr(report, "render_png", broken)
    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        report.write_outputs(study, out)
    assert not out.exists()


# --- the command ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def files(dataset_b: Datasets, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """Dataset B as CSV files, and a validation file too short to validate on."""
    folder = tmp_path_factory.mktemp("study")
    train, validation = dataset_b
    paths = folder / "B.csv", folder / "B_val.csv", folder / "short_val.csv"
    write_dataset(paths[0], train)
    write_dataset(paths[1], validation)
    write_dataset(paths[2], validation.subset(slice(0, 12)))
    return paths


def test_cli_end_to_end(files: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    train, validation, _ = files
    out = tmp_path / "study"
    argv = ["study", "data-efficiency", "--train", str(train), "--validate", str(validation)]
    code = main([*argv, "--sizes", "10,60,1313", "--draws", "6", "--seed", "2", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    document = json.loads((out / "data_efficiency.json").read_text(encoding="utf-8"))
    assert set(document) >= TOP_KEYS
    assert document["train"] == {"source": str(train), "n_points": 1313}
    assert document["validate"]["source"] == str(validation)
    assert (document["kind"], document["draws"], document["seed"]) == ("plf+", 6, 2)
    assert [s["n"] for s in document["sizes"]] == [10, 60, 1313]
    assert document["sizes"][-1]["rmse_mean"] == pytest.approx(document["full_data_rmse"], rel=1e-9)
    assert document["sizes"][0]["rmse_mean"] > document["sizes"][1]["rmse_mean"]
    assert (out / "data_efficiency.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "data_efficiency.md").is_file()
    assert "enough points" in captured.out
    assert "1313" in captured.out
    assert captured.err == ""


@pytest.mark.parametrize(
    ("extra", "names"),
    [
        (["--draws", "0"], "--draws 0"),
        (["--sizes", "0,50"], "--sizes: 0 is out of range; expected sizes from 1 to 1313"),
        (["--sizes", "50,2000"], "--sizes: 2000 is out of range"),
        (["--sizes", "10,x"], "--sizes: 'x'"),
        (["--seed", "-3"], "--seed -3"),
        (["--kind", "ap"], "--kind ap"),
        (["--kind", "gp"], "unknown model kind 'gp'"),
        (["--kind", "penn"], "--kind penn: the study refits the model"),
        (["--validate", "SHORT"], "short_val.csv: 12 stationary points; expected at least 20"),
        (["--train", "MISSING"], "missing.csv"),
    ],
)
def test_cli_bad_input_exits_2_and_writes_nothing(
    files: tuple[Path, Path, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    extra: list[str],
    names: str,
) -> None:
    train, validation, short = files
    substitutes = {"SHORT": str(short), "MISSING": str(tmp_path / "missing.csv")}
    extra = [substitutes.get(x, x) for x in extra]
    out = tmp_path / "study"
    inputs = ["--train", str(train), "--validate", str(validation)]
    argv = ["study", "data-efficiency", *inputs, "--draws", "2", "--sizes", "10", *extra, "--out", str(out)]
    code = main(argv)  # a later --option overrides the defaults above
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.rstrip("\n").split("\n")
    assert len(lines) == 1, err
    assert lines[0].startswith("daror study data-efficiency: error: ")
    assert names in lines[0]
    assert not out.exists()


def test_cli_refuses_an_out_path_that_is_a_file(
    files: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    train, validation, _ = files
    out = tmp_path / "taken"
    out.write_text("not a directory\n", encoding="utf-8")
    argv = ["study", "data-efficiency", "--train", str(train), "--validate", str(validation), "--out", str(out)]
    assert main(argv) == 2
    assert f"{out}: is a file; expected a folder" in capsys.readouterr().err
    assert out.read_text(encoding="utf-8") == "not a directory\n"


def test_nrmse_mean_is_the_mean_of_the_draws(study: DataEfficiencyResult) -> None:
    # nRMSE is RMSE normalised per joint (Eq. 4.32): it tracks the RMSE and is finite everywhere
    for s in study.sizes:
        assert s.nrmse_mean is not None
        assert math.isfinite(s.nrmse_mean)
        assert s.nrmse_mean > 0
    assert study.sizes[0].nrmse_mean > study.sizes[-1].nrmse_mean
