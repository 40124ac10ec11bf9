"""The torque ramp of a simulated drive's quick stop or fault reaction (CiA 402, torque modes).

A drive told to slow down on its slow-down ramp (0x605A or 0x605E = 1) brings the torque its power
stage applies from where it was to zero at the torque slope 0x6087 (per mille of the rated torque
per second), linearly, then goes on to SWITCH ON DISABLED (a quick stop) or FAULT (a fault
reaction). The slope is read at every step, as a drive reads its object dictionary: a master that
rewrites it during a ramp changes the rest of the ramp.
"""

from __future__ import annotations

import math

__all__ = ["StopRamp"]


class StopRamp:
    """A torque ramp to zero under way, in per mille of the rated torque.

    Args:
        torque_permille: the torque the power stage applied when the stop began.
        now_s: when it began, s (robot time).
    """

    def __init__(self, torque_permille: float, now_s: float) -> None:
        self._torque = float(torque_permille)
        self._t_s = now_s

    @property
    def torque_permille(self) -> float:
        """The torque the power stage applies now (0.0 once the ramp is over)."""
        return self._torque

    @property
    def done(self) -> bool:
        return self._torque == 0.0

    def step(self, now_s: float, slope_permille_per_s: int) -> float:
        """Move on to ``now_s``, s, at ``slope_permille_per_s``; the torque then (0.0: over). Time never runs back.

        A slope that is not positive (a drive without 0x6087) ends the ramp at once: there is no
        ramp to follow, and a torque nobody commands must not stay.
        """
        dt = now_s - self._t_s
        if dt <= 0.0:
            return self._torque
        self._t_s = now_s
        if slope_permille_per_s <= 0 or not math.isfinite(self._torque):
            self._torque = 0.0
            return 0.0
        magnitude = abs(self._torque) - slope_permille_per_s * dt
        self._torque = 0.0 if magnitude <= 0.0 else math.copysign(magnitude, self._torque)
        return self._torque
