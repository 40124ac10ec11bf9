"""Benchmarks of the residual analysis (issue 5).

* Full diagnosis on 1,250 training and 200 validation points: target below 10 s. The data are
  dataset B (exo + Dummy Arm, direction error on every joint), the hardest shipped case: four
  effects are found, so the diagnosis runs five rounds of every candidate.
* The whole ``daror residual`` job on the same files (diagnosis, closure, report, plots): no target.
* Issue 16: the diagnosis with the hysteresis family on a full protocol's closed-loop data
  (``daror identify`` training and validation runs of ``exo_dummy_arm``, 752 s and 145 s of robot
  time, their raw logs beside them): the diagnosis with the sign, the travel constants' fit and the
  second diagnosis (target below 10 s), and the whole ``daror residual`` command, process start to
  exit.
* The augmented model's torque for one q (it runs inside the 1 kHz tick): target below 20 us,
  the budget of PLF+.
* The data-efficiency study (Fig. 5.4) on dataset B, 100 draws per size: no target.
* Issue 10: the whole ``daror residual`` command on ~10^5 and ~10^6 training points (the
  ``residual_gravity_tilt`` scenario from the static generator, CSV files as a lab would hand them
  over), process start to exit in a fresh interpreter: wall time and the child's own peak memory
  (``VmHWM`` read by the child at the end; ``ru_maxrss`` of a parent counts an inherited peak).
  Targets at 10^6: below 120 s and below 2,000 MB.

Run directly, the script measures one source tree (e.g. the code before a change, extracted with
``git archive``): ``python bench/bench_residual.py --root /tmp/daror_before --points 100000``.
``--memory-limit-mb`` caps the child's address space, so a run that would need more memory than
the machine has fails with a MemoryError instead of waking the OOM killer.
"""

from __future__ import annotations

import argparse
import atexit
import json
import shutil
import tempfile
from pathlib import Path

from daror_runtime.bench import BenchFigure, command_in_child, time_calls, time_torque_one_q
from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.residual.diagnosis import closure, diagnose
from daror_runtime.residual.model import augmented_model
from daror_runtime.residual.pipeline import run_residual
from daror_runtime.studies.data_efficiency import run_data_efficiency
from hal.robot import load_description
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary

N_TRAIN, N_VALIDATE = 1250, 200


def _data() -> tuple[StationaryDataset, StationaryDataset]:
    scenario = load_scenario("exo_dummy_arm")
    train = generate_stationary(scenario, "training")
    validate = generate_stationary(scenario, "validation", n_waypoints=100)
    as_data = lambda s, n: StationaryDataset(s.q_rad[:n], s.tau_nm[:n], s.direction[:n], s.t_s[:n])  # noqa: E731
    return as_data(train, N_TRAIN), as_data(validate, N_VALIDATE)


def bench_residual_diagnosis(quick: bool) -> BenchFigure:
    train, validate = _data()
    description = load_description()
    repeats = 2 if quick else 7
    median, p90 = time_calls(lambda: closure(diagnose(train, description), validate), repeats=repeats, scale=1.0)
    found = len(diagnose(train, description).found)
    return BenchFigure(
        f"residual diagnosis, {N_TRAIN} + {N_VALIDATE} points",
        median,
        p90,
        "s",
        repeats,
        10.0,
        None,
        f"dataset B, {found} effects found",
    )


def bench_residual_job(quick: bool) -> BenchFigure:
    train, validate = _data()
    description = load_description()
    with tempfile.TemporaryDirectory() as folder:
        train_path, validate_path = Path(folder) / "train.csv", Path(folder) / "validate.csv"
        write_dataset(train_path, train)
        write_dataset(validate_path, validate)
        repeats = 2 if quick else 5
        median, p90 = time_calls(
            lambda: run_residual(train_path, validate_path, Path(folder) / "out", description),
            repeats=repeats,
            scale=1.0,
        )
    return BenchFigure(
        "daror residual job (with report and plots)", median, p90, "s", repeats, None, None, "CSV in, report out"
    )


def _protocol_runs(folder: Path) -> tuple[Path, Path]:
    """``daror identify`` training and validation runs of exo_dummy_arm in ``folder`` (with their raw logs)."""
    paths = []
    for run in ("training", "validation"):
        out = folder / f"B_{run}.csv"
        result = command_in_child(
            ["identify", "--scenario", "exo_dummy_arm", "--dummy-arm", "--trajectory", run, "--out", str(out)], folder
        )
        if result.code != 0:
            raise RuntimeError(f"daror identify failed: {result.stderr.strip()[-300:]}")
        paths.append(out)
    return paths[0], paths[1]


def bench_residual_hysteresis(quick: bool) -> list[BenchFigure]:
    from daror_runtime.residual.data import load_pair
    from daror_runtime.residual.evidence import DiagnosisSettings
    from daror_runtime.residual.travel import choose_direction_signal

    description = load_description()
    repeats = 2 if quick else 5
    with tempfile.TemporaryDirectory() as folder:
        train_path, validate_path = _protocol_runs(Path(folder))
        inputs = load_pair(train_path, validate_path)
        history = inputs.train_history
        if history is None or not history.from_raw_log:
            raise RuntimeError(f"{train_path}: its raw log was not found beside it")

        def diagnosis() -> object:
            first = diagnose(inputs.train, description)
            return choose_direction_signal(first, inputs.train, history, description, DiagnosisSettings())

        median, p90 = time_calls(diagnosis, repeats=repeats, scale=1.0)
        walls = [
            command_in_child(
                ["residual", "--train", str(train_path), "--validate", str(validate_path), "--out", f"{folder}/out{k}"],
                Path(folder),
            )
            for k in range(repeats)
        ]
    if any(w.code != 0 for w in walls):
        raise RuntimeError(f"daror residual failed: {walls[0].stderr.strip()[-300:]}")
    wall = sorted(w.wall_s for w in walls)
    return [
        BenchFigure(
            f"residual diagnosis with the hysteresis, full protocol ({len(inputs.train)} + {len(inputs.validate)} points)",
            median,
            p90,
            "s",
            repeats,
            10.0,
            None,
            "exo_dummy_arm closed-loop runs; the sign's diagnosis, the travel fit on the raw log (752,282 ticks), the second diagnosis",
        ),
        BenchFigure(
            "daror residual on the same runs, process start to exit",
            wall[len(wall) // 2],
            wall[-1],
            "s",
            repeats,
            None,
            None,
            "loads both raw logs, writes the report and plots",
        ),
    ]


def bench_augmented_torque_one_q(quick: bool) -> BenchFigure:
    train, _ = _data()
    description = load_description()
    model = augmented_model(diagnose(train, description).final_fit)
    median, p90, repeats = time_torque_one_q(model, train.q_rad, quick)
    return BenchFigure("augmented model torque, one q", median, p90, "us", repeats, 20.0, None, "dataset B effects")


def bench_data_efficiency_study(quick: bool) -> BenchFigure:
    scenario = load_scenario("exo_dummy_arm")
    train = generate_stationary(scenario, "training")
    validate = generate_stationary(scenario, "validation")
    as_data = lambda s: StationaryDataset(s.q_rad, s.tau_nm, s.direction, s.t_s)  # noqa: E731
    description = load_description()
    repeats = 1 if quick else 3
    median, p90 = time_calls(
        lambda: run_data_efficiency(as_data(train), as_data(validate), description), repeats=repeats, scale=1.0
    )
    return BenchFigure(
        f"data-efficiency study, PLF+, {len(train)} points, 100 draws x 18 sizes",
        median,
        p90,
        "s",
        repeats,
        None,
        "Fig. 5.4: 100 models per size",
        "1,800 fits",
    )


# --- issue 10: the whole command at 10^5 and 10^6 points ----------------------------------------

#: Training set sizes: (waypoints, samples per stop) of the static generator, 10 stops per leg.
#: 800 x 6 gives 105,474 points; 4,000 x 12 gives 1,055,748. Validation: one tenth or so.
BIG_SETS = {100_000: (800, 6), 1_000_000: (4000, 12)}
BIG_SCENARIO = "residual_gravity_tilt"

_folder: list[Path] = []


def _big_folder() -> Path:
    if not _folder:
        _folder.append(Path(tempfile.mkdtemp(prefix="daror-bench-residual-")))
        atexit.register(shutil.rmtree, _folder[0], True)
    return _folder[0]


def big_files(points: int, scenario_name: str = BIG_SCENARIO) -> tuple[Path, Path, int]:
    """Training and validation CSV files of about ``points`` training points (written once per run)."""
    waypoints, samples = BIG_SETS[points]
    train = _big_folder() / f"train_{scenario_name}_{points}.csv"
    validate = _big_folder() / f"validate_{scenario_name}_{points}.csv"
    scenario = load_scenario(scenario_name)
    measured = generate_stationary(scenario, "training", n_waypoints=waypoints, sub_steps=10, samples_per_stop=samples)
    n_train = len(measured.q_rad)
    if not train.exists():
        write_dataset(train, StationaryDataset(measured.q_rad, measured.tau_nm, measured.direction, measured.t_s))
        held = generate_stationary(scenario, "validation", n_waypoints=waypoints, samples_per_stop=samples)
        write_dataset(validate, StationaryDataset(held.q_rad, held.tau_nm, held.direction, held.t_s))
    return train, validate, n_train


def residual_command_in_child(
    train: Path, validate: Path, root: Path | None = None, memory_limit_mb: float | None = None
) -> dict[str, object]:
    """``daror residual`` in a fresh interpreter: wall time start to exit (s), VmHWM (MB), what it found."""
    out = _big_folder() / f"report_{train.stem}"
    argv = ["residual", "--train", str(train), "--validate", str(validate), "--out", str(out)]
    run = command_in_child(argv, _big_folder(), root, memory_limit_mb)
    if run.code != 0:
        last = run.stderr.strip().splitlines()[-1:] or ["(no output)"]
        return {"wall_s": run.wall_s, "peak_mb": run.peak_mb, "failed": last[0][-300:]}
    summary = json.loads((out / "summary.json").read_text())
    found = ", ".join(e["name"] for e in summary["effects"]) or "nothing"
    return {"wall_s": run.wall_s, "peak_mb": run.peak_mb, "found": found, "rmse_after": summary["rmse_after"]}


def _big_figures(
    points: int, root: Path | None = None, memory_limit_mb: float | None = None, scenario: str = BIG_SCENARIO
) -> list[BenchFigure]:
    train, validate, n_train = big_files(points, scenario)
    run = residual_command_in_child(train, validate, root, memory_limit_mb)
    big = points >= 1_000_000
    note = f"{n_train:,} training points, {scenario}, CSV; " + (
        f"failed (VmHWM last seen): {run['failed']}" if run.get("failed") else f"found {run['found']}"
    )
    wall, peak = float(run["wall_s"]), run["peak_mb"]  # type: ignore[arg-type]
    return [
        BenchFigure(
            f"daror residual, {n_train:,} points: start to exit", wall, wall, "s", 1, 120.0 if big else None, None, note
        ),
        BenchFigure(
            "  its peak memory (VmHWM)",
            float("nan") if peak is None else float(peak),  # type: ignore[arg-type]
            float("nan") if peak is None else float(peak),  # type: ignore[arg-type]
            "MB",
            1,
            2000.0 if big else None,
        ),
    ]


def bench_residual_command_big(quick: bool) -> list[BenchFigure]:
    """``daror residual`` on ~10^5 and ~10^6 training points (10^5 only with ``quick``)."""
    figures = _big_figures(100_000)
    if not quick:
        figures += _big_figures(1_000_000)
    return figures


BENCHMARKS = [
    bench_residual_diagnosis,
    bench_residual_job,
    bench_residual_hysteresis,
    bench_augmented_torque_one_q,
    bench_data_efficiency_study,
    bench_residual_command_big,
]


def _main() -> None:
    parser = argparse.ArgumentParser(description="daror residual on big files, in a child process")
    parser.add_argument("--root", type=Path, help="source tree to measure (PYTHONPATH of the child)")
    parser.add_argument("--points", type=int, choices=sorted(BIG_SETS), action="append", help="training set size")
    parser.add_argument("--memory-limit-mb", type=float, help="address-space limit of the child")
    parser.add_argument("--scenario", default=BIG_SCENARIO, help="scenario of the static generator")
    args = parser.parse_args()
    for points in args.points or sorted(BIG_SETS):
        for f in _big_figures(points, args.root, args.memory_limit_mb, args.scenario):
            print(f"{f.name}: {f.median:.4g} {f.unit}  {f.note}", flush=True)


if __name__ == "__main__":
    _main()
