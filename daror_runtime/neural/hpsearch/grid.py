"""The grid of a hyper-parameter search (thesis Sec. 4.2.5, Tables I and II): its axes and its training.

A :class:`SearchGrid` names the values of every axis (model, hidden layers, width, activation,
inputs, L1 rate lambda, initialisation seeds) and how every network is trained
(:class:`~daror_runtime.neural.training.TrainingSettings`). The search trains every combination.

Built-in grids (:data:`BUILTIN_GRIDS`):

* ``thesis``: exactly the thesis's axes: layers 1, 2, 8, 21; width 5, 10, 25; tanh, relu,
  sigmoid; lambda 1e-5, 1e-3, 1e-1; inputs ``q`` or ``[sin q, cos q]``; PENN and NNN; two
  initialisations: 144 shapes, 864 networks;
* ``small``: a quick look (2 x 2 x 2 x 2 shapes, 64 networks, about a minute).

Both train with :data:`SEARCH_TRAINING` (docs/hpsearch.md): ``daror fit``'s default optimiser
(Adam then L-BFGS, 300 loss evaluations), 4 folds with the last one held out (75 % training, 25 %
validation, as the thesis), and no final fit on all the data (the search ranks the fold networks'
minimal validation loss; it builds no model).

A grid may also come from a YAML file (:func:`load_grid`): the same fields, each axis a list::

    name: tanh-only
    models: [penn]
    layers: [1, 2]
    widths: [10, 25]
    activations: [tanh]
    inputs: [sincos]
    l1: [1.0e-5]
    seeds: [0, 1, 2]
    training: {adam_steps: 100, lbfgs_steps: 200, final_fit: false}

Values are strict (``"2"`` or ``true`` is not a number of layers), unknown fields and repeated
values are refused, and every shape must make a network :class:`NetworkSpec` accepts.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator
from pydantic_core import PydanticCustomError

from daror_runtime.errors import InputError, UsageError
from daror_runtime.models.neural import MAX_LAYERS, MAX_WIDTH, NetworkSpec
from daror_runtime.neural.training import TrainingSettings
from hal.yamlfile import Integer, Number, format_validation_error, read_yaml

__all__ = [
    "BUILTIN_GRIDS",
    "SEARCH_TRAINING",
    "GridFileError",
    "SearchGrid",
    "grid_from_argument",
    "load_grid",
]

#: Most values one axis may have (a grid is a person's list, not a sweep of thousands).
MAX_AXIS_VALUES = 64
#: Largest initialisation seed (``jax.random.PRNGKey`` takes any 63-bit integer; JSON keeps 2**53 exact).
MAX_SEED = 2**53 - 1


class GridFileError(InputError):
    """A hyper-parameter grid YAML file that cannot be read or does not describe a grid (exit code 2)."""


Model = Literal["penn", "nnn"]
Activation = Literal["tanh", "sigmoid", "relu", "softplus"]
Inputs = Literal["q", "sincos"]
Layers = Annotated[Integer, Field(ge=1, le=MAX_LAYERS)]
Width = Annotated[Integer, Field(ge=1, le=MAX_WIDTH)]
Rate = Annotated[Number, Field(ge=0.0, le=1e3)]
Seed = Annotated[Integer, Field(ge=0, le=MAX_SEED)]


def _axis(description: str) -> Any:
    # not min_length=1: pydantic checks it on the values that passed, so one bad value of a
    # one-value axis would also read "should have at least 1 item" (the validator below says it)
    return Field(max_length=MAX_AXIS_VALUES, description=description)


#: How the built-in grids train (docs/hpsearch.md): the default optimiser of ``daror fit`` (Adam 100 steps, then
#: L-BFGS 200 iterations), 4 folds with the last held out, no final fit.
SEARCH_TRAINING = TrainingSettings(loss="scaled", folds=4, validation_folds=1, final_fit=False)


class SearchGrid(BaseModel):
    """The axes of a search and how each network is trained (frozen; unknown fields refused).

    Raises (constructor): pydantic ``ValidationError`` for a value out of range, an empty axis, a
    value given twice, or a shape that makes no network (too many weights).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1, max_length=100, description="shown in the report")
    models: tuple[Model, ...] = _axis("penn: V(q), torque dV/dq; nnn: the 4 torques")
    layers: tuple[Layers, ...] = _axis("hidden layers")
    widths: tuple[Width, ...] = _axis("units per hidden layer")
    activations: tuple[Activation, ...] = _axis("of the hidden layers")
    inputs: tuple[Inputs, ...] = _axis("q, or [sin q, cos q] (Eq. 4.28)")
    l1: tuple[Rate, ...] = _axis("L1 rates lambda (meaning depends on the loss)")
    seeds: tuple[Seed, ...] = _axis("initialisation seeds: the best MVL over them is kept per configuration")
    training: TrainingSettings = Field(SEARCH_TRAINING, description="how every network is trained")

    @model_validator(mode="before")
    @classmethod
    def _lists_are_axes(cls, data: Any) -> Any:
        # A YAML list is an axis; validation is strict (no "2" for 2), and strict tuples take only tuples.
        if isinstance(data, dict):
            return {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return data

    @field_validator("models", "layers", "widths", "activations", "inputs", "l1", "seeds")
    @classmethod
    def _each_value_once(cls, values: tuple[Any, ...]) -> tuple[Any, ...]:
        if not values:
            raise PydanticCustomError("empty", "no value; expected at least one")
        repeated = sorted({v for v in values if values.count(v) > 1}, key=str)
        if repeated:
            raise PydanticCustomError(
                "repeated", "{values} given twice; expected each value once", {"values": ", ".join(map(str, repeated))}
            )
        return values

    @field_validator("widths")
    @classmethod
    def _every_shape_is_a_network(cls, widths: tuple[int, ...], info: ValidationInfo) -> tuple[int, ...]:
        layers = info.data.get("layers")
        if layers:
            try:  # the largest network of the grid: most layers, widest, sin/cos inputs, four outputs
                NetworkSpec(model="nnn", layers=max(layers), width=max(widths), activation="tanh", inputs="sincos")
            except ValidationError as exc:
                message = exc.errors()[0]["msg"].removeprefix("Value error, ")
                raise PydanticCustomError("too_large", "{message}", {"message": message}) from None
        return widths

    def shapes(self) -> list[NetworkSpec]:
        """Every network shape (model, layers, width, activation, inputs), in the grid's order."""
        return [
            NetworkSpec(model=m, layers=n, width=w, activation=a, inputs=i)
            for m, n, w, a, i in itertools.product(self.models, self.layers, self.widths, self.activations, self.inputs)
        ]

    @property
    def n_networks(self) -> int:
        """Networks the search trains: shapes x lambdas x seeds."""
        return len(self.shapes()) * len(self.l1) * len(self.seeds)

    def with_loss(self, loss: Literal["scaled", "thesis"] | None) -> SearchGrid:
        """This grid with its training's loss replaced (None: unchanged)."""
        if loss is None:
            return self
        training = TrainingSettings.model_validate(self.training.model_dump() | {"loss": loss})
        return self.model_copy(update={"training": training})

    def describe(self) -> str:
        """One line: ``thesis: 144 shapes, 864 networks (PENN, NNN; layers 1, 2, 8, 21; ...)``."""
        axes = "; ".join(
            f"{label} {', '.join(f'{v:g}' if isinstance(v, float) else str(v) for v in values)}"
            for label, values in (
                ("models", self.models),
                ("layers", self.layers),
                ("width", self.widths),
                ("activation", self.activations),
                ("inputs", self.inputs),
                ("lambda", self.l1),
                ("seeds", self.seeds),
            )
        )
        return f"{self.name}: {len(self.shapes())} shapes, {self.n_networks} networks ({axes})"


_THESIS_AXES: dict[str, Any] = {
    "models": ("penn", "nnn"),
    "layers": (1, 2, 8, 21),
    "widths": (5, 10, 25),
    "activations": ("tanh", "relu", "sigmoid"),
    "inputs": ("q", "sincos"),
    "l1": (1e-5, 1e-3, 1e-1),
    "seeds": (0, 1),
}

#: The grids ``--grid`` knows by name.
BUILTIN_GRIDS: dict[str, SearchGrid] = {
    "thesis": SearchGrid(name="thesis", **_THESIS_AXES),
    "small": SearchGrid(
        name="small",
        models=("penn", "nnn"),
        layers=(1, 2),
        widths=(5, 10),
        activations=("tanh", "sigmoid"),
        inputs=("sincos",),
        l1=(1e-5, 1e-3),
        seeds=(0, 1),
    ),
}


def load_grid(path: Path | str) -> SearchGrid:
    """A grid from a YAML file (the fields of :class:`SearchGrid`; ``name`` defaults to the file's stem).

    Raises:
        GridFileError: the file cannot be read, is not YAML, or does not describe a grid; one line
            naming the file, the line and the field.
    """
    path = Path(path)
    data, root = read_yaml(path, GridFileError)
    data.setdefault("name", path.stem)
    try:
        return SearchGrid.model_validate(data, strict=True)
    except ValidationError as exc:
        raise GridFileError(format_validation_error(str(path), exc, root)) from None


def grid_from_argument(value: str) -> SearchGrid:
    """The grid ``--grid VALUE`` names: a built-in grid's name, or a YAML file.

    Raises:
        UsageError: neither a built-in name nor a path to a ``.yaml``/``.yml`` file or an existing file.
        GridFileError: the file does not describe a grid.
    """
    if value in BUILTIN_GRIDS:
        return BUILTIN_GRIDS[value]
    path = Path(value)
    if path.suffix.lower() not in (".yaml", ".yml") and not path.exists():
        raise UsageError(f"--grid {value}: expected {', '.join(BUILTIN_GRIDS)} or a grid YAML file")
    return load_grid(path)
