"""Objective indicators of how the support serves the pilot, measured while he uses it (thesis Sec. 7.2).

Offline, a model is judged by its RMSE on held-out stationary data; online, the runtime measures,
outside the tick, from what it reads every tick (the springs' torque from the encoders, the joints'
angles and speeds) and the model's torque at full support:

* **The pilot's effort at rest** (Nm per joint): whenever the arm has been still for
  :data:`SETTLE_S` and stays still for at least :data:`MIN_REST_S`, the mean over that rest of
  ``model(q) - k (theta - q)``: what the model says the arm needs at that pose minus what the springs
  carry. At rest the links are in equilibrium, so the arm's true holding torque ``g(q)`` is carried by
  the springs and the pilot together: ``pilot = g(q) - springs``. The indicator is that with the model
  standing in for ``g``: its error is the model's own error at the pose, plus what the estimate adds
  (the encoders' resolution, friction, a rest not quite still), which docs/online.md measures.
* **The support delivered** (a level, 0-1): over the rests, ``sum(springs . model) / sum(model . model)``:
  the share of the model's torque the springs actually carry, against the level the operator asked.
* **Transparency while moving** (Nm per joint, Nms/rad per joint): while a joint moves faster than
  :data:`MOVING_RAD_S`, the interaction torque ``model(q) - springs + J a`` (``J``: the link's inertia
  about its axis from the robot description, ``a`` the joint's acceleration between two
  observations): its RMS, and its slope against the joint's speed, the damping the pilot feels.

Everything here is plain numpy on a few numbers per observation (the session observes at
:data:`OBSERVE_PERIOD_S` of robot time, in the service between ticks): nothing here runs in the tick.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hal.robot import N_JOINTS, FloatArray

#: The session observes the loop this often (s of robot time): 50 Hz, the web console's rate.
OBSERVE_PERIOD_S = 0.02
#: Every joint slower than this (rad/s): the arm is still.
STILL_RAD_S = 0.03
#: A still arm's first part is left out (s): the springs and the pilot settle after a motion.
SETTLE_S = 0.3
#: A rest shorter than this (s, after settling) gives no figure.
MIN_REST_S = 0.5
#: Observations the stillness is judged over (the arm moved less than STILL_RAD_S x their span).
HISTORY = 5
#: A joint faster than this (rad/s) is moving: its samples count for transparency.
MOVING_RAD_S = 0.1
#: At most this many rests are kept (the session's record); the summary is over all of them.
MAX_RESTS = 500
#: Transparency's slope needs this many moving samples of a joint, over this spread of speed (rad/s).
MIN_MOVING_SAMPLES = 50
MIN_SPEED_SPREAD_RAD_S = 0.2


@dataclass(frozen=True)
class Rest:
    """One rest of the arm under compensation: where, how long, and what the pilot carried there."""

    t_start_s: float
    t_end_s: float
    pose_rad: tuple[float, ...]
    effort_nm: tuple[float, ...]  # model(q) - springs, mean over the rest, per joint
    level_asked: float
    level_delivered: float | None  # measured: sum(springs . model) / sum(model . model); None: no model torque

    def as_dict(self) -> dict[str, Any]:
        return {
            "t_start_s": round(self.t_start_s, 3),
            "t_end_s": round(self.t_end_s, 3),
            "pose_deg": [round(float(np.rad2deg(v)), 2) for v in self.pose_rad],
            "effort_nm": [round(v, 4) for v in self.effort_nm],
            "level_asked": self.level_asked,
            "level_delivered": None if self.level_delivered is None else round(self.level_delivered, 4),
        }


@dataclass
class _Accumulator:
    """Sums over the samples of one rest in progress."""

    t_start_s: float
    n: int = 0
    pose: FloatArray = field(default_factory=lambda: np.zeros(N_JOINTS))
    effort: FloatArray = field(default_factory=lambda: np.zeros(N_JOINTS))
    springs_dot_model: float = 0.0
    model_dot_model: float = 0.0
    level_asked: float = 0.0
    t_end_s: float = 0.0

    def rest(self) -> Rest | None:
        """The rest these sums make, or None while it is shorter than :data:`MIN_REST_S`."""
        if self.n == 0 or self.t_end_s - self.t_start_s < MIN_REST_S:
            return None
        delivered = self.springs_dot_model / self.model_dot_model if self.model_dot_model > 1e-9 else None
        return Rest(
            self.t_start_s,
            self.t_end_s,
            tuple(float(v) for v in self.pose / self.n),
            tuple(float(v) for v in self.effort / self.n),
            self.level_asked,
            delivered,
        )


@dataclass(frozen=True)
class OnlineSummary:
    """The indicators so far (per joint tuples of 4; None where nothing was measured yet)."""

    rests: int
    last_rest: Rest | None
    effort_at_rest_rms_nm: tuple[float, ...] | None  # over every rest
    level_delivered: float | None  # over every rest
    moving_samples: tuple[int, ...]
    interaction_rms_nm: tuple[float | None, ...]
    apparent_damping_nms_per_rad: tuple[float | None, ...]

    def as_dict(self) -> dict[str, Any]:
        def rounded(values: tuple[float | None, ...] | None, digits: int = 4) -> list[float | None] | None:
            return None if values is None else [None if v is None else round(v, digits) for v in values]

        return {
            "rests": self.rests,
            "last_rest": None if self.last_rest is None else self.last_rest.as_dict(),
            "effort_at_rest_rms_nm": rounded(self.effort_at_rest_rms_nm),
            "level_delivered": None if self.level_delivered is None else round(self.level_delivered, 4),
            "moving_samples": list(self.moving_samples),
            "interaction_rms_nm": rounded(self.interaction_rms_nm),
            "apparent_damping_nms_per_rad": rounded(self.apparent_damping_nms_per_rad),
        }


class OnlineIndicators:
    """The indicators of one stretch of compensation with one model (start anew with :meth:`reset`).

    Args:
        inertia_kgm2: each link's inertia about its joint axis (4,), kg m^2, for the interaction
            torque while moving (the robot description's; the pilot's arm as the description holds it).
    """

    def __init__(self, inertia_kgm2: FloatArray) -> None:
        self._inertia = np.asarray(inertia_kgm2, dtype=float).copy()
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new model, or compensation entered anew)."""
        self._rests: list[Rest] = []
        self._still_since_s: float | None = None
        self._current: _Accumulator | None = None
        #: the last observations (t, q, springs, model, level): speed and acceleration from the angles
        self._history: deque[tuple[float, FloatArray, FloatArray, FloatArray, float, bool]] = deque(maxlen=HISTORY)
        # per joint sums for the RMS and the line interaction = c + b * speed
        self._n = np.zeros(N_JOINTS, dtype=int)
        self._sum_y2 = np.zeros(N_JOINTS)
        self._sum_v = np.zeros(N_JOINTS)
        self._sum_v2 = np.zeros(N_JOINTS)
        self._sum_y = np.zeros(N_JOINTS)
        self._sum_vy = np.zeros(N_JOINTS)
        self._v_min = np.full(N_JOINTS, np.inf)
        self._v_max = np.full(N_JOINTS, -np.inf)
        self._springs_dot_model = 0.0
        self._model_dot_model = 0.0
        self._effort_sq = np.zeros(N_JOINTS)
        self._rest_total = 0  # every rest, also those no longer kept

    def interrupt(self) -> None:
        """Compensation paused (another state, a fault, the entry's handover): a rest ends, no acceleration spans it."""
        self._end_rest()
        self._still_since_s = None
        self._history.clear()

    def still_for_s(self, t_s: float) -> float:
        """How long the arm has been still at ``t_s`` (s; 0 while it moves), judged from the angles."""
        return 0.0 if self._still_since_s is None else max(t_s - self._still_since_s, 0.0)

    @property
    def rests(self) -> list[Rest]:
        """Every rest so far (at most :data:`MAX_RESTS`, the newest kept), oldest first."""
        return list(self._rests)

    def observe(
        self,
        t_s: float,
        q_rad: FloatArray,
        springs_nm: FloatArray,
        model_nm: FloatArray,
        level_asked: float,
        handing_over: bool = False,
    ) -> None:
        """One observation (4,) arrays: angles, the springs' torque, the model's torque at full support.

        ``handing_over``: the entry's handover still adds to the support (the springs carry more
        than the level of the model): the pilot's effort counts, the support delivered does not.

        Speed and acceleration come from the angles of the last observations (the drives' speed
        estimate is too noisy to tell a still arm: 0.04 rad/s median at rest in the simulator), so a
        figure lags one observation. Observations must come in order of ``t_s``; a gap longer than
        three periods starts anew; non-finite values are skipped (the safety monitor acts on them).
        """
        q = np.array(q_rad, dtype=float)
        springs = np.array(springs_nm, dtype=float)
        model = np.array(model_nm, dtype=float)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(springs)) and np.all(np.isfinite(model))):
            return
        history = self._history
        if history and not 0.0 < t_s - history[-1][0] <= 3 * OBSERVE_PERIOD_S:
            self.interrupt()
        history.append((t_s, q, springs, model, level_asked, handing_over))
        if len(history) < 3:
            return
        (t0, q0, *_), (t1, q1, springs1, model1, level1, handing1), (t2, q2, *_) = history[-3], history[-2], history[-1]
        speed = (q2 - q0) / (t2 - t0)
        acceleration = 2.0 * ((q2 - q1) / (t2 - t1) - (q1 - q0) / (t1 - t0)) / (t2 - t0)
        angles = np.array([entry[1] for entry in history])
        span_s = history[-1][0] - history[0][0]
        still = len(history) == HISTORY and float(np.ptp(angles, axis=0).max()) < STILL_RAD_S * span_s
        if still:
            self._still(t1, q1, springs1, model1, level1, handing1)
        else:
            self._end_rest()
            self._still_since_s = None
        self._moving(speed, acceleration, springs1, model1)

    def _still(
        self, t_s: float, q: FloatArray, springs: FloatArray, model: FloatArray, level_asked: float, handing_over: bool
    ) -> None:
        if self._still_since_s is None:
            self._still_since_s = t_s
        if t_s - self._still_since_s < SETTLE_S:
            return
        rest = self._current
        if rest is None or rest.level_asked != level_asked:  # a new level asked: a new rest
            self._end_rest()
            rest = self._current = _Accumulator(t_s, level_asked=level_asked)
        rest.n += 1
        rest.pose += q
        rest.effort += model - springs
        if not handing_over:  # the springs carry the level of the model (plus nothing else)
            rest.springs_dot_model += float(springs @ model)
            rest.model_dot_model += float(model @ model)
        rest.t_end_s = t_s

    def _end_rest(self) -> None:
        current, self._current = self._current, None
        rest = None if current is None else current.rest()
        if current is None or rest is None:
            return
        self._rests.append(rest)
        del self._rests[:-MAX_RESTS]
        self._rest_total += 1
        self._effort_sq += np.square(rest.effort_nm)
        self._springs_dot_model += current.springs_dot_model
        self._model_dot_model += current.model_dot_model

    def _moving(self, speed: FloatArray, acceleration: FloatArray, springs: FloatArray, model: FloatArray) -> None:
        interaction = model - springs + self._inertia * acceleration
        moving = np.abs(speed) > MOVING_RAD_S
        if not moving.any():
            return
        self._n += moving
        self._sum_y2 += np.where(moving, interaction * interaction, 0.0)
        self._sum_y += np.where(moving, interaction, 0.0)
        self._sum_v += np.where(moving, speed, 0.0)
        self._sum_v2 += np.where(moving, speed * speed, 0.0)
        self._sum_vy += np.where(moving, speed * interaction, 0.0)
        self._v_min = np.where(moving, np.minimum(self._v_min, speed), self._v_min)
        self._v_max = np.where(moving, np.maximum(self._v_max, speed), self._v_max)

    def summary(self) -> OnlineSummary:
        """The indicators so far; a rest in progress counts once it is long enough."""
        rests = list(self._rests)
        effort_sq = self._effort_sq.copy()
        count = self._rest_total
        springs_dot_model, model_dot_model = self._springs_dot_model, self._model_dot_model
        current = self._current
        in_progress = None if current is None else current.rest()
        if current is not None and in_progress is not None:  # a rest in progress counts once long enough
            rests.append(in_progress)
            effort_sq += np.square(in_progress.effort_nm)
            count += 1
            springs_dot_model += current.springs_dot_model
            model_dot_model += current.model_dot_model
        rms = tuple(float(v) for v in np.sqrt(effort_sq / count)) if count else None
        interaction: list[float | None] = []
        damping: list[float | None] = []
        for j in range(N_JOINTS):
            n = int(self._n[j])
            interaction.append(float(np.sqrt(self._sum_y2[j] / n)) if n else None)
            spread = self._v_max[j] - self._v_min[j]
            if n < MIN_MOVING_SAMPLES or not spread >= MIN_SPEED_SPREAD_RAD_S:
                damping.append(None)
                continue
            variance = self._sum_v2[j] / n - (self._sum_v[j] / n) ** 2
            covariance = self._sum_vy[j] / n - (self._sum_v[j] / n) * (self._sum_y[j] / n)
            damping.append(float(covariance / variance) if variance > 1e-12 else None)
        return OnlineSummary(
            rests=count,
            last_rest=rests[-1] if rests else None,
            effort_at_rest_rms_nm=rms,
            level_delivered=springs_dot_model / model_dot_model if model_dot_model > 1e-9 else None,
            moving_samples=tuple(int(v) for v in self._n),
            interaction_rms_nm=tuple(interaction),
            apparent_damping_nms_per_rad=tuple(damping),
        )


__all__ = [
    "MIN_REST_S",
    "MOVING_RAD_S",
    "OBSERVE_PERIOD_S",
    "SETTLE_S",
    "STILL_RAD_S",
    "OnlineIndicators",
    "OnlineSummary",
    "Rest",
]
