"""The records' database for the tests: SQLite in a file, and a real PostgreSQL server (tests/postgres_server.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.postgres_server import PostgresServer, start_or_skip_reason


@pytest.fixture(scope="session")
def postgres() -> Iterator[PostgresServer | str]:
    """The private server (one per worker), or the reason it could not be started."""
    server, why = start_or_skip_reason()
    if server is None:
        yield why
        return
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """An empty database: a SQLite file in the test's folder, or a new database on the PostgreSQL server."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'daror.db'}"
    server = request.getfixturevalue("postgres")
    if isinstance(server, str):
        pytest.skip(server)
    return server.new_database()
