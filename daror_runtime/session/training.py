"""Training and validating the session's compensation model (state ``training``), outside the tick.

A model is *validated* when its RMSE on a validation dataset (Eq. 4.31, over all joints) is at
most the session's ``max_validation_rmse_nm``; the guard ``model_trained_and_validated`` reads
exactly that. Training fits the session's model kind on the identification's training data and
validates it on its validation data; selecting an existing model file validates it the same way,
on held-out data (never the file it was trained on). Files are read and checked in the caller's
thread, so a bad file is refused when it is named; only the validation itself is a job.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import structlog

from daror_runtime.data.checksum import file_sha256
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import InputError, ModelFileError, UsageError
from daror_runtime.fsm.signals import SelectedModel
from daror_runtime.models.base import CompensationModel
from daror_runtime.models.extrapolation import Extrapolation, model_extrapolation
from daror_runtime.models.files import TrainingSummary, load_model, save_model, training_summary
from daror_runtime.models.metrics import ErrorMetrics, error_metrics
from daror_runtime.models.registry import fit_model, installation_options, kind_entry
from daror_runtime.session.identification import next_free_path
from hal.robot import FloatArray, RobotDescription

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class TrainedModel:
    model: CompensationModel
    selected: SelectedModel
    validation: ErrorMetrics
    extrapolation: Extrapolation | None = None  # the validation points outside the training range (issue 24)


def validation_errors(model: CompensationModel, data: StationaryDataset, signal: FloatArray | None) -> ErrorMetrics:
    """The model's errors (Eq. 4.31-4.32) on a validation dataset, predicting with ``signal``.

    ``signal``: what :func:`daror_runtime.residual.data.prediction_signal` gives for the model and
    the file: the sign of the last motion, or a hysteresis model's state along the run's path.
    """
    return error_metrics(data.tau_nm, model.predict(data.q_rad, signal))


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

    The kind's options follow from the installed robot (``dummy_arm``: the A Priori model includes
    the Dummy Arm; a fitted kind learns it from the data).

    Raises:
        UnknownModelKindError: ``kind`` is not registered.
        UsageError: the registry does not let a session train ``kind`` (capability ``session_training``).
        DataError, IdentifiabilityError: the data cannot train the model.
    """
    # here: data.load brings the table readers along (~25 ms), which a session's start-up does not need
    from daror_runtime.data.load import load_stationary

    entry = kind_entry(kind)
    if not entry.session_training:
        raise UsageError(f"model kind {kind} cannot be trained in a session")
    training = load_stationary(training_path)
    result = fit_model(kind, training, description, installation_options(kind, dummy_arm))
    from daror_runtime.residual.data import prediction_signal  # the analysis's path reader, when asked for

    validation = load_stationary(validation_path)
    metrics = validation_errors(result.model, validation, prediction_signal(result.model, validation, validation_path))
    path = next_free_path(directory, f"model_{kind.replace('+', '_plus')}", ".json")
    summary = training_summary(training, training_path)
    save_model(path, result.model, summary, result.report)
    extrapolated = model_extrapolation(
        result.model, summary, validation, prediction_signal(result.model, validation, validation_path)
    )
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
    return TrainedModel(result.model, selected, metrics, extrapolated)


class NotHeldOutError(InputError):
    """The validation data is the model's own training data: a validation on it says nothing."""


@dataclass(frozen=True)
class ModelCandidate:
    """A model file and its validation data, both read and checked (in the caller's thread)."""

    model: CompensationModel
    kind: str
    path: Path
    validation: StationaryDataset
    validation_path: Path
    signal: FloatArray | None  # what the model predicts the validation readings with (prediction_signal)
    training: TrainingSummary | None  # what the model file says it was trained on (its range of joint angles)


def read_model_candidate(path: Path, validation_path: Path, description: RobotDescription) -> ModelCandidate:
    """Read a model file fitted for this robot and its validation data; refuse what cannot be validated.

    The validation file's signal map is judged from physics (issue 27, docs/data.md) and a failed
    one refused: the session's gate has no ``--trust-signal-map`` (a model validated on columns that
    are not what their names say was not validated).

    Raises:
        ModelFileError: the model file is missing, unreadable, corrupted, or fitted for another geometry.
        DataError: the validation file is missing or malformed, or (SignalMapError) its columns are
            not what their names say.
        NotHeldOutError: the validation file is the one the model was trained on.
        DataError: the raw log beside the validation file (a hysteresis model's path) is not this run's.
    """
    from daror_runtime.data.load import load_stationary_checked

    model, document = load_model(path)
    if document.robot.geometry != description.geometry:
        raise ModelFileError(f"{path}: the model was fitted for another robot geometry than this session's")
    validation, _ = load_stationary_checked(
        validation_path, description, remedy="a session validates a model only on data whose columns are what they say"
    )
    training = document.training
    if training is not None and training.sha256 is not None and training.sha256 == file_sha256(validation_path):
        raise NotHeldOutError(
            f"{validation_path}: this is the data {path} was trained on; validate it on held-out data of this pilot"
        )
    from daror_runtime.residual.data import prediction_signal  # the analysis's path reader, when asked for

    signal = prediction_signal(model, validation, validation_path)  # a raw log, read here with the other files
    return ModelCandidate(model, document.kind, Path(path), validation, Path(validation_path), signal, training)


def validate_candidate(candidate: ModelCandidate, max_rmse_nm: float) -> TrainedModel:
    """The candidate's errors on its validation data, and whether that validates it (a job: outside the tick)."""
    metrics = validation_errors(candidate.model, candidate.validation, candidate.signal)
    extrapolated = model_extrapolation(candidate.model, candidate.training, candidate.validation, candidate.signal)
    selected = SelectedModel(candidate.model.name, candidate.kind, candidate.path, metrics.rmse_nm, max_rmse_nm)
    log.info(
        "model validated",
        path=str(candidate.path),
        kind=candidate.kind,
        validation=str(candidate.validation_path),
        validation_rmse_nm=round(metrics.rmse_nm, 4),
        validated=selected.validated,
        max_rmse_nm=max_rmse_nm,
    )
    return TrainedModel(candidate.model, selected, metrics, extrapolated)
