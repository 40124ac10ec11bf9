"""Where a model is extrapolating: the points of a dataset outside the range it was trained on (issue 24).

A model file records the joint angles its training data spanned (``training.q_min_rad`` and
``training.q_max_rad``, :class:`~daror_runtime.models.files.TrainingSummary`). A point is *outside*
that range when any joint lies more than :data:`TOLERANCE_RAD` below its minimum or above its
maximum. A model's error there is extrapolation, and a network's in particular can be anything: on
a session's closed-loop validation run (166 points, 106 of them outside the static training set's
range) a PENN's RMSE was 0.91 Nm against PLF+'s 0.43 Nm, which one RMSE over all points does not
explain. :func:`extrapolation` gives, per model, how many points lie outside and the RMSE (Eq. 4.31)
inside and outside the range separately.

The A Priori model built without data has no training range (its file has no ``training``): it
was never fitted, so nothing is extrapolated and the result is None.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.base import CompensationModel
from hal.errors import ShapeError
from hal.robot import N_JOINTS, FloatArray

__all__ = [
    "TOLERANCE_RAD",
    "Extrapolation",
    "TrainingRange",
    "extrapolation",
    "model_extrapolation",
    "outside_range",
]


class TrainingRange(Protocol):
    """The joint angles a model was trained on: a model file's ``training``
    (:class:`~daror_runtime.models.files.TrainingSummary`) is one."""

    @property
    def q_min_rad(self) -> Sequence[float]:
        """Smallest angle of each joint in the training data (rad, 4 values)."""
        ...

    @property
    def q_max_rad(self) -> Sequence[float]:
        """Largest angle of each joint in the training data (rad, 4 values)."""
        ...


#: How far (rad) a joint may lie beyond the training range and still count as inside: ten times the
#: spread of an encoder's readings at one stop (1e-4 rad, docs/data.md). The range's ends are
#: themselves measured points, so a validation stop at the same pose reads within the noise of
#: them, and a strict comparison would call half of such repeats extrapolation.
TOLERANCE_RAD = 1e-3


@dataclass(frozen=True)
class Extrapolation:
    """How many points of a dataset lie outside a model's training range, and its errors inside and outside.

    Attributes:
        n_points: points in the dataset.
        n_outside: points with at least one joint outside the training range (beyond the tolerance).
        outside_per_joint: for each joint, the points where that joint is outside (a point may count
            for several joints).
        rmse_inside_nm: RMSE (Nm, Eq. 4.31: every joint of every point) over the points inside;
            None when there is none.
        rmse_outside_nm: the same over the points outside; None when there is none.
        q_min_rad, q_max_rad: the training range (rad, per joint).
        tolerance_rad: the tolerance used (rad).
    """

    n_points: int
    n_outside: int
    outside_per_joint: tuple[int, int, int, int]
    rmse_inside_nm: float | None
    rmse_outside_nm: float | None
    q_min_rad: tuple[float, float, float, float]
    q_max_rad: tuple[float, float, float, float]
    tolerance_rad: float

    @property
    def n_inside(self) -> int:
        """Points inside the training range."""
        return self.n_points - self.n_outside

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: ``points``, ``outside``, ``outside_per_joint``, ``rmse_inside``, ``rmse_outside`` (Nm or
        null), ``q_min``, ``q_max`` (rad), ``tolerance_rad``."""
        return {
            "points": self.n_points,
            "outside": self.n_outside,
            "outside_per_joint": list(self.outside_per_joint),
            "rmse_inside": self.rmse_inside_nm,
            "rmse_outside": self.rmse_outside_nm,
            "q_min": list(self.q_min_rad),
            "q_max": list(self.q_max_rad),
            "tolerance_rad": self.tolerance_rad,
        }


def outside_range(
    q_rad: FloatArray, q_min_rad: FloatArray, q_max_rad: FloatArray, tolerance_rad: float = TOLERANCE_RAD
) -> np.ndarray:
    """Per point and joint, whether the joint lies more than ``tolerance_rad`` outside ``[q_min, q_max]``: (N, 4) bool.

    Raises:
        ShapeError: ``q_rad`` is not (N, 4), or a bound is not 4 values.
    """
    q = np.asarray(q_rad, dtype=float)
    low = np.asarray(q_min_rad, dtype=float)
    high = np.asarray(q_max_rad, dtype=float)
    if q.ndim != 2 or q.shape[1] != N_JOINTS or low.shape != (N_JOINTS,) or high.shape != (N_JOINTS,):
        raise ShapeError(f"expected q (N, 4) and bounds of 4 values, got {q.shape}, {low.shape} and {high.shape}")
    return (q < low - tolerance_rad) | (q > high + tolerance_rad)


def _rmse(error: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(error**2))) if error.size else None


def extrapolation(
    training: TrainingRange | None,
    q_rad: FloatArray,
    tau_measured_nm: FloatArray,
    tau_model_nm: FloatArray,
    tolerance_rad: float = TOLERANCE_RAD,
) -> Extrapolation | None:
    """The points of ``q_rad`` outside the training range of ``training``, and the RMSE inside and outside it.

    Args:
        training: the model file's ``training`` (its ``q_min_rad``, ``q_max_rad``); None for a model
            that was never fitted (A Priori without data).
        q_rad: joint angles of the dataset (rad, (N, 4)).
        tau_measured_nm, tau_model_nm: measured and model torque at those points (Nm, (N, 4)).
        tolerance_rad: how far beyond the range still counts as inside (rad, :data:`TOLERANCE_RAD`).

    Returns:
        None when ``training`` is None; else the counts and the two RMSEs (None where no point is).

    Raises:
        ShapeError: arrays that are not (N, 4) of one N.
    """
    if training is None:
        return None
    measured = np.asarray(tau_measured_nm, dtype=float)
    model = np.asarray(tau_model_nm, dtype=float)
    q = np.asarray(q_rad, dtype=float)
    if measured.shape != model.shape or measured.shape != q.shape:
        raise ShapeError(
            f"expected q and two torque arrays of one shape (N, 4), got {q.shape}, {measured.shape}, {model.shape}"
        )
    beyond = outside_range(q, training.q_min_rad, training.q_max_rad, tolerance_rad)
    outside = beyond.any(axis=1)
    error = measured - model
    return Extrapolation(
        n_points=int(q.shape[0]),
        n_outside=int(outside.sum()),
        outside_per_joint=tuple(int(v) for v in beyond.sum(axis=0)),  # type: ignore[arg-type]
        rmse_inside_nm=_rmse(error[~outside]),
        rmse_outside_nm=_rmse(error[outside]),
        q_min_rad=tuple(float(v) for v in training.q_min_rad),  # type: ignore[arg-type]
        q_max_rad=tuple(float(v) for v in training.q_max_rad),  # type: ignore[arg-type]
        tolerance_rad=float(tolerance_rad),
    )


def model_extrapolation(
    model: CompensationModel,
    training: TrainingRange | None,
    data: StationaryDataset,
    signal: FloatArray | None = None,
    tolerance_rad: float = TOLERANCE_RAD,
) -> Extrapolation | None:
    """:func:`extrapolation` of ``model`` on ``data``, predicting with ``signal`` (:meth:`CompensationModel.predict`).

    ``training``: the ``training`` of the model's file (``load_model(path)[1].training``, or the
    :func:`~daror_runtime.models.files.training_summary` a fit saved); None: no range, None returned.
    ``signal``: what the model predicts with (None: the dataset's ``dir``; a hysteresis model's
    state: ``daror_runtime.residual.data.prediction_signal``).
    """
    if training is None:
        return None
    direction = data.direction if signal is None else signal
    return extrapolation(training, data.q_rad, data.tau_nm, model.predict(data.q_rad, direction), tolerance_rad)
