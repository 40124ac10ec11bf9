"""Training and validating the session's compensation model (state ``training``), outside the tick.

A model is *validated* when its RMSE on a validation dataset (Eq. 4.31, over all joints) is at
most the session's ``max_validation_rmse_nm``; the guard ``model_trained_and_validated`` reads
exactly that. Training fits the session's model kind on the identification's training data and
validates it on its validation data; selecting an existing model file validates it the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import structlog

from daror_runtime.data.load import load_stationary
from daror_runtime.errors import ModelFileError
from daror_runtime.fsm.signals import SelectedModel
from daror_runtime.models.base import CompensationModel
from daror_runtime.models.files import load_model, save_model, training_summary
from daror_runtime.models.metrics import ErrorMetrics, error_metrics
from daror_runtime.models.registry import FitOptions, fit_model
from daror_runtime.session.identification import next_free_path
from hal.robot import RobotDescription

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class TrainedModel:
    model: CompensationModel
    selected: SelectedModel
    validation: ErrorMetrics


def validate(model: CompensationModel, validation_path: Path) -> ErrorMetrics:
    """The model's errors on a validation dataset (a stationary dataset or a raw log).

    Raises:
        DataError: the file is missing or malformed.
    """
    data = load_stationary(validation_path)
    return error_metrics(data.tau_nm, model.predict(data.q_rad, data.direction))


def train_model(
    kind: str,
    training_path: Path,
    validation_path: Path,
    description: RobotDescription,
    dummy_arm: bool,
    max_rmse_nm: float,
    directory: Path,
) -> TrainedModel:
    """Fit ``kind`` on the training data, validate it, and save the model file (atomically).

    Raises:
        DataError, IdentifiabilityError: the data cannot train the model.
    """
    training = load_stationary(training_path)
    result = fit_model(kind, training, description, FitOptions(dummy_arm=dummy_arm))
    metrics = validate(result.model, validation_path)
    path = next_free_path(directory, f"model_{kind.replace('+', '_plus')}", ".json")
    save_model(path, result.model, training_summary(training, training_path), result.report)
    selected = SelectedModel(result.model.name, kind, path, metrics.rmse_nm, max_rmse_nm)
    log.info(
        "model trained",
        kind=kind,
        path=str(path),
        training_points=len(training),
        validation_rmse_nm=round(metrics.rmse_nm, 4),
        validated=selected.validated,
        max_rmse_nm=max_rmse_nm,
    )
    return TrainedModel(result.model, selected, metrics)


def select_model_file(
    path: Path, validation_path: Path, max_rmse_nm: float, description: RobotDescription
) -> TrainedModel:
    """Load a model file fitted for this robot's geometry and validate it on ``validation_path``.

    Raises:
        ModelFileError: the model file is unreadable, corrupted, or fitted for another geometry.
        DataError: the validation file is.
    """
    model, document = load_model(path)
    if document.robot.geometry != description.geometry:
        raise ModelFileError(f"{path}: the model was fitted for another robot geometry than this session's")
    metrics = validate(model, validation_path)
    selected = SelectedModel(model.name, document.kind, path, metrics.rmse_nm, max_rmse_nm)
    log.info(
        "model selected",
        path=str(path),
        kind=document.kind,
        validation=str(validation_path),
        validation_rmse_nm=round(metrics.rmse_nm, 4),
        validated=selected.validated,
    )
    return TrainedModel(model, selected, metrics)
