"""``daror hpsearch`` (issue 13, item 4; thesis Sec. 4.2.5, Tables I and II): the grid, the schedule,
the executors giving the same numbers, the files, the refusals, and no worker outliving the command.

Every search here runs a tiny grid (two shapes, PENN and NNN 2 x 10 sigmoid, two lambdas, two
seeds: 8 networks of 50 loss evaluations) with the thesis's loss, on which lambda 0.1 makes the PENN
collapse within those 50 evaluations, as the thesis's network does (docs/hpsearch.md).
"""

from __future__ import annotations

import csv
import errno
import itertools
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from daror_runtime.bench import machine
from daror_runtime.cli import build_parser, main
from daror_runtime.data.load import load_stationary, write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DarorError
from daror_runtime.models.files import load_model
from daror_runtime.neural.hpsearch import report
from daror_runtime.neural.hpsearch.grid import (
    BUILTIN_GRIDS,
    SEARCH_TRAINING,
    GridFileError,
    SearchGrid,
    grid_from_argument,
    load_grid,
)
from daror_runtime.neural.hpsearch.report import OUTPUT_NAMES, REPORT_NAMES, networks_csv
from daror_runtime.neural.hpsearch.search import SearchRun, run_search, schedule, work_units
from daror_runtime.neural.hpsearch.winner import fit_arguments, fit_options
from daror_runtime.neural.hpsearch.work import NetworkRow
from daror_runtime.neural.training import TrainingSettings

#: A search trains networks (JAX) in worker processes: left out of `make check`.
pytestmark = pytest.mark.slow

TINY_GRID = """\
name: tiny
models: [penn, nnn]
layers: [2]
widths: [10]
activations: [sigmoid]
inputs: [sincos]
l1: [1.0e-5, 0.1]
seeds: [0, 1]
training: {loss: thesis, adam_steps: 10, lbfgs_steps: 40, final_fit: false}
"""
#: Units of several seconds each (300 loss evaluations of an 8 x 25 PENN), for the tests that stop a
#: search while its workers train.
LONG_GRID = """\
name: long
models: [penn]
layers: [8]
widths: [25]
activations: [tanh, sigmoid, relu]
inputs: [sincos, q]
l1: [1.0e-5]
seeds: [0]
training: {final_fit: false}
"""
#: networks.csv's columns that are measured times, not results (they differ from run to run).
TIMING = {"group_wall_s", "group_cpu_s", "group_compile_s"}
#: Runs the command line as ``daror`` does, in a fresh interpreter.
CLI = "import sys\nfrom daror_runtime.cli import main\nraise SystemExit(main(sys.argv[1:]))\n"


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory, dataset_b: tuple[StationaryDataset, StationaryDataset]) -> Path:
    """Dataset B's training set as a CSV, the tiny grid, a compilation cache shared by the searches."""
    path = tmp_path_factory.mktemp("hpsearch")
    write_dataset(path / "B-train.csv", dataset_b[0])
    (path / "tiny.yaml").write_text(TINY_GRID)
    (path / "long.yaml").write_text(LONG_GRID)
    (path / "cache").mkdir()
    return path


def _argv(folder: Path, out: Path, *extra: str) -> list[str]:
    return [
        "hpsearch",
        "--train", str(folder / "B-train.csv"),
        "--out", str(out),
        "--grid", str(folder / "tiny.yaml"),
        "--cache-dir", str(folder / "cache"),
        *extra,
    ]  # fmt: skip


@pytest.fixture(scope="module")
def searched(folder: Path) -> Path:
    """The tiny search by ``daror hpsearch`` with two local worker processes: its output folder."""
    out = folder / "local2"
    assert main(_argv(folder, out, "--workers", "2")) == 0
    return out


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


def _results(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """The rows without the timing columns, as text: equal only if every digit is."""
    return [{k: v for k, v in row.items() if k not in TIMING} for row in rows]


def _snapshot(path: Path) -> dict[str, tuple[bytes, int]]:
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(path.iterdir())}


# --- the grid ------------------------------------------------------------------------------------


def test_thesis_grid_is_the_thesis_axes() -> None:
    grid = BUILTIN_GRIDS["thesis"]
    assert grid.models == ("penn", "nnn")
    assert grid.layers == (1, 2, 8, 21)
    assert grid.widths == (5, 10, 25)
    assert grid.activations == ("tanh", "relu", "sigmoid")
    assert grid.inputs == ("q", "sincos")
    assert grid.l1 == (1e-5, 1e-3, 1e-1)
    assert grid.seeds == (0, 1)
    assert len(grid.shapes()) == 144
    assert len(set(grid.shapes())) == 144
    assert grid.n_networks == 864
    assert grid.describe().startswith("thesis: 144 shapes, 864 networks (models penn, nnn; layers 1, 2, 8, 21;")
    # trained as docs/hpsearch.md says: Adam 100 + L-BFGS 200, 4 blocks, the last held out, no final fit
    assert grid.training == SEARCH_TRAINING
    s = grid.training
    assert (s.loss, s.adam_steps, s.lbfgs_steps, s.folds, s.held_out(), s.final_fit) == (
        "scaled", 100, 200, 4, (3,), False
    )  # fmt: skip
    assert grid.with_loss("thesis").training.loss == "thesis"
    assert grid.with_loss(None) is grid
    units = work_units(grid)
    assert [u.spec for u in units] == grid.shapes()
    assert {u.n_networks for u in units} == {6}
    assert sum(u.n_networks for u in units) == 864


def test_grid_file_and_grid_argument(folder: Path) -> None:
    grid = load_grid(folder / "tiny.yaml")
    assert grid.name == "tiny"
    assert grid.n_networks == 8
    assert grid.training == TrainingSettings(loss="thesis", adam_steps=10, lbfgs_steps=40, final_fit=False)
    assert grid_from_argument(str(folder / "tiny.yaml")) == grid
    assert grid_from_argument("small") is BUILTIN_GRIDS["small"]
    assert BUILTIN_GRIDS["small"].n_networks == 64
    nameless = folder / "nameless.yaml"
    nameless.write_text(TINY_GRID.replace("name: tiny\n", ""))
    assert load_grid(nameless).name == "nameless"  # the file's stem


_GOOD = {
    "models": "[penn]",
    "layers": "[1]",
    "widths": "[5]",
    "activations": "[tanh]",
    "inputs": "[q]",
    "l1": "[0.1]",
    "seeds": "[0]",
}


def _grid_text(**changes: str | None) -> str:
    fields = {**_GOOD, **changes}
    return "".join(f"{k}: {v}\n" for k, v in fields.items() if v is not None)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (_grid_text(layers='["2"]'), "line 2, field layers.0: Input should be a valid integer; got the text '2'"),
        (_grid_text(layers="[true]"), "line 2, field layers.0: Input should be a valid integer"),
        (_grid_text(layers="[0]"), "line 2, field layers.0: Input should be greater than or equal to 1"),
        (_grid_text(widths="[10, 5, 10]"), "line 3, field widths: 10 given twice; expected each value once"),
        (_grid_text(seeds="[]"), "line 7, field seeds: no value; expected at least one"),
        (_grid_text(activations="[swish]"), "line 4, field activations.0: Input should be 'tanh', 'sigmoid'"),
        (_grid_text(inputs="[sin]"), "line 5, field inputs.0: Input should be 'q' or 'sincos'"),
        (_grid_text(l1="[-0.1]"), "line 6, field l1.0: Input should be greater than or equal to 0"),
        (_grid_text(seeds="[-1]"), "line 7, field seeds.0: Input should be greater than or equal to 0"),
        (_grid_text(models=None), "field models: Field required"),
        (_grid_text() + "colour: red\n", "line 8, field colour: Extra inputs are not permitted"),
        (_grid_text() + "training: {epochs: 3}\n", "line 8, field training.epochs: Extra inputs are not permitted"),
        (
            _grid_text() + "training: {adam_steps: 0, lbfgs_steps: 0}\n",
            "line 8, field training: Value error, no training step",
        ),
        (_grid_text(layers="[32]", widths="[256]"), "field widths: "),  # 2 million weights: no network
        ("- 1\n- 2\n", "line 1: expected a YAML mapping"),
        ("models: [penn\n", "nameless.yaml"),  # not YAML
    ],
)
def test_bad_grid_files_are_refused_in_one_line_naming_the_field(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "nameless.yaml"
    path.write_text(text)
    with pytest.raises(GridFileError) as caught:
        load_grid(path)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(str(path))
    assert expected in message
    assert message.count(str(path)) == 1  # one problem, one message (no echo of a follow-up error)


def test_bad_grid_on_the_command_line_exits_2_in_one_line(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = folder / "bad.yaml"
    bad.write_text(_grid_text(widths="[5, 5]"))
    out = folder / "not_written"
    argv = _argv(folder, out)
    for grid, expected in ((str(bad), "field widths: 5 given twice"), ("thesys", "--grid thesys: expected thesis")):
        argv[argv.index("--grid") + 1] = grid
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1
        assert expected in err
    assert not out.exists()


def test_a_repeated_value_is_refused_in_code_too() -> None:
    with pytest.raises(ValueError, match="1e-05 given twice"):
        SearchGrid(name="x", models=("penn",), layers=(1,), widths=(5,), activations=("tanh",), inputs=("q",),
                   l1=(1e-5, 1e-5), seeds=(0,))  # fmt: skip


# --- the schedule --------------------------------------------------------------------------------


def test_schedule_starts_with_the_most_expensive_units() -> None:
    units = work_units(BUILTIN_GRIDS["thesis"])
    order = schedule(units)
    assert sorted(u.index for u in order) == list(range(144))  # every unit, once
    costs = [u.cost() for u in order]
    assert costs == sorted(costs, reverse=True)
    for a, b in itertools.pairwise(order):  # ties in the grid's order
        if a.cost() == b.cost():
            assert a.index < b.index
    assert {(u.spec.model, u.spec.layers, u.spec.width) for u in order[:6]} == {("penn", 21, 25)}
    assert {(u.spec.model, u.spec.layers, u.spec.width) for u in order[-6:]} == {("nnn", 1, 5)}
    by_shape = {(u.spec.model, u.spec.layers, u.spec.width, u.spec.activation, u.spec.inputs): u for u in units}
    for layers in (1, 2, 8, 21):
        for width in (5, 10, 25):
            penn, nnn = by_shape[("penn", layers, width, "tanh", "q")], by_shape[("nnn", layers, width, "tanh", "q")]
            assert penn.cost() > nnn.cost()  # a PENN's torque is a gradient: its training costs more
    cost = {(m, n, w): by_shape[(m, n, w, "tanh", "q")].cost() for m, n, w, _, _ in by_shape}
    assert cost[("penn", 21, 25)] > cost[("penn", 8, 25)] > cost[("penn", 2, 25)] > cost[("penn", 1, 25)]
    assert cost[("nnn", 8, 25)] > cost[("nnn", 8, 10)] > cost[("nnn", 8, 5)]


# --- the search, end to end ----------------------------------------------------------------------


def test_the_command_writes_the_four_files(searched: Path, folder: Path) -> None:
    assert sorted(p.name for p in searched.iterdir()) == sorted(OUTPUT_NAMES)  # no temporary file left
    rows = _rows(searched / "networks.csv")
    assert len(rows) == 8
    assert [(r["model"], r["l1"], r["seed"]) for r in rows] == [
        (m, lam, s) for m in ("penn", "nnn") for lam in ("1e-05", "0.1") for s in ("0", "1")
    ]
    assert {(r["layers"], r["width"], r["activation"], r["inputs"]) for r in rows} == {("2", "10", "sigmoid", "sincos")}
    for r in rows:
        assert 0 <= int(r["mvl_step"]) < 50
        assert float(r["mvl"]) > 0
        # the thesis's loss: MVL is the mean squared error (Nm^2), so the RMSE is its root
        assert float(r["val_rmse_nm"]) == pytest.approx(float(r["mvl"]) ** 0.5, rel=1e-9)
        assert float(r["group_wall_s"]) > 0
    ranking = _rows(searched / "ranking.csv")
    assert [(r["model"], r["rank"]) for r in ranking] == [("penn", "1"), ("penn", "2"), ("nnn", "1"), ("nnn", "2")]
    for model in ("penn", "nnn"):
        mine = [r for r in ranking if r["model"] == model]
        assert float(mine[0]["mvl"]) <= float(mine[1]["mvl"])
        for r in mine:  # the best of the two seeds
            seeds = [float(n["mvl"]) for n in rows if n["model"] == model and n["l1"] == r["l1"]]
            assert float(r["mvl"]) == min(seeds)
            assert float(r["mvl_worst_init"]) == max(seeds)
            assert r["inits"] == "2"
    summary = json.loads((searched / "summary.json").read_text())
    assert summary["networks"] == 8
    assert summary["configurations"] == 4
    assert summary["loss"] == "thesis"
    assert summary["mvl_unit"] == "Nm^2"
    assert summary["executor"] == "local"
    assert summary["workers"] == 2
    assert summary["files"] == list(OUTPUT_NAMES)
    assert summary["grid"]["name"] == "tiny"
    assert summary["data"]["points"] == len(load_stationary(folder / "B-train.csv"))
    assert summary["top"]["penn"][0]["l1"] == 1e-5


def test_lambda_0_1_collapses_the_penn_under_the_thesis_loss_and_the_report_says_so(searched: Path) -> None:
    rows = _rows(searched / "networks.csv")
    data_rms = json.loads((searched / "summary.json").read_text())["data"]["torque_rms_nm"]
    assert 3.0 < data_rms < 6.0
    for r in rows:
        torque, collapsed = float(r["torque_rms_nm"]), r["collapsed"] == "true"
        assert collapsed == (torque < 0.05 * data_rms)
        if r["l1"] == "1e-05":
            assert not collapsed
            assert torque > 0.5 * data_rms
        if r["model"] == "penn" and r["l1"] == "0.1":
            assert collapsed
            assert torque < 0.01 * data_rms  # zero torque, to a hundredth of the data's
            # a network of zero torque scores the held-out block's own RMS
            assert float(r["val_rmse_nm"]) > 0.9 * data_rms
    summary = json.loads((searched / "summary.json").read_text())
    assert summary["collapsed_configurations"]["penn"] == 1
    md = (searched / "ranking.md").read_text()
    assert "- PENN: 1 of 2 configurations collapsed (lambda 1e-05: 0 of 1, lambda 0.1: 1 of 1)" in md
    assert "at lambda 0.1 the penalty outweighs the error and drives a network to zero torque" in md


def test_ranking_md_has_tables_i_and_ii(searched: Path) -> None:
    md = (searched / "ranking.md").read_text()
    assert md.startswith("# Hyper-parameter search (thesis Sec. 4.2.5, Tables I and II)\n")
    assert "- **Loss**: **thesis** (Eq. 3.7)" in md
    assert "- **Grid**: tiny: 2 shapes, 8 networks" in md
    assert "Adam 10 steps (learning rate 0.005) then L-BFGS 40 iterations, 50 loss evaluations" in md
    assert "8 networks in " in md
    assert "executor local, 2 workers" in md
    header = "| rank | layers | width | activation | inputs | lambda | MVL (Nm^2) | validation RMSE (Nm) | seed | collapsed |"
    sections = md.split("\n## ")
    tables = {s.split("\n", 1)[0]: s for s in sections[1:]}
    assert set(tables) >= {
        "Table I: PENN, the 2 best of 2 configurations",
        "Table II: NNN, the 2 best of 2 configurations",
        "Collapsed configurations (zero torque: the network learned nothing)",
    }
    for title in ("Table I: PENN, the 2 best of 2 configurations", "Table II: NNN, the 2 best of 2 configurations"):
        lines = [line for line in tables[title].splitlines() if line.startswith("| ")]
        assert lines[0] == header
        assert [line.split(" | ")[0] for line in lines[1:]] == ["| 1", "| 2"]
        assert all(" | 2 | 10 | sigmoid | sincos | " in line for line in lines[1:])
    penn = [
        line for line in tables["Table I: PENN, the 2 best of 2 configurations"].splitlines() if line.startswith("| ")
    ]
    assert penn[1].startswith("| 1 | 2 | 10 | sigmoid | sincos | 1e-05 | ")
    assert penn[1].endswith(" | no |")
    assert penn[2].startswith("| 2 | 2 | 10 | sigmoid | sincos | 0.1 | ")
    assert penn[2].endswith(" | yes |")


@pytest.fixture(scope="module")
def one_worker(folder: Path) -> tuple[SearchRun, list[tuple[int, int, float]]]:
    """The tiny search by :func:`run_search` with one worker process, and its progress reports."""
    progress: list[tuple[int, int, float]] = []
    run = run_search(
        load_grid(folder / "tiny.yaml"),
        load_stationary(folder / "B-train.csv"),  # what the command read
        workers=1,
        cache_dir=folder / "cache",
        on_progress=lambda done, total, work: progress.append((done, total, work)),
    )
    return run, progress


def test_one_worker_gives_the_same_numbers_as_two(
    searched: Path, one_worker: tuple[SearchRun, list[tuple[int, int, float]]]
) -> None:
    run, progress = one_worker
    one = list(csv.DictReader(networks_csv(run).splitlines()))
    assert _results(one) == _results(_rows(searched / "networks.csv"))
    # after each unit: networks done, in all, and the estimated work done (the PENN's unit costs more)
    assert [p[:2] for p in progress] == [(4, 8), (8, 8)]
    assert 0.5 < progress[0][2] < progress[1][2] == 1.0
    assert run.workers == 1
    assert run.cpu_s > 0


@pytest.mark.parametrize("existing", [False, True])
def test_a_failed_write_leaves_the_folder_as_it_was(
    searched: Path,
    one_worker: tuple[SearchRun, list[tuple[int, int, float]]],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    existing: bool,
) -> None:
    """The disk full at the third file: no file of this run is there, the previous run's are untouched."""
    out = tmp_path / "out"
    if existing:
        shutil.copytree(searched, out)
        before = _snapshot(out)
    calls = []

    def fsync(fd: int) -> None:
        calls.append(fd)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(fd)

    real_fsync = os.fsync
    monkeypatch.setattr(report.os, "fsync", fsync)
    with pytest.raises(DarorError, match="writing failed \\(No space left on device\\); nothing was written"):
        report.write_outputs(one_worker[0], out, machine())
    if existing:
        assert _snapshot(out) == before  # no temporary file left either
    else:
        assert not out.exists()
    monkeypatch.undo()
    assert report.write_outputs(one_worker[0], out, machine()) == [out / name for name in REPORT_NAMES]
    # without winners only the report is written (a folder copied from the command keeps its model files)
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUT_NAMES if existing else REPORT_NAMES)


def test_ray_gives_the_same_numbers_and_force_replaces_only_our_files(
    searched: Path,
    folder: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ray = pytest.importorskip("ray", reason="the optional extra ray (make test installs it)")
    out = folder / "ray"
    shutil.copytree(searched, out)
    (out / "notes.txt").write_text("mine")
    # Ray's workers inherit this environment: a relu network fails in them (the tiny grid has none)
    for name, value in _with_sitecustomize(tmp_path, _FAILING_UNIT, DAROR_TEST_FAILING_ACTIVATION="relu").items():
        monkeypatch.setenv(name, value)
    failing = folder / "relu.yaml"
    failing.write_text(TINY_GRID.replace("[sigmoid]", "[relu]"))
    failed = folder / "ray_failed"
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)  # the test's local instance
    try:
        capsys.readouterr()  # Ray's own messages about the test's instance
        code = main(_argv(folder, out, "--executor", "ray", "--force"))
        first_err = capsys.readouterr().err
        argv = _argv(folder, failed, "--executor", "ray")
        argv[argv.index("--grid") + 1] = str(failing)
        failed_code = main(argv)
        err = capsys.readouterr().err
    finally:
        ray.shutdown()
    assert code == 0, first_err
    assert sorted(p.name for p in out.iterdir()) == sorted([*OUTPUT_NAMES, "notes.txt"])
    assert (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "summary.json").read_text())["executor"] == "ray"
    assert _results(_rows(out / "networks.csv")) == _results(_rows(searched / "networks.csv"))
    # a unit's error is reported as the local executor reports it: its own message, no Ray traceback
    assert failed_code == 1
    assert err.splitlines()[0] == "daror hpsearch: failed: injected: the relu unit failed"
    assert "Traceback" not in err
    assert not failed.exists()


# --- the winners as models (issue 24) ------------------------------------------------------------


def test_the_winners_model_files_load_and_their_fit_lines_reproduce_them(
    searched: Path, folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each model's best configuration is written as a model file, and its ``daror fit`` line (parsed by the
    command's own parser) trains the very same parameters."""
    summary = json.loads((searched / "summary.json").read_text())
    ranking = _rows(searched / "ranking.csv")
    assert list(summary["winners"]) == ["penn", "nnn"]
    for model, winner in summary["winners"].items():
        best = next(r for r in ranking if r["model"] == model and r["rank"] == "1")
        assert winner["file"] == f"best_{model}.json"
        loaded, contents = load_model(searched / winner["file"])
        assert contents.kind == model
        spec = loaded.parameters()["network"]
        assert (spec["layers"], spec["width"], spec["activation"], spec["inputs"]) == (
            int(best["layers"]), int(best["width"]), best["activation"], best["inputs"]
        )  # fmt: skip
        assert contents.training is not None
        assert contents.training.n_points == summary["data"]["points"]
        # the line, as a person would paste it: the CLI's parser takes it and means this configuration
        argv = shlex.split(winner["command"])
        assert argv[0] == "daror"
        assert argv[1:] == winner["argv"]
        args = build_parser().parse_args(argv[1:])
        assert (args.kind, args.train, args.out) == (model, folder / "B-train.csv", searched / winner["file"])
        assert (args.layers, args.width, args.activation, args.inputs) == (
            int(best["layers"]), int(best["width"]), best["activation"], best["inputs"]
        )  # fmt: skip
        assert args.l1 == float(best["l1"])
        assert (args.seed, args.inits, args.folds, args.adam_steps, args.lbfgs, args.thesis) == (
            0,
            2,
            4,
            10,
            True,
            True,
        )
        # the tiny grid's own learning rate and L-BFGS iterations have no fit option: said, not hidden
        assert any(d.startswith("learning_rate: the search trained with 0.005") for d in winner["differences"])
        assert any(d.startswith("lbfgs_steps: the search trained with 40") for d in winner["differences"])
        # running the line gives the file's parameters, digit for digit
        again = tmp_path / f"again_{model}.json"
        argv[argv.index("--out") + 1] = str(again)
        assert main(argv[1:]) == 0
        assert load_model(again)[1].parameters == contents.parameters
    capsys.readouterr()
    md = (searched / "ranking.md").read_text()
    assert "## The winners as models" in md
    assert summary["winners"]["penn"]["command"] in md


def test_the_fit_line_starts_from_the_searched_initialisations_where_daror_fit_can() -> None:
    """``daror fit`` starts initialisation i from 1000 x --seed + i: seeds 0..N-1 (the built-in grids) are
    --seed 0 --inits N; a seed it cannot start from is named as a difference."""
    row = NetworkRow("penn", 1, 25, "sigmoid", "q", 1e-3, 1, 0.1, 5, 0.4, 0.1, 4.0, False, 1.0, 1.0, 0.1)
    thesis = BUILTIN_GRIDS["thesis"]
    argv = fit_arguments("penn", row, thesis, "B.csv", "out/best_penn.json")
    assert argv == [
        "fit", "penn", "--train", "B.csv", "--out", "out/best_penn.json", "--layers", "1", "--width", "25",
        "--activation", "sigmoid", "--inputs", "q", "--l1", "0.001", "--seed", "0", "--inits", "2", "--folds", "4",
        "--adam-steps", "100", "--lbfgs",
    ]  # fmt: skip
    far = thesis.model_copy(update={"seeds": (2000, 2001, 2002)})
    assert fit_arguments("penn", row, far, "B.csv", "o.json")[-9:-5] == ["--seed", "2", "--inits", "3"]
    assert fit_options(row, far)[1] == []
    odd = thesis.model_copy(update={"seeds": (7, 1)})
    options, differences = fit_options(replace(row, seed=7), odd)
    assert (options["seed"], options["inits"]) == (0, 1)
    assert differences == [
        "initialisation seed 7: daror fit starts from 1000 x --seed + i, so the model starts from seed 0 instead"
    ]


# --- refusals: exit code 2, one line, nothing written --------------------------------------------


def test_a_folder_that_is_not_empty_is_refused_without_force(
    searched: Path, folder: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = _snapshot(searched)
    assert main(_argv(folder, searched)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"{searched}: the folder is not empty" in err
    assert "--force" in err
    assert _snapshot(searched) == before


@pytest.mark.parametrize(
    ("content", "expected"),
    [(None, "B-missing.csv"), ("q1,q2\n1,2\n", "B-missing.csv"), ("", "B-missing.csv")],
)
def test_bad_training_data_exits_2_in_one_line(
    folder: Path, capsys: pytest.CaptureFixture[str], content: str | None, expected: str
) -> None:
    train = folder / "B-missing.csv"
    train.unlink(missing_ok=True)
    if content is not None:
        train.write_text(content)
    out = folder / "not_written"
    argv = _argv(folder, out)
    argv[argv.index("--train") + 1] = str(train)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert expected in err
    assert not out.exists()


def test_too_few_points_exit_2(
    folder: Path, dataset_b: tuple[StationaryDataset, StationaryDataset], capsys: pytest.CaptureFixture[str]
) -> None:
    train = folder / "B-few.csv"
    full = dataset_b[0]
    write_dataset(train, full.subset(slice(0, 30)))
    out = folder / "not_written"
    argv = _argv(folder, out)
    argv[argv.index("--train") + 1] = str(train)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "30 points cannot be cut into 4 validation blocks" in err
    assert not out.exists()


def test_executor_options_that_do_not_go_together_exit_2(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = folder / "not_written"
    assert main(_argv(folder, out, "--ray-address", "10.0.0.1:6379")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "--ray-address goes with --executor ray" in err
    pytest.importorskip("ray", reason="the optional extra ray (make test installs it)")
    assert main(_argv(folder, out, "--executor", "ray", "--ray-address", "10.0.0.1:6379", "--workers", "2")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "--workers: a Ray cluster (--ray-address) runs as many units at once as it has CPUs" in err
    assert not out.exists()


def test_without_ray_the_ray_executor_says_how_to_install_it(
    folder: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # as if the extra ray were not installed
    out = folder / "not_written"
    assert main(_argv(folder, out, "--executor", "ray")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert (
        "--executor ray needs the optional extra 'ray', which is not installed: pip install 'daror-runtime[ray]'" in err
    )
    assert not out.exists()


_WITHOUT_JAX = """
import sys
sys.modules["jax"] = None  # as if the extra nn were not installed: any import of jax fails
from daror_runtime.bench import machine
from daror_runtime.cli import build_parser, main
code = main(sys.argv[1:])
assert "jax" not in {m.split(".")[0] for m in sys.modules if sys.modules[m] is not None}
raise SystemExit(code)
"""


@pytest.mark.subprocess
def test_without_jax_the_search_says_how_to_install_it(folder: Path) -> None:
    out = folder / "not_written"
    run = subprocess.run(
        [sys.executable, "-c", _WITHOUT_JAX, *_argv(folder, out)], capture_output=True, text=True, cwd=folder
    )
    assert run.returncode == 2, run.stderr
    assert run.stderr.count("\n") == 1
    assert "the search trains networks with JAX and needs the optional extra 'nn', which is not installed" in run.stderr
    assert "pip install 'daror-runtime[nn]'" in run.stderr
    assert not out.exists()


# --- workers: none outlives the command ----------------------------------------------------------


def _workers_of(pid: int) -> list[int]:
    """The worker processes (``spawn``) the process ``pid`` started, not its resource tracker."""
    try:
        children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return []
    workers = []
    for child in map(int, children):
        try:
            command = Path(f"/proc/{child}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in command:
            workers.append(child)
    return workers


def _gone(pid: int) -> bool:
    """The process has exited (no longer there, or a zombie nobody has reaped yet)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def _wait_until(condition: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return False


#: Loaded at the start of every interpreter that has it on its path (``sitecustomize``), the
#: workers included: training a network of the activation ``DAROR_TEST_FAILING_ACTIVATION`` names
#: fails, as a unit can fail in a worker (an error of XLA, of memory).
_FAILING_UNIT = """
import os

import daror_runtime.neural.training as training
from daror_runtime.errors import DarorError
from daror_runtime.models.files import load_model

_train_group = training.train_group


def train_group(spec, *args, **kwargs):
    if spec.activation == os.environ.get("DAROR_TEST_FAILING_ACTIVATION"):
        raise DarorError(f"injected: the {spec.activation} unit failed")
    return _train_group(spec, *args, **kwargs)


training.train_group = train_group
"""


#: ``sitecustomize`` again: a worker process dies as it starts, before it has read anything.
_WORKERS_DIE_AT_START = """
import os
import sys

if "--multiprocessing-fork" in sys.argv:
    os._exit(3)
"""


def _with_sitecustomize(tmp_path: Path, source: str, **variables: str) -> dict[str, str]:
    """An environment whose interpreters (the command's and its workers') run ``source`` first."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(source)
    return {**os.environ, "PYTHONPATH": str(site), **variables}


def _start(folder: Path, tmp_path: Path, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """``daror hpsearch`` (the long grid, 2 workers, out: ``tmp_path/out``) in a fresh process; its
    temporary folder (the data file for the workers) in ``tmp_path``: a killed command leaves it."""
    argv = _argv(folder, tmp_path / "out", "--workers", "2")
    argv[argv.index("--grid") + 1] = str(folder / "long.yaml")
    return subprocess.Popen(
        [sys.executable, "-c", CLI, *argv],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env={**(os.environ if env is None else env), "TMPDIR": str(tmp_path)},
    )


@pytest.mark.subprocess
def test_a_failing_unit_ends_the_search_with_its_error_and_nothing_written(folder: Path, tmp_path: Path) -> None:
    """The first unit fails while the others wait in the queue to the workers: the command ends the
    workers and reports the error."""
    process = _start(
        folder, tmp_path, _with_sitecustomize(tmp_path, _FAILING_UNIT, DAROR_TEST_FAILING_ACTIVATION="tanh")
    )
    try:
        _, err = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 1
    assert err.splitlines()[0] == "daror hpsearch: failed: injected: the tanh unit failed"
    assert "Traceback" not in err  # nor an error of the pool's thread (it used to print one, then hang)
    assert not (tmp_path / "out").exists()


@pytest.mark.subprocess
def test_workers_that_die_as_they_start_end_the_search(folder: Path, tmp_path: Path) -> None:
    """Nothing is left half-sent to a dead worker (the start of a worker, written by the command's main
    thread, would block it for ever if it outgrew the pipe: it did with the dataset in it)."""
    process = _start(folder, tmp_path, _with_sitecustomize(tmp_path, _WORKERS_DIE_AT_START))
    try:
        _, err = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 1
    assert err.splitlines()[0] == (
        "daror hpsearch: failed: a worker process died (killed, or out of memory); nothing was written"
    )
    assert not (tmp_path / "out").exists()


@pytest.fixture
def command(folder: Path, tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], list[int], Path]]:
    """``daror hpsearch`` (the long grid, 2 workers) in a fresh process, once its two workers run."""
    out = tmp_path / "out"
    process = _start(folder, tmp_path)
    workers: list[int] = []
    try:
        assert _wait_until(lambda: len(_workers_of(process.pid)) == 2 or process.poll() is not None, 60)
        workers = _workers_of(process.pid)
        assert len(workers) == 2, "the command did not start two workers"
        yield process, workers, out
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        for pid in workers:  # the test's own processes; gone already when the test passed
            if not _gone(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.subprocess
def test_a_killed_worker_ends_the_search_with_nothing_written(
    command: tuple[subprocess.Popen[str], list[int], Path],
) -> None:
    process, workers, out = command
    os.kill(workers[0], signal.SIGKILL)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 1
    assert err.splitlines()[0] == (
        "daror hpsearch: failed: a worker process died (killed, or out of memory); nothing was written"
    )
    assert "Traceback" not in err  # the rest is the failure's log line
    assert not out.exists()
    assert all(_gone(pid) for pid in workers)


@pytest.mark.subprocess
def test_ctrl_c_ends_the_workers_and_writes_nothing(command: tuple[subprocess.Popen[str], list[int], Path]) -> None:
    process, workers, out = command
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=30)
    assert process.returncode == 130
    assert "interrupted" in err
    assert not out.exists()
    assert not list(out.parent.glob("daror-hpsearch-*"))  # the data file removed
    assert all(_gone(pid) for pid in workers)


@pytest.mark.subprocess
def test_the_workers_end_when_the_command_is_killed(command: tuple[subprocess.Popen[str], list[int], Path]) -> None:
    process, workers, out = command
    time.sleep(1.0)  # into their initialisation or training (a unit trains for seconds)
    process.kill()  # SIGKILL: the command cannot end its workers; the kernel does (PR_SET_PDEATHSIG)
    process.wait()
    assert _wait_until(lambda: all(_gone(pid) for pid in workers), 5)
    assert not out.exists()
    assert len(list(out.parent.glob("daror-hpsearch-*"))) == 1  # the data file, left behind (documented)


@pytest.mark.slow
def test_a_training_file_with_two_joints_exchanged_is_refused_unless_trusted_and_then_every_file_says_so(
    folder: Path,
    tmp_path: Path,
    dataset_b: tuple[StationaryDataset, StationaryDataset],
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Issue 27: the search judges its training file's signal map (docs/data.md) before it trains anything."""
    train = dataset_b[0]
    swapped = tmp_path / "swapped.csv"
    write_dataset(swapped, replace(train, q_rad=train.q_rad[:, [1, 0, 2, 3]], tau_nm=train.tau_nm[:, [1, 0, 2, 3]]))
    out = tmp_path / "search"
    argv = [
        "hpsearch", "--train", str(swapped), "--out", str(out), "--grid", str(folder / "tiny.yaml"),
        "--cache-dir", str(folder / "cache"), "--workers", "1",
    ]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "most likely joints 1 and 2 exchanged" in err[0]
    assert not out.exists()
    assert main([*argv, "--trust-signal-map"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["signal_map"].startswith(f"accepted with --trust-signal-map although {swapped}")
    for winner in summary["winners"].values():
        _, contents = load_model(out / winner["file"])
        assert contents.training is not None
        assert contents.training.signal_map == summary["signal_map"]
        assert winner["argv"][-1] == "--trust-signal-map"  # its fit line is refused without it
