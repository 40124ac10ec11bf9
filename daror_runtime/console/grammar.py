"""The console's commands: what each one takes, its help in plain words, and checking a line.

Every console line is checked here before anything runs: the command exists, its words are of the
right kind and in range, named files can be read and parse (an ISB limits file, a model file and
its validation data), and world commands are only accepted where there is a simulated world. A
script is checked whole before its first line runs (:func:`check_lines`), so a typo on line 80
costs nothing. A check returns a :class:`Parsed` line: the command and its typed arguments; the
console session executes it (:mod:`daror_runtime.console.commands`).

Lines are split like a shell's; ``#`` starts a comment.
"""

from __future__ import annotations

import math
import re
import shlex
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from daror_runtime.errors import InputError, UsageError
from daror_runtime.fsm.signals import Checklist
from daror_runtime.models.registry import kind_names
from daror_runtime.records.codes import PILOT_CODE_PATTERN
from hal.files import DATA_MAX_BYTES, MODEL_MAX_BYTES, YAML_MAX_BYTES, regular_file
from hal.isb import load_isb_limits
from hal.robot import RobotDescription

__all__ = ["COMMANDS", "CommandError", "CommandSpec", "ParseContext", "Parsed", "check_lines", "parse_line"]


class CommandError(UsageError):
    """A console line that is not a command, or has the wrong arguments (the message shows the usage)."""


@dataclass(frozen=True)
class ParseContext:
    """What a line is checked against (known before the session starts).

    Attributes:
        state_names: the FSM's states (``expect state``, ``wait until state``), FAIL included.
        has_world: the backend offers a simulated world (``sim`` commands).
        description: the robot the session runs (a model file must be fitted for its geometry).
        fault_kinds: the faults the simulated world can inject.
    """

    state_names: tuple[str, ...]
    has_world: bool
    description: RobotDescription | None = None
    fault_kinds: tuple[str, ...] = ()


@dataclass(frozen=True)
class Parsed:
    """One checked line: the command's name and its typed arguments."""

    command: str
    args: tuple[Any, ...] = ()
    line: str = ""


@dataclass(frozen=True)
class CommandSpec:
    """One console command: its usage, its help in plain words, and how its words are checked."""

    name: str
    usage: str
    summary: str
    group: str
    parse: Callable[[list[str], ParseContext], tuple[Any, ...]]
    details: str = ""
    world: bool = False  # acts on the simulated world: refused on hardware
    aliases: tuple[str, ...] = field(default_factory=tuple)


GROUPS = (
    "moving through the session",
    "the session's work",
    "looking",
    "time",
    "scripts",
    "the simulated world (simulated plant only)",
    "ending",
)


# --- argument checks ----------------------------------------------------------------------------


def _usage(spec_usage: str) -> CommandError:
    return CommandError(f"usage: {spec_usage}")


def _arity(usage: str, args: Sequence[str], n: int | tuple[int, ...]) -> None:
    allowed = (n,) if isinstance(n, int) else n
    if len(args) not in allowed:
        raise _usage(usage)


def number(what: str, text: str, low: float | None = None, high: float | None = None) -> float:
    """``text`` as a finite number within [low, high].

    Raises:
        CommandError: not a number, not finite, or out of range (named).
    """
    try:
        value = float(text)
    except ValueError:
        raise CommandError(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise CommandError(f"{what}: {text!r} is not a finite number")
    if (low is not None and value < low) or (high is not None and value > high):
        bounds = f"between {low:g} and {high:g}" if low is not None and high is not None else f">= {low:g}"
        raise CommandError(f"{what}: expected a number {bounds}, got {text}")
    return value


def _one_of(what: str, text: str, choices: Iterable[str]) -> str:
    options = list(choices)
    if text not in options:
        raise CommandError(f"{what}: {text!r} is not one of {', '.join(options)}")
    return text


def _readable_file(what: str, text: str, max_bytes: int = DATA_MAX_BYTES) -> Path:
    try:
        return regular_file(text, CommandError, max_bytes, "file")
    except CommandError as exc:
        raise CommandError(f"{what}: {exc}") from None


def _no_args(usage: str) -> Callable[[list[str], ParseContext], tuple[Any, ...]]:
    def parse(args: list[str], context: ParseContext) -> tuple[Any, ...]:
        _arity(usage, args, 0)
        return ()

    return parse


def _quit(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    if args == ["now"]:
        return (True,)
    _arity("quit [now]", args, 0)
    return (False,)


def _confirm(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    _arity("confirm CHECKLIST", args, 1)
    return (_one_of("confirm CHECKLIST", args[0], (c.value for c in Checklist)),)


def _pilot(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    _arity("pilot CODE", args, 1)
    if re.match(PILOT_CODE_PATTERN, args[0]) is None:
        raise CommandError(
            f"pilot CODE: {args[0]!r} is not a code; expected letters, digits, '_', '.', '-' (at most 32), e.g. P-007"
        )
    return (args[0],)


def _support(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    _arity("support LEVEL", args, 1)
    return (number("support LEVEL", args[0], 0.0, 1.0),)


def _compare(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    usage = "compare a_priori [PAIRS] [SECONDS]"
    if not args or args[0] != "a_priori" or len(args) > 3:
        raise _usage(usage)
    pairs = number("compare PAIRS", args[1], 2.0, 30.0) if len(args) > 1 else 8.0
    if pairs != int(pairs):
        raise CommandError(f"compare PAIRS: a whole number of pairs, got {args[1]!r}")
    seconds = number("compare SECONDS", args[2], 5.0, 120.0) if len(args) > 2 else 20.0
    return (int(pairs), seconds)


def _rate(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    _arity("rate N | rate sim", args, 1)
    if args[0] == "sim":
        return (None,)
    return (number("rate N", args[0], 0.0, 10.0),)


def _rom(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    usage = "rom start | rom stop | rom load FILE | rom last"
    if args in (["start"], ["stop"], ["last"]):
        return (args[0],)
    if len(args) == 2 and args[0] == "load":
        path = _readable_file("rom load FILE", args[1], YAML_MAX_BYTES)
        try:
            limits = load_isb_limits(path)
        except InputError as exc:
            raise CommandError(f"rom load: {exc}") from None
        return ("load", limits, str(path))
    raise _usage(usage)


def _identify(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    _arity("identify training | identify validation | identify stop", args, 1)
    return (_one_of("identify", args[0], ("training", "validation", "stop")),)


def _session_kinds() -> tuple[str, ...]:
    """The model kinds a session may train: the registry's kinds with the capability ``session_training``."""
    return kind_names(lambda entry: entry.session_training)


def _train(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    _arity("train [KIND]", args, (0, 1))
    if not args:
        return (None,)
    return (_one_of("train KIND", args[0], _session_kinds()),)


def _model(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    nonconservative = bool(args) and args[-1] == "nonconservative"
    if nonconservative:
        args = args[:-1]
    _arity("model FILE [VALIDATION_FILE] [nonconservative] | model last [nonconservative]", args, (1, 2))
    if args == ["last"]:  # the pilot's last model in the lab's records, re-validated on this session's run
        return ("last", None, nonconservative)
    path = _readable_file("model FILE", args[0], MODEL_MAX_BYTES)
    from daror_runtime.models.files import load_model  # the model kinds import lazily

    try:
        _, document = load_model(path)
    except InputError as exc:
        raise CommandError(f"model: {exc}") from None
    if context.description is not None and document.robot.geometry != context.description.geometry:
        raise CommandError(f"model: {path}: fitted for another robot geometry than this session's")
    validation = _readable_file("model VALIDATION_FILE", args[1]) if len(args) == 2 else None
    return (path, validation, nonconservative)


def _status(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    _arity("status [json]", args, (0, 1))
    if args and args[0] != "json":
        raise _usage("status [json]")
    return (bool(args),)


def _help(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    _arity("help [COMMAND]", args, (0, 1))
    if args:
        spec = lookup(args[0])
        if spec is None:
            raise CommandError(f"help: no command {args[0]!r}; type help for the list")
        return (spec.name,)
    return (None,)


WAIT_CONDITIONS = ("idle", "still", "model", "state")
#: How long ``wait until`` waits when no timeout is given (s): the full protocol takes 15 minutes.
DEFAULT_WAIT_TIMEOUT_S = 3600.0


def _wait(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    usage = "wait SECONDS | wait until idle|still|model|state NAME [timeout SECONDS]"
    if len(args) == 1:
        return ("seconds", number("wait SECONDS", args[0], 0.0, 86400.0))
    if len(args) < 2 or args[0] != "until":
        raise _usage(usage)
    rest = args[1:]
    timeout_s = DEFAULT_WAIT_TIMEOUT_S
    if len(rest) >= 2 and rest[-2] == "timeout":
        timeout_s = number("timeout SECONDS", rest[-1], 0.0, 86400.0)
        rest = rest[:-2]
    if rest in (["idle"], ["still"], ["model"]):
        return ("until", rest[0], None, timeout_s)
    if len(rest) == 2 and rest[0] == "state":
        return ("until", "state", _one_of("wait until state", rest[1], context.state_names), timeout_s)
    raise CommandError("wait until: expected idle, still, model or state NAME (and optionally timeout SECONDS)")


def _expect(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    usage = "expect state NAME | expect accepted | expect refused"
    if len(args) == 2 and args[0] == "state":
        return ("state", _one_of("expect state", args[1], context.state_names))
    if args in (["accepted"], ["refused"]):
        return (args[0],)
    raise _usage(usage)


SIM_USAGE = (
    "sim estop operator|pilot on|off | sim fault KIND [JOINT] [VALUE] | sim clear | "
    "sim pilot carry SHARE|stiffness SCALE|hold|stop|sweep [SECONDS_PER_MOVE]|move ELEVATION HORIZONTAL AXIAL "
    "ELBOW [SECONDS] | sim rest here|off"
)
_ISB_WORDS = ("ELEVATION", "HORIZONTAL", "AXIAL", "ELBOW")


def _sim(args: list[str], context: ParseContext) -> tuple[Any, ...]:
    if len(args) == 3 and args[0] == "estop":
        return (
            "estop",
            _one_of("sim estop", args[1], ("operator", "pilot")),
            _one_of("sim estop", args[2], ("on", "off")) == "on",
        )
    if args and args[0] == "fault" and 2 <= len(args) <= 4:
        kind = _one_of("sim fault KIND", args[1], context.fault_kinds)
        joint = int(number("sim fault JOINT", args[2], 1, 4)) if len(args) >= 3 else None
        value = number("sim fault VALUE", args[3]) if len(args) == 4 else None
        return ("fault", kind, joint, value)
    if args == ["clear"]:
        return ("clear",)
    if len(args) == 2 and args[0] == "rest":
        return ("rest", _one_of("sim rest", args[1], ("here", "off")))
    if len(args) >= 2 and args[0] == "pilot":
        what, rest = args[1], args[2:]
        if what == "carry" and len(rest) == 1:
            return ("pilot", "carry", number("sim pilot carry SHARE", rest[0], 0.0, 1.0))
        if what == "stiffness" and len(rest) == 1:
            return ("pilot", "stiffness", number("sim pilot stiffness SCALE", rest[0], 0.0, 2.0))
        if what in ("hold", "stop") and not rest:
            return ("pilot", what)
        if what == "move" and len(rest) in (4, 5):
            pose = tuple(
                number(f"sim pilot move {name}", text, -180.0, 180.0)
                for name, text in zip(_ISB_WORDS, rest[:4], strict=True)
            )
            seconds = number("sim pilot move SECONDS", rest[4], 0.2, 60.0) if len(rest) == 5 else None
            return ("pilot", "move", pose, seconds)
        if what == "sweep" and len(rest) <= 1:
            return ("pilot", "sweep", number("sim pilot sweep SECONDS_PER_MOVE", rest[0], 0.2, 60.0) if rest else None)
    raise CommandError(f"usage: {SIM_USAGE}")


COMMANDS: tuple[CommandSpec, ...] = (
    CommandSpec(
        "advance",
        "advance",
        "go on to the next state (when every condition of this state holds)",
        GROUPS[0],
        _no_args("advance"),
        "The status view lists what this state still needs under 'next steps'.",
    ),
    CommandSpec("revert", "revert", "go back one state", GROUPS[0], _no_args("revert")),
    CommandSpec(
        "reset",
        "reset",
        "go back to the first state (also the way out of FAIL)",
        GROUPS[0],
        _no_args("reset"),
        "Leaving FAIL needs the fault's cause gone and the fault acknowledged (ack).",
    ),
    CommandSpec(
        "ack",
        "ack",
        "acknowledge the faults shown in the status view",
        GROUPS[0],
        _no_args("ack"),
        aliases=("acknowledge",),
    ),
    CommandSpec(
        "lower",
        "lower",
        "a fault's reaction holds the pilot's arm: lower it to its rest",
        GROUPS[0],
        _no_args("lower"),
        "The arm goes to the rest pose of the session settings at a bounded speed, then onto its rest (lap, "
        "armrest or the robot's stops), and the torque goes off (docs/safety.md).",
    ),
    CommandSpec(
        "release",
        "release",
        "a fault's reaction holds the pilot's arm: ramp the torque to zero (someone must hold the arm)",
        GROUPS[0],
        _no_args("release"),
        "Only once a person holds the pilot's arm: the robot lets go of it over the handoff time.",
    ),
    CommandSpec(
        "confirm",
        "confirm CHECKLIST",
        "confirm a checklist of this state",
        GROUPS[0],
        _confirm,
        "Checklists: settings (the session settings are right: type settings to see them), installation "
        "(straps, shoulder alignment, cables), safety_experience (the pilot felt the limits and knows the "
        "e-stop), a_priori_model (the A Priori model may support this pilot until a validated model exists).",
    ),
    CommandSpec(
        "pilot",
        "pilot CODE",
        "name the session's pilot by his code (in settings, before the state is left)",
        GROUPS[0],
        _pilot,
        "A code from the lab's records (daror pilots add CODE), never a name. On a real robot settings is not left "
        "until the pilot is named; a simulated robot's pilot is its scenario's unless named. Every file, the audit "
        "trail and the records carry the code.",
    ),
    CommandSpec(
        "support",
        "support LEVEL",
        "set the compensation support level, 0 to 1 (it ramps there)",
        GROUPS[1],
        _support,
    ),
    CommandSpec(
        "compare",
        "compare a_priori [PAIRS] [SECONDS]",
        "blind comparison: the validated model in use against the A Priori model, in rated blocks",
        GROUPS[1],
        _compare,
        "In state compensation, with the A Priori model confirmed for this pilot. PAIRS pairs of blocks (default 8, "
        "2-30) of SECONDS each (default 20, 5-120), in a balanced random order the console does not show; after "
        "each block: rate N. The verdict (ratings, indicators, paired tests) at the end. docs/online.md.",
    ),
    CommandSpec(
        "rate",
        "rate N | rate sim",
        "the pilot's rating (0-10) of the comparison's block just ended (sim: the simulated pilot rates)",
        GROUPS[1],
        _rate,
    ),
    CommandSpec(
        "drift",
        "drift",
        "drift test: the model alone holds the relaxed arm; caught after 1 s or 3 deg, the torque it missed measured",
        GROUPS[1],
        _no_args("drift"),
        "In state compensation at support 1.0, the arm still and 8 deg inside every limit, the pilot relaxed "
        "(he holds nothing). The session catches the arm by reverting to training (a bumpless hold); advance "
        "returns to compensation. docs/online.md.",
    ),
    CommandSpec(
        "rom",
        "rom start | rom stop | rom load FILE | rom last",
        "record the pilot's range of motion, load it from a file, or take his last from the lab's records",
        GROUPS[1],
        _rom,
        "rom start begins recording; move the pilot's arm through its whole comfortable range; rom stop makes "
        "the recorded range the pilot's limits. rom load FILE reads the limits from a YAML file of ISB angles. "
        "rom last takes a returning pilot's last limits from the lab's records, if they are not older than the "
        "settings' limits_max_age_days.",
    ),
    CommandSpec(
        "identify",
        "identify training | identify validation | identify stop",
        "run the identification protocol (the robot moves the arm; the pilot relaxes)",
        GROUPS[1],
        _identify,
        "Run training first, then validation; each takes several minutes. identify stop stops a run.",
    ),
    CommandSpec(
        "train",
        "train [KIND]",
        "train a model on this session's identification data",
        GROUPS[1],
        _train,
        f"KIND: {', '.join(_session_kinds())} (default: the session's, plf+). The model is used only if it passes "
        "validation.",
    ),
    CommandSpec(
        "model",
        "model FILE [VALIDATION_FILE] [nonconservative] | model last [nonconservative]",
        "use a model file, once it passes validation on held-out data of this pilot",
        GROUPS[1],
        _model,
        "Without VALIDATION_FILE the session's own validation run is used; a VALIDATION_FILE must be a recording "
        "of this pilot on this robot (its provenance file says so: an earlier session's run). A model that fails "
        "validation is refused and never drives the arm. A model the closed-path test finds not conservative is "
        "refused with its energy figure; add 'nonconservative' to use it anyway. model last takes a returning "
        "pilot's last validated model from the lab's records and re-validates it on this session's validation run "
        "(identify validation first). A model file the records hold with another hash is refused.",
    ),
    CommandSpec("status", "status [json]", "what the robot is doing, and what to do next", GROUPS[2], _status),
    CommandSpec("settings", "settings", "the session settings", GROUPS[2], _no_args("settings")),
    CommandSpec("help", "help [COMMAND]", "this list, or one command in detail", GROUPS[2], _help),
    CommandSpec(
        "wait",
        "wait SECONDS | wait until idle|still|model|state NAME [timeout SECONDS]",
        "let time pass, or wait for something to happen",
        GROUPS[3],
        _wait,
        "idle: no protocol run, job or request in progress; still: the arm at rest; model: a model chosen; "
        f"state NAME: the robot in that state. Without timeout it waits up to {DEFAULT_WAIT_TIMEOUT_S:g} s.",
    ),
    CommandSpec(
        "expect",
        "expect state NAME | expect accepted | expect refused",
        "check the state or the last answer (a script stops when it does not hold)",
        GROUPS[4],
        _expect,
    ),
    CommandSpec(
        "sim",
        SIM_USAGE,
        "act as the pilot, the e-stop buttons or a fault",
        GROUPS[5],
        _sim,
        "sim estop operator|pilot on|off presses or releases an e-stop. sim pilot carry SHARE: how much of the "
        "arm's unsupported weight the pilot carries (1 all, 0 relaxed); stiffness SCALE (0 limp, 1 calm); "
        "hold (keep the arm where it is); stop (stop moving); sweep (move through the session's waypoints at "
        "the pilot's own pace, or SECONDS_PER_MOVE); move ELEVATION HORIZONTAL AXIAL ELBOW [SECONDS] (to that ISB "
        "pose, deg, at his own pace or in SECONDS). sim fault KIND injects a fault, sim clear removes it. "
        "sim rest here: the pilot's arm lies on something where it is now (his lap, an armrest), what a fault's "
        "lowering hands it to; sim rest off takes it away.",
        world=True,
    ),
    CommandSpec(
        "quit",
        "quit [now]",
        "end the session: torque off first, then the session is saved",
        GROUPS[6],
        _quit,
        "While a fault's reaction holds the pilot's arm, quit is refused: lower it to its rest or release it "
        "once someone holds it; quit now ends the session anyway and the torque off drops the arm.",
        aliases=("exit",),
    ),
)

_BY_NAME = {name: spec for spec in COMMANDS for name in (spec.name, *spec.aliases)}


def lookup(word: str) -> CommandSpec | None:
    return _BY_NAME.get(word)


def split(line: str) -> list[str]:
    """The words of ``line`` (shell-like; ``#`` starts a comment).

    Raises:
        CommandError: unbalanced quotes.
    """
    try:
        return shlex.split(line, comments=True)
    except ValueError as exc:
        raise CommandError(f"cannot split {line!r}: {exc}") from None


def parse_line(line: str, context: ParseContext) -> Parsed | None:
    """Check one line; None for an empty or comment line.

    Raises:
        CommandError: unknown command, wrong words, an unreadable file, a world command on hardware.
    """
    words = split(line)
    if not words:
        return None
    spec = lookup(words[0])
    if spec is None:
        raise CommandError(f"unknown command {words[0]!r}; type help for the list of commands")
    if spec.world and not context.has_world:
        raise CommandError(f"'{spec.name}' acts on the simulated plant; this session runs on hardware")
    return Parsed(spec.name, spec.parse(words[1:], context), line.strip())


def check_lines(lines: Iterable[tuple[int, str]], source: str, context: ParseContext) -> list[tuple[int, Parsed]]:
    """Check every line of a script before any runs.

    Raises:
        CommandError: the first bad line, as ``SOURCE: line N: problem``.
    """
    checked = []
    for number_, line in lines:
        try:
            parsed = parse_line(line, context)
        except CommandError as exc:
            raise CommandError(f"{source}: line {number_}: {exc}") from None
        if parsed is not None:
            checked.append((number_, parsed))
    return checked


def help_text(command: str | None = None) -> str:
    """The help, in plain words: every command by group, or one command in detail."""
    if command is not None:
        spec = _BY_NAME[command]
        lines = [f"{spec.usage}", f"  {spec.summary}"]
        if spec.details:
            lines.append(f"  {spec.details}")
        if spec.aliases:
            lines.append(f"  also: {', '.join(spec.aliases)}")
        return "\n".join(lines)
    lines = [
        "Type a command and press Enter. 'status' shows what the robot is doing and lists the next steps;",
        "'help COMMAND' explains one command. Tab completes, the arrow keys recall earlier lines.",
    ]
    for group in GROUPS:
        specs = [s for s in COMMANDS if s.group == group]
        if specs:
            lines.append("")
            lines.append(f"{group}:")
            for spec in specs:
                if len(spec.usage) <= 28:
                    lines.append(f"  {spec.usage:<28} {spec.summary}")
                else:
                    lines.append(f"  {spec.usage}")
                    lines.append(f"  {'':<28} {spec.summary}")
    return "\n".join(lines)


def completion_words(context: ParseContext) -> dict[str, Any]:
    """The command tree for completion (prompt_toolkit's NestedCompleter.from_nested_dict)."""
    checklists = {c.value: None for c in Checklist}
    states = {name: None for name in context.state_names}
    tree: dict[str, Any] = {
        "advance": None,
        "revert": None,
        "reset": None,
        "ack": None,
        "lower": None,
        "release": None,
        "confirm": checklists,
        "pilot": None,
        "support": None,
        "drift": None,
        "compare": {"a_priori": None},
        "rate": {"sim": None},
        "rom": {"start": None, "stop": None, "load": None, "last": None},
        "identify": {"training": None, "validation": None, "stop": None},
        "train": {kind: None for kind in _session_kinds()},
        "model": None,
        "status": {"json": None},
        "settings": None,
        "help": {s.name: None for s in COMMANDS},
        "wait": {"until": {"idle": None, "still": None, "model": None, "state": states}},
        "expect": {"state": states, "accepted": None, "refused": None},
        "quit": {"now": None},
    }
    if context.has_world:
        tree["sim"] = {
            "estop": {"operator": {"on": None, "off": None}, "pilot": {"on": None, "off": None}},
            "fault": {kind: None for kind in context.fault_kinds},
            "clear": None,
            "rest": {"here": None, "off": None},
            "pilot": {"carry": None, "stiffness": None, "hold": None, "stop": None, "sweep": None, "move": None},
        }
    return tree
