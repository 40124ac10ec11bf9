"""Who is on the bus: a listen-only CANopen node scan (``daror can scan``, docs/canopen.md, Commissioning).

The scan never changes a node's state: it sends no NMT command, no SYNC, no PDO and no SDO
download; the only frames it sends are expedited SDO upload requests (reads). For a time
(``listen_s``) it listens to every heartbeat on the bus and probes every node id 1-127 with a read
of 0x1000 (device type), all at once through the project's SDO client (one transfer in flight per
node, :class:`hal.canopen.cia301.sdo.SdoClient`), so an empty bus costs one SDO timeout, not 127.
A node that answers (even with an abort: it exists) is then asked for its identity, 0x1018 sub
1-4 (vendor, product, revision, serial), where it has them. A node heard only by its heartbeat is
listed too (a STOPPED node serves no SDO). Each node's vendor and product are matched against the
``[DeviceInfo]`` of the EDS files given (:func:`eds_catalogue`).

Units: times in s; node ids 1-127; identity numbers as the node sent them (u32).
"""

from __future__ import annotations

import configparser
import contextlib
import itertools
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import can

from hal.canopen.bus import PolledFrames
from hal.canopen.cia301.nmt import HEARTBEAT_BASE, SDO_RESPONSE_BASE, NmtState, parse_heartbeat
from hal.canopen.cia301.sdo import SdoClient, SdoTransfer
from hal.canopen.dictionary import DEFAULT_EDS, EDS_MAX_BYTES
from hal.config import CanSimHalConfig
from hal.errors import HalConfigError, HalError
from hal.files import read_text_bounded

__all__ = [
    "DEFAULT_LISTEN_S",
    "EdsIdentity",
    "FoundNode",
    "ScanResult",
    "eds_catalogue",
    "eds_identity",
    "open_bus",
    "scan_bus",
    "sdo_probe_timeout_s",
    "simulated_drives",
]

#: How long a scan listens for heartbeats, s: a node with a heartbeat period up to 1 s is heard.
DEFAULT_LISTEN_S = 1.0
#: Every node id a CANopen network may hold (CiA 301).
ALL_NODE_IDS: tuple[int, ...] = tuple(range(1, 128))
#: The identity object's subs the scan reads: (sub, what).
_IDENTITY_SUBS = ((1, "vendor_id"), (2, "product_code"), (3, "revision"), (4, "serial"))
#: Bits of one 8-byte standard frame on the wire, worst case with stuffing (55 + 10 x 8, rounded up).
_FRAME_BITS = 135
#: A send the controller's queue refuses (full) is tried again for this long, s.
_SEND_RETRY_S = 0.1


def sdo_probe_timeout_s(bitrate: int, probes: int = len(ALL_NODE_IDS)) -> float:
    """How long a probe waits for its answer, s: 100 ms for the node, plus the bus time of every probe and answer.

    All probes go out at once; the last one's answer waits behind ``probes`` requests and answers
    on the wire (135 bits each): 34 ms at 1 Mbit/s, 274 ms at 125 kbit/s.
    """
    return 0.1 + 2 * probes * _FRAME_BITS / bitrate


@dataclass(frozen=True)
class EdsIdentity:
    """The identity an EDS declares in its ``[DeviceInfo]`` section.

    Attributes:
        path: the EDS file.
        vendor_id: ``VendorNumber`` (what 0x1018:1 reports).
        product_code: ``ProductNumber`` (0x1018:2).
        revision: ``RevisionNumber`` (0x1018:3), None where the EDS gives none.
        product_name: ``ProductName`` ("" where none).
    """

    path: Path
    vendor_id: int
    product_code: int
    revision: int | None
    product_name: str


def _eds_number(info: configparser.SectionProxy, key: str, path: Path, required: bool) -> int | None:
    text = info.get(key)
    if text is None or not text.strip():
        if required:
            raise HalConfigError(f"{path}: [DeviceInfo] {key} is missing; expected the number 0x1018 reports")
        return None
    try:
        return int(text.strip(), 0)
    except ValueError:
        raise HalConfigError(f"{path}: [DeviceInfo] {key} = {text.strip()!r}; expected a whole number") from None


def eds_identity(path: Path | str) -> EdsIdentity:
    """The ``[DeviceInfo]`` identity of the EDS at ``path`` (CiA 306; the rest of the file is not read here).

    Raises:
        HalConfigError: the file cannot be read, is not an INI file, or lacks ``[DeviceInfo]``
            ``VendorNumber`` or ``ProductNumber`` (one line naming the file).
    """
    path = Path(path)
    text = read_text_bounded(path, HalConfigError, EDS_MAX_BYTES, "EDS file")
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    try:
        parser.read_string(text, source=str(path))
    except configparser.Error as exc:
        problem = " ".join(str(exc).split())
        raise HalConfigError(f"{path}: not a valid EDS file ({problem})") from None
    if not parser.has_section("DeviceInfo"):
        raise HalConfigError(f"{path}: no [DeviceInfo] section; expected an EDS (CiA 306)")
    info = parser["DeviceInfo"]
    vendor = _eds_number(info, "VendorNumber", path, required=True)
    product = _eds_number(info, "ProductNumber", path, required=True)
    revision = _eds_number(info, "RevisionNumber", path, required=False)
    return EdsIdentity(path, vendor or 0, product or 0, revision, info.get("ProductName", "").strip())


def eds_catalogue(sources: Iterable[Path | str]) -> tuple[list[EdsIdentity], list[str]]:
    """The identities of the EDS files in ``sources`` (files, or folders whose ``*.eds`` are read), and the problems.

    The shipped ``daror_sea.eds`` is always in the catalogue. A file that cannot be read is not an
    error of the scan: it is left out, and its one-line problem returned.

    Raises:
        HalConfigError: a source that does not exist (a mistyped ``--eds-dir``).
    """
    files: list[Path] = []
    for source in sources:
        source = Path(source)
        if source.is_dir():
            files += sorted(p for p in source.iterdir() if p.suffix.lower() == ".eds" and p.is_file())
        elif source.is_file():
            files.append(source)
        else:
            raise HalConfigError(f"{source}: no such file or folder; expected a folder of EDS files")
    found: list[EdsIdentity] = []
    problems: list[str] = []
    seen: set[Path] = set()
    for path in [*files, DEFAULT_EDS]:
        resolved = path.resolve()
        if resolved in seen:
            continue
        seen.add(resolved)
        try:
            found.append(eds_identity(path))
        except HalConfigError as exc:
            problems.append(str(exc))
    return found, problems


@dataclass
class FoundNode:
    """One node the scan found.

    Attributes:
        node_id: 1-127.
        nmt_state: its last heartbeat's NMT state (``operational``, ``pre-operational``,
            ``stopped``, ``boot-up``), or ``no heartbeat`` when none was heard.
        answered_sdo: True when it answered the 0x1000 read (with the value or an abort).
        device_type: 0x1000, None when it did not give it.
        identity: 0x1018 sub -> value, for the subs it gave (1 vendor, 2 product, 3 revision, 4 serial).
        problems: what it did not give and why (an abort code's meaning, no answer).
        eds: the EDS whose vendor and product match, None when none does.
        eds_note: why there is no EDS, or the other EDS files that match as well ("" otherwise).
    """

    node_id: int
    nmt_state: str = "no heartbeat"
    answered_sdo: bool = False
    device_type: int | None = None
    identity: dict[int, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    eds: Path | None = None
    eds_note: str = ""

    @property
    def vendor_id(self) -> int | None:
        return self.identity.get(1)

    @property
    def product_code(self) -> int | None:
        return self.identity.get(2)

    def as_dict(self) -> dict[str, object]:
        """The node for ``--json``: numbers as numbers, None where the node did not give them."""
        return {
            "node_id": self.node_id,
            "nmt_state": self.nmt_state,
            "answered_sdo": self.answered_sdo,
            "device_type": self.device_type,
            **{name: self.identity.get(sub) for sub, name in _IDENTITY_SUBS},
            "eds": str(self.eds) if self.eds is not None else None,
            "eds_note": self.eds_note,
            "problems": list(self.problems),
        }


@dataclass(frozen=True)
class ScanResult:
    """What a scan found.

    Attributes:
        nodes: every node found, by node id.
        duration_s: how long the scan took, s.
        frames_sent: how many frames the scan sent (SDO upload requests only).
        eds_problems: EDS files that could not be read (left out of the matching).
    """

    nodes: tuple[FoundNode, ...]
    duration_s: float
    frames_sent: int
    eds_problems: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, object]:
        return {
            "nodes": [node.as_dict() for node in self.nodes],
            "duration_s": round(self.duration_s, 3),
            "frames_sent": self.frames_sent,
            "eds_problems": list(self.eds_problems),
        }


def _nmt_name(state: NmtState) -> str:
    return state.name.lower().replace("_", "-")


def _send(
    bus: can.BusABC, cob_id: int, data: bytes, clock: Callable[[], float], sleep: Callable[[float], None]
) -> None:
    """One frame; a full transmit queue (a burst of probes) is waited out for up to :data:`_SEND_RETRY_S`.

    Raises:
        HalError: the bus refused the frame for longer than that.
    """
    message = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
    deadline = clock() + _SEND_RETRY_S
    while True:
        try:
            bus.send(message)
            return
        except can.CanError as exc:
            if clock() >= deadline:
                raise HalError(f"sending frame 0x{cob_id:03X} failed: {exc}") from None
            sleep(0.001)


def scan_bus(
    bus: can.BusABC,
    catalogue: Sequence[EdsIdentity] = (),
    listen_s: float = DEFAULT_LISTEN_S,
    sdo_timeout_s: float = 0.134,
    node_ids: Sequence[int] = ALL_NODE_IDS,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> ScanResult:
    """Listen to ``bus`` for ``listen_s`` and probe ``node_ids`` by SDO reads (see the module docstring).

    Args:
        bus: an open python-can bus (not shut down here).
        catalogue: the EDS identities a node's vendor and product are matched against.
        listen_s: how long to listen for heartbeats, s (the scan also lasts until every read ended).
        sdo_timeout_s: how long a read waits for its answer, s (:func:`sdo_probe_timeout_s`).
        node_ids: the node ids probed.
        clock: the time, s (monotonic).
        sleep: how the scan waits between polls.

    Raises:
        HalError: the bus refused a frame or failed while being read.
    """
    started = clock()
    sdo = SdoClient(timeout_s=sdo_timeout_s)
    source = PolledFrames(bus, lambda: clock() - started)
    probes = {node_id: sdo.read(node_id, 0x1000, 0, "device type") for node_id in node_ids}
    identity_reads: dict[int, list[SdoTransfer]] = {}
    nodes: dict[int, FoundNode] = {}
    sent = 0
    while True:
        now = clock() - started
        for cob_id, data in sdo.frames_due(now):
            _send(bus, cob_id, data, clock, sleep)
            sent += 1
        for cob_id, data, _ in source.drain():
            if HEARTBEAT_BASE < cob_id <= HEARTBEAT_BASE + 127:
                state = parse_heartbeat(data)
                if state is not None:
                    node = nodes.setdefault(cob_id - HEARTBEAT_BASE, FoundNode(cob_id - HEARTBEAT_BASE))
                    node.nmt_state = _nmt_name(state)
            elif SDO_RESPONSE_BASE < cob_id <= SDO_RESPONSE_BASE + 127:
                node_id = cob_id - SDO_RESPONSE_BASE
                done = sdo.on_response(node_id, data)
                if done is not None and done is probes.get(node_id):
                    node = nodes.setdefault(node_id, FoundNode(node_id))
                    node.answered_sdo = True  # an abort is an answer too: the node is there
                    identity_reads[node_id] = [
                        sdo.read(node_id, 0x1018, sub, f"identity {name}") for sub, name in _IDENTITY_SUBS
                    ]
        if not sdo.busy and clock() - started >= listen_s:
            break
        sleep(0.001)
    for node_id, node in nodes.items():
        _fill(node, probes.get(node_id), identity_reads.get(node_id, []))
        _match(node, catalogue)
    return ScanResult(tuple(nodes[n] for n in sorted(nodes)), clock() - started, sent, ())


def _fill(node: FoundNode, probe: SdoTransfer | None, reads: list[SdoTransfer]) -> None:
    """The values a node gave, and why it gave no others."""
    if probe is None or not node.answered_sdo:
        why = "no SDO answer" + (" (a STOPPED node serves no SDO)" if node.nmt_state == "stopped" else "")
        node.problems.append(f"0x1000: {why}")
        return
    if probe.succeeded:
        node.device_type = int.from_bytes(probe.value, "little")
    else:
        node.problems.append(f"0x1000: {_why(probe)}")
    for transfer in reads:
        if transfer.succeeded:
            node.identity[transfer.sub] = int.from_bytes(transfer.value, "little")
        else:
            node.problems.append(f"0x1018:{transfer.sub}: {_why(transfer)}")


def _why(transfer: SdoTransfer) -> str:
    error = transfer.error or "not read"
    marker = "the drive aborted the transfer: "
    return error.split(marker, 1)[1] if marker in error else error.split(": ", 1)[-1]


def _match(node: FoundNode, catalogue: Sequence[EdsIdentity]) -> None:
    vendor, product = node.vendor_id, node.product_code
    if vendor is None or product is None:
        node.eds_note = "no 0x1018 vendor and product to match an EDS with"
        return
    matches = [eds for eds in catalogue if (eds.vendor_id, eds.product_code) == (vendor, product)]
    if not matches:
        node.eds_note = f"no EDS with vendor 0x{vendor:08X} and product 0x{product:08X}"
        return
    node.eds = matches[0].path
    if len(matches) > 1:
        node.eds_note = "also matches " + ", ".join(str(m.path) for m in matches[1:])


def open_bus(interface: str, channel: str, bitrate: int) -> can.BusABC:
    """A python-can bus (``can.Bus``) for a commissioning command.

    Raises:
        HalError: the interface cannot be opened (python-can's reason in one line).
    """
    try:
        return can.Bus(interface=interface, channel=channel, bitrate=bitrate)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise HalError(f"CAN interface {interface!r} channel {channel!r}: cannot be opened: {exc}") from None


_SIM_CHANNELS = itertools.count(1)


@contextlib.contextmanager
def simulated_drives(config: CanSimHalConfig) -> Iterator[str]:
    """The simulated drives of a ``can-sim`` configuration, switched on and answering on a virtual bus of their own.

    The drives serve the bus from their thread on the wall clock, as real drives do
    (:meth:`hal.canopen.sim.drives.SimulatedDriveSet.start_thread`), from their factory state: a
    boot-up message each, pre-operational, the EDS's values. Yields the ``virtual`` channel to
    open; the drives are stopped when the block ends.

    Raises:
        HalConfigError: the EDS of the configuration cannot be read.
        DescriptionError: the scenario cannot be loaded.
    """
    from hal.canopen.backend import SimulatedCanHal
    from hal.canopen.sim.bus import SimulationBus

    channel = f"{config.channel}-scan-{next(_SIM_CHANNELS)}"
    drives = SimulatedCanHal(config).drive_set  # built as the backend builds them, never opened by it
    bus = SimulationBus(channel=channel, preserve_timestamps=True)
    drives.attach(bus)
    drives.power_on()  # the plant at rest, every drive's boot-up message, pre-operational
    started = time.monotonic()
    drives.start_thread(lambda: time.monotonic() - started)
    try:
        yield channel
    finally:
        try:
            drives.stop_thread()
        finally:
            drives.attach(None)
            bus.shutdown()
