"""Running a console session: a script, lines piped in, or an operator typing at a terminal.

* **script** (``--script FILE``): every line is checked before the first one runs (a bad line: exit
  2, nothing written); then each line is echoed with its number and run. A failed ``expect`` or
  ``wait until`` stops the script (exit 1).
* **piped** (standard input is not a terminal): each line is echoed (``> line``) and run as it
  arrives; a bad or failed line is answered and the session goes on; the exit code says whether
  anything went wrong (2 a line was not a command, 1 a command failed or was refused, else 0).
* **typed** (a terminal): a prompt with line editing, history and completion (prompt_toolkit);
  what the runtime announces (transitions, faults, finished work) is printed above the prompt as
  it happens; a bottom line shows the state.

``quit`` (or the end of the input) and Ctrl-C end the session the same way, in any state: torque
off first, then a line confirming it from the drives (``daror_runtime.runtime.Runtime.shutdown``),
recorded in the audit log and ``session.json``.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from daror_runtime.console.commands import CommandError, ConsoleSession, QuitRequested, ScriptCheckError
from daror_runtime.console.grammar import Parsed, completion_words
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import DarorError, InputError, UsageError
from daror_runtime.runtime import Runtime
from hal.files import YAML_MAX_BYTES, read_text_bounded


class ScriptError(UsageError):
    """A script that cannot be read (file named)."""


@dataclass(frozen=True)
class ScriptResult:
    lines_run: int
    state: str
    quit: bool = False


def read_script(path: Path | str) -> list[tuple[int, str]]:
    """The non-empty, non-comment lines of a script with their line numbers.

    Raises:
        ScriptError: not a readable regular text file of at most 1 MiB (a directory, a FIFO, ...).
    """
    text = read_text_bounded(path, ScriptError, YAML_MAX_BYTES, "console script")
    lines = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            lines.append((number, stripped))
    return lines


def run_script(session: ConsoleSession, path: Path | str, checked: Sequence[tuple[int, Parsed]]) -> ScriptResult:
    """Run the checked lines of the script at ``path`` (:func:`daror_runtime.console.grammar.check_lines`).

    Raises:
        ScriptCheckError: an ``expect`` or ``wait until`` did not hold, or the runtime refused a
            request before queueing it (the message names the line; exit 1).
    """
    count = 0
    for number, parsed in checked:
        session.say(f"{path}:{number} > {parsed.line}")
        try:
            session.run(parsed)
        except QuitRequested:
            return ScriptResult(count + 1, session.runtime.state_name, quit=True)
        except ScriptCheckError as exc:
            raise ScriptCheckError(f"{path}: line {number}: {exc}") from None
        except InputError as exc:  # checked words, but the runtime refused now (no data yet, ...)
            raise ScriptCheckError(f"{path}: line {number}: refused: {exc}") from None
        count += 1
    return ScriptResult(count, session.runtime.state_name)


def run_piped(session: ConsoleSession, stream: TextIO) -> int:
    """Run lines from ``stream`` as they arrive, echoing each; returns the exit code (0, 1 or 2)."""
    tally = session.tally
    for raw in stream:
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        session.say(f"> {line}")
        try:
            session.execute(line)
        except QuitRequested:
            break
        except CommandError as exc:
            tally.bad_lines += 1
            session.say(f"  error: {exc}")
        except (ScriptCheckError, DarorError) as exc:
            session.record_failure(f"{line}: {exc}")
            session.say(f"  failed: {exc}")
    if tally.bad_lines:
        return 2
    return 1 if tally.failed else 0


def _toolbar(runtime: Runtime) -> str:
    status = runtime.snapshot()
    faults = f"{len(status.faults)} fault(s)" if status.faults else "no faults"
    model = status.model.name if status.model is not None else "no model"
    return f" {status.state} | {faults} | {model} | support {status.support_level:.2f} | 'status' for the next steps"


def run_interactive(
    session: ConsoleSession, history: Path | None = None, start: Callable[[], None] | None = None
) -> None:
    """Prompt until ``quit`` or end of input (Ctrl-D); a bad line is answered and the session goes on.

    ``start`` (the loop's start) is called once the prompt is built: building it imports and
    renders for tens of milliseconds, which would stall a loop already running. KeyboardInterrupt
    (Ctrl-C) propagates: the caller ends the session with torque off.
    """
    from prompt_toolkit import PromptSession
    from prompt_toolkit.completion import NestedCompleter
    from prompt_toolkit.history import FileHistory, InMemoryHistory
    from prompt_toolkit.patch_stdout import patch_stdout

    runtime = session.runtime
    remembered: FileHistory | InMemoryHistory = InMemoryHistory()
    if history is not None:
        try:
            history.parent.mkdir(parents=True, exist_ok=True)
            history.touch()
            remembered = FileHistory(str(history))
        except OSError as exc:  # no writable home: history for this session only
            session.say(f"note: typed lines are not remembered ({history}: {exc.strerror})")
    prompt: PromptSession[str] = PromptSession(
        history=remembered,
        completer=NestedCompleter.from_nested_dict(completion_words(session.context)),
        complete_while_typing=False,
        bottom_toolbar=lambda: _toolbar(runtime),
        refresh_interval=0.5,
    )
    if start is not None:
        start()
    stop = threading.Event()

    def announce() -> None:  # what happens while the operator types is printed above the prompt
        while not stop.wait(0.1):
            session.show_announcements()

    with patch_stdout(raw=True):
        session.say("daror console: type 'status' to see the robot and the next steps, 'help' for the commands")
        printer = threading.Thread(target=announce, name="daror-console-announcements", daemon=True)
        printer.start()
        try:
            while True:
                try:
                    line = prompt.prompt(f"[{runtime.state_name}] > ")
                except EOFError:
                    return
                try:
                    session.execute(line)
                except QuitRequested:
                    return
                except (CommandError, InputError, ScriptCheckError) as exc:
                    session.say(f"  error: {exc}")
                except DarorError as exc:
                    session.say(f"  failed: {exc}")
        finally:
            stop.set()
            printer.join()


def history_path() -> Path:
    """Where typed lines are remembered between sessions (``$XDG_STATE_HOME/daror/console_history``)."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "daror" / "console_history"


def stdin_is_terminal() -> bool:
    return sys.stdin.isatty()


def world_for(runtime: Runtime) -> SimWorld | None:
    """The simulated world around the runtime's (opened) HAL, its pilot seated; None on hardware."""
    world = runtime.world
    return SimWorld(world) if world is not None else None


def make_session(runtime: Runtime, out: object | None = None) -> ConsoleSession:
    from rich.console import Console

    console = out if isinstance(out, Console) else Console(highlight=False)
    return ConsoleSession(runtime, console, world_for(runtime))
