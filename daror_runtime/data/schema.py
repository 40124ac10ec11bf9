"""Dataset contracts (docs/data.md). SI units: rad, rad/s, Nm, s. Joints numbered 1-4.

* Raw log: ``t, q1..q4, dq1..dq4, tau1..tau4`` (+ optional ``theta1..4``, ``tau_cmd1..4``); without
  ``dq`` when the data show a log (the velocity is then derived from ``t`` and ``q``).
* Stationary dataset: ``q1..q4, tau1..tau4`` (+ optional ``dir1..dir4``, ``t``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hal.robot import N_JOINTS, FloatArray


def joint_columns(prefix: str) -> tuple[str, ...]:
    """``('q1', 'q2', 'q3', 'q4')`` for prefix ``'q'``."""
    return tuple(f"{prefix}{j}" for j in range(1, N_JOINTS + 1))


Q_COLUMNS = joint_columns("q")
DQ_COLUMNS = joint_columns("dq")
TAU_COLUMNS = joint_columns("tau")
DIR_COLUMNS = joint_columns("dir")
THETA_COLUMNS = joint_columns("theta")
TAU_CMD_COLUMNS = joint_columns("tau_cmd")

STATIONARY_REQUIRED = Q_COLUMNS + TAU_COLUMNS
RAW_REQUIRED = ("t", *Q_COLUMNS, *DQ_COLUMNS, *TAU_COLUMNS)
#: A raw log whose velocity is derived from ``t`` and ``q`` (docs/data.md, "Raw log without dq").
RAW_WITHOUT_VELOCITY_REQUIRED = ("t", *Q_COLUMNS, *TAU_COLUMNS)
#: Columns whose values are joint angles in radians (checked for "looks like degrees").
ANGLE_COLUMNS = Q_COLUMNS + THETA_COLUMNS
#: Columns a table keeps side by side in one (rows, k) array, so a dataset takes them without a copy.
STORAGE_GROUPS: tuple[tuple[str, ...], ...] = (
    ("t",),
    Q_COLUMNS,
    DQ_COLUMNS,
    TAU_COLUMNS,
    DIR_COLUMNS,
    THETA_COLUMNS,
    TAU_CMD_COLUMNS,
)

# Plausible ranges: a value beyond is refused with its file, line and column (docs/data.md says why
# each bound is where it is). They are far outside anything the DAROR-01 can produce, so they only
# catch wrong units, wrong columns and corrupted numbers, never a real reading.

#: |q|, |theta| (rad): no joint of the DAROR-01 turns a full circle, so more is degrees.
MAX_ANGLE_RAD = 2 * np.pi
#: |dq| (rad/s): the joints' own limits are a few rad/s; a human arm peaks near 20 rad/s.
MAX_VELOCITY_RAD_S = 50.0
#: |tau|, |tau_cmd| (Nm): the drives give at most 40 Nm, the springs' end stop is near 35 Nm.
MAX_TORQUE_NM = 500.0
#: |t| (s): 116 days; a session's robot clock never runs that long (more is a Unix time or ms/us).
MAX_TIME_S = 1e7
#: A raw log is sampled at the loop rate: its median time step lies in this range (s): 10 Hz-100 kHz.
RAW_STEP_S = (1e-5, 0.1)


@dataclass(frozen=True)
class StationaryDataset:
    """Joint angles and joint torques at points where the robot stood still.

    ``direction`` holds the sign (-1, 0, +1) of each joint's last motion before the stop, when
    known; ``t_s`` the robot time of each point, when known.
    """

    q_rad: FloatArray
    tau_nm: FloatArray
    direction: FloatArray | None = None
    t_s: FloatArray | None = None
    source: str = field(default="<memory>", compare=False)

    def __len__(self) -> int:
        return int(self.q_rad.shape[0])

    def subset(self, index: np.ndarray | slice) -> StationaryDataset:
        """The points selected by ``index`` (a mask, indices or a slice)."""
        return StationaryDataset(
            q_rad=self.q_rad[index],
            tau_nm=self.tau_nm[index],
            direction=None if self.direction is None else self.direction[index],
            t_s=None if self.t_s is None else self.t_s[index],
            source=self.source,
        )

    def to_columns(self) -> dict[str, FloatArray]:
        """Named columns in file order (``t`` first when present)."""
        columns: dict[str, FloatArray] = {}
        if self.t_s is not None:
            columns["t"] = self.t_s
        columns.update(zip(Q_COLUMNS, self.q_rad.T, strict=True))
        columns.update(zip(TAU_COLUMNS, self.tau_nm.T, strict=True))
        if self.direction is not None:
            columns.update(zip(DIR_COLUMNS, self.direction.T, strict=True))
        return columns


@dataclass(frozen=True)
class RawLog:
    """Everything logged at the loop rate during a run."""

    t_s: FloatArray
    q_rad: FloatArray
    dq_rad_s: FloatArray
    tau_nm: FloatArray
    theta_rad: FloatArray | None = None
    tau_cmd_nm: FloatArray | None = None
    source: str = field(default="<memory>", compare=False)
    #: True when the file had no ``dq`` columns and ``dq_rad_s`` was derived from ``t`` and ``q``.
    velocity_derived: bool = field(default=False, compare=False)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def to_columns(self) -> dict[str, FloatArray]:
        columns: dict[str, FloatArray] = {"t": self.t_s}
        columns.update(zip(Q_COLUMNS, self.q_rad.T, strict=True))
        columns.update(zip(DQ_COLUMNS, self.dq_rad_s.T, strict=True))
        columns.update(zip(TAU_COLUMNS, self.tau_nm.T, strict=True))
        if self.theta_rad is not None:
            columns.update(zip(THETA_COLUMNS, self.theta_rad.T, strict=True))
        if self.tau_cmd_nm is not None:
            columns.update(zip(TAU_CMD_COLUMNS, self.tau_cmd_nm.T, strict=True))
        return columns
