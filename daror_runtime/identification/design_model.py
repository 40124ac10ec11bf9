"""What a designed protocol must identify: the model's base parameters and how noisy a stop is.

The holding torque of the linear models is ``tau = K(q) theta`` (PLF, PLF+; Eq. 4.21-4.27), with
the linear effects of the residual analysis (:mod:`daror_runtime.residual.effects`) as extra
columns: ``direction_offset`` adds ``dir_j`` on joint ``j`` (Sec. 2.2.2), ``joint_stiffness`` a
polynomial ``sum_k c_k q_j^k`` on joint ``j``. Only the base parameters (the identifiable
combinations: 14 of PLF+'s 18, docs/models.md) can be estimated; they are chosen once, on generic
configurations, with the fit report's own rule (:func:`~daror_runtime.models.identifiability.base_parameters`:
x and y moments first), so the design's standard errors name the combinations ``daror fit`` prints.

Noise of one stop (the mean torque of a stop), per joint, independent between stops:

* ``sensor_noise_nm``: what no model explains;
* ``direction_error_nm``: the direction-dependent error ``d_j dir_j`` (Sec. 2.2.2). A model with
  ``direction_offset`` on joint ``j`` explains it. Otherwise it is noise, except when a pose is
  approached from both directions: its two stops then carry ``-d_j`` and ``+d_j`` at the same
  ``K(q)``, which cancel exactly in the least-squares fit, so only the sensor noise is left.

The information matrix of a design is ``M = sum over stops of K_b^T W K_b`` (``K_b`` the base
columns, ``W`` the inverse noise variance per joint); the fit ``daror fit`` runs is unweighted
least squares, so the predicted covariance is the sandwich ``(X^T X)^-1 X^T S X (X^T X)^-1``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from daror_runtime.errors import UsageError
from daror_runtime.models.identifiability import base_parameters
from daror_runtime.models.least_squares import min_norm_least_squares
from daror_runtime.models.linear import PLF_PLUS_ELBOW_ORDER
from daror_runtime.models.regressor import (
    GRAVITY_PARAMETER_NAMES,
    polynomial_parameter_names,
    regressor_parameter_major,
)
from hal.robot import N_JOINTS, FloatArray, RobotDescription

__all__ = [
    "DESIGN_BASES",
    "LINEAR_EFFECTS",
    "DesignEffect",
    "DesignModel",
    "information",
    "parse_effects",
    "relative_condition_number",
    "scaled_condition_number",
]

#: Model kinds a protocol can be designed for: the linear kinds fitted by least squares.
DESIGN_BASES: dict[str, int | None] = {"plf": None, "plf+": PLF_PLUS_ELBOW_ORDER}
#: The linear effect families of the residual analysis (their columns enter the least squares).
LINEAR_EFFECTS = ("direction_offset", "joint_stiffness")
#: The residual analysis's nonlinear families: named in the refusal, not designed for.
_NONLINEAR_EFFECTS = ("gravity_tilt", "encoder_offset", "torque_gain")
#: Polynomial order of a ``joint_stiffness`` effect (the residual analysis's default).
STIFFNESS_ORDER = 3
#: Generic configurations used to find the base parameters (as ``structural_rank`` does).
_GENERIC_POINTS = 96


@dataclass(frozen=True, order=True)
class DesignEffect:
    """One linear effect on one joint (1-4), as the residual analysis names it."""

    family: str
    joint: int

    @property
    def label(self) -> str:
        return f"{self.family}:{self.joint}"

    def names(self) -> list[str]:
        if self.family == "direction_offset":
            return [f"direction_offset{self.joint}_nm"]
        return [f"stiffness{self.joint}_c{k}" for k in range(STIFFNESS_ORDER + 1)]


def parse_effects(text: str | Sequence[str] | None) -> tuple[DesignEffect, ...]:
    """Effects from ``direction_offset,joint_stiffness:2`` (a family alone means every joint).

    Raises:
        UsageError: an unknown family, a nonlinear one, a joint outside 1-4, an effect twice.
    """
    if text is None:
        return ()
    tokens = [t.strip() for t in (text.split(",") if isinstance(text, str) else text)]
    found: list[DesignEffect] = []
    for token in tokens:
        if not token:
            continue
        name, _, joint = token.partition(":")
        if name in _NONLINEAR_EFFECTS:
            raise UsageError(
                f"--effects {token}: {name} is nonlinear in its parameters; a protocol is designed for the "
                f"linear effects {', '.join(LINEAR_EFFECTS)}"
            )
        if name not in LINEAR_EFFECTS:
            raise UsageError(
                f"--effects {token}: unknown effect; expected {', '.join(LINEAR_EFFECTS)}, optionally with :JOINT (1-4)"
            )
        if joint:
            if joint not in {"1", "2", "3", "4"}:
                raise UsageError(f"--effects {token}: expected a joint 1-4 after the colon")
            found.append(DesignEffect(name, int(joint)))
        else:
            found.extend(DesignEffect(name, j) for j in range(1, N_JOINTS + 1))
    if len(set(found)) != len(found):
        raise UsageError(f"--effects {','.join(tokens)}: an effect is named twice")
    return tuple(sorted(found))


class DesignModel:
    """The base regressor of a model kind plus linear effects, and the noise of one stop.

    Args:
        base: ``plf`` or ``plf+``.
        effects: linear effects on top (:func:`parse_effects`).
        description: the robot.
        direction_error_nm: ``d_j`` (4,), Nm, the direction-dependent error per joint.
        sensor_noise_nm: (4,), Nm, the rest of a stop's torque error.

    Raises:
        UsageError: an unknown base; non-positive sensor noise or negative direction error; an
            effect that adds nothing the base model does not already identify.
    """

    def __init__(
        self,
        base: str,
        effects: Sequence[DesignEffect],
        description: RobotDescription,
        direction_error_nm: Sequence[float],
        sensor_noise_nm: Sequence[float],
    ) -> None:
        if base not in DESIGN_BASES:
            raise UsageError(f"--base {base}: a protocol is designed for {', '.join(DESIGN_BASES)}")
        direction = np.asarray(direction_error_nm, dtype=float)
        sensor = np.asarray(sensor_noise_nm, dtype=float)
        if direction.shape != (N_JOINTS,) or not np.all(np.isfinite(direction) & (direction >= 0)):
            raise UsageError(f"direction error {direction_error_nm}: expected four values of 0 Nm or more")
        if sensor.shape != (N_JOINTS,) or not np.all(np.isfinite(sensor) & (sensor > 0)):
            raise UsageError(f"sensor noise {sensor_noise_nm}: expected four values above 0 Nm")
        self.base = base
        self.effects = tuple(effects)
        self.description = description
        self.kinematics = description.kinematics()
        self.elbow_order = DESIGN_BASES[base]
        self.direction_error_nm = direction
        self.sensor_noise_nm = sensor
        poly = polynomial_parameter_names(self.elbow_order) if self.elbow_order is not None else ()
        self.names: tuple[str, ...] = (*GRAVITY_PARAMETER_NAMES, *poly, *(n for e in self.effects for n in e.names()))
        self._choose_base_parameters()

    # -- columns ------------------------------------------------------------------------------

    @property
    def models_direction(self) -> FloatArray:
        """(4,) bool: joints whose direction error the model explains (``direction_offset``)."""
        out = np.zeros(N_JOINTS, dtype=bool)
        for e in self.effects:
            if e.family == "direction_offset":
                out[e.joint - 1] = True
        return out

    @property
    def needs_direction(self) -> bool:
        return bool(self.models_direction.any())

    def full_rows(self, q: FloatArray, direction: FloatArray) -> FloatArray:
        """Every column of the model at configurations ``q`` (N, 4) rad with ``dir`` (N, 4): (N, 4, P)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        direction = np.broadcast_to(np.asarray(direction, dtype=float), q.shape)
        base = np.transpose(regressor_parameter_major(self.kinematics, q, self.elbow_order), (2, 1, 0))
        extra = []
        for e in self.effects:
            j = e.joint - 1
            if e.family == "direction_offset":
                col = np.zeros((q.shape[0], N_JOINTS, 1))
                col[:, j, 0] = direction[:, j]
            else:
                col = np.zeros((q.shape[0], N_JOINTS, STIFFNESS_ORDER + 1))
                col[:, j, :] = q[:, j, None] ** np.arange(STIFFNESS_ORDER + 1)
            extra.append(col)
        return np.concatenate([base, *extra], axis=2) if extra else np.ascontiguousarray(base)

    def rows(self, q: FloatArray, direction: FloatArray) -> FloatArray:
        """The base columns at ``q`` (N, 4) with ``dir`` (N, 4): (N, 4, rank), unweighted."""
        return self.full_rows(q, direction)[:, :, self.base_index]

    def _choose_base_parameters(self) -> None:
        rng = np.random.default_rng(20240614)
        lo, hi = self.description.lower_limits_rad, self.description.upper_limits_rad
        q = rng.uniform(lo, hi, size=(_GENERIC_POINTS, N_JOINTS))
        direction = rng.choice([-1.0, 1.0], size=q.shape)
        x = self.full_rows(q, direction).reshape(-1, len(self.names))
        fit = min_norm_least_squares(np.ascontiguousarray(x.T), np.zeros(x.shape[0]))
        chosen = base_parameters(fit, self.names)
        self.rank = fit.rank
        self.base_index = np.array([self.names.index(p.lead) for p in chosen])
        self.base_expressions = tuple(p.expression() for p in chosen)
        leads = {p.lead for p in chosen}
        for e in self.effects:
            if not leads & set(e.names()):
                raise UsageError(
                    f"--effects {e.label}: the {self.base} model already holds what this effect would add "
                    "(its columns are combinations of the model's own); leave it out"
                )

    # -- noise --------------------------------------------------------------------------------

    def stop_variance(self, paired: bool) -> FloatArray:
        """Variance (4,) Nm^2 of a stop's torque error as the fit sees it (the module docstring).

        ``paired``: every pose is approached from both directions, so an unmodelled direction
        error cancels within each pose's pair of stops.
        """
        direction = np.where(self.models_direction | paired, 0.0, self.direction_error_nm**2)
        return direction + self.sensor_noise_nm**2

    def floor_variance(self) -> FloatArray:
        """Variance (4,) Nm^2 the model cannot explain on any data: the floor of the validation error."""
        direction = np.where(self.models_direction, 0.0, self.direction_error_nm**2)
        return direction + self.sensor_noise_nm**2

    # -- figures of a design ------------------------------------------------------------------

    def covariance(self, rows: FloatArray, paired: bool) -> FloatArray:
        """Predicted covariance (rank, rank) of the base parameters fitted by unweighted least squares.

        ``rows`` (S, 4, rank): one block per stop. Raises ``numpy.linalg.LinAlgError`` when the
        stops do not identify every base parameter (check :func:`information` first).
        """
        x = rows.reshape(-1, rows.shape[2])
        gram_inv = np.linalg.inv(x.T @ x)
        variance = np.tile(self.stop_variance(paired), rows.shape[0])
        middle = (x * variance[:, None]).T @ x
        return gram_inv @ middle @ gram_inv

    def predicted_validation_rmse(self, covariance: FloatArray, q_validate: FloatArray) -> tuple[float, FloatArray]:
        """RMSE (Nm) and per-joint RMSE (4,) the fitted model should reach on poses ``q_validate`` (N, 4).

        The floor (:meth:`floor_variance`) plus the spread the parameters' covariance puts on the
        torque, averaged over the poses (both directions of motion for a direction effect).
        """
        per_joint = np.zeros(N_JOINTS)
        for sign in (-1.0, 1.0):
            k = self.rows(q_validate, np.full_like(q_validate, sign))
            per_joint += np.einsum("njp,pr,njr->j", k, covariance, k) / k.shape[0] / 2.0
        joint_mse = self.floor_variance() + per_joint
        return float(np.sqrt(joint_mse.mean())), np.sqrt(joint_mse)


def information(rows: FloatArray, variance: FloatArray) -> FloatArray:
    """``sum over stops of K^T W K`` for ``rows`` (S, 4, p) and the per-joint variance (4,)."""
    x = (rows / np.sqrt(variance)[None, :, None]).reshape(-1, rows.shape[2])
    return x.T @ x


def scaled_condition_number(matrix: FloatArray) -> tuple[float, FloatArray]:
    """Condition number of a symmetric ``matrix`` scaled to unit diagonal, and its weakest direction.

    Scale-free: a parameter's units do not count, only how well the data separate the parameters.
    This is what the fit's rank decision sees (it scales the regressor's columns the same way,
    :func:`~daror_runtime.models.least_squares.min_norm_least_squares`). Infinite when a diagonal
    entry or an eigenvalue is not positive; the direction is in the scaled coordinates.
    """
    d = np.sqrt(np.clip(np.diag(matrix), 0.0, None))
    if not np.all(d > 0):
        weakest = np.zeros(matrix.shape[0])
        weakest[int(np.argmin(d))] = 1.0
        return float("inf"), weakest
    values, vectors = np.linalg.eigh(matrix / np.outer(d, d))
    if not values[0] > 0:
        return float("inf"), vectors[:, 0]
    return float(values[-1] / values[0]), vectors[:, 0]


def relative_condition_number(matrix: FloatArray, reference: FloatArray) -> tuple[float, FloatArray]:
    """Condition number of ``matrix`` relative to ``reference`` (both symmetric), and its weakest direction.

    The ratio of the largest to the smallest generalised eigenvalue of ``matrix v = lambda
    reference v``, on both matrices scaled by the reference's diagonal: invariant under any change
    of the parameters' units or combinations, 1 when the design is shaped like the reference.
    Infinite when the reference is not positive definite or the design misses a direction.
    """
    d = np.sqrt(np.clip(np.diag(reference), 0.0, None))
    if not np.all(d > 0):
        return float("inf"), np.zeros(matrix.shape[0])
    scale = np.outer(d, d)
    try:
        values, vectors = scipy.linalg.eigh(matrix / scale, reference / scale)
    except np.linalg.LinAlgError:
        return float("inf"), np.zeros(matrix.shape[0])
    if not values[0] > 0:
        return float("inf"), vectors[:, 0]
    return float(values[-1] / values[0]), vectors[:, 0]
