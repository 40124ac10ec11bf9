"""What a ``daror hil`` run did with its faults: the summary in ``hil.json`` (docs/canopen.md).

A HIL run injects faults into the simulated drives (``--fault KIND:NODE@T_S``, or a script's
``sim fault`` lines) or into the bus itself (``--fault bus_off@T_S``, ``error_passive@T_S``: the
master's controller, no node; its summary has ``node`` and ``joint`` null) and records the session
as every session does. This module reads the two records after the run, whatever the session or
the script did, and says for every injection:

* when it happened (the SYNC the drive got it at, robot time) and in which state;
* what the runtime found (the audit log's faults), the state it went to and the reaction it took,
  beside the reaction the spec declares for those faults in that state (``fault_reactions``): within
  1 s of the injection, and while a FAIL entered then lasts;
* when each drive's power stage stopped applying torque (the simulated drives' own record), in
  ticks from the injection: the faulted joint's at once or after its drive's stop ramp, the
  others' when the reaction lets go of the arm (or not within the run: it still holds it).

The audit log stamps a fault found in a tick whose reading failed with the last reading's time,
one tick before the injection; such a fault counts as found in the injection's tick (0 ticks).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from daror_runtime.fsm.spec import FsmSpec
from daror_runtime.safety.faults import FaultKind

if TYPE_CHECKING:
    from daror_runtime.runtime import Runtime
    from hal.config import CanSimHalConfig

__all__ = [
    "REACTION_LIMIT_S",
    "ScheduledFault",
    "fault_lines",
    "fault_summaries",
    "hil_config",
    "let_the_reaction_play_out",
    "read_audit",
]

#: Faults listed per injection at most (``found_count`` counts them all: one may repeat while the arm is lowered).
_MAX_FAULTS = 8
#: A fault's consequence is looked for this long after it, s: every bus fault is found well within
#: (a lost heartbeat after the consumer's 250 ms); a FAIL entered then is followed until it is left.
_FOUND_WITHIN_S = 1.0


@dataclass(frozen=True)
class ScheduledFault:
    """One ``--fault KIND:NODE@T_S``: the kind, the drive's node id and joint (1-4), the robot time asked for (s).

    A fault of the bus itself (``--fault KIND@T_S``) has no node (None) and joint 0.
    """

    kind: str
    node: int | None
    joint: int
    at_s: float


def read_audit(path: Path) -> list[dict[str, Any]]:
    """The audit log's events (JSON lines), oldest first; a line that is not a JSON object is skipped.

    A missing file gives no events (a session that never started writes none).
    """
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return []
    events = []
    for line in text.splitlines():
        try:
            event = json.loads(line)
        except ValueError:
            continue
        if isinstance(event, dict):
            events.append(event)
    return events


def _t(event: dict[str, Any]) -> float | None:
    value = event.get("t_s")
    return float(value) if isinstance(value, int | float) else None


def fault_summaries(
    scheduled: Sequence[ScheduledFault],
    drive_events: Iterable[tuple[float, int, str]],
    audit: Sequence[dict[str, Any]],
    spec: FsmSpec,
    node_ids: Sequence[int],
    rate_hz: float,
) -> list[dict[str, Any]]:
    """One summary (JSON-ready) per fault injected into a drive or the bus, and per scheduled fault the run never reached.

    Args:
        scheduled: the run's ``--fault`` options (a script's ``sim fault`` lines are found in ``drive_events``).
        drive_events: the simulated drives' record (``FaultSchedule.drive_events``): robot time s, joint 1-4
            (0: the bus itself), what.
        audit: the session's audit events (:func:`read_audit`).
        spec: the FSM spec the session ran (its first state, its reactions).
        node_ids: the drives' node ids, joint 1-4 in order.
        rate_hz: the loop's rate, Hz (robot time to ticks).
    """
    events = sorted(drive_events, key=lambda e: e[0])
    injected = [(t, joint, what.removeprefix("injected ")) for t, joint, what in events if what.startswith("injected ")]
    period = 1.0 / rate_hz
    transitions = [e for e in audit if e.get("event") == "transition" and _t(e) is not None]
    faults = [e for e in audit if e.get("event") == "fault" and "kind" in e and _t(e) is not None]
    reactions = [e for e in audit if e.get("event") in ("reaction", "reaction escalated") and _t(e) is not None]
    phases = [e for e in audit if e.get("event") == "reaction phase" and _t(e) is not None]
    stops = [_t(e) for e in audit if e.get("event") == "session stopped: torque off" and _t(e) is not None]
    ended = float(stops[-1]) if stops else float("inf")  # type: ignore[arg-type]
    unmatched = list(scheduled)
    summaries = []
    for n, (t_inj, joint, kind) in enumerate(injected):
        end = injected[n + 1][0] if n + 1 < len(injected) else float("inf")
        start = t_inj - 1.5 * period  # a fault found in the injection's tick may carry the tick before's time
        origin = next((s for s in unmatched if s.kind == kind and s.joint == joint and s.at_s <= t_inj + 1e-9), None)
        if origin is not None:
            unmatched.remove(origin)
        before = [e for e in transitions if _t(e) < start]  # type: ignore[operator]
        state_before = str(before[-1]["dest"]) if before else spec.first.name
        soon = min(end, t_inj + _FOUND_WITHIN_S)
        after = [e for e in transitions if start <= _t(e) < end]  # type: ignore[operator]
        first = after[0] if after and _t(after[0]) < soon else None  # type: ignore[operator]
        if first is not None and first.get("dest") == spec.fail.name:  # its episode: until FAIL is left
            window = next((_t(e) for e in after if e.get("source") == spec.fail.name), end)
        else:
            window = soon
        found = [e for e in faults if start <= _t(e) < window]  # type: ignore[operator]
        taken = [e for e in reactions if start <= _t(e) < window]  # type: ignore[operator]
        kinds = list(dict.fromkeys(str(e["kind"]) for e in found))
        summaries.append(
            {
                "kind": kind,
                "node": node_ids[joint - 1] if joint else None,
                "joint": joint or None,
                "scheduled_at_s": origin.at_s if origin is not None else None,
                "injected_s": round(t_inj, 6),
                "state_before": state_before,
                "found": [
                    {"kind": e["kind"], "t_s": _t(e), "joint": e.get("joint"), "message": e.get("message")}
                    for e in found[:_MAX_FAULTS]
                ],
                "found_count": len(found),
                "ticks_to_found": _ticks(_t(found[0]), t_inj, period) if found else None,
                "state_after": str(first["dest"]) if first is not None else state_before,
                "ticks_to_state_after": _ticks(_t(first), t_inj, period) if first is not None else None,
                "declared_reaction": _declared(kinds, state_before, spec),
                "reaction": _reaction(taken, phases, start, window),
                "power_stage": _power_stages(events, t_inj, end, len(node_ids), period, ended),
            }
        )
    summaries.extend(
        {"kind": s.kind, "node": s.node, "joint": s.joint or None, "scheduled_at_s": s.at_s, "injected_s": None}
        for s in unmatched  # the session ended before their time
    )
    return summaries


def _ticks(t_s: float | None, t_inj: float, period: float) -> int | None:
    return None if t_s is None else max(0, round((t_s - t_inj) / period))


def _declared(kinds: Sequence[str], state: str, spec: FsmSpec) -> dict[str, dict[str, str]]:
    """What the spec's ``fault_reactions`` declare for each fault kind found, in the state it was found in."""
    declared = {}
    for kind in kinds:
        try:
            entry = spec.fault_reactions[FaultKind(kind)]
        except (ValueError, KeyError):
            continue
        declared[kind] = {"reaction": entry.in_state(state), "faulted_joint": entry.faulted_joint}
    return declared


def _reaction(
    taken: Sequence[dict[str, Any]], phases: Sequence[dict[str, Any]], start: float, end: float
) -> dict[str, Any] | None:
    """The reaction the runtime took (the last one decided: escalations included) and its phases."""
    if not taken:
        return None
    last = taken[-1]
    return {
        "reaction": last.get("reaction"),
        "category": last.get("category"),
        "joints_off": last.get("joints_off"),
        "causes": last.get("causes"),
        "decided_s": _t(taken[0]),
        "phases": [
            {"phase": e.get("phase"), "t_s": _t(e), "note": e.get("note") or ""}
            for e in phases
            if start <= _t(e) < end  # type: ignore[operator]
        ],
    }


def _power_stages(
    events: Sequence[tuple[float, int, str]], t_inj: float, end: float, joints: int, period: float, ended: float
) -> dict[str, dict[str, Any]]:
    """Per joint: was its power stage on at the injection, when (ticks after it) it went off before
    ``end``, and whether that was the session's end (its torque off at robot time ``ended``)."""
    out = {}
    for joint in range(1, joints + 1):
        own = [(t, what) for t, j, what in events if j == joint and what.startswith("power stage")]
        on = False
        for t, what in own:
            if t > t_inj:
                break
            on = what == "power stage on"
        off = next((t for t, what in own if t_inj <= t < end and what == "power stage off"), None) if on else None
        out[str(joint)] = {
            "on_at_injection": on,
            "off_s": None if off is None else round(off, 6),
            "ticks_to_off": None if off is None else round((off - t_inj) / period),
            "by_session_end": off is not None and off >= ended - 0.5 * period,
        }
    return out


def fault_lines(summaries: Sequence[dict[str, Any]]) -> list[str]:
    """One line per summary, for the console after the run."""
    lines = []
    for s in summaries:
        head = f"fault {s['kind']} " + (f"on node {s['node']} (joint {s['joint']})" if s["joint"] else "of the bus")
        if s["injected_s"] is None:
            lines.append(f"{head}: scheduled at {s['scheduled_at_s']:g} s, never injected (the session ended first)")
            continue
        found = ", ".join(dict.fromkeys(f["kind"] + (f" {f['joint']}" if f["joint"] else "") for f in s["found"]))
        found_text = f"found in {s['ticks_to_found']} ticks ({found})" if s["found"] else "not found by the runtime"
        reaction = s["reaction"]
        react = (
            f"reaction {reaction['reaction']} (category {reaction['category']})"
            + (f", joint(s) {', '.join(map(str, reaction['joints_off']))} off" if reaction["joints_off"] else "")
            if reaction is not None
            else "no reaction"
        )
        stages = []
        for joint, stage in s["power_stage"].items():
            if not stage["on_at_injection"]:
                continue
            ticks = stage["ticks_to_off"]
            by_end = " (the session's end)" if stage["by_session_end"] else ""
            stages.append(f"{joint} after {ticks} ticks{by_end}" if ticks is not None else f"{joint} still on")
        torque = f"power stage off: joint {'; '.join(stages)}" if stages else "no power stage was on"
        lines.append(
            f"{head} at t = {s['injected_s']:.3f} s in {s['state_before']}: {found_text}; "
            f"state {s['state_after']}; {react}; {torque}"
        )
    return lines


#: The longest robot time a HIL run waits, after its script, for a fault's reaction to hold or rest the arm, s.
REACTION_LIMIT_S = 60.0


def let_the_reaction_play_out(
    runtime: Runtime, say: Callable[[str], None], show: Callable[[], None], limit_s: float = REACTION_LIMIT_S
) -> None:
    """After a HIL script (ended or failed): while a fault's reaction moves the arm, robot time runs on.

    The run's report is about the reaction, which a script that ends in FAIL would cut short (the
    session's end takes every torque off): in lock-step, robot time goes on in steps of 0.1 s
    until the reaction holds the arm (``held``), has rested it (``rested``, torque off) or has
    ended, at most ``limit_s`` s. ``say`` prints a line, ``show`` the announcements meanwhile.
    Nothing happens on a loop on its own thread or without a reaction under way.
    """
    if not runtime.lock_step:
        return
    reaction = runtime.snapshot().reaction
    if reaction is None or not reaction.arm_held or reaction.phase in ("held", "rested"):
        return
    say(
        f"the reaction ({reaction.reaction}) moves the arm: robot time runs on until it holds or rests it (at most {limit_s:g} s)"
    )
    steps = max(round(limit_s / 0.1), 1)
    for _ in range(steps):
        runtime.runner.pass_time(0.1)
        show()
        reaction = runtime.snapshot().reaction
        if reaction is None or not reaction.arm_held or reaction.phase in ("held", "rested"):
            return
    say(f"the reaction still moves the arm after {limit_s:g} s (phase {reaction.phase}): the session ends")


def hil_config(robot_file: Path | None, scenario: str | None, rate_hz: float | None, traffic: Path) -> CanSimHalConfig:
    """The ``can-sim`` configuration of a HIL run: a robot file's nodes on simulated drives, or the DAROR-01's.

    A ``backend: can`` robot file runs its nodes as they are (EDS, objects, units, PDOs) on python-can's
    virtual bus, with simulated drives built from each node's EDS and profile, in front of the
    simulated plant; a ``can-sim`` file likewise. ``scenario`` and ``rate_hz`` (the flags) replace
    the file's; the bus log goes to ``traffic``.

    Raises:
        HalConfigError: the file cannot be read, is not a CAN robot file, or a field is wrong (one line).
    """
    from hal.config import CanHalConfig, CanSimHalConfig, hal_config, load_hal_config
    from hal.errors import HalConfigError

    flags = {"scenario": scenario, "rate_hz": rate_hz, "traffic_log": str(traffic)}
    if robot_file is None:
        return cast(CanSimHalConfig, hal_config("can-sim", "--scenario/--rate-hz", **flags))  # the can-sim variant
    loaded = load_hal_config(robot_file)
    if not isinstance(loaded, CanHalConfig | CanSimHalConfig):
        raise HalConfigError(
            f"{robot_file}: backend {loaded.backend}; expected a CAN robot file (backend: can or can-sim) for daror hil"
        )
    hardware_only = {"backend", "interface", "channel", "velocity_filter_hz", "traffic_log"}
    if loaded.nodes is not None:
        hardware_only |= {"node_ids", "eds"}  # the nodes' own (a robot file gives one of the two)
    fields = loaded.model_dump(by_alias=True, exclude=hardware_only)
    fields.update({k: v for k, v in flags.items() if v is not None})
    try:
        return CanSimHalConfig.model_validate(fields)
    except ValueError as exc:  # a field of the file that only hardware takes: said in one line
        raise HalConfigError(f"{robot_file}: {' '.join(str(exc).split())}") from None
