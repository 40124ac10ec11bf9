"""The web server's process: ``python -m daror_runtime.console.web.server LINK RING LISTEN``.

Started by :func:`daror_runtime.console.web.serve.start_web` (never by hand): the arguments are
file descriptors it inherited, the runtime's end of a ``SOCK_SEQPACKET`` pair (``LINK``), the
shared ring of live rows (``RING``) and the socket already listening for browsers (``LISTEN``,
bound by the runtime's process, which so reports a bad address itself). The first message on the
link is the hello (:class:`~daror_runtime.console.web.page.PageState`); the server answers
``("ready",)`` once it serves, and exits when the runtime's end closes. Its output goes to
``web-server.log`` in the session's folder.
"""

from __future__ import annotations

import pickle
import socket
import sys
import threading
import time

from daror_runtime.console.web.bridge import MAX_MESSAGE_BYTES
from daror_runtime.console.web.ring import RowRing

#: Seconds the server waits for the runtime's hello.
HELLO_TIMEOUT_S = 30.0


def main(argv: list[str]) -> int:
    """Serve until the runtime's end of the link closes; 0, or 2 when started wrongly."""
    if len(argv) != 3 or not all(arg.isdigit() for arg in argv):
        sys.stderr.write("usage: python -m daror_runtime.console.web.server LINK RING LISTEN (file descriptors)\n")
        return 2
    import uvicorn

    from daror_runtime.console.web.app import create_app
    from daror_runtime.console.web.page import PageState

    link = socket.socket(fileno=int(argv[0]))
    listen = socket.socket(fileno=int(argv[2]))
    link.settimeout(HELLO_TIMEOUT_S)
    kind, hello = pickle.loads(link.recv(MAX_MESSAGE_BYTES))
    link.settimeout(None)
    if kind != "hello":
        sys.stderr.write(f"web server: expected the runtime's hello, got {kind!r}\n")
        return 2
    ring = RowRing.attach(int(argv[1]), hello["capacity"], hello["n_joints"])
    page = PageState(link, ring, hello)
    app = create_app(page, hello["access"])
    config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="off", ws="websockets-sansio")
    server = uvicorn.Server(config)

    def stop() -> None:
        server.should_exit = True

    page.on_runtime_gone = stop
    threading.Thread(target=page.read_forever, name="daror-web-link", daemon=True).start()

    def announce_ready() -> None:
        while not server.started and not server.should_exit:
            time.sleep(0.01)
        if server.started:
            link.send(pickle.dumps(("ready",), protocol=5))

    threading.Thread(target=announce_ready, name="daror-web-ready", daemon=True).start()
    server.run(sockets=[listen])
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
