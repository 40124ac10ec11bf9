"""The PDOs of a drive, and the DAROR-01 drives' own: what the master sends each drive and what each drive sends back, every SYNC.

Sixteen bytes a drive a cycle, so that four drives, the SYNC and every heartbeat fit one cycle of a
1 Mbit/s bus at 400 Hz under a 70 % load budget (hal/canopen/busload.py, D160, docs/canopen.md)::

    RPDO1 (master -> drive, 4 bytes): controlword 0x6040 (u16), target torque 0x6071 (i16, per mille)
    TPDO1 (drive -> master, 6 bytes): statusword 0x6041 (u16), position actual 0x6064 (i32, motor side)
    TPDO2 (drive -> master, 6 bytes): load side position 0x2010 (i32), torque actual 0x6077 (i16, per mille)

All three are synchronous (transmission type 1): the drive applies the RPDO's values at the next
SYNC and samples what its TPDOs carry at every SYNC. The link velocity is not sent: the backend
differentiates the load-side position (the bytes a velocity would take do not fit the budget).

Other drives' PDOs are derived from their robot file (:func:`hal.canopen.profile.derive_pdos`).
"""

from __future__ import annotations

from dataclasses import dataclass

from hal.canopen import objects as obj
from hal.canopen.cia301.pdo import MappedObject, PdoMapping

__all__ = ["DAROR_MAPPING", "DrivePdos"]


@dataclass(frozen=True)
class DrivePdos:
    """The PDOs of one drive: the RPDO the master writes and the TPDOs it reads, in number order."""

    rpdo: PdoMapping
    tpdos: tuple[PdoMapping, ...]

    @property
    def all(self) -> tuple[PdoMapping, ...]:
        return (self.rpdo, *self.tpdos)

    @property
    def tpdo_status(self) -> PdoMapping:
        """TPDO1 (the DAROR drive's statusword and motor-side position)."""
        return self.tpdos[0]

    @property
    def tpdo_load(self) -> PdoMapping:
        """TPDO2 (the DAROR drive's load-side position and spring torque)."""
        return self.tpdos[1]


#: The mapping of the DAROR SEA drive (what hal.canopen.profile derives for it; a test holds them equal).
DAROR_MAPPING = DrivePdos(
    rpdo=PdoMapping("rpdo", 1, (MappedObject(obj.CONTROLWORD, 0, 16), MappedObject(obj.TARGET_TORQUE, 0, 16))),
    tpdos=(
        PdoMapping("tpdo", 1, (MappedObject(obj.STATUSWORD, 0, 16), MappedObject(obj.POSITION_ACTUAL, 0, 32))),
        PdoMapping("tpdo", 2, (MappedObject(obj.LOAD_POSITION_ACTUAL, 0, 32), MappedObject(obj.TORQUE_ACTUAL, 0, 16))),
    ),
)
