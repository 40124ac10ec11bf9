"""The web console's application, served from its own process: the page, the status, console lines, live data.

Every request and the WebSocket handshake pass :class:`~daror_runtime.console.web.access.Access`
first (the Host header, the Origin of what changes state, the token): refused with 403 and nothing
run. Routes:

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
import json
from importlib import resources
from typing import Any

from fastapi import FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles

from daror_runtime.console.web.access import SAFE_METHODS, Access
from daror_runtime.console.web.page import PageState

#: Seconds between two messages on a socket (20 Hz); the status goes with the first after it changed.
PUSH_PERIOD_S = 0.05
STATIC = resources.files("daror_runtime.console.web") / "static"
#: The header a client that is not a browser presents the token in.
TOKEN_HEADER = "x-daror-token"


def _presented(access: Access, query: Any, cookies: dict[str, str], headers: Any) -> str | None:
    """The token a request presents: ``?token=``, the header, or the cookie (in that order)."""
    return query.get("token") or headers.get(TOKEN_HEADER) or cookies.get(access.cookie)


def create_app(page: PageState, access: Access) -> FastAPI:
    """The FastAPI application of one web console (served by :mod:`daror_runtime.console.web.server`)."""
    app = FastAPI(title="DAROR-01 operator console", docs_url=None, redoc_url=None, openapi_url=None)

    @app.middleware("http")
    async def guard(request: Request, call_next: Any) -> Response:
        refusal = access.refusal(
            request.headers.get("host"),
            request.headers.get("origin"),
            _presented(access, request.query_params, request.cookies, request.headers),
            state_changing=request.method not in SAFE_METHODS,
        )
        if refusal is not None:  # before any route: nothing runs
            return JSONResponse({"error": refusal}, status_code=403)
        response: Response = await call_next(request)
        if access.token is not None and request.query_params.get("token"):
            response.set_cookie(access.cookie, access.token, httponly=True, samesite="strict")
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
        refusal = access.refusal(  # a browser always sends its page's Origin here; WebSockets skip CORS
            socket.headers.get("host"),
            socket.headers.get("origin"),
            _presented(access, socket.query_params, socket.cookies, socket.headers),
            state_changing=True,
        )
        if refusal is not None:  # closed before it is accepted: the handshake is answered 403
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
