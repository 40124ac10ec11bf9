"""Reading recordings offline: the header, the rows, and a recording as a raw log.

A recording is what :class:`daror_runtime.data.recorder.Recorder` wrote (format in that module and
``docs/recorder.md``): one JSON header line, then whole rows of little-endian float64. A partial
last row (the writer was killed in the middle of a write) is ignored; every row returned was
written whole. Nothing here runs in the tick.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from daror_runtime.data.recorder import DTYPE, FORMAT_NAME, FORMAT_VERSION, VALUE_BYTES
from daror_runtime.data.schema import DQ_COLUMNS, Q_COLUMNS, TAU_CMD_COLUMNS, TAU_COLUMNS, THETA_COLUMNS, RawLog
from daror_runtime.errors import DataError

#: Rows read at a time when a recording is converted (bounds the extra memory to ~20 MB).
_CHUNK_ROWS = 20_000  # 3.8 MB of a loop recording per read
#: A header line longer than this is not a recording header (guards against reading a whole
#: binary file looking for a newline).
MAX_HEADER_BYTES = 1 << 20

__all__ = ["MAX_HEADER_BYTES", "RecordingInfo", "inspect_recording", "read_recording", "recording_to_raw_log"]


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


def _read_into(handle: BinaryIO, view: memoryview) -> int:
    """Fill ``view`` from ``handle``; the bytes read (fewer only at the end of the file)."""
    done = 0
    while done < len(view):
        n = handle.readinto(view[done:])  # type: ignore[attr-defined]
        if not n:
            break
        done += n
    return done


def recording_to_raw_log(
    path: Path | str, mapping: Mapping[str, str] | None = None, drop_nan_rows: bool = False
) -> RawLog:
    """A recording as a raw log (docs/data.md), checked like a raw-log file.

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
    # A group in consecutive columns (the loop's recordings: every group) is copied as a slice, in
    # one pass and without the temporary a list index makes.
    selectors = {
        group: slice(cols[0], cols[0] + len(cols)) if cols == list(range(cols[0], cols[0] + len(cols))) else cols
        for group, cols in sources.items()
    }
    with open(info.path, "rb") as handle:
        handle.seek(info.data_offset)
        n_columns = len(info.columns)
        chunk = np.empty(_CHUNK_ROWS * n_columns, dtype=DTYPE)  # one buffer, read into chunk after chunk
        for start in range(0, info.n_rows, _CHUNK_ROWS):
            count = min(_CHUNK_ROWS, info.n_rows - start)
            wanted_bytes = count * n_columns * VALUE_BYTES
            if _read_into(handle, memoryview(chunk).cast("B")[:wanted_bytes]) != wanted_bytes:
                raise DataError(f"{path}: the recording shrank while it was read")
            rows_of_chunk = chunk[: count * n_columns].reshape(count, n_columns)
            for group, selector in selectors.items():
                arrays[group][start : start + count] = rows_of_chunk[:, selector]
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
    # here: data.load brings the table readers along (~25 ms), which a session's start-up does not need
    from daror_runtime.data.load import check_raw_log

    check_raw_log(raw, lambda row, column: f"{path}: row {int(rows[row])}, column {column}")
    return raw
