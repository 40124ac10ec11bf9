"""Identification waypoints and trajectories (Sec. 4.3.1-4.3.2): the shipped set, the checks, the reference."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.errors import InputError
from daror_runtime.identification import (
    ReferenceTrajectory,
    TrajectoryError,
    TrajectorySettings,
    WaypointFileError,
    WaypointSet,
    build_trajectory,
    load_waypoints,
)
from daror_runtime.identification.trajectory import ReferenceTimeError
from daror_runtime.identification.trajectory_planning import integrate_move, minimum_jerk
from hal.isb import AngleRange, IsbLimits, Shoulder, default_shoulder
from hal.robot import RobotDescription

MINUTE = 60.0


def visits(trajectory: ReferenceTrajectory) -> tuple[int, ...]:
    """Waypoint numbers of every waypoint stop, forward run then reverse run."""
    return tuple(s.waypoint for s in trajectory.stops if s.waypoint is not None)


def table_bytes(trajectory: ReferenceTrajectory) -> int:
    """Memory the reference table holds, bytes: its arrays and two Python lists of piece starts and ends."""
    starts, coefficients = trajectory.piecewise_table
    return int(coefficients.nbytes + starts.nbytes + 2 * 32 * len(starts))


@pytest.fixture(scope="module")
def shoulder() -> Shoulder:
    return default_shoulder()


@pytest.fixture(scope="module")
def waypoints() -> WaypointSet:
    return load_waypoints()


@pytest.fixture(scope="module")
def training(waypoints: WaypointSet) -> ReferenceTrajectory:
    return build_trajectory(waypoints, "training")


@pytest.fixture(scope="module")
def validation(waypoints: WaypointSet) -> ReferenceTrajectory:
    return build_trajectory(waypoints, "validation")


@pytest.fixture(params=["training", "validation"])
def trajectory(request: pytest.FixtureRequest) -> ReferenceTrajectory:
    return request.getfixturevalue(request.param)


def waypoint_set(*poses: tuple[float, float, float, float]) -> WaypointSet:
    n = len(poses)
    return WaypointSet(
        waypoints=[
            {"elevation_deg": e, "horizontal_rotation_deg": h, "axial_rotation_deg": a, "elbow_deg": el}
            for e, h, a, el in poses
        ],
        training_order=list(range(1, n + 1)),
        validation_order=list(range(n, 0, -1)),
    )


def move_times(trajectory: ReferenceTrajectory) -> np.ndarray:
    """Times strictly inside the moves, 2 ms apart."""
    t = np.arange(0.0, trajectory.duration_s, 0.002)
    inside_stop = np.zeros(t.shape, dtype=bool)
    for stop in trajectory.stops:
        inside_stop |= (t >= stop.start_s - 1e-9) & (t <= stop.end_s + 1e-9)
    return t[~inside_stop]


# --- the shipped waypoint set ------------------------------------------------------------


def test_shipped_waypoints_cover_the_workspace(waypoints: WaypointSet) -> None:
    isb = np.degrees(waypoints.isb_rad)
    assert 40 <= len(waypoints) <= 85
    assert len(waypoints) == 83  # 2 x 83 = the thesis's 166 validation points
    assert isb[:, 0].min() == 0
    assert isb[:, 0].max() == 90
    assert np.ptp(isb[:, 1]) >= 180  # planes from behind the side to across the body
    assert np.ptp(isb[:, 2]) >= 90
    assert (isb[:, 3].min(), isb[:, 3].max()) == (10, 110)
    assert np.all(IsbLimits().contains(waypoints.isb_rad))
    described = waypoints.describe(17)  # "waypoint 17 (<file> line L)": L is the line a person edits
    line = int(described.rsplit(" ", 1)[1].rstrip(")"))
    assert Path(waypoints.source).read_text().splitlines()[line - 1].endswith("# 17: plane 30")


def test_orders_visit_the_same_waypoints_differently(waypoints: WaypointSet) -> None:
    train, val = waypoints.order("training"), waypoints.order("validation")
    assert sorted(train) == sorted(val) == list(range(1, len(waypoints) + 1))
    assert train != val
    # Runs go both ways, so a move is the same path in either direction.
    moves = [{frozenset(pair) for pair in itertools.pairwise(order)} for order in (train, val)]
    assert len(moves[0] & moves[1]) < 0.25 * (len(train) - 1)


# --- waypoint file errors ----------------------------------------------------------------


def _write(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "wp.yaml"
    path.write_text(body)
    return path


WAYPOINTS = (
    "waypoints:\n"
    "  - {elevation_deg: 0, horizontal_rotation_deg: 0, axial_rotation_deg: 0, elbow_deg: 30}\n"
    "  - {elevation_deg: 30, horizontal_rotation_deg: 90, axial_rotation_deg: 0, elbow_deg: 60}\n"
    "  - {elevation_deg: 50, horizontal_rotation_deg: 60, axial_rotation_deg: 10, elbow_deg: 200}\n"
)


def test_waypoint_file_errors_name_file_line_waypoint_and_field(tmp_path: Path) -> None:
    path = _write(tmp_path, WAYPOINTS + "training_order: [1, 2, 3]\nvalidation_order: [3, 2, 1]\n")
    with pytest.raises(
        WaypointFileError, match=r"wp\.yaml: line 4, waypoint 3, field elbow_deg: Input should be less"
    ) as info:
        load_waypoints(path)
    assert isinstance(info.value, InputError)


@pytest.mark.parametrize(
    ("orders", "message"),
    [
        (
            "training_order: [1, 2]\nvalidation_order: [2, 1]\n",
            r"line 5, field training_order: .*waypoints \[3\] are missing",
        ),
        ("training_order: [1, 2, 4]\nvalidation_order: [2, 1, 3]\n", r"line 5, .*waypoint numbers \[4\] do not exist"),
        ("training_order: [1, 2, 2]\nvalidation_order: [2, 1, 3]\n", r"waypoints \[2\] appear more than once"),
        (
            "training_order: [1, 2, 3]\nvalidation_order: [1, 2, 3]\n",
            r"line 6, field validation_order: .*equals the training",
        ),
        ("training_order: [1, 2, 3]\n", r"field validation_order: Field required"),
    ],
)
def test_order_errors(tmp_path: Path, orders: str, message: str) -> None:
    path = _write(tmp_path, WAYPOINTS.replace("200", "90") + orders)
    with pytest.raises(WaypointFileError, match=message):
        load_waypoints(path)


def test_unreadable_waypoint_files(tmp_path: Path) -> None:
    with pytest.raises(WaypointFileError, match="file not found"):
        load_waypoints(tmp_path / "nothing.yaml")
    with pytest.raises(WaypointFileError, match="not valid YAML"):
        load_waypoints(_write(tmp_path, "waypoints: [\n"))
    with pytest.raises(WaypointFileError, match="line 2, waypoint 1, field elevation_deg: Field required"):
        load_waypoints(
            _write(tmp_path, "waypoints:\n  - {horizontal_rotation_deg: 0, axial_rotation_deg: 0, elbow_deg: 3}\n")
        )


# --- the trajectories pass through the waypoints -----------------------------------------


def test_every_waypoint_stop_is_on_the_exact_waypoint_rotation(
    trajectory: ReferenceTrajectory, waypoints: WaypointSet, shoulder: Shoulder
) -> None:
    worst = 0.0
    for stop in trajectory.waypoint_stops:
        target = waypoints.waypoints[stop.waypoint - 1]
        q = np.array(stop.q_rad)
        difference = shoulder.rotation_from_q(q) @ shoulder.shoulder_rotation(target.isb_rad).T
        worst = max(worst, np.arccos(np.clip((np.trace(difference) - 1) / 2, -1, 1)), abs(q[3] - target.isb_rad[3]))
        # The reference itself holds that pose for the whole stop.
        q_mid, _ = trajectory.reference(0.5 * (stop.start_s + stop.end_s))
        assert q_mid == pytest.approx(q, abs=0)
    assert worst < 1e-6


def test_the_feedback_pulls_a_disturbed_start_back_onto_the_rotation(shoulder: Shoulder) -> None:
    """Without the feedback an error in the start angles is carried to the end of the move."""
    isb_a, isb_b = np.radians([20, 90, 0, 40]), np.radians([50, 120, -10, 60])
    q_a = shoulder.q_from_isb(isb_a)
    r3_a = shoulder.shoulder_rotation(isb_a) @ shoulder.r3_neutral
    r3_b = shoulder.shoulder_rotation(isb_b) @ shoulder.r3_neutral
    disturbed = q_a + np.array([0.01, -0.01, 0.01, 0.0])

    def end_error(gain: float) -> float:
        q, _ = integrate_move(shoulder, disturbed, r3_a, r3_b, isb_b[3], 2.0, 1000.0, gain)
        return float(np.linalg.norm(shoulder.isb_from_q(q[-1]) - isb_b))

    assert end_error(0.0) > 5e-3
    assert end_error(20.0) < 1e-9


def test_forward_then_reverse_ends_where_it_started(trajectory: ReferenceTrajectory) -> None:
    order = trajectory.order
    assert visits(trajectory) == order + order[::-1]
    assert trajectory.stops[0].waypoint == trajectory.stops[-1].waypoint == order[0]
    assert np.array(trajectory.stops[-1].q_rad) == pytest.approx(trajectory.start_q_rad, abs=1e-9)
    # The reverse run stops at the forward run's (sub-)waypoints, backwards.
    stops = trajectory.stops
    half = len(stops) // 2
    assert [s.run for s in stops] == ["forward"] * half + ["reverse"] * half
    forward = np.array([s.q_rad for s in stops[:half]])
    reverse = np.array([s.q_rad for s in stops[half:]])[::-1]
    assert reverse == pytest.approx(forward, abs=1e-9)


def test_training_and_validation_differ_in_order_and_stops(
    training: ReferenceTrajectory, validation: ReferenceTrajectory
) -> None:
    assert sorted(visits(training)) == sorted(visits(validation))
    assert training.order != validation.order
    assert len(validation.stops) == len(validation.waypoint_stops) == 166
    assert len(training.waypoint_stops) == 166
    assert len(training.stops) > 2 * len(validation.stops)
    assert 10 * MINUTE <= training.duration_s <= 15 * MINUTE  # Sec. 5.3: "between 5-15 minutes"
    assert validation.duration_s < training.duration_s
    assert table_bytes(training) < 100e6
    assert table_bytes(validation) < 100e6


def test_stops_are_still_and_every_move_is_smooth(trajectory: ReferenceTrajectory) -> None:
    for stop in trajectory.stops:
        for t in (stop.start_s, 0.5 * (stop.start_s + stop.end_s), stop.end_s - 1e-9):
            q, dq = trajectory.reference(t)
            assert np.array_equal(dq, np.zeros(4))
            assert q == pytest.approx(stop.q_rad, abs=1e-12)
    # Continuity of q and dq across every piece boundary (knots, move ends, stop ends).
    boundaries = np.asarray(trajectory._starts[1:])
    before_q, before_dq = trajectory.sample(boundaries - 1e-9)
    after_q, after_dq = trajectory.sample(boundaries)
    assert np.abs(after_q - before_q).max() < 1e-8
    assert np.abs(after_dq - before_dq).max() < 1e-7


def test_dq_ref_is_the_derivative_of_q_ref(trajectory: ReferenceTrajectory, rng: np.random.Generator) -> None:
    t = rng.choice(move_times(trajectory), 3000, replace=False)
    h = 1e-6
    q_plus, _ = trajectory.sample(t + h)
    q_minus, _ = trajectory.sample(t - h)
    _, dq = trajectory.sample(t)
    assert (q_plus - q_minus) / (2 * h) == pytest.approx(dq, abs=1e-7)
    assert np.abs(dq).max() > 0.1  # it does move


def test_the_whole_path_is_inside_every_limit(
    trajectory: ReferenceTrajectory, shoulder: Shoulder, description: RobotDescription
) -> None:
    t = np.arange(0.0, trajectory.duration_s, 0.005)
    q, dq = trajectory.sample(t)
    assert np.all(q >= description.lower_limits_rad - 1e-9)
    assert np.all(q <= description.upper_limits_rad + 1e-9)
    assert np.all(IsbLimits().contains(shoulder.isb_from_q(q)))
    assert shoulder.sigma_min(q).min() >= trajectory.settings.min_sigma
    limit = np.minimum(description.limits.max_velocity_rad_s, trajectory.settings.max_joint_speed_rad_s)
    assert np.all(np.abs(dq) <= limit)


def test_moves_follow_a_minimum_jerk_profile_on_one_euler_axis(
    training: ReferenceTrajectory, shoulder: Shoulder
) -> None:
    """Between two stops the shoulder turns about one fixed axis, speed rising and falling smoothly."""
    first, second = training.stops[0], training.stops[1]
    t = np.linspace(first.end_s, second.start_s, 101)
    q, dq = training.sample(t)
    omega = np.einsum("nij,nj->ni", shoulder.shoulder_jacobian(q), dq[:, :3])
    speed = np.linalg.norm(omega, axis=1)
    axes = omega[5:-5] / speed[5:-5, None]
    assert np.abs(axes - axes[len(axes) // 2]).max() < 1e-4  # knots 10 ms apart: Hermite-accurate
    s, ds = minimum_jerk((t - t[0]) / (t[-1] - t[0]))
    assert speed / speed.max() == pytest.approx(ds / ds.max(), abs=1e-4)
    assert s[0] == 0
    assert s[-1] == 1


# --- reference() per tick ------------------------------------------------------------------


def test_reference_outside_and_backwards(training: ReferenceTrajectory) -> None:
    q, dq = training.reference(-5.0)
    assert q == pytest.approx(training.start_q_rad)
    assert not dq.any()
    q, dq = training.reference(training.duration_s + 100.0)
    assert q == pytest.approx(np.array(training.stops[-1].q_rad))
    assert not dq.any()
    forward = training.reference(300.0)
    training.reference(700.0)
    again = training.reference(300.0)  # a jump back: found again, same answer
    assert np.array_equal(forward[0], again[0])
    assert np.array_equal(forward[1], again[1])
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ReferenceTimeError):
            training.reference(bad)


def test_reference_matches_sample(training: ReferenceTrajectory, rng: np.random.Generator) -> None:
    t = np.sort(rng.uniform(0, training.duration_s, 500))
    q, dq = training.sample(t)
    for i, ti in enumerate(t):
        qi, dqi = training.reference(float(ti))
        assert qi == pytest.approx(q[i], abs=1e-12)
        assert dqi == pytest.approx(dq[i], abs=1e-12)


# --- refusals ------------------------------------------------------------------------------


def test_unreachable_waypoint_is_refused_by_number() -> None:
    with pytest.raises(
        TrajectoryError, match=r"training trajectory, waypoint 2: pose \(elevation 60\.0.*unreachable"
    ) as info:
        build_trajectory(waypoint_set((0, 0, 0, 30), (60, 0, 0, 40)), "training")
    assert isinstance(info.value, InputError)


def test_waypoint_outside_the_pilots_limits_is_refused_by_number() -> None:
    limits = IsbLimits(elevation=AngleRange(lower_deg=0, upper_deg=60))
    with pytest.raises(
        TrajectoryError, match=r"waypoint 3 is outside the pilot's ISB limits: elevation 80\.0 deg outside \[0, 60\]"
    ):
        build_trajectory(waypoint_set((0, 0, 0, 30), (40, 90, 0, 40), (80, 90, 0, 40)), "validation", limits=limits)


def test_path_leaving_the_pilots_limits_between_waypoints_is_refused() -> None:
    # Both ends at 45 deg of elevation; the shortest rotation between two planes 120 deg apart dips
    # lower on the way, below a pilot's lower elevation limit of 35 deg.
    limits = IsbLimits(elevation=AngleRange(lower_deg=35, upper_deg=100))
    with pytest.raises(
        TrajectoryError,
        match=r"training trajectory, forward run, move from waypoint 1 to waypoint 2 \(step \d of \d\): the path leaves "
        r"the pilot's ISB limits at \d+% of the way, worst at \d+% of the way: elevation 3[0-4]\.\d deg outside \[35, 100\]",
    ):
        build_trajectory(waypoint_set((45, 30, 10, 40), (45, 150, -25, 40)), "training", limits=limits)


def test_path_through_a_singular_region_is_refused() -> None:
    # Both waypoints are 0.34 from singular; the shortest rotation between them dips to 0.24.
    pair = waypoint_set((30, 15, 65, 40), (70, 75, 35, 40))
    with pytest.raises(
        TrajectoryError, match=r"move from waypoint 1 to waypoint 2 .*near a shoulder singularity \(q2 = 3"
    ):
        build_trajectory(pair, "training")


def test_waypoint_near_a_singularity_is_refused() -> None:
    with pytest.raises(TrajectoryError, match=r"waypoint 2 is too near a shoulder singularity"):
        build_trajectory(
            waypoint_set((0, 0, 0, 30), (30, 15, 65, 40)), "validation", settings=TrajectorySettings(min_sigma=0.4)
        )


def test_messages_name_the_line_of_a_file(tmp_path: Path) -> None:
    path = tmp_path / "wp.yaml"
    path.write_text(
        "waypoints:\n"
        "  - {elevation_deg: 0, horizontal_rotation_deg: 0, axial_rotation_deg: 0, elbow_deg: 30}\n"
        "  - {elevation_deg: 60, horizontal_rotation_deg: 0, axial_rotation_deg: 0, elbow_deg: 40}\n"
        "training_order: [1, 2]\nvalidation_order: [2, 1]\n"
    )
    with pytest.raises(TrajectoryError, match=r"waypoint 2 \(.*wp\.yaml line 3\)"):
        build_trajectory(load_waypoints(path), "training")


def test_joint_speed_limit_slows_the_moves_down() -> None:
    pair = waypoint_set((10, 90, 0, 30), (60, 90, 0, 90))
    fast = build_trajectory(pair, "validation")
    slow = build_trajectory(
        pair, "validation", settings=TrajectorySettings(sub_waypoint_spacing_deg=None, max_joint_speed_rad_s=0.1)
    )
    _, dq = slow.sample(np.arange(0, slow.duration_s, 0.001))
    assert np.abs(dq).max() <= 0.1
    assert slow.duration_s > fast.duration_s


@pytest.mark.parametrize(
    "bad",
    [
        {"stop_s": 0.0},
        {"shoulder_speed_rad_s": -1.0},
        {"knot_rate_hz": 300.0},
        {"sub_waypoint_spacing_deg": 0.0},
        {"feedback_gain_per_s": 1e4},
        {"min_sigma": 1.5},
    ],
)
def test_bad_settings_are_refused(bad: dict[str, float]) -> None:
    with pytest.raises(TrajectoryError, match=next(iter(bad))):
        TrajectorySettings(**bad)
