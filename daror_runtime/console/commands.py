"""Console commands: one line, one request to the runtime (or one act of the simulated world).

Operator requests (they take effect at the next tick boundary; the console shows the answer)::

    advance | revert | reset | ack
    confirm settings|installation|safety_experience
    support LEVEL                      compensation support level in [0, 1]
    rom start | rom stop | rom load FILE
    identify training|validation | identify stop
    train [ap|plf|plf+]                train on this session's identification data (a job)
    model FILE [VALIDATION_FILE]       use a model file, validated on validation data (a job)
    status

Time (lock-step: robot time passes; real time: the console waits)::

    wait SECONDS
    wait until idle|still|model|state NAME [timeout SECONDS]

Script checks (a failed check stops the script, exit code 1)::

    expect state NAME | expect accepted | expect refused

The simulated world (only with the simulated plant)::

    sim estop operator|pilot on|off
    sim fault nan|jump|stale|drive_fault|bus [JOINT] [VALUE] | sim clear
    sim pilot carry SHARE | sim pilot stiffness SCALE | sim pilot hold | sim pilot sweep [SECONDS_PER_MOVE]

Lines are split like a shell's; ``#`` starts a comment.
"""

from __future__ import annotations

import json
import math
import shlex
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from daror_runtime.errors import DarorError, UsageError
from daror_runtime.fsm.supervisor import Response, Ticket
from daror_runtime.runtime import Runtime
from hal.isb import load_isb_limits

from .world import SimWorld

__all__ = ["CommandError", "ConsoleSession", "ScriptCheckError"]


class CommandError(UsageError):
    """A console line that is not a command, or has the wrong arguments (the message shows the usage)."""


class ScriptCheckError(DarorError):
    """An ``expect`` line of a script did not hold."""


@dataclass
class _Last:
    response: Response | None = None


class ConsoleSession:
    """Executes console lines against a runtime (and the simulated world, if any).

    Args:
        runtime: an opened runtime.
        out: where answers are printed.
        world: the simulated world (None on hardware: ``sim`` commands are refused).
        request_timeout_s: how long a request may wait for its tick (robot time in lock-step).
    """

    def __init__(
        self, runtime: Runtime, out: Console, world: SimWorld | None = None, request_timeout_s: float = 5.0
    ) -> None:
        self.runtime = runtime
        self.out = out
        self.world = world
        self.timeout_s = request_timeout_s
        self.last = _Last()
        self._commands: dict[str, Callable[[list[str]], None]] = {
            "advance": self._fsm("advance"),
            "revert": self._fsm("revert"),
            "reset": self._fsm("reset"),
            "ack": self._fsm("acknowledge"),
            "acknowledge": self._fsm("acknowledge"),
            "confirm": self._confirm,
            "support": self._support,
            "rom": self._rom,
            "identify": self._identify,
            "train": self._train,
            "model": self._model,
            "status": self._status,
            "wait": self._wait,
            "expect": self._expect,
            "sim": self._sim,
        }

    # --- entry ----------------------------------------------------------------------------

    def execute(self, line: str) -> None:
        """Run one line.

        Raises:
            CommandError: unknown command or bad arguments.
            ScriptCheckError: an ``expect`` did not hold.
            InputError, DarorError: the runtime refused the request before queueing it.
        """
        try:
            words = shlex.split(line, comments=True)
        except ValueError as exc:
            raise CommandError(f"cannot split {line!r}: {exc}") from None
        if not words:
            return
        command = self._commands.get(words[0])
        if command is None:
            raise CommandError(f"unknown command {words[0]!r}; commands: {', '.join(sorted(self._commands))}")
        command(words[1:])

    # --- operator requests ----------------------------------------------------------------

    def _fsm(self, event: str) -> Callable[[list[str]], None]:
        def run(args: list[str]) -> None:
            _arity(event, args, 0)
            self._answer(self.runtime.request(event))

        return run

    def _confirm(self, args: list[str]) -> None:
        _arity("confirm CHECKLIST", args, 1)
        self._answer(self.runtime.confirm(args[0]))

    def _support(self, args: list[str]) -> None:
        _arity("support LEVEL", args, 1)
        self._answer(self.runtime.set_support(_number("support LEVEL", args[0])))

    def _rom(self, args: list[str]) -> None:
        if args == ["start"]:
            self._answer(self.runtime.rom_start())
        elif args == ["stop"]:
            self._answer(self.runtime.rom_stop())
        elif len(args) == 2 and args[0] == "load":
            self._answer(self.runtime.set_isb_limits(load_isb_limits(args[1]), source=args[1]))
        else:
            raise CommandError("usage: rom start | rom stop | rom load FILE")

    def _identify(self, args: list[str]) -> None:
        if args == ["stop"]:
            self._answer(self.runtime.stop_identification())
        elif len(args) == 1 and args[0] in ("training", "validation"):
            self._answer(self.runtime.identify(args[0]))
        else:
            raise CommandError("usage: identify training | identify validation | identify stop")

    def _train(self, args: list[str]) -> None:
        if len(args) > 1:
            raise CommandError("usage: train [ap|plf|plf+]")
        self.runtime.train(args[0] if args else None)
        self.out.print("training queued (outside the tick); 'wait until model' waits for it")

    def _model(self, args: list[str]) -> None:
        if len(args) not in (1, 2):
            raise CommandError("usage: model FILE [VALIDATION_FILE]")
        self.runtime.select_model(Path(args[0]), Path(args[1]) if len(args) == 2 else None)
        self.out.print("model validation queued (outside the tick); 'wait until model' waits for it")

    def _status(self, args: list[str]) -> None:
        _arity("status", args, 0)
        self.out.print_json(json.dumps(self.runtime.status(), default=str))

    # --- time -----------------------------------------------------------------------------

    def _wait(self, args: list[str]) -> None:
        runtime = self.runtime
        if len(args) == 1:
            seconds = _number("wait SECONDS", args[0])
            if seconds < 0:
                raise CommandError("wait SECONDS: expected a duration >= 0")
            self._advance_time(seconds)
            return
        if not args or args[0] != "until" or len(args) < 2:
            raise CommandError("usage: wait SECONDS | wait until idle|still|model|state NAME [timeout SECONDS]")
        rest = args[1:]
        timeout_s = 600.0
        if len(rest) >= 2 and rest[-2] == "timeout":
            timeout_s = _number("timeout SECONDS", rest[-1])
            rest = rest[:-2]
        condition = self._condition(rest)
        if not runtime.run_until(condition, timeout_s) and not condition():
            raise ScriptCheckError(f"'wait until {' '.join(rest)}' did not happen within {timeout_s:g} s")
        self.out.print(f"{self._stamp()} {escape(' '.join(rest))}")

    def _condition(self, words: list[str]) -> Callable[[], bool]:
        runtime = self.runtime
        if words == ["idle"]:
            return lambda: not runtime.busy
        if words == ["still"]:

            def still() -> bool:
                moving = self.world is not None and self.world.pilot.moving
                return not moving and runtime.at_rest

            return still
        if words == ["model"]:
            return lambda: runtime.signals.model is not None and not runtime.jobs.pending
        if len(words) == 2 and words[0] == "state":
            name = words[1]
            return lambda: runtime.supervisor.state_name == name
        raise CommandError("wait until: expected idle, still, model or state NAME")

    def _advance_time(self, seconds: float) -> None:
        self.runtime.pass_time(seconds)

    # --- checks ---------------------------------------------------------------------------

    def _expect(self, args: list[str]) -> None:
        if len(args) == 2 and args[0] == "state":
            state = self.runtime.supervisor.state_name
            if state != args[1]:
                raise ScriptCheckError(f"expected state {args[1]}, the robot is in {state}")
        elif args in (["accepted"], ["refused"]):
            response = self.last.response
            if response is None:
                raise ScriptCheckError("expect accepted/refused: no request was answered yet")
            if response.accepted != (args[0] == "accepted"):
                raise ScriptCheckError(
                    f"expected {response.request!r} to be {args[0]}; it was "
                    + ("accepted" if response.accepted else f"refused ({response.reason})")
                )
        else:
            raise CommandError("usage: expect state NAME | expect accepted | expect refused")
        self.out.print(f"  ok: {escape(' '.join(args))}")

    # --- the simulated world --------------------------------------------------------------

    def _sim(self, args: list[str]) -> None:
        world = self.world
        if world is None:
            raise CommandError("'sim' commands act on the simulated plant; this session runs on hardware")
        if len(args) == 3 and args[0] == "estop" and args[2] in ("on", "off"):
            world.estop(args[1], args[2] == "on")
        elif args and args[0] == "fault" and 2 <= len(args) <= 4:
            joint = int(_number("JOINT", args[2])) if len(args) >= 3 else None
            value = _number("VALUE", args[3]) if len(args) == 4 else None
            world.fault(args[1], joint, value)
        elif args == ["clear"]:
            world.clear_faults()
        elif len(args) >= 2 and args[0] == "pilot":
            self._pilot(world, args[1:])
        else:
            raise CommandError(
                "usage: sim estop operator|pilot on|off | sim fault KIND [JOINT] [VALUE] | sim clear | sim pilot ..."
            )
        self.out.print(f"{self._stamp()} world: {escape(' '.join(args))}")

    def _pilot(self, world: SimWorld, args: list[str]) -> None:
        if len(args) == 2 and args[0] == "carry":
            world.pilot_carries(_number("carry SHARE", args[1]))
        elif len(args) == 2 and args[0] == "stiffness":
            world.pilot_stiffness(_number("stiffness SCALE", args[1]))
        elif args == ["hold"]:
            world.pilot_hold_here()
        elif args[0] == "sweep" and len(args) <= 2:
            seconds = _number("sweep SECONDS_PER_MOVE", args[1]) if len(args) == 2 else 2.0
            end = world.pilot_sweep(self.runtime.settings.identification, seconds)
            self.out.print(f"  the pilot moves through the session's waypoints until t = {end:.1f} s")
        else:
            raise CommandError("usage: sim pilot carry SHARE | stiffness SCALE | hold | sweep [SECONDS_PER_MOVE]")

    # --- internals ------------------------------------------------------------------------

    def _stamp(self) -> str:
        return escape(f"[t={self._t():.3f} s]")

    def _t(self) -> float:
        sample = self.runtime.signals.sample
        return sample.t_s if sample is not None else 0.0

    def _answer(self, ticket: Ticket) -> None:
        response = self.runtime.wait(ticket, self.timeout_s)
        self.last.response = response
        if response.accepted:
            self.out.print(f"{self._stamp()} {escape(response.request)}: accepted, state {response.state}")
        else:
            self.out.print(
                f"{self._stamp()} {escape(response.request)}: [bold]refused[/bold] ({escape(response.reason)})"
            )


def _arity(usage: str, args: list[str], n: int) -> None:
    if len(args) != n:
        raise CommandError(f"usage: {usage}")


def _number(what: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise CommandError(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise CommandError(f"{what}: {text!r} is not a finite number")
    return value
