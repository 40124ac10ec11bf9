"""The master's side of the bus: frames in (drained once per tick), frames out, the traffic log.

Two ways to receive, one interface (:class:`FrameSource`): drain what arrived since the last tick.

* :class:`PolledFrames` reads the bus in the tick (``recv(timeout=0)`` until empty): no thread at
  all, so a lock-step run over simulated drives processes every frame in one fixed order.
* :class:`ListenedFrames` lets python-can's ``Notifier`` thread receive, as on real hardware (a
  slow tick does not let the controller's buffer overflow). Its listener only stores the COB-ID,
  the bytes and the time the frame was received; an exception in the receive thread (python-can
  ends the thread on one) is latched and raised by the next drain, so the tick learns of it at
  once instead of reading an empty bus forever. Start-up (outside the tick) waits for answers
  with :meth:`ListenedFrames.wait`, woken by the frame that arrives rather than polling; the tick
  never waits (the listener sets the waiter's event only while a start-up waits).

A frame's time is the interface's receive time (``msg.timestamp``: socketcan's kernel stamp,
SO_TIMESTAMPNS), put on the master's clock by its age (:class:`ReceiveClock`, D153), so that the
TPDO latency the master reports is the bus's and not how late Python took the frame. A stamp that
is missing or not plausible is replaced by the time the frame was taken, and counted.

Error frames (``is_error_frame``: socketcan's controller events, linux/can/error.h) are kept apart
for the bus's health (:meth:`FrameSource.take_error_frames`, :mod:`hal.canopen.health`); remote and
extended frames are dropped (the DAROR bus carries standard data frames only).

Software filters are never set on a bus we drain: python-can's ``recv(timeout=0)`` returns None
at the first frame a filter rejects, even with matching frames queued behind it.

:class:`TrafficLog` writes every frame the master sends or receives in candump's ``-L`` format
as python-can's ``CanutilsLogWriter`` writes them, stamped ``epoch_s + robot time`` (docs/canopen.md: the
standard tools read a log whose first second is not 0); the lines are formatted and written by a
process of their own (:mod:`hal.canopen.traffic_writer`), off the GIL the tick needs.
"""

from __future__ import annotations

import locale
import marshal
import os
import subprocess
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from itertools import repeat, starmap
from pathlib import Path
from typing import IO, cast

import can

from hal.canopen.traffic_writer import LENGTH
from hal.errors import HalError

__all__ = ["Frame", "FrameSource", "ListenedFrames", "PolledFrames", "ReceiveClock", "TrafficLog"]


#: One received frame: ``(COB-ID, data, the time it was received in s on the source's clock)``. A plain tuple,
#: not a NamedTuple: the bus log ships a received batch to its writer process as it is (``marshal`` takes
#: tuples of its own types only), instead of a tuple rebuilt per frame in the tick (issue 25).
Frame = tuple[int, bytes, float]


class ReceiveClock:
    """A frame's receive time on the master's clock, from the interface's stamp (see the module docstring).

    The stamp (``msg.timestamp``, s) is on the interface's clock: socketcan's is the kernel's wall
    clock (CLOCK_REALTIME). Its age is read on that same clock when the frame is taken, and the
    frame's time is the master's now less that age: no offset is kept that an NTP step or slew
    could make wrong over a session. A stamp whose age is negative beyond :data:`FUTURE_S`, or
    over :data:`MAX_AGE_S` (a missing stamp, 0; an interface whose clock is not the wall clock;
    a clock stepped between the stamp and now), is not used: the frame takes the time it was
    taken, and :attr:`fallbacks` counts it.

    Args:
        now: the master's clock, s.
        wall: the clock the interface's stamps are on, s (``time.time``).
    """

    #: A stamp this far ahead of the wall clock is still taken as now (the clocks' granularity), s.
    FUTURE_S = 0.002
    #: A frame stamped longer ago than this is not believed, s: the receive thread takes frames
    #: within milliseconds; a second is a stamp on another clock.
    MAX_AGE_S = 1.0

    def __init__(self, now: Callable[[], float], wall: Callable[[], float] = time.time) -> None:
        self._now = now
        self._wall = wall
        self.fallbacks = 0
        self.stamped = 0

    def __call__(self, stamp_s: float) -> float:
        """The master's time at which a frame stamped ``stamp_s`` (interface clock) was received."""
        now = self._now()
        age = self._wall() - stamp_s
        if -self.FUTURE_S <= age <= self.MAX_AGE_S:
            self.stamped += 1
            return now - max(age, 0.0)
        self.fallbacks += 1
        return now


class FrameSource(ABC):
    """Frames that arrived since the last :meth:`drain`, and the error frames among them."""

    def receive_time_report(self) -> dict[str, object]:
        """How the frames' receive times were taken (for the bus report)."""
        return {"source": "the tick's time when drained (lock-step: the bus has no time of its own)"}

    def take_error_frames(self) -> list[tuple[int, bytes]]:
        """The error frames (CAN id, data) received since the last call, in arrival order (none: a source
        that sees none)."""
        return []

    @abstractmethod
    def drain(self) -> list[Frame]:
        """Every frame received since the last call, in arrival order.

        Raises:
            HalError: the receiving side failed (the message says how); latched, raised once.
        """

    def close(self) -> None:  # noqa: B027 - a default: a polled source has nothing to stop
        """Stop receiving (a thread is stopped; a polled source does nothing)."""


def _take_all(errors: deque[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
    taken = []
    while errors:  # deque pops are atomic: a receive thread may append meanwhile
        taken.append(errors.popleft())
    return taken


class PolledFrames(FrameSource):
    """Reads the bus itself, in the caller's thread (lock-step: no thread, a fixed order).

    Args:
        bus: the master's bus.
        now: the time a frame is stamped with when it is drained (robot time in lock-step).
    """

    def __init__(self, bus: can.BusABC, now: Callable[[], float]) -> None:
        self._recv = bus.recv
        self._now = now
        self._errors: deque[tuple[int, bytes]] = deque()

    def take_error_frames(self) -> list[tuple[int, bytes]]:
        return _take_all(self._errors)

    def drain(self) -> list[Frame]:
        frames = []
        recv = self._recv
        now = self._now()
        while True:
            try:
                message = recv(timeout=0)
            except can.CanError as exc:
                raise HalError(f"reading the CAN bus failed: {exc}") from None
            if message is None:
                return frames
            if message.is_error_frame:
                self._errors.append((message.arbitration_id, bytes(message.data)))
                continue
            if message.is_remote_frame or message.is_extended_id:
                continue  # the DAROR bus carries standard data frames only
            frames.append((message.arbitration_id, bytes(message.data), now))


class _StoringListener(can.Listener):
    """Runs in python-can's receive thread: stores the frame, nothing else, and keeps the thread alive."""

    def __init__(
        self,
        frames: deque[Frame],
        errors: list[BaseException],
        clock: ReceiveClock,
        error_frames: deque[tuple[int, bytes]],
    ) -> None:
        self._frames = frames
        self._errors = errors
        self._clock = clock
        self._error_frames = error_frames
        self.failures = 0
        #: Set after each frame or failure stored while a start-up waits (:meth:`ListenedFrames.wait`); None
        #: otherwise (the tick: one attribute read a frame, no lock).
        self.waiter: threading.Event | None = None

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self._error_frames.append((msg.arbitration_id, bytes(msg.data)))
        elif not (msg.is_remote_frame or msg.is_extended_id):
            self._frames.append((msg.arbitration_id, bytes(msg.data), self._clock(msg.timestamp)))
        else:
            return
        waiter = self.waiter  # read after the append: a waiter that missed the frame in its check is woken
        if waiter is not None:
            waiter.set()

    def on_error(self, exc: Exception) -> None:
        # Latched (the first one; the tick raises it) and handled, so python-can keeps the thread
        # alive for a bus that recovers. A bus that keeps failing would make python-can retry at
        # once, forever: a pause bounds that spin to a hundred tries a second.
        if not self._errors:
            self._errors.append(exc)
        waiter = self.waiter
        if waiter is not None:
            waiter.set()
        self.failures += 1
        time.sleep(0.01)


class ListenedFrames(FrameSource):
    """python-can's ``Notifier`` receives in its own thread; the tick drains what it stored.

    Args:
        bus: the master's bus.
        now: the master's clock (wall time since the backend opened), s: a frame's receive time is
            put on it (:class:`ReceiveClock`).
        wall: the clock of the interface's stamps, s.
    """

    def __init__(self, bus: can.BusABC, now: Callable[[], float], wall: Callable[[], float] = time.time) -> None:
        self._frames: deque[Frame] = deque()
        self._failures: list[BaseException] = []
        self._errors: deque[tuple[int, bytes]] = deque()
        self.clock = ReceiveClock(now, wall)
        self._listener = _StoringListener(self._frames, self._failures, self.clock, self._errors)
        self._notifier = can.Notifier(bus, [self._listener], timeout=0.05)
        self._reported = False
        self._arrived = threading.Event()

    def wait(self, timeout_s: float) -> float:
        """Start-up only: wait until a frame (or an error frame, or a failure of the receive thread) is
        stored, at most ``timeout_s``; the time waited, s.

        Returns at once when a frame the last :meth:`drain` did not take, or a failure it did not raise,
        is already there. The master's start-up waits with it between its polls (the ``wait`` of
        :class:`hal.canopen.master.CanMaster`): woken by the answer it waits for instead of sleeping a
        fixed step, and counting the time it really waited against its timeouts. Never called in the
        tick (it would block it).
        """
        began = time.monotonic()
        arrived = self._arrived
        arrived.clear()
        self._listener.waiter = arrived  # from now on a stored frame sets it: checked below, then waited for
        try:
            if self._frames or (not self._reported and (self._failures or self._notifier.exception is not None)):
                return 0.0  # for the next drain (error frames are not what a start-up waits for: no early return)
            arrived.wait(timeout_s)
        finally:
            self._listener.waiter = None
        return time.monotonic() - began

    def drain(self) -> list[Frame]:
        frames = []
        popleft = self._frames.popleft
        while self._frames:  # deque appends and pops are atomic: the thread never waits on the tick
            frames.append(popleft())
        failure = self._failures[0] if self._failures else self._notifier.exception
        if failure is not None and not self._reported:
            self._reported = True
            raise HalError(f"the CAN receive thread failed: {type(failure).__name__}: {failure}")
        return frames

    def take_error_frames(self) -> list[tuple[int, bytes]]:
        return _take_all(self._errors)

    def receive_time_report(self) -> dict[str, object]:
        return {
            "source": "the interface's receive stamp (msg.timestamp), put on the master's clock by its age",
            "stamped": self.clock.stamped,
            "fallbacks": self.clock.fallbacks,
        }

    def close(self) -> None:
        self._notifier.stop(timeout=1.0)


class TrafficLog:
    """Every frame on the master's side of the bus, in candump ``-L`` format (python-can's writer's lines).

    The tick only appends the frame to a queue (:meth:`frame`, :meth:`received`: no I/O, never
    waits). A writer thread takes what is queued every :data:`WRITE_EVERY_S` and ships it, one
    ``marshal`` of the batch's tuples a write, down a pipe to a writer process of its own
    (:mod:`hal.canopen.traffic_writer`, standard library only), which formats the lines as
    python-can's ``CanutilsLogWriter`` does and writes each batch with one write, flushed: the
    formatting runs on another core, not in a thread that holds the GIL the tick needs (the thread
    holds it under 0.1 us a frame; docs/performance.md). A write that fails, or a writer process that
    ends before :meth:`close`, is latched (:attr:`error`): the backend raises it as a fault at the
    next read, as the recorder's failure is one (the audit trail is part of the run).

    The file is created (or, with ``append``, opened) here, before the writer process starts, and
    handed to it: an existing log is never overwritten, and a log that cannot be created raises here.
    If this process dies, the writer reads the end of its input, writes what it was given (the frames
    still queued here, at most :data:`WRITE_EVERY_S` of them, are lost), closes the log and exits; it
    ignores SIGINT, SIGTERM and SIGHUP (they reach the whole process group, and the session closes
    the log in order).

    A path ending in ``.gz`` is written gzip-compressed by the writer process (level
    :data:`GZIP_LEVEL`, each batch flushed to the OS as a whole deflate block, so a crash loses
    no more than a plain log does): ``zcat can.log.gz | canplayer vcan0=daror`` and ``log2asc``
    read it from their standard input, Python's ``gzip.open`` directly (docs/canopen.md, D137). A log
    opened again with ``append`` gets a second gzip member, which every reader concatenates.

    Args:
        path: the log file (``.gz``: compressed); it must not exist (a log is never overwritten) unless ``append``.
        epoch_s: whole seconds added to robot time in the log (the session's start, Unix time).
        channel: the interface name written on every line.
        append: continue an existing log (the same backend opened again).

    Raises:
        HalError: the file exists (and not ``append``), cannot be created or opened, or the writer
            process cannot be started.
    """

    #: How often the writer thread ships what the tick queued to the writer process, s.
    WRITE_EVERY_S = 0.02
    #: zlib's level for a ``.gz`` log (docs/performance.md: size and time of levels 1 and 6).
    GZIP_LEVEL = 6
    #: The writer process's script (standard library only, run with ``python -I -S``).
    WRITER_SCRIPT = Path(__file__).with_name("traffic_writer.py")

    def __init__(self, path: Path, epoch_s: int, channel: str = "can0", append: bool = False) -> None:
        self.path = Path(path)
        self.epoch_s = int(epoch_s)
        flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | (0 if append else os.O_EXCL)
        try:
            fd = os.open(self.path, flags, 0o666)  # a new file unless append: an existing log is never overwritten
        except FileExistsError:
            raise HalError(f"{self.path}: exists; the bus log is not overwritten: expected a new file") from None
        except OSError as exc:
            raise HalError(f"{self.path}: cannot be {'opened' if append else 'created'} ({exc.strerror})") from None
        gz = self.path.suffix == ".gz"
        # the lines' encoding as before the writer process: gzip.open's ascii, python-can's writer the locale's
        encoding = "ascii" if gz else locale.getpreferredencoding(False)
        command = [sys.executable, "-I", "-S", str(self.WRITER_SCRIPT), str(fd), str(self.path), str(self.epoch_s)]
        command += [channel, str(self.GZIP_LEVEL) if gz else "plain", encoding]
        try:
            self._process = subprocess.Popen(
                command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, pass_fds=(fd,)
            )
        except (OSError, ValueError) as exc:
            raise HalError(f"{self.path}: the bus log's writer process cannot be started ({exc})") from None
        finally:
            os.close(fd)  # the writer process has its own
        self._to_writer = cast(IO[bytes], self._process.stdin).fileno()  # stdin=PIPE: always a pipe
        # a frame (cob_id, data, robot_t_s, sent), or a list of received frames as drained (the writer's protocol)
        self._pending: deque[tuple[int, bytes, float, bool] | list[Frame]] = deque()
        self.error: str | None = None
        #: Lines in the file, as the writer process reports at its end (after :meth:`close`).
        self.frames_written = 0
        self._ended = False  # the writer process has ended and its report is read
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="CAN traffic log", daemon=True)
        self._thread.start()

    def frame(self, cob_id: int, data: bytes, robot_t_s: float, sent: bool) -> None:
        """Queue one frame the master sent (``sent``) or received, at robot time ``robot_t_s`` (never waits).

        The values are Python's own int, bytes, float and bool (``marshal`` ships them; the writer
        latches a frame of other types, a numpy scalar, as an :attr:`error`).
        """
        self._pending.append((cob_id, data, robot_t_s, sent))

    def received(self, frames: list[Frame]) -> None:
        """Queue frames the master received, each at its own time (never waits).

        The list is queued as it is (one append a tick, not a tuple per frame): the caller does not
        change it afterwards (a drained list is the caller's own, read only).
        """
        self._pending.append(frames)

    def _run(self) -> None:
        while not self._stop.wait(self.WRITE_EVERY_S):
            self._ship_pending()
        self._ship_pending()
        self._end_writer()

    def _ship_pending(self) -> None:
        """Send what is queued to the writer process as one batch (drop it once the log has failed)."""
        pending = self._pending
        if not self._ended and self._process.poll() is not None:
            self._end_writer()  # it ended before close(): killed, or it reported a failed write
        if self.error is not None:
            pending.clear()
            return
        count = len(pending)
        if not count:
            return
        # the oldest ``count`` frames, popped in C (only this thread pops; the tick may append meanwhile)
        batch = list(starmap(pending.popleft, repeat((), count)))
        try:
            payload = marshal.dumps(batch)
        except ValueError as exc:  # a frame of a type marshal does not know
            self._latch(f"a frame cannot be sent to the writer process ({exc})")
            return
        message = memoryview(LENGTH.pack(len(payload)) + payload)
        try:
            while message:  # a pipe takes at most its capacity a write: the rest once the writer read it
                message = message[os.write(self._to_writer, message) :]
        except OSError:  # a broken pipe: the writer process has ended
            self._end_writer()

    def _end_writer(self) -> None:
        """Close the writer process's input, wait for it to end, and take its report (count, failure)."""
        if self._ended:
            return
        self._ended = True
        process = self._process
        try:
            out, err = process.communicate()  # closes its input: it writes what it was given, and ends
        except OSError:
            out, err = b"", b""
        try:
            written, failure = marshal.loads(out)
        except (EOFError, ValueError, TypeError):  # no report: it died
            written, failure = None, None
        if isinstance(written, int):
            self.frames_written = written
        if failure:
            self._latch(f"the bus log cannot be written: {failure}")
        elif written is None or process.returncode != 0 or not self._stop.is_set():
            code = process.returncode
            how = f"killed by signal {-code}" if code is not None and code < 0 else f"exit status {code}"
            said = err.decode(errors="replace").split("\n")
            last = next((line.strip() for line in reversed(said) if line.strip()), "")
            self._latch(
                f"the bus log's writer process (pid {process.pid}) ended unexpectedly ({how}{': ' + last if last else ''})"
            )

    def _latch(self, message: str) -> None:
        """Keep the first failure, one line naming the log (:attr:`error`)."""
        self.error = self.error or f"{self.path}: {' '.join(message.split())}"

    def close(self) -> None:
        """Write what is queued, close the log and wait for the writer process to end. Safe twice.

        :attr:`frames_written` is the writer's count after it; a failure is latched in :attr:`error`.
        """
        if self._thread.is_alive():
            self._stop.set()
            self._thread.join()
        self._end_writer()  # the thread does it; here too should the thread have died
