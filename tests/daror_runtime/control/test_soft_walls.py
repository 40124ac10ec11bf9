"""Soft walls before the device's joint limits and the pilot's ISB limits (daror_runtime/control/soft_walls.py).

Unit physics first (no torque away from the walls, a continuous force, the spring part the negative
gradient of the potential, a damper that only resists motion toward a limit, the cost of a call),
then the closed loop on the simulated plant: a limp pilot's arm pushed by a constant model error
stops before the pilot's limit with the walls and faults the monitor without them.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from numba.core.runtime import _nrt_python, rtsys

from daror_runtime.control.base import ControlError, ControlSettingError
from daror_runtime.control.sea_torque import SeaTorqueController
from daror_runtime.control.soft_walls import (
    CORNER_ROUNDING,
    DAMPING_FADE,
    DEFAULT_DAMPING_NMS_PER_RAD,
    DEFAULT_MAX_TORQUE_NM,
    DEFAULT_ONSET_DEG,
    DEFAULT_STIFFNESS_NM_PER_RAD,
    SoftWalls,
)
from daror_runtime.errors import ShapeError
from daror_runtime.safety.faults import FaultKind
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from hal.interface import CheckedSample, Command, DriveState, Sample
from hal.isb import AngleRange, IsbLimits, Shoulder, default_shoulder, monitor_isb_function
from hal.robot import N_JOINTS, FloatArray, RobotDescription, load_description
from hal.sim.backend import SimHal

ONSET_RAD = math.radians(DEFAULT_ONSET_DEG)
K_NM_PER_RAD = DEFAULT_STIFFNESS_NM_PER_RAD
C_NMS_PER_RAD = DEFAULT_DAMPING_NMS_PER_RAD
FADE_RAD = DAMPING_FADE * ONSET_RAD
ROUND_RAD = CORNER_ROUNDING * ONSET_RAD
#: The session's ISB margin: the monitor faults at the recorded limit + this.
MARGIN_RAD = math.radians(5.0)

DEFAULT_LIMITS = IsbLimits()
#: Narrower limits, with an elevation lower limit above 0 (its wall exists) and another threshold.
TIGHT_LIMITS = IsbLimits(
    elevation=AngleRange(lower_deg=10.0, upper_deg=80.0),
    horizontal_rotation=AngleRange(lower_deg=0.0, upper_deg=120.0),
    axial_rotation=AngleRange(lower_deg=-40.0, upper_deg=40.0),
    elbow=AngleRange(lower_deg=20.0, upper_deg=100.0),
    horizontal_free_below_deg=30.0,
)
LIMIT_SETS = {"none": None, "default": DEFAULT_LIMITS, "tight": TIGHT_LIMITS}

#: The home pose of the simulated plant (ISB 0, 0, 0, 30 deg).
HOME_Q_RAD = np.radians([-20.25, 82.41, -30.27, 30.0])


@pytest.fixture(scope="module")
def description() -> RobotDescription:
    return load_description()


@pytest.fixture(scope="module")
def shoulder() -> Shoulder:
    return default_shoulder()


@pytest.fixture(scope="module")
def walls_for(description: RobotDescription, shoulder: Shoulder) -> Callable[[str], SoftWalls]:
    """One :class:`SoftWalls` per limit set of :data:`LIMIT_SETS`, built once."""
    built: dict[str, SoftWalls] = {}

    def get(name: str) -> SoftWalls:
        if name not in built:
            walls = SoftWalls(description, shoulder)
            walls.set_limits(LIMIT_SETS[name])
            built[name] = walls
        return built[name]

    return get


def wrap(angle: FloatArray) -> FloatArray:
    return np.pi - np.mod(np.pi - np.asarray(angle), 2.0 * np.pi)


def torque(walls: SoftWalls, q: FloatArray, dq: FloatArray | None = None) -> FloatArray:
    out = np.zeros(N_JOINTS)
    walls.torque(np.asarray(q, dtype=float), np.zeros(N_JOINTS) if dq is None else np.asarray(dq, dtype=float), out)
    return out


def joint_box(description: RobotDescription, inset_rad: float = 0.0) -> st.SearchStrategy[FloatArray]:
    lower, upper = description.lower_limits_rad + inset_rad, description.upper_limits_rad - inset_rad
    return st.tuples(*(st.floats(float(lo), float(hi)) for lo, hi in zip(lower, upper, strict=True))).map(np.array)


DESCRIPTION = load_description()
ANY_Q = joint_box(DESCRIPTION)
VELOCITY = st.tuples(*(st.floats(-1.0, 1.0) for _ in range(N_JOINTS))).map(np.array)


#: "Inside the limits minus the onset", by a hair: exactly at the onset, round-off decides.
INSET_RAD = ONSET_RAD + 1e-9


def isb_inside_minus_onset(isb: FloatArray, limits: IsbLimits) -> bool:
    """True where no ISB wall may act: every angle ``onset`` inside its limits, and the horizontal
    rotation either ``onset`` below its free threshold or ``onset / s`` inside its limits (s = sin(e_free))."""
    e, h, a, elbow = isb
    lo, hi = limits.lower_rad, limits.upper_rad
    if e > hi[0] - INSET_RAD or (lo[0] > 0.0 and e < lo[0] + INSET_RAD):
        return False
    if not lo[2] + INSET_RAD <= a <= hi[2] - INSET_RAD or not lo[3] + INSET_RAD <= elbow <= hi[3] - INSET_RAD:
        return False
    free = limits.horizontal_free_below_rad
    if e <= free - INSET_RAD:
        return True
    inside = min(wrap(h - lo[1]), wrap(hi[1] - h))  # angular distance inside the nearest limit
    return bool(math.sin(free) * inside >= INSET_RAD and lo[1] <= h <= hi[1])


# --- the walls' kinematics ----------------------------------------------------------------------------


@given(q=ANY_Q)
def test_isb_angles_and_jacobian_match_central_differences_of_the_shoulder(
    q: FloatArray, walls_for: Callable[[str], SoftWalls], shoulder: Shoulder
) -> None:
    expected = shoulder.isb_single(q)
    assume(math.radians(3.0) < expected[0] < math.radians(170.0))  # the horizontal rotation is defined
    assume(shoulder.sigma_min(q) > 0.05)
    isb, jac = walls_for("default").isb_and_jacobian(q)
    assert np.abs(wrap(isb - expected)).max() < 1e-12
    step = 1e-6
    numeric = np.empty((N_JOINTS, N_JOINTS))
    for j in range(N_JOINTS):
        dq = np.zeros(N_JOINTS)
        dq[j] = step
        numeric[:, j] = wrap(shoulder.isb_single(q + dq) - shoulder.isb_single(q - dq)) / (2.0 * step)
    assert np.abs(jac - numeric).max() < 1e-6 * (1.0 + np.abs(numeric).max())


# --- no torque away from the walls --------------------------------------------------------------------


@given(q=joint_box(DESCRIPTION, INSET_RAD), dq=VELOCITY)
def test_no_torque_onset_inside_the_joint_limits_without_isb_limits(
    q: FloatArray, dq: FloatArray, walls_for: Callable[[str], SoftWalls]
) -> None:
    out = np.full(N_JOINTS, np.nan)
    assert walls_for("none").torque(q, dq, out) is False
    assert np.array_equal(out, np.zeros(N_JOINTS))


@given(
    name=st.sampled_from(["default", "tight"]),
    below_free=st.booleans(),
    fractions=st.tuples(*(st.floats(0.0, 1.0) for _ in range(N_JOINTS))),
    h_anywhere=st.floats(-math.pi, math.pi),
    dq=VELOCITY,
)
def test_no_torque_onset_inside_every_limit(
    name: str,
    below_free: bool,
    fractions: tuple[float, float, float, float],
    h_anywhere: float,
    dq: FloatArray,
    walls_for: Callable[[str], SoftWalls],
    shoulder: Shoulder,
    description: RobotDescription,
) -> None:
    """Poses drawn inside the pilot's limits minus the onset, solved for q: no torque, none acts."""
    limits = LIMIT_SETS[name]
    assert limits is not None
    lo, hi = limits.lower_rad, limits.upper_rad
    free = limits.horizontal_free_below_rad
    e_lo = lo[0] + INSET_RAD if lo[0] > 0.0 else 0.0
    e_hi = min(hi[0] - INSET_RAD, free - INSET_RAD) if below_free else hi[0] - INSET_RAD
    if not below_free:
        e_lo = max(e_lo, free - INSET_RAD)
    h_inset = INSET_RAD / math.sin(free)
    f = fractions
    pose = np.array(
        [
            e_lo + f[0] * (e_hi - e_lo),
            h_anywhere if below_free else lo[1] + h_inset + f[1] * (hi[1] - lo[1] - 2.0 * h_inset),
            lo[2] + INSET_RAD + f[2] * (hi[2] - lo[2] - 2.0 * INSET_RAD),
            lo[3] + INSET_RAD + f[3] * (hi[3] - lo[3] - 2.0 * INSET_RAD),
        ]
    )
    q = shoulder.q_from_isb(pose, unreachable_as_nan=True)
    assume(np.all(np.isfinite(q)))
    assume(
        np.all(q > description.lower_limits_rad + INSET_RAD) and np.all(q < description.upper_limits_rad - INSET_RAD)
    )
    assume(isb_inside_minus_onset(shoulder.isb_single(q), limits))  # the angles q really has (after clipping)
    out = np.full(N_JOINTS, np.nan)
    assert walls_for(name).torque(q, dq, out) is False
    assert np.array_equal(out, np.zeros(N_JOINTS))


# --- the force is continuous ----------------------------------------------------------------------------

#: A force step of 0.01 Nm across a 2e-6 rad move would show as 5000 Nm/rad; the smooth field stays
#: far below this bound (stiffness 15 Nm/rad times the Jacobian's square, plus its curvature).
LIPSCHITZ_NM_PER_RAD = 1000.0


def switch_pose(family: str, t: float, limits: IsbLimits) -> FloatArray:
    """An ISB pose exactly on a surface where a wall's formula switches, ``t`` in [0, 1] along it."""
    free = limits.horizontal_free_below_rad
    s = math.sin(free)
    h_lo = limits.horizontal_rotation.lower_rad
    span = math.radians(25.0)
    e_near = free - math.radians(10.0) + t * span  # across the free threshold
    h_near = h_lo - math.radians(40.0) + t * math.radians(55.0)  # across the lower horizontal limit
    e, h = {
        "elevation onset, h out of range": (free - ONSET_RAD, h_lo - math.radians(20.0) - t * math.radians(60.0)),
        "free threshold": (free, h_near),
        "horizontal limit": (e_near, h_lo),
        "horizontal onset": (e_near, h_lo + ONSET_RAD / s),
        "inner quadrant, elevation edge": (free + ROUND_RAD, h_near),
        "inner quadrant, horizontal edge": (e_near, h_lo - ROUND_RAD / s),
        # into the region along its diagonal, from its corner to the monitor's margin
        "diagonal from the corner": (free + t * s * MARGIN_RAD, h_lo - t * MARGIN_RAD),
        "elbow onset": (math.radians(30.0) + t * math.radians(30.0), math.radians(60.0)),
    }[family]
    elbow = limits.elbow.lower_rad + ONSET_RAD if family == "elbow onset" else math.radians(60.0)
    return np.array([e, h, 0.0, elbow])


@given(
    family=st.sampled_from(
        [
            "elevation onset, h out of range",
            "free threshold",
            "horizontal limit",
            "horizontal onset",
            "inner quadrant, elevation edge",
            "inner quadrant, horizontal edge",
            "diagonal from the corner",
            "elbow onset",
        ]
    ),
    t=st.floats(0.0, 1.0),
    name=st.sampled_from(["default", "tight"]),
    steps=st.tuples(*(st.floats(-1e-6, 1e-6) for _ in range(2 * N_JOINTS))),
    dq=VELOCITY,
)
def test_force_is_continuous_across_the_onset_and_the_horizontal_branches(
    family: str,
    t: float,
    name: str,
    steps: tuple[float, ...],
    dq: FloatArray,
    walls_for: Callable[[str], SoftWalls],
    shoulder: Shoulder,
) -> None:
    """Two configurations a few 1e-6 rad apart on either side of a switch: the torques differ by
    at most the Lipschitz bound times their distance (spring and damper, at any velocity)."""
    limits = LIMIT_SETS[name]
    assert limits is not None
    pose = switch_pose(family, t, limits)
    if family.startswith("inner quadrant"):
        # The corner of the inner quadrant (rho beyond both edges, past the monitor's margin) is the
        # one point where the force has no direction (see the module's docstring): not this test's.
        corner = (limits.horizontal_free_below_rad + ROUND_RAD, limits.horizontal_rotation.lower_rad)
        s = math.sin(limits.horizontal_free_below_rad)
        assume(math.hypot(pose[0] - corner[0], s * (pose[1] - corner[1]) + ROUND_RAD) > math.radians(1.0))
    q0 = shoulder.q_from_isb(pose, unreachable_as_nan=True)
    assume(np.all(np.isfinite(q0)))
    walls = walls_for(name)
    a, b = q0 + np.array(steps[:N_JOINTS]), q0 + np.array(steps[N_JOINTS:])
    change = np.abs(torque(walls, a, dq) - torque(walls, b, dq)).max()
    assert change <= LIPSCHITZ_NM_PER_RAD * np.abs(a - b).max() + 1e-12


# Poses drawn inside the pilot's limits + margin are about half reachable: filtering is expected.
@settings(suppress_health_check=[HealthCheck.filter_too_much])
@given(
    name=st.sampled_from(["default", "tight"]),
    fractions=st.tuples(*(st.floats(0.0, 1.0) for _ in range(N_JOINTS))),
    h_anywhere=st.floats(-math.pi, math.pi),
    dq=VELOCITY,
    direction=VELOCITY,
)
def test_small_moves_give_small_torque_changes_anywhere_before_the_fault(
    name: str,
    fractions: tuple[float, float, float, float],
    h_anywhere: float,
    dq: FloatArray,
    direction: FloatArray,
    walls_for: Callable[[str], SoftWalls],
    shoulder: Shoulder,
) -> None:
    """The same bound anywhere the monitor does not fault yet (ISB limits + margin), the arm off
    the pole (where the horizontal rotation, and the direction of its wall, is undefined)."""
    limits = LIMIT_SETS[name]
    assert limits is not None
    lower, upper = limits.lower_rad - MARGIN_RAD, limits.upper_rad + MARGIN_RAD
    lower[0] = max(lower[0], math.radians(2.0))
    pose = lower + np.array(fractions) * (upper - lower)
    if pose[0] < limits.horizontal_free_below_rad:
        pose[1] = h_anywhere  # not limited there
    q = shoulder.q_from_isb(pose, unreachable_as_nan=True)
    assume(np.all(np.isfinite(q)))
    checked = monitor_isb_function(shoulder, limits)(q)
    assume(np.all(checked >= lower) and np.all(checked <= upper))
    walls = walls_for(name)
    step = 1e-6 * direction
    change = np.abs(torque(walls, q + step, dq) - torque(walls, q, dq)).max()
    assert change <= LIPSCHITZ_NM_PER_RAD * np.abs(step).max() + 1e-12


# --- the spring is a potential; the damper only resists --------------------------------------------------


@given(q=ANY_Q, name=st.sampled_from(["none", "default", "tight"]))
def test_spring_torque_is_the_negative_gradient_of_the_potential(
    q: FloatArray, name: str, walls_for: Callable[[str], SoftWalls]
) -> None:
    walls = walls_for(name)
    tau = torque(walls, q)
    assume(np.any(tau != 0.0))
    assume(np.abs(tau).max() < DEFAULT_MAX_TORQUE_NM - 1e-6)  # where the cap clips, it is not a gradient
    step = 1e-6
    gradient = np.empty(N_JOINTS)
    for j in range(N_JOINTS):
        dq = np.zeros(N_JOINTS)
        dq[j] = step
        gradient[j] = (walls.energy_j(q + dq) - walls.energy_j(q - dq)) / (2.0 * step)
    assert np.abs(tau + gradient).max() < 1e-5 * (1.0 + np.abs(tau).max())


@given(q=ANY_Q, dq=VELOCITY, name=st.sampled_from(["none", "default", "tight"]))
def test_the_damper_only_takes_energy_out(
    q: FloatArray, dq: FloatArray, name: str, walls_for: Callable[[str], SoftWalls]
) -> None:
    """The velocity-dependent part of the torque never does positive work on the arm."""
    walls = walls_for(name)
    spring, both = torque(walls, q), torque(walls, q, dq)
    assume(np.abs(both).max() < DEFAULT_MAX_TORQUE_NM and np.abs(spring).max() < DEFAULT_MAX_TORQUE_NM)
    assert float((both - spring) @ dq) <= 1e-12


@given(
    penetration=st.floats(1e-6, ONSET_RAD - math.radians(0.5)),
    speed=st.floats(1e-3, 2.0),
)
def test_elbow_wall_numbers_spring_and_a_damper_only_toward_the_limit(
    penetration: float, speed: float, walls_for: Callable[[str], SoftWalls]
) -> None:
    """One wall alone (the pilot's elbow limit, home shoulder pose): k p; the damper c w(p) |dq|
    only while the elbow extends toward the limit, faded in over the first half of the onset."""
    q = HOME_Q_RAD.copy()
    q[3] = DEFAULT_LIMITS.elbow.lower_rad + ONSET_RAD - penetration  # the device's wall (5 deg lower) is farther
    walls = walls_for("default")
    spring = torque(walls, q)
    assert spring == pytest.approx([0.0, 0.0, 0.0, K_NM_PER_RAD * penetration], abs=1e-12)
    leaving = torque(walls, q, np.array([0.0, 0.0, 0.0, speed]))
    assert np.array_equal(leaving, spring)
    toward = torque(walls, q, np.array([0.0, 0.0, 0.0, -speed]))
    fade = min(penetration / FADE_RAD, 1.0)
    assert toward[3] - spring[3] == pytest.approx(C_NMS_PER_RAD * fade * speed, rel=1e-9, abs=1e-12)
    assert np.array_equal(toward[:3], np.zeros(3))


@given(e_deg=st.floats(12.5, 19.5), h_deg=st.floats(-100.0, -40.0), speed=st.floats(1e-3, 1.0))
def test_rising_behind_the_body_the_wall_pushes_down_and_damps_only_the_rise(
    e_deg: float, h_deg: float, speed: float, walls_for: Callable[[str], SoftWalls], shoulder: Shoulder
) -> None:
    """Below the free threshold with the horizontal rotation out of range, the only wall is an
    elevation wall: its torque lowers the arm (k p), and moving along it (leaving) adds no damping,
    against it adds damping along the same direction."""
    q = shoulder.q_from_isb(np.radians([e_deg, h_deg, 0.0, 60.0]), seed=HOME_Q_RAD, unreachable_as_nan=True)
    assume(np.all(np.isfinite(q)))
    assume(
        np.all(q > DESCRIPTION.lower_limits_rad + ONSET_RAD) and np.all(q < DESCRIPTION.upper_limits_rad - ONSET_RAD)
    )
    walls = walls_for("default")
    spring = torque(walls, q)
    _, jac = walls.isb_and_jacobian(q)
    penetration = ONSET_RAD - (DEFAULT_LIMITS.horizontal_free_below_rad - math.radians(e_deg))
    # The torque is -k p grad(elevation): its elevation "push", grad(e) . tau / |grad(e)|^2, is -k p.
    grad_e = jac[0]
    assert float(grad_e @ spring) / float(grad_e @ grad_e) == pytest.approx(-K_NM_PER_RAD * penetration, rel=1e-6)
    along = spring / np.linalg.norm(spring)
    assert np.array_equal(torque(walls, q, speed * along), spring)
    extra = torque(walls, q, -speed * along) - spring
    assert float(extra @ along) > 0.0
    assert np.linalg.norm(extra - (extra @ along) * along) < 1e-9 * (1.0 + np.linalg.norm(extra))


@given(
    above_deg=st.floats(5.0, 40.0),
    inside=st.floats(0.0, 1.0),
    lower_side=st.booleans(),
    name=st.sampled_from(["default", "tight"]),
)
def test_above_the_free_elevation_the_horizontal_wall_starts_onset_over_sin_free_inside(
    above_deg: float,
    inside: float,
    lower_side: bool,
    name: str,
    walls_for: Callable[[str], SoftWalls],
    shoulder: Shoulder,
) -> None:
    """Above ``e_free`` (by more than the corner's rounding) the region's wall is the horizontal
    edge: distance ``s v`` with ``s = sin(e_free)``, so it starts ``onset / s`` inside the limit
    (23 deg at the defaults) and pushes the horizontal rotation back with ``k p s`` (p = onset - s v)."""
    limits = LIMIT_SETS[name]
    assert limits is not None
    free = limits.horizontal_free_below_rad
    s = math.sin(free)
    v = inside * ONSET_RAD / s  # angular distance inside the limit, rad
    rng = limits.horizontal_rotation
    h = rng.lower_rad + v if lower_side else rng.upper_rad - v
    pose = np.array([free + math.radians(above_deg), h, 0.0, math.radians(60.0)])
    assume(pose[0] < limits.elevation.upper_rad - ONSET_RAD)
    q = shoulder.q_from_isb(pose, unreachable_as_nan=True)
    assume(np.all(np.isfinite(q)))
    assume(
        np.all(q > DESCRIPTION.lower_limits_rad + ONSET_RAD) and np.all(q < DESCRIPTION.upper_limits_rad - ONSET_RAD)
    )
    walls = walls_for(name)
    tau = torque(walls, q)
    _, jac = walls.isb_and_jacobian(q)
    grad_h = jac[1]
    push = float(grad_h @ tau) / float(grad_h @ grad_h)  # along the horizontal rotation, Nm per rad of h
    expected = K_NM_PER_RAD * (ONSET_RAD - s * v) * s
    assert push == pytest.approx(expected if lower_side else -expected, rel=1e-6, abs=1e-9)


def test_a_constant_error_of_1_nm_rests_before_the_limit_and_far_before_the_fault(
    walls_for: Callable[[str], SoftWalls],
) -> None:
    """Statics of the defaults: the elbow's wall balances 1 Nm 3.8 deg into itself, 4.2 deg before
    the recorded limit, 9.2 deg before the monitor's fault (required: before limit + half the margin)."""
    walls = walls_for("default")
    lower = DEFAULT_LIMITS.elbow.lower_rad
    lo, hi = lower - MARGIN_RAD, lower + ONSET_RAD  # torque(lo) > 1 Nm > torque(hi) = 0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        q = HOME_Q_RAD.copy()
        q[3] = mid
        lo, hi = (mid, hi) if torque(walls, q)[3] > 1.0 else (lo, mid)
    rest_rad = 0.5 * (lo + hi)
    assert math.degrees(rest_rad - lower) == pytest.approx(
        DEFAULT_ONSET_DEG - math.degrees(1.0 / K_NM_PER_RAD), abs=1e-6
    )
    assert rest_rad - lower > math.radians(4.0)


# --- settings, inputs, cost ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "setting",
    [
        {"onset_deg": 0.0},
        {"onset_deg": math.nan},
        {"stiffness_nm_per_rad": -1.0},
        {"stiffness_nm_per_rad": math.inf},
        {"damping_nms_per_rad": -0.1},
        {"max_torque_nm": 0.0},
        {"max_torque_nm": True},
    ],
)
def test_refuses_settings_that_are_not_positive_and_finite(
    setting: dict[str, float], description: RobotDescription, shoulder: Shoulder
) -> None:
    with pytest.raises(ControlSettingError):
        SoftWalls(description, shoulder, **setting)


def test_refuses_bad_inputs_and_leaves_out_untouched(walls_for: Callable[[str], SoftWalls]) -> None:
    walls = walls_for("default")
    out = np.full(N_JOINTS, 7.0)
    bad = HOME_Q_RAD.copy()
    bad[2] = np.nan
    with pytest.raises(ControlError):
        walls.torque(bad, np.zeros(N_JOINTS), out)
    with pytest.raises(ShapeError):
        walls.torque(HOME_Q_RAD[:3], np.zeros(N_JOINTS), out)
    with pytest.raises(ShapeError):
        walls.torque(HOME_Q_RAD, np.zeros(N_JOINTS), np.zeros(3))
    with pytest.raises(ShapeError):
        walls.torque(HOME_Q_RAD.astype(np.float32), np.zeros(N_JOINTS), out)
    assert np.array_equal(out, np.full(N_JOINTS, 7.0))


@numba.njit
def _six_arrays(q, dq, params, mats, vec, out):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    return 0


def test_cost_per_call_and_no_allocation(
    walls_for: Callable[[str], SoftWalls], record_property: Callable[[str, object], None]
) -> None:
    """Far from every wall (the common case) and near one: the time per call (reported, not
    asserted), and no allocation: numba's memory records are only those its unboxing of the six
    array arguments makes for any compiled call (counted on an empty kernel), no Python object outlives the call."""
    walls = walls_for("default")
    far = HOME_Q_RAD
    near = HOME_Q_RAD.copy()
    near[3] = math.radians(10.0)
    dq = np.zeros(N_JOINTS)
    out = np.zeros(N_JOINTS)
    assert walls.torque(far, dq, out) is False
    assert walls.torque(near, dq, out) is True
    calls = 20000
    for label, q in (("far", far), ("near", near)):
        start = time.perf_counter()
        for _ in range(calls):
            walls.torque(q, dq, out)
        record_property(f"soft_walls_us_per_call_{label}", 1e6 * (time.perf_counter() - start) / calls)
    params, mats, vec = np.zeros(28), np.zeros((9, 3, 3)), np.zeros(14)  # arrays like the kernel's own
    _six_arrays(far, dq, params, mats, vec, out)
    _nrt_python.memsys_enable_stats()
    try:
        for q in (far, near):
            before = rtsys.get_allocation_stats().alloc
            for _ in range(100):
                walls.torque(q, dq, out)
            used = rtsys.get_allocation_stats().alloc - before
            before = rtsys.get_allocation_stats().alloc
            for _ in range(100):
                _six_arrays(q, dq, params, mats, vec, out)
            baseline = rtsys.get_allocation_stats().alloc - before
            assert used == baseline
    finally:
        _nrt_python.memsys_disable_stats()
    blocks = sys.getallocatedblocks()
    for _ in range(1000):
        walls.torque(far, dq, out)
    assert sys.getallocatedblocks() - blocks <= 2  # nothing kept per call (a few blocks of interpreter noise)


def test_isb_limits_can_be_removed_between_ticks(description: RobotDescription, shoulder: Shoulder) -> None:
    walls = SoftWalls(description, shoulder)
    q = HOME_Q_RAD.copy()
    q[3] = math.radians(10.0)  # inside the pilot's elbow wall, far from the device's
    walls.set_limits(DEFAULT_LIMITS)
    assert torque(walls, q)[3] == pytest.approx(K_NM_PER_RAD * math.radians(3.0))
    walls.set_limits(None)
    assert np.array_equal(torque(walls, q), np.zeros(N_JOINTS))


# --- closed loop: a limp arm on the simulated plant --------------------------------------------------------


@dataclass(frozen=True)
class Drift:
    """What happened in one run: true ISB angles and joint speeds per tick, the monitor's ISB faults."""

    isb_rad: FloatArray  # (N, 4)
    speed_rad_s: FloatArray  # (N, 4), |dq|
    isb_faults: list[str]
    faults: list[str]
    wall_nm: FloatArray  # (N, 4)


def limp_drift(error_nm: FloatArray, seconds: float, with_walls: bool, limits: IsbLimits = DEFAULT_LIMITS) -> Drift:
    """A limp pilot in compensation with a constant model error, lock-step on ``exo_dummy_arm``.

    The torque reference is the plant's true holding torque plus ``error_nm`` (and the walls'
    torque), delivered by the SEA torque controller as :class:`~daror_runtime.control.modes.Compensation`
    does; the safety monitor checks every sample against ``limits`` with the session's 5 deg margin.
    """
    hal = SimHal("exo_dummy_arm")
    hal.open()
    world = hal.world
    world.seat_pilot()
    world.pilot_carries(0.0)
    world.pilot_stiffness(0.0)
    shoulder = default_shoulder()
    controller = SeaTorqueController(hal.description.sea)
    walls = SoftWalls(hal.description, shoulder)
    walls.set_limits(limits)
    monitor = SafetyMonitor(
        SafetyLimits.from_description(hal.description).with_isb(limits, MARGIN_RAD),
        monitor_isb_function(shoulder, limits),
    )
    dt_s = 1.0 / hal.rate_hz
    controller.reset(hal.read())
    wall = np.zeros(N_JOINTS)
    ticks = int(seconds * hal.rate_hz)
    isb, speed, walls_nm = np.empty((ticks, N_JOINTS)), np.empty((ticks, N_JOINTS)), np.zeros((ticks, N_JOINTS))
    faults: list[str] = []
    for i in range(ticks):
        sample = hal.read()
        faults += [f"{f.kind.value}: {f.message}" for f in monitor.check(sample)]
        reference = hal.plant.holding_torque_nm(sample.q_rad) + error_nm
        if with_walls:
            walls.torque(sample.q_rad, sample.dq_rad_s, wall)
            reference = reference + wall
            walls_nm[i] = wall
        hal.write(Command(controller.motor_torque(reference, sample, dt_s), True))
        truth = hal.truth()
        isb[i] = shoulder.isb_single(truth.q_rad)
        speed[i] = np.abs(truth.dq_rad_s)
    hal.close()
    isb_faults = [f for f in faults if f.startswith(FaultKind.ISB_LIMIT.value)]
    return Drift(isb, speed, isb_faults, faults, walls_nm)


ELBOW_ERROR_NM = np.array([0.0, 0.0, 0.0, -1.0])
#: 1 Nm on joints 2 and 3 (0.8, 0.6): from the home pose the limp arm rises behind the body and,
#: without walls, reaches 20 deg of elevation at a horizontal rotation of -118 deg (the case measured).
BEHIND_ERROR_NM = np.array([0.0, -0.8, -0.6, 0.0])


@pytest.mark.parametrize("with_walls", [True, False], ids=["walls", "no walls"])
def test_limp_elbow_drifting_toward_extension_stops_before_the_pilots_limit(
    with_walls: bool, record_property: Callable[[str, object], None]
) -> None:
    """-1 Nm on the elbow from 30 deg: toward the pilot's 5 deg limit (fault at 0 deg).

    Measured: the free drift runs at 0.59 rad/s (the limp arm's damping, with or without walls);
    with the walls the elbow rests at 9.2 deg, 4.2 deg before the limit, slower than 0.2 rad/s from
    3 deg into the wall on. Without them the monitor faults at 0.94 s.
    """
    drift = limp_drift(ELBOW_ERROR_NM, 2.5, with_walls)
    elbow = drift.isb_rad[:, 3]
    lower = DEFAULT_LIMITS.elbow.lower_rad
    if not with_walls:
        assert elbow.min() < lower - MARGIN_RAD
        assert any(f.startswith("isb_limit: elbow") for f in drift.isb_faults)
        return
    stop_deg = math.degrees(elbow.min() - lower)
    record_property("elbow_stop_before_limit_deg", stop_deg)
    record_property("elbow_peak_speed_rad_s", float(drift.speed_rad_s.max()))
    assert drift.faults == []
    assert stop_deg > 3.0
    deep = elbow < lower + ONSET_RAD - math.radians(3.0)
    assert np.any(deep)
    assert drift.speed_rad_s[deep].max() < 0.2
    assert drift.speed_rad_s[-100:].max() < 0.01  # at rest at the end
    assert np.abs(drift.wall_nm).max() < DEFAULT_MAX_TORQUE_NM


@pytest.mark.parametrize("with_walls", [True, False], ids=["walls", "no walls"])
def test_limp_arm_rising_behind_the_body_stays_below_the_free_elevation(
    with_walls: bool, record_property: Callable[[str, object], None]
) -> None:
    """From the home pose (ISB 0, 0, 0, 30 deg) a 1 Nm error lifts the limp arm behind the body
    (horizontal rotation about -118 deg, outside the pilot's -20..165 deg) toward 20 deg of
    elevation, where the horizontal rotation becomes limited.

    Measured: without walls the monitor faults at 1.24 s ("horizontal rotation -118 deg beyond the
    pilot's limit -25.0 deg", elevation 20 deg). With them the elevation wall stops the rise at
    16.0 deg (4 deg below the threshold, at most 0.18 rad/s on any joint); the arm then slides along
    the wall (the error has a component along it), no fault.
    """
    drift = limp_drift(BEHIND_ERROR_NM, 3.0, with_walls)
    free = DEFAULT_LIMITS.horizontal_free_below_rad
    elevation, horizontal = drift.isb_rad[:, 0], drift.isb_rad[:, 1]
    rising = elevation > math.radians(5.0)
    h_range = DEFAULT_LIMITS.horizontal_rotation
    out_of_range = (horizontal < h_range.lower_rad) | (horizontal > h_range.upper_rad)
    assert np.all(out_of_range[rising])  # behind the body the whole way up: the elevation edge is the wall
    if not with_walls:
        assert elevation.max() >= free
        assert any(f.startswith("isb_limit: horizontal rotation") for f in drift.isb_faults)
        at = int(np.argmax(elevation >= free))
        assert math.degrees(horizontal[at]) == pytest.approx(-118.0, abs=4.0)
        return
    below_deg = math.degrees(free - elevation.max())
    record_property("behind_stop_below_free_deg", below_deg)
    record_property("behind_peak_speed_rad_s", float(drift.speed_rad_s.max()))
    assert drift.faults == []
    assert below_deg > 2.5
    assert drift.speed_rad_s.max() < 0.2
    assert np.abs(drift.wall_nm).max() < DEFAULT_MAX_TORQUE_NM


def test_a_recorded_range_that_starts_at_the_hanging_arm_has_no_wall_under_it() -> None:
    """A range of motion recorded from the hanging arm starts at an elevation of ~0.001 deg: a wall there would push
    the arm resting by the pilot's side up (the demo's rehearsal measured 0.6-1.0 Nm the relaxed pilot had to hold
    against it). Only a lower elevation limit beyond the onset gets a wall."""
    description = load_description()
    shoulder = default_shoulder()
    walls = SoftWalls(description, shoulder)
    recorded = IsbLimits(
        elevation=AngleRange(lower_deg=0.00125, upper_deg=91.4),
        horizontal_rotation=AngleRange(lower_deg=27.0, upper_deg=153.5),
        axial_rotation=AngleRange(lower_deg=-50.9, upper_deg=41.1),
        elbow=AngleRange(lower_deg=9.2, upper_deg=110.8),
    )
    walls.set_limits(recorded)
    out = np.zeros(4)
    hanging = shoulder.q_from_isb(np.deg2rad([0.4, -105.4, 0.2, 29.7]))
    assert not walls.torque(hanging, np.zeros(4), out)
    np.testing.assert_array_equal(out, 0.0)
    # a shoulder that cannot hang straight (its range starts at 20 deg) gets the wall: pushed up at 15 deg
    walls.set_limits(recorded.model_copy(update={"elevation": AngleRange(lower_deg=20.0, upper_deg=91.4)}))
    low = shoulder.q_from_isb(np.deg2rad([15.0, 60.0, 0.0, 30.0]))
    assert walls.torque(low, np.zeros(4), out)
    assert np.any(out != 0.0)


def _sample(q: FloatArray, dq: FloatArray, checked: bool) -> Sample:
    fields = (0, 0.0, q, dq, q.copy(), np.zeros(N_JOINTS), (False, False), (DriveState.ENABLED,) * N_JOINTS)
    return CheckedSample(*fields) if checked else Sample(*fields)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    q=joint_box(DESCRIPTION, -math.radians(3.0)),
    dq=st.lists(st.floats(-2.0, 2.0), min_size=N_JOINTS, max_size=N_JOINTS).map(np.array),
    checked=st.booleans(),
)
def test_the_tick_s_call_gives_the_checked_call_s_torque(
    walls_for: Callable[[str], SoftWalls], q: FloatArray, dq: FloatArray, checked: bool
) -> None:
    """torque_for (a CheckedSample through the kernel's entry point, or any sample) is torque(): None where no wall acts."""
    walls = walls_for("tight")
    expected = np.zeros(N_JOINTS)
    acts = walls.torque(q, dq, expected)
    got = walls.torque_for(_sample(q, dq, checked))
    if not acts:
        assert got is None
    else:
        assert got is not None
        assert np.array_equal(got, expected)


def test_the_tick_s_call_refuses_a_non_finite_reading(walls_for: Callable[[str], SoftWalls]) -> None:
    bad = HOME_Q_RAD.copy()
    bad[1] = np.inf
    for checked in (True, False):
        with pytest.raises(ControlError):
            walls_for("default").torque_for(_sample(bad, np.zeros(N_JOINTS), checked))
