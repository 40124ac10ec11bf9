"""The console's status view and announcements, as plain text an operator reads at a glance.

No markup: the view is the same text on a terminal, in a pipe and in a log. The last block, "next
steps", lists what to do, with the commands to type after "type:" separated by " ; " (one line per
step, so a person or a script can follow it).
"""

from __future__ import annotations

from collections.abc import Sequence

from daror_runtime.console.guide import Step
from daror_runtime.session.events import Announcement
from daror_runtime.session.status import RuntimeStatus

NEXT_HEADING = "next steps:"
TYPE_MARK = "type:"


def stamp(t_s: float | None) -> str:
    return f"[t={t_s:.3f} s]" if t_s is not None else "[t=-]"


def announcement_line(item: Announcement) -> str:
    return f"{stamp(item.t_s)} {item.kind.value}: {item.text}"


def _row(label: str, values: Sequence[float], digits: int) -> str:
    return f"  {label:<20}" + "".join(f"{v:>9.{digits}f}" for v in values)


def render_status(status: RuntimeStatus, steps: Sequence[Step], notes: Sequence[str] = ()) -> str:
    """The status view: state, what blocks the next step, faults, joints, model, support, limits, loop, next steps."""
    lines = [
        *_state_lines(status),
        *_gate_lines(status),
        *_fault_lines(status),
        *_reaction_lines(status),
        _estop_line(status),
        *_joint_lines(status),
        *_model_lines(status),
        *_refused_model_lines(status),
        _support_line(status),
        *_online_lines(status),
        *_comparison_lines(status),
        _isb_line(status),
        _identification_line(status),
    ]
    if status.last_error:
        lines.append(f"last error: {status.last_error}")
    lines.append(_loop_line(status))
    lines.extend(f"note: {note}" for note in notes)
    lines.extend(_next_step_lines(steps))
    return "\n".join(lines)


def _state_lines(status: RuntimeStatus) -> list[str]:
    """The state (number, name, superstate, what it is), then its mode, time and session."""
    if status.number is None:
        state = f"state {status.state}: {status.description}"
    else:
        kind = "  (e-stop test state: a fault is met by its reaction, no FAIL)" if status.estop_test_state else ""
        state = f"state {status.number} {status.state} ({status.superstate}): {status.description}{kind}"
    pilot = f"pilot {status.pilot}" if status.pilot is not None else "no pilot named (pilot CODE)"
    return [
        state,
        f"  mode {status.mode}, t = {status.t_s:.3f} s, session {status.session_id}, {pilot}"
        if status.t_s is not None
        else f"  mode {status.mode}, no sample yet, session {status.session_id}, {pilot}",
    ]


def _gate_lines(status: RuntimeStatus) -> list[str]:
    """Each transition the state has: possible, or blocked and the guards it needs (acknowledge only with faults)."""
    lines: list[str] = []
    for name in ("advance", "revert", "reset", "acknowledge"):
        gate = status.gates[name]
        if not gate.possible or (name == "acknowledge" and not status.faults):
            continue
        if gate.ready:
            lines.append(f"{name}: possible")
        else:
            lines.append(f"{name}: blocked, needs")
            lines.extend(f"  - {g.name}: {g.description}" for g in gate.unmet)
    return lines


def _fault_lines(status: RuntimeStatus) -> list[str]:
    """The active faults, one a line, or "none"."""
    if not status.faults:
        return ["faults: none"]
    return [
        "faults (each met by its reaction until acknowledged and reset):",
        *(f"  - {f['kind']}: {f['message']} (t = {f['t_s']:.3f} s)" for f in status.faults),
    ]


def _reaction_lines(status: RuntimeStatus) -> list[str]:
    """The fault reaction under way (what, its stop category, causes, joints off, support) and its phase; none without."""
    reaction = status.reaction
    if reaction is None:
        return []
    what = {"off": "torque off", "lower": "hold, lower to the rest, torque off", "hold": "hold"}[reaction.reaction]
    off = f", joint(s) {', '.join(map(str, reaction.joints_off))} off" if reaction.joints_off else ""
    lines = [
        f"reaction: {what} (category {reaction.category}; {', '.join(reaction.causes)}{off}; support "
        f"{reaction.support})"
    ]
    if reaction.phase is not None:
        lines.append(f"  now: {reaction.phase}" + (f": {reaction.note}" if reaction.note else ""))
    return lines


def _estop_line(status: RuntimeStatus) -> str:
    """The e-stops: which are pressed, or "released"."""
    pressed = [b for b, on in status.estop_pressed.items() if on]
    return f"e-stops: {'PRESSED: ' + ', '.join(pressed) if pressed else 'released'}"


def _joint_lines(status: RuntimeStatus) -> list[str]:
    """The joints' table (angle, speed, spring torque, motor command per joint) and the drives; none before a sample."""
    joints = status.joints
    if joints is None:
        return []
    return [
        "  joint" + " " * 15 + "".join(f"{j:>9d}" for j in range(1, 5)),
        _row("angle, deg", joints.q_deg, 1),
        _row("speed, deg/s", joints.dq_deg_s, 1),
        _row("spring torque, Nm", joints.spring_torque_nm, 2),
        _row("motor command, Nm", joints.motor_command_nm, 2),
        f"  drives: {', '.join(joints.drives)}",
    ]


def _model_lines(status: RuntimeStatus) -> list[str]:
    """The compensation model in use: none, validated (with its figures), or approved but not validated."""
    model = status.model
    if model is None:
        return ["model: none approved yet (compensation cannot start)"]
    if not model.validated:
        arm = "with the Dummy Arm" if model.includes_dummy_arm else "robot only, without the pilot's arm"
        return [f"model: {model.name} ({model.kind}, {arm}), approved by the operator, not validated"]
    lines = [
        f"model: {model.name} ({model.kind}), validated: RMSE {model.validation_rmse_nm:.3f} Nm on held-out data "
        f"(limit {model.max_validation_rmse_nm:g} Nm)"
    ]
    if model.validation_data is not None:
        lines.append(f"  validation data: {model.validation_data}")
    if model.validation_extrapolation is not None:
        lines.append(f"  {model.validation_extrapolation}")
    if model.nonconservative_confirmed and model.closed_path_energy_j:
        lines.append(
            f"  NOT conservative: {model.closed_path_energy_j[-1]:.3g} J over the closed path; used because the "
            "operator confirmed it"
        )
    return lines


def _refused_model_lines(status: RuntimeStatus) -> list[str]:
    """The model last refused and why (failed validation, or not conservative); none without."""
    refused = status.model_refused
    if refused is None:
        return []
    if refused["validated"]:  # validated, but the closed-path test found it not conservative
        return [
            f"  refused: {refused['name']} is not conservative ({refused['closed_path_energy_j'][-1]:.3g} J over "
            "the closed path); 'model FILE VALIDATION nonconservative' uses it anyway"
        ]
    return [
        f"  refused: {refused['name']} failed validation (RMSE {refused['validation_rmse_nm']:.3f} Nm > "
        f"{refused['max_validation_rmse_nm']:g} Nm); it never drives the arm"
    ]


def _support_line(status: RuntimeStatus) -> str:
    """The support level asked and delivered, and the torque still being handed over (compensation only), N m."""
    handover = max(abs(v) for v in status.handover_nm) if status.mode == "compensation" else 0.0
    return f"support level: {status.support_level:.2f} (delivered {status.delivered_support_level:.2f}" + (
        f"; handing over {handover:.2f} Nm held at entry)" if handover > 0 else ")"
    )


def _joints(values: Sequence[float | None], digits: int = 2) -> str:
    return " ".join("-" if v is None else f"{v:.{digits}f}" for v in values)


def _online_lines(status: RuntimeStatus) -> list[str]:
    """The online indicators per model that compensated (issue 29): the pilot's effort at rest, the
    support delivered, the interaction while moving (docs/online.md)."""
    lines = []
    for entry in status.online:
        last = entry["last_rest"]
        rest = (
            "no rest yet"
            if last is None
            else f"his effort at the last rest {_joints(last['effort_nm'])} Nm "
            f"({last['t_end_s'] - last['t_start_s']:.1f} s at level {last['level_asked']:.2f}"
            + (
                f"; {_joints(last['effort_corrected_nm'])} Nm less the model's error a drift test measured there)"
                if last.get("effort_corrected_nm")
                else ")"
            )
        )
        delivered = entry["level_delivered"]
        lines.append(
            f"online, {entry['model']}: {rest}; {entry['rests']} rests, RMS {_joints(entry['effort_at_rest_rms_nm'] or [None] * 4)} Nm"
            + ("" if delivered is None else f"; support delivered {delivered:.2f}")
        )
        tests = entry.get("drift_tests") or []
        if tests:
            last = tests[-1]
            worst = [max(abs(test["unsupported_nm"][j]) for test in tests) for j in range(len(last["unsupported_nm"]))]
            lines.append(
                f"  drift tests: {len(tests)}; the last: unsupported torque {_joints(last['unsupported_nm'])} Nm, "
                f"drift {_joints(last['drift_deg'], 1)} deg in {last['drift_s']:.2f} s ({last['why_caught']}); "
                f"the largest over all: {_joints(worst)} Nm"
            )
        if any(n for n in entry["moving_samples"]):
            lines.append(
                f"  while moving: interaction RMS {_joints(entry['interaction_rms_nm'])} Nm, "
                f"felt damping {_joints(entry['apparent_damping_nms_per_rad'])} Nms/rad"
            )
    return lines


def _comparison_lines(status: RuntimeStatus) -> list[str]:
    """A blind comparison's progress (never which model a block has) or its verdict (issue 29)."""
    comparison = status.comparison
    if comparison is None:
        return []
    if "verdict_text" in comparison:
        return [comparison["verdict_text"]]
    if "why_stopped" in comparison:
        return [f"blind comparison stopped: {comparison['why_stopped']}"]
    return [
        f"blind comparison: block {comparison['block']} of {comparison['blocks']} ({comparison['phase']}; "
        f"{comparison['rated']} rated; the model is not shown)"
    ]


def _isb_line(status: RuntimeStatus) -> str:
    """The pilot's ISB limits, deg, and the monitor's margin beyond them; or not recorded (recording)."""
    if status.isb_limits_deg is None:
        return "ISB limits: not recorded" + (" (recording)" if status.rom_recording else "")
    ranges = ", ".join(
        f"{name.replace('_', ' ')} {lo:.0f}..{hi:.0f}" for name, (lo, hi) in status.isb_limits_deg.items()
    )
    return (
        f"ISB limits, deg: {ranges} (where they are enforced, the monitor allows {status.isb_margin_deg:g} deg "
        "beyond each: isb_margin_deg)"
    )


def _identification_line(status: RuntimeStatus) -> str:
    """The identification run under way (kind, elapsed of duration, s) and what was saved."""
    run = status.identification_running
    saved = ", ".join(f"{kind} saved" for kind in status.identification_saved) or "nothing saved"
    if run is None:
        return f"identification: {saved}"
    return f"identification: {run['kind']} running, {run['elapsed_s']:.0f} of {run['duration_s']:.0f} s ({saved})"


def _loop_line(status: RuntimeStatus) -> str:
    """The control loop: clock, rate, ticks, its timing faults (or stalls when paced), lateness and tick work."""
    loop = status.loop
    timing = (  # paced: a stall of the process delayed the simulated world, it is not a fault
        f"{loop.stalls} stalls (not faults), the world {loop.behind_ms:.1f} ms behind the wall clock"
        if loop.clock == "paced"
        else f"{loop.overruns} overruns, {loop.missed_deadlines} missed deadlines"
    )
    return (
        f"loop: {loop.clock} at {loop.rate_hz:g} Hz, {loop.ticks} ticks, {timing}, "
        f"worst lateness {loop.worst_lateness_ms:.2f} ms, "
        f"tick work {loop.tick_work_mean_us:.0f} us mean, {loop.tick_work_max_us:.0f} us worst"
        + (f", {loop.dropped_rows} recorder rows dropped" if loop.dropped_rows else "")
    )


def _next_step_lines(steps: Sequence[Step]) -> list[str]:
    """The "next steps" block: one line per step, its commands after "type:" separated by " ; "."""
    return [
        NEXT_HEADING,
        *(
            f"  - {step.text}" + (f". {TYPE_MARK} {' ; '.join(step.commands)}" if step.commands else "")
            for step in steps
        ),
    ]


def suggested_commands(view: str) -> list[str]:
    """The commands a status view suggests, in order (what a person following it would type)."""
    commands: list[str] = []
    after = view.split(NEXT_HEADING, 1)
    if len(after) < 2:
        return commands
    for line in after[1].splitlines():
        if f". {TYPE_MARK} " in line:
            commands.extend(c.strip() for c in line.split(f". {TYPE_MARK} ", 1)[1].split(" ; "))
    return commands
