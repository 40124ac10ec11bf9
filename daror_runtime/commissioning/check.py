"""``daror can check``: boot the bus, read what every drive is, enable each joint alone at zero torque, and say what was found.

The procedure (docs/canopen.md, Commissioning), every step a row of the table with what was found,
what was expected and PASS, FAIL or INFO (a value with nothing to compare it with):

1. start-up through the backend (:meth:`hal.canopen.backend.CanHal.open`: NMT reset, identity,
   units, the configuration, NMT start), with the drives' peak torque 0x6072 at the check's
   torque limit;
2. per drive, by SDO while every drive is disabled: 0x1000 (a CiA 402 device), 0x1018:1-4 (vendor
   and product against the EDS's ``[DeviceInfo]``; revision and serial shown), the units (0x6076,
   0x608F:1/2, 0x2011 against what the backend converts with), the mode (0x6061 against the mode
   the master wrote, 10: cyclic synchronous torque; 0x6502's bit of it where the EDS has 0x6502),
   0x6072 (the check's torque limit in force);
3. every item of step 2 passed (a drive that is not what the robot file says, or in another mode,
   is not enabled at all), the arm at rest (every joint slower than ``rest_speed_rad_s``), no
   e-stop pressed, no drive in fault: else nothing is enabled;
4. per joint, the others disabled: enabled at zero torque until OPERATION ENABLED, its motor and
   link encoders and spring torque read for ``window_s`` (mean, spread), then disabled and seen
   disabled. A joint that moves more than ``max_motion_rad`` while enabled, another drive that
   shows enabled, or a latched fault stops the check there: torque off at once;
5. every drive disabled, confirmed by each drive's own statusword (three SYNCs in a row), whatever
   happened (Ctrl-C included), then the bus closed.

Units: angles in rad, torques in N m, times in s (shown in ms where short).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from daror_runtime.commissioning.bus_session import BusSession, Stats, only_joint, stats
from hal.errors import HalError
from hal.interface import Command, DriveState, Sample

__all__ = ["CheckLimits", "CheckReport", "CheckRow", "Verdict", "run_check"]

Verdict = Literal["PASS", "FAIL", "INFO"]

#: The low word of 0x1000 of a CiA 402 drive.
_CIA402_PROFILE = 0x0192


@dataclass(frozen=True)
class CheckLimits:
    """What the check demands and how long it looks.

    Attributes:
        torque_limit_nm: the drives' peak torque during the check (0x6072), N m.
        enable_timeout_s: how long a joint may take to reach OPERATION ENABLED, s.
        window_s: how long each enabled joint is read, s.
        rest_timeout_s: how long the check waits for the arm to be at rest before enabling, s.
        rest_speed_rad_s: every joint slower than this (for ``window_s``) is at rest, rad/s.
        max_motion_rad: an enabled joint that moves more than this from where it was enabled is
            stopped at once (a drive applying torque it was not commanded), rad.
        encoder_spread_rad: the largest spread of an encoder over the window of a joint at rest, rad.
        range_margin_rad: how far past the joint's range (the robot description's limits) the link
            may read: a joint resting on its end stop reads a little past it; a wrong zero or a
            reversed encoder reads far past, rad.
        torque_tolerance_nm: the largest mean spring torque of a joint enabled at zero torque, N m.
        sdo_timeout_s: how long the identity, units and mode reads may take in all, s.
    """

    torque_limit_nm: float = 2.0
    enable_timeout_s: float = 1.0
    window_s: float = 0.25
    rest_timeout_s: float = 5.0
    rest_speed_rad_s: float = 0.05
    max_motion_rad: float = 0.05
    encoder_spread_rad: float = 0.01
    range_margin_rad: float = 0.1
    torque_tolerance_nm: float = 1.0
    sdo_timeout_s: float = 3.0


@dataclass(frozen=True)
class CheckRow:
    """One line of the check's table: ``joint`` 0 and ``node_id`` 0 for the bus as a whole."""

    joint: int
    node_id: int
    item: str
    found: str
    expected: str
    verdict: Verdict

    def as_dict(self) -> dict[str, object]:
        return {
            "joint": self.joint,
            "node_id": self.node_id,
            "item": self.item,
            "found": self.found,
            "expected": self.expected,
            "verdict": self.verdict,
        }


@dataclass
class CheckReport:
    """The rows, the readings of each enabled joint, and how the check ended.

    Attributes:
        rows: the table, in the order found.
        readings: joint -> {"motor_rad", "link_rad", "spring_nm"} -> :class:`Stats` over its window.
        interrupted: Ctrl-C stopped the check (every drive was disabled all the same).
        disabled_confirmed: every drive's own statusword said its power stage was off, three SYNCs in a
            row, before the bus was closed.
    """

    rows: list[CheckRow] = field(default_factory=list)
    readings: dict[int, dict[str, Stats]] = field(default_factory=dict)
    interrupted: bool = False
    disabled_confirmed: bool = False

    @property
    def passed(self) -> bool:
        """True when no row failed and every drive was seen disabled at the end."""
        return self.disabled_confirmed and not self.interrupted and all(r.verdict != "FAIL" for r in self.rows)

    def as_dict(self) -> dict[str, object]:
        return {
            "passed": self.passed,
            "interrupted": self.interrupted,
            "disabled_confirmed": self.disabled_confirmed,
            "rows": [row.as_dict() for row in self.rows],
            "readings": {
                str(joint): {
                    name: {"mean": finite_or_none(s.mean), "spread": finite_or_none(s.spread), "n": s.n}
                    for name, s in values.items()
                }
                for joint, values in self.readings.items()
            },
        }


class _StopError(Exception):
    """A finding after which nothing more is enabled (the row says why)."""


def run_check(
    session: BusSession,
    limits: CheckLimits,
    expected_identity: Callable[[int], dict[str, int | None]],
    on_row: Callable[[CheckRow], None] = lambda row: None,
    calibration_rows: Callable[[int], list[tuple[str, str]]] = lambda node: [],
) -> CheckReport:
    """The check (see the module docstring) on ``session``'s backend, not yet opened; it is closed at the end.

    Args:
        session: the backend and its clock (:mod:`daror_runtime.commissioning.bus_session`).
        limits: what is demanded.
        expected_identity: node id -> ``{"vendor_id": ..., "product_code": ..., "revision": ...}``
            (None where nothing is expected).
        on_row: called with each row as it is found (the terminal shows progress).
        calibration_rows: node id -> ``(item, value)`` of its stored calibration, shown as INFO.

    Returns the report; Ctrl-C during the check is recorded in it (``interrupted``) after every
    drive was disabled.
    """
    report = CheckReport()

    def add(joint: int, node: int, item: str, found: str, expected: str, verdict: Verdict) -> None:
        row = CheckRow(joint, node, item, found, expected, verdict)
        report.rows.append(row)
        on_row(row)

    try:
        started = time.monotonic()
        try:
            session.open()
        except HalError as exc:
            add(0, 0, "start-up", str(exc), "every drive configured and operational", "FAIL")
            return report
        node_ids = list(session.probe.node_ids)
        add(0, 0, "start-up", f"{len(node_ids)} drives configured and operational in {time.monotonic() - started:.2f} s",
            "every drive configured and operational", "PASS")  # fmt: skip
        _read_objects(session, limits, node_ids, expected_identity, add)
        for joint, node in enumerate(node_ids, start=1):
            for item, value in calibration_rows(node):
                add(joint, node, item, value, "-", "INFO")
        try:
            failed = [row.item for row in report.rows if row.verdict == "FAIL"]
            if failed:  # a drive that is not what the file says, or in another mode, is not enabled at all
                add(0, 0, "enable", f"not tried: {len(failed)} item(s) above failed", "identity, units, mode right",
                    "FAIL")  # fmt: skip
                raise _StopError
            _wait_for_rest(session, limits, add)
            for joint, node in enumerate(node_ids, start=1):
                report.readings[joint] = _enable_one(session, limits, joint, node, add)
        except _StopError:
            pass
    except KeyboardInterrupt:
        report.interrupted = True
        add(0, 0, "interrupted", "Ctrl-C", "the check to run to its end", "FAIL")
    finally:
        booted = session.probe is not None
        report.disabled_confirmed = session.disable_all()
        for fault in session.faults:
            add(0, 0, "fault latched", fault, "no fault", "FAIL")
        if not booted:  # the start-up failed or was interrupted: no enable was ever sent
            add(0, 0, "every drive disabled", "nothing was enabled (no start-up)", "-", "INFO")
        else:
            add(0, 0, "every drive disabled",
                "every statusword: power stage off" if report.disabled_confirmed else "NOT confirmed",
                "3 SYNCs in a row, then the bus closed", "PASS" if report.disabled_confirmed else "FAIL")  # fmt: skip
    return report


def _read_objects(
    session: BusSession,
    limits: CheckLimits,
    node_ids: list[int],
    expected_identity: Callable[[int], dict[str, int | None]],
    add: Callable[..., None],
) -> None:
    """Identity, units, mode and the torque limit of every drive, by SDO through the master, drives disabled.

    One row per item; an item may need several reads (a ratio of two subs), judged together.
    """
    probe = session.probe
    rows: dict[int, list[tuple[str, list[Any], str, Callable[[list[int]], tuple[str, Verdict]]]]] = {}
    for node in node_ids:
        want = expected_identity(node)
        mode = probe.mode(node)
        peak_counts = round(limits.torque_limit_nm / probe.nm_per_torque_count(node))
        items: list[tuple[str, list[tuple[int, int]], tuple[str, Callable[[list[int]], tuple[str, Verdict]]]]] = [
            ("device type 0x1000", [(0x1000, 0)], _cia402()),
            ("vendor 0x1018:1", [(0x1018, 1)], _equal(want.get("vendor_id"), "0x{:08X}")),
            ("product 0x1018:2", [(0x1018, 2)], _equal(want.get("product_code"), "0x{:08X}")),
            ("revision 0x1018:3", [(0x1018, 3)], _equal(None, "0x{:08X}")),
            ("serial 0x1018:4", [(0x1018, 4)], _equal(None, "0x{:08X}")),
            *((u.what, [(u.index, sub) for sub in u.subs], _unit(u)) for u in probe.unit_objects(node)),
            ("mode display 0x6061", [(0x6061, 0)], _equal(mode, "{}", signed=True)),
            ("max torque 0x6072 (per mille)", [(0x6072, 0)], _equal(peak_counts, "{}")),
        ]
        if probe.has_object(node, 0x6502, 0):
            items.append(("supported modes 0x6502", [(0x6502, 0)], _bit(mode - 1)))
        rows[node] = [
            (what, [probe.read(node, index, sub, what) for index, sub in objects], expected, judge)
            for what, objects, (expected, judge) in items
        ]
    for _ in range(session.ticks_for(limits.sdo_timeout_s)):
        session.tick(Command.torque_off())
        if all(read.done for node_rows in rows.values() for _, reads, _, _ in node_rows for read in reads):
            break
    for joint, node in enumerate(node_ids, start=1):
        for what, reads, expected, judge in rows[node]:
            failed = [read for read in reads if read.value is None]
            if failed:
                add(joint, node, what, failed[0].error, "an answer", "FAIL")
                continue
            found, verdict = judge([read.value for read in reads])
            add(joint, node, what, found, expected, verdict)


def _equal(
    expected: int | None, shown: str, signed: bool = False
) -> tuple[str, Callable[[list[int]], tuple[str, Verdict]]]:
    """The value must be ``expected`` (None: shown, not compared: INFO). ``signed``: a one-byte value read as i8."""

    def judge(values: list[int]) -> tuple[str, Verdict]:
        value = values[0] - 256 if signed and values[0] > 127 else values[0]
        if expected is None:
            return shown.format(value), "INFO"
        return shown.format(value), "PASS" if value == expected else "FAIL"

    return ("-" if expected is None else shown.format(expected)), judge


def _unit(unit: Any) -> tuple[str, Callable[[list[int]], tuple[str, Verdict]]]:
    """A unit (one value, or a ratio of two) must be what the backend converts with."""

    def judge(values: list[int]) -> tuple[str, Verdict]:
        value = unit.value(values)
        return f"{value:g}", "PASS" if abs(value - unit.expected) <= 1e-9 * max(1.0, abs(unit.expected)) else "FAIL"

    return f"{unit.expected:g}", judge


def _cia402() -> tuple[str, Callable[[list[int]], tuple[str, Verdict]]]:
    """0x1000's low word must name the CiA 402 profile."""
    return f"low word 0x{_CIA402_PROFILE:04X} (CiA 402)", lambda values: (
        f"0x{values[0]:08X}",
        "PASS" if values[0] & 0xFFFF == _CIA402_PROFILE else "FAIL",
    )


def _bit(bit: int) -> tuple[str, Callable[[list[int]], tuple[str, Verdict]]]:
    """0x6502 must have the mode's bit (CiA 402: bit n is mode n + 1)."""
    return f"bit {bit} (the mode written)", lambda values: (
        f"0x{values[0]:08X}",
        "PASS" if values[0] >> bit & 1 else "FAIL",
    )


def _wait_for_rest(session: BusSession, limits: CheckLimits, add: Callable[..., None]) -> None:
    """Every drive disabled until the arm is at rest; no e-stop, no fault. Raises _StopError (with a FAIL row) otherwise."""
    rest = session.wait_for_rest(limits.window_s, limits.rest_timeout_s, limits.rest_speed_rad_s)
    if not rest.at_rest:
        add(0, 0, "arm at rest", f"a joint moves at {rest.speed_rad_s:.3f} rad/s after {rest.waited_s:.1f} s",
            f"every joint below {limits.rest_speed_rad_s:g} rad/s", "FAIL")  # fmt: skip
        raise _StopError
    add(0, 0, "arm at rest", f"fastest joint {rest.speed_rad_s:.3f} rad/s", f"below {limits.rest_speed_rad_s:g} rad/s",
        "PASS")  # fmt: skip
    _require_safe(rest.sample, add)


def _require_safe(sample: Sample, add: Callable[..., None]) -> None:
    """No e-stop pressed and no drive in fault before a joint is enabled. Raises _StopError (with a FAIL row) otherwise."""
    if sample.any_estop:
        add(0, 0, "e-stops", f"pressed (operator, pilot) = {sample.estop}", "released", "FAIL")
        raise _StopError
    faulted = [j + 1 for j, state in enumerate(sample.drives) if state is DriveState.FAULT]
    if faulted:
        codes = ", ".join(f"joint {j}: 0x{sample.drive_fault_codes[j - 1]:04X}" for j in faulted)
        add(0, 0, "drives in fault", codes, "none", "FAIL")
        raise _StopError


def _enable_one(
    session: BusSession, limits: CheckLimits, joint: int, node: int, add: Callable[..., None]
) -> dict[str, Stats]:
    """Joint ``joint`` alone enabled at zero torque, read, disabled; its window's statistics."""
    j = joint - 1
    enable = only_joint(joint)
    faults_before = len(session.faults)
    ticks = 0
    sample = session.sample
    while ticks < session.ticks_for(limits.enable_timeout_s) and (
        sample is None or sample.drives[j] is not DriveState.ENABLED
    ):
        sample = session.tick(enable)
        ticks += 1
        _watch_others(session, joint, node, add)
    if sample is None or sample.drives[j] is not DriveState.ENABLED:
        state = sample.drives[j].name if sample is not None else "unknown"
        add(joint, node, "enable at zero torque", f"{state} after {ticks * session.period_s * 1e3:.0f} ms",
            f"OPERATION ENABLED within {limits.enable_timeout_s * 1e3:.0f} ms", "FAIL")  # fmt: skip
        _disable_one(session, limits, joint, node, add)
        return {}
    add(joint, node, "enable at zero torque", f"OPERATION ENABLED after {ticks * session.period_s * 1e3:.0f} ms",
        f"within {limits.enable_timeout_s * 1e3:.0f} ms", "PASS")  # fmt: skip
    q0 = float(sample.q_rad[j])
    motor, link, spring = [], [], []
    last_seq = sample.seq
    for _ in range(session.ticks_for(limits.window_s)):
        sample = session.tick(enable)
        _watch_others(session, joint, node, add)
        if len(session.faults) > faults_before:
            add(joint, node, "while enabled", session.faults[-1], "no fault", "FAIL")
            _disable_one(session, limits, joint, node, add)
            raise _StopError
        moved = abs(float(sample.q_rad[j]) - q0)
        if moved > limits.max_motion_rad:
            session.tick(Command.torque_off())  # at once: this tick's write is the torque off
            add(joint, node, "motion while enabled", f"{moved:.3f} rad", f"at most {limits.max_motion_rad:g} rad "
                "(zero torque commanded)", "FAIL")  # fmt: skip
            _disable_one(session, limits, joint, node, add)
            raise _StopError
        if sample.seq != last_seq:  # a fresh reading
            last_seq = sample.seq
            motor.append(float(sample.theta_rad[j]))
            link.append(float(sample.q_rad[j]))
            spring.append(float(sample.tau_nm[j]))
    readings = {"motor_rad": stats(motor), "link_rad": stats(link), "spring_nm": stats(spring)}
    _judge_readings(session, limits, joint, node, readings, add)
    _disable_one(session, limits, joint, node, add)
    return readings


def _watch_others(session: BusSession, joint: int, node: int, add: Callable[..., None]) -> None:
    """Every other drive's own statusword must say its power stage is off while ``joint`` is enabled; else torque off, stop."""
    others = [k + 1 for k, on in enumerate(session.stage_on) if k + 1 != joint and on]
    if others:
        session.tick(Command.torque_off())
        add(joint, node, "other drives", f"joint(s) {others} enabled", "disabled", "FAIL")
        raise _StopError


def _judge_readings(
    session: BusSession, limits: CheckLimits, joint: int, node: int, readings: dict[str, Stats],
    add: Callable[..., None],
) -> None:  # fmt: skip
    """The rows of one enabled joint's readings: both encoders, their agreement, the spring torque."""
    hal: Any = session.hal
    description = hal.description
    j = joint - 1
    margin = limits.range_margin_rad
    lower = float(description.lower_limits_rad[j]) - margin
    upper = float(description.upper_limits_rad[j]) + margin
    motor, link, spring = readings["motor_rad"], readings["link_rad"], readings["spring_nm"]
    if link.n == 0:
        add(joint, node, "readings", "no fresh sample while enabled", f"{limits.window_s:g} s of samples", "FAIL")
        return
    spread = limits.encoder_spread_rad
    for name, s in (("motor encoder", motor), ("link encoder", link)):
        inside = lower <= s.mean <= upper
        steady = s.spread <= spread
        add(joint, node, f"{name} (rad)", f"{s.mean:+.4f} +- {s.spread:.4f}",
            f"in [{lower:+.2f}, {upper:+.2f}], +- <= {spread:g}", "PASS" if inside and steady else "FAIL")  # fmt: skip
    deflection = motor.mean - link.mean
    max_deflection = float(description.sea.max_spring_deflection_rad)
    add(joint, node, "motor - link (rad)", f"{deflection:+.4f}",
        f"|.| <= {max_deflection:g} (spring end stop)", "PASS" if abs(deflection) <= max_deflection else "FAIL")  # fmt: skip
    tol = limits.torque_tolerance_nm
    add(joint, node, "spring torque (N m)", f"{spring.mean:+.3f} +- {spring.spread:.3f}",
        f"|mean| <= {tol:g} (zero torque)", "PASS" if abs(spring.mean) <= tol else "FAIL")  # fmt: skip


def _disable_one(session: BusSession, limits: CheckLimits, joint: int, node: int, add: Callable[..., None]) -> None:
    """Torque off until ``joint``'s drive says (its statusword of a SYNC) its power stage is off; a row either way."""
    j = joint - 1
    for ticks in range(1, session.ticks_for(limits.enable_timeout_s) + 1):
        session.tick(Command.torque_off())
        if session.stage_on[j] is False:
            add(joint, node, "disabled again", f"power stage off after {ticks * session.period_s * 1e3:.0f} ms",
                "its statusword: not enabled", "PASS")  # fmt: skip
            return
    add(joint, node, "disabled again", "its statusword still says enabled (or nothing)", "not enabled", "FAIL")
    raise _StopError


def finite_or_none(value: float) -> float | None:
    """``value``, or None for NaN (JSON has no NaN)."""
    return value if math.isfinite(value) else None
