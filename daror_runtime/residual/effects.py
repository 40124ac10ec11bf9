"""The effect library: physically named augmentations of a base compensation model.

Each family says what physical effect it stands for, which parameters it has (with units) and
how they enter the measured torque. With ``q`` the measured joint angles, ``dir`` the sign of
each joint's last motion and ``tau_base(q)`` the base model (PLF+ by default)::

    tau_measured = G (tau_base(q - delta; gravity tilted by alpha) + sum_j P_j(q_j - delta_j))
                   + d * dir

* ``direction_offset`` (linear, per joint): ``d_j dir_j``, the direction-dependent torque error
  of Sec. 2.2.2 (static friction across the spring, or an encoder that shifts with the rotor).
* ``hysteresis`` (linear given its travel constants, per joint): ``d_j s_j``, the same error as
  a play operator over the travel since the last reversal (:mod:`.hysteresis`); its travel
  constants are fitted by :mod:`.travel`, with the raw log when there is one.
* ``joint_stiffness`` (linear, per joint): ``P_j`` a polynomial in the joint angle, stiffness the
  model does not hold (a cable harness, a seal, a soft end stop; PLF+ has it on the elbow only).
* ``gravity_tilt`` (nonlinear, whole robot): the base is mounted rotated by ``alpha`` about the
  world x and z axes, so gravity has all three components in the base frame instead of only
  ``V_y`` (Sec. 6.6: constant rotations built with limited accuracy).
* ``encoder_offset`` (nonlinear, per joint): ``delta_j``, the joint's zero calibrated wrong: the
  model is evaluated at the wrong angle.
* ``torque_gain`` (nonlinear, per joint): ``G_j``, a torque reading scaled by a spring constant
  that is off (Sec. 6.6): ``measured = true * k_nominal / k_true``.

Linear families add least-squares columns; nonlinear ones add parameters that
:mod:`daror_runtime.residual.structure` optimises with ``scipy.optimize`` around an inner
least-squares solve (variable projection).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from daror_runtime.errors import ConfigurationError, UsageError
from hal.robot import N_JOINTS, FloatArray, rot_x, rot_z


@dataclass(frozen=True, order=True)
class Effect:
    """One effect of one family, on one joint (1-4) or, for whole-robot families, ``joint=None``."""

    family: str
    joint: int | None = None
    #: Polynomial order of ``joint_stiffness`` (None: the diagnosis's default); unused otherwise.
    order: int | None = None

    @property
    def label(self) -> str:
        if self.joint is None:
            return self.family
        order = "" if self.order is None else f", order {self.order}"
        return f"{self.family} (joint {self.joint}{order})"

    @property
    def site(self) -> tuple[str, int | None]:
        """Family and joint: two effects at one site are alternatives, never both in a model.

        The direction offset and the hysteresis share a site: both are the direction signal's column.
        """
        return (
            ("direction", self.joint)
            if self.family in ("direction_offset", "hysteresis")
            else (self.family, self.joint)
        )


@dataclass
class Transform:
    """What the nonlinear effects do to the base model: angle offsets, gravity tilt, gains."""

    angle_offset_rad: FloatArray = field(default_factory=lambda: np.zeros(N_JOINTS))
    tilt_rad: FloatArray = field(default_factory=lambda: np.zeros(2))
    gain: FloatArray = field(default_factory=lambda: np.ones(N_JOINTS))

    def key(self) -> tuple[float, ...]:
        """What the base model's regressor depends on (gains only scale it)."""
        return (*self.angle_offset_rad.tolist(), *self.tilt_rad.tolist())


def tilt_rotation(tilt_rad: FloatArray) -> FloatArray:
    """World-frame rotation of a base mounted tilted by ``(about_x, about_z)`` rad: ``Rx Rz``."""
    return rot_x(float(tilt_rad[0])) @ rot_z(float(tilt_rad[1]))


class EffectFamily(ABC):
    """One family of the library; stateless, shared."""

    name: ClassVar[str]
    summary: ClassVar[str]
    per_joint: ClassVar[bool] = True
    needs_direction: ClassVar[bool] = False
    #: The family's column is the joints' path (the hysteresis state), not a function of the point.
    needs_history: ClassVar[bool] = False
    #: Parameters optimised by scipy.optimize (0 for linear families).
    n_nonlinear: ClassVar[int] = 0

    def n_linear(self, effect: Effect, stiffness_order: int) -> int:
        """Least-squares columns this family adds."""
        return 0

    def linear_names(self, effect: Effect, stiffness_order: int) -> list[str]:
        return []

    # nonlinear families
    initial: ClassVar[tuple[float, ...]] = ()
    lower: ClassVar[tuple[float, ...]] = ()
    upper: ClassVar[tuple[float, ...]] = ()
    #: Typical size of each nonlinear parameter: the optimiser's scale and the finite-difference step.
    typical: ClassVar[tuple[float, ...]] = ()

    def apply(self, effect: Effect, values: FloatArray, transform: Transform) -> None:
        """Write this effect's nonlinear ``values`` into ``transform``."""
        raise ConfigurationError(f"{self.name} has no nonlinear parameters; only nonlinear families are applied")

    @abstractmethod
    def physical(
        self, effect: Effect, linear: FloatArray, nonlinear: FloatArray, context: PhysicalContext
    ) -> dict[str, Any]:
        """The effect's parameters in physical units, JSON-ready."""

    @abstractmethod
    def sentence(self, effect: Effect, parameters: Mapping[str, Any]) -> str:
        """One line a person reads, e.g. ``joint 2 direction offset 0.52 Nm``."""


@dataclass(frozen=True)
class PhysicalContext:
    """What turning fitted numbers into physical ones needs: the data's angle range and the SEA."""

    q_mean_rad: FloatArray
    q_min_rad: FloatArray
    q_max_rad: FloatArray
    spring_nm_per_rad: float
    standard_errors: Mapping[str, float]
    travel_rad: FloatArray | None = None  # the hysteresis travel constants, when fitted


def _joint_index(effect: Effect) -> int:
    if effect.joint is None or not 1 <= effect.joint <= N_JOINTS:
        raise UsageError(f"{effect.family} is a per-joint effect; expected a joint 1-{N_JOINTS}, got {effect.joint}")
    return effect.joint - 1


class DirectionOffset(EffectFamily):
    name = "direction_offset"
    summary = "direction-dependent torque error d_j dir_j (Sec. 2.2.2), Nm"
    needs_direction = True

    def n_linear(self, effect: Effect, stiffness_order: int) -> int:
        return 1

    def linear_names(self, effect: Effect, stiffness_order: int) -> list[str]:
        return [f"direction_offset{effect.joint}_nm"]

    def physical(
        self, effect: Effect, linear: FloatArray, nonlinear: FloatArray, context: PhysicalContext
    ) -> dict[str, Any]:
        name = self.linear_names(effect, 0)[0]
        return {"offset_nm": float(linear[0]), "offset_std_error_nm": context.standard_errors.get(name)}

    def sentence(self, effect: Effect, parameters: Mapping[str, Any]) -> str:
        return (
            f"joint {effect.joint} direction offset {abs(parameters['offset_nm']):.3g} Nm "
            f"(the reading is {parameters['offset_nm']:+.3g} Nm x the sign of the last motion)"
        )


class Hysteresis(EffectFamily):
    """The direction error as a hysteresis: ``d_j s_j``, the play operator's state over the joint's travel.

    It takes the direction offset's column (the two are alternatives at one joint): the analysis
    replaces each point's sign of the last motion by the state ``s_j`` for the travel constants it
    fitted (:mod:`daror_runtime.residual.travel`), from the raw log when there is one.
    """

    name = "hysteresis"
    summary = (
        "direction error as a hysteresis over the travel since the last reversal (Sec. 2.2.2): amplitude Nm, travel rad"
    )
    needs_history = True

    def n_linear(self, effect: Effect, stiffness_order: int) -> int:
        return 1

    def linear_names(self, effect: Effect, stiffness_order: int) -> list[str]:
        return [f"hysteresis{effect.joint}_nm"]

    def physical(
        self, effect: Effect, linear: FloatArray, nonlinear: FloatArray, context: PhysicalContext
    ) -> dict[str, Any]:
        j = _joint_index(effect)
        if context.travel_rad is None:
            raise ConfigurationError("a hysteresis effect's physical parameters need the fitted travel constants")
        name = self.linear_names(effect, 0)[0]
        return {
            "amplitude_nm": float(linear[0]),
            "amplitude_std_error_nm": context.standard_errors.get(name),
            "travel_rad": float(context.travel_rad[j]),
        }

    def sentence(self, effect: Effect, parameters: Mapping[str, Any]) -> str:
        return (
            f"joint {effect.joint} hysteresis {abs(parameters['amplitude_nm']):.3g} Nm over "
            f"{parameters['travel_rad'] * 1e3:.2g} mrad of travel (the reading is {parameters['amplitude_nm']:+.3g} Nm "
            "x a state that turns over that travel after each reversal)"
        )


class JointStiffness(EffectFamily):
    name = "joint_stiffness"
    summary = "stiffness the model does not hold: a polynomial in the joint angle, Nm"

    def n_linear(self, effect: Effect, stiffness_order: int) -> int:
        return (stiffness_order if effect.order is None else effect.order) + 1

    def linear_names(self, effect: Effect, stiffness_order: int) -> list[str]:
        return [f"stiffness{effect.joint}_c{k}" for k in range(self.n_linear(effect, stiffness_order))]

    def physical(
        self, effect: Effect, linear: FloatArray, nonlinear: FloatArray, context: PhysicalContext
    ) -> dict[str, Any]:
        j = _joint_index(effect)
        poly = np.polynomial.Polynomial(linear)
        stiffness = float(poly.deriv()(context.q_mean_rad[j]))
        lo, hi = float(context.q_min_rad[j]), float(context.q_max_rad[j])
        roots = [r.real for r in poly.roots() if abs(r.imag) < 1e-9 and lo - 0.5 <= r.real <= hi + 0.5]
        rest = min(roots, key=lambda r: abs(r - context.q_mean_rad[j])) if roots else None
        span = np.linspace(lo, hi, 50)
        return {
            "coefficients": [float(c) for c in linear],
            "coefficient_units": [f"Nm/rad^{k}" for k in range(len(linear))],
            "stiffness_nm_per_rad": stiffness,
            "rest_angle_deg": None if rest is None else math.degrees(rest),
            "torque_range_nm": [float(np.min(poly(span))), float(np.max(poly(span)))],
        }

    def sentence(self, effect: Effect, parameters: Mapping[str, Any]) -> str:
        rest = parameters["rest_angle_deg"]
        where = f", zero torque at {rest:.1f} deg" if rest is not None else ""
        low, high = parameters["torque_range_nm"]
        return (
            f"joint {effect.joint} stiffness {parameters['stiffness_nm_per_rad']:.3g} Nm/rad at the mean angle{where} "
            f"({low:+.2f} to {high:+.2f} Nm over the data)"
        )


class GravityTilt(EffectFamily):
    name = "gravity_tilt"
    summary = "base mounted tilted: gravity has all three components in the base frame, deg"
    per_joint = False
    n_nonlinear = 2
    initial = (0.0, 0.0)
    lower = (-0.35, -0.35)  # 20 deg: beyond that it is not a mounting tolerance
    upper = (0.35, 0.35)
    typical = (0.01, 0.01)

    def apply(self, effect: Effect, values: FloatArray, transform: Transform) -> None:
        transform.tilt_rad = np.asarray(values, dtype=float).copy()

    def physical(
        self, effect: Effect, linear: FloatArray, nonlinear: FloatArray, context: PhysicalContext
    ) -> dict[str, Any]:
        rotation = tilt_rotation(nonlinear)
        total = math.degrees(math.acos(min(1.0, max(-1.0, float(rotation[1, 1])))))
        ex, ez = (context.standard_errors.get(f"gravity_tilt_{a}_rad") for a in ("x", "z"))
        return {
            "about_x_deg": math.degrees(nonlinear[0]),
            "about_z_deg": math.degrees(nonlinear[1]),
            "about_x_std_error_deg": None if ex is None else math.degrees(ex),
            "about_z_std_error_deg": None if ez is None else math.degrees(ez),
            "tilt_deg": total,
        }

    def sentence(self, effect: Effect, parameters: Mapping[str, Any]) -> str:
        return (
            f"gravity tilted {parameters['tilt_deg']:.2f} deg from the base frame's vertical "
            f"({parameters['about_x_deg']:+.2f} deg about x, {parameters['about_z_deg']:+.2f} deg about z)"
        )


class EncoderOffset(EffectFamily):
    name = "encoder_offset"
    summary = "joint zero calibrated wrong: the model sees q + delta, deg"
    n_nonlinear = 1
    initial = (0.0,)
    lower = (-0.2,)
    upper = (0.2,)
    typical = (0.01,)

    def apply(self, effect: Effect, values: FloatArray, transform: Transform) -> None:
        transform.angle_offset_rad[_joint_index(effect)] = float(values[0])

    def physical(
        self, effect: Effect, linear: FloatArray, nonlinear: FloatArray, context: PhysicalContext
    ) -> dict[str, Any]:
        error = context.standard_errors.get(f"encoder_offset{effect.joint}_rad")
        return {
            "offset_deg": math.degrees(nonlinear[0]),
            "offset_std_error_deg": None if error is None else math.degrees(error),
        }

    def sentence(self, effect: Effect, parameters: Mapping[str, Any]) -> str:
        return f"joint {effect.joint} encoder offset {parameters['offset_deg']:+.3g} deg (the reading minus the true angle)"


class TorqueGain(EffectFamily):
    name = "torque_gain"
    summary = "torque reading scaled: a spring constant that is off, measured = gain x true"
    n_nonlinear = 1
    initial = (1.0,)
    lower = (0.5,)
    upper = (2.0,)
    typical = (0.01,)

    def apply(self, effect: Effect, values: FloatArray, transform: Transform) -> None:
        transform.gain[_joint_index(effect)] = float(values[0])

    def physical(
        self, effect: Effect, linear: FloatArray, nonlinear: FloatArray, context: PhysicalContext
    ) -> dict[str, Any]:
        gain = float(nonlinear[0])
        return {
            "gain": gain,
            "gain_std_error": context.standard_errors.get(f"torque_gain{effect.joint}"),
            "spring_constant_ratio": 1.0 / gain,
            "spring_nm_per_rad": context.spring_nm_per_rad / gain,
        }

    def sentence(self, effect: Effect, parameters: Mapping[str, Any]) -> str:
        ratio = parameters["spring_constant_ratio"]
        stiffer = "stiffer" if ratio >= 1 else "softer"
        return (
            f"joint {effect.joint} torque gain {parameters['gain']:.4g}: its SEA spring is {abs(ratio - 1) * 100:.1f} % "
            f"{stiffer} than the nominal constant ({parameters['spring_nm_per_rad']:.1f} Nm/rad)"
        )


FAMILIES: dict[str, EffectFamily] = {
    f.name: f for f in (DirectionOffset(), Hysteresis(), JointStiffness(), GravityTilt(), EncoderOffset(), TorqueGain())
}

#: Families whose column is each point's direction signal (the sign of the last motion, or the
#: hysteresis state): alternatives at one joint, never both in a model.
DIRECTION_FAMILIES = ("direction_offset", "hysteresis")


def family(name: str) -> EffectFamily:
    """The family called ``name``.

    Raises:
        UsageError: no such family (the message lists the known ones).
    """
    try:
        return FAMILIES[name]
    except KeyError:
        raise UsageError(f"unknown effect family {name!r}; expected one of {', '.join(FAMILIES)}") from None


def candidate_effects(families: tuple[str, ...]) -> list[Effect]:
    """Every effect of ``families``: one per joint for per-joint families, one for the others."""
    out: list[Effect] = []
    for name in families:
        fam = family(name)
        if fam.per_joint:
            out.extend(Effect(name, j) for j in range(1, N_JOINTS + 1))
        else:
            out.append(Effect(name))
    return out
