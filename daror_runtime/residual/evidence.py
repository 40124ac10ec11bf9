"""The evidence for one candidate effect: is it identifiable, significant, and does it generalise?

A candidate is *found* only when all four hold (one configuration for every dataset; the
defaults and their reasons are in ``docs/residual.md``):

1. **Identifiable**: the directions it adds to the model's prediction are not already spanned
   by the model (its linear columns and the local directions of its nonlinear parameters).
   An encoder offset on joint 3 or 4, or a stiffness polynomial on the elbow, is absorbed by
   PLF+ exactly (a rotated ``theta``, a shifted polynomial): the base already holds it, so it
   is reported as *absorbed*, never *found*.
2. **Significant**: the nested-model F test rejects "no effect" at ``alpha`` divided by the
   number of candidates of the round (Bonferroni).
3. **Worth its parameters**: the Bayesian information criterion falls by more than
   ``bic_margin`` (10: "very strong" on Kass and Raftery's scale).
4. **Generalises**: the held-out RMSE of a contiguous-block cross-validation on the training
   data falls by at least ``min_cv_gain``. Contiguous blocks, not random points, so that a
   neighbouring stop cannot vouch for its neighbour and a drift in time is not mistaken for a
   configuration effect as easily.

The validation file plays no part in choosing: it is kept for the before/after report.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.stats

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import ConfigurationError
from daror_runtime.residual.effects import FAMILIES, Effect, family
from daror_runtime.residual.reduced import Factor
from daror_runtime.residual.structure import (
    DEFAULT_STIFFNESS_ORDER,
    Structure,
    StructureFit,
    Workspace,
    fit_structure,
    solve_reduced,
)
from hal.robot import N_JOINTS, FloatArray


@dataclass(frozen=True)
class DiagnosisSettings:
    """Thresholds of the diagnosis; the same for every dataset (never tuned per scenario)."""

    families: tuple[str, ...] = tuple(FAMILIES)
    alpha: float = 1e-3
    bic_margin: float = 10.0
    min_cv_gain: float = 0.02
    absorbed_below: float = 1e-3
    folds: int = 5
    max_effects: int = 6
    stiffness_order: int = DEFAULT_STIFFNESS_ORDER
    unexplained_alpha: float = 1e-3
    unexplained_min_r2: float = 0.05


@dataclass(frozen=True)
class CandidateEvidence:
    """What one round of the diagnosis measured for one candidate."""

    effect: Effect
    verdict: str  # found | absorbed | not significant | too small | does not generalise
    orthogonal_fraction: float
    delta_parameters: int = 0
    rss_ratio: float = 1.0
    delta_bic: float = 0.0
    f_statistic: float = 0.0
    p_value: float = 1.0
    cv_rmse_before_nm: float = math.nan
    cv_rmse_after_nm: float = math.nan
    fit: StructureFit | None = None

    @property
    def found(self) -> bool:
        return self.verdict == "found"

    @property
    def cv_gain(self) -> float:
        """Relative fall of the held-out RMSE (0.1: ten percent lower)."""
        if not (self.cv_rmse_before_nm > 0):
            return 0.0
        return 1.0 - self.cv_rmse_after_nm / self.cv_rmse_before_nm

    def to_dict(self) -> dict[str, object]:
        """JSON-ready; figures not measured (an absorbed candidate is never fitted) are None."""
        return {
            key: (None if isinstance(value, float) and not math.isfinite(value) else value)
            for key, value in self._figures().items()
        }

    def _figures(self) -> dict[str, object]:
        return {
            "effect": self.effect.family,
            "joint": self.effect.joint,
            "verdict": self.verdict,
            "orthogonal_fraction": self.orthogonal_fraction,
            "delta_parameters": self.delta_parameters,
            "rss_ratio": self.rss_ratio,
            "delta_bic": self.delta_bic,
            "f_statistic": self.f_statistic,
            "p_value": self.p_value,
            "cv_rmse_before": self.cv_rmse_before_nm,
            "cv_rmse_after": self.cv_rmse_after_nm,
            "cv_gain": self.cv_gain,
        }


def _on(fit: StructureFit, data: StationaryDataset, folds: int) -> StructureFit:
    """``fit``, moved to a workspace of ``data`` and ``folds`` when it was fitted with others."""
    workspace = fit.workspace
    if data is workspace.data and folds == workspace.folds:
        return fit
    structure = fit.structure
    workspace = Workspace(
        data, structure.description, structure.base, structure.families, structure.stiffness_order, folds
    )
    return dataclasses.replace(fit, workspace=workspace, _memo={})


def cv_rmse(fit: StructureFit, data: StationaryDataset, folds: int) -> float:
    """Held-out RMSE (Nm) of the structure refitted on all but one contiguous block, per block.

    The nonlinear parameters stay at the full-data fit (a handful against dozens of linear
    ones); the linear ones are refitted per fold. Each fold has a QR factor of its own, and the
    other folds' factors stacked stand for the training rows (:mod:`.reduced`): nothing is copied.
    """
    fit = _on(fit, data, folds)
    factor = fit.factor()
    structure = fit.structure
    co = structure.coefficients(fit.phi, factor.layout)
    target = co.per_joint_target(factor.layout)
    design = co.per_joint_design()
    total = 0.0
    for k in range(factor.folds):
        if factor.points(("fold", k)) == 0:
            continue
        held = factor.assemble(("fold", k), target)
        if structure.n_linear:
            theta = solve_reduced(factor, co, ("train", k)).x
            held = held - factor.assemble(("fold", k), design) @ theta
        total += float(held @ held)
    return float(np.sqrt(total / (N_JOINTS * len(data))))


@dataclass(frozen=True)
class Span:
    """Orthonormal basis (M, r) of every direction the fitted model can already move in, in the
    reduced rows of a diagnosis round's factor (:meth:`.Workspace.round_factor`)."""

    basis: FloatArray
    factor: Factor


def _parameter_direction(
    structure: Structure, phi: FloatArray, x: FloatArray, factor: Factor, index: int
) -> FloatArray:
    """d(prediction)/d(phi[index]) in ``factor``'s rows: a combination of its columns, or for an
    encoder offset the derivative column the round factor carries for that joint."""
    coefficients = structure.direction_coefficients(phi, x, factor.layout, index)
    if coefficients is None:
        kind, joint = structure.derivative_requests()[index]
        layout = factor.layout
        if kind != "delta" or layout.n_derivatives != N_JOINTS:
            raise ConfigurationError(f"no derivative column for {kind} {joint + 1} in this factor")
        unit = np.zeros(layout.size)
        unit[layout.derivative(joint)] = 1.0
        coefficients = [unit] * N_JOINTS
    return factor.assemble("all", coefficients)


def span_basis(fit: StructureFit, data: StationaryDataset) -> Span:
    """Orthonormal basis of every direction the fitted model can already move in."""
    fit = _on(fit, data, fit.workspace.folds)
    factor = fit.workspace.round_factor(fit)
    structure = fit.structure
    co = structure.coefficients(fit.phi, factor.layout)
    parts = [factor.assemble("all", co.per_joint_design())]
    parts += [_parameter_direction(structure, fit.phi, fit.x, factor, i)[:, None] for i in range(structure.n_nonlinear)]
    directions = np.column_stack(parts)
    if directions.shape[1] == 0:
        return Span(np.zeros((directions.shape[0], 0)), factor)
    norms = np.linalg.norm(directions, axis=0)
    if not np.any(norms > 0):
        return Span(np.zeros((directions.shape[0], 0)), factor)
    directions = directions[:, norms > 0] / norms[norms > 0]
    # Pivoted Householder QR: as reliable as an SVD for the span, several times faster here.
    q, r, _ = scipy.linalg.qr(directions, mode="economic", pivoting=True)
    diagonal = np.abs(np.diag(r))
    return Span(q[:, diagonal > 1e-10 * diagonal[0]], factor)


def candidate_directions(fit: StructureFit, effect: Effect, data: StationaryDataset, factor: Factor) -> FloatArray:
    """Directions (M, m) the candidate adds to the fitted model's prediction, in ``factor``'s rows."""
    extended = fit.structure.with_effect(effect)
    phi = np.concatenate([fit.phi, np.asarray(family(effect.family).initial, dtype=float)])
    linear = extended.linear_slice(effect)
    if linear is not None:
        co = extended.coefficients(phi, factor.layout)
        return factor.assemble("all", [co.gain[j] * co.design[:, linear] for j in range(N_JOINTS)])
    where = extended.nonlinear_slice(effect)
    indices = range(where.start, where.stop)  # type: ignore[union-attr]
    return np.column_stack([_parameter_direction(extended, phi, fit.x, factor, i) for i in indices])


def orthogonal_fraction(basis: FloatArray, directions: FloatArray) -> float:
    """Smallest share of a candidate direction's norm outside the span of ``basis`` (0 to 1)."""
    worst = 1.0
    for d in directions.T:
        norm = float(np.linalg.norm(d))
        if norm == 0.0:
            return 0.0
        outside = d - basis @ (basis.T @ d)
        worst = min(worst, float(np.linalg.norm(outside)) / norm)
    return worst


def evaluate_candidate(
    current: StructureFit,
    cv_before_nm: float,
    span: Span,
    effect: Effect,
    data: StationaryDataset,
    settings: DiagnosisSettings,
    n_candidates: int,
) -> CandidateEvidence:
    """Fit ``current`` plus ``effect`` and weigh the evidence (see the module docstring)."""
    fraction = orthogonal_fraction(span.basis, candidate_directions(current, effect, data, span.factor))
    if fraction < settings.absorbed_below:
        return CandidateEvidence(effect, "absorbed", fraction)
    extended = current.structure.with_effect(effect)
    phi0 = np.concatenate([current.phi, np.asarray(family(effect.family).initial, dtype=float)])
    fit = fit_structure(extended, data, phi0 if extended.n_nonlinear else None, current.workspace)
    n = fit.n_rows
    delta_k = fit.n_effective - current.n_effective
    if delta_k <= 0:
        return CandidateEvidence(effect, "absorbed", fraction, fit=fit)
    rss0, rss1 = max(current.rss, 1e-300), max(fit.rss, 1e-300)
    dof = n - fit.n_effective
    f_stat = max((rss0 - rss1) / delta_k, 0.0) / (rss1 / dof)
    p_value = float(scipy.stats.f.sf(f_stat, delta_k, dof))
    delta_bic = n * math.log(rss1 / rss0) + delta_k * math.log(n)
    cv_after = cv_rmse(fit, data, settings.folds)
    evidence = CandidateEvidence(
        effect,
        "found",
        fraction,
        delta_parameters=delta_k,
        rss_ratio=rss1 / rss0,
        delta_bic=delta_bic,
        f_statistic=f_stat,
        p_value=p_value,
        cv_rmse_before_nm=cv_before_nm,
        cv_rmse_after_nm=cv_after,
        fit=fit,
    )
    if p_value >= settings.alpha / max(n_candidates, 1):
        verdict = "not significant"
    elif delta_bic > -settings.bic_margin:
        verdict = "too small"
    elif evidence.cv_gain < settings.min_cv_gain:
        verdict = "does not generalise"
    else:
        return evidence
    return dataclasses.replace(evidence, verdict=verdict)


# --- what remains ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Correlate:
    """How much of one joint's residual one signal explains (a cubic fit, or per-value means)."""

    joint: int
    signal: str
    r2: float
    p_value: float
    pearson_r: float
    structured: bool

    def to_dict(self) -> dict[str, object]:
        return {
            "joint": self.joint,
            "signal": self.signal,
            "r2": self.r2,
            "p_value": self.p_value,
            "pearson_r": self.pearson_r,
            "structured": self.structured,
        }


def residual_signals(data: StationaryDataset) -> dict[str, FloatArray]:
    """Signals a residual may depend on: each joint angle, time (or sample order), directions."""
    signals = {f"q{j + 1}": data.q_rad[:, j] for j in range(N_JOINTS)}
    signals["t" if data.t_s is not None else "order"] = (
        data.t_s if data.t_s is not None else np.arange(len(data), dtype=float)
    )
    if data.direction is not None:
        # the sign of the last motion (-1, 0, +1), or the hysteresis state in [-1, 1] (.travel)
        sign = bool(np.all(np.isin(data.direction, (-1.0, 0.0, 1.0))))
        signals.update({f"{'dir' if sign else 's'}{j + 1}": data.direction[:, j] for j in range(N_JOINTS)})
    return signals


def _is_direction_signal(name: str) -> bool:
    return name.startswith("dir") or (name.startswith("s") and name[1:].isdigit())


def _basis(values: FloatArray, categorical: bool) -> FloatArray:
    if categorical:
        levels = np.unique(values)
        return np.column_stack([values == level for level in levels]).astype(float)
    spread = float(np.std(values))
    z = (values - np.mean(values)) / (spread if spread > 0 else 1.0)
    return np.vander(z, 4, increasing=True)


def residual_structure(
    residual_nm: FloatArray, data: StationaryDataset, settings: DiagnosisSettings
) -> list[Correlate]:
    """Each joint's residual against each signal, and against its own previous point; strongest first.

    ``structured`` marks a signal that explains at least ``unexplained_min_r2`` of a joint's
    residual variance with a p-value below ``unexplained_alpha`` over the number of tests
    (an F test for the signals, the normal limit of the lag-1 autocorrelation for the previous
    point). A direction signal (the sign ``dir_j``, or the hysteresis state ``s_j``) is only
    tested against its own joint.
    """
    signals = residual_signals(data)
    tests: list[tuple[int, str, FloatArray, bool]] = []
    for j in range(N_JOINTS):
        for name, values in signals.items():
            if _is_direction_signal(name) and not name.endswith(str(j + 1)):
                continue
            tests.append((j, name, values, name.startswith("dir")))  # a sign has levels; a state is continuous
    n = residual_nm.shape[0]
    out: list[Correlate] = []
    for j, name, values, categorical in tests:
        r = residual_nm[:, j]
        centred = r - r.mean()
        total = float(centred @ centred)
        basis = _basis(values, categorical)
        p = np.linalg.matrix_rank(basis)
        if total <= 0 or p < 2 or n - p <= 0:
            out.append(Correlate(j + 1, name, 0.0, 1.0, 0.0, False))
            continue
        coef, *_ = np.linalg.lstsq(basis, r, rcond=None)
        fitted = r - basis @ coef
        rss = float(fitted @ fitted)
        r2 = max(0.0, 1.0 - rss / total)
        f_stat = ((total - rss) / (p - 1)) / (rss / (n - p)) if rss > 0 else math.inf
        p_value = float(scipy.stats.f.sf(f_stat, p - 1, n - p))
        spread = float(np.std(values))
        pearson = float(np.corrcoef(values, r)[0, 1]) if spread > 0 and np.std(r) > 0 else 0.0
        structured = (
            p_value < settings.unexplained_alpha / (len(tests) + N_JOINTS) and r2 >= settings.unexplained_min_r2
        )
        out.append(Correlate(j + 1, name, r2, p_value, pearson, structured))
    # Structure tied to how the robot got there (a direction error without dir columns, hysteresis,
    # anything that persists along a segment) makes neighbours in recording order alike even
    # when no tested signal explains it: the lag-1 autocorrelation of white noise is ~N(0, 1/n).
    n_tests = len(tests) + N_JOINTS
    for j in range(N_JOINTS):
        r = residual_nm[:, j] - residual_nm[:, j].mean()
        denominator = float(r @ r)
        lag1 = float(r[1:] @ r[:-1]) / denominator if denominator > 0 and n > 2 else 0.0
        p_value = float(scipy.stats.norm.sf(lag1 * math.sqrt(n)))
        structured = p_value < settings.unexplained_alpha / n_tests and lag1**2 >= settings.unexplained_min_r2
        out.append(Correlate(j + 1, "previous point (lag-1 autocorrelation)", lag1**2, p_value, lag1, structured))
    return sorted(out, key=lambda c: -c.r2)
