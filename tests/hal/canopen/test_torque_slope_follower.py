"""The torque slope follower (hal.canopen.cia402.torque_slope) against its rules, written here without its memos.

The follower keeps two memos for the tick (issue 25): the slope wanted per torque, and the torques
whose slope fits the slope the drive holds. These tests run random sequences of cycles (torque,
time, a confirmed write now and then) through the follower and through :class:`_Rules`, the
module docstring's rules computed from scratch each call, and require the same answer every cycle.
"""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from hal.canopen.cia402.torque_slope import (
    FLOOR_FRACTION,
    LOWER_AFTER_S,
    MIN_INTERVAL_S,
    TOLERANCE,
    SlopeFollower,
    slope_for,
)

PEAK_PERMILLE = 3000


class _Rules:
    """The follower's rules, each answer computed from scratch (no memo): the reference."""

    def __init__(self, ramp_s: float, peak_permille: int, held: int) -> None:
        self.ramp_s, self.peak, self.held = ramp_s, peak_permille, held
        self.last_write_s = -math.inf
        self.lower_since_s: float | None = None
        self.lower_largest = 0

    def due(self, torque: int | None, now_s: float) -> int | None:
        magnitude = self.peak if torque is None else max(abs(torque), FLOOR_FRACTION * self.peak)
        wanted = slope_for(magnitude, self.ramp_s)
        if wanted > self.held * (1.0 + TOLERANCE):
            self.lower_since_s = None
            return self._write(wanted, now_s)
        if wanted < self.held * (1.0 - TOLERANCE):
            if self.lower_since_s is None:
                self.lower_since_s, self.lower_largest = now_s, wanted
            else:
                self.lower_largest = max(self.lower_largest, wanted)
            if now_s - self.lower_since_s >= LOWER_AFTER_S:
                return self._write(self.lower_largest, now_s)
            return None
        self.lower_since_s = None
        return None

    def _write(self, slope: int, now_s: float) -> int | None:
        if now_s - self.last_write_s < MIN_INTERVAL_S:
            return None
        self.last_write_s = now_s
        self.lower_since_s = None
        return slope


# A torque walk: a few values revisited often (the memos' case) and jumps; None = not commanded torque
_torques = st.one_of(st.none(), st.sampled_from([0, 5, 30, 31, 600, 629, 630, -630, 1500, 3000]),
                     st.integers(-PEAK_PERMILLE, PEAK_PERMILLE))  # fmt: skip
_cycle = st.tuples(_torques, st.sampled_from([0.0025, 0.0025, 0.0025, 0.05, 0.3]), st.booleans())


@settings(max_examples=300, deadline=None)
@given(
    ramp_s=st.sampled_from([0.2, 0.5, 1.0]),
    start_held=st.sampled_from([1, 100, 3000, 15000]),
    cycles=st.lists(_cycle, min_size=1, max_size=300),
)
def test_the_follower_answers_as_its_rules_every_cycle(
    ramp_s: float, start_held: int, cycles: list[tuple[int | None, float, bool]]
) -> None:
    follower = SlopeFollower(ramp_s, PEAK_PERMILLE, start_held)
    rules = _Rules(ramp_s, PEAK_PERMILLE, start_held)
    now_s = 0.0
    for torque, dt_s, confirm in cycles:
        now_s += dt_s
        got, expected = follower.due(torque, now_s), rules.due(torque, now_s)
        assert got == expected, (torque, now_s)
        if got is not None and confirm:  # the drive took the write: both now hold it
            follower.confirmed(got)
            rules.held = got
        assert follower.held == rules.held


def test_a_torque_that_fits_stops_fitting_once_the_drive_holds_another_slope() -> None:
    follower = SlopeFollower(1.0, PEAK_PERMILLE, 600)
    assert follower.due(600, 0.0) is None  # 600 per mille over 1 s: the slope held, it fits (memoised)
    assert follower.due(600, 0.01) is None
    follower.confirmed(3000)  # the drive now holds the peak's slope: 600 is far below it
    assert follower.due(600, 0.02) is None  # lower: only after LOWER_AFTER_S
    assert follower.due(600, 0.02 + LOWER_AFTER_S) == 600
    follower.held = 100  # held set directly (a field): the memo follows it too
    assert follower.due(600, 1.0) == 600  # higher than 100 by far: written at once
