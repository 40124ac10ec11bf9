"""Model error metrics of the thesis: RMSE (Eq. 4.31) and nRMSE (Eq. 4.32).

* ``rmse_nm``: root mean square over every joint of every point (Nm).
* ``rmse_per_joint_nm``: the same per joint (Nm).
* ``nrmse``: Eq. 4.32 as printed, ``sqrt(1/N sum_j sum_i ((tau_v - tau_m) / max_j)^2)``; the sum
  runs over the four joints while the mean is over the N points, so it is the root of the sum of
  the per-joint normalised mean squares. ``max_j`` is the peak *magnitude* of the validation
  torque of joint ``j`` (the thesis writes ``max(tau_v,j)``; a joint whose torque is mostly
  negative would otherwise divide by a small or negative number). Unitless.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hal.errors import ShapeError
from hal.robot import N_JOINTS, FloatArray


@dataclass(frozen=True)
class ErrorMetrics:
    """Errors of a model's torque against measured torque."""

    rmse_nm: float
    nrmse: float
    rmse_per_joint_nm: tuple[float, float, float, float]
    n_points: int

    def to_dict(self) -> dict[str, object]:
        return {
            "rmse": self.rmse_nm,
            "nrmse": self.nrmse,
            "rmse_per_joint": list(self.rmse_per_joint_nm),
            "n_points": self.n_points,
        }


def error_metrics(tau_measured_nm: FloatArray, tau_model_nm: FloatArray) -> ErrorMetrics:
    """RMSE, nRMSE and per-joint RMSE of ``tau_model`` against ``tau_measured``, both (N, 4)."""
    measured = np.asarray(tau_measured_nm, dtype=float)
    model = np.asarray(tau_model_nm, dtype=float)
    if measured.shape != model.shape or measured.ndim != 2 or measured.shape[1] != N_JOINTS or measured.shape[0] == 0:
        raise ShapeError(f"expected two equal (N>0, 4) torque arrays, got {measured.shape} and {model.shape}")
    error = measured - model
    per_joint = np.sqrt(np.mean(error**2, axis=0))
    peak = np.max(np.abs(measured), axis=0)
    normalised = error / np.where(peak > 0, peak, 1.0)
    nrmse = float(np.sqrt(np.sum(normalised**2) / measured.shape[0]))
    return ErrorMetrics(
        rmse_nm=float(np.sqrt(np.mean(error**2))),
        nrmse=nrmse,
        rmse_per_joint_nm=tuple(float(v) for v in per_joint),  # type: ignore[arg-type]
        n_points=int(measured.shape[0]),
    )
