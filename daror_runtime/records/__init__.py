"""The lab's records (issue 28): every pilot, session, range of motion, model and dataset, in a database.

DMD progresses, and the research question is whether support over months keeps the arm working
longer, so a lab needs each pilot's record across sessions. Files stay files (datasets, raw logs,
model files, ``session.json``); the database indexes them with their SHA-256, so a moved or changed
file is found out. SQLite in a file by default (``daror.db`` beside the sessions), PostgreSQL for a
lab or a multi-site study (``--db URL`` or ``DAROR_DB``). The schema is SQLAlchemy 2's declarative
mapping (:mod:`.schema`) and every change to it an Alembic migration (``migrations/``).

Design time only: nothing here runs in the tick (a session is recorded when it ends).
"""
