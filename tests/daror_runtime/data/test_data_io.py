"""Dataset files: exact round trips, atomic writes, and bad input refused with file, line and column.

The contracts are those of ``daror_runtime/data/schema.py``; every refusal is a
:class:`daror_runtime.errors.DataError` whose message names the file and, where there is one, the
line (CSV, 1-based text line) or row (npz/mat, 1-based) and the column.
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from daror_runtime.data import tables
from daror_runtime.data.load import load_dataset, load_stationary, raw_log_path, write_dataset
from daror_runtime.data.schema import MAX_TIME_S, MAX_TORQUE_NM, MAX_VELOCITY_RAD_S, RawLog, StationaryDataset
from daror_runtime.data.tables import read_table, write_table
from daror_runtime.errors import DarorError, DataError, InputError

FORMATS = (".csv", ".npz", ".mat")
STATIONARY_HEADER = "q1,q2,q3,q4,tau1,tau2,tau3,tau4"
RAW_HEADER = "t,q1,q2,q3,q4,dq1,dq2,dq3,dq4,tau1,tau2,tau3,tau4"


# --- helpers -------------------------------------------------------------------------------


def assert_bitwise_equal(actual: np.ndarray | None, expected: np.ndarray | None, what: str) -> None:
    """Same presence, shape and IEEE-754 bits (so -0.0 and subnormals count too)."""
    if expected is None:
        assert actual is None, f"{what}: expected no column, got {actual!r}"
        return
    assert actual is not None, f"{what}: column missing after the round trip"
    actual = np.asarray(actual)
    expected = np.asarray(expected, dtype=float)
    assert actual.dtype == np.float64, what
    assert actual.shape == expected.shape, f"{what}: shape {actual.shape} != {expected.shape}"
    assert np.array_equal(actual.view(np.int64), expected.view(np.int64)), f"{what}: values differ"


def assert_same_stationary(actual: object, expected: StationaryDataset) -> None:
    assert isinstance(actual, StationaryDataset)
    assert_bitwise_equal(actual.q_rad, expected.q_rad, "q")
    assert_bitwise_equal(actual.tau_nm, expected.tau_nm, "tau")
    assert_bitwise_equal(actual.direction, expected.direction, "dir")
    assert_bitwise_equal(actual.t_s, expected.t_s, "t")


def assert_same_raw(actual: object, expected: RawLog) -> None:
    assert isinstance(actual, RawLog)
    assert_bitwise_equal(actual.t_s, expected.t_s, "t")
    assert_bitwise_equal(actual.q_rad, expected.q_rad, "q")
    assert_bitwise_equal(actual.dq_rad_s, expected.dq_rad_s, "dq")
    assert_bitwise_equal(actual.tau_nm, expected.tau_nm, "tau")
    assert_bitwise_equal(actual.theta_rad, expected.theta_rad, "theta")
    assert_bitwise_equal(actual.tau_cmd_nm, expected.tau_cmd_nm, "tau_cmd")


def stationary_sample(n: int = 25, with_dir: bool = True, with_t: bool = True, seed: int = 7) -> StationaryDataset:
    rng = np.random.default_rng(seed)
    return StationaryDataset(
        q_rad=rng.uniform(-3.0, 3.0, (n, 4)),
        tau_nm=rng.normal(0.0, 5.0, (n, 4)),
        direction=rng.choice([-1.0, 0.0, 1.0], (n, 4)) if with_dir else None,
        t_s=np.cumsum(rng.uniform(0.5, 2.0, n)) if with_t else None,
    )


def raw_sample(n: int = 40, with_theta: bool = True, with_tau_cmd: bool = True, seed: int = 11) -> RawLog:
    rng = np.random.default_rng(seed)
    q = rng.uniform(-3.0, 3.0, (n, 4))
    return RawLog(
        t_s=np.arange(n) * 0.001 + 12.5,
        q_rad=q,
        dq_rad_s=rng.normal(0.0, 0.3, (n, 4)),
        tau_nm=rng.normal(0.0, 5.0, (n, 4)),
        theta_rad=q + rng.normal(0.0, 0.01, (n, 4)) if with_theta else None,
        tau_cmd_nm=rng.normal(0.0, 5.0, (n, 4)) if with_tau_cmd else None,
    )


def csv_rows(header: str, rows: list[list[object]]) -> str:
    return header + "\n" + "".join(",".join(str(v) for v in row) + "\n" for row in rows)


def good_stationary_rows(n: int = 5) -> list[list[object]]:
    """Plausible rows: angles well inside +-2 pi, torques of a few Nm."""
    return [[0.1 * i, -0.2, 0.3, 1.0 + 0.01 * i, 1.5, -2.5, 0.75, 0.125 * i] for i in range(n)]


def write_text(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def refusal(path: Path) -> str:
    """The message of the DataError that ``load_dataset(path)`` raises."""
    with pytest.raises(DataError) as caught:
        load_dataset(path)
    message = str(caught.value)
    assert str(path) in message, f"message does not name the file: {message}"
    assert "\n" not in message, f"message is not one line: {message!r}"
    return message


# --- round trips ---------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", FORMATS)
@pytest.mark.parametrize(("with_dir", "with_t"), [(True, True), (True, False), (False, True), (False, False)])
def test_stationary_round_trip_is_exact(tmp_path: Path, suffix: str, with_dir: bool, with_t: bool) -> None:
    data = stationary_sample(with_dir=with_dir, with_t=with_t)
    path = tmp_path / f"stationary{suffix}"
    write_dataset(path, data)
    back = load_dataset(path)
    assert_same_stationary(back, data)
    assert back.source == str(path)
    assert len(back) == 25


@pytest.mark.parametrize("suffix", FORMATS)
@pytest.mark.parametrize(("with_theta", "with_tau_cmd"), [(True, True), (True, False), (False, True), (False, False)])
def test_raw_log_round_trip_is_exact(tmp_path: Path, suffix: str, with_theta: bool, with_tau_cmd: bool) -> None:
    raw = raw_sample(with_theta=with_theta, with_tau_cmd=with_tau_cmd)
    path = tmp_path / f"raw{suffix}"
    write_dataset(path, raw)
    back = load_dataset(path)
    assert_same_raw(back, raw)
    assert back.source == str(path)


def test_csv_layout_is_header_then_rows_in_file_order(tmp_path: Path) -> None:
    data = StationaryDataset(
        q_rad=np.array([[0.1, 0.2, 0.3, 0.4]]),
        tau_nm=np.array([[1.0, -2.0, 3.5, 0.0]]),
        direction=np.array([[1.0, -1.0, 0.0, 1.0]]),
        t_s=np.array([2.0]),
    )
    path = tmp_path / "one.csv"
    write_dataset(path, data)
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[0] == "t,q1,q2,q3,q4,tau1,tau2,tau3,tau4,dir1,dir2,dir3,dir4"
    expected = "2 0.1 0.2 0.3 0.4 1 -2 3.5 0 1 -1 0 1"
    assert [float(v) for v in lines[1].split(",")] == [float(v) for v in expected.split()]
    assert len(lines) == 2


_angles = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)
# every float (subnormals, -0.0, 17 digits) within each column kind's plausible range (schema.py)
_torques = st.floats(-MAX_TORQUE_NM, MAX_TORQUE_NM, allow_nan=False, allow_infinity=False)
_velocities = st.floats(-MAX_VELOCITY_RAD_S, MAX_VELOCITY_RAD_S, allow_nan=False, allow_infinity=False)
_times = st.floats(-MAX_TIME_S, MAX_TIME_S, allow_nan=False, allow_infinity=False)
_sign = st.sampled_from([-1.0, 0.0, 1.0])


@st.composite
def stationary_sets(draw: st.DrawFn) -> StationaryDataset:
    n = draw(st.integers(1, 12))
    q = draw(hnp.arrays(np.float64, (n, 4), elements=_angles))
    tau = draw(hnp.arrays(np.float64, (n, 4), elements=_torques))
    direction = draw(st.none() | hnp.arrays(np.float64, (n, 4), elements=_sign))
    t = draw(st.none() | hnp.arrays(np.float64, (n,), elements=_times))
    return StationaryDataset(q, tau, direction, t)


@st.composite
def raw_logs(draw: st.DrawFn) -> RawLog:
    n = draw(st.integers(1, 12))
    start = draw(st.floats(-1e6, 1e6, allow_nan=False))
    # strictly increasing at a loop's rate (median step 1e-5..0.1 s), as a raw log must be
    steps = draw(hnp.arrays(np.float64, (n,), elements=st.floats(1e-3, 0.1)))
    t = start + np.concatenate([[0.0], np.cumsum(steps[1:])])
    q = draw(hnp.arrays(np.float64, (n, 4), elements=_angles))
    dq = draw(hnp.arrays(np.float64, (n, 4), elements=_velocities))
    tau = draw(hnp.arrays(np.float64, (n, 4), elements=_torques))
    theta = draw(st.none() | hnp.arrays(np.float64, (n, 4), elements=_angles))
    tau_cmd = draw(st.none() | hnp.arrays(np.float64, (n, 4), elements=_torques))
    return RawLog(t, q, dq, tau, theta, tau_cmd)


@pytest.mark.slow
@given(data=stationary_sets(), suffix=st.sampled_from(FORMATS))
def test_property_stationary_round_trip(data: StationaryDataset, suffix: str) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"d{suffix}"
        write_dataset(path, data)
        assert_same_stationary(load_dataset(path), data)


@pytest.mark.slow
@given(raw=raw_logs(), suffix=st.sampled_from(FORMATS))
def test_property_raw_round_trip(raw: RawLog, suffix: str) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"r{suffix}"
        write_dataset(path, raw)
        assert_same_raw(load_dataset(path), raw)


def test_raw_log_path_puts_raw_before_the_extension() -> None:
    assert raw_log_path("out/train.csv") == Path("out/train.raw.csv")
    assert raw_log_path(Path("data/B.npz")) == Path("data/B.raw.npz")
    assert raw_log_path("run.v2.mat") == Path("run.v2.raw.mat")
    assert raw_log_path("out/train.csv", ".npz") == Path("out/train.raw.npz")
    assert raw_log_path("out/train.npz", ".csv") == Path("out/train.raw.csv")


# --- atomic writes -------------------------------------------------------------------------


def _fail_midway(writer_name: str):
    """A stand-in for a writer that puts some bytes into the temporary file, then fails."""

    def fail(target: object, *args: object, **kwargs: object) -> None:
        if hasattr(target, "write"):
            target.write(b"PARTIAL")
        else:
            Path(str(target)).write_bytes(b"PARTIAL")
        raise OSError(28, f"No space left on device ({writer_name})")

    return fail


_WRITERS = {".csv": (tables, "_write_csv"), ".npz": (tables, "_write_npz"), ".mat": (scipy.io, "savemat")}


@pytest.mark.parametrize("suffix", FORMATS)
def test_failed_write_leaves_no_file_and_no_temporary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, suffix: str
) -> None:
    module, name = _WRITERS[suffix]
    monkeypatch.setattr(module, name, _fail_midway(name))
    target = tmp_path / f"new{suffix}"
    with pytest.raises(DarorError, match="No space left"):  # util/atomic.py: the OSError, as one message
        write_table(target, stationary_sample().to_columns())
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", FORMATS)
def test_failed_write_keeps_the_previous_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, suffix: str) -> None:
    target = tmp_path / f"existing{suffix}"
    old = stationary_sample(n=3, seed=1)
    write_dataset(target, old)
    before = target.read_bytes()
    module, name = _WRITERS[suffix]
    monkeypatch.setattr(module, name, _fail_midway(name))
    with pytest.raises(DarorError, match="No space left"):  # util/atomic.py: the OSError, as one message
        write_dataset(target, stationary_sample(n=30, seed=2))
    monkeypatch.undo()
    assert target.read_bytes() == before
    assert_same_stationary(load_dataset(target), old)
    assert [p.name for p in tmp_path.iterdir()] == [target.name]


def test_write_refuses_columns_of_different_lengths(tmp_path: Path) -> None:
    target = tmp_path / "bad.csv"
    with pytest.raises(DataError, match="different lengths"):
        write_table(target, {"q1": np.zeros(3), "q2": np.zeros(4)})
    assert list(tmp_path.iterdir()) == []


def test_write_refuses_an_unsupported_extension(tmp_path: Path) -> None:
    target = tmp_path / "data.txt"
    with pytest.raises(DataError, match=r"unsupported file type '\.txt'"):
        write_dataset(target, stationary_sample())
    assert list(tmp_path.iterdir()) == []


# --- bad input: CSV ------------------------------------------------------------------------


def test_data_error_is_an_input_error() -> None:
    assert issubclass(DataError, InputError)


def test_missing_columns_are_listed(tmp_path: Path) -> None:
    header = "q1,q3,q4,tau1,tau2,tau4"
    path = write_text(tmp_path / "missing.csv", csv_rows(header, [[0.1, 0.2, 0.3, 1, 2, 4]] * 3))
    message = refusal(path)
    assert "missing column(s) q2, tau3" in message
    assert "found q1, q3, q4, tau1, tau2, tau4" in message


def test_missing_raw_column_is_named(tmp_path: Path) -> None:
    header = "t,q1,q2,q3,q4,dq1,dq2,dq3,dq4,tau1,tau2,tau4"
    rows = [[0.01 * i, 0.1, 0.2, 0.3, 0.4, 0, 0, 0, 0, 1, 2, 4] for i in range(3)]
    message = refusal(write_text(tmp_path / "raw.csv", csv_rows(header, rows)))
    assert "missing column(s) tau3" in message
    assert "raw log" in message


def test_nan_names_line_and_column(tmp_path: Path) -> None:
    rows = good_stationary_rows(5)
    rows[2][5] = "nan"  # third data row -> line 4 (the header is line 1); column tau2
    message = refusal(write_text(tmp_path / "nan.csv", csv_rows(STATIONARY_HEADER, rows)))
    assert f"{tmp_path / 'nan.csv'}: line 4, column tau2: NaN" in message


def test_line_numbers_count_blank_lines(tmp_path: Path) -> None:
    rows = good_stationary_rows(3)
    rows[1][0] = "NaN"
    text = csv_rows(STATIONARY_HEADER, rows).splitlines()
    text.insert(1, "")  # a blank line right under the header
    text.insert(2, "  ")
    path = write_text(tmp_path / "blank.csv", "\n".join(text) + "\n")
    assert "line 5, column q1: NaN" in refusal(path)


def test_infinite_value_names_line_and_column(tmp_path: Path) -> None:
    rows = good_stationary_rows(4)
    rows[3][7] = "-inf"
    message = refusal(write_text(tmp_path / "inf.csv", csv_rows(STATIONARY_HEADER, rows)))
    assert "line 5, column tau4: an infinite value" in message


def test_non_numeric_cell_names_line_column_and_cell(tmp_path: Path) -> None:
    rows = good_stationary_rows(4)
    rows[1][2] = "abc"
    message = refusal(write_text(tmp_path / "text.csv", csv_rows(STATIONARY_HEADER, rows)))
    assert "line 3, column q3: 'abc' is not a number" in message


def test_empty_cell_is_not_a_number(tmp_path: Path) -> None:
    rows = good_stationary_rows(3)
    rows[0][4] = ""
    message = refusal(write_text(tmp_path / "hole.csv", csv_rows(STATIONARY_HEADER, rows)))
    assert "line 2, column tau1: '' is not a number" in message


def test_ragged_row_names_line_and_field_counts(tmp_path: Path) -> None:
    rows = good_stationary_rows(4)
    rows[1] = rows[1][:-1]
    message = refusal(write_text(tmp_path / "ragged.csv", csv_rows(STATIONARY_HEADER, rows)))
    assert "line 3 has 7 fields; the header has 8" in message


def test_row_with_too_many_fields(tmp_path: Path) -> None:
    rows = good_stationary_rows(4)
    rows[3] = [*rows[3], 9.0]
    assert "line 5 has 9 fields; the header has 8" in refusal(
        write_text(tmp_path / "long.csv", csv_rows(STATIONARY_HEADER, rows))
    )


@pytest.mark.parametrize("content", ["", "\n\n", " , ,\n"])
def test_empty_file(tmp_path: Path, content: str) -> None:
    message = refusal(write_text(tmp_path / "empty.csv", content))
    assert "file is empty" in message


def test_header_only(tmp_path: Path) -> None:
    message = refusal(write_text(tmp_path / "header.csv", STATIONARY_HEADER + "\n"))
    assert "no data rows" in message


def test_header_of_numbers(tmp_path: Path) -> None:
    rows = good_stationary_rows(3)
    message = refusal(write_text(tmp_path / "noheader.csv", "".join(",".join(map(str, r)) + "\n" for r in rows)))
    assert "line 1: the first row holds numbers ('0.0')" in message
    assert "header" in message


def test_header_cell_without_name(tmp_path: Path) -> None:
    path = write_text(
        tmp_path / "unnamed.csv", csv_rows(STATIONARY_HEADER + ",", [[*r, 1] for r in good_stationary_rows(2)])
    )
    assert "line 1: column 9 of the header has no name" in refusal(path)


def test_duplicate_column_names(tmp_path: Path) -> None:
    header = "q1,q2,q3,q4,tau1,tau2,tau3,tau4,q2,tau1"
    rows = [[*r, 0.0, 0.0] for r in good_stationary_rows(3)]
    message = refusal(write_text(tmp_path / "dup.csv", csv_rows(header, rows)))
    assert "line 1: column name(s) q2, tau1 appear more than once" in message


def test_angles_in_degrees(tmp_path: Path) -> None:
    rows = good_stationary_rows(4)
    rows[1][2] = 45.0  # q3 = 45: no joint of the robot turns that far in radians
    message = refusal(write_text(tmp_path / "deg.csv", csv_rows(STATIONARY_HEADER, rows)))
    assert "line 3, column q3: angle 45 is beyond 2 pi" in message
    assert "degrees" in message


def test_angle_of_exactly_two_pi_is_accepted(tmp_path: Path) -> None:
    rows = good_stationary_rows(2)
    rows[0][0] = repr(-2 * np.pi)
    data = load_dataset(write_text(tmp_path / "edge.csv", csv_rows(STATIONARY_HEADER, rows)))
    assert data.q_rad[0, 0] == -2 * np.pi


def test_degrees_in_a_raw_log_theta_column(tmp_path: Path) -> None:
    raw = raw_sample(n=6)
    theta = raw.theta_rad.copy()
    theta[4, 1] = -120.0
    path = tmp_path / "raw.npz"
    write_dataset(path, RawLog(raw.t_s, raw.q_rad, raw.dq_rad_s, raw.tau_nm, theta))
    message = refusal(path)
    assert "row 5, column theta2: angle -120 is beyond 2 pi" in message
    assert "degrees" in message


def test_torque_beyond_two_pi_is_not_taken_for_degrees(tmp_path: Path) -> None:
    rows = good_stationary_rows(3)
    rows[0][4] = 25.0  # 25 Nm is a torque, not an angle
    data = load_dataset(write_text(tmp_path / "tau.csv", csv_rows(STATIONARY_HEADER, rows)))
    assert data.tau_nm[0, 0] == 25.0


def test_direction_must_be_minus_one_zero_or_one(tmp_path: Path) -> None:
    header = STATIONARY_HEADER + ",dir1,dir2,dir3,dir4"
    rows = [[*r, 1, -1, 0, 1] for r in good_stationary_rows(4)]
    rows[2][9] = 0.5
    message = refusal(write_text(tmp_path / "dir.csv", csv_rows(header, rows)))
    assert "line 4, column dir2: 0.5; expected -1, 0 or +1" in message


def test_only_some_direction_columns(tmp_path: Path) -> None:
    header = STATIONARY_HEADER + ",dir1,dir3"
    rows = [[*r, 1, -1] for r in good_stationary_rows(3)]
    message = refusal(write_text(tmp_path / "somedir.csv", csv_rows(header, rows)))
    assert "has dir1, dir3 but not dir2, dir4" in message


def test_only_some_theta_columns_in_a_raw_log(tmp_path: Path) -> None:
    header = RAW_HEADER + ",theta1,theta2,theta3"
    rows = [[0.01 * i, 0.1, 0.2, 0.3, 0.4, 0, 0, 0, 0, 1, 2, 3, 4, 0.1, 0.2, 0.3] for i in range(3)]
    message = refusal(write_text(tmp_path / "sometheta.csv", csv_rows(header, rows)))
    assert "has theta1, theta2, theta3 but not theta4" in message


def test_raw_log_time_going_backwards(tmp_path: Path) -> None:
    times = [0.0, 0.01, 0.02, 0.015, 0.03]
    rows = [[t, 0.1, 0.2, 0.3, 0.4, 0, 0, 0, 0, 1, 2, 3, 4] for t in times]
    message = refusal(write_text(tmp_path / "back.csv", csv_rows(RAW_HEADER, rows)))
    assert "line 5, column t: time 0.015 s does not come after 0.02 s" in message


def test_raw_log_time_standing_still(tmp_path: Path) -> None:
    times = [0.0, 0.01, 0.01]
    rows = [[t, 0.1, 0.2, 0.3, 0.4, 0, 0, 0, 0, 1, 2, 3, 4] for t in times]
    message = refusal(write_text(tmp_path / "same.csv", csv_rows(RAW_HEADER, rows)))
    assert "line 4, column t: time 0.01 s does not come after 0.01 s" in message


def test_stationary_time_need_not_increase(tmp_path: Path) -> None:
    header = "t," + STATIONARY_HEADER
    rows = [[t, *r] for t, r in zip([3.0, 1.0, 2.0], good_stationary_rows(3), strict=True)]
    data = load_dataset(write_text(tmp_path / "shuffled.csv", csv_rows(header, rows)))
    assert isinstance(data, StationaryDataset)
    assert data.t_s.tolist() == [3.0, 1.0, 2.0]


def test_some_dq_columns_do_not_make_a_stationary_dataset(tmp_path: Path) -> None:
    """A raw log with one velocity column missing must not pass as a stationary dataset of every sample."""
    header = "t,q1,q2,q3,q4,dq1,dq2,dq4,tau1,tau2,tau3,tau4"
    rows = [[0.01 * i, 0.1, 0.2, 0.3, 0.4, 0.5, 0.5, 0.5, 1, 2, 3, 4] for i in range(5)]
    message = refusal(write_text(tmp_path / "nodq3.csv", csv_rows(header, rows)))
    assert "has dq1, dq2, dq4 but not dq3" in message


def test_velocity_columns_without_time_are_extra_columns_of_a_stationary_dataset(tmp_path: Path) -> None:
    """docs/data.md: a raw log needs ``t`` and all four ``dq``; other columns are ignored."""
    header = STATIONARY_HEADER + ",dq1,dq2,dq3,dq4"
    rows = [[*r, 0.0, 0.0, 0.0, 0.0] for r in good_stationary_rows(3)]
    data = load_dataset(write_text(tmp_path / "extra.csv", csv_rows(header, rows)))
    assert isinstance(data, StationaryDataset)
    assert len(data) == 3


def test_utf8_byte_order_mark_is_not_part_of_the_first_column_name(tmp_path: Path) -> None:
    """Spreadsheets save "CSV UTF-8" with a byte order mark; the first column must still be q1."""
    path = tmp_path / "excel.csv"
    path.write_bytes(b"\xef\xbb\xbf" + csv_rows(STATIONARY_HEADER, good_stationary_rows(3)).encode())
    data = load_dataset(path)
    assert isinstance(data, StationaryDataset)
    assert data.q_rad[:, 0].tolist() == [0.0, 0.1, 0.2]


def test_binary_file_named_csv(tmp_path: Path) -> None:
    path = tmp_path / "binary.csv"
    path.write_bytes(bytes(range(128, 256)) * 4)
    assert "not a text file" in refusal(path)


def test_missing_file(tmp_path: Path) -> None:
    assert "file not found" in refusal(tmp_path / "nowhere.csv")


def test_unsupported_extension(tmp_path: Path) -> None:
    path = write_text(tmp_path / "data.txt", csv_rows(STATIONARY_HEADER, good_stationary_rows(2)))
    message = refusal(path)
    assert "unsupported file type '.txt'" in message
    assert ".csv, .npz, .mat" in message


def test_no_extension(tmp_path: Path) -> None:
    path = write_text(tmp_path / "data", csv_rows(STATIONARY_HEADER, good_stationary_rows(2)))
    assert "unsupported file type '(none)'" in refusal(path)


# --- bad input: npz and mat ----------------------------------------------------------------


def _columns(n: int) -> dict[str, np.ndarray]:
    return {name: np.full(n, 0.25) for name in STATIONARY_HEADER.split(",")}


def test_npz_columns_of_different_lengths(tmp_path: Path) -> None:
    columns = _columns(5)
    columns["tau3"] = np.zeros(4)
    path = tmp_path / "ragged.npz"
    np.savez(path, **columns)
    message = refusal(path)
    assert "column tau3 has 4 values but q1 has 5" in message


def test_mat_columns_of_different_lengths(tmp_path: Path) -> None:
    columns = {k: v.reshape(-1, 1) for k, v in _columns(6).items()}
    columns["q4"] = np.zeros((2, 1))
    path = tmp_path / "ragged.mat"
    scipy.io.savemat(path, columns)
    message = refusal(path)
    assert re.search(r"column q4 has 2 values but \w+ has 6", message), message


def test_npz_nan_names_row_and_column(tmp_path: Path) -> None:
    columns = _columns(5)
    columns["tau2"][2] = np.nan
    path = tmp_path / "nan.npz"
    np.savez(path, **columns)
    assert f"{path}: row 3, column tau2: NaN" in refusal(path)


def test_mat_infinity_names_row_and_column(tmp_path: Path) -> None:
    columns = {k: v.reshape(-1, 1) for k, v in _columns(4).items()}
    columns["q1"][3, 0] = np.inf
    path = tmp_path / "inf.mat"
    scipy.io.savemat(path, columns)
    assert f"{path}: row 4, column q1: an infinite value" in refusal(path)


def test_npz_matrix_variable_is_refused(tmp_path: Path) -> None:
    columns = _columns(3)
    columns["q1"] = np.zeros((3, 2))
    path = tmp_path / "matrix.npz"
    np.savez(path, **columns)
    assert "variable q1 has shape (3, 2); expected a column of values" in refusal(path)


def test_npz_text_variable_is_refused(tmp_path: Path) -> None:
    columns: dict[str, np.ndarray] = dict(_columns(3))
    columns["tau1"] = np.array(["a", "b", "c"])
    path = tmp_path / "text.npz"
    np.savez(path, **columns)
    assert "variable tau1 holds" in refusal(path)


def test_corrupted_npz_random_bytes(tmp_path: Path) -> None:
    path = tmp_path / "random.npz"
    path.write_bytes(np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    message = refusal(path)
    assert "not a readable .npz archive" in message
    assert "pickle" not in message  # garbage is not a pickle: no advice to unpickle it


def test_npy_array_named_npz(tmp_path: Path) -> None:
    """A single array saved with np.save is not a table of named columns (np.load would accept it)."""
    path = tmp_path / "array.npz"
    with open(path, "wb") as handle:
        np.save(handle, np.zeros((3, 8)))
    assert "not a readable .npz archive" in refusal(path)


def test_truncated_npz(tmp_path: Path) -> None:
    path = tmp_path / "cut.npz"
    write_dataset(path, stationary_sample(n=200))
    path.write_bytes(path.read_bytes()[:700])
    assert "not a readable .npz archive" in refusal(path)


def test_corrupted_mat(tmp_path: Path) -> None:
    path = tmp_path / "random.mat"
    path.write_bytes(np.random.default_rng(4).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    assert "not a readable .mat file" in refusal(path)


def test_npz_without_any_column(tmp_path: Path) -> None:
    path = tmp_path / "nothing.npz"
    np.savez(path)
    assert "holds no columns" in refusal(path)


def test_npz_without_rows(tmp_path: Path) -> None:
    path = tmp_path / "norows.npz"
    np.savez(path, **_columns(0))
    assert "no data rows" in refusal(path)


def test_read_table_reports_csv_lines_and_npz_rows(tmp_path: Path) -> None:
    text = csv_rows(STATIONARY_HEADER, good_stationary_rows(2)).replace("\n", "\n\n", 1)
    table = read_table(write_text(tmp_path / "t.csv", text))
    assert table.row_lines.tolist() == [3, 4]
    assert table.where(1, "q2") == f"{tmp_path / 't.csv'}: line 4, column q2"
    path = tmp_path / "t.npz"
    np.savez(path, **_columns(3))
    table = read_table(path)
    assert table.row_word == "row"
    assert table.where(0) == f"{path}: row 1"
    assert tables.SUPPORTED_SUFFIXES == FORMATS


# --- load_stationary on stationary files ---------------------------------------------------


@pytest.mark.parametrize("suffix", FORMATS)
def test_load_stationary_returns_a_stationary_file_unchanged(tmp_path: Path, suffix: str) -> None:
    data = stationary_sample(n=9)
    path = tmp_path / f"s{suffix}"
    write_dataset(path, data)
    assert_same_stationary(load_stationary(path), data)


def test_written_files_get_the_usual_permissions(tmp_path: Path) -> None:
    """Atomic writes go through mkstemp (mode 0600); the result must be readable like any file."""
    import os
    import stat

    from daror_runtime.util.atomic import write_text_atomic

    umask = os.umask(0)
    os.umask(umask)
    fresh = tmp_path / "fresh.json"
    write_text_atomic(fresh, "{}")
    assert stat.S_IMODE(fresh.stat().st_mode) == 0o666 & ~umask
    kept = tmp_path / "kept.json"
    kept.write_text("old")
    kept.chmod(0o640)
    write_text_atomic(kept, "new")
    assert stat.S_IMODE(kept.stat().st_mode) == 0o640
    assert kept.read_text() == "new"
