"""What every ``daror`` command shares: its parser class, the top-level flags, handler binding, exit codes.

A command module (``daror_runtime/cli/<group>.py``) has a ``register(commands)`` that adds its
subcommand's parser to ``commands``, declares its flags beside its handler, and binds the handler
with :func:`bind`; :func:`run_command` runs the bound handler and maps its errors to exit codes:
0 success, 1 failure, 2 bad input (one line on stderr, no traceback), 130 Ctrl-C.

Importing this module imports no model, HAL or numpy code: every command imports what it needs
when it runs (``daror --help`` stays fast, docs/performance.md).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

import structlog
from rich.console import Console

from daror_runtime.errors import DarorError, InputError, UsageError

if TYPE_CHECKING:
    from hal.config import AnyHalConfig

__all__ = [
    "CommandParser",
    "Commands",
    "Handler",
    "UsageError",
    "add_common_flags",
    "at_least",
    "bind",
    "hal_config_from_flags",
    "hal_kinds",
    "non_negative_int",
    "output_dir",
    "output_file",
    "positive_int",
    "progress",
    "run_command",
    "write_json",
]

log = structlog.get_logger(__name__)

#: A command's handler: the parsed flags and the console to print on; returns the exit code.
Handler: TypeAlias = Callable[[argparse.Namespace, Console], int]


class CommandParser(argparse.ArgumentParser):
    """The ``daror`` parser, and every subcommand's (argparse makes a subparser of its parent's class).

    Flags whose help or choices come from a registry that is costly to import (the HAL backends'
    registry imports numpy, ~0.1 s) are declared with :meth:`declare_on_use`: they are added when
    this parser first parses or formats its help or usage, so ``daror --help`` and the other
    commands never import that registry.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._on_use: list[Callable[[CommandParser], None]] = []

    def declare_on_use(self, declare: Callable[[CommandParser], None]) -> None:
        """Call ``declare(self)`` (which adds flags) before this parser is first used; calls keep their order."""
        self._on_use.append(declare)

    def declare_now(self) -> None:
        """Add every flag declared for first use now (once)."""
        while self._on_use:
            self._on_use.pop(0)(self)

    def parse_known_args(  # type: ignore[override]  # the same signature as argparse's, without its overloads
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        """Declare the pending flags, then parse as argparse does."""
        self.declare_now()
        return super().parse_known_args(args, namespace)

    def format_usage(self) -> str:
        """Declare the pending flags, then the usage line as argparse makes it."""
        self.declare_now()
        return super().format_usage()

    def format_help(self) -> str:
        """Declare the pending flags, then the help as argparse makes it."""
        self.declare_now()
        return super().format_help()


#: The ``daror`` parser's subcommands (what ``add_subparsers`` returns), where a command module registers.
Commands: TypeAlias = "argparse._SubParsersAction[CommandParser]"


def add_common_flags(parser: argparse.ArgumentParser) -> None:
    """The flags of ``daror`` itself, before the command: ``--log-level`` and ``--log-json``."""
    parser.add_argument(
        "--log-level",
        default=None,
        choices=["debug", "info", "warning", "error"],
        help="least severe event shown on stderr (default warning; the console shows its own announcements)",
    )
    parser.add_argument("--log-json", type=Path, help="also append every event from info up as JSON lines to this file")


def bind(parser: argparse.ArgumentParser, handler: Handler, **defaults: Any) -> None:
    """Make ``handler`` the command of ``parser`` (with further ``defaults`` of the namespace).

    The command's name in messages (``daror fsm check: error: ...``) is the parser's ``prog``
    without the program's name.
    """
    parser.set_defaults(handler=handler, command_name=parser.prog.partition(" ")[2], **defaults)


#: ``--trust-signal-map``'s help: a command that reads data accepts a file whose columns fail the physics check.
TRUST_SIGNAL_MAP_HELP = (
    "accept data whose columns fail the physics check of their names (daror data check, docs/data.md); "
    "what the command writes then says so"
)


def run_command(args: argparse.Namespace, console: Console) -> int:
    """Run the handler bound to the parsed command; its errors as exit codes.

    Returns the handler's exit code; 2 on bad input (:class:`InputError`: one line on stderr naming
    the command), 1 on another :class:`DarorError` (one line), 130 on Ctrl-C. Other exceptions
    are bugs and propagate.
    """
    command: str = args.command_name
    handler: Handler = args.handler
    try:
        return handler(args, console)
    except InputError as exc:
        log.info("refused", command=command, reason=str(exc))
        sys.stderr.write(f"daror {command}: error: {exc}\n")
        return 2
    except DarorError as exc:
        # the user's line first: the log is written by its own thread, which may come before or after
        sys.stderr.write(f"daror {command}: failed: {exc}\n")
        sys.stderr.flush()
        log.error("failed", command=command, reason=str(exc))
        return 1
    except KeyboardInterrupt:
        sys.stderr.write(f"daror {command}: interrupted\n")
        return 130


def make_console() -> Console:
    """The console every command prints on: no highlighting, 120 columns, no soft wrapping."""
    return Console(highlight=False, width=120, soft_wrap=False)


# --- flag types -------------------------------------------------------------------------------


def at_least(minimum: int) -> Callable[[str], int]:
    """A flag type: a whole number of at least ``minimum`` (argparse's one-line error otherwise)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{value} must be at least {minimum}")
        return value

    return parse


positive_int = at_least(1)
non_negative_int = at_least(0)


# --- the HAL from flags -----------------------------------------------------------------------


def hal_kinds() -> tuple[str, ...]:
    """The registered HAL backends' names, ``--hal``'s choices (:func:`hal.interface.backend_kinds`).

    Imports the HAL's registry (and numpy): call it in a declaration made with
    :meth:`CommandParser.declare_on_use`.
    """
    from hal.interface import backend_kinds

    return backend_kinds()


def hal_config_from_flags(args: argparse.Namespace) -> AnyHalConfig:
    """The HAL configuration of ``--hal-config FILE``, or of the ``--hal``/``--scenario`` flags (default sim).

    Raises:
        UsageError: ``--hal-config`` together with ``--hal`` or ``--scenario``; ``--scenario`` for ``--hal can``.
        HalConfigError: the file or the flags do not make a configuration (one line).
    """
    from hal.config import hal_config, load_hal_config

    if args.hal_config is not None:
        given = [flag for flag, value in (("--hal", args.hal), ("--scenario", args.scenario)) if value is not None]
        if given:
            raise UsageError(f"--hal-config names the backend and its scenario; leave out {' and '.join(given)}")
        return load_hal_config(args.hal_config)
    backend = args.hal or "sim"
    if args.scenario is not None and backend == "can":
        raise UsageError("--scenario names a simulated plant: it goes with --hal sim or can-sim, not --hal can")
    return hal_config(backend, source=f"--hal {backend}", scenario=args.scenario)


# --- output -----------------------------------------------------------------------------------


def write_json(path: Path | str, document: dict[str, Any]) -> None:
    """``document`` as indented JSON, written atomically (no NaN: a figure that is not a number is a bug)."""
    from daror_runtime.util.atomic import write_text_atomic

    write_text_atomic(path, json.dumps(document, indent=2, allow_nan=False) + "\n")


def output_file(out: Path | str, *inputs: Path | str | None) -> Path:
    """Check an output file before any work (nothing is created); see :mod:`daror_runtime.util.outputs`.

    Raises:
        OutputPathError: the file cannot be written there, or it is one of ``inputs``.
    """
    from daror_runtime.util.outputs import check_output_file

    return check_output_file(out, *inputs)


def output_dir(out: Path | str, *inputs: Path | str | None) -> Path:
    """Check an output folder before any work (nothing is created); see :mod:`daror_runtime.util.outputs`.

    Raises:
        OutputPathError: the folder cannot be made or written there.
    """
    from daror_runtime.util.outputs import check_output_dir

    return check_output_dir(out, *inputs)


def progress(console: Console, label: str, counter: str, elapsed: bool = False) -> Any:
    """A transient rich progress bar: ``label``, the bar, ``counter`` (a task format), time elapsed
    (with ``elapsed``), time left."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    shown = (TimeElapsedColumn(),) if elapsed else ()
    return Progress(
        TextColumn(label),
        BarColumn(),
        TextColumn(counter),
        *shown,
        TimeRemainingColumn(),
        console=console,
        transient=True,
    )
