"""The web server's side of the web console: the session as the pages see it, kept in the server's process.

:class:`PageState` holds what the runtime's process published (:mod:`daror_runtime.console.web.bridge`):
the latest status, built once into the page's JSON for every browser; the shared log; and the live
rows, read from the shared ring from each socket's own cursor. A page's console line is forwarded to
the runtime's process and its answer awaited (the runtime applies the request at a tick boundary).
A reader thread receives the runtime's messages; when the runtime's end closes, :attr:`PageState.on_runtime_gone`
is called (the server stops).
"""

from __future__ import annotations

import itertools
import json
import math
import pickle
import socket
import sys
import threading
import traceback
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from daror_runtime.console.guide import next_steps
from daror_runtime.console.web.bridge import LOG_LINES, MAX_MESSAGE_BYTES
from daror_runtime.console.web.ring import RowRing
from daror_runtime.session.status import RuntimeStatus

#: Seconds a page waits for the runtime to answer a console line.
ANSWER_TIMEOUT_S = 30.0


def status_document(status: RuntimeStatus, has_world: bool, notes: list[str]) -> dict[str, Any]:
    """The page's status: :meth:`RuntimeStatus.as_dict`, the next steps, the simulated world's notes (JSON-ready)."""
    document = status.as_dict()
    document["next_steps"] = [
        {"what": step.text, "type": list(step.commands)} for step in next_steps(status, has_world)
    ]
    document["has_world"] = has_world
    document["notes"] = [*status.notes, *notes]
    return json.loads(json.dumps(document, default=str))


def rows_json(rows: np.ndarray, n_joints: int) -> list[str]:
    """Live rows as JSON arrays: t (s), angles (deg), measured torques (Nm), references (Nm; null: none)."""
    out = []
    for row in rows:
        values = [round(float(row[0]), 4)]
        values += [round(math.degrees(v), 3) for v in row[1 : 1 + n_joints].tolist()]
        values += [None if math.isnan(v) else round(v, 3) for v in row[1 + n_joints :].tolist()]
        out.append(json.dumps(values))
    return out


class PageState:
    """What the server shows, fed by the runtime's messages on ``link``.

    Args:
        link: the server's end of the ``SOCK_SEQPACKET`` pair.
        ring: the live rows (read-only here).
        hello: the runtime's first message: ``fsm`` (the diagram's layout), ``has_world``, the
            first status and world notes.
    """

    def __init__(self, link: socket.socket, ring: RowRing, hello: dict[str, Any]) -> None:
        self._link = link
        self.ring = ring
        self.fsm: dict[str, Any] = hello["fsm"]
        self.has_world: bool = hello["has_world"]
        self._lock = threading.Lock()
        self._log: deque[tuple[int, str]] = deque(maxlen=LOG_LINES)
        self._status: dict[str, Any] = status_document(hello["status"], self.has_world, hello["notes"])
        #: (version, the status as JSON text): a socket sends it when the version changed.
        self.status_json: tuple[int, str] = (1, json.dumps(self._status))
        self._ids = itertools.count(1)
        self._waiting: dict[int, tuple[threading.Event, list[Any]]] = {}
        self._send = threading.Lock()
        self.on_runtime_gone: Callable[[], None] = lambda: None
        self.gone = threading.Event()

    # --- from the runtime -------------------------------------------------------------------

    def read_forever(self) -> None:
        """Receive the runtime's messages until its end closes (then :attr:`on_runtime_gone`).

        A message that cannot be handled is written to the server's log (stderr: ``web-server.log``)
        and skipped: the reader never dies while the runtime is there, and an answer always reaches
        the page that waits for it (without a status if its status could not be built).
        """
        while True:
            try:
                data = self._link.recv(MAX_MESSAGE_BYTES)
            except OSError:
                data = b""
            if not data:
                self.gone.set()
                for event, _ in list(self._waiting.values()):
                    event.set()
                self.on_runtime_gone()
                return
            try:
                self._handle(pickle.loads(data))
            except Exception:
                traceback.print_exc(file=sys.stderr)

    def _handle(self, message: tuple[Any, ...]) -> None:
        kind, *body = message
        if kind == "status":
            status, notes, lines = body
            self._add_lines(lines)
            self._set_status(status, notes)
        elif kind == "answer":
            request_id, ok, text, status, notes = body
            waiting = self._waiting.get(request_id)
            document: dict[str, Any] | None = None
            try:
                if status is not None:
                    document = self._set_status(status, notes)
            finally:  # the page gets its answer even when the status could not be built
                if waiting is not None:
                    waiting[1].append({"ok": ok, "answer": text, "status": document})
                    waiting[0].set()

    def _set_status(self, status: RuntimeStatus, notes: list[str]) -> dict[str, Any]:
        document = status_document(status, self.has_world, notes)
        text = json.dumps(document)
        with self._lock:
            self._status = document
            self.status_json = (self.status_json[0] + 1, text)
        return document

    def _add_lines(self, lines: list[tuple[int, str]]) -> None:
        with self._lock:
            last = self._log[-1][0] if self._log else 0
            self._log.extend((n, text) for n, text in lines if n > last)

    # --- to the pages -----------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        with self._lock:
            return self._status

    def log_since(self, cursor: int) -> tuple[int, list[str]]:
        """Log lines after ``cursor`` (0: everything kept) and the new cursor."""
        with self._lock:
            lines = [(n, text) for n, text in self._log if n > cursor]
        return (lines[-1][0] if lines else cursor), [text for _, text in lines]

    def rows_since(self, cursor: int, limit: int = 100) -> tuple[int, list[str]]:
        """Live rows after ``cursor`` as JSON texts (the oldest ``limit``) and the new cursor."""
        cursor, rows = self.ring.since(cursor, limit)
        return cursor, rows_json(rows, self.ring.n_joints)

    def command(self, line: str) -> dict[str, Any]:
        """Send one console line to the runtime and wait for its answer (``ok``, ``answer``, ``status``)."""
        if self.gone.is_set():
            return {"line": line, "ok": False, "answer": "  failed: the session has ended", "status": None}
        request_id = next(self._ids)
        event: threading.Event = threading.Event()
        box: list[Any] = []
        self._waiting[request_id] = (event, box)
        try:
            with self._send:
                self._link.send(pickle.dumps(("command", request_id, line), protocol=5))
            answered = event.wait(ANSWER_TIMEOUT_S)
        except OSError as exc:
            return {"line": line, "ok": False, "answer": f"  failed: the session cannot be reached ({exc})", "status": None}  # fmt: skip
        finally:
            self._waiting.pop(request_id, None)
        if not answered or not box:
            why = (
                "the session has ended"
                if self.gone.is_set()
                else f"no answer from the session in {ANSWER_TIMEOUT_S:g} s"
            )
            return {"line": line, "ok": False, "answer": f"  failed: {why}", "status": None}
        return {"line": line, **box[0]}
