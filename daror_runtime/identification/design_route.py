"""Robot time of a designed protocol and the order of its visits (a shortest-path tour).

Timing follows the trajectory generator's rule (:mod:`.trajectory_planning`, section 5 of
docs/identification.md): a move lasts ``max(min_move_s, 1.875 angle / v_shoulder, 1.875 |elbow
change| / v_elbow)`` rounded up to whole knot intervals, ``angle`` the rotation between the two
shoulder orientations; a stop lasts its own time; the run starts with the protocol's approach
(a minimum-jerk joint move from the start pose, at least ``min_approach_s``) and the settle hold.
The generator may stretch a move whose joints would exceed their speed limit; the design
therefore measures the built trajectory at the end (:mod:`.design`), this module only estimates.

The tour is a path from the start pose through every chosen pose: cheapest insertion while the
design grows it, then 2-opt (reverse a stretch) and relocation (move one pose elsewhere) until
neither shortens it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.identification.trajectory_planning import MIN_JERK_PEAK, TrajectorySettings
from hal.isb import IsbLimits, Shoulder, UnreachablePoseError
from hal.robot import FloatArray

IntArray = npt.NDArray[np.intp]
BoolArray = npt.NDArray[np.bool_]

__all__ = ["RouteTimes", "geodesic_leaves_limits", "improve_tour", "insertion_costs", "rotation_angles"]


def rotation_angles(a: FloatArray, b: FloatArray) -> FloatArray:
    """Angle (rad) of ``b_j a_i^T`` for rotations ``a`` (N, 3, 3) and ``b`` (M, 3, 3): (N, M)."""
    trace = a.reshape(a.shape[0], 9) @ b.reshape(b.shape[0], 9).T
    return np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0))


@dataclass(frozen=True)
class RouteTimes:
    """Estimated times (s) of the candidates' visits and of the moves between them.

    ``between[i, j]``: from where candidate ``i``'s visit ends to where ``j``'s begins;
    ``start[j]``: the approach and settle hold from the start pose to where ``j``'s visit begins;
    ``visit[j]``: the visit itself (stops, and the short moves between its vias and the pose).
    """

    between: FloatArray
    start: FloatArray
    visit: FloatArray

    def tour_time(self, tour: list[int]) -> float:
        """Robot time (s) of the tour, approach included; 0 for an empty tour."""
        if not tour:
            return 0.0
        index = np.asarray(tour)
        return float(self.start[index[0]] + self.between[index[:-1], index[1:]].sum() + self.visit[index].sum())


def move_duration_s(angle_rad: FloatArray, elbow_change_rad: FloatArray, settings: TrajectorySettings) -> FloatArray:
    """The generator's duration of a move (s) before any stretch for the joint-speed limit."""
    raw = np.maximum(
        settings.min_move_s,
        np.maximum(
            MIN_JERK_PEAK * np.asarray(angle_rad) / settings.shoulder_speed_rad_s,
            MIN_JERK_PEAK * np.abs(elbow_change_rad) / settings.elbow_speed_rad_s,
        ),
    )
    return np.ceil(raw * settings.knot_rate_hz - 1e-9) / settings.knot_rate_hz


def route_times(
    shoulder: Shoulder,
    entry_q: FloatArray,
    exit_q: FloatArray,
    visit_s: FloatArray,
    start_q: FloatArray,
    trajectory: TrajectorySettings,
    identification: IdentificationSettings,
) -> RouteTimes:
    """:class:`RouteTimes` of candidates entered at ``entry_q`` (C, 4) and left at ``exit_q`` (C, 4), rad."""
    entry_r, exit_r = shoulder.rotor3(entry_q), shoulder.rotor3(exit_q)
    angles = rotation_angles(exit_r, entry_r)
    elbow = exit_q[:, 3][:, None] - entry_q[:, 3][None, :]
    between = move_duration_s(angles, elbow, trajectory)
    distance = np.abs(entry_q - start_q).max(axis=1)
    start = np.array([identification.approach_duration_s(float(d)) for d in distance]) + identification.settle_s
    return RouteTimes(between, start, np.asarray(visit_s, dtype=float))


def insertion_costs(times: RouteTimes, tour: list[int], candidates: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Cheapest added time (s) and position (index in the tour) of inserting each candidate (K,)."""
    c = np.asarray(candidates)
    if not tour:
        return times.start[c] + times.visit[c], np.zeros(c.size, dtype=int)
    t = np.asarray(tour)
    options = [times.start[c] + times.between[c, t[0]] - times.start[t[0]]]  # in front
    if t.size > 1:
        a, b = t[:-1], t[1:]
        inner = times.between[a][:, c] + times.between[c][:, b].T - times.between[a, b][:, None]  # (k - 1, K)
        options.extend(inner)
    options.append(times.between[t[-1], c])  # at the end
    stacked = np.vstack(options)
    best = np.argmin(stacked, axis=0)
    return stacked[best, np.arange(c.size)] + times.visit[c], best


@lru_cache(maxsize=256)
def _reversal_index(n: int) -> tuple[IntArray, IntArray, IntArray, IntArray, BoolArray, BoolArray]:
    """The positions every 2-opt reversal of an ``n``-pose tour reads (arrays shared: read-only).

    Returns ``i``, ``k`` (``np.triu_indices(n, 1)``), ``max(i - 1, 0)``, ``min(k + 1, n - 1)``,
    ``i > 0`` and ``k >= n - 1``; they depend on ``n`` alone, and a tour is improved many times.
    """
    i, k = np.triu_indices(n, 1)
    out = (i, k, np.maximum(i - 1, 0), np.minimum(k + 1, n - 1), i > 0, k >= n - 1)
    for array in out:
        array.setflags(write=False)
    return out


def _best_reversal(times: RouteTimes, tour: FloatArray) -> tuple[float, int, int]:
    """The 2-opt move (reverse ``tour[i..k]``) that saves the most time: (saving s, i, k).

    With prefix sums of the edges forwards and backwards every reversal costs O(1), so all
    ``n (n - 1) / 2`` are evaluated at once (the moves' times need not be symmetric).
    """
    n = tour.size
    b, t = times.between, tour
    forward = np.concatenate([[0.0], np.cumsum(b[t[:-1], t[1:]])])  # forward[j]: edges 0..j-1
    backward = np.concatenate([[0.0], np.cumsum(b[t[1:], t[:-1]])])
    i, k, before_i, after_k, inner, last = _reversal_index(n)
    t_before, t_i, t_k, t_after = t[before_i], t[i], t[k], t[after_k]
    into_old = np.where(inner, b[t_before, t_i], times.start[t_i])
    into_new = np.where(inner, b[t_before, t_k], times.start[t_k])
    out_old = np.where(last, 0.0, b[t_k, t_after])
    out_new = np.where(last, 0.0, b[t_i, t_after])
    saving = (into_old + out_old + forward[k] - forward[i]) - (into_new + out_new + backward[k] - backward[i])
    best = int(np.argmax(saving))
    return float(saving[best]), int(i[best]), int(k[best])


@lru_cache(maxsize=256)
def _relocation_index(n: int) -> tuple[IntArray, ...]:
    """The positions every relocation in an ``n``-pose tour reads (arrays shared: read-only).

    Returns, for positions ``p = 0..n-1``: ``p``, ``p < n - 1``, ``min(p + 1, n - 1)``,
    ``max(p - 1, 0)``, ``p > 0``; for gaps ``g = 0..n``: ``max(g - 1, 0)``, ``min(g, n - 1)``,
    ``g > 0`` (1, n + 1), ``g < n`` (1, n + 1), ``g < n``, ``g > 0``.
    """
    position = np.arange(n)
    gap = np.arange(n + 1)
    out = (
        position,
        position < n - 1,
        np.minimum(position + 1, n - 1),
        np.maximum(position - 1, 0),
        position > 0,
        np.maximum(gap - 1, 0),
        np.minimum(gap, n - 1),
        gap[None, :] > 0,
        gap[None, :] < n,
        gap < n,
        gap > 0,
    )
    for array in out:
        array.setflags(write=False)
    return out


def _best_relocation(times: RouteTimes, tour: FloatArray) -> tuple[float, int, int]:
    """The single move of one pose elsewhere that saves the most time: (saving s, from, gap).

    Gap ``g`` is the place before ``tour[g]`` (``g = n``: at the end) in the tour as it is; all
    ``n (n + 1)`` moves are evaluated at once.
    """
    n = tour.size
    b, t = times.between, tour
    position, has_next, next_p, previous_p, not_first, before_g, after_g, gap_inner, gap_not_end, not_end, inner = (
        _relocation_index(n)
    )
    nxt = t[next_p]
    t_previous = t[previous_p]
    into = np.where(not_first, b[t_previous, t], times.start[t])
    out = np.where(has_next, b[t, nxt], 0.0)
    bridge = np.where(has_next, np.where(not_first, b[t_previous, nxt], times.start[nxt]), 0.0)
    removal = into + out - bridge  # (n,)
    before = t[before_g]
    after = t[after_g]
    # add[x, g]: pose x put into gap g
    to_x = np.where(gap_inner, b[before][:, t].T, times.start[t][:, None])
    from_x = np.where(gap_not_end, b[t][:, after], 0.0)
    old = np.where(not_end, np.where(inner, b[before, after], times.start[after]), 0.0)
    add = to_x + from_x - old[None, :]
    saving = removal[:, None] - add
    saving[position, position] = -np.inf  # its own place
    saving[position, position + 1] = -np.inf
    best = int(np.argmax(saving))
    source, target = divmod(best, n + 1)
    return float(saving[source, target]), source, target


def improve_tour(times: RouteTimes, tour: list[int], max_moves: int | None = None) -> list[int]:
    """The tour shortened by 2-opt reversals and single relocations until neither helps (the start stays).

    Every step applies the one move that saves the most; ``max_moves`` (default ``10 n``) bounds the work.
    """
    best = np.asarray(tour, dtype=int)
    if best.size < 2:
        return list(tour)
    for _ in range(10 * best.size if max_moves is None else max_moves):
        reversal, i, k = _best_reversal(times, best)
        relocation, source, target = _best_relocation(times, best)
        if max(reversal, relocation) <= 1e-9:
            break
        if reversal >= relocation:
            best = np.concatenate([best[:i], best[i : k + 1][::-1], best[k + 1 :]])
        else:
            node = best[source]
            best = np.insert(best, target, node)
            best = np.delete(best, source if source < target else source + 1)
    return [int(c) for c in best]


def geodesic_leaves_limits(
    shoulder: Shoulder,
    limits: IsbLimits,
    min_sigma: float,
    q_from: FloatArray,
    q_to: FloatArray,
    samples: int = 24,
) -> bool:
    """Whether the move ``q_from -> q_to`` (rad) would leave ``limits``, the joint limits or
    ``min_sigma``: the shoulder's geodesic sampled at ``samples`` points (a cheap check before the
    generator's exact one at every tick)."""
    r_from, r_to = shoulder.rotor3(q_from), shoulder.rotor3(q_to)
    relative = r_to @ r_from.T
    angle = float(np.arccos(np.clip(0.5 * (np.trace(relative) - 1.0), -1.0, 1.0)))
    if angle < 1e-9:
        return False
    axis = np.array([relative[2, 1] - relative[1, 2], relative[0, 2] - relative[2, 0], relative[1, 0] - relative[0, 1]])
    norm = float(np.linalg.norm(axis))
    if norm < 1e-9:  # a half turn: no move of a protocol is that long
        return True
    axis /= norm
    s = np.linspace(0.0, 1.0, samples + 2)[1:-1]
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    phi = angle * s
    rotations = np.eye(3) + np.sin(phi)[:, None, None] * k + (1.0 - np.cos(phi))[:, None, None] * (k @ k)
    elbow = q_from[3] + (q_to[3] - q_from[3]) * s
    try:
        q = shoulder.q_from_rotor3(rotations @ r_from, elbow, seed=q_from)
    except UnreachablePoseError:
        return True
    # Joints move at most 1 / sigma_min times as fast as the shoulder turns: a bigger step between
    # neighbouring samples means the nearest solution jumped to the other branch.
    step = (angle / max(min_sigma, 0.1) + abs(float(q_to[3] - q_from[3]))) / (samples + 1)
    if np.abs(np.diff(np.vstack([q_from, q, q_to]), axis=0)).max() > max(1.5 * step, math.radians(1.0)):
        return True
    if np.any(np.asarray(shoulder.sigma_min(q)) < min_sigma):
        return True
    return not bool(np.all(limits.contains(shoulder.isb_from_q(q))))
