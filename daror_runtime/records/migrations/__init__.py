"""Alembic's migrations of the records' schema (``daror db upgrade``); one file per revision in ``versions``."""
