"""Make the example data files of docs/residual.md: data that did NOT come from our simulator.

A lab's own logger writes stationary points in its own way: columns in its own order, extra
columns the tool does not know (a temperature, a sample id), no time column, and the validation
set as a MATLAB file. The torques here come from a plain formula (the PLF structure of Eq. 4.21
with made-up link moments, an elbow spring, a 0.4 Nm direction error on joint 2 and Gaussian
noise), not from ``hal.sim``: no CoM Jacobians, no SEA encoders, no quantisation.

Run from the repository root: ``.venv/bin/python examples/residual/make_external.py``.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import scipy.io

from daror_runtime.models.regressor import LinearTorqueEvaluator
from hal.robot import load_description

HERE = Path(__file__).parent
RNG = np.random.default_rng(20261121)
# First moments m g p of the four links (Nm), elbow spring 2.5 Nm/rad about -20 deg.
THETA = np.array([1.1, 0.6, 0.5, 1.6, 0.9, 0.4, 6.2, 0.5, 0.2, 1.3, 0.05, 0.3])
ELBOW = np.array([2.5 * np.deg2rad(20.0), 2.5])
DIRECTION_ERROR_NM = np.array([0.0, 0.4, 0.0, 0.0])
NOISE_NM = 0.03


def points(n: int) -> dict[str, np.ndarray]:
    """``n`` stationary points along a random walk through the joint space."""
    lower, upper = np.deg2rad([-40.0, -25.0, -55.0, 10.0]), np.deg2rad([55.0, 75.0, 55.0, 105.0])
    q = np.empty((n, 4))
    q[0] = (lower + upper) / 2
    for i in range(1, n):
        q[i] = np.clip(q[i - 1] + RNG.normal(0.0, 0.15, 4), lower, upper)
    direction = np.vstack([np.zeros((1, 4)), np.sign(np.diff(q, axis=0))])
    model = LinearTorqueEvaluator(load_description().kinematics(), THETA, ELBOW)
    tau = model.torque_batch(q) + DIRECTION_ERROR_NM * direction + RNG.normal(0.0, NOISE_NM, q.shape)
    columns = {"sample_id": np.arange(n, dtype=float), "temperature_c": 24.0 + RNG.normal(0, 0.3, n)}
    for j in range(4):  # the lab's order: per joint, angle then torque then direction
        columns[f"q{j + 1}"] = q[:, j]
        columns[f"tau{j + 1}"] = tau[:, j]
        columns[f"dir{j + 1}"] = direction[:, j]
    return columns


def main() -> None:
    train = points(400)
    with open(HERE / "external_train.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(list(train))
        for row in np.column_stack(list(train.values())):
            writer.writerow([f"{v:.6f}" for v in row])
    validate = points(80)
    scipy.io.savemat(HERE / "external_validate.mat", {k: v.reshape(-1, 1) for k, v in validate.items()})


if __name__ == "__main__":
    main()
