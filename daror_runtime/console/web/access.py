"""Who may use the web console: the token, the ``Host`` header and the ``Origin``, as Jupyter does.

A console in a browser drives the robot, so a page must not reach it just because it runs on the
same computer (docs/safety.md, H29):

* **the token**, on every address by default (``--no-token`` only on the loopback): a random
  secret printed in the console's URL; presented once as ``?token=`` (the answer then sets it as
  an HttpOnly, SameSite=strict cookie, which another site's page never sends), or in the
  ``X-Daror-Token`` header;
* **the Host header** must name an address the server listens on, with its port: a DNS-rebinding
  site reaches the server under its own name (``Host: evil.example:8765``) and is refused;
* **the Origin** of every state-changing request (anything but GET, HEAD, OPTIONS) and of the
  WebSocket handshake (WebSockets are outside CORS) must be absent (a client that is not a
  browser) or the console's own (``http://`` + an accepted Host).

:class:`Access` is built in the runtime's process (:func:`daror_runtime.console.web.serve.start_web`)
and applied in the server's (:mod:`daror_runtime.console.web.app`); it imports no web framework.
"""

from __future__ import annotations

import functools
import hmac
import ipaddress
import socket
from dataclasses import dataclass

from daror_runtime.errors import UsageError

#: The names a browser may use for a server on the loopback (Host header, without the port).
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "[::1]")
#: Methods that change nothing (no Origin check; CORS keeps their answers from another site's page).
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
#: Characters of a refused header quoted back in the answer.
QUOTED_CHARS = 100


def is_loopback(host: str) -> bool:
    """Whether ``host`` is reachable from this machine only (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def is_wildcard(host: str) -> bool:
    """Whether ``host`` is an unspecified address (0.0.0.0, ::): the server listens on every interface."""
    try:
        return ipaddress.ip_address(host.strip("[]")).is_unspecified
    except ValueError:
        return False


def host_name(host: str) -> str:
    """``host`` as a Host header names it, without the port: lower case, an IPv6 address in brackets."""
    bare = host.strip("[]").lower()
    try:
        address = ipaddress.ip_address(bare)
    except ValueError:
        return bare
    return f"[{address}]" if address.version == 6 else str(address)


def check_no_token(host: str) -> None:
    """Raises :class:`UsageError` unless ``--no-token`` may be used on ``host`` (the loopback only)."""
    if not is_loopback(host):
        raise UsageError(
            f"--no-token --host {host}: a console without a token is allowed on the loopback only "
            "(127.0.0.1, ::1, localhost); beyond it, open the URL with the token the console prints"
        )


@functools.lru_cache(maxsize=256)
def _is_local_address(name: str) -> bool:
    """Whether ``name`` (an IP literal, IPv6 in brackets) is an address of this machine (it can be bound)."""
    try:
        address = ipaddress.ip_address(name.strip("[]"))
    except ValueError:
        return False
    family = socket.AF_INET6 if address.version == 6 else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as probe:
            probe.bind((str(address), 0))
    except OSError:  # EADDRNOTAVAIL: not one of ours
        return False
    return True


def _split_host(header: str) -> tuple[str, int | None] | None:
    """``(name, port)`` of a Host header (``name:port``, ``[v6]:port``, ``name``); None: malformed."""
    if header.startswith("["):
        end = header.find("]")
        if end < 0:
            return None
        name, rest = header[: end + 1], header[end + 1 :]
    else:
        name, colon, port = header.rpartition(":")
        if not colon:
            name, port = header, ""
        rest = f":{port}" if colon else ""
    if not rest:
        return name.lower(), None
    if not rest.startswith(":") or not rest[1:].isdigit() or len(rest) > 6:
        return None
    return name.lower(), int(rest[1:])


@dataclass(frozen=True)
class Access:
    """What one web console accepts (see the module's docstring).

    Attributes:
        token: the secret a request must present; None: none asked (``--no-token``, loopback only).
        port: the port the server listens on (a Host header must name it; 80 may be left out).
        names: the host names and addresses accepted in a Host header (as :func:`host_name` writes them).
        any_local_address: the server listens on every interface: any address of this machine is
            accepted too (checked when asked: interfaces come and go).
    """

    token: str | None
    port: int
    names: frozenset[str]
    any_local_address: bool = False

    @classmethod
    def for_address(cls, host: str, port: int, token: str | None) -> Access:
        """The access of a server bound to ``host:port`` (port: the bound one).

        On the loopback: its names (``localhost``, ``127.0.0.1``, ``[::1]``). Elsewhere: the address
        given, this machine's name (``gethostname()``, and ``NAME.local`` for mDNS; no DNS lookup,
        which may hang offline), and on a wildcard address every address of the machine and the
        loopback names.

        Raises:
            UsageError: no token on an address beyond the loopback (:func:`check_no_token`).
        """
        if token is None:
            check_no_token(host)
        names = {host_name(host)}
        wildcard = is_wildcard(host)
        if is_loopback(host) or wildcard:
            names.update(LOOPBACK_NAMES)
        if not is_loopback(host):
            machine = socket.gethostname().lower()
            names.update({machine, f"{machine}.local"})
        return cls(token, port, frozenset(names), wildcard)

    @property
    def cookie(self) -> str:
        """The token's cookie: one per port (cookies do not tell ports apart; two consoles may run)."""
        return f"daror_token_{self.port}"

    def host_allowed(self, header: str | None) -> bool:
        """Whether a Host header names this server (an accepted name and the bound port)."""
        if not header:
            return False
        parsed = _split_host(header.strip())
        if parsed is None:
            return False
        name, port = parsed
        if (port if port is not None else 80) != self.port:
            return False
        return name in self.names or (self.any_local_address and _is_local_address(name))

    def origin_allowed(self, header: str | None) -> bool:
        """Whether an Origin header is absent (not a browser) or this console's own page."""
        if header is None:
            return True
        scheme, separator, rest = header.strip().partition("://")
        return separator == "://" and scheme.lower() == "http" and "/" not in rest and self.host_allowed(rest)

    def token_allowed(self, presented: str | None) -> bool:
        """Whether ``presented`` opens this console (any value when it asks no token)."""
        if self.token is None:
            return True
        return presented is not None and hmac.compare_digest(presented.encode(), self.token.encode())

    def refusal(self, host: str | None, origin: str | None, presented: str | None, state_changing: bool) -> str | None:
        """Why a request (or a WebSocket handshake: ``state_changing`` True) is refused, or None: allowed."""
        if not self.host_allowed(host):
            return f"Host {_quoted(host)} is not this console's address (expected {self.example_host})"
        if state_changing and not self.origin_allowed(origin):
            return f"a request from {_quoted(origin)} is refused: only this console's own page may send it"
        if not self.token_allowed(presented):
            return "a token is required (open the URL printed when the console started)"
        return None

    @property
    def example_host(self) -> str:
        """An accepted Host header, for a refusal's message."""
        name = "127.0.0.1" if "127.0.0.1" in self.names else min(self.names)
        return f"{name}:{self.port}"


def _quoted(value: str | None) -> str:
    return "(none)" if value is None else repr(value[:QUOTED_CHARS])
