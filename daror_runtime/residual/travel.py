"""Direction offset or hysteresis: the travel constants fitted, and the choice made by the evidence.

The diagnosis first runs with the sign of each joint's last motion as the direction signal
(:mod:`.diagnosis`). When it found a direction offset and the joints' path is known
(:class:`~daror_runtime.residual.hysteresis.PointHistory`: the raw log, else the points in order),
this module:

1. fits the travel constants ``r_j`` of the hysteresis (:mod:`.hysteresis`): the structure the
   diagnosis found, refitted with the signal ``s_j(r)`` in place of the sign, on a logarithmic
   grid of one ``r`` for all joints, then each joint's own ``r_j`` by a bounded scalar search
   around it (least squares on the training data: the hysteresis amplitude is linear);
2. runs the diagnosis again with that signal, where the ``hysteresis`` family takes the
   direction offset's place;
3. keeps whichever of the two diagnoses has the lower BIC, the travel constants counted as
   parameters: a pure direction offset stays a direction offset (its data gain nothing from a
   travel), a hysteresis that the sign describes only in part becomes one.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.residual.diagnosis import Diagnosis, bic, diagnose
from daror_runtime.residual.evidence import DiagnosisSettings
from daror_runtime.residual.hysteresis import PointHistory
from daror_runtime.residual.structure import Structure, fit_structure
from hal.robot import N_JOINTS, FloatArray, RobotDescription

#: Travel constants tried for all joints at once (rad): 0.2 mrad (a sign) to 50 mrad (3 degrees).
TRAVEL_GRID_RAD = np.geomspace(2e-4, 5e-2, 25)


@dataclass(frozen=True)
class TravelChoice:
    """What the choice between the direction offset and the hysteresis measured."""

    diagnosis: Diagnosis  # the one kept
    hysteresis: bool  # True: the hysteresis was kept
    travel_rad: FloatArray  # the fitted travel constants (also when the direction offset was kept)
    bic_direction: float
    bic_hysteresis: float  # travel constants counted
    profile: list[tuple[float, float]]  # (one travel for all joints, training RMSE in Nm): the grid
    from_raw_log: bool


def with_signal(data: StationaryDataset, history: PointHistory, travel_rad: FloatArray | float) -> StationaryDataset:
    """``data`` with its direction signal replaced by the hysteresis state for ``travel_rad``."""
    return dataclasses.replace(data, direction=history.states(travel_rad))


def _rmse(structure: Structure, data: StationaryDataset, history: PointHistory, travel_rad: FloatArray) -> float:
    fit = fit_structure(structure, with_signal(data, history, travel_rad))
    return math.sqrt(fit.rss / fit.n_rows)


def fit_travel(
    structure: Structure, train: StationaryDataset, history: PointHistory, joints: tuple[int, ...]
) -> tuple[FloatArray, list[tuple[float, float]]]:
    """Travel constants (rad, per joint) that fit ``structure`` best with the hysteresis signal, and the grid's profile.

    ``joints`` (0-based) are those with a direction column; the others keep the grid's best value
    (their column is not in the model, so it does not matter).
    """
    profile = [(float(r), _rmse(structure, train, history, np.full(N_JOINTS, r))) for r in TRAVEL_GRID_RAD]
    best = int(np.argmin([rmse for _, rmse in profile]))
    travel = np.full(N_JOINTS, TRAVEL_GRID_RAD[best])
    lo = math.log(TRAVEL_GRID_RAD[max(best - 1, 0)])
    hi = math.log(TRAVEL_GRID_RAD[min(best + 1, len(TRAVEL_GRID_RAD) - 1)])
    for j in joints:

        def objective(log_r: float, j: int = j) -> float:
            trial = travel.copy()
            trial[j] = math.exp(log_r)
            return _rmse(structure, train, history, trial)

        result = scipy.optimize.minimize_scalar(objective, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3})
        travel[j] = math.exp(float(result.x))
    return travel, profile


def choose_direction_signal(
    first: Diagnosis,
    train: StationaryDataset,
    history: PointHistory,
    description: RobotDescription,
    settings: DiagnosisSettings,
    dummy_arm: bool = False,
) -> TravelChoice | None:
    """Direction offset or hysteresis for the diagnosis ``first`` (run with the sign); None when it found no direction offset."""
    structure = first.final_fit.structure
    joints = tuple(sorted(e.joint - 1 for e in structure.effects if e.family == "direction_offset"))  # type: ignore[operator]
    if not joints:
        return None
    travel, profile = fit_travel(structure, train, history, joints)
    second = diagnose(
        with_signal(train, history, travel), description, first.base_kind, settings, dummy_arm, travel_rad=travel
    )
    found = sum(1 for f in second.found if f.effect.family == "hysteresis")
    bic_direction = bic(first.final_fit)
    bic_hysteresis = bic(second.final_fit) + found * math.log(second.final_fit.n_rows)
    keep = found > 0 and bic_hysteresis < bic_direction
    return TravelChoice(
        second if keep else first, keep, travel, bic_direction, bic_hysteresis, profile, history.from_raw_log
    )
