"""Drive profiles: each node of a robot file resolved, once, into what the master and the drives use.

A robot file (:class:`hal.config.NodeConfig` per joint; docs/canopen.md, "Robot file") says which
EDS a node has and which of its objects carry what. :func:`resolve_profiles` reads every EDS and
turns each node into an immutable :class:`DriveProfile`: the objects, their sizes and scales (rad
per count, N m per count), the PDOs derived from them and checked against the EDS, the e-stop
bits, the start-up writes and checks, the timeouts. The master (:mod:`hal.canopen.master`), the
backends, the simulated drives (:mod:`hal.canopen.sim`) and the test harnesses take profiles;
nothing looks an object up in an EDS while the loop runs.

The short form of a CAN configuration (``node_ids``, ``eds``, no ``nodes``) stands for four DAROR
SEA drives (:func:`daror_node`): it resolves to exactly the profiles of
``examples/robot/daror01.yaml``.

The PDO mapping (:func:`derive_pdos`)::

    RPDO1 (master -> drive): controlword 0x6040, target torque 0x6071
    TPDOs (drive -> master): statusword 0x6041, the motor position, the link position, the spring
        torque's object (if it has one), the e-stop object (if it is not the statusword)

in that order, packed into as few TPDOs as fit 8 bytes each (a new TPDO where the next object
does not fit the current one). For the DAROR SEA drive it is :data:`hal.canopen.mapping.DAROR_MAPPING`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from hal.canopen import objects as obj
from hal.canopen.busload import BusLoad, bus_load, frame_bits
from hal.canopen.calibration import NO_CALIBRATION, Calibration
from hal.canopen.cia301.pdo import MappedObject, PdoCodec, PdoMapping
from hal.canopen.dictionary import DEFAULT_EDS, DriveDictionary
from hal.canopen.mapping import DrivePdos
from hal.config import CanHalConfig, CanSimHalConfig, EstopInput, NodeConfig, PositionObject, SpringTorque
from hal.errors import HalConfigError

__all__ = [
    "MODE_CODES",
    "DriveProfile",
    "UnitCheck",
    "daror_node",
    "decode_supported_modes",
    "derive_pdos",
    "node_configs",
    "profile_of",
    "resolve_profiles",
    "robot_bus_load",
]

#: The robot file's ``mode`` -> the modes of operation code (CiA 402 0x6060).
MODE_CODES: dict[str, int] = {"cst": obj.MODE_CYCLIC_SYNCHRONOUS_TORQUE, "tq": obj.MODE_PROFILE_TORQUE}
#: The mode names CiA 402 gives the bits of 0x6502 (supported drive modes): bit n is mode n + 1.
_MODE_BITS: dict[int, str] = {0: "pp", 1: "vl", 2: "pv", 3: "tq", 5: "hm", 6: "ip", 7: "csp", 8: "csv", 9: "cst", 10: "cstca"}  # fmt: skip
#: A CAN frame's data, bits: the most one PDO carries.
_PDO_BITS = 64


@dataclass(frozen=True)
class UnitCheck:
    """A unit the robot file declares, compared at start-up with what the drive reports.

    The value read is ``index:subs[0]``, or ``subs[0] / subs[1]`` for a ratio (0x608F's increments
    per revolutions); ``expected`` is what the profile converts with.
    """

    index: int
    subs: tuple[int, ...]
    expected: float
    what: str

    def value(self, raw: Sequence[int]) -> float:
        """The reported value from the raw reads of ``subs``, in order."""
        return raw[0] / raw[1] if len(raw) == 2 else float(raw[0])


@dataclass(frozen=True)
class DriveProfile:
    """One node of the robot, resolved (see the module docstring). Immutable; compared by content, not by its EDS object.

    Attributes:
        joint: the joint it drives, 1-4.
        node_id: its CANopen node id.
        eds: its EDS file (resolved path).
        dictionary: the parsed EDS (start-up: types, access; never used by the tick).
        mode: the modes of operation code written to 0x6060 (10 cst, 4 tq).
        identity: (vendor id, product code or None) 0x1018 must report; None: not checked.
        rated_torque_mnm: 0x6076, mNm: the target torque 0x6071 is in per mille of it.
        torque_gear_ratio: the gearbox between the motor and the SEA's motor side (the motor
            position's ``gear_ratio``): the arm gets this many times the motor's torque.
        motor, link: the motor and link position objects as mapped (index, sub, bits).
        rad_per_motor_count, rad_per_link_count: their scales, rad per increment (joint side).
        torque: the spring torque's object as mapped; None: the torque is the deflection.
        nm_per_torque_count: the torque object's scale, N m per count (0.0 without one).
        spring_k_nm_per_rad: the spring stiffness the deflection is scaled with; None with a torque object.
        estop: the e-stop object as mapped; None: this node reports no e-stop.
        estop_operator_mask, estop_pilot_mask: the buttons' bits in it.
        estop_pressed_when_clear: the inputs are normally closed (a clear bit is a pressed button).
        sdo_init: the robot file's start-up writes ``(index, sub, value)``, in order.
        enable_timeout_s: how long one power state transition may take, s.
        heartbeat_ms: its heartbeat producer time 0x1017, ms.
        pdos: its PDOs (:func:`derive_pdos`).
        unit_checks: what start-up compares (:class:`UnitCheck`).
        calibration: its encoder zeros and torque tare (the robot file's ``calibration``), applied
            to every reading (:mod:`hal.canopen.calibration`).
    """

    joint: int
    node_id: int
    eds: Path
    dictionary: DriveDictionary = field(compare=False, repr=False)
    mode: int
    identity: tuple[int, int | None] | None
    rated_torque_mnm: int
    torque_gear_ratio: float
    motor: MappedObject
    rad_per_motor_count: float
    link: MappedObject
    rad_per_link_count: float
    torque: MappedObject | None
    nm_per_torque_count: float
    spring_k_nm_per_rad: float | None
    estop: MappedObject | None
    estop_operator_mask: int
    estop_pilot_mask: int
    estop_pressed_when_clear: bool
    sdo_init: tuple[tuple[int, int, int], ...]
    enable_timeout_s: float
    heartbeat_ms: int
    pdos: DrivePdos
    unit_checks: tuple[UnitCheck, ...]
    calibration: Calibration = NO_CALIBRATION

    @property
    def nm_per_permille(self) -> float:
        """N m at the gearbox output of one per mille of the rated torque (the target torque's unit)."""
        return self.rated_torque_mnm / 1e6 * self.torque_gear_ratio

    @property
    def name(self) -> str:
        """``node N (joint J)``, as messages name it."""
        return f"node {self.node_id} (joint {self.joint})"

    @property
    def estop_in_statusword(self) -> bool:
        return self.estop is not None and self.estop.index == obj.STATUSWORD and self.estop.sub == 0


def decode_supported_modes(value: int) -> list[str]:
    """The mode names of a 0x6502 value (CiA 402: bit n = mode n + 1; manufacturer bits 16-31 as ``bit N``)."""
    return [_MODE_BITS.get(bit, f"bit {bit}") for bit in range(32) if value >> bit & 1]


def daror_node(joint: int, node_id: int, dictionary: DriveDictionary, heartbeat_ms: int) -> NodeConfig:
    """The DAROR SEA drive of the short form: its units are its EDS's defaults (checked again at start-up).

    Raises:
        HalConfigError: the EDS lacks a unit object of the DAROR drive or gives it no positive default.
    """
    units = dictionary.units
    return NodeConfig(
        joint=joint,
        node_id=node_id,
        eds=str(dictionary.path),
        mode="cst",
        rated_torque_mnm=units.rated_torque_mnm,
        motor_position=PositionObject(index=obj.POSITION_ACTUAL, counts_per_rev=units.motor_increments_per_rev),
        link_position=PositionObject(
            index=obj.LOAD_POSITION_ACTUAL,
            counts_per_rev=units.load_increments_per_rev,
            resolution_index=obj.LOAD_ENCODER_RESOLUTION,
        ),
        spring_torque=SpringTorque(index=obj.TORQUE_ACTUAL),
        estop=EstopInput(index=obj.STATUSWORD, operator_bit=14, pilot_bit=15),
        enable_timeout_ms=20,
        heartbeat_ms=heartbeat_ms,
    )


def node_configs(config: CanHalConfig | CanSimHalConfig) -> tuple[list[NodeConfig], dict[str, DriveDictionary]]:
    """The nodes of ``config`` (the short form's four DAROR drives when it has no ``nodes``) and their EDSs, by path.

    Raises:
        HalConfigError: an EDS cannot be read (:class:`hal.canopen.dictionary.DriveDictionary`).
    """
    dictionaries: dict[str, DriveDictionary] = {}

    def load(path: str | Path) -> DriveDictionary:
        key = str(Path(path).resolve())
        if key not in dictionaries:
            dictionaries[key] = DriveDictionary(Path(path))
        return dictionaries[key]

    if config.nodes is None:
        shared = load(config.eds if config.eds is not None else DEFAULT_EDS)
        nodes = [
            daror_node(j + 1, node_id, shared, config.heartbeat_producer_ms)
            for j, node_id in enumerate(config.node_ids)
        ]
    else:
        nodes = list(config.nodes)
        for node in nodes:
            load(node.eds)
    return nodes, dictionaries


def resolve_profiles(config: CanHalConfig | CanSimHalConfig, spring_k_nm_per_rad: float) -> tuple[DriveProfile, ...]:
    """Every node of ``config`` resolved into its profile, joint 1-4 in order (see the module docstring).

    Args:
        config: a CAN configuration (the robot file's, or the short form).
        spring_k_nm_per_rad: the robot description's spring stiffness (``{from: deflection}``).

    Raises:
        HalConfigError: an EDS that cannot be read, an object a node names that its EDS lacks, that
            cannot be mapped or whose size differs, PDOs that do not fit the EDS; one line naming
            the node, the field, the object and the EDS.
    """
    nodes, dictionaries = node_configs(config)
    return tuple(
        profile_of(node, dictionaries[str(Path(node.eds).resolve())], spring_k_nm_per_rad, config.heartbeat_producer_ms)
        for node in nodes
    )


def profile_of(
    node: NodeConfig, dictionary: DriveDictionary, spring_k_nm_per_rad: float, heartbeat_ms: int
) -> DriveProfile:
    """One node's profile (see :func:`resolve_profiles`).

    Raises:
        HalConfigError: see :func:`resolve_profiles`.
    """
    where = f"node {node.node_id} (joint {node.joint})"

    def mapped(index: int, sub: int, field_name: str) -> MappedObject:
        if not dictionary.has(index, sub):
            raise HalConfigError(
                f"{where}: {field_name} 0x{index:04X}:{sub} is not in its EDS {dictionary.path}; expected an object it has"
            )
        if not dictionary.pdo_mappable(index, sub):
            raise HalConfigError(
                f"{where}: {field_name} 0x{index:04X}:{sub} is not PDO-mappable in its EDS {dictionary.path}"
            )
        return MappedObject(index, sub, dictionary.size_bits(index, sub))

    rated = node.rated_torque_mnm
    if rated is None:
        rated = _positive_default(dictionary, obj.MOTOR_RATED_TORQUE, 0, where, "rated_torque_mnm")
    statusword = mapped(obj.STATUSWORD, 0, "the statusword")
    motor = mapped(node.motor_position.index, node.motor_position.subindex, "motor_position")
    link = mapped(node.link_position.index, node.link_position.subindex, "link_position")
    spring = node.spring_torque
    torque = mapped(spring.index, spring.subindex, "spring_torque") if spring.index is not None else None
    estop_config = node.estop if isinstance(node.estop, EstopInput) else None
    estop = mapped(estop_config.index, estop_config.subindex, "estop") if estop_config is not None else None
    if estop is not None and estop_config is not None:
        for bit in (estop_config.operator_bit, estop_config.pilot_bit):
            if bit >= estop.bits:
                raise HalConfigError(
                    f"{where}: estop bit {bit} of 0x{estop.index:04X}:{estop.sub}, which has {estop.bits} bits"
                )
    for write in node.sdo_init:
        owner = _master_owned(write.index)
        if owner is not None:
            raise HalConfigError(
                f"{where}: sdo_init writes 0x{write.index:04X}:{write.subindex}, {owner}; expected it left out"
            )
        if not dictionary.writable(write.index, write.subindex):
            raise HalConfigError(
                f"{where}: sdo_init writes 0x{write.index:04X}:{write.subindex}, which its EDS {dictionary.path} "
                "does not have as writable"
            )
    sends = [statusword, motor, link]
    for extra in (torque, estop):
        if extra is not None and all((extra.index, extra.sub) != (m.index, m.sub) for m in sends):
            sends.append(extra)
    receives = [mapped(obj.CONTROLWORD, 0, "the controlword"), mapped(obj.TARGET_TORQUE, 0, "the target torque")]
    pdos = derive_pdos(receives, sends, dictionary, where)
    return DriveProfile(
        joint=node.joint,
        node_id=node.node_id,
        eds=dictionary.path.resolve(),
        dictionary=dictionary,
        mode=MODE_CODES[node.mode],
        identity=(node.identity.vendor_id, node.identity.product_code) if node.identity is not None else None,
        rated_torque_mnm=rated,
        torque_gear_ratio=float(node.motor_position.gear_ratio),
        motor=motor,
        rad_per_motor_count=_rad_per_count(node.motor_position),
        link=link,
        rad_per_link_count=_rad_per_count(node.link_position),
        torque=torque,
        nm_per_torque_count=(spring.nm_per_count or rated / 1e6) if torque is not None else 0.0,
        spring_k_nm_per_rad=float(spring_k_nm_per_rad) if torque is None else None,
        estop=estop,
        estop_operator_mask=1 << estop_config.operator_bit if estop_config is not None else 0,
        estop_pilot_mask=1 << estop_config.pilot_bit if estop_config is not None else 0,
        estop_pressed_when_clear=estop_config.pressed_when_clear if estop_config is not None else False,
        sdo_init=tuple((w.index, w.subindex, w.value) for w in node.sdo_init),
        enable_timeout_s=node.enable_timeout_ms / 1000.0,
        heartbeat_ms=node.heartbeat_ms if node.heartbeat_ms is not None else heartbeat_ms,
        pdos=pdos,
        unit_checks=_unit_checks(node, dictionary, rated),
        calibration=(Calibration(**node.calibration.model_dump()) if node.calibration is not None else NO_CALIBRATION),
    )


#: Objects the master writes itself at start-up: a robot file's ``sdo_init`` may not write them too.
_MASTER_OWNED: tuple[tuple[range, str], ...] = (
    (range(0x1400, 0x1C00), "a PDO parameter the master derives"),
    (range(0x1016, 0x1018), "a heartbeat time the master sets from the file's heartbeat fields"),
    (range(0x1006, 0x1007), "the cycle period the master sets from the loop's rate"),
    (range(0x60C2, 0x60C3), "the interpolation period the master sets from the loop's rate"),
    (range(0x6040, 0x6041), "the controlword the master's power state machine sends"),
    (range(0x6060, 0x6061), "the modes of operation, the node's mode field"),
    (range(0x6071, 0x6073), "a torque the master commands and limits (the robot description's peak)"),
    (range(0x6007, 0x6008), "the drive's reaction to losing the master, which the runtime declares (hal/canopen/reaction.py)"),
    (range(0x605A, 0x605B), "the drive's reaction to losing the master, which the runtime declares (hal/canopen/reaction.py)"),
    (range(0x605E, 0x605F), "the drive's reaction to losing the master, which the runtime declares (hal/canopen/reaction.py)"),
    (range(0x605C, 0x605D), "how a disable operation ends, which the runtime declares with its reaction (hal/canopen/reaction.py)"),
    (range(0x6087, 0x6088), "the torque slope of the drive's stop ramp, which the runtime declares (hal/canopen/reaction.py)"),
)  # fmt: skip


def _master_owned(index: int) -> str | None:
    return next((why for indices, why in _MASTER_OWNED if index in indices), None)


def _rad_per_count(position: PositionObject) -> float:
    # 2 pi / (counts per joint-side revolution): the same float operations the DAROR units always used.
    return 2.0 * math.pi / (float(position.counts_per_rev) * position.gear_ratio)


def _positive_default(dictionary: DriveDictionary, index: int, sub: int, where: str, field_name: str) -> int:
    value = dictionary.default(index, sub) if dictionary.has(index, sub) else None
    if not isinstance(value, int) or value <= 0:
        raise HalConfigError(
            f"{where}: {field_name} not given and its EDS {dictionary.path} gives 0x{index:04X}:{sub} {value!r}; "
            "expected a positive whole number in one of the two"
        )
    return value


def _unit_checks(node: NodeConfig, dictionary: DriveDictionary, rated_mnm: int) -> tuple[UnitCheck, ...]:
    """What start-up compares: 0x6076, 0x608F (for 0x6064), each position's resolution object, where the EDS has them."""
    checks = []
    if dictionary.has(obj.MOTOR_RATED_TORQUE, 0):
        checks.append(UnitCheck(obj.MOTOR_RATED_TORQUE, (0,), float(rated_mnm), "0x6076 motor rated torque (mNm)"))
    for position, name in ((node.motor_position, "motor_position"), (node.link_position, "link_position")):
        cpr = float(position.counts_per_rev)
        if position.index == obj.POSITION_ACTUAL and all(
            dictionary.has(obj.POSITION_ENCODER_RESOLUTION, s) for s in (1, 2)
        ):
            checks.append(
                UnitCheck(obj.POSITION_ENCODER_RESOLUTION, (1, 2), cpr, f"0x608F:1/0x608F:2 {name} counts per rev")
            )
        if position.resolution_index is not None:
            checks.append(
                UnitCheck(
                    position.resolution_index, (0,), cpr, f"0x{position.resolution_index:04X} {name} counts per rev"
                )
            )
    return tuple(checks)


def derive_pdos(
    receives: Sequence[MappedObject], sends: Sequence[MappedObject], dictionary: DriveDictionary, where: str
) -> DrivePdos:
    """The fewest PDOs that carry ``receives`` (RPDOs) and ``sends`` (TPDOs) in order, 8 bytes each, checked against the EDS.

    Raises:
        HalConfigError: a PDO the EDS does not define (or with too few mapping entries), a type a
            PDO cannot carry, or more objects than four PDOs hold.
    """

    def pack(direction: str, objects: Sequence[MappedObject]) -> tuple[PdoMapping, ...]:
        groups: list[list[MappedObject]] = [[]]
        for m in objects:
            if sum(o.bits for o in groups[-1]) + m.bits > _PDO_BITS:
                groups.append([])
            groups[-1].append(m)
        if len(groups) > 4:
            raise HalConfigError(f"{where}: its {direction.upper()}s would need {len(groups)} PDOs; at most 4 exist")
        pdos = tuple(PdoMapping(direction, n, tuple(g)) for n, g in enumerate(groups, start=1))  # type: ignore[arg-type]
        for pdo in pdos:
            _check_pdo(pdo, dictionary, where)
        return pdos

    rpdos, tpdos = pack("rpdo", receives), pack("tpdo", sends)
    if len(rpdos) != 1:
        raise HalConfigError(f"{where}: the controlword and the target torque do not fit one RPDO")
    return DrivePdos(rpdos[0], tpdos)


def _check_pdo(pdo: PdoMapping, dictionary: DriveDictionary, where: str) -> None:
    comm, mapping = pdo.communication_index, pdo.mapping_index
    for index, sub, what in ((comm, 1, "COB-ID"), (comm, 2, "transmission type"), (mapping, 0, "mapping count")):
        if not dictionary.has(index, sub):
            raise HalConfigError(
                f"{where}: its {pdo.name} needs 0x{index:04X}:{sub} ({pdo.name} {what}), which its EDS "
                f"{dictionary.path} lacks"
            )
    for n in range(1, len(pdo.objects) + 1):
        if not dictionary.has(mapping, n):
            raise HalConfigError(
                f"{where}: its {pdo.name} maps {len(pdo.objects)} objects; its EDS {dictionary.path} gives "
                f"0x{mapping:04X} {n - 1} entries"
            )
    try:
        PdoCodec(pdo, tuple(dictionary.data_type(m.index, m.sub) for m in pdo.objects))
    except ValueError as exc:
        raise HalConfigError(f"{where}: {exc} (EDS {dictionary.path})") from None


def robot_bus_load(
    profiles: Sequence[DriveProfile], rate_hz: float, bitrate: int, master_heartbeat_ms: float
) -> BusLoad:
    """The bus load of ``profiles`` at ``rate_hz``: every node's PDOs, the SYNC, each node's and the master's heartbeats."""
    load = bus_load(tuple(pdo for p in profiles for pdo in p.pdos.all), 1, rate_hz, bitrate, master_heartbeat_ms)
    heartbeat_bits_per_s = (
        frame_bits(1) * 1000.0 * (1.0 / master_heartbeat_ms + sum(1.0 / p.heartbeat_ms for p in profiles))
    )
    burst_bits = frame_bits(1) * (len(profiles) + 1)  # every node's beat and the master's in one cycle (D160)
    return dataclasses.replace(load, heartbeat_bits_per_s=heartbeat_bits_per_s, heartbeat_burst_bits=burst_bits)
