"""``daror can zero`` and ``daror can tare``: what each drive reads with the robot held still, every drive disabled.

Zero: the operator has put the robot in its zero pose (every joint angle 0, the arm supported so
the springs carry nothing); each drive's motor and link encoder counts, averaged over a window,
are that node's ``motor_zero_counts`` and ``link_zero_counts``. Tare: the arm unloaded (supported,
or out of the robot); the spring torque each drive reports, averaged, is its ``torque_tare_nm``
(added to the tare the backend already applied, so a second tare corrects the first). Nothing is
enabled: a disabled SEA drive applies no torque, and its TPDOs keep coming. A robot that moves
(faster than ``rest_speed_rad_s``) or whose readings spread more than the limits is refused:
nothing is stored.

Units: counts as the drives send them; torques in N m; times in s.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Literal

from daror_runtime.commissioning.bus_session import BusSession, Stats, stats
from hal.interface import Command

__all__ = ["CalibrationLimits", "Measured", "measure_still", "utc_now"]

Kind = Literal["zero", "tare"]


@dataclass(frozen=True)
class CalibrationLimits:
    """How long the robot is read and how still it must be.

    Attributes:
        window_s: how long each drive is read, s.
        rest_timeout_s: how long to wait for the robot to be at rest, s.
        rest_speed_rad_s: every joint slower than this is at rest, rad/s.
        max_spread_counts: the largest spread of an encoder over the window (zero), counts.
        max_spread_nm: the largest spread of the spring torque over the window (tare), N m.
    """

    window_s: float = 0.5
    rest_timeout_s: float = 5.0
    rest_speed_rad_s: float = 0.05
    max_spread_counts: float = 20.0
    max_spread_nm: float = 0.2


@dataclass(frozen=True)
class Measured:
    """One drive's readings over the window (raw counts; the spring torque as the backend reports it, N m)."""

    joint: int
    node_id: int
    motor_counts: Stats
    link_counts: Stats
    spring_nm: Stats


def utc_now() -> str:
    """Now, UTC, to the second, ISO 8601 (``2026-11-28T09:30:00Z``): when a zero or tare was taken."""
    return dt.datetime.now(dt.UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def measure_still(session: BusSession, limits: CalibrationLimits) -> tuple[list[Measured], list[str]]:
    """Boot the bus, wait for rest, read every drive for ``limits.window_s``, close; the readings and the problems.

    Every drive stays disabled (torque off is every command written); the bus is closed with every
    drive confirmed disabled whatever happens. The problems (one line each) say why the readings
    must not be stored: the robot moved, a reading spread, a fault latched, a drive not seen off.

    Raises:
        HalError: the start-up failed (the bus is closed).
    """
    problems: list[str] = []
    readings: list[Measured] = []
    try:
        session.open()
        probe = session.probe
        rest = session.wait_for_rest(limits.window_s, limits.rest_timeout_s, limits.rest_speed_rad_s)
        if not rest.at_rest:
            problems.append(
                f"the robot moves: a joint at {rest.speed_rad_s:.3f} rad/s after {rest.waited_s:.1f} s "
                f"(at rest: below {limits.rest_speed_rad_s:g} rad/s)"
            )
            return readings, problems
        n = len(probe.node_ids)
        motor: list[list[float]] = [[] for _ in range(n)]
        link: list[list[float]] = [[] for _ in range(n)]
        spring: list[list[float]] = [[] for _ in range(n)]
        last_seq = rest.sample.seq
        for _ in range(session.ticks_for(limits.window_s)):
            sample = session.tick(Command.torque_off())
            if sample.seq == last_seq:
                continue  # not a fresh cycle
            last_seq = sample.seq
            for k, counts in enumerate(probe.raw_counts()):
                motor[k].append(float(counts.motor_counts))
                link[k].append(float(counts.link_counts))
                spring[k].append(float(sample.tau_nm[k]))
        for k, node_id in enumerate(probe.node_ids):
            readings.append(Measured(k + 1, node_id, stats(motor[k]), stats(link[k]), stats(spring[k])))
    finally:
        confirmed = session.disable_all()
        problems += [f"a fault latched: {fault}" for fault in session.faults]
        if not confirmed:
            problems.append("not every drive was seen disabled at the end")
    return readings, problems


def spread_problems(readings: list[Measured], kind: Kind, limits: CalibrationLimits) -> list[str]:
    """Readings too unsteady to store: an encoder spread over ``max_spread_counts`` (zero), a torque over ``max_spread_nm`` (tare)."""
    problems = []
    for r in readings:
        if r.link_counts.n == 0:
            problems.append(f"joint {r.joint} (node {r.node_id}): no fresh reading in the window")
            continue
        if kind == "zero":
            for name, s in (("motor encoder", r.motor_counts), ("link encoder", r.link_counts)):
                if s.spread > limits.max_spread_counts:
                    problems.append(
                        f"joint {r.joint} (node {r.node_id}): the {name} spreads {s.spread:.1f} counts "
                        f"(at most {limits.max_spread_counts:g})"
                    )
        elif r.spring_nm.spread > limits.max_spread_nm:
            problems.append(
                f"joint {r.joint} (node {r.node_id}): the spring torque spreads {r.spring_nm.spread:.3f} N m "
                f"(at most {limits.max_spread_nm:g})"
            )
    return problems
