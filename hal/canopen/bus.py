"""The master's side of the bus: frames in (drained once per tick), frames out, the traffic log.

Two ways to receive, one interface (:class:`FrameSource`): drain what arrived since the last tick.

* :class:`PolledFrames` reads the bus in the tick (``recv(timeout=0)`` until empty): no thread at
  all, so a lock-step run over simulated drives processes every frame in one fixed order.
* :class:`ListenedFrames` lets python-can's ``Notifier`` thread receive, as on real hardware (a
  slow tick does not let the controller's buffer overflow). Its listener only stores the COB-ID,
  the bytes and the time the frame was received; an exception in the receive thread (python-can
  ends the thread on one) is latched and raised by the next drain, so the tick learns of it at
  once instead of reading an empty bus forever.

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
standard tools read a log whose first second is not 0).
"""

from __future__ import annotations

import gzip
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import can

from hal.errors import HalError

__all__ = ["Frame", "FrameSource", "ListenedFrames", "PolledFrames", "ReceiveClock", "TrafficLog"]


class Frame(NamedTuple):
    """One received frame: COB-ID, data, the time it was received (s, the source's clock)."""

    cob_id: int
    data: bytes
    t_s: float


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
            frames.append(Frame(message.arbitration_id, bytes(message.data), now))


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

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self._error_frames.append((msg.arbitration_id, bytes(msg.data)))
        elif not (msg.is_remote_frame or msg.is_extended_id):
            self._frames.append(Frame(msg.arbitration_id, bytes(msg.data), self._clock(msg.timestamp)))

    def on_error(self, exc: Exception) -> None:
        # Latched (the first one; the tick raises it) and handled, so python-can keeps the thread
        # alive for a bus that recovers. A bus that keeps failing would make python-can retry at
        # once, forever: a pause bounds that spin to a hundred tries a second.
        if not self._errors:
            self._errors.append(exc)
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
        listener = _StoringListener(self._frames, self._failures, self.clock, self._errors)
        self._notifier = can.Notifier(bus, [listener], timeout=0.05)
        self._reported = False

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
    """Every frame on the master's side of the bus, in candump ``-L`` format (python-can's writer).

    The tick only appends the frame to a queue (:meth:`frame`: no I/O, never waits); a writer
    thread formats the lines as python-can's ``CanutilsLogWriter`` does (:meth:`_stamp`; the writer
    owns the file) and writes them in one batch every :data:`WRITE_EVERY_S`. A write that fails is latched (:attr:`error`): the backend raises it as a
    fault at the next read, as the recorder's failure is one (the audit trail is part of the run).

    A path ending in ``.gz`` is written gzip-compressed by the same thread (level
    :data:`GZIP_LEVEL`, each write flushed to the OS as a whole deflate block, so a crash loses
    no more than a plain log does): ``zcat can.log.gz | canplayer vcan0=daror`` and ``log2asc``
    read it from their standard input, Python's ``gzip.open`` directly (docs/canopen.md, D137). A log
    opened again with ``append`` gets a second gzip member, which every reader concatenates.

    Args:
        path: the log file (``.gz``: compressed); it must not exist (a log is never overwritten) unless ``append``.
        epoch_s: whole seconds added to robot time in the log (the session's start, Unix time).
        channel: the interface name written on every line.
        append: continue an existing log (the same backend opened again).

    Raises:
        HalError: the file exists (and not ``append``) or cannot be created.
    """

    #: How often the writer thread writes what the tick queued, s.
    WRITE_EVERY_S = 0.02
    #: zlib's level for a ``.gz`` log (docs/performance.md: size and time of levels 1 and 6).
    GZIP_LEVEL = 6

    def __init__(self, path: Path, epoch_s: int, channel: str = "can0", append: bool = False) -> None:
        self.path = Path(path)
        self.epoch_s = int(epoch_s)
        if not append:
            try:
                with open(self.path, "x"):  # a new file: an existing log is never overwritten
                    pass
            except FileExistsError:
                raise HalError(f"{self.path}: exists; the bus log is not overwritten: expected a new file") from None
            except OSError as exc:
                raise HalError(f"{self.path}: cannot be created ({exc.strerror})") from None
        try:
            if self.path.suffix == ".gz":
                # closed with the writer (stop(), from close()): it lives as long as the log
                stream = gzip.open(self.path, "at", compresslevel=self.GZIP_LEVEL, encoding="ascii", newline="")  # noqa: SIM115
                self._writer = can.CanutilsLogWriter(stream, channel=channel)
            else:
                self._writer = can.CanutilsLogWriter(str(self.path), channel=channel, append=True)
        except OSError as exc:
            raise HalError(f"{self.path}: cannot be opened ({exc.strerror})") from None
        # python-can's writer names a numbered channel canN, and clamps a time before its first frame's
        self._line_channel = f"can{channel}" if channel.isdigit() else channel
        self._first_s: float | None = None
        self._stamped_s: float | None = None  # the time of the last line's stamp, and its text
        self._stamp_text = ""
        self._pending: deque[tuple[int, bytes, float, bool]] = deque()
        self.error: str | None = None
        self.frames_written = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="CAN traffic log", daemon=True)
        self._thread.start()

    def frame(self, cob_id: int, data: bytes, robot_t_s: float, sent: bool) -> None:
        """Queue one frame the master sent (``sent``) or received, at robot time ``robot_t_s`` (never waits)."""
        self._pending.append((cob_id, data, robot_t_s, sent))

    def received(self, frames: list[Frame]) -> None:
        """Queue frames the master received, each at its own time (:meth:`frame` for a batch; never waits)."""
        self._pending.extend([(cob_id, data, t_s, False) for cob_id, data, t_s in frames])

    def _run(self) -> None:
        while not self._stop.wait(self.WRITE_EVERY_S):
            self._write_pending()
        self._write_pending()

    def _write_pending(self) -> None:
        pending, epoch, file = self._pending, self.epoch_s, self._writer.file
        lines = []
        try:
            while pending:
                cob_id, data, t_s, sent = pending.popleft()
                lines.append(f"{self._stamp(epoch + t_s)}{cob_id:03X}#{data.hex().upper()}{' T' if sent else ' R'}\n")
            if lines:
                file.write("".join(lines))  # one write a batch: the writer thread holds the GIL less
                self.frames_written += len(lines)
            file.flush()  # whole lines reach the OS: a crash loses at most the queue
        except (OSError, ValueError) as exc:  # a full disk, a removed stick: latched, raised by the backend
            self.error = self.error or f"{self.path}: the bus log cannot be written: {exc}"
            pending.clear()

    def _stamp(self, timestamp_s: float) -> str:
        """A line's start, ``(time) channel ``, as python-can's ``CanutilsLogWriter`` writes it for a standard data frame.

        Its rules, kept: a time before the log's first frame is written as that first time; the
        channel of a number is ``canN``. The lines are formatted here because building a
        ``can.Message`` per frame for the writer cost the session more than its drives (D163); the
        frames of a cycle share their time, so its text is made once a cycle.
        """
        if timestamp_s == self._stamped_s:
            return self._stamp_text
        first = self._first_s
        if first is None:
            first = self._first_s = timestamp_s or 0.0
        self._stamped_s = timestamp_s
        self._stamp_text = f"({max(timestamp_s, first):f}) {self._line_channel} "
        return self._stamp_text

    def close(self) -> None:
        """Write what is queued and close the file (waits for the writer thread). Safe twice."""
        if self._thread.is_alive():
            self._stop.set()
            self._thread.join()
            self._writer.stop()
