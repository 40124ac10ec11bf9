"""Faults provoked as the monitor finds them on a robot, so that it finds one of a given kind in the next tick.

Shared by tests/daror_runtime/safety/test_fault_reactions.py and bench/bench_fault_reactions.py. The faults of the drives
and sensors are injected in the simulated plant (:func:`inject_in_plant`); those of a reading over a
limit (a torque, a deflection, a speed, a joint or the elbow beyond its range) come from a limit
narrowed just below the reading the session has now, on one joint (:func:`narrowed_limits`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from daror_runtime.safety.faults import FaultKind
from daror_runtime.safety.limits import SafetyLimits
from hal.interface import HalBusFaultError, HalFaultError, Sample
from hal.isb import AngleRange, IsbLimits
from hal.sim.backend import SimHal

#: The kinds :func:`inject_in_plant` provokes.
PLANT_KINDS = (FaultKind.STALE, FaultKind.HAL, FaultKind.BUS, FaultKind.DRIVE, FaultKind.NOT_FINITE, FaultKind.JUMP)
#: The kinds :func:`narrowed_limits` provokes.
LIMIT_KINDS = (
    FaultKind.TORQUE,
    FaultKind.DEFLECTION,
    FaultKind.VELOCITY,
    FaultKind.JOINT_LIMIT,
    FaultKind.ISB_LIMIT,
)


def narrowed_limits(limits: SafetyLimits, sample: Sample, kind: FaultKind) -> SafetyLimits:
    """``limits`` with one bound just below ``sample``'s reading, so that a fault of ``kind`` follows.

    TORQUE: joint 2's torque reading over half its value; DEFLECTION: the most deflected spring alone
    beyond the limit; VELOCITY: the elbow's speed over 1e-9 rad/s; JOINT_LIMIT: the elbow 0.02 rad
    beyond its upper limit; ISB_LIMIT: the elbow 2 deg beyond the pilot's upper limit.

    Raises:
        ValueError: a kind not in :data:`LIMIT_KINDS`.
    """
    if kind == FaultKind.TORQUE:
        limit = np.array(limits.max_spring_torque_nm, dtype=float)
        limit[1] = abs(float(sample.tau_nm[1])) * 0.5
        return dataclasses.replace(limits, max_spring_torque_nm=limit)
    if kind == FaultKind.DEFLECTION:
        deflection = np.sort(np.abs(np.asarray(sample.theta_rad) - np.asarray(sample.q_rad)))
        return dataclasses.replace(limits, max_deflection_rad=float(0.5 * (deflection[-2] + deflection[-1])))
    if kind == FaultKind.VELOCITY:
        speed = np.array(limits.max_velocity_rad_s, dtype=float)
        speed[3] = 1e-9
        return dataclasses.replace(limits, max_velocity_rad_s=speed)
    if kind == FaultKind.JOINT_LIMIT:
        upper = np.array(limits.joint_upper_rad, dtype=float)
        upper[3] = float(sample.q_rad[3]) - 0.02
        return dataclasses.replace(limits, joint_upper_rad=upper)
    if kind == FaultKind.ISB_LIMIT:
        elbow = math.degrees(float(sample.q_rad[3]))
        return limits.with_isb(IsbLimits(elbow=AngleRange(lower_deg=elbow - 40.0, upper_deg=elbow - 2.0)), 0.0)
    raise ValueError(f"{kind}: not a fault of a reading over a limit")


def inject_in_plant(hal: SimHal, kind: FaultKind, stale_ticks: int = 2000) -> None:
    """Inject in the simulated plant what the monitor finds as a fault of ``kind``.

    STALE: ``stale_ticks`` samples without news; HAL: one failed read (the bus); BUS: one read that
    fails as a CAN bus gone bus-off does (:func:`fail_next_read_as_bus_off`); DRIVE: joint 2's drive
    faults; NOT_FINITE: joint 3 reads NaN; JUMP: joint 1's encoder slips 0.1 rad.

    Raises:
        ValueError: a kind not in :data:`PLANT_KINDS`.
    """
    if kind == FaultKind.STALE:
        hal.inject_fault("stale", None, stale_ticks)
    elif kind == FaultKind.HAL:
        hal.inject_fault("bus")
    elif kind == FaultKind.BUS:
        fail_next_read_as_bus_off(hal)
    elif kind == FaultKind.DRIVE:
        hal.inject_fault("drive_fault", 2)
    elif kind == FaultKind.NOT_FINITE:
        hal.inject_fault("nan", 3)
    elif kind == FaultKind.JUMP:
        hal.inject_fault("jump", 1, 0.1)
    else:
        raise ValueError(f"{kind}: not a fault the plant injects")


def fail_next_read_as_bus_off(hal: SimHal) -> None:
    """The plant's next read fails as the CAN backend's does when its controller goes bus-off.

    The plant has no bus: its own one-shot ``bus`` fault (which also stops its compiled batches
    for that tick) is raised as :class:`hal.interface.HalBusFaultError`, the class the CAN backend
    raises (hal/canopen/health.py; on the CAN bus itself: tests/hal/canopen/test_canopen_bus_health.py).
    """
    hal.inject_fault("bus")
    plant_read = type(hal).read

    def read_bus_off() -> Sample:
        try:
            return plant_read(hal)
        except HalFaultError as exc:
            raise HalBusFaultError(f"CAN bus: bus-off (provoked: {exc})") from None
        finally:
            del hal.read  # once: the plant's own read again

    hal.read = read_bus_off  # type: ignore[method-assign]
