"""The second drive family (maxon EPOS4, examples/robot/epos4.yaml) runs the demo session over durand drives in lock-step.

Issue 25's last acceptance point: a drive family described only by its vendor EDS and a robot file
(the load encoder in 0x60E4:2, the e-stops on 0x60FD) runs the demo session over drives built
from that EDS on the independent stack (durand), as it does on the project's simulated drives
(tests/hal/canopen/test_canopen_robot_golden.py). ``daror hil`` runs the console's session script in-process,
its HAL the ``can-sim`` backend of the robot file with :class:`tests.durand_lockstep.DurandCanHal`
in place of the project's drives (``hal.interface.open_hal`` patched for the run: nothing else of
the command changes). The shorter identification of tests/data/hil_settings.yaml (every twelfth waypoint, D200) keeps
it at about 7 s.

What shows that durand answered: every frame the master received is one a durand node sent
(counts per drive: the TPDOs of every SYNC, the SDO responses of durand's server with the EDS's
identity, heartbeats on durand's timer every 100 ms of robot time), and a drive wired otherwise
than its robot file says (the e-stop bits, their polarity, the link encoder's sub-index or scale,
the motor encoder's scale) fails the session.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import hal.interface
from daror_runtime.cli import main
from daror_runtime.hil import hil_config
from hal.config import AnyHalConfig, CanSimHalConfig
from hal.errors import InputError
from hal.interface import Command, DriveState, Hal, HalFaultError
from tests.durand_drives import DevicePower, DriveWiring, robot_file_drives, sdo_responses
from tests.durand_lockstep import HEARTBEAT_OPERATIONAL, DurandCanHal, DurandDriveSet
from tests.hal.canopen.test_canopen_robot_golden import SESSION_PATH

ROOT = Path(__file__).resolve().parents[3]
ROBOT_FILE = ROOT / "examples" / "robot" / "epos4.yaml"
SCRIPT = ROOT / "daror_runtime" / "console" / "scripts" / "session.txt"
SETTINGS = ROOT / "tests" / "data" / "hil_settings.yaml"
DRIVES = robot_file_drives(ROBOT_FILE)
NODE_IDS = [11, 12, 13, 14]
HEARTBEAT_S = 0.1  # the robot file's heartbeat_ms
PERIOD_S = 1.0 / 400.0  # the EPOS4 bus's rate (its worst cycle fits the budget at 400 Hz, D160)
#: Bit 16 (operator) and 17 (pilot) of 0x60FD, wired normally closed: both set while neither is pressed.
INPUTS_RELEASED = 1 << 16 | 1 << 17


@dataclass
class Run:
    """One ``daror hil`` run over durand drives: its exit code, its files, its drive set, its wall time."""

    code: int
    out: Path
    drives: DurandDriveSet
    wall_s: float

    def audit(self) -> list[dict[str, Any]]:
        return [json.loads(line) for line in (self.out / "audit.jsonl").read_text(encoding="utf-8").splitlines()]

    def transitions(self) -> list[tuple[str, str]]:
        return [(e["source"], e["dest"]) for e in self.audit() if e.get("event") == "transition"]

    def faults(self) -> list[tuple[float, str]]:
        return [(e["t_s"], e["message"]) for e in self.audit() if e.get("event") == "fault" and e.get("message")]

    def bus(self) -> dict[str, Any]:
        return json.loads((self.out / "hil.json").read_text(encoding="utf-8"))["bus"]  # type: ignore[no-any-return]


@pytest.fixture
def hil(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[..., Run]]:
    """``hil(script, drives=DRIVES)``: ``daror hil --hal-config epos4.yaml --settings hil_settings.yaml`` over durand drives."""
    made: list[DurandCanHal] = []
    runs = itertools.count(1)

    def run(script: Path, drives: Mapping[int, tuple[Path, DriveWiring]] = DRIVES) -> Run:
        def open_hal(config: AnyHalConfig) -> Hal:
            assert isinstance(config, CanSimHalConfig)  # daror hil's configuration of the robot file
            backend = DurandCanHal(config, drives)
            made.append(backend)
            return backend

        monkeypatch.setattr(hal.interface, "open_hal", open_hal)
        out = tmp_path / f"run{next(runs)}"
        start = time.perf_counter()
        code = main(
            [
                "hil",
                "--script",
                str(script),
                "--out",
                str(out),
                "--hal-config",
                str(ROBOT_FILE),
                "--settings",
                str(SETTINGS),
            ]
        )
        wall_s = time.perf_counter() - start
        assert made, "daror hil did not build its HAL through hal.interface.open_hal"
        return Run(code, out, made[-1].durand, wall_s)

    yield run
    for backend in made:
        backend.durand.release()  # durand's scheduler back, whatever the run did


def _prefix(tmp_path: Path, last_line: str) -> Path:
    """The session script up to and including ``last_line`` (a prefix of the same session)."""
    lines = SCRIPT.read_text(encoding="utf-8").splitlines(keepends=True)
    end = lines.index(last_line + "\n") + 1
    path = tmp_path / f"session_to_{last_line.split()[-1]}.txt"
    path.write_text("".join(lines[:end]), encoding="utf-8")
    return path


@pytest.mark.slow
def test_the_epos4_family_runs_the_demo_session_on_durand_drives_in_lock_step(
    hil: Callable[..., Run], tmp_path: Path
) -> None:
    run = hil(SCRIPT)
    assert run.code == 0
    assert run.transitions() == SESSION_PATH
    session = json.loads((run.out / "session.json").read_text(encoding="utf-8"))
    assert session["state"] == "compensation"
    assert session["faults"] == []
    assert session["model"]["validated"] is True
    bus = run.bus()
    assert bus["node_ids"] == NODE_IDS
    assert bus["rate_hz"] == 400.0
    assert bus["unknown_frames"] == 0
    drives = run.drives
    assert drives.errors.snapshot() == []
    assert set(drives.durand_defects) <= {"durand: SYNC handler of an inactive TPDO (node not operational)"}

    # Every SYNC the master sent reached every durand node, which answered it with its two TPDOs.
    assert drives.syncs == bus["syncs"] > 130 / PERIOD_S  # the session's ~131 s of robot time
    sent_total = 0
    for n in NODE_IDS:
        traffic = drives.traffic(n)
        assert traffic.syncs == bus["syncs"]
        assert traffic.sent[0x180 + n] == traffic.sent[0x280 + n] == bus["syncs"]
        sent_total += sum(traffic.sent.values())

        # durand's SDO server answered the start-up with the EDS's values and the robot file's.
        reads = {(i, s): v for kind, i, s, v in sdo_responses(traffic.service_frames, n) if kind == "read"}
        assert reads[(0x1018, 1)] == 0xFB  # maxon, from the EDS's [DeviceInfo]
        assert reads[(0x1018, 2)] == 0x60500000
        assert reads[(0x6502, 0)] == 0x208  # the application's torque modes (tq, cst)
        assert reads[(0x6076, 0)] == 160  # the robot file's sdo_init, read back
        assert reads[(0x6061, 0)] == 10  # cyclic synchronous torque
        assert drives.read(n, 0x1A01, 1) == 0x60E40220  # TPDO2: the link encoder, sensor 2

        # durand's heartbeat producer, on its timer in robot time: every 100 ms once operational.
        beats = [f.t_s for f in traffic.service_frames if f.cob_id == 0x700 + n and f.data == HEARTBEAT_OPERATIONAL]
        assert len(beats) > 125 / HEARTBEAT_S  # operational from ~0.5 s to the end
        # Each goes out at the first SYNC at or after its time on durand's timer: one SYNC period either way.
        gaps = [b - a for a, b in itertools.pairwise(beats)]
        assert max(abs(gap - HEARTBEAT_S) for gap in gaps) <= PERIOD_S + 1e-9
        assert (beats[-1] - beats[0]) / len(gaps) == pytest.approx(HEARTBEAT_S, abs=1e-6)
    # Every frame the master received came from a durand node; those it did not read are the drives'
    # answers to its last cycle (one SYNC: two TPDOs per drive), sent after its last read at close.
    assert 0 <= sent_total - bus["frames_received"] <= 2 * len(NODE_IDS)

    # The e-stop chain on joint 1's 0x60FD (normally closed): each press the script makes, by the button pressed.
    assert [m for _, m in run.faults()] == [
        "e-stop pressed (operator)",
        "e-stop pressed (pilot)",
        "e-stop pressed (pilot)",
        "e-stop pressed (operator)",
    ]
    assert drives.read(11, 0x60FD, 0) == INPUTS_RELEASED
    assert [drives.read(n, 0x60FD, 0) for n in NODE_IDS[1:]] == [0, 0, 0]  # not wired: durand keeps the EDS's 0

    # Deterministic: the same session to identification again gives the same frames, SYNC by SYNC.
    again = hil(_prefix(tmp_path, "expect state identification"))
    assert again.code == 0
    assert again.transitions() == SESSION_PATH[:7]
    ended_s = max(e["t_s"] for e in again.audit() if e.get("event") == "transition")
    common = [c for c in again.drives.checkpoints if c[1] < ended_s]
    assert len(common) > 20 / (1000 * PERIOD_S) - 2  # ~24 s of robot time, a digest every 1000 SYNCs (2.5 s)
    assert common == run.drives.checkpoints[: len(common)]


def _miswired(change: Callable[[DriveWiring], DriveWiring]) -> dict[int, tuple[Path, DriveWiring]]:
    return {n: (eds, change(wiring)) for n, (eds, wiring) in DRIVES.items()}


#: Drives wired otherwise than the robot file says, and the first fault each makes the session find.
MISWIRED: dict[str, tuple[Callable[[DriveWiring], DriveWiring], str]] = {
    "link encoder in 0x60E4:1": (
        lambda w: dataclasses.replace(w, link=(0x60E4, 1)),
        "joint 1: spring torque -100.6 Nm beyond the limit -30 Nm",
    ),
    "link encoder 16 times coarser": (
        lambda w: dataclasses.replace(w, rad_per_link_count=w.rad_per_link_count * 16),
        "joint 1: spring torque -94.41 Nm beyond the limit -30 Nm",
    ),
    "motor encoder twice as coarse": (
        lambda w: dataclasses.replace(w, rad_per_motor_count=w.rad_per_motor_count * 2),
        "joint 1: spring torque 49.07 Nm beyond the limit 30 Nm",
    ),
    "e-stops wired normally open": (
        lambda w: dataclasses.replace(w, pressed_when_clear=False),
        "e-stop pressed (operator, pilot)",
    ),
    "e-stop bits swapped": (
        lambda w: dataclasses.replace(w, operator_mask=w.pilot_mask, pilot_mask=w.operator_mask),
        "e-stop pressed (pilot)",  # the operator's press, read as the pilot's
    ),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(MISWIRED))
def test_a_drive_wired_otherwise_than_its_robot_file_fails_the_session(
    hil: Callable[..., Run], tmp_path: Path, name: str
) -> None:
    change, first_fault = MISWIRED[name]
    run = hil(_prefix(tmp_path, "expect state rom_limits"), _miswired(change))
    assert run.code == 1  # the script's expectation failed
    assert run.transitions() != SESSION_PATH[:5]
    assert run.faults()[0][1] == first_fault
    assert run.drives.errors.snapshot() == []


@pytest.fixture
def backend(tmp_path: Path) -> Iterator[DurandCanHal]:
    """The ``can-sim`` backend of ``daror hil`` for the EPOS4 robot file, over durand drives, opened."""
    hal_ = DurandCanHal(hil_config(ROBOT_FILE, None, None, tmp_path / "can.log.gz"), DRIVES)
    try:
        hal_.open()
        yield hal_
    finally:
        hal_.close()
        hal_.durand.release()


def test_a_tpdo_carries_the_plant_at_its_sync_and_the_plant_gets_the_torque_durand_applies(
    backend: DurandCanHal,
) -> None:
    """Lock-step as the project's drives do it: what the master reads after a cycle is the plant at that cycle's SYNC,
    in the robot file's units (the link encoder through 0x60E4:2, 65536 counts a turn), and a torque the
    master sends acts from that SYNC on, in the EDS's scale; the e-stop circuit's cut switches durand's
    CiA 402 application off."""
    plant, drives = backend.plant, backend.durand
    k = backend.description.sea.spring_stiffness_nm_per_rad
    wiring = [DRIVES[n][1] for n in NODE_IDS]
    torque = np.array([0.8, -0.8, 0.0, 0.0])  # 50 and -50 per mille of 160 mNm times 100
    for _ in range(round(1.0 / PERIOD_S)):  # enable, then one second with the arm moving under the torques
        truth = plant.read_without_faults()  # robot time stands still until the SYNC: what the SYNC samples
        backend.write(Command(torque, True))
        sample = backend.read()
        for j, w in enumerate(wiring):
            assert sample.q_rad[j] == round(truth.q_rad[j] / w.rad_per_link_count) * w.rad_per_link_count
            assert sample.theta_rad[j] == round(truth.theta_rad[j] / w.rad_per_motor_count) * w.rad_per_motor_count
            assert sample.tau_nm[j] == pytest.approx(k * (sample.theta_rad[j] - sample.q_rad[j]), abs=1e-12)
    assert sample.drives == (DriveState.ENABLED,) * 4
    assert [drives.device(n).applied_permille for n in NODE_IDS] == [50, -50, 0, 0]
    np.testing.assert_allclose(drives.applied_motor_torque_nm, torque, atol=1e-12)
    np.testing.assert_allclose(plant.applied_motor_torque_nm, torque, atol=1e-12)
    moved = plant.read_without_faults().q_rad
    assert abs(moved[0] - truth.q_rad[0]) > 0  # the arm moves: a sample taken a tick late would differ

    plant.press_estop(0, True)  # the operator's button: the plant reads it in its next tick, sto cuts there
    backend.write(Command(torque, True))
    assert backend.read().estop == (False, False)  # that SYNC sampled the plant before its tick
    assert [drives.device(n).power for n in NODE_IDS] == [DevicePower.SWITCH_ON_DISABLED] * 4  # cut in the tick
    backend.write(Command(torque, True))
    assert backend.read().estop == (True, False)  # joint 1's 0x60FD, bit 16 cleared (normally closed)
    assert drives.read(11, 0x60FD, 0) == 1 << 17
    assert [drives.device(n).power for n in NODE_IDS] == [DevicePower.SWITCH_ON_DISABLED] * 4
    assert plant.applied_motor_torque_nm.tolist() == [0.0] * 4
    assert drives.errors.snapshot() == []


def _cycle(backend: DurandCanHal, enable: bool = True) -> tuple[Any, str | None]:
    """One cycle at zero torque: the sample and the fault the backend latched in it (None: none)."""
    backend.write(Command(np.zeros(4), enable))
    try:
        return backend.read(), None
    except HalFaultError as exc:
        return None, str(exc)


def test_faults_injected_into_durand_drives_reach_the_master_as_on_the_project_drives(backend: DurandCanHal) -> None:
    """``emcy`` and ``drive_fault``: durand's EMCY producer and 0x603F, the drive in FAULT; ``heartbeat_loss``: durand's
    producer off, the drive lost after the master's consumer time (250 ms) of robot time."""
    drives = backend.durand
    for _ in range(40):
        sample, fault = _cycle(backend)
        assert fault is None
    assert sample.drives == (DriveState.ENABLED,) * 4
    backend.world.inject_fault("emcy", 2)
    sample, fault = _cycle(backend)
    assert fault == "drive 12: EMCY 0x1000 generic error, error register 0x01"
    assert drives.device(12).power is DevicePower.FAULT
    assert drives.read(12, 0x603F, 0) == 0x1000
    assert drives.traffic(12).sent[0x080 + 12] == 1  # durand's EMCY producer sent it
    backend.world.inject_fault("drive_fault", 4)
    assert _cycle(backend)[1] == "drive 14: EMCY 0x2320 current, error register 0x03"
    assert drives.device(14).power is DevicePower.FAULT
    backend.world.inject_fault("heartbeat_loss", 3)
    t0 = drives.t_s
    faults = []
    while drives.t_s - t0 < 0.5:
        _, fault = _cycle(backend)
        if fault is not None:
            faults.append((drives.t_s - t0, fault))
    assert [f for _, f in faults] == ["drive 13 lost: no heartbeat for 252 ms (limit 250 ms)"]  # a SYNC's 2.5 ms
    assert 0.25 - HEARTBEAT_S <= faults[0][0] <= 0.25 + 2 * PERIOD_S  # the consumer's 250 ms after the last beat
    assert drives.read(13, 0x1017, 0) == 0
    assert [e[1:] for e in drives.events if e[2].startswith("injected")] == [
        (2, "injected emcy"),
        (4, "injected drive_fault"),
        (3, "injected heartbeat_loss"),
    ]
    with pytest.raises(InputError, match="durand drives take heartbeat_loss, emcy, drive_fault"):
        backend.world.inject_fault("frozen_pdo", 1)
    assert drives.errors.snapshot() == []
