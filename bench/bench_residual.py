"""Benchmarks of the residual analysis (issue 5).

* Full diagnosis on 1,250 training and 200 validation points: target below 10 s. The data are
  dataset B (exo + Dummy Arm, direction error on every joint), the hardest shipped case: four
  effects are found, so the diagnosis runs five rounds of every candidate.
* The whole ``daror residual`` job on the same files (diagnosis, closure, report, plots): no target.
* The augmented model's torque for one q (it runs inside the 1 kHz tick): target below 20 us,
  the budget of PLF+.
* The data-efficiency study (Fig. 5.4) on dataset B, 100 draws per size: no target.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from daror_runtime.bench import BenchFigure, time_calls, time_torque_one_q
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


BENCHMARKS = [
    bench_residual_diagnosis,
    bench_residual_job,
    bench_augmented_torque_one_q,
    bench_data_efficiency_study,
]
