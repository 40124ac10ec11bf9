"""The augmented model: a base model plus the effects a diagnosis found, as an ordinary model.

It is a :class:`~daror_runtime.models.base.CompensationModel` of kind ``augmented``: saved as a
model file, loaded by the registry, selected in the console and run in the loop like PLF+::

    tau(q) = G (tau_base(q - delta; gravity tilted by alpha) + sum_j P_j(q_j - delta_j))

The direction-dependent term ``d * dir`` is part of what the sensors *read* (Sec. 2.2.2), not a
torque the robot needs: :meth:`AugmentedModel.predict` includes it, so errors on measured data
are fair, while :meth:`AugmentedModel.torque` leaves it out. The sign of the last motion
(``direction_offset``) never reaches the loop, so compensation never steps when a joint changes
direction (docs/decisions.md, D41). The hysteresis (``hysteresis_nm`` over
``hysteresis_travel_rad``) does: it is continuous in the path, and
:meth:`AugmentedModel.reading_error_tracker` gives the loop its state (D110).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from daror_runtime.control.reading_error import MIN_TRAVEL_RAD, HysteresisTracker
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import ModelFileError
from daror_runtime.models.base import CompensationModel, FitReport, FitResult
from daror_runtime.models.metrics import error_metrics
from daror_runtime.models.registry import ModelOptions
from daror_runtime.models.regressor import N_GRAVITY_PARAMETERS, LinearTorqueEvaluator
from daror_runtime.residual.structure import StructureFit, base_kinds, tilted_kinematics
from hal.robot import N_JOINTS, FloatArray, RobotDescription

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
PerJoint = list[FiniteFloat]


class AugmentedParameters(BaseModel):
    """Parameters of an augmented model as stored in its model file."""

    model_config = ConfigDict(extra="forbid")

    base_kind: str
    theta: list[FiniteFloat] = Field(min_length=N_GRAVITY_PARAMETERS, max_length=N_GRAVITY_PARAMETERS)
    elbow_polynomial: list[FiniteFloat] = Field(default_factory=list, max_length=12)
    angle_offset_rad: PerJoint = Field(default_factory=lambda: [0.0] * N_JOINTS, min_length=4, max_length=4)
    gravity_tilt_rad: list[FiniteFloat] = Field(default_factory=lambda: [0.0, 0.0], min_length=2, max_length=2)
    torque_gain: PerJoint = Field(default_factory=lambda: [1.0] * N_JOINTS, min_length=4, max_length=4)
    direction_offset_nm: PerJoint = Field(default_factory=lambda: [0.0] * N_JOINTS, min_length=4, max_length=4)
    hysteresis_nm: PerJoint = Field(default_factory=lambda: [0.0] * N_JOINTS, min_length=4, max_length=4)
    hysteresis_travel_rad: list[Annotated[float, Field(ge=MIN_TRAVEL_RAD, allow_inf_nan=False)]] | None = Field(
        default=None,
        min_length=4,
        max_length=4,
        description="the play operator's travel per joint; None: no hysteresis",
    )
    joint_polynomials: list[list[FiniteFloat]] = Field(
        default_factory=lambda: [[] for _ in range(N_JOINTS)], min_length=4, max_length=4
    )
    effects: list[str] = Field(default_factory=list, description="what was added, for people")


class AugmentedModel(CompensationModel):
    """A base model (PLF+, PLF or AP) with physical effects added (see the module docstring)."""

    kind: ClassVar[str] = "augmented"
    display_name: ClassVar[str] = "augmented"
    conservative_by_construction: ClassVar[bool] = False  # a polynomial P_j(q_j) alone is; gains are not

    def __init__(self, description: RobotDescription, parameters: AugmentedParameters, name: str | None = None) -> None:
        super().__init__(description, name or f"{parameters.base_kind.upper()} + effects")
        self.spec = parameters
        kinematics = tilted_kinematics(description.geometry, np.asarray(parameters.gravity_tilt_rad))
        self._base = LinearTorqueEvaluator(kinematics, parameters.theta, parameters.elbow_polynomial)
        self._offset = np.asarray(parameters.angle_offset_rad, dtype=float)
        self._gain = np.asarray(parameters.torque_gain, dtype=float)
        # the direction signal's coefficient: the sign's (direction offset) or the state's (hysteresis)
        self._direction = np.asarray(parameters.direction_offset_nm, dtype=float) + np.asarray(
            parameters.hysteresis_nm, dtype=float
        )
        self._polynomials = [np.asarray(p, dtype=float) for p in parameters.joint_polynomials]

    @property
    def effects(self) -> list[str]:
        return list(self.spec.effects)

    def torque(self, q: FloatArray) -> np.ndarray:
        q_model = np.asarray(q, dtype=float) - self._offset
        out = self._base.torque(q_model)
        for j, poly in enumerate(self._polynomials):
            if poly.size:
                out[j] += np.polynomial.polynomial.polyval(q_model[j], poly)
        return out * self._gain

    def torque_batch(self, q: FloatArray) -> FloatArray:
        q_model = np.asarray(q, dtype=float) - self._offset[None, :]
        out = self._base.torque_batch(q_model)
        for j, poly in enumerate(self._polynomials):
            if poly.size:
                out[:, j] += np.polynomial.polynomial.polyval(q_model[:, j], poly)
        return out * self._gain[None, :]

    def reading_error_tracker(self) -> HysteresisTracker | None:
        """The hysteresis's tracker (amplitudes ``gain * hysteresis_nm``), or None for a model without one.

        The direction offset (a sign) is not tracked: it steps at every reversal (D41).
        """
        travel = self.path_travel_rad()
        if travel is None:
            return None
        return HysteresisTracker(travel, self._gain * np.asarray(self.spec.hysteresis_nm, dtype=float))

    def path_travel_rad(self) -> FloatArray | None:
        """The hysteresis's travel constants (rad) when the model carries one: :meth:`predict` then takes its state."""
        travel = self.spec.hysteresis_travel_rad
        if travel is None or not np.any(self.spec.hysteresis_nm):
            return None
        return np.asarray(travel, dtype=float)

    def predict(self, q: FloatArray, direction: FloatArray | None = None) -> FloatArray:
        """What the sensors read at ``q``: the torque plus the direction term (``direction``: the sign of
        the last motion, or the hysteresis state for :attr:`AugmentedParameters.hysteresis_travel_rad`)."""
        out = self.torque_batch(q)
        if direction is not None:
            out = out + self._gain[None, :] * self._direction[None, :] * np.asarray(direction, dtype=float)
        return out

    def parameters(self) -> dict[str, Any]:
        return self.spec.model_dump(mode="json")

    @classmethod
    def from_parameters(
        cls, description: RobotDescription, parameters: Mapping[str, Any], name: str | None = None
    ) -> AugmentedModel:
        try:
            spec = AugmentedParameters.model_validate(parameters)
        except ValidationError as exc:
            problem = exc.errors()[0]
            field = ".".join(str(p) for p in problem["loc"])
            raise ModelFileError(f"parameters.{field}: {problem['msg']} (model kind {cls.kind})") from None
        if spec.base_kind not in base_kinds():
            raise ModelFileError(f"parameters.base_kind: {spec.base_kind!r}; expected one of {', '.join(base_kinds())}")
        return cls(description, spec, name)


def augmented_model(fit: StructureFit, name: str | None = None, travel_rad: FloatArray | None = None) -> AugmentedModel:
    """The model of a fitted structure (what the runtime runs); ``travel_rad``: the hysteresis's travel constants."""
    structure = fit.structure
    base = structure.base
    if base.is_fitted:
        theta = fit.x[:N_GRAVITY_PARAMETERS]
        n_mu = 0 if base.elbow_order is None else base.elbow_order + 1
        mu = fit.x[N_GRAVITY_PARAMETERS : N_GRAVITY_PARAMETERS + n_mu]
    else:
        theta, mu = base.fixed_theta, base.fixed_mu  # type: ignore[assignment]
    transform = structure.transform(fit.phi)
    direction = np.zeros(N_JOINTS)
    hysteresis = np.zeros(N_JOINTS)
    polynomials: list[list[float]] = [[] for _ in range(N_JOINTS)]
    for effect in structure.effects:
        linear, _ = fit.effect_values(effect)
        if effect.family == "direction_offset":
            direction[effect.joint - 1] = linear[0]  # type: ignore[operator]
        elif effect.family == "hysteresis":
            hysteresis[effect.joint - 1] = linear[0]  # type: ignore[operator]
        elif effect.family == "joint_stiffness":
            polynomials[effect.joint - 1] = [float(v) for v in linear]  # type: ignore[operator]
    spec = AugmentedParameters(
        base_kind=base.kind,
        theta=[float(v) for v in theta],
        elbow_polynomial=[float(v) for v in mu],
        angle_offset_rad=[float(v) for v in transform.angle_offset_rad],
        gravity_tilt_rad=[float(v) for v in transform.tilt_rad],
        torque_gain=[float(v) for v in transform.gain],
        direction_offset_nm=[float(v) for v in direction],
        hysteresis_nm=[float(v) for v in hysteresis],
        hysteresis_travel_rad=None if travel_rad is None or not np.any(hysteresis) else [float(v) for v in travel_rad],
        joint_polynomials=polynomials,
        effects=[e.label for e in structure.effects],
    )
    return AugmentedModel(structure.description, spec, name)


def fit_augmented(dataset: StationaryDataset, description: RobotDescription, name: str | None = None) -> FitResult:
    """``daror fit augmented``: diagnose on the training data alone (PLF+ base) and close the loop."""
    from daror_runtime.residual.diagnosis import diagnose

    start = time.perf_counter()
    diagnosis = diagnose(dataset, description)
    model = augmented_model(diagnosis.final_fit, name)
    metrics = error_metrics(dataset.tau_nm, model.predict(dataset.q_rad, dataset.direction))
    notes = tuple(f.sentence for f in diagnosis.found) or ("no effect beyond PLF+ is supported by the data",)
    report = FitReport("augmented", len(dataset), metrics, time.perf_counter() - start, notes=notes)
    return FitResult(model, report)


def fit_augmented_kind(dataset: StationaryDataset, description: RobotDescription, options: ModelOptions) -> FitResult:
    """The registry's fitter of kind ``augmented`` (:mod:`daror_runtime.residual.kind`): :func:`fit_augmented`.

    ``options`` is the kind's options model (a name only).

    Raises:
        DataError, IdentifiabilityError: the data cannot train the base model.
    """
    return fit_augmented(dataset, description, options.name)
