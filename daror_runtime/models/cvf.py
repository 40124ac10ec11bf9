"""Is a model a conservative vector field? The closed-path energy test (Sec. 4.4.4, 5.2, Table IV).

The path leaves a start configuration and steps +pi/4 in joint 1, then joint 2, 3 and 4, then
-pi/4 in joint 1, 2, 3 and 4, back to the start (Fig. 5.3). The work the model's torque does
along it is summed step by step, ``dV = sum tau(q_k) . dq`` (Eq. 4.33, a left Riemann sum). For
a conservative field the exact closed-path integral is zero and the sum's error shrinks in
proportion to the step; a non-conservative field keeps a net ``dV`` however fine the step.

Verdict: *conservative* when, from each step size to the next (ten times smaller), ``|dV|``
falls at least :data:`SHRINK_FACTOR` times, or is already below :data:`ENERGY_FLOOR_J`.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from daror_runtime.errors import UsageError
from hal.robot import N_JOINTS, FloatArray

THESIS_STEPS_RAD = (np.pi / 400, np.pi / 4000, np.pi / 40000)
PATH_AMPLITUDE_RAD = np.pi / 4
#: |dV| must shrink at least this much for a ten times smaller step (first order predicts 10).
SHRINK_FACTOR = 5.0
#: Below this, |dV| (J) is numerical noise whatever the trend.
ENERGY_FLOOR_J = 1e-9


@dataclass(frozen=True)
class CvfStep:
    step_rad: float
    energy_j: float

    def to_dict(self) -> dict[str, float]:
        return {"dq": self.step_rad, "dV": self.energy_j}


@dataclass(frozen=True)
class CvfResult:
    steps: tuple[CvfStep, ...]
    conservative: bool
    start_rad: tuple[float, ...]


def closed_path(start_rad: Sequence[float], step_rad: float, amplitude_rad: float = PATH_AMPLITUDE_RAD) -> FloatArray:
    """Points of the closed 4-D path, first point repeated at the end; (K, 4)."""
    if not 0 < step_rad <= amplitude_rad:
        raise UsageError(f"step {step_rad} rad must be positive and at most the path amplitude {amplitude_rad} rad")
    n = round(amplitude_rad / step_rad)
    ramp = np.arange(1, n + 1) * (amplitude_rad / n)
    points = [np.asarray(start_rad, dtype=float)[None, :]]
    for sign in (1.0, -1.0):
        for j in range(N_JOINTS):
            segment = np.repeat(points[-1][-1:], n, axis=0)
            segment[:, j] += sign * ramp
            points.append(segment)
    return np.concatenate(points)


def closed_path_energy_j(torque_batch: Callable[[FloatArray], FloatArray], path: FloatArray) -> float:
    """``sum_k tau(q_k) . (q_{k+1} - q_k)`` along ``path`` (Eq. 4.33)."""
    torque = torque_batch(path[:-1])
    return float(np.sum(torque * np.diff(path, axis=0)))


def default_start(lower_rad: FloatArray, upper_rad: FloatArray) -> FloatArray:
    """A start that keeps the whole path inside the limits: centred in the range of motion."""
    return (np.asarray(lower_rad) + np.asarray(upper_rad)) / 2 - PATH_AMPLITUDE_RAD / 2


def cvf_test(
    torque_batch: Callable[[FloatArray], FloatArray],
    start_rad: Sequence[float],
    steps_rad: Sequence[float] = THESIS_STEPS_RAD,
) -> CvfResult:
    """Run the closed-path test at every step size (coarse to fine) and give the verdict."""
    steps = tuple(
        CvfStep(float(dq), closed_path_energy_j(torque_batch, closed_path(start_rad, dq)))
        for dq in sorted(steps_rad, reverse=True)
    )
    conservative = all(
        abs(fine.energy_j) <= ENERGY_FLOOR_J or abs(fine.energy_j) * SHRINK_FACTOR <= abs(coarse.energy_j)
        for coarse, fine in itertools.pairwise(steps)
    )
    return CvfResult(steps, conservative, tuple(float(v) for v in start_rad))
