"""The crash-safe recorder the control loop streams every tick into (issue 3).

The loop thread calls :meth:`Recorder.push` once per tick. ``push`` copies the row into a
preallocated block and, when the block is full, hands it to one background writer thread; it never
does I/O, never waits for the writer, and allocates no array memory. The writer appends each block
to the file as raw little-endian float64 rows and flushes it to the operating system, so every row
of a handed-over block survives the death of the process (``kill -9``) once its block is written.

File format (``docs/recorder.md``)::

    {"format": "daror-recording", "format_version": 1, "columns": [...], "dtype": "<f8", ...}   \\n
    row 0: len(columns) little-endian float64
    row 1: ...

The header is one line of JSON padded with spaces to a multiple of 64 bytes, so the rows start
aligned for memory mapping. Nothing follows the rows (no trailer, no index): a file cut anywhere
after the header is a valid recording of its complete rows, and a partial last row (the process
died in the middle of a write) is ignored by :func:`read_recording`.

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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from daror_runtime.data.load import check_raw_log
from daror_runtime.data.schema import (
    DQ_COLUMNS,
    Q_COLUMNS,
    RAW_REQUIRED,
    TAU_CMD_COLUMNS,
    TAU_COLUMNS,
    THETA_COLUMNS,
    RawLog,
)
from daror_runtime.errors import DarorError, DataError, ShapeError, UsageError
from hal.interface import Command, Sample
from hal.robot import FloatArray

FORMAT_NAME = "daror-recording"
FORMAT_VERSION = 1
DTYPE = "<f8"
#: Rows read at a time when a recording is converted (bounds the extra memory to ~20 MB).
_CHUNK_ROWS = 100_000
#: Bytes per value of a recorded row.
VALUE_BYTES = 8
#: The header is padded to a multiple of this, so the rows start aligned for memory mapping.
HEADER_ALIGN_BYTES = 64
#: A header line longer than this is not a recording header (guards against reading a whole
#: binary file looking for a newline).
MAX_HEADER_BYTES = 1 << 20

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "Recorder",
    "RecorderError",
    "RecordingInfo",
    "fill_raw_row",
    "inspect_recording",
    "read_recording",
    "recording_columns",
    "recording_to_raw_log",
]


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
    def memory_bytes(self) -> int:
        """Bytes of row storage the recorder owns (allocated at :meth:`start`)."""
        return self.capacity_rows * self._n_columns * VALUE_BYTES

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


# --- reading ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordingInfo:
    """What a recording file holds, from its header and size."""

    path: Path
    columns: tuple[str, ...]
    created_utc: str
    data_offset: int  # bytes before the first row
    n_rows: int  # complete rows
    tail_bytes: int  # bytes of a partial last row (a write cut short by a crash), ignored
    header: dict[str, Any]

    @property
    def row_bytes(self) -> int:
        return len(self.columns) * VALUE_BYTES


def _damaged(path: Path, why: str) -> DataError:
    return DataError(f"{path}: damaged recording header: {why}; expected a {FORMAT_NAME} file written by Recorder")


def _read_header(path: Path, handle: BinaryIO) -> tuple[dict[str, Any], int]:
    head = handle.read(MAX_HEADER_BYTES)
    end = head.find(b"\n")
    if not head:
        raise _damaged(path, "the file is empty (the process may have died before the header was written)")
    if end < 0:
        raise _damaged(path, f"no end of line in the first {min(len(head), MAX_HEADER_BYTES)} bytes")
    try:
        header = json.loads(head[:end].decode("ascii"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _damaged(path, f"the first line is not JSON ({exc})") from None
    if not isinstance(header, dict):
        raise _damaged(path, "the first line is not a JSON object")
    if header.get("format") != FORMAT_NAME:
        raise _damaged(path, f"format is {header.get('format')!r}")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise _damaged(path, f"format_version {version!r} is not {FORMAT_VERSION}, the version this reader knows")
    columns = header.get("columns")
    if (
        not isinstance(columns, list)
        or not columns
        or not all(isinstance(c, str) and c for c in columns)
        or len(set(columns)) != len(columns)
    ):
        raise _damaged(path, "'columns' is not a list of unique, non-empty names")
    if header.get("dtype") != DTYPE:
        raise _damaged(path, f"dtype {header.get('dtype')!r} is not {DTYPE!r}")
    return header, end + 1


def inspect_recording(path: Path | str) -> RecordingInfo:
    """Read the header and count the complete rows of a recording (the rows are not read).

    Raises:
        DataError: missing file, or a damaged or unknown header (the message names the file).
    """
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            header, offset = _read_header(path, handle)
            size = os.fstat(handle.fileno()).st_size
    except FileNotFoundError:
        raise DataError(f"{path}: file not found") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read the recording ({exc})") from None
    columns = tuple(header["columns"])
    row_bytes = len(columns) * VALUE_BYTES
    n_rows, tail = divmod(size - offset, row_bytes)
    return RecordingInfo(path, columns, str(header.get("created_utc", "")), offset, n_rows, tail, header)


def read_recording(path: Path | str, mmap: bool = False) -> tuple[tuple[str, ...], np.ndarray]:
    """The column names and the complete rows, ``(rows, columns)`` float64, of a recording.

    A partial last row (the writer was killed in the middle of a write) is left out; every row
    returned was written whole. ``mmap=True`` maps the file read-only instead of reading it
    (for recordings larger than memory); the array then keeps the file open.

    Raises:
        DataError: missing file, or a damaged or unknown header (the message names the file).
    """
    info = inspect_recording(path)
    n_columns = len(info.columns)
    if info.n_rows == 0:
        return info.columns, np.empty((0, n_columns))
    if mmap:
        data = np.memmap(info.path, dtype=DTYPE, mode="r", offset=info.data_offset, shape=(info.n_rows, n_columns))
        return info.columns, data
    try:
        with open(info.path, "rb") as handle:
            handle.seek(info.data_offset)
            flat = np.fromfile(handle, dtype=DTYPE, count=info.n_rows * n_columns)
    except OSError as exc:
        raise DataError(f"{info.path}: cannot read the recording ({exc})") from None
    # The file may have shrunk since it was inspected (a reader racing a truncation): whole rows only.
    whole = flat.size - flat.size % n_columns
    return info.columns, flat[:whole].reshape(-1, n_columns).astype(np.float64, copy=False)


def recording_columns(theta: bool = True, tau_cmd: bool = True, extra: Sequence[str] = ()) -> tuple[str, ...]:
    """The columns of a raw-log recording: ``t, q1..4, dq1..4, tau1..4`` (+ ``theta1..4``, ``tau_cmd1..4``) + ``extra``.

    Raises:
        UsageError: an ``extra`` name repeats a raw-log column.
    """
    columns = (*RAW_REQUIRED, *(THETA_COLUMNS if theta else ()), *(TAU_CMD_COLUMNS if tau_cmd else ()))
    clash = sorted(set(columns) & set(extra))
    if clash:
        raise UsageError(f"extra column(s) {', '.join(clash)} repeat raw-log columns")
    return (*columns, *extra)


def fill_raw_row(out: FloatArray, sample: Sample, command: Command | None = None) -> FloatArray:
    """Write a tick's sample (and command) into ``out`` in :func:`recording_columns` order; no allocation.

    ``out`` must have the layout of ``recording_columns(theta=True, tau_cmd=command is not None)``
    (values after that, for extra columns, are left alone). ``tau_cmd`` is the command's motor
    torque (Nm) as the controller set it, whether or not the command enables the drives (record
    ``enable`` as an extra column when that matters), as the loop's own recording does.

    Returns:
        ``out``.

    Raises:
        ShapeError: ``out`` is too short for the layout.
    """
    needed = 17 if command is None else 21
    if out.shape[0] < needed:
        raise ShapeError(f"a raw-log row needs {needed} values; got an array of {out.shape[0]}")
    out[0] = sample.t_s
    out[1:5] = sample.q_rad
    out[5:9] = sample.dq_rad_s
    out[9:13] = sample.tau_nm
    out[13:17] = sample.theta_rad
    if command is not None:
        out[17:21] = command.motor_torque_nm
    return out


def recording_to_raw_log(
    path: Path | str, mapping: Mapping[str, str] | None = None, drop_nan_rows: bool = False
) -> RawLog:
    """A recording as a raw log (DESIGN.md section 5), checked like a raw-log file.

    ``mapping`` names, for a raw-log column (``t``, ``q1``, ...), the recording column that holds
    it when the names differ (``{"t": "time_s"}``); other columns are looked up by their own name.
    ``theta1..4`` and ``tau_cmd1..4`` are taken when the recording has all four.

    ``drop_nan_rows`` leaves out rows with a NaN in any raw-log column taken (the loop records
    NaN for a tick without a fresh sample) instead of refusing the file; infinities are still
    refused. Error messages give row numbers of the recording (1-based), dropped rows counted.

    Raises:
        DataError: a damaged header, a missing column, a non-finite value, angles beyond 2 pi,
            time not increasing, or no rows (the message names the file).
    """
    info = inspect_recording(path)
    if info.n_rows == 0:
        raise DataError(f"{path}: the recording holds no complete row; expected at least one")
    mapping = dict(mapping or {})
    groups = {
        "t": ("t",),
        "q": Q_COLUMNS,
        "dq": DQ_COLUMNS,
        "tau": TAU_COLUMNS,
        "theta": THETA_COLUMNS,
        "tau_cmd": TAU_CMD_COLUMNS,
    }
    wanted = tuple(name for names in groups.values() for name in names)
    unknown = sorted(name for name in mapping if name not in wanted)
    if unknown:
        raise DataError(f"{path}: mapping names {', '.join(unknown)}, which are not raw-log columns")
    index = {name: i for i, name in enumerate(info.columns)}
    missing_sources = sorted(src for src in mapping.values() if src not in index)
    if missing_sources:
        raise DataError(
            f"{path}: mapped column(s) {', '.join(missing_sources)} not in the recording (it has {', '.join(info.columns)})"
        )
    sources: dict[str, list[int]] = {}
    for group, names in groups.items():
        found = [index.get(mapping.get(name, name)) for name in names]
        if all(i is not None for i in found):
            sources[group] = found  # type: ignore[assignment]
        elif group not in ("theta", "tau_cmd"):
            absent = [n for n, i in zip(names, found, strict=True) if i is None]
            raise DataError(f"{path}: missing column(s) {', '.join(absent)}; a raw log needs t, q1..4, dq1..4, tau1..4")
    # Stream the rows in chunks into one array per group: only what the raw log keeps is ever
    # held (a 15-minute run at 1 kHz is ~150 MB of recording, ~125 MB of raw log).
    arrays = {group: np.empty((info.n_rows, len(cols))) for group, cols in sources.items()}
    with open(info.path, "rb") as handle:
        handle.seek(info.data_offset)
        n_columns = len(info.columns)
        for start in range(0, info.n_rows, _CHUNK_ROWS):
            count = min(_CHUNK_ROWS, info.n_rows - start)
            chunk = np.fromfile(handle, dtype=DTYPE, count=count * n_columns)
            if chunk.size != count * n_columns:
                raise DataError(f"{path}: the recording shrank while it was read")
            chunk = chunk.reshape(count, n_columns)
            for group, cols in sources.items():
                arrays[group][start : start + count] = chunk[:, cols]
    rows = np.arange(1, info.n_rows + 1)
    if drop_nan_rows:
        keep = np.ones(info.n_rows, dtype=bool)
        for group in ("t", "q", "dq", "tau"):  # per group: no stacked copy of the whole log
            keep &= ~np.isnan(arrays[group]).any(axis=1)
        if not keep.any():
            raise DataError(f"{path}: every row has a NaN in a raw-log column; no sample to keep")
        if not keep.all():
            arrays = {group: values[keep] for group, values in arrays.items()}
            rows = rows[keep]
    raw = RawLog(
        t_s=arrays["t"][:, 0],
        q_rad=arrays["q"],
        dq_rad_s=arrays["dq"],
        tau_nm=arrays["tau"],
        theta_rad=arrays.get("theta"),
        tau_cmd_nm=arrays.get("tau_cmd"),
        source=str(path),
    )
    check_raw_log(raw, lambda row, column: f"{path}: row {int(rows[row])}, column {column}")
    return raw
