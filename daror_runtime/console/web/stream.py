"""Live data for the web console, gathered outside the tick: a ring buffer and the shared log.

:class:`LiveStream` runs its own thread (never the loop's): every ``period_s`` (20 ms: 50 Hz) it
reads :attr:`Runtime.last_sample` (the sample the last tick read, an immutable NamedTuple) and
appends one row to a bounded ring buffer (``window_s`` of data, the oldest dropped). The tick
never waits for it and never knows it exists; a browser reads the ring from its own cursor, so a
closed or slow browser only misses rows (nothing queues up behind it).

:class:`AnnouncementHub` drains the runtime's announcements once and fans them out: every console
on the session (the text console at the terminal, each browser) reads the same log, from its own
cursor, bounded (the oldest lines dropped).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from daror_runtime.console.view import announcement_line
from daror_runtime.runtime import Runtime
from daror_runtime.session.events import Announcement

#: Live rows sampled per second (>= 20 Hz to the browser).
SAMPLE_HZ = 50.0
#: Seconds of live data kept (the plots show the last 20 s).
WINDOW_S = 30.0
#: Lines of the shared log kept.
LOG_LINES = 500


def raise_priority(nice: int = -10) -> None:
    """Run the calling thread at a higher CPU priority than ordinary work, if allowed (else leave it).

    The loop waits for whichever thread holds the interpreter; a web thread that other processes
    (the browser, a fit) pre-empt while holding it stalls the loop for a scheduler's time slice.
    """
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except (OSError, AttributeError):  # not permitted (no CAP_SYS_NICE), or not Linux
        return


@dataclass(frozen=True)
class LiveRow:
    """One decimated row: time, joint angles (deg), measured spring torques and motor commands (Nm)."""

    index: int
    t_s: float
    q_deg: tuple[float, ...]
    tau_nm: tuple[float, ...]
    command_nm: tuple[float, ...]

    def as_list(self) -> list[Any]:
        return [round(self.t_s, 4), *(round(v, 3) for v in (*self.q_deg, *self.tau_nm, *self.command_nm))]

    def as_json(self) -> str:
        return json.dumps(self.as_list())


class AnnouncementHub:
    """The one reader of the runtime's announcements; every console reads its lines from here.

    ``extra`` lines (a command typed in a browser and its answer) join the same log, so two
    browsers and the terminal show one history.
    """

    def __init__(self, runtime: Runtime, lines: int = LOG_LINES) -> None:
        self._runtime = runtime
        self._lock = threading.Lock()
        self._log: deque[tuple[int, str]] = deque(maxlen=lines)
        self._counter = itertools.count(1)
        self._terminal: deque[Announcement] = deque(maxlen=lines)

    def pump(self) -> None:
        """Drain the runtime's feed into the log (any thread; called by the stream's thread)."""
        items = self._runtime.drain_announcements()
        if not items:
            return
        with self._lock:
            for item in items:
                self._log.append((next(self._counter), announcement_line(item)))
                self._terminal.append(item)

    def add(self, text: str) -> None:
        """A line of the shared log that is not an announcement (a browser's command and its answer)."""
        with self._lock:
            for line in text.splitlines() or [""]:
                self._log.append((next(self._counter), line))

    def since(self, cursor: int) -> tuple[int, list[str]]:
        """Lines after ``cursor`` (0: everything kept) and the new cursor."""
        with self._lock:
            lines = [(n, text) for n, text in self._log if n > cursor]
        return (lines[-1][0] if lines else cursor), [text for _, text in lines]

    def terminal_reader(self) -> Callable[[], list[Announcement]]:
        """What the text console drains instead of the runtime's feed (same announcements)."""

        def drain() -> list[Announcement]:
            self.pump()
            with self._lock:
                items = list(self._terminal)
                self._terminal.clear()
            return items

        return drain


class LiveStream:
    """Samples the runtime from its own thread into a ring buffer; pumps the shared log.

    Args:
        runtime: an opened runtime (its loop running or not).
        hub: the shared log, pumped at every sample.
        sample_hz: rows per second (decimated from the loop's rate).
        window_s: seconds kept.
    """

    def __init__(
        self, runtime: Runtime, hub: AnnouncementHub, sample_hz: float = SAMPLE_HZ, window_s: float = WINDOW_S
    ) -> None:
        self._runtime = runtime
        self.hub = hub
        self.period_s = 1.0 / sample_hz
        # (index, the row as JSON text): serialised once, here, in small pieces; a message is a join of
        # texts (a C call on one big list would hold the interpreter for milliseconds: the loop waits)
        self._ring: deque[tuple[int, str]] = deque(maxlen=max(1, int(sample_hz * window_s)))
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._index = 0
        self._last_seq = -1
        self._last_command: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
        self._status_every = max(1, int(sample_hz / 5))  # the status (and the motor commands): 5 Hz
        #: What the page shows of the status, built here once for every browser (set by the app).
        self.status_source: Callable[[], dict[str, Any]] | None = None
        #: (version, the status as JSON text): a socket sends it when the version changed.
        self.status_json: tuple[int, str] = (0, "null")

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="daror-web-stream", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def _run(self) -> None:
        raise_priority()
        ticks = 0
        while not self._stop.wait(self.period_s):
            try:
                if ticks % self._status_every == 0:
                    self.refresh_status()
                self.sample_once()
            except Exception as exc:  # a display thread must not die silently: say why, once
                self.hub.add(f"web console: live data stopped: {exc}")
                return
            ticks += 1

    def refresh_status(self) -> None:
        """Pump the log; build the status once for every browser; keep the motor commands for the rows."""
        self.hub.pump()
        source = self.status_source
        if source is not None:
            document = source()
            self.status_json = (self.status_json[0] + 1, json.dumps(document))
            joints = document.get("joints")
            if joints is not None:
                self._last_command = tuple(float(v) for v in joints["motor_command_nm"])
        else:
            readings = self._runtime.snapshot().joints
            if readings is not None:
                self._last_command = tuple(readings.motor_command_nm)

    def sample_once(self) -> None:
        """Append the runtime's last sample (if new) to the ring."""
        sample = self._runtime.last_sample
        if sample is None or sample.seq == self._last_seq:
            return
        self._last_seq = sample.seq
        row = LiveRow(
            self._index + 1,
            float(sample.t_s),
            tuple(math.degrees(float(v)) for v in sample.q_rad),
            tuple(float(v) for v in sample.tau_nm),
            self._last_command,
        )
        text = row.as_json()
        with self._lock:
            self._index += 1
            self._ring.append((row.index, text))

    def since(self, cursor: int, limit: int = 100) -> tuple[int, list[str]]:
        """Rows after ``cursor`` as JSON texts (the oldest ``limit`` of them) and the new cursor.

        A browser that connects late or falls behind catches up ``limit`` rows per message; one
        that fell more than the window behind has lost the oldest rows (dropped, never queued).
        """
        with self._lock:
            newest = self._index
            if newest <= cursor:
                return cursor, []
            count = min(newest - cursor, len(self._ring))
            first = len(self._ring) - count
            rows = [self._ring[i][1] for i in range(first, min(first + limit, len(self._ring)))]
        return newest - count + len(rows), rows
