"""ISB angles, the shoulder's inverse kinematics and Jacobian, the pilot's ISB limits (hal/isb.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from hal.errors import InputError, ShapeError
from hal.isb import (
    IsbLimits,
    IsbLimitsError,
    Shoulder,
    UnreachablePoseError,
    default_shoulder,
    isb_from_q,
    isb_single,
    jacobian_sigma_min,
    load_isb_limits,
    monitor_isb_function,
    q_from_isb,
    shoulder_jacobian,
    shoulder_rotation,
)
from hal.robot import RobotDescription, rot_y

DOWN, UP = np.array([0.0, -1.0, 0.0]), np.array([0.0, 1.0, 0.0])
FORWARD, LATERAL = np.array([0.0, 0.0, 1.0]), np.array([-1.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def shoulder() -> Shoulder:
    return default_shoulder()


def deg(*values: float) -> np.ndarray:
    return np.radians(np.array(values, dtype=float))


def vee(skew: np.ndarray) -> np.ndarray:
    return 0.5 * np.array([skew[2, 1] - skew[1, 2], skew[0, 2] - skew[2, 0], skew[1, 0] - skew[0, 1]])


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle of the rotation between a and b, accurate for tiny angles (unlike arccos of the trace)."""
    return float(np.arcsin(min(np.linalg.norm(vee(a @ b.T)), 1.0)))


# --- strategies: configurations on the device's branch, away from singularities ---------------

angle = st.floats(-np.pi, np.pi, allow_nan=False)
on_branch = st.tuples(
    st.floats(-np.pi / 2, np.pi / 2),  # q1 inside its limits
    st.floats(np.radians(30), np.radians(120)),  # q2 > 0: the branch of the neutral pose
    st.floats(-np.radians(110), np.radians(110)),
    st.floats(-np.radians(5), np.radians(135)),
).map(np.array)
isb_box = st.tuples(
    st.floats(np.radians(3), np.radians(120)),
    st.floats(np.radians(-30), np.radians(170)),
    st.floats(np.radians(-70), np.radians(70)),
    st.floats(0.0, np.radians(130)),
).map(np.array)


# --- the convention ------------------------------------------------------------------------


def test_neutral_pose_hangs_the_arm_with_the_elbow_flexing_forward(shoulder: Shoulder) -> None:
    q = shoulder.q_neutral
    assert np.degrees(q) == pytest.approx([-20.25, 82.41, -30.27, 0.0], abs=0.01)
    r3 = shoulder.rotor3(q)
    assert r3[:, 0] == pytest.approx(DOWN, abs=1e-12)  # upper arm straight down
    assert r3[:, 1] == pytest.approx(FORWARD, abs=1e-12)  # positive q4 swings the forearm forward
    assert r3[:, 2] == pytest.approx(LATERAL, abs=1e-12)  # elbow axis to the pilot's right
    assert shoulder.isb_from_q(q) == pytest.approx(np.zeros(4), abs=1e-12)
    # Reachable with room to spare and far from a singularity (the best possible is 0.71).
    margin = np.minimum(q - shoulder.lower_rad, shoulder.upper_rad - q)[:3]
    assert np.degrees(margin.min()) > 35
    assert shoulder.sigma_min(q) == pytest.approx(0.604, abs=1e-3)


@pytest.mark.parametrize(
    ("isb_deg", "arm", "forearm"),
    [
        ((0, 0, 0, 90), DOWN, FORWARD),  # hanging, elbow at 90: forearm forward
        ((0, 77, 0, 90), DOWN, FORWARD),  # the plane of elevation means nothing while the arm hangs
        ((0, 0, 90, 90), DOWN, LATERAL),  # external rotation of the hanging arm: forearm out
        ((90, 0, 0, 90), LATERAL, FORWARD),  # 90 deg abduction, neutral rotation: forearm forward
        ((90, 0, 90, 90), LATERAL, UP),  # ... and external rotation turns it up
        ((90, 90, 0, 90), FORWARD, UP),  # 90 deg flexion: forearm up
        ((90, 180, 0, 90), -LATERAL, FORWARD),  # across the body: the swing axis is the forward axis
        ((180, 0, 0, 0), UP, UP),  # arm straight up
    ],
)
def test_example_poses(shoulder: Shoulder, isb_deg: tuple[float, ...], arm: np.ndarray, forearm: np.ndarray) -> None:
    isb = deg(*isb_deg)
    r3 = shoulder.shoulder_rotation(isb) @ shoulder.r3_neutral
    r4 = r3 @ np.array([[np.cos(isb[3]), -np.sin(isb[3]), 0], [np.sin(isb[3]), np.cos(isb[3]), 0], [0, 0, 1]])
    assert r3[:, 0] == pytest.approx(arm, abs=1e-12)
    assert r4[:, 0] == pytest.approx(forearm, abs=1e-12)


@given(isb=isb_box)
def test_elevation_is_the_angle_from_hanging_and_rotation_is_a_y_x_y_sequence(
    shoulder: Shoulder, isb: np.ndarray
) -> None:
    r_sh = shoulder.shoulder_rotation(isb)
    arm = r_sh @ DOWN
    assert np.arccos(np.clip(-arm[1], -1, 1)) == pytest.approx(isb[0], abs=1e-9)
    # The plane: 0 = lateral, 90 deg = forward.
    assert np.arctan2(arm @ FORWARD, arm @ LATERAL) == pytest.approx(isb[1], abs=1e-9)
    # Swing (about a horizontal axis) then twist about the upper arm by gamma_a.
    swing_axis = shoulder.thorax_in_world @ rot_y(isb[1]) @ np.array([1.0, 0.0, 0.0])  # forward, turned by the plane
    swing = _rodrigues(swing_axis, -isb[0])
    twist = _rodrigues(DOWN, isb[2])
    assert r_sh == pytest.approx(swing @ twist, abs=1e-12)


def _rodrigues(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * k @ k


def test_axial_rotation_does_not_jump_near_the_hanging_pose(shoulder: Shoulder) -> None:
    """ISB's own third angle jumps with the plane of elevation as the arm hangs; ours does not."""
    for plane in np.radians([-90, -30, 0, 45, 90, 160]):
        isb = shoulder.isb_from_q(shoulder.q_from_isb(np.array([1e-4, plane, 0.3, 0.5])))
        assert isb[2] == pytest.approx(0.3, abs=1e-9)
        assert isb[1] == pytest.approx(plane, abs=1e-6)
    # Exactly at the pole the plane is reported as 0 and the axial rotation is still exact.
    assert shoulder.isb_from_q(shoulder.q_from_isb(np.array([0.0, 1.0, 0.3, 0.5]))) == pytest.approx(
        [0.0, 0.0, 0.3, 0.5], abs=1e-9
    )


# --- round trips ---------------------------------------------------------------------------


@given(q=on_branch)
def test_q_to_isb_to_q(shoulder: Shoulder, q: np.ndarray) -> None:
    back = shoulder.q_from_isb(shoulder.isb_from_q(q), seed=q)
    assert back == pytest.approx(q, abs=1e-9)


@given(isb=isb_box)
def test_isb_to_q_to_isb(shoulder: Shoulder, isb: np.ndarray) -> None:
    try:
        q = shoulder.q_from_isb(isb)
    except UnreachablePoseError:
        assume(False)
        return
    assert np.all(q >= shoulder.lower_rad)
    assert np.all(q <= shoulder.upper_rad)
    assert shoulder.isb_from_q(q) == pytest.approx(isb, abs=1e-9)
    assert rotation_angle(shoulder.rotation_from_q(q), shoulder.shoulder_rotation(isb)) < 1e-9


def test_round_trip_vectorised_with_per_row_seeds(shoulder: Shoulder, rng: np.random.Generator) -> None:
    q = np.column_stack(
        [
            rng.uniform(-1.5, 1.5, 500),
            rng.uniform(0.6, 2.0, 500),
            rng.uniform(-1.9, 1.9, 500),
            rng.uniform(0.0, 2.3, 500),
        ]
    )
    assert shoulder.q_from_isb(shoulder.isb_from_q(q), seed=q) == pytest.approx(q, abs=1e-9)


def test_the_nearest_branch_to_the_seed_wins(shoulder: Shoulder) -> None:
    # Both branches (q2 = +-33.9 deg) are inside the limits for this pose; each seed gets its own.
    q_plus = deg(-66.4, 33.9, 3.6, 22.9)
    isb = shoulder.isb_from_q(q_plus)
    q_minus = shoulder.q_from_isb(isb, seed=np.array([0.0, -0.5, 0.0, 0.4]))
    assert np.degrees(q_minus) == pytest.approx([-3.7, -33.9, 66.3, 22.9], abs=0.05)
    assert rotation_angle(shoulder.rotation_from_q(q_minus), shoulder.rotation_from_q(q_plus)) < 1e-9
    assert shoulder.q_from_isb(isb, seed=q_plus) == pytest.approx(q_plus, abs=1e-12)


@given(q=st.tuples(angle, angle, angle, angle).map(np.array))
def test_single_configuration_equals_vectorised(shoulder: Shoulder, q: np.ndarray) -> None:
    assert shoulder.isb_single(q) == pytest.approx(shoulder.isb_from_q(q[None])[0], abs=1e-12)


def test_single_configuration_at_the_pole_and_module_functions(shoulder: Shoulder) -> None:
    q = shoulder.q_neutral.copy()
    assert isb_single(q) == pytest.approx(np.zeros(4), abs=1e-12)
    assert isb_from_q(q) == pytest.approx(np.zeros(4), abs=1e-12)
    assert q_from_isb(np.zeros(4)) == pytest.approx(q, abs=1e-12)
    assert shoulder_rotation(np.zeros(4)) == pytest.approx(np.eye(3), abs=1e-12)
    assert shoulder_jacobian(q).shape == (3, 3)
    assert jacobian_sigma_min(q) == pytest.approx(shoulder.sigma_min(q))


# --- differential kinematics --------------------------------------------------------------


@given(q=on_branch)
def test_jacobian_equals_finite_differences_of_the_rotation(shoulder: Shoulder, q: np.ndarray) -> None:
    jac = shoulder.shoulder_jacobian(q)
    h = 1e-6
    for i in range(3):
        step = np.zeros(4)
        step[i] = h
        plus, minus = shoulder.rotor3(q + step), shoulder.rotor3(q - step)
        omega = vee((plus - minus) / (2 * h) @ shoulder.rotor3(q).T)
        assert omega == pytest.approx(jac[:, i], abs=1e-8)
    # The shoulder rotation R_sh turns with the same angular velocity as rotor 3.
    q_dot = np.array([0.3, -0.2, 0.5, 0.0])
    r_dot = (shoulder.rotation_from_q(q + h * q_dot) - shoulder.rotation_from_q(q - h * q_dot)) / (2 * h)
    assert vee(r_dot @ shoulder.rotation_from_q(q).T) == pytest.approx(jac @ q_dot[:3], abs=1e-8)


@given(q=st.tuples(angle, angle, angle, angle).map(np.array))
def test_sigma_min_equals_the_svd_and_depends_on_q2_only(shoulder: Shoulder, q: np.ndarray) -> None:
    svd = np.linalg.svd(shoulder.shoulder_jacobian(q), compute_uv=False)[-1]
    assert shoulder.sigma_min(q) == pytest.approx(svd, abs=1e-9)
    other = np.array([0.7, q[1], -1.1, 0.0])
    assert shoulder.sigma_min(other) == pytest.approx(shoulder.sigma_min(q), abs=1e-12)


def test_singular_configurations(shoulder: Shoulder) -> None:
    coplanar = np.array([0.3, 0.0, -0.4, 0.0])  # q2 = 0: axes 1, 2, 3 in one plane
    aligned = np.array([0.3, np.pi, -0.4, 0.0])  # q2 = 180 deg: axes 1 and 3 aligned
    assert shoulder.sigma_min(coplanar) == pytest.approx(0.0, abs=1e-7)
    assert shoulder.sigma_min(aligned) == pytest.approx(0.0, abs=1e-7)
    axes = shoulder.shoulder_jacobian(aligned)
    assert abs(axes[:, 0] @ axes[:, 2]) == pytest.approx(1.0)
    assert np.linalg.det(shoulder.shoulder_jacobian(np.array([0, 1.0, 0, 0]))) == pytest.approx(0.75 * np.sin(1.0))
    q = np.array([[0, a, 0, 0] for a in np.radians([10, 45, 90, 105, 120])])
    assert shoulder.sigma_min(np.array([0, np.arccos(-1 / 3), 0, 0])) == pytest.approx(np.sqrt(0.5))  # the best
    assert shoulder.sigma_min(q) == pytest.approx([0.087, 0.373, 0.638, 0.693, 0.612], abs=1e-3)


# --- refusals --------------------------------------------------------------------------------


def test_unreachable_pose_is_refused_with_the_reason(shoulder: Shoulder) -> None:
    with pytest.raises(UnreachablePoseError, match=r"elevation 60\.0.*joint 1 \[-90, 90\]") as info:
        shoulder.q_from_isb(deg(60, 0, 0, 40))
    assert isinstance(info.value, InputError)
    with pytest.raises(UnreachablePoseError, match=r"elbow 150\.0 deg outside joint 4"):
        shoulder.q_from_isb(deg(30, 90, 0, 150))
    with pytest.raises(UnreachablePoseError, match="pose 2 of 2"):
        shoulder.q_from_isb(np.vstack([deg(30, 90, 0, 40), deg(60, 0, 0, 40)]))


def test_wrong_shapes_are_refused(shoulder: Shoulder) -> None:
    with pytest.raises(ShapeError):
        shoulder.isb_from_q(np.zeros(3))
    with pytest.raises(ShapeError):
        shoulder.q_from_isb(np.zeros((2, 3)))
    with pytest.raises(ShapeError):
        shoulder.q_from_isb(np.zeros(4), seed=np.zeros(2))


def test_a_neutral_pose_outside_the_limits_is_refused(description: RobotDescription) -> None:
    tight = description.model_copy(
        update={
            "joint_limits": [
                r if i else r.model_copy(update={"upper_deg": -30.0}) for i, r in enumerate(description.joint_limits)
            ]
        }
    )
    with pytest.raises(UnreachablePoseError):
        Shoulder.from_description(tight)


# --- the pilot's limits --------------------------------------------------------------------


def test_default_limits_hold_the_neutral_pose_and_have_radian_bounds(shoulder: Shoulder) -> None:
    limits = IsbLimits()
    assert limits.contains(shoulder.isb_from_q(shoulder.q_neutral) + deg(0, 0, 0, 30))
    assert np.degrees(limits.lower_rad) == pytest.approx([0, -20, -75, 5])
    assert np.degrees(limits.upper_rad) == pytest.approx([100, 165, 75, 120])


def test_horizontal_rotation_is_free_near_the_hanging_pose() -> None:
    limits = IsbLimits()
    behind_low = deg(10, -120, 0, 40)  # 10 deg of extension-abduction: harmless
    behind_high = deg(40, -120, 0, 40)
    assert limits.contains(behind_low)
    assert not limits.contains(behind_high)
    assert limits.violations(behind_high) == ["horizontal rotation -120.0 deg outside [-20, 165] deg"]
    assert list(limits.contains(np.vstack([behind_low, behind_high]))) == [True, False]
    assert limits.violations(deg(110, 90, 80, 130)) == [
        "elevation 110.0 deg outside [0, 100] deg",
        "axial rotation 80.0 deg outside [-75, 75] deg",
        "elbow 130.0 deg outside [5, 120] deg",
    ]


def test_monitor_function_boxes_the_plane_only_near_hanging(shoulder: Shoulder) -> None:
    limits = IsbLimits()
    angles = monitor_isb_function(shoulder, limits)
    low = shoulder.q_from_isb(deg(10, -120, 0, 40))
    assert np.degrees(angles(low)) == pytest.approx([10, -20, 0, 40], abs=1e-6)
    high = shoulder.q_from_isb(deg(60, 90, 0, 40))
    assert np.degrees(angles(high)) == pytest.approx([60, 90, 0, 40], abs=1e-6)
    boxed = angles(low)
    assert np.all((boxed >= limits.lower_rad) & (boxed <= limits.upper_rad))


@settings(max_examples=200, deadline=None)
@given(
    q=st.lists(st.floats(-3.2, 3.2, allow_nan=False), min_size=4, max_size=4),
    nan_at=st.sampled_from([None, 0, 1, 2, 3]),
    readonly=st.booleans(),
)
def test_monitor_function_is_the_single_angles_projected_bit_for_bit(
    shoulder: Shoulder, q: list[float], nan_at: int | None, readonly: bool
) -> None:
    """The one compiled call gives what isb_single then Python's min(max(h, lo), hi) below the free elevation gave."""
    limits = IsbLimits()
    angles = monitor_isb_function(shoulder, limits)
    q_rad = np.array(q)
    if nan_at is not None:
        q_rad[nan_at] = math.nan
    q_rad.flags.writeable = not readonly  # a HAL sample's arrays are read-only
    expected = shoulder.isb_single(q_rad)
    if expected[0] < limits.horizontal_free_below_rad:
        expected[1] = min(max(expected[1], limits.horizontal_rotation.lower_rad), limits.horizontal_rotation.upper_rad)
    assert angles(q_rad).tobytes() == expected.tobytes()


def test_limits_file_round_trip_and_line_numbered_errors(tmp_path: Path) -> None:
    good = tmp_path / "pilot.yaml"
    good.write_text(
        "# recorded in rom_limits\n"
        "elevation: {lower_deg: 0, upper_deg: 80}\n"
        "horizontal_rotation: {lower_deg: 10, upper_deg: 120}\n"
        "axial_rotation: {lower_deg: -40, upper_deg: 50}\n"
        "elbow: {lower_deg: 15, upper_deg: 110}\n"
    )
    limits = load_isb_limits(good)
    assert np.degrees(limits.upper_rad) == pytest.approx([80, 120, 50, 110])
    bad = tmp_path / "bad.yaml"
    bad.write_text("elevation: {lower_deg: 0, upper_deg: 80}\nelbow: {lower_deg: 120, upper_deg: 110}\n")
    with pytest.raises(IsbLimitsError, match=r"bad\.yaml: line 2, field elbow: .*lower_deg \(120.0\) must be below"):
        load_isb_limits(bad)
    typo = tmp_path / "typo.yaml"
    typo.write_text("elevation: {lower_deg: 0, upper_deg: 80}\naxial: {lower_deg: 1, upper_deg: 2}\n")
    with pytest.raises(IsbLimitsError, match="line 2, field axial: Extra inputs are not permitted"):
        load_isb_limits(typo)
    with pytest.raises(IsbLimitsError, match="file not found"):
        load_isb_limits(tmp_path / "missing.yaml")


def test_a_limits_file_gives_every_angle_and_a_session_summary_is_told_where_its_limits_are(tmp_path: Path) -> None:
    """Issue 28: the defaults are a placeholder, never a pilot's range; ``rom load session.json`` gets one line."""
    part = tmp_path / "part.yaml"
    part.write_text("elevation: {lower_deg: 0, upper_deg: 80}\n")
    with pytest.raises(IsbLimitsError, match=r"part\.yaml: horizontal_rotation, axial_rotation, elbow not given"):
        load_isb_limits(part)
    empty = tmp_path / "empty.yaml"
    empty.write_text("{}\n")
    with pytest.raises(
        IsbLimitsError, match=r"empty\.yaml: elevation, horizontal_rotation, axial_rotation, elbow not given"
    ):
        load_isb_limits(empty)
    summary = tmp_path / "session.json"
    summary.write_text(json.dumps({"session_id": "abc", "state": "compensation", "isb_limits_deg": None}))
    with pytest.raises(IsbLimitsError) as refused:
        load_isb_limits(summary)
    message = str(refused.value)
    assert "\n" not in message
    assert message.endswith("a session's limits are in isb_limits.yaml beside its session.json")
