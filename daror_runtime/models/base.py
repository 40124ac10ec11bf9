"""The one interface every compensation model implements.

A compensation model maps joint angles to the torque that holds the robot (and pilot) against
gravity and stiffness. Once built it is a pure function of its parameters and ``q``: no I/O, no
state, no threads, so the loop can call :meth:`CompensationModel.torque` inside the tick.
Fitting is separate (``daror_runtime.models.registry.fit_model``) and happens outside the tick.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

import numpy as np

from daror_runtime.models.identifiability import BaseParameter
from daror_runtime.models.metrics import ErrorMetrics
from hal.robot import FloatArray, RobotDescription


@dataclass(frozen=True)
class TickKernel:
    """A compiled form of :meth:`CompensationModel.torque` that a compiled controller may call in the tick.

    A controller compiled against a known ``function`` (compare by identity: ``kernel.function is
    linear_torque``) runs the model inside its own compiled code; for any other function, or no
    kernel, it calls :meth:`CompensationModel.torque`. Both give the same torque.

    Attributes:
        function: a numba-compiled ``function(q, parameters, out)``: writes the holding torque (Nm,
            shape (4,)) at the joint angles ``q`` (rad, shape (4,)) into ``out``; allocates nothing.
        parameters: the float64 vector ``function`` reads (the model's; never modify it).
    """

    function: Callable[[np.ndarray, np.ndarray, np.ndarray], None]
    parameters: np.ndarray


class ReadingErrorTracker(Protocol):
    """The torque reading's path-dependent error, carried from tick to tick (:mod:`daror_runtime.control.reading_error`)."""

    def reset(self, q_rad: FloatArray) -> None:
        """Start at the pose ``q_rad`` (rad), the state unknown."""

    def update(self, q_rad: FloatArray, dt_s: float) -> FloatArray:
        """The reading's error (Nm, per joint) after moving to ``q_rad`` (rad) in ``dt_s`` (s); never blocks."""
        ...


class Feedforward(Protocol):
    """What a controller's feed-forward offers: a torque (Nm) at ``q`` (rad), and maybe a compiled one.

    Every :class:`CompensationModel` is one; so is a hold's constant held torque.
    """

    def torque(self, q: FloatArray) -> np.ndarray: ...

    def tick_kernel(self) -> TickKernel | None: ...


class CompensationModel(ABC):
    """Holding torque (Nm) as a function of joint angles (rad)."""

    #: Registry key and the ``kind`` field of model files: ``ap``, ``plf``, ``plf+``, ``penn``, ``nnn``.
    kind: ClassVar[str]
    #: Name in tables, as the thesis writes it.
    display_name: ClassVar[str]
    #: True when the torque is the gradient of a potential by construction (Sec. 3.1.3).
    conservative_by_construction: ClassVar[bool]
    #: True for a kind composed on another model, stored in its parameters under ``base`` as
    #: ``{"kind", "name", "parameters"}``: the model-file layer builds that model first (by its kind)
    #: and passes it to :meth:`from_parameters` in place of the entry (``penn-residual``).
    nested_base: ClassVar[bool] = False

    def __init__(self, description: RobotDescription, name: str | None = None) -> None:
        self.description = description
        self.name = name or self.display_name

    @abstractmethod
    def torque(self, q: FloatArray) -> np.ndarray:
        """Holding torque (4,) at one configuration ``q`` (4,). Cheap enough for the 1 kHz tick."""

    @abstractmethod
    def torque_batch(self, q: FloatArray) -> FloatArray:
        """Holding torque (N, 4) at N configurations (N, 4)."""

    def tick_kernel(self) -> TickKernel | None:
        """The compiled torque a compiled controller may run in the tick, or None (the default: none).

        Controllers ask this instead of checking the model's class; a model without a kernel runs
        through :meth:`torque`.
        """
        return None

    def reading_error_tracker(self) -> ReadingErrorTracker | None:
        """A new tracker of what the torque sensors read beyond the springs' torque, or None (the default: nothing).

        A model that knows a path-dependent reading error (the SEA's hysteresis, issue 16) returns
        one; :class:`~daror_runtime.control.modes.Compensation` runs it in the tick and adds its
        error to the torque reference, so the springs carry what the model says.
        """
        return None

    def path_travel_rad(self) -> FloatArray | None:
        """The travel constants (rad, per joint) of a reading error that depends on each joint's path, or None.

        None (the default): :meth:`predict`'s ``direction`` is the sign of each joint's last motion
        (a dataset's ``dir``). Otherwise it is the hysteresis state of each point, which the
        joints' path gives (the residual analysis computes it from a run's raw log).
        """
        return None

    def predict(self, q: FloatArray, direction: FloatArray | None = None) -> FloatArray:
        """What the torque sensors would read at N configurations (N, 4).

        The same as :meth:`torque_batch` unless the model knows sensor effects that depend on
        how a joint arrived (``direction``: sign of each joint's last motion, (N, 4)).
        """
        return self.torque_batch(q)

    @abstractmethod
    def parameters(self) -> dict[str, Any]:
        """JSON-ready parameters; :meth:`from_parameters` rebuilds an identical model from them."""

    @classmethod
    @abstractmethod
    def from_parameters(
        cls, description: RobotDescription, parameters: Mapping[str, Any], name: str | None = None
    ) -> CompensationModel:
        """Rebuild a model from :meth:`parameters` output.

        Raises:
            daror_runtime.errors.ModelFileError: the parameters do not match this kind.
        """


@dataclass(frozen=True)
class FitReport:
    """What a fit found out about the data and the model, for the model file and the console."""

    kind: str
    n_points: int
    training: ErrorMetrics | None
    duration_s: float
    rank: int | None = None
    n_parameters: int | None = None
    base_parameters: tuple[BaseParameter, ...] = ()
    unidentifiable: tuple[str, ...] = ()
    notes: tuple[str, ...] = field(default=())

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "kind": self.kind,
            "n_points": self.n_points,
            "training": None if self.training is None else self.training.to_dict(),
            "duration_s": self.duration_s,
        }
        if self.rank is not None:
            out["rank"] = self.rank
            out["n_parameters"] = self.n_parameters
            out["base_parameters"] = [b.to_dict() for b in self.base_parameters]
            out["unidentifiable"] = list(self.unidentifiable)
        if self.notes:
            out["notes"] = list(self.notes)
        return out


@dataclass(frozen=True)
class FitResult:
    model: CompensationModel
    report: FitReport
