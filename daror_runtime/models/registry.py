"""The model kinds the runtime knows: the one list, looked up by name, imported lazily.

Like python-can's backend registry: a kind maps to ``module:attribute`` strings, so a kind whose
optional extra is missing (a neural model needing ``jax``) costs nothing until it is used, and
then fails with a message that says which extra to install. This module imports no numpy and no
model code: listing the kinds (help texts, the settings check) stays cheap.

Everything else that names kinds asks here: the session settings (``model_kind``), the console's
``train KIND``, the CLI's help and ``daror fit``, the residual analysis's base kinds, the model
files. What a kind supports is a *capability* of its entry (:class:`ModelKind`): whether it needs
training data, whether the residual analysis can augment it, whether a session may train it. Each
kind has its own options model (:class:`ModelOptions` and subclasses, frozen, unknown fields
refused), so an option given to a kind that does not take it is refused, not ignored.

The built-in kinds (``ap``, ``plf``, ``plf+``, ``penn``, ``nnn``, ``penn-residual``) are listed
here. The neural kinds need the optional extra ``nn`` (JAX) to be *fitted* only: their fitters
live in ``daror_runtime.neural``, their model classes in ``daror_runtime.models.neural`` and
``daror_runtime.models.penn_residual`` (numpy and numba), so a neural model file loads and runs
on the base install. Other packages add kinds through
the entry point group :data:`ENTRY_POINT_GROUP`, each entry naming a :class:`ModelKind` object
(this project's ``augmented`` kind comes from ``daror_runtime.residual`` that way: the models
package never names the residual analysis). The entry points are read once, the first time a
name is not a built-in kind or the whole list is asked for; a plugin cannot replace a built-in
kind, and one that cannot be loaded is named in a warning and, when asked for, in the error.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Self

import structlog
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)

from daror_runtime.errors import DarorError, ExtraMissingError, UnknownModelKindError, UsageError

if TYPE_CHECKING:
    from daror_runtime.data.schema import StationaryDataset
    from daror_runtime.models.base import CompensationModel, FitResult
    from hal.robot import RobotDescription

__all__ = [
    "BUILTIN_KINDS",
    "ENTRY_POINT_GROUP",
    "APOptions",
    "ExtraNotInstalledError",
    "KindRegistry",
    "ModelKind",
    "ModelKindPluginError",
    "ModelOptionError",
    "ModelOptions",
    "NetworkOptions",
    "PennResidualOptions",
    "fit_model",
    "installation_options",
    "kind_entry",
    "kind_names",
    "kinds",
    "model_class",
    "options_for",
]

log = structlog.get_logger(__name__)

#: Entry point group through which a package registers model kinds (``pyproject.toml``)::
#:
#:     [project.entry-points."daror_runtime.model_kinds"]
#:     augmented = "daror_runtime.residual.kind:MODEL_KIND"
ENTRY_POINT_GROUP = "daror_runtime.model_kinds"


class ModelOptionError(UsageError):
    """An option a model kind does not take, or a value it cannot use (CLI exit code 2)."""


class ModelKindPluginError(DarorError):
    """A model kind registered through an entry point that cannot be used (a broken installation)."""


class ExtraNotInstalledError(ExtraMissingError, UsageError):
    """A model kind's optional extra is not installed: one line saying what to install (CLI exit code 2).

    An :class:`~daror_runtime.errors.ExtraMissingError` (what callers catch) that is also a
    :class:`UsageError`: like a HAL backend that is not installed
    (``hal.errors.BackendUnavailableError``), the person asked for something this installation
    cannot do until they install it, and nothing was written.
    """


# --- options ----------------------------------------------------------------------------------


class ModelOptions(BaseModel):
    """Options of a kind that takes nothing but a name (PLF, PLF+, augmented); base of every options model.

    Frozen; an unknown field is refused (``extra="forbid"``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str | None = Field(None, description="model name shown in tables; default the kind's display name")

    @classmethod
    def for_installation(cls, dummy_arm: bool, name: str | None = None) -> Self:
        """The options of this kind that follow from the installed robot (``dummy_arm``: the Dummy Arm is on).

        A fitted kind learns the Dummy Arm from the data and takes only the name; AP overrides this.
        """
        return cls(name=name)


class APOptions(ModelOptions):
    """Options of the A Priori model (Sec. 4.1): which design terms it includes."""

    dummy_arm: StrictBool = Field(False, description="add the Dummy Arm's theta_DA (Eq. 4.5)")
    elbow_stiffness: StrictBool | None = Field(
        None, description="add the first-order elbow stiffness (Eq. 4.7); None: with the Dummy Arm"
    )

    @property
    def with_elbow_stiffness(self) -> bool:
        """Whether the elbow stiffness is included: as given, or with the Dummy Arm when not given."""
        return self.dummy_arm if self.elbow_stiffness is None else self.elbow_stiffness

    @classmethod
    def for_installation(cls, dummy_arm: bool, name: str | None = None) -> Self:
        """AP with the Dummy Arm (and its elbow stiffness) exactly when it is installed."""
        return cls(name=name, dummy_arm=dummy_arm)


class NetworkOptions(ModelOptions):
    """Options of the neural kinds PENN and NNN (``daror_runtime.neural.presets``): None keeps the preset's value.

    The preset is the default network (or, with ``thesis``, the thesis's Table I / II network and
    its loss, Eq. 3.7); each option given replaces one field of it. Values are checked here; a
    combination that makes no network (too many weights) is refused by the fitter.
    """

    seed: StrictInt | None = Field(
        None, ge=0, le=2**53 // 1000 - 1, description="seed of the initialisations (default 0)"
    )
    thesis: StrictBool | None = Field(
        None, description="start from the thesis's network and loss (Tables I, II; Eq. 3.7)"
    )
    layers: StrictInt | None = Field(None, ge=1, le=32, description="hidden layers")
    width: StrictInt | None = Field(None, ge=1, le=256, description="units per hidden layer")
    activation: Literal["tanh", "sigmoid", "relu", "softplus"] | None = Field(None, description="of the hidden layers")
    inputs: Literal["q", "sincos"] | None = Field(None, description="q, or [sin q, cos q] (Eq. 4.28)")
    l1: float | None = Field(None, ge=0.0, le=1e3, allow_inf_nan=False, description="L1 rate lambda")
    inits: StrictInt | None = Field(None, ge=1, le=100, description="initialisations trained; the best MVL is kept")
    folds: StrictInt | None = Field(None, ge=2, le=20, description="validation blocks of time (k)")
    adam_steps: StrictInt | None = Field(None, ge=0, le=1_000_000, description="full-batch Adam steps")
    lbfgs: StrictBool | None = Field(None, description="finish with L-BFGS")

    @field_validator("l1", mode="before")
    @classmethod
    def _l1_is_a_number(cls, value: object) -> object:
        if isinstance(value, bool | str):  # pydantic would read true as 1.0 and "0.1" as 0.1
            raise ValueError(f"expected a number, got {value!r}")
        return value


class PennResidualOptions(NetworkOptions):
    """Options of ``penn-residual``: the physical base fitted first, then the network (the residual preset's fields).

    ``base`` is a registered kind with the capability ``physical``; ``dummy_arm`` is passed to a
    base that takes it (AP) and refused for one that does not. The network options override the
    residual preset (``daror_runtime.neural.presets.residual_preset``), as for ``penn``.
    """

    base: str = Field("plf+", description="the physical model fitted first, on which the PENN learns the residual")
    dummy_arm: StrictBool | None = Field(None, description="a base that takes it (ap): include the Dummy Arm")

    @field_validator("base")
    @classmethod
    def _physical(cls, value: str) -> str:
        physical = kind_names(lambda entry: entry.physical)
        if value not in physical:
            raise ValueError(f"{value!r} is not a physical model kind; expected one of {', '.join(physical)}")
        return value

    @model_validator(mode="after")
    def _base_takes_the_dummy_arm(self) -> PennResidualOptions:
        if self.dummy_arm is not None and not kind_entry(self.base).takes("dummy_arm"):
            raise ValueError(f"the base model {self.base} takes no Dummy Arm (it learns it from the data)")
        return self


# --- entries ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelKind:
    """One registry entry: a model kind, where its code is, what it takes and what it supports.

    Attributes:
        kind: registry key and the ``kind`` field of model files (lower case).
        summary: one line for help texts.
        model: ``"module:Class"`` of its :class:`~daror_runtime.models.base.CompensationModel`.
        fitter: ``"module:function"``, ``function(dataset, description, options) -> FitResult``;
            ``dataset`` is None only for a kind that does not need data.
        options: its options model (a :class:`ModelOptions` subclass, or that class itself).
        extra: the optional dependency extra it needs (``nn``), named when it is missing.
        needs_data: False for a kind built from the robot description alone (AP).
        residual_base: the residual analysis (``daror residual --base``) can augment it.
        session_training: a session may train it (``train KIND``, ``model_kind`` of the settings).
        physical: a physical model (parameters with a physical meaning, no network): a learned
            residual (kind ``penn-residual``) may sit on top of it.
    """

    kind: str
    summary: str
    model: str
    fitter: str
    options: type[ModelOptions] = ModelOptions
    extra: str | None = None
    needs_data: bool = True
    residual_base: bool = False
    session_training: bool = False
    physical: bool = False

    @property
    def option_names(self) -> tuple[str, ...]:
        """The fields of its options model, in their order (``name`` first)."""
        return tuple(self.options.model_fields)

    def takes(self, option: str) -> bool:
        """Whether the kind has the option ``option`` (a field name such as ``dummy_arm``)."""
        return option in self.options.model_fields


def _fit_ap(dataset: StationaryDataset | None, description: RobotDescription, options: APOptions) -> FitResult:
    from daror_runtime.models.linear import build_ap

    return build_ap(description, dataset, options.dummy_arm, options.with_elbow_stiffness, options.name)


def _fit_plf(dataset: StationaryDataset, description: RobotDescription, options: ModelOptions) -> FitResult:
    from daror_runtime.models.linear import fit_plf

    return fit_plf(dataset, description, options.name)


def _fit_plf_plus(dataset: StationaryDataset, description: RobotDescription, options: ModelOptions) -> FitResult:
    from daror_runtime.models.linear import fit_plf_plus

    return fit_plf_plus(dataset, description, options.name)


#: The kinds this package implements, in the order lists show them (plugins follow, by name).
BUILTIN_KINDS: tuple[ModelKind, ...] = (
    ModelKind(
        "ap",
        "A Priori: design parameters (+ Dummy Arm, + elbow stiffness), Sec. 4.1",
        "daror_runtime.models.linear:APModel",
        f"{__name__}:_fit_ap",
        options=APOptions,
        needs_data=False,
        residual_base=True,
        session_training=True,
        physical=True,
    ),
    ModelKind(
        "plf",
        "Parameter Linear Form, least squares, Sec. 4.2.1",
        "daror_runtime.models.linear:PLFModel",
        f"{__name__}:_fit_plf",
        residual_base=True,
        session_training=True,
        physical=True,
    ),
    ModelKind(
        "plf+",
        "PLF + fifth-order elbow stiffness polynomial, Sec. 4.2.2",
        "daror_runtime.models.linear:PLFPlusModel",
        f"{__name__}:_fit_plf_plus",
        residual_base=True,
        session_training=True,
        physical=True,
    ),
    # The neural kinds: the fitter needs JAX (the extra ``nn``), the model class does not. Not a
    # residual base (the residual analysis augments models linear in their parameters). Not trained
    # in a session yet: a fit takes seconds of CPU (docs/models.md, "PENN and NNN: Timing"), which in real time would
    # run on the job thread beside the 1 kHz loop on a 2-core machine; that needs its own measurement
    # of the tick's jitter and a job that can be cancelled, before a session may start one.
    ModelKind(
        "penn",
        "Potential Energy Neural Network: torque = dV/dq of a network V(q), Sec. 3.2.2, 4.2.3",
        "daror_runtime.models.neural:PennModel",
        "daror_runtime.neural.fit:fit_penn",
        options=NetworkOptions,
        extra="nn",
        residual_base=False,
        session_training=False,
    ),
    ModelKind(
        "nnn",
        "Naive Neural Network: a network outputs the torque (not conservative), Sec. 3.1.1, 4.2.4",
        "daror_runtime.models.neural:NnnModel",
        "daror_runtime.neural.fit:fit_nnn",
        options=NetworkOptions,
        extra="nn",
        residual_base=False,
        session_training=False,
    ),
    # A physical base (fitted first) plus a PENN on what it leaves: the fitter needs JAX, the model
    # class does not. Not trained in a session, for the reason the neural kinds are not.
    ModelKind(
        "penn-residual",
        "a physical base (--base, default plf+) plus a PENN on its residual: V = V_base + V_nn (issue 13)",
        "daror_runtime.models.penn_residual:PennResidualModel",
        "daror_runtime.neural.residual_fit:fit_penn_residual",
        options=PennResidualOptions,
        extra="nn",
    ),
)


# --- the registry -----------------------------------------------------------------------------


def _group_entry_points() -> Iterable[importlib.metadata.EntryPoint]:
    return importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)


def _distribution(entry_point: importlib.metadata.EntryPoint) -> str:
    dist = getattr(entry_point, "dist", None)
    return "an unknown package" if dist is None else f"package {dist.name}"


class KindRegistry:
    """Built-in kinds plus those registered through entry points (read once, on first need; thread-safe).

    Args:
        builtins: the kinds known without reading any entry point.
        entry_points: where the plugin entry points come from (default: the installed packages'
            :data:`ENTRY_POINT_GROUP`; tests pass their own).
    """

    def __init__(
        self,
        builtins: Iterable[ModelKind] = BUILTIN_KINDS,
        entry_points: Callable[[], Iterable[importlib.metadata.EntryPoint]] = _group_entry_points,
    ) -> None:
        self._kinds: dict[str, ModelKind] = {k.kind: k for k in builtins}
        self._builtin = frozenset(self._kinds)
        self._entry_points = entry_points
        self._broken: dict[str, str] = {}
        self._plugins_read = False
        self._reading = False
        self._lock = threading.RLock()

    def _read_plugins(self) -> None:
        """Read the entry points once. Other threads wait for the first read; a plugin module that
        lists the kinds while it is being loaded (same thread) sees the kinds loaded so far."""
        with self._lock:
            if self._plugins_read or self._reading:
                return
            self._reading = True
            try:
                by_name: dict[str, list[importlib.metadata.EntryPoint]] = {}
                try:
                    for entry_point in self._entry_points():
                        by_name.setdefault(entry_point.name, []).append(entry_point)
                except Exception as exc:  # unreadable package metadata: the built-in kinds still work
                    log.warning("model kind plugins not read", group=ENTRY_POINT_GROUP, problem=str(exc))
                for name in sorted(by_name):
                    entry, problem = self._load(name, by_name[name])
                    if entry is not None:
                        self._kinds[name] = entry
                    elif problem is not None:
                        self._broken[name] = problem
                        log.warning("model kind plugin not loaded", kind=name, problem=problem)
            finally:
                self._reading = False
                self._plugins_read = True

    def _load(
        self, name: str, entry_points: list[importlib.metadata.EntryPoint]
    ) -> tuple[ModelKind | None, str | None]:
        """The entry of plugin kind ``name``, or the problem that keeps it out (None, None: ignored)."""
        values = sorted({e.value for e in entry_points})
        if name in self._builtin:
            log.warning(
                "a plugin cannot replace a built-in model kind; ignored",
                kind=name,
                plugin=", ".join(f"{e.value} ({_distribution(e)})" for e in entry_points),
            )
            return None, None
        if len(values) > 1:
            return None, f"registered more than once, as {' and '.join(values)}"
        try:
            entry = entry_points[0].load()
        except Exception as exc:  # third-party code: any failure keeps only this kind out
            return None, f"{values[0]} ({_distribution(entry_points[0])}) cannot be loaded: {type(exc).__name__}: {exc}"
        if not isinstance(entry, ModelKind):
            return None, f"{values[0]} is a {type(entry).__name__}, not a daror_runtime.models.registry.ModelKind"
        if entry.kind != name:
            return None, f"{values[0]} declares kind {entry.kind!r} under the entry point name {name!r}"
        if name != name.lower():
            return None, f"{values[0]}: model kind names are lower case, not {name!r}"
        options = entry.options
        if not (isinstance(options, type) and issubclass(options, ModelOptions)):
            return None, f"{values[0]}: its options are not a daror_runtime.models.registry.ModelOptions model"
        if options.model_config.get("extra") != "forbid" or not options.model_config.get("frozen"):
            return None, f"{values[0]}: its options model must be frozen and refuse unknown fields"
        return entry, None

    def entry(self, kind: str) -> ModelKind:
        """The entry of ``kind`` (exact, lower-case key); the plugins are read if it is not built in.

        Raises:
            UnknownModelKindError: ``kind`` is not registered (the known kinds are listed).
            ModelKindPluginError: ``kind`` is registered by a plugin that cannot be loaded.
        """
        found = self._kinds.get(kind)
        if found is not None:
            return found
        self._read_plugins()
        found = self._kinds.get(kind)
        if found is not None:
            return found
        if kind in self._broken:
            raise ModelKindPluginError(f"model kind {kind!r} is registered but cannot be used: {self._broken[kind]}")
        raise UnknownModelKindError(f"unknown model kind {kind!r}; expected one of {', '.join(self.names())}")

    def kinds(self, where: Callable[[ModelKind], bool] | None = None) -> tuple[ModelKind, ...]:
        """Every registered kind (built-in first, then plugins by name), or those ``where`` accepts."""
        self._read_plugins()
        return tuple(k for k in self._kinds.values() if where is None or where(k))

    def names(self, where: Callable[[ModelKind], bool] | None = None) -> tuple[str, ...]:
        """The keys of :meth:`kinds`, in the same order."""
        return tuple(k.kind for k in self.kinds(where))


_REGISTRY = KindRegistry()


def kind_entry(kind: str) -> ModelKind:
    """The registry entry of ``kind`` (an exact key: ``plf+``, not ``PLF+``).

    Raises:
        UnknownModelKindError: ``kind`` is not registered.
        ModelKindPluginError: ``kind`` is registered by a plugin that cannot be loaded.
    """
    return _REGISTRY.entry(kind)


def kinds(where: Callable[[ModelKind], bool] | None = None) -> tuple[ModelKind, ...]:
    """Every registered kind (built-in first, then plugins by name), or those ``where`` accepts.

    ``kinds(lambda k: k.residual_base)``: the kinds the residual analysis can augment.
    """
    return _REGISTRY.kinds(where)


def kind_names(where: Callable[[ModelKind], bool] | None = None) -> tuple[str, ...]:
    """The keys of :func:`kinds`, in the same order (for messages, help texts and checks)."""
    return _REGISTRY.names(where)


def _resolve(target: str, entry: ModelKind) -> object:
    module_name, attribute = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        if entry.extra is None:
            raise
        raise ExtraNotInstalledError(
            f"model kind {entry.kind} needs the optional extra '{entry.extra}', which is not installed: "
            f"pip install 'daror-runtime[{entry.extra}]' ({exc})"
        ) from None
    return getattr(module, attribute)


def model_class(kind: str) -> type[CompensationModel]:
    """The class implementing ``kind`` (imported on first use).

    Raises:
        UnknownModelKindError: ``kind`` is not registered.
        ExtraMissingError: the kind's optional extra is not installed.
        ModelKindPluginError: the plugin cannot be loaded, or its class declares another kind.
    """
    entry = kind_entry(kind)
    cls: type[CompensationModel] = _resolve(entry.model, entry)  # type: ignore[assignment]
    if getattr(cls, "kind", None) != entry.kind:
        raise ModelKindPluginError(
            f"model kind {kind!r}: its class {entry.model} declares kind {getattr(cls, 'kind', None)!r}"
        )
    return cls


#: The ``daror fit`` flag of each model option (a field of the kinds' options models), for messages and for
#: writing a fit's command line (``neural/hpsearch/winner.py``); a bool field's ``--x/--no-x`` spells both.
FIT_OPTION_FLAGS = {
    "name": "--name",
    "dummy_arm": "--dummy-arm",
    "elbow_stiffness": "--elbow-stiffness/--no-elbow-stiffness",
    "seed": "--seed",
    "thesis": "--thesis",
    "layers": "--layers",
    "width": "--width",
    "activation": "--activation",
    "inputs": "--inputs",
    "l1": "--l1",
    "inits": "--inits",
    "folds": "--folds",
    "adam_steps": "--adam-steps",
    "lbfgs": "--lbfgs/--no-lbfgs",
    "base": "--base",
}


def options_for(
    kind: str, values: Mapping[str, Any] | None = None, spelled: Mapping[str, str] | None = None
) -> ModelOptions:
    """The options model of ``kind`` with ``values`` (field name to value); absent fields take their defaults.

    Args:
        kind: a registered kind.
        values: the options given, by field name (``{"dummy_arm": True}``); give only what the
            user actually set, so that an option the kind does not take is refused, not ignored.
        spelled: how the caller names each field in messages (the CLI: ``{"dummy_arm": "--dummy-arm"}``).

    Raises:
        UnknownModelKindError: ``kind`` is not registered.
        ModelOptionError: an option the kind does not take, or a value it cannot use (one line).
    """
    entry = kind_entry(kind)
    given = dict(values or {})
    names = spelled or {}

    def spell(field: str) -> str:
        return names.get(field, field)

    unknown = [field for field in given if not entry.takes(field)]
    if unknown:
        takes = ", ".join(spell(f) for f in entry.option_names)
        raise ModelOptionError(f"model kind {kind} does not take {spell(unknown[0])}; its options: {takes}")
    try:
        return entry.options.model_validate(given)
    except ValidationError as exc:
        problem = exc.errors()[0]
        field = ".".join(str(p) for p in problem["loc"])
        raise ModelOptionError(f"model kind {kind}, option {spell(field)}: {problem['msg']}") from None


def installation_options(kind: str, dummy_arm: bool, name: str | None = None) -> ModelOptions:
    """The options of ``kind`` that follow from the installed robot (:meth:`ModelOptions.for_installation`).

    ``dummy_arm``: the Dummy Arm is installed (AP then includes it and its elbow stiffness; a
    fitted kind learns it from the data). ``name``: the model's name (None: the kind's).

    Raises:
        UnknownModelKindError: ``kind`` is not registered.
    """
    return kind_entry(kind).options.for_installation(dummy_arm, name)


def _options_of(entry: ModelKind, options: ModelOptions | None) -> ModelOptions:
    """``options`` as the options model of ``entry`` (another model's are re-checked field by field)."""
    if options is None:
        return entry.options()
    if type(options) is entry.options:
        return options
    return options_for(entry.kind, options.model_dump(exclude_unset=True))


def fit_model(
    kind: str,
    dataset: StationaryDataset | None,
    description: RobotDescription,
    options: ModelOptions | None = None,
) -> FitResult:
    """Fit (or, for a kind that needs no data, build) a model of ``kind``.

    Args:
        kind: a registered kind.
        dataset: the training data; None only for a kind with ``needs_data`` False.
        description: the robot the model is for.
        options: the kind's options model (default: its defaults). Options of another model
            are accepted when every field set in them is one this kind takes.

    Raises:
        UnknownModelKindError: ``kind`` is not registered.
        ModelOptionError: an option the kind does not take.
        UsageError: no dataset for a kind that learns from data.
        IdentifiabilityError: the data cannot identify the model.
        ExtraMissingError: the kind's optional extra is not installed.
    """
    entry = kind_entry(kind)
    checked = _options_of(entry, options)
    if dataset is None and entry.needs_data:
        raise UsageError(f"model kind {kind} learns from data; give it training data")
    fitter: Callable[..., FitResult] = _resolve(entry.fitter, entry)  # type: ignore[assignment]
    return fitter(dataset, description, checked)
