"""Running a console session: a script (lock-step on the simulated plant) or typed lines.

A script is a text file of console lines (:mod:`daror_runtime.console.commands`). Every line is
echoed with its line number, then its answer. A line that is not a command stops the script with
exit code 2 (``FILE: line N: ...``); a failed ``expect`` or ``wait until`` stops it with exit 1.
Either way the runtime is closed: torque off, background work finished, ``session.json`` written.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from rich.console import Console
from rich.markup import escape

from daror_runtime.console.commands import CommandError, ConsoleSession, ScriptCheckError
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import DarorError, InputError, UsageError
from daror_runtime.runtime import Runtime


class ScriptError(UsageError):
    """A script line that is not a valid command (file and line named)."""


@dataclass(frozen=True)
class ScriptResult:
    lines_run: int
    state: str


def read_script(path: Path | str) -> list[tuple[int, str]]:
    """The non-empty, non-comment lines of a script with their line numbers.

    Raises:
        ScriptError: the file cannot be read.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScriptError(f"{path}: cannot read the console script ({exc})") from None
    lines = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            lines.append((number, stripped))
    return lines


def run_script(
    session: ConsoleSession, path: Path | str, lines: Iterable[tuple[int, str]] | None = None
) -> ScriptResult:
    """Run every line of the script at ``path``.

    Raises:
        ScriptError: a line is not a command, or the runtime refused it as bad input (exit 2).
        ScriptCheckError: an ``expect`` or ``wait until`` did not hold (exit 1).
    """
    count = 0
    for number, line in lines if lines is not None else read_script(path):
        session.out.print(f"[dim]{escape(str(path))}:{number}[/dim] > {escape(line)}")
        try:
            session.execute(line)
        except ScriptCheckError as exc:
            raise ScriptCheckError(f"{path}: line {number}: {exc}") from None
        except InputError as exc:
            raise ScriptError(f"{path}: line {number}: {exc}") from None
        count += 1
    return ScriptResult(count, session.runtime.supervisor.state_name)


def run_interactive(session: ConsoleSession, stdin: TextIO | None = None) -> None:
    """Read lines until ``quit`` or end of input; a bad line is answered and the session goes on."""
    stream = stdin if stdin is not None else sys.stdin
    out = session.out
    out.print("daror console: type a command ('status', 'advance', ...), 'help' or 'quit'")
    while True:
        out.print(escape(f"[{session.runtime.supervisor.state_name}] > "), end="")
        line = stream.readline()
        if not line:
            break
        line = line.strip()
        if line in ("quit", "exit"):
            break
        if line == "help":
            from daror_runtime.console import commands

            out.print(escape(commands.__doc__ or ""))
            continue
        try:
            session.execute(line)
        except (CommandError, InputError, ScriptCheckError) as exc:
            out.print(f"  [bold]error[/bold]: {escape(str(exc))}")
        except DarorError as exc:
            out.print(f"  [bold]failed[/bold]: {escape(str(exc))}")


def world_for(runtime: Runtime) -> SimWorld | None:
    """The simulated world around the runtime's HAL, or None on hardware."""
    from hal.sim.backend import SimHal

    return SimWorld(runtime.hal) if isinstance(runtime.hal, SimHal) else None


def make_session(runtime: Runtime, out: Console | None = None) -> ConsoleSession:
    return ConsoleSession(runtime, out or Console(highlight=False), world_for(runtime))
