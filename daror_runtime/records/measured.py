"""What a session's own validation run measures of the pilot's elbow, beside what his model holds.

A returning pilot's model is re-validated, not retrained (D214), so its parameters stay those of
the session that trained it: the model's elbow stiffness does not follow his. His elbow does show in
the session's validation run: where the model misses a change of his elbow's stiffness, the elbow's
residual (measured minus predicted torque, Nm) grows with the elbow angle. Its slope over the run's
points (a least-squares line, Nm/rad) is the stiffness his elbow gained since the model's data; the
model's own stiffness plus it is his elbow's stiffness today, as long as his arm's weight did not
change (the forearm's gravity torque also changes with the elbow angle; the report says so).

Design time, never in the tick: the report reads the files the records index, each checked against
its recorded hash first.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daror_runtime.data.checksum import file_sha256
from daror_runtime.errors import DarorError

ELBOW = 3  # joint 4
#: Fewer validation points than this, or a narrower elbow span, cannot give a slope worth reading.
MIN_POINTS = 5
MIN_ELBOW_SPAN_DEG = 10.0


@dataclass(frozen=True)
class ElbowToday:
    """The elbow's residual on a session's validation run, against the model in use."""

    slope_nm_per_rad: float  # d(measured - predicted)/d(elbow angle): the stiffness gained since the model's data
    points: int
    span_deg: float  # the elbow angles the run covered


def _checked(path: str, sha256: str | None, what: str) -> Path:
    source = Path(path)
    if not source.is_file():
        raise MeasureError(f"{what} {path}: missing")
    if sha256 is not None and file_sha256(source) != sha256:
        raise MeasureError(f"{what} {path}: changed since it was recorded")
    return source


class MeasureError(DarorError):
    """A file the measure needs is missing or changed, or the run cannot give a slope (the reason named)."""


def elbow_today(model_path: str, model_sha256: str, validation_path: str, validation_sha256: str) -> ElbowToday:
    """The slope of the elbow's residual over the validation run's points (Nm/rad) under the model.

    Raises:
        MeasureError: a file missing or not the one recorded, a file that does not load, fewer than
            :data:`MIN_POINTS` points, or an elbow span under :data:`MIN_ELBOW_SPAN_DEG`.
    """
    from daror_runtime.data.load import load_stationary
    from daror_runtime.models.files import load_model
    from daror_runtime.residual.data import prediction_signal

    model_file = _checked(model_path, model_sha256, "model")
    data_file = _checked(validation_path, validation_sha256, "validation run")
    try:
        model, _ = load_model(model_file)
        data = load_stationary(data_file)
        predicted = model.predict(data.q_rad, prediction_signal(model, data, data_file))
    except DarorError as error:
        raise MeasureError(str(error)) from error
    elbow_rad = data.q_rad[:, ELBOW]
    residual_nm = data.tau_nm[:, ELBOW] - predicted[:, ELBOW]
    span_deg = float(np.rad2deg(np.ptp(elbow_rad))) if len(elbow_rad) else 0.0
    if len(elbow_rad) < MIN_POINTS:
        raise MeasureError(f"validation run {validation_path}: {len(elbow_rad)} points, fewer than {MIN_POINTS}")
    if span_deg < MIN_ELBOW_SPAN_DEG:
        raise MeasureError(
            f"validation run {validation_path}: the elbow spans {span_deg:.1f} deg, under {MIN_ELBOW_SPAN_DEG:g}"
        )
    slope, _ = np.polyfit(elbow_rad, residual_nm, 1)
    return ElbowToday(float(slope), len(elbow_rad), span_deg)


__all__ = ["ElbowToday", "MeasureError", "elbow_today"]
