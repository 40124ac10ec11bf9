"""The records' database: where it is, opening it (owner-only for SQLite), its migrations, and the store's verbs.

``database_url``: ``--db URL``, else ``DAROR_DB``, else ``sqlite:///<folder>/daror.db`` beside the
sessions. ``DAROR_DB=none`` (or ``--db none``) records nothing: a rehearsal a lab does not keep.
A database the migrations have not brought to this version is refused with one line naming
``daror db upgrade``; a new SQLite file is created and brought up to date at once.

Raises :class:`RecordsError` (an :class:`~daror_runtime.errors.InputError`: exit 2, one line) for
every problem a user can fix: a URL that names no database we know, a server that cannot be
reached, a schema older or newer than this runtime's.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import structlog

from daror_runtime.errors import InputError

if TYPE_CHECKING:
    from sqlalchemy.engine import Connection, Engine
    from sqlalchemy.orm import Session

log = structlog.get_logger(__name__)

#: The environment variable that names the database (a SQLAlchemy URL, or ``none``).
DB_ENV = "DAROR_DB"
#: The SQLite file's name in the sessions' folder.
DEFAULT_DB_NAME = "daror.db"
#: The newest migration (``migrations/versions``): a database at another revision is not opened.
#: ``tests/daror_runtime/records/test_migrations.py`` checks that it is Alembic's head.
HEAD_REVISION = "0003"
#: How long a writer waits for another's lock on a SQLite file (two consoles on one database), s.
SQLITE_BUSY_TIMEOUT_S = 30.0
_MIGRATIONS = Path(__file__).with_name("migrations")


class RecordsError(InputError):
    """The records' database cannot be used (URL, server, schema version, a record that is not there)."""


class NoRecordsError(RecordsError):
    """A command that only reads was pointed at a SQLite file that does not exist (no records yet)."""


def database_url(explicit: str | None, folder: Path | str | None) -> str | None:
    """The database to record into: ``explicit``, else ``$DAROR_DB``, else ``daror.db`` in ``folder``.

    Returns None when the choice is ``none`` (record nothing) or there is no folder to put a default in.
    """
    chosen = explicit if explicit is not None else os.environ.get(DB_ENV)
    if chosen is not None:
        chosen = chosen.strip()
        if chosen.lower() == "none":
            return None
        # a plain path is a SQLite file (what a lab types most): --db sessions/daror.db
        return chosen if "://" in chosen else f"sqlite:///{Path(chosen).expanduser().resolve()}"
    if folder is None:
        return None
    return f"sqlite:///{Path(folder).resolve() / DEFAULT_DB_NAME}"


def describe_url(url: str) -> str:
    """``url`` without its password, for messages and the audit log."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        return make_url(url).render_as_string(hide_password=True)
    except ArgumentError:  # not a URL: whatever stood before an @ may be a password
        return url.split("@")[-1]


def _engine(url: str, create: bool = True) -> Engine:
    from sqlalchemy import create_engine, event
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError, NoSuchModuleError

    try:
        parsed = make_url(url)
    except ArgumentError:
        raise RecordsError(
            f"--db {url!r}: not a database URL; expected sqlite:///PATH or postgresql+psycopg://USER@HOST/NAME"
        ) from None
    backend = parsed.get_backend_name()
    if backend not in ("sqlite", "postgresql"):
        raise RecordsError(f"--db {describe_url(url)}: a {backend} database; expected sqlite or postgresql")
    if backend == "sqlite":
        database = parsed.database
        if not database or database == ":memory:":
            raise RecordsError(f"--db {url}: a SQLite database in memory keeps nothing; expected sqlite:///PATH")
        path = Path(database)
        if not path.parent.is_dir():
            raise RecordsError(f"--db {url}: folder {path.parent} does not exist")
        if not path.exists() and not create:
            raise NoRecordsError(
                f"{path}: no records there; expected --db URL or DAROR_DB (a console session records into "
                "daror.db beside its session folder)"
            )
        if not path.exists():
            # created for its owner only before SQLite opens it: a pilot's record is health data
            os.close(os.open(path, os.O_CREAT | os.O_WRONLY, 0o600))
        engine = create_engine(parsed, connect_args={"timeout": SQLITE_BUSY_TIMEOUT_S})

        @event.listens_for(engine, "connect")
        def _pragmas(dbapi_connection: Any, _record: object) -> None:
            dbapi_connection.isolation_level = None  # SQLAlchemy's BEGIN below, not the driver's own
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA foreign_keys = ON")
            cursor.execute("PRAGMA journal_mode = WAL")  # readers do not wait for a writer
            cursor.close()

        @event.listens_for(engine, "begin")
        def _begin(connection: Connection) -> None:
            # the write lock at the start: two consoles' transactions queue (busy timeout) instead of
            # both reading "no such pilot" and the second failing on his code (a lost record)
            connection.exec_driver_sql("BEGIN IMMEDIATE")

        return engine
    if parsed.drivername == "postgresql":
        parsed = parsed.set(drivername="postgresql+psycopg")  # the driver the extra installs
    try:
        return create_engine(parsed, pool_pre_ping=True)
    except NoSuchModuleError:
        raise RecordsError(
            f"--db {describe_url(url)}: no PostgreSQL driver installed; install the extra: pip install 'daror-runtime[postgres]'"
        ) from None
    except ModuleNotFoundError as exc:
        raise RecordsError(
            f"--db {describe_url(url)}: {exc.name} is not installed; install the extra: pip install 'daror-runtime[postgres]'"
        ) from None


def _revision(connection: Connection) -> str | None:
    from sqlalchemy import inspect, text

    if not inspect(connection).has_table("alembic_version"):
        return None
    return connection.execute(text("SELECT version_num FROM alembic_version")).scalar_one_or_none()


def _alembic_config(connection: Connection):  # type: ignore[no-untyped-def]  # alembic's Config
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(_MIGRATIONS))
    config.attributes["connection"] = connection
    return config


def _connect(engine: Engine, url: str) -> Connection:
    from sqlalchemy.exc import OperationalError

    try:
        return engine.connect()
    except OperationalError as exc:
        reason = str(exc.orig).strip().splitlines()[0] if exc.orig is not None else str(exc)
        raise RecordsError(f"--db {describe_url(url)}: cannot connect: {reason}") from None


def upgrade(url: str) -> tuple[str | None, str]:
    """Bring the database at ``url`` to :data:`HEAD_REVISION` (``daror db upgrade``); (before, after).

    Raises:
        RecordsError: the URL or the server (see :func:`_engine`), or a database newer than this runtime.
    """
    from alembic import command

    engine = _engine(url)
    try:
        with _connect(engine, url) as connection:
            before = _revision(connection)
            if before is not None and not _known(before):
                raise RecordsError(
                    f"{describe_url(url)}: schema revision {before} is newer than this runtime's ({HEAD_REVISION}); "
                    "expected a runtime at least as new as the database"
                )
            command.upgrade(_alembic_config(connection), "head")
            connection.commit()
            after = _revision(connection)
    finally:
        engine.dispose()
    log.info("records database upgraded", db=describe_url(url), before=before, after=after)
    return before, after or HEAD_REVISION


T = TypeVar("T")
#: How many times a write that conflicted with another writer's is tried.
WRITE_ATTEMPTS = 5


def _reason(exc: Exception) -> str:
    orig = getattr(exc, "orig", None)
    return (str(orig) if orig is not None else str(exc)).strip().splitlines()[0]


def _conflict(exc: Exception) -> bool:
    """True for what another writer's commit causes: a unique key taken meanwhile, a serialization failure."""
    from sqlalchemy.exc import IntegrityError

    code = getattr(getattr(exc, "orig", None), "sqlstate", None)
    return isinstance(exc, IntegrityError) or code in ("40001", "40P01")


def _known(revision: str) -> bool:
    return any(p.name.startswith(f"{revision}_") for p in (_MIGRATIONS / "versions").glob("*.py"))


@dataclass
class Store:
    """An open records database; :meth:`session` gives an ORM session in a transaction."""

    url: str
    engine: Engine

    @property
    def url_shown(self) -> str:
        """The URL without its password (messages, the audit log)."""
        return describe_url(self.url)

    @contextmanager
    def session(self) -> Iterator[Session]:
        """An ORM session; committed when the block ends without an exception, else rolled back."""
        from sqlalchemy.orm import Session

        with Session(self.engine, expire_on_commit=False) as orm, orm.begin():
            yield orm

    def write(self, work: Callable[[Session], T]) -> T:
        """``work`` in one transaction, run again if another writer's commit conflicted with it.

        PostgreSQL lets two transactions read that a pilot is new and refuses the second's insert of
        his code at commit (or a serialization failure): the whole transaction runs again and finds
        him (at most :data:`WRITE_ATTEMPTS` times). SQLite takes the write lock at the start instead.

        Raises:
            RecordsError: still conflicting after the attempts (the reason named).
        """
        from sqlalchemy.exc import IntegrityError, OperationalError

        for attempt in range(1, WRITE_ATTEMPTS + 1):
            try:
                with self.session() as orm:
                    return work(orm)
            except (IntegrityError, OperationalError) as exc:
                if attempt == WRITE_ATTEMPTS or not _conflict(exc):
                    raise RecordsError(f"{self.url_shown}: {_reason(exc)}") from None
                log.info("records write conflicted, again", db=self.url_shown, attempt=attempt, reason=_reason(exc))
        raise AssertionError("unreachable")  # pragma: no cover

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_store(url: str, create: bool = True) -> Store:
    """Open the records at ``url``; a new or empty database is created at :data:`HEAD_REVISION`.

    ``create`` False (a command that only reads): a SQLite file that does not exist is refused,
    not created empty.

    Raises:
        RecordsError: the URL or server, or a database at another revision (``daror db upgrade``
            brings an older one up to date; a newer one needs a newer runtime).
    """
    engine = _engine(url, create)
    try:
        with _connect(engine, url) as connection:
            revision = _revision(connection)
    except BaseException:
        engine.dispose()
        raise
    if revision is None:
        from sqlalchemy import inspect

        with _connect(engine, url) as connection:
            tables = inspect(connection).get_table_names()
        if tables:
            engine.dispose()
            raise RecordsError(
                f"{describe_url(url)}: a database with tables ({', '.join(sorted(tables)[:3])}, ...) but no records "
                "schema; expected an empty database or one daror created"
            )
        engine.dispose()
        upgrade(url)
        engine = _engine(url)
    elif revision != HEAD_REVISION:
        engine.dispose()
        newer = not _known(revision)
        raise RecordsError(
            f"{describe_url(url)}: schema revision {revision}, this runtime's is {HEAD_REVISION}; "
            + ("expected a runtime at least as new as the database" if newer else "run: daror db upgrade")
        )
    return Store(url, engine)
