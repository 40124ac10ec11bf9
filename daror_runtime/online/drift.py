"""The drift test (issue 29, part 2): the model alone holds the relaxed arm, the drift shows what it misses.

In state ``compensation``, at support level 1, the operator asks for the test with the pilot
relaxed (his muscles slack: he holds nothing). From then on the model's torque alone supports his
arm; where the model is wrong the arm drifts. The test watches the drift for at most
:data:`DRIFT_MAX_S` or until a joint has drifted :data:`DRIFT_MAX_DEG`, then the session catches the
arm: it reverts to ``training``, whose hold takes over exactly the torque the springs carry (the
transition is bumpless, docs/control.md), and holds the pose the arm drifted to. After
:data:`SETTLE_S` the held springs carry the relaxed arm's true holding torque ``g(q)``: over
:data:`MEASURE_S` the mean of ``model(q) - springs`` is the **unsupported torque** per joint, the
model's error at that pose in Nm, an online validation error comparable to the offline RMSE. The
drift (deg, and the peak speed) is what the pilot would feel of it.

This module is the test's bookkeeping on observations (plain numpy); the session
(:mod:`daror_runtime.session.drift`) feeds it between ticks and asks for the catch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np

from hal.robot import N_JOINTS, FloatArray

#: The longest the model alone holds the relaxed arm (s).
DRIFT_MAX_S = 1.0
#: The drift at which the arm is caught at once (deg, any joint): well inside the soft walls.
DRIFT_MAX_DEG = 3.0
#: The test starts only with the arm this far inside the pilot's limits and the device's (deg).
MARGIN_DEG = 8.0
#: After the catch the hold settles this long before the springs are read (s).
SETTLE_S = 0.5
#: The springs are averaged over this (s).
MEASURE_S = 0.5


#: A rest within this of a drift test's caught pose (deg, every joint) is corrected by its unsupported torque.
CORRECTION_RADIUS_DEG = 5.0


class DriftPhase(StrEnum):
    DRIFTING = "drifting"  # the model alone holds the arm
    CATCHING = "catching"  # the catch is asked for; the next tick's revert holds the arm
    HOLDING = "holding"  # held; the springs settle, then are measured
    DONE = "done"
    ABANDONED = "abandoned"


@dataclass(frozen=True)
class DriftResult:
    """One drift test: where, how far the arm drifted, and what the model missed there."""

    model: str
    t_start_s: float
    start_pose_rad: tuple[float, ...]
    caught_pose_rad: tuple[float, ...]
    drift_s: float
    why_caught: str
    peak_speed_deg_s: tuple[float, ...]
    unsupported_nm: tuple[float, ...]  # model(q) - springs at the hold: the model's error there

    @property
    def drift_deg(self) -> tuple[float, ...]:
        return tuple(float(np.rad2deg(b - a)) for a, b in zip(self.start_pose_rad, self.caught_pose_rad, strict=True))

    def as_dict(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "t_start_s": round(self.t_start_s, 3),
            "start_pose_deg": [round(float(np.rad2deg(v)), 2) for v in self.start_pose_rad],
            "drift_deg": [round(v, 3) for v in self.drift_deg],
            "drift_s": round(self.drift_s, 3),
            "why_caught": self.why_caught,
            "peak_speed_deg_s": [round(v, 2) for v in self.peak_speed_deg_s],
            "unsupported_nm": [round(v, 4) for v in self.unsupported_nm],
        }


class DriftTest:
    """One drift test from the pose ``q_rad`` at ``t_s`` under the model labelled ``model``."""

    def __init__(self, model: str, t_s: float, q_rad: FloatArray) -> None:
        self.model = model
        self.phase = DriftPhase.DRIFTING
        self.t_start_s = t_s
        self.start_q = np.array(q_rad, dtype=float)
        self._last: tuple[float, FloatArray] = (t_s, self.start_q)
        self._peak_speed = np.zeros(N_JOINTS)
        self.why_caught = ""
        self.drift_s = 0.0
        self.caught_q: FloatArray | None = None
        self._held_since_s: float | None = None
        self._n = 0
        self._unsupported = np.zeros(N_JOINTS)
        self.result: DriftResult | None = None
        self.why_abandoned = ""

    def observe_drift(self, t_s: float, q_rad: FloatArray) -> str | None:
        """While drifting: the reason to catch the arm now, or None to let it drift on."""
        q = np.asarray(q_rad, dtype=float)
        last_t, last_q = self._last
        if t_s > last_t:
            self._peak_speed = np.maximum(self._peak_speed, np.abs(q - last_q) / (t_s - last_t))
        self._last = (t_s, q.copy())
        drift = np.abs(np.rad2deg(q - self.start_q))
        if float(drift.max()) >= DRIFT_MAX_DEG:
            joint = int(np.argmax(drift))
            return f"joint {joint + 1} drifted {drift[joint]:.1f} deg"
        if t_s - self.t_start_s >= DRIFT_MAX_S:
            return f"{DRIFT_MAX_S:g} s passed"
        return None

    def catch(self, t_s: float, why: str) -> None:
        """The catch is asked for at ``t_s``."""
        self.phase = DriftPhase.CATCHING
        self.why_caught = why
        self.drift_s = t_s - self.t_start_s

    def held(self, t_s: float, q_rad: FloatArray) -> None:
        """The hold has the arm, at ``q_rad``."""
        self.phase = DriftPhase.HOLDING
        self.caught_q = np.array(q_rad, dtype=float)
        self._held_since_s = t_s

    def observe_hold(self, t_s: float, springs_nm: FloatArray, model_nm: FloatArray) -> bool:
        """While held: the springs against the model after settling; True once measured (:attr:`result`)."""
        if self._held_since_s is None or self.caught_q is None:
            return False
        held_s = t_s - self._held_since_s
        if held_s < SETTLE_S:
            return False
        self._n += 1
        self._unsupported += np.asarray(model_nm, dtype=float) - np.asarray(springs_nm, dtype=float)
        if held_s < SETTLE_S + MEASURE_S:
            return False
        self.phase = DriftPhase.DONE
        self.result = DriftResult(
            self.model,
            self.t_start_s,
            tuple(float(v) for v in self.start_q),
            tuple(float(v) for v in self.caught_q),
            self.drift_s,
            self.why_caught,
            tuple(float(v) for v in np.rad2deg(self._peak_speed)),
            tuple(float(v) for v in self._unsupported / self._n),
        )
        return True

    def abandon(self, why: str) -> None:
        self.phase = DriftPhase.ABANDONED
        self.why_abandoned = why


def corrected_effort(
    pose_rad: Sequence[float], effort_nm: Sequence[float], tests: Sequence[DriftResult]
) -> tuple[tuple[float, ...], DriftResult] | None:
    """The pilot's effort at a rest less the model's error the nearest drift test measured there.

    The at-rest indicator is his effort plus the model's error at the pose (docs/online.md); a drift
    test of the same model within :data:`CORRECTION_RADIUS_DEG` of the rest's pose (every joint)
    measured that error, so subtracting it leaves his effort. None: no test near enough.
    """
    pose = np.asarray(pose_rad, dtype=float)
    best: tuple[float, DriftResult] | None = None
    for test in tests:
        distance = float(np.rad2deg(np.abs(np.asarray(test.caught_pose_rad) - pose).max()))
        if distance <= CORRECTION_RADIUS_DEG and (best is None or distance < best[0]):
            best = (distance, test)
    if best is None:
        return None
    test = best[1]
    return tuple(float(e - u) for e, u in zip(effort_nm, test.unsupported_nm, strict=True)), test


__all__ = [
    "CORRECTION_RADIUS_DEG",
    "DRIFT_MAX_DEG",
    "DRIFT_MAX_S",
    "MARGIN_DEG",
    "MEASURE_S",
    "SETTLE_S",
    "DriftPhase",
    "DriftResult",
    "DriftTest",
    "corrected_effort",
]
