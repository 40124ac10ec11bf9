"""Issue 28: the records' schema is what the migrations build, on SQLite and on PostgreSQL.

From an empty database the migrations build exactly the tables the ORM maps (Alembic's own
comparison finds nothing to change); the runtime's HEAD_REVISION is the migrations' head; a
new SQLite file is brought to the head by ``daror db upgrade``. (A database at an older revision
than the head is refused until upgraded, and migrated by it: tested once there is an older revision,
the first migration after 0001.)
"""

from __future__ import annotations

from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import create_engine, inspect

from daror_runtime.cli import main
from daror_runtime.records.schema import Base
from daror_runtime.records.store import _MIGRATIONS, HEAD_REVISION, RecordsError, upgrade


def test_the_runtime_s_revision_is_the_migrations_head() -> None:
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(_MIGRATIONS))
    assert ScriptDirectory.from_config(config).get_heads() == [HEAD_REVISION]


def test_from_an_empty_database_the_migrations_build_the_mapped_schema(db_url: str) -> None:
    assert upgrade(db_url) == (None, HEAD_REVISION)
    engine = create_engine(db_url)
    try:
        with engine.connect() as connection:
            differences = compare_metadata(MigrationContext.configure(connection), Base.metadata)
            tables = set(inspect(connection).get_table_names())
    finally:
        engine.dispose()
    assert differences == []
    assert tables == {*Base.metadata.tables, "alembic_version"}
    assert upgrade(db_url) == (HEAD_REVISION, HEAD_REVISION)  # idempotent


def test_db_upgrade_on_a_new_sqlite_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    db = tmp_path / "lab.db"
    assert main(["db", "upgrade", "--db", str(db)]) == 0
    assert f"schema empty -> {HEAD_REVISION}" in capsys.readouterr().out
    assert db.is_file()
    with pytest.raises(RecordsError, match=r"folder .* does not exist"):
        upgrade(f"sqlite:///{tmp_path / 'nowhere' / 'lab.db'}")
