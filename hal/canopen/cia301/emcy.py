"""CiA 301 emergency messages (EMCY): an error code, the error register, manufacturer bytes.

A standard EMCY has 8 bytes (error code u16 little-endian, error register u8, 5 manufacturer
bytes). Some drives send fewer; python canopen 2.4's consumer drops such frames silently (the
issue's facts). :func:`parse_emcy` reads whatever arrived: a frame of at least two bytes carries
an error code, and missing bytes read as zero. An empty frame cannot say which error it reports:
it is returned as :data:`MALFORMED_EMCY`, which the backend treats as an error (a drive that
shouts without words still shouted).

:func:`classify_emcy` sorts an EMCY into an error reset, a warning or an error (D154, CiA 301
7.2.7 and 7.5.2.2): the error register's bit 0 (generic error) is set while *any* error is present
in the device, so an EMCY whose register (when the frame carries one) has it clear reports no
present error: a warning. The codes of the drive's own CAN controller state (0x8110 CAN overrun,
0x8120 CAN in error passive mode, 0x8140 recovered from bus-off) are warnings whatever the
register says: the drive operates on, and the bus is the master's to judge (its own controller's
health, the heartbeat and TPDO watchdogs). Everything else is an error, and so is a frame too
short to carry a register: the master takes that drive's torque until an error reset (0x0000),
the drive's statusword leaving FAULT, or the operator's fault reset. A warning takes nothing: it
is logged (the session's audit) and counted (:class:`EmcyWarnings`). Either way the drive's
statusword stays the authority: a drive that faults shows FAULT there, whatever its EMCY said.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import structlog

__all__ = [
    "COMMUNICATION_WARNINGS",
    "MALFORMED_EMCY",
    "EmcyClass",
    "EmcyMessage",
    "EmcyWarnings",
    "classify_emcy",
    "emcy_frame_data",
    "parse_emcy",
]

log = structlog.get_logger("hal.canopen.emcy")

#: The error code of "no error" (error reset): the drive's error is gone.
NO_ERROR = 0x0000


@dataclass(frozen=True)
class EmcyMessage:
    """One emergency message.

    Attributes:
        code: the CiA 301 / CiA 402 error code (0 = error reset, the error is gone).
        register: the error register (object 0x1001) when it was sent (0 if the frame was too short).
        manufacturer: the manufacturer-specific bytes that arrived (0-5 bytes).
        length: how many bytes the frame had (8 for a standard one).
    """

    code: int
    register: int
    manufacturer: bytes
    length: int

    @property
    def is_error_reset(self) -> bool:
        return self.code == NO_ERROR and self.length >= 2

    def describe(self) -> str:
        """One line for a fault message: the code, its name (the communication ones) or the standard's class."""
        short = "" if self.length == 8 else f" (a {self.length}-byte frame)"
        name = COMMUNICATION_WARNINGS.get(self.code) or error_class(self.code)
        return f"EMCY 0x{self.code:04X} {name}, error register 0x{self.register:02X}{short}"


#: What an empty EMCY frame is read as: an error of unknown kind.
MALFORMED_EMCY = EmcyMessage(0xFFFF, 0, b"", 0)

_CLASSES = (
    (0x0000, 0x00FF, "error reset or no error"),
    (0x1000, 0x1FFF, "generic error"),
    (0x2000, 0x2FFF, "current"),
    (0x3000, 0x3FFF, "voltage"),
    (0x4000, 0x4FFF, "temperature"),
    (0x5000, 0x5FFF, "device hardware"),
    (0x6000, 0x6FFF, "device software"),
    (0x7000, 0x7FFF, "additional modules"),
    (0x8000, 0x8FFF, "monitoring (communication, control)"),
    (0x9000, 0x9FFF, "external error"),
    (0xF000, 0xFFFF, "additional functions or device specific"),
)


def error_class(code: int) -> str:
    """The error class of a CiA 301 error code (its high byte), in the standard's words."""
    for low, high, name in _CLASSES:
        if low <= code <= high:
            return name
    return "unknown class"


def parse_emcy(data: bytes) -> EmcyMessage:
    """The EMCY message in ``data`` (any length 0-8; see the module docstring)."""
    n = len(data)
    if n == 0:
        return MALFORMED_EMCY
    if n == 1:
        return EmcyMessage(data[0], 0, b"", 1)  # half an error code: still an error report
    code = data[0] | (data[1] << 8)
    register = data[2] if n >= 3 else 0
    return EmcyMessage(code, register, bytes(data[3:8]), n)


def emcy_frame_data(code: int, register: int, manufacturer: bytes = b"", length: int = 8) -> bytes:
    """The first ``length`` bytes of a standard EMCY frame (a simulated drive may send a short one)."""
    full = bytes((code & 0xFF, (code >> 8) & 0xFF, register & 0xFF)) + manufacturer[:5].ljust(5, b"\0")
    return full[:length]


#: The error register's bit 0: set while any error is present in the device (CiA 301, object 0x1001).
REGISTER_GENERIC_ERROR = 0x01
#: CiA 301 codes of a device's own CAN controller state: the device operates on (warnings, D154).
COMMUNICATION_WARNINGS: dict[int, str] = {
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8140: "recovered from bus off",
}


class EmcyClass(StrEnum):
    """What an EMCY means for the drive's torque (see the module docstring)."""

    RESET = "error reset"  # 0x0000: the drive's errors are gone
    WARNING = "warning"  # reported; the torque stays
    ERROR = "error"  # the torque goes until a reset


def classify_emcy(message: EmcyMessage) -> EmcyClass:
    """Error reset, warning or error (see the module docstring)."""
    if message.is_error_reset:
        return EmcyClass.RESET
    if message.length >= 2 and message.code in COMMUNICATION_WARNINGS:
        return EmcyClass.WARNING
    if message.length >= 3 and not message.register & REGISTER_GENERIC_ERROR:
        return EmcyClass.WARNING
    return EmcyClass.ERROR


@dataclass
class EmcyWarnings:
    """The warnings the drives reported by EMCY: each logged once while it lasts (until the drive's
    error reset), all counted (for the bus report)."""

    counts: dict[str, int] = field(default_factory=dict)
    _active: set[tuple[int, int]] = field(default_factory=set)

    def warn(self, node_id: int, joint: int, message: EmcyMessage, t_s: float) -> None:
        """Drive ``node_id`` (joint 1-4) warned at robot time ``t_s``: counted; logged if it is new."""
        key = f"0x{node_id:02X} {message.describe()}"
        self.counts[key] = self.counts.get(key, 0) + 1
        if (node_id, message.code) not in self._active:
            self._active.add((node_id, message.code))
            log.warning(
                "drive warning", t_s=t_s, joint=joint, node=node_id, code=f"0x{message.code:04X}",
                message=f"drive {node_id}: {message.describe()} (a warning: the drive keeps its torque)",
            )  # fmt: skip

    def reset(self, node_id: int) -> None:
        """Drive ``node_id`` sent an error reset: its warnings are over (a new one is logged again)."""
        self._active = {key for key in self._active if key[0] != node_id}

    def report(self) -> dict[str, int]:
        """Warning -> how many times it was received."""
        return dict(self.counts)
