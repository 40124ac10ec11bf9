"""The model kinds the runtime knows, looked up by name, imported lazily.

Like python-can's backend registry: a kind maps to ``module:attribute`` strings, so a kind whose
optional extra is missing (the neural models need ``jax``) costs nothing until it is used, and
then fails with a message that says which extra to install.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import ExtraMissingError, UnknownModelKindError
from daror_runtime.models.base import CompensationModel, FitResult
from hal.robot import RobotDescription


@dataclass(frozen=True)
class FitOptions:
    """Settings a fit may use; each kind reads the ones it understands."""

    name: str | None = None
    dummy_arm: bool = False  # ap: add theta_DA (Eq. 4.5)
    elbow_stiffness: bool | None = None  # ap: add Eq. 4.7; default: with the Dummy Arm
    seed: int = 0  # neural models: initialisation and shuffling


@dataclass(frozen=True)
class ModelKind:
    kind: str
    summary: str
    model: str  # "module:Class"
    fitter: str  # "module:function(dataset, description, options) -> FitResult"
    extra: str | None = None


def _fit_ap(dataset: StationaryDataset | None, description: RobotDescription, options: FitOptions) -> FitResult:
    from daror_runtime.models.linear import build_ap

    stiffness = options.dummy_arm if options.elbow_stiffness is None else options.elbow_stiffness
    return build_ap(description, dataset, options.dummy_arm, stiffness, options.name)


def _fit_plf(dataset: StationaryDataset, description: RobotDescription, options: FitOptions) -> FitResult:
    from daror_runtime.models.linear import fit_plf

    return fit_plf(dataset, description, options.name)


def _fit_plf_plus(dataset: StationaryDataset, description: RobotDescription, options: FitOptions) -> FitResult:
    from daror_runtime.models.linear import fit_plf_plus

    return fit_plf_plus(dataset, description, options.name)


def _fit_augmented(dataset: StationaryDataset, description: RobotDescription, options: FitOptions) -> FitResult:
    from daror_runtime.residual.model import fit_augmented

    return fit_augmented(dataset, description, options.name)


KINDS: dict[str, ModelKind] = {
    k.kind: k
    for k in (
        ModelKind(
            "ap",
            "A Priori: design parameters (+ Dummy Arm, + elbow stiffness), Sec. 4.1",
            "daror_runtime.models.linear:APModel",
            f"{__name__}:_fit_ap",
        ),
        ModelKind(
            "plf",
            "Parameter Linear Form, least squares, Sec. 4.2.1",
            "daror_runtime.models.linear:PLFModel",
            f"{__name__}:_fit_plf",
        ),
        ModelKind(
            "plf+",
            "PLF + fifth-order elbow stiffness polynomial, Sec. 4.2.2",
            "daror_runtime.models.linear:PLFPlusModel",
            f"{__name__}:_fit_plf_plus",
        ),
        ModelKind(
            "augmented",
            "a base model plus the physical effects the data support (daror residual)",
            "daror_runtime.residual.model:AugmentedModel",
            f"{__name__}:_fit_augmented",
        ),
    )
}

#: Kinds that may be fitted without training data.
NO_DATA_KINDS = frozenset({"ap"})


def kind_entry(kind: str) -> ModelKind:
    """The registry entry of ``kind``.

    Raises:
        UnknownModelKindError: ``kind`` is not registered.
    """
    try:
        return KINDS[kind]
    except KeyError:
        raise UnknownModelKindError(f"unknown model kind {kind!r}; expected one of {', '.join(KINDS)}") from None


def _resolve(target: str, entry: ModelKind) -> object:
    module_name, attribute = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        if entry.extra is None:
            raise
        raise ExtraMissingError(
            f"model kind {entry.kind} needs the optional extra '{entry.extra}' "
            f"(pip install 'daror-runtime[{entry.extra}]'): {exc}"
        ) from None
    return getattr(module, attribute)


def model_class(kind: str) -> type[CompensationModel]:
    """The class implementing ``kind`` (imported on first use)."""
    entry = kind_entry(kind)
    return _resolve(entry.model, entry)  # type: ignore[return-value]


def fit_model(
    kind: str, dataset: StationaryDataset | None, description: RobotDescription, options: FitOptions | None = None
) -> FitResult:
    """Fit (or, for AP, build) a model of ``kind``.

    Raises:
        UnknownModelKindError, IdentifiabilityError, ExtraMissingError.
    """
    entry = kind_entry(kind)
    fitter: Callable[..., FitResult] = _resolve(entry.fitter, entry)  # type: ignore[assignment]
    return fitter(dataset, description, options or FitOptions())
