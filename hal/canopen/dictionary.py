"""The drive's object dictionary, read from its EDS, and the units the backend converts with.

``canopen`` parses the EDS (CiA 306): the data types, the access, the defaults. The backend needs
from it the types of what it maps into PDOs and the drive's units, which it also checks against
the drives themselves at start-up (a drive whose rated torque or encoder resolution differs from
its EDS would turn every torque command into a wrong one):

* torque: per mille of the rated torque 0x6076 (mNm): ``Nm = permille * rated_mNm / 1e6``;
* motor-side angle (0x6064): 0x608F sub 1 increments per sub 2 revolutions;
* load-side angle (0x2010): 0x2011 increments per revolution.

Raises :class:`hal.errors.HalConfigError` (one line naming the file) for an EDS that is missing, not
parseable or lacks an object the backend uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import canopen  # the backend's package: a core install without it is told so by the registry
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from hal.canopen import objects as obj
from hal.errors import HalConfigError
from hal.files import read_bytes_bounded

__all__ = ["DEFAULT_EDS", "DriveDictionary", "DriveUnits", "load_dictionary"]

#: The DAROR-01 SEA drive's EDS, shipped with the backend.
DEFAULT_EDS = Path(__file__).with_name("daror_sea.eds")
#: The largest EDS read (a drive's EDS is tens of kB).
EDS_MAX_BYTES = 2 * 1024 * 1024
#: EDS access types a master may write by SDO (CiA 306).
_WRITABLE_ACCESS = frozenset({"rw", "wo", "rww", "rwr"})


@dataclass(frozen=True)
class DriveUnits:
    """How a drive's numbers map to SI units (from its EDS, checked against the drive at start-up).

    Attributes:
        rated_torque_mnm: 0x6076, mNm; torques are in per mille of it.
        motor_increments_per_rev: 0x608F sub 1 / sub 2.
        load_increments_per_rev: 0x2011.
    """

    rated_torque_mnm: int
    motor_increments_per_rev: float
    load_increments_per_rev: float

    @property
    def nm_per_permille(self) -> float:
        return self.rated_torque_mnm / 1e6

    @property
    def rad_per_motor_increment(self) -> float:
        return 2.0 * math.pi / self.motor_increments_per_rev

    @property
    def rad_per_load_increment(self) -> float:
        return 2.0 * math.pi / self.load_increments_per_rev


class DriveDictionary:
    """The parsed EDS of the drives (one type of drive on every joint).

    Args:
        path: the EDS file.

    Raises:
        HalConfigError: see the module docstring.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        read_bytes_bounded(self.path, HalConfigError, EDS_MAX_BYTES, "EDS file")  # regular, bounded, readable
        try:
            self._od = canopen.import_od(str(self.path))
        except Exception as exc:  # canopen raises bare configparser/KeyError/ValueError on a broken file
            problem = " ".join(str(exc).split())  # configparser's messages span lines: one line here
            raise HalConfigError(f"{self.path}: not a valid EDS file ({type(exc).__name__}: {problem})") from None
        self._variable, self._containers = ODVariable, (ODArray, ODRecord)
        for index, sub, what in obj.REQUIRED:
            if self._find(index, sub) is None:
                raise HalConfigError(
                    f"{self.path}: object 0x{index:04X}:{sub} ({what}) is missing; the backend needs it"
                )

    @property
    def units(self) -> DriveUnits:
        """The DAROR SEA drive's units, from this EDS's defaults (0x6076, 0x608F, 0x2011): the short form's.

        Raises:
            HalConfigError: the EDS lacks one of them or gives it no positive whole number.
        """
        values = []
        for index, sub, what in ((obj.MOTOR_RATED_TORQUE, 0, "0x6076 motor rated torque"),
                                 (obj.POSITION_ENCODER_RESOLUTION, 1, "0x608F:1 encoder increments"),
                                 (obj.POSITION_ENCODER_RESOLUTION, 2, "0x608F:2 motor revolutions"),
                                 (obj.LOAD_ENCODER_RESOLUTION, 0, "0x2011 load encoder increments")):  # fmt: skip
            value = self.default(index, sub) if self.has(index, sub) else None
            if not isinstance(value, int) or value <= 0:
                raise HalConfigError(
                    f"{self.path}: {what} is {value!r}; expected a positive whole number (the DAROR SEA drive's "
                    "units: a drive of another make is described by a robot file's nodes)"
                )
            values.append(value)
        rated, increments, revolutions, load = values
        return DriveUnits(int(rated), increments / revolutions, float(load))

    def device_info(self) -> tuple[int | None, int | None, int | None]:
        """The EDS's [DeviceInfo] vendor number, product number and revision number (None where it gives none)."""
        info = self._od.device_information
        return (info.vendor_number, info.product_number, info.revision_number)

    def _find(self, index: int, sub: int) -> Any:
        try:
            entry = self._od[index]
        except KeyError:
            return None
        if isinstance(entry, self._variable):
            return entry if sub == 0 else None
        if sub not in getattr(entry, "subindices", {}):
            return None  # canopen makes up an array's missing entries from sub 1: only those the EDS has count
        return entry[sub]

    def variable(self, index: int, sub: int = 0) -> Any:
        """The canopen ``ODVariable`` of ``index:sub``.

        Raises:
            HalConfigError: the EDS has no such object.
        """
        found = self._find(index, sub)
        if found is None:
            raise HalConfigError(f"{self.path}: object 0x{index:04X}:{sub} is not in the EDS")
        return found

    def data_type(self, index: int, sub: int = 0) -> int:
        """The EDS data type code of ``index:sub``."""
        return int(self.variable(index, sub).data_type)

    def default(self, index: int, sub: int = 0, node_id: int = 0) -> Any:
        """The default (factory) value of ``index:sub`` on ``node_id`` (``$NODEID+...`` resolved for it).

        Raises:
            HalConfigError: the EDS gives no default for it.
        """
        variable = self.variable(index, sub)
        value = getattr(variable, "default", None)
        raw = getattr(variable, "default_raw", None)  # canopen sets it only when the EDS has a DefaultValue
        if value is None and isinstance(raw, str) and raw.upper().startswith("$NODEID"):
            offset = raw[len("$NODEID") :].strip().lstrip("+").strip() or "0"
            try:
                value = node_id + int(offset, 0)
            except ValueError:
                value = None
        if value is None:
            raise HalConfigError(f"{self.path}: object 0x{index:04X}:{sub} has no default value")
        return value

    def size_bits(self, index: int, sub: int = 0) -> int:
        """Bits the object takes in a PDO."""
        return len(self.variable(index, sub))

    def access(self, index: int, sub: int = 0) -> str:
        return str(self.variable(index, sub).access_type)

    def has(self, index: int, sub: int = 0) -> bool:
        """True if the EDS defines ``index:sub`` (an optional object the backend configures only where it exists)."""
        return self._find(index, sub) is not None

    def writable(self, index: int, sub: int = 0) -> bool:
        """True if the EDS defines ``index:sub`` and a master may write it by SDO."""
        return self.has(index, sub) and self.access(index, sub) in _WRITABLE_ACCESS

    def limits(self, index: int, sub: int = 0) -> tuple[int | None, int | None]:
        """The value range the EDS gives ``index:sub`` (LowLimit, HighLimit; None where it gives none).

        Raises:
            HalConfigError: the EDS has no such object.
        """
        variable = self.variable(index, sub)
        low, high = getattr(variable, "min", None), getattr(variable, "max", None)
        return (int(low) if low is not None else None, int(high) if high is not None else None)

    def pdo_mappable(self, index: int, sub: int = 0) -> bool:
        return bool(self.variable(index, sub).pdo_mappable)

    def encode(self, index: int, sub: int, value: int) -> bytes:
        """``value`` as the drive stores ``index:sub`` (little-endian, the object's size)."""
        return bytes(self.variable(index, sub).encode_raw(value))

    def decode(self, index: int, sub: int, data: bytes) -> Any:
        return self.variable(index, sub).decode_raw(data)


def load_dictionary(path: Path | str | None = None) -> DriveDictionary:
    """The drives' dictionary from ``path`` (None: the shipped DAROR-01 SEA drive's EDS).

    Raises:
        HalConfigError: the file cannot be read or lacks what the backend needs.
    """
    return DriveDictionary(Path(path) if path is not None else DEFAULT_EDS)
