"""Issue 29, part 1: the online indicators on observations whose truth is known by construction."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from daror_runtime.online.indicators import (
    MIN_REST_S,
    MOVING_RAD_S,
    OBSERVE_PERIOD_S,
    SETTLE_S,
    OnlineIndicators,
)

INERTIA = np.array([0.1, 0.1, 0.05, 0.01])
POSE = np.array([0.2, 0.5, -0.1, 1.0])
MODEL = np.array([1.0, 4.0, 0.5, 1.5])  # the model's torque at full support, Nm


def _hold(ind: OnlineIndicators, t_s: float, seconds: float, springs: np.ndarray, level: float = 1.0) -> float:
    """Observations of a still arm at POSE for ``seconds``; returns the time after them."""
    for _ in range(round(seconds / OBSERVE_PERIOD_S)):
        ind.observe(t_s, POSE, springs, MODEL, level)
        t_s += OBSERVE_PERIOD_S
    return t_s


def _move(ind: OnlineIndicators, t_s: float, seconds: float, speed_rad_s: float) -> float:
    """Observations of joint 4 moving at ``speed_rad_s`` from POSE and back; returns the time after them."""
    n = round(seconds / OBSERVE_PERIOD_S)
    for k in range(n):
        q = POSE.copy()
        q[3] += speed_rad_s * OBSERVE_PERIOD_S * min(k, n - k)
        ind.observe(t_s, q, MODEL, MODEL, 1.0)
        t_s += OBSERVE_PERIOD_S
    return t_s


def test_a_still_arm_gives_the_effort_the_springs_do_not_carry() -> None:
    ind = OnlineIndicators(INERTIA)
    springs = 0.7 * MODEL  # level 0.7 delivered: the pilot carries the rest
    t = _hold(ind, 0.0, 2.0, springs, level=0.7)
    _move(ind, t, 1.0, 0.5)
    summary = ind.summary()
    assert summary.rests == 1
    rest = summary.last_rest
    assert rest is not None
    np.testing.assert_allclose(rest.effort_nm, 0.3 * MODEL, atol=1e-12)
    assert rest.level_delivered == pytest.approx(0.7)
    assert rest.level_asked == 0.7
    # the settling time is left out; the rest ends one observation before the motion is seen
    assert rest.t_start_s >= SETTLE_S
    assert rest.t_end_s - rest.t_start_s >= MIN_REST_S
    assert summary.level_delivered == pytest.approx(0.7)


def test_a_short_pause_is_no_rest_and_a_moving_arm_is_never_one() -> None:
    ind = OnlineIndicators(INERTIA)
    t = _hold(ind, 0.0, SETTLE_S + MIN_REST_S - 0.1, MODEL)  # too short once the settling is left out
    t = _move(ind, t, 2.0, 0.5)
    assert ind.summary().rests == 0
    assert ind.summary().moving_samples[3] > 0
    assert ind.summary().moving_samples[:3] == (0, 0, 0)  # only joint 4 moved


def test_a_new_level_starts_a_new_rest_and_a_gap_ends_one() -> None:
    ind = OnlineIndicators(INERTIA)
    t = _hold(ind, 0.0, 1.5, 1.0 * MODEL, level=1.0)
    t = _hold(ind, t, 1.5, 0.5 * MODEL, level=0.5)
    ind.interrupt()  # compensation paused
    rests = ind.rests
    assert [r.level_asked for r in rests] == [1.0, 0.5]
    np.testing.assert_allclose(rests[0].effort_nm, 0.0, atol=1e-12)
    np.testing.assert_allclose(rests[1].effort_nm, 0.5 * MODEL, atol=1e-12)
    # after a gap the history starts anew: no acceleration spans it, no rest without settling again
    _hold(ind, t + 5.0, SETTLE_S + 0.1, MODEL)
    assert ind.summary().rests == 2


def test_the_interaction_while_moving_counts_the_link_s_inertia_and_its_damping_is_its_slope() -> None:
    """The springs lag the model by b x speed while the elbow swings: the felt damping is b."""
    ind = OnlineIndicators(INERTIA)
    damping = 0.8
    t = 0.0
    for k in range(400):
        t = k * OBSERVE_PERIOD_S
        q = POSE.copy()
        q[3] += 0.4 * np.sin(2.0 * t)  # rad; speed 0.8 cos(2t), acceleration -1.6 sin(2t)
        speed = 0.8 * np.cos(2.0 * t)
        acceleration = -1.6 * np.sin(2.0 * t)
        springs = MODEL.copy()
        springs[3] -= damping * speed + INERTIA[3] * acceleration  # the interaction = b v exactly
        ind.observe(t, q, springs, MODEL, 1.0)
    summary = ind.summary()
    assert summary.apparent_damping_nms_per_rad[3] == pytest.approx(damping, rel=0.02)
    assert summary.apparent_damping_nms_per_rad[0] is None  # a joint that never moved
    assert summary.interaction_rms_nm[3] == pytest.approx(damping * 0.8 / np.sqrt(2), rel=0.08)
    assert summary.moving_samples[3] > 0


@given(st.lists(st.tuples(st.floats(0.1, 3.0), st.floats(-2.0, 2.0)), min_size=1, max_size=8))
def test_every_rest_is_a_still_stretch_long_enough_and_carries_its_effort(stretches: list[tuple[float, float]]) -> None:
    """Still stretches (each with its own effort on joint 2) between motions: a rest for each stretch
    clearly long enough after settling, none for one clearly too short, each with its stretch's effort
    exactly (never mixed with a motion's samples)."""
    ind = OnlineIndicators(INERTIA)
    t = 0.0
    for seconds, effort in stretches:
        springs = MODEL.copy()
        springs[1] -= effort
        t = _hold(ind, t, seconds, springs)
        t = _move(ind, t, 0.3, 2 * MOVING_RAD_S)
    ind.interrupt()
    rests = ind.rests
    efforts = [effort for _, effort in stretches]
    for rest in rests:
        assert any(abs(rest.effort_nm[1] - e) < 1e-9 for e in efforts), (rest.effort_nm, efforts)
        assert rest.t_end_s - rest.t_start_s >= MIN_REST_S
    surely = sum(1 for seconds, _ in stretches if seconds >= SETTLE_S + MIN_REST_S + 0.2)
    maybe = sum(1 for seconds, _ in stretches if seconds >= SETTLE_S + MIN_REST_S)
    assert surely <= len(rests) <= maybe
