"""The noise floor of a pair of runs on a simulated plant, whose hysteresis is known (D109).

What the measured data allow a model that lacks nothing: the base model alone, fitted and
validated on the very same runs with the plant's true hysteresis (its amplitudes and travel)
taken out of the readings, its state computed from the measured angles as the analysis computes
it (:class:`~daror_runtime.residual.hysteresis.PointHistory`). It pays for the sensors' noise, for
what that noise does to the hysteresis state, and for points whose state no log determines, as the
analysis does; no analysis of these data can do better. Only a simulator knows the truth it needs.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from daror_runtime.errors import DataError
from daror_runtime.residual.data import ResidualInputs
from daror_runtime.residual.diagnosis import Closure, closure, diagnose
from daror_runtime.residual.evidence import DiagnosisSettings
from hal.robot import FloatArray, RobotDescription


def floor_of_the_same_runs(
    inputs: ResidualInputs,
    amplitudes_nm: FloatArray,
    travel_rad: float,
    description: RobotDescription,
    unknown_state: np.ndarray | None = None,
    base_kind: str = "plf+",
    dummy_arm: bool = False,
) -> Closure:
    """The base model on ``inputs`` with the plant's true hysteresis taken out: its ``after`` is the floor (Nm).

    Args:
        inputs: the training and validation runs, with their histories (raw logs or points in order).
        amplitudes_nm: the plant's hysteresis amplitude per joint (4,), Nm.
        travel_rad: the plant's travel constant, rad.
        description: the robot description the base model is built from.
        unknown_state: as :func:`~daror_runtime.residual.diagnosis.closure` takes it: the floor is
            then also given without the points whose state no log determines (``undetermined``).
        base_kind, dummy_arm: the base model, as the analysis used it.

    Raises:
        DataError: the inputs carry no history to compute the hysteresis state from.
    """
    if inputs.train_history is None or inputs.validate_history is None:
        raise DataError(f"{inputs.train.source}: no history of the points; the floor needs the runs' paths")
    truth = np.asarray(amplitudes_nm, dtype=float)
    without = [
        dataclasses.replace(data, tau_nm=data.tau_nm - truth * history.states(travel_rad))
        for data, history in ((inputs.train, inputs.train_history), (inputs.validate, inputs.validate_history))
    ]
    plain = diagnose(without[0], description, base_kind, DiagnosisSettings(families=()), dummy_arm)
    return closure(plain, without[1], unknown_state)
