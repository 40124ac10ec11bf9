"""Bumpless entry into a torque mode: the torque that held the arm is handed over, never dropped.

When the FSM switches into a torque mode, the springs carry some torque ``held`` (what the last
mode, or the pilot, was holding the arm with) and the new mode wants its own reference
``target`` (the model's support in compensation, zero in minimal impedance). A step from one to
the other is a step in the force on the pilot's arm: with a relaxed pilot whose arm the robot was
holding, restarting the support at zero lets the arm fall (issue 9, defect 2). So every entry
starts from ``held`` and the *gap* ``held - target`` is handed over in one of two ways:

* **by time** (at the session's support ramp rate, 0.5/s: the whole gap in 2 s): support that is
  *missing* (the springs carry less than the target asks, in the target's direction, by more than
  ``tolerance_nm``) ramps in, as a pilot who was carrying his own arm feels it come; and torque
  that a pilot-driven mode removes (minimal impedance) ramps out. In compensation the missing
  support also arrives as the arm falls (moves against it), all of it within ``DEFAULT_CATCH_RAD``
  (1.5 deg) of the joint that fell farthest: a pilot who goes limp while it ramps in is caught after
  a sag of a degree or two, not dropped for the rest of the ramp.
* **by motion** (compensation only): support the springs already carry, and the missing part
  within ``tolerance_nm`` (what a validated model may be off by at one pose), is kept until the
  pilot moves the arm away from where it was held, then handed over between ``hold_rad`` and
  ``release_rad`` of motion of the farthest joint. While it lasts, a weak stiffness
  ``anchor_nm_per_rad`` toward the entry pose covers what one sample cannot measure (the spring
  torque's resolution of k x 1e-4 rad = 0.03 Nm, the model's slope near the pose). A relaxed arm
  the robot was holding therefore stays where it was, carried by the torque that held it, however
  far the model is off at that pose; a pilot who moves takes the model's support within a few
  degrees.

Both weights only ever fall (once handed over, never back), so the added torque is bounded by the
gap and removes itself: it cannot pump energy into the arm over a cycle. The per-tick work is one
compiled call (:func:`handover_reference`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from daror_runtime.control.base import ControlSettingError
from hal.interface import DriveState, Sample
from hal.robot import N_JOINTS, FloatArray

#: Motion (farthest joint, rad) before the motion part of the handover starts, and where it ends.
DEFAULT_HOLD_RAD = math.radians(1.0)
DEFAULT_RELEASE_RAD = math.radians(5.0)
#: Motion (farthest joint, rad) that completes the time part at once: the arm falling while the
#: missing support ramps in (a pilot going limp) gets all of it within this.
DEFAULT_CATCH_RAD = math.radians(1.5)
#: Missing support within this (Nm per joint) is handed over by motion, not by time.
DEFAULT_TOLERANCE_NM = 0.5
#: Stiffness (Nm/rad) toward the entry pose while the motion part lasts: a relaxed arm's, so the
#: pilot hardly feels it (0.09 Nm at 1 deg), yet it keeps a limp arm where it was held against what
#: one sample cannot measure (the spring torque's 0.03 Nm resolution, the model's slope).
DEFAULT_ANCHOR_NM_PER_RAD = 5.0
#: A stalled tick must not turn a ramp into a step: at most this much time counts per tick (s).
MAX_RAMP_DT_S = 0.01

# Layout of the state vector (one float64 array, so the tick is one compiled call).
_GAP_TIME = 0  # [0:4] gap handed over by time, Nm
_GAP_MOTION = 4  # [4:8] gap handed over by motion, Nm
_Q0 = 8  # [8:12] where the arm was held at entry, rad
_W_TIME = 12
_W_MOTION = 13
_STEP = 14  # weight removed by time per tick (set each tick from dt)
_HOLD = 15
_RELEASE = 16
_ANCHOR = 17  # [17:21] stiffness toward the entry pose while the motion part lasts, Nm/rad
_CATCH = 21  # motion (rad) over which the time part completes if the arm moves first
_DIRECTION = 22  # [22:26] sign of the target torque: a joint moving against it is falling
_SIZE = 26


@njit(cache=True)
def handover_reference(
    target: np.ndarray, q: np.ndarray, state: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``out = target + gap_time w_time + (gap_motion + K_a (q0 - q)) w_motion``, advancing both weights (one tick)."""
    w_time = state[_W_TIME]
    w_motion = state[_W_MOTION]
    moved = 0.0
    fallen = 0.0
    if w_time > 0.0 or w_motion > 0.0:
        for j in range(q.shape[0]):
            away = q[j] - state[_Q0 + j]
            moved = max(moved, abs(away))
            fallen = max(fallen, -state[_DIRECTION + j] * away)
    if w_time > 0.0:
        # by time, or sooner if the arm falls (moves against the support): a pilot who goes limp while
        # the support ramps in is caught; an arm the pilot lifts does not speed the ramp up
        w_time = min(w_time - state[_STEP], 1.0 - fallen / state[_CATCH])
        w_time = max(w_time, 0.0)
        state[_W_TIME] = w_time
    if w_motion > 0.0:
        w = (state[_RELEASE] - moved) / (state[_RELEASE] - state[_HOLD])
        w = min(max(w, 0.0), 1.0)
        if w < w_motion:
            w_motion = w
            state[_W_MOTION] = w
    for j in range(target.shape[0]):
        anchor = state[_ANCHOR + j] * (state[_Q0 + j] - q[j])
        out[j] = target[j] + state[_GAP_TIME + j] * w_time + (state[_GAP_MOTION + j] + anchor) * w_motion


class Handover:
    """The gap between the torque held at entry and a mode's own reference, handed over per tick.

    Args:
        ramp_per_s: the share of the time part handed over per second (the session's support
            ramp; 0.5/s: 2 s for the whole gap).
        by_motion: hand over the support already carried by motion (compensation) instead of
            by time (minimal impedance, which must end at zero torque whatever the pilot does).
        tolerance_nm: missing support up to this per joint counts as carried (model error).
        hold_rad, release_rad: the motion handover runs between these displacements of the
            farthest joint from the entry pose.
        anchor_nm_per_rad: stiffness toward the entry pose while the motion part lasts.

    Raises:
        ControlSettingError: a rate, tolerance or distance that is not positive and finite, or
            ``release_rad <= hold_rad``.
    """

    def __init__(
        self,
        ramp_per_s: float,
        by_motion: bool,
        tolerance_nm: float = DEFAULT_TOLERANCE_NM,
        hold_rad: float = DEFAULT_HOLD_RAD,
        release_rad: float = DEFAULT_RELEASE_RAD,
        anchor_nm_per_rad: float = DEFAULT_ANCHOR_NM_PER_RAD,
    ) -> None:
        for name, value in (("ramp", ramp_per_s), ("release distance", release_rad)):
            if not (math.isfinite(value) and value > 0.0):
                raise ControlSettingError(f"handover {name} must be a positive finite number, got {value!r}")
        for name, value in (("tolerance", tolerance_nm), ("hold distance", hold_rad), ("anchor", anchor_nm_per_rad)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ControlSettingError(f"handover {name} must be a finite number >= 0, got {value!r}")
        if release_rad <= hold_rad:
            raise ControlSettingError(
                f"handover release distance ({release_rad} rad) must be beyond the hold distance ({hold_rad} rad)"
            )
        self.ramp_per_s = float(ramp_per_s)
        self.by_motion = by_motion
        self.tolerance_nm = float(tolerance_nm)
        self.state = np.zeros(_SIZE)
        self.state[_HOLD] = hold_rad
        self.state[_RELEASE] = release_rad
        self.state[_ANCHOR : _ANCHOR + N_JOINTS] = anchor_nm_per_rad if by_motion else 0.0
        # Minimal impedance hands its gap out by time only: its target is zero whatever the arm does.
        self.state[_CATCH] = DEFAULT_CATCH_RAD if by_motion else math.inf

    def start(self, sample: Sample, spring_nm: FloatArray, target_nm: FloatArray) -> None:
        """A new entry at ``sample``: the springs carry ``spring_nm``; the mode wants ``target_nm`` there (4,).

        Only what an enabled drive holds counts as held: behind a disabled drive (torque was off)
        the spring is unwinding, the robot holds nothing there, and the handover starts from zero.
        """
        enabled = np.fromiter((d == DriveState.ENABLED for d in sample.drives), dtype=bool, count=N_JOINTS)
        held = np.where(enabled, np.asarray(spring_nm, dtype=float), 0.0)
        target = np.asarray(target_nm, dtype=float)
        gap = held - target
        state = self.state
        if self.by_motion:
            # Missing support, in the direction of the target: |target| - (held along target).
            direction = np.sign(target)
            missing = np.abs(target) - direction * held
            beyond = np.maximum(missing - self.tolerance_nm, 0.0)
            gap_time = -direction * beyond
        else:
            gap_time = gap
        state[_GAP_TIME : _GAP_TIME + N_JOINTS] = gap_time
        state[_GAP_MOTION : _GAP_MOTION + N_JOINTS] = gap - gap_time
        state[_Q0 : _Q0 + N_JOINTS] = sample.q_rad
        state[_DIRECTION : _DIRECTION + N_JOINTS] = np.sign(target)
        state[_W_TIME] = 1.0 if np.any(gap_time != 0.0) else 0.0
        state[_W_MOTION] = 1.0 if np.any(gap != gap_time) else 0.0

    def clear(self) -> None:
        """Nothing left to hand over (the mode's own reference from now on)."""
        self.state[_W_TIME] = self.state[_W_MOTION] = 0.0

    def set_dt(self, dt_s: float) -> None:
        """The time the coming tick hands over (at most :data:`MAX_RAMP_DT_S`; a stall is no step)."""
        step = self.ramp_per_s * min(max(dt_s, 0.0), MAX_RAMP_DT_S) if math.isfinite(dt_s) else 0.0
        self.state[_STEP] = step

    @property
    def remaining_nm(self) -> FloatArray:
        """The gap (4,) still added to the mode's reference (Nm, without the anchor): what is yet to be handed over."""
        s = self.state
        return s[_GAP_TIME : _GAP_TIME + N_JOINTS] * s[_W_TIME] + s[_GAP_MOTION : _GAP_MOTION + N_JOINTS] * s[_W_MOTION]

    @property
    def active(self) -> bool:
        return bool(self.state[_W_TIME] > 0.0 or self.state[_W_MOTION] > 0.0)
