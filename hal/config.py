"""HAL configuration: one pydantic model per backend, chosen by ``backend``.

A configuration says which backend runs the session and everything that backend needs; it is a
YAML file a person edits (``daror console --hal-config FILE``) or is built from the command-line
flags (``--hal``, ``--scenario``). :func:`hal.interface.open_hal` turns it into a backend.

Each backend registers its configuration model together with its class (:mod:`hal.registry`):
a subclass of :class:`AnyHalConfig` whose ``backend`` field is ``Literal[<its name>]``, frozen,
unknown fields refused. :func:`load_hal_config` and :func:`hal_config` validate against the
model of the backend the file or the call names, a plug-in's as a built-in's; this module defines
the built-ins' (``sim``, ``can-sim``, ``can``)::

    backend: sim                  # sim | can-sim | can
    scenario: exo_dummy_arm       # a shipped scenario or a .yaml path (relative to this file)
    rate_hz: 1000

    backend: can
    interface: socketcan          # python-can interface
    channel: can0
    bitrate: 1000000              # bit/s
    node_ids: [1, 2, 3, 4]        # CANopen node id of the drive of joints 1-4
    rate_hz: 500                  # loop rate = SYNC rate (left out: the highest the bus allows)
    heartbeat_producer_ms: 100    # how often every node sends its heartbeat
    heartbeat_consumer_ms: 250    # a drive silent this long is lost: a latched fault
    eds: drives.eds               # the drives' EDS file (relative to this file)

That is the short form: four DAROR SEA drives. A robot file describes each drive by its own EDS
instead (``nodes:``, one :class:`NodeConfig` per joint; docs/canopen.md, "Robot file";
``examples/robot/``), resolved into drive profiles by :mod:`hal.canopen.profile`::

    nodes:
      - {joint: 1, node_id: 11, eds: drives/maxon_epos4_0x6050.eds, mode: cst, rated_torque_mnm: 160,
         motor_position: {index: 0x6064, counts_per_rev: 4096, gear_ratio: 100.0},
         link_position: {index: 0x60E4, subindex: 2, counts_per_rev: 65536},
         spring_torque: {from: deflection}, estop: {index: 0x60FD, operator_bit: 16, pilot_bit: 17}}

Files are read through :func:`hal.yamlfile.read_yaml` (strict types; a bool or a string where a
number is meant is refused) and every problem is one line naming the file, the line and the
field: ``hal.yaml: line 3, field rate_hz: Input should be greater than 0; got -5``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, Self, get_args, get_origin

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from hal.errors import BackendUnavailableError, HalConfigError
from hal.registry import backend_entry, backend_kinds, import_target
from hal.robot import N_JOINTS
from hal.yamlfile import Flag, Integer, Number, format_validation_error, line_of, read_yaml

__all__ = [
    "CAN_BITRATES",
    "DEFAULT_SCENARIO",
    "AnyHalConfig",
    "CanHalConfig",
    "CanSimHalConfig",
    "EstopInput",
    "IdentityCheck",
    "NodeConfig",
    "PositionObject",
    "SdoInitWrite",
    "SimHalConfig",
    "SpringTorque",
    "config_model",
    "hal_config",
    "load_hal_config",
]

#: The scenario of the simulated plant when none is named.
DEFAULT_SCENARIO = "exo_dummy_arm"
#: A CAN bus bit rate, bit/s: one of the CiA 301 recommended rates.
Bitrate = Literal[10_000, 20_000, 50_000, 125_000, 250_000, 500_000, 800_000, 1_000_000]
#: The bit rates a CAN bus may run at, bit/s.
CAN_BITRATES: tuple[int, ...] = get_args(Bitrate)

#: A loop rate, Hz: positive, at most 10 kHz (the drives' current loops run at 10-20 kHz).
RateHz = Annotated[Number, Field(gt=0, le=10_000)]
#: A CANopen node id (CiA 301: 1-127).
NodeId = Annotated[Integer, Field(ge=1, le=127)]
#: A CANopen heartbeat time in ms (objects 0x1016/0x1017 hold 16 bits).
HeartbeatMs = Annotated[Integer, Field(ge=1, le=65_535)]
#: A file path or a shipped name: text that is not empty.
Text = Annotated[str, Field(min_length=1, max_length=4096)]


class _Config(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


def _looks_like_path(value: str) -> bool:
    return Path(value).suffix.lower() in {".yaml", ".yml", ".eds", ".log"} or "/" in value or "\\" in value


class AnyHalConfig(_Config):
    """A HAL configuration: the base of every backend's configuration model (the type of any configuration).

    A backend's model (registered with it, :mod:`hal.registry`) narrows ``backend`` to
    ``Literal[<its name>]`` and adds its fields; it stays frozen, strict and refuses unknown
    fields (checked by :func:`config_model`).

    Attributes:
        backend: the registered backend this configuration is for.
        path_fields: the fields that may hold a file path: a relative one in a file is taken
            relative to that file's folder (:meth:`resolved_against`; a value that does not look
            like a path, such as a shipped scenario's name, stays as it is).
    """

    path_fields: ClassVar[tuple[str, ...]] = ()

    backend: str

    def resolved_against(self, folder: Path) -> Self:
        """This configuration with every relative path of :attr:`path_fields` taken relative to ``folder``."""
        updates: dict[str, Any] = {}
        for name in self.path_fields:
            value = getattr(self, name, None)
            if isinstance(value, str) and _looks_like_path(value) and not Path(value).is_absolute():
                updates[name] = str(folder / value)
        return self.model_copy(update=updates) if updates else self


class SimHalConfig(AnyHalConfig):
    """The simulated plant (:class:`hal.sim.backend.SimHal`), lock-step: its time is virtual.

    Attributes:
        scenario: a shipped scenario (``daror simulate list``) or a scenario ``.yaml`` path.
        rate_hz: tick rate, Hz; one write advances the plant by ``1 / rate_hz``.
        seed: replaces the scenario's random seed (encoder noise); None keeps the scenario's.
        robot: robot description file; None: the one the scenario names.
    """

    path_fields: ClassVar[tuple[str, ...]] = ("scenario", "robot")

    backend: Literal["sim"] = "sim"
    scenario: Text = DEFAULT_SCENARIO
    rate_hz: RateHz = 1000.0
    seed: Annotated[Integer, Field(ge=0)] | None = None
    robot: Text | None = None


#: An object dictionary index (CiA 301: 16 bits) and a sub-index (8 bits).
ObjectIndex = Annotated[Integer, Field(ge=0x1000, le=0xFFFF)]
SubIndex = Annotated[Integer, Field(ge=0, le=0xFF)]
#: A count that scales a position: increments per revolution, positive.
CountsPerRev = Annotated[Number, Field(gt=0, le=2.0**32)]


class IdentityCheck(_Config):
    """The identity object 0x1018 a node must report at start-up (sub 1 vendor id, sub 2 product code).

    Attributes:
        vendor_id: 0x1018:1, the CiA-assigned vendor id.
        product_code: 0x1018:2; None: not checked.
    """

    vendor_id: Annotated[Integer, Field(ge=0, le=0xFFFF_FFFF)]
    product_code: Annotated[Integer, Field(ge=0, le=0xFFFF_FFFF)] | None = None


class NodeCalibration(_Config):
    """What ``daror can zero`` and ``daror can tare`` measured on a node (docs/canopen.md, Commissioning).

    Attributes:
        motor_zero_counts: the motor encoder's counts at the robot's zero pose.
        link_zero_counts: the link encoder's counts at the robot's zero pose.
        torque_tare_nm: the spring torque read with the arm unloaded, N m (subtracted from every reading).
        zeroed_utc: when the zeros were taken (ISO 8601, UTC); None: never.
        tared_utc: when the tare was taken (ISO 8601, UTC); None: never.
    """

    motor_zero_counts: Annotated[Integer, Field(ge=-(2**31), le=2**31 - 1)] = 0
    link_zero_counts: Annotated[Integer, Field(ge=-(2**31), le=2**31 - 1)] = 0
    torque_tare_nm: Annotated[Number, Field(ge=-1000.0, le=1000.0)] = 0.0
    zeroed_utc: Text | None = None
    tared_utc: Text | None = None


class PositionObject(_Config):
    """An encoder the drive reports in a PDO: its object and its scale.

    Attributes:
        index, subindex: the object (e.g. 0x6064:0 position actual value, 0x60E4:1 an additional position).
        counts_per_rev: increments per revolution of the shaft the encoder sits on.
        gear_ratio: revolutions of that shaft per revolution of the joint side it stands for (the
            motor encoder behind a gearbox: the gearbox's ratio); 1.0 for an encoder on the joint side.
            The motor position's ratio also scales the torque: the arm gets ``gear_ratio`` times the
            motor torque the target torque 0x6071 commands.
        resolution_index: an object of the drive that holds ``counts_per_rev`` (the DAROR drive's
            0x2011), read at start-up and compared; None: none (0x6064's 0x608F is checked by itself).
    """

    index: ObjectIndex
    subindex: SubIndex = 0
    counts_per_rev: CountsPerRev
    gear_ratio: Annotated[Number, Field(gt=0, le=1e6)] = 1.0
    resolution_index: ObjectIndex | None = None


class SpringTorque(_Config):
    """Where the spring torque comes from: the encoders' deflection, or an object the drive reports.

    ``{from: deflection}``: ``k (theta - q)``, k the robot description's spring stiffness, theta the
    motor position (joint side), q the link position. ``{index: 0x6077, nm_per_count: 0.01}``: the
    object, in N m per count; without ``nm_per_count`` the object is in per mille of the rated
    torque (``rated_torque_mnm``), as CiA 402's torque objects are.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, populate_by_name=True)

    source: Literal["deflection", "object"] = Field("object", alias="from")
    index: ObjectIndex | None = None
    subindex: SubIndex = 0
    nm_per_count: Annotated[Number, Field(gt=0, le=1e3)] | None = None

    @model_validator(mode="after")
    def _one_source(self) -> SpringTorque:
        if self.source == "deflection" and (self.index is not None or self.nm_per_count is not None):
            raise ValueError("from: deflection takes no index or nm_per_count; expected one of the two forms")
        if self.source == "object" and self.index is None:
            raise ValueError("expected {from: deflection} or {index: ..., nm_per_count: ...}")
        return self


class EstopInput(_Config):
    """Where a node reports the e-stop buttons: two bits of one object it sends in a PDO.

    Attributes:
        index, subindex: the object (0x6041 the statusword, 0x60FD the digital inputs).
        operator_bit, pilot_bit: the bit of each button (0 = the lowest).
        pressed_when_clear: True for inputs wired normally closed (the bit is 1 while the button is
            released: a cut wire reads as pressed); False: the bit is 1 while it is pressed.
    """

    index: ObjectIndex
    subindex: SubIndex = 0
    operator_bit: Annotated[Integer, Field(ge=0, le=63)]
    pilot_bit: Annotated[Integer, Field(ge=0, le=63)]
    pressed_when_clear: Flag = False

    @model_validator(mode="after")
    def _two_bits(self) -> EstopInput:
        if self.operator_bit == self.pilot_bit:
            raise ValueError(f"operator_bit and pilot_bit are both {self.pilot_bit}; expected two different bits")
        return self


class SdoInitWrite(_Config):
    """One SDO write of a node's start-up (after the master's own), read back and compared."""

    index: ObjectIndex
    subindex: SubIndex = 0
    value: Annotated[Integer, Field(ge=-(2**31), le=2**32 - 1)]


class NodeConfig(_Config):
    """One drive of the robot file: which joint, which node, its EDS and how its objects are read.

    Attributes:
        joint: the joint it drives, 1-4.
        node_id: its CANopen node id.
        eds: its EDS file (relative to the robot file).
        identity: 0x1018 checked at start-up; None: not checked.
        mode: ``cst`` (cyclic synchronous torque, 10) or ``tq`` (profile torque, 4): written to
            0x6060, read back from 0x6061, refused at start-up if the drive's 0x6502 lacks it.
        rated_torque_mnm: the motor rated torque 0x6076, mNm: the target torque 0x6071 is in per
            mille of it; None: the EDS's default. Compared with the drive's 0x6076 at start-up.
        motor_position: the motor side encoder (SEA: the gearbox output, theta).
        link_position: the link side encoder (q).
        spring_torque: see :class:`SpringTorque`.
        estop: the e-stop inputs, or None: this node reports none (another node does).
        sdo_init: writes at start-up, after the master's own, each read back.
        enable_timeout_ms: how long one CiA 402 power state transition may take, ms.
        heartbeat_ms: the node's heartbeat producer time 0x1017, ms; None: the file's
            ``heartbeat_producer_ms``.
        calibration: the encoder zeros and the torque tare commissioning stored (applied to every
            reading); None: never zeroed nor tared.
    """

    joint: Annotated[Integer, Field(ge=1, le=N_JOINTS)]
    node_id: NodeId
    eds: Text
    identity: IdentityCheck | None = None
    mode: Literal["cst", "tq"] = "cst"
    rated_torque_mnm: Annotated[Integer, Field(ge=1, le=0xFFFF_FFFF)] | None = None
    motor_position: PositionObject
    link_position: PositionObject
    spring_torque: SpringTorque
    estop: EstopInput | Literal["none"] | None = None
    sdo_init: Annotated[list[SdoInitWrite], Field(max_length=64)] = []
    enable_timeout_ms: Annotated[Integer, Field(ge=1, le=60_000)] = 200
    heartbeat_ms: HeartbeatMs | None = None
    calibration: NodeCalibration | None = None


class _CanFields(AnyHalConfig):
    """What a CANopen backend needs (``hal/canopen``, issue 12).

    Attributes:
        interface: the python-can interface (``socketcan``, ``pcan``, ``virtual``, ...).
        channel: the python-can channel (``can0``, ``PCAN_USBBUS1``, a virtual bus name).
        bitrate: the bus bit rate, bit/s (one of :data:`CAN_BITRATES`).
        node_ids: CANopen node id of the drive of joints 1-4 (distinct, 1-127).
        rate_hz: loop rate, Hz; also the SYNC rate. None: the highest rate the PDO mapping allows
            within the bus-load budget (hal/canopen/busload.py: 400 Hz for four drives on 1 Mbit/s);
            a rate over the budget is refused when the backend is built.
        heartbeat_producer_ms: how often the drives (and the master) send a heartbeat, ms.
        heartbeat_consumer_ms: how long a drive's heartbeat may be missing before the backend
            latches a fault (raised by the next ``read``), ms; longer than the producer time. The
            drives watch the master's heartbeat with the same time (a silent master stops them).
        master_node_id: the node id of the master's heartbeat (not one of the drives').
        sdo_timeout_ms: how long the master waits for a drive's SDO answer at start-up, ms.
        boot_timeout_ms: how long a drive may take to boot after a reset (and to answer the
            first SYNC), ms.
        rpdo_deadline_ms: the drives' RPDO deadline monitoring: a drive that receives no RPDO
            this long faults by itself, torque off (0: off); None: five SYNC periods (13 ms at 400 Hz).
        eds: the drives' EDS file (object dictionary); None: the backend's own.
        traffic_log: a file to log every frame on the bus to, in candump's ``-L`` format (it must
            not exist yet; a name ending in ``.gz`` is written gzip-compressed); None: no log.
        nodes: the robot file's drives, one per joint (:class:`NodeConfig`; docs/canopen.md,
            "Robot file"); None: the short form, four DAROR SEA drives on ``node_ids`` with ``eds``.
            With ``nodes``, ``node_ids`` is theirs (joint 1-4 in order) and neither ``node_ids``
            nor ``eds`` may be given.
    """

    path_fields: ClassVar[tuple[str, ...]] = ("eds", "traffic_log")

    interface: Text
    channel: Text
    bitrate: Bitrate = 1_000_000
    node_ids: Annotated[list[NodeId], Field(min_length=N_JOINTS, max_length=N_JOINTS)] = [1, 2, 3, 4]
    rate_hz: Annotated[Number, Field(gt=0, le=2_000)] | None = None
    heartbeat_producer_ms: HeartbeatMs = 100
    heartbeat_consumer_ms: HeartbeatMs = Field(250, validate_default=True)  # checked against the producer's
    master_node_id: NodeId = 127
    sdo_timeout_ms: Annotated[Integer, Field(ge=1, le=60_000)] = 500
    boot_timeout_ms: Annotated[Integer, Field(ge=1, le=60_000)] = 2000
    rpdo_deadline_ms: Annotated[Integer, Field(ge=0, le=65_535)] | None = None
    eds: Text | None = None
    traffic_log: Text | None = None
    nodes: Annotated[list[NodeConfig], Field(min_length=N_JOINTS, max_length=N_JOINTS)] | None = None

    @model_validator(mode="before")
    @classmethod
    def _node_ids_of_the_nodes(cls, data: Any) -> Any:
        """With ``nodes``: ``node_ids`` is theirs, joint 1-4 in order (given both ways, refused)."""
        if not isinstance(data, dict) or data.get("nodes") is None:
            return data
        for name in ("node_ids", "eds"):
            if data.get(name) is not None:
                raise ValueError(f"{name} and nodes both given; expected one: each node names its node_id and eds")
        nodes = data["nodes"]
        if isinstance(nodes, list) and all(isinstance(n, dict) for n in nodes):
            by_joint = {n.get("joint"): n.get("node_id") for n in nodes}
            if sorted(by_joint, key=repr) == list(range(1, N_JOINTS + 1)) and len(by_joint) == len(nodes):
                data = {**data, "node_ids": [by_joint[j] for j in range(1, N_JOINTS + 1)]}
        return data

    def resolved_against(self, folder: Path) -> Self:
        """As :meth:`AnyHalConfig.resolved_against`, and each node's EDS too (relative to the robot file, as every path in it)."""
        resolved = super().resolved_against(folder)
        if resolved.nodes is None:
            return resolved
        nodes = [
            n if Path(n.eds).is_absolute() else n.model_copy(update={"eds": str(folder / n.eds)})
            for n in resolved.nodes
        ]
        return resolved.model_copy(update={"nodes": nodes})

    @field_validator("nodes")
    @classmethod
    def _one_node_a_joint(cls, nodes: list[NodeConfig] | None) -> list[NodeConfig] | None:
        if nodes is None:
            return None
        joints = [n.joint for n in nodes]
        if sorted(joints) != list(range(1, N_JOINTS + 1)):
            raise ValueError(f"joints {joints}: expected each of joints 1-{N_JOINTS} once")
        ids = [n.node_id for n in nodes]
        if len(set(ids)) != len(ids):
            raise ValueError(f"node ids {ids}: expected four different node ids, one per drive")
        if all(n.estop in (None, "none") for n in nodes):
            raise ValueError("no node reports the e-stop buttons; expected estop: on at least one node")
        return sorted(nodes, key=lambda n: n.joint)

    @field_validator("node_ids")
    @classmethod
    def _distinct(cls, node_ids: list[int]) -> list[int]:
        if len(set(node_ids)) != len(node_ids):
            raise ValueError(f"{node_ids}: expected four different node ids, one per drive")
        return node_ids

    @field_validator("master_node_id")
    @classmethod
    def _not_a_drive(cls, master_node_id: int, info: ValidationInfo) -> int:
        if master_node_id in (info.data.get("node_ids") or []):
            raise ValueError(f"{master_node_id} is a drive's node id; expected the master's own")
        return master_node_id

    @field_validator("heartbeat_consumer_ms")
    @classmethod
    def _after_the_producer(cls, consumer_ms: int, info: ValidationInfo) -> int:
        producer_ms = info.data.get("heartbeat_producer_ms")
        if producer_ms is not None and consumer_ms <= producer_ms:
            raise ValueError(
                f"{consumer_ms} ms is not longer than heartbeat_producer_ms ({producer_ms} ms): "
                "expected a longer time, else a heartbeat on time would already count as lost"
            )
        return consumer_ms


class CanSimHalConfig(_CanFields):
    """The CANopen backend against simulated drives on a virtual bus, in front of the simulated plant.

    Attributes:
        scenario: the simulated plant behind the drives (as :class:`SimHalConfig`).
        seed: replaces the scenario's random seed; None keeps the scenario's.
    """

    path_fields: ClassVar[tuple[str, ...]] = ("scenario", "eds", "traffic_log")

    backend: Literal["can-sim"] = "can-sim"
    interface: Text = "virtual"
    channel: Text = "daror"
    scenario: Text = DEFAULT_SCENARIO
    seed: Annotated[Integer, Field(ge=0)] | None = None


class CanHalConfig(_CanFields):
    """The CANopen backend on the DAROR-01's drives: real hardware, real time.

    Attributes:
        velocity_filter_hz: first-order low-pass of the link velocity the backend estimates from
            the load-side encoder, Hz (the drives do not send a velocity: hal/canopen/mapping.py).
    """

    backend: Literal["can"] = "can"
    interface: Text = "socketcan"
    channel: Text = "can0"
    velocity_filter_hz: Annotated[Number, Field(gt=0, le=1_000)] = 50.0


def config_model(kind: str) -> type[AnyHalConfig]:
    """The configuration model registered with backend ``kind`` (:mod:`hal.registry`; its module imported now).

    Raises:
        HalConfigError: ``kind`` is not a registered backend (the registered ones are listed).
        BackendUnavailableError: a plug-in registered it but cannot be loaded, its model's module is
            missing or needs a package that is not installed, or the model is not an
            :class:`AnyHalConfig` subclass with ``backend: Literal[kind]``, frozen, refusing
            unknown fields (one line naming it).
        HalError: the model's module failed to import for another reason.
    """
    target = backend_entry(kind).config
    model = import_target(kind, target)
    if not (isinstance(model, type) and issubclass(model, AnyHalConfig)):
        raise BackendUnavailableError(
            f"HAL backend {kind!r}: its configuration {target} is not a hal.config.AnyHalConfig model"
        )
    field = model.model_fields.get("backend")
    annotation = None if field is None else field.annotation
    if get_origin(annotation) is not Literal or get_args(annotation) != (kind,):
        raise BackendUnavailableError(
            f"HAL backend {kind!r}: its configuration {target} has backend: {annotation}; expected Literal[{kind!r}]"
        )
    if model.model_config.get("extra") != "forbid" or not model.model_config.get("frozen"):
        raise BackendUnavailableError(
            f"HAL backend {kind!r}: its configuration {target} must be frozen and refuse unknown fields"
        )
    return model


def _variant(backend: object, source: str, where: str = "") -> type[AnyHalConfig]:
    """The configuration model of ``backend`` as a file or the flags name it.

    Raises:
        HalConfigError: no backend, or one that is not registered (the registered ones listed).
        BackendUnavailableError: a backend registered but not usable (see :func:`config_model`).
    """
    if backend is None:
        raise HalConfigError(f"{source}: {where}field backend: missing; expected one of {', '.join(backend_kinds())}")
    if isinstance(backend, str):
        try:
            return config_model(backend)
        except HalConfigError:
            pass  # not registered: said below, with the registered ones
        except BackendUnavailableError as exc:
            raise BackendUnavailableError(f"{source}: {where}field backend: {exc}") from None
    shown = repr(backend) if isinstance(backend, str) else f"{backend!r} ({type(backend).__name__})"
    raise HalConfigError(
        f"{source}: {where}field backend: unknown backend {shown}; expected one of {', '.join(backend_kinds())}"
    )


def load_hal_config(path: Path | str) -> AnyHalConfig:
    """Read a HAL configuration file (see the module docstring), validated by its backend's registered model.

    A relative path in a field that holds one (``scenario``, ``robot``, ``eds``, ``traffic_log``,
    each node's ``eds``: :attr:`AnyHalConfig.path_fields`) is taken relative to the file's folder
    (a shipped scenario's name stays a name).

    Raises:
        HalConfigError: the file cannot be read or is not YAML (:func:`hal.yamlfile.read_yaml`), it
            names no or an unknown ``backend``, or a field is missing, unknown or of the wrong
            type or range; one line naming the file, the line and the field.
        BackendUnavailableError: the backend it names is a plug-in that cannot be loaded (one line).
    """
    path = Path(path)
    data, root = read_yaml(path, HalConfigError, "a YAML mapping with a backend: key")
    line = line_of(root, ("backend",)) if "backend" in data else None
    model = _variant(data.get("backend"), str(path), f"line {line}, " if line is not None else "")
    try:
        config = model.model_validate(data)
    except ValidationError as exc:
        raise HalConfigError(format_validation_error(str(path), exc, root)) from None
    return config.resolved_against(path.parent)


def hal_config(backend: str, source: str = "command line", **fields: Any) -> AnyHalConfig:
    """A configuration of ``backend`` from ``fields`` (e.g. the command-line flags); None values are left out.

    Args:
        backend: a registered backend (``sim``, ``can-sim``, ``can``, or a plug-in's).
        source: what a message names as the origin (``--hal/--scenario``).
        fields: the backend's configuration fields; a field that is None takes its default.

    Raises:
        HalConfigError: an unknown backend, or a field the backend does not take or of the wrong type.
        BackendUnavailableError: ``backend`` is a plug-in that cannot be loaded (one line).
    """
    model = _variant(backend, source)
    given = {key: value for key, value in fields.items() if value is not None}
    try:
        return model.model_validate({**given, "backend": backend})
    except ValidationError as exc:
        problems = []
        for problem in exc.errors():
            field = ".".join(str(p) for p in problem["loc"]) or "(top level)"
            if problem["type"] == "extra_forbidden":
                problems.append(f"{source}: {field}: the {backend} backend does not take it")
            else:
                problems.append(f"{source}: {field}: {problem['msg']}")
        raise HalConfigError("; ".join(problems)) from None
