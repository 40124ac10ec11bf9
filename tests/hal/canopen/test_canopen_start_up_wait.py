"""The start-up on the hardware code path waits for the drives' answers woken by the frame that arrives.

:meth:`hal.canopen.bus.ListenedFrames.wait` (python-can's Notifier thread wakes it) replaced a
fixed sleep between the start-up's polls; its timeouts count the time really waited, so a bus that
keeps waking the master does not end them early, and a drive that does not answer still fails the
start-up in one line after its timeout. The tick never waits: the listener only reads its waiter.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator

import can
import pytest

from hal.canopen.backend import CanHal
from hal.canopen.bus import ListenedFrames
from hal.config import CanHalConfig
from hal.errors import HalError


@pytest.fixture
def pair() -> Iterator[tuple[can.BusABC, can.BusABC, str]]:
    """Two python-can virtual buses on a channel of their own: the drives' side, the master's side, the channel."""
    channel = f"daror-wait-{uuid.uuid4().hex}"
    drives = can.Bus(interface="virtual", channel=channel)
    master = can.Bus(interface="virtual", channel=channel)
    try:
        yield drives, master, channel
    finally:
        drives.shutdown()
        master.shutdown()


def _frame(cob_id: int, data: bytes = b"\x00") -> can.Message:
    return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)


def test_a_wait_ends_when_a_frame_arrives(pair: tuple[can.BusABC, can.BusABC, str]) -> None:
    drives, master, _ = pair
    source = ListenedFrames(master, time.monotonic)
    timer = threading.Timer(0.05, lambda: drives.send(_frame(0x701)))
    try:
        began = time.monotonic()
        timer.start()
        waited = source.wait(5.0)
        elapsed = time.monotonic() - began
        timer.join()
        assert elapsed < 2.5  # woken by the frame, not at the end of the 5 s
        assert 0.0 < waited <= elapsed
        assert [(cob_id, data) for cob_id, data, _ in source.drain()] == [(0x701, b"\x00")]
    finally:
        timer.cancel()
        source.close()


def test_a_wait_returns_at_once_only_for_a_frame_not_drained(pair: tuple[can.BusABC, can.BusABC, str]) -> None:
    """A stored frame: no wait; nothing, or only an error frame (the start-up's SDO phase does not take those): the whole time."""
    drives, master, _ = pair
    source = ListenedFrames(master, time.monotonic)
    try:
        assert source.wait(0.05) >= 0.04  # nothing arrives: the whole time, as a sleep
        drives.send(_frame(0x181))
        assert source.wait(5.0) < 2.5
        assert source.wait(5.0) == 0.0  # not drained yet: at once
        assert len(source.drain()) == 1
        drives.send(can.Message(arbitration_id=0x004, is_error_frame=True, data=bytes(8)))
        assert source.wait(5.0) < 2.5  # woken by it
        assert source.wait(0.05) >= 0.04  # but kept: no return at once, no spin while it waits to be taken
        assert len(source.take_error_frames()) == 1
    finally:
        source.close()


def _chatter(bus: can.BusABC, stop: threading.Event) -> None:
    """Frames a few times a millisecond (more often than the start-up's 1 ms step) that are nothing it waits for."""
    while not stop.is_set():
        bus.send(_frame(0x185, b"\x01\x02"))  # another node's TPDO
        time.sleep(0.0002)


def _open_fails(
    pair: tuple[can.BusABC, can.BusABC, str],
    drives_side: Callable[[can.BusABC, threading.Event], None],
    match: str,
    at_least_s: float,
    **config: int,
) -> None:
    """``open()`` of a ``CanHal`` with ``config`` raises ``HalError`` matching ``match``, after ``at_least_s`` of wall time,
    while ``drives_side(bus, stop)`` plays the drives on their own thread."""
    drives, master, channel = pair
    hal = CanHal(CanHalConfig(interface="virtual", channel=channel, **config), bus=master)
    stop = threading.Event()
    thread = threading.Thread(target=drives_side, args=(drives, stop), daemon=True)
    thread.start()
    try:
        began = time.monotonic()
        with pytest.raises(HalError, match=match):
            hal.open()
        assert time.monotonic() - began >= at_least_s
    finally:
        stop.set()
        thread.join()
        hal.close()


def test_the_boot_timeout_counts_the_time_waited_on_a_busy_bus(pair: tuple[can.BusABC, can.BusABC, str]) -> None:
    """Woken thousands of times a second by frames it does not wait for, the start-up still waits its whole boot timeout."""
    match = r"^CAN bus: no boot-up message from node\(s\) 1, 2, 3, 4 within 0.3 s"
    _open_fails(pair, _chatter, match, 0.3, boot_timeout_ms=300)


def _boot_but_never_answer_sdo(bus: can.BusABC, stop: threading.Event, requests: list[int] | None = None) -> None:
    """Drives 1-4 that boot when the master resets them and never answer an SDO request (``requests``: their COB-IDs)."""
    while not stop.is_set():
        message = bus.recv(0.01)
        if message is not None and message.arbitration_id == 0x000 and message.data[0] == 0x82:
            nodes = [1, 2, 3, 4] if message.data[1] == 0 else [message.data[1]]
            for node in nodes:
                bus.send(_frame(0x700 + node))
        elif message is not None and 0x601 <= message.arbitration_id <= 0x67F and requests is not None:
            requests.append(message.arbitration_id)


def test_an_sdo_never_answered_fails_the_start_up_after_its_timeout(pair: tuple[can.BusABC, can.BusABC, str]) -> None:
    """After one timeout: a silent drive is sent nothing more, its other 37 transfers are skipped (D207).

    Before, each was sent and timed out in turn: 38 timeouts, 7.6 s at 200 ms (19 s at the default 500 ms).
    """
    match = r"^CAN bus: configuring the drives: node 1 0x1000:0 \(device type\): no SDO response within 200 ms$"
    requests: list[int] = []
    _open_fails(pair, lambda bus, stop: _boot_but_never_answer_sdo(bus, stop, requests), match, 0.2, sdo_timeout_ms=200)
    assert sorted(requests) == [0x601, 0x602, 0x603, 0x604]  # one request on the bus per drive, none after its timeout
