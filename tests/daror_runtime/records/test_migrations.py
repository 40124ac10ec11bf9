"""Issue 28: the records' schema is what the migrations build, on SQLite and on PostgreSQL.

From an empty database the migrations build exactly the tables the ORM maps (Alembic's own
comparison finds nothing to change); the runtime's HEAD_REVISION is the migrations' head; a
new SQLite file is brought to the head by ``daror db upgrade``; a database at the previous revision
with records in it is refused until upgraded, and keeps every record through the upgrade.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import create_engine, inspect, text

from daror_runtime.cli import main
from daror_runtime.records.schema import Base
from daror_runtime.records.store import _MIGRATIONS, HEAD_REVISION, RecordsError, open_store, upgrade


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


@pytest.mark.parametrize("previous", ["0001", "0002"])
def test_from_the_previous_schema_with_records_in_it(
    db_url: str, capsys: pytest.CaptureFixture[str], previous: str
) -> None:
    """A database at an earlier revision holding a pilot, a session and a model is refused until
    upgraded, then migrated to the head with every record kept and the new columns empty."""
    from alembic import command

    from daror_runtime.records.store import _alembic_config, _engine

    engine = _engine(db_url)
    with engine.connect() as connection:
        command.upgrade(_alembic_config(connection), previous)
        connection.commit()
    with engine.begin() as connection:
        connection.execute(
            text(
                "INSERT INTO pilots (id, code, arm_side, notes, simulated, created_utc) "
                "VALUES (1, 'P-007', 'right', 'ambulant', false, '2026-01-05 10:00:00+00:00')"
            )
        )
        connection.execute(
            text(
                "INSERT INTO sessions (id, session_id, pilot_id, ended_by_crash, robot, backend, directory, "
                "final_state, robot_time_s, states_reached, faults, support_levels, recorded_utc) VALUES "
                "(1, 's1', 1, false, 'DAROR-01', 'can', '/lab/s1', 'compensation', 612.5, '[]', '[]', '[0.8]', "
                "'2026-01-05 11:00:00+00:00')"
            )
        )
        connection.execute(
            text(
                "INSERT INTO models (id, pilot_id, session_id, kind, path, sha256, validation_rmse_nm, validated, "
                "in_use, parameters, recorded_utc) VALUES (1, 1, 1, 'plf+', '/lab/s1/model_plf_plus.json', "
                "'ab', 0.42, true, true, '{}', '2026-01-05 11:00:00+00:00')"
            )
        )
    engine.dispose()
    with pytest.raises(
        RecordsError, match=f"schema revision {previous}, this runtime's is {HEAD_REVISION}; run: daror db upgrade"
    ):
        open_store(db_url)
    assert upgrade(db_url) == (previous, HEAD_REVISION)
    store = open_store(db_url)
    try:
        from daror_runtime.records.pilots import pilot_summaries
        from daror_runtime.records.schema import ModelRecord

        summaries = pilot_summaries(store)
        assert [(s.code, s.sessions, s.model) for s in summaries] == [("P-007", 1, "plf+ 0.420 Nm")]
        with store.session() as orm:
            model = orm.query(ModelRecord).one()
            assert model.validation_rmse_per_joint_nm is None  # the new column, empty for what was there
            assert model.session.support_levels == [0.8]
            assert model.session.online is None  # 0003's columns, empty for a session recorded before
            assert model.session.comparison is None
    finally:
        store.close()
    engine = create_engine(db_url)
    try:
        with engine.connect() as connection:
            assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
    finally:
        engine.dispose()
