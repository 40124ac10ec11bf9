"""What the commissioning commands need of an open CANopen backend beyond the HAL contract (``daror can check|zero|tare``).

The HAL contract gives angles, torques and drive states in SI units and the master's view of the
drives. Commissioning also needs the drives' own words, which only the master holds:

* each drive's statusword of the last SYNC: whether its power stage is on (the sample counts a drive
  the master commanded off as disabled before the drive itself says so);
* SDO reads while the bus runs (identity, units, mode, the torque limit), one transfer in flight
  per drive, completed over the next ticks (:class:`hal.canopen.cia301.sdo.SdoClient`, never waiting);
* the raw encoder counts the drives sent (a zero is stored in counts);
* what the EDS says of an object (exists, its factory value) and of the drive (its identity).

:class:`BusProbe` is that, for one open :class:`hal.canopen.backend.CanHal`; it reads the master,
changes nothing. The runtime reaches it through :func:`hal.commissioning.bus_probe`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hal.canopen.cia301.sdo import SdoTransfer
from hal.canopen.cia402.statemachine import PowerState
from hal.canopen.dictionary import DEFAULT_EDS
from hal.canopen.objects import MODE_CYCLIC_SYNCHRONOUS_TORQUE
from hal.canopen.scan import eds_identity
from hal.errors import HalError
from hal.interface import Hal, Sample

__all__ = ["BusProbe", "ObjectRead", "RawCounts", "UnitObject", "eds_of", "identity_of"]

#: Power states in which a drive's power stage applies torque: commanded, or ramping down by itself.
_STAGE_ON = frozenset({PowerState.OPERATION_ENABLED, PowerState.QUICK_STOP_ACTIVE, PowerState.FAULT_REACTION_ACTIVE})


@dataclass(frozen=True)
class ObjectRead:
    """An SDO read queued by :meth:`BusProbe.read`: done once answered, failed or timed out."""

    node_id: int
    index: int
    sub: int
    what: str
    _transfer: SdoTransfer

    @property
    def done(self) -> bool:
        return self._transfer.done

    @property
    def value(self) -> int | None:
        """The value read (unsigned, little-endian), None unless it succeeded."""
        t = self._transfer
        return int.from_bytes(t.value, "little") if t.succeeded else None

    @property
    def error(self) -> str:
        """Why it failed ("" if it did not): the abort code's meaning, or no answer in time."""
        t = self._transfer
        if t.succeeded:
            return ""
        text = t.error or "no answer yet"
        marker = "the drive aborted the transfer: "
        return text.split(marker, 1)[1] if marker in text else text.split(": ", 1)[-1]


@dataclass(frozen=True)
class UnitObject:
    """A drive's unit: the subs of ``index`` read (one, or two for a ratio: sub 1 / sub 2), the value the backend
    converts with."""

    index: int
    subs: tuple[int, ...]
    what: str
    expected: float

    def value(self, raw: list[int]) -> float:
        """The unit from the values read of ``subs``, in order."""
        return raw[0] / raw[1] if len(raw) == 2 and raw[1] else float(raw[0])


@dataclass(frozen=True)
class RawCounts:
    """One drive's encoders as it sent them in its last TPDOs: increments."""

    node_id: int
    motor_counts: int
    link_counts: int


class BusProbe:
    """The drives' own words through the master of an open CANopen backend (see the module docstring).

    Args:
        hal: a :class:`hal.canopen.backend.CanHal` (or ``SimulatedCanHal``), opened.

    Raises:
        HalError: the backend is not a CANopen one, or not open.
    """

    def __init__(self, hal: Hal) -> None:
        master: Any = getattr(hal, "master", None)  # raises HalNotOpenError before open
        if master is None:
            raise HalError(f"the {hal.kind} backend has no CANopen master")
        self._hal: Any = hal
        self._master = master

    @property
    def node_ids(self) -> tuple[int, ...]:
        """The drive of joints 1-4."""
        return tuple(int(n) for n in self._hal.config.node_ids)

    def stage_on(self, sample: Sample) -> tuple[bool | None, ...]:
        """Per drive, its own statusword of ``sample``'s SYNC: True its power stage is on (OPERATION ENABLED, QUICK
        STOP ACTIVE, FAULT REACTION ACTIVE), False off; None when ``sample`` is not of the last SYNC or the drive is lost.
        """
        master = self._master
        if sample.seq != master.syncs - 1:
            return tuple(None for _ in master.drives)
        return tuple(
            (drive.power in _STAGE_ON) if drive.lost is None and drive.power is not None else None
            for drive in master.drives
        )

    def read(self, node_id: int, index: int, sub: int, what: str) -> ObjectRead:
        """Queue an SDO read of ``index:sub`` of ``node_id``; it goes out and is answered over the next ticks."""
        return ObjectRead(node_id, index, sub, what, self._master.sdo.read(node_id, index, sub, what))

    def raw_counts(self) -> list[RawCounts]:
        """Every drive's motor and link encoder counts of its last TPDOs, joint 1-4."""
        return [RawCounts(d.node_id, int(d.motor_counts), int(d.load_counts)) for d in self._master.drives]

    def _profile(self, node_id: int) -> Any:
        """The node's resolved drive profile (robot files, issue 25), None on a backend that has one EDS for all."""
        for profile in getattr(self._hal, "profiles", None) or ():
            if profile.node_id == node_id:
                return profile
        return None

    def has_object(self, node_id: int, index: int, sub: int = 0) -> bool:
        """True if the EDS of ``node_id`` defines ``index:sub``."""
        profile = self._profile(node_id)
        dictionary = profile.dictionary if profile is not None else self._hal.dictionary
        return bool(dictionary.has(index, sub))

    def unit_objects(self, node_id: int) -> list[UnitObject]:
        """The objects that hold ``node_id``'s units and the values the backend converts with.

        Raises:
            HalConfigError: the EDS gives one of them no default.
        """
        profile = self._profile(node_id)
        if profile is not None:
            return [UnitObject(c.index, tuple(c.subs), c.what, float(c.expected)) for c in profile.unit_checks]
        d = self._hal.dictionary
        return [
            UnitObject(0x6076, (0,), "rated torque 0x6076 (mNm)", float(d.default(0x6076, 0))),
            UnitObject(0x608F, (1, 2), "motor counts/rev 0x608F:1/0x608F:2",
                       d.default(0x608F, 1) / d.default(0x608F, 2)),
            UnitObject(0x2011, (0,), "link counts/rev 0x2011", float(d.default(0x2011, 0))),
        ]  # fmt: skip

    def mode(self, node_id: int) -> int:
        """The modes of operation code the master writes to ``node_id`` (0x6060; 10: cyclic synchronous torque)."""
        profile = self._profile(node_id)
        return int(profile.mode) if profile is not None else MODE_CYCLIC_SYNCHRONOUS_TORQUE

    def nm_per_torque_count(self, node_id: int) -> float:
        """N m per count of ``node_id``'s torque objects (0x6071, 0x6072: per mille of its rated torque 0x6076)."""
        profile = self._profile(node_id)
        if profile is not None:
            return float(profile.nm_per_permille)
        return float(self._hal.dictionary.units.nm_per_permille)


def eds_of(config: Any) -> dict[int, Path]:
    """Node id -> the EDS file a CANopen configuration gives it (the shipped one when it names none)."""
    nodes = {node.node_id: Path(node.eds) for node in getattr(config, "nodes", None) or []}
    shared = Path(config.eds) if getattr(config, "eds", None) else DEFAULT_EDS
    return {int(n): nodes.get(int(n), shared) for n in config.node_ids}


def identity_of(path: Path) -> tuple[int, int]:
    """``(vendor id, product code)`` the EDS at ``path`` declares in ``[DeviceInfo]``.

    Raises:
        HalConfigError: the EDS cannot be read or declares no identity.
    """
    found = eds_identity(path)
    return found.vendor_id, found.product_code
