"""A private PostgreSQL server for the records' tests: its own cluster in a temporary folder, on a socket.

``make test`` installs Debian's ``postgresql`` package (the server's programs; its own service is
never used). :class:`PostgresServer` runs ``initdb`` and ``pg_ctl`` from it: a cluster in a
temporary folder that listens on a Unix socket there and on no TCP address at all, trust
authentication for its one user, fsync off (a test server). As root the programs run as the
package's ``postgres`` user (the server refuses root). When it cannot be started (no package, no
such user), :func:`start_or_skip_reason` says why and the tests that need it skip with that reason.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
import uuid
from pathlib import Path

#: The cluster's only user (trust authentication on the socket).
USER = "daror"


def _program(name: str) -> str | None:
    found = shutil.which(name)
    if found is not None:
        return found
    candidates = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))
    return candidates[-1] if candidates else None


class PostgresServer:
    """A running private cluster; :meth:`new_database` gives each test an empty database's URL."""

    def __init__(self) -> None:
        initdb, pg_ctl = _program("initdb"), _program("pg_ctl")
        if initdb is None or pg_ctl is None:
            raise RuntimeError("PostgreSQL's initdb and pg_ctl not found (Debian package postgresql)")
        self.pg_ctl = pg_ctl
        self.root = Path(tempfile.mkdtemp(prefix="daror-pg-"))
        self.data = self.root / "data"
        self.socket = self.root
        self._as_user: list[str] = []
        if os.geteuid() == 0:  # the server refuses to run as root: as the package's user
            if shutil.which("runuser") is None:
                raise RuntimeError("running as root without runuser: cannot start PostgreSQL as another user")
            try:
                shutil.chown(self.root, "postgres", "postgres")
            except LookupError:
                raise RuntimeError("running as root and no postgres user (Debian package postgresql)") from None
            self._as_user = ["runuser", "-u", "postgres", "--"]
        self._run([initdb, "-D", str(self.data), "-A", "trust", "-U", USER, "--no-sync", "-E", "UTF8"])
        options = f"-k {self.socket} -c listen_addresses='' -c fsync=off -c full_page_writes=off"
        self._run([pg_ctl, "-D", str(self.data), "-o", options, "-l", str(self.root / "server.log"), "-w", "start"])
        self.admin_url = f"postgresql+psycopg://{USER}@/postgres?host={self.socket}"

    def _run(self, argv: list[str]) -> None:
        done = subprocess.run([*self._as_user, *argv], capture_output=True, text=True, timeout=120, check=False)
        if done.returncode != 0:
            raise RuntimeError(f"{Path(argv[0]).name} failed: {(done.stderr or done.stdout).strip()[-400:]}")

    def new_database(self) -> str:
        """A new empty database on the server; its URL."""
        from sqlalchemy import create_engine, text

        name = f"t_{uuid.uuid4().hex[:12]}"
        engine = create_engine(self.admin_url, isolation_level="AUTOCOMMIT")
        try:
            with engine.connect() as connection:
                connection.execute(text(f'CREATE DATABASE "{name}"'))
        finally:
            engine.dispose()
        return f"postgresql+psycopg://{USER}@/{name}?host={self.socket}"

    def stop(self) -> None:
        try:
            self._run([self.pg_ctl, "-D", str(self.data), "-m", "immediate", "-w", "stop"])
        finally:
            shutil.rmtree(self.root, ignore_errors=True)


def start_or_skip_reason() -> tuple[PostgresServer | None, str]:
    """A started server and "", or None and why it could not start (the skip's reason)."""
    try:
        import psycopg  # noqa: F401 - the driver the extra installs
    except ImportError:
        return None, "psycopg is not installed (extra: postgres)"
    try:
        return PostgresServer(), ""
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        return None, f"PostgreSQL cannot be started here: {exc}"
