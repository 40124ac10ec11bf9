"""The SEA sensor model: two absolute encoders per joint and the spring between them.

The link-side encoder reads the joint angle ``q``; the gearbox-side encoder reads the motor-side
angle ``theta = q + tau / k`` (the spring deflects by ``tau / k``, Eq. 2.16). Both carry white
noise and are rounded to the encoder resolution, so the measured torque
``k * (theta - q)`` resolves ``k * resolution`` (0.0289 Nm for the DAROR-01). On top comes the
direction-dependent torque error of Sec. 2.2.2: ``error_j * dir_j``, ``dir`` being the sign of
the joint's last motion (the thesis suspects static friction across the spring or an encoder
that shifts with the rotor; either way it depends on how the joint arrived).

Undeclared effects (docs/simulation.md, "Undeclared effects"), the same as the dynamic path's
``hal.sim.dynamics.sense``:

* the as-built spring constant may differ from the nominal one the drive computes with, so the
  deflection is ``tau / k_true`` and the drive reports ``k_nominal * deflection``;
* a wrong joint zero (``angle_offset_deg``) adds the same offset to both encoders' readings; the
  torque is computed from the readings before it, as the offset cancels in the deflection;
* a torque drift adds ``torque_drift_nm_per_min * t / 60``, ``t`` the robot time of the reading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hal.errors import InputError, ShapeError
from hal.robot import N_JOINTS, FloatArray, SeaConstants
from hal.sim.scenario import SensorTruth

#: Seconds per minute: the drift is declared per minute, robot time is in seconds.
SECONDS_PER_MINUTE = 60.0


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
    *,
    stiffness_nm_per_rad: FloatArray | None = None,
    t_s: FloatArray | None = None,
) -> EncoderReadings:
    """Measure joint angle and spring torque the way the SEA does.

    Args:
        q_true_rad: true link angles, (N, 4).
        torque_true_nm: true torque carried by each spring, (N, 4).
        direction: sign (-1, 0, +1) of each joint's last motion, (N, 4).
        sensors: noise, quantisation, direction error, angle offset and torque drift of the scenario.
        sea: the nominal spring stiffness (what the drive computes torque with) and the encoder
            resolution.
        rng: the scenario's random generator (the only source of randomness; not drawn from
            when ``sensors.encoder_noise_rad`` is 0).
        stiffness_nm_per_rad: the as-built spring constant per joint (4,), Nm/rad (what the
            spring deflects by); default the nominal ``sea.spring_stiffness_nm_per_rad``.
        t_s: robot time of each reading since the session started, (N,) s; needed only when
            ``sensors.torque_drift_nm_per_min`` is not all zero.

    Returns:
        The readings: ``q`` and ``theta`` in rad (offset included), torque in Nm.

    Raises:
        ShapeError: ``stiffness_nm_per_rad`` is not (4,) or ``t_s`` not (N,).
        InputError: the sensors drift but no ``t_s`` was given.
    """
    k = sea.spring_stiffness_nm_per_rad
    if stiffness_nm_per_rad is None:
        k_true: float | FloatArray = k
    else:
        k_true = np.asarray(stiffness_nm_per_rad, dtype=float)
        if k_true.shape != (N_JOINTS,):
            raise ShapeError(f"stiffness_nm_per_rad: expected shape ({N_JOINTS},), got {k_true.shape}")
    theta_true = q_true_rad + torque_true_nm / k_true  # the spring deflects with its as-built constant
    noise = sensors.encoder_noise_rad
    q_read = q_true_rad + rng.normal(0.0, noise, q_true_rad.shape) if noise > 0 else q_true_rad.copy()
    theta_read = theta_true + rng.normal(0.0, noise, theta_true.shape) if noise > 0 else theta_true.copy()
    if sensors.quantise:
        step = sea.encoder_resolution_rad
        q_read = np.round(q_read / step) * step
        theta_read = np.round(theta_read / step) * step
    error = np.asarray(sensors.direction_error_nm, dtype=float)
    # The drive knows only the nominal constant: with an as-built one this is true torque / scale.
    torque = k * (theta_read - q_read) + error * direction
    drift = np.asarray(sensors.torque_drift_nm_per_min, dtype=float)
    # Each effect is added only where declared, so a scenario without it gives the very same
    # floats as before the effect existed (adding 0.0 would turn -0.0 readings into +0.0).
    if np.any(drift != 0.0):
        if t_s is None:
            raise InputError("the scenario's sensors drift (torque_drift_nm_per_min); read_encoders needs t_s")
        t = np.asarray(t_s, dtype=float)
        if t.shape != (q_true_rad.shape[0],):
            raise ShapeError(f"t_s: expected shape ({q_true_rad.shape[0]},), got {t.shape}")
        torque = torque + (drift / SECONDS_PER_MINUTE) * t[:, None]
    offset = np.deg2rad(np.asarray(sensors.angle_offset_deg, dtype=float))
    if np.any(offset != 0.0):
        # After the torque: the offset is common to both encoders and cancels in the deflection;
        # after quantisation: it is a calibration constant the drive adds to its counts.
        q_read = q_read + offset
        theta_read = theta_read + offset
    return EncoderReadings(q_rad=q_read, theta_rad=theta_read, torque_nm=torque)
