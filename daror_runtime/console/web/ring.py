"""The live rows the runtime's process shares with the web server's: a ring buffer in shared memory.

One writer (the runtime's service thread, outside the tick, :class:`~daror_runtime.console.web.bridge.WebBridge`)
and any number of readers (the server process's websockets, each from its own cursor). The memory
is an anonymous file (``memfd_create``, Linux): it has no name to leak and is freed when both
processes have closed it. Writing a row is a few array copies with no system call and no lock, so
the runtime's process never waits for the server nor hands it the interpreter.

Layout (native byte order): one int64, the number of rows written so far; then ``capacity`` rows
of float64: ``t_s``, ``q_rad`` (one per joint), ``tau_nm`` (the spring torques measured), and
``reference_nm`` (the spring torques compensation asked for, NaN outside compensation).

A row is written before the count that makes it visible (stores are not reordered with stores on
x86-64, the control computers this runs on); a reader takes only rows that are well behind the
writer, so it never reads a row being written unless it stalled for most of the window.
"""

from __future__ import annotations

import mmap
import os
from collections.abc import Sequence

import numpy as np

from daror_runtime.errors import ConfigurationError

_HEADER_BYTES = 8
#: Rows a reader leaves between what it takes and the slot the writer fills next.
_MARGIN_ROWS = 8


def row_width(n_joints: int) -> int:
    """Floats per row: time, then angles, measured torques and references, one per joint each."""
    return 1 + 3 * n_joints


def ring_bytes(capacity: int, n_joints: int) -> int:
    """Size (bytes) of a ring of ``capacity`` rows."""
    return _HEADER_BYTES + capacity * row_width(n_joints) * 8


class RowRing:
    """A ring of live rows over a shared mapping (create it with :meth:`create`, open it with :meth:`attach`).

    Raises:
        ConfigurationError: a capacity too small for the reader's margin, or a mapping of the wrong size.
    """

    def __init__(self, memory: mmap.mmap, capacity: int, n_joints: int) -> None:
        if capacity <= 2 * _MARGIN_ROWS:
            raise ConfigurationError(f"a live-row ring needs more than {2 * _MARGIN_ROWS} rows, got {capacity}")
        if len(memory) != ring_bytes(capacity, n_joints):
            raise ConfigurationError(
                f"the live-row ring is {len(memory)} bytes, expected {ring_bytes(capacity, n_joints)}"
            )
        self._memory = memory
        self.capacity = capacity
        self.n_joints = n_joints
        self._count = np.frombuffer(memory, dtype=np.int64, count=1)
        self._rows = np.frombuffer(memory, dtype=np.float64, offset=_HEADER_BYTES).reshape(
            capacity, row_width(n_joints)
        )

    @classmethod
    def create(cls, capacity: int, n_joints: int) -> tuple[RowRing, int]:
        """A new ring in anonymous shared memory and its file descriptor (to hand to the other process)."""
        fd = os.memfd_create("daror-live-rows", os.MFD_CLOEXEC)
        size = ring_bytes(capacity, n_joints)
        os.ftruncate(fd, size)
        return cls(mmap.mmap(fd, size), capacity, n_joints), fd

    @classmethod
    def attach(cls, fd: int, capacity: int, n_joints: int) -> RowRing:
        """The ring another process created, from its file descriptor (the mapping keeps the memory)."""
        ring = cls(mmap.mmap(fd, ring_bytes(capacity, n_joints)), capacity, n_joints)
        os.close(fd)
        return ring

    @property
    def written(self) -> int:
        """Rows written since the ring was created."""
        return int(self._count[0])

    def push(self, t_s: float, q_rad: Sequence[float], tau_nm: Sequence[float], reference_nm: object) -> None:
        """Write one row (the writer's side; one thread only). ``reference_nm`` None: NaN (not compensating)."""
        n = int(self._count[0])
        row = self._rows[n % self.capacity]
        j = self.n_joints
        row[0] = t_s
        row[1 : 1 + j] = q_rad
        row[1 + j : 1 + 2 * j] = tau_nm
        if reference_nm is None:
            row[1 + 2 * j :] = np.nan
        else:
            row[1 + 2 * j :] = reference_nm  # type: ignore[assignment]  # an array of n_joints floats
        self._count[0] = n + 1

    def since(self, cursor: int, limit: int) -> tuple[int, np.ndarray]:
        """Rows after ``cursor`` (at most ``limit``, the oldest first; a copy) and the new cursor.

        A reader more than the window behind has lost the oldest rows: it resumes in the window.
        """
        newest = int(self._count[0])
        oldest = max(cursor, newest - (self.capacity - _MARGIN_ROWS))
        last = min(newest, oldest + limit)
        if last <= oldest:
            return max(cursor, newest), np.empty((0, self._rows.shape[1]))
        slots = np.arange(oldest, last) % self.capacity
        return last, self._rows[slots].copy()

    def close(self) -> None:
        """Release the mapping (the arrays over it must not be used after this)."""
        del self._count, self._rows
        self._memory.close()
