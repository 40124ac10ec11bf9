"""Named numeric columns in CSV, ``.npz`` and MATLAB ``.mat`` files.

A table is a set of equally long float columns with names. Reading reports every problem with
the file, the line (CSV) or row (npz/mat) and the column; writing is atomic.

Every file is opened through :mod:`hal.files` (a regular file of at most
:data:`~hal.files.DATA_MAX_BYTES`): a directory, FIFO, device, socket, symlink loop or unreadable
file is refused with one message before anything is read.

CSV is read in two passes over blocks of whole lines, never the whole file in memory: the first
counts the lines (so the columns are allocated once), the second parses. The parse has a fast
path, a compiled parser of plain decimal numbers (:func:`_parse_lines`, correctly rounded: the
Eisel-Lemire algorithm, bit for bit what ``float()`` gives), and the careful parser as its
fallback: any line the fast path does not take (a quoted cell, a blank line, ``nan``, 20 digits, a
wrong number of fields, text) goes through ``csv`` and ``float()``, which either reads it or names
the line, the column and what was expected.

Columns of the groups in :data:`~daror_runtime.data.schema.STORAGE_GROUPS` (``q1..q4``, ...) are
stored side by side in one C-contiguous ``(rows, 4)`` array, which :meth:`Table.matrix` hands to a
dataset without a copy: 10^6 rows of a stationary dataset cost their 104 MB once.
"""

from __future__ import annotations

import csv
import os
import re
import stat
import time
import warnings
import zipfile
import zlib
from collections import Counter
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from numba import njit

from daror_runtime.data.schema import STORAGE_GROUPS
from daror_runtime.errors import DataError
from daror_runtime.util.atomic import atomic_path
from hal.files import DATA_MAX_BYTES, regular_file
from hal.robot import FloatArray

SUPPORTED_SUFFIXES = (".csv", ".npz", ".mat")

#: Bytes read at a time (CSV); a block is cut at its last line end.
CHUNK_BYTES = 4 << 20
#: A CSV line longer than this is refused (a 200,000-column header is about 1.4 MB).
MAX_LINE_BYTES = 16 << 20
#: What the file is when it starts with these bytes (a CSV that is not text).
_MAGIC = (
    (b"PK\x03\x04", "a zip archive (an .npz, or a spreadsheet .xlsx/.ods saved under a .csv name)"),
    (b"PK\x05\x06", "an empty zip archive"),
    (b"\x1f\x8b", "a gzip-compressed file"),
    (b"\x93NUMPY", "a NumPy .npy array"),
    (b"\x89HDF", "an HDF5 file (MATLAB v7.3?)"),
    (b"MATLAB 5.0 MAT-file", "a MATLAB .mat file"),
    (b"\xd0\xcf\x11\xe0", "an old Excel .xls workbook"),
    (b"%PDF", "a PDF document"),
    (b"\xff\xfe", "UTF-16 text (little endian, with a byte order mark)"),
    (b"\xfe\xff", "UTF-16 text (big endian, with a byte order mark)"),
)
_UTF8_BOM = b"\xef\xbb\xbf"
_NO_RUNS = np.empty(0, dtype=np.int64)
#: Cells a spreadsheet or a logger writes for "no value".
_MISSING = frozenset({"", "na", "n/a", "#n/a", "null", "none", "nil", "-", "?", "#num!", "#div/0!", "#value!", "#ref!"})
_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+([eE][+-]?\d+)?$")
#: What a cell may hold (the careful parser): a decimal number in ASCII digits, or nan/inf (named
#: as not finite by the dataset's checks), with spaces or tabs around it.
_PLAIN_NUMBER = re.compile(
    r"[ \t]*[+-]?(?:(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|inf|infinity|nan)[ \t]*",
    re.IGNORECASE | re.ASCII,
)
#: Names of dataset columns (to recognise a header separated by spaces).
_DATA_COLUMN = re.compile(r"^(t|q\d|dq\d|tau\d|dir\d|theta\d|tau_cmd\d)$")


@dataclass(frozen=True)
class Table:
    """Columns read from ``path``; :attr:`row_lines` tells where each row stands in the file.

    Where rows stand is kept as runs of consecutive lines (``run_starts[k]`` is the first row of
    run ``k``, ``run_lines[k]`` its line), not one number per row: a file without blank lines is
    one run per block read. ``blocks`` holds groups of columns stored side by side
    (``("q1", ..., "q4")`` -> a C-contiguous ``(rows, 4)`` array); the group's entries in
    ``columns`` are views of it.
    """

    path: Path
    columns: dict[str, FloatArray]
    n_rows: int
    run_starts: np.ndarray
    run_lines: np.ndarray
    row_word: str  # "line" for CSV (1-based text line), "row" for npz/mat (1-based)
    blocks: dict[tuple[str, ...], FloatArray] = field(default_factory=dict)

    @property
    def row_lines(self) -> np.ndarray:
        """The line (CSV) or row (npz/mat) of every row, 1-based."""
        ends = np.append(self.run_starts[1:], self.n_rows)
        return np.concatenate(
            [
                np.arange(line, line + end - start)
                for start, end, line in zip(self.run_starts, ends, self.run_lines, strict=True)
            ]
            or [np.empty(0, dtype=np.int64)]
        )

    def line_of(self, row: int) -> int:
        """The line (CSV) or row (npz/mat) of row ``row`` (0-based), 1-based."""
        k = int(np.searchsorted(self.run_starts, row, side="right")) - 1
        return int(self.run_lines[k]) + row - int(self.run_starts[k])

    def where(self, row: int, column: str | None = None) -> str:
        """``"data.csv: line 17, column tau2"``, for error messages."""
        place = f"{self.path}: {self.row_word} {self.line_of(row)}"
        return place if column is None else f"{place}, column {column}"

    def matrix(self, names: tuple[str, ...]) -> FloatArray:
        """The columns ``names`` side by side, ``(rows, len(names))``, C-contiguous.

        A stored group is returned as it is (no copy: do not write to it); other columns are
        stacked into a new array.
        """
        block = self.blocks.get(tuple(names))
        if block is not None:
            return block
        return np.column_stack([self.columns[c] for c in names])


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise DataError(
            f"{path}: unsupported file type {suffix or '(none)'!r}; expected one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    return suffix


def _shown(text: str, limit: int = 40) -> str:
    """``text`` quoted for a message, cut to ``limit`` characters."""
    return repr(text if len(text) <= limit else text[: limit - 3] + "...")


def shown_names(names: list[str], limit: int = 10) -> str:
    """``names`` joined for a message, the first ``limit`` of them and how many there are."""
    shown = ", ".join(names[:limit])
    return shown if len(names) <= limit else f"{shown}, ... ({len(names):,} in all)"


def _open(path: Path) -> IO[bytes]:
    """Open a regular file for reading, checked by :func:`hal.files.regular_file` first.

    ``O_NONBLOCK`` and a second check on the open descriptor: a path swapped for a FIFO between
    the check and the open neither blocks nor gets read.
    """
    regular_file(path, DataError, DATA_MAX_BYTES, "data file")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise DataError(f"{path}: cannot read the data file ({exc.strerror})") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        regular_file(path, DataError, DATA_MAX_BYTES, "data file")  # names what it is now
        raise DataError(f"{path}: changed while it was opened; expected a regular file")
    os.set_blocking(fd, True)
    return os.fdopen(fd, "rb")


def read_table(path: Path | str) -> Table:
    """Read a CSV (header row, comma separated), ``.npz`` or ``.mat`` file of named columns.

    Raises:
        DataError: missing, not a regular file (directory, FIFO, device, ...), unreadable or too
            large; no header, ragged or non-numeric rows; columns of different lengths; or no data
            rows at all. The message names the file and, where there is one, the line or row and
            the column.
    """
    path = Path(path)
    regular_file(path, DataError, DATA_MAX_BYTES, "data file")
    suffix = _suffix(path)
    with _open(path) as handle:
        if suffix == ".csv":
            table = _CsvReader(path, handle).read()
        else:
            columns = _read_npz(path, handle) if suffix == ".npz" else _read_mat(path, handle)
            table = _table_of_columns(path, columns)
    if table.n_rows == 0:
        raise DataError(f"{path}: no data rows; expected at least one row of values under the header")
    return table


# --- CSV: the fast path ----------------------------------------------------------------------


def _powers_of_five() -> np.ndarray:
    """128-bit truncated powers of five 5^q, q in [-342, 308], as (high, low) uint64 pairs.

    The table of the Eisel-Lemire algorithm (D. Lemire, "Number parsing at a gigabyte per second",
    2021; the ``fast_float`` library's ``table_generation.py``), computed here in exact integers.
    """
    values = []
    for q in range(-342, 0):
        power5 = 5**-q
        z = (power5 - 1).bit_length()  # the least z with 2^z >= 5^-q
        if q >= -27:
            values.append(2 ** (z + 127) // power5 + 1)
        else:
            c = 2 ** (2 * z + 128) // power5 + 1
            while c >= 1 << 128:
                c //= 2
            values.append(c)
    for q in range(309):
        power5 = 5**q
        while power5 < 1 << 127:
            power5 *= 2
        while power5 >= 1 << 128:
            power5 //= 2
        values.append(power5)
    table = np.empty(2 * len(values), dtype=np.uint64)
    table[0::2] = [v >> 64 for v in values]
    table[1::2] = [v & ((1 << 64) - 1) for v in values]
    return table


_POW5 = _powers_of_five()
_P10 = np.array([10.0**k for k in range(23)])
_U0 = np.uint64(0)
_U1 = np.uint64(1)
_U10 = np.uint64(10)
_U32 = np.uint64(32)
_U52 = np.uint64(52)
_U63 = np.uint64(63)
_LOW32 = np.uint64(0xFFFFFFFF)
_TWO53 = np.uint64(1 << 53)
_SIGN = np.uint64(1 << 63)
_INFINITY = np.uint64(0x7FF << 52)


@njit(cache=True, inline="always")
def _multiply_128(a: np.uint64, b: np.uint64) -> tuple[np.uint64, np.uint64]:  # pragma: no cover (compiled)
    """The 128-bit product of two uint64 as (high, low)."""
    a_lo, a_hi, b_lo, b_hi = a & _LOW32, a >> _U32, b & _LOW32, b >> _U32
    p0, p1, p2, p3 = a_lo * b_lo, a_lo * b_hi, a_hi * b_lo, a_hi * b_hi
    middle = (p0 >> _U32) + (p1 & _LOW32) + (p2 & _LOW32)
    return p3 + (p1 >> _U32) + (p2 >> _U32) + (middle >> _U32), (p0 & _LOW32) | (middle << _U32)


@njit(cache=True)
def _decimal_to_bits(w: np.uint64, q: int, negative: bool) -> np.uint64:  # pragma: no cover (compiled)
    """IEEE-754 bits of ``(-1)^negative * w * 10^q`` rounded to nearest, ties to even; ``w < 10^19``.

    The Eisel-Lemire algorithm as in ``fast_float``'s ``compute_float`` (exact without a fallback
    for a significand of at most 19 digits: Mushtak and Lemire, "Fast number parsing without
    fallback", 2023).
    """
    sign = _SIGN if negative else _U0
    if w == _U0 or q < -342:
        return sign
    if q > 308:
        return sign | _INFINITY
    leading = 0
    while (w >> _U63) == _U0:
        w = w << _U1
        leading += 1
    index = 2 * (q + 342)
    high, low = _multiply_128(w, _POW5[index])
    if (high & np.uint64(0x1FF)) == np.uint64(0x1FF):
        high2, _ = _multiply_128(w, _POW5[index + 1])
        low = low + high2
        if high2 > low:
            high = high + _U1
    upper = np.int64(high >> _U63)
    shift = np.uint64(upper + 9)
    mantissa = high >> shift
    power2 = (((152170 + 65536) * q) >> 16) + 63 + upper - leading + 1023
    if power2 <= 0:  # subnormal
        if -power2 + 1 >= 64:
            return sign
        mantissa = mantissa >> np.uint64(-power2 + 1)
        mantissa = (mantissa + (mantissa & _U1)) >> _U1
        power2 = 0 if mantissa < (_U1 << _U52) else 1
        return sign | mantissa | (np.uint64(power2) << _U52)
    if low <= _U1 and -4 <= q <= 23 and (mantissa & np.uint64(3)) == _U1 and (mantissa << shift) == high:
        mantissa = mantissa & ~_U1  # exactly half way: round to even
    mantissa = (mantissa + (mantissa & _U1)) >> _U1
    if mantissa >= (np.uint64(2) << _U52):
        mantissa = _U1 << _U52
        power2 += 1
    mantissa = mantissa & ~(_U1 << _U52)
    if power2 >= 0x7FF:
        return sign | _INFINITY
    return sign | mantissa | (np.uint64(power2) << _U52)


@njit(cache=True)
def _parse_lines(
    buf: np.ndarray,
    pos: int,
    stop: int,
    n_columns: int,
    out: np.ndarray,
    out_bits: np.ndarray,
    lines: np.ndarray,
    row: int,
    line: int,
) -> tuple[int, int, int, bool]:  # pragma: no cover (compiled)
    """Parse lines of plain decimal numbers from ``buf[pos:stop]`` into ``out[row:]``.

    A line is ``n_columns`` numbers (``[+-]digits[.digits][e[+-]digits]``, at most 19 significant
    digits, spaces or tabs around them) separated by commas, ending in LF, CRLF or the end of
    ``stop``. ``out_bits`` is ``out`` viewed as uint64. Returns ``(row, pos, line, done)``: with
    ``done`` False, the line at ``pos`` (file line ``line``) is not such a line and is left to the
    careful parser; nothing of it counts.
    """
    n = stop
    while pos < n:
        p = pos
        for c in range(n_columns):
            while p < n and (buf[p] == 32 or buf[p] == 9):
                p += 1
            negative = False
            if p < n and (buf[p] == 43 or buf[p] == 45):
                negative = buf[p] == 45
                p += 1
            w = _U0
            digits = 0
            q = 0
            seen = False
            while p < n and 48 <= buf[p] <= 57:
                seen = True
                d = np.uint64(buf[p] - 48)
                if digits > 0 or d != _U0:
                    if digits == 19:
                        return row, pos, line, False
                    w = w * _U10 + d
                    digits += 1
                p += 1
            if p < n and buf[p] == 46:
                p += 1
                while p < n and 48 <= buf[p] <= 57:
                    seen = True
                    d = np.uint64(buf[p] - 48)
                    if digits > 0 or d != _U0:
                        if digits == 19:
                            return row, pos, line, False
                        w = w * _U10 + d
                        digits += 1
                    q -= 1
                    p += 1
            if not seen:
                return row, pos, line, False
            if p < n and (buf[p] == 101 or buf[p] == 69):
                p += 1
                negative_exponent = False
                if p < n and (buf[p] == 43 or buf[p] == 45):
                    negative_exponent = buf[p] == 45
                    p += 1
                if not (p < n and 48 <= buf[p] <= 57):
                    return row, pos, line, False
                e = 0
                while p < n and 48 <= buf[p] <= 57:
                    if e < 100000:
                        e = e * 10 + (buf[p] - 48)
                    p += 1
                q += -e if negative_exponent else e
            while p < n and (buf[p] == 32 or buf[p] == 9):
                p += 1
            if w != _U0 and w <= _TWO53 and -22 <= q <= 22:  # exact operands, one rounding (Clinger)
                value = float(w) * _P10[q] if q >= 0 else float(w) / _P10[-q]
                out[row, c] = -value if negative else value
            else:
                out_bits[row, c] = _decimal_to_bits(w, q, negative)
            if c + 1 < n_columns:
                if p >= n or buf[p] != 44:
                    return row, pos, line, False
                p += 1
        if p < n and buf[p] == 13:
            p += 1
        if p < n:
            if buf[p] != 10:
                return row, pos, line, False
            p += 1
        lines[row] = line
        row += 1
        line += 1
        pos = p
    return row, pos, line, True


# --- CSV: reading ----------------------------------------------------------------------------


def _blank(raw: bytes) -> bool:
    """A line of nothing but whitespace, commas and quotes (an empty row of a spreadsheet)."""
    return not raw.strip(b" \t\r\n,\"'")


class _CsvReader:
    """Two passes over a CSV file: count the lines, then read the header and the rows into
    preallocated columns. One buffer of whole lines is reused (no copy of a block, no growth of
    the heap): the fast parser reads it in place."""

    def __init__(self, path: Path, handle: IO[bytes]) -> None:
        self.path = path
        self.handle = handle
        self.size = os.fstat(handle.fileno()).st_size  # read no further: the file may grow
        self.buffer = bytearray(min(CHUNK_BYTES, max(self.size, 1)))
        self.names: list[str] = []
        self.n_rows = 0
        self.capacity = 0
        self.groups: list[tuple[tuple[str, ...], np.ndarray, np.ndarray]] = []  # names, column indices, storage
        self.rest_index = np.empty(0, dtype=np.intp)
        self.rest = np.empty((0, 0))
        self.run_starts: list[np.ndarray] = []
        self.run_lines: list[np.ndarray] = []
        self.scratch = np.empty((0, 0))
        self.scratch_lines = np.empty(0, dtype=np.int64)

    # -- file access

    def _read_into(self, start: int, limit: int) -> int:
        """Read up to ``limit`` bytes into the buffer at ``start``; the number read."""
        view = memoryview(self.buffer)[start : start + limit]
        try:
            return self.handle.readinto(view) or 0
        except OSError as exc:
            raise DataError(f"{self.path}: cannot read the data file ({exc.strerror})") from None
        finally:
            view.release()  # the buffer may grow only without views

    def _count_newlines(self) -> int:
        """Line ends in the file (the first pass), after refusing a file that is not text at all."""
        count, left = 0, self.size
        while left > 0:
            got = self._read_into(0, min(len(self.buffer), left))
            if got == 0:
                break
            if left == self.size:
                self._sniff(bytes(self.buffer[: min(got, 4096)]))
            count += self.buffer.count(b"\n", 0, got)
            left -= got
        self.handle.seek(0)
        return count

    def _blocks(self) -> Iterator[tuple[int, int]]:
        """``(number of the first line, end)``: ``self.buffer[:end]`` holds whole lines (the last one
        may lack its line end at the end of the file). Valid until the next iteration."""
        buffer = self.buffer
        line, filled, left = 1, 0, self.size
        while True:
            if left > 0:
                if filled == len(buffer):  # one line fills the buffer
                    if len(buffer) >= MAX_LINE_BYTES:
                        raise DataError(
                            f"{self.path}: line {line} is longer than {MAX_LINE_BYTES >> 20} MB; expected lines "
                            "of comma-separated values"
                        )
                    buffer.extend(bytes(min(len(buffer), MAX_LINE_BYTES - len(buffer))))
                got = self._read_into(filled, min(len(buffer) - filled, left))
                filled += got
                left = left - got if got else 0  # a file that shrank ends here
            at_end = left <= 0
            cut = filled if at_end else buffer.rfind(b"\n", 0, filled) + 1
            if cut > 0:
                yield line, cut
                line += buffer.count(b"\n", 0, cut)
                tail = filled - cut
                buffer[:tail] = buffer[cut:filled]
                filled = tail
            if at_end:
                return

    def _line_end(self, start: int, end: int) -> int:
        """Where the line at ``start`` ends (after its line end), within ``self.buffer[:end]``."""
        found = self.buffer.find(b"\n", start, end)
        return end if found < 0 else found + 1

    # -- the header

    def _sniff(self, start: bytes) -> None:
        """Refuse a file that is not text at all, saying what it looks like."""
        for magic, what in _MAGIC:
            if start.startswith(magic):
                raise DataError(
                    f"{self.path}: not a text file: this looks like {what}; expected comma-separated values "
                    "(UTF-8 text) with a header row"
                )
        head = start[:4096]
        if b"\x00" in head:
            raise DataError(
                f"{self.path}: not a text file (binary data: NUL bytes); expected comma-separated values with a header row"
            )

    def _decode(self, raw: bytes, line: int) -> str:
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            sample = raw[:1024]
            odd = sum(1 for b in sample if b >= 0x80 or (b < 0x20 and b not in (9, 10, 13)))
            if line == 1 and odd > 0.3 * len(sample):
                raise DataError(
                    f"{self.path}: not a text file (line 1 is binary data); expected comma-separated values "
                    "with a header row"
                ) from None
            raise DataError(
                f"{self.path}: line {line}: byte 0x{raw[exc.start]:02x} is not UTF-8 text; expected a UTF-8 text "
                "file (save it as 'CSV UTF-8')"
            ) from None
        if "\x00" in text:
            raise DataError(f"{self.path}: line {line}: a NUL byte; not a text file (expected comma-separated values)")
        text = text.rstrip("\r\n")
        if "\r" in text:
            raise DataError(
                f"{self.path}: line {line}: a carriage return (CR) inside the line; expected lines ending in LF "
                "or CRLF (old Mac line ends?)"
            )
        return text

    def _cells(self, text: str, line: int) -> list[str]:
        try:
            return next(csv.reader([text], strict=False), [])
        except csv.Error as exc:
            raise DataError(f"{self.path}: line {line}: cannot read CSV ({exc})") from None

    def _header(self, raw: bytes, line: int, next_raw: bytes | None) -> None:
        text = self._decode(raw, line)
        cells = self._cells(text, line)
        self._check_separator(text, cells, line, next_raw)
        names = [cell.strip() for cell in cells]
        for position, name in enumerate(names, start=1):
            if not name:
                raise DataError(f"{self.path}: line {line}: column {position} of the header has no name")
        numbers = [name for name in names if _is_float(name)]
        if numbers:
            raise DataError(
                f"{self.path}: line {line}: the first row holds numbers ({_shown(numbers[0])}); expected a header "
                "row of column names"
            )
        duplicates = sorted(name for name, count in Counter(names).items() if count > 1)
        if duplicates:
            raise DataError(f"{self.path}: line {line}: column name(s) {shown_names(duplicates)} appear more than once")
        by_case: dict[str, str] = {}
        for name in names:
            other = by_case.setdefault(name.casefold(), name)
            if other != name:
                raise DataError(
                    f"{self.path}: line {line}: columns {other} and {name} differ only in case; expected each "
                    "column once (names are case-sensitive: q1..q4, tau1..tau4, ...)"
                )
        self.names = names

    def _check_separator(self, text: str, cells: list[str], line: int, next_raw: bytes | None) -> None:
        """Refuse a header separated by something else than commas, saying what it looks like."""
        commas, semicolons, tabs = text.count(","), text.count(";"), text.count("\t")
        if semicolons > commas:
            kind = "semicolon"
        elif tabs > commas:
            kind = "tab"
        elif len(cells) == 1 and sum(1 for word in text.split() if _DATA_COLUMN.match(word)) >= 2:
            kind = "space"
        else:
            return
        hint = ""
        if next_raw is not None:
            following = next_raw.decode("utf-8", errors="replace").strip()
            match = re.search(r"(?<![\d.,])[+-]?\d+,\d+(?![\d,])", following)
            if match:
                hint = f", with a decimal point (line {line + 1} has decimal commas: {_shown(match.group(0))})"
        raise DataError(
            f"{self.path}: line {line}: the header looks {kind}-separated ({_shown(text)}); "
            f"expected comma-separated values{hint}"
        )

    def _allocate(self, capacity: int) -> None:
        names = self.names
        index = {name: c for c, name in enumerate(names)}
        grouped: set[str] = set()
        for group in STORAGE_GROUPS:
            if all(name in index for name in group):
                columns = np.array([index[name] for name in group], dtype=np.intp)
                self.groups.append((group, columns, np.empty((capacity, len(group)))))
                grouped.update(group)
        self.rest_index = np.array([c for c, name in enumerate(names) if name not in grouped], dtype=np.intp)
        self.rest = np.empty((capacity, self.rest_index.size))
        self.capacity = capacity

    # -- rows

    def _careful_row(self, raw: bytes, line: int) -> list[float] | None:
        """One line read with ``csv`` and ``float()``: its values, None for a blank line, or the error."""
        if _blank(raw):
            return None
        text = self._decode(raw, line)
        cells = self._cells(text, line)
        names = self.names
        if len(cells) != len(names):
            fields = f"{len(cells)} field" if len(cells) == 1 else f"{len(cells)} fields"
            raise DataError(
                f"{self.path}: line {line} has {fields}; the header has {len(names)}"
                + _ragged_hint(text, cells, len(names))
            )
        values = []
        for name, cell in zip(names, cells, strict=True):
            # float() alone would also take "1_000.5", "١٢" (other scripts' digits) and other whitespace
            if not _PLAIN_NUMBER.fullmatch(cell):
                raise DataError(f"{self.path}: line {line}, column {name}: {_not_a_number(cell)}")
            values.append(float(cell))
        return values

    def _scratch(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """A reused ``(k, columns)`` array for one block's rows, and one for their line numbers."""
        if self.scratch.shape[0] < k:
            self.scratch = np.empty((k, len(self.names)))
            self.scratch_lines = np.empty(k, dtype=np.int64)
        return self.scratch, self.scratch_lines

    def _rows(self, line: int, start: int, end: int) -> None:
        """Parse the whole lines in ``self.buffer[start:end]`` (the first is line ``line``) into the columns."""
        buffer = self.buffer
        k = buffer.count(b"\n", start, end) + (0 if buffer.endswith(b"\n", start, end) else 1)
        out, lines = self._scratch(k)
        bits = out.view(np.uint64)
        view = np.frombuffer(buffer, dtype=np.uint8)
        pos, row = start, 0
        try:
            while pos < end:
                row, pos, line, done = _parse_lines(view, pos, end, len(self.names), out, bits, lines, row, line)
                if done:
                    break
                stop = self._line_end(pos, end)
                values = self._careful_row(bytes(buffer[pos:stop]), line)
                if values is not None:
                    out[row] = values
                    lines[row] = line
                    row += 1
                pos, line = stop, line + 1
        finally:
            del view  # the buffer may grow again only without views
        first, last = self.n_rows, self.n_rows + row
        if last > self.capacity:
            raise DataError(f"{self.path}: the file changed while it was read; read it again when it is complete")
        for _, columns, storage in self.groups:
            np.take(out[:row], columns, axis=1, out=storage[first:last], mode="clip")
        if self.rest_index.size:
            np.take(out[:row], self.rest_index, axis=1, out=self.rest[first:last], mode="clip")
        if row:
            starts = np.flatnonzero(np.diff(lines[:row]) != 1) + 1
            starts = np.concatenate([[0], starts])
            self.run_starts.append(first + starts)
            self.run_lines.append(lines[starts])
        self.n_rows = last

    def _find_header(self, line: int, start: int, end: int) -> tuple[int, int]:
        """Read the header if it is in ``self.buffer[start:end]``: the line and position after it."""
        buffer = self.buffer
        while start < end and not self.names:
            stop = self._line_end(start, end)
            raw = bytes(buffer[start:stop])
            if not _blank(raw):
                following = self._line_end(stop, end) if stop < end else stop
                next_raw = bytes(buffer[stop:following]).rstrip(b"\r\n") if stop < end else None
                self._header(raw, line, next_raw)
            start, line = stop, line + 1
        return line, start

    def read(self) -> Table:
        """The table of the file.

        Raises:
            DataError: see :func:`read_table`.
        """
        newlines = self._count_newlines()
        for first_line, end in self._blocks():
            line, start = first_line, 0
            if not self.names:
                if first_line == 1 and self.buffer.startswith(_UTF8_BOM):  # "CSV UTF-8" of spreadsheets
                    start = len(_UTF8_BOM)
                line, start = self._find_header(line, start, end)
                if not self.names:
                    continue
                self._allocate(max(newlines + 2 - line, 0))  # the lines after the header's
            if start < end:
                self._rows(line, start, end)
        if not self.names:
            raise DataError(f"{self.path}: file is empty; expected a header row of column names, then data rows")
        n = self.n_rows
        columns: dict[str, FloatArray] = {}
        blocks: dict[tuple[str, ...], FloatArray] = {}
        for group, _, storage in self.groups:
            blocks[group] = storage[:n]
            for j, name in enumerate(group):
                columns[name] = blocks[group][:, j]
        for j, c in enumerate(self.rest_index):
            columns[self.names[c]] = self.rest[:n, j]
        ordered = {name: columns[name] for name in self.names}
        runs = (
            (np.concatenate(self.run_starts), np.concatenate(self.run_lines))
            if self.run_starts
            else (_NO_RUNS, _NO_RUNS)
        )
        return Table(self.path, ordered, n, *runs, "line", blocks)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _not_a_number(cell: str) -> str:
    """Why ``cell`` is not a number, and what was expected."""
    value = cell.strip()
    if _DECIMAL_COMMA.match(value):
        return f"{_shown(value)} looks like a decimal comma; expected a decimal point"
    if "_" in value and _is_float(value):
        return f"{_shown(value)} has a digit separator (_); expected a plain decimal number such as 1000.5"
    if _is_float(value):
        return f"{_shown(value)} is not a plain decimal number; expected ASCII digits 0-9, a decimal point, an exponent"
    if value.casefold() in _MISSING:
        return f"{_shown(value)} is not a number (a missing value); expected a finite number"
    return f"{_shown(value)} is not a number"


def _ragged_hint(text: str, cells: list[str], expected: int) -> str:
    """A reason for a wrong number of fields, when the line shows one."""
    for separator, kind in ((";", "semicolon"), ("\t", "tab")):
        if text.count(separator) >= max(expected - 1, 1) and len(cells) < expected:
            return f" (the line looks {kind}-separated; expected comma-separated values)"
    if len(cells) == 2 * expected and all(c.strip().isdigit() for c in cells[1::2]):
        return " (decimal commas split each number in two? expected a decimal point)"
    return ""


# --- npz and mat -----------------------------------------------------------------------------


def _table_of_columns(path: Path, columns: dict[str, FloatArray]) -> Table:
    """A table of equally long columns read from npz/mat, its groups stacked side by side."""
    if not columns:
        raise DataError(f"{path}: file holds no columns")
    lengths = {name: values.shape[0] for name, values in columns.items()}
    if len(set(lengths.values())) > 1:
        first = next(iter(lengths))
        odd = next(n for n, k in lengths.items() if k != lengths[first])
        raise DataError(
            f"{path}: column {odd} has {lengths[odd]} values but {first} has {lengths[first]}; columns must be equally long"
        )
    n = next(iter(lengths.values()))
    blocks: dict[tuple[str, ...], FloatArray] = {}
    for group in STORAGE_GROUPS:
        if all(name in columns for name in group):
            block = np.empty((n, len(group)))
            for j, name in enumerate(group):
                block[:, j] = columns[name]
                columns[name] = block[:, j]  # the original array is freed here
            blocks[group] = block
    return Table(path, columns, n, np.zeros(1, dtype=np.int64), np.ones(1, dtype=np.int64), "row", blocks)


def _check_dtype(path: Path, name: str, dtype: np.dtype) -> None:
    """Refuse a variable that does not hold real numbers, saying what it holds."""
    if dtype.hasobject:
        raise DataError(
            f"{path}: variable {name} holds Python objects (they would need pickle, which is not allowed); "
            "expected numbers"
        )
    if dtype.names is not None:
        raise DataError(f"{path}: variable {name} holds records (a structured array); expected a column of numbers")
    if dtype.kind == "c":
        raise DataError(f"{path}: variable {name} holds complex numbers; expected real numbers")
    if dtype.kind in "US":
        raise DataError(f"{path}: variable {name} holds text ({dtype.str}); expected numbers")
    if dtype.kind == "b":  # a mask or a flag, not a measurement: True would become 1.0 unseen
        raise DataError(f"{path}: variable {name} holds booleans (true/false); expected numbers")
    if dtype.kind not in "iuf":
        raise DataError(f"{path}: variable {name} holds {dtype} values; expected numbers")


def _as_column(path: Path, name: str, value: Any) -> FloatArray:
    """A 1-D float64 column of ``value`` (a 1-D array, or a matrix with one row or one column)."""
    if not isinstance(value, np.ndarray):
        kind = type(value).__name__
        raise DataError(f"{path}: variable {name} is a {kind}, not an array; expected a full numeric column vector")
    _check_dtype(path, name, value.dtype)
    array = value
    if array.ndim == 2 and 1 in array.shape:
        array = array.reshape(-1)
    if array.ndim != 1:
        raise DataError(f"{path}: variable {name} has shape {array.shape}; expected a column of values")
    return np.asarray(array, dtype=np.float64)


def _npy_header(path: Path, name: str, member: IO[bytes]) -> tuple[tuple[int, ...], bool, np.dtype]:
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(member)
    if version == (2, 0):
        return np.lib.format.read_array_header_2_0(member)
    raise DataError(f"{path}: variable {name} is a .npy array of format version {version}; expected 1.0 or 2.0")


def _read_npz(path: Path, handle: IO[bytes]) -> dict[str, FloatArray]:
    """The arrays of an ``.npz`` archive, each checked before a byte of its data is read.

    np.load is not used: it would take a single ``.npy`` array too, and it trusts the header's
    shape (a truncated or hostile member would allocate what the header claims).
    """
    if handle.read(4) not in (b"PK\x03\x04", b"PK\x05\x06"):
        raise DataError(f"{path}: not a readable .npz archive (no zip archive header)")
    handle.seek(0)
    columns: dict[str, FloatArray] = {}
    try:
        with zipfile.ZipFile(handle) as archive:
            members = archive.infolist()
            expanded = sum(m.file_size for m in members)
            if expanded > DATA_MAX_BYTES:
                raise DataError(
                    f"{path}: the archive expands to {expanded:,} bytes; a data file may have at most {DATA_MAX_BYTES:,}"
                )
            for member in members:
                if not member.filename.endswith(".npy"):
                    raise DataError(
                        f"{path}: member {_shown(member.filename)} is not a .npy array; expected one array per column"
                    )
                name = member.filename[: -len(".npy")]
                with archive.open(member) as stream:
                    shape, fortran, dtype = _npy_header(path, name, stream)
                    _check_dtype(path, name, dtype)
                    count = int(np.prod(shape, dtype=np.int64))
                    if count * dtype.itemsize > member.file_size:
                        raise DataError(
                            f"{path}: variable {name} is truncated (its header says {count:,} values of "
                            f"{dtype.itemsize} bytes, the archive holds fewer); expected a complete array"
                        )
                    buffer = bytearray(count * dtype.itemsize)
                    if stream.readinto(buffer) != len(buffer):
                        raise DataError(f"{path}: variable {name} is truncated; expected {count:,} values")
                array = np.frombuffer(buffer, dtype=dtype).reshape(shape, order="F" if fortran else "C")
                columns[name] = _as_column(path, name, array)
    except DataError:
        raise
    except (zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError, KeyError, NotImplementedError) as exc:
        raise DataError(f"{path}: not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    return columns


def _read_mat(path: Path, handle: IO[bytes]) -> dict[str, FloatArray]:
    import scipy.io  # here: only .mat files need it (and it costs 20 MB to import)

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # scipy warns about odd headers before it fails on them
            contents = scipy.io.loadmat(handle, squeeze_me=False)
    except NotImplementedError:
        raise DataError(f"{path}: MATLAB v7.3 (HDF5) files are not supported; save with -v7") from None
    except Exception as exc:  # scipy raises assorted types for corrupted files
        message = " ".join(str(exc).split())[:200]
        raise DataError(f"{path}: not a readable .mat file ({type(exc).__name__}: {message})") from None
    columns = {}
    for name, value in contents.items():
        if name.startswith("__"):
            continue
        if isinstance(value, np.ndarray) and value.dtype.names is not None:
            raise DataError(f"{path}: variable {name} is a MATLAB struct; expected a numeric column vector")
        if isinstance(value, np.ndarray) and value.dtype.hasobject:
            raise DataError(f"{path}: variable {name} is a MATLAB cell array; expected a numeric column vector")
        columns[name] = _as_column(path, name, value)
    return columns


def write_table(path: Path | str, columns: Mapping[str, np.ndarray]) -> None:
    """Write equally long columns to ``path`` (format by extension), atomically.

    Every format reads back bit for bit: a CSV cell is the shortest decimal that reads back as the
    same float64 (:func:`_write_csv`, D130), an ``.npz`` holds the arrays themselves, deflated
    (:func:`_write_npz`, D131), a ``.mat`` is compressed by scipy.

    Raises:
        DataError: unsupported extension or columns of different lengths.
    """
    path = Path(path)
    suffix = _suffix(path)
    arrays = {name: np.asarray(values, dtype=float).reshape(-1) for name, values in columns.items()}
    if len({a.shape[0] for a in arrays.values()}) > 1:
        raise DataError(f"{path}: refusing to write columns of different lengths")
    with atomic_path(path) as tmp:
        if suffix == ".csv":
            _write_csv(tmp, arrays)
        elif suffix == ".npz":
            _write_npz(tmp, arrays)
        else:
            import scipy.io

            scipy.io.savemat(tmp, {name: a.reshape(-1, 1) for name, a in arrays.items()}, do_compression=True)


#: Rows formatted at a time when writing a CSV (bounds the text held in memory to a few MB).
CSV_WRITE_ROWS = 8192
#: zlib level of the ``.npz`` files we write (D131): level 1 keeps 96 % of level 6's saving on a
#: session's raw log (126 MB -> 70 MB against 68 MB) at about half its CPU time.
NPZ_DEFLATE_LEVEL = 1
#: A column is deflated only when deflate shrinks samples of it below this share of their size
#: (D207): a noisy velocity or command column deflates only to 92-96 %, for 40 % of the CPU time.
NPZ_DEFLATE_BELOW = 0.9
#: Bytes of a column deflated to judge it, from each of its start, middle and end.
NPZ_SAMPLE_BYTES = 65536


def _write_csv(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """A header row, then one row per index: each value ``repr`` of its float, the shortest decimal that reads back as
    the same float64 (``0.3756``, not ``%.17g``'s ``0.37559999999999999``); D130."""
    matrix = np.column_stack(list(arrays.values())) if arrays else np.empty((0, 0))
    # One %-format of a whole block of rows: the per-row overhead of numpy.savetxt is the cost here.
    row = ",".join(["%r"] * matrix.shape[1]) + "\n"
    with open(path, "w", encoding="utf-8", newline="") as handle:
        handle.write(",".join(arrays) + "\n")
        for start in range(0, matrix.shape[0], CSV_WRITE_ROWS):
            block = matrix[start : start + CSV_WRITE_ROWS]
            handle.write((row * block.shape[0]) % tuple(block.ravel().tolist()))


def _write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """An ``.npz`` archive of ``arrays`` (one ``NAME.npy`` member each), deflated at :data:`NPZ_DEFLATE_LEVEL`.

    What ``numpy.savez_compressed`` writes, at another level, but a member that deflate barely
    shrinks (:func:`_deflates`) is stored: :func:`read_table` (and ``numpy.load``) read deflated
    and stored members alike.
    """
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=NPZ_DEFLATE_LEVEL) as archive:
        for name, values in arrays.items():
            values = np.ascontiguousarray(values)
            member_name = f"{name}.npy"
            member: str | zipfile.ZipInfo = member_name
            if not _deflates(values):
                member = zipfile.ZipInfo(member_name, date_time=time.localtime()[:6])
                member.compress_type = zipfile.ZIP_STORED
            with archive.open(member, "w", force_zip64=True) as handle:
                np.lib.format.write_array(handle, values, allow_pickle=False)


def _deflates(values: np.ndarray) -> bool:
    """Whether deflating ``values`` is worth its CPU: samples of its bytes shrink below :data:`NPZ_DEFLATE_BELOW`.

    Three samples of :data:`NPZ_SAMPLE_BYTES` (start, middle, end; the whole column when it is
    shorter), deflated at :data:`NPZ_DEFLATE_LEVEL`: a few milliseconds against the seconds a
    session's incompressible columns cost.
    """
    data = memoryview(values).cast("B")
    size = len(data)
    if size <= 3 * NPZ_SAMPLE_BYTES:
        samples = [data]
    else:
        middle = (size - NPZ_SAMPLE_BYTES) // 2
        samples = [data[:NPZ_SAMPLE_BYTES], data[middle : middle + NPZ_SAMPLE_BYTES], data[-NPZ_SAMPLE_BYTES:]]
    taken = sum(len(sample) for sample in samples)
    deflated = sum(len(zlib.compress(sample, NPZ_DEFLATE_LEVEL)) for sample in samples)
    return taken == 0 or deflated < NPZ_DEFLATE_BELOW * taken
