"""CiA 301 network management: NMT commands, the NMT states a heartbeat reports, and the fixed COB-IDs.

Units: node ids 1-127; COB-IDs are 11-bit standard identifiers.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = [
    "EMCY_BASE",
    "HEARTBEAT_BASE",
    "NMT_COB_ID",
    "RPDO1_BASE",
    "SDO_REQUEST_BASE",
    "SDO_RESPONSE_BASE",
    "SYNC_COB_ID",
    "TPDO1_BASE",
    "TPDO2_BASE",
    "NmtCommand",
    "NmtState",
    "heartbeat_frame",
    "nmt_frame",
    "parse_heartbeat",
]

#: NMT commands from the master (2 bytes: command specifier, node id or 0 for all).
NMT_COB_ID = 0x000
#: SYNC from the producer (the runtime's tick): no data.
SYNC_COB_ID = 0x080
#: Emergency messages: 0x80 + node id.
EMCY_BASE = 0x080
#: Default PDO COB-IDs (CiA 301 pre-defined connection set): + node id.
TPDO1_BASE = 0x180
RPDO1_BASE = 0x200
TPDO2_BASE = 0x280
#: SDO server's response (0x580 + id) and the client's request (0x600 + id).
SDO_RESPONSE_BASE = 0x580
SDO_REQUEST_BASE = 0x600
#: Heartbeat (and boot-up) messages: 0x700 + node id, one byte: the NMT state.
HEARTBEAT_BASE = 0x700


class NmtCommand(IntEnum):
    """NMT command specifiers (byte 0 of an NMT frame)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """The state byte of a heartbeat (bit 7, the node guarding toggle, is masked off)."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


def nmt_frame(command: NmtCommand, node_id: int) -> tuple[int, bytes]:
    """``(COB-ID, data)`` of an NMT command to ``node_id`` (0: every node)."""
    return NMT_COB_ID, bytes((int(command), node_id))


def heartbeat_frame(node_id: int, state: NmtState) -> tuple[int, bytes]:
    """``(COB-ID, data)`` of ``node_id``'s heartbeat (or boot-up message) in ``state``."""
    return HEARTBEAT_BASE + node_id, bytes((int(state),))


def parse_heartbeat(data: bytes) -> NmtState | None:
    """The NMT state a heartbeat reports, or None for a frame that is not one (empty, or an unknown state)."""
    if len(data) < 1:
        return None
    try:
        return NmtState(data[0] & 0x7F)
    except ValueError:
        return None
