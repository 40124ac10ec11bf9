"""The torque slope 0x6087 of a drive's own stop ramp: what slope gives a ramp of ``ramp_s``, and when to rewrite it.

CiA 402 gives a stop ramp of the torque modes as a slope, in per mille of the rated torque 0x6076
per second, not as a time: a drive that quick-stops from a torque ``T`` (per mille) at slope ``S``
reaches zero after ``|T| / S`` seconds. The runtime asks for a time (``ramp_s``: the drive brings
the torque it holds when it loses the master to zero in that time), so the slope follows the torque::

    S = ceil(max(|T|, floor) / ramp_s)        per mille per second; rounded up: never longer than ramp_s

The master cannot know at start-up what torque a drive will hold when it loses the master. It writes
the peak's slope there (``T`` = 0x6072: any torque then ramps out within ``ramp_s``, a smaller one
sooner), and while it commands torque a :class:`SlopeFollower` per drive says when to rewrite the
slope by SDO so that it fits the torque the drive holds now. Rules, and why:

* the torque rose (the drive would now take longer than ``ramp_s`` by more than :data:`TOLERANCE`):
  rewrite at once. A ramp that is too long is a drive applying torque that nobody commands;
* the torque fell (the drive would stop sooner than ``ramp_s`` by more than :data:`TOLERANCE`):
  rewrite once the torque stayed lower for :data:`LOWER_AFTER_S`, with the largest slope wanted in
  that time. A ramp that is too short is closer to dropping the arm, not a new hazard, and a torque
  that oscillates is not chased;
* while the drive is not commanded torque, the peak's slope is wanted (it holds nothing; when it
  gets torque again the ramp errs on the short side until the follower lowered the slope);
* never two writes within :data:`MIN_INTERVAL_S`: four drives then add at most 4 x 10 expedited
  SDO transfers a second (8 frames of 135 worst-case bits each: 1.08 % of 1 Mbit/s), inside the
  room the 70 % bus-load budget leaves (docs/canopen.md);
* torques under :data:`FLOOR_FRACTION` of the peak count as that floor (a slope of 0 never ends).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["FLOOR_FRACTION", "LOWER_AFTER_S", "MIN_INTERVAL_S", "TOLERANCE", "SlopeFollower", "slope_for"]

#: The largest value of 0x6087 (UNSIGNED32).
SLOPE_MAX = 0xFFFF_FFFF
#: How far the ramp a drive would make may be off ``ramp_s`` before the slope is rewritten (0.05: 5 %).
TOLERANCE = 0.05
#: How long a lower torque must last before the slope is lowered, s.
LOWER_AFTER_S = 0.5
#: The shortest time between two writes of one drive's slope, s.
MIN_INTERVAL_S = 0.1
#: Torques below this fraction of the peak count as it (the smallest slope is the floor's).
FLOOR_FRACTION = 0.01


def slope_for(torque_permille: float, ramp_s: float) -> int:
    """The torque slope, per mille of the rated torque per second, that brings ``torque_permille`` to zero in ``ramp_s`` s.

    Rounded up (the ramp is never longer than ``ramp_s``), at least 1, at most 0x6087's largest value.

    Raises:
        ValueError: ``ramp_s`` is not finite and positive.
    """
    if not (math.isfinite(ramp_s) and ramp_s > 0.0):
        raise ValueError(f"a ramp of {ramp_s} s: expected a finite, positive time")
    return max(1, min(SLOPE_MAX, math.ceil(abs(torque_permille) / ramp_s)))


@dataclass
class SlopeFollower:
    """When to rewrite one drive's torque slope so that its stop ramp from the torque it holds lasts ``ramp_s``.

    Pure (no bus, no clock): the master calls :meth:`due` once a cycle with the torque it commands
    and its time, writes what it returns, and calls :meth:`confirmed` when the drive took it. See
    the module docstring for the rules.

    Args:
        ramp_s: the ramp the runtime asked for, s.
        peak_permille: the drives' peak torque (0x6072), per mille of the rated torque.
        held: the slope the drive holds now (what the start-up wrote), per mille per second.
    """

    ramp_s: float
    peak_permille: int
    held: int
    _last_write_s: float = field(default=-math.inf, init=False)
    _lower_since_s: float | None = field(default=None, init=False)
    _lower_largest: int = field(default=0, init=False)
    # wanted()'s answers by torque (a pure function of it; at most the 2 x peak + 2 torques a drive can be sent)
    _wanted_of: dict[int | None, int] = field(default_factory=dict, init=False, repr=False)
    # (held, first, last, None fits, lower, upper): the torque magnitudes first..last (within the peak) and the
    # torque None whose slope is within the tolerance lower..upper of that held slope (:meth:`_fitting_band`)
    _band: tuple[float, int, int, bool, float, float] = field(  # NaN: equal to no slope held (derived at first)
        default=(math.nan, 0, -1, False, -math.inf, math.inf), init=False, repr=False
    )

    def wanted(self, torque_permille: int | None) -> int:
        """The slope for ``torque_permille`` (None: the drive is not commanded torque: the peak's)."""
        found = self._wanted_of.get(torque_permille)
        if found is None:  # once per torque: due() runs per drive and cycle (issue 25)
            if torque_permille is None:
                found = slope_for(self.peak_permille, self.ramp_s)
            else:
                found = slope_for(max(abs(torque_permille), FLOOR_FRACTION * self.peak_permille), self.ramp_s)
            self._wanted_of[torque_permille] = found
        return found

    def due(self, torque_permille: int | None, now_s: float) -> int | None:
        """The slope to write now (per mille per second), or None: nothing to write this cycle.

        Args:
            torque_permille: the target torque the drive applies from this cycle (None: it is not
                commanded torque).
            now_s: the master's time, s.
        """
        band = self._band
        if band[0] != self.held:
            band = self._band = self._fitting_band()
        if band[3] if torque_permille is None else band[1] <= abs(torque_permille) <= band[2]:
            self._lower_since_s = None  # nearly every cycle (issue 25): the drive's ramp fits, the test below in short
            return None
        wanted = self._wanted_of.get(torque_permille)
        if wanted is None:
            wanted = self.wanted(torque_permille)
        if wanted > band[5]:  # more than the tolerance above the slope held
            self._lower_since_s = None
            return self._write(wanted, now_s)
        if wanted < band[4]:  # more than the tolerance below it
            if self._lower_since_s is None:
                self._lower_since_s, self._lower_largest = now_s, wanted
            elif wanted > self._lower_largest:
                self._lower_largest = wanted
            if now_s - self._lower_since_s >= LOWER_AFTER_S:
                return self._write(self._lower_largest, now_s)
            return None
        self._lower_since_s = None  # within the tolerance: the drive's ramp fits
        return None

    def _fitting_band(self) -> tuple[float, int, int, bool, float, float]:
        """:attr:`_band` for the slope held now: once per slope the drive takes, two bisections of ``[0, peak]``.

        :meth:`wanted` does not fall as the torque's magnitude grows, so the magnitudes whose slope
        is within the tolerance are one interval. Magnitudes above the peak (the master never sends
        them) are left to the general test.
        """
        held = self.held
        lower, upper = held * (1.0 - TOLERANCE), held * (1.0 + TOLERANCE)
        lo, hi = 0, self.peak_permille + 1  # the smallest magnitude not below the tolerance (peak + 1: none)
        while lo < hi:
            mid = (lo + hi) // 2
            if self.wanted(mid) >= lower:
                hi = mid
            else:
                lo = mid + 1
        first = lo
        lo, hi = -1, self.peak_permille  # the largest magnitude not above it (-1: none)
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if self.wanted(mid) <= upper:
                lo = mid
            else:
                hi = mid - 1
        return held, first, lo, lower <= self.wanted(None) <= upper, lower, upper

    def _write(self, slope: int, now_s: float) -> int | None:
        if now_s - self._last_write_s < MIN_INTERVAL_S:
            return None
        self._last_write_s = now_s
        self._lower_since_s = None
        return slope

    def confirmed(self, slope: int) -> None:
        """The drive took ``slope`` (its SDO write was answered)."""
        self.held = slope
