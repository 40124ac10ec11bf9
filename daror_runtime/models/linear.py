"""The models that are linear in their parameters: A Priori, PLF and PLF+ (thesis Sec. 4.1-4.2).

All three compute ``tau = K(q) theta + [0 0 0 K_s(q4) mu]`` and differ only in where ``theta``
and ``mu`` come from:

* **AP** (Sec. 4.1): design masses and CoMs of ``hal/daror01.yaml`` (the gravity the thesis's RNE
  model gives), plus the Dummy Arm's ``theta_DA`` (Eq. 4.5), plus optionally the first-order
  elbow stiffness ``mu0 + mu1 q4`` (Eq. 4.7). Nothing is learned from data.
* **PLF** (Sec. 4.2.1): ``theta`` by minimum-norm least squares on stationary data (Eq. 3.29).
* **PLF+** (Sec. 4.2.2): PLF plus a fifth-order elbow polynomial, fitted together.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from functools import lru_cache
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import IdentifiabilityError, ModelFileError
from daror_runtime.models.base import CompensationModel, FitReport, FitResult, TickKernel
from daror_runtime.models.identifiability import base_parameters, unidentifiable_parameters
from daror_runtime.models.least_squares import min_norm_least_squares
from daror_runtime.models.metrics import error_metrics
from daror_runtime.models.regressor import (
    GRAVITY_PARAMETER_NAMES,
    N_GRAVITY_PARAMETERS,
    LinearTorqueEvaluator,
    linear_torque,
    polynomial_parameter_names,
    regressor_parameter_major,
)
from hal.robot import N_JOINTS, FloatArray, Geometry, Kinematics, RobotDescription

PLF_PLUS_ELBOW_ORDER = 5


#: The A Priori model's own parameters: which design terms it includes (no fitted kind has them).
DESIGN_FLAGS = ("includes_dummy_arm", "includes_elbow_stiffness")


class LinearParameters(BaseModel):
    """Parameters of a linear model as stored in a model file (what every linear kind may hold; each kind
    then checks what it must hold: :meth:`LinearCompensationModel._validated`)."""

    model_config = ConfigDict(extra="forbid")

    theta: list[float]
    theta_names: list[str] = Field(default_factory=lambda: list(GRAVITY_PARAMETER_NAMES))
    elbow_polynomial: list[float] = Field(default_factory=list, max_length=12)
    includes_dummy_arm: bool | None = None
    includes_elbow_stiffness: bool | None = None

    @field_validator("theta_names")
    @classmethod
    def _known_order(cls, names: list[str]) -> list[str]:
        if names != list(GRAVITY_PARAMETER_NAMES):
            raise ValueError(f"expected the parameter order {', '.join(GRAVITY_PARAMETER_NAMES)}")
        return names


class LinearCompensationModel(CompensationModel):
    """``tau = K(q) theta + elbow polynomial``: shared by AP, PLF and PLF+."""

    conservative_by_construction: ClassVar[bool] = True
    #: How many elbow polynomial coefficients (``mu_0 .. mu_k``, Nm/rad^i) a model of this kind has,
    #: and in words for messages.
    elbow_terms: ClassVar[tuple[int, ...]] = (0,)
    elbow_terms_said: ClassVar[str] = "none (no elbow polynomial)"
    #: Whether the parameters say which design terms are included (:data:`DESIGN_FLAGS`, A Priori only).
    design_flags: ClassVar[bool] = False

    def __init__(
        self,
        description: RobotDescription,
        theta: FloatArray,
        elbow_polynomial: FloatArray = (),  # type: ignore[assignment]
        name: str | None = None,
    ) -> None:
        super().__init__(description, name)
        self._evaluator = LinearTorqueEvaluator(description.kinematics(), theta, elbow_polynomial)

    @property
    def theta(self) -> np.ndarray:
        return self._evaluator.theta.copy()

    @property
    def elbow_polynomial(self) -> np.ndarray:
        return self._evaluator.mu.copy()

    def torque(self, q: FloatArray) -> np.ndarray:
        return self._evaluator.torque(q)

    def tick_kernel(self) -> TickKernel:
        """:func:`daror_runtime.models.regressor.linear_torque` with this model's packed parameters."""
        return TickKernel(linear_torque, self._evaluator.packed_parameters)

    def torque_batch(self, q: FloatArray) -> FloatArray:
        return self._evaluator.torque_batch(q)

    def potential_batch(self, q: FloatArray) -> FloatArray:
        """Potential energy (J, up to a constant) whose gradient is the torque."""
        return self._evaluator.potential_batch(q)

    def parameters(self) -> dict[str, Any]:
        return {
            "theta": [float(v) for v in self._evaluator.theta],
            "theta_names": list(GRAVITY_PARAMETER_NAMES),
            "elbow_polynomial": [float(v) for v in self._evaluator.mu],
        }

    @classmethod
    def _validated(cls, parameters: Mapping[str, Any]) -> LinearParameters:
        """``parameters`` checked against this kind: the fields, and the lengths and flags the kind has.

        A file whose ``kind`` was changed (PLF parameters under ``plf+``, A Priori's under ``plf``)
        or whose vectors were cut or padded is refused here, not run with a polynomial it never fitted.

        Raises:
            ModelFileError: one line naming the field, what it holds and what this kind has.
        """
        try:
            p = LinearParameters.model_validate(parameters)
        except ValidationError as exc:
            problem = exc.errors()[0]
            field = ".".join(str(p) for p in problem["loc"])
            raise ModelFileError(f"parameters.{field}: {problem['msg']} (model kind {cls.kind})") from None
        if len(p.theta) != N_GRAVITY_PARAMETERS:
            raise ModelFileError(
                f"parameters.theta: {len(p.theta)} values; a model of kind {cls.kind} has {N_GRAVITY_PARAMETERS}, "
                f"the first moments m g p (x, y, z) of the robot's {N_GRAVITY_PARAMETERS // 3} links"
            )
        if len(p.elbow_polynomial) not in cls.elbow_terms:
            raise ModelFileError(
                f"parameters.elbow_polynomial: {len(p.elbow_polynomial)} values; a model of kind {cls.kind} has "
                f"{cls.elbow_terms_said}: the parameters are another kind's or were cut"
            )
        flags = [name for name in DESIGN_FLAGS if name in parameters]
        if cls.design_flags:
            missing = [name for name in DESIGN_FLAGS if getattr(p, name) is None]
            if missing:
                raise ModelFileError(
                    f"parameters.{missing[0]}: missing; a model of kind {cls.kind} says true or false (the "
                    "parameters are another kind's)"
                )
            if bool(p.includes_elbow_stiffness) != bool(p.elbow_polynomial):
                raise ModelFileError(
                    f"parameters.elbow_polynomial: {len(p.elbow_polynomial)} values with includes_elbow_stiffness "
                    f"{str(p.includes_elbow_stiffness).lower()}; expected 2 (mu0, mu1) with it, none without"
                )
        elif flags:
            raise ModelFileError(
                f"parameters.{flags[0]}: an A Priori model's field in a model of kind {cls.kind}; the parameters "
                "are another kind's"
            )
        return p

    @classmethod
    def from_parameters(
        cls, description: RobotDescription, parameters: Mapping[str, Any], name: str | None = None
    ) -> LinearCompensationModel:
        p = cls._validated(parameters)
        return cls(description, np.array(p.theta), np.array(p.elbow_polynomial), name)


class PLFModel(LinearCompensationModel):
    kind: ClassVar[str] = "plf"
    display_name: ClassVar[str] = "PLF"


class PLFPlusModel(LinearCompensationModel):
    kind: ClassVar[str] = "plf+"
    display_name: ClassVar[str] = "PLF+"
    elbow_terms: ClassVar[tuple[int, ...]] = (PLF_PLUS_ELBOW_ORDER + 1,)
    elbow_terms_said: ClassVar[str] = (
        f"{PLF_PLUS_ELBOW_ORDER + 1} (mu0 .. mu{PLF_PLUS_ELBOW_ORDER} of its elbow polynomial, Sec. 4.2.2)"
    )


class APModel(LinearCompensationModel):
    kind: ClassVar[str] = "ap"
    display_name: ClassVar[str] = "A Priori"
    elbow_terms: ClassVar[tuple[int, ...]] = (0, 2)
    elbow_terms_said: ClassVar[str] = "none, or 2 with the elbow stiffness (mu0, mu1, Eq. 4.7)"
    design_flags: ClassVar[bool] = True

    def __init__(
        self,
        description: RobotDescription,
        theta: FloatArray,
        elbow_polynomial: FloatArray = (),  # type: ignore[assignment]
        name: str | None = None,
        includes_dummy_arm: bool = False,
        includes_elbow_stiffness: bool = False,
    ) -> None:
        super().__init__(description, theta, elbow_polynomial, name)
        self.includes_dummy_arm = includes_dummy_arm
        self.includes_elbow_stiffness = includes_elbow_stiffness

    @classmethod
    def from_description(
        cls, description: RobotDescription, dummy_arm: bool, elbow_stiffness: bool, name: str | None = None
    ) -> APModel:
        theta = design_theta(description) + (dummy_arm_theta(description) if dummy_arm else 0.0)
        prior = description.ap_elbow_stiffness
        mu = np.array([prior.mu0_nm, prior.mu1_nm_per_rad]) if elbow_stiffness else np.zeros(0)
        return cls(description, theta, mu, name, includes_dummy_arm=dummy_arm, includes_elbow_stiffness=elbow_stiffness)

    def parameters(self) -> dict[str, Any]:
        return super().parameters() | {
            "includes_dummy_arm": self.includes_dummy_arm,
            "includes_elbow_stiffness": self.includes_elbow_stiffness,
        }

    @classmethod
    def from_parameters(
        cls, description: RobotDescription, parameters: Mapping[str, Any], name: str | None = None
    ) -> APModel:
        p = cls._validated(parameters)
        return cls(
            description,
            np.array(p.theta),
            np.array(p.elbow_polynomial),
            name,
            includes_dummy_arm=bool(p.includes_dummy_arm),
            includes_elbow_stiffness=bool(p.includes_elbow_stiffness),
        )


# --- parameters from the description (A Priori) -------------------------------------------


def design_theta(description: RobotDescription) -> np.ndarray:
    """``theta`` of Eq. 4.20 from the design masses and CoMs: ``m_i g p_i``, ``theta_3 += m_4 g delta``."""
    g = description.gravity_mps2
    theta = np.concatenate([link.mass_kg * g * np.asarray(link.com_m) for link in description.links])
    theta[6:9] += description.links[3].mass_kg * g * np.asarray(description.geometry.elbow_offset_m)
    return theta


def dummy_arm_theta(description: RobotDescription) -> np.ndarray:
    """``theta_DA`` of Eq. 4.5: upper arm and elbow load on link 3's x, lower arm on link 4's x.

    With the Sec. 4.4.3 values this gives 5.1222 and 1.1260 Nm; the thesis prints 5.0963 and
    1.1559 (Eq. 4.6), which these inputs do not reproduce (see docs/models.md).
    """
    arm, g = description.dummy_arm, description.gravity_mps2
    theta = np.zeros(N_GRAVITY_PARAMETERS)
    theta[6] = (arm.upper_arm_com_m * arm.upper_arm_mass_kg + arm.lower_arm_mass_kg * arm.elbow_offset_m) * g
    theta[9] = arm.lower_arm_com_m * arm.lower_arm_mass_kg * g
    return theta


# --- fitting ------------------------------------------------------------------------------


@lru_cache(maxsize=16)
def structural_rank(geometry: Geometry, elbow_order: int | None) -> int:
    """Rank of the regressor on generic data: the most any dataset can identify (8 or 14 here)."""
    rng = np.random.default_rng(12345)
    q = rng.uniform(-np.pi, np.pi, size=(64, N_JOINTS))
    kt = regressor_parameter_major(Kinematics(geometry), q, elbow_order)
    kt = kt.reshape(kt.shape[0], -1)
    return min_norm_least_squares(kt, np.zeros(kt.shape[1])).rank


def fit_linear(
    model_cls: type[LinearCompensationModel],
    dataset: StationaryDataset,
    description: RobotDescription,
    elbow_order: int | None,
    name: str | None = None,
) -> FitResult:
    """Least-squares fit of PLF (``elbow_order=None``) or PLF+ on stationary data.

    Raises:
        IdentifiabilityError: the data identify fewer combinations than the model structurally has.
    """
    start = time.perf_counter()
    kt = regressor_parameter_major(description.kinematics(), dataset.q_rad, elbow_order)
    n_parameters = kt.shape[0]
    target = np.ascontiguousarray(dataset.tau_nm.T).reshape(-1)
    fit = min_norm_least_squares(kt.reshape(n_parameters, -1), target)
    expected = structural_rank(description.geometry, elbow_order)
    if fit.rank < expected:
        extra = f" and at least {elbow_order + 1} distinct elbow angles" if elbow_order is not None else ""
        raise IdentifiabilityError(
            f"{dataset.source}: {len(dataset)} stationary points identify only {fit.rank} of the {expected} "
            f"independent parameter combinations of {model_cls.kind}; expected points that move every joint{extra}"
        )
    if fit.degrees_of_freedom < fit.rank:
        # With fewer spare equations than unknowns the fit (nearly) interpolates its data: its
        # training error says nothing, and one noisy reading moves every parameter.
        needed = -(-2 * fit.rank // N_JOINTS)
        raise IdentifiabilityError(
            f"{dataset.source}: {len(dataset)} stationary points give {fit.n_rows} equations for the {fit.rank} "
            f"identifiable combinations of {model_cls.kind}; expected at least {needed} points, so that as many "
            "equations are left over as there are unknowns"
        )
    model = model_cls(description, fit.theta[:N_GRAVITY_PARAMETERS], fit.theta[N_GRAVITY_PARAMETERS:], name)
    duration = time.perf_counter() - start
    names = GRAVITY_PARAMETER_NAMES + (polynomial_parameter_names(elbow_order) if elbow_order is not None else ())
    residual = fit.residual.reshape(N_JOINTS, -1).T
    report = FitReport(
        kind=model_cls.kind,
        n_points=len(dataset),
        training=error_metrics(dataset.tau_nm, dataset.tau_nm - residual),
        duration_s=duration,
        rank=fit.rank,
        n_parameters=n_parameters,
        base_parameters=tuple(base_parameters(fit, names)),
        unidentifiable=tuple(unidentifiable_parameters(fit, names)),
    )
    return FitResult(model, report)


def fit_plf(dataset: StationaryDataset, description: RobotDescription, name: str | None = None) -> FitResult:
    """PLF (Sec. 4.2.1) on stationary data."""
    return fit_linear(PLFModel, dataset, description, None, name)


def fit_plf_plus(
    dataset: StationaryDataset,
    description: RobotDescription,
    name: str | None = None,
    elbow_order: int = PLF_PLUS_ELBOW_ORDER,
) -> FitResult:
    """PLF+ (Sec. 4.2.2) on stationary data."""
    return fit_linear(PLFPlusModel, dataset, description, elbow_order, name)


def build_ap(
    description: RobotDescription,
    dataset: StationaryDataset | None,
    dummy_arm: bool,
    elbow_stiffness: bool,
    name: str | None = None,
) -> FitResult:
    """The A Priori model; ``dataset``, when given, only provides the training-error figures."""
    start = time.perf_counter()
    model = APModel.from_description(description, dummy_arm, elbow_stiffness, name)
    duration = time.perf_counter() - start
    notes = ("A Priori: built from the robot description; nothing was fitted to data",)
    if dataset is None:
        return FitResult(model, FitReport("ap", 0, None, duration, notes=notes))
    metrics = error_metrics(dataset.tau_nm, model.torque_batch(dataset.q_rad))
    return FitResult(model, FitReport("ap", len(dataset), metrics, duration, notes=notes))
