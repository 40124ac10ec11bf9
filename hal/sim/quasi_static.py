"""A quasi-static raw log: the robot moving between stops, sampled like the loop would log it.

Each move follows a minimum-jerk profile, then the robot dwells. The torque is the static holding
torque plus a simple stand-in for dynamics while moving (a diagonal inertia times the joint
acceleration and a viscous term), so that samples taken while moving are visibly wrong and a
raw-log reducer that keeps them would bias a fit. The velocity column is what a drive would
report: the finite difference of the quantised link encoder. This is not the rigid-body plant of
the control loop (``hal.sim.plant``); it exists to exercise raw-log handling on static scenarios.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hal.robot import FloatArray
from hal.signals import last_motion_sign
from hal.sim.scenario import Scenario
from hal.sim.sensors import read_encoders


@dataclass(frozen=True)
class QuasiStaticSettings:
    rate_hz: float = 100.0
    joint_speed_rad_s: float = 0.3  # mean speed of the joint that moves most
    dwell_s: float = 1.5
    inertia_kgm2: float = 0.05  # stand-in diagonal inertia while moving
    viscous_nms_per_rad: float = 0.5


@dataclass(frozen=True)
class QuasiStaticLog:
    t_s: FloatArray
    q_rad: FloatArray
    dq_rad_s: FloatArray
    tau_nm: FloatArray
    theta_rad: FloatArray
    moving: np.ndarray  # True while the commanded profile moves (truth, for tests)


def _min_jerk(fraction: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Position, velocity and acceleration of the unit minimum-jerk profile."""
    f = fraction
    return (
        10 * f**3 - 15 * f**4 + 6 * f**5,
        30 * f**2 - 60 * f**3 + 30 * f**4,
        60 * f - 180 * f**2 + 120 * f**3,
    )


def quasi_static_log(
    scenario: Scenario, stops: FloatArray, rng: np.random.Generator, settings: QuasiStaticSettings | None = None
) -> QuasiStaticLog:
    """Log of visiting ``stops`` (K, 4) in order: dwell, move, dwell, ... ."""
    settings = settings or QuasiStaticSettings()
    dt = 1.0 / settings.rate_hz
    dwell_n = max(round(settings.dwell_s * settings.rate_hz), 1)
    q_parts, dq_parts, ddq_parts, moving_parts = [], [], [], []
    for i, stop in enumerate(stops):
        if i > 0:
            delta = stop - stops[i - 1]
            duration = max(np.abs(delta).max() / settings.joint_speed_rad_s, 2 * dt)
            n = max(round(duration * settings.rate_hz), 2)
            f = np.arange(1, n + 1) / n
            s, ds, dds = _min_jerk(f)
            q_parts.append(stops[i - 1] + s[:, None] * delta)
            dq_parts.append(ds[:, None] * delta / duration)
            ddq_parts.append(dds[:, None] * delta / duration**2)
            moving_parts.append(np.ones(n, dtype=bool))
        q_parts.append(np.repeat(stop[None, :], dwell_n, axis=0))
        dq_parts.append(np.zeros((dwell_n, stops.shape[1])))
        ddq_parts.append(np.zeros((dwell_n, stops.shape[1])))
        moving_parts.append(np.zeros(dwell_n, dtype=bool))
    q = np.concatenate(q_parts)
    dq = np.concatenate(dq_parts)
    ddq = np.concatenate(ddq_parts)
    moving = np.concatenate(moving_parts)
    description = scenario.description()
    plant = scenario.static_plant(description)
    tau = plant.holding_torque_nm(q) + settings.inertia_kgm2 * ddq + settings.viscous_nms_per_rad * dq
    direction = last_motion_sign(dq)
    t = np.arange(len(q)) * dt
    readings = read_encoders(
        q,
        tau,
        direction,
        scenario.sensors,
        description.sea,
        rng,
        stiffness_nm_per_rad=scenario.stiffness_nm_per_rad(description),
        t_s=t,
    )
    velocity = np.gradient(readings.q_rad, dt, axis=0)
    return QuasiStaticLog(t, readings.q_rad, velocity, readings.torque_nm, readings.theta_rad, moving)
