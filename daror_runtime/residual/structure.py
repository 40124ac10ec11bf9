"""A base model plus effects as one separable least-squares problem (variable projection).

The measured torque of joint ``j`` at point ``n`` is modelled as::

    y[j, n] = G_j(phi) * (f[j, n](phi) + sum_p A[p, j, n](phi) x_p)

with ``x`` the linear parameters (the base model's ``theta`` and elbow polynomial, plus the
columns of linear effects) and ``phi`` the nonlinear ones (encoder offsets, gravity tilt, torque
gains). For fixed ``phi`` the best ``x`` is a minimum-norm least-squares solve (the PLF regressor
is rank-deficient, Sec. 3.3); ``scipy.optimize.least_squares`` then minimises the remaining
residual over the few ``phi`` (Golub and Pereyra's variable projection). With no nonlinear
effect the whole fit is one least-squares solve, exactly the base model's fit.

``f`` is non-zero only for the A Priori base, whose parameters are not fitted.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.optimize

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import UsageError
from daror_runtime.models.least_squares import min_norm_least_squares
from daror_runtime.models.linear import PLF_PLUS_ELBOW_ORDER, APModel
from daror_runtime.models.regressor import (
    GRAVITY_PARAMETER_NAMES,
    LinearTorqueEvaluator,
    polynomial_parameter_names,
    regressor_parameter_major,
)
from daror_runtime.residual.effects import ColumnContext, Effect, Transform, family, tilt_rotation
from hal.robot import N_JOINTS, FloatArray, Geometry, Kinematics, RobotDescription

#: Base model kinds the analysis can augment. The neural models (PENN, NNN) are not linear in
#: their parameters and are not implemented yet.
BASE_KINDS = ("plf+", "plf", "ap")
DEFAULT_STIFFNESS_ORDER = 3


def tilted_kinematics(geometry: Geometry, tilt_rad: FloatArray) -> Kinematics:
    """The chain of ``geometry`` with its base rotated by ``Rx Rz`` (world frame, gravity -y)."""
    kinematics = Kinematics(geometry)
    if not np.any(tilt_rad):
        return kinematics
    return kinematics.with_base_rotation(tilt_rotation(tilt_rad) @ kinematics.base_rotation)


@dataclass(frozen=True)
class BaseModel:
    """The model being augmented: a fitted linear kind, or the fixed A Priori model."""

    kind: str
    elbow_order: int | None = None
    fixed_theta: FloatArray | None = None
    fixed_mu: FloatArray | None = None

    @property
    def is_fitted(self) -> bool:
        return self.fixed_theta is None

    def linear_names(self) -> list[str]:
        if not self.is_fitted:
            return []
        names = list(GRAVITY_PARAMETER_NAMES)
        if self.elbow_order is not None:
            names += list(polynomial_parameter_names(self.elbow_order))
        return names


def base_model(kind: str, description: RobotDescription, dummy_arm: bool = False) -> BaseModel:
    """The base model of ``kind`` (``plf+``, ``plf`` or ``ap``; AP with the Dummy Arm when asked).

    Raises:
        UsageError: a kind the analysis cannot augment.
    """
    if kind == "plf+":
        return BaseModel("plf+", PLF_PLUS_ELBOW_ORDER)
    if kind == "plf":
        return BaseModel("plf")
    if kind == "ap":
        ap = APModel.from_description(description, dummy_arm=dummy_arm, elbow_stiffness=dummy_arm)
        return BaseModel("ap", fixed_theta=ap.theta, fixed_mu=ap.elbow_polynomial)
    raise UsageError(
        f"--base {kind}: the residual analysis augments {', '.join(BASE_KINDS)}; "
        "the neural models are not linear in their parameters (and not implemented yet)"
    )


@dataclass(frozen=True)
class Design:
    """The problem at one ``phi``: columns (P, 4, N), fixed part (4, N), gains (4,)."""

    columns: FloatArray
    fixed: FloatArray
    gain: FloatArray

    def matrix(self) -> FloatArray:
        """``(G A)`` laid out (P, 4 N) for :func:`min_norm_least_squares`."""
        return (self.columns * self.gain[None, :, None]).reshape(self.columns.shape[0], -1)

    def target(self, y: FloatArray) -> FloatArray:
        """``y - G f`` flattened joint-major (4 N,)."""
        return (y - self.gain[:, None] * self.fixed).reshape(-1)


class Structure:
    """A base model and an ordered tuple of effects: parameter layout, design, prediction."""

    def __init__(
        self,
        base: BaseModel,
        effects: Sequence[Effect],
        description: RobotDescription,
        stiffness_order: int = DEFAULT_STIFFNESS_ORDER,
    ) -> None:
        sites = [e.site for e in effects]
        if len(set(sites)) != len(sites):
            raise UsageError(f"an effect appears twice: {', '.join(e.label for e in effects)}")
        self.base = base
        self.effects = tuple(effects)
        self.description = description
        self.stiffness_order = stiffness_order
        self.linear_names: list[str] = base.linear_names()
        self.nonlinear_names: list[str] = []
        self._linear_slices: dict[Effect, slice] = {}
        self._nonlinear_slices: dict[Effect, slice] = {}
        for effect in self.effects:
            fam = family(effect.family)
            n = fam.n_linear(effect, stiffness_order)
            if n:
                self._linear_slices[effect] = slice(len(self.linear_names), len(self.linear_names) + n)
                self.linear_names += fam.linear_names(effect, stiffness_order)
            if fam.n_nonlinear:
                start = len(self.nonlinear_names)
                self._nonlinear_slices[effect] = slice(start, start + fam.n_nonlinear)
                self.nonlinear_names += _nonlinear_names(effect)
        self._design_cache: tuple[tuple[float, ...], StationaryDataset, Design] | None = None

    def with_effect(self, effect: Effect) -> Structure:
        return Structure(self.base, (*self.effects, effect), self.description, self.stiffness_order)

    def replacing(self, old: Effect, new: Effect) -> Structure:
        """The same structure with ``old`` swapped for ``new`` (same place in the layout)."""
        effects = tuple(new if e == old else e for e in self.effects)
        return Structure(self.base, effects, self.description, self.stiffness_order)

    def has_site(self, effect: Effect) -> bool:
        return any(e.site == effect.site for e in self.effects)

    @property
    def n_nonlinear(self) -> int:
        return len(self.nonlinear_names)

    @property
    def needs_direction(self) -> bool:
        return any(family(e.family).needs_direction for e in self.effects)

    def linear_slice(self, effect: Effect) -> slice | None:
        return self._linear_slices.get(effect)

    def nonlinear_slice(self, effect: Effect) -> slice | None:
        return self._nonlinear_slices.get(effect)

    @cached_property
    def nonlinear_bounds(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Initial value, lower and upper bound, and typical size of every nonlinear parameter."""
        initial, lower, upper, typical = [], [], [], []
        for effect in self.effects:
            fam = family(effect.family)
            initial += fam.initial
            lower += fam.lower
            upper += fam.upper
            typical += fam.typical
        return np.array(initial), np.array(lower), np.array(upper), np.array(typical)

    def initial_phi(self) -> FloatArray:
        return self.nonlinear_bounds[0].copy()

    def transform(self, phi: FloatArray) -> Transform:
        transform = Transform()
        for effect, where in self._nonlinear_slices.items():
            family(effect.family).apply(effect, phi[where], transform)
        return transform

    def design(self, phi: FloatArray, data: StationaryDataset) -> Design:
        """The least-squares problem at ``phi`` on ``data`` (cached for the last data and offsets)."""
        transform = self.transform(phi)
        key = transform.key()
        cached = self._design_cache
        if cached is not None and cached[0] == key and cached[1] is data:
            return Design(cached[2].columns, cached[2].fixed, transform.gain)
        q = data.q_rad - transform.angle_offset_rad[None, :]
        kinematics = tilted_kinematics(self.description.geometry, transform.tilt_rad)
        n = len(data)
        blocks: list[FloatArray] = []
        fixed = np.zeros((N_JOINTS, n))
        if self.base.is_fitted:
            blocks.append(regressor_parameter_major(kinematics, q, self.base.elbow_order))
        else:
            evaluator = LinearTorqueEvaluator(kinematics, self.base.fixed_theta, self.base.fixed_mu)  # type: ignore[arg-type]
            fixed = evaluator.torque_batch(q).T.copy()
        context = ColumnContext(q, data.direction)
        for effect in self._linear_slices:
            values = family(effect.family).columns(effect, context, self.stiffness_order)
            block = np.zeros((values.shape[0], N_JOINTS, n))
            block[:, effect.joint - 1, :] = values  # type: ignore[operator]
            blocks.append(block)
        columns = np.concatenate(blocks) if blocks else np.zeros((0, N_JOINTS, n))
        design = Design(columns, fixed, transform.gain)
        self._design_cache = (key, data, design)
        return design

    def predict(self, phi: FloatArray, x: FloatArray, data: StationaryDataset) -> FloatArray:
        """Modelled torque (N, 4) on ``data``."""
        design = self.design(phi, data)
        linear = np.tensordot(x, design.columns, axes=(0, 0)) if x.size else 0.0
        return (design.gain[:, None] * (design.fixed + linear)).T


def _nonlinear_names(effect: Effect) -> list[str]:
    if effect.family == "gravity_tilt":
        return ["gravity_tilt_x_rad", "gravity_tilt_z_rad"]
    if effect.family == "encoder_offset":
        return [f"encoder_offset{effect.joint}_rad"]
    return [f"torque_gain{effect.joint}"]


@dataclass(frozen=True)
class LinearSolve:
    x: FloatArray
    residual: FloatArray  # (4 N,) joint-major
    rank: int


def solve_linear(design: Design, y: FloatArray) -> LinearSolve:
    """Best linear parameters at one design: minimum-norm least squares (rank-deficient base)."""
    target = design.target(y)
    if design.columns.shape[0] == 0:
        return LinearSolve(np.zeros(0), target, 0)
    fit = min_norm_least_squares(design.matrix(), target, refinement_steps=1)
    return LinearSolve(fit.theta, fit.residual, fit.rank)


@dataclass(frozen=True)
class StructureFit:
    """A structure fitted to data."""

    structure: Structure
    phi: FloatArray
    x: FloatArray
    residual_nm: FloatArray  # (N, 4): measured minus modelled
    rss: float
    rank: int
    n_rows: int
    converged: bool

    @property
    def n_effective(self) -> int:
        """Parameters the data actually determine: identifiable linear combinations plus ``phi``."""
        return self.rank + self.structure.n_nonlinear

    @property
    def sigma2(self) -> float:
        dof = self.n_rows - self.n_effective
        return self.rss / dof if dof > 0 else float("nan")

    def predict(self, data: StationaryDataset) -> FloatArray:
        return self.structure.predict(self.phi, self.x, data)

    def effect_values(self, effect: Effect) -> tuple[FloatArray, FloatArray]:
        """(linear, nonlinear) parameter values of one effect."""
        lin = self.structure.linear_slice(effect)
        non = self.structure.nonlinear_slice(effect)
        return (self.x[lin] if lin else np.zeros(0)), (self.phi[non] if non else np.zeros(0))


def fit_structure(structure: Structure, data: StationaryDataset, phi0: FloatArray | None = None) -> StructureFit:
    """Fit ``structure`` to ``data``: least squares, and scipy.optimize over the nonlinear effects."""
    y = np.ascontiguousarray(data.tau_nm.T)
    converged = True
    if structure.n_nonlinear == 0:
        phi = np.zeros(0)
    else:
        start, lower, upper, typical = structure.nonlinear_bounds
        if phi0 is not None:
            start = np.clip(phi0, lower + 1e-9 * typical, upper - 1e-9 * typical)

        def residual(phi: FloatArray) -> FloatArray:
            return solve_linear(structure.design(phi, data), y).residual

        result = scipy.optimize.least_squares(
            residual,
            start,
            bounds=(lower, upper),
            x_scale=typical,
            method="trf",
            ftol=1e-12,
            xtol=1e-10,
            gtol=1e-12,
            max_nfev=60 * (structure.n_nonlinear + 1),
        )
        phi, converged = result.x, bool(result.success)
    solved = solve_linear(structure.design(phi, data), y)
    residual_nm = solved.residual.reshape(N_JOINTS, -1).T
    return StructureFit(
        structure=structure,
        phi=phi,
        x=solved.x,
        residual_nm=residual_nm,
        rss=float(solved.residual @ solved.residual),
        rank=solved.rank,
        n_rows=solved.residual.size,
        converged=converged,
    )


def nonlinear_jacobian(
    structure: Structure, phi: FloatArray, x: FloatArray, data: StationaryDataset, which: slice | None = None
) -> FloatArray:
    """d(prediction)/d(phi) at fixed linear parameters, (4 N, m), by central differences."""
    indices = range(structure.n_nonlinear) if which is None else range(*which.indices(structure.n_nonlinear))
    _, _, _, typical = structure.nonlinear_bounds
    columns = []
    for i in indices:
        step = 1e-4 * typical[i]
        up, down = phi.copy(), phi.copy()
        up[i] += step
        down[i] -= step
        diff = structure.predict(up, x, data) - structure.predict(down, x, data)
        columns.append((diff.T / (2 * step)).reshape(-1))
    return np.column_stack(columns) if columns else np.zeros((len(data) * N_JOINTS, 0))


def standard_errors(fit: StructureFit, data: StationaryDataset) -> dict[str, float]:
    """Standard error of every identifiable parameter, from ``sigma^2 (J^T J)^+`` at the fit.

    A parameter the data cannot determine (a null-space direction of the rank-deficient base)
    gets no entry.
    """
    structure = fit.structure
    design = structure.design(fit.phi, data)
    jac = np.column_stack([design.matrix().T, nonlinear_jacobian(structure, fit.phi, fit.x, data)])
    names = structure.linear_names + structure.nonlinear_names
    norms = np.linalg.norm(jac, axis=0)
    scale = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 0.0)
    scaled = jac * scale
    # Eigen-decomposition of the small normal matrix instead of an SVD of the tall Jacobian:
    # standard errors need two digits, not the last bit.
    eigenvalues, vectors = np.linalg.eigh(scaled.T @ scaled)
    order = np.argsort(eigenvalues)[::-1]
    eigenvalues, vectors = np.clip(eigenvalues[order], 0.0, None), vectors[:, order]
    keep = eigenvalues > 1e-14 * eigenvalues[0]
    v = vectors[:, keep]
    cov_scaled = (v / eigenvalues[keep]) @ v.T
    null = vectors[:, ~keep].T
    out: dict[str, float] = {}
    for i, name in enumerate(names):
        unit = np.zeros(len(names))
        unit[i] = 1.0
        if null.size and np.linalg.norm(null @ unit) > 1e-6:
            continue  # not estimable on its own
        out[name] = float(np.sqrt(max(fit.sigma2 * cov_scaled[i, i], 0.0)) * scale[i])
    return out
