"""Issue 10: hostile or mistaken data files, one table, through the loader and the real command line.

Every case is a small file made in ``tmp_path``. Each must be refused by ``load_stationary`` with a
:class:`~daror_runtime.errors.DataError` of one line naming the file and the problem (and the line
or row and the column where there is one), and by ``daror fit plf+ --train FILE`` with exit code
2, exactly that one line on stderr, no model file, no traceback, each within a few seconds.

Then what the table cannot show: a raw log without ``dq`` is reduced as a log, never fitted sample
by sample; stationary datasets that carry ``t`` stay stationary; the fast CSV parser reads every
number bit for bit as ``float()`` does and hands the rest to the careful parser, whatever the block
boundaries; a 10^6-row file keeps one copy of its columns.
"""

from __future__ import annotations

import json
import os
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import given
from hypothesis import strategies as st

from daror_runtime.cli import main
from daror_runtime.data import tables
from daror_runtime.data.load import load_dataset, load_stationary, write_dataset
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.stationary import ReductionSettings, reduce_to_stationary
from daror_runtime.data.tables import _parse_lines, read_table
from daror_runtime.errors import DataError
from daror_runtime.logs import configure_logging
from hal.sim.quasi_static import quasi_static_log
from hal.sim.scenario import Scenario
from hal.sim.static_dataset import generate_stationary, path_through, random_waypoints

#: Seconds a refusal may take, through the loader or the whole command.
TIME_LIMIT_S = 5.0

STATIONARY_HEADER = "t,q1,q2,q3,q4,tau1,tau2,tau3,tau4,dir1,dir2,dir3,dir4"
RAW_HEADER = "t,q1,q2,q3,q4,dq1,dq2,dq3,dq4,tau1,tau2,tau3,tau4"
DIRS = ("1", "0", "-1", "1")


# --- the files ------------------------------------------------------------------------------


def stationary_rows(n: int = 6) -> list[list[str]]:
    """Plausible stationary rows: stops seconds apart, angles in radians, torques of a few Nm."""
    return [
        [f"{2.0 * i + 1:g}", f"{0.1 * i:g}", "0.3", "-0.2", f"{1.0 + 0.05 * i:g}", "0.5", "-2.5", "1.25", "4.5", *DIRS]
        for i in range(n)
    ]


def raw_rows(n: int = 30, step: float = 0.01, start: float = 0.0) -> list[list[str]]:
    """A raw log at 100 Hz standing still: t, q, dq, tau."""
    return [
        [f"{start + step * i:.6f}", "0.1", "0.3", "-0.2", "1.0", "0", "0", "0", "0", "0.5", "-2.5", "1.2", "4.5"]
        for i in range(n)
    ]


def text_file(
    name: str, header: str, rows: list[list[str]], separator: str = ",", newline: str = "\n"
) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        path = folder / name
        lines = [header] + [separator.join(row) for row in rows]
        path.write_bytes((newline.join(lines) + newline).encode("utf-8"))
        return path

    return make


def edited(name: str, row: int, column: str, value: str, raw: bool = False) -> Callable[[Path], Path]:
    """A valid file with one cell replaced (``row`` 0 is the first data row, line 2)."""
    header = RAW_HEADER if raw else STATIONARY_HEADER
    rows = raw_rows() if raw else stationary_rows()
    rows[row][header.split(",").index(column)] = value
    return text_file(name, header, rows)


def raw_bytes(name: str, data: bytes) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        path = folder / name
        path.write_bytes(data)
        return path

    return make


def stationary_columns(n: int = 20) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(5)
    columns = {f"q{j}": rng.uniform(-1.0, 1.0, n) for j in range(1, 5)}
    columns.update({f"tau{j}": rng.normal(0.0, 3.0, n) for j in range(1, 5)})
    return columns


def npz_file(name: str, change: Callable[[dict[str, np.ndarray]], None]) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        columns: dict[str, np.ndarray] = dict(stationary_columns())
        change(columns)
        path = folder / name
        np.savez(path, **columns)
        return path

    return make


def mat_file(name: str, change: Callable[[dict[str, object]], None]) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        columns: dict[str, object] = {k: v.reshape(-1, 1) for k, v in stationary_columns().items()}
        change(columns)
        path = folder / name
        scipy.io.savemat(path, columns)
        return path

    return make


def _set(name: str, value: object) -> Callable[[dict], None]:
    def change(columns: dict) -> None:
        columns[name] = value

    return change


def _cell(name: str, row: int, value: float) -> Callable[[dict], None]:
    def change(columns: dict) -> None:
        columns[name] = columns[name].copy()
        columns[name][row] = value

    return change


def truncated_npz(folder: Path) -> Path:
    path = folder / "cut.npz"
    np.savez(path, **stationary_columns(500))
    path.write_bytes(path.read_bytes()[:1500])
    return path


def npz_with_a_text_member(folder: Path) -> Path:
    path = folder / "extra.npz"
    np.savez(path, **stationary_columns())
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("readme.txt", "columns q1..q4, tau1..tau4\n")
    return path


def zip_named_csv(folder: Path) -> Path:
    path = folder / "really_a_zip.csv"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("data.csv", STATIONARY_HEADER + "\n")
    return path


def directory(folder: Path) -> Path:
    path = folder / "folder.csv"
    path.mkdir()
    return path


def fifo(folder: Path) -> Path:
    path = folder / "pipe.csv"
    os.mkfifo(path)
    return path


def dev_zero_link(folder: Path) -> Path:
    path = folder / "zeros.csv"
    path.symlink_to("/dev/zero")
    return path


def symlink_loop(folder: Path) -> Path:
    path = folder / "loop.csv"
    other = folder / "loop2.csv"
    path.symlink_to(other)
    other.symlink_to(path)
    return path


def unreadable(folder: Path) -> Path:
    path = text_file("locked.csv", STATIONARY_HEADER, stationary_rows())(folder)
    path.chmod(0)
    return path


def wide_header(folder: Path) -> Path:
    """200,000 columns, none of them a dataset's, and one row of zeros."""
    path = folder / "wide.csv"
    n = 200_000
    path.write_text(",".join(f"c{k}" for k in range(n)) + "\n" + ",".join(["0"] * n) + "\n", encoding="utf-8")
    return path


def long_line(folder: Path) -> Path:
    path = folder / "long.csv"
    with open(path, "wb") as handle:
        handle.write((STATIONARY_HEADER + "\n").encode())
        handle.write(b"1" * (tables.MAX_LINE_BYTES + 1000))
        handle.write(b"\n")
    return path


def moving_log_without_dq(name: str, times: np.ndarray | None = None, jump: bool = False) -> Callable[[Path], Path]:
    """A log of t, q, tau at 100 Hz whose joint 1 ramps at 0.5 rad/s the whole time (no stop)."""

    def make(folder: Path) -> Path:
        n = 300
        t = np.arange(n) * 0.01 if times is None else times
        q = np.tile([0.1, 0.3, -0.2, 1.0], (n, 1))
        q[:, 0] = 0.5 * np.arange(n) * 0.01
        if jump:
            q[150:, 1] += 1.5  # the encoder jumps by 1.5 rad between two samples
        columns = {"t": t, **{f"q{j + 1}": q[:, j] for j in range(4)}}
        columns.update({f"tau{j}": np.full(n, 0.5 * j) for j in range(1, 5)})
        path = folder / name
        tables.write_table(path, columns)
        return path

    return make


def utf16(folder: Path) -> Path:
    path = folder / "utf16.csv"
    text = STATIONARY_HEADER + "\n" + "\n".join(",".join(r) for r in stationary_rows()) + "\n"
    path.write_bytes(text.encode("utf-16"))  # with its byte order mark
    return path


def _semicolons(decimal_comma: bool, bom: bool = False) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        rows = [";".join(c.replace(".", ",") if decimal_comma else c for c in r) for r in stationary_rows()]
        path = folder / ("semicolons_bom.csv" if bom else "semicolons.csv")
        text = STATIONARY_HEADER.replace(",", ";") + "\n" + "\n".join(rows) + "\n"
        path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
        return path

    return make


def ms_raw_log(folder: Path) -> Path:
    rows = raw_rows()
    for i, row in enumerate(rows):
        row[0] = f"{10.0 * i:g}"  # 100 Hz, in milliseconds
    return text_file("ms.raw.csv", RAW_HEADER, rows)(folder)


# (name, make the file, words the one line must hold; the path is always checked too)
Case = tuple[str, Callable[[Path], Path], tuple[str, ...]]

CASES: list[Case] = [
    # values beyond each column kind's plausible range
    (
        "torque 1e300",
        edited("tau.csv", 1, "tau2", "1e300"),
        ("line 3, column tau2", "torque 1e+300 Nm", "-500..500 Nm"),
    ),
    ("torque 600 Nm", edited("tau600.csv", 4, "tau4", "-600"), ("line 6, column tau4", "torque -600 Nm")),
    ("angle in degrees", edited("deg.csv", 2, "q3", "45"), ("line 4, column q3", "angle 45 is beyond 2 pi", "degrees")),
    ("angle 1e300", edited("q300.csv", 0, "q1", "1e300"), ("line 2, column q1", "angle 1e+300", "radians")),
    (
        "velocity 120 rad/s",
        edited("dq.raw.csv", 7, "dq3", "120", raw=True),
        ("line 9, column dq3", "velocity 120 rad/s", "-50..50 rad/s"),
    ),
    ("time 1e300", edited("t300.csv", 3, "t", "1e300"), ("line 5, column t", "time 1e+300 s", "-1e+07..1e+07 s")),
    ("time as a Unix time", edited("unix.csv", 0, "t", "1700000000"), ("line 2, column t", "Unix time")),
    ("dir 2", edited("dir.csv", 5, "dir1", "2"), ("line 7, column dir1: 2; expected -1, 0 or +1",)),
    (
        "theta in degrees",
        text_file(
            "theta.raw.csv",
            RAW_HEADER + ",theta1,theta2,theta3,theta4",
            [[*r, "0.1", "90", "0", "1"] for r in raw_rows()],
        ),
        ("line 2, column theta2", "degrees"),
    ),
    (
        "tau_cmd 1e6",
        text_file(
            "cmd.raw.csv",
            RAW_HEADER + ",tau_cmd1,tau_cmd2,tau_cmd3,tau_cmd4",
            [[*r, "1e6", "0", "0", "0"] for r in raw_rows()],
        ),
        ("line 2, column tau_cmd1", "torque 1e+06 Nm"),
    ),
    # NaN and infinity, spelled in various ways
    ("nan", edited("nan.csv", 1, "q2", "nan"), ("line 3, column q2: NaN; expected a finite number",)),
    ("NaN with a sign", edited("nan2.csv", 2, "tau1", "-NaN"), ("line 4, column tau1: NaN",)),
    ("-inf", edited("inf.csv", 3, "tau3", "-inf"), ("line 5, column tau3: an infinite value",)),
    ("Infinity", edited("infinity.csv", 0, "q4", "Infinity"), ("line 2, column q4: an infinite value",)),
    ("1e999 overflows", edited("e999.csv", 4, "tau1", "1e999"), ("line 6, column tau1: an infinite value",)),
    (
        "#N/A of a spreadsheet",
        edited("na.csv", 1, "tau2", "#N/A"),
        ("line 3, column tau2", "'#N/A' is not a number (a missing value)"),
    ),
    ("empty cell", edited("hole.csv", 2, "q1", ""), ("line 4, column q1: '' is not a number",)),
    ("text cell", edited("text.csv", 0, "tau4", "abc"), ("line 2, column tau4: 'abc' is not a number",)),
    ("npz NaN", npz_file("nan.npz", _cell("tau2", 2, np.nan)), ("row 3, column tau2: NaN",)),
    ("npz 1e300", npz_file("big.npz", _cell("tau1", 4, 1e300)), ("row 5, column tau1", "torque 1e+300 Nm")),
    # separators, decimal commas, units
    (
        "semicolons",
        _semicolons(False),
        ("line 1: the header looks semicolon-separated", "expected comma-separated values"),
    ),
    ("semicolons and decimal commas", _semicolons(True), ("semicolon-separated", "line 2 has decimal commas")),
    ("BOM and semicolons", _semicolons(False, bom=True), ("line 1: the header looks semicolon-separated",)),
    (
        "quoted decimal comma",
        edited("comma.csv", 1, "q1", '"0,52"'),
        ("line 3, column q1: '0,52' looks like a decimal comma; expected a decimal point",),
    ),
    (
        "tabs",
        text_file("tabs.csv", STATIONARY_HEADER.replace(",", "\t"), stationary_rows(), separator="\t"),
        ("the header looks tab-separated",),
    ),
    (
        "spaces",
        text_file("spaces.csv", STATIONARY_HEADER.replace(",", " "), stationary_rows(), separator=" "),
        ("the header looks space-separated",),
    ),
    (
        "row separated by semicolons",
        text_file("mixed.csv", STATIONARY_HEADER, [*stationary_rows(2), ["1;2;3;4;5;6;7;8;9;0;0;0;0"]]),
        ("line 4 has 1 field; the header has 13", "semicolon-separated"),
    ),
    ("time in milliseconds", ms_raw_log, ("column t looks like milliseconds (steps of 10); expected seconds",)),
    (
        "log without dq, time in milliseconds",
        moving_log_without_dq("ms_nodq.csv", times=np.arange(300) * 10.0),
        ("column t looks like milliseconds (steps of 10)",),
    ),
    (
        "log sampled at 3 Hz",
        text_file("slow.raw.csv", RAW_HEADER, raw_rows(step=0.3)),
        ("column t has steps of 0.3 s", "at most 0.1 s"),
    ),
    (
        "log in Unix time",
        text_file("unix.raw.csv", RAW_HEADER, raw_rows(start=1.7e9)),
        ("line 2, column t", "Unix time"),
    ),
    # encodings and the shape of the text
    ("UTF-16 with a byte order mark", utf16, ("not a text file", "UTF-16")),
    (
        "Latin-1 byte",
        raw_bytes(
            "latin1.csv", (STATIONARY_HEADER + "\n" + ",".join(stationary_rows()[0]) + "\n0.1,\xe9\n").encode("latin-1")
        ),
        ("line 3: byte 0xe9 is not UTF-8",),
    ),
    ("NUL bytes", raw_bytes("nul.csv", b"t,q1\x00\x00\x00,q2\n1,2,3\n"), ("not a text file", "NUL")),
    (
        "old Mac line ends",
        raw_bytes("cr.csv", (STATIONARY_HEADER + "\r" + ",".join(stationary_rows()[0]) + "\r").encode()),
        ("line 1: a carriage return (CR) inside the line",),
    ),
    (
        "binary garbage",
        raw_bytes("garbage.csv", np.random.default_rng(1).integers(128, 256, 5000, dtype=np.uint8).tobytes()),
        ("not a text file",),
    ),
    ("a zip named .csv", zip_named_csv, ("not a text file", "zip archive")),
    ("empty file", raw_bytes("empty.csv", b""), ("file is empty",)),
    ("blank lines only", raw_bytes("blank.csv", b"\n \n,,\n\r\n"), ("file is empty",)),
    ("header only", text_file("header.csv", STATIONARY_HEADER, []), ("no data rows",)),
    (
        "no header",
        raw_bytes("noheader.csv", (",".join(stationary_rows()[0]) + "\n").encode()),
        ("line 1: the first row holds numbers",),
    ),
    (
        "duplicate column",
        text_file("dup.csv", STATIONARY_HEADER + ",tau2", [[*r, "0"] for r in stationary_rows()]),
        ("line 1: column name(s) tau2 appear more than once",),
    ),
    (
        "a column twice, in two cases",
        text_file("case.csv", STATIONARY_HEADER + ",Q1", [[*r, "0"] for r in stationary_rows()]),
        ("line 1: columns q1 and Q1 differ only in case",),
    ),
    (
        "upper-case names",
        text_file("upper.csv", STATIONARY_HEADER.upper(), stationary_rows()),
        ("missing column(s) q1", "case-sensitive", "Q1 for q1"),
    ),
    (
        "ragged row, short",
        text_file("short.csv", STATIONARY_HEADER, [*stationary_rows(3), stationary_rows()[0][:-1]]),
        ("line 5 has 12 fields; the header has 13",),
    ),
    (
        "ragged row, long",
        text_file("longrow.csv", STATIONARY_HEADER, [stationary_rows()[0] + ["7"], *stationary_rows(2)]),
        ("line 2 has 14 fields; the header has 13",),
    ),
    ("a line of 16 MB", long_line, ("line 2 is longer than 16 MB",)),
    ("200,000-column header", wide_header, ("missing column(s) q1", "(200,000 in all)")),
    ("unsupported extension", raw_bytes("data.xlsx", b"PK\x03\x04"), ("unsupported file type '.xlsx'",)),
    # npz and mat
    ("truncated npz", truncated_npz, ("not a readable .npz archive",)),
    (
        "npz of Python objects",
        npz_file("objects.npz", _set("q1", np.array([{"a": 1}] * 20, dtype=object))),
        ("variable q1 holds Python objects", "pickle"),
    ),
    (
        "npz complex column",
        npz_file("complex.npz", _set("tau3", np.full(20, 1 + 2j))),
        ("variable tau3 holds complex numbers",),
    ),
    (
        "npz complex column, zero imaginary part",
        npz_file("complex0.npz", _set("q2", np.zeros(20, dtype=complex))),
        ("variable q2 holds complex numbers",),
    ),
    ("npz 2-D array", npz_file("matrix.npz", _set("q4", np.zeros((20, 2)))), ("variable q4 has shape (20, 2)",)),
    (
        "npz columns of different lengths",
        npz_file("ragged.npz", _set("tau1", np.zeros(7))),
        ("column tau1 has 7 values but q1 has 20",),
    ),
    ("npz with a text member", npz_with_a_text_member, ("member 'readme.txt' is not a .npy array",)),
    (
        "a single .npy named .npz",
        raw_bytes("single.npz", b"\x93NUMPY\x01\x00" + b" " * 100),
        ("not a readable .npz archive",),
    ),
    (
        "mat struct",
        mat_file("struct.mat", _set("q1", {"a": np.zeros(3), "b": 1.0})),
        ("variable q1 is a MATLAB struct",),
    ),
    (
        "mat cell array",
        mat_file("cell.mat", _set("tau1", np.array([[np.zeros(2)], [np.ones(3)]], dtype=object))),
        ("variable tau1 is a MATLAB cell array",),
    ),
    (
        "mat complex column",
        mat_file("complex.mat", _set("tau2", np.full((20, 1), 1j))),
        ("variable tau2 holds complex numbers",),
    ),
    ("mat text", mat_file("text.mat", _set("q3", "twenty")), ("variable q3 holds text",)),
    (
        "mat garbage",
        raw_bytes("garbage.mat", np.random.default_rng(2).integers(0, 256, 4096, dtype=np.uint8).tobytes()),
        ("not a readable .mat file",),
    ),
    # what the path is
    ("a directory", directory, ("a directory, not a data file",)),
    ("a FIFO", fifo, ("a named pipe (FIFO), not a data file",)),
    ("a symlink to /dev/zero", dev_zero_link, ("a device, not a data file",)),
    ("a symlink loop", symlink_loop, ("a symbolic link loop",)),
    ("unreadable", unreadable, ("not readable (permission denied)",)),
    ("missing", lambda folder: folder / "nowhere.csv", ("data file not found",)),
    # raw logs
    (
        "raw log with time going back",
        text_file("back.raw.csv", RAW_HEADER, [*raw_rows(5), raw_rows(9)[3]]),
        ("line 7, column t: time 0.03 s does not come after 0.04 s",),
    ),
    (
        "log without dq, time going back",
        moving_log_without_dq("back_nodq.csv", times=np.concatenate([np.arange(150), np.arange(149, 299)]) * 0.01),
        ("line 152, column t: time 1.49 s does not come after 1.49 s",),
    ),
    ("log without dq, never still", moving_log_without_dq("moving_nodq.csv"), ("no stationary samples",)),
    (
        "log without dq, an encoder jump",
        moving_log_without_dq("jump_nodq.csv", jump=True),
        ("line 152, column q2: the joint moves 1.5 rad in 0.01 s", "expected at most 50 rad/s"),
    ),
    (
        "raw log missing one dq",
        text_file("nodq3.csv", RAW_HEADER.replace(",dq3", ""), [r[:7] + r[8:] for r in raw_rows()]),
        ("has dq1, dq2, dq4 but not dq3",),
    ),
]


def parse_decimal(text: str) -> float | None:
    """``text`` read by the fast path alone, or None where it would leave it to the careful parser."""
    data = text.encode("ascii", errors="replace")
    out = np.zeros((1, 1))
    buf = np.frombuffer(data, np.uint8)
    row, _, _, _ = _parse_lines(buf, 0, buf.size, 1, out, out.view(np.uint64), np.zeros(1, np.int64), 0, 1)
    return float(out[0, 0]) if row == 1 else None


def test_the_table_has_forty_distinct_cases() -> None:
    names = [name for name, _, _ in CASES]
    assert len(names) == len(set(names))
    assert len(names) >= 40, len(names)


@pytest.fixture(scope="module", autouse=True)
def _compiled(tmp_path_factory: pytest.TempPathFactory) -> None:
    """The fast parser compiled (or loaded from numba's cache) before any case is timed."""
    folder = tmp_path_factory.mktemp("warm")
    read_table(text_file("warm.csv", STATIONARY_HEADER, stationary_rows())(folder))


def _skip_unless_meaningful(name: str) -> None:
    if name == "unreadable" and os.geteuid() == 0:
        pytest.skip("root reads a file of mode 000")


@pytest.mark.parametrize(("name", "make", "words"), CASES, ids=[name for name, _, _ in CASES])
def test_the_loader_refuses_in_one_line(
    name: str, make: Callable[[Path], Path], words: tuple[str, ...], tmp_path: Path
) -> None:
    _skip_unless_meaningful(name)
    path = make(tmp_path)
    start = time.perf_counter()
    with pytest.raises(DataError) as caught:
        load_stationary(path)
    elapsed = time.perf_counter() - start
    message = str(caught.value)
    assert message.startswith(f"{path}: "), message
    assert "\n" not in message, message
    assert len(message) < 400, f"{len(message)} characters: {message[:500]}"
    for word in words:
        assert word in message, f"{word!r} not in: {message}"
    assert elapsed < TIME_LIMIT_S, f"{name}: {elapsed:.1f} s"


@pytest.mark.parametrize(("name", "make", "words"), CASES, ids=[name for name, _, _ in CASES])
def test_the_command_refuses_with_exit_2_and_one_line(
    name: str, make: Callable[[Path], Path], words: tuple[str, ...], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _skip_unless_meaningful(name)
    path = make(tmp_path)
    out = tmp_path / "out" / "model.json"
    out.parent.mkdir()
    capsys.readouterr()
    start = time.perf_counter()
    code = main(["fit", "plf+", "--train", str(path), "--out", str(out)])
    elapsed = time.perf_counter() - start
    captured = capsys.readouterr()
    configure_logging("critical")
    assert code == 2, (name, captured.err)
    assert captured.err.endswith("\n")
    lines = captured.err.rstrip("\n").split("\n")
    assert len(lines) == 1, f"{name}: stderr is not one line: {captured.err!r}"
    assert lines[0].startswith(f"daror fit: error: {path}: "), lines[0]
    for word in words:
        assert word in lines[0], f"{word!r} not in: {lines[0]}"
    assert "Traceback" not in captured.out + captured.err
    assert list(out.parent.iterdir()) == [], "something was written"
    assert elapsed < TIME_LIMIT_S, f"{name}: {elapsed:.1f} s"


# --- a raw log without dq is a log ----------------------------------------------------------


@pytest.fixture(scope="module")
def stops(exo_dummy_arm: Scenario) -> np.ndarray:
    """Stops through six random waypoints of the workspace (rad)."""
    return path_through(random_waypoints(exo_dummy_arm.workspace, 6, np.random.default_rng(4)), 1)


@pytest.fixture(scope="module")
def log_files(
    exo_dummy_arm: Scenario, stops: np.ndarray, tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, Path, RawLog]:
    """The same simulated log written with and without its dq columns."""
    folder = tmp_path_factory.mktemp("logs")
    log = quasi_static_log(exo_dummy_arm, stops, np.random.default_rng(7))
    raw = RawLog(log.t_s, log.q_rad, log.dq_rad_s, log.tau_nm, log.theta_rad)
    with_dq = folder / "with_dq.raw.csv"
    write_dataset(with_dq, raw)
    columns = raw.to_columns()
    without = folder / "without_dq.raw.csv"
    tables.write_table(without, {k: v for k, v in columns.items() if not k.startswith("dq")})
    return with_dq, without, raw


def test_a_log_without_dq_is_read_as_a_log_with_its_velocity_derived(log_files: tuple[Path, Path, RawLog]) -> None:
    with_dq, without, raw = log_files
    loaded = load_dataset(without)
    assert isinstance(loaded, RawLog)
    assert loaded.velocity_derived
    assert not load_dataset(with_dq).velocity_derived
    assert len(loaded) == len(raw)
    # the derived velocity is the logged one where the log moves smoothly (both differentiate q)
    assert np.abs(loaded.dq_rad_s - np.gradient(raw.q_rad, raw.t_s, axis=0)).max() < 1e-9


def test_a_log_without_dq_gives_the_stops_of_the_same_log_with_dq(
    log_files: tuple[Path, Path, RawLog], stops: np.ndarray
) -> None:
    with_dq, without, raw = log_files
    settings = ReductionSettings(per_stop="mean")
    derived = load_stationary(without, settings)
    logged = load_stationary(with_dq, settings)
    assert len(derived) == len(logged) == len(stops)
    assert np.abs(derived.q_rad - stops).max() < 2e-4
    assert np.array_equal(derived.direction, logged.direction)
    every = load_stationary(without)
    assert len(every) < 0.7 * len(raw), "the moves were kept"


def test_the_command_fits_a_log_without_dq_on_its_stops_only(
    log_files: tuple[Path, Path, RawLog], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, without, raw = log_files
    out = tmp_path / "model.json"
    assert main(["fit", "plf", "--train", str(without), "--out", str(out)]) == 0
    configure_logging("critical")
    points = json.loads(out.read_text())["training"]["n_points"]
    assert points == len(load_stationary(without))
    assert points < 0.7 * len(raw)


def test_stationary_datasets_with_t_stay_stationary(
    exo_dummy_arm: Scenario, tmp_path: Path, log_files: tuple[Path, Path, RawLog]
) -> None:
    """Repeated readings of each stop 1 ms apart, and a log's stationary samples at 100 Hz (with
    dir, or without: the reduction's output keeps t), must not be read as logs."""
    points = generate_stationary(exo_dummy_arm, "validation", n_waypoints=8, samples_per_stop=5)
    repeated = StationaryDataset(points.q_rad, points.tau_nm, None, points.t_s)
    _, without, _ = log_files
    reduced = load_stationary(without)
    for name, data in (
        ("repeated.csv", repeated),
        ("reduced.csv", reduced),
        ("reduced_nodir.csv", StationaryDataset(reduced.q_rad, reduced.tau_nm, None, reduced.t_s)),
    ):
        path = tmp_path / name
        write_dataset(path, data)
        back = load_dataset(path)
        assert isinstance(back, StationaryDataset), name
        assert np.array_equal(back.q_rad, data.q_rad), name


# --- the CSV parser ---------------------------------------------------------------------------


def _bits(value: float) -> int:
    return int(np.float64(value).view(np.uint64))


@given(value=st.floats(allow_nan=False), form=st.sampled_from(["%.17g", "%r", "%.15g", "%.3e", "%.19g", "%.0f"]))
def test_the_fast_parser_reads_what_float_reads_bit_for_bit(value: float, form: str) -> None:
    text = repr(value) if form == "%r" else form % value
    parsed = parse_decimal(text)
    assert parsed is None or _bits(parsed) == _bits(float(text)), text


@given(
    digits=st.text("0123456789", min_size=1, max_size=19),
    point=st.integers(0, 19),
    exponent=st.integers(-360, 330),
    sign=st.sampled_from(["", "-", "+"]),
)
def test_the_fast_parser_on_any_decimal(digits: str, point: int, exponent: int, sign: str) -> None:
    text = f"{sign}{digits[:point]}.{digits[point:]}e{exponent}"
    parsed = parse_decimal(text)
    assert parsed is not None, text
    assert _bits(parsed) == _bits(float(text)), text


@pytest.mark.parametrize(
    "text",
    [
        "9007199254740993",
        "4.9406564584124654e-324",
        "2.4703282292062327e-324",
        "2.2250738585072011e-308",
        "1.7976931348623157e308",
        "1.7976931348623159e308",
        "-0",
        "0.000000000000000000001",
        "1e-400",
        "1e400",
        "123456789012345678e-20",
        "0.1",
        "0.3",
        "2.5",
        "3.5",
        "-7.450580596923828125e-9",
    ],
)
def test_the_fast_parser_at_its_edges(text: str) -> None:
    parsed = parse_decimal(text)
    assert parsed is not None
    assert _bits(parsed) == _bits(float(text))


@pytest.mark.parametrize(
    "text", ["nan", "inf", "1,5", "", " ", ".", "1e", "--1", "0x10", "1_0", "12345678901234567890"]
)
def test_the_fast_parser_leaves_the_rest_to_the_careful_one(text: str) -> None:
    assert parse_decimal(text) is None


def _odd_but_valid_file(path: Path) -> list[list[float]]:
    """Quoted cells, spaces, CRLF, blank lines, 20 digits: all read by the careful parser."""
    rows = [[0.1 * i + 1e-17 * i, 0.3, -0.2, 1.0, 0.5, -2.5, 1.25, 4.5] for i in range(40)]
    lines = ["q1,q2,q3,q4,tau1,tau2,tau3,tau4"]
    for i, row in enumerate(rows):
        cells = [repr(v) for v in row]
        if i % 7 == 1:
            cells[2] = f'"{cells[2]}"'
        if i % 5 == 2:
            cells[4] = f"  {cells[4]} "
        if i % 11 == 3:
            cells[0] = "0.10000000000000000000"  # 20 significant digits
            rows[i][0] = float(cells[0])
        lines.append(",".join(cells))
        if i % 9 == 4:
            lines.append("")
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode())
    return rows


@pytest.mark.parametrize("chunk", [64, 100, 1000, tables.CHUNK_BYTES])
def test_blocks_of_any_size_read_the_same_values_and_lines(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, chunk: int
) -> None:
    monkeypatch.setattr(tables, "CHUNK_BYTES", chunk)
    path = tmp_path / "odd.csv"
    rows = _odd_but_valid_file(path)
    table = read_table(path)
    assert table.n_rows == len(rows)
    got = table.matrix(("q1", "q2", "q3", "q4"))
    assert np.array_equal(got, np.array(rows)[:, :4])
    lines = path.read_bytes().decode().split("\r\n")
    for i, line in enumerate(table.row_lines):  # each row's line in the file holds its first value
        assert float(lines[line - 1].split(",")[0]) == rows[i][0], (i, line)
    # an error after a blank line names the line in the file, whatever the blocks
    text = path.read_text().replace("\r\n", "\n").split("\n")
    text[30] = text[30].replace(",", ",x", 1)
    path.write_text("\n".join(text))
    with pytest.raises(DataError, match=r"line 31, column q2: 'x") as caught:
        read_table(path)
    assert str(caught.value).startswith(f"{path}: ")


def test_a_large_file_keeps_one_copy_of_its_columns(tmp_path: Path) -> None:
    """The dataset's arrays are the table's blocks: C-contiguous, float64, no stacked copy."""
    n = 20_000
    rng = np.random.default_rng(3)
    data = StationaryDataset(
        rng.uniform(-1, 1, (n, 4)), rng.normal(0, 3, (n, 4)), rng.choice([-1.0, 0.0, 1.0], (n, 4)), np.arange(n) * 2.0
    )
    path = tmp_path / "large.csv"
    write_dataset(path, data)
    table = read_table(path)
    q = table.matrix(("q1", "q2", "q3", "q4"))
    assert q.flags.c_contiguous
    assert np.shares_memory(q, table.columns["q1"])
    loaded = load_stationary(path)
    for name in ("q_rad", "tau_nm", "direction", "t_s"):
        assert np.array_equal(getattr(loaded, name), getattr(data, name)), name
        assert getattr(loaded, name).flags.c_contiguous, name


def test_a_reduced_log_from_a_file_without_dq_reduces_like_memory(log_files: tuple[Path, Path, RawLog]) -> None:
    _, without, raw = log_files
    derived = RawLog(raw.t_s, raw.q_rad, np.gradient(raw.q_rad, raw.t_s, axis=0), raw.tau_nm, raw.theta_rad)
    expected = reduce_to_stationary(derived)
    loaded = load_stationary(without)
    assert np.array_equal(loaded.t_s, expected.t_s)
    assert np.array_equal(loaded.q_rad, expected.q_rad)
