"""Benchmarks of the residual analysis (issue 5).

* Full diagnosis on 1,250 training and 200 validation points: target below 10 s. The data are
  dataset B (exo + Dummy Arm, direction error on every joint), the hardest shipped case: four
  effects are found, so the diagnosis runs five rounds of every candidate.
* The whole ``daror residual`` job on the same files (diagnosis, closure, report, plots): no target.
* The augmented model's torque for one q (it runs inside the 1 kHz tick): target below 20 us,
  the budget of PLF+.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from daror_runtime.bench import BenchFigure, time_calls
from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.residual.diagnosis import closure, diagnose
from daror_runtime.residual.model import augmented_model
from daror_runtime.residual.pipeline import run_residual
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
    configurations = [np.asarray(q) for q in train.q_rad[:1000]]
    state = {"i": 0}

    def one() -> None:
        state["i"] = (state["i"] + 1) % len(configurations)
        model.torque(configurations[state["i"]])

    repeats = 20 if quick else 200
    median, p90 = time_calls(one, repeats=repeats, per_call=1000, scale=1e6)
    return BenchFigure("augmented model torque, one q", median, p90, "us", repeats, 20.0, None, "dataset B effects")


BENCHMARKS = [bench_residual_diagnosis, bench_residual_job, bench_augmented_torque_one_q]
