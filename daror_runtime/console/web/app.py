"""The web console's application, served from its own process: the page, the status, console lines, live data.

Routes (all behind the token when the server listens beyond the loopback):

* ``GET /``: the page (``static/index.html``; every asset is in the package: the lab PC is offline);
* ``GET /api/fsm``: the diagram of ``fsm_spec.yaml``, laid out (:func:`daror_runtime.fsm.diagram.layout`);
* ``GET /api/status``: the session's status as the runtime last published it (on a change, else 2.5 Hz);
* ``POST /api/command`` ``{"line": "advance"}``: one console line, forwarded to the runtime's process,
  checked and answered exactly as typed at the text console; the request it posts is applied at a
  tick boundary, a refusal comes back with its reason;
* ``WS /ws``: live rows (>= 20 Hz, in batches of 50 ms), the status (when it changed) and new log lines.

Nothing here runs in the runtime's process (:mod:`daror_runtime.console.web.page`): a socket reads
the shared ring of rows from its own cursor, and a socket that is closed or slow only misses rows.
"""

from __future__ import annotations

import asyncio
import hmac
import json
from importlib import resources
from typing import Any

from fastapi import FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles

from daror_runtime.console.web.page import PageState

#: Seconds between two messages on a socket (20 Hz); the status goes with the first after it changed.
PUSH_PERIOD_S = 0.05
STATIC = resources.files("daror_runtime.console.web") / "static"
TOKEN_COOKIE = "daror_token"


def allowed(token: str | None, presented: str | None) -> bool:
    """Whether ``presented`` opens a server whose token is ``token`` (None: loopback, no token)."""
    return token is None or (presented is not None and hmac.compare_digest(presented, token))


def _presented(token: str | None, cookies: dict[str, str], headers: Any) -> str | None:
    return token or headers.get("x-daror-token") or cookies.get(TOKEN_COOKIE)


def create_app(page: PageState, token: str | None) -> FastAPI:
    """The FastAPI application of one web console (served by :mod:`daror_runtime.console.web.server`)."""
    app = FastAPI(title="DAROR-01 operator console", docs_url=None, redoc_url=None, openapi_url=None)

    @app.middleware("http")
    async def guard(request: Request, call_next: Any) -> Response:
        presented = _presented(request.query_params.get("token"), request.cookies, request.headers)
        if not allowed(token, presented):
            return JSONResponse({"error": "a token is required (printed when the console started)"}, status_code=403)
        response: Response = await call_next(request)
        if token is not None and request.query_params.get("token"):
            response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="strict")
        return response

    @app.get("/")
    def index() -> FileResponse:
        return FileResponse(str(STATIC / "index.html"), headers={"Cache-Control": "no-store"})

    @app.get("/api/fsm")
    def fsm() -> dict[str, Any]:
        return page.fsm

    @app.get("/api/status")
    def status() -> dict[str, Any]:
        return page.status()

    @app.post("/api/command")
    def command(body: dict[str, Any]) -> dict[str, Any]:  # a thread of the pool: waits for the runtime's answer
        line = body.get("line")
        if not isinstance(line, str) or len(line) > 2000:
            return {"line": "", "ok": False, "answer": "  error: expected {'line': 'a console line'}", "status": None}
        return page.command(line)

    @app.websocket("/ws")
    async def live(socket: WebSocket) -> None:
        presented = _presented(socket.query_params.get("token"), socket.cookies, socket.headers)
        if not allowed(token, presented):
            await socket.close(code=1008)
            return
        await socket.accept()
        rows_at, log_at, sent = 0, 0, -1
        try:
            while True:
                rows_at, rows = page.rows_since(rows_at)
                log_at, lines = page.log_since(log_at)
                version, status = page.status_json
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
