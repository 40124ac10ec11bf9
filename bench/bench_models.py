"""Benchmarks of the compensation models (issue 2; thesis Table V for the fit).

* PLF+ fit on 25,000 stationary samples: thesis 4.5 s (Matlab); target below 50 ms.
* PLF+ torque for one q: target below 20 us (it runs inside the 1 kHz tick).
* PLF+ torque for 25,000 q at once: target below 20 ms.
"""

from __future__ import annotations

from daror_runtime.bench import BenchFigure, time_calls, time_torque_one_q
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.cvf import cvf_test
from daror_runtime.models.linear import fit_plf, fit_plf_plus
from hal.robot import load_description
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary

N_SAMPLES = 25_000


def _dataset_25000() -> StationaryDataset:
    # 1,313 stops x 20 readings each, cut to 25,000: the size of the thesis's datasets (Sec. 4.3.2).
    points = generate_stationary(load_scenario("exo_dummy_arm"), "training", samples_per_stop=20)
    data = StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s)
    return data.subset(slice(0, N_SAMPLES))


def bench_plf_plus_fit_25000(quick: bool) -> BenchFigure:
    data, description = _dataset_25000(), load_description()
    median, p90 = time_calls(lambda: fit_plf_plus(data, description), repeats=5 if quick else 30)
    return BenchFigure(
        "PLF+ fit, 25,000 samples", median, p90, "ms", 5 if quick else 30, 50.0, "4.5 s (Matlab, Table V)"
    )


def bench_plf_fit_25000(quick: bool) -> BenchFigure:
    data, description = _dataset_25000(), load_description()
    median, p90 = time_calls(lambda: fit_plf(data, description), repeats=5 if quick else 30)
    return BenchFigure(
        "PLF fit, 25,000 samples", median, p90, "ms", 5 if quick else 30, 50.0, "4.5 s (Matlab, Table V)"
    )


def bench_plf_plus_torque_one_q(quick: bool) -> BenchFigure:
    data, description = _dataset_25000(), load_description()
    model = fit_plf_plus(data, description).model
    median, p90, repeats = time_torque_one_q(model, data.q_rad, quick)
    return BenchFigure("PLF+ torque, one q", median, p90, "us", repeats, 20.0, None, "per call, ndarray in and out")


def bench_plf_plus_torque_25000(quick: bool) -> BenchFigure:
    data, description = _dataset_25000(), load_description()
    model = fit_plf_plus(data, description).model
    median, p90 = time_calls(lambda: model.torque_batch(data.q_rad), repeats=5 if quick else 50)
    return BenchFigure("PLF+ torque, 25,000 q at once", median, p90, "ms", 5 if quick else 50, 20.0)


def bench_cvf_test(quick: bool) -> BenchFigure:
    data, description = _dataset_25000(), load_description()
    model = fit_plf_plus(data, description).model
    median, p90 = time_calls(lambda: cvf_test(model.torque_batch, [0.0, 0.2, 0.0, 0.5]), repeats=3 if quick else 10)
    return BenchFigure("closed-path test, 3 step sizes (88,800 q)", median, p90, "ms", 3 if quick else 10)


BENCHMARKS = [
    bench_plf_plus_fit_25000,
    bench_plf_fit_25000,
    bench_plf_plus_torque_one_q,
    bench_plf_plus_torque_25000,
    bench_cvf_test,
]
