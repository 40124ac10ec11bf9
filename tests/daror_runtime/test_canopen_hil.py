"""Hardware-in-the-loop over a simulated CAN bus (issue 12): ``daror hil`` end to end.

One run of the demo's session script over ``can-sim`` (lock-step, 400 Hz, four simulated CiA 402
drives on python-can's virtual bus, the bus logged to ``can.log.gz``) reaches compensation; then each
bus fault in turn is injected into the drive of joint 2 (node 2) in compensation, the robot fails,
the operator acknowledges and resets, and a new session reaches compensation again. Checked on
what an engineer would check: the session's states (audit log), the frames on the bus (the
candump log: the RPDOs that remove torque), the model's validation error beside the ``sim``
backend's on the same script, and the log read by an independent tool (can-utils' ``log2asc``).
"""

from __future__ import annotations

import gzip
import itertools
import json
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from daror_runtime.cli import main
from hal.capabilities import BUS_FAULT_KINDS

pytestmark = pytest.mark.slow

DATA = Path(__file__).parents[1] / "data"
SESSION = Path(__file__).parents[2] / "daror_runtime" / "console" / "scripts" / "session.txt"
SETTINGS = DATA / "hil_fault_settings.yaml"  # every sixth waypoint (D200)
FAULT_BLOCK = DATA / "hil_fault_and_new_session.txt"
PERIOD_S = 1.0 / 400.0  # the default rate of four drives on 1 Mbit/s (D160)
NODES = (1, 2, 3, 4)
#: One frame of the log: (robot time s, COB-ID, data, sent by the master).
LINE = re.compile(r"^\((\d+\.\d+)\) (\S+) ([0-9A-F]{3})#([0-9A-F]*) ([TR])$")


@dataclass
class BusLog:
    """What the tests need of a long ``can.log.gz``, read in one pass (the whole log is millions of lines).

    Times are robot time (the log's timestamp minus the run's epoch).
    """

    sent: int = 0
    received: int = 0
    first: tuple[float, int, bool] | None = None  # time, COB-ID, sent
    first_sync: tuple[int, float] | None = None  # line index, time
    near_fails: dict[int, list[tuple[float, int, bytes]]] | None = None  # per FAIL: frames around it (see _read_log)
    nmt: list[tuple[float, bytes]] | None = None  # every NMT command
    sdo_to_2: list[float] | None = None  # every SDO request to node 2
    cycle_bits: list[tuple[float, int]] | None = None  # per SYNC cycle: its SYNC's time, its frames' worst-case bits


def frame_bits(data_hex: str) -> int:
    """Worst-case bits of a standard frame with ``len(data_hex) / 2`` bytes (55 + 10 s: the issue's count, D160)."""
    return 55 + 10 * (len(data_hex) // 2)


#: Frames kept around each FAIL: the master's RPDOs, SYNCs, and node 2's EMCY, heartbeat and TPDO1.
WINDOW_IDS = {f"{0x200 + n:03X}" for n in NODES} | {"080", "082", "702", "182"}


def _read_log(log: Path, epoch_s: int, fail_times: list[float], before_s: float = 0.6, after_s: float = 0.2) -> BusLog:
    found = BusLog(near_fails={n: [] for n in range(len(fail_times))}, nmt=[], sdo_to_2=[], cycle_bits=[])
    cycle: list = [None, 0]  # the open cycle: its SYNC's stamp (None before the first SYNC), its bits
    with gzip.open(log, "rt") as lines:
        for index, line in enumerate(lines):
            stamp, _, rest = line.partition(" ")
            frame, direction = rest.rsplit(" ", 1)
            cob_text, _, data_text = frame.split(" ", 1)[1].partition("#")
            if cob_text == "080":  # a SYNC closes the cycle before it (the frames between two SYNCs)
                if cycle[0] is not None:
                    found.cycle_bits.append((float(cycle[0].strip("()")) - epoch_s, cycle[1]))
                cycle = [stamp, frame_bits(data_text)]
            elif cycle[0] is not None:
                cycle[1] += frame_bits(data_text)
            sent = direction.strip() == "T"
            if sent:
                found.sent += 1
            else:
                found.received += 1
            if found.first is None or cob_text in ("000", "602") or cob_text in WINDOW_IDS:
                match = LINE.match(line.rstrip("\n"))
                assert match is not None, f"not a candump -L line: {line!r}"
                t_s = float(stamp.strip("()")) - epoch_s
                cob_id = int(cob_text, 16)
                if found.first is None:
                    found.first = (t_s, cob_id, sent)
                if cob_id == 0x080 and found.first_sync is None:
                    found.first_sync = (index, t_s)
                if cob_id == 0x000:
                    found.nmt.append((t_s, bytes.fromhex(data_text)))
                elif cob_id == 0x602 and sent:
                    found.sdo_to_2.append(t_s)
                elif cob_text in WINDOW_IDS:
                    for n, fail_t in enumerate(fail_times):
                        if fail_t - before_s <= t_s <= fail_t + after_s:
                            found.near_fails[n].append((t_s, cob_id, bytes.fromhex(data_text)))
    return found


@dataclass
class HilRun:
    out: Path
    code: int
    events: list[dict]
    report: dict
    session: dict
    log: BusLog


def _events(audit: Path) -> list[dict]:
    return [json.loads(line) for line in audit.read_text().splitlines() if line.strip()]


@pytest.fixture(scope="module")
def hil(tmp_path_factory: pytest.TempPathFactory) -> HilRun:
    folder = tmp_path_factory.mktemp("hil")
    script = folder / "every_fault.txt"
    block = FAULT_BLOCK.read_text()
    script.write_text(SESSION.read_text() + "".join("\n" + block.replace("KIND", k) for k in BUS_FAULT_KINDS))
    out = folder / "run"
    code = main(["hil", "--script", str(script), "--out", str(out), "--settings", str(SETTINGS)])
    report = json.loads((out / "hil.json").read_text())
    events = _events(out / "audit.jsonl")
    fails = [e["t_s"] for e in events if e.get("event") == "transition" and e["dest"] == "FAIL"]
    log = _read_log(out / "can.log.gz", report["bus"]["traffic_log_epoch_s"], fails)
    return HilRun(out, code, events, report, json.loads((out / "session.json").read_text()), log)


@pytest.fixture(scope="module")
def sim_rmse(tmp_path_factory: pytest.TempPathFactory) -> float:
    """The PLF+ validation RMSE of the same script and settings on the ``sim`` backend."""
    out = tmp_path_factory.mktemp("sim") / "run"
    assert (
        main(["console", "--hal", "sim", "--script", str(SESSION), "--settings", str(SETTINGS), "--out", str(out)]) == 0
    )
    return _validation_rmse(json.loads((out / "session.json").read_text()))


def _validation_rmse(session: dict) -> float:
    model = session["status"]["model"] if "status" in session else session["model"]
    return float(model["validation_rmse_nm"])


def _transitions(run: HilRun) -> list[dict]:
    return [e for e in run.events if e.get("event") == "transition"]


def test_the_run_ends_in_compensation_and_the_bus_stayed_within_its_budget(hil: HilRun) -> None:
    assert hil.code == 0
    bus = hil.report["bus"]
    assert bus["backend"] == "can-sim"
    assert bus["rate_hz"] == 400.0
    assert bus["worst_case_load"] == pytest.approx(0.5453, abs=0.0001)  # 1,355 bits a cycle + heartbeats, on average
    assert bus["worst_cycle_load"] == pytest.approx(0.672, abs=0.0001)  # 1,355 + 5 x 65 of 2,500 bits (D160)
    assert bus["unknown_frames"] == 0
    assert _transitions(hil)[-1]["dest"] == "compensation"
    # every frame of the session is in the log, both directions
    assert hil.log.sent == bus["frames_sent"]
    assert hil.log.received == bus["frames_received"]


def test_every_cycle_of_the_session_stays_within_the_budget(hil: HilRun) -> None:
    """The worst SYNC cycle of the log, counted as the issue counted it (55 + 10 s bits a frame), is within 70 %.

    Until the first bus fault is injected (the first FAIL): the demo session, its identification runs and the torque slope
    writes paced into cycles with room (D161). What the faults add (EMCY, NMT, a reconfiguration) is
    the drives' and the operator's, not scheduled, and is not bounded here.
    """
    first_fault_s = min(e["t_s"] for e in _transitions(hil) if e["dest"] == "FAIL")  # the first bus fault injected
    assert hil.log.cycle_bits is not None
    session = [bits for t_s, bits in hil.log.cycle_bits if t_s < first_fault_s - 1.0]
    assert len(session) > 0.9 * (first_fault_s - 1.0) / PERIOD_S  # the cycles were read, from the first SYNC
    budget_bits = 0.70 * hil.report["bus"]["bitrate"] * PERIOD_S
    assert budget_bits == pytest.approx(1750.0)
    assert max(session) <= budget_bits, sorted(set(session))[-5:]
    # once started, every cycle carries at least the SYNC and every PDO of four drives
    assert min(bits for t_s, bits in hil.log.cycle_bits if 1.0 <= t_s < first_fault_s) == 1355
    assert hil.report["bus"]["sdo_deferred"] > 0  # the slope writes met the heartbeats' cycles and waited


def test_the_demo_session_reaches_compensation_with_the_sim_backends_model_error(hil: HilRun, sim_rmse: float) -> None:
    first = next(e for e in _transitions(hil) if e["dest"] == "compensation")
    assert first["source"] == "training"
    rmse = _validation_rmse(hil.session)
    assert abs(rmse - sim_rmse) <= 0.10 * sim_rmse, (rmse, sim_rmse)
    assert rmse < 0.5  # PLF+ on dataset B: the A Priori model is at 1.38 Nm


def _fail_times(run: HilRun) -> list[float]:
    return [e["t_s"] for e in _transitions(run) if e["dest"] == "FAIL"]


def test_every_fault_fails_the_robot_naming_the_drive(hil: HilRun) -> None:
    fails = [e for e in _transitions(hil) if e["dest"] == "FAIL"]
    assert [e["source"] for e in fails] == ["compensation"] * len(BUS_FAULT_KINDS)
    faults = [e for e in hil.events if e.get("event") == "fault" and e.get("kind") in ("hal", "drive")]
    for fail in fails:
        at = [f for f in faults if f["t_s"] == fail["t_s"]]
        assert at, f"no HAL or drive fault at the FAIL of t = {fail['t_s']}"
        assert any("drive 2" in f["message"] or f.get("joint") == 2 for f in at), at


def _onset(kind: str, frames: list[tuple[float, int, bytes]], fail_t: float) -> float:
    """When the fault became visible on the bus (robot time): what the master can first see of it.

    An EMCY (emcy, drive_fault): the frame. Frozen or dropped frames: the first SYNC that node 2's
    TPDO1 did not answer. A lost heartbeat: its last heartbeat plus the consumer time (250 ms).
    """
    if kind in ("emcy", "drive_fault"):
        return min(t for t, cob, _ in frames if cob == 0x082 and t <= fail_t + 0.05)
    if kind == "heartbeat_loss":
        return max(t for t, cob, _ in frames if cob == 0x702 and t <= fail_t) + 0.25
    # The FAIL's time is its sample's, which stops advancing while node 2 is quiet: look a little
    # past it for the gap in node 2's TPDO1 (a dropout's TPDOs come back after it).
    tpdos = sorted(t for t, cob, _ in frames if cob == 0x182 and fail_t - 0.05 <= t <= fail_t + 0.05)
    gaps = [(a, b) for a, b in itertools.pairwise(tpdos) if b - a > 1.5 * PERIOD_S]
    answered = gaps[0][0] if gaps else tpdos[-1]  # logged when drained: a cycle after the SYNC it answered
    return min(t for t, cob, _ in frames if cob == 0x080 and t >= answered)


@pytest.mark.parametrize("kind", BUS_FAULT_KINDS)
def test_each_fault_takes_the_drive_off_within_three_cycles_and_the_others_hold_the_arm(hil: HilRun, kind: str) -> None:
    """From the cycle the fault is visible on the bus, within three cycles node 2's RPDO carries controlword
    0x0000 and target torque 0, and keeps doing so; the other drives stay enabled (controlword 0x000F) with
    torque: the reaction holds the arm with them (fsm_spec.yaml: a drive fault takes its joint off, lower)."""
    n = BUS_FAULT_KINDS.index(kind)
    frames = hil.log.near_fails[n]
    onset = _onset(kind, frames, _fail_times(hil)[n])
    rpdos = [(t, data) for t, cob, data in frames if cob == 0x202 and t >= onset - 1e-9]
    off = [t for t, data in rpdos if data == b"\x00\x00\x00\x00"]
    assert off, f"node 2: no torque-off RPDO after the fault's onset at {onset} s"
    assert off[0] - onset <= 3 * PERIOD_S + 1e-6, (off[0], onset)  # the log prints microseconds
    assert all(data == b"\x00\x00\x00\x00" for t, data in rpdos if t >= off[0])  # and it stays off
    for node in (1, 3, 4):
        held = [data for t, cob, data in frames if cob == 0x200 + node and onset <= t]
        assert held, f"node {node}: no RPDO after the fault"
        assert all(data[:2] == b"\x0f\x00" for data in held), (node, held[:3])  # enable operation, every cycle
        assert any(data[2:] != b"\x00\x00" for data in held), node  # with torque: the arm is held


def test_after_acknowledge_and_reset_a_new_session_reaches_compensation_every_time(hil: HilRun) -> None:
    transitions = _transitions(hil)
    resets = [e for e in transitions if e["source"] == "FAIL"]
    assert [e["dest"] for e in resets] == ["startup"] * len(BUS_FAULT_KINDS)
    for reset in resets:
        later = [e for e in transitions if e["t_s"] > reset["t_s"]]
        assert any(e["dest"] == "compensation" for e in later)
    assert sum(1 for e in transitions if e["dest"] == "compensation") == 1 + len(BUS_FAULT_KINDS)


def test_lost_drives_were_brought_back_by_nmt_reset_and_configured_again(hil: HilRun) -> None:
    """Heartbeat loss and frozen PDOs: the fault reset resets node 2 (NMT 0x81) and configures it by SDO again."""
    resets = [t for t, data in hil.log.nmt if data == b"\x81\x02"]
    assert len(resets) >= 2  # heartbeat_loss, frozen_pdo (drop_frames recovers by itself)
    for reset_t in resets:
        sdo = [t for t in hil.log.sdo_to_2 if reset_t < t < reset_t + 1.0]
        assert len(sdo) >= 20, "node 2 was not configured again after its reset"
        start = [t for t, data in hil.log.nmt if data == b"\x01\x02" and t > reset_t]
        assert start, "node 2 was not started again after its configuration"


@pytest.mark.subprocess
def test_can_utils_log2asc_reads_the_bus_log(hil: HilRun, tmp_path: Path) -> None:
    log2asc = shutil.which("log2asc")
    if log2asc is None:
        pytest.skip("can-utils is not installed (the Makefile installs it with apt-get for make test)")
    asc = tmp_path / "can.asc"
    # the log is gzip-compressed: decompressed into log2asc's standard input, as docs/canopen.md says
    with subprocess.Popen(["zcat", str(hil.out / "can.log.gz")], stdout=subprocess.PIPE) as zcat:
        done = subprocess.run(
            [log2asc, "-O", str(asc), "daror"], stdin=zcat.stdout, capture_output=True, text=True, timeout=300
        )
    assert zcat.returncode == 0
    assert done.returncode == 0, done.stderr
    assert hil.log.first is not None
    assert hil.log.first_sync is not None
    first_t, first_id, first_sent = hil.log.first
    sync_index, sync_t = hil.log.first_sync
    headers = body_lines = 0
    first_body: list[str] = []
    sync_body: list[str] = []
    with open(asc) as lines:  # millions of lines: read as a stream
        for number, line in enumerate(lines):
            if line.startswith("date "):
                headers += 1
            if number < 3 or not line.strip():
                continue
            if body_lines == 0:
                first_body = line.split()
            if body_lines == sync_index:
                sync_body = line.split()
            body_lines += 1
    assert headers == 1, "log2asc restarted its header: a time it misread"
    assert body_lines == hil.log.sent + hil.log.received
    # ASC: relative time, channel 1, id, Tx/Rx, d, length, bytes
    assert first_body[2].upper() == f"{first_id:X}"
    assert first_body[3] == ("Tx" if first_sent else "Rx")
    assert sync_body[2] == "80"
    assert float(sync_body[0]) == pytest.approx(sync_t - first_t, abs=2e-6)
