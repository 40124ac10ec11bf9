"""``daror can scan`` (hal/canopen/scan.py) on python-can's virtual bus against the project's simulated drives.

What is asserted: the node ids, the 0x1000 and 0x1018 numbers the drives' EDS gives them, the NMT
state their heartbeats report, the EDS each is matched to, and the frames on the bus: the scan
sends SDO upload requests only (no NMT, no SYNC, no PDO, no SDO download), and no drive's state or
object changes.
"""

from __future__ import annotations

import itertools
import json
import shutil
import struct
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from daror_runtime.cli import main
from hal.canopen.backend import SimulatedCanHal
from hal.canopen.cia301.nmt import NmtCommand, NmtState
from hal.canopen.cia301.sdo import download_request
from hal.canopen.dictionary import DEFAULT_EDS
from hal.canopen.scan import eds_catalogue, eds_identity, open_bus, scan_bus, sdo_probe_timeout_s
from hal.canopen.sim.bus import SimulationBus
from hal.config import hal_config
from hal.errors import HalConfigError

_CHANNELS = itertools.count(1)
NODES = (5, 9, 12, 100)


class Rig:
    """Simulated drives serving a virtual channel from their thread, and a sniffer that sees every frame."""

    def __init__(self, node_ids: tuple[int, ...]) -> None:
        self.channel = f"scan-test-{next(_CHANNELS)}"
        self.drives = SimulatedCanHal(
            hal_config("can-sim", node_ids=list(node_ids))
        ).drive_set  # as can-sim builds them
        self.bus = SimulationBus(channel=self.channel, preserve_timestamps=True)
        self.sniffer = can.Bus(interface="virtual", channel=self.channel)
        self.drives.attach(self.bus)
        self.drives.power_on()

    def configure(self, node_id: int, heartbeat_ms: int, nmt: NmtCommand | None = None) -> None:
        """Before the drives run: a heartbeat period (0x1017) and an NMT command, as another master left them."""
        drive = self.drives.drives[[d.node_id for d in self.drives.drives].index(node_id)]
        drive.receive(0x600 + node_id, download_request(0x1017, 0, struct.pack("<H", heartbeat_ms)), 0.0)
        if nmt is not None:
            drive.receive(0x000, bytes((int(nmt), node_id)), 0.0)

    def start(self) -> None:
        self.drain()  # what the set-up made the drives say is not the scan's
        started = time.monotonic()
        self.drives.start_thread(lambda: time.monotonic() - started)

    def drain(self) -> list[can.Message]:
        frames = []
        while (message := self.sniffer.recv(timeout=0)) is not None:
            frames.append(message)
        return frames

    def close(self) -> None:
        self.drives.stop_thread()
        self.drives.attach(None)
        self.bus.shutdown()
        self.sniffer.shutdown()


@pytest.fixture
def rig() -> Iterator[Rig]:
    made = Rig(NODES)
    yield made
    made.close()


def _scan(rig: Rig, **kwargs: object) -> tuple[object, list[can.Message]]:
    bus = open_bus("virtual", rig.channel, 1_000_000)
    try:
        result = scan_bus(bus, eds_catalogue([])[0], **kwargs)  # type: ignore[arg-type]
    finally:
        bus.shutdown()
    return result, rig.drain()


def test_scan_finds_every_drive_with_its_identity_state_and_eds(rig: Rig) -> None:
    rig.configure(9, 50, NmtCommand.START)  # operational, heartbeat every 50 ms
    rig.configure(12, 50)  # pre-operational, heartbeat every 50 ms
    rig.start()
    before = {d.node_id: (d.nmt_state, d.power_state, d.value(0x1017), d.value(0x6060)) for d in rig.drives.drives}
    result, frames = _scan(rig, listen_s=0.3)

    assert [n.node_id for n in result.nodes] == list(NODES)
    by_id = {n.node_id: n for n in result.nodes}
    for node in result.nodes:  # the EDS's factory values: 0x1000 and 0x1018:1-4
        assert node.answered_sdo
        assert node.device_type == 0x00020192
        assert node.identity == {1: 0x00000000, 2: 0x00000001, 3: 0x00010000, 4: 0x00000000}
        assert node.eds == DEFAULT_EDS
        assert node.problems == []
    assert by_id[9].nmt_state == "operational"
    assert by_id[12].nmt_state == "pre-operational"
    assert by_id[5].nmt_state == by_id[100].nmt_state == "no heartbeat"

    sent = [m for m in frames if 0x600 < m.arbitration_id <= 0x67F]  # requests: only a client sends them
    assert len(sent) == 127 + 4 * 4 == result.frames_sent  # 0x1000 to every id, 0x1018:1-4 to each node found
    assert all(m.data[0] == 0x40 for m in sent)  # expedited upload requests: reads, never a download
    assert not [m for m in frames if m.arbitration_id in (0x000, 0x080)]  # no NMT, no SYNC
    assert not [m for m in frames if 0x200 <= m.arbitration_id < 0x580]  # no PDO
    after = {d.node_id: (d.nmt_state, d.power_state, d.value(0x1017), d.value(0x6060)) for d in rig.drives.drives}
    assert after == before


def test_a_stopped_node_is_listed_by_its_heartbeat(rig: Rig) -> None:
    rig.configure(100, 50, NmtCommand.STOP)  # a STOPPED node serves no SDO
    rig.start()
    result, _ = _scan(rig, listen_s=0.3)
    node = {n.node_id: n for n in result.nodes}[100]
    assert node.nmt_state == "stopped"
    assert not node.answered_sdo
    assert node.device_type is None
    assert node.problems == ["0x1000: no SDO answer (a STOPPED node serves no SDO)"]
    assert node.eds is None
    assert "no 0x1018" in node.eds_note


def test_a_scan_of_an_empty_bus_takes_well_under_2_s() -> None:
    bus = open_bus("virtual", f"scan-empty-{next(_CHANNELS)}", 1_000_000)
    started = time.monotonic()
    try:
        result = scan_bus(bus, listen_s=1.0, sdo_timeout_s=sdo_probe_timeout_s(1_000_000))
    finally:
        bus.shutdown()
    took = time.monotonic() - started
    assert result.nodes == ()
    assert result.frames_sent == 127
    assert 1.0 <= took < 1.8  # the listening window (1.00 s measured); the 127 probes time out together, within it
    assert sdo_probe_timeout_s(1_000_000) == pytest.approx(0.1 + 2 * 127 * 135 / 1e6)


def test_nodes_are_matched_to_the_eds_of_their_vendor_and_product(tmp_path: Path, rig: Rig) -> None:
    other = tmp_path / "other_vendor.eds"
    other.write_text(DEFAULT_EDS.read_text().replace("VendorNumber=0x00000000", "VendorNumber=0x000001A3"))
    broken = tmp_path / "broken.eds"
    broken.write_text("[DeviceInfo]\nProductNumber=1\n")
    catalogue, problems = eds_catalogue([tmp_path])
    assert [(e.path.name, e.vendor_id, e.product_code) for e in catalogue] == [
        ("other_vendor.eds", 0x1A3, 1),
        ("daror_sea.eds", 0, 1),
    ]
    assert problems == [f"{broken}: [DeviceInfo] VendorNumber is missing; expected the number 0x1018 reports"]
    rig.start()
    bus = open_bus("virtual", rig.channel, 1_000_000)
    try:
        result = scan_bus(bus, catalogue, listen_s=0.1)
    finally:
        bus.shutdown()
    assert {n.eds for n in result.nodes} == {DEFAULT_EDS}  # vendor 0: the shipped EDS, not the 0x1A3 one
    copy = tmp_path / "copy.eds"
    shutil.copy(DEFAULT_EDS, copy)
    catalogue, _ = eds_catalogue([copy])
    bus = open_bus("virtual", rig.channel, 1_000_000)
    try:
        result = scan_bus(bus, catalogue, listen_s=0.1)
    finally:
        bus.shutdown()
    assert result.nodes[0].eds == copy
    assert result.nodes[0].eds_note == f"also matches {DEFAULT_EDS}"


def test_an_eds_folder_that_does_not_exist_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(HalConfigError, match=r"nothere: no such file or folder; expected a folder of EDS files$"):
        eds_catalogue([tmp_path / "nothere"])
    assert eds_identity(DEFAULT_EDS).product_name == "DAROR-01 SEA drive"


def test_daror_can_scan_on_a_can_sim_robot_file_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text("backend: can-sim\nnode_ids: [3, 4, 5, 6]\n")
    out = tmp_path / "scan.json"
    assert main(["can", "scan", "--hal-config", str(robot), "--listen-s", "0.2", "--json", str(out)]) == 0
    found = json.loads(out.read_text())
    assert [n["node_id"] for n in found["nodes"]] == [3, 4, 5, 6]
    assert {(n["device_type"], n["vendor_id"], n["product_code"]) for n in found["nodes"]} == {(0x00020192, 0, 1)}
    assert "4 node(s)" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--listen-s", "0", "--interface", "virtual", "--channel", "x"], "--listen-s 0: expected a time above 0 s"),
        (["--interface", "virtual"], "name the bus: --interface and --channel"),
        (["--interface", "virtual", "--channel", "x", "--eds-dir", "/nonexistent"], "/nonexistent: no such file"),
        (["--interface", "virtual", "--channel", "x", "--bitrate", "0"], "--bitrate 0: expected one of the CiA 301"),
    ],
)
def test_daror_can_scan_bad_input_is_one_line_exit_2(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["can", "scan", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("daror can scan: error: ")
    assert message in err
    assert err.count("\n") == 1


def test_daror_can_scan_refuses_a_sim_robot_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text("backend: sim\n")
    assert main(["can", "scan", "--hal-config", str(robot)]) == 2
    assert "backend sim; a scan needs backend can or can-sim" in capsys.readouterr().err


def test_the_scan_never_sends_nmt_even_to_a_booting_node(rig: Rig) -> None:
    """A node that just booted (boot-up message, pre-operational) is found and stays pre-operational."""
    rig.start()
    result, frames = _scan(rig, listen_s=0.1)
    assert len(result.nodes) == 4
    assert {d.nmt_state for d in rig.drives.drives} == {NmtState.PRE_OPERATIONAL}
    assert not [m for m in frames if m.arbitration_id == 0x000]


def test_daror_can_scan_of_a_hardware_robot_file_scans_its_interface(
    tmp_path: Path, rig: Rig, capsys: pytest.CaptureFixture[str]
) -> None:
    """``backend: can``: the file's interface and channel (here python-can's virtual bus, the drives on it)."""
    rig.start()
    robot = tmp_path / "robot.yaml"
    robot.write_text(f"backend: can\ninterface: virtual\nchannel: {rig.channel}\nnode_ids: [5, 9, 12, 100]\n")
    out = tmp_path / "scan.json"
    assert main(["can", "scan", "--hal-config", str(robot), "--listen-s", "0.2", "--json", str(out)]) == 0
    assert [n["node_id"] for n in json.loads(out.read_text())["nodes"]] == list(NODES)
    assert not [m for m in rig.drain() if m.arbitration_id == 0x000 or 0x200 <= m.arbitration_id < 0x580]
    assert f"scanning virtual {rig.channel} at 1000000 bit/s" in capsys.readouterr().out
