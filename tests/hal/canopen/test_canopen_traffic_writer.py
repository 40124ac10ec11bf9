"""The traffic log's writer process (hal/canopen/traffic_writer.py): the same bytes, its failures latched, its end."""

from __future__ import annotations

import gzip
import io
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from hal.canopen.bus import TrafficLog
from hal.canopen.traffic_writer import LineFormatter

EPOCH = 1_700_000_000

#: A few frames of each kind: sent and received, no data to 8 bytes, a time before the first frame's,
#: frames sharing a time, a time with more digits than %f keeps.
FRAMES: list[tuple[int, bytes, float, bool]] = [
    (0x080, b"", 0.5, True),
    (0x705, b"\x05", 0.25, False),
    (0x181, bytes(range(8)), 0.5, False),
    (0x201, b"\xff\x00\x7f", 0.5025, True),
    (0x000, b"\x01\x02", 0.5025, True),
    (0x7FF, b"\xab", 123.4567891, False),
    (0x581, b"\x43\x17\x10\x00\x64\x00\x00\x00", 1e-7 + 123.4567891, False),
]


def _python_can_lines(frames: list[tuple[int, bytes, float, bool]], channel: str) -> str:
    stream = io.StringIO()
    writer = can.CanutilsLogWriter(stream, channel=channel)
    for cob_id, data, t_s, sent in frames:
        message = can.Message(
            timestamp=EPOCH + t_s,
            arbitration_id=cob_id,
            data=data,
            is_extended_id=False,
            is_rx=not sent,
            channel=channel,
        )
        writer.on_message_received(message)
    return stream.getvalue()


def _wait_for(condition: Callable[[], object], within_s: float = 10.0) -> None:
    deadline = time.monotonic() + within_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)


def test_the_formatter_writes_python_cans_lines() -> None:
    for channel in ("can0", "3", "daror"):
        formatter = LineFormatter(EPOCH, channel)
        text = formatter.lines(FRAMES[:3]) + formatter.lines(FRAMES[3:])  # its state carries from batch to batch
        assert text == _python_can_lines(FRAMES, channel)


def test_a_gzip_log_holds_python_cans_lines_and_a_second_open_adds_a_member(tmp_path: Path) -> None:
    path = tmp_path / "bus.log.gz"
    first = TrafficLog(path, epoch_s=EPOCH, channel="7")
    for frame in FRAMES:
        first.frame(*frame)
    first.close()
    again = TrafficLog(path, epoch_s=EPOCH, channel="7", append=True)
    again.received([])
    again.frame(0x080, b"", 200.0, sent=True)
    again.close()
    assert (first.frames_written, again.frames_written, first.error, again.error) == (len(FRAMES), 1, None, None)
    expected = _python_can_lines(FRAMES, "7") + _python_can_lines([(0x080, b"", 200.0, True)], "7")
    assert gzip.decompress(path.read_bytes()).decode("ascii") == expected
    assert path.read_bytes().count(b"\x1f\x8b\x08\x08") == 2  # two members, each with the file's name
    assert b"bus.log\x00" in path.read_bytes()[:30]  # the header names the file as gzip.open does


def test_many_frames_in_batches_larger_than_a_pipe(tmp_path: Path) -> None:
    path = tmp_path / "bus.log"
    log = TrafficLog(path, epoch_s=EPOCH, channel="can0")
    frames = [(0x180 + k % 4, k.to_bytes(8, "little"), k * 0.0025 / 13, k % 3 == 0) for k in range(60_000)]
    for frame in frames[:30_000]:
        log.frame(*frame)  # one batch of about 900 KB, many times the pipe's 64 KB
    for start in range(30_000, 60_000, 8):  # received as the master drains them: a list of a tick's frames
        log.received([(cob_id, data, t_s) for cob_id, data, t_s, _ in frames[start : start + 8]])
    log.close()
    expected = _python_can_lines(frames[:30_000], "can0") + _python_can_lines(
        [(c, d, t, False) for c, d, t, _ in frames[30_000:]], "can0"
    )
    assert path.read_text() == expected
    assert log.frames_written == len(frames)


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs Linux's /dev/full (every write: no space left)")
def test_a_write_that_fails_in_the_writer_is_latched_naming_the_log() -> None:
    log = TrafficLog(Path("/dev/full"), epoch_s=EPOCH, append=True)  # a full disk
    log.frame(0x080, b"", 0.0, sent=True)
    _wait_for(lambda: log.error is not None)
    assert log.error == "/dev/full: the bus log cannot be written: [Errno 28] No space left on device"
    log.frame(0x080, b"", 0.0025, sent=True)  # the tick goes on queueing: dropped, the error stays
    log.close()
    log.close()
    assert log.error == "/dev/full: the bus log cannot be written: [Errno 28] No space left on device"
    assert log.frames_written == 0


def test_a_writer_process_that_is_killed_is_latched_naming_the_log(tmp_path: Path) -> None:
    path = tmp_path / "bus.log"
    log = TrafficLog(path, epoch_s=EPOCH)
    log.frame(0x080, b"", 0.0, sent=True)
    _wait_for(lambda: path.stat().st_size > 0)
    assert log.error is None
    pid = log._process.pid
    os.kill(pid, signal.SIGKILL)
    _wait_for(lambda: log.error is not None)  # noticed by the writer thread, with no frame queued
    assert log.error == f"{path}: the bus log's writer process (pid {pid}) ended unexpectedly (killed by signal 9)"
    assert "\n" not in log.error
    log.frame(0x080, b"", 0.0025, sent=True)
    log.close()
    log.close()
    assert path.read_text() == "(1700000000.000000) can0 080# T\n"


def test_ctrl_c_and_a_service_stop_do_not_end_the_writer(tmp_path: Path) -> None:
    path = tmp_path / "bus.log.gz"
    log = TrafficLog(path, epoch_s=EPOCH)
    log.frame(0x080, b"", 0.0, sent=True)
    _wait_for(lambda: path.stat().st_size > 10)  # the writer is running (the gzip header is written)
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        os.kill(log._process.pid, signum)  # what reaches the whole process group
    log.frame(0x080, b"", 0.0025, sent=True)
    log.close()
    assert log.error is None
    assert log.frames_written == 2
    assert gzip.decompress(path.read_bytes()).decode().splitlines() == [
        "(1700000000.000000) can0 080# T",
        "(1700000000.002500) can0 080# T",
    ]


def test_a_frame_marshal_sends_as_bytes_is_latched_not_written_wrong(tmp_path: Path) -> None:
    np = pytest.importorskip("numpy")
    path = tmp_path / "bus.log"
    log = TrafficLog(path, epoch_s=EPOCH)
    log.frame(0x080, b"", np.float64(0.5), sent=True)  # marshal sends a numpy scalar as its 8 bytes
    log.close()
    assert log.error is not None
    assert log.error.startswith(f"{path}: the bus log cannot be written: a batch of frames cannot be written")
    assert path.read_text() == ""


@pytest.mark.subprocess
def test_a_parent_that_dies_leaves_a_complete_log_and_no_writer_behind(tmp_path: Path) -> None:
    path = tmp_path / "bus.log.gz"
    parent = textwrap.dedent(
        f"""
        import os, sys, time
        from pathlib import Path
        from hal.canopen.bus import TrafficLog
        log = TrafficLog(Path({str(path)!r}), epoch_s={EPOCH})
        for k in range(5000):
            log.frame(0x181, k.to_bytes(4, "little"), k * 0.0025, sent=False)
        while log._pending:
            time.sleep(0.005)  # taken by the writer thread
        time.sleep(0.5)  # and shipped to the writer process
        print(log._process.pid, flush=True)
        os._exit(3)  # a crash: no close(), no clean-up
        """
    )
    done = subprocess.run([sys.executable, "-c", parent], capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 3, done.stderr
    pid = int(done.stdout)

    def writer_gone() -> bool:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (FileNotFoundError, ProcessLookupError):
            return True
        return state in ("Z", "X")  # ended; a zombie until whoever adopted it reaps it

    _wait_for(writer_gone)
    assert writer_gone()
    lines = gzip.decompress(path.read_bytes()).decode().splitlines()  # the gzip member's end is written
    assert len(lines) == 5000
    assert lines[-1] == f"({EPOCH + 4999 * 0.0025:f}) can0 181#{(4999).to_bytes(4, 'little').hex().upper()} R"


@pytest.mark.subprocess
def test_the_writer_imports_the_standard_library_only(tmp_path: Path) -> None:
    read_end, write_end = os.pipe()
    os.close(write_end)  # no batch: it starts, closes the log, reports and ends
    with open(tmp_path / "bus.log", "ab") as log:
        arguments = [str(log.fileno()), str(tmp_path / "bus.log"), str(EPOCH), "can0", "plain", "ascii"]
        done = subprocess.run(
            [sys.executable, "-I", "-S", "-X", "importtime", str(TrafficLog.WRITER_SCRIPT), *arguments],
            stdin=read_end, capture_output=True, pass_fds=(log.fileno(),), timeout=30, check=False,
        )  # fmt: skip
    os.close(read_end)
    assert done.returncode == 0, done.stderr
    assert done.stdout == b")\x02\xe9\x00\x00\x00\x00N"  # marshal of (0, None)
    imported = {line.split("|")[-1].strip().split(".")[0] for line in done.stderr.decode().splitlines()[1:]}
    assert imported - set(sys.stdlib_module_names) == set()
    assert not imported & {"hal", "can", "numpy"}
