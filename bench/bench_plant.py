"""Benchmarks of the dynamic plant and the simulated HAL (issue 3).

* One RK4 step of the full plant (4 links + Dummy Arm, 4 SEAs), the kernel called from Python
  the way the simulated HAL calls it: target a few microseconds (5 us).
* One tick of the simulated HAL, ``read()`` + ``write()``, with a constant enabled command:
  target below 10 us, so lock-step simulation runs at 100x real time or more.
* 10 s of robot time (10,000 ticks at 1 kHz) through ``read()`` + ``write()``: wall time, with
  the real-time factor (robot time / wall time) in the note.

The first two keep the plant moving (the holding torque plus 3 Nm sinusoids, cycled from a
precomputed list): at rest some library functions (tanh of 0) take shortcuts that a moving robot
never gets. The 10 s run holds a constant command, as a session's tests do.
"""

from __future__ import annotations

import time

import numpy as np

from daror_runtime.bench import BenchFigure, time_calls
from hal.interface import Command
from hal.sim import dynamics
from hal.sim.backend import SimHal

SCENARIO = "exo_dummy_arm"


N_VARIED = 1000  # commands cycled through, 1 s at 1 kHz


def _hal() -> tuple[SimHal, Command]:
    hal = SimHal(SCENARIO)
    hal.open()
    command = Command(hal.plant.holding_torque_nm(hal.truth().q_rad), True)
    return hal, command


def _varied_torques(holding: np.ndarray) -> list[np.ndarray]:
    """Holding torque plus 3 Nm sinusoids of 1-4 Hz per joint: the robot keeps moving."""
    t = np.arange(N_VARIED)[:, None] * 1e-3
    torques = holding + 3.0 * np.sin(2 * np.pi * np.array([1.0, 2.0, 3.0, 4.0]) * t)
    return [np.ascontiguousarray(row) for row in torques]


def bench_plant_rk4_step(quick: bool) -> BenchFigure:
    hal, command = _hal()
    plant = hal.plant
    inputs = [np.concatenate([torque, np.zeros(4)]) for torque in _varied_torques(command.motor_torque_nm)]
    state, params, work = plant.state, plant.params, plant.work
    index = {"i": 0}

    def one() -> None:
        index["i"] = (index["i"] + 1) % N_VARIED
        dynamics.rk4_step(state, inputs[index["i"]], 1e-3, params, work)

    repeats = 20 if quick else 200
    median, p90 = time_calls(one, repeats=repeats, per_call=1000, scale=1e6)
    # The same step inside a compiled loop: the arithmetic alone, without Python's call overhead.
    steps = 20_000
    plant.set_state(state[:4], np.full(4, 0.3), state[4:8], np.full(4, -0.2))  # moving
    dynamics.simulate(state, inputs[0], 1e-3, 10, params, work)
    start = time.perf_counter()
    dynamics.simulate(state, inputs[0], 1e-3, steps, params, work)
    in_kernel = (time.perf_counter() - start) / steps * 1e6
    note = f"moving; kernel called from Python (4 derivative evaluations); {in_kernel:.2f} us in a compiled loop"
    return BenchFigure("plant RK4 step (4 links + Dummy Arm, 4 SEAs)", median, p90, "us", repeats, 5.0, None, note)


def bench_sim_hal_tick(quick: bool) -> BenchFigure:
    hal, command = _hal()
    commands = [Command(torque, True) for torque in _varied_torques(command.motor_torque_nm)]
    index = {"i": 0}

    def one() -> None:
        index["i"] = (index["i"] + 1) % N_VARIED
        hal.read()
        hal.write(commands[index["i"]])

    repeats = 20 if quick else 200
    median, p90 = time_calls(one, repeats=repeats, per_call=1000, scale=1e6)
    note = "moving; RK4 step + command FIFO + encoders + drives' filters + Sample"
    return BenchFigure("SimHal read() + write(), one tick", median, p90, "us", repeats, 10.0, None, note)


def bench_sim_hal_10_s(quick: bool) -> BenchFigure:
    ticks = 10_000  # 10 s at 1 kHz
    hal, command = _hal()

    def run() -> None:
        hal.open()  # back to rest at the initial pose: every repeat simulates the same 10 s
        for _ in range(ticks):
            hal.read()
            hal.write(command)

    repeats = 3 if quick else 10
    median, p90 = time_calls(run, repeats=repeats, scale=1e3)
    note = f"real-time factor {10.0 / (median / 1e3):.0f}x (p90 {10.0 / (p90 / 1e3):.0f}x), includes open(), not construction"
    return BenchFigure("SimHal, 10 s of robot time at 1 kHz", median, p90, "ms", repeats, 100.0, None, note)


BENCHMARKS = [bench_plant_rk4_step, bench_sim_hal_tick, bench_sim_hal_10_s]
