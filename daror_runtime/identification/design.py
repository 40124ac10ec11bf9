"""A short identification protocol designed for one pilot (thesis Sec. 6.5, 7.1; issue 14).

The thesis's protocol takes 5-15 minutes, too long for a boy with DMD; its data-efficiency study
(Fig. 5.4) found a few hundred random stationary points enough, and its future work asks for
configurations chosen by how much they shrink the covariance of the estimated parameters. This
module chooses them, for a budget of robot time, inside the pilot's recorded ISB limits:

1. **Candidates** (:mod:`.design_candidates`): a Sobol sample of the pilot's ISB box, reachable
   inside the joint limits, away from the shoulder's singularity; with their via poses when
   every pose is approached from both directions (the default).
2. **Information** (:mod:`.design_model`): each candidate's stops add ``K_b^T W K_b`` to the
   information matrix of the model's base parameters.
3. **Selection**: D-optimal (maximise ``log det M``) under the time budget: greedy by gain per
   second of added robot time (cheapest insertion into the tour), then exchanges (swap a chosen
   pose for another whenever ``log det`` grows and the tour still fits), the tour shortened by
   2-opt and relocation (:mod:`.design_route`) and the freed time filled again.
4. **Realisation**: the visits are built by the trajectory generator itself
   (:func:`~daror_runtime.identification.trajectory_planning.build_visit_trajectory`, every tick
   checked); a move that would leave the limits gets a via at the ISB midpoint, or its pose is
   dropped; the approach from the start pose (which may lie outside the limits: a pilot who
   cannot reach the robot's home) must enter them once and stay in, through the start pose
   brought inside the limits if the direct way does not (D135), or the first pose is dropped;
   the built trajectory's robot time (approach and settle included) must fit the budget, or the
   pose that costs the least information per second is dropped.
5. **Checks and predictions**: the condition number of the information matrix (unit diagonal)
   must stay below ``max_condition``, or the design is refused naming the weakest combination;
   the protocol carries the predicted standard errors and validation error.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import structlog

from daror_runtime.errors import ConfigurationError, InputError, UsageError
from daror_runtime.identification.design_candidates import Candidates, candidate_poses, shrunk
from daror_runtime.identification.design_model import (
    DesignEffect,
    DesignModel,
    information,
    relative_condition_number,
    scaled_condition_number,
)
from daror_runtime.identification.design_route import (
    RouteTimes,
    geodesic_leaves_limits,
    improve_tour,
    insertion_costs,
    move_duration_s,
    route_times,
)
from daror_runtime.identification.protocol_file import (
    BaseParameterPrediction,
    DesignedProtocol,
    DesignRecord,
    IsbPose,
    Prediction,
    ProtocolTrajectory,
    Visit,
)
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.identification.trajectory import ReferenceTrajectory
from daror_runtime.identification.trajectory_planning import (
    MoveError,
    TrajectoryError,
    build_visit_trajectory,
    check_approach,
)
from hal.isb import ISB_NAMES, IsbLimits, Shoulder, UnreachablePoseError
from hal.robot import N_JOINTS, FloatArray, RobotDescription, load_description

__all__ = ["HOME", "DesignError", "DesignResult", "DesignSettings", "design_protocol"]

log = structlog.get_logger(__name__)

#: Where ``daror identify`` starts (the scenarios' ``initial_q``): the arm hanging, elbow 30 deg.
HOME = IsbPose(elevation_deg=0.0, horizontal_rotation_deg=0.0, axial_rotation_deg=0.0, elbow_deg=30.0)
#: Regularisation of the information matrix while it is still singular (unit-scaled columns).
_EPSILON = 1e-6
#: Longest budget (s): the shipped protocol takes 752 s; a design ten times as long helps nobody.
MAX_BUDGET_S = 3600.0
#: Deepest splitting of a move that would leave the limits (2: up to four moves instead of one).
_SPLIT_DEPTH = 2


class DesignError(InputError):
    """No protocol within the budget and the pilot's limits identifies the model (the message says why)."""


@dataclass(frozen=True)
class DesignSettings:
    """How a protocol is designed; angles in degrees, times in seconds, torques in Nm.

    Attributes:
        base: model kind the protocol identifies (``plf+`` or ``plf``).
        effects: linear effects of the augmented model on top (:func:`~.design_model.parse_effects`).
        approach: ``both``: every pose is stopped at twice, arriving from opposite directions in
            every joint (the direction-dependent error cancels in the fit); ``once``: one stop.
        stop_s: how long the robot stands at a data stop.
        via_deg: joint offset of the via poses that set the direction of arrival.
        margin_deg: distance of every pose from the ISB and joint limits.
        candidates: Sobol points drawn in the pilot's ISB box.
        seed: scrambling seed of the Sobol sample.
        direction_error_nm, sensor_noise_nm: the noise model (:mod:`.design_model`).
        max_condition: largest condition number of the information matrix scaled to unit diagonal
            (what the fit's rank decision sees: it drops singular values below 1e-7 of the largest,
            a condition number of 1e14; the default keeps a factor 10 from it).
        max_workspace_condition: largest condition number of the information relative to stops
            spread evenly over the pilot's own reachable workspace (the candidates).
        min_sigma: smallest singular value of the shoulder Jacobian at a pose.
        trajectory: how the moves are timed (the trajectory generator's settings).
        identification: the approach and settle hold before the run (their robot time counts).
        exchange_rounds: rounds of exchange, route shortening and refilling.
    """

    base: str = "plf+"
    effects: tuple[DesignEffect, ...] = ()
    approach: Literal["both", "once"] = "both"
    stop_s: float = 1.0
    via_deg: float = 3.0
    margin_deg: float = 2.0
    candidates: int = 1024
    seed: int = 0
    direction_error_nm: tuple[float, float, float, float] = (0.25, 0.75, 0.35, 0.15)
    sensor_noise_nm: tuple[float, float, float, float] = (0.024, 0.024, 0.024, 0.024)
    max_condition: float = 1e13
    max_workspace_condition: float = 1e3
    min_sigma: float = 0.35
    trajectory: ProtocolTrajectory = field(default_factory=ProtocolTrajectory)
    identification: IdentificationSettings = field(default_factory=IdentificationSettings)
    exchange_rounds: int = 4

    def check(self) -> None:
        """Raises UsageError naming the first setting out of range."""
        if self.approach not in ("both", "once"):
            raise UsageError(f"--approach {self.approach}: expected both or once")
        if not 0.3 <= self.stop_s <= 30.0:
            raise UsageError(f"--stop-s {self.stop_s}: expected 0.3 to 30 s (a shorter stop gives no data)")
        if not 0.5 <= self.via_deg <= 20.0:
            raise UsageError(f"via_deg {self.via_deg}: expected 0.5 to 20 deg")
        if not 0.0 <= self.margin_deg <= 30.0:
            raise UsageError(f"margin_deg {self.margin_deg}: expected 0 to 30 deg")
        if not 16 <= self.candidates <= 16384:
            raise UsageError(f"--candidates {self.candidates}: expected 16 to 16384")
        if self.seed < 0:
            raise UsageError(f"--seed {self.seed}: expected a whole number from 0 up")
        if not (self.max_condition > 1.0 and self.max_workspace_condition > 1.0):
            raise UsageError(
                f"max_condition {self.max_condition}, max_workspace_condition {self.max_workspace_condition}: expected numbers above 1"
            )
        if not self.trajectory.min_sigma <= self.min_sigma < 1.0:
            raise UsageError(
                f"min_sigma {self.min_sigma}: expected at least the trajectory's {self.trajectory.min_sigma}"
            )


@dataclass(frozen=True)
class DesignResult:
    """A designed protocol, its built trajectory (as the generator runs it) and the design's figures.

    ``problem`` and ``tour`` (candidate indices in visiting order) are what the selection worked
    on and chose: for comparing the design with other choices.
    """

    protocol: DesignedProtocol
    trajectory: ReferenceTrajectory
    candidates: int
    wall_s: float
    problem: DesignProblem
    tour: tuple[int, ...]

    def log_det(self, tour: list[int] | tuple[int, ...]) -> float:
        """``log det`` of the information matrix of the stops of candidates ``tour`` (as the prediction's)."""
        return self.problem.log_det(tour)


@dataclass
class DesignProblem:
    """What the selection works on, built once per design: the candidates, each one's stops'
    regressor rows (unweighted, and whitened and unit-scaled for the selection), the route times."""

    model: DesignModel
    candidates: Candidates
    rows: FloatArray  # (C, m, p) unweighted base columns of each candidate's stops
    weighted: FloatArray  # (C, m, p) whitened and unit-scaled: the selection's information
    times: RouteTimes
    paired: bool
    start_q: FloatArray

    def log_det(self, tour: list[int] | tuple[int, ...]) -> float:
        """``log det`` of the information matrix of the stops of candidates ``tour``."""
        rows = self.rows[list(tour)].reshape(-1, N_JOINTS, self.rows.shape[2])
        return float(np.linalg.slogdet(information(rows, self.model.stop_variance(self.paired)))[1])


def _gains(weighted: FloatArray, matrix: FloatArray) -> FloatArray:
    """``log det(M + F_c^T F_c) - log det M`` for every candidate's ``F_c`` (C, m, p)."""
    chol = np.linalg.cholesky(matrix)
    inverse = np.linalg.inv(chol)
    y = weighted @ inverse.T
    inner = y @ np.swapaxes(y, 1, 2)
    inner += np.eye(inner.shape[1])
    return np.linalg.slogdet(inner)[1]


class _Selection:
    """A tour of chosen candidates and its information matrix, grown and exchanged under a time limit."""

    def __init__(self, problem: DesignProblem, limit_s: float) -> None:
        self.p = problem
        self.limit_s = limit_s
        p = problem.weighted.shape[2]
        self.tour: list[int] = []
        self.matrix = _EPSILON * np.eye(p)

    def contribution(self, c: int) -> FloatArray:
        f = self.p.weighted[c]
        return f.T @ f

    def grow(self) -> bool:
        """Add candidates by gain per second of robot time until nothing more fits."""
        grew = False
        n = len(self.p.candidates)
        while True:
            chosen = np.zeros(n, dtype=bool)
            chosen[self.tour] = True
            free = np.flatnonzero(~chosen)
            if free.size == 0:
                return grew
            cost, where = insertion_costs(self.p.times, self.tour, free)
            fits = self.p.times.tour_time(self.tour) + cost <= self.limit_s
            if not fits.any():
                return grew
            gains = _gains(self.p.weighted[free[fits]], self.matrix)
            best = int(np.argmax(gains / np.maximum(cost[fits], 1e-9)))
            c = int(free[fits][best])
            self.tour.insert(int(where[fits][best]), c)
            self.matrix += self.contribution(c)
            grew = True

    def exchange(self) -> bool:
        """Swap chosen poses for better ones (larger log det, still within the limit)."""
        changed = False
        for c in list(self.tour):
            if c not in self.tour:
                continue
            rest = [x for x in self.tour if x != c]
            reduced = self.matrix - self.contribution(c)
            chosen = np.zeros(len(self.p.candidates), dtype=bool)
            chosen[rest] = True
            pool = np.flatnonzero(~chosen)
            cost, where = insertion_costs(self.p.times, rest, pool)
            fits = self.p.times.tour_time(rest) + cost <= self.limit_s
            if not fits.any():
                continue
            gains = _gains(self.p.weighted[pool[fits]], reduced)
            own = gains[pool[fits] == c]
            best = int(np.argmax(gains))
            new = int(pool[fits][best])
            if new != c and (own.size == 0 or gains[best] > own[0] + 1e-9):
                rest.insert(int(where[fits][best]), new)
                self.tour = rest
                self.matrix = reduced + self.contribution(new)
                changed = True
        return changed

    def shorten(self) -> None:
        self.tour = improve_tour(self.p.times, self.tour)

    def drop_least_useful(self) -> None:
        """Remove the pose that loses the least log det per second of robot time saved."""
        times = self.p.times
        whole = times.tour_time(self.tour)
        scores = []
        for c in self.tour:
            rest = [x for x in self.tour if x != c]
            saved = max(whole - times.tour_time(rest), 1e-6)
            loss = float(np.linalg.slogdet(self.matrix)[1] - np.linalg.slogdet(self.matrix - self.contribution(c))[1])
            scores.append(loss / saved)
        self.remove(self.tour[int(np.argmin(scores))])

    def remove(self, c: int) -> None:
        self.tour.remove(c)
        self.matrix = self.matrix - self.contribution(c)


def _problem(
    model: DesignModel,
    candidates: Candidates,
    shoulder: Shoulder,
    settings: DesignSettings,
    start_q: FloatArray,
) -> DesignProblem:
    traj = settings.trajectory.settings(settings.stop_s)
    paired = candidates.paired
    if paired:
        up, down = _vias(candidates)
        signs = np.sign(up - candidates.q)
        # Stop A arrives from the upper via (every joint moving by -delta s), stop B from the lower one.
        rows = np.concatenate([model.rows(candidates.q, -signs), model.rows(candidates.q, signs)], axis=1)
        pose_r, up_r, down_r = shoulder.rotor3(candidates.q), shoulder.rotor3(up), shoulder.rotor3(down)
        short = np.zeros(len(candidates))
        for a, b, qa, qb in (
            (up_r, pose_r, up, candidates.q),
            (pose_r, down_r, candidates.q, down),
            (down_r, pose_r, down, candidates.q),
        ):
            angle = np.arccos(np.clip(0.5 * (np.einsum("nij,nij->n", a, b) - 1.0), -1.0, 1.0))
            short += move_duration_s(angle, qb[:, 3] - qa[:, 3], traj)
        visit_s = short + 2.0 * settings.stop_s
        entry = up
    else:
        rows = model.rows(candidates.q, np.zeros_like(candidates.q))
        visit_s = np.full(len(candidates), settings.stop_s)
        entry = candidates.q
    joint = np.arange(rows.shape[1]) % N_JOINTS
    sigma = np.sqrt(model.stop_variance(paired))[joint]
    weighted = rows / sigma[None, :, None]
    scale = np.sqrt(np.mean(weighted**2, axis=(0, 1)))
    weighted = weighted / np.where(scale > 0, scale, 1.0)
    times = route_times(shoulder, entry, candidates.q, visit_s, start_q, traj, settings.identification)
    return DesignProblem(model, candidates, rows, weighted, times, paired, start_q)


def _vias(candidates: Candidates) -> tuple[FloatArray, FloatArray]:
    """The upper and lower via poses (C, 4) of candidates approached from both directions."""
    if candidates.via_up_q is None or candidates.via_down_q is None:
        raise ConfigurationError("candidates approached once have no via poses")
    return candidates.via_up_q, candidates.via_down_q


def _visits_of(problem: DesignProblem, c: int, stop_s: float) -> list[tuple[FloatArray, float]]:
    """(q, stop) of candidate ``c``'s visits: via, pose, via, pose when paired; the pose alone otherwise."""
    q = problem.candidates.q[c]
    if not problem.paired:
        return [(q, stop_s)]
    up, down = _vias(problem.candidates)
    return [(up[c], 0.0), (q, stop_s), (down[c], 0.0), (q, stop_s)]


def _bridge(
    shoulder: Shoulder, limits: IsbLimits, min_sigma: float, q_from: FloatArray, q_to: FloatArray, depth: int
) -> list[FloatArray] | None:
    """Via poses (possibly none) that keep the move ``q_from -> q_to`` inside everything; None if none do."""
    if not geodesic_leaves_limits(shoulder, limits, min_sigma, q_from, q_to):
        return []
    if depth == 0:
        return None
    # The box is convex: the middle of two poses inside it is inside (the horizontal rotation of a
    # low pose, free there, taken at its nearest value inside the range first).
    ends = limits.for_box_check(shoulder.isb_from_q(np.vstack([q_from, q_to])))
    middle_isb = 0.5 * (ends[0] + ends[1])
    try:
        middle = shoulder.q_from_isb(middle_isb)
    except UnreachablePoseError:
        return None
    if middle[1] <= 0.0 or not limits.contains(shoulder.isb_from_q(middle)):
        return None
    first = _bridge(shoulder, limits, min_sigma, q_from, middle, depth - 1)
    second = _bridge(shoulder, limits, min_sigma, middle, q_to, depth - 1) if first is not None else None
    if first is None or second is None:
        return None
    return [*first, middle, *second]


def _realise(
    problem: DesignProblem, tour: list[int], shoulder: Shoulder, limits: IsbLimits, settings: DesignSettings
) -> tuple[list[tuple[FloatArray, float, int]], int | None, str | None]:
    """The visits (q, stop, pose number from 1) of a tour, with bridges; or the tour index of a pose
    to drop, and why when it is the approach from the start pose that fails."""
    visits: list[tuple[FloatArray, float, int]] = []
    check_limits = _inner(limits)
    for k, c in enumerate(tour):
        own = _visits_of(problem, c, settings.stop_s)
        if visits:
            bridge = _bridge(
                shoulder, check_limits, settings.trajectory.min_sigma, visits[-1][0], own[0][0], _SPLIT_DEPTH
            )
            if bridge is None:
                return visits, k, None
            visits.extend((q, 0.0, k + 1) for q in bridge)
        else:
            entry, why = _entry(problem.start_q, own[0][0], shoulder, limits, settings)
            if entry is None:
                return visits, k, why
            visits.extend((q, 0.0, k + 1) for q in entry)
        visits.extend((q, stop, k + 1) for q, stop in own)
    return visits, None, None


def _entry(
    start_q: FloatArray, first_q: FloatArray, shoulder: Shoulder, limits: IsbLimits, settings: DesignSettings
) -> tuple[list[FloatArray] | None, str]:
    """Via poses (possibly none) that let the approach from ``start_q`` reach ``first_q`` inside the limits.

    The approach is a straight joint move (:func:`check_approach`): from a start outside the
    limits it must enter them once and stay in. When the direct approach does not, it aims for the
    start pose brought ``margin_deg`` inside the limits (the nearest way in), and the generator's
    move goes on from there. Returns (None, why) when neither works.
    """
    try:
        check_approach(shoulder, limits, start_q, first_q)
        return [], ""
    except TrajectoryError as exc:
        why = str(exc)
    inside = shrunk(limits, settings.margin_deg)
    start_isb = inside.for_box_check(shoulder.isb_from_q(start_q))
    try:
        entry = shoulder.q_from_isb(np.clip(start_isb, inside.lower_rad, inside.upper_rad), seed=start_q)
    except UnreachablePoseError as exc:
        return None, f"{why}; the nearest pose inside the limits is out of the robot's reach ({exc})"
    if entry[1] <= 0.0 or shoulder.sigma_min(entry) < settings.min_sigma:
        return None, f"{why}; the nearest pose inside the limits is too near the shoulder's singularity"
    try:
        check_approach(shoulder, limits, start_q, entry)
    except TrajectoryError as exc:
        return None, str(exc)
    bridge = _bridge(shoulder, _inner(limits), settings.trajectory.min_sigma, entry, first_q, _SPLIT_DEPTH)
    if bridge is None:
        return None, f"{why}; from the nearest pose inside the limits no move stays inside them"
    return [entry, *bridge], ""


def _inner(limits: IsbLimits) -> IsbLimits:
    """The limits the cheap path check uses: 0.5 deg inside the real ones (it samples, the generator checks every tick)."""
    return shrunk(limits, 0.5)


def _protocol_of(visits: list[tuple[FloatArray, float, int]], shoulder: Shoulder) -> list[Visit]:
    out = []
    for q, stop, pose in visits:
        isb = IsbPose.from_rad(shoulder.isb_from_q(q))
        out.append(Visit(**isb.model_dump(), stop_s=stop, pose=pose))
    return out


#: Candidate sets of recent designs, by their inputs: a study designs one pilot's limits for many budgets.
_CANDIDATES: dict[tuple[str, str, int, int, float, float, float | None], Candidates] = {}
_CANDIDATES_KEPT = 4


def _candidates(
    description: RobotDescription, shoulder: Shoulder, limits: IsbLimits, settings: DesignSettings, via: float | None
) -> Candidates:
    """:func:`candidate_poses` of the design's inputs, drawn once a process for the same inputs.

    The candidates depend on the robot, the limits and the sampling settings alone, not on the
    budget; the arrays of a kept set are made read-only, so no design can change another's.
    """
    key = (
        description.model_dump_json(),
        limits.model_dump_json(),
        settings.candidates,
        settings.seed,
        settings.margin_deg,
        settings.min_sigma,
        via,
    )
    found = _CANDIDATES.get(key)
    if found is None:
        found = candidate_poses(
            shoulder, limits, settings.candidates, settings.seed, settings.margin_deg, settings.min_sigma, via
        )
        for array in (found.isb, found.q, found.via_up_q, found.via_down_q, found.via_up_isb, found.via_down_isb):
            if array is not None:
                array.setflags(write=False)
        if len(_CANDIDATES) >= _CANDIDATES_KEPT:
            del _CANDIDATES[next(iter(_CANDIDATES))]
        _CANDIDATES[key] = found
    return found


def design_protocol(
    budget_s: float,
    limits: IsbLimits | None = None,
    description: RobotDescription | None = None,
    settings: DesignSettings | None = None,
    start: IsbPose = HOME,
) -> DesignResult:
    """The D-optimal protocol of at most ``budget_s`` seconds of robot time inside ``limits``.

    Args:
        budget_s: robot time (s) of the whole run as ``daror identify`` measures it: approach from
            ``start``, settle hold, moves and stops.
        limits: the pilot's recorded ISB limits (default :class:`~hal.isb.IsbLimits`).
        description: the robot (default the packaged DAROR-01).
        settings: the design's settings (default :class:`DesignSettings`).
        start: where the robot stands when the run starts (default :data:`HOME`).

    Raises:
        UsageError: a setting out of range; a direction effect with ``approach="once"``.
        DesignError: no pose, or too few, inside the limits; the budget cannot hold a design
            that identifies the model; the design's information matrix is too ill-conditioned
            (the message names the weakest parameter combination).
    """
    wall_start = time.perf_counter()
    settings = settings or DesignSettings()
    settings.check()
    limits = limits or IsbLimits()
    description = description or load_description()
    if not (np.isfinite(budget_s) and 0.0 < budget_s <= MAX_BUDGET_S):
        raise UsageError(f"--budget-s {budget_s}: expected seconds of robot time above 0 and at most {MAX_BUDGET_S:g}")
    model = DesignModel(
        settings.base, settings.effects, description, settings.direction_error_nm, settings.sensor_noise_nm
    )
    if model.needs_direction and settings.approach != "both":
        raise UsageError(
            "--effects direction_offset needs --approach both: the offset is identified only from stops "
            "reached from both directions"
        )
    shoulder = Shoulder.from_description(description)
    try:
        start_q = shoulder.q_from_isb(start.isb_rad)
    except UnreachablePoseError as exc:
        raise DesignError(f"the start pose: {exc}") from None
    via = settings.via_deg if settings.approach == "both" else None
    candidates = _candidates(description, shoulder, limits, settings, via)
    if len(candidates) < 2:
        raise DesignError(
            f"only {len(candidates)} of {candidates.sampled} sampled poses inside the pilot's ISB limits are reachable "
            f"{settings.margin_deg:g} deg inside every limit (and with room for the via poses): widen the recorded limits"
        )
    problem = _problem(model, candidates, shoulder, settings, start_q)
    selection = _Selection(problem, budget_s)
    selection.grow()
    for _ in range(settings.exchange_rounds):
        changed = selection.exchange()
        selection.shorten()
        grew = selection.grow()
        if not (changed or grew):
            break
    trajectory, visits = _fit_to_budget(selection, problem, shoulder, limits, description, settings, budget_s)
    protocol = _finish(problem, selection, visits, trajectory, shoulder, limits, settings, budget_s, start)
    wall = time.perf_counter() - wall_start
    log.info(
        "protocol designed",
        budget_s=budget_s,
        robot_s=round(protocol.prediction.robot_time_s, 2),
        poses=protocol.prediction.poses,
        stops=protocol.prediction.data_stops,
        candidates=len(candidates),
        wall_s=round(wall, 2),
    )
    return DesignResult(protocol, trajectory, len(candidates), wall, problem, tuple(selection.tour))


def _fit_to_budget(
    selection: _Selection,
    problem: DesignProblem,
    shoulder: Shoulder,
    limits: IsbLimits,
    description: RobotDescription,
    settings: DesignSettings,
    budget_s: float,
) -> tuple[ReferenceTrajectory, list[tuple[FloatArray, float, int]]]:
    """Build the tour with the trajectory generator; drop poses until it is valid and fits the budget."""
    traj = settings.trajectory.settings(settings.stop_s)
    ident = settings.identification
    approach_failed = ""  # why the last pose dropped for the approach from the start pose was dropped
    while selection.tour:
        visits, bad, why = _realise(problem, selection.tour, shoulder, limits, settings)
        if bad is not None:
            approach_failed = why or ""
            selection.remove(selection.tour[bad])
            continue
        approach_failed = ""
        poses = [IsbPose.from_rad(shoulder.isb_from_q(q)) for q, _, _ in visits]
        record = _provisional(poses, [s for _, s, _ in visits], limits, settings)
        try:
            trajectory = build_visit_trajectory(record.waypoint_set(), record.stops_s, traj, limits, description)
        except MoveError as exc:
            selection.remove(selection.tour[visits[exc.to_visit - 1][2] - 1])
            continue
        approach = ident.approach_duration_s(float(np.abs(trajectory.start_q_rad - problem.start_q).max()))
        total = approach + ident.settle_s + trajectory.duration_s
        if total <= budget_s:
            return trajectory, visits
        selection.drop_least_useful()
    if approach_failed:
        start_deg = np.degrees(shoulder.isb_from_q(problem.start_q))
        start = "; ".join(f"{name} {v:.1f} deg" for name, v in zip(ISB_NAMES, start_deg, strict=True))
        raise DesignError(
            f"no approach from the start pose ({start}) enters the pilot's ISB limits and stays inside them "
            f"({approach_failed}): record limits the arm can be brought into from there"
        )
    raise DesignError(
        f"a budget of {budget_s:g} s of robot time holds no pose of the design inside the pilot's ISB limits: "
        "raise --budget-s"
    )


def _provisional(
    poses: list[IsbPose], stops: list[float], limits: IsbLimits, settings: DesignSettings
) -> DesignedProtocol:
    """A protocol record of the visits alone (for the generator), predictions left empty."""
    visits = [Visit(**p.model_dump(), stop_s=s, pose=1) for p, s in zip(poses, stops, strict=True)]
    empty = Prediction(
        robot_time_s=0.0, approach_s=0.0, settle_s=0.0, moves_s=0.0, stops_s=0.0, poses=1, data_stops=1,
        log_det=0.0, condition_number=1.0, workspace_condition_number=1.0, validation_rmse_nm=0.0,
        validation_rmse_per_joint_nm=[0.0] * N_JOINTS, base_parameters=[],
    )  # fmt: skip
    return DesignedProtocol(
        start=HOME,
        limits=limits,
        trajectory=settings.trajectory,
        design=_record(settings, 0.0, 0),
        prediction=empty,
        visits=visits,
    )


def _record(settings: DesignSettings, budget_s: float, candidates: int) -> DesignRecord:
    return DesignRecord(
        base=settings.base,
        effects=[e.label for e in settings.effects],
        approach=settings.approach,
        budget_s=max(budget_s, 1e-9),
        seed=settings.seed,
        candidates=candidates,
        via_deg=settings.via_deg if settings.approach == "both" else None,
        margin_deg=settings.margin_deg,
        direction_error_nm=list(settings.direction_error_nm),
        sensor_noise_nm=list(settings.sensor_noise_nm),
    )


def _finish(
    problem: DesignProblem,
    selection: _Selection,
    visits: list[tuple[FloatArray, float, int]],
    trajectory: ReferenceTrajectory,
    shoulder: Shoulder,
    limits: IsbLimits,
    settings: DesignSettings,
    budget_s: float,
    start: IsbPose,
) -> DesignedProtocol:
    """Check the design's conditioning and write down its predictions."""
    model = problem.model
    rows = problem.rows[selection.tour].reshape(-1, N_JOINTS, problem.rows.shape[2])
    variance = model.stop_variance(problem.paired)
    matrix = information(rows, variance)
    poses = len(selection.tour)
    condition, weakest = scaled_condition_number(matrix)
    if not condition <= settings.max_condition:
        raise DesignError(_ill_conditioned(model, weakest, condition, settings.max_condition, budget_s, poses, None))
    everywhere = problem.rows.reshape(-1, N_JOINTS, problem.rows.shape[2])
    workspace = information(everywhere, variance) * (poses / len(problem.candidates))
    relative, weakest = relative_condition_number(matrix, workspace)
    if not relative <= settings.max_workspace_condition:
        raise DesignError(
            _ill_conditioned(model, weakest, relative, settings.max_workspace_condition, budget_s, poses, workspace)
        )
    covariance = model.covariance(rows, problem.paired)
    rmse, per_joint = model.predicted_validation_rmse(covariance, problem.candidates.q)
    ident = settings.identification
    approach = ident.approach_duration_s(float(np.abs(trajectory.start_q_rad - problem.start_q).max()))
    stops = float(sum(s.end_s - s.start_s for s in trajectory.stops))
    base = [
        BaseParameterPrediction(expression=e, std_error=float(np.sqrt(max(covariance[i, i], 0.0))))
        for i, e in enumerate(model.base_expressions)
    ]
    prediction = Prediction(
        robot_time_s=approach + ident.settle_s + trajectory.duration_s,
        approach_s=approach,
        settle_s=ident.settle_s,
        moves_s=trajectory.duration_s - stops,
        stops_s=stops,
        poses=len(selection.tour),
        data_stops=len(trajectory.stops),
        log_det=float(np.linalg.slogdet(matrix)[1]),
        condition_number=condition,
        workspace_condition_number=relative,
        validation_rmse_nm=rmse,
        validation_rmse_per_joint_nm=[float(v) for v in per_joint],
        base_parameters=base,
    )
    effects = f" + {', '.join(e.label for e in settings.effects)}" if settings.effects else ""
    return DesignedProtocol(
        description=(
            f"D-optimal {settings.base}{effects} protocol: {len(selection.tour)} poses, "
            f"{len(trajectory.stops)} stops, {prediction.robot_time_s:.1f} s of robot time (budget {budget_s:g} s)"
        ),
        start=start,
        limits=limits,
        trajectory=settings.trajectory,
        design=_record(settings, budget_s, len(problem.candidates)),
        prediction=prediction,
        visits=_protocol_of(visits, shoulder),
    )


def _ill_conditioned(
    model: DesignModel,
    weakest: FloatArray,
    condition: float,
    limit: float,
    budget_s: float,
    poses: int,
    workspace: FloatArray | None,
) -> str:
    """One sentence: how bad, which combination the data hardly see, what to change.

    ``workspace``: the reference of a relative condition number (None: the unit-diagonal one).
    """
    if workspace is None:
        share = np.abs(weakest)
        against = "scaled to unit diagonal, as the fit sees it"
    else:
        share = np.abs(weakest) * np.sqrt(np.clip(np.diag(workspace), 0.0, None))
        against = "relative to stops spread over the pilot's reachable range"
    name = model.base_expressions[int(np.argmax(share))]
    return (
        f"the best {poses}-pose design within {budget_s:g} s and the pilot's ISB limits cannot identify {model.base}: "
        f"the condition number of its information matrix ({against}) is {condition:.3g}, above {limit:.3g}; "
        f"the data hardly see {name}; widen the recorded limits (the elbow above all: {model.base}'s elbow "
        "polynomial needs a wide range) or raise --budget-s"
    )
