"""Serving the web console next to a session: uvicorn on its own thread, the stream on another.

``daror console --web`` (``daror_runtime/cli.py``) opens the runtime, starts its loop in real time,
then :func:`start_web`; the text console may run at the terminal meanwhile, on the same runtime and
the same log (:meth:`WebServer.terminal_announcements`). Closing a browser changes nothing on the
robot; stopping the server neither (the session ends at the terminal: quit or Ctrl-C).
"""

from __future__ import annotations

import ipaddress
import secrets
import threading
import time
from dataclasses import dataclass

from daror_runtime.console.web import require_web_extra
from daror_runtime.console.web.stream import AnnouncementHub, LiveStream, raise_priority
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import UsageError
from daror_runtime.runtime import Runtime

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765


def is_loopback(host: str) -> bool:
    """Whether ``host`` is reachable from this machine only (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass
class WebServer:
    """A running web console: its address, its token (None on the loopback) and how to stop it."""

    url: str
    token: str | None
    stream: LiveStream
    _server: object
    _thread: threading.Thread

    @property
    def hub(self) -> AnnouncementHub:
        return self.stream.hub

    @property
    def address(self) -> str:
        """What to open in a browser (with the token when there is one)."""
        return f"{self.url}/?token={self.token}" if self.token else f"{self.url}/"

    def stop(self) -> None:
        """Stop serving (the session and its loop go on)."""
        self._server.should_exit = True  # type: ignore[attr-defined]
        self._thread.join(timeout=5.0)
        self.stream.stop()

    def serve_until_interrupted(self) -> None:
        """Block until Ctrl-C (KeyboardInterrupt propagates: the caller ends the session)."""
        while self._thread.is_alive():
            time.sleep(0.2)


def start_web(
    runtime: Runtime,
    world: SimWorld | None,
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    token: str | None = None,
) -> WebServer:
    """Serve the web console of ``runtime`` on ``host:port`` (port 0: any free port) until :meth:`WebServer.stop`.

    Beyond the loopback a token is required (``token`` or a new random one).

    Raises:
        WebExtraMissingError: FastAPI, uvicorn or websockets are not installed.
        UsageError: the address cannot be bound.
    """
    require_web_extra()
    import uvicorn

    from daror_runtime.console.web.app import WebConsole, create_app

    if not is_loopback(host) and token is None:
        token = secrets.token_urlsafe(18)
    stream = LiveStream(runtime, AnnouncementHub(runtime))
    web = WebConsole(runtime, world, stream, token=token)
    config = uvicorn.Config(
        create_app(web), host=host, port=port, log_level="warning", access_log=False, lifespan="off", ws="websockets"
    )
    server = uvicorn.Server(config)
    server.install_signal_handlers = lambda: None  # type: ignore[method-assign]  # Ctrl-C is the session's

    def run() -> None:
        raise_priority()
        server.run()

    thread = threading.Thread(target=run, name="daror-web", daemon=True)
    stream.start()
    thread.start()
    deadline = time.monotonic() + 10.0
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            stream.stop()
            raise UsageError(f"--host {host} --port {port}: the web console could not listen there")
        time.sleep(0.02)
    bound = port
    for s in getattr(server, "servers", []):
        for sock in s.sockets:
            bound = sock.getsockname()[1]
    shown = f"[{host}]" if ":" in host else host
    served = WebServer(f"http://{shown}:{bound}", token, stream, server, thread)
    _warm_up(served)
    return served


def _warm_up(served: WebServer) -> None:
    """Ask every route once, a socket included, before the loop runs beside the server.

    The first request of each kind imports and builds what serves it (the websocket protocol,
    the thread pool, the file responses): loading compiled modules holds the interpreter for
    milliseconds, which would be a stall of a loop already running.
    """
    import urllib.request

    from websockets.sync.client import connect

    query = f"?token={served.token}" if served.token else ""
    local = served.url.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")
    for route in ("/", "/api/fsm", "/api/status", "/static/app.js"):
        with urllib.request.urlopen(f"{local}{route}{query}", timeout=10.0) as answer:
            answer.read()
    with connect(local.replace("http", "ws", 1) + "/ws" + query, open_timeout=10.0) as socket:
        socket.recv(timeout=10.0)
