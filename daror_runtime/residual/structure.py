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

Scale: ``A`` and ``f`` are combinations of fixed columns (:mod:`.columns`), and every solve runs
on their QR factor (:mod:`.reduced`): a few hundred rows whatever the number of points, with the
same solution, rank and residual norm as the full (4 N)-row problem. Nothing of size N is kept
per candidate; a fit's residual is computed when asked for.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.optimize

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import UsageError
from daror_runtime.models.least_squares import min_norm_least_squares
from daror_runtime.models.linear import PLF_PLUS_ELBOW_ORDER, APModel
from daror_runtime.models.registry import kind_names
from daror_runtime.models.regressor import (
    GRAVITY_PARAMETER_NAMES,
    N_GRAVITY_PARAMETERS,
    polynomial_parameter_names,
)
from daror_runtime.residual.columns import (
    BLOCK_POINTS,
    FREE_TILT_BASIS,
    Block,
    Derivatives,
    Layout,
    blocks,
    fill_columns,
    up_vector,
    up_vector_derivatives,
)
from daror_runtime.residual.effects import DIRECTION_FAMILIES, Effect, Transform, family, tilt_rotation
from daror_runtime.residual.reduced import Factor, FactorCache, factorize
from hal.robot import N_JOINTS, FloatArray, Geometry, Kinematics, RobotDescription


def base_kinds() -> tuple[str, ...]:
    """The model kinds the analysis can augment: those of the registry with the capability ``residual_base``.

    :func:`base_model` builds each of them. The neural models (PENN, NNN) are not linear in their
    parameters and are not implemented yet.
    """
    return kind_names(lambda entry: entry.residual_base)


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
        f"--base {kind}: the residual analysis augments {', '.join(base_kinds())}; "
        "the neural models are not linear in their parameters (and not implemented yet)"
    )


@dataclass(frozen=True)
class Coefficients:
    """A structure at one ``phi`` on a layout: ``pred_j = g_j Z_j (t_f + T x)`` (:mod:`.columns`)."""

    design: FloatArray  # T, (layout size, P)
    fixed: FloatArray  # t_f, (layout size,)
    gain: FloatArray  # (4,)
    offset_rad: FloatArray  # (4,) encoder offsets: the layout's columns are taken at q - offset
    up: FloatArray  # (3,) the up direction seen by the untilted chain
    theta_total: FloatArray  # (12,) fixed first moments on u (the A Priori base's; zero for a fitted base)

    def unscaled(self, x: FloatArray) -> FloatArray:
        """Global coefficients of the prediction before gains: ``t_f + T x``."""
        return self.fixed + (self.design @ x if x.size else 0.0)

    def per_joint_design(self) -> list[FloatArray]:
        return [self.gain[j] * self.design for j in range(N_JOINTS)]

    def per_joint_target(self, layout: Layout) -> list[FloatArray]:
        unit = np.zeros(layout.size)
        unit[layout.tau] = 1.0
        return [unit - self.gain[j] * self.fixed for j in range(N_JOINTS)]


class Structure:
    """A base model and an ordered tuple of effects: parameter layout, columns, prediction."""

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
    def n_linear(self) -> int:
        return len(self.linear_names)

    @property
    def needs_direction(self) -> bool:
        return any(family(e.family).needs_direction for e in self.effects)

    @property
    def has_offsets(self) -> bool:
        """Encoder offsets move the angles every column is taken at: fits need passes over the data."""
        return any(e.family == "encoder_offset" for e in self.effects)

    @property
    def families(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(e.family for e in self.effects))

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

    @cached_property
    def kinematics(self) -> Kinematics:
        """The untilted chain: a tilt enters as the up direction the chain sees (:mod:`.columns`)."""
        return Kinematics(self.description.geometry)

    def transform(self, phi: FloatArray) -> Transform:
        transform = Transform()
        for effect, where in self._nonlinear_slices.items():
            family(effect.family).apply(effect, phi[where], transform)
        return transform

    def derivative_requests(self) -> tuple[tuple[str, int], ...]:
        """What each nonlinear parameter is, in order, for :class:`.columns.Derivatives`."""
        out: list[tuple[str, int]] = []
        for effect in self.effects:
            if effect.family == "gravity_tilt":
                out += [("tilt", 0), ("tilt", 1)]
            elif effect.family == "encoder_offset":
                out.append(("delta", effect.joint - 1))  # type: ignore[operator]
            elif effect.family == "torque_gain":
                out.append(("gain", effect.joint - 1))  # type: ignore[operator]
        return tuple(out)

    # -- columns ----------------------------------------------------------------------------

    @property
    def n_poly(self) -> int:
        """Elbow-polynomial powers the base needs (PLF+'s fitted ones, or AP's fixed spring)."""
        if self.base.is_fitted:
            return 0 if self.base.elbow_order is None else self.base.elbow_order + 1
        return int(np.asarray(self.base.fixed_mu).size)

    def own_layout(self, up: FloatArray) -> Layout:
        """The columns this structure needs, with the gravity regressor for one up direction."""
        direction = tuple(sorted(e.joint - 1 for e in self.effects if e.family in DIRECTION_FAMILIES))  # type: ignore[operator]
        stiffness = tuple(
            sorted(
                (e.joint - 1, family(e.family).n_linear(e, self.stiffness_order))  # type: ignore[operator]
                for e in self.effects
                if e.family == "joint_stiffness"
            )
        )
        return Layout((tuple(float(v) for v in up),), self.n_poly, direction, stiffness)  # type: ignore[arg-type]

    def coefficients(self, phi: FloatArray, layout: Layout) -> Coefficients:
        """``T``, ``t_f`` and the gains of this structure at ``phi`` over ``layout``'s columns."""
        transform = self.transform(phi)
        up = up_vector(transform.tilt_rad)
        on_up = layout.up_coefficients(up)
        design = np.zeros((layout.size, self.n_linear))
        fixed = np.zeros(layout.size)
        theta_total = np.zeros(N_GRAVITY_PARAMETERS)
        if self.base.is_fitted:
            for a, weight in enumerate(on_up):
                for p in range(N_GRAVITY_PARAMETERS):
                    design[layout.gravity(a, p), p] = weight
            for k in range(self.n_poly):
                design[layout.poly(k), N_GRAVITY_PARAMETERS + k] = 1.0
        else:
            theta_total = np.asarray(self.base.fixed_theta, dtype=float)
            for a, weight in enumerate(on_up):
                fixed[layout.gravity(a, 0) : layout.gravity(a, N_GRAVITY_PARAMETERS)] = weight * theta_total
            fixed[layout.poly(0) : layout.poly(self.n_poly)] = np.asarray(self.base.fixed_mu, dtype=float)
        for effect, where in self._linear_slices.items():
            joint = effect.joint - 1  # type: ignore[operator]
            if effect.family in DIRECTION_FAMILIES:
                design[layout.direction(joint), where.start] = 1.0
            else:
                for k in range(where.stop - where.start):
                    design[layout.stiffness_power(joint, k), where.start + k] = 1.0
        return Coefficients(design, fixed, transform.gain.copy(), transform.angle_offset_rad.copy(), up, theta_total)

    def direction_coefficients(
        self, phi: FloatArray, x: FloatArray, layout: Layout, index: int
    ) -> list[FloatArray] | None:
        """d(prediction)/d(phi[index]) at fixed ``x`` as per-joint coefficients over ``layout``'s
        columns, when it is a combination of them (gains; the tilt on a free-tilt layout).
        None for an encoder offset, whose derivative is a column of its own (:func:`.columns.derivative_values`).
        """
        kind, which = self.derivative_requests()[index]
        co = self.coefficients(phi, layout)
        if kind == "gain":
            c = co.unscaled(x)
            return [c if j == which else np.zeros(layout.size) for j in range(N_JOINTS)]
        if kind == "tilt" and layout.free_tilt:
            theta = co.theta_total + (x[:N_GRAVITY_PARAMETERS] if self.base.is_fitted else 0.0)
            d_up = up_vector_derivatives(self.transform(phi).tilt_rad)[which]
            c = np.zeros(layout.size)
            for a in range(3):
                c[layout.gravity(a, 0) : layout.gravity(a, N_GRAVITY_PARAMETERS)] = d_up[a] * theta
            return [co.gain[j] * c for j in range(N_JOINTS)]
        return None

    def derivatives(
        self, phi: FloatArray, x: FloatArray, layout: Layout, requests: tuple[tuple[str, int], ...]
    ) -> Derivatives:
        """What :func:`.columns.derivative_values` needs for this structure's prediction at ``(phi, x)``."""
        co = self.coefficients(phi, layout)
        d_up = up_vector_derivatives(self.transform(phi).tilt_rad)
        return Derivatives(co.unscaled(x), co.gain, requests, d_up)

    def predict(self, phi: FloatArray, x: FloatArray, data: StationaryDataset) -> FloatArray:
        """Modelled torque (N, 4) on ``data``, evaluated a block of points at a time."""
        transform = self.transform(phi)
        layout = self.own_layout(up_vector(transform.tilt_rad))
        co = self.coefficients(phi, layout)
        c = co.unscaled(x)
        out = np.empty((len(data), N_JOINTS))
        for lo, hi in blocks(len(data)):
            direction = None if data.direction is None else data.direction[lo:hi]
            block = Block(self.kinematics, data.q_rad[lo:hi], direction, None, co.offset_rad)
            columns = [np.empty((len(local), block.n)) for local in layout.local]
            fill_columns(layout, block, columns)
            for j in range(N_JOINTS):
                out[lo:hi, j] = co.gain[j] * (c[layout.local[j]] @ columns[j])
        return out


def _nonlinear_names(effect: Effect) -> list[str]:
    if effect.family == "gravity_tilt":
        return ["gravity_tilt_x_rad", "gravity_tilt_z_rad"]
    if effect.family == "encoder_offset":
        return [f"encoder_offset{effect.joint}_rad"]
    return [f"torque_gain{effect.joint}"]


# --- the shared factorizations of one dataset ------------------------------------------------


class Workspace:
    """One dataset and the factorizations every fit on it shares (:mod:`.reduced`).

    The *universe* holds every column any structure of the analysis can use (the base, the
    linear families' columns on every joint, the gravity regressor for three up directions when
    the tilt is a candidate), factored once per fold. Every structure without encoder offsets is
    a combination of it: fitting it, its cross-validation, a tilt or a gain optimised by
    ``scipy.optimize`` all run on the reduced rows, with no pass over the data. Encoder offsets
    change the angles every column is taken at; their fits factor the structure's own columns
    anew at each offset (two passes per evaluation, see :func:`fit_structure`).
    """

    def __init__(
        self,
        data: StationaryDataset,
        description: RobotDescription,
        base: BaseModel,
        families: Sequence[str],
        stiffness_order: int = DEFAULT_STIFFNESS_ORDER,
        folds: int = 5,
    ) -> None:
        self.data = data
        self.description = description
        self.base = base
        self.families = tuple(dict.fromkeys(families))
        self.stiffness_order = stiffness_order
        self.folds = folds
        self.kinematics = Kinematics(description.geometry)
        structure = Structure(base, (), description, stiffness_order)
        self.layout = Layout(
            FREE_TILT_BASIS if "gravity_tilt" in self.families else ((0.0, 1.0, 0.0),),
            structure.n_poly,
            tuple(range(N_JOINTS))
            if any(f in self.families for f in DIRECTION_FAMILIES) and data.direction is not None
            else (),
            tuple((j, stiffness_order + 1) for j in range(N_JOINTS)) if "joint_stiffness" in self.families else (),
        )
        self.cache = FactorCache()
        self._universe: Factor | None = None
        self._round: tuple[StructureFit, Factor] | None = None

    def covers(self, structure: Structure, data: StationaryDataset) -> bool:
        """Whether ``structure`` on ``data`` can be fitted from this workspace's factors."""
        base = structure.base
        same_base = base.kind == self.base.kind and base.elbow_order == self.base.elbow_order
        if same_base and not base.is_fitted:
            same_base = np.array_equal(base.fixed_theta, self.base.fixed_theta) and np.array_equal(  # type: ignore[arg-type]
                base.fixed_mu,  # type: ignore[arg-type]
                self.base.fixed_mu,  # type: ignore[arg-type]
            )
        return (
            data is self.data
            and same_base
            and structure.description is self.description
            and structure.stiffness_order == self.stiffness_order
            and set(structure.families) <= set(self.families)
        )

    def universe(self, offset_rad: FloatArray) -> Factor:
        """The universe factored per fold at ``offset_rad`` (the latest one is reused)."""
        current = self._universe
        if current is not None and np.array_equal(current.offset_rad, offset_rad):
            return current
        factor = factorize(self.data, self.kinematics, self.layout, offset_rad, self.folds)
        self._universe = factor
        return factor

    def round_factor(self, fit: StructureFit) -> Factor:
        """The universe at ``fit``'s offsets, with the derivative of ``fit``'s prediction by every
        joint's encoder offset appended when encoder offsets are candidates or in the model: the
        space of a diagnosis round (its span test, its cross-validation, its linear candidates).
        """
        if self._round is not None and self._round[0] is fit:
            return self._round[1]
        structure = fit.structure
        offsets = structure.transform(fit.phi).angle_offset_rad
        if "encoder_offset" in self.families or structure.has_offsets:
            requests = tuple(("delta", j) for j in range(N_JOINTS))
            layout = self.layout.with_derivatives(len(requests))
            spec = structure.derivatives(fit.phi, fit.x, layout, requests)
            factor = factorize(self.data, self.kinematics, layout, offsets, self.folds, spec)
        else:
            factor = self.universe(offsets)
        self._universe = factor
        self._round = (fit, factor)
        return factor

    def own_factor(self, structure: Structure, phi: FloatArray, per_fold: bool = True) -> Factor:
        """``structure``'s own columns at ``phi`` (one up direction, its encoder offsets), per fold
        (for cross-validation) or over all points at once (inside an optimisation)."""
        transform = structure.transform(phi)
        layout = structure.own_layout(up_vector(transform.tilt_rad))
        folds = self.folds if per_fold else 1
        key = ("own", layout, transform.angle_offset_rad.tobytes(), folds)
        factor = self.cache.get(key)
        if factor is None:
            factor = factorize(self.data, self.kinematics, layout, transform.angle_offset_rad, folds)
            self.cache.put(key, factor)
        return factor

    def jacobian_factor(self, structure: Structure, phi: FloatArray, x: FloatArray) -> Factor:
        """``structure``'s own columns and the derivatives of its prediction at ``(phi, x)``, all points."""
        transform = structure.transform(phi)
        requests = structure.derivative_requests()
        layout = structure.own_layout(up_vector(transform.tilt_rad)).with_derivatives(len(requests))
        key = ("jacobian", layout, structure.effects, requests, phi.tobytes(), x.tobytes())
        factor = self.cache.get(key)
        if factor is None:
            spec = structure.derivatives(phi, x, layout, requests)
            factor = factorize(self.data, self.kinematics, layout, transform.angle_offset_rad, 1, spec)
            self.cache.put(key, factor)
        return factor

    def factor_for(self, structure: Structure, phi: FloatArray) -> Factor:
        """The factor a fit of ``structure`` at ``phi`` is solved on (per fold)."""
        if structure.has_offsets:
            return self.own_factor(structure, phi)
        return self.universe(np.zeros(N_JOINTS))


def workspace_for(structure: Structure, data: StationaryDataset, workspace: Workspace | None = None) -> Workspace:
    """``workspace`` when it covers ``structure`` on ``data``; else a new one for them alone."""
    if workspace is not None and workspace.covers(structure, data):
        return workspace
    return Workspace(data, structure.description, structure.base, structure.families, structure.stiffness_order)


# --- solving -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class LinearSolve:
    x: FloatArray
    residual: FloatArray  # reduced rows: the same norm as the 4 N residual
    rank: int
    design: FloatArray  # the reduced design (M, P)


def solve_reduced(factor: Factor, co: Coefficients, which: object = "all") -> LinearSolve:
    """Best linear parameters on ``factor``'s rows: minimum-norm least squares (rank-deficient base)."""
    target = factor.assemble(which, co.per_joint_target(factor.layout))
    design = factor.assemble(which, co.per_joint_design())
    if design.shape[1] == 0:
        return LinearSolve(np.zeros(0), target, 0, design)
    fit = min_norm_least_squares(np.ascontiguousarray(design.T), target, refinement_steps=1)
    return LinearSolve(fit.theta, fit.residual, fit.rank, design)


@dataclass(frozen=True)
class StructureFit:
    """A structure fitted to data (the data are the workspace's)."""

    structure: Structure
    phi: FloatArray
    x: FloatArray
    rss: float
    rank: int
    n_rows: int
    converged: bool
    workspace: Workspace = field(repr=False, compare=False)
    _memo: dict[str, object] = field(default_factory=dict, repr=False, compare=False)

    @property
    def n_effective(self) -> int:
        """Parameters the data actually determine: identifiable linear combinations plus ``phi``."""
        return self.rank + self.structure.n_nonlinear

    @property
    def sigma2(self) -> float:
        dof = self.n_rows - self.n_effective
        return self.rss / dof if dof > 0 else float("nan")

    @cached_property
    def residual_nm(self) -> FloatArray:
        """Measured minus modelled torque on the fitted data, (N, 4) (computed when first asked)."""
        data = self.workspace.data
        return data.tau_nm - self.predict(data)

    def predict(self, data: StationaryDataset) -> FloatArray:
        return self.structure.predict(self.phi, self.x, data)

    def effect_values(self, effect: Effect) -> tuple[FloatArray, FloatArray]:
        """(linear, nonlinear) parameter values of one effect."""
        lin = self.structure.linear_slice(effect)
        non = self.structure.nonlinear_slice(effect)
        return (self.x[lin] if lin else np.zeros(0)), (self.phi[non] if non else np.zeros(0))

    def factor(self) -> Factor:
        """The per-fold factor this fit was solved on."""
        return self.workspace.factor_for(self.structure, self.phi)


class _OffsetProblem:
    """The variable-projection problem of a structure with encoder offsets, for ``least_squares``.

    Each ``phi`` costs two passes: the structure's columns at the new offsets (the linear solve),
    then the same columns with the derivatives of that solution's prediction appended. Residual and
    Jacobian (Kaufman's: the derivatives projected off the design's span) are both taken on the
    second factor's rows, so they live in one coordinate system.
    """

    def __init__(self, structure: Structure, workspace: Workspace) -> None:
        self.structure = structure
        self.workspace = workspace
        self._last: tuple[bytes, FloatArray, FloatArray] | None = None

    def _evaluate(self, phi: FloatArray) -> tuple[FloatArray, FloatArray]:
        key = phi.tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1], self._last[2]
        structure = self.structure
        # On big data every factor is a pass: factor per fold, so the last one serves the final solve
        # and the cross-validation too. On small data the folds' extra QR calls cost more than a pass.
        own = self.workspace.own_factor(structure, phi, per_fold=len(self.workspace.data) > 8 * BLOCK_POINTS)
        solved = solve_reduced(own, structure.coefficients(phi, own.layout))
        factor = self.workspace.jacobian_factor(structure, phi, solved.x)
        co = structure.coefficients(phi, factor.layout)
        reduced = solve_reduced(factor, co)
        layout = factor.layout
        units = np.zeros((layout.size, layout.n_derivatives))
        units[[layout.derivative(d) for d in range(layout.n_derivatives)], range(layout.n_derivatives)] = 1.0
        derivative = factor.assemble("all", [units] * N_JOINTS)
        if reduced.rank:
            design = reduced.design
            norms = np.linalg.norm(design, axis=0)
            scaled = design / np.where(norms > 0, norms, 1.0)
            left = np.linalg.svd(scaled, full_matrices=False)[0][:, : reduced.rank]
            derivative = derivative - left @ (left.T @ derivative)
        self._last = (key, reduced.residual, -derivative)
        return reduced.residual, -derivative

    def residual(self, phi: FloatArray) -> FloatArray:
        return self._evaluate(phi)[0]

    def jacobian(self, phi: FloatArray) -> FloatArray:
        return self._evaluate(phi)[1]


def fit_structure(
    structure: Structure, data: StationaryDataset, phi0: FloatArray | None = None, workspace: Workspace | None = None
) -> StructureFit:
    """Fit ``structure`` to ``data``: least squares, and scipy.optimize over the nonlinear effects.

    Without encoder offsets the nonlinear parameters (tilt, gains) are optimised on the reduced
    rows of the workspace's universe, finite differences included, exactly as on the full data.
    With encoder offsets every evaluation factors the structure's columns anew (see
    :class:`_OffsetProblem`), with an analytic Jacobian.
    """
    ws = workspace_for(structure, data, workspace)
    converged = True
    if structure.n_nonlinear == 0:
        phi = np.zeros(0)
    else:
        start, lower, upper, typical = structure.nonlinear_bounds
        if phi0 is not None:
            start = np.clip(phi0, lower + 1e-9 * typical, upper - 1e-9 * typical)
        settings = dict(
            bounds=(lower, upper),
            x_scale=typical,
            method="trf",
            ftol=1e-12,
            xtol=1e-10,
            gtol=1e-12,
            max_nfev=60 * (structure.n_nonlinear + 1),
        )
        if structure.has_offsets:
            problem = _OffsetProblem(structure, ws)
            result = scipy.optimize.least_squares(problem.residual, start, jac=problem.jacobian, **settings)
        else:
            universe = ws.universe(np.zeros(N_JOINTS))

            def residual(phi: FloatArray) -> FloatArray:
                return solve_reduced(universe, structure.coefficients(phi, universe.layout)).residual

            result = scipy.optimize.least_squares(residual, start, **settings)
        phi, converged = result.x, bool(result.success)
    factor = ws.factor_for(structure, phi)
    solved = solve_reduced(factor, structure.coefficients(phi, factor.layout))
    return StructureFit(
        structure=structure,
        phi=phi,
        x=solved.x,
        rss=float(solved.residual @ solved.residual),
        rank=solved.rank,
        n_rows=len(data) * N_JOINTS,
        converged=converged,
        workspace=ws,
    )


def jacobian_reduced(fit: StructureFit) -> FloatArray:
    """``[G A | d prediction / d phi]`` at the fit, in reduced rows (same Gram matrix as the full one)."""
    structure = fit.structure
    if not structure.has_offsets:
        factor = fit.workspace.universe(np.zeros(N_JOINTS))
        co = structure.coefficients(fit.phi, factor.layout)
        columns = [factor.assemble("all", co.per_joint_design())]
        for i in range(structure.n_nonlinear):
            coefficients = structure.direction_coefficients(fit.phi, fit.x, factor.layout, i)
            if coefficients is None:  # a tilt on a layout without the free tilt: factor its derivative
                return _jacobian_from_pass(fit)
            columns.append(factor.assemble("all", coefficients)[:, None])
        return np.column_stack(columns)
    return _jacobian_from_pass(fit)


def _jacobian_from_pass(fit: StructureFit) -> FloatArray:
    factor = fit.workspace.jacobian_factor(fit.structure, fit.phi, fit.x)
    layout = factor.layout
    co = fit.structure.coefficients(fit.phi, layout)
    units = np.zeros((layout.size, layout.n_derivatives))
    units[[layout.derivative(d) for d in range(layout.n_derivatives)], range(layout.n_derivatives)] = 1.0
    return np.column_stack([factor.assemble("all", co.per_joint_design()), factor.assemble("all", [units] * N_JOINTS)])


def standard_errors(fit: StructureFit, data: StationaryDataset) -> dict[str, float]:
    """Standard error of every identifiable parameter, from ``sigma^2 (J^T J)^+`` at the fit.

    A parameter the data cannot determine (a null-space direction of the rank-deficient base)
    gets no entry.
    """
    memo = fit._memo.get("standard_errors")
    if memo is not None:
        return dict(memo)  # type: ignore[call-overload]
    structure = fit.structure
    jac = jacobian_reduced(fit) if data is fit.workspace.data else _full_jacobian(fit, data)
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
    if data is fit.workspace.data:
        fit._memo["standard_errors"] = dict(out)
    return out


def _full_jacobian(fit: StructureFit, data: StationaryDataset) -> FloatArray:
    """The Jacobian at ``fit``'s parameters on other data (a workspace of their own)."""
    moved = dataclasses.replace(fit, workspace=workspace_for(fit.structure, data), _memo={})
    return jacobian_reduced(moved)
