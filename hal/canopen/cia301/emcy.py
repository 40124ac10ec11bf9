"""CiA 301 emergency messages (EMCY): an error code, the error register, manufacturer bytes.

A standard EMCY has 8 bytes (error code u16 little-endian, error register u8, 5 manufacturer
bytes). Some drives send fewer; python canopen 2.4's consumer drops such frames silently (the
issue's facts). :func:`parse_emcy` reads whatever arrived: a frame of at least two bytes carries
an error code, and missing bytes read as zero. An empty frame cannot say which error it reports:
it is returned as :data:`MALFORMED_EMCY`, which the backend treats as an error (a drive that
shouts without words still shouted).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["MALFORMED_EMCY", "EmcyMessage", "emcy_frame_data", "parse_emcy"]

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
        """One line for a fault message: the code and what the standard calls its class."""
        short = "" if self.length == 8 else f" (a {self.length}-byte frame)"
        return f"EMCY 0x{self.code:04X} {error_class(self.code)}, error register 0x{self.register:02X}{short}"


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
