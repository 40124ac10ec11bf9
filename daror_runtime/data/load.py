"""Read and write datasets, checking every contract of docs/data.md on the way in.

Every command that takes data accepts a stationary dataset or a raw log; a raw log (it has ``t``
and ``dq1..dq4``, or ``t`` and joints that move between samples: docs/data.md) is reduced to
stationary points first. A file that does not match is refused with a message naming the file,
the line or row and the column, and what was expected; every column kind has a plausible range
(``daror_runtime.data.schema``), so a wrong unit or a corrupted number is refused where it stands
instead of overflowing in a fit.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import structlog

from daror_runtime.data.schema import (
    DIR_COLUMNS,
    DQ_COLUMNS,
    MAX_ANGLE_RAD,
    MAX_TIME_S,
    MAX_TORQUE_NM,
    MAX_VELOCITY_RAD_S,
    Q_COLUMNS,
    RAW_REQUIRED,
    RAW_STEP_S,
    RAW_WITHOUT_VELOCITY_REQUIRED,
    STATIONARY_REQUIRED,
    TAU_CMD_COLUMNS,
    TAU_COLUMNS,
    THETA_COLUMNS,
    RawLog,
    StationaryDataset,
)
from daror_runtime.data.stationary import ReductionSettings, reduce_to_stationary
from daror_runtime.data.tables import Table, read_table, shown_names, write_table
from daror_runtime.errors import DataError

if TYPE_CHECKING:
    from daror_runtime.data.signal_map import SignalMapReport
    from hal.robot import RobotDescription

log = structlog.get_logger(__name__)

#: A joint angle beyond this is not radians: no joint of the DAROR-01 turns a full circle.
MAX_PLAUSIBLE_ANGLE_RAD = MAX_ANGLE_RAD

# Telling a raw log without dq columns from a stationary dataset with t (docs/data.md).
#: A log is sampled at the loop rate: a median time step below this (s) is 10 Hz or faster.
LOG_STEP_S = 0.1
#: Within a stretch of regular sampling the joints of a log move more than this (rad); the repeated
#: readings of one stop in a stationary dataset stay within the encoders' noise (1e-4 rad).
LOG_MOVE_RAD = 0.05
#: Consecutive samples of a log differ by less than this (rad): 2 rad/s at 100 Hz.
LOG_SMALL_STEP_RAD = 0.02
#: A stretch of a log holds at least this many samples (fewer could not be filtered and reduced).
LOG_MIN_SAMPLES = 20


def is_raw_log(table: Table) -> bool:
    """A table is a raw log by its columns when it has ``t`` and every ``dq`` column."""
    return "t" in table.columns and all(c in table.columns for c in DQ_COLUMNS)


def _require(table: Table, required: tuple[str, ...], kind: str) -> None:
    missing = [c for c in required if c not in table.columns]
    if missing:
        found = list(table.columns)
        by_case = {name.casefold(): name for name in found}
        spelled = [f"{by_case[m.casefold()]} for {m}" for m in missing if m.casefold() in by_case]
        hint = f"; column names are case-sensitive (found {', '.join(spelled[:4])})" if spelled else ""
        raise DataError(
            f"{table.path}: missing column(s) {', '.join(missing)}; a {kind} needs {', '.join(required)} "
            f"(found {shown_names(found, 20) or 'none'}){hint}"
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
    """Refuse a NaN or infinity, naming its place.

    Raises:
        DataError: the first (by row) value that is not finite.
    """
    if np.isfinite(matrix).all():  # the common case without a boolean matrix per check
        return
    row, col = np.argwhere(~np.isfinite(matrix))[0]
    value = matrix[row, col]
    word = "NaN" if np.isnan(value) else "an infinite value"
    raise DataError(f"{where(int(row), names[col])}: {word}; expected a finite number")


def check_range(
    matrix: np.ndarray, names: tuple[str, ...], where: Locator, limit: float, describe: Callable[[float], str]
) -> None:
    """Refuse a value beyond ``-limit..limit``; ``describe(value)`` says what it is and what was expected.

    Raises:
        DataError: the first (by row) value out of range, with its place.
    """
    if matrix.size == 0 or (matrix.max() <= limit and matrix.min() >= -limit):  # no temporary array
        return
    beyond = np.argwhere(np.abs(matrix) > limit)
    if beyond.size == 0:  # a NaN made max() NaN: check_finite's to name, not this
        return
    row, col = beyond[0]
    raise DataError(f"{where(int(row), names[col])}: {describe(float(matrix[row, col]))}")


def _angle_message(value: float) -> str:
    if abs(value) <= 1000.0:
        return f"angle {value:g} is beyond 2 pi; angles must be in radians (this looks like degrees)"
    return f"angle {value:g} is beyond 2 pi; expected an angle in radians, -2 pi..2 pi"


def _velocity_message(value: float) -> str:
    unit = " (in deg/s?)" if abs(value) <= MAX_VELOCITY_RAD_S * 180 / np.pi else ""
    return (
        f"velocity {value:g} rad/s is beyond the plausible range -{MAX_VELOCITY_RAD_S:g}..{MAX_VELOCITY_RAD_S:g} "
        f"rad/s; expected a joint velocity in rad/s{unit}"
    )


def _torque_message(value: float) -> str:
    return (
        f"torque {value:g} Nm is beyond the plausible range -{MAX_TORQUE_NM:g}..{MAX_TORQUE_NM:g} Nm; expected a "
        "joint torque in Nm (the DAROR-01's drives give at most 40 Nm)"
    )


def _time_message(value: float) -> str:
    if 1e8 <= abs(value) < 1e10:
        hint = " (this looks like a Unix time)"
    elif 1e11 <= abs(value) < 1e13:
        hint = " (this looks like a Unix time in milliseconds)"
    else:
        hint = ""
    return (
        f"time {value:g} s is beyond the plausible range -{MAX_TIME_S:g}..{MAX_TIME_S:g} s (116 days); expected "
        f"the robot's time in seconds{hint}"
    )


def check_increasing(t: np.ndarray, where: Locator) -> None:
    """Refuse time that stands still or goes back.

    Raises:
        DataError: the first sample whose time does not come after the one before.
    """
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        row = int(back[0]) + 1
        raise DataError(
            f"{where(row, 't')}: time {t[row]:g} s does not come after {t[row - 1]:g} s; expected increasing time"
        )


def check_sample_steps(t: np.ndarray, source: str) -> None:
    """Refuse a raw log whose median time step is not that of a loop (10 Hz to 100 kHz, in seconds).

    Raises:
        DataError: the steps look like milliseconds or microseconds, or are too long or too short.
    """
    if t.shape[0] < 2:
        return
    step = float(np.median(np.diff(t)))
    low, high = RAW_STEP_S
    if low * (1 - 1e-6) <= step <= high * (1 + 1e-6):  # 1.1 - 1.0 is 0.10000000000000009
        return
    if 0.5 <= step <= 100.0:
        problem = f"column t looks like milliseconds (steps of {step:g}); expected seconds"
    elif 100.0 < step <= 1e5:
        problem = f"column t looks like microseconds (steps of {step:g}); expected seconds"
    elif step > high:
        problem = (
            f"column t has steps of {step:g} s ({1 / step:.3g} Hz); a raw log is sampled at the loop rate: "
            f"expected steps of at most {high:g} s"
        )
    else:
        problem = f"column t has steps of {step:g} s ({1 / step:.3g} Hz); expected steps of at least {low:g} s (is t in seconds?)"
    raise DataError(f"{source}: {problem}")


def check_time(t: np.ndarray, where: Locator, raw_log: bool, source: str) -> None:
    """Every check of a ``t`` column: finite and plausible; for a raw log also increasing at a loop's rate.

    Raises:
        DataError: see :func:`check_finite`, :func:`check_increasing`, :func:`check_sample_steps`.
    """
    column = t[:, None]
    check_finite(column, ("t",), where)
    if raw_log:
        check_increasing(t, where)
        check_sample_steps(t, source)
    check_range(column, ("t",), where, MAX_TIME_S, _time_message)


def check_raw_log(raw: RawLog, where: Locator) -> None:
    """Every raw-log contract check (docs/data.md) on arrays already assembled.

    Raises:
        DataError: a non-finite value, time not increasing or not at a loop's rate, or a value
            beyond its column's plausible range (an angle beyond 2 pi, ...).
    """
    check_time(raw.t_s, where, raw_log=True, source=raw.source)
    groups = [(raw.q_rad, Q_COLUMNS), (raw.dq_rad_s, DQ_COLUMNS), (raw.tau_nm, TAU_COLUMNS)]
    if raw.theta_rad is not None:
        groups.append((raw.theta_rad, THETA_COLUMNS))
    if raw.tau_cmd_nm is not None:
        groups.append((raw.tau_cmd_nm, TAU_CMD_COLUMNS))
    for matrix, names in groups:
        _check_group(matrix, names, where)


_LIMITS: dict[str, tuple[float, Callable[[float], str]]] = {
    "q": (MAX_ANGLE_RAD, _angle_message),
    "theta": (MAX_ANGLE_RAD, _angle_message),
    "dq": (MAX_VELOCITY_RAD_S, _velocity_message),
    "tau": (MAX_TORQUE_NM, _torque_message),
    "tau_cmd": (MAX_TORQUE_NM, _torque_message),
}


def _check_group(matrix: np.ndarray, names: tuple[str, ...], where: Locator) -> None:
    check_finite(matrix, names, where)
    limit, describe = _LIMITS[names[0].rstrip("0123456789")]
    check_range(matrix, names, where, limit, describe)


def _group(table: Table, names: tuple[str, ...]) -> np.ndarray:
    """A joint group's ``(rows, 4)`` values, finite and within the group's plausible range."""
    matrix = table.matrix(names)
    _check_group(matrix, names, table.where)
    return matrix


def _directions(table: Table) -> np.ndarray | None:
    if _optional_group(table, DIR_COLUMNS) is None:
        return None
    matrix = table.matrix(DIR_COLUMNS)
    check_finite(matrix, DIR_COLUMNS, table.where)
    if not ((matrix == 0.0) | (matrix == 1.0) | (matrix == -1.0)).all():
        row, col = np.argwhere((matrix != 0.0) & (matrix != 1.0) & (matrix != -1.0))[0]
        raise DataError(f"{table.where(int(row), DIR_COLUMNS[col])}: {matrix[row, col]:g}; expected -1, 0 or +1")
    return matrix


def _time(table: Table, raw_log: bool) -> np.ndarray | None:
    if "t" not in table.columns:
        return None
    t = table.matrix(("t",))[:, 0]
    check_time(t, table.where, raw_log, str(table.path))
    return t


def derive_velocity(t: np.ndarray, q: np.ndarray, where: Locator) -> np.ndarray:
    """Joint velocity (rad/s, ``(N, 4)``) from time (s, strictly increasing) and angles (rad).

    Central differences inside, one-sided at the ends (``np.gradient``); the reduction's low-pass
    filter then removes the encoders' quantisation noise as it does from a logged velocity.

    Raises:
        DataError: a joint moves faster than the plausible velocity between two samples (a jump in
            the encoder reading, or a wrong time column), named by the later sample.
    """
    dt = np.diff(t)
    for j, name in enumerate(Q_COLUMNS):
        step = np.diff(q[:, j])
        fast = np.flatnonzero(np.abs(step) > MAX_VELOCITY_RAD_S * dt)
        if fast.size:
            i = int(fast[0])
            raise DataError(
                f"{where(i + 1, name)}: the joint moves {step[i]:g} rad in {dt[i]:g} s ({step[i] / dt[i]:g} rad/s) "
                f"since the previous sample; expected at most {MAX_VELOCITY_RAD_S:g} rad/s (this log has no dq "
                "columns: its velocity is derived from t and q)"
            )
    return np.gradient(q, t, axis=0)


def stationary_from_table(table: Table) -> StationaryDataset:
    """Validate a table as a stationary dataset.

    Raises:
        DataError: a missing column, a partial joint group, or a value that is not finite or
            beyond its column's plausible range (file, line or row, column and the range named).
    """
    _require(table, STATIONARY_REQUIRED, "stationary dataset")
    return StationaryDataset(
        q_rad=_group(table, Q_COLUMNS),
        tau_nm=_group(table, TAU_COLUMNS),
        direction=_directions(table),
        t_s=_time(table, raw_log=False),
        source=str(table.path),
    )


def raw_from_table(table: Table) -> RawLog:
    """Validate a table as a raw log; without ``dq`` columns the velocity is derived from ``t`` and ``q``.

    Raises:
        DataError: a missing column, a partial joint group, time that is not increasing or not at
            a loop's rate (e.g. milliseconds), or a value that is not finite or beyond its
            column's plausible range.
    """
    derived = not any(c in table.columns for c in DQ_COLUMNS)
    _require(table, RAW_WITHOUT_VELOCITY_REQUIRED if derived else RAW_REQUIRED, "raw log")
    theta = _optional_group(table, THETA_COLUMNS)
    tau_cmd = _optional_group(table, TAU_CMD_COLUMNS)
    t = table.matrix(("t",))[:, 0]
    check_time(t, table.where, raw_log=True, source=str(table.path))
    q = _group(table, Q_COLUMNS)
    if derived:
        dq = derive_velocity(t, q, table.where)
        log.info("raw log without dq columns: velocity derived from t and q", path=str(table.path), samples=len(t))
    else:
        dq = _group(table, DQ_COLUMNS)
    return RawLog(
        t_s=t,
        q_rad=q,
        dq_rad_s=dq,
        tau_nm=_group(table, TAU_COLUMNS),
        theta_rad=None if theta is None else _group(table, theta),
        tau_cmd_nm=None if tau_cmd is None else _group(table, tau_cmd),
        source=str(table.path),
        velocity_derived=derived,
    )


def _largest_stretch_travel(q: np.ndarray, joined: np.ndarray) -> float:
    """The largest range (rad) of any joint over a stretch of rows joined by ``joined`` steps.

    ``joined[i]`` joins rows ``i`` and ``i + 1``; a stretch is a maximal run of joined rows, and
    counts only with at least :data:`LOG_MIN_SAMPLES` rows.
    """
    if not joined.any():
        return 0.0
    in_stretch = np.zeros(q.shape[0], dtype=bool)
    in_stretch[:-1] |= joined
    in_stretch[1:] |= joined
    starts = in_stretch & ~np.concatenate([[False], joined])
    rows = np.flatnonzero(in_stretch)
    boundaries = np.flatnonzero(starts[rows])
    long_enough = np.diff(np.append(boundaries, rows.size)) >= LOG_MIN_SAMPLES
    if not long_enough.any():
        return 0.0
    travel = 0.0
    for j in range(q.shape[1]):
        values = q[rows, j]
        spread = np.maximum.reduceat(values, boundaries) - np.minimum.reduceat(values, boundaries)
        travel = max(travel, float(spread[long_enough].max()))
    return travel


def _is_log_without_velocity(table: Table) -> bool:
    """A table with ``t`` but no ``dq`` columns is a raw log when the data show one (docs/data.md).

    A log: sampled at 10 Hz or faster (median time step below :data:`LOG_STEP_S`) while the joints
    move more than :data:`LOG_MOVE_RAD` within a stretch of at least :data:`LOG_MIN_SAMPLES`
    regularly sampled rows (steps of at most twice the median). A stationary dataset's repeated
    readings of one stop do not move, and its stops are seconds apart. ``dir`` columns belong to
    stationary datasets only.

    Raises:
        DataError: slower steps, but the joints move in small steps between rows over a stretch, as a
            log whose time is not in seconds would (e.g. milliseconds): neither kind can be assumed.
    """
    columns = table.columns
    if any(c not in columns for c in STATIONARY_REQUIRED) or any(c in columns for c in DIR_COLUMNS):
        return False
    t = table.matrix(("t",))[:, 0]
    q = table.matrix(Q_COLUMNS)
    if t.shape[0] < 3 or not (np.isfinite(t).all() and np.isfinite(q).all()):
        return False  # too short to be a log; or a bad value the dataset's own checks will name
    dt = np.diff(t)
    positive = dt[dt > 0]
    if positive.size < 2:
        return False
    median = float(np.median(positive))
    regular = (dt > 0) & (dt <= 2 * median)
    if median < LOG_STEP_S:
        return _largest_stretch_travel(q, regular) > LOG_MOVE_RAD
    step = np.zeros(dt.shape[0])
    for j in range(q.shape[1]):
        np.maximum(step, np.abs(np.diff(q[:, j])), out=step)
    if _largest_stretch_travel(q, regular & (step <= LOG_SMALL_STEP_RAD)) <= LOG_MOVE_RAD:
        return False
    if 0.5 <= median <= 100.0:
        raise DataError(
            f"{table.path}: column t looks like milliseconds (steps of {median:g}); expected seconds (the rows "
            "look like a log: the joints move in small steps from row to row)"
        )
    raise DataError(
        f"{table.path}: column t has steps of {median:g} s, but the joints move in small steps from row to row "
        "like a log's; expected a log sampled at 10 Hz or faster (t in seconds), or a stationary dataset with "
        "dir1..dir4"
    )


def load_dataset(path: Path | str) -> StationaryDataset | RawLog:
    """Read a file as whichever of the two dataset kinds it is.

    Raises:
        DataError: the file does not match either contract.
    """
    return dataset_from_table(read_table(path))


def dataset_from_table(table: Table) -> StationaryDataset | RawLog:
    """Validate a table as whichever of the two dataset kinds it is.

    A table with ``t`` and all four ``dq`` is a raw log; with ``t`` and no ``dq`` it is a raw log
    when its data show one (:func:`_is_log_without_velocity`), never fitted sample by sample.

    Raises:
        DataError: the table does not match either contract, or cannot be told apart.
    """
    # t with only some dq columns is a raw log that lost a column, not a stationary dataset whose
    # every (moving) sample would count as a stationary point: _optional_group refuses it.
    try:
        if "t" in table.columns and _optional_group(table, DQ_COLUMNS) is None and _is_log_without_velocity(table):
            return raw_from_table(table)
        return raw_from_table(table) if is_raw_log(table) else stationary_from_table(table)
    except DataError as exc:
        mix_up = _mix_up_of_refused(table)
        if mix_up is None:
            raise
        from daror_runtime.data.signal_map import SignalMapError

        raise SignalMapError(f"{exc}; the signal map looks wrong: most likely {mix_up}") from exc


#: A dataset's joint groups by the field they fill (:class:`RawLog`, :class:`StationaryDataset`).
_FIELDS = {
    "q_rad": Q_COLUMNS,
    "dq_rad_s": DQ_COLUMNS,
    "tau_nm": TAU_COLUMNS,
    "theta_rad": THETA_COLUMNS,
    "tau_cmd_nm": TAU_CMD_COLUMNS,
}


def _mix_up_of_refused(table: Table) -> str | None:
    """For a table refused for its values: the exchange or shift of its columns that explains it (issue 27).

    Only when every column the kinds need is there and finite (a missing column or a NaN is its own
    error) and a remap puts every value in its range with the springs, the command, the velocity and
    the A Priori torque consistent (:func:`daror_runtime.data.signal_map.explain_refused_groups`).
    """
    names = {field: group for field, group in _FIELDS.items() if all(c in table.columns for c in group)}
    if "q_rad" not in names or "tau_nm" not in names:
        return None
    groups = {field: table.matrix(group) for field, group in names.items()}
    if groups["q_rad"].shape[0] < 3 or not all(np.isfinite(values).all() for values in groups.values()):
        return None
    t_s = table.matrix(("t",))[:, 0] if "t" in table.columns and "dq_rad_s" in names else None
    if t_s is not None and not (np.isfinite(t_s).all() and np.all(np.diff(t_s) > 0)):
        return None
    if t_s is None:  # a stationary dataset: what its kind holds
        groups = {field: groups[field] for field in ("q_rad", "tau_nm")}
    # here: the check is needed only for a refused file; the robot is the packaged one (a hint only)
    from daror_runtime.data.signal_map import explain_refused_groups
    from hal.robot import load_description

    def in_range(field: str, values: np.ndarray) -> bool:
        limit, _ = _LIMITS[_FIELDS[field][0].rstrip("0123456789")]
        return bool(np.abs(values).max() <= limit)

    return explain_refused_groups(groups, t_s, in_range, load_description())


def load_stationary(path: Path | str, reduction: ReductionSettings | None = None) -> StationaryDataset:
    """Read stationary points from a stationary dataset, or from a raw log by reducing it.

    Raises:
        DataError: the file does not match, or a raw log holds no stationary points.
    """
    data = load_dataset(path)
    return reduce_to_stationary(data, reduction) if isinstance(data, RawLog) else data


def load_stationary_checked(
    path: Path | str,
    description: RobotDescription,
    dummy_arm: bool = False,
    trust_signal_map: bool = False,
    remedy: str = "--trust-signal-map accepts the file anyway",
) -> tuple[StationaryDataset, SignalMapReport]:
    """:func:`load_stationary` with the file's signal map judged from physics first (issue 27).

    A raw log is judged on its own samples (the springs, the command, the velocity, the A Priori
    torque), then reduced; a stationary dataset on its points (the A Priori torque). ``dummy_arm``:
    the Dummy Arm was installed. ``trust_signal_map``: a failed map is accepted (the report says so).
    ``remedy``: what a refusal tells the user to do (a caller without the flag names its own rule).

    Raises:
        DataError: the file does not match, or a raw log holds no stationary points.
        SignalMapError: the columns are not what their names say, and the user did not trust the file.
    """
    from daror_runtime.data.signal_map import require_signal_map

    data = load_dataset(path)
    # the file's own contract first (a log with no stationary point says so), then its physics
    points = reduce_to_stationary(data) if isinstance(data, RawLog) else data
    return points, require_signal_map(data, description, dummy_arm=dummy_arm, trust=trust_signal_map, remedy=remedy)


def write_dataset(path: Path | str, data: StationaryDataset | RawLog) -> None:
    """Write a dataset atomically; the format follows the extension (.csv, .npz, .mat)."""
    write_table(path, data.to_columns())


#: The raw log's format when nobody asks for another: binary, exact, and written 20x faster than
#: CSV (752,282 ticks x 17 columns: 0.3 s and 102 MB against 6.7 s and 291 MB).
RAW_LOG_SUFFIX = ".npz"


def raw_log_path(stationary_path: Path | str, suffix: str | None = None) -> Path:
    """Where the raw log beside a stationary dataset goes: ``.raw`` before the extension.

    ``suffix`` (``.npz``, ``.csv``, ``.mat``) replaces the dataset's own extension: ``train.csv``
    with ``.npz`` gives ``train.raw.npz``; None keeps it (``train.raw.csv``).
    """
    path = Path(stationary_path)
    return path.with_name(f"{path.stem}.raw{path.suffix if suffix is None else suffix}")
