"""The registry's fitters of the neural kinds: ``fit_penn`` and ``fit_nnn`` (``daror fit penn|nnn``).

A fit trains the preset's initialisations together (:func:`daror_runtime.neural.training.train_group`,
the same code path as the hyper-parameter search), keeps the one with the best minimal validation
loss (Sec. 4.2.3) and builds the model from its final fit on all the data. The report's notes say
what was trained, the MVL of every initialisation, the chosen one and the time it took; a fit
whose network gives (nearly) zero torque says so and why.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

import numpy as np

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DarorError
from daror_runtime.models.base import FitReport, FitResult
from daror_runtime.models.metrics import error_metrics
from daror_runtime.models.neural import MAX_WIDTH, NeuralModel, NnnModel, PennModel
from daror_runtime.neural.compile_cache import use_compilation_cache
from daror_runtime.neural.ensemble import mean_network
from daror_runtime.neural.presets import Preset, init_seeds, preset, residual_preset, with_options
from daror_runtime.neural.training import NetworkResult, train_group
from hal.robot import RobotDescription

if TYPE_CHECKING:
    from daror_runtime.models.registry import NetworkOptions

__all__ = ["COLLAPSE_FRACTION", "TrainingDivergedError", "fit_network", "fit_nnn", "fit_penn"]

#: A model whose torque's RMS over the training points is below this fraction of the data's has
#: collapsed (learned nothing): the report says so.
COLLAPSE_FRACTION = 0.05


class TrainingDivergedError(DarorError):
    """Training produced weights that are not finite numbers (exit code 1: nothing is written)."""


def fit_penn(dataset: StationaryDataset, description: RobotDescription, options: NetworkOptions) -> FitResult:
    """A PENN (Sec. 3.2.2, 4.2.3) on stationary data, with the options' preset and overrides.

    Raises:
        IdentifiabilityError: too few points for the validation folds.
        TrainingDivergedError: the training diverged.
        ModelOptionError: options that make no network (from :func:`resolve`).
    """
    return fit_network("penn", dataset, description, options)


def fit_nnn(dataset: StationaryDataset, description: RobotDescription, options: NetworkOptions) -> FitResult:
    """An NNN (Sec. 3.1.1, 4.2.4) on stationary data; as :func:`fit_penn`."""
    return fit_network("nnn", dataset, description, options)


def resolve(model: str, options: NetworkOptions, residual: bool = False) -> Preset:
    """The preset a fit of ``model`` with ``options`` trains: the default or thesis preset (with
    ``residual``, the residual preset), overridden field by field.

    Raises:
        ModelOptionError: a combination of options that makes no network (one line).
    """
    from pydantic import ValidationError

    from daror_runtime.models.registry import ModelOptionError

    start = residual_preset if residual else preset
    try:
        chosen = with_options(start(model, bool(options.thesis)), options)
    except ValidationError as exc:
        problem = exc.errors()[0]
        raise ModelOptionError(f"model kind {model}: {problem['msg'].removeprefix('Value error, ')}") from None
    if chosen.ensemble and chosen.inits * chosen.spec.width > MAX_WIDTH:
        raise ModelOptionError(
            f"model kind {model}: the mean of {chosen.inits} networks of {chosen.spec.width} units is one network of "
            f"{chosen.inits * chosen.spec.width} units; at most {MAX_WIDTH} (fewer --inits or a smaller --width)"
        )
    return chosen


def _finite(results: list[NetworkResult]) -> list[NetworkResult]:
    """The results whose MVL and weights are finite (training did not diverge)."""
    return [r for r in results if math.isfinite(r.mvl) and np.all(np.isfinite(r.parameters))]


def _best(results: list[NetworkResult]) -> NetworkResult | None:
    """The result with the lowest MVL among those whose MVL and weights are finite (ties: the lower seed);
    None when training diverged for every one."""
    finite = _finite(results)
    return min(finite, key=lambda r: (r.mvl, r.seed)) if finite else None


def fit_network(
    model: str,
    dataset: StationaryDataset,
    description: RobotDescription,
    options: NetworkOptions,
    residual: bool = False,
) -> FitResult:
    """Train the initialisations of ``model``'s preset together, keep the best MVL's final fit.

    ``residual``: start from the residual preset (a network on what a physical model leaves,
    :func:`daror_runtime.neural.presets.residual_preset`) instead of the default.

    Raises:
        IdentifiabilityError: too few points for the validation folds.
        TrainingDivergedError: the chosen network's weights are not finite.
        ModelOptionError: options that make no network.
    """
    start = time.perf_counter()
    use_compilation_cache()  # a later process with the same network loads its programs instead of compiling
    chosen = resolve(model, options, residual)
    seed = 0 if options.seed is None else options.seed
    seeds = init_seeds(seed, chosen.inits)
    results = train_group(chosen.spec, dataset, [chosen.l1], seeds, chosen.settings)
    best = _best(results)
    if best is None or (chosen.ensemble and len(_finite(results)) < len(results)):
        raise TrainingDivergedError(
            f"{model}: training diverged (weights not finite) for "
            f"{'an' if best is not None else 'every'} initialisation of {chosen.describe()}; "
            "try another --seed, fewer --adam-steps or a smaller network"
        )
    network = mean_network([r.network() for r in results]) if chosen.ensemble else best.network()
    model_cls: type[NeuralModel] = PennModel if model == "penn" else NnnModel
    fitted = model_cls(description, network, options.name)
    predicted = fitted.torque_batch(dataset.q_rad)
    training = error_metrics(dataset.tau_nm, predicted)
    duration = time.perf_counter() - start
    notes = _notes(chosen, seed, results, best, dataset, predicted)
    report = FitReport(
        kind=model,
        n_points=len(dataset),
        training=training,
        duration_s=duration,
        notes=tuple(notes),
    )
    return FitResult(fitted, report)


def _notes(
    chosen: Preset,
    seed: int,
    results: list[NetworkResult],
    best: NetworkResult,
    dataset: StationaryDataset,
    predicted: np.ndarray,
) -> list[str]:
    settings = chosen.settings
    loss_unit = "" if settings.loss == "scaled" else " Nm^2"
    mvls = ", ".join(f"seed {r.seed}: {r.mvl:.5g}{loss_unit} at step {r.mvl_step}" for r in results)
    notes = [
        chosen.describe(),
        f"{len(results)} initialisations trained together; minimal validation loss {mvls}",
        (
            f"the model is the mean of all {len(results)} initialisations' networks, each "
            + ("fitted on all the points" if settings.final_fit else "its fold network")
            + f" at its stopping step (the last within {settings.stop_tolerance:.0%} of its MVL: "
            + ", ".join(f"seed {r.seed} step {r.stop_step}" for r in results)
            + ")"
        )
        if chosen.ensemble
        else f"chosen: seed {best.seed} (MVL {best.mvl:.5g}{loss_unit} at step {best.mvl_step} of {settings.steps}); "
        f"stopped at step {best.stop_step}, the last within {settings.stop_tolerance:.0%} of the MVL"
        + (
            f"; the model is the fit on all {len(dataset)} points at that step "
            f"(training loss {best.final_train_loss:.5g}{loss_unit})"
            if settings.final_fit and best.final_train_loss is not None
            else f"; the model is the fold network at that step (trained on {settings.folds - 1} of {settings.folds} blocks)"
        ),
        f"training time {best.wall_s:.2f} s wall, {best.cpu_s:.2f} s CPU (compiling {best.compile_s:.2f} s); "
        f"fit seed {seed}",
    ]
    data_rms = float(np.sqrt(np.mean(dataset.tau_nm**2)))
    model_rms = float(np.sqrt(np.mean(predicted**2)))
    if data_rms > 0 and model_rms < COLLAPSE_FRACTION * data_rms:
        mean_abs = float(np.mean(np.abs(best.parameters)))
        if chosen.l1 > 0:
            penalty, error, remedy = (
                (f"lambda {chosen.l1:g} times the sum of |weights|, Eq. 3.7", "the torque error in Nm^2",
                 "the scaled loss (the default, without --thesis) avoids this")
                if settings.loss == "thesis"
                else (f"lambda {chosen.l1:g} times the mean |weight|", "the scaled torque error",
                      "a smaller --l1 avoids this")
            )  # fmt: skip
            why = (
                f"the L1 penalty ({penalty}) outweighed {error}: the torque is a product of the layers' weights, "
                "so near zero the error's gradient vanishes while the penalty's stays lambda, and training drove "
                f"every weight to zero; {remedy}"
            )
        else:
            why = "training never moved the network away from zero torque; try more --adam-steps or another --seed"
        notes.append(
            f"COLLAPSED: the model's torque is {model_rms:.3g} Nm RMS against the data's {data_rms:.3g} Nm "
            f"(mean |weight| {mean_abs:.2g}): {why}"
        )
    return notes
