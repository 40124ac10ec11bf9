"""What to do next: the status view's steps, derived from the state's unmet guards.

An operator who knows only ``help`` and ``status`` must be able to take a pilot from start-up to
compensation. So every guard an FSM spec may name has a step here: what it means in plain words and
the commands that satisfy it, in the order they are typed (on the simulated plant the world's
``sim`` lines are included: the pilot, the buttons). The steps follow the spec's guards in the
order the spec lists them; a test checks every registered guard has a step, and another replays a
whole session typed only from these steps (tests/daror_runtime/console/test_console_operator.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from daror_runtime.fsm.guards import GUARDS
from daror_runtime.session.status import RuntimeStatus


@dataclass(frozen=True)
class Step:
    """One thing to do: a sentence, and the commands to type for it (may be empty: a person's act)."""

    text: str
    commands: tuple[str, ...] = ()


StepFor = Callable[[RuntimeStatus, bool], Step]


def _estop_test(button: str) -> StepFor:
    def step(status: RuntimeStatus, world: bool) -> Step:
        text = f"test the {button}'s e-stop: press it, see the torque go off, release it"
        if world:
            return Step(text, (f"sim estop {button} on", "wait 0.5", f"sim estop {button} off", "wait 0.5"))
        return Step(text)

    return step


def _estop_test_under_support(status: RuntimeStatus, world: bool) -> Step:
    """The e-stop test while the robot supports the arm, made with the forearm on a rest (D217).

    With the torque off a limp arm falls to where its weight and his springs take it, which for a
    pilot whose arm changed since his range was recorded may be outside that range (an ISB fault).
    """
    text = (
        "test the operator's e-stop under support with the pilot's forearm on the armrest or his lap "
        "(a limp arm falls where its weight takes it): press it, see the torque go off, release it, "
        "take the rest away"
    )
    if world:
        return Step(
            text,
            ("sim rest here", "sim estop operator on", "wait 0.5", "sim estop operator off", "wait 1", "sim rest off"),
        )
    return Step(text)


def _estop_released(status: RuntimeStatus, world: bool) -> Step:
    pressed = [button for button, on in status.estop_pressed.items() if on]
    text = f"release the e-stop ({', '.join(pressed) or 'none is pressed now'})"
    if world:
        return Step(text, (*(f"sim estop {button} off" for button in pressed), "wait 0.5"))
    return Step(text)


def _no_active_faults(status: RuntimeStatus, world: bool) -> Step:
    if any(status.estop_pressed.values()):
        return _estop_released(status, world)
    kinds = ", ".join(sorted({f["kind"] for f in status.faults})) or "a fault"
    return Step(f"{kinds} is latched (see faults): once its cause is gone, acknowledge it", ("ack",))


def _faults_cleared(status: RuntimeStatus, world: bool) -> Step:
    if any(status.estop_pressed.values()):
        return _estop_released(status, world)
    text = "the cause of the fault must go away (see faults): fix it, then check the status again"
    if world:
        return Step(text, ("sim clear", "wait 0.5"))
    return Step(text)


def _isb_limits(status: RuntimeStatus, world: bool) -> Step:
    moving = ("sim pilot sweep", "wait until still") if world else ()
    text = (
        "record the pilot's range of motion: the pilot moves the arm through its whole comfortable range "
        "while it is recorded (or load it from a file: rom load FILE)"
    )
    if status.rom_recording:
        return Step(
            "the range of motion is being recorded: the pilot moves the arm through its range, then stop",
            (*moving, "rom stop"),
        )
    return Step(text, ("rom start", *moving, "rom stop"))


def _model_approved(status: RuntimeStatus, world: bool) -> Step:
    arm = "the design values of the DAROR-01 " + (
        "and the Dummy Arm" if status.a_priori_includes_dummy_arm else "only, without the pilot's arm"
    )
    return Step(
        f"the next state supports the pilot with the A Priori model ({arm}): confirm it, "
        "or use a model validated for this pilot (model FILE VALIDATION_FILE)",
        ("confirm a_priori_model",),
    )


def _arm_inside_isb_limits(status: RuntimeStatus, world: bool) -> Step:
    gate = status.gates.get("advance")
    why = next((g.why for g in gate.unmet if g.name == "arm_inside_isb_limits"), None) if gate else None
    move = ("sim pilot hold",) if world else ()
    return Step(
        f"the pilot's arm is outside his recorded ISB limits ({why or 'see the status'}): the next state enforces "
        "them from its first tick, so move the arm inside them, with the pilot, before you advance (or record the "
        "limits again, rom start, if they are too narrow for the pose he rests in)",
        move,
    )


def _refused_data(refused: dict[str, Any], kind: str) -> str | None:
    """The training or validation file a refused model was trained or validated on (None: not this session's)."""
    if kind == "training":
        return refused.get("training_data")
    origin = refused.get("validation_data")
    return origin.get("path") if isinstance(origin, dict) else None


def _identification(status: RuntimeStatus, world: bool) -> Step:
    if status.identification_running is not None:
        running = status.identification_running
        return Step(
            f"the {running['kind']} run is going ({running['elapsed_s']:.0f} of {running['duration_s']:.0f} s): wait for it",
            ("wait until idle",),
        )
    relax = ("sim pilot carry 0", "sim pilot stiffness 0") if world else ()
    refused = status.model_refused or {}
    for kind in ("training", "validation"):
        saved = status.identification_saved.get(kind)
        if saved is None:
            return Step(
                f"run the {kind} protocol: the pilot relaxes completely and the robot moves the arm (minutes)",
                (*relax, f"identify {kind}", "wait until idle"),
            )
        if _refused_data(refused, kind) == saved:
            return Step(
                f"the model trained on this session's data failed validation: run the {kind} protocol again, "
                "with the pilot relaxed completely (no effort, no stiffness)",
                (*relax, f"identify {kind}", "wait until idle"),
            )
    return Step("wait until the saved data is taken over", ("wait until idle",))


def _model_trained(status: RuntimeStatus, world: bool) -> Step:
    if status.jobs_pending:
        return Step("training and validation are running outside the loop: wait for them", ("wait until idle",))
    refused = status.model_refused
    if refused is not None and refused.get("training_data") == status.identification_saved.get("training"):
        return Step(
            f"the model trained on this session's data failed validation (RMSE {refused['validation_rmse_nm']:.3g} Nm): "
            "the data cannot train a validated model; go back and record it again with the pilot relaxed",
            ("revert",),
        )
    return Step("train the compensation model on this session's data and validate it", ("train", "wait until idle"))


def _arm_released(status: RuntimeStatus, world: bool) -> Step:
    reaction = status.reaction
    if reaction is None or not reaction.arm_held:
        return Step("no reaction holds the arm")
    if reaction.phase in ("hold", "lower", "handoff", "letting go", "releasing"):
        return Step(
            f"the robot is stopping the pilot's arm ({reaction.phase}): wait until it rests on its {reaction.rest}",
            ("wait 2",),
        )
    text = f"the robot holds the pilot's arm ({reaction.note})"
    if reaction.lowering_refused is not None:
        return Step(text + ": hold the arm yourself, then release it (the torque ramps to zero)", ("release",))
    return Step(
        text + f": lower it to its rest on the {reaction.rest}, or release it once someone holds it", ("lower",)
    )


STEPS: dict[str, StepFor] = {
    "hal_connected": lambda s, w: Step("wait for the hardware to answer (drives powered, bus connected)", ("wait 1",)),
    "no_active_faults": _no_active_faults,
    "faults_cleared": _faults_cleared,
    "fault_acknowledged": lambda s, w: Step("acknowledge the fault", ("ack",)),
    "fault_latched": lambda s, w: Step("nothing to acknowledge"),
    "arm_released": _arm_released,
    "robot_at_rest": lambda s, w: Step("wait until the arm is at rest", ("wait until still",)),
    "estop_operator_tested": _estop_test("operator"),
    "estop_pilot_tested": _estop_test("pilot"),
    "estop_tested": _estop_test_under_support,
    "estop_released": _estop_released,
    "settings_confirmed": lambda s, w: Step(
        "review the session settings, then confirm them", ("settings", "confirm settings")
    ),
    "pilot_named": lambda s, w: Step(
        "name the pilot: type pilot CODE with his code in the lab's records (never his name)"
    ),
    "installation_confirmed": lambda s, w: Step(
        "check the straps, the shoulder's alignment and the cables, then confirm", ("confirm installation",)
    ),
    "safety_experience_confirmed": lambda s, w: Step(
        "once the pilot has felt the safety limits and tried the e-stop, confirm", ("confirm safety_experience",)
    ),
    "isb_limits_recorded": _isb_limits,
    "arm_inside_isb_limits": _arm_inside_isb_limits,
    "compensation_model_approved": _model_approved,
    "identification_data_or_model": _identification,
    "model_trained_and_validated": _model_trained,
}


def next_steps(status: RuntimeStatus, world: bool) -> list[Step]:
    """What to do next in ``status``, in order (``world``: the simulated world's commands are offered)."""
    if status.identification_running is not None:
        return [_identification(status, world)]
    if status.jobs_pending:
        return [Step("work is running outside the loop (saving data, training): wait for it", ("wait until idle",))]
    if status.number is None:  # FAIL
        reset = status.gates["reset"]
        if reset.ready:
            return [Step("the fault is cleared and acknowledged: go back to the first state", ("reset",))]
        return [STEPS[g.name](status, world) for g in reset.unmet]
    advance = status.gates["advance"]
    if not advance.possible:
        return [
            Step(
                f"the robot supports the pilot (support level {status.support_level:g}); "
                "'support LEVEL' changes it, 'quit' ends the session"
            )
        ]
    if advance.ready:
        return [Step("everything this state needs is done: go on to the next state", ("advance",))]
    steps: list[Step] = []
    if any(status.estop_pressed.values()):  # a held e-stop first: no other button's test counts meanwhile
        steps.append(_estop_released(status, world))
    for guard in advance.unmet:
        step = STEPS[guard.name](status, world)
        if step not in steps:
            steps.append(step)
    return steps


def unguided_steps_cover_every_guard() -> list[str]:
    """Registered guards without a step (a test keeps this empty)."""
    return sorted(set(GUARDS) - set(STEPS))
