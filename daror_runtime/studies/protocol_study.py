"""Validation error against robot time: designed protocols, random subsets of the full protocol, the full one.

The study behind ``daror study protocol`` (issue 14, docs/identification.md section 8). On one
simulated plant it runs, in lock-step and through the same pipeline as ``daror identify``
(:func:`~daror_runtime.identification.protocol.run_protocol`):

* the full training protocol (the shipped 83 waypoints, ~750 s of robot time) and the validation
  protocol; every model below is scored on that one validation run;
* for every budget of robot time, the designed protocol (:func:`~daror_runtime.identification.design.design_protocol`)
  of each approach asked for, run in closed loop, PLF+ fitted on its data;
* for every budget, random subsets of the full protocol's data, two ways (``draws`` each, seeded):

  - *random points*, the thesis's method (Sec. 5.3.1, Fig. 5.4, ``daror study data-efficiency``):
    ``n`` stationary points drawn from the full run, ``n`` the budget's share of the full run's
    points (robot time per point as in the full protocol: generous to random subsets, whose
    points are in reality scattered over the whole workspace);
  - *random stops*: stops of the full run drawn in random order and added to a tour (cheapest
    insertion, then shortened by 2-opt) while the tour's robot time, timed like a designed
    protocol (:mod:`~daror_runtime.identification.design_route`), fits the budget; all points
    of those stops are kept.

Random draws that cannot identify the model are counted as refused (as in the data-efficiency
study, whose :class:`~daror_runtime.studies.data_efficiency.SizeResult` summarises them).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import structlog

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import ConfigurationError, IdentifiabilityError, UsageError
from daror_runtime.identification.design import HOME, DesignError, DesignSettings, design_protocol
from daror_runtime.identification.design_route import RouteTimes, improve_tour, route_times
from daror_runtime.identification.protocol import ProtocolResult, run_protocol
from daror_runtime.identification.protocol_file import ProtocolTrajectory
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.identification.trajectory import ReferenceTrajectory
from daror_runtime.identification.trajectory_planning import build_trajectory
from daror_runtime.identification.waypoints import load_waypoints
from daror_runtime.models.base import CompensationModel
from daror_runtime.models.least_squares import min_norm_least_squares
from daror_runtime.models.linear import PLF_PLUS_ELBOW_ORDER, structural_rank
from daror_runtime.models.metrics import ErrorMetrics, error_metrics
from daror_runtime.models.registry import fit_model, kind_entry
from daror_runtime.models.regressor import N_GRAVITY_PARAMETERS, LinearTorqueEvaluator, regressor_parameter_major
from daror_runtime.studies.data_efficiency import SizeResult
from hal.interface import Hal
from hal.isb import IsbLimits, Shoulder
from hal.robot import RobotDescription

__all__ = [
    "DEFAULT_BUDGETS_S",
    "DesignedRun",
    "ProtocolStudyResult",
    "RandomSubsets",
    "parse_budgets",
    "run_protocol_study",
]

log = structlog.get_logger(__name__)

#: Budgets of robot time studied by default, seconds.
DEFAULT_BUDGETS_S = (45.0, 60.0, 90.0, 120.0, 180.0, 240.0)
#: Random subsets per budget and method (the thesis: 100 models per size).
DEFAULT_DRAWS = 100
#: "Within" the full protocol's validation RMSE: the issue's acceptance.
TOLERANCE = 0.05
#: Consecutive points closer than this in every joint and in time belong to one stop (rad, s).
_SAME_STOP_RAD = 3e-3
_SAME_STOP_S = 0.7
#: The model kind the study fits (the design's default base).
KIND = "plf+"

HalFactory = Callable[[], Hal]
Progress = Callable[[str], None]


@dataclass(frozen=True)
class RunFigures:
    """One closed-loop run and the PLF+ fitted on its data, scored on the validation run."""

    robot_time_s: float
    stops: int
    points: int
    wall_s: float
    validation: ErrorMetrics | None  # None for the validation run itself

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "robot_time_s": self.robot_time_s,
            "stops": self.stops,
            "points": self.points,
        }
        if self.validation is not None:
            out["rmse_nm"] = self.validation.rmse_nm
            out["rmse_per_joint_nm"] = list(self.validation.rmse_per_joint_nm)
        return out


@dataclass(frozen=True)
class DesignedRun:
    """The designed protocol of one budget and approach: what it predicted and what its run gave."""

    budget_s: float
    approach: str
    refused: str | None  # the design's refusal (budget too small, ...); then nothing below
    poses: int = 0
    predicted_robot_time_s: float = 0.0
    predicted_rmse_nm: float = 0.0
    design_wall_s: float = 0.0
    run: RunFigures | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"budget_s": self.budget_s, "approach": self.approach, "refused": self.refused}
        if self.run is not None:
            out |= {
                "poses": self.poses,
                "predicted_robot_time_s": self.predicted_robot_time_s,
                "predicted_rmse_nm": self.predicted_rmse_nm,
                "run": self.run.to_dict(),
            }
        return out


@dataclass(frozen=True)
class RandomSubsets:
    """Random subsets of the full protocol's data for one budget (``method`` ``points`` or ``stops``)."""

    budget_s: float
    method: str
    mean_points: float
    mean_robot_time_s: float
    summary: SizeResult
    mean_stops: float | None = None  # ``stops`` only

    def to_dict(self) -> dict[str, Any]:
        return {
            "budget_s": self.budget_s,
            "method": self.method,
            "mean_points": self.mean_points,
            "mean_stops": self.mean_stops,
            "mean_robot_time_s": self.mean_robot_time_s,
            **{k: v for k, v in self.summary.to_dict().items() if k != "n"},
        }


@dataclass(frozen=True)
class ProtocolStudyResult:
    """Everything the study found; :meth:`to_dict` is ``protocol_study.json`` (no wall times: reproducible)."""

    scenario: str
    dummy_arm: bool
    limits: IsbLimits
    draws: int
    seed: int
    full: RunFigures
    validation: RunFigures
    designed: tuple[DesignedRun, ...]
    random_points: tuple[RandomSubsets, ...]
    random_stops: tuple[RandomSubsets, ...]
    tolerance: float = TOLERANCE
    wall_s: float = field(default=0.0, compare=False)

    @property
    def full_rmse(self) -> float:
        if self.full.validation is None:
            raise ConfigurationError("the full protocol's run was not scored on the validation run")
        return self.full.validation.rmse_nm

    def to_dict(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "dummy_arm": self.dummy_arm,
            "kind": KIND,
            "limits": self.limits.model_dump(mode="json"),
            "draws": self.draws,
            "seed": self.seed,
            "tolerance": self.tolerance,
            "full_protocol": self.full.to_dict(),
            "validation_run": self.validation.to_dict(),
            "designed": [d.to_dict() for d in self.designed],
            "random_points": [r.to_dict() for r in self.random_points],
            "random_stops": [r.to_dict() for r in self.random_stops],
        }


def parse_budgets(text: str) -> list[float]:
    """Budgets (s) from ``--budgets 60,120``: positive numbers, sorted, without repeats.

    Raises:
        UsageError: a part is not a positive number.
    """
    budgets = set()
    for part in text.split(","):
        token = part.strip()
        try:
            value = float(token)
        except ValueError:
            raise UsageError(f"--budgets: {token!r} is not a number; expected seconds such as 60,120") from None
        if not (np.isfinite(value) and 0.0 < value <= 3600.0):
            raise UsageError(f"--budgets: {token} is out of range; expected seconds from above 0 to 3600")
        budgets.add(value)
    return sorted(budgets)


# --- runs ------------------------------------------------------------------------------------


def _run(hal_factory: HalFactory, trajectory: ReferenceTrajectory, folder: Path, name: str,
         feedforward: CompensationModel | None) -> ProtocolResult:  # fmt: skip
    """One run as ``daror identify`` makes it without ``--isb-limits``: every trajectory here was
    checked inside the limits when it was built, and the monitor's per-tick ISB check would keep the
    loop from its compiled batches (2.5 times the wall time)."""
    hal = hal_factory()
    hal.open()
    try:
        return run_protocol(hal, trajectory, folder / f"{name}.rec", folder / f"{name}.csv", feedforward=feedforward)
    finally:
        hal.close()
        (folder / f"{name}.rec").unlink(missing_ok=True)


def _fit(train: StationaryDataset, description: RobotDescription) -> CompensationModel:
    return fit_model(KIND, train, description, kind_entry(KIND).options()).model


def _score(train: StationaryDataset, validate: StationaryDataset, description: RobotDescription) -> ErrorMetrics:
    return error_metrics(validate.tau_nm, _fit(train, description).torque_batch(validate.q_rad))


def _figures(result: ProtocolResult, validation: ErrorMetrics | None) -> RunFigures:
    return RunFigures(result.robot_time_s, result.stops, len(result.stationary), result.wall_time_s, validation)


# --- random subsets --------------------------------------------------------------------------


def stop_groups(points: StationaryDataset) -> list[np.ndarray]:
    """Indices of the points of each stop of a run, in time order (points of one stop share their pose)."""
    order = np.argsort(points.t_s) if points.t_s is not None else np.arange(len(points))
    q = points.q_rad[order]
    t = points.t_s[order] if points.t_s is not None else np.zeros(len(points))
    new = np.ones(len(points), dtype=bool)
    new[1:] = (np.abs(np.diff(q, axis=0)).max(axis=1) > _SAME_STOP_RAD) | (np.diff(t) > _SAME_STOP_S)
    return np.split(order, np.flatnonzero(new)[1:])


class _DrawScorer:
    """PLF+ of random draws scored on the validation run, as :func:`_score` scores them, without the fit report.

    The numbers are those of ``fit_model("plf+", ...)`` (:func:`~daror_runtime.models.linear.fit_linear`)
    to the last bit: the same regressor, least squares, refusals (rank below the structural rank, fewer
    spare equations than identifiable combinations) and torque evaluator. What a draw does not need is
    left out: the robot's kinematics built anew for every fit and every model, the base parameters,
    the unidentifiable ones and the training error of the fit report (two thirds of a fit's time, and
    the study fits 1,200 draws). A refused draw is only counted, so its message is not written.
    """

    def __init__(self, validate: StationaryDataset, description: RobotDescription) -> None:
        self.validate = validate
        self.kinematics = description.kinematics()
        self.expected_rank = structural_rank(description.geometry, PLF_PLUS_ELBOW_ORDER)

    def metrics(self, train: StationaryDataset) -> ErrorMetrics | None:
        """Validation error of PLF+ fitted on ``train``; None if ``train`` cannot identify it."""
        kt = regressor_parameter_major(self.kinematics, train.q_rad, PLF_PLUS_ELBOW_ORDER)
        target = np.ascontiguousarray(train.tau_nm.T).reshape(-1)
        fit = min_norm_least_squares(kt.reshape(kt.shape[0], -1), target)
        if fit.rank < self.expected_rank or fit.degrees_of_freedom < fit.rank:
            return None
        theta = fit.theta
        evaluator = LinearTorqueEvaluator(self.kinematics, theta[:N_GRAVITY_PARAMETERS], theta[N_GRAVITY_PARAMETERS:])
        return error_metrics(self.validate.tau_nm, evaluator.torque_batch(self.validate.q_rad))


def _score_draw(
    train: StationaryDataset,
    scorer: _DrawScorer,
    rmse: list[float],
    nrmse: list[float],
) -> bool:
    """Fit one random draw and append its validation RMSE (Nm) and nRMSE; False if the draw identifies too little."""
    metrics = scorer.metrics(train)
    if metrics is None:
        return False
    rmse.append(metrics.rmse_nm)
    nrmse.append(metrics.nrmse)
    return True


def _summarise(budget_s: float, method: str, points: list[int], times: list[float], refused: int,
               rmse: list[float], nrmse: list[float], stops: list[int] | None = None) -> RandomSubsets:  # fmt: skip
    summary = SizeResult.from_draws(round(float(np.mean(points))) if points else 0, refused, rmse, nrmse)
    return RandomSubsets(
        budget_s,
        method,
        float(np.mean(points)) if points else 0.0,
        float(np.mean(times)) if times else 0.0,
        summary,
        float(np.mean(stops)) if stops else None,
    )


def random_points(
    train: StationaryDataset, validate: StationaryDataset, description: RobotDescription,
    budget_s: float, full_robot_s: float, draws: int, seed: int,
) -> RandomSubsets:  # fmt: skip
    """The thesis's method: ``n`` random points, ``n`` the budget's share of the full run's points."""
    n = int(np.clip(round(len(train) * budget_s / full_robot_s), 1, len(train)))
    rng = np.random.default_rng([seed, 1, round(budget_s * 1000)])
    rmse: list[float] = []
    nrmse: list[float] = []
    refused = 0
    scorer = _DrawScorer(validate, description)
    for _ in range(draws):
        index = np.sort(rng.choice(len(train), size=n, replace=False))
        refused += not _score_draw(train.subset(index), scorer, rmse, nrmse)
    return _summarise(budget_s, "points", [n] * draws, [budget_s] * draws, refused, rmse, nrmse)


def _insertion(times: RouteTimes, tour: list[int], c: int) -> tuple[float, float, int]:
    """Robot time (s) of ``tour``, the cheapest added time (s) of inserting stop ``c`` and where.

    The numbers of ``times.tour_time(tour)`` and ``insertion_costs(times, tour, [c])`` to the last
    bit (the same operations on the same values, in the same order), for one candidate without
    their general-purpose stacking: the random-stops draws ask this some 33,000 times.
    """
    if not tour:
        return 0.0, float(times.start[c] + times.visit[c]), 0
    t = np.asarray(tour)
    between = times.between
    edges = between[t[:-1], t[1:]]
    tour_s = float(times.start[t[0]] + edges.sum() + times.visit[t].sum())
    options = np.empty(t.size + 1)
    options[0] = times.start[c] + between[c, t[0]] - times.start[t[0]]  # in front
    options[1:-1] = between[t[:-1], c] + between[c, t[1:]] - edges  # between two stops
    options[-1] = between[t[-1], c]  # at the end
    where = int(np.argmin(options))
    return tour_s, float(options[where] + times.visit[c]), where


def _random_tour(times: RouteTimes, order: npt.NDArray[np.int64], budget_s: float) -> list[int]:
    """Stops taken in ``order`` into a tour by cheapest insertion while its robot time fits ``budget_s`` (s).

    When a stop does not fit, the tour is first shortened (:func:`improve_tour`); the first stop that
    still does not fit ends the tour.
    """
    tour: list[int] = []
    for c in order:
        tour_s, cost, where = _insertion(times, tour, int(c))
        if tour_s + cost > budget_s:
            tour = improve_tour(times, tour)  # a shorter tour may still take it
            tour_s, cost, where = _insertion(times, tour, int(c))
            if tour_s + cost > budget_s:
                break
        tour.insert(where, int(c))
    return tour


def random_stops(
    train: StationaryDataset, validate: StationaryDataset, description: RobotDescription,
    budget_s: float, draws: int, seed: int, stop_s: float,
) -> RandomSubsets:  # fmt: skip
    """Random stops of the full run, toured and timed like a designed protocol, while they fit the budget."""
    groups = stop_groups(train)
    q = np.array([train.q_rad[g].mean(axis=0) for g in groups])
    shoulder = Shoulder.from_description(description)
    start_q = shoulder.q_from_isb(HOME.isb_rad)
    times = route_times(
        shoulder, q, q, np.full(len(groups), stop_s), start_q,
        ProtocolTrajectory().settings(stop_s), IdentificationSettings(),
    )  # fmt: skip
    rng = np.random.default_rng([seed, 2, round(budget_s * 1000)])
    rmse, nrmse, refused, counts, robot, sizes = [], [], 0, [], [], []
    scorer = _DrawScorer(validate, description)
    for _ in range(draws):
        tour = _random_tour(times, rng.permutation(len(groups)), budget_s)
        index = np.sort(np.concatenate([groups[c] for c in tour])) if tour else np.zeros(0, dtype=int)
        counts.append(index.size)
        sizes.append(len(tour))
        robot.append(times.tour_time(tour))
        refused += not _score_draw(train.subset(index), scorer, rmse, nrmse)
    return _summarise(budget_s, "stops", counts, robot, refused, rmse, nrmse, sizes)


# --- the study -------------------------------------------------------------------------------


def run_protocol_study(
    scenario: str,
    hal_factory: HalFactory,
    description: RobotDescription,
    feedforward: CompensationModel | None,
    dummy_arm: bool,
    budgets_s: Sequence[float] = DEFAULT_BUDGETS_S,
    approaches: Sequence[str] = ("both", "once"),
    draws: int = DEFAULT_DRAWS,
    seed: int = 0,
    limits: IsbLimits | None = None,
    progress: Progress | None = None,
) -> ProtocolStudyResult:
    """Run the study on one simulated plant (see the module docstring).

    Args:
        scenario: the plant's name, for the record.
        hal_factory: a new, unopened simulated backend of the plant for every run.
        description: the robot description the models are fitted for.
        feedforward: the position controller's gravity feed-forward (the A Priori model).
        dummy_arm: whether the Dummy Arm is installed, for the record.
        budgets_s: robot-time budgets, seconds.
        approaches: design approaches to run (``both``, ``once``).
        draws: random subsets per budget and method.
        seed: seed of the random subsets (the design's own seed stays its default).
        limits: the pilot's ISB limits (default :class:`~hal.isb.IsbLimits`).
        progress: told what runs next.

    Raises:
        UsageError: no budget, ``draws < 1``, ``seed < 0``, an unknown approach.
        TrajectoryError: the full protocol leaves ``limits``.
        ProtocolAbortedError: a run stopped on a fault.
        IdentifiabilityError: the full protocol cannot identify PLF+.
    """
    started = time.perf_counter()
    if not budgets_s:
        raise UsageError("--budgets: no budget given; expected seconds such as 60,120")
    if draws < 1:
        raise UsageError(f"--draws {draws}: expected at least 1")
    if seed < 0:
        raise UsageError(f"--seed {seed}: expected a whole number from 0 up")
    for approach in approaches:
        if approach not in ("both", "once"):
            raise UsageError(f"--approaches: {approach!r}; expected both and/or once")
    limits = limits or IsbLimits()
    say = progress or (lambda _: None)
    waypoints = load_waypoints()
    training = build_trajectory(waypoints, "training", limits=limits, description=description)
    validation_trajectory = build_trajectory(waypoints, "validation", limits=limits, description=description)
    with tempfile.TemporaryDirectory(prefix="daror-protocol-study-") as tmp:
        folder = Path(tmp)
        say("full training protocol")
        full = _run(hal_factory, training, folder, "full", feedforward)
        say("validation protocol")
        validation = _run(hal_factory, validation_trajectory, folder, "validation", feedforward)
        validate = validation.stationary
        full_figures = _figures(full, _score(full.stationary, validate, description))
        designed: list[DesignedRun] = []
        for budget in budgets_s:
            for approach in approaches:
                say(f"designed protocol, {budget:g} s, approach {approach}")
                designed.append(
                    _designed(hal_factory, folder, budget, approach, limits, description, feedforward, validate)
                )
    stop_s = DesignSettings().stop_s
    say("random subsets")
    points = tuple(
        random_points(full.stationary, validate, description, b, full.robot_time_s, draws, seed) for b in budgets_s
    )
    stops = tuple(random_stops(full.stationary, validate, description, b, draws, seed, stop_s) for b in budgets_s)
    result = ProtocolStudyResult(
        scenario=scenario,
        dummy_arm=dummy_arm,
        limits=limits,
        draws=draws,
        seed=seed,
        full=full_figures,
        validation=_figures(validation, None),
        designed=tuple(designed),
        random_points=points,
        random_stops=stops,
        wall_s=time.perf_counter() - started,
    )
    log.info("protocol study done", scenario=scenario, budgets=list(budgets_s), wall_s=round(result.wall_s, 1))
    return result


def _designed(
    hal_factory: HalFactory, folder: Path, budget_s: float, approach: str, limits: IsbLimits,
    description: RobotDescription, feedforward: CompensationModel | None, validate: StationaryDataset,
) -> DesignedRun:  # fmt: skip
    try:
        design = design_protocol(budget_s, limits, description, DesignSettings(approach=approach))  # type: ignore[arg-type]
    except DesignError as exc:
        return DesignedRun(budget_s, approach, refused=str(exc))
    result = _run(hal_factory, design.trajectory, folder, f"designed_{approach}_{budget_s:g}", feedforward)
    try:
        metrics = _score(result.stationary, validate, description)
    except IdentifiabilityError as exc:
        return DesignedRun(budget_s, approach, refused=f"the run's data: {exc}")
    prediction = design.protocol.prediction
    return DesignedRun(
        budget_s,
        approach,
        refused=None,
        poses=prediction.poses,
        predicted_robot_time_s=prediction.robot_time_s,
        predicted_rmse_nm=prediction.validation_rmse_nm,
        design_wall_s=design.wall_s,
        run=_figures(result, metrics),
    )
