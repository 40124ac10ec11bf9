"""Diagnosis: from the base fit's residual to the effects the data support, and what remains.

Forward selection with evidence (:mod:`.evidence`): every round fits each remaining candidate
on top of the current model, keeps those that are identifiable, significant, worth their
parameters and generalise, and adds the strongest (largest fall of the BIC). It stops when no
candidate passes, or at ``max_effects``. Nothing significant: nothing is added, and the report
says so. Then the residual of the final model is tested against every signal it could depend
on; structure that remains is reported as ``unexplained``, with what it correlates with.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import structlog

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import ConfigurationError, IdentifiabilityError
from daror_runtime.models.linear import structural_rank
from daror_runtime.models.metrics import ErrorMetrics, error_metrics
from daror_runtime.residual.effects import Effect, PhysicalContext, candidate_effects, family
from daror_runtime.residual.evidence import (
    CandidateEvidence,
    Correlate,
    DiagnosisSettings,
    cv_rmse,
    evaluate_candidate,
    residual_structure,
    span_basis,
)
from daror_runtime.residual.structure import (
    Structure,
    StructureFit,
    Workspace,
    base_model,
    fit_structure,
    standard_errors,
)
from hal.robot import N_JOINTS, FloatArray, RobotDescription

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class FoundEffect:
    """An effect the diagnosis added, with its physical parameters and the evidence for it."""

    effect: Effect
    parameters: dict[str, Any]
    sentence: str
    evidence: CandidateEvidence
    fit: StructureFit  # the model right after this effect was added


@dataclass(frozen=True)
class Diagnosis:
    """Everything the diagnosis found on the training data."""

    base_kind: str
    base_fit: StructureFit
    final_fit: StructureFit
    found: list[FoundEffect]
    rounds: list[list[CandidateEvidence]]
    correlates: list[Correlate]
    settings: DiagnosisSettings
    notes: list[str] = field(default_factory=list)
    duration_s: float = 0.0
    #: The hysteresis travel constants (rad, per joint) the direction signal was computed with;
    #: None: the direction signal is the sign of the last motion.
    travel_rad: FloatArray | None = None

    @property
    def unexplained(self) -> bool:
        return any(c.structured for c in self.correlates)

    @property
    def structured_correlates(self) -> list[Correlate]:
        return [c for c in self.correlates if c.structured]


def _check_base_identifiable(fit: StructureFit, data: StationaryDataset, description: RobotDescription) -> None:
    base = fit.structure.base
    if not base.is_fitted:
        return
    expected = structural_rank(description.geometry, base.elbow_order)
    if fit.rank < expected:
        raise IdentifiabilityError(
            f"{data.source}: {len(data)} stationary points identify only {fit.rank} of the {expected} independent "
            f"parameter combinations of {base.kind}; expected points that move every joint"
        )
    if fit.n_rows - fit.rank < fit.rank:
        raise IdentifiabilityError(
            f"{data.source}: {len(data)} stationary points are too few for {base.kind}; expected at least "
            f"{-(-2 * fit.rank // N_JOINTS)}"
        )


def bic(fit: StructureFit) -> float:
    """Bayesian information criterion of a fit (Gaussian residual, n = scalar equations)."""
    n = fit.n_rows
    return n * math.log(max(fit.rss, 1e-300) / n) + fit.n_effective * math.log(n)


def _lowest_order(
    fit: StructureFit, effect: Effect, data: StationaryDataset, settings: DiagnosisSettings
) -> tuple[StructureFit, Effect]:
    """For a stiffness polynomial, the order (1 up to the default) with the lowest BIC.

    The default order detects a stiffness of any shape; but terms the data do not need trade
    off against the gravity model's own angle dependence and smear the physical figures (a
    linear spring read as a cubic). The order that best pays for its terms is kept.
    """
    if effect.family != "joint_stiffness":
        return fit, effect
    best_fit, best_effect, best_bic = fit, effect, bic(fit)
    for order in range(1, settings.stiffness_order):
        candidate = Effect(effect.family, effect.joint, order)
        trial = fit_structure(
            fit.structure.replacing(effect, candidate), data, fit.phi if fit.phi.size else None, fit.workspace
        )
        if bic(trial) < best_bic:
            best_fit, best_effect, best_bic = trial, candidate, bic(trial)
    return best_fit, best_effect


def physical_parameters(
    fit: StructureFit, effect: Effect, data: StationaryDataset, travel_rad: FloatArray | None = None
) -> dict[str, Any]:
    """Physical parameters of ``effect`` in ``fit`` (with standard errors where identifiable)."""
    linear, nonlinear = fit.effect_values(effect)
    context = PhysicalContext(
        q_mean_rad=np.mean(data.q_rad, axis=0),
        q_min_rad=np.min(data.q_rad, axis=0),
        q_max_rad=np.max(data.q_rad, axis=0),
        spring_nm_per_rad=fit.structure.description.sea.spring_stiffness_nm_per_rad,
        standard_errors=standard_errors(fit, data),
        travel_rad=travel_rad,
    )
    return family(effect.family).physical(effect, linear, nonlinear, context)


def diagnose(
    train: StationaryDataset,
    description: RobotDescription,
    base_kind: str = "plf+",
    settings: DiagnosisSettings | None = None,
    dummy_arm: bool = False,
    travel_rad: FloatArray | None = None,
) -> Diagnosis:
    """Find the effects the training data support on top of ``base_kind``.

    Families that need a signal the data lack (``direction_offset`` without ``dir``) are skipped
    with a note; callers that were asked for them explicitly refuse before calling.

    ``travel_rad``: the data's direction signal is the hysteresis state for these travel
    constants (:mod:`.travel`), so ``hysteresis`` is tested in the direction offset's place;
    None: the sign of the last motion, and ``hysteresis`` is left to :mod:`.travel`.

    Raises:
        UsageError: an unknown base kind or family.
        IdentifiabilityError: the data cannot identify the base model.
    """
    settings = settings or DiagnosisSettings()
    start = time.perf_counter()
    notes: list[str] = []
    base = base_model(base_kind, description, dummy_arm)
    structure = Structure(base, (), description, settings.stiffness_order)
    workspace = Workspace(train, description, base, settings.families, settings.stiffness_order, settings.folds)
    current = fit_structure(structure, train, workspace=workspace)
    _check_base_identifiable(current, train, description)
    base_fit = current
    candidates = []
    for effect in candidate_effects(settings.families):
        if family(effect.family).needs_history if travel_rad is None else effect.family == "direction_offset":
            continue  # the direction signal is the sign, or the hysteresis state: one of the two families
        needs_signal = family(effect.family).needs_direction or family(effect.family).needs_history
        if needs_signal and train.direction is None:
            note = f"{effect.family}: not tested, the data have no dir1..dir4 columns"
            if note not in notes:
                notes.append(note)
            continue
        candidates.append(effect)
    found: list[FoundEffect] = []
    rounds: list[list[CandidateEvidence]] = []
    while len(found) < settings.max_effects:
        remaining = [c for c in candidates if not current.structure.has_site(c)]
        if not remaining:
            break
        span = span_basis(current, train)  # first: its factor serves the cross-validation too
        cv_before = cv_rmse(current, train, settings.folds)
        evidence = [evaluate_candidate(current, cv_before, span, c, train, settings, len(remaining)) for c in remaining]
        rounds.append(sorted(evidence, key=lambda e: e.delta_bic))
        passing = [e for e in evidence if e.found]
        if not passing:
            break
        best = min(passing, key=lambda e: e.delta_bic)
        if best.fit is None:
            raise ConfigurationError(f"candidate {best.effect.label} was found without a fit")
        current, effect = _lowest_order(best.fit, best.effect, train, settings)
        parameters = physical_parameters(current, effect, train, travel_rad)
        sentence = family(effect.family).sentence(effect, parameters)
        found.append(FoundEffect(effect, parameters, sentence, best, current))
        log.info("residual.effect_found", effect=effect.label, detail=sentence, delta_bic=best.delta_bic)
    if len(found) == settings.max_effects:
        notes.append(f"stopped at max_effects = {settings.max_effects}; more candidates may pass")
    # Re-derive the parameters of every effect from the final model, where they are estimated jointly.
    final_found = []
    for f in found:
        parameters = physical_parameters(current, f.effect, train, travel_rad)
        sentence = family(f.effect.family).sentence(f.effect, parameters)
        final_found.append(FoundEffect(f.effect, parameters, sentence, f.evidence, f.fit))
    correlates = residual_structure(current.residual_nm, train, settings)
    return Diagnosis(
        base_kind=base_kind,
        base_fit=base_fit,
        final_fit=current,
        found=final_found,
        rounds=rounds,
        correlates=correlates,
        settings=settings,
        notes=notes,
        duration_s=time.perf_counter() - start,
        travel_rad=travel_rad,
    )


@dataclass(frozen=True)
class UndeterminedPoints:
    """Validation points whose hysteresis state their run's log does not determine, and the closure without them.

    ``index``: the points' positions in the validation data; ``joints``: the joints (1-4) whose
    state is unknown at one of them; ``before``/``after``: the base and the augmented model on the
    other points (None when no other point is left).
    """

    index: np.ndarray
    t_s: tuple[float, ...]
    joints: tuple[int, ...]
    before: ErrorMetrics | None
    after: ErrorMetrics | None

    @property
    def n_points(self) -> int:
        return int(self.index.size)


@dataclass(frozen=True)
class Closure:
    """Before/after errors on the validation data, and each effect's share of the gain."""

    before: ErrorMetrics
    after: ErrorMetrics
    rmse_after_each_nm: list[float]  # validation RMSE after each found effect, in order
    #: validation points no model can get right for want of their hysteresis state (None: none)
    undetermined: UndeterminedPoints | None = None

    def rmse_gain_nm(self, index: int) -> float:
        """Fall of the validation RMSE (Nm) when effect ``index`` was added."""
        previous = self.before.rmse_nm if index == 0 else self.rmse_after_each_nm[index - 1]
        return previous - self.rmse_after_each_nm[index]


def closure(diagnosis: Diagnosis, validate: StationaryDataset, unknown_state: np.ndarray | None = None) -> Closure:
    """Errors of the base and the augmented model on ``validate`` (Eq. 4.31-4.32).

    ``unknown_state``: (points, joints) True where a point's hysteresis state is not determined by
    its log (:meth:`~daror_runtime.residual.hysteresis.PointHistory.undetermined`), on the joints
    whose hysteresis was found; the closure is then also given without those points.
    """
    base = diagnosis.base_fit.predict(validate)
    final = diagnosis.final_fit.predict(validate)
    before = error_metrics(validate.tau_nm, base)
    after = error_metrics(validate.tau_nm, final)
    each = [error_metrics(validate.tau_nm, f.fit.predict(validate)).rmse_nm for f in diagnosis.found]
    undetermined = None
    if unknown_state is not None and unknown_state.any():
        left_out = unknown_state.any(axis=1)
        kept = ~left_out
        times = validate.t_s[left_out] if validate.t_s is not None else np.full(int(left_out.sum()), np.nan)
        undetermined = UndeterminedPoints(
            np.flatnonzero(left_out),
            tuple(float(t) for t in times),
            tuple(int(j) + 1 for j in np.flatnonzero(unknown_state.any(axis=0))),
            error_metrics(validate.tau_nm[kept], base[kept]) if kept.any() else None,
            error_metrics(validate.tau_nm[kept], final[kept]) if kept.any() else None,
        )
    return Closure(before, after, each, undetermined)
