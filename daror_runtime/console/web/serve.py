"""Serving the web console beside a session: the server in its own process, a thin bridge in the runtime's.

``daror console --web`` (``daror_runtime/cli/console.py``) opens the runtime, then :func:`start_web`, then
starts the loop; the text console may run at the terminal meanwhile, on the same runtime and the
same log (:attr:`WebServer.hub`). The HTTP and websocket work (uvicorn, FastAPI, JSON) runs in a
process of its own (:mod:`daror_runtime.console.web.server`), so it never holds the interpreter
the control loop needs; the runtime's process keeps only :class:`~daror_runtime.console.web.bridge.WebBridge`
(docs/console.md, "What the page costs the loop"). Closing a browser changes nothing on the robot;
neither does the server stopping (the session ends at the terminal: quit, Ctrl-C, or a signal).
Who may use the page: :mod:`daror_runtime.console.web.access` (a token by default on every address,
the Host header, the Origin).
"""

from __future__ import annotations

import os
import pickle
import secrets
import socket
import subprocess
import sys
import time
from dataclasses import dataclass

from daror_runtime.console.web import require_web_extra
from daror_runtime.console.web.access import Access, check_no_token
from daror_runtime.console.web.bridge import MAX_MESSAGE_BYTES, AnnouncementHub, WebBridge
from daror_runtime.console.web.ring import RowRing
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import DarorError, UsageError
from daror_runtime.fsm.diagram import layout
from daror_runtime.runtime import Runtime
from hal.robot import N_JOINTS

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
#: Live rows per second the bridge writes (>= 20 Hz to the browser): one per service period.
SAMPLE_HZ = 50.0
#: Seconds of live rows the ring keeps (the plots show the last 20 s).
WINDOW_S = 30.0
#: Seconds the server process gets to import and serve.
START_TIMEOUT_S = 30.0
#: The server process's output, in the session's folder.
SERVER_LOG = "web-server.log"


@dataclass
class WebServer:
    """A running web console: its address, its token (None: ``--no-token``, loopback only), and how to stop it."""

    url: str
    token: str | None
    bridge: WebBridge
    process: subprocess.Popen[bytes]
    ring: RowRing

    @property
    def hub(self) -> AnnouncementHub:
        """The shared log (the terminal's console drains :meth:`AnnouncementHub.terminal_reader`)."""
        return self.bridge.hub

    @property
    def address(self) -> str:
        """What to open in a browser (with the token when there is one)."""
        return f"{self.url}/?token={self.token}" if self.token else f"{self.url}/"

    def stop(self) -> None:
        """Stop serving (the session and its loop go on): the bridge closes, the server process exits."""
        self.bridge.close()
        try:
            self.process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(timeout=5.0)
        self.ring.close()

    def serve_until_interrupted(self) -> str:
        """Block until a stop signal (KeyboardInterrupt propagates) or the server is lost; then why it was lost."""
        while self.process.poll() is None and self.bridge.lost is None:
            time.sleep(0.2)
        return f"{self.bridge.lost or 'the web server exited'} (see {SERVER_LOG})"


def _listen(host: str, port: int) -> socket.socket:
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
        return socket.create_server((host, port), family=family, backlog=128)
    except (OSError, OverflowError) as exc:
        why = getattr(exc, "strerror", None) or str(exc)
        raise UsageError(f"--host {host} --port {port}: the web console cannot listen there ({why})") from None


def start_web(
    runtime: Runtime,
    world: SimWorld | None,
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    require_token: bool = True,
    token: str | None = None,
    records_url: str | None = None,
) -> WebServer:
    """Serve the web console of ``runtime`` on ``host:port`` (port 0: any free port) until :meth:`WebServer.stop`.

    A token is required on every address (``token``, or a new random one; :attr:`WebServer.address`
    carries it); ``require_token`` False (``--no-token``) only on the loopback. The Host and Origin
    headers are checked whatever the token (:class:`~daror_runtime.console.web.access.Access`).
    ``records_url``: the lab's records the pages' lines read a returning pilot's from (``pilot``,
    ``rom last``, ``model last``), as the terminal's do (None: none).
    Call it before the loop starts: starting a process beside a running loop costs it a stall.

    Raises:
        WebExtraMissingError: FastAPI, uvicorn or websockets are not installed.
        UsageError: no token beyond the loopback, or the address cannot be bound (nothing started).
        DarorError: the server process did not start (its log names why).
    """
    require_web_extra()
    if require_token:
        token = token or secrets.token_urlsafe(18)
    else:
        check_no_token(host)
        token = None
    listen = _listen(host, port)
    bound = listen.getsockname()[1]
    access = Access.for_address(host, bound, token)
    n_joints = N_JOINTS
    ring, ring_fd = RowRing.create(int(SAMPLE_HZ * WINDOW_S), n_joints)
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for end in (ours, theirs):
        end.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 2 * MAX_MESSAGE_BYTES)
        end.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2 * MAX_MESSAGE_BYTES)
    runtime.session_dir.mkdir(parents=True, exist_ok=True)
    log_path = runtime.session_dir / SERVER_LOG
    with open(log_path, "ab") as output:
        fds = (theirs.fileno(), ring_fd, listen.fileno())
        process = subprocess.Popen(
            [sys.executable, "-m", "daror_runtime.console.web.server", *map(str, fds)],
            pass_fds=fds, stdin=subprocess.DEVNULL, stdout=output, stderr=subprocess.STDOUT,
            start_new_session=True,  # Ctrl-C at the terminal is the session's, not the server's
        )  # fmt: skip
    theirs.close()
    listen.close()
    os.close(ring_fd)
    hello = {
        "access": access,  # the token, the accepted Host names and port
        "fsm": layout(runtime.spec),  # the diagram the page draws
        "has_world": world is not None,
        "capacity": ring.capacity,
        "n_joints": n_joints,
        "status": runtime.snapshot(),
        "notes": world.notes(runtime.settings) if world is not None else [],
    }
    try:
        ours.send(pickle.dumps(("hello", hello), protocol=5))
        _await_ready(ours, process, log_path)
    except BaseException:
        process.kill()
        process.wait(timeout=5.0)
        ours.close()
        ring.close()
        raise
    bridge = WebBridge(runtime, world, ours, ring, AnnouncementHub(runtime), records_url)
    bridge.start()
    shown = f"[{host}]" if ":" in host else host
    return WebServer(f"http://{shown}:{bound}", token, bridge, process, ring)


def _await_ready(link: socket.socket, process: subprocess.Popen[bytes], log_path: object) -> None:
    link.settimeout(START_TIMEOUT_S)
    try:
        data = link.recv(MAX_MESSAGE_BYTES)
    except TimeoutError:
        data = None
    finally:
        link.settimeout(None)
    if data and pickle.loads(data)[0] == "ready":
        return
    why = "did not answer in time" if data is None else f"exited with code {process.poll()}"
    raise DarorError(f"the web console's server {why}: {_last_line(log_path)}")


def _last_line(path: object) -> str:
    try:
        with open(str(path), encoding="utf-8", errors="replace") as text:
            lines = [line.strip() for line in text if line.strip()]
    except OSError:
        return "no log"
    return lines[-1] if lines else "no output"
