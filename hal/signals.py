"""Small signal helpers shared by the simulator and the runtime's data handling."""

from __future__ import annotations

import numpy as np

from hal.robot import FloatArray


def last_motion_sign(velocity: FloatArray, threshold: float = 0.0) -> FloatArray:
    """Per sample and column: the sign of ``velocity`` the last time ``|velocity| > threshold``.

    Columns that have not moved yet read 0. This is the ``dir`` of a stationary point: how each
    joint arrived where it stands (Sec. 2.2.2's torque error depends on it).
    """
    velocity = np.asarray(velocity, dtype=float)
    moving = np.abs(velocity) > threshold
    signs = np.where(moving, np.sign(velocity), 0.0)
    last = np.where(moving, np.arange(velocity.shape[0])[:, None], -1)
    np.maximum.accumulate(last, axis=0, out=last)
    return np.where(last >= 0, np.take_along_axis(signs, np.maximum(last, 0), axis=0), 0.0)
