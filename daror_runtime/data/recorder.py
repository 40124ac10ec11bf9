"""The crash-safe recorder the control loop streams every tick into (issue 3): the writing side.

The loop thread calls :meth:`Recorder.push` once per tick. ``push`` copies the row into a
preallocated block and, when the block is full, hands it to one background writer thread; it never
does I/O, never waits for the writer, and allocates no array memory. The writer appends each block
to the file as raw little-endian float64 rows and flushes it to the operating system, so every row
of a handed-over block survives the death of the process (``kill -9``) once its block is written.

File format (``docs/recorder.md``), written here and read by
:mod:`daror_runtime.data.recording_reader`::

    {"format": "daror-recording", "format_version": 1, "columns": [...], "dtype": "<f8", ...}   \\n
    row 0: len(columns) little-endian float64
    row 1: ...

The header is one line of JSON padded with spaces to a multiple of 64 bytes, so the rows start
aligned for memory mapping. Nothing follows the rows (no trailer, no index): a file cut anywhere
after the header is a valid recording of its complete rows, and a partial last row (the process
died in the middle of a write) is ignored by the reader. The loop's rows are laid out by
:mod:`daror_runtime.data.tick_row`; the recorder itself takes any columns.

Memory: the recorder owns exactly ``max_queued_blocks`` blocks of ``block_rows`` rows, allocated
once at :meth:`Recorder.start`: the block being filled plus those queued for or being written by
the writer. When the writer falls behind and no block is free, ``push`` drops the row and counts
it (:attr:`Recorder.dropped_rows`); what a drop means is the runtime's decision.

Errors: a failure in the writer thread (a full disk, a removed USB stick) is latched and raised
by the next ``push`` (and by ``close``) as :class:`RecorderError`, so the loop faults instead of
running on without a record.
"""

from __future__ import annotations

import json
import os
import queue
import threading
from collections import deque
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import BinaryIO

import numpy as np

from daror_runtime.errors import DarorError, ShapeError, UsageError
from hal.robot import FloatArray

#: The ``format`` of a recording's header.
FORMAT_NAME = "daror-recording"
#: The ``format_version`` this recorder writes (and the reader knows).
FORMAT_VERSION = 1
#: The rows' value type: little-endian float64.
DTYPE = "<f8"
#: Bytes per value of a recorded row.
VALUE_BYTES = 8
#: The header is padded to a multiple of this, so the rows start aligned for memory mapping.
HEADER_ALIGN_BYTES = 64

__all__ = ["DTYPE", "FORMAT_NAME", "FORMAT_VERSION", "HEADER_ALIGN_BYTES", "VALUE_BYTES", "Recorder", "RecorderError"]


class RecorderError(DarorError):
    """Recording failed: the writer thread could not write the file, or the recorder is not open.

    A failure of the run, not of a person's input: the loop treats it as a fault.
    """


# --- writing ---------------------------------------------------------------------------------


class Recorder:
    """Streams rows of float64 values to a file from the control loop, in bounded memory.

    One thread (the loop) calls :meth:`push` and :meth:`flush`; :meth:`start` and :meth:`close`
    are called outside the tick, from the same thread or after the loop stopped. Usable as a
    context manager (``with Recorder(...) as rec:`` starts and closes it).

    Args:
        path: the recording file; it must not exist yet.
        columns: one name per value of a row, in row order; non-empty and unique.
        block_rows: rows per block; the writer writes and flushes one block at a time, so this
            many rows (at 1 kHz: ``block_rows`` ms) are what a crash can lose besides the queue.
        max_queued_blocks: blocks the recorder owns in all (the one being filled, those waiting
            for the writer, the one being written); at least 2. Memory is
            ``max_queued_blocks * block_rows * len(columns) * 8`` bytes, whatever the run length.
        fsync_every_blocks: call ``fsync`` after every this many blocks, so rows survive a power
            loss too (None: only at :meth:`close`). A flush to the OS already survives a crash.

    Raises:
        UsageError: an empty or duplicated column name, or a size below its minimum.
    """

    def __init__(
        self,
        path: Path | str,
        columns: Sequence[str],
        block_rows: int = 1000,
        max_queued_blocks: int = 64,
        fsync_every_blocks: int | None = None,
    ) -> None:
        self._path = Path(path)
        names = tuple(columns)
        if not names:
            raise UsageError(f"{self._path}: a recording needs at least one column")
        for name in names:
            if not isinstance(name, str) or not name.strip():
                raise UsageError(f"{self._path}: column name {name!r} is not a non-empty string")
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise UsageError(f"{self._path}: column name(s) {', '.join(duplicates)} appear more than once")
        if block_rows < 1:
            raise UsageError(f"{self._path}: block_rows is {block_rows}; expected at least 1")
        if max_queued_blocks < 2:
            # One block is always being filled; with fewer than two, none could ever be written.
            raise UsageError(f"{self._path}: max_queued_blocks is {max_queued_blocks}; expected at least 2")
        if fsync_every_blocks is not None and fsync_every_blocks < 1:
            raise UsageError(f"{self._path}: fsync_every_blocks is {fsync_every_blocks}; expected at least 1 or None")
        self._columns = names
        self._n_columns = len(names)
        self._block_rows = int(block_rows)
        self._n_blocks = int(max_queued_blocks)
        self._fsync_every = fsync_every_blocks
        # Set before start and after close, so push refuses with one attribute check.
        self._refusal: str | None = "the recorder is not started; call start() first"
        self._started = False
        self._closed = False
        self._error: RecorderError | None = None
        self._pool: np.ndarray = np.empty((0, self._block_rows, self._n_columns))  # allocated in start()
        self._block: np.ndarray = np.empty((0, self._n_columns))
        self._block_index = -1
        self._fill = 0
        self._free: deque[int] = deque()
        # SimpleQueue.put never blocks (documented); the pool, not the queue, bounds its length.
        self._queue: queue.SimpleQueue[tuple[int, int] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._file: BinaryIO | None = None
        self._rows_written = 0
        self._rows_accepted = 0
        self._dropped_rows = 0
        self._blocks_written = 0

    # -- properties ------------------------------------------------------------------------

    @property
    def path(self) -> Path:
        return self._path

    @property
    def columns(self) -> tuple[str, ...]:
        return self._columns

    @property
    def capacity_rows(self) -> int:
        """Rows the recorder can hold in memory: ``block_rows * max_queued_blocks``."""
        return self._block_rows * self._n_blocks

    @property
    def rows_written(self) -> int:
        """Rows written and flushed to the operating system (they survive a crash of the process)."""
        return self._rows_written

    @property
    def rows_accepted(self) -> int:
        """Rows :meth:`push` took (written, queued or in the block being filled)."""
        return self._rows_accepted

    @property
    def dropped_rows(self) -> int:
        """Rows :meth:`push` dropped because every block was full (the writer fell behind)."""
        return self._dropped_rows

    @property
    def error(self) -> RecorderError | None:
        """The latched writer failure, or None."""
        return self._error

    # -- life cycle ------------------------------------------------------------------------

    def start(self) -> None:
        """Create the file, write the header (fsynced), allocate the blocks and start the writer.

        Raises:
            UsageError: the file exists already (a recording is never overwritten) or the
                recorder was started before.
            RecorderError: the file cannot be created or the header cannot be written.
        """
        if self._started or self._closed:
            raise UsageError(f"{self._path}: the recorder was started or closed already; a Recorder records one file")
        header = _header_bytes(self._columns, self._block_rows)
        try:
            # "x": exclusive create, so an existing recording is refused without a check-then-open race.
            handle = open(self._path, "xb")  # noqa: SIM115 - the writer thread owns and closes it
        except FileExistsError:
            raise UsageError(f"{self._path}: file exists; refusing to overwrite a recording") from None
        except OSError as exc:
            raise RecorderError(f"{self._path}: cannot create the recording ({exc})") from exc
        try:
            handle.write(header)
            handle.flush()
            os.fsync(handle.fileno())
            _fsync_directory(self._path.parent)
        except OSError as exc:
            handle.close()
            raise RecorderError(f"{self._path}: cannot write the recording header ({exc})") from exc
        self._file = handle
        # One allocation for the whole run; np.zeros so the pages are the OS's zero pages until used.
        self._pool = np.zeros((self._n_blocks, self._block_rows, self._n_columns), dtype=DTYPE)
        self._free = deque(range(1, self._n_blocks))
        self._block_index = 0
        self._block = self._pool[0]
        self._fill = 0
        self._started = True
        self._refusal = None
        self._thread = threading.Thread(target=self._run, name=f"recorder:{self._path.name}", daemon=True)
        self._thread.start()

    def push(self, row: FloatArray | Sequence[float]) -> bool:
        """Record one row (``len(columns)`` values); call once per tick from the loop thread.

        O(1), no I/O, no waiting, no array allocation: the values are copied into the current
        block; a full block is handed to the writer. When every block is full (the writer fell
        behind) the row is dropped and counted in :attr:`dropped_rows`.

        Returns:
            True if the row was recorded, False if it was dropped.

        Raises:
            RecorderError: the writer failed (latched), or the recorder is not started or closed.
            ShapeError: ``row`` does not hold ``len(columns)`` numbers (nothing is recorded).
        """
        if self._error is not None:
            raise self._latched()
        if self._refusal is not None:
            raise RecorderError(f"{self._path}: {self._refusal}")
        fill = self._fill
        if fill == self._block_rows:
            if not self._hand_over():
                self._dropped_rows += 1
                return False
            fill = 0
        try:
            n_values = len(row)
        except TypeError:
            n_values = -1
        if n_values != self._n_columns:
            raise ShapeError(
                f"{self._path}: a row of {n_values if n_values >= 0 else 'no sequence of'} values; "
                f"the recording has {self._n_columns} columns"
            )
        try:
            self._block[fill] = row
        except (TypeError, ValueError) as exc:
            # ShapeError: a 2-D row, or values that are not numbers; the slot is reused by the next push.
            raise ShapeError(
                f"{self._path}: cannot record {type(row).__name__} as a row of {self._n_columns} float64 values ({exc})"
            ) from None
        fill += 1
        self._fill = fill
        self._rows_accepted += 1
        if fill == self._block_rows:
            # Hand the full block over now, not at the next push, so it reaches the disk a tick sooner;
            # if no block is free the next push retries before it drops anything.
            self._hand_over()
        return True

    def push_into(self, fill: Callable[..., None], n_values: int, *args: object) -> bool:
        """Record one row that ``fill(block, index, *args)`` writes into row ``index`` of ``block``.

        :meth:`push` for a row that is computed rather than held: ``fill`` (typically compiled, e.g.
        :func:`daror_runtime.data.tick_row.fill_tick_row_at`) writes the row's ``n_values`` values
        straight into the recorder's current block, so nothing is copied twice and no row array
        exists. The same guarantees as :meth:`push` (O(1), no I/O, no waiting, no allocation; a row
        is dropped and counted when every block is full). ``fill`` must write row ``index`` and
        nothing else; an error it raises leaves the slot to the next row.

        Returns:
            True if the row was recorded, False if it was dropped.

        Raises:
            RecorderError: the writer failed (latched), or the recorder is not started or closed.
            ShapeError: ``n_values`` is not ``len(columns)`` (nothing is written).
        """
        if self._error is not None:
            raise self._latched()
        if self._refusal is not None:
            raise RecorderError(f"{self._path}: {self._refusal}")
        if n_values != self._n_columns:
            # Checked before fill runs: a compiled fill checks no bounds.
            raise ShapeError(f"{self._path}: a row of {n_values} values; the recording has {self._n_columns} columns")
        index = self._fill
        if index == self._block_rows:
            if not self._hand_over():
                self._dropped_rows += 1
                return False
            index = 0
        fill(self._block, index, *args)
        index += 1
        self._fill = index
        self._rows_accepted += 1
        if index == self._block_rows:
            self._hand_over()  # as in push: the full block goes to the writer now
        return True

    def batch_slot(self) -> tuple[FloatArray, int, int] | None:
        """``(block, index, free)``: rows ``index .. index + free - 1`` of ``block`` may be filled now, or None.

        For a lock-step batch that fills rows in compiled code and then calls :meth:`commit_batch`
        with how many it filled (the rows :meth:`push_into` would have filled one by one). None
        when the next row needs :meth:`push_into` (the block is full and must be handed over, a
        writer error is latched, or the recorder is not recording).
        """
        if self._error is not None or self._refusal is not None or self._fill == self._block_rows:
            return None
        return self._block, self._fill, self._block_rows - self._fill

    def commit_batch(self, rows: int) -> None:
        """``rows`` rows were filled from :meth:`batch_slot`'s index on; a full block goes to the writer now."""
        index = self._fill + rows
        self._fill = index
        self._rows_accepted += rows
        if index == self._block_rows:
            self._hand_over()

    def flush(self) -> bool:
        """Hand the partly filled block to the writer (no I/O, no waiting).

        Each call uses up a block for the rows filled so far, so flush at events (a state change,
        before a risky step), not every tick.

        Returns:
            True if the rows were handed over (or there were none), False if no block was free
            (the rows stay in the current block and go with it later).

        Raises:
            RecorderError: the writer failed (latched), or the recorder is not started or closed.
        """
        if self._error is not None:
            raise self._latched()
        if self._refusal is not None:
            raise RecorderError(f"{self._path}: {self._refusal}")
        return self._fill == 0 or self._hand_over()

    def close(self) -> None:
        """Write every pending row, fsync, close the file and stop the writer thread (blocks).

        Closing twice, or closing a recorder that was never started, does nothing.

        Raises:
            RecorderError: the writer failed at any time during the recording (latched).
        """
        if self._closed or not self._started or self._thread is None:
            self._closed = True
            self._refusal = "the recorder is closed"
            return
        self._closed = True
        self._refusal = "the recorder is closed"
        if self._fill:
            # No free block is needed any more: the writer gets the current block as it is.
            self._queue.put((self._block_index, self._fill))
            self._fill = 0
        self._queue.put(None)
        self._thread.join()
        # Every block is written (or the writer failed): the memory goes back now, not with the object.
        self._pool = np.empty((0, self._block_rows, self._n_columns))
        self._block = np.empty((0, self._n_columns))
        self._free.clear()
        if self._error is not None:
            raise self._latched()

    def __enter__(self) -> Recorder:
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        # An error raised here while another propagates keeps that one as its __context__.
        self.close()

    # -- internals -------------------------------------------------------------------------

    def _hand_over(self) -> bool:
        """Queue the current block and take a free one; False (nothing changed) if none is free."""
        free = self._free
        if not free:
            return False
        # Only this thread pops and only the writer appends, so the check above cannot go stale.
        self._queue.put((self._block_index, self._fill))
        index = free.popleft()
        self._block_index = index
        self._block = self._pool[index]
        self._fill = 0
        return True

    def _latched(self) -> RecorderError:
        # A fresh exception per raise: re-raising one object would pile up its traceback.
        error = self._error
        fresh = RecorderError(str(error))
        fresh.__cause__ = None if error is None else error.__cause__
        return fresh

    def _handle(self) -> BinaryIO:
        if self._file is None:
            raise RecorderError(f"{self._path}: the recording file is not open")
        return self._file

    def _write_block(self, rows: np.ndarray) -> None:
        """Append ``rows`` (C-contiguous ``<f8``) to the file and flush it to the OS (writer thread)."""
        handle = self._handle()
        handle.write(rows.data)
        handle.flush()

    def _sync(self) -> None:
        """fsync the file: its rows then survive a power loss (writer thread)."""
        os.fsync(self._handle().fileno())

    def _run(self) -> None:
        """The writer thread: write blocks in order until the stop marker, then fsync and close."""
        pool = self._pool
        try:
            while True:
                item = self._queue.get()
                if item is None:
                    break
                index, n_rows = item
                self._write_block(pool[index, :n_rows])
                self._rows_written += n_rows
                self._blocks_written += 1
                self._free.append(index)
                if self._fsync_every is not None and self._blocks_written % self._fsync_every == 0:
                    self._sync()
            self._sync()
        except BaseException as exc:  # latched and raised in the loop thread, never lost
            error = RecorderError(
                f"{self._path}: writing the recording failed after {self._rows_written} rows "
                f"({type(exc).__name__}: {exc}); later rows are not recorded"
            )
            error.__cause__ = exc
            self._error = error  # published complete: the loop thread may read it at any moment
        finally:
            self._close_file()

    def _close_file(self) -> None:
        if self._file is None:
            return
        try:
            self._file.close()
        except OSError as exc:
            # A buffered close can still fail to write; that loses data, so it is an error too.
            if self._error is None:
                error = RecorderError(f"{self._path}: closing the recording failed ({exc})")
                error.__cause__ = exc
                self._error = error


def _header_bytes(columns: Sequence[str], block_rows: int) -> bytes:
    document = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "columns": list(columns),
        "dtype": DTYPE,
        "created_utc": datetime.now(UTC).isoformat(timespec="microseconds"),
        "block_rows": block_rows,
    }
    # ensure_ascii: the header is plain ASCII with no raw newline, whatever the column names.
    text = json.dumps(document, ensure_ascii=True).encode("ascii")
    padded = -(len(text) + 1) % HEADER_ALIGN_BYTES
    return text + b" " * padded + b"\n"


def _fsync_directory(directory: Path) -> None:
    """Make the new file's directory entry durable (a power loss would otherwise lose the file)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
