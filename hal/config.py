"""HAL configuration: one pydantic variant per backend, chosen by ``backend``.

A configuration says which backend runs the session and everything that backend needs; it is a
YAML file a person edits (``daror console --hal-config FILE``) or is built from the command-line
flags (``--hal``, ``--scenario``). :func:`hal.interface.open_hal` turns it into a backend::

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

Files are read through :func:`hal.yamlfile.read_yaml` (strict types; a bool or a string where a
number is meant is refused) and every problem is one line naming the file, the line and the
field: ``hal.yaml: line 3, field rate_hz: Input should be greater than 0; got -5``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, ValidationInfo, field_validator

from hal.errors import HalConfigError
from hal.robot import N_JOINTS
from hal.yamlfile import Integer, Number, format_validation_error, line_of, read_yaml

__all__ = [
    "BACKEND_NAMES",
    "CAN_BITRATES",
    "DEFAULT_SCENARIO",
    "AnyHalConfig",
    "CanHalConfig",
    "CanSimHalConfig",
    "HalConfig",
    "SimHalConfig",
    "hal_config",
    "load_hal_config",
]

#: The backends a configuration may name (the registry's names, hal.interface.BACKENDS).
BACKEND_NAMES: tuple[str, ...] = ("sim", "can-sim", "can")
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


class SimHalConfig(_Config):
    """The simulated plant (:class:`hal.sim.backend.SimHal`), lock-step: its time is virtual.

    Attributes:
        scenario: a shipped scenario (``daror simulate list``) or a scenario ``.yaml`` path.
        rate_hz: tick rate, Hz; one write advances the plant by ``1 / rate_hz``.
        seed: replaces the scenario's random seed (encoder noise); None keeps the scenario's.
        robot: robot description file; None: the one the scenario names.
    """

    backend: Literal["sim"] = "sim"
    scenario: Text = DEFAULT_SCENARIO
    rate_hz: RateHz = 1000.0
    seed: Annotated[Integer, Field(ge=0)] | None = None
    robot: Text | None = None


class _CanFields(_Config):
    """What a CANopen backend needs (``hal/canopen``, issue 12).

    Attributes:
        interface: the python-can interface (``socketcan``, ``pcan``, ``virtual``, ...).
        channel: the python-can channel (``can0``, ``PCAN_USBBUS1``, a virtual bus name).
        bitrate: the bus bit rate, bit/s (one of :data:`CAN_BITRATES`).
        node_ids: CANopen node id of the drive of joints 1-4 (distinct, 1-127).
        rate_hz: loop rate, Hz; also the SYNC rate. None: the highest rate the PDO mapping allows
            within the bus-load budget (hal/canopen/busload.py: 500 Hz for four drives on 1 Mbit/s);
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
            this long faults by itself, torque off (0: off); None: five SYNC periods (10 ms at 500 Hz).
        eds: the drives' EDS file (object dictionary); None: the backend's own.
        traffic_log: a file to log every frame on the bus to, in candump's ``-L`` format (it must
            not exist yet; a name ending in ``.gz`` is written gzip-compressed); None: no log.
    """

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


#: A HAL configuration: one of the variants (the type of a value).
AnyHalConfig = SimHalConfig | CanSimHalConfig | CanHalConfig
#: A HAL configuration for pydantic: one of the variants, told apart by ``backend``.
HalConfig = Annotated[AnyHalConfig, Field(discriminator="backend")]

_VARIANTS: dict[str, type[_Config]] = {"sim": SimHalConfig, "can-sim": CanSimHalConfig, "can": CanHalConfig}
_ADAPTER: TypeAdapter[AnyHalConfig] = TypeAdapter(HalConfig)
#: Fields that hold a file path; a relative one in a file is relative to that file's folder.
_PATH_FIELDS = ("scenario", "robot", "eds", "traffic_log")


def _looks_like_path(value: str) -> bool:
    return Path(value).suffix.lower() in {".yaml", ".yml", ".eds", ".log"} or "/" in value or "\\" in value


def _variant(backend: object, source: str, where: str = "") -> type[_Config]:
    if backend is None:
        raise HalConfigError(f"{source}: {where}field backend: missing; expected one of {', '.join(BACKEND_NAMES)}")
    if not isinstance(backend, str) or backend not in _VARIANTS:
        shown = repr(backend) if isinstance(backend, str) else f"{backend!r} ({type(backend).__name__})"
        raise HalConfigError(
            f"{source}: {where}field backend: unknown backend {shown}; expected one of {', '.join(BACKEND_NAMES)}"
        )
    return _VARIANTS[backend]


def load_hal_config(path: Path | str) -> AnyHalConfig:
    """Read a HAL configuration file (see the module docstring).

    A relative path in ``scenario``, ``robot`` or ``eds`` is taken relative to the file's folder
    (a shipped scenario's name stays a name).

    Raises:
        HalConfigError: the file cannot be read or is not YAML (:func:`hal.yamlfile.read_yaml`), it
            names no or an unknown ``backend``, or a field is missing, unknown or of the wrong
            type or range; one line naming the file, the line and the field.
    """
    path = Path(path)
    data, root = read_yaml(path, HalConfigError, "a YAML mapping with a backend: key")
    line = line_of(root, ("backend",)) if "backend" in data else None
    model = _variant(data.get("backend"), str(path), f"line {line}, " if line is not None else "")
    try:
        config = model.model_validate(data)
    except ValidationError as exc:
        raise HalConfigError(format_validation_error(str(path), exc, root)) from None
    updates = {}
    for name in _PATH_FIELDS:
        value = getattr(config, name, None)
        if isinstance(value, str) and _looks_like_path(value) and not Path(value).is_absolute():
            updates[name] = str(path.parent / value)
    return config.model_copy(update=updates) if updates else config  # type: ignore[return-value]


def hal_config(backend: str, source: str = "command line", **fields: Any) -> AnyHalConfig:
    """A configuration of ``backend`` from ``fields`` (e.g. the command-line flags); None values are left out.

    Args:
        backend: ``sim``, ``can-sim`` or ``can``.
        source: what a message names as the origin (``--hal/--scenario``).
        fields: the variant's fields; a field that is None takes its default.

    Raises:
        HalConfigError: an unknown backend, or a field the backend does not take or of the wrong type.
    """
    _variant(backend, source)
    given = {key: value for key, value in fields.items() if value is not None}
    try:
        return _ADAPTER.validate_python({**given, "backend": backend})
    except ValidationError as exc:
        problems = []
        for problem in exc.errors():
            location = [str(p) for p in problem["loc"][1:]]  # without the discriminator's tag
            field = ".".join(location) or "(top level)"
            if problem["type"] == "extra_forbidden":
                problems.append(f"{source}: {field}: the {backend} backend does not take it")
            else:
                problems.append(f"{source}: {field}: {problem['msg']}")
        raise HalConfigError("; ".join(problems)) from None
