"""Candidate poses of a designed protocol: where inside the pilot's ISB limits the robot may stop.

Candidates are a scrambled Sobol sample (``scipy.stats.qmc``, seeded: the same seed gives the same
set) of the pilot's ISB box, shrunk by a margin so that a stop never sits on a limit. A sample is
kept when the robot reaches it inside its joint limits (with the same margin) on the ``q2 > 0``
branch every trajectory uses (the path cannot cross the singularity at ``q2 = 0``), and the
shoulder Jacobian's smallest singular value stays clear of the trajectory check's minimum.

When poses are approached from both directions each candidate gets two *via* poses, ``q + delta s``
and ``q - delta s`` in joint space (``s`` a sign per joint, the first of the eight patterns with
both vias inside every limit): the robot passes through one, stops at ``q`` (every joint arrives
moving by ``-delta s``), passes through the other and stops again (every joint arrives moving by
``+delta s``). ``delta`` (3 deg by default) is ten times the 5 mrad after which the SEA's direction
error has reversed (docs/simulation.md), so both stops see it fully, with opposite signs.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from hal.isb import AngleRange, IsbLimits, Shoulder
from hal.robot import N_JOINTS, FloatArray

__all__ = ["Candidates", "candidate_poses", "shrunk"]

#: A range narrower than twice the margin keeps this much around its middle, degrees.
_NARROWEST_DEG = 0.01
#: Sign patterns of the via offset: joint 1 always +1 (a pattern and its negative give the same vias).
_PATTERNS = np.array([(1.0, *rest) for rest in itertools.product((1.0, -1.0), repeat=N_JOINTS - 1)])


@dataclass(frozen=True)
class Candidates:
    """Poses a design may choose from; rows match across the arrays (angles in rad).

    ``via_up_q``/``via_down_q`` (and their ISB angles) are ``None`` when poses are approached once.
    """

    isb: FloatArray  # (C, 4)
    q: FloatArray  # (C, 4)
    via_up_q: FloatArray | None
    via_down_q: FloatArray | None
    via_up_isb: FloatArray | None
    via_down_isb: FloatArray | None
    sampled: int  # how many Sobol points were drawn

    def __len__(self) -> int:
        return int(self.q.shape[0])

    @property
    def paired(self) -> bool:
        return self.via_up_q is not None


def shrunk(limits: IsbLimits, margin_deg: float) -> IsbLimits:
    """``limits`` with every range narrowed by ``margin_deg`` on both sides (a range too narrow
    for it collapses to its middle)."""

    def narrower(r: AngleRange) -> AngleRange:
        lo, hi = r.lower_deg + margin_deg, r.upper_deg - margin_deg
        if hi - lo < _NARROWEST_DEG:
            middle = 0.5 * (r.lower_deg + r.upper_deg)
            lo, hi = middle - 0.5 * _NARROWEST_DEG, middle + 0.5 * _NARROWEST_DEG
        return AngleRange(lower_deg=lo, upper_deg=hi)

    return IsbLimits(
        elevation=narrower(limits.elevation),
        horizontal_rotation=narrower(limits.horizontal_rotation),
        axial_rotation=narrower(limits.axial_rotation),
        elbow=narrower(limits.elbow),
        horizontal_free_below_deg=limits.horizontal_free_below_deg,
    )


def _solve(shoulder: Shoulder, isb: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Joint angles (N, 4) of ISB poses (N, 4) and whether each is reachable (N,); NaN where not."""
    q = shoulder.q_from_isb(isb, unreachable_as_nan=True)
    return q, np.all(np.isfinite(q), axis=1)


def _usable(
    shoulder: Shoulder, q: FloatArray, isb_limits: IsbLimits, joint_margin_rad: float, min_sigma: float
) -> FloatArray:
    """(N,) bool: inside the joint limits by the margin, q2 > 0, sigma_min high enough, ISB inside."""
    finite = np.all(np.isfinite(q), axis=1)
    safe_q = np.where(finite[:, None], q, shoulder.q_neutral)
    inside = np.all(
        (safe_q >= shoulder.lower_rad + joint_margin_rad) & (safe_q <= shoulder.upper_rad - joint_margin_rad), axis=1
    )
    sigma = np.asarray(shoulder.sigma_min(safe_q)) >= min_sigma
    isb_ok = np.asarray(isb_limits.contains(shoulder.isb_from_q(safe_q)))
    return finite & inside & sigma & (safe_q[:, 1] > 0.0) & isb_ok


def candidate_poses(
    shoulder: Shoulder,
    limits: IsbLimits,
    count: int,
    seed: int,
    margin_deg: float,
    min_sigma: float,
    via_deg: float | None,
) -> Candidates:
    """Candidate poses inside ``limits`` (see the module docstring).

    Args:
        shoulder: the robot's shoulder (joint limits, kinematics).
        limits: the pilot's ISB limits.
        count: Sobol points drawn (a power of two keeps the sequence balanced).
        seed: scrambling seed.
        margin_deg: distance kept from every ISB and joint limit, degrees.
        min_sigma: smallest singular value of the shoulder Jacobian at a pose or via.
        via_deg: joint offset of the vias, degrees; ``None``: poses are approached once.
    """
    # here: scipy.stats takes ~0.4 s to import, and a session imports this module without designing
    from scipy.stats import qmc

    inner = shrunk(limits, margin_deg)
    lo, hi = inner.lower_rad, inner.upper_rad
    sample = qmc.Sobol(d=N_JOINTS, scramble=True, seed=seed).random(count)
    isb = lo + sample * (hi - lo)
    q, reachable = _solve(shoulder, isb)
    margin = float(np.deg2rad(margin_deg))
    keep = reachable & _usable(shoulder, q, inner, margin, min_sigma)
    isb, q = isb[keep], q[keep]
    if via_deg is None:
        return Candidates(isb, q, None, None, None, None, count)
    delta = float(np.deg2rad(via_deg))
    via_margin = 0.25 * margin
    via_limits = shrunk(limits, 0.25 * margin_deg)
    chosen = np.full(q.shape[0], -1)
    up = np.full_like(q, np.nan)
    down = np.full_like(q, np.nan)
    for k, pattern in enumerate(_PATTERNS):
        todo = chosen < 0
        if not todo.any():
            break
        a, b = q[todo] + delta * pattern, q[todo] - delta * pattern
        # The via must be the pose the trajectory generator solves for (same branch), inside everything.
        ok = _usable(shoulder, a, via_limits, via_margin, min_sigma) & _usable(
            shoulder, b, via_limits, via_margin, min_sigma
        )
        ok &= _same_branch(shoulder, a) & _same_branch(shoulder, b)
        rows = np.flatnonzero(todo)[ok]
        chosen[rows] = k
        up[rows], down[rows] = a[ok], b[ok]
    keep = chosen >= 0
    up, down = up[keep], down[keep]
    return Candidates(isb[keep], q[keep], up, down, shoulder.isb_from_q(up), shoulder.isb_from_q(down), count)


def _same_branch(shoulder: Shoulder, q: FloatArray) -> FloatArray:
    """(N,) bool: solving ``q``'s own ISB angles gives ``q`` back (the generator will reach it)."""
    finite = np.all(np.isfinite(q), axis=1)
    out = np.zeros(q.shape[0], dtype=bool)
    if not finite.any():
        return out
    back, ok = _solve(shoulder, shoulder.isb_from_q(q[finite]))
    close = ok & np.all(np.abs(np.nan_to_num(back, nan=1e9) - q[finite]) < 1e-6, axis=1)
    out[np.flatnonzero(finite)] = close
    return out
