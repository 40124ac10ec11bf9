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

``quit`` (or the end of the input), Ctrl-C, ``kill -TERM`` and a hang-up (the terminal closed,
SIGHUP) end the session the same way, in any state: torque off first, then a line confirming it
from the drives (``daror_runtime.runtime.Runtime.shutdown``), recorded in the audit log and
``session.json`` with the reason (:func:`stop_signals`). While the loop runs on its own thread
(real time), what the runtime announces is printed as it happens (:func:`announcing`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, TextIO

import structlog

from daror_runtime.console.commands import CommandError, ConsoleSession, QuitRequested, ScriptCheckError
from daror_runtime.console.grammar import Parsed, completion_words
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import DarorError, InputError, UsageError
from daror_runtime.runtime import Runtime
from hal.files import YAML_MAX_BYTES, read_text_bounded

if TYPE_CHECKING:
    from rich.console import Console

log = structlog.get_logger(__name__)


class ScriptError(UsageError):
    """A script that cannot be read (file named)."""


#: The signals that end a session like Ctrl-C, and the reason each is recorded with (``ended.reason``).
STOP_SIGNALS: dict[int, str] = {
    signal.SIGINT: "interrupted by the operator (Ctrl-C)",
    signal.SIGTERM: "terminated (SIGTERM)",
    signal.SIGHUP: "hang-up (SIGHUP)",
}
#: Seconds between two looks for announcements while the loop runs on its own thread.
ANNOUNCE_PERIOD_S = 0.1
#: Seconds the end of a session waits for the announcement printer to stop.
PRINTER_JOIN_S = 1.0


class SessionSignal(KeyboardInterrupt):
    """A stop signal (SIGINT, SIGTERM, SIGHUP), raised in the main thread: the session ends like Ctrl-C.

    A ``KeyboardInterrupt`` so that whatever lets Ctrl-C through (prompt_toolkit's event loop,
    asyncio) lets it through too; never an ``Exception`` that a library might swallow.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(STOP_SIGNALS[signum])
        self.signum = signum

    @property
    def reason(self) -> str:
        """Why the session ended, as recorded (e.g. ``terminated (SIGTERM)``)."""
        return STOP_SIGNALS[self.signum]

    @property
    def exit_code(self) -> int:
        """The shell's convention for a process ended by a signal: 128 + its number (130, 143, 129)."""
        return 128 + self.signum


@dataclass
class StopSignals:
    """The stop signals of one session (see :func:`stop_signals`): which came, and whether the session ends.

    ``received``: the signal numbers in the order they came (the first one is the session's reason).
    """

    received: list[int] = field(default_factory=list)
    ending: bool = False

    def handle(self, signum: int, frame: FrameType | None) -> None:
        """The Python-level handler (main thread, between two bytecodes): raise once, then only note.

        It raises and nothing else: no lock, no log, no I/O (the interrupted code may hold the very
        lock a log call needs). The shutdown itself runs in the caller's ``finally``, in the main
        thread's own frame, never here.
        """
        self.received.append(signum)
        if not self.ending:
            self.ending = True  # a second signal must not interrupt the torque off under way
            raise SessionSignal(signum)

    def hold(self) -> None:
        """The session is ending (torque off under way): later signals are noted, never raised."""
        self.ending = True

    def stop(self, interrupt: KeyboardInterrupt | None = None) -> SessionSignal | None:
        """The signal the session ends with: the first received, or ``interrupt`` (Ctrl-C typed at the
        prompt arrives as a key, a plain ``KeyboardInterrupt``: SIGINT), or None (no signal)."""
        if self.received:
            return SessionSignal(self.received[0])
        if isinstance(interrupt, SessionSignal):
            return interrupt
        return SessionSignal(signal.SIGINT) if interrupt is not None else None


@contextlib.contextmanager
def stop_signals() -> Iterator[StopSignals]:
    """Within: SIGINT, SIGTERM and SIGHUP raise :class:`SessionSignal` in the main thread (the first one).

    The caller ends the session in its ``finally`` after :meth:`StopSignals.hold`, exactly as for
    Ctrl-C; the previous handlers are restored on the way out. Python runs signal handlers in the
    main thread only, whichever thread runs the loop; call this there.
    """
    signals = StopSignals()
    previous = {signum: signal.signal(signum, signals.handle) for signum in STOP_SIGNALS}
    try:
        yield signals
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def run_session(
    runtime: Runtime,
    out: Console,
    body: Callable[[], tuple[int, str]],
    stopping: Callable[[], None] | None = None,
) -> int:
    """Run a session's ``body`` (returns its exit code and why it ended), then end it: torque off first.

    The one way every console session ends (``daror console`` in every mode, ``daror hil``):
    whatever ends ``body`` (its end, an error, Ctrl-C, SIGTERM, SIGHUP), :meth:`Runtime.shutdown`
    takes the torque off and confirms it from the drives, ``stopping`` runs (the web server stops),
    a line says so, and :meth:`Runtime.close` writes ``session.json``. A stop signal during ``body``
    ends it like Ctrl-C (:func:`stop_signals`), also while a fault's reaction holds the arm (a
    signal is no operator's considered choice, D122): the reason names it (``terminated
    (SIGTERM)``) and the exit code is 128 + its number. Signals during the ending are noted, never
    raised. Call it in the main thread (the runtime opened).

    Raises:
        whatever ``body`` raised other than KeyboardInterrupt, after the session ended.
    """
    code, reason = 0, "the session ended with an error"
    interrupt: KeyboardInterrupt | None = None
    with stop_signals() as signals:
        try:
            code, reason = body()
        except KeyboardInterrupt as exc:  # Ctrl-C typed at the prompt (a key), or a stop signal
            interrupt = exc
        finally:
            signals.hold()  # from here on a signal is noted, never raised: nothing interrupts the torque off
            stop = signals.stop(interrupt)
            if stop is not None:  # also a signal that came as the body ended by itself (a hang-up's EOF)
                reason, code = stop.reason, stop.exit_code
            ended = runtime.shutdown(reason)  # torque off first, whatever happened
            try:
                if stopping is not None:
                    stopping()
            finally:
                _tell(out, ended.sentence())
                runtime.close()
                _tell(out, f"session {runtime.session_id}: {runtime.session_dir / 'session.json'}")
                if len(signals.received) > 1:
                    log.warning("signals while the session ended, ignored", signals=signals.received[1:])
    return code


def _tell(out: Console, text: str) -> None:
    """One line at the end of a session; a terminal that is gone (a hang-up) does not stop the ending."""
    try:
        out.print(text, soft_wrap=True)
    except OSError:  # the audit log and session.json have it
        return


@contextlib.contextmanager
def announcing(session: ConsoleSession, enabled: bool = True) -> Iterator[None]:
    """Within: what the runtime announces (transitions, faults, reactions) is printed as it happens.

    A thread drains the session's announcements every :data:`ANNOUNCE_PERIOD_S` seconds: for a
    loop on its own thread (real time: the web console, a ``--realtime`` script or pipe, the
    prompt), where nothing else would print them until the next line is run. ``enabled`` False:
    nothing (lock-step: the lines' own runs print them).
    """
    if not enabled:
        yield
        return
    stop = threading.Event()

    def announce() -> None:
        while not stop.wait(ANNOUNCE_PERIOD_S):
            try:
                session.show_announcements()
            except OSError:  # the terminal is gone (a hang-up): the audit log still has everything
                return

    printer = threading.Thread(target=announce, name="daror-console-announcements", daemon=True)
    printer.start()
    try:
        yield
    finally:
        stop.set()
        # bounded: a printer blocked on a stopped terminal (Ctrl-S) or a full pipe must not hold up
        # the torque off that follows; it is a daemon thread
        printer.join(timeout=PRINTER_JOIN_S)


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
    (Ctrl-C, or a stop signal: :class:`SessionSignal`) propagates: the caller ends the session with
    torque off.
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
    with patch_stdout(raw=True):
        session.say("daror console: type 'status' to see the robot and the next steps, 'help' for the commands")
        with announcing(session):  # what happens while the operator types is printed above the prompt
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


def make_session(runtime: Runtime, out: object | None = None, records_url: str | None = None) -> ConsoleSession:
    """A console on ``runtime``; ``records_url``: the lab's records it reads a returning pilot's from (None: none)."""
    from rich.console import Console

    console = out if isinstance(out, Console) else Console(highlight=False)
    return ConsoleSession(runtime, console, world_for(runtime), records_url=records_url)
