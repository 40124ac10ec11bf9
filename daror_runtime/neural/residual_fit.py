"""Networks on what a physical model leaves: the fitter of ``penn-residual`` and the residual networks.

* :func:`residual_dataset`: the training data minus a base model's prediction (Nm);
* :func:`fit_residual_network`: a PENN or an NNN trained on that residual (the residual preset,
  :func:`daror_runtime.neural.presets.residual_preset`), as a plain network model;
* :func:`fit_penn_residual`: the registry's fitter of ``penn-residual``: fit the base kind, then a
  PENN on its residual, composed into a :class:`~daror_runtime.models.penn_residual.PennResidualModel`.

The base is fitted first and stays fixed: the network learns only what the base cannot, so the
base keeps its physical parameters and the network never competes with them.
"""

from __future__ import annotations

import time
from typing import Literal

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import ConfigurationError
from daror_runtime.models.base import CompensationModel, FitReport, FitResult
from daror_runtime.models.metrics import error_metrics
from daror_runtime.models.neural import PennModel
from daror_runtime.models.penn_residual import PennResidualModel
from daror_runtime.models.registry import NetworkOptions, PennResidualOptions, fit_model, options_for
from daror_runtime.neural.fit import fit_network
from hal.robot import RobotDescription

__all__ = ["fit_penn_residual", "fit_residual_network", "residual_dataset"]


def residual_dataset(dataset: StationaryDataset, base: CompensationModel) -> StationaryDataset:
    """``dataset`` with each torque replaced by what ``base`` leaves of it: ``tau - base.predict(q, dir)`` (Nm).

    The base's prediction includes the sensor effects it knows (an augmented model's direction
    term), so the residual holds only what the base cannot explain.
    """
    remaining = dataset.tau_nm - base.predict(dataset.q_rad, dataset.direction)
    return StationaryDataset(
        dataset.q_rad, remaining, dataset.direction, dataset.t_s, f"{dataset.source} (residual of {base.name})"
    )


def fit_residual_network(
    model: Literal["penn", "nnn"],
    base: CompensationModel,
    dataset: StationaryDataset,
    description: RobotDescription,
    options: NetworkOptions | None = None,
) -> FitResult:
    """A PENN or NNN trained on what ``base`` leaves of ``dataset`` (the residual preset, overridden by ``options``).

    The result's model outputs the residual torque only (Nm); add the base's to compare with data.

    Raises:
        IdentifiabilityError: too few points for the validation folds.
        TrainingDivergedError: the training diverged.
        ModelOptionError: options that make no network.
    """
    return fit_network(model, residual_dataset(dataset, base), description, options or NetworkOptions(), residual=True)


def fit_penn_residual(
    dataset: StationaryDataset, description: RobotDescription, options: PennResidualOptions
) -> FitResult:
    """``daror fit penn-residual``: fit the base kind (``options.base``), then a PENN on its residual.

    Raises:
        IdentifiabilityError: the data cannot identify the base, or are too few for the folds.
        TrainingDivergedError: the network's training diverged.
        ModelOptionError: options that make no network.
    """
    start = time.perf_counter()
    base_options = options_for(options.base, {} if options.dummy_arm is None else {"dummy_arm": options.dummy_arm})
    base_fit = fit_model(options.base, dataset, description, base_options)
    network_fit = fit_residual_network("penn", base_fit.model, dataset, description, options)
    residual = network_fit.model
    if not isinstance(residual, PennModel):  # fit_network("penn") builds one; a guard, not a branch
        raise ConfigurationError(f"fit_network('penn') built a {type(residual).__name__}")
    model = PennResidualModel(description, base_fit.model, residual, options.name)
    base_training = error_metrics(dataset.tau_nm, base_fit.model.predict(dataset.q_rad, dataset.direction))
    training = error_metrics(dataset.tau_nm, model.predict(dataset.q_rad, dataset.direction))
    notes = (
        f"base {base_fit.model.name} ({options.base}) fitted first: training RMSE {base_training.rmse_nm:.4g} Nm; "
        f"with the PENN residual {training.rmse_nm:.4g} Nm",
        *(f"base: {n}" for n in base_fit.report.notes),
        *network_fit.report.notes,
    )
    report = FitReport(
        kind=PennResidualModel.kind,
        n_points=len(dataset),
        training=training,
        duration_s=time.perf_counter() - start,
        notes=notes,
    )
    return FitResult(model, report)
