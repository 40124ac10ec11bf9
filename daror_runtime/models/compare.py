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
    name: str
    kind: str
    metrics: ErrorMetrics


def evaluate_models(
    models: Sequence[CompensationModel],
    data: StationaryDataset,
    signals: Sequence[FloatArray | None] | None = None,
) -> list[Evaluation]:
    """Errors of every model on ``data`` (Eq. 4.31-4.32).

    ``signals``: the ``direction`` each model predicts with (None: the dataset's ``dir`` for all;
    a model whose reading carries a hysteresis needs its state, see
    ``daror_runtime.residual.data.prediction_signal``).
    """
    directions = list(signals) if signals is not None else [data.direction] * len(models)
    return [
        Evaluation(m.name, m.kind, error_metrics(data.tau_nm, m.predict(data.q_rad, d)))
        for m, d in zip(models, directions, strict=True)
    ]


def evaluation_document(evaluations: Sequence[Evaluation]) -> dict[str, Any]:
    """``{"models": [{"name", "kind", "rmse", "nrmse", "rmse_per_joint": [4]}]}`` (docs/models.md)."""
    return {
        "models": [
            {
                "name": e.name,
                "kind": e.kind,
                "rmse": e.metrics.rmse_nm,
                "nrmse": e.metrics.nrmse,
                "rmse_per_joint": list(e.metrics.rmse_per_joint_nm),
            }
            for e in evaluations
        ]
    }


def evaluation_table(evaluations: Sequence[Evaluation], title: str) -> Table:
    """Table III style: RMSE (Nm), nRMSE and RMSE per joint."""
    table = Table(title=title)
    for header in ("Model", "Kind", "RMSE (Nm)", "nRMSE ( )", "J1", "J2", "J3", "J4"):
        table.add_column(header, justify="left" if header in ("Model", "Kind") else "right")
    for e in evaluations:
        table.add_row(
            e.name,
            e.kind,
            f"{e.metrics.rmse_nm:.3g}",
            f"{e.metrics.nrmse:.3g}",
            *(f"{v:.3g}" for v in e.metrics.rmse_per_joint_nm),
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
