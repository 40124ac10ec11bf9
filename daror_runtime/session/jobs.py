"""Work that must not run in the tick (closing a recording, reducing data, fitting a model).

In real time, jobs run one at a time on a worker thread while the loop keeps its rate. In
lock-step (virtual) time the driver runs them between two ticks: virtual time does not pass while
a job runs, so a session in lock-step is deterministic, whatever the machine's speed.

A job never fails silently: its exception is logged with the job's name and kept in
:attr:`Jobs.failures`, and the job's own code reports the outcome to the operator.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import structlog

log = structlog.get_logger(__name__)


class Jobs:
    """A queue of jobs: ``threaded`` runs them on one worker thread, else :meth:`run_pending` runs them.

    ``on_failure(name, exception)`` is called (in the job's thread) when a job raises.
    """

    def __init__(self, threaded: bool, on_failure: Callable[[str, BaseException], None] | None = None) -> None:
        self.threaded = threaded
        self._on_failure = on_failure
        self._pending: deque[tuple[str, Callable[[], None]]] = deque()
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="daror-job") if threaded else None
        self._futures: list[Future[None]] = []
        self._lock = threading.Lock()
        self.failures: list[tuple[str, BaseException]] = []

    @property
    def pending(self) -> bool:
        """True while a job is queued or running."""
        if self._pending:
            return True
        if self._executor is None:
            return False
        with self._lock:
            return any(not f.done() for f in self._futures)

    def submit(self, name: str, job: Callable[[], None]) -> None:
        """Queue ``job``; it never runs inside the caller's tick."""
        if self._executor is None:
            self._pending.append((name, job))
            return
        future = self._executor.submit(self._run, name, job)
        with self._lock:
            self._futures = [f for f in self._futures if not f.done()]
            self._futures.append(future)

    def run_pending(self) -> int:
        """Lock-step: run the queued jobs now (between ticks); returns how many ran."""
        ran = 0
        while self._pending:
            name, job = self._pending.popleft()
            self._run(name, job)
            ran += 1
        return ran

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait until every job finished (threaded) or run them (lock-step); False on timeout."""
        self.run_pending()
        with self._lock:
            futures = list(self._futures)
        for future in futures:
            try:
                future.result(timeout=timeout_s)
            except TimeoutError:
                return False
        return True

    def close(self) -> None:
        self.wait()
        if self._executor is not None:
            self._executor.shutdown(wait=True)

    def _run(self, name: str, job: Callable[[], None]) -> None:
        log.info("job started", job=name)
        try:
            job()
        except Exception as exc:  # kept and logged: the job's result is missing, the operator is told
            log.exception("job failed", job=name, error=str(exc))
            self.failures.append((name, exc))
            if self._on_failure is not None:
                self._on_failure(name, exc)
        else:
            log.info("job finished", job=name)
