"""The bit rate a CAN interface really runs at, compared with the robot file's ``bitrate`` before the bus opens.

python-can passes ``bitrate`` to the interfaces that set it themselves (pcan, kvaser, ixxat, ...),
which then run at it or refuse to open. A Linux SocketCAN interface is configured outside the
process (``ip link set can0 type can bitrate 1000000``) and python-can ignores the argument: a bus
configured at 500 kbit/s would carry the loop that was budgeted for 1 Mbit/s at twice the load
(D160). So for ``socketcan`` the rate is read from the kernel (``ip -json -details link show``,
``linkinfo.info_data.bittiming.bitrate``) and a mismatch refuses the backend in one line; where it
cannot be read (no ``ip``, an interface that reports none) the backend says so in its bus report.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Callable

from hal.errors import HalConfigError

__all__ = ["check_bitrate", "socketcan_bitrate"]

#: How long ``ip`` may take to answer, s (it reads the kernel's netlink: milliseconds).
IP_TIMEOUT_S = 5.0


def _ip_link(channel: str) -> str:
    done = subprocess.run(
        ["ip", "-json", "-details", "link", "show", channel],
        capture_output=True,
        text=True,
        timeout=IP_TIMEOUT_S,
        check=False,
    )
    if done.returncode != 0:
        raise OSError(done.stderr.strip() or f"ip exited with code {done.returncode}")
    return done.stdout


def socketcan_bitrate(channel: str, ip_link: Callable[[str], str] = _ip_link) -> int | None:
    """The bit rate the kernel's SocketCAN ``channel`` runs at, bit/s; None where it reports none (vcan).

    Raises:
        OSError: ``ip`` is missing or refused (no such device: the message is ip's).
    """
    try:
        links = json.loads(ip_link(channel))
    except json.JSONDecodeError as exc:
        raise OSError(f"ip's answer is not JSON ({exc})") from None
    for link in links if isinstance(links, list) else []:
        timing = link.get("linkinfo", {}).get("info_data", {}).get("bittiming", {})
        if isinstance(timing.get("bitrate"), int):
            return int(timing["bitrate"])
    return None


def check_bitrate(
    interface: str, channel: str, bitrate: int, where: str, ip_link: Callable[[str], str] = _ip_link
) -> str:
    """Refuse a SocketCAN interface that runs at another bit rate than ``bitrate``; what was checked, in words.

    Other interfaces set the rate themselves from python-can's argument: nothing to read.

    Raises:
        HalConfigError: the kernel's interface runs at another rate (one line with both rates and the fix).
    """
    if interface != "socketcan":
        return f"set by python-can's {interface} interface"
    try:
        found = socketcan_bitrate(channel, ip_link)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"not checked: {channel}'s bit rate could not be read ({' '.join(str(exc).split())})"
    if found is None:
        return f"not checked: {channel} reports no bit rate (a virtual CAN interface)"
    if found != bitrate:
        raise HalConfigError(
            f"{where}: {bitrate} bit/s, but {channel} runs at {found} bit/s: expected the interface set "
            f"to the robot file's rate (ip link set {channel} down; ip link set {channel} type can bitrate {bitrate}; "
            f"ip link set {channel} up) or the file's bitrate changed to {found}"
        )
    return f"{found} bit/s, read from the kernel"
