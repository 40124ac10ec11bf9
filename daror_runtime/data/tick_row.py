"""The row the control loop records every tick: its column names and indices, defined once.

One row of :data:`RECORD_COLUMNS` per tick (docs/recorder.md)::

    t | q1..q4 | dq1..dq4 | tau1..tau4 | theta1..theta4 | tau_cmd1..tau_cmd4 | enable | faulted | lateness_s
    0   1..4     5..8       9..12        13..16           17..20               21       22        23

The first 21 columns are the raw-log columns of :mod:`daror_runtime.data.schema`, named as a raw
log names them, so :func:`daror_runtime.data.recording_reader.recording_to_raw_log` reads a loop
recording by name. Units: s, rad, rad/s, Nm (``tau`` the measured spring torque, ``tau_cmd`` the
motor torque the controller asked for, whether or not the drives were enabled); ``enable`` and
``faulted`` are 0 or 1; ``lateness_s`` is how long after its deadline the tick started.

The loop fills a row with :func:`fill_tick_row_at` straight into the recorder's block
(``Recorder.push_into``; compiled, no allocation, no copy) or, for a recorder without
``push_into``, into a row of its own (a (1, N) view of it); code that reads a loop
row in memory (a ``Recording`` that takes the recorder's place) uses the index constants here,
never literal numbers. The constants are plain integers in this file on purpose: the compiled
fill bakes them in when it is compiled, and numba's cache is refreshed only when this file
changes, so they must not come from another module. :data:`RECORD_COLUMNS` is built from them and
the raw-log names when the module is imported, and refused if the indices leave a gap or overlap.
"""

from __future__ import annotations

from numba import njit

from daror_runtime.data.schema import DQ_COLUMNS, Q_COLUMNS, TAU_CMD_COLUMNS, TAU_COLUMNS, THETA_COLUMNS
from daror_runtime.errors import ConfigurationError
from hal.robot import N_JOINTS, FloatArray

__all__ = [
    "DQ_INDEX",
    "DQ_SLICE",
    "ENABLE_INDEX",
    "FAULTED_INDEX",
    "LATENESS_INDEX",
    "N_RECORD_COLUMNS",
    "Q_INDEX",
    "Q_SLICE",
    "RECORD_COLUMNS",
    "TAU_CMD_INDEX",
    "TAU_CMD_SLICE",
    "TAU_INDEX",
    "TAU_SLICE",
    "THETA_INDEX",
    "THETA_SLICE",
    "T_INDEX",
    "fill_tick_row_at",
]

#: Robot time of the sample (s); the last known time when the tick had no reading.
T_INDEX = 0
#: First of the four link angles q1..q4 (rad).
Q_INDEX = 1
#: First of the four link velocities dq1..dq4 (rad/s).
DQ_INDEX = 5
#: First of the four measured spring torques tau1..tau4 (Nm).
TAU_INDEX = 9
#: First of the four motor angles theta1..theta4 (rad).
THETA_INDEX = 13
#: First of the four commanded motor torques tau_cmd1..tau_cmd4 (Nm).
TAU_CMD_INDEX = 17
#: 1 when the command written enabled the drives, else 0.
ENABLE_INDEX = 21
#: 1 when a fault was latched after the tick's safety filter, else 0.
FAULTED_INDEX = 22
#: Lateness of the tick's start after its deadline (s): a 20 ms stall records ~0.02.
LATENESS_INDEX = 23
#: Values per row.
N_RECORD_COLUMNS = 24

#: The four joints' columns of each group, for readers of a row in memory.
Q_SLICE = slice(Q_INDEX, Q_INDEX + N_JOINTS)
DQ_SLICE = slice(DQ_INDEX, DQ_INDEX + N_JOINTS)
TAU_SLICE = slice(TAU_INDEX, TAU_INDEX + N_JOINTS)
THETA_SLICE = slice(THETA_INDEX, THETA_INDEX + N_JOINTS)
TAU_CMD_SLICE = slice(TAU_CMD_INDEX, TAU_CMD_INDEX + N_JOINTS)


def _record_columns() -> tuple[str, ...]:
    """The column names, placed at the indices above.

    Raises:
        ConfigurationError: the indices leave a gap or put two names on one column (an edit of
            this file broke the layout; the loop must not record a row nobody can read).
    """
    placed: dict[int, str] = {}
    groups = (
        (T_INDEX, ("t",)),
        (Q_INDEX, Q_COLUMNS),
        (DQ_INDEX, DQ_COLUMNS),
        (TAU_INDEX, TAU_COLUMNS),
        (THETA_INDEX, THETA_COLUMNS),
        (TAU_CMD_INDEX, TAU_CMD_COLUMNS),
        (ENABLE_INDEX, ("enable",)),
        (FAULTED_INDEX, ("faulted",)),
        (LATENESS_INDEX, ("lateness_s",)),
    )
    for start, names in groups:
        for offset, name in enumerate(names):
            index = start + offset
            if index in placed:
                raise ConfigurationError(f"tick row layout: {name} and {placed[index]} both at column {index}")
            placed[index] = name
    if sorted(placed) != list(range(N_RECORD_COLUMNS)):
        raise ConfigurationError(f"tick row layout: the columns do not fill 0..{N_RECORD_COLUMNS - 1} exactly")
    return tuple(placed[i] for i in range(N_RECORD_COLUMNS))


#: Column names of the loop's recording, in row order (``t, q1..4, dq1..4, tau1..4, theta1..4,
#: tau_cmd1..4, enable, faulted, lateness_s``).
RECORD_COLUMNS: tuple[str, ...] = _record_columns()


@njit(cache=True)
def fill_tick_row_at(
    rows: FloatArray,
    index: int,
    t_s: float,
    q_rad: FloatArray,
    dq_rad_s: FloatArray,
    tau_nm: FloatArray,
    theta_rad: FloatArray,
    tau_cmd_nm: FloatArray,
    enable: float,
    faulted: float,
    lateness_s: float,
) -> None:  # pragma: no cover - compiled
    """Write one tick into row ``index`` of ``rows`` (n, :data:`N_RECORD_COLUMNS`), in :data:`RECORD_COLUMNS` order.

    ``rows`` is a recorder's block (``Recorder.push_into``) or any 2-D array. Compiled, no
    allocation, copies only (no arithmetic): it runs every tick. The joint arrays are (4,) in rad,
    rad/s, Nm; ``enable`` and ``faulted`` 0.0 or 1.0; ``lateness_s`` in s; a tick without a
    reading passes NaN vectors for the sample's arrays. Nothing is
    checked (numba does not check bounds): the caller guarantees ``0 <= index < n`` and that
    ``rows`` has :data:`N_RECORD_COLUMNS` columns (``Recorder.push_into`` checks the count).
    """
    rows[index, T_INDEX] = t_s
    for j in range(4):
        rows[index, Q_INDEX + j] = q_rad[j]
        rows[index, DQ_INDEX + j] = dq_rad_s[j]
        rows[index, TAU_INDEX + j] = tau_nm[j]
        rows[index, THETA_INDEX + j] = theta_rad[j]
        rows[index, TAU_CMD_INDEX + j] = tau_cmd_nm[j]
    rows[index, ENABLE_INDEX] = enable
    rows[index, FAULTED_INDEX] = faulted
    rows[index, LATENESS_INDEX] = lateness_s
