"""The two files a residual analysis reads, and the checks that they belong together.

Training and validation data must come from the same robot and carry the same columns: a
direction effect fitted on ``dir`` cannot be validated on a file without it, and a file with a
fifth joint's columns is another robot's data. Both are refused before anything is fitted.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from daror_runtime.data.load import dataset_from_table
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.stationary import ReductionSettings, reduce_to_stationary
from daror_runtime.data.tables import read_table, shown_names
from daror_runtime.errors import DataError
from daror_runtime.models.base import CompensationModel
from daror_runtime.residual.hysteresis import PointHistory, find_raw_log
from hal.robot import N_JOINTS, FloatArray

#: Fewer validation points than this give RMSE figures that mean little (and nRMSE peaks that
#: one point decides); the thesis validates on 166.
MIN_VALIDATION_POINTS = 20

_JOINT_COLUMN = re.compile(r"^(q|dq|tau|dir|theta|tau_cmd)(\d+)$")


@dataclass(frozen=True)
class ResidualInputs:
    """Training and validation data of one analysis, checked to belong together.

    ``*_history``: the path the joints took to each point (the hysteresis family's signal): the
    raw log of the run when there is one, else the points in their order.
    """

    train: StationaryDataset
    validate: StationaryDataset
    train_history: PointHistory | None = None
    validate_history: PointHistory | None = None
    #: What the report must say of a file whose signal map failed and was trusted (``--trust-signal-map``).
    signal_map_notes: tuple[str, ...] = ()

    @property
    def has_direction(self) -> bool:
        return self.train.direction is not None


def _extra_joints(columns: list[str]) -> list[str]:
    """Joint columns numbered beyond the DAROR-01's four (``q5``, ``tau6``, ...)."""
    extra = []
    for name in columns:
        match = _JOINT_COLUMN.match(name)
        if match and not 1 <= int(match.group(2)) <= N_JOINTS:
            extra.append(name)
    return extra


def read_residual_file(
    path: Path | str, reduction: ReductionSettings | None = None
) -> tuple[StationaryDataset, RawLog | None]:
    """Stationary points of ``path`` and, when the file is a raw log, that raw log (read once).

    A raw log is reduced to its stationary points (``reduction``; the points keep their ``t``),
    and is returned beside them: its samples are the joints' path to each point. A stationary
    dataset comes back with None.

    Raises:
        DataError: the file does not match the dataset contract, holds joints beyond 1-4, or a
            raw log holds no stationary point.
    """
    table = read_table(path)
    extra = _extra_joints(list(table.columns))
    if extra:
        raise DataError(
            f"{path}: column(s) {shown_names(extra)} belong to a robot with more than {N_JOINTS} joints; "
            f"expected DAROR-01 data with joints 1-{N_JOINTS}"
        )
    data = dataset_from_table(table)
    if isinstance(data, RawLog):
        return reduce_to_stationary(data, reduction), data
    return data, None


def check_pair(train: StationaryDataset, validate: StationaryDataset) -> ResidualInputs:
    """Refuse a training/validation pair that cannot be analysed together.

    Raises:
        DataError: a validation set smaller than :data:`MIN_VALIDATION_POINTS`, or ``dir``
            present in one file only (the message names both files).
    """
    if len(validate) < MIN_VALIDATION_POINTS:
        raise DataError(
            f"{validate.source}: {len(validate)} validation points; expected at least {MIN_VALIDATION_POINTS} "
            "for before/after figures that mean something"
        )
    if (train.direction is None) != (validate.direction is None):
        with_dir, without = (train, validate) if train.direction is not None else (validate, train)
        raise DataError(
            f"{without.source}: no dir1..dir4 columns, but {with_dir.source} has them; training and validation "
            "files must carry the same columns (record both with directions, or drop them from both)"
        )
    return ResidualInputs(train, validate)


def load_history(points: StationaryDataset, raw_path: Path | str | None) -> PointHistory:
    """The path to each point: from ``raw_path`` (a raw log of the same run), else from the points in order.

    Raises:
        DataError: ``raw_path`` is not a raw log, or not this run's (a point outside its time).
    """
    if raw_path is None:
        return PointHistory.from_points(points)
    raw = dataset_from_table(read_table(raw_path))
    if not isinstance(raw, RawLog):
        raise DataError(f"{raw_path}: a stationary dataset; expected the raw log (t, q, dq, tau at the loop's rate)")
    return PointHistory.from_raw(raw, points)


def _history(
    points: StationaryDataset, data_path: Path | str, own_raw: RawLog | None, given: Path | str | None
) -> PointHistory:
    """The path to ``points``: the raw log named by ``given``, else the data file's own (a raw log given
    as data), else the ``NAME.raw.*`` beside it, else the points in order.

    Raises:
        DataError: see :func:`load_history`.
    """
    if given is None and own_raw is not None:
        return PointHistory.from_raw(own_raw, points)
    return load_history(points, given if given is not None else find_raw_log(data_path))


def prediction_signal(
    model: CompensationModel, data: StationaryDataset, data_path: Path | str | None = None
) -> FloatArray | None:
    """The ``direction`` :meth:`CompensationModel.predict` needs on ``data`` to predict what the sensors read.

    The dataset's ``dir`` (the sign of each joint's last motion), unless the model's reading error
    depends on the joints' path (:meth:`CompensationModel.path_travel_rad`, the hysteresis): then
    its state at each point, along the raw log written beside ``data_path`` (``NAME.raw.*``), else
    along the points in their order, as ``daror residual`` computes it.

    Raises:
        DataError: the raw log beside ``data_path`` is not a raw log, or not this run's.
    """
    travel = model.path_travel_rad()
    if travel is None:
        return data.direction
    raw = find_raw_log(data_path) if data_path is not None else None
    return load_history(data, raw).states(travel)


def load_pair(
    train_path: Path | str,
    validate_path: Path | str,
    reduction: ReductionSettings | None = None,
    raw_paths: tuple[Path | str | None, Path | str | None] | None = None,
    judge: Callable[[StationaryDataset | RawLog], str | None] | None = None,
) -> ResidualInputs:
    """Load and check the training and validation files of an analysis, with the joints' paths.

    ``raw_paths``: the raw logs of the training and validation runs. None for either: a data
    file that is itself a raw log is its own path; else the ``NAME.raw.*`` file beside its
    dataset when there is one; else the points in order. An explicit raw log always wins.

    ``judge``: the signal map's check of each file as read (its raw log when it is one): raises
    when the map fails, returns what the report must say of a trusted file (None: nothing).

    Raises:
        DataError: see :func:`read_residual_file`, :func:`check_pair` and :func:`load_history`;
            ``judge``'s SignalMapError.
    """
    train, train_raw = read_residual_file(train_path, reduction)
    validate, validate_raw = read_residual_file(validate_path, reduction)
    notes: list[str] = []
    if judge is not None:
        for points, raw in ((train, train_raw), (validate, validate_raw)):
            note = judge(raw if raw is not None else points)
            if note is not None:
                notes.append(note)
    pair = check_pair(train, validate)
    given = raw_paths or (None, None)
    return ResidualInputs(
        pair.train,
        pair.validate,
        _history(pair.train, train_path, train_raw, given[0]),
        _history(pair.validate, validate_path, validate_raw, given[1]),
        tuple(notes),
    )
