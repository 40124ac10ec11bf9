"""The runtime's side of the web console: what it publishes to the server process, and the lines it runs.

The web server (HTTP, websockets, JSON) runs in a process of its own
(:mod:`daror_runtime.console.web.server`): its work never holds the interpreter the control loop
needs. What stays in the runtime's process is small, and none of it runs in the tick:

* :meth:`WebBridge.publish`, called by the runtime's service thread every 20 ms
  (:meth:`LoopRunner.add_publisher`): the last sample (and compensation's torque reference) into the
  shared ring of live rows (:class:`~daror_runtime.console.web.ring.RowRing`: array copies, no
  system call); the status (:meth:`Runtime.snapshot`, pickled) and the new lines of the shared
  log at once when the state changed or something was logged, else every 400 ms, sent without
  waiting (a full socket: sent next time). The service thread runs in the part of the loop's
  period where the loop sleeps; the status is built in one period and sent in the next, so each
  step fits there;
* a thread blocked on the socket that runs the console lines the pages send, one at a time,
  exactly as typed at the text console (:class:`~daror_runtime.console.commands.ConsoleSession`),
  and sends back the answer with a fresh status.

:class:`AnnouncementHub` is the one reader of the runtime's announcements: the terminal's console
and the pages read the same log.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import pickle
import socket
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import structlog
from rich.console import Console

from daror_runtime.console.commands import CommandError, ConsoleSession, QuitRequested, ScriptCheckError
from daror_runtime.console.view import announcement_line
from daror_runtime.console.web.ring import RowRing
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import DarorError, InputError
from daror_runtime.runtime import Runtime
from daror_runtime.session.events import Announcement
from daror_runtime.session.status import RuntimeStatus

log = structlog.get_logger(__name__)

#: Lines of the shared log kept.
LOG_LINES = 500
#: Service periods (20 ms) between two statuses sent to the server when nothing happens (2.5 Hz);
#: a transition or a new log line (a fault, an e-stop, an answer) sends one at once.
STATUS_EVERY = 20
#: Statuses that fail to be read in a row (one a service period, 20 ms) before the publisher gives up.
STATUS_FAILURES = 50
#: Log lines per status message at most (the rest go with the next).
LOG_LINES_PER_MESSAGE = 100
#: Characters of one log line kept.
LINE_CHARS = 2000
#: The largest message either side sends (bytes); both sockets' buffers are made this large.
MAX_MESSAGE_BYTES = 1 << 20
#: Console lines a page may not send: they block the session or end it from a page.
NOT_FROM_THE_PAGE = {"wait": "waits belong in scripts", "expect": "checks belong in scripts", "quit": "end the session at the terminal (quit or Ctrl-C)"}  # fmt: skip


class AnnouncementHub:
    """The one reader of the runtime's announcements; every console reads its lines from here.

    ``add`` lines (a command sent from a page and its answer) join the same log, so the pages and
    the terminal show one history. Lines are numbered from 1; the oldest are dropped past ``lines``.
    """

    def __init__(self, runtime: Runtime, lines: int = LOG_LINES) -> None:
        self._runtime = runtime
        self._lock = threading.Lock()
        self._log: deque[tuple[int, str]] = deque(maxlen=lines)
        self._counter = itertools.count(1)
        self._terminal: deque[Announcement] = deque(maxlen=lines)

    def pump(self) -> None:
        """Drain the runtime's feed into the log (any thread)."""
        items = self._runtime.drain_announcements()
        if not items:
            return
        with self._lock:
            for item in items:
                self._log.append((next(self._counter), announcement_line(item)))
                self._terminal.append(item)

    def add(self, text: str) -> None:
        """Lines of the shared log that are not announcements (a page's command and its answer)."""
        with self._lock:
            for line in text.splitlines() or [""]:
                self._log.append((next(self._counter), line[:LINE_CHARS]))

    @property
    def newest(self) -> int:
        """The number of the newest line (0: none yet)."""
        with self._lock:
            return self._log[-1][0] if self._log else 0

    def since(self, cursor: int, limit: int = LOG_LINES) -> list[tuple[int, str]]:
        """The numbered lines after ``cursor`` (0: everything kept), the oldest ``limit`` of them."""
        with self._lock:
            return [(n, text) for n, text in self._log if n > cursor][:limit]

    def terminal_reader(self) -> Callable[[], list[Announcement]]:
        """What the text console drains instead of the runtime's feed (the same announcements)."""

        def drain() -> list[Announcement]:
            self.pump()
            with self._lock:
                items = list(self._terminal)
                self._terminal.clear()
            return items

        return drain


class WebBridge:
    """Publishes the runtime to the server process and runs the console lines its pages send.

    Args:
        runtime: the session's runtime (opened).
        world: its simulated world, or None on hardware.
        link: this process's end of a ``SOCK_SEQPACKET`` socket pair (one message per packet).
        ring: the live rows shared with the server (this side writes).
        hub: the shared log.
    """

    def __init__(
        self,
        runtime: Runtime,
        world: SimWorld | None,
        link: socket.socket,
        ring: RowRing,
        hub: AnnouncementHub,
        records_url: str | None = None,
    ) -> None:
        self.runtime = runtime
        self.world = world
        self.hub = hub
        self._link = link
        self._ring = ring
        self._last_seq = -1
        self._periods = 0  # service periods since the last status
        self._state = ""  # the state the last status was in
        self._failures = 0  # statuses that failed to be read in a row
        self._log_sent = 0  # the last log line the server has
        self._staged: tuple[RuntimeStatus, list[tuple[int, str]]] | None = None  # built, to send next period
        self._closed = threading.Event()
        self.lost: str | None = None  # why the server can no longer be reached, None while it can
        self._buffer = io.StringIO()
        out = Console(file=self._buffer, width=110, color_system=None, highlight=False, soft_wrap=True)
        # the pages' lines are answered like the terminal's; announcements reach every console
        # through the hub, so this session drains nothing itself
        self.session = ConsoleSession(runtime, out, world, announcements=lambda: [], records_url=records_url)
        self._lines = threading.Lock()
        self._thread = threading.Thread(target=self._serve_lines, name="daror-web-lines", daemon=True)

    def start(self) -> None:
        """Publish from the service thread and answer the pages' lines (until :meth:`close`)."""
        self._thread.start()
        self.runtime.runner.add_publisher(self.publish)

    def close(self) -> None:
        """Stop publishing and answering; the server sees the socket close and exits."""
        self._closed.set()
        self.runtime.runner.remove_publisher(self.publish)
        with contextlib.suppress(OSError):  # the server already closed its end
            self._link.shutdown(socket.SHUT_RDWR)
        self._thread.join(timeout=5.0)
        self._link.close()

    # --- the service thread (every 20 ms, outside the tick) -----------------------------------

    def publish(self) -> None:
        """The last sample into the ring; the status when something happened, or every :data:`STATUS_EVERY` calls."""
        runtime = self.runtime
        sample = runtime.last_sample
        if sample is not None and sample.seq != self._last_seq:
            self._last_seq = sample.seq
            self._ring.push(sample.t_s, sample.q_rad, sample.tau_nm, runtime.torque_reference_nm)
        if self.lost is not None:
            return
        # the status in two steps, each in its own service period: each fits the loop's quiet part
        # of a period (Clock.until_quiet_s), where it never makes the loop wait for the interpreter
        if self._staged is not None:
            status, lines = self._staged
            self._staged = None
            self.send_status(status, lines)
            return
        self._periods += 1
        self.hub.pump()  # an empty feed: one failed pop
        state = runtime.state_name
        if state != self._state or self.hub.newest > self._log_sent or self._periods >= STATUS_EVERY:
            try:
                status = runtime.snapshot()
            except Exception:  # read while the loop moves on: try again next period, give up after a second
                self._failures += 1
                if self._failures >= STATUS_FAILURES:
                    raise  # the runtime removes this publisher and announces why
                log.exception("web console status failed", failures=self._failures)
                return
            self._failures = 0
            self._state = state
            self._periods = 0
            self._staged = (status, self.hub.since(self._log_sent, LOG_LINES_PER_MESSAGE))

    def send_status(self, status: RuntimeStatus, lines: list[tuple[int, str]]) -> None:
        """Send ``status`` and the log ``lines`` the server lacks, without waiting (full: they go next time)."""
        message = pickle.dumps(("status", status, self._notes(), lines), protocol=5)
        try:
            self._link.send(message, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return  # the server is behind: nothing waits for it; the lines stay pending
        except OSError as exc:
            self._lose(f"the web server cannot be reached ({exc.strerror or exc})")
            return
        if lines:
            self._log_sent = lines[-1][0]

    def _notes(self) -> list[str]:
        return self.world.notes(self.runtime.settings) if self.world is not None else []

    def _lose(self, why: str) -> None:
        if self.lost is None and not self._closed.is_set():
            self.lost = why
            log.error("web console lost", reason=why)

    # --- the pages' console lines (their own thread) ------------------------------------------

    def run_line(self, line: str) -> tuple[bool, str]:
        """Run one console line from a page: (accepted, the answer); the echo and answer join the shared log."""
        line = line.strip()
        word = line.split(maxsplit=1)[0] if line else ""
        if word in NOT_FROM_THE_PAGE:
            ok, text = False, f"  error: '{word}' is not sent from the web console: {NOT_FROM_THE_PAGE[word]}"
        else:
            ok, text = self._execute(line)
        self.hub.pump()  # what happened before this line is logged before it
        self.hub.add(f"(web) > {line}\n{text}" if text else f"(web) > {line}")
        self.hub.pump()
        return ok, text

    def _execute(self, line: str) -> tuple[bool, str]:
        session = self.session
        with self._lines:  # one line at a time, like the terminal
            self._buffer.seek(0)
            self._buffer.truncate()
            ok = True
            refusals = session.tally.failed
            try:
                session.execute(line)
            except QuitRequested:
                ok = False
            except (CommandError, InputError, ScriptCheckError) as exc:
                session.say(f"  error: {exc}")
                ok = False
            except DarorError as exc:
                session.say(f"  failed: {exc}")
                ok = False
            if session.tally.failed > refusals:
                ok = False
            return ok, self._buffer.getvalue().rstrip()

    def _serve_lines(self) -> None:
        link = self._link
        while not self._closed.is_set():
            try:
                data = link.recv(MAX_MESSAGE_BYTES)
            except OSError as exc:
                self._lose(f"the web server's socket failed ({exc.strerror or exc})")
                return
            if not data:
                self._lose("the web server exited")
                return
            kind, *body = pickle.loads(data)
            if kind != "command":
                continue  # "ready" (read by start_web) or a message of a newer server: nothing to run
            request_id, line = body
            try:
                ok, text = self.run_line(line)
            except Exception as exc:  # an unexpected error in a page's line: answered and logged, never lost
                log.exception("web console line failed", line=line)
                ok, text = False, f"  failed: {exc}"
            try:
                status: RuntimeStatus | None = self.runtime.snapshot()
            except Exception:  # a status that cannot be read now: the answer goes without it (the next has one)
                log.exception("web console status failed", line=line)
                status = None
            answer: tuple[Any, ...] = ("answer", request_id, ok, text, status, self._notes())
            try:
                link.send(pickle.dumps(answer, protocol=5))
            except OSError as exc:
                self._lose(f"the web server cannot be reached ({exc.strerror or exc})")
                return
