"""Benchmarks of the neural models PENN and NNN (issue 13, issue 27; thesis Table V for the fit).

* One PENN fit with the default preset (2 x 32 tanh on q, one initialisation trained on 3 of 4
  validation blocks and on all the data, 100 Adam steps + 850 L-BFGS iterations, D206) on dataset
  B's training trajectory (1,313 points): process CPU seconds (``time.process_time``, every thread;
  target below 2 s, thesis 36.7 s for one network) and wall seconds. "Warm": the fit repeated in
  one process, its program compiled once; "cold": ``daror fit penn`` in a fresh process, as a user
  runs it (importing JAX and tracing the program included, XLA's compilation from JAX's persistent
  cache after the first run), timed from inside and as the whole command, process start to exit
  (target below 4 s, issue 27).
* One NNN fit likewise (target below 2 s; thesis 15.3 s).
* A PENN's torque at one q: through ``model.torque`` (ndarray in and out, what a controller calls)
  and through the compiled kernel called from compiled code (target below 5 us each).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from numba import njit

from daror_runtime.bench import BenchFigure, time_torque_one_q
from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.neural import PennModel, network_torque, network_torque_into
from daror_runtime.models.registry import NetworkOptions, fit_model
from hal.robot import load_description
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary


def _dataset_b() -> StationaryDataset:
    points = generate_stationary(load_scenario("exo_dummy_arm"), "training")
    return StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s, "B-training")


def _fit_warm(kind: str, quick: bool, cpu_target: float, thesis: str) -> list[BenchFigure]:
    data, description = _dataset_b(), load_description()
    fit_model(kind, data, description, NetworkOptions(seed=0))  # compiles the program once
    cpu, wall = [], []
    repeats = 2 if quick else 5
    for seed in range(1, repeats + 1):  # another seed each time: other initial weights, the same program
        c0, w0 = time.process_time(), time.perf_counter()
        fit_model(kind, data, description, NetworkOptions(seed=seed))
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    name = kind.upper()
    note = f"{len(data):,} points, default preset, program compiled beforehand"
    return [
        BenchFigure(
            f"{name} fit, default preset, CPU (all threads)", float(np.median(cpu)), float(np.percentile(cpu, 90)),
            "s", repeats, cpu_target, thesis, note,
        ),
        BenchFigure(
            f"{name} fit, default preset, wall", float(np.median(wall)), float(np.percentile(wall, 90)),
            "s", repeats, None, None, note,
        ),
    ]  # fmt: skip


def bench_penn_fit(quick: bool) -> list[BenchFigure]:
    return _fit_warm("penn", quick, 2.0, "36.7 s (one network, JAX, Table V)")


def bench_nnn_fit(quick: bool) -> list[BenchFigure]:
    return _fit_warm("nnn", quick, 2.0, "15.3 s (one network, JAX, Table V)")


_COLD = """
import json, sys, time
c0, w0 = time.process_time(), time.perf_counter()
from daror_runtime.cli import main
code = main(["fit", sys.argv[1], "--train", sys.argv[2], "--out", sys.argv[3], "--seed", "1"])
print(json.dumps([code, time.process_time() - c0, time.perf_counter() - w0]))
"""


def bench_fit_cold(quick: bool) -> list[BenchFigure]:
    """``daror fit penn|nnn`` in a fresh interpreter: what a user waits for (imports and compiling included)."""
    import json

    figures = []
    with tempfile.TemporaryDirectory() as folder:
        train = Path(folder) / "B.csv"
        write_dataset(train, _dataset_b())
        for kind in ("penn", "nnn"):
            cpu, wall, whole = [], [], []
            repeats = 1 if quick else 3
            for i in range(repeats):
                out = Path(folder) / f"{kind}{i}.json"
                started = time.perf_counter()
                run = subprocess.run(
                    [sys.executable, "-c", _COLD, kind, str(train), str(out)],
                    capture_output=True, text=True, check=True, env=dict(os.environ),
                )  # fmt: skip
                whole.append(time.perf_counter() - started)
                code, c, w = json.loads(run.stdout.strip().splitlines()[-1])
                if code != 0:
                    raise RuntimeError(f"daror fit {kind} failed: {run.stderr}")
                cpu.append(c)
                wall.append(w)
            note = (
                "imports JAX and traces the training program (XLA's compilation cached); reads the CSV, writes the file"
            )
            for label, values, target in (
                ("CPU (all threads)", cpu, None),
                ("wall", wall, None),
                ("whole command, process start to exit, wall", whole, 4.0),
            ):
                figures.append(
                    BenchFigure(
                        f"daror fit {kind}, fresh process, {label}", float(np.median(values)),
                        float(np.percentile(values, 90)), "s", repeats, target, None, note,
                    )
                )  # fmt: skip
    return figures


@njit  # not cache=True: daror bench loads this file as a dynamic module, which numba cannot cache
def _kernel_loop(q: np.ndarray, p: np.ndarray, scratch: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    for i in range(q.shape[0]):
        network_torque_into(q[i], p, scratch, out)


@njit  # not cache=True: daror bench loads this file as a dynamic module, which numba cannot cache
def _tick_kernel_loop(q: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    for i in range(q.shape[0]):
        network_torque(q[i], p, out)


def bench_penn_torque_one_q(quick: bool) -> list[BenchFigure]:
    data, description = _dataset_b(), load_description()
    model: PennModel = fit_model("penn", data, description, NetworkOptions(seed=1)).model  # type: ignore[assignment]
    median, p90, repeats = time_torque_one_q(model, data.q_rad, quick)
    figures = [
        BenchFigure(
            "PENN torque, one q, model.torque", median, p90, "us", repeats, 5.0, None,
            f"{model.spec.describe()}; ndarray in and out",
        )
    ]  # fmt: skip
    q = np.ascontiguousarray(data.q_rad[:1000])
    packed = model.tick_kernel().parameters
    scratch = np.zeros(model.spec.scratch_size)
    out = np.empty(4)
    for label, loop, args in (
        ("PENN torque, one q, kernel from compiled code", _kernel_loop, (q, packed, scratch, out)),
        ("PENN torque, one q, TickKernel (allocates its scratch)", _tick_kernel_loop, (q, packed, out)),
    ):
        loop(*args)  # compile
        samples = []
        for _ in range(20 if quick else 200):
            start = time.perf_counter()
            loop(*args)
            samples.append((time.perf_counter() - start) / q.shape[0] * 1e6)
        figures.append(
            BenchFigure(
                label, float(np.median(samples)), float(np.percentile(samples, 90)), "us", len(samples), 5.0, None,
                "per call, 1,000 configurations a sample",
            )
        )  # fmt: skip
    return figures


BENCHMARKS = [bench_penn_fit, bench_nnn_fit, bench_fit_cold, bench_penn_torque_one_q]
