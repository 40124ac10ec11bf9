"""Benchmarks of the controllers (issue 3, item 5): ``update()`` cost per 1 kHz tick, four joints.

The whole tick in lock-step (HAL read, safety, FSM, controller, safety filter, write, recorder)
must fit in ~20 us; each controller's share should be a few microseconds. Measured here, never
asserted in tests.

* MinimalImpedance: the SEA torque loop with its observer (one compiled kernel call).
* Compensation: the same plus a PLF+ model's torque (fitted as bench/bench_models.py does).
* Compensation with a tracked hysteresis (issue 16): an augmented model of the same fit whose
  torque reading carries a hysteresis, on a loop that regulates the drive's reading, so the
  tracker (:mod:`daror_runtime.control.reading_error`) runs every tick.
* MotorPositionPD: the identification's position controller on a validation trajectory (with its
  approach) and an A Priori feed-forward: reference, model and PD in one compiled call.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from daror_runtime.bench import BenchFigure, time_calls
from daror_runtime.control import (
    Compensation,
    Controller,
    LinkBounds,
    MinimalImpedance,
    SeaTorqueController,
)
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.sea_torque_design import SeaTorqueDesign
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.identification.trajectory_planning import build_trajectory, prepend_approach
from daror_runtime.identification.waypoints import load_waypoints
from daror_runtime.models.linear import APModel, fit_plf_plus
from daror_runtime.residual.diagnosis import diagnose
from daror_runtime.residual.model import AugmentedModel, augmented_model
from hal.interface import CheckedSample, DriveState, Sample
from hal.robot import load_description
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary

TICK_S = 1e-3


#: Where :func:`samples_near`'s readings are by default.
Q0_RAD = np.deg2rad([0.0, 20.0, 0.0, 45.0])


def samples_near(q0_rad: np.ndarray = Q0_RAD, count: int = 1000, checked: bool = False) -> list[Sample]:
    """Plausible readings near a pose, so the controllers do their ordinary work (no saturation).

    ``checked``: as the simulated and CAN backends hand them to the tick (a ``CheckedSample``).
    """
    rng = np.random.default_rng(7)
    kind = CheckedSample if checked else Sample
    out = []
    for i in range(count):
        q = q0_rad + rng.normal(0.0, 1e-3, 4)
        tau = np.round(rng.normal(1.0, 0.05, 4) / 0.0289) * 0.0289
        out.append(
            kind(i, i * TICK_S, q, rng.normal(0.0, 0.01, 4), q + tau / 289.0, tau, (False, False),
                 (DriveState.ENABLED,) * 4)
        )  # fmt: skip
    return out


def plf_plus() -> Any:
    """PLF+ fitted on the training points of ``exo_dummy_arm``."""
    description = load_description()
    points = generate_stationary(load_scenario("exo_dummy_arm"), "training")
    return fit_plf_plus(StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s), description).model


def time_update(
    controller: Any, quick: bool, samples: list[Sample] | None = None, reset: bool = True
) -> tuple[float, float, int]:
    """``controller.update`` over ``samples`` (default :func:`samples_near`), us: median, p90, repeats."""
    samples = samples if samples is not None else samples_near()
    if reset:
        controller.reset(samples[0])
    state = {"i": 0}

    def one() -> None:
        state["i"] = (state["i"] + 1) % len(samples)
        controller.update(samples[state["i"]], TICK_S)

    repeats = 20 if quick else 200
    median, p90 = time_calls(one, repeats=repeats, per_call=1000, scale=1e6)
    return median, p90, repeats


def _figure(name: str, build: Callable[[], Controller], quick: bool, target_us: float, note: str) -> BenchFigure:
    median, p90, repeats = time_update(build(), quick)
    return BenchFigure(name, median, p90, "us", repeats, target_us, None, note)


def bench_minimal_impedance_update(quick: bool) -> BenchFigure:
    description = load_description()
    return _figure(
        "MinimalImpedance.update, 4 joints",
        lambda: MinimalImpedance(SeaTorqueController(description.sea)),
        quick,
        5.0,
        "torque loop + observer, one compiled kernel",
    )


def bench_compensation_update(quick: bool) -> BenchFigure:
    description = load_description()
    model = plf_plus()
    return _figure(
        "Compensation(PLF+).update, 4 joints",
        lambda: Compensation(SeaTorqueController(description.sea), model, support_level=0.8, ramp_per_s=None),
        quick,
        12.0,
        "PLF+ torque (~5 us) + torque loop",
    )


def bench_compensation_hysteresis_update(quick: bool) -> BenchFigure:
    description = load_description()
    points = generate_stationary(load_scenario("exo_dummy_arm"), "training")
    diagnosis = diagnose(StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s), description)
    signed = augmented_model(diagnosis.final_fit)
    model = AugmentedModel(
        description,
        signed.spec.model_copy(
            update={
                "direction_offset_nm": [0.0] * 4,
                "hysteresis_nm": signed.spec.direction_offset_nm,
                "hysteresis_travel_rad": [5e-3] * 4,
            }
        ),
    )
    design = SeaTorqueDesign(torque_from_encoders=False)
    return _figure(
        "Compensation(augmented, hysteresis tracked).update, 4 joints",
        lambda: Compensation(SeaTorqueController(description.sea, design), model, support_level=0.8, ramp_per_s=None),
        quick,
        12.0,
        "augmented torque + the reading's hysteresis tracker + torque loop",
    )


def bench_motor_position_update(quick: bool) -> BenchFigure:
    description = load_description()
    bounds = LinkBounds.from_description(description)
    q0 = Q0_RAD  # where samples_near()'s readings are
    reference = prepend_approach(build_trajectory(load_waypoints(), "validation"), q0, 2.0, 1.0)
    feedforward = APModel.from_description(description, dummy_arm=True, elbow_stiffness=True)

    def build() -> Controller:
        return MotorPositionPD(description, reference, bounds, feedforward=feedforward)

    return _figure(
        "MotorPositionPD.update, 4 joints", build, quick, 10.0, "trajectory table + AP feed-forward + PD, one kernel"
    )


BENCHMARKS = [
    bench_minimal_impedance_update,
    bench_compensation_update,
    bench_compensation_hysteresis_update,
    bench_motor_position_update,
]
