"""Compare models: the Table III (errors) and Table IV (closed-path energy) of the thesis.

Computes, renders (rich tables for people) and serialises (the JSON of docs/models.md for
machines). ``daror evaluate``, ``daror cvf`` and the demo all go through here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from rich.table import Table

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.base import CompensationModel
from daror_runtime.models.cvf import THESIS_STEPS_RAD, CvfResult, cvf_test, default_start
from daror_runtime.models.extrapolation import TOLERANCE_RAD, Extrapolation, TrainingRange, extrapolation
from daror_runtime.models.metrics import ErrorMetrics, error_metrics
from hal.robot import FloatArray

#: Table III of the thesis: (RMSE A Nm, nRMSE A, RMSE B Nm, nRMSE B).
THESIS_TABLE_III: dict[str, tuple[float, float, float, float]] = {
    "ap": (0.909, 0.231, 1.21, 0.176),
    "plf": (0.476, 0.134, 1.24, 0.190),
    "plf+": (0.475, 0.140, 0.742, 9.32e-2),
    "penn": (1.18, 0.327, 2.38, 0.315),
    "nnn": (1.21, 0.338, 2.59, 0.345),
}
#: Table IV of the thesis: dV (J) at dq = pi/400, pi/4000, pi/40000.
THESIS_TABLE_IV: dict[str, tuple[float, float, float]] = {
    "plf": (0.014, 0.0014, 1.35e-4),
    "plf+": (0.013, 0.0013, 1.29e-4),
    "penn": (0.0178, 0.0018, 1.76e-4),
    "nnn": (-0.0223, -0.0298, -0.0305),
}


@dataclass(frozen=True)
class Evaluation:
    """One model's errors on a dataset; ``extrapolation``: the points outside its training range and its
    RMSE inside and outside it (None: the model has no training range)."""

    name: str
    kind: str
    metrics: ErrorMetrics
    extrapolation: Extrapolation | None = None


def distinct_labels(names: Sequence[str], paths: Sequence[object]) -> list[str]:
    """A label per model: its name, and where two models share a name, the shortest end of its file's path that
    tells it from the others of that name (``PLF+ (a/model_plf_plus.json)``, ``PLF+ (b/model_plf_plus.json)``).

    ``paths``: the files as given (``str()`` of each is split at ``/``). A path that is the end of
    another's is shown whole; the same path given twice also gets its position among the files (``#2``).
    """
    labels = list(names)
    shown = [str(p) for p in paths]
    for name in set(names):
        members = [i for i, n in enumerate(names) if n == name]
        if len(members) < 2:
            continue
        parts = {i: tuple(part for part in shown[i].split("/") if part not in ("", ".")) for i in members}
        for i in members:
            others = [parts[j] for j in members if j != i]
            for k in range(1, len(parts[i]) + 1):
                if all(other[-k:] != parts[i][-k:] for other in others):
                    labels[i] = f"{name} ({'/'.join(parts[i][-k:])})"
                    break
            else:  # its whole path ends another's (a/m.json, x/a/m.json), or is the very same path again
                again = any(other == parts[i] for other in others)
                labels[i] = f"{name} ({shown[i]}{f' #{i + 1}' if again else ''})"
    return labels


def evaluate_models(
    models: Sequence[CompensationModel],
    data: StationaryDataset,
    signals: Sequence[FloatArray | None] | None = None,
    training: Sequence[TrainingRange | None] | None = None,
) -> list[Evaluation]:
    """Errors of every model on ``data`` (Eq. 4.31-4.32), and where it extrapolates.

    ``signals``: the ``direction`` each model predicts with (None: the dataset's ``dir`` for all;
    a model whose reading carries a hysteresis needs its state, see
    ``daror_runtime.residual.data.prediction_signal``). ``training``: each model's training summary
    (its file's ``training``: the range it was trained on); None: no extrapolation figures.
    """
    directions = list(signals) if signals is not None else [data.direction] * len(models)
    ranges = list(training) if training is not None else [None] * len(models)
    out = []
    for model, direction, summary in zip(models, directions, ranges, strict=True):
        predicted = model.predict(data.q_rad, direction)
        out.append(
            Evaluation(
                model.name,
                model.kind,
                error_metrics(data.tau_nm, predicted),
                extrapolation(summary, data.q_rad, data.tau_nm, predicted),
            )
        )
    return out


def evaluation_document(evaluations: Sequence[Evaluation]) -> dict[str, Any]:
    """``{"models": [{"name", "kind", "rmse", "nrmse", "rmse_per_joint": [4], "training_range"}]}`` (docs/models.md).

    ``training_range``: :meth:`Extrapolation.to_dict` (points outside the model's training range, the
    RMSE inside and outside it), or null for a model without one.
    """
    return {
        "models": [
            {
                "name": e.name,
                "kind": e.kind,
                "rmse": e.metrics.rmse_nm,
                "nrmse": e.metrics.nrmse,
                "rmse_per_joint": list(e.metrics.rmse_per_joint_nm),
                "training_range": None if e.extrapolation is None else e.extrapolation.to_dict(),
            }
            for e in evaluations
        ]
    }


def _nm(value: float | None) -> str:
    return "-" if value is None else f"{value:.3g}"


def evaluation_table(evaluations: Sequence[Evaluation], title: str) -> Table:
    """Table III style: RMSE (Nm), nRMSE and RMSE per joint; then the points outside each model's training
    range (any joint more than :data:`~daror_runtime.models.extrapolation.TOLERANCE_RAD` beyond it) and
    the RMSE inside and outside it ("-": none, or no training range)."""
    table = Table(title=title)
    table.add_column("Model", overflow="fold")  # a label's path is what tells two models apart: never cut
    table.add_column("Kind")
    for header in ("RMSE (Nm)", "nRMSE ( )", "J1", "J2", "J3", "J4", "outside", "RMSE in", "RMSE out"):
        table.add_column(header, justify="right")
    for e in evaluations:
        x = e.extrapolation
        table.add_row(
            e.name,
            e.kind,
            f"{e.metrics.rmse_nm:.3g}",
            f"{e.metrics.nrmse:.3g}",
            *(f"{v:.3g}" for v in e.metrics.rmse_per_joint_nm),
            "-" if x is None else f"{x.n_outside}/{x.n_points}",
            "-" if x is None else _nm(x.rmse_inside_nm),
            "-" if x is None else _nm(x.rmse_outside_nm),
        )
    table.caption = (
        f"outside: points with a joint more than {TOLERANCE_RAD:g} rad beyond the model's training range "
        "(q_min_rad..q_max_rad of its file); RMSE in/out (Nm): over the points inside/outside it"
    )
    return table


@dataclass(frozen=True)
class CvfEvaluation:
    name: str
    kind: str
    result: CvfResult


def cvf_models(
    models: Sequence[CompensationModel],
    start_rad: Sequence[float] | None = None,
    steps_rad: Sequence[float] = THESIS_STEPS_RAD,
) -> list[CvfEvaluation]:
    """The closed-path test of every model; the default start is the centre of each robot's range."""
    out = []
    for model in models:
        d = model.description
        start = default_start(d.lower_limits_rad, d.upper_limits_rad) if start_rad is None else start_rad
        out.append(CvfEvaluation(model.name, model.kind, cvf_test(model.torque_batch, start, steps_rad)))
    return out


def cvf_document(evaluations: Sequence[CvfEvaluation]) -> dict[str, Any]:
    """``{"models": [{"name", "kind", "steps": [{"dq", "dV"}], "conservative": bool}]}``."""
    return {
        "models": [
            {
                "name": e.name,
                "kind": e.kind,
                "steps": [s.to_dict() for s in e.result.steps],
                "conservative": e.result.conservative,
            }
            for e in evaluations
        ]
    }


def cvf_table(evaluations: Sequence[CvfEvaluation], title: str = "Closed-path energy (Table IV)") -> Table:
    table = Table(title=title)
    table.add_column("Model")
    table.add_column("Kind")
    steps = evaluations[0].result.steps if evaluations else ()
    for s in steps:
        table.add_column(f"dV (J), dq = pi/{np.pi / s.step_rad:.0f}", justify="right")
    table.add_column("Verdict")
    for e in evaluations:
        verdict = "conservative" if e.result.conservative else "NOT conservative"
        table.add_row(e.name, e.kind, *(f"{s.energy_j:.3g}" for s in e.result.steps), verdict)
    return table
