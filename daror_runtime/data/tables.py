"""Named numeric columns in CSV, ``.npz`` and MATLAB ``.mat`` files.

A table is a set of equally long float columns with names. Reading reports every problem with
the file, the line (CSV) or row (npz/mat) and the column; writing is atomic.
"""

from __future__ import annotations

import csv
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io

from daror_runtime.errors import DataError
from daror_runtime.util.atomic import atomic_path
from hal.robot import FloatArray

SUPPORTED_SUFFIXES = (".csv", ".npz", ".mat")


@dataclass(frozen=True)
class Table:
    """Columns read from ``path``; ``row_lines[i]`` is where row ``i`` stands in the file."""

    path: Path
    columns: dict[str, FloatArray]
    row_lines: np.ndarray
    row_word: str  # "line" for CSV (1-based text line), "row" for npz/mat (1-based)

    @property
    def n_rows(self) -> int:
        return int(self.row_lines.shape[0])

    def where(self, row: int, column: str | None = None) -> str:
        """``"data.csv: line 17, column tau2"``, for error messages."""
        place = f"{self.path}: {self.row_word} {int(self.row_lines[row])}"
        return place if column is None else f"{place}, column {column}"


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise DataError(
            f"{path}: unsupported file type {suffix or '(none)'!r}; expected one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    return suffix


def read_table(path: Path | str) -> Table:
    """Read a CSV (header row, comma separated), ``.npz`` or ``.mat`` file of named columns.

    Raises:
        DataError: missing or unreadable file, no header, ragged or non-numeric rows, columns of
            different lengths, or no data rows at all.
    """
    path = Path(path)
    suffix = _suffix(path)
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    if suffix == ".csv":
        table = _read_csv(path)
    else:
        columns = _read_npz(path) if suffix == ".npz" else _read_mat(path)
        lengths = {name: values.shape[0] for name, values in columns.items()}
        if not columns:
            raise DataError(f"{path}: file holds no columns")
        if len(set(lengths.values())) > 1:
            first = next(iter(lengths))
            odd = next(n for n, k in lengths.items() if k != lengths[first])
            raise DataError(
                f"{path}: column {odd} has {lengths[odd]} values but {first} has {lengths[first]}; columns must be equally long"
            )
        n = next(iter(lengths.values()))
        table = Table(path, columns, np.arange(1, n + 1), "row")
    if table.n_rows == 0:
        raise DataError(f"{path}: no data rows; expected at least one row of values under the header")
    return table


def _read_csv(path: Path) -> Table:
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:  # -sig: spreadsheets add a BOM
            rows = list(csv.reader(handle))
    except UnicodeDecodeError:
        raise DataError(f"{path}: not a text file; expected comma-separated values with a header row") from None
    except (OSError, csv.Error) as exc:
        raise DataError(f"{path}: cannot read CSV ({exc})") from None
    numbered = [(i, row) for i, row in enumerate(rows, start=1) if row and any(cell.strip() for cell in row)]
    if not numbered:
        raise DataError(f"{path}: file is empty; expected a header row of column names, then data rows")
    header_line, header = numbered[0]
    names = [cell.strip() for cell in header]
    for position, name in enumerate(names, start=1):
        if not name:
            raise DataError(f"{path}: line {header_line}: column {position} of the header has no name")
        try:
            float(name)
        except ValueError:
            pass
        else:
            raise DataError(
                f"{path}: line {header_line}: the first row holds numbers ({name!r}); expected a header row of column names"
            )
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise DataError(f"{path}: line {header_line}: column name(s) {', '.join(duplicates)} appear more than once")
    body = numbered[1:]
    values = np.empty((len(body), len(names)))
    for r, (line, row) in enumerate(body):
        if len(row) != len(names):
            raise DataError(f"{path}: line {line} has {len(row)} fields; the header has {len(names)}")
        for c, cell in enumerate(row):
            try:
                values[r, c] = float(cell)
            except ValueError:
                raise DataError(f"{path}: line {line}, column {names[c]}: {cell.strip()!r} is not a number") from None
    columns = {name: values[:, c].copy() for c, name in enumerate(names)}
    return Table(path, columns, np.array([line for line, _ in body], dtype=int), "line")


def _as_column(path: Path, name: str, value: np.ndarray) -> FloatArray:
    array = np.asarray(value)
    if array.ndim == 2 and 1 in array.shape:
        array = array.reshape(-1)
    if array.ndim != 1:
        raise DataError(f"{path}: variable {name} has shape {array.shape}; expected a column of values")
    if not np.issubdtype(array.dtype, np.number) and array.dtype != bool:
        raise DataError(f"{path}: variable {name} holds {array.dtype} values; expected numbers")
    return array.astype(float)


def _read_npz(path: Path) -> dict[str, FloatArray]:
    try:
        with open(path, "rb") as handle:  # np.load would also take a .npy array or try to unpickle
            if handle.read(4) not in (b"PK\x03\x04", b"PK\x05\x06"):
                raise zipfile.BadZipFile("no zip archive header")
        with np.load(path, allow_pickle=False) as archive:
            return {name: _as_column(path, name, archive[name]) for name in archive.files}
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise DataError(f"{path}: not a readable .npz archive ({exc})") from None
    except ValueError as exc:  # object arrays refuse to load without pickle
        raise DataError(f"{path}: cannot read .npz ({exc}); expected numeric arrays") from None


def _read_mat(path: Path) -> dict[str, FloatArray]:
    try:
        contents = scipy.io.loadmat(path, squeeze_me=False)
    except NotImplementedError:
        raise DataError(f"{path}: MATLAB v7.3 (HDF5) files are not supported; save with -v7") from None
    except Exception as exc:  # scipy raises assorted types for corrupted files
        raise DataError(f"{path}: not a readable .mat file ({type(exc).__name__}: {exc})") from None
    return {name: _as_column(path, name, value) for name, value in contents.items() if not name.startswith("__")}


def write_table(path: Path | str, columns: Mapping[str, np.ndarray]) -> None:
    """Write equally long columns to ``path`` (format by extension), atomically.

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
            matrix = np.column_stack(list(arrays.values())) if arrays else np.empty((0, 0))
            np.savetxt(tmp, matrix, delimiter=",", header=",".join(arrays), comments="", fmt="%.17g")
        elif suffix == ".npz":
            with open(tmp, "wb") as handle:
                np.savez(handle, **arrays)
        else:
            scipy.io.savemat(tmp, {name: a.reshape(-1, 1) for name, a in arrays.items()}, do_compression=True)
