"""The web console's application: the page, the session's status, console lines, and live data.

Routes (all behind the token when the server listens beyond the loopback):

* ``GET /``: the page (``static/index.html``; every asset is in the package: the lab PC is offline);
* ``GET /api/fsm``: the spec's states laid out per superstate (the diagram is drawn from it);
* ``GET /api/status``: :meth:`Runtime.snapshot` as JSON;
* ``POST /api/command`` ``{"line": "advance"}``: one console line, checked and answered exactly as
  typed at the text console (:class:`daror_runtime.console.commands.ConsoleSession`); the request
  it posts is applied at a tick boundary, a refusal comes back with its reason;
* ``WS /ws``: live rows (>= 20 Hz, in batches of 50 ms), the status (5 Hz) and new log lines.

Nothing here runs in the tick: the rows come from :class:`LiveStream`'s ring buffer, each socket
reads it from its own cursor, and a socket that is closed or slow only misses rows.
"""

from __future__ import annotations

import asyncio
import hmac
import io
import json
import threading
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

from fastapi import FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from rich.console import Console

from daror_runtime.console.commands import CommandError, ConsoleSession, QuitRequested, ScriptCheckError
from daror_runtime.console.guide import next_steps
from daror_runtime.console.web.stream import AnnouncementHub, LiveStream
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import DarorError, InputError
from daror_runtime.runtime import Runtime

#: Console lines a browser may not send: they block the server or end the session from a page.
NOT_FROM_THE_PAGE = {"wait": "waits belong in scripts", "expect": "checks belong in scripts", "quit": "end the session at the terminal (quit or Ctrl-C)"}  # fmt: skip
#: Seconds between two messages on a socket (20 Hz); the status goes with the first after it changed (5 Hz).
PUSH_PERIOD_S = 0.05
STATIC = resources.files("daror_runtime.console.web") / "static"
TOKEN_COOKIE = "daror_token"


@dataclass
class WebConsole:
    """What the application serves: one runtime, its world (or None), the stream and the log."""

    runtime: Runtime
    world: SimWorld | None
    stream: LiveStream
    token: str | None = None  # None: loopback only, no token
    lock: threading.Lock = field(default_factory=threading.Lock)
    session: ConsoleSession = field(init=False)

    def __post_init__(self) -> None:
        self.buffer = io.StringIO()
        out = Console(file=self.buffer, width=110, color_system=None, highlight=False, soft_wrap=True)
        # the page's lines are answered like the terminal's; announcements reach every console
        # through the hub (pumped by the stream), so this session drains nothing itself
        self.session = ConsoleSession(self.runtime, out, self.world, announcements=lambda: [])
        self.stream.status_source = self.status  # built by the stream's thread, once for all sockets

    @property
    def hub(self) -> AnnouncementHub:
        return self.stream.hub

    def run_line(self, line: str) -> dict[str, Any]:
        """Run one console line from a page; its echo and answer join the shared log."""
        line = line.strip()
        word = line.split(maxsplit=1)[0] if line else ""
        if word in NOT_FROM_THE_PAGE:
            return self._answer(
                line, False, f"  error: '{word}' is not sent from the web console: {NOT_FROM_THE_PAGE[word]}"
            )
        session = self.session
        with self.lock:  # one line at a time, like the terminal
            self.buffer.seek(0)
            self.buffer.truncate()
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
            text = self.buffer.getvalue().rstrip()
        return self._answer(line, ok, text)

    def _answer(self, line: str, ok: bool, text: str) -> dict[str, Any]:
        self.hub.pump()  # what happened before this line is logged before it
        self.hub.add(f"(web) > {line}\n{text}" if text else f"(web) > {line}")
        self.hub.pump()
        return {"line": line, "ok": ok, "answer": text, "status": self.status()}

    def status(self) -> dict[str, Any]:
        status = self.runtime.snapshot()
        document = status.as_dict()
        document["next_steps"] = [
            {"what": step.text, "type": list(step.commands)} for step in next_steps(status, self.world is not None)
        ]
        document["has_world"] = self.world is not None
        document["notes"] = [*status.notes, *(self.world.notes(self.runtime.settings) if self.world else [])]
        return json.loads(json.dumps(document, default=str))

    def fsm(self) -> dict[str, Any]:
        spec = self.runtime.spec
        return {
            "superstates": [
                {
                    "name": sup.name,
                    "description": sup.description,
                    "states": [
                        {"name": s.name, "number": s.number, "description": s.description, "mode": s.mode}
                        for s in spec.states
                        if s.superstate == sup.name
                    ],
                }
                for sup in spec.superstates
            ],
            "fail": {"name": spec.fail.name, "description": spec.fail.description},
        }

    def allowed(self, presented: str | None) -> bool:
        return self.token is None or (presented is not None and hmac.compare_digest(presented, self.token))


def _presented(token: str | None, cookies: dict[str, str], headers: Any) -> str | None:
    return token or headers.get("x-daror-token") or cookies.get(TOKEN_COOKIE)


def create_app(web: WebConsole) -> FastAPI:
    """The FastAPI application of one web console (served by :func:`daror_runtime.console.web.serve.serve`)."""
    app = FastAPI(title="DAROR-01 operator console", docs_url=None, redoc_url=None, openapi_url=None)

    @app.middleware("http")
    async def guard(request: Request, call_next: Any) -> Response:
        presented = _presented(request.query_params.get("token"), request.cookies, request.headers)
        if not web.allowed(presented):
            return JSONResponse({"error": "a token is required (printed when the console started)"}, status_code=403)
        response: Response = await call_next(request)
        if web.token is not None and request.query_params.get("token"):
            response.set_cookie(TOKEN_COOKIE, web.token, httponly=True, samesite="strict")
        return response

    @app.get("/")
    def index() -> FileResponse:
        return FileResponse(str(STATIC / "index.html"), headers={"Cache-Control": "no-store"})

    @app.get("/api/fsm")
    def fsm() -> dict[str, Any]:
        return web.fsm()

    @app.get("/api/status")
    def status() -> dict[str, Any]:
        return web.status()

    @app.post("/api/command")
    def command(body: dict[str, Any]) -> dict[str, Any]:  # a thread of the pool: may wait for a tick
        line = body.get("line")
        if not isinstance(line, str) or len(line) > 2000:
            return {"line": "", "ok": False, "answer": "  error: expected {'line': 'a console line'}", "status": None}
        return web.run_line(line)

    @app.websocket("/ws")
    async def live(socket: WebSocket) -> None:
        presented = _presented(socket.query_params.get("token"), socket.cookies, socket.headers)
        if not web.allowed(presented):
            await socket.close(code=1008)
            return
        await socket.accept()
        rows_at, log_at, sent = 0, 0, -1
        try:
            while True:
                rows_at, rows = web.stream.since(rows_at)
                log_at, lines = web.hub.since(log_at)
                version, status = web.stream.status_json
                if version == sent:
                    status = "null"
                sent = version
                message = f'{{"rows":[{",".join(rows)}],"log":{json.dumps(lines)},"status":{status}}}'
                # a slow browser: the send waits, the ring moves on (the oldest rows are dropped)
                await asyncio.wait_for(socket.send_text(message), timeout=2.0)
                await asyncio.sleep(PUSH_PERIOD_S)
        except (TimeoutError, WebSocketDisconnect, RuntimeError, OSError):
            return  # the robot does not notice a browser leaving

    app.mount("/static", StaticFiles(directory=str(STATIC)), name="static")
    return app
