"""``daror pilots``, ``daror sessions``, ``daror db``: the lab's records (issue 28, docs/records.md)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console
from rich.table import Table

from daror_runtime.cli.common import Commands, bind

if TYPE_CHECKING:
    from daror_runtime.records.store import Store

ARM_SIDES = ("right", "left")


def _db_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--db",
        metavar="URL",
        help="the records' database: sqlite:///PATH or postgresql://USER@HOST/NAME "
        "(default: $DAROR_DB, else daror.db in the current folder)",
    )


def register(commands: Commands) -> None:
    """``daror pilots``, ``daror sessions`` and ``daror db`` on ``commands``."""
    pilots = commands.add_parser("pilots", help="the lab's pilots: add one, list them, show one's record")
    pilot_cmds = pilots.add_subparsers(dest="pilots_command", required=True, metavar="WHAT")
    add = pilot_cmds.add_parser("add", help="add a pilot under a code (never a name)")
    add.add_argument("code", help="the pilot's code, e.g. P-007: letters, digits, '_', '.', '-' (at most 32)")
    add.add_argument("--arm", choices=ARM_SIDES, default="right", help="the arm the robot supports (default right)")
    add.add_argument("--birth-year", type=int, metavar="YEAR", help="the pilot's birth year (not his date of birth)")
    add.add_argument("--notes", default="", help="the lab's notes (free text; no names)")
    _db_flag(add)
    bind(add, cmd_pilots_add)
    listing = pilot_cmds.add_parser("list", help="every pilot: sessions, the last one, the model in use")
    _db_flag(listing)
    bind(listing, cmd_pilots_list)
    report = pilot_cmds.add_parser(
        "report",
        help="one pilot's trend over his sessions: range of motion, the model's arm moments and elbow stiffness, "
        "validation RMSE and support (report.md, report.png, report.json)",
    )
    report.add_argument("code", help="the pilot's code")
    report.add_argument("--out", type=Path, required=True, metavar="DIR", help="the folder the report is written to")
    _db_flag(report)
    bind(report, cmd_pilots_report)
    export = pilot_cmds.add_parser(
        "export", help="one pilot's records and every file they index, to a new folder (CSV + files, for an archive)"
    )
    export.add_argument("code", help="the pilot's code")
    export.add_argument("--out", type=Path, required=True, metavar="DIR", help="a new folder")
    _db_flag(export)
    bind(export, cmd_pilots_export)
    show = pilot_cmds.add_parser("show", help="one pilot's record: his sessions, ranges of motion and models")
    show.add_argument("code", help="the pilot's code")
    _db_flag(show)
    bind(show, cmd_pilots_show)

    sessions = commands.add_parser("sessions", help="the lab's sessions: list them, record a session folder")
    session_cmds = sessions.add_subparsers(dest="sessions_command", required=True, metavar="WHAT")
    slist = session_cmds.add_parser("list", help="every session, newest last")
    slist.add_argument("--pilot", metavar="CODE", help="only this pilot's sessions")
    _db_flag(slist)
    bind(slist, cmd_sessions_list)
    sadd = session_cmds.add_parser(
        "add", help="record a session folder (a console session records itself when it ends)"
    )
    sadd.add_argument("directory", type=Path, help="the session's folder (with session.json)")
    sadd.add_argument("--pilot", metavar="CODE", help="the pilot, when the session named none")
    _db_flag(sadd)
    bind(sadd, cmd_sessions_add)

    recover = session_cmds.add_parser(
        "recover",
        help="a session whose process died: its recordings into raw logs and datasets, session.json marked "
        "ended by a crash, the records told",
    )
    recover.add_argument("directory", type=Path, help="the session's folder")
    recover.add_argument("--pilot", metavar="CODE", help="the pilot, when the session named none")
    _db_flag(recover)
    bind(recover, cmd_sessions_recover)

    db = commands.add_parser("db", help="the records' database: bring its schema up to date")
    db_cmds = db.add_subparsers(dest="db_command", required=True, metavar="WHAT")
    upgrade = db_cmds.add_parser("upgrade", help="run the migrations up to this runtime's schema")
    _db_flag(upgrade)
    bind(upgrade, cmd_db_upgrade)


def _url(args: argparse.Namespace) -> str:
    from daror_runtime.records.store import RecordsError, database_url

    url = database_url(args.db, Path.cwd())
    if url is None:
        raise RecordsError("--db none: no database to read or write; expected a database URL")
    return url


def _open(args: argparse.Namespace, create: bool = False) -> Store:
    """The records; ``create``: a new SQLite file may be made (a command that writes), else it must exist."""
    from daror_runtime.records.store import open_store

    return open_store(_url(args), create)


def cmd_db_upgrade(args: argparse.Namespace, console: Console) -> int:
    """Bring the database to this runtime's schema; print the revisions before and after."""
    from daror_runtime.records.store import describe_url, upgrade

    url = _url(args)
    before, after = upgrade(url)
    console.print(
        f"{describe_url(url)}: schema {before or 'empty'} -> {after}", markup=False, highlight=False, soft_wrap=True
    )
    return 0


def cmd_pilots_add(args: argparse.Namespace, console: Console) -> int:
    """Add a pilot.

    Raises:
        RecordsError: a code that is not one, a code already recorded, a birth year out of range.
    """
    from daror_runtime.records.pilots import add_pilot

    with _open(args, create=True) as store:
        pilot = add_pilot(store, args.code, args.arm, args.birth_year, args.notes)
    console.print(f"pilot {pilot.code} added ({pilot.arm_side} arm) to {store.url_shown}", markup=False, soft_wrap=True)
    return 0


def cmd_pilots_list(args: argparse.Namespace, console: Console) -> int:
    """Every pilot with his number of sessions, the last one and the model it ended with."""
    from daror_runtime.records.pilots import pilot_summaries

    with _open(args) as store:
        rows = pilot_summaries(store)
    table = Table("pilot", "arm", "born", "sessions", "last session (UTC)", "model in use", box=None)
    for row in rows:
        table.add_row(
            row.code + (" (simulated)" if row.simulated else ""),
            row.arm_side,
            "-" if row.birth_year is None else str(row.birth_year),
            str(row.sessions),
            "-" if row.last_session_utc is None else row.last_session_utc.isoformat(timespec="minutes"),
            row.model or "-",
        )
    console.print(table)
    console.print(f"{len(rows)} pilot(s) in {store.url_shown}", markup=False, highlight=False, soft_wrap=True)
    return 0


def cmd_pilots_show(args: argparse.Namespace, console: Console) -> int:
    """One pilot's record.

    Raises:
        RecordsError: no pilot under that code.
    """
    from daror_runtime.records.pilots import pilot_record_lines

    with _open(args) as store:
        lines = pilot_record_lines(store, args.code)
    for line in lines:
        console.print(line, markup=False, highlight=False, soft_wrap=True)
    return 0


def cmd_sessions_list(args: argparse.Namespace, console: Console) -> int:
    """Every session (of one pilot with ``--pilot``), oldest first."""
    from daror_runtime.records.pilots import session_rows

    with _open(args) as store:
        rows = session_rows(store, args.pilot)
    from rich.table import Column

    # the session and its date are what a reader looks up: never cut, the longer texts wrap instead
    table = Table(
        Column("session", no_wrap=True), Column("pilot", no_wrap=True), Column("started (UTC)", no_wrap=True),
        "operator", "robot",
        "backend", "reached", "ended", "faults", box=None,
    )  # fmt: skip
    for row in rows:
        table.add_row(*row)
    console.print(table)
    console.print(f"{len(rows)} session(s)", markup=False, highlight=False, soft_wrap=True)
    return 0


def cmd_sessions_add(args: argparse.Namespace, console: Console) -> int:
    """Record a session folder.

    Raises:
        RecordsError: no session.json there, no pilot named, or a pilot code that is not one.
    """
    from daror_runtime.records.index import record_session

    with _open(args, create=True) as store:
        recorded = record_session(store, args.directory, args.pilot)
    verb = "recorded" if recorded.new else "updated"
    console.print(
        f"session {recorded.session_id} {verb} for pilot {recorded.pilot}: {recorded.datasets} data file(s), "
        f"{recorded.models} model(s), range of motion {'yes' if recorded.range_of_motion else 'no'}",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    return 0


def cmd_sessions_recover(args: argparse.Namespace, console: Console) -> int:
    """Recover a crashed session's folder, then record it (unless ``--db none``).

    Raises:
        RecordsError: no session.json there; the records cannot take it (what was recovered stays).
        DataError: a recording too damaged to read.
    """
    from daror_runtime.records.index import record_session
    from daror_runtime.records.recover import recover_session
    from daror_runtime.records.store import database_url, open_store

    recovered = recover_session(args.directory)
    for line in recovered.lines:
        console.print(line, markup=False, highlight=False, soft_wrap=True)
    url = database_url(args.db, Path.cwd())
    if url is None:
        return 0
    with open_store(url) as store:
        recorded = record_session(store, args.directory, args.pilot)
    console.print(
        f"records: session {recorded.session_id} of pilot {recorded.pilot} in {store.url_shown}"
        + (" (ended by a crash)" if not recovered.already_ended else ""),
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    return 0


def cmd_pilots_report(args: argparse.Namespace, console: Console) -> int:
    """Write the pilot's trend report.

    Raises:
        RecordsError: no such pilot, or no session of his; OutputPathError: ``--out`` cannot be written.
    """
    from daror_runtime.cli.common import output_dir
    from daror_runtime.records.report import write_report

    out = output_dir(args.out)
    with _open(args) as store:
        trend = write_report(store, args.code, out)
    console.print(
        f"pilot {args.code}: {len(trend)} session(s); report: {out / 'report.md'} (report.png, report.json)",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    return 0


def cmd_pilots_export(args: argparse.Namespace, console: Console) -> int:
    """Export the pilot's records and files; exit 1 when a file was missing or changed (problems.txt).

    Raises:
        RecordsError: no such pilot, or ``--out`` exists.
    """
    from daror_runtime.cli.common import output_dir
    from daror_runtime.records.report import export_pilot

    out = output_dir(args.out)
    with _open(args) as store:
        exported = export_pilot(store, args.code, out)
    console.print(
        f"pilot {args.code}: {exported.files} file(s) exported to {out} (MANIFEST.sha256)", markup=False, soft_wrap=True
    )
    if exported.problems:
        console.print(
            f"{len(exported.problems)} file(s) missing or changed since they were recorded: {out / 'problems.txt'}",
            markup=False,
            soft_wrap=True,
        )
        return 1
    return 0
