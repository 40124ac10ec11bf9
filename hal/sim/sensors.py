"""The SEA sensor model: two absolute encoders per joint and the spring between them.

The link-side encoder reads the joint angle ``q``; the gearbox-side encoder reads the motor-side
angle ``theta = q + tau / k`` (the spring deflects by ``tau / k``, Eq. 2.16). Both carry white
noise and are rounded to the encoder resolution, so the measured torque
``k * (theta - q)`` resolves ``k * resolution`` (0.0289 Nm for the DAROR-01). On top comes the
direction-dependent torque error of Sec. 2.2.2: ``error_j * dir_j``, ``dir`` being the sign of
the joint's last motion (the thesis suspects static friction across the spring or an encoder
that shifts with the rotor; either way it depends on how the joint arrived).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hal.robot import FloatArray, SeaConstants
from hal.sim.scenario import SensorTruth


@dataclass(frozen=True)
class EncoderReadings:
    """What the two encoders of every joint report; shapes (N, 4), radians and Nm."""

    q_rad: FloatArray
    theta_rad: FloatArray
    torque_nm: FloatArray


def read_encoders(
    q_true_rad: FloatArray,
    torque_true_nm: FloatArray,
    direction: FloatArray,
    sensors: SensorTruth,
    sea: SeaConstants,
    rng: np.random.Generator,
) -> EncoderReadings:
    """Measure joint angle and spring torque the way the SEA does.

    Args:
        q_true_rad: true link angles, (N, 4).
        torque_true_nm: true torque carried by each spring, (N, 4).
        direction: sign (-1, 0, +1) of each joint's last motion, (N, 4).
        sensors: noise, quantisation and direction error of the scenario.
        sea: spring stiffness and encoder resolution.
        rng: the scenario's random generator (the only source of randomness).
    """
    k = sea.spring_stiffness_nm_per_rad
    theta_true = q_true_rad + torque_true_nm / k
    noise = sensors.encoder_noise_rad
    q_read = q_true_rad + rng.normal(0.0, noise, q_true_rad.shape) if noise > 0 else q_true_rad.copy()
    theta_read = theta_true + rng.normal(0.0, noise, theta_true.shape) if noise > 0 else theta_true.copy()
    if sensors.quantise:
        step = sea.encoder_resolution_rad
        q_read = np.round(q_read / step) * step
        theta_read = np.round(theta_read / step) * step
    error = np.asarray(sensors.direction_error_nm, dtype=float)
    torque = k * (theta_read - q_read) + error * direction
    return EncoderReadings(q_rad=q_read, theta_rad=theta_read, torque_nm=torque)
