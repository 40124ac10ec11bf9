"""The lowering of a fault's reaction (daror_runtime/safety/lowering.py): planned, checked, then sampled per tick.

What must hold of every path from anywhere in the pilot's range to the rest pose: it starts where
the arm is held and ends at the rest pose, no driven joint ever moves faster than the speed asked,
it stays inside the joint limits and never goes farther outside the pilot's ISB limits than the arm
already is, it starts and ends at rest (minimum jerk); a joint whose torque is off is not moved.
A path that cannot be safe is refused with the reason.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from daror_runtime.safety.lowering import DEFAULT_LOWERING_SPEED_RAD_S, LoweringError, plan_lowering
from hal.isb import AngleRange, IsbLimits, default_shoulder

SHOULDER = default_shoulder()
REST = SHOULDER.q_from_isb(np.deg2rad([0.0, 0.0, 0.0, 30.0]))
LIMITS = IsbLimits()
MARGIN = np.deg2rad(5.0)

#: Poses inside the default ISB limits (elevation, horizontal rotation, axial rotation, elbow), deg.
poses = st.tuples(st.floats(25.0, 95.0), st.floats(-15.0, 160.0), st.floats(-70.0, 70.0), st.floats(6.0, 118.0))


def _dense(path: object, step_s: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    times = np.arange(0.0, path.duration_s + step_s, step_s)  # type: ignore[attr-defined]
    return path.sample(times)  # type: ignore[attr-defined]


@settings(max_examples=40, deadline=None)
@given(isb=poses)
@example(isb=(76.0, 48.0, -11.0, 6.0))  # q2 at 119.8 deg: the shoulder rotation passed 120 (a clean-clone run found it)
def test_every_lowering_from_the_pilot_s_range_is_slow_inside_the_limits_and_ends_at_rest(
    isb: tuple[float, ...],
) -> None:
    q0 = SHOULDER.q_from_isb(np.deg2rad(isb), unreachable_as_nan=True)
    if not np.all(np.isfinite(q0)) or SHOULDER.sigma_min(q0) < 0.35:
        return  # not a pose this robot holds an arm in
    try:
        path = plan_lowering(q0, REST, SHOULDER, (), LIMITS, MARGIN)
    except LoweringError as exc:
        refusal = str(exc)
        path = None
    if path is None:  # refused with a reason, never a bad path
        assert "singularity" in refusal or "ISB" in refusal
        return
    q, dq = _dense(path)
    np.testing.assert_allclose(q[0], q0, atol=1e-9)
    np.testing.assert_allclose(q[-1], REST, atol=2e-3)
    assert np.abs(dq).max() <= DEFAULT_LOWERING_SPEED_RAD_S * 1.02
    np.testing.assert_allclose(dq[0], 0.0, atol=1e-6)  # minimum jerk: from rest...
    np.testing.assert_allclose(dq[-1], 0.0, atol=1e-6)  # ...to rest
    assert np.all((q >= SHOULDER.lower_rad - 1e-9) & (q <= SHOULDER.upper_rad + 1e-9))
    boxed = LIMITS.for_box_check(SHOULDER.isb_from_q(q))
    excess = np.maximum(LIMITS.lower_rad - MARGIN - boxed, boxed - LIMITS.upper_rad - MARGIN)
    assert excess.max() <= 1e-6, np.degrees(excess.max())  # it started inside: it never leaves what the monitor allows


def test_a_joint_whose_torque_is_off_stays_where_it_is_and_the_others_go_straight() -> None:
    q0 = SHOULDER.q_from_isb(np.deg2rad([40.0, 60.0, 0.0, 70.0]))
    path = plan_lowering(q0, REST, SHOULDER, joints_off=(2,))
    q, dq = _dense(path)
    assert path.method.startswith("joint space")
    np.testing.assert_allclose(q[:, 1], q0[1])  # joint 2 is not driven: the plan leaves it
    np.testing.assert_allclose(dq[:, 1], 0.0)
    np.testing.assert_allclose(q[-1, [0, 2, 3]], REST[[0, 2, 3]], atol=1e-9)
    assert np.abs(dq).max() <= DEFAULT_LOWERING_SPEED_RAD_S * 1.001


def test_an_arm_outside_the_pilot_s_range_is_brought_back_never_farther_out() -> None:
    """After an ISB fault the arm is beyond the limit: the lowering may start there, it may not go farther."""
    q0 = SHOULDER.q_from_isb(np.deg2rad([40.0, 60.0, 0.0, 70.0]))
    narrow = IsbLimits(elbow=AngleRange(lower_deg=5.0, upper_deg=60.0))  # the elbow 10 deg beyond its limit
    path = plan_lowering(q0, REST, SHOULDER, (), narrow, 0.0)
    q, _ = _dense(path)
    elbow = np.degrees(q[:, 3])
    assert elbow[0] == pytest.approx(70.0)
    assert np.all(np.diff(elbow) <= 1e-6)  # only ever back toward the range (the pieces' round-off aside)


def test_a_lowering_that_would_leave_the_range_is_refused_with_the_reason() -> None:
    """A rest pose the path can only reach through a forbidden region: refused, never handed to the tick."""
    tight = IsbLimits(axial_rotation=AngleRange(lower_deg=-2.0, upper_deg=2.0))
    held = SHOULDER.q_from_isb(np.deg2rad([30.0, 60.0, 10.0, 70.0]))  # held 8 deg beyond the axial limit
    plan_lowering(held, SHOULDER.q_from_isb(np.deg2rad([10.0, 60.0, 0.0, 30.0])), SHOULDER, (), tight, 0.0)  # back in
    farther = SHOULDER.q_from_isb(np.deg2rad([30.0, 60.0, 30.0, 70.0]))
    with pytest.raises(LoweringError, match="ISB limits"):
        plan_lowering(held, farther, SHOULDER, (), tight, 0.0)


def test_non_finite_poses_and_speeds_are_refused() -> None:
    with pytest.raises(LoweringError, match="not finite"):
        plan_lowering(np.array([0.0, np.nan, 0.0, 0.0]), REST, SHOULDER)
    with pytest.raises(LoweringError, match="speed"):
        plan_lowering(REST + 0.1, REST, SHOULDER, speed_rad_s=0.0)


def test_an_arm_at_its_rest_pose_needs_no_motion() -> None:
    path = plan_lowering(REST, REST, SHOULDER)
    assert path.duration_s == 0.0
    q, dq = path.reference(5.0)
    np.testing.assert_allclose(q, REST)
    np.testing.assert_allclose(dq, 0.0)
