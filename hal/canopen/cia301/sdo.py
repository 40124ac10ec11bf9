"""CiA 301 service data objects: expedited transfers, and a client that never waits on the bus.

An expedited transfer moves up to 4 bytes in one request and one response (8 bytes each)::

    request  0x600 + id: [command][index lo][index hi][sub][data, 4 bytes]
    response 0x580 + id: [command][index lo][index hi][sub][data or abort code, 4 bytes]

Every object the backend writes or reads at start-up (PDO parameters, heartbeat times, the
drive's units) fits in 4 bytes, so segmented and block transfers are not implemented; a request
for more is refused before it is sent.

:class:`SdoClient` keeps a queue of transfers per node with one in flight, sends what is due when
asked (:meth:`SdoClient.frames_due`), takes responses as they arrive (:meth:`SdoClient.on_response`)
and times transfers out against a time the caller passes in. It blocks nowhere: ``open`` runs it
until every transfer is done (outside the tick), and the tick can run it a frame at a time.

A write may be one the drive is free to refuse (``may_decline``: a capability, not a failure; its
abort is recorded in ``declined``) and may need earlier transfers to the same node to have
succeeded (``needs``: else it is skipped, never sent). A missing answer is always an error.
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass, field

from hal.canopen.cia301.nmt import SDO_REQUEST_BASE

__all__ = [
    "ABORT_MESSAGES",
    "SdoClient",
    "SdoTransfer",
    "abort_frame",
    "describe_abort",
    "download_request",
    "download_response",
    "parse_request",
    "parse_response",
    "upload_request",
    "upload_response",
]

_HEADER = struct.Struct("<BHB")
#: Abort codes that say an object or sub-index does not exist.
_DOES_NOT_EXIST = (0x06020000, 0x06090011)
_ABORT = struct.Struct("<BHBI")

#: Abort codes (CiA 301 table 22) and what they mean.
ABORT_MESSAGES: dict[int, str] = {
    0x05040000: "SDO protocol timed out",
    0x05040001: "client/server command specifier not valid or unknown",
    0x06010000: "unsupported access to an object",
    0x06010001: "attempt to read a write-only object",
    0x06010002: "attempt to write a read-only object",
    0x06020000: "object does not exist in the object dictionary",
    0x06040041: "object cannot be mapped to the PDO",
    0x06040042: "the number and length of the objects to be mapped would exceed the PDO length",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06090011: "sub-index does not exist",
    0x06090030: "invalid value for parameter (download only)",
    0x06090031: "value of parameter written too high",
    0x06090032: "value of parameter written too low",
    0x08000000: "general error",
    0x08000020: "data cannot be transferred or stored to the application",
    0x08000022: "data cannot be transferred or stored because of the present device state",
}


def describe_abort(code: int) -> str:
    """An abort code and its meaning (CiA 301 table 22), for a message: ``0x06020000 object does not exist ...``."""
    return f"0x{code:08X} {ABORT_MESSAGES.get(code, 'unknown abort code')}"


def download_request(index: int, sub: int, data: bytes) -> bytes:
    """An expedited download (write) of 1-4 bytes to ``index:sub``.

    Raises:
        ValueError: ``data`` is empty or longer than 4 bytes (not expedited).
    """
    n = len(data)
    if not 1 <= n <= 4:
        raise ValueError(f"an expedited SDO download carries 1-4 bytes, not {n}")
    return _HEADER.pack(0x23 | ((4 - n) << 2), index, sub) + data.ljust(4, b"\0")


def upload_request(index: int, sub: int) -> bytes:
    """An upload (read) request of ``index:sub``."""
    return _HEADER.pack(0x40, index, sub) + b"\0\0\0\0"


def download_response(index: int, sub: int) -> bytes:
    """The server's confirmation of a download."""
    return _HEADER.pack(0x60, index, sub) + b"\0\0\0\0"


def upload_response(index: int, sub: int, data: bytes) -> bytes:
    """The server's expedited upload response carrying ``data`` (1-4 bytes)."""
    n = len(data)
    if not 1 <= n <= 4:
        raise ValueError(f"an expedited SDO upload carries 1-4 bytes, not {n}")
    return _HEADER.pack(0x43 | ((4 - n) << 2), index, sub) + data.ljust(4, b"\0")


def abort_frame(index: int, sub: int, code: int) -> bytes:
    """An abort of the transfer of ``index:sub`` with ``code`` (either side may send it)."""
    return _ABORT.pack(0x80, index, sub, code)


@dataclass(frozen=True)
class SdoRequest:
    """A request as a server reads it: ``kind`` "download" (with ``data``) or "upload"; "abort" or "unknown"."""

    kind: str
    index: int
    sub: int
    data: bytes = b""


def parse_request(frame: bytes) -> SdoRequest:
    """What a client asked in ``frame`` (a server's view; 8 bytes expected)."""
    if len(frame) < 8:
        return SdoRequest("unknown", 0, 0)
    command, index, sub = _HEADER.unpack_from(frame)
    ccs = command >> 5
    if ccs == 1 and command & 0x02:  # expedited download
        size = 4 - ((command >> 2) & 0x03) if command & 0x01 else 4
        return SdoRequest("download", index, sub, bytes(frame[4 : 4 + size]))
    if ccs == 2:
        return SdoRequest("upload", index, sub)
    if ccs == 4:
        return SdoRequest("abort", index, sub)
    return SdoRequest("unknown", index, sub)


@dataclass(frozen=True)
class SdoResponse:
    """A server's answer: ``kind`` "downloaded", "uploaded" (with ``data``), "aborted" (with ``abort_code``) or "unknown"."""

    kind: str
    index: int
    sub: int
    data: bytes = b""
    abort_code: int = 0


def parse_response(frame: bytes) -> SdoResponse:
    """What a server answered in ``frame`` (8 bytes expected)."""
    if len(frame) < 8:
        return SdoResponse("unknown", 0, 0)
    command, index, sub = _HEADER.unpack_from(frame)
    scs = command >> 5
    if command == 0x80:
        return SdoResponse("aborted", index, sub, abort_code=_ABORT.unpack_from(frame)[3])
    if scs == 3:
        return SdoResponse("downloaded", index, sub)
    if scs == 2 and command & 0x02:  # expedited upload
        size = 4 - ((command >> 2) & 0x03) if command & 0x01 else 4
        return SdoResponse("uploaded", index, sub, bytes(frame[4 : 4 + size]))
    return SdoResponse("unknown", index, sub)


@dataclass
class SdoTransfer:
    """One transfer of an :class:`SdoClient`: a write of ``data`` to, or a read of, ``index:sub`` of ``node_id``.

    ``done`` once answered, failed, declined or skipped; ``error`` says why it failed (None if it
    did not: a transport failure, an unexpected answer, or an abort of a transfer that may not be
    declined); ``declined`` says why the drive refused a write that may be declined (its abort
    code and meaning); ``skipped`` is set when a transfer it ``needs`` did not succeed, and it was
    never sent. ``value`` holds the bytes a read returned.
    """

    node_id: int
    index: int
    sub: int
    data: bytes | None  # None: a read
    what: str = ""  # what the transfer is for, for messages ("TPDO1 mapping entry 2")
    optional: bool = False  # the object may not exist on the drive: "does not exist" is not an error
    may_decline: bool = False  # any abort is the drive's answer (recorded in ``declined``), not an error
    needs: tuple[SdoTransfer, ...] = ()  # earlier transfers of the same node that must have succeeded
    sent_at_s: float | None = None
    done: bool = False
    error: str | None = None
    declined: str | None = None
    skipped: bool = False
    value: bytes = b""

    @property
    def target(self) -> str:
        return f"node {self.node_id} 0x{self.index:04X}:{self.sub}" + (f" ({self.what})" if self.what else "")

    @property
    def succeeded(self) -> bool:
        """True once the drive answered it as asked (not failed, declined or skipped)."""
        return self.done and self.error is None and self.declined is None and not self.skipped


@dataclass
class SdoClient:
    """Expedited SDO transfers to several nodes, one in flight per node, never waiting.

    Args:
        timeout_s: how long a transfer may wait for its response, s (the caller's clock).
    """

    timeout_s: float = 0.5
    _queues: dict[int, deque[SdoTransfer]] = field(default_factory=dict)
    _in_flight: dict[int, SdoTransfer] = field(default_factory=dict)

    def write(
        self,
        node_id: int,
        index: int,
        sub: int,
        data: bytes,
        what: str = "",
        optional: bool = False,
        may_decline: bool = False,
        needs: tuple[SdoTransfer, ...] = (),
    ) -> SdoTransfer:
        """Queue a write of ``data`` (1-4 bytes) to ``index:sub`` of ``node_id``.

        ``optional``: an object the drive may not have; its "object/sub-index does not exist"
        abort completes the transfer without an error. ``may_decline``: a write the drive may
        refuse (a capability the caller checks): any abort completes it with ``declined`` set, not
        ``error`` (a missing answer is still an error). ``needs``: earlier transfers to the same
        node; if one of them did not succeed when this one's turn comes, it is skipped, never sent
        (a value that only makes sense once those were taken).

        Raises:
            ValueError: ``data`` does not fit an expedited transfer, or a transfer it needs is for another node.
        """
        download_request(index, sub, data)  # refused now rather than on the bus
        if any(needed.node_id != node_id for needed in needs):
            raise ValueError(f"node {node_id} 0x{index:04X}:{sub}: a transfer can only need transfers to its own node")
        return self._queue(SdoTransfer(node_id, index, sub, data, what, optional, may_decline, needs))

    def read(self, node_id: int, index: int, sub: int, what: str = "") -> SdoTransfer:
        """Queue a read of ``index:sub`` of ``node_id`` (at most 4 bytes expected)."""
        return self._queue(SdoTransfer(node_id, index, sub, None, what))

    def _queue(self, transfer: SdoTransfer) -> SdoTransfer:
        self._queues.setdefault(transfer.node_id, deque()).append(transfer)
        return transfer

    @property
    def busy(self) -> bool:
        """True while a transfer is queued or in flight."""
        return bool(self._in_flight) or any(self._queues.values())

    def idle(self) -> bool:
        """True while no transfer is queued or in flight (:attr:`busy`'s opposite, as a call: it runs every cycle)."""
        return not self._in_flight and not any(self._queues.values())

    def startable(self) -> int:
        """How many nodes have a transfer queued and none in flight: the most :meth:`frames_due` would start."""
        if not any(self._queues.values()):  # nearly every cycle: nothing queued (one C call, no generator)
            return 0
        return sum(1 for node_id, queue in self._queues.items() if queue and node_id not in self._in_flight)

    def frames_due(
        self, now_s: float, limit: int | None = None, abandon_silent: bool = False
    ) -> list[tuple[int, bytes]]:
        """Time out what waited too long; start the next transfer of idle nodes: ``(COB-ID, data)`` to send.

        ``limit``: start at most this many (None: one per idle node). The nodes take turns: the one
        that started last goes to the back, so a limit never starves a node. ``abandon_silent``: a
        node whose transfer timed out is sent nothing more of what is queued for it; those
        transfers are skipped, as a transfer whose ``needs`` failed is (a start-up, which fails on
        the timed-out transfer, then fails after one timeout, not one per queued transfer).
        """
        if self.idle():  # nearly every cycle: nothing to do
            return []
        for node_id, transfer in list(self._in_flight.items()):
            if transfer.sent_at_s is not None and now_s - transfer.sent_at_s > self.timeout_s:
                transfer.done = True
                transfer.error = f"{transfer.target}: no SDO response within {self.timeout_s * 1e3:.0f} ms"
                del self._in_flight[node_id]
                if abandon_silent:
                    for queued in self._queues.pop(node_id, ()):
                        queued.done = queued.skipped = True
        frames: list[tuple[int, bytes]] = []
        for node_id, queue in list(self._queues.items()):
            if limit is not None and len(frames) >= limit:
                break
            if node_id in self._in_flight or not queue:
                continue
            transfer = self._next(queue)
            if transfer is None:
                continue
            transfer.sent_at_s = now_s
            self._in_flight[node_id] = transfer
            payload = (
                upload_request(transfer.index, transfer.sub)
                if transfer.data is None
                else download_request(transfer.index, transfer.sub, transfer.data)
            )
            frames.append((SDO_REQUEST_BASE + node_id, payload))
            if limit is not None:
                self._queues[node_id] = self._queues.pop(node_id)  # to the back of the turn
        return frames

    @staticmethod
    def _next(queue: deque[SdoTransfer]) -> SdoTransfer | None:
        """The next transfer of a node to send; those whose needed transfers did not succeed are skipped."""
        while queue:
            transfer = queue.popleft()
            if all(needed.succeeded for needed in transfer.needs):
                return transfer
            transfer.done = transfer.skipped = True
        return None

    def on_response(self, node_id: int, frame: bytes) -> SdoTransfer | None:
        """A frame from ``node_id``'s SDO server: completes its transfer in flight (returned), or is ignored."""
        transfer = self._in_flight.get(node_id)
        if transfer is None:
            return None
        response = parse_response(frame)
        if (response.index, response.sub) != (transfer.index, transfer.sub) and response.kind != "aborted":
            return None  # an answer to something else (a late one): not ours
        del self._in_flight[node_id]
        transfer.done = True
        if response.kind == "aborted" and transfer.optional and response.abort_code in _DOES_NOT_EXIST:
            pass  # the drive has no such object: nothing to configure
        elif response.kind == "aborted" and transfer.may_decline and transfer.data is not None:
            transfer.declined = describe_abort(response.abort_code)
        elif response.kind == "aborted":
            transfer.error = f"{transfer.target}: the drive aborted the transfer: {describe_abort(response.abort_code)}"
        elif transfer.data is None and response.kind == "uploaded":
            transfer.value = response.data
        elif transfer.data is not None and response.kind == "downloaded":
            pass
        else:
            transfer.error = f"{transfer.target}: unexpected SDO response {frame.hex()}"
        return transfer

    def node_busy(self, node_id: int) -> bool:
        """True while a transfer to ``node_id`` is queued or in flight."""
        return node_id in self._in_flight or bool(self._queues.get(node_id))

    def cancel_node(self, node_id: int) -> None:
        """Forget ``node_id``'s queued and in-flight transfers (marked failed)."""
        for transfer in [
            *([self._in_flight.pop(node_id)] if node_id in self._in_flight else []),
            *self._queues.pop(node_id, []),
        ]:
            transfer.done = True
            transfer.error = transfer.error or f"{transfer.target}: cancelled"

    def cancel(self) -> None:
        """Forget every queued and in-flight transfer (marked failed)."""
        for transfer in [*self._in_flight.values(), *(t for q in self._queues.values() for t in q)]:
            transfer.done = True
            transfer.error = transfer.error or f"{transfer.target}: cancelled"
        self._in_flight.clear()
        self._queues.clear()
