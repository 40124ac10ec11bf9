"""The robot file's bitrate against the SocketCAN interface's (hal/canopen/bitrate.py)."""

from __future__ import annotations

import json

import pytest

from hal.canopen.bitrate import check_bitrate, socketcan_bitrate
from hal.errors import HalConfigError


def _ip(bitrate: int | None) -> str:
    """What ``ip -json -details link show can0`` prints for a CAN interface at ``bitrate`` (None: a vcan)."""
    info = {"bittiming": {"bitrate": bitrate, "sample_point": "0.875"}} if bitrate else {}
    kind = "can" if bitrate else "vcan"
    return json.dumps([{"ifname": "can0", "linkinfo": {"info_kind": kind, "info_data": info}}])


def test_the_kernels_rate_is_read_from_ip() -> None:
    assert socketcan_bitrate("can0", lambda channel: _ip(500_000)) == 500_000
    assert socketcan_bitrate("vcan0", lambda channel: _ip(None)) is None


def test_a_socketcan_interface_at_another_rate_is_refused_in_one_line() -> None:
    with pytest.raises(HalConfigError) as info:
        check_bitrate("socketcan", "can0", 1_000_000, "robot.yaml: bitrate", lambda channel: _ip(500_000))
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("robot.yaml: bitrate: 1000000 bit/s, but can0 runs at 500000 bit/s")
    assert "ip link set can0 type can bitrate 1000000" in message


def test_what_cannot_be_read_is_said_not_refused() -> None:
    def missing(channel: str) -> str:
        raise OSError('Device "can7" does not exist.')

    assert check_bitrate("socketcan", "can0", 1_000_000, "x", lambda c: _ip(1_000_000)) == (
        "1000000 bit/s, read from the kernel"
    )
    assert check_bitrate("socketcan", "vcan0", 1_000_000, "x", lambda c: _ip(None)).startswith("not checked")
    assert "does not exist" in check_bitrate("socketcan", "can7", 1_000_000, "x", missing)
    assert check_bitrate("pcan", "PCAN_USBBUS1", 1_000_000, "x") == "set by python-can's pcan interface"


def test_this_machines_ip_answers_for_an_interface_that_is_no_can() -> None:
    """The real ``ip`` (where it exists): the loopback has no bit timing, so nothing is refused."""
    result = check_bitrate("socketcan", "lo", 1_000_000, "x")
    assert result.startswith("not checked"), result
