"""The safety monitor on hand-made samples: every check, latching, clearing and the command filter."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from daror_runtime.errors import ConfigurationError
from daror_runtime.safety.faults import FaultKind
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from hal.interface import Command, DriveState, Sample
from hal.robot import RobotDescription, load_description

DESCRIPTION = load_description()
LIMITS = SafetyLimits.from_description(DESCRIPTION, command_limit_nm=10.0)
SAFE_Q = np.array([0.1, 0.3, -0.2, 1.0])


def sample(seq: int = 1, **changes: object) -> Sample:
    base = Sample(
        seq=seq,
        t_s=seq * 1e-3,
        q_rad=SAFE_Q.copy(),
        dq_rad_s=np.zeros(4),
        theta_rad=SAFE_Q + 0.01,
        tau_nm=np.full(4, 2.89),
        estop=(False, False),
        drives=(DriveState.ENABLED,) * 4,
    )
    return base._replace(**changes)


def with_joint(field: str, joint: int, value: float, seq: int = 2) -> Sample:
    s = sample(seq)
    array = getattr(s, field).copy()
    array[joint - 1] = value
    return s._replace(**{field: array})


def fresh_monitor() -> SafetyMonitor:
    monitor = SafetyMonitor(LIMITS)
    assert monitor.check(sample(1)) == []
    return monitor


@pytest.mark.parametrize(
    ("field", "joint", "value", "kind"),
    [
        ("q_rad", 2, np.deg2rad(125.0), FaultKind.JOINT_LIMIT),  # joint 2 ends at 120 deg
        ("dq_rad_s", 4, 3.5, FaultKind.VELOCITY),
        ("tau_nm", 1, -31.0, FaultKind.TORQUE),
        ("theta_rad", 3, -0.2 + 0.2, FaultKind.DEFLECTION),  # theta - q = 0.4 rad beyond 0.108
        ("q_rad", 1, float("nan"), FaultKind.NOT_FINITE),
        ("tau_nm", 3, float("inf"), FaultKind.NOT_FINITE),
    ],
)
def test_each_bound_is_checked_and_named(field: str, joint: int, value: float, kind: FaultKind) -> None:
    monitor = fresh_monitor()
    faults = monitor.check(with_joint(field, joint, value))
    assert [f.kind for f in faults] == [kind] or kind in {f.kind for f in faults}
    fault = next(f for f in faults if f.kind == kind)
    assert fault.joint == joint
    assert f"joint {joint}" in fault.message
    assert monitor.faulted
    assert monitor.filter(Command(np.ones(4), True), sample(3)).enable is False


def moved(joint: int, delta_rad: float, seq: int = 2) -> Sample:
    """The robot moved ``joint`` by ``delta_rad``, spring deflection unchanged."""
    s = sample(seq)
    step = np.zeros(4)
    step[joint - 1] = delta_rad
    return s._replace(q_rad=s.q_rad + step, theta_rad=s.theta_rad + step)


def test_a_jump_between_samples_is_implausible() -> None:
    monitor = fresh_monitor()
    assert monitor.check(moved(3, 0.04)) == []  # 40 mrad in one tick is within the 50 mrad bound
    faults = monitor.check(moved(3, 0.2, seq=3))
    assert {f.kind for f in faults} == {FaultKind.JUMP}
    assert faults[0].joint == 3
    assert "jump" in faults[0].message


def test_stale_samples_fault_after_the_configured_count() -> None:
    monitor = fresh_monitor()
    repeated = sample(1)
    for _ in range(LIMITS.stale_ticks - 1):
        assert monitor.check(repeated) == []
    faults = monitor.check(repeated)
    assert [f.kind for f in faults] == [FaultKind.STALE]


def test_estop_and_drive_faults() -> None:
    monitor = fresh_monitor()
    faults = monitor.check(sample(2, estop=(False, True)))
    assert [f.kind for f in faults] == [FaultKind.ESTOP]
    assert "pilot" in faults[0].message
    monitor = fresh_monitor()
    drives = (DriveState.ENABLED, DriveState.FAULT, DriveState.ENABLED, DriveState.ENABLED)
    faults = monitor.check(sample(2, drives=drives, drive_fault_codes=(0, 0x2310, 0, 0)))
    assert [(f.kind, f.joint) for f in faults] == [(FaultKind.DRIVE, 2)]
    assert "0x2310" in faults[0].message


def test_a_held_condition_is_reported_once_and_clears_only_when_gone() -> None:
    monitor = fresh_monitor()
    pressed = [monitor.check(sample(seq, estop=(True, False))) for seq in range(2, 7)]
    assert [len(f) for f in pressed] == [1, 0, 0, 0, 0]
    assert monitor.clear() != []  # still pressed: stays latched
    assert monitor.faulted
    monitor.check(sample(7))
    assert monitor.clear() == []
    assert not monitor.faulted
    assert monitor.filter(Command(np.full(4, 3.0), True), sample(8)).enable


def test_reported_faults_latch_until_cleared() -> None:
    monitor = fresh_monitor()
    fault = monitor.report(FaultKind.HAL, 0.5, "bus off")
    assert fault is not None
    assert fault.kind == FaultKind.HAL
    assert monitor.faulted
    monitor.begin_tick()
    monitor.check(sample(2))
    assert monitor.clear() == [fault], "reported in the tick before: it may still hold"
    monitor.begin_tick()  # a whole tick without the report
    monitor.check(sample(3))
    assert monitor.clear() == []


def test_the_filter_clips_to_the_state_limit_and_refuses_non_finite_commands() -> None:
    monitor = fresh_monitor()
    out = monitor.filter(Command(np.array([20.0, -20.0, 5.0, 0.0]), True), sample(2))
    assert out.enable
    assert out.motor_torque_nm.tolist() == [10.0, -10.0, 5.0, 0.0]
    out = monitor.filter(Command(np.array([0.0, np.nan, 0.0, 0.0]), True), sample(3))
    assert not out.enable
    assert [f.kind for f in monitor.latched] == [FaultKind.SOFTWARE]
    assert monitor.filter(Command(np.ones(4), True), None).enable is False  # no sample, no torque


def test_isb_limits_are_checked_with_the_given_function() -> None:
    class Limits:
        lower_rad = np.deg2rad([0.0, -30.0, -45.0, 5.0])
        upper_rad = np.deg2rad([90.0, 90.0, 45.0, 120.0])

    pose = {"isb": np.deg2rad([30.0, 10.0, 0.0, 60.0])}

    def isb(q: np.ndarray) -> np.ndarray:
        return pose["isb"]  # stand-in for hal.isb: the pilot's pose, set by the test

    monitor = SafetyMonitor(LIMITS.with_isb(Limits()), isb_angles=isb)  # type: ignore[arg-type]
    assert monitor.check(sample(1)) == []
    pose["isb"] = np.deg2rad([30.0, 10.0, -50.0, 60.0])
    faults = monitor.check(sample(2))
    assert [f.kind for f in faults] == [FaultKind.ISB_LIMIT]
    assert "axial rotation -50.0 deg" in faults[0].message
    with pytest.raises(ConfigurationError):
        SafetyMonitor(LIMITS.with_isb(Limits()))  # type: ignore[arg-type]


finite_or_not = st.one_of(st.floats(-50, 50), st.sampled_from([float("nan"), float("inf"), -float("inf")]))


@given(
    field=st.sampled_from(["q_rad", "dq_rad_s", "tau_nm", "theta_rad"]),
    joint=st.integers(1, 4),
    value=finite_or_not,
)
def test_torque_is_off_whenever_a_signal_is_out_of_bounds(field: str, joint: int, value: float) -> None:
    monitor = fresh_monitor()
    s = with_joint(field, joint, value)
    monitor.check(s)
    signals = np.concatenate([s.q_rad, s.dq_rad_s, s.tau_nm, s.theta_rad - s.q_rad, s.q_rad - SAFE_Q])
    lower = np.concatenate(
        [
            LIMITS.joint_lower_rad,
            -LIMITS.max_velocity_rad_s,
            -LIMITS.max_spring_torque_nm,
            [-LIMITS.max_deflection_rad] * 4,
            [-LIMITS.max_jump_rad] * 4,
        ]
    )
    upper = -lower
    upper[:4] = LIMITS.joint_upper_rad
    violated = not np.all((signals >= lower) & (signals <= upper))
    out = monitor.filter(Command(np.ones(4), True), s)
    assert out.enable is (not violated)
    assert monitor.faulted is violated


def test_limits_from_description(description: RobotDescription) -> None:
    limits = SafetyLimits.from_description(description)
    assert limits.command_limit_nm.tolist() == [40.0] * 4
    assert limits.max_deflection_rad == pytest.approx(0.108)
