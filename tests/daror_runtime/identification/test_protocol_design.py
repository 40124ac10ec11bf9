"""Issue 14: a short identification protocol designed for each pilot.

* The acceptance on three as-built scenarios (different masses and direction errors): a designed
  protocol of at most 120 s of robot time gives a PLF+ validation RMSE within 5 % of the full
  protocol's (~750 s) and beats the median random subset of equal robot time, on real
  closed-loop runs (lock-step), the same validation run for every model.
* The design: D-optimal (its log det beats random choices of as many poses), never outside the
  pilot's ISB limits (hypothesis over random limits), refused in one sentence when the limits
  cannot identify the model; the tour it plans only gets shorter.
* The file: the protocol YAML round-trips; a bad file is refused in one line naming the field.
* Where it runs: ``daror identify --protocol`` (robot time as predicted, within the budget;
  a scenario given as a file path), a session's training run.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from daror_runtime.cli import main
from daror_runtime.data.load import load_dataset, load_stationary
from daror_runtime.errors import UsageError
from daror_runtime.identification.design import HOME, DesignError, DesignSettings, design_protocol
from daror_runtime.identification.design_model import parse_effects
from daror_runtime.identification.design_route import RouteTimes, improve_tour, insertion_costs
from daror_runtime.identification.protocol import run_protocol
from daror_runtime.identification.protocol_file import (
    DesignedProtocol,
    IsbPose,
    ProtocolFileError,
    Visit,
    load_protocol,
    protocol_text,
    write_protocol,
)
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.identification.trajectory_planning import (
    APPROACH_SLACK_DEG,
    TrajectoryError,
    approach_limits,
    check_approach,
    prepend_approach,
)
from daror_runtime.models.least_squares import min_norm_least_squares
from daror_runtime.models.linear import APModel
from daror_runtime.models.registry import fit_model, installation_options
from daror_runtime.session.identification import prepare_run, session_waypoints
from daror_runtime.studies import protocol_study
from daror_runtime.studies.protocol_study import ProtocolStudyResult, run_protocol_study
from hal.isb import IsbLimits, Shoulder, UnreachablePoseError
from hal.robot import RobotDescription
from hal.sim.backend import SimHal

BUDGET_S = 120.0
#: The three as-built plants: dataset B, the robot alone (other masses, no arm), and a heavier
#: arm with stiffer springs and a larger direction error on every joint.
SCENARIOS = {"exo_dummy_arm": True, "exo": False, "exo_heavy_arm": True}


@pytest.fixture(scope="module")
def designed() -> DesignedProtocol:
    return design_protocol(60.0).protocol


def limits_of(**ranges: tuple[float, float]) -> IsbLimits:
    return IsbLimits.model_validate({k: {"lower_deg": lo, "upper_deg": hi} for k, (lo, hi) in ranges.items()})


# --- acceptance: three scenarios, closed loop ----------------------------------------------------


class _Once:
    """``function``'s result for arguments equal to an earlier call's is that call's result (made once)."""

    def __init__(self, function: Callable[..., Any]) -> None:
        self.function = function
        self.made: list[tuple[tuple[Any, ...], dict[str, Any], Any]] = []

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        for made_args, made_kwargs, result in self.made:
            if made_args == args and made_kwargs == kwargs:
                return result
        result = self.function(*args, **kwargs)
        self.made.append((args, kwargs, result))
        return result


@pytest.fixture(scope="module")
def studies(description: RobotDescription) -> dict[str, ProtocolStudyResult]:
    # The three plants share the robot and the limits, so each study plans the same full protocol
    # (training and validation trajectories) and designs the same protocol: planned once (the
    # study's own functions, their results handed out again for equal arguments: both are pure),
    # then run in closed loop on every plant as before.
    out = {}
    with pytest.MonkeyPatch.context() as patch:
        for name in ("build_trajectory", "design_protocol"):
            patch.setattr(protocol_study, name, _Once(getattr(protocol_study, name)))
        for name, dummy_arm in SCENARIOS.items():
            out[name] = run_protocol_study(
                name,
                lambda name=name: SimHal(name),
                description,
                APModel.from_description(description, dummy_arm, dummy_arm),
                dummy_arm,
                budgets_s=(BUDGET_S,),
                approaches=("both",),
                draws=100,
            )
    return out


@pytest.mark.slow
@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_a_two_minute_protocol_identifies_plf_plus_as_well_as_the_full_one(
    studies: dict[str, ProtocolStudyResult], scenario: str
) -> None:
    study = studies[scenario]
    (design,) = study.designed
    assert design.refused is None
    assert design.run is not None
    assert design.run.validation is not None
    assert study.full.robot_time_s > 700.0  # the shipped protocol: ~750 s
    # at most the budget, and as the design predicted it (the generator's own timing)
    assert design.run.robot_time_s <= BUDGET_S
    assert design.run.robot_time_s == pytest.approx(design.predicted_robot_time_s, abs=0.01)
    rmse = design.run.validation.rmse_nm
    assert rmse <= 1.05 * study.full_rmse, (rmse, study.full_rmse)
    # better than the median random subset of equal robot time, either way of counting it
    (points,) = study.random_points
    (stops,) = study.random_stops
    assert points.summary.fitted >= 90
    assert stops.summary.fitted >= 90
    assert stops.mean_robot_time_s <= BUDGET_S
    assert rmse < points.summary.rmse_median, (rmse, points.summary.rmse_median)
    assert rmse < stops.summary.rmse_median, (rmse, stops.summary.rmse_median)


# --- the design ------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(("budget", "approach"), [(60.0, "both"), (120.0, "both"), (60.0, "once"), (120.0, "once")])
def test_the_design_beats_random_choices_of_equal_robot_time_in_log_det(budget: float, approach: str) -> None:
    result = design_protocol(budget, settings=DesignSettings(approach=approach))  # type: ignore[arg-type]
    problem = result.problem
    assert result.log_det(result.tour) == pytest.approx(result.protocol.prediction.log_det, abs=1e-9)
    times = problem.times
    assert times.tour_time(list(result.tour)) <= budget
    rng = np.random.default_rng(7)
    random = []
    for _ in range(100):  # random candidates, each added to the tour where it costs least, while it fits
        tour: list[int] = []
        for c in rng.permutation(len(problem.candidates)):
            cost, where = insertion_costs(times, tour, np.array([c]))
            if times.tour_time(tour) + cost[0] <= budget:
                tour.insert(int(where[0]), int(c))
        random.append(result.log_det(tour))
    assert result.protocol.prediction.log_det > max(random), (result.protocol.prediction.log_det, max(random))


isb_limits = st.builds(
    lambda e0, e, h0, h, a0, a1, w0, w: limits_of(
        elevation=(e0, e0 + e), horizontal_rotation=(h0, h0 + h), axial_rotation=(a0, a1), elbow=(w0, w0 + w)
    ),
    st.floats(0.0, 30.0),
    st.floats(35.0, 90.0),
    st.floats(-20.0, 60.0),
    st.floats(40.0, 120.0),
    st.floats(-75.0, -10.0),
    st.floats(10.0, 75.0),
    st.floats(5.0, 40.0),
    st.floats(15.0, 90.0),
)


@pytest.mark.slow
@settings(max_examples=12, deadline=None)
@given(limits=isb_limits, budget=st.floats(40.0, 90.0), approach=st.sampled_from(["both", "once"]))
def test_a_designed_protocol_never_leaves_the_recorded_isb_limits(
    description: RobotDescription, limits: IsbLimits, budget: float, approach: str
) -> None:
    refusal = None
    try:
        result = design_protocol(budget, limits, description, DesignSettings(approach=approach))  # type: ignore[arg-type]
    except DesignError as exc:
        refusal = str(exc)
    if refusal is not None:  # limits that cannot identify PLF+ are refused, in one sentence
        assert "\n" not in refusal
        assert "condition number" in refusal or "poses" in refusal or "budget" in refusal
        return
    protocol, trajectory = result.protocol, result.trajectory
    assert protocol.prediction.robot_time_s <= budget
    shoulder = Shoulder.from_description(description)
    assert np.all(limits.contains(np.array([v.isb_rad for v in protocol.visits])))
    t = np.arange(0.0, trajectory.duration_s, 0.002)  # every 2 ms of the run, moves and stops
    q, _ = trajectory.sample(t)
    assert np.all(limits.contains(shoulder.isb_from_q(q)))
    assert np.all((q >= shoulder.lower_rad - 1e-9) & (q <= shoulder.upper_rad + 1e-9))
    assert np.min(shoulder.sigma_min(q)) >= protocol.trajectory.min_sigma
    # the run as daror identify makes it, the approach from the robot's home included (issue 24): the
    # arm enters the limits once, before the trajectory starts, and stays in; on its way in it goes no
    # further out than where it started
    home = shoulder.q_from_isb(HOME.isb_rad)
    run = prepend_approach(trajectory, home, protocol.prediction.approach_s, protocol.prediction.settle_s)
    assert run.duration_s == pytest.approx(protocol.prediction.robot_time_s, abs=1e-9)
    isb = shoulder.isb_from_q(run.sample(np.arange(0.0, run.duration_s, 0.001))[0])
    inside = np.asarray(limits.contains(isb))
    entry = int(np.argmax(inside))
    assert inside[entry:].all()
    assert entry * 0.001 <= run.time_offset_s
    assert np.all(approach_limits(limits, isb[0]).contains(isb[:entry]))


def test_limits_that_cannot_identify_the_elbow_polynomial_are_refused_in_one_sentence(
    description: RobotDescription,
) -> None:
    narrow = limits_of(elbow=(50.0, 60.0))  # 6 deg of elbow between the margins: mu1..mu5 barely apart
    with pytest.raises(DesignError) as refused:
        design_protocol(120.0, narrow, description)
    message = str(refused.value)
    assert "\n" not in message
    assert "condition number of its information matrix (scaled to unit diagonal, as the fit sees it)" in message
    assert "above 1e+13" in message
    assert "the data hardly see mu" in message
    assert "widen the recorded limits" in message
    # a design that covers the pilot's range unevenly is refused too (here with a strict limit)
    with pytest.raises(DesignError, match="relative to stops spread over the pilot's reachable range"):
        design_protocol(60.0, settings=DesignSettings(max_workspace_condition=1.5))
    # and a wide enough range is designed for
    assert design_protocol(120.0, limits_of(elbow=(30.0, 80.0)), description).protocol.prediction.poses > 10


def test_the_design_command_refuses_degenerate_limits_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    limits = tmp_path / "narrow.yaml"
    limits.write_text(
        "elevation: {lower_deg: 0, upper_deg: 100}\nhorizontal_rotation: {lower_deg: -20, upper_deg: 165}\n"
        "axial_rotation: {lower_deg: -75, upper_deg: 75}\nelbow: {lower_deg: 50, upper_deg: 60}\n"
    )
    out = tmp_path / "p.yaml"
    code = main(["protocol", "design", "--budget-s", "120", "--limits", str(limits), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("daror protocol design: error: the best")
    assert err.count("\n") == 1
    assert "Traceback" not in err
    assert list(tmp_path.iterdir()) == [limits]


def test_bad_design_options_are_refused(description: RobotDescription) -> None:
    with pytest.raises(UsageError, match="nonlinear"):
        parse_effects("gravity_tilt")
    with pytest.raises(UsageError, match="unknown effect"):
        parse_effects("friction")
    with pytest.raises(UsageError, match="needs --approach both"):
        design_protocol(60.0, settings=DesignSettings(approach="once", effects=parse_effects("direction_offset")))
    with pytest.raises(UsageError, match="already holds"):
        design_protocol(60.0, settings=DesignSettings(effects=parse_effects("joint_stiffness:4")))
    with pytest.raises(UsageError, match="budget-s"):
        design_protocol(-5.0)


def test_a_design_for_direction_offsets_predicts_their_standard_errors(description: RobotDescription) -> None:
    protocol = design_protocol(90.0, settings=DesignSettings(effects=parse_effects("direction_offset"))).protocol
    names = [b.expression for b in protocol.prediction.base_parameters]
    assert names[-4:] == [f"direction_offset{j}_nm" for j in range(1, 5)]
    errors = [b.std_error for b in protocol.prediction.base_parameters[-4:]]
    assert all(0.0 < e < 0.05 for e in errors)  # every pose seen from both directions: offsets well identified
    # what the model explains is no longer in the floor of the predicted validation error
    assert protocol.prediction.validation_rmse_nm < 0.1


def test_a_design_for_direction_offsets_identifies_them_in_closed_loop(
    tmp_path: Path, description: RobotDescription
) -> None:
    result = design_protocol(90.0, settings=DesignSettings(effects=parse_effects("direction_offset")))
    hal = SimHal("exo_dummy_arm")
    hal.open()
    feedforward = APModel.from_description(description, dummy_arm=True, elbow_stiffness=True)
    run = run_protocol(hal, result.trajectory, tmp_path / "x.rec", tmp_path / "x.csv", feedforward=feedforward)
    data = run.stationary
    assert set(np.unique(data.direction)) == {-1.0, 1.0}  # every stop reached after a full reversal
    model = result.problem.model
    x = model.full_rows(data.q_rad, data.direction)
    fit = min_norm_least_squares(np.ascontiguousarray(x.reshape(-1, x.shape[2]).T), data.tau_nm.reshape(-1))
    assert fit.rank == model.rank == 18  # PLF+'s 14 and the four offsets
    offsets = fit.theta[-4:]
    assert np.all(offsets > 0.1)
    assert int(np.argmax(offsets)) == 1  # joint 2's, the largest (Sec. 2.2.2)
    plf_plus = fit_model("plf+", data, description, installation_options("plf+", dummy_arm=True))
    rmse = float(np.sqrt(np.mean(fit.residual**2)))
    assert rmse < 0.5 * plf_plus.report.training.rmse_nm  # the offsets hold most of what PLF+ cannot


def test_screening_poses_gives_nan_rows_for_the_unreachable_ones(description: RobotDescription) -> None:
    shoulder = Shoulder.from_description(description)
    isb = np.radians(
        [[30.0, 90.0, 0.0, 60.0], [90.0, 0.0, 0.0, 90.0], [60.0, 150.0, -40.0, 60.0]]
    )  # middle: abduction 90
    q = shoulder.q_from_isb(isb, unreachable_as_nan=True)
    assert np.all(np.isnan(q[1]))
    assert q[[0, 2]] == pytest.approx(shoulder.q_from_isb(isb[[0, 2]]), abs=0.0)
    with pytest.raises(UnreachablePoseError, match="pose 2 of 3"):
        shoulder.q_from_isb(isb)


@settings(max_examples=60, deadline=None)
@given(data=st.data(), n=st.integers(2, 25))
def test_shortening_a_tour_keeps_its_poses_and_never_lengthens_it(data: st.DataObject, n: int) -> None:
    seed = data.draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    points = rng.uniform(size=(n, 2))
    between = np.linalg.norm(points[:, None] - points[None], axis=2) + rng.uniform(0, 0.2, (n, n))  # not symmetric
    times = RouteTimes(between, rng.uniform(size=n), rng.uniform(size=n))
    tour = [int(c) for c in rng.permutation(n)]
    shorter = improve_tour(times, tour)
    assert sorted(shorter) == sorted(tour)
    assert times.tour_time(shorter) <= times.tour_time(tour) + 1e-12


# --- the file ----------------------------------------------------------------------------------------


def test_the_protocol_file_round_trips(tmp_path: Path, designed: DesignedProtocol) -> None:
    path = tmp_path / "p.yaml"
    write_protocol(path, designed)
    loaded, visits = load_protocol(path)
    assert loaded == designed
    assert protocol_text(loaded) == path.read_text()
    assert len(visits) == len(designed.visits)
    assert visits.describe(3).startswith(f"waypoint 3 ({path} line ")


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda d: d["visits"][3].update(stop_s=-1.0), "field visits.3.stop_s"),
        (lambda d: d["visits"][1].update(stop_s=0.1), "field visits.1: Value error, stop_s 0.1 s gives no data"),
        (lambda d: d["visits"][2].update(elbow_deg="ninety"), "field visits.2.elbow_deg"),
        (lambda d: d["visits"][0].pop("pose"), "field visits.0.pose: Field required"),
        (lambda d: d.update(version=2), "field version"),
        (lambda d: d.update(speed=1.0), "field speed: Extra inputs are not permitted"),
        (lambda d: d["limits"]["elevation"].update(upper_deg=400), "field limits.elevation.upper_deg"),
        (lambda d: [v.update(stop_s=0.0) for v in d["visits"]], "no visit has a stop"),
        (lambda d: d.update(visits=d["visits"][:1]), "field visits"),
    ],
)
def test_a_bad_protocol_file_is_refused_in_one_line_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], designed: DesignedProtocol, edit: object, field: str
) -> None:
    document = yaml.safe_load(protocol_text(designed))
    edit(document)  # type: ignore[operator]
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(document, sort_keys=False))
    with pytest.raises(ProtocolFileError, match=f"^{bad}: "):
        load_protocol(bad)
    out = tmp_path / "train.npz"
    code = main(["identify", "--scenario", "exo_dummy_arm", "--protocol", str(bad), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1
    assert field in err
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml"]  # nothing written


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ([], "expected --trajectory training|validation or --protocol"),
        (["--trajectory", "training", "--protocol", "p.yaml"], "(one of them)"),
        (["--protocol", "p.yaml", "--waypoints", "w.yaml"], "leave --waypoints out with --protocol"),
    ],
)
def test_identify_needs_one_of_trajectory_and_protocol(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    out = tmp_path / "x.npz"
    assert main(["identify", "--scenario", "exo", *extra, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--budgets", "abc"], "--budgets: 'abc' is not a number"),
        (["--budgets", "0"], "--budgets: 0 is out of range"),
        (["--approaches", "sideways"], "--approaches: 'sideways'"),
        (["--draws", "0"], "--draws 0: expected at least 1"),
    ],
)
def test_the_study_refuses_bad_options_before_any_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    out = tmp_path / "study"
    assert main(["study", "protocol", "--scenario", "exo", *extra, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert err.count("\n") == 1
    assert not out.exists()


# --- issue 24: limits the robot's home pose lies outside ------------------------------------------------

#: A pilot who cannot let the arm hang: the robot's home (elevation 0) is outside these limits.
ABOVE_HOME = (
    "elevation: {lower_deg: 10.0, upper_deg: 70.0}\n"
    "horizontal_rotation: {lower_deg: 0.0, upper_deg: 120.0}\n"
    "axial_rotation: {lower_deg: -40.0, upper_deg: 40.0}\n"
    "elbow: {lower_deg: 20.0, upper_deg: 100.0}\n"
)


@pytest.mark.slow
def test_a_protocol_designed_for_limits_that_exclude_the_home_pose_runs_with_those_limits_enforced(
    tmp_path: Path, description: RobotDescription
) -> None:
    """Before: ``daror identify`` stopped at t = 0.001 s, "isb_limit: elevation 0.0 deg beyond the
    pilot's limit 10.0 deg": the robot starts at its home, which the design itself was told is out."""
    limits_file = tmp_path / "pilot_isb.yaml"
    limits_file.write_text(ABOVE_HOME)
    protocol_file, out = tmp_path / "short.yaml", tmp_path / "B_short.npz"
    design = ["protocol", "design", "--budget-s", "60", "--limits", str(limits_file), "--out", str(protocol_file)]
    assert main(design) == 0
    identify = ["identify", "--scenario", "exo_dummy_arm", "--dummy-arm", "--protocol", str(protocol_file)]
    assert main([*identify, "--isb-limits", str(limits_file), "--out", str(out)]) == 0
    protocol, _ = load_protocol(protocol_file)
    assert len(load_stationary(out)) == 3 * protocol.prediction.data_stops  # the whole protocol ran
    raw = load_dataset(tmp_path / "B_short.raw.npz")
    limits = IsbLimits.model_validate(yaml.safe_load(ABOVE_HOME))
    isb = Shoulder.from_description(description).isb_from_q(raw.q_rad)  # the arm as measured, every tick
    inside = np.asarray(limits.contains(isb))
    assert not inside[0]  # it started at home, below the pilot's lowest elevation
    assert np.degrees(isb[0, 0]) < 1.0
    entry = int(np.argmax(inside))
    assert inside[entry:].all()  # once in, never out: what the monitor enforced from then on
    entered_s = raw.t_s[entry] - raw.t_s[0]
    assert entered_s <= protocol.prediction.approach_s  # in, before the approach's end
    assert np.degrees(isb[:entry, 0]).min() >= -APPROACH_SLACK_DEG  # no further out on the way in than home


def test_an_approach_that_would_leave_the_limits_is_refused_before_anything_moves(
    tmp_path: Path, description: RobotDescription, capsys: pytest.CaptureFixture[str]
) -> None:
    limits_file = tmp_path / "pilot_isb.yaml"
    limits_file.write_text(ABOVE_HOME)
    limits = IsbLimits.model_validate(yaml.safe_load(ABOVE_HOME))
    designed = design_protocol(60.0, limits, description).protocol
    # a first pose whose straight joint approach from home enters the limits, then leaves them (horizontal
    # rotation beyond 120 deg on the way) before it comes back in
    first = IsbPose(elevation_deg=42.4, horizontal_rotation_deg=114.3, axial_rotation_deg=15.6, elbow_deg=63.4)
    then = first.model_copy(update={"elbow_deg": 70.0})
    visits = [first.model_dump() | {"stop_s": 1.0, "pose": 1}, then.model_dump() | {"stop_s": 1.0, "pose": 2}]
    protocol_file, out = tmp_path / "p.yaml", tmp_path / "B.npz"
    write_protocol(protocol_file, designed.model_copy(update={"visits": [Visit(**v) for v in visits]}))
    identify = ["identify", "--scenario", "exo_dummy_arm", "--dummy-arm", "--protocol", str(protocol_file)]
    capsys.readouterr()
    assert main([*identify, "--isb-limits", str(limits_file), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith(
        "daror identify: error: the approach from where the robot stands leaves the pilot's ISB limits at "
    )
    assert "horizontal rotation" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.yaml", "pilot_isb.yaml"]  # nothing written


def test_the_approach_check_names_where_an_approach_leaves_or_strays(description: RobotDescription) -> None:
    shoulder = Shoulder.from_description(description)
    limits = IsbLimits.model_validate(yaml.safe_load(ABOVE_HOME))
    home = shoulder.q_from_isb(HOME.isb_rad)
    first = shoulder.q_from_isb(np.radians([22.6, 83.6, -14.4, 27.5]))
    check = check_approach(shoulder, limits, home, first)  # in through the elevation, then inside
    assert check.outside == ("elevation 0.0 deg outside [10, 70] deg",)
    assert 0.3 < check.entry_fraction < 0.6
    assert check.on_the_way.elevation.lower_deg == pytest.approx(np.degrees(shoulder.isb_from_q(home)[0]) - 1.0)
    assert check.on_the_way.ranges[1:] == limits.ranges[1:]  # only the side the start lies beyond moves
    inside = check_approach(shoulder, limits, first, shoulder.q_from_isb(np.radians([40.0, 60.0, 0.0, 50.0])))
    assert inside.starts_inside
    assert inside.entry_fraction == 0.0
    assert inside.on_the_way is limits
    with pytest.raises(TrajectoryError, match=r"^the approach ends outside the pilot's ISB limits: elevation 0\.0"):
        check_approach(shoulder, limits, first, home)
    # from an axial rotation of 41 deg (limit 40) towards a pose inside, the path first turns further out
    start = shoulder.q_from_isb(np.radians([30.0, 90.0, 41.0, 50.0]))
    with pytest.raises(TrajectoryError, match=r"goes further out on its way in, at \d+% of the way: axial rotation 42"):
        check_approach(shoulder, limits, start, shoulder.q_from_isb(np.radians([64.0, 40.0, 37.0, 36.0])))
    bent = shoulder.q_from_isb(np.radians([42.4, 114.3, 15.6, 63.4]))
    with pytest.raises(TrajectoryError, match=r"leaves the pilot's ISB limits at \d+% of the way after it was inside"):
        check_approach(shoulder, limits, home, bent)


def test_a_design_from_a_start_outside_the_limits_enters_them_and_stays_in(description: RobotDescription) -> None:
    """A start pose beyond the axial limit: the approach aims for the start brought inside the limits."""
    shoulder = Shoulder.from_description(description)
    limits = IsbLimits.model_validate(yaml.safe_load(ABOVE_HOME))
    start = IsbPose(elevation_deg=30.0, horizontal_rotation_deg=90.0, axial_rotation_deg=45.0, elbow_deg=50.0)
    result = design_protocol(60.0, limits, description, start=start)
    protocol = result.protocol
    assert protocol.start == start
    start_q = shoulder.q_from_isb(start.isb_rad)
    run = prepend_approach(result.trajectory, start_q, protocol.prediction.approach_s, protocol.prediction.settle_s)
    assert run.duration_s == pytest.approx(protocol.prediction.robot_time_s, abs=1e-9)
    isb = shoulder.isb_from_q(run.sample(np.arange(0.0, run.duration_s, 0.001))[0])
    inside = np.asarray(limits.contains(isb))
    entry = int(np.argmax(inside))
    assert entry > 0
    assert inside[entry:].all()
    assert np.degrees(isb[:entry, 2]).max() <= 45.0 + APPROACH_SLACK_DEG


# --- where it runs -----------------------------------------------------------------------------------


def test_identify_runs_a_protocol_in_its_budget_on_a_scenario_given_as_a_file(
    tmp_path: Path, designed: DesignedProtocol
) -> None:
    protocol = tmp_path / "p.yaml"
    write_protocol(protocol, designed)
    scenario = tmp_path / "my_plant.yaml"  # an as-built variant of dataset B, by path
    scenario.write_text(
        "extends: exo_dummy_arm\nname: my_plant\nsensors:\n  direction_error_nm: [0.2, 0.5, 0.3, 0.1]\n"
    )
    out = tmp_path / "train.npz"
    argv = ["identify", "--scenario", str(scenario), "--dummy-arm", "--protocol", str(protocol), "--out", str(out)]
    assert main(argv) == 0
    data = load_stationary(out)
    raw = load_dataset(tmp_path / "train.raw.npz")
    robot_s = float(raw.t_s[-1] - raw.t_s[0])
    assert robot_s == pytest.approx(designed.prediction.robot_time_s, abs=0.01)
    assert robot_s <= designed.design.budget_s
    assert len(data) == 3 * designed.prediction.data_stops  # every stop gives its three points
    # the points stand where the protocol stopped
    shoulder = Shoulder.from_description(SimHal("exo").description)
    stops = np.array([shoulder.q_from_isb(v.isb_rad) for v in designed.visits if v.stop_s > 0])
    nearest = np.abs(data.q_rad[:, None, :] - stops[None]).max(axis=2).min(axis=1)
    assert nearest.max() < 0.03


def test_a_session_designs_its_training_run_inside_the_recorded_limits(
    tmp_path: Path, description: RobotDescription
) -> None:
    recorded = limits_of(elevation=(0.0, 60.0), axial_rotation=(-40.0, 40.0), elbow=(20.0, 100.0))
    settings_ = IdentificationSettings(protocol_budget_s=60.0)
    waypoints, _ = session_waypoints(settings_, recorded, description)
    shoulder = Shoulder.from_description(description)
    home = shoulder.q_from_isb(HOME.isb_rad)
    run = prepare_run("training", description, home, waypoints, recorded, settings_, None, 0.001, tmp_path)
    run.recorder.close()
    assert run.duration_s <= 60.0  # approach and settle included
    q, _ = run.reference.sample(np.arange(run.reference.time_offset_s, run.duration_s, 0.002))
    assert np.all(recorded.contains(shoulder.isb_from_q(q)))
    # the validation run stays the waypoints'
    validation = prepare_run("validation", description, home, waypoints, recorded, settings_, None, 0.001, tmp_path)
    validation.recorder.close()
    assert len(validation.reference.waypoint_stops) == 2 * len(waypoints)


def test_a_session_runs_a_protocol_file(
    tmp_path: Path, description: RobotDescription, designed: DesignedProtocol
) -> None:
    path = tmp_path / "p.yaml"
    write_protocol(path, designed)
    settings_ = IdentificationSettings(protocol_file=path)
    waypoints, _ = session_waypoints(settings_, IsbLimits(), description)
    home = Shoulder.from_description(description).q_from_isb(HOME.isb_rad)
    run = prepare_run("training", description, home, waypoints, IsbLimits(), settings_, None, 0.001, tmp_path)
    run.recorder.close()
    assert run.duration_s == pytest.approx(designed.prediction.robot_time_s, abs=1e-9)
    with pytest.raises(ValueError, match="set one of them"):
        IdentificationSettings(protocol_file=path, protocol_budget_s=60.0)
