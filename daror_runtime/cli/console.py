"""``daror console``: an operator's console session, typed, scripted, piped or in a browser (docs/console.md).

:func:`run_console_session` is the session itself, shared with ``daror hil``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog
from rich.console import Console

from daror_runtime.cli.common import (
    CommandParser,
    Commands,
    UsageError,
    bind,
    hal_config_from_flags,
    hal_kinds,
    output_dir,
)
from daror_runtime.errors import DarorError
from daror_runtime.logs import configure_logging

log = structlog.get_logger(__name__)

#: Said after the web console's address when it asks no token (``--no-token``, loopback only).
_NO_TOKEN_NOTE = " (no token: any program on this computer can drive the robot)"


def register(commands: Commands) -> None:
    """``daror console`` on ``commands``; its flags declared when it is used (``--hal``'s choices import the HAL)."""
    con = commands.add_parser(
        "console",
        help="operator console session: typed at a terminal, a --script, or lines piped in (audit log in --out)",
    )
    con.declare_on_use(_declare_flags)
    bind(con, cmd_console)


def _declare_flags(con: CommandParser) -> None:
    """The flags of ``daror console``; ``--hal``'s choices are the registered backends."""
    con.add_argument("--hal", choices=hal_kinds(), help="backend (default sim)")
    con.add_argument("--scenario", help="simulated plant: a scenario name or .yaml (default exo_dummy_arm)")
    con.add_argument("--hal-config", type=Path, metavar="FILE", help="HAL configuration YAML (instead of --hal)")
    con.add_argument(
        "--script", type=Path, help="run these console lines, all checked first (lock-step unless --clock says)"
    )
    con.add_argument("--settings", type=Path, help="session settings YAML (default: the built-in settings)")
    con.add_argument("--spec", type=Path, help="FSM spec (default: fsm_spec.yaml of the repository)")
    con.add_argument("--out", type=Path, help="session directory (default sessions/DATE-TIME)")
    con.add_argument(
        "--db",
        metavar="URL",
        help="the lab's records, where the session is recorded when it ends: sqlite:///PATH or "
        "postgresql://USER@HOST/NAME, or none (default: $DAROR_DB, else daror.db beside the session directory)",
    )
    con.add_argument(
        "--operator",
        metavar="NAME",
        help="who runs the session, for the lab's records: initials or a staff code "
        "(default: $DAROR_OPERATOR, else the login name)",
    )
    con.add_argument("--realtime", action="store_true", help="the same as --clock realtime")
    con.add_argument(
        "--clock",
        choices=["paced", "realtime", "lockstep"],
        help="paced: simulated time follows the wall clock, a stall of the PC delays it (typed or --web on a "
        "simulated backend); realtime: the overrun watchdog faults a stall (hardware); lockstep: as fast as the CPU "
        "allows (scripts, pipes). docs/loop.md",
    )
    con.add_argument("--web", action="store_true", help="also serve the console in a browser (live; web extra)")
    con.add_argument("--port", type=int, default=8765, help="with --web: the port (default 8765)")
    con.add_argument(
        "--host", default="127.0.0.1", help="with --web: the address (default 127.0.0.1; the printed URL has the token)"
    )
    con.add_argument(
        "--no-token",
        action="store_true",
        help="with --web on the loopback only: ask no token (any program on this computer can then drive the robot)",
    )


def cmd_console(args: argparse.Namespace, console: Console) -> int:
    """An operator's console session in ``--out``: every input checked before anything is written.

    Returns the session's exit code (:func:`run_console_session`).

    Raises:
        UsageError: flags that contradict each other (``--no-token`` without ``--web``, ``--realtime``
            with another ``--clock``); a clock the backend cannot run.
    """
    from daror_runtime.clocks import session_clock
    from daror_runtime.console.commands import parse_context
    from daror_runtime.console.grammar import check_lines
    from daror_runtime.console.run import read_script, stdin_is_terminal
    from daror_runtime.fsm.spec import load_fsm_spec
    from daror_runtime.session.settings import load_session_settings
    from daror_runtime.util.outputs import output_lock
    from hal.interface import open_hal

    if args.web:  # without the web extra: one line saying how to install it, exit 2
        from daror_runtime.console.web import require_web_extra
        from daror_runtime.console.web.access import check_no_token

        require_web_extra()
        if args.no_token:  # a console without a token: the loopback only, refused before anything is written
            check_no_token(args.host)
    elif args.no_token:
        raise UsageError("--no-token goes with --web (the web console's token)")
    args.operator = session_operator(args)  # a name the records cannot keep: refused before anything is written
    spec = load_fsm_spec(args.spec)  # a bad spec: the runtime refuses to start, nothing is written
    settings = load_session_settings(args.settings)
    hal = open_hal(hal_config_from_flags(args))  # a backend not built or not installed: one line, exit 2
    checked = None
    if args.script is not None:  # the whole script is checked before anything runs or is written
        checked = check_lines(
            read_script(args.script),
            str(args.script),
            parse_context(spec, hal.description, hal.world.fault_kinds if hal.world is not None else None),
        )
    typed = checked is None and stdin_is_terminal()
    if args.realtime and args.clock not in (None, "realtime"):
        raise UsageError(f"--realtime is --clock realtime; it contradicts --clock {args.clock}: give one of them")
    # paced or lock-step on hardware, lock-step typed or on the web: refused here, before anything is written
    clock = session_clock(hal, "realtime" if args.realtime else args.clock, live=typed or args.web)
    if args.out is None:  # the default: a new folder under ./sessions (created)
        output_dir("sessions").mkdir(exist_ok=True)
    out = output_dir(args.out if args.out is not None else Path("sessions") / time.strftime("%Y%m%d-%H%M%S"))
    with output_lock(out):  # one session per folder
        return run_console_session(args, console, hal, out, spec, settings, checked, typed, clock)


def run_console_session(
    args: argparse.Namespace,
    console: Console,
    hal: Any,
    out: Path,
    spec: Any,
    settings: Any,
    checked: Any,
    typed: bool,
    clock: Any,
    after_script: Callable[[Any, Any], None] | None = None,
) -> int:
    """The session itself, in ``out`` (checked and locked by :func:`cmd_console`), on ``clock``.

    ``after_script(runtime, session)`` runs when a script has ended or failed, before the session
    ends (``daror hil``: a fault's reaction under way plays out).

    Returns the exit code: the mode's (0, 1, 2), or 128 + the signal's number when SIGINT (Ctrl-C,
    130), SIGTERM (143) or SIGHUP (129) ended it, in any mode and state: torque off first, the
    reason named in the audit log and ``session.json`` (D124).
    """
    from daror_runtime.console.run import (
        announcing,
        history_path,
        make_session,
        run_interactive,
        run_piped,
        run_script,
        run_session,
    )
    from daror_runtime.runtime import Runtime

    realtime = not clock.virtual
    runtime = Runtime(hal, out, spec=spec, settings=settings, clock=clock, operator=session_operator(args))
    out.mkdir(parents=True, exist_ok=True)
    configure_logging(
        args.log_level or "critical",  # the console announces what the operator must see
        [out / "audit.jsonl", *([args.log_json] if args.log_json is not None else [])],  # the session keeps its own
    )
    runtime.open()
    web = None

    def body() -> tuple[int, str]:
        nonlocal web
        from daror_runtime.records.store import database_url

        session = make_session(runtime, console, database_url(getattr(args, "db", None), out.resolve().parent))
        if getattr(args, "web", False):  # the browser and the terminal share the runtime and its log (not hil)
            from daror_runtime.console.web.serve import start_web

            web = start_web(
                runtime,
                session.world,
                args.host,
                args.port,
                require_token=not args.no_token,
                records_url=session.records_url,
            )
            session.announcements = web.hub.terminal_reader()
            console.print(f"web console: {web.address}" + ("" if web.token else _NO_TOKEN_NOTE), soft_wrap=True)
        background = realtime and not typed  # the loop on its own thread: announcements printed as they come
        if background:
            runtime.runner.start()
        with announcing(session, enabled=background):
            if checked is not None:
                try:
                    result = run_script(session, args.script, checked)
                except DarorError:
                    if after_script is not None:
                        after_script(runtime, session)
                    raise
                if after_script is not None:
                    after_script(runtime, session)
                console.print(f"script done: {result.lines_run} lines, state {result.state}")
                return 0, "quit" if result.quit else "the script ended"
            if typed:
                run_interactive(session, history_path(), start=runtime.runner.start)
                return 0, "quit"
            if web is None:
                return run_piped(session, sys.stdin), "quit or the end of the input"
            # the page is the console: until a signal, or until the server is lost (nothing would control the robot)
            reason = web.serve_until_interrupted()
            console.print(f"web console: {reason}", soft_wrap=True)
            return 0, reason

    def stop_web() -> None:
        if web is not None:
            web.stop()

    try:
        return run_session(runtime, console, body, stop_web)  # SIGINT, SIGTERM, SIGHUP: torque off, 128 + signal
    finally:  # the session has ended (torque off, session.json written): the lab's records learn of it
        record_the_session(console, getattr(args, "db", None), out)


def session_operator(args: argparse.Namespace) -> str | None:
    """Who runs the session: ``--operator``, else ``$DAROR_OPERATOR``, else the login name (None: unknown).

    Raises:
        UsageError: ``--operator`` or ``$DAROR_OPERATOR`` is not a name the records keep
            (:data:`~daror_runtime.records.codes.OPERATOR_PATTERN`).
    """
    import getpass
    import os
    import re

    from daror_runtime.records.codes import OPERATOR_PATTERN

    given = getattr(args, "operator", None)
    where = "--operator"
    if given is None and os.environ.get("DAROR_OPERATOR"):
        given, where = os.environ["DAROR_OPERATOR"], "$DAROR_OPERATOR"
    if given is None:
        try:
            login = getpass.getuser()
        except (KeyError, OSError):  # no user name in the environment nor the password database
            return None
        return login if re.match(OPERATOR_PATTERN, login) else None
    if not re.match(OPERATOR_PATTERN, given):
        raise UsageError(
            f"{where} {given!r}: expected initials or a staff code (letters, digits, spaces, _ . @ -; at most 64)"
        )
    return given


def record_the_session(console: Console, db: str | None, directory: Path) -> None:
    """Record the ended session in ``directory`` into the lab's records; a line says where, or why not.

    A database that cannot take it (unreachable, another schema) does not undo the session: the
    line names the command that records it later (``daror sessions add DIR``).
    """
    from daror_runtime.records.store import database_url

    url = database_url(db, directory.resolve().parent)
    if url is None:
        return
    from daror_runtime.errors import DataError
    from daror_runtime.records.index import record_session
    from daror_runtime.records.store import RecordsError, describe_url, open_store

    try:
        with open_store(url) as store:
            recorded = record_session(store, directory)
    except (RecordsError, DataError) as exc:
        log.error("session not recorded", db=describe_url(url), reason=str(exc))
        console.print(
            f"records: the session was not recorded: {exc}; record it later: daror sessions add {directory}",
            soft_wrap=True,
            markup=False,
            highlight=False,
        )
        return
    console.print(
        f"records: session {recorded.session_id} of pilot {recorded.pilot} in {describe_url(url)}",
        soft_wrap=True,
        markup=False,
        highlight=False,
    )
