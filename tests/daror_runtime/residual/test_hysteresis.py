"""The play operator of the SEA reading's hysteresis (issue 16): bounded, rate-independent, the tick's tracker the same."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from daror_runtime.control.reading_error import HysteresisTracker
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.errors import DataError, UsageError
from daror_runtime.residual.hysteresis import (
    PointHistory,
    estimate_path,
    find_raw_log,
    play_states,
)

paths = arrays(np.float64, st.tuples(st.integers(2, 60), st.just(4)), elements=st.floats(-0.05, 0.05))
travels = st.floats(1e-4, 0.05)


@given(paths, travels)
def test_the_state_stays_in_minus_one_to_one(path: np.ndarray, travel: float) -> None:
    states = play_states(np.cumsum(path, axis=0), travel)
    assert states.shape == path.shape
    assert np.all(np.abs(states) <= 1.0)


@given(paths, travels, st.integers(1, 5))
@settings(max_examples=60)
def test_the_state_depends_on_the_path_not_on_its_speed(path: np.ndarray, travel: float, between: int) -> None:
    """Samples added on the straight lines between samples change nothing at the samples (rate independence)."""
    q = np.cumsum(path, axis=0)
    fractions = np.arange(between + 1) / (between + 1)
    dense = np.concatenate([q[k] + np.outer(fractions, q[k + 1] - q[k]) for k in range(len(q) - 1)] + [q[-1:]])
    assert play_states(dense, travel)[:: between + 1] == pytest.approx(play_states(q, travel), abs=1e-9)


@given(paths, st.floats(0.002, 0.05))
def test_after_a_move_longer_than_the_travel_it_is_the_sign_of_that_move(path: np.ndarray, travel: float) -> None:
    """The direction offset is the hysteresis whose travel is short against every move."""
    q = np.cumsum(path, axis=0)
    move = np.where(np.arange(4) % 2 == 0, 2.5, -2.5) * travel
    ended = np.vstack([q, q[-1] + move])
    assert play_states(ended, travel)[-1] == pytest.approx(np.sign(move))


@given(paths, travels)
def test_a_point_is_undetermined_exactly_where_the_state_before_the_path_still_matters(
    path: np.ndarray, travel: float
) -> None:
    """D204: the operator run from -1 and from +1 disagrees at a point if and only if it is marked undetermined."""
    q = np.cumsum(path, axis=0)
    history = PointHistory.from_points(StationaryDataset(q, np.zeros_like(q)))
    disagree = play_states(q, travel, -1.0) != play_states(q, travel, 1.0)
    assert np.array_equal(history.undetermined(travel), disagree)


def test_a_run_that_begins_at_rest_at_its_first_point_leaves_that_point_s_state_unknown() -> None:
    """The demo session's validation run (D204): still at the first stop, then a move of 3 travels settles it."""
    travel = 0.005
    ramp = np.linspace(0.0, 0.015, 300)[:, None] * np.ones((1, 4))
    q = np.concatenate([np.zeros((300, 4)), ramp, np.full((300, 4), 0.015)])  # 1 kHz: still, 15 mrad up, still
    raw = RawLog(np.arange(900) * 0.001, q, np.zeros_like(q), np.zeros_like(q))
    points = StationaryDataset(q[[150, 850]], np.zeros((2, 4)), t_s=np.array([0.15, 0.85]))
    unknown = PointHistory.from_raw(raw, points).undetermined(travel)
    assert unknown[0].all()  # nothing moved before it: up or down last, nobody can say
    assert not unknown[1].any()  # 15 mrad one way: +1 whatever the state was


def test_a_reversal_shorter_than_the_travel_only_partly_flips_it() -> None:
    """An overshoot that settles back 1 mrad after a long move: the sign of the last motion says -1, the state +0.6."""
    q = np.array([[0.0], [0.1], [0.099]])  # up 100 mrad, back 1 mrad
    state = play_states(q, 0.005)[-1, 0]
    assert state == pytest.approx(1.0 - 0.001 / 0.005)  # the state moves by travel / r: 1 - 0.2


@given(paths, travels)
@settings(max_examples=60)
def test_the_ticks_tracker_is_the_operator_on_the_causally_filtered_path(path: np.ndarray, travel: float) -> None:
    """What the tick adds is the fitted operator on the measured angles through a first-order 20 Hz low-pass."""
    q = np.cumsum(path, axis=0)
    amplitude = np.array([0.25, 0.75, 0.35, 0.15])
    tracker = HysteresisTracker(np.full(4, travel), amplitude)
    tracker.reset(q[0])
    errors = np.array([tracker.update(row, 1e-3).copy() for row in q[1:]])
    a = 1.0 - np.exp(-2.0 * np.pi * 20.0 * 1e-3)
    filtered = scipy.signal.lfilter([a], [1.0, a - 1.0], q - q[:1], axis=0) + q[:1]
    offline = amplitude * play_states(filtered, travel)[1:]
    assert errors == pytest.approx(offline, abs=1e-9)


def test_the_path_estimate_does_not_lag_the_turning_points() -> None:
    """A 1 Hz swing of 20 mrad with 5e-5 rad of noise: the estimate turns where the joint turned (zero phase),
    where the tick's causal filter turns ~8 ms late."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 2.0, 1e-3)
    true = 0.02 * np.sin(2.0 * np.pi * t)
    measured = (true + 5e-5 * rng.standard_normal(len(t)))[:, None]
    estimate = estimate_path(measured, 1e-3)[:, 0]
    inner = slice(750, 1750)  # one crest, away from the ends' padding
    assert abs(t[inner][np.argmax(estimate[inner])] - 1.25) < 0.002
    assert abs(estimate[inner].max() - 0.02) < 3e-5
    assert np.std(estimate[inner] - true[inner]) < 1.5e-5  # the noise, 5e-5 rad a sample, mostly gone
    a = 1.0 - np.exp(-2.0 * np.pi * 20.0 * 1e-3)
    causal = scipy.signal.lfilter([a], [1.0, a - 1.0], measured[:, 0])
    assert t[inner][np.argmax(causal[inner])] - 1.25 > 0.005


def test_the_filter_keeps_the_encoders_noise_from_walking_a_held_joints_state() -> None:
    """A joint held still for 10 s with 5e-5 rad of noise a tick: unfiltered the state sags by the noise's
    excursions over the travel (~5 %: 37 mNm of joint 2's 0.75 Nm), filtered it stays within 2 %."""
    rng = np.random.default_rng(1)
    ramp = np.linspace(0.0, 0.1, 1000)[:, None] * np.ones((1, 4))
    q = np.vstack([ramp, 0.1 + 5e-5 * rng.standard_normal((10_000, 4))])
    held_filtered = play_states(estimate_path(q, 1e-3), 0.005)[1000:]
    held_raw = play_states(q, 0.005)[1000:]
    assert held_filtered.min() > 0.98
    assert held_raw.min() < 0.95


def _points(t: np.ndarray, q: np.ndarray) -> StationaryDataset:
    return StationaryDataset(q, np.zeros_like(q), None, t, "points.csv")


def test_a_points_history_reads_the_raw_log_up_to_each_point(tmp_path: Path) -> None:
    t = np.arange(0.0, 1.0, 0.001)
    q = np.where(t < 0.5, t, 1.0 - t)[:, None] * np.ones((1, 4)) * 0.04  # up 20 mrad, then back down
    raw = RawLog(t, q, np.zeros_like(q), np.zeros_like(q), source="run.raw.npz")
    history = PointHistory.from_raw(raw, _points(np.array([0.4, 0.85]), q[[400, 850]]))  # states averaged over +-0.1 s
    assert history.from_raw_log
    states = history.states(0.004)
    assert states[0] == pytest.approx(np.ones(4), abs=1e-6)
    assert states[1] == pytest.approx(-np.ones(4), abs=1e-6)
    assert history.subset(np.array([1])).states(0.004) == pytest.approx(states[1:])
    with pytest.raises(DataError, match="outside this raw log"):
        PointHistory.from_raw(raw, _points(np.array([1.5]), q[:1]))
    (tmp_path / "train.csv").write_text("", encoding="utf-8")
    assert find_raw_log(tmp_path / "train.csv") is None
    (tmp_path / "train.raw.npz").write_bytes(b"")
    assert find_raw_log(tmp_path / "train.csv") == tmp_path / "train.raw.npz"


@pytest.mark.parametrize("travel", [0.0, -0.0, -1e-3, float("nan"), float("inf"), -float("inf"), 1e-300, 9.99e-5])
def test_a_travel_constant_must_be_finite_and_at_least_the_encoders_resolution(travel: float) -> None:
    with pytest.raises(UsageError, match="travel constant"):
        play_states(np.zeros((3, 4)), travel)
    with pytest.raises(UsageError, match="travel constant"):
        HysteresisTracker(np.full(4, travel), np.ones(4))


def test_the_tracker_takes_frozen_and_listed_angles_skips_a_non_finite_one_and_refuses_a_wrong_shape() -> None:
    from daror_runtime.errors import ShapeError

    tracker = HysteresisTracker(np.full(4, 0.005), np.array([0.25, 0.75, 0.35, 0.15]))
    tracker.reset(np.zeros(4))
    frozen = np.full(4, 0.1)
    frozen.flags.writeable = False  # a HAL's sample arrays may be read-only
    for _ in range(500):
        error = tracker.update(frozen, 1e-3)
    assert error == pytest.approx([0.25, 0.75, 0.35, 0.15])  # 100 mrad up: saturated
    before = tracker.state.copy()
    assert tracker.update([0.0, float("nan"), 0.0, 0.0], 1e-3) == pytest.approx(0.25 * before * [1, 3, 1.4, 0.6])
    assert np.array_equal(tracker.state, before)  # the NaN moved no joint
    tracker.update([0.0, 0.1, 0.1, 0.1], 1e-3)  # a list is converted: joint 1 starts down
    assert tracker.state[0] < 1.0
    assert np.all(tracker.state[1:] == 1.0)
    with pytest.raises(ShapeError, match="4 angles"):
        tracker.update(np.zeros(3), 1e-3)
