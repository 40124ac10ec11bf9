"""The crash-safe recorder (``daror_runtime.data.recorder``, issue 3), its reader and the loop's row layout.

What is checked: exact round trips over many blocks; the partial block at close and at flush;
bounded memory (a slowed writer makes ``push`` drop and count rows, never wait); a disk error in
the writer thread latched and raised at the next ``push``; no overwrite; a real ``kill -9`` of a
recording process, after which every complete row is readable and exact; a truncated tail is
ignored, a damaged header refused; the loop's row (``daror_runtime.data.tick_row``) puts every value
under its name; and a recording of such rows turns into a raw log the reducer accepts.
"""

from __future__ import annotations

import errno
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from daror_runtime.data import tick_row
from daror_runtime.data.recorder import FORMAT_NAME, VALUE_BYTES, Recorder, RecorderError
from daror_runtime.data.recording_reader import inspect_recording, read_recording, recording_to_raw_log
from daror_runtime.data.schema import RAW_REQUIRED, RawLog
from daror_runtime.data.stationary import reduce_to_stationary
from daror_runtime.data.tick_row import RECORD_COLUMNS, fill_tick_row_at
from daror_runtime.errors import DataError, ShapeError, UsageError
from hal.sim.quasi_static import QuasiStaticSettings, quasi_static_log
from hal.sim.scenario import Scenario
from hal.sim.static_dataset import stream

REPO = Path(__file__).resolve().parents[3]
COLUMNS = tuple(f"c{k}" for k in range(6))


# --- helpers -------------------------------------------------------------------------------


def pool_bytes(recorder: Recorder) -> int:
    """Bytes of row storage the recorder owns: its blocks, allocated at start."""
    return recorder.capacity_rows * len(recorder.columns) * VALUE_BYTES


def counting_rows(n_rows: int, n_columns: int, start: int = 0) -> np.ndarray:
    """Row i holds ``[i, 2 i, 3 i, ...]``: any lost, repeated or shifted value shows."""
    index = np.arange(start, start + n_rows, dtype=float)[:, None]
    return index * np.arange(1, n_columns + 1, dtype=float)


def wait_for(condition: Callable[[], bool], timeout_s: float = 10.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.002)


def assert_bitwise_equal(actual: np.ndarray, expected: np.ndarray) -> None:
    assert actual.dtype == np.float64
    assert actual.shape == expected.shape, f"shape {actual.shape} != {expected.shape}"
    assert np.array_equal(actual.view(np.int64), np.ascontiguousarray(expected).view(np.int64)), "values differ"


def slow_writes(recorder: Recorder, monkeypatch: pytest.MonkeyPatch, delay_s: float) -> threading.Event:
    """Slow the writer down by ``delay_s`` per block; set the returned event to let it run at full speed."""
    original = recorder._write_block
    release = threading.Event()

    def slow(rows: np.ndarray) -> None:
        if not release.is_set():
            release.wait(delay_s)
        original(rows)

    monkeypatch.setattr(recorder, "_write_block", slow)
    return release


@pytest.fixture
def path(tmp_path: Path) -> Path:
    return tmp_path / "run.rec"


# --- round trips ---------------------------------------------------------------------------


def test_round_trip_of_many_blocks_is_bitwise_exact(path: Path, rng: np.random.Generator) -> None:
    rows = rng.normal(size=(10_007, len(COLUMNS))) * 10.0 ** rng.integers(-300, 300, size=(10_007, len(COLUMNS)))
    rows[0] = [0.0, -0.0, np.inf, -np.inf, 5e-324, np.nan]  # the recorder stores bits, not "numbers"
    # 101 blocks of 100 rows fit in memory at once, so no row can be dropped whatever the scheduling.
    with Recorder(path, COLUMNS, block_rows=100, max_queued_blocks=101) as recorder:
        for row in rows:
            assert recorder.push(row)
    assert recorder.rows_written == 10_007
    assert recorder.dropped_rows == 0
    columns, data = read_recording(path)
    assert columns == COLUMNS
    assert_bitwise_equal(data, rows)
    _, mapped = read_recording(path, mmap=True)
    assert_bitwise_equal(np.asarray(mapped), rows)


def test_push_takes_sequences_and_copies_the_values(path: Path) -> None:
    row = np.zeros(3)
    with Recorder(path, ("a", "b", "c"), block_rows=4) as recorder:
        for i in range(10):
            row[:] = (i, -i, 0.5 * i)  # the loop reuses one array every tick
            recorder.push(row)
        recorder.push([10, -10, 5])
        recorder.push((11.0, -11.0, 5.5))
    _, data = read_recording(path)
    expected = np.array([[i, -i, 0.5 * i] for i in range(12)], dtype=float)
    assert_bitwise_equal(data, expected)


def test_streaming_with_drops_keeps_every_accepted_row_in_order(path: Path) -> None:
    """Whatever the scheduling does, the file holds exactly the rows push accepted, in order."""
    rows = counting_rows(20_000, 4)
    accepted = []
    with Recorder(path, ("a", "b", "c", "d"), block_rows=16, max_queued_blocks=3) as recorder:
        for i, row in enumerate(rows):
            if recorder.push(row):
                accepted.append(i)
    assert recorder.rows_written + recorder.dropped_rows == 20_000
    _, data = read_recording(path)
    assert_bitwise_equal(data, rows[accepted])


def test_partial_block_is_written_at_close(path: Path) -> None:
    with Recorder(path, COLUMNS, block_rows=1000) as recorder:
        for row in counting_rows(1234, len(COLUMNS)):
            recorder.push(row)
    assert recorder.rows_written == 1234
    _, data = read_recording(path)
    assert_bitwise_equal(data, counting_rows(1234, len(COLUMNS)))


def test_flush_hands_the_partial_block_over_without_closing(path: Path) -> None:
    recorder = Recorder(path, COLUMNS, block_rows=1000)
    recorder.start()
    try:
        for row in counting_rows(10, len(COLUMNS)):
            recorder.push(row)
        assert recorder.flush()
        wait_for(lambda: recorder.rows_written == 10, what="the flushed rows to be written")
        _, data = read_recording(path)  # readable while the recording goes on
        assert_bitwise_equal(data, counting_rows(10, len(COLUMNS)))
        assert recorder.flush()  # nothing pending: nothing to do
        for row in counting_rows(5, len(COLUMNS), start=10):
            recorder.push(row)
    finally:
        recorder.close()
    _, data = read_recording(path)
    assert_bitwise_equal(data, counting_rows(15, len(COLUMNS)))


def test_empty_recording_has_a_header_and_no_rows(path: Path) -> None:
    with Recorder(path, COLUMNS):
        pass
    columns, data = read_recording(path)
    assert columns == COLUMNS
    assert data.shape == (0, len(COLUMNS))


def test_header_is_one_aligned_json_line(path: Path) -> None:
    with Recorder(path, ("t", "q 1", "ünïcode\n")) as recorder:
        recorder.push([1.0, 2.0, 3.0])
    info = inspect_recording(path)
    assert info.columns == ("t", "q 1", "ünïcode\n")
    assert info.header["format"] == FORMAT_NAME
    assert info.header["dtype"] == "<f8"
    assert info.data_offset % 64 == 0
    assert path.read_bytes()[: info.data_offset].count(b"\n") == 1
    assert (info.n_rows, info.tail_bytes) == (1, 0)


# --- bounded memory and the drop policy ----------------------------------------------------


def test_full_queue_drops_and_counts_rows_and_push_never_waits(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    recorder = Recorder(path, COLUMNS, block_rows=10, max_queued_blocks=4)
    release = slow_writes(recorder, monkeypatch, delay_s=1.0)
    rows = counting_rows(400, len(COLUMNS))
    durations, accepted = [], []
    recorder.start()
    try:
        for i, row in enumerate(rows):
            start = time.perf_counter()
            ok = recorder.push(row)
            durations.append(time.perf_counter() - start)
            if ok:
                accepted.append(i)
    finally:
        release.set()
        recorder.close()
    # 4 blocks of 10 rows in all; the writer holds one for 1 s, so at most 40 rows get in.
    assert len(accepted) <= recorder.capacity_rows == 40
    assert recorder.dropped_rows == 400 - len(accepted) >= 360
    # A push that waited for the slowed writer would take 1 s; this bound is 10x below that, which
    # leaves room for a busy two-core machine.
    assert max(durations) < 0.1, f"slowest push {max(durations) * 1e3:.1f} ms"
    _, data = read_recording(path)
    assert_bitwise_equal(data, rows[accepted])


def test_rows_are_accepted_again_once_the_writer_catches_up(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    recorder = Recorder(path, COLUMNS, block_rows=10, max_queued_blocks=3)
    release = slow_writes(recorder, monkeypatch, delay_s=5.0)
    rows = counting_rows(200, len(COLUMNS))
    accepted = []
    with recorder:
        for i in range(100):
            if recorder.push(rows[i]):
                accepted.append(i)
        assert recorder.dropped_rows > 0
        release.set()
        wait_for(lambda: recorder.rows_written == 20, what="the writer to catch up")
        for i in range(100, 200):
            assert recorder.push(rows[i]), "a row was dropped after the writer caught up"
            accepted.append(i)
            if i % 10 == 9:  # a block was handed over: let the writer finish it before the next fills
                wait_for(lambda: recorder.rows_written == len(accepted), what="the block to be written")
    _, data = read_recording(path)
    assert_bitwise_equal(data, rows[accepted])
    assert recorder.rows_written + recorder.dropped_rows == 200


def test_memory_stays_within_the_blocks_whatever_the_run_length(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    recorder = Recorder(path, COLUMNS, block_rows=100, max_queued_blocks=5)
    release = slow_writes(recorder, monkeypatch, delay_s=0.05)
    row = np.zeros(len(COLUMNS))
    tracemalloc.start()
    try:
        baseline = tracemalloc.get_traced_memory()[0]
        recorder.start()
        after_start = tracemalloc.get_traced_memory()[0]
        for i in range(100_000):  # 200 times what the blocks hold
            row[0] = i
            recorder.push(row)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
        release.set()
        recorder.close()
    assert after_start - baseline >= pool_bytes(recorder)  # the blocks, allocated once at start
    # Blocks plus a little bookkeeping (queue entries, the thread); nothing that grows with the run.
    assert peak - baseline < pool_bytes(recorder) + 256 * 1024, f"peak {peak - baseline} bytes"
    assert recorder.rows_written + recorder.dropped_rows == 100_000


# --- errors --------------------------------------------------------------------------------


def test_disk_error_is_latched_and_raised_at_the_next_push(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    recorder = Recorder(path, COLUMNS, block_rows=10)
    failed = threading.Event()

    def full_disk(rows: np.ndarray) -> None:
        failed.set()
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(recorder, "_write_block", full_disk)
    recorder.start()
    for row in counting_rows(10, len(COLUMNS)):
        recorder.push(row)  # the tenth push hands the first block over
    assert failed.wait(5.0)
    wait_for(lambda: recorder.error is not None, what="the error to be latched")
    with pytest.raises(RecorderError, match="No space left on device") as raised:
        recorder.push(np.zeros(len(COLUMNS)))
    message = str(raised.value)
    assert str(path) in message
    assert "after 0 rows" in message
    assert isinstance(raised.value.__cause__, OSError)
    with pytest.raises(RecorderError, match="No space left"):  # latched: every push refuses
        recorder.push(np.zeros(len(COLUMNS)))
    with pytest.raises(RecorderError, match="No space left"):
        recorder.flush()
    with pytest.raises(RecorderError, match="No space left"):
        recorder.close()


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_real_full_disk_is_raised_at_the_next_push(path: Path) -> None:
    recorder = Recorder(path, COLUMNS, block_rows=10)
    recorder.start()
    # Swap the file for /dev/full, whose every write fails with ENOSPC in the kernel.
    real = recorder._file
    recorder._file = open("/dev/full", "wb")  # noqa: SIM115 - the recorder's writer closes it
    real.close()
    for row in counting_rows(10, len(COLUMNS)):
        recorder.push(row)
    wait_for(lambda: recorder.error is not None, what="the error to be latched")
    with pytest.raises(RecorderError, match="No space left on device"):
        recorder.push(np.zeros(len(COLUMNS)))
    with pytest.raises(RecorderError):
        recorder.close()


def test_refuses_to_overwrite_an_existing_file(path: Path) -> None:
    path.write_bytes(b"precious")
    recorder = Recorder(path, COLUMNS)
    with pytest.raises(UsageError, match=r"file exists; refusing to overwrite") as raised:
        recorder.start()
    assert str(path) in str(raised.value)
    assert path.read_bytes() == b"precious"
    with pytest.raises(RecorderError, match="not started"):
        recorder.push(np.zeros(len(COLUMNS)))


def test_a_missing_directory_is_a_recorder_error(tmp_path: Path) -> None:
    with pytest.raises(RecorderError, match="cannot create the recording"):
        Recorder(tmp_path / "no" / "such" / "dir.rec", COLUMNS).start()


def test_push_outside_start_and_close_refuses(path: Path) -> None:
    recorder = Recorder(path, COLUMNS)
    with pytest.raises(RecorderError, match="not started"):
        recorder.push(np.zeros(len(COLUMNS)))
    recorder.start()
    with pytest.raises(UsageError, match="started or closed already"):
        recorder.start()
    recorder.close()
    recorder.close()  # a second close does nothing
    with pytest.raises(RecorderError, match="closed"):
        recorder.push(np.zeros(len(COLUMNS)))
    with pytest.raises(RecorderError, match="closed"):
        recorder.flush()


@pytest.mark.parametrize(
    "row",
    [np.zeros(5), np.zeros(7), 1.0, np.zeros((6, 1)), ["a", "b", "c", "d", "e", "f"], None],
    ids=["short", "long", "scalar", "column", "strings", "none"],
)
def test_a_malformed_row_is_a_shape_error_and_records_nothing(path: Path, row: object) -> None:
    with Recorder(path, COLUMNS) as recorder:
        recorder.push(np.ones(len(COLUMNS)))
        with pytest.raises(ShapeError, match=str(path)):
            recorder.push(row)  # type: ignore[arg-type]
        recorder.push(2 * np.ones(len(COLUMNS)))
    _, data = read_recording(path)
    assert_bitwise_equal(data, np.array([np.ones(len(COLUMNS)), 2 * np.ones(len(COLUMNS))]))


@pytest.mark.parametrize(
    ("columns", "kwargs", "message"),
    [
        ((), {}, "at least one column"),
        (("a", "a"), {}, "appear more than once"),
        (("a", ""), {}, "non-empty"),
        (("a",), {"block_rows": 0}, "block_rows"),
        (("a",), {"max_queued_blocks": 1}, "max_queued_blocks"),
        (("a",), {"fsync_every_blocks": 0}, "fsync_every_blocks"),
    ],
)
def test_bad_settings_are_refused(path: Path, columns: tuple[str, ...], kwargs: dict[str, int], message: str) -> None:
    with pytest.raises(UsageError, match=message):
        Recorder(path, columns, **kwargs)


def test_fsync_every_n_blocks_and_at_close(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    recorder = Recorder(path, COLUMNS, block_rows=10, max_queued_blocks=20, fsync_every_blocks=3)
    calls = []
    original = recorder._sync

    def counting_sync() -> None:
        calls.append(recorder.rows_written)
        original()

    monkeypatch.setattr(recorder, "_sync", counting_sync)
    with recorder:
        for row in counting_rows(100, len(COLUMNS)):
            recorder.push(row)
    assert calls == [30, 60, 90, 100]  # after blocks 3, 6, 9 and at close


# --- crash safety --------------------------------------------------------------------------

CRASH_CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from daror_runtime.data.recorder import Recorder

    path, n_columns, rate_hz = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    recorder = Recorder(path, [f"c{k}" for k in range(n_columns)], block_rows=100, max_queued_blocks=64)
    recorder.start()
    scale = np.arange(1, n_columns + 1, dtype=float)
    row = np.empty(n_columns)
    period = 1.0 / rate_hz
    deadline = time.perf_counter()
    i = 0
    while True:  # a 1 kHz loop that never ends by itself: only SIGKILL stops it
        np.multiply(scale, float(i), out=row)
        if not recorder.push(row):
            sys.exit(3)  # a drop would break the contiguity the parent checks
        i += 1
        deadline += period
        delay = deadline - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    """
)


@pytest.mark.subprocess
def test_kill_9_leaves_every_complete_row_readable_and_exact(tmp_path: Path) -> None:
    path = tmp_path / "crash.rec"
    n_columns, target_rows = 13, 3000
    child = subprocess.Popen(
        [sys.executable, "-c", CRASH_CHILD, str(path), str(n_columns), "1000"],
        cwd=REPO,
        stderr=subprocess.PIPE,
    )
    try:

        def enough_rows() -> bool:
            if child.poll() is not None:
                pytest.fail(f"recording process ended by itself ({child.returncode}): {child.stderr.read().decode()}")  # type: ignore[union-attr]
            try:
                return inspect_recording(path).n_rows >= target_rows
            except DataError:
                return False  # not created, or the header not written yet

        wait_for(enough_rows, timeout_s=60.0, what=f"{target_rows} rows in the recording")
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=10.0)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        child.stderr.close()  # type: ignore[union-attr]
    assert child.returncode == -signal.SIGKILL

    info = inspect_recording(path)
    columns, data = read_recording(path)
    assert columns == tuple(f"c{k}" for k in range(n_columns)), "header damaged"
    assert info.n_rows == data.shape[0] >= target_rows
    # Every complete row is there, exact, contiguous from 0; nothing partial is returned.
    assert_bitwise_equal(data, counting_rows(data.shape[0], n_columns))
    # Blocks are written whole unless the kill lands inside a write; either way only whole rows count.
    assert info.tail_bytes < n_columns * 8


def _recording_of(tmp_path: Path, n_rows: int, n_columns: int) -> Path:
    path = tmp_path / "whole.rec"
    with Recorder(path, [f"c{k}" for k in range(n_columns)], block_rows=32) as recorder:
        for row in counting_rows(n_rows, n_columns):
            recorder.push(row)
    return path


@given(cut=st.integers(min_value=0, max_value=100 * 5 * 8))
def test_a_truncated_tail_is_ignored_never_misread(tmp_path_factory: pytest.TempPathFactory, cut: int) -> None:
    directory = tmp_path_factory.getbasetemp() / "truncation"
    directory.mkdir(exist_ok=True)
    whole = directory / "whole.rec"
    if not whole.exists():
        _recording_of(directory, 100, 5)
    offset = inspect_recording(whole).data_offset
    cut_path = directory / "cut.rec"
    cut_path.write_bytes(whole.read_bytes()[: offset + cut])
    info = inspect_recording(cut_path)
    columns, data = read_recording(cut_path)
    assert columns == tuple(f"c{k}" for k in range(5))
    assert (info.n_rows, info.tail_bytes) == divmod(cut, 5 * 8)
    assert_bitwise_equal(data, counting_rows(cut // 40, 5))


def test_a_hand_truncated_file_keeps_its_complete_rows(tmp_path: Path) -> None:
    path = _recording_of(tmp_path, 100, 5)
    offset = inspect_recording(path).data_offset
    with open(path, "r+b") as handle:
        handle.truncate(offset + 37 * 40 + 21)  # 37 rows and 21 bytes of the 38th
    info = inspect_recording(path)
    assert (info.n_rows, info.tail_bytes) == (37, 21)
    _, data = read_recording(path)
    assert_bitwise_equal(data, counting_rows(37, 5))
    _, mapped = read_recording(path, mmap=True)
    assert_bitwise_equal(np.asarray(mapped), counting_rows(37, 5))


def _damage(content: bytes) -> Callable[[bytes], bytes]:
    return lambda original: content + original[original.index(b"\n") + 1 :]


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda original: b"", "file is empty"),
        (lambda original: original[:30], "no end of line"),
        (lambda original: b"\x00\x01\x02" + original[3:], "not JSON"),
        (_damage(b'["a list"]\n'), "not a JSON object"),
        (_damage(b'{"format": "csv"}\n'), "format is 'csv'"),
        (_damage(b'{"format": "daror-recording", "format_version": 2}\n'), "format_version 2"),
        (_damage(b'{"format": "daror-recording", "format_version": 1, "columns": []}\n'), "'columns'"),
        (
            _damage(b'{"format": "daror-recording", "format_version": 1, "columns": ["a"], "dtype": ">f4"}\n'),
            "dtype '>f4'",
        ),
    ],
    ids=["empty", "cut-header", "binary", "list", "other-format", "newer-version", "no-columns", "dtype"],
)
def test_a_damaged_header_is_a_data_error_naming_the_file(
    tmp_path: Path, damage: Callable[[bytes], bytes], message: str
) -> None:
    path = _recording_of(tmp_path, 10, 5)
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(DataError, match=message) as raised:
        read_recording(path)
    assert str(path) in str(raised.value)


def test_a_missing_recording_is_a_data_error(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="file not found"):
        read_recording(tmp_path / "nothing.rec")


def test_a_non_recording_binary_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "blob.rec"
    path.write_bytes(os.urandom(4096).replace(b"\n", b"x"))
    with pytest.raises(DataError, match="damaged recording header"):
        read_recording(path)


# --- raw logs ------------------------------------------------------------------------------


def test_the_tick_row_puts_every_value_under_its_name() -> None:
    """One layout: the names, the index constants and the compiled fill agree, and the raw-log part
    is named as a raw log names it."""
    columns = RECORD_COLUMNS
    assert columns[:13] == ("t", "q1", "q2", "q3", "q4", "dq1", "dq2", "dq3", "dq4", "tau1", "tau2", "tau3", "tau4")
    assert columns[13:21] == ("theta1", "theta2", "theta3", "theta4", "tau_cmd1", "tau_cmd2", "tau_cmd3", "tau_cmd4")
    assert columns[21:] == ("enable", "faulted", "lateness_s")
    assert len(columns) == len(set(columns)) == tick_row.N_RECORD_COLUMNS
    for name, index in (
        ("t", tick_row.T_INDEX),
        ("enable", tick_row.ENABLE_INDEX),
        ("faulted", tick_row.FAULTED_INDEX),
        ("lateness_s", tick_row.LATENESS_INDEX),
    ):
        assert columns[index] == name
    for prefix, group in (
        ("q", tick_row.Q_SLICE),
        ("dq", tick_row.DQ_SLICE),
        ("tau", tick_row.TAU_SLICE),
        ("theta", tick_row.THETA_SLICE),
        ("tau_cmd", tick_row.TAU_CMD_SLICE),
    ):
        assert columns[group] == tuple(f"{prefix}{j}" for j in range(1, 5))
    row = np.full(len(columns), -1.0)
    q, dq, tau, theta, tau_cmd = (np.array([k + 0.1, k + 0.2, k + 0.3, k + 0.4]) for k in range(5))
    fill_tick_row_at(row[None, :], 0, 2.5, q, dq, tau, theta, tau_cmd, 1.0, 0.0, 0.003)
    named = dict(zip(columns, row, strict=True))
    assert named["t"] == 2.5
    assert [named[f"q{j}"] for j in range(1, 5)] == [0.1, 0.2, 0.3, 0.4]
    assert [named[f"dq{j}"] for j in range(1, 5)] == [1.1, 1.2, 1.3, 1.4]
    assert [named[f"tau{j}"] for j in range(1, 5)] == [2.1, 2.2, 2.3, 2.4]
    assert [named[f"theta{j}"] for j in range(1, 5)] == [3.1, 3.2, 3.3, 3.4]
    assert [named[f"tau_cmd{j}"] for j in range(1, 5)] == [4.1, 4.2, 4.3, 4.4]
    assert (named["enable"], named["faulted"], named["lateness_s"]) == (1.0, 0.0, 0.003)


def test_a_recorded_raw_log_reduces_to_the_same_stationary_points(path: Path, exo: Scenario) -> None:
    stops = np.array([[0.0, 0.3, 0.0, 0.6], [0.2, 0.5, 0.1, 0.9], [0.1, 0.2, -0.1, 1.2], [0.3, 0.4, 0.0, 0.8]])
    log = quasi_static_log(exo, stops, stream(exo.seed, 7), QuasiStaticSettings(rate_hz=1000.0, dwell_s=1.0))
    row = np.empty(len(RECORD_COLUMNS))
    tau_cmd = np.empty((len(log.t_s), 4))
    with Recorder(path, RECORD_COLUMNS, block_rows=500, max_queued_blocks=len(log.t_s) // 500 + 2) as recorder:
        for i in range(len(log.t_s)):  # the loop's rows, as the loop fills them
            tau_cmd[i] = log.tau_nm[i] + 0.01 * i
            fill_tick_row_at(
                row[None, :],
                0,
                log.t_s[i],
                log.q_rad[i],
                log.dq_rad_s[i],
                log.tau_nm[i],
                log.theta_rad[i],
                tau_cmd[i],
                1.0,
                0.0,
                0.0,
            )
            recorder.push(row)
    assert recorder.dropped_rows == 0

    raw = recording_to_raw_log(path)
    assert isinstance(raw, RawLog)
    assert raw.source == str(path)
    assert_bitwise_equal(raw.t_s, log.t_s)
    assert_bitwise_equal(raw.q_rad, log.q_rad)
    assert_bitwise_equal(raw.dq_rad_s, log.dq_rad_s)
    assert_bitwise_equal(raw.tau_nm, log.tau_nm)
    assert raw.theta_rad is not None
    assert_bitwise_equal(raw.theta_rad, log.theta_rad)
    assert raw.tau_cmd_nm is not None
    assert_bitwise_equal(raw.tau_cmd_nm, tau_cmd)
    from_recording = reduce_to_stationary(raw)
    direct = reduce_to_stationary(RawLog(log.t_s, log.q_rad, log.dq_rad_s, log.tau_nm, log.theta_rad))
    assert len(from_recording) > 0
    assert_bitwise_equal(from_recording.q_rad, direct.q_rad)
    assert_bitwise_equal(from_recording.tau_nm, direct.tau_nm)


def test_recording_to_raw_log_maps_renamed_columns_and_refuses_what_is_missing(tmp_path: Path) -> None:
    n = 300
    t = np.arange(n) * 1e-3
    rng = np.random.default_rng(3)
    values = rng.uniform(-1, 1, size=(n, 12))
    renamed = tmp_path / "renamed.rec"
    with Recorder(renamed, ("time_s", *RAW_REQUIRED[1:])) as recorder:
        for i in range(n):
            recorder.push(np.concatenate([[t[i]], values[i]]))
    raw = recording_to_raw_log(renamed, {"t": "time_s"})
    assert_bitwise_equal(raw.t_s, t)
    assert_bitwise_equal(raw.tau_nm, values[:, 8:12])
    assert raw.theta_rad is None
    assert raw.tau_cmd_nm is None
    with pytest.raises(DataError, match=r"missing column\(s\) t;"):
        recording_to_raw_log(renamed)
    with pytest.raises(DataError, match="mapped column"):
        recording_to_raw_log(renamed, {"t": "clock"})
    with pytest.raises(DataError, match="not raw-log columns"):
        recording_to_raw_log(renamed, {"time": "time_s"})

    degrees = tmp_path / "degrees.rec"
    shutil.copy(renamed, degrees)
    info = inspect_recording(degrees)
    with open(degrees, "r+b") as handle:  # q1 of row 5 set to 45 (degrees, not radians)
        handle.seek(info.data_offset + (4 * 13 + 1) * 8)
        handle.write(np.array([45.0], dtype="<f8").tobytes())
    with pytest.raises(DataError, match=r"row 5, column q1: angle 45 is beyond 2 pi"):
        recording_to_raw_log(degrees, {"t": "time_s"})

    gaps = tmp_path / "gaps.rec"  # the loop records NaN (and the previous t) for a tick without a sample
    with Recorder(gaps, (*RAW_REQUIRED, "enable")) as recorder:
        for i in range(n):
            values_i = np.full(12, np.nan) if i in (7, 8, 100) else values[i]
            recorder.push(np.concatenate([[t[i - 1 if i in (7, 8, 100) else i]], values_i, [1.0]]))
    with pytest.raises(DataError, match=r"gaps\.rec: row 8, column t"):
        recording_to_raw_log(gaps)
    kept = np.setdiff1d(np.arange(n), [7, 8, 100])
    raw = recording_to_raw_log(gaps, drop_nan_rows=True)
    assert_bitwise_equal(raw.t_s, t[kept])
    assert_bitwise_equal(raw.q_rad, values[kept, :4])
    info = inspect_recording(gaps)
    with open(gaps, "r+b") as handle:  # an infinite torque is a fault, not a missing sample
        handle.seek(info.data_offset + (50 * 14 + 9) * 8)
        handle.write(np.array([np.inf], dtype="<f8").tobytes())
    with pytest.raises(DataError, match="row 51, column tau1: an infinite value"):
        recording_to_raw_log(gaps, drop_nan_rows=True)

    empty = tmp_path / "empty.rec"
    with Recorder(empty, RECORD_COLUMNS):
        pass
    with pytest.raises(DataError, match="no complete row"):
        recording_to_raw_log(empty)
