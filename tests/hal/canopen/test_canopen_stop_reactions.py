"""What the CAN drives do by themselves when they lose the master (issue 23, point 6), on can-sim in lock-step.

A runtime that goes silent (a crash, a hung process) leaves the drives alone with a boy's arm. The
master configures each drive at start-up (0x6007, 0x605E, 0x6087, 0x605A: hal/canopen/reaction.py)
for what the runtime declared (``Hal.set_drive_reaction``): disable at once (category 0), or ramp
the torque from the last target to zero over ``ramp_s`` then disable. Checked on what an engineer
would check: the SDO bytes on the bus (candump log), the torque the drives' power stages apply
while nobody commands them, the arm's true speed in the simulated plant, the statuswords, the
report per drive; a drive without the objects degrades to category 0 and says so; the e-stop's ss1
wiring keeps the drives' power for the relay's delay.

The master goes silent with :meth:`SimulatedCanHal.tick_without_master`: robot time goes on one
SYNC period at a time for the drives and the plant, and the master sends nothing.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from hal.canopen import objects as obj
from hal.canopen.backend import SimulatedCanHal
from hal.canopen.cia402.statemachine import PowerState, statusword_of
from hal.canopen.dictionary import DEFAULT_EDS
from hal.canopen.sim.drive import SimulatedSeaDrive
from hal.config import CanSimHalConfig, hal_config
from hal.errors import HalError
from hal.interface import Command, DriveReaction, DriveState, HalFaultError
from hal.robot import EstopWiring
from hal.sim.scenario import load_scenario
from tests.can_rig import CanOnSimulatedDrives

NODES = (0x21, 0x22, 0x23, 0x24)
PERIOD_S = 1.0 / 400.0  # the default rate of four drives on 1 Mbit/s (D160)
#: How many cycles an SDO transfer may wait for room around the heartbeats (D161): a beat at h blocks the
#: cycles whose window (one cycle wider each way) or whose next cycle's holds it, h - 3 to h + 1 periods:
#: five cycles, six when the master's own beat falls a cycle apart from the drives'.
BUDGET_DEFER_CYCLES = 6
RAMP_S = 2.0
#: The peak torque (40 Nm) in per mille of the rated torque (10 Nm): 0x6072, and the start-up slope's base.
PEAK_PERMILLE = 4000
#: One frame of the candump log: (timestamp) channel COB-ID#data direction.
LINE = re.compile(r"^\((\d+\.\d+)\) (\S+) ([0-9A-F]{3})#([0-9A-F]*) ([TR])$")
SW_SWITCH_ON_DISABLED = statusword_of(PowerState.SWITCH_ON_DISABLED)


def config(**fields: object) -> CanSimHalConfig:
    made = hal_config("can-sim", node_ids=list(NODES), **fields)
    assert isinstance(made, CanSimHalConfig)
    return made


@contextlib.contextmanager
def session(
    ramp_s: float | None,
    traffic_log: Path | None = None,
    estop: EstopWiring | None = None,
    drive_eds: dict[int, Path] | None = None,
    **fields: object,
) -> Iterator[SimulatedCanHal]:
    """An open can-sim backend whose drives were told to ramp over ``ramp_s`` (None: category 0)."""
    settings = config(**fields)
    description = None
    if estop is not None:
        description = load_scenario(settings.scenario).description().model_copy(update={"estop": estop})
    hal = SimulatedCanHal(settings, description, traffic_log, drive_eds)
    hal.set_drive_reaction(DriveReaction(ramp_s))
    hal.open()
    try:
        yield hal
    finally:
        hal.close()


def holding_torque(hal: SimulatedCanHal) -> Command:
    """The motor torques that hold the simulated arm where it rests (the plant's statics)."""
    plant = hal.plant
    return Command(np.asarray(plant.plant.holding_torque_nm(plant.truth().q_rad), dtype=float), True)


def cycles(hal: SimulatedCanHal, command: Command, n: int) -> None:
    for _ in range(n):
        hal.read()
        hal.write(command)


@dataclass(frozen=True)
class LogFrame:
    t_s: float
    cob_id: int
    data: bytes
    sent: bool


def read_log(path: Path) -> list[LogFrame]:
    frames = []
    for line in path.read_text().splitlines():
        match = LINE.match(line)
        assert match is not None, f"not a candump -L line: {line!r}"
        stamp, _, cob, data, direction = match.groups()
        frames.append(LogFrame(float(stamp), int(cob, 16), bytes.fromhex(data), direction == "T"))
    return frames


def sdo_writes(frames: list[LogFrame], node: int, indices: set[int]) -> list[bytes]:
    """The SDO requests the master sent ``node`` for ``indices``, in order (8 bytes each)."""
    return [
        f.data
        for f in frames
        if f.sent and f.cob_id == 0x600 + node and struct.unpack_from("<H", f.data, 1)[0] in indices
    ]


#: The objects of a drive's own stop reaction.
REACTION_OBJECTS = {0x6007, 0x605A, 0x605E, 0x6087}


# ---------------------------------------------------------------------------- (a) the SDO writes on the bus


@pytest.mark.parametrize(
    ("ramp_s", "expected"),
    [
        (
            RAMP_S,
            [
                "2b07600002000000",  # 0x6007 abort connection: 2 disable voltage (category 0 whatever follows)
                "2b5e600000000000",  # 0x605E fault reaction: 0 disable drive
                "23876000d0070000",  # 0x6087 torque slope: 2000 per mille/s = 4000 (40 Nm, the peak) / 2 s
                "2b5a600001000000",  # 0x605A quick stop: 1 slow down on the slow-down ramp, then disable
                "2b07600003000000",  # 0x6007 abort connection: 3 quick stop
                "2b5e600001000000",  # 0x605E fault reaction: 1 slow down on the slow-down ramp
            ],
        ),
        (None, ["2b07600002000000", "2b5e600000000000"]),  # category 0: no slope, no quick stop ramp
    ],
    ids=["ramp-2s", "category-0"],
)
def test_start_up_writes_each_drive_s_stop_reaction(tmp_path: Path, ramp_s: float | None, expected: list[str]) -> None:
    """The bytes of 0x6007/0x605E/0x6087/0x605A to every node, each answered by the drive, before NMT start.

    Expedited downloads (CiA 301): 0x2B carries 2 bytes (the INTEGER16 option codes), 0x23 carries 4 (the
    UNSIGNED32 slope); index little-endian, sub-index 0, the value little-endian.
    """
    log = tmp_path / "can.log"
    with session(ramp_s, log) as hal:
        held = [(d.value(0x6007), d.value(0x605A), d.value(0x605E), d.value(0x6087)) for d in hal.drive_set.drives]
    frames = read_log(log)
    for node in NODES:
        assert [w.hex() for w in sdo_writes(frames, node, REACTION_OBJECTS)] == expected, f"node 0x{node:02X}"
        answers = [f.data for f in frames if not f.sent and f.cob_id == 0x580 + node]
        for request in map(bytes.fromhex, expected):
            assert bytes((0x60, *request[1:4], 0, 0, 0, 0)) in answers, "the drive confirmed it"
        start = next(f for f in frames if f.sent and f.cob_id == 0x000 and f.data == bytes((0x01, node)))
        last_sdo = max(f.t_s for f in frames if f.sent and f.cob_id == 0x600 + node)
        assert start.t_s >= last_sdo, "NMT start after the reaction was configured"
    if ramp_s is None:
        assert held == [(2, 0, 0, 1000)] * 4  # 0x605A and 0x6087 left at the factory's
    else:
        assert held == [(3, 1, 1, 2000)] * 4


def test_the_report_says_what_every_drive_got() -> None:
    with session(RAMP_S) as hal:
        assert hal.drive_reaction_report() == tuple(
            f"drive {j} (node 0x{n:02X}): ramps its torque to zero over 2.0 s, then disables, when it loses the master"
            for j, n in enumerate(NODES, start=1)
        )
    assert len(hal.drive_reaction_report()) == 4  # kept after close
    with session(None) as hal:
        assert hal.drive_reaction_report() == tuple(
            f"drive {j} (node 0x{n:02X}): it disables at once when it loses the master (category 0)"
            for j, n in enumerate(NODES, start=1)
        )


def test_the_reaction_is_set_before_open_and_must_be_a_time() -> None:
    hal = SimulatedCanHal(config())
    assert hal.drive_reaction_report() == ()  # nothing before open
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(HalError, match="expected a finite, positive time"):
            hal.set_drive_reaction(DriveReaction(bad))
    hal.set_drive_reaction(DriveReaction(RAMP_S))
    hal.open()
    try:
        with pytest.raises(HalError, match=r"configured at start-up; set it before open\(\)"):
            hal.set_drive_reaction(DriveReaction(None))
    finally:
        hal.close()
    hal.set_drive_reaction(DriveReaction(None))  # closed: for the next session


# ---------------------------------------------------------------------------- (b) the master goes silent


@dataclass
class Silence:
    """What happened while the master was silent: per tick (rows) and drive (columns)."""

    held_nm: np.ndarray  # the torque each drive applied before the master went silent
    applied_nm: np.ndarray  # the torque each drive's power stage applied, per tick
    plant_nm: np.ndarray  # the torque the plant applied (truth), per tick
    speed_rad_s: np.ndarray  # |dq| of each joint (truth), per tick
    states: list[PowerState]  # each drive's power state at the end
    statuswords: list[int]


def go_silent(hal: SimulatedCanHal, ticks: int) -> Silence:
    """Hold the arm for 1.5 s (the slope follower settles), then the master sends nothing for ``ticks`` periods."""
    command = holding_torque(hal)
    cycles(hal, command, 750)
    held = hal.applied_motor_torque_nm.copy()
    assert np.allclose(held, command.motor_torque_nm, atol=0.006)  # the drives hold the arm, quantised to 0.01 Nm
    applied, plant, speed = [], [], []
    for _ in range(ticks):
        hal.tick_without_master()
        applied.append(hal.applied_motor_torque_nm.copy())
        plant.append(hal.plant.applied_motor_torque_nm.copy())
        speed.append(np.abs(hal.plant.truth().dq_rad_s))
    drives = hal.drive_set.drives
    return Silence(
        held,
        np.array(applied),
        np.array(plant),
        np.array(speed),
        [d.power_state for d in drives],
        [d.value(obj.STATUSWORD) for d in drives],
    )


def test_a_silent_master_the_drives_ramp_their_torque_to_zero_over_ramp_s_then_disable(tmp_path: Path) -> None:
    """Each drive's torque falls linearly from what it held to 0 over 2 s (within 3 %), then it disables (the
    statusword says so, its EMCYs say why); the plant applies exactly that. When the master is back, its
    acknowledge finds the drives disabled and they enable again as ever."""
    log = tmp_path / "can.log"
    with session(RAMP_S, log) as hal:
        silent = go_silent(hal, int(2.6 / PERIOD_S))
        # The drives' power stages, and the plant's truth (which applies their torque after its drive latency).
        for series in (silent.applied_nm, silent.plant_nm):
            for j in range(4):
                torque = series[:, j]
                start = int(np.argmax(np.abs(torque) < abs(silent.held_nm[j]) - 1e-9))
                # the RPDO deadline (five periods, in whole ms: 13 ms at 400 Hz) and the plant's latency (two periods)
                assert start * PERIOD_S <= math.ceil(5 * PERIOD_S * 1e3) / 1e3 + 2 * PERIOD_S, (j, start)
                end = int(np.argmax(torque == 0.0))
                ramp_s = (end - start + 1) * PERIOD_S
                assert ramp_s == pytest.approx(RAMP_S, rel=0.03), (j, ramp_s)
                line = silent.held_nm[j] * (1.0 - (np.arange(start, end) - start + 1) * PERIOD_S / ramp_s)
                np.testing.assert_allclose(torque[start:end], line, atol=0.02 * abs(silent.held_nm[j]) + 1e-3)
                assert np.all(torque[end:] == 0.0)
        assert silent.states == [PowerState.SWITCH_ON_DISABLED] * 4
        assert silent.statuswords == [SW_SWITCH_ON_DISABLED] * 4
        # The master is back: the EMCYs it missed are a fault once; its heartbeat and RPDOs end the drives'
        # communication errors (EMCY error reset), and the runtime's enable brings them back.
        with pytest.raises(HalFaultError, match=r"drive 33: EMCY 0x8250"):
            hal.read()
        for _ in range(10):
            with contextlib.suppress(HalFaultError):
                hal.read()
            hal.write(Command.torque_off())
        assert hal.read().drives == (DriveState.DISABLED,) * 4
        assert hal.read().drive_fault_codes == (0, 0, 0, 0)
        hold = holding_torque(hal)
        cycles(hal, hold, int(0.05 / PERIOD_S))
        assert hal.read().drives == (DriveState.ENABLED,) * 4
        np.testing.assert_allclose(hal.applied_motor_torque_nm, hold.motor_torque_nm, atol=0.006)
    frames = read_log(log)
    for node in NODES:
        emcys = [f.data[:2] for f in frames if f.cob_id == 0x080 + node and not f.sent]
        assert emcys[:3] == [b"\x50\x82", b"\x30\x81", b"\x00\x00"]  # RPDO deadline, heartbeat, both over


def test_a_silent_master_with_category_0_the_drives_disable_at_once() -> None:
    with session(None) as hal:
        silent = go_silent(hal, int(0.3 / PERIOD_S))
    for j in range(4):
        off = int(np.argmax(silent.applied_nm[:, j] == 0.0))
        assert off * PERIOD_S <= 0.010  # the RPDO deadline (five periods)
        assert np.all(silent.applied_nm[off:, j] == 0.0)
        assert np.all(silent.applied_nm[:off, j] == pytest.approx(silent.held_nm[j]))  # held until then: no ramp
    assert silent.states == [PowerState.SWITCH_ON_DISABLED] * 4


def test_with_the_ramp_the_arm_sinks_slowly_instead_of_dropping() -> None:
    """The plant's truth over 3 s of a silent master: the peak joint speed with the 2 s ramp against category 0.

    Measured (exo_dummy_arm, resting pose, holding torques -1.12, 2.19, 1.89, 3.56 Nm): the ramp's peak is
    0.49 rad/s (elbow), category 0's 1.80 rad/s.
    """
    with session(RAMP_S) as hal:
        ramped = go_silent(hal, int(3.0 / PERIOD_S)).speed_rad_s.max(axis=0)
    with session(None) as hal:
        dropped = go_silent(hal, int(3.0 / PERIOD_S)).speed_rad_s.max(axis=0)
    assert ramped.max() < 0.6
    assert ramped.max() < 0.35 * dropped.max()
    assert np.all(ramped <= dropped + 1e-9)


def test_the_torque_slope_follows_the_held_torque_on_the_bus(tmp_path: Path) -> None:
    """A higher torque is covered at once, a lower one after it lasted 0.5 s; never more than 10 writes a second."""
    log = tmp_path / "can.log"
    with session(RAMP_S, log) as hal:
        base = holding_torque(hal)
        cycles(hal, base, 500)  # 1 s: settled on the holding torque
        t_double = hal.world.t_s
        cycles(hal, Command(2.0 * base.motor_torque_nm, True), 500)
        t_back = hal.world.t_s
        cycles(hal, base, 500)
        rng = np.random.default_rng(5)
        t_noise = hal.world.t_s
        for _ in range(500):  # a torque that changes every cycle by up to +-30 %
            hal.read()
            hal.write(Command(base.motor_torque_nm * rng.uniform(0.7, 1.3, 4), True))
        t_end = hal.world.t_s
        epoch = hal.bus_report()["traffic_log_epoch_s"]
    assert isinstance(epoch, int)
    frames = read_log(log)
    node = NODES[3]  # the elbow: 3.56 Nm, 356 per mille
    writes = [
        (f.t_s - epoch, struct.unpack_from("<I", f.data, 4)[0])
        for f in frames
        if f.sent and f.cob_id == 0x600 + node and f.data[:4] == b"\x23\x87\x60\x00"
    ]
    held = round(abs(float(base.motor_torque_nm[3])) * 100)  # per mille of 10 Nm, as the RPDO carries it
    doubled = round(abs(float(base.motor_torque_nm[3])) * 200)
    assert writes[0][1] == 2000  # start-up: the peak's
    settled = [(t, v) for t, v in writes if t < t_double]
    assert settled[-1][1] == -(-held // 2)  # ceil(356 / 2 s) = 178 per mille a second
    raised = [(t, v) for t, v in writes if t_double <= t < t_back]
    assert raised[0][0] - t_double <= (2 + BUDGET_DEFER_CYCLES) * PERIOD_S  # at once, or after the heartbeats' cycles
    assert raised[0][1] == -(-doubled // 2)
    lowered = [(t, v) for t, v in writes if t_back <= t < t_noise]
    # once it lasted 0.5 s (and the cycle had room for it)
    assert 0.5 - 3 * PERIOD_S <= lowered[0][0] - t_back <= 0.5 + (3 + BUDGET_DEFER_CYCLES) * PERIOD_S
    assert lowered[0][1] == -(-held // 2)
    noisy = [t for t, _ in writes if t_noise <= t <= t_end]
    assert len(noisy) <= 10 * (t_end - t_noise) + 1  # the bus-load bound: one write per 0.1 s at most
    assert all(b - a >= 0.1 - 1e-6 for a, b in itertools.pairwise(noisy))


# ---------------------------------------------------------------------------- (c) drives without the objects


def eds_without(tmp_path: Path, sections: tuple[str, ...], name: str = "no_slope.eds") -> Path:
    """A copy of the shipped EDS without ``sections`` (their objects do not exist in it)."""
    text = DEFAULT_EDS.read_text()
    for section in sections:
        text, found = re.subn(rf"^\[{section}\]\n(?:(?!\[).*\n)*\n?", "", text, flags=re.MULTILINE)
        assert found == 1, section
    path = tmp_path / name
    path.write_text(text)
    return path


def eds_with_limit(tmp_path: Path, section: str, high: str) -> Path:
    text = DEFAULT_EDS.read_text()
    text, found = re.subn(
        rf"(^\[{section}\]\n(?:(?!\[).*\n)*?)HighLimit=\S+", rf"\1HighLimit={high}", text, flags=re.MULTILINE
    )
    assert found == 1
    path = tmp_path / "slope_limited.eds"
    path.write_text(text)
    return path


def test_an_eds_without_the_torque_slope_gets_category_0_and_says_so(tmp_path: Path) -> None:
    """The master's EDS lacks 0x6087: nothing of the ramp is written, every drive disables at once, the session starts."""
    eds = eds_without(tmp_path, ("6087",))
    log = tmp_path / "can.log"
    with session(RAMP_S, log, eds=str(eds)) as hal:
        assert hal.drive_reaction_report() == tuple(
            f"drive {j} (node 0x{n:02X}): its EDS has no 0x6087 torque slope: it disables at once when it loses "
            "the master (category 0)"
            for j, n in enumerate(NODES, start=1)
        )
        silent = go_silent(hal, int(0.1 / PERIOD_S))
    assert np.all(silent.applied_nm[5:] == 0.0)
    for node in NODES:
        assert [w.hex() for w in sdo_writes(read_log(log), node, REACTION_OBJECTS)] == [
            "2b07600002000000",
            "2b5e600000000000",
        ]


@pytest.mark.parametrize(
    ("drive_eds", "refusal"),
    [
        (lambda tmp: eds_without(tmp, ("6087",)), "0x06020000 object does not exist in the object dictionary"),
        (lambda tmp: eds_with_limit(tmp, "6087", "0x00000064"), "0x06090031 value of parameter written too high"),
    ],
    ids=["no-object", "out-of-range"],
)
def test_a_drive_that_refuses_the_slope_gets_category_0_the_others_ramp(
    tmp_path: Path, drive_eds: object, refusal: str
) -> None:
    """Node 0x23 runs firmware that lacks 0x6087 or takes at most 100 per mille/s: it aborts the write, the
    master configures it for category 0 and says why; the session starts and the other three ramp."""
    path = drive_eds(tmp_path)  # type: ignore[operator]
    with session(RAMP_S, drive_eds={0x23: path}) as hal:
        report = hal.drive_reaction_report()
        assert report[2] == (
            "drive 3 (node 0x23): refused 0x6087 torque slope = 2000 per mille of the rated torque per second "
            f"({refusal}): it disables at once when it loses the master (category 0)"
        )
        assert all("ramps its torque to zero over 2.0 s" in report[j] for j in (0, 1, 3))
        assert hal.drive_set.drives[2].value(0x6007) == 2  # the quick stop was never asked of it
        silent = go_silent(hal, int(0.5 / PERIOD_S))
    assert np.all(silent.applied_nm[5:, 2] == 0.0)  # at once
    for j in (0, 1, 3):
        assert abs(silent.applied_nm[-1, j]) > 0.7 * abs(silent.held_nm[j])  # still ramping


def test_a_drive_that_does_not_answer_fails_the_start_up_in_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """A transport failure is not a capability: no answer to the slope's write is a failed start-up, as ever."""
    on_sdo = SimulatedSeaDrive._on_sdo

    def deaf_to_the_slope(drive: SimulatedSeaDrive, data: bytes, now_s: float) -> None:
        if drive.node_id == 0x23 and data[1:3] == b"\x87\x60":
            return
        on_sdo(drive, data, now_s)

    monkeypatch.setattr(SimulatedSeaDrive, "_on_sdo", deaf_to_the_slope)
    hal = SimulatedCanHal(config())
    hal.set_drive_reaction(DriveReaction(RAMP_S))
    with pytest.raises(HalError) as info:
        hal.open()
    assert str(info.value) == (
        "CAN bus: configuring the drives: node 35 0x6087:0 (torque slope): no SDO response within 500 ms"
    )
    hal.close()


# ---------------------------------------------------------------------------- the drives' own faults


@pytest.mark.parametrize(
    ("kind", "ramps"), [("emcy", True), ("drive_fault", False)], ids=["temperature", "power-stage"]
)
def test_a_fault_the_drive_can_act_on_ramps_a_power_stage_fault_cannot(kind: str, ramps: bool) -> None:
    """0x605E = 1 with the ramp: an excess temperature ramps the torque over the slope; an over current cuts it.

    The operator's acknowledge during the ramp is not lost: the fault reset edge goes out once the
    drive is in FAULT, and it is disabled without a fault after.
    """

    def torque_off_cycles(n: int) -> list[float]:
        applied = []
        for _ in range(n):  # the runtime takes torque off: a drive in its fault reaction does not listen
            with contextlib.suppress(HalFaultError):
                hal.read()
            hal.write(Command.torque_off())
            applied.append(float(hal.applied_motor_torque_nm[3]))
        return applied

    with session(RAMP_S) as hal:
        hold = holding_torque(hal)
        cycles(hal, hold, 750)
        held = hal.applied_motor_torque_nm[3]
        hal.world.inject_fault(kind, 4)
        applied = torque_off_cycles(int(0.5 / PERIOD_S))
        state = hal.drive_set.drives[3].power_state
        hal.request_fault_reset()  # the operator acknowledges while the drive may still ramp
        later = torque_off_cycles(int(2.0 / PERIOD_S))
        after = hal.read()
    if ramps:
        assert applied[-1] == pytest.approx(held * (1.0 - 0.5 / RAMP_S), rel=0.03)
        assert state is PowerState.FAULT_REACTION_ACTIVE
        assert later[0] != 0.0  # the acknowledge did not cut the ramp
    else:
        assert applied == [0.0] * len(applied)
        assert state is PowerState.FAULT
    assert later[-1] == 0.0
    assert after.drives[3] is DriveState.DISABLED
    assert after.drive_fault_codes == (0, 0, 0, 0)


# ---------------------------------------------------------------------------- (d) ss1: the relay's delay


@pytest.mark.parametrize(
    ("wiring", "cut_after_s"),
    [(EstopWiring(wiring="ss1", relay_delay_s=0.2), 0.2), (EstopWiring(), 0.0)],
    ids=["ss1-0.2s", "sto"],
)
def test_a_pressed_button_shows_at_once_and_the_drives_keep_their_power_for_the_relay_s_delay(
    wiring: EstopWiring, cut_after_s: float
) -> None:
    """ss1: statusword bit 14 in the sample of the first SYNC after the press; the drives apply the runtime's
    torque for 0.2 s (the plant's truth), then the relay cuts their power stages. sto: cut at once."""
    with session(None, estop=wiring) as hal:
        hold = holding_torque(hal)
        cycles(hal, hold, 100)
        hal.read()
        hal.world.press_estop(0, True)
        samples, plant, drives = [], [], []
        for _ in range(int(0.3 / PERIOD_S)):  # tick k: its SYNC, the plant's tick, then the sample of that SYNC
            hal.write(hold)
            plant.append(hal.plant.applied_motor_torque_nm.copy())
            drives.append(hal.applied_motor_torque_nm.copy())
            try:
                samples.append(hal.read())
            except HalFaultError:  # an enable the cut power stage cannot follow is reported; the next read is a sample
                samples.append(hal.read())
    assert all(s.estop == (True, False) for s in samples)  # from the first SYNC after the press
    powered = [bool(np.any(p != 0.0)) for p in plant]
    cut = powered.index(False)
    assert cut * PERIOD_S == pytest.approx(cut_after_s, abs=PERIOD_S + 1e-9)
    assert not any(powered[cut:])
    for p, d in zip(plant[:cut], drives[:cut], strict=True):
        np.testing.assert_allclose(p, hold.motor_torque_nm, atol=0.006)  # the runtime's torque, for the delay
        np.testing.assert_allclose(d, p, atol=1e-12)
    assert all(np.all(d == 0.0) for d in drives[cut:])  # the drives' power stages are off with the plant's
    assert all(DriveState.ENABLED not in s.drives for s in samples[cut + 1 :])  # their statusword, a SYNC later
    assert all(s.drives == (DriveState.ENABLED,) * 4 for s in samples[:cut])


# ---------------------------------------------------------------------------- the hardware code path


@pytest.mark.slow
@pytest.mark.realtime
def test_on_the_hardware_code_path_the_drives_are_configured_and_the_slope_follows() -> None:
    """The ``can`` backend's own code (Notifier thread, wall clock) against the simulated drives in their thread:
    the same report, and while the arm is held every drive comes to hold the slope of its torque over 2 s.

    The slope is written by SDO, one node at a time in cycles with room (D161): on wall-clock time, a
    machine that starves the drives' thread delays it (a clean-clone run beside another worker had
    none written after 1.2 s), so the test holds the arm until every slope is written, up to 10 s, and
    checks the values (the pacing's cycle count is checked in lock-step, tests/daror_runtime/test_canopen_hil.py)."""
    # Generous timeouts: a loaded test machine may starve the drives' thread (as in the HAL contract suite).
    rig = CanOnSimulatedDrives(
        node_ids=list(NODES), heartbeat_consumer_ms=5000, sdo_timeout_ms=10_000, boot_timeout_ms=10_000
    )
    rig.set_drive_reaction(DriveReaction(RAMP_S))
    rig.open()
    try:
        assert all("ramps its torque to zero over 2.0 s" in sentence for sentence in rig.drive_reaction_report())
        command = Command(np.array([-1.12, 2.19, 1.89, 3.56]), True)  # about what holds the arm at rest
        sent = [round(abs(float(t)) * 100) for t in command.motor_torque_nm]  # per mille, as the RPDO carries it
        wanted = [-(-p // 2) for p in sent]
        for _ in range(int(10.0 / PERIOD_S)):
            with contextlib.suppress(HalFaultError):
                rig.read()
            rig.write(command)
            if [d.value(obj.TORQUE_SLOPE) for d in rig.drives.drives] == wanted:
                break
        assert [d.value(obj.TORQUE_SLOPE) for d in rig.drives.drives] == wanted
    finally:
        rig.close()
