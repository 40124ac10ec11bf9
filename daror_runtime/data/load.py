"""Read and write datasets, checking every contract of DESIGN.md section 5 on the way in.

Every command that takes data accepts a stationary dataset or a raw log; a raw log (it has ``t``
and ``dq1..dq4``) is reduced to stationary points first. A file that does not match is refused
with a message naming the file, the line or column, and what was expected.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from daror_runtime.data.schema import (
    ANGLE_COLUMNS,
    DIR_COLUMNS,
    DQ_COLUMNS,
    Q_COLUMNS,
    RAW_REQUIRED,
    STATIONARY_REQUIRED,
    TAU_CMD_COLUMNS,
    TAU_COLUMNS,
    THETA_COLUMNS,
    RawLog,
    StationaryDataset,
)
from daror_runtime.data.stationary import ReductionSettings, reduce_to_stationary
from daror_runtime.data.tables import Table, read_table, write_table
from daror_runtime.errors import DataError

#: A joint angle beyond this is not radians: no joint of the DAROR-01 turns a full circle.
MAX_PLAUSIBLE_ANGLE_RAD = 2 * np.pi


def is_raw_log(table: Table) -> bool:
    """A table is a raw log when it has ``t`` and every ``dq`` column."""
    return "t" in table.columns and all(c in table.columns for c in DQ_COLUMNS)


def _require(table: Table, required: tuple[str, ...], kind: str) -> None:
    missing = [c for c in required if c not in table.columns]
    if missing:
        raise DataError(
            f"{table.path}: missing column(s) {', '.join(missing)}; a {kind} needs {', '.join(required)} "
            f"(found {', '.join(table.columns) or 'none'})"
        )


def _optional_group(table: Table, group: tuple[str, ...]) -> tuple[str, ...] | None:
    present = [c for c in group if c in table.columns]
    if not present:
        return None
    if len(present) != len(group):
        missing = [c for c in group if c not in table.columns]
        raise DataError(
            f"{table.path}: has {', '.join(present)} but not {', '.join(missing)}; give all four joints or none"
        )
    return group


#: Where a value stands, for messages: (row index, column name) -> "file: line L, column C".
Locator = Callable[[int, str], str]


def check_finite(matrix: np.ndarray, names: tuple[str, ...], where: Locator) -> None:
    """Refuse a NaN or infinity, naming its place."""
    if np.isfinite(matrix).all():  # the common case without a boolean matrix per check
        return
    row, col = np.argwhere(~np.isfinite(matrix))[0]
    value = matrix[row, col]
    word = "NaN" if np.isnan(value) else "an infinite value"
    raise DataError(f"{where(int(row), names[col])}: {word}; expected a finite number")


def check_radians(matrix: np.ndarray, names: tuple[str, ...], where: Locator) -> None:
    """Refuse angles beyond 2 pi (degrees handed in as radians)."""
    if np.abs(matrix).max(initial=0.0) <= MAX_PLAUSIBLE_ANGLE_RAD:
        return
    row, col = np.argwhere(np.abs(matrix) > MAX_PLAUSIBLE_ANGLE_RAD)[0]
    raise DataError(
        f"{where(int(row), names[col])}: angle {matrix[row, col]:g} is beyond 2 pi; "
        "angles must be in radians (this looks like degrees)"
    )


def check_increasing(t: np.ndarray, where: Locator) -> None:
    """Refuse time that stands still or goes back."""
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        row = int(back[0]) + 1
        raise DataError(
            f"{where(row, 't')}: time {t[row]:g} s does not come after {t[row - 1]:g} s; expected increasing time"
        )


def check_raw_log(raw: RawLog, where: Locator) -> None:
    """Every raw-log contract check (DESIGN.md section 5) on arrays already assembled.

    Raises:
        DataError: a non-finite value, an angle beyond 2 pi, or time not increasing.
    """
    check_finite(raw.t_s[:, None], ("t",), where)
    check_increasing(raw.t_s, where)
    groups = [(raw.q_rad, Q_COLUMNS, True), (raw.dq_rad_s, DQ_COLUMNS, False), (raw.tau_nm, TAU_COLUMNS, False)]
    if raw.theta_rad is not None:
        groups.append((raw.theta_rad, THETA_COLUMNS, True))
    if raw.tau_cmd_nm is not None:
        groups.append((raw.tau_cmd_nm, TAU_CMD_COLUMNS, False))
    for matrix, names, angles in groups:
        check_finite(matrix, names, where)
        if angles:
            check_radians(matrix, names, where)


def _matrix(table: Table, names: tuple[str, ...]) -> np.ndarray:
    matrix = np.column_stack([table.columns[c] for c in names])
    check_finite(matrix, names, table.where)
    return matrix


def _check_radians(table: Table, names: tuple[str, ...], matrix: np.ndarray) -> None:
    if names[0] in ANGLE_COLUMNS:
        check_radians(matrix, names, table.where)


def _angles(table: Table, names: tuple[str, ...]) -> np.ndarray:
    matrix = _matrix(table, names)
    _check_radians(table, names, matrix)
    return matrix


def _directions(table: Table) -> np.ndarray | None:
    if _optional_group(table, DIR_COLUMNS) is None:
        return None
    matrix = _matrix(table, DIR_COLUMNS)
    bad = ~np.isin(matrix, (-1.0, 0.0, 1.0))
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise DataError(f"{table.where(int(row), DIR_COLUMNS[col])}: {matrix[row, col]:g}; expected -1, 0 or +1")
    return matrix


def _time(table: Table, strictly_increasing: bool) -> np.ndarray | None:
    if "t" not in table.columns:
        return None
    t = _matrix(table, ("t",))[:, 0]
    if strictly_increasing:
        check_increasing(t, table.where)
    return t


def stationary_from_table(table: Table) -> StationaryDataset:
    """Validate a table as a stationary dataset."""
    _require(table, STATIONARY_REQUIRED, "stationary dataset")
    return StationaryDataset(
        q_rad=_angles(table, Q_COLUMNS),
        tau_nm=_matrix(table, TAU_COLUMNS),
        direction=_directions(table),
        t_s=_time(table, strictly_increasing=False),
        source=str(table.path),
    )


def raw_from_table(table: Table) -> RawLog:
    """Validate a table as a raw log."""
    _require(table, RAW_REQUIRED, "raw log")
    theta = _optional_group(table, THETA_COLUMNS)
    tau_cmd = _optional_group(table, TAU_CMD_COLUMNS)
    return RawLog(
        t_s=_time(table, strictly_increasing=True),
        q_rad=_angles(table, Q_COLUMNS),
        dq_rad_s=_matrix(table, DQ_COLUMNS),
        tau_nm=_matrix(table, TAU_COLUMNS),
        theta_rad=None if theta is None else _angles(table, theta),
        tau_cmd_nm=None if tau_cmd is None else _matrix(table, tau_cmd),
        source=str(table.path),
    )


def load_dataset(path: Path | str) -> StationaryDataset | RawLog:
    """Read a file as whichever of the two dataset kinds it is.

    Raises:
        DataError: the file does not match either contract.
    """
    return dataset_from_table(read_table(path))


def dataset_from_table(table: Table) -> StationaryDataset | RawLog:
    """Validate a table as whichever of the two dataset kinds it is.

    Raises:
        DataError: the table does not match either contract.
    """
    if "t" in table.columns:
        # t with only some dq columns is a raw log that lost a column, not a stationary dataset
        # whose every (moving) sample would count as a stationary point: refuse it.
        _optional_group(table, DQ_COLUMNS)
    return raw_from_table(table) if is_raw_log(table) else stationary_from_table(table)


def load_stationary(path: Path | str, reduction: ReductionSettings | None = None) -> StationaryDataset:
    """Read stationary points from a stationary dataset, or from a raw log by reducing it.

    Raises:
        DataError: the file does not match, or a raw log holds no stationary points.
    """
    data = load_dataset(path)
    return reduce_to_stationary(data, reduction) if isinstance(data, RawLog) else data


def write_dataset(path: Path | str, data: StationaryDataset | RawLog) -> None:
    """Write a dataset atomically; the format follows the extension (.csv, .npz, .mat)."""
    write_table(path, data.to_columns())


def raw_log_path(stationary_path: Path | str) -> Path:
    """Where the raw log beside a stationary dataset goes: ``FILE`` with ``.raw`` before the extension."""
    path = Path(stationary_path)
    return path.with_name(f"{path.stem}.raw{path.suffix}")
