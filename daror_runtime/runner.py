"""The loop runner: who runs the ticks, on which thread, and what the interpreter does meanwhile.

The :class:`~daror_runtime.runtime.Runtime` is the operator's door (requests, status); this module
owns the execution of the :class:`~daror_runtime.loop.ControlLoop` behind one interface,
:class:`LoopRunner`, in one of two ways chosen by the backend's clock:

* **lock-step** (a backend that owns its time): :meth:`LoopRunner.run_ticks`,
  :meth:`LoopRunner.run_until` and :meth:`LoopRunner.pass_time` run ticks in the caller's thread,
  with the session's between-ticks service after each, so a session is deterministic whatever the
  machine's speed;
* **real time** (:meth:`LoopRunner.start`): a loop thread runs the ticks (in batches of
  :data:`TICKS_PER_BATCH`, the loop's own fast path, with real-time scheduling when asked and
  granted) and a service thread does the between-ticks work and feeds the displays every
  :data:`SERVICE_PERIOD_S`, in the quiet part of a period.

While the loop runs in real time the runner also owns the interpreter's settings that decide
whether another thread can stall a tick (docs/safety.md H7): the garbage collector is off with what
exists frozen (the service thread collects the young generations once a second) and the thread
switch interval is :data:`REALTIME_SWITCH_INTERVAL_S`; :meth:`LoopRunner.stop` restores both.
Nothing else in the runtime starts a thread of the loop or touches these settings
(``tests/test_boundaries.py``).
"""

from __future__ import annotations

import gc
import sys
import threading
import time
from collections.abc import Callable

import structlog

from daror_runtime.clocks import Clock
from daror_runtime.errors import DarorError
from daror_runtime.fsm.supervisor import Response, Ticket
from daror_runtime.loop import ControlLoop, LoopStats, TickResult

log = structlog.get_logger(__name__)

__all__ = ["LoopRunner", "LoopRunningError"]

#: The interpreter's thread switch interval while the loop runs in real time (s): how long another
#: thread may keep the GIL once the loop thread asks for it.
REALTIME_SWITCH_INTERVAL_S = 1e-4
#: How often the service thread collects finished work and announces faults while the loop runs (s).
SERVICE_PERIOD_S = 0.02
#: Sleeps the service thread takes at most to reach the quiet part of a period (Clock.until_quiet_s).
QUIET_TRIES = 3
#: Service periods between two collections of the garbage collector's young generations (1 s).
YOUNG_COLLECTION_EVERY = 50
#: Ticks the loop thread runs per call of the loop's batch (its stop condition is checked every tick).
TICKS_PER_BATCH = 100
#: How often a real-time :meth:`LoopRunner.run_until` checks its condition (s of wall-clock time).
POLL_PERIOD_S = 0.005

#: Between two ticks (lock-step) or every service period (real time): the session's own work.
#: The argument counts the ticks run by this call of the runner (0 on the service thread).
Service = Callable[[int], None]


class LoopRunningError(DarorError):
    """Ticks were asked for in the caller's thread while the loop runs on its own."""


class LoopRunner:
    """Runs one :class:`~daror_runtime.loop.ControlLoop`: in the caller's thread (lock-step) or on its own.

    Args:
        loop: the session's loop (started by the session before the first tick).
        clock: the loop's clock (its ``needs_virtual_time`` decides whether real-time scheduling is
            asked for by default; its ``until_quiet_s`` places the service thread's work).
        service: the session's between-ticks work (announcing faults, collecting a finished run,
            lock-step jobs); it never runs inside a tick.
        on_display_error: told when a display's publisher raised (the publisher is then dropped).
    """

    def __init__(
        self,
        loop: ControlLoop,
        clock: Clock,
        service: Service,
        on_display_error: Callable[[Exception], None],
    ) -> None:
        self._loop = loop
        self._clock = clock
        self._service = service
        self._on_display_error = on_display_error
        self._thread: threading.Thread | None = None
        self._service_thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._thread_error: BaseException | None = None
        self._publishers: list[Callable[[], None]] = []
        self._switch_interval_s = sys.getswitchinterval()
        self._gc_was_enabled = True

    @property
    def clock(self) -> Clock:
        """The loop's clock (lock-step, paced or real time)."""
        return self._clock

    @property
    def stats(self) -> LoopStats:
        """The loop's counters so far: ticks, overruns, missed deadlines, worst lateness."""
        return self._loop.stats

    @property
    def running(self) -> bool:
        """True while the loop runs on its own thread (between :meth:`start` and :meth:`stop`)."""
        return self._thread is not None

    # --- lock-step: ticks in the caller's thread ---------------------------------------------

    def run_ticks(self, ticks: int, stop: Callable[[TickResult], bool] | None = None) -> TickResult | None:
        """Run ``ticks`` ticks in this thread, the service after each; stop early when ``stop(result)``.

        Returns the last tick's result (None for 0 ticks).

        Raises:
            LoopRunningError: the loop runs on its own thread.
        """
        self._refuse_while_running("run ticks")
        result = None
        tick = self._loop.tick
        service = self._service
        for n in range(ticks):
            result = tick()
            service(n)
            if stop is not None and stop(result):
                break
        return result

    def run_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Until ``done()`` (checked after every tick; polled while the loop runs on its own); False if ``timeout_s`` passed first.

        In lock-step the ticks run here and ``timeout_s`` is robot time; while the loop runs on its
        own thread it is wall-clock time.
        """
        if self._thread is not None:
            deadline = time.monotonic() + timeout_s
            while not done():
                if time.monotonic() > deadline:
                    return False
                time.sleep(POLL_PERIOD_S)
            return True
        tick = self._loop.tick
        for n in range(max(1, round(timeout_s / self._loop.dt_s))):
            tick()
            self._service(n)
            if done():
                return True
        return done()

    def pass_time(self, seconds: float) -> None:
        """Let ``seconds`` pass: ticks in lock-step (robot time), a sleep while the loop runs on its own."""
        if self._thread is not None:
            time.sleep(seconds)
        else:
            self.run_ticks(round(seconds / self._loop.dt_s))

    def wait_for(self, ticket: Ticket, timeout_s: float) -> Response | None:
        """The response to ``ticket``, or None if it was not resolved within ``timeout_s``.

        In lock-step, ticks run here until it is resolved (``timeout_s`` of robot time at most);
        while the loop runs on its own, this thread waits (wall-clock time).
        """
        if self._thread is None:
            self.run_until(lambda: ticket.done, timeout_s)
            return ticket.response
        return ticket.wait(timeout_s)

    # --- real time: the loop on its own thread ------------------------------------------------

    def start(self, realtime: bool | None = None) -> None:
        """Run the loop on its own thread, and a service thread, until :meth:`stop` (no-op while running).

        Args:
            realtime: ask the OS for real-time scheduling for the loop's thread (``SCHED_FIFO``,
                ``mlockall``: :mod:`daror_runtime.realtime`); None: only on a clock whose stalls
                are faults (the real-time clock), not on a paced one, whose stalls only delay the
                simulated world (D142).
        """
        if self._thread is not None:
            return
        self._stop.clear()
        if realtime is None:
            realtime = not self._clock.needs_virtual_time
        if self._loop.stats.ticks > 0:  # a restart: a new grid, so the pause is not counted as a stall
            self._clock.start()
        self._quiet_the_interpreter()
        self._thread = threading.Thread(target=self._loop_thread, args=(realtime,), name="daror-loop", daemon=True)
        self._service_thread = threading.Thread(target=self._service_thread_main, name="daror-service", daemon=True)
        self._thread.start()
        self._service_thread.start()

    def stop(self) -> None:
        """Stop both threads (the tick under way finishes) and restore the interpreter's settings; no-op when stopped.

        Raises:
            DarorError: the loop thread had failed (the exception it died of is the cause).
        """
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        if self._service_thread is not None:
            self._service_thread.join()
        self._thread = self._service_thread = None
        self._restore_the_interpreter()
        if self._thread_error is not None:
            error, self._thread_error = self._thread_error, None
            raise DarorError(f"the control loop thread failed: {error!r}") from error

    def add_publisher(self, publish: Callable[[], None]) -> None:
        """Call ``publish()`` from the service thread every service period (20 ms) while the loop runs on its own.

        For displays (the web console): it runs outside the tick, in a thread that already wakes
        (no other thread to schedule beside the loop), and must return in microseconds without
        blocking. A publisher that raises is dropped and the session told (``on_display_error``).
        """
        self._publishers.append(publish)

    def remove_publisher(self, publish: Callable[[], None]) -> None:
        """Stop calling ``publish`` (no-op if it is not registered)."""
        if publish in self._publishers:
            self._publishers.remove(publish)

    # --- internals ------------------------------------------------------------------------

    def _refuse_while_running(self, what: str) -> None:
        if self._thread is not None:
            raise LoopRunningError(f"cannot {what}: the loop runs in its background thread; use wait() instead")

    def _loop_thread(self, realtime: bool) -> None:
        from daror_runtime.realtime import release_realtime, request_realtime

        if realtime:
            request_realtime()
        stop = self._stop.is_set
        run = self._loop.run
        try:
            while not stop():
                run(TICKS_PER_BATCH, stop=lambda _result: stop(), disable_gc=False)  # off for the whole run
        except BaseException as exc:  # kept for stop() to raise in the caller's thread: never swallowed
            self._thread_error = exc
            log.exception("control loop thread stopped")
        finally:
            if realtime:
                release_realtime()

    def _service_thread_main(self) -> None:
        n = 0
        until_quiet = self._clock.until_quiet_s
        while not self._stop.wait(SERVICE_PERIOD_S):
            # between two ticks, in the part of the period where the loop sleeps: this thread's work
            # then never makes the loop wait for the interpreter (a sleep re-checked: it may
            # overshoot the window)
            for _ in range(QUIET_TRIES):
                delay = until_quiet()
                if delay <= 0.0:
                    break
                time.sleep(delay)
            self._service(0)
            if self._publishers:
                self._publish()
            n += 1
            if n % YOUNG_COLLECTION_EVERY == 0:
                gc.collect(1)  # the young generations only: well under a millisecond

    def _publish(self) -> None:
        for publish in list(self._publishers):
            try:
                publish()
            except Exception as exc:  # a display's error: stop that display, say why, the loop goes on
                self.remove_publisher(publish)
                log.exception("publisher removed", publisher=repr(publish))
                self._on_display_error(exc)

    def _quiet_the_interpreter(self) -> None:
        # The cyclic garbage collector runs in whichever thread allocates and holds the GIL while it
        # scans: a full collection in the console's thread is a stall of the loop. So it is off while
        # the loop runs; what exists now is frozen out of every scan; the service thread collects
        # the young generations once a second (what a session allocates is mostly freed by
        # reference counting; cycles older than that wait for the end of the session).
        gc.freeze()
        self._gc_was_enabled = gc.isenabled()
        gc.disable()
        # Another Python thread (the console, a job) holds the GIL for up to the switch interval
        # (5 ms by default) before the loop thread gets it: a stall the watchdog faults. 0.1 ms
        # bounds that wait; the cost is more frequent switches in the other threads.
        self._switch_interval_s = sys.getswitchinterval()
        sys.setswitchinterval(REALTIME_SWITCH_INTERVAL_S)

    def _restore_the_interpreter(self) -> None:
        sys.setswitchinterval(self._switch_interval_s)
        if self._gc_was_enabled:
            gc.enable()
        gc.unfreeze()
