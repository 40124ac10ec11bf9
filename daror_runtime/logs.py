"""Structured logging, configured once per process: the audit trail of every session.

People read one line per event on stderr; machines read JSON lines (one object per event) from
an optional file. The two sinks have their own levels: the JSON audit file keeps everything from
``info`` up while the console stays quiet by default. Library code only ever calls
``structlog.get_logger(__name__)`` and logs events with key-value context.

The tick logs too (a transition, a refusal, a fault), and the tick must never block: an event is
rendered where it happens (CPU only) and handed to a writer thread through a queue that never
blocks the caller; the writer does the file and terminal I/O. :func:`flush_logs` waits until
everything logged so far is written (tests, the end of a command; also run at exit).

Every event carries ``session_id`` once a runtime set one (:func:`set_session_id`), from every
thread, so the audit lines of a session can be picked out of a shared file.
"""

from __future__ import annotations

import atexit
import logging
import queue
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import structlog

_configured = False
_json_handles: list[TextIO] = []
_session_id: str | None = None
_pilot: str | None = None  # the session's pilot's code (the audit trail says whose session)


def _level(name: str) -> int:
    return logging.getLevelNamesMapping()[name.upper()]


class _Writer:
    """One daemon thread writing (stream, text) pairs in the order they were logged."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[tuple[TextIO, str] | None] = queue.SimpleQueue()
        self._pending = 0
        self._idle = threading.Condition()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def put(self, stream: TextIO, text: str) -> None:
        with self._idle:
            self._pending += 1
        if self._thread is None or not self._thread.is_alive():
            self._start()
        self._queue.put((stream, text))  # SimpleQueue.put never blocks

    def _start(self) -> None:
        with self._lock:
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="daror-log-writer", daemon=True)
                self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            stream, text = item
            try:
                stream.write(text)
                stream.flush()
            except (OSError, ValueError):  # a closed stream (end of a test, a closed terminal): nothing to do
                pass
            with self._idle:
                self._pending -= 1
                if self._pending == 0:
                    self._idle.notify_all()

    def flush(self, timeout_s: float = 5.0) -> bool:
        with self._idle:
            return self._idle.wait_for(lambda: self._pending == 0, timeout=timeout_s)


_writer = _Writer()


def flush_logs(timeout_s: float = 5.0) -> bool:
    """Wait until every event logged so far is written; False on timeout."""
    return _writer.flush(timeout_s)


atexit.register(flush_logs)


def set_session_id(session_id: str | None) -> None:
    """Tag every event from now on (all threads) with ``session_id`` (None: stop tagging)."""
    global _session_id
    _session_id = session_id


def set_session_pilot(pilot: str | None) -> None:
    """Tag every event from now on (all threads) with the session's ``pilot`` code (None: stop tagging)."""
    global _pilot
    _pilot = pilot


def _add_session_id(logger: Any, method: str, event_dict: dict[str, Any]) -> dict[str, Any]:
    if _session_id is not None:
        event_dict.setdefault("session_id", _session_id)
    if _pilot is not None:
        event_dict.setdefault("pilot", _pilot)
    return event_dict


def configure_logging(
    console_level: str = "warning",
    json_path: Path | str | Sequence[Path | str] | None = None,
    json_level: str = "info",
    stream: TextIO | None = None,
) -> None:
    """Readable lines at ``console_level`` and up to ``stream`` (stderr); JSON lines to ``json_path``.

    ``json_path`` may name several files (a session's own ``audit.jsonl`` and the one ``--log-json``
    names): every JSON line goes to each, appended. Calling it again replaces the previous
    configuration (tests and the CLI rely on this).
    """
    global _configured
    flush_logs()
    for handle in _json_handles:
        handle.close()
    _json_handles.clear()
    console_threshold = _level(console_level)
    json_threshold = _level(json_level)
    paths = [json_path] if isinstance(json_path, (str, Path)) else list(json_path or ())
    for path in dict.fromkeys(Path(p).resolve() for p in paths):  # one handle per file, however named
        path.parent.mkdir(parents=True, exist_ok=True)
        _json_handles.append(open(path, "a", encoding="utf-8"))  # noqa: SIM115 - lives as long as the config
    json_handles = tuple(_json_handles)
    console_stream = stream if stream is not None else sys.stderr
    console = structlog.dev.ConsoleRenderer(colors=False)
    json_renderer = structlog.processors.JSONRenderer()

    def route(logger: Any, method: str, event_dict: dict[str, Any]) -> str:
        level = _level(event_dict.get("level", method))
        if json_handles and level >= json_threshold:
            document = structlog.processors.format_exc_info(logger, method, dict(event_dict))
            line = json_renderer(logger, method, document) + "\n"
            for handle in json_handles:
                _writer.put(handle, line)
        if level >= console_threshold:
            _writer.put(console_stream, console(logger, method, event_dict) + "\n")
        raise structlog.DropEvent  # written by the writer thread, never by the caller

    floor = min(console_threshold, json_threshold) if json_handles else console_threshold
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            _add_session_id,
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            route,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(floor),
        logger_factory=structlog.PrintLoggerFactory(file=console_stream),
        cache_logger_on_first_use=False,
    )
    _configured = True
