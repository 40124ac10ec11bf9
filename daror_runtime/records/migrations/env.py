"""Alembic's environment: the migrations run on the connection :mod:`daror_runtime.records.store` hands over."""

from __future__ import annotations

from alembic import context

from daror_runtime.records.schema import Base

connection = context.config.attributes.get("connection")
if connection is None:  # pragma: no cover - only the store runs the migrations, always with its connection
    raise RuntimeError("the records' migrations run through daror_runtime.records.store (daror db upgrade)")
# batch mode: SQLite alters a table by copying it, which a later migration needs and PostgreSQL ignores
context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
