"""``daror can zero`` and ``daror can tare``: what is read (simulated drives), how it is stored in the robot file, and how it is applied.

What is asserted: the zero counts and the tare are the simulated plant's own readings in the drives'
units; a robot that moves is refused (nothing stored); the robot file keeps every byte but each
node's ``calibration:`` (comments, layout), a backup holds the previous file, a refused update
leaves no file behind; the pure functions of hal/canopen/calibration.py give the numbers.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import can
import numpy as np
import pytest

from daror_runtime.cli import main
from daror_runtime.clocks import LockStepClock
from daror_runtime.commissioning.bus_session import BusSession, commissioning_backend
from daror_runtime.commissioning.calibration import CalibrationLimits, measure_still, spread_problems, utc_now
from daror_runtime.commissioning.robot_file import check_storable, read_calibrations, store_calibrations
from hal.canopen.calibration import Calibration, angle_rad, spring_torque_nm
from hal.canopen.cia402.statemachine import PowerState
from hal.config import hal_config
from hal.errors import HalConfigError

_CHANNELS = itertools.count(1)
COUNT_RAD = 2 * math.pi / 65536

ROBOT = """\
# The lab's robot (a comment the operator wrote)
backend: can
interface: socketcan
channel: can0
nodes:
  - joint: 1
    node_id: 1
    eds: drives/daror_sea.eds     # the shipped EDS
    motor_position: {index: 0x6064, counts_per_rev: 65536}
    link_position: {index: 0x2010, counts_per_rev: 65536}
    sdo_init: []
  - joint: 2
    node_id: 2
    eds: drives/daror_sea.eds
    calibration:                  # an earlier zero
      motor_zero_counts: 100
      link_zero_counts: -200
      zeroed_utc: '2026-01-01T00:00:00Z'
    spring_torque: {index: 0x6077}
  - node_id: 3                    # node_id first
    joint: 3
    eds: drives/daror_sea.eds
  - {joint: 4, node_id: 4, eds: drives/daror_sea.eds}
"""


class Recorder(BusSession):
    """Records, per tick, the plant's joint angles and spring torques next to the raw counts the master holds."""

    def __init__(self, hal: object, clock: object) -> None:
        super().__init__(hal, clock)  # type: ignore[arg-type]
        self.truth: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.window_end = 0  # the ticks recorded when the close began: the reading window ends there

    def disable_all(self):  # type: ignore[no-untyped-def]
        self.window_end = len(self.truth)
        return super().disable_all()

    def tick(self, command):  # type: ignore[no-untyped-def]
        sample = super().tick(command)
        world = self.hal.plant.read_without_faults()  # type: ignore[attr-defined]
        self.truth.append((world.q_rad.copy(), world.theta_rad.copy(), world.tau_nm.copy()))
        return sample


def _session(cls: type[BusSession] = BusSession) -> BusSession:
    hal = commissioning_backend(hal_config("can-sim"), 2.0)
    return cls(hal, LockStepClock(1.0 / hal.rate_hz))  # type: ignore[arg-type]


# --- what is read -----------------------------------------------------------------------------------


def test_zero_counts_and_tare_are_the_plants_readings_in_the_drives_units() -> None:
    session = _session(Recorder)
    limits = CalibrationLimits(window_s=0.1)
    readings, problems = measure_still(session, limits)
    assert problems == []
    assert spread_problems(readings, "zero", limits) == []
    assert spread_problems(readings, "tare", limits) == []
    assert [(r.joint, r.node_id) for r in readings] == [(1, 1), (2, 2), (3, 3), (4, 4)]
    n = round(limits.window_s * session.hal.rate_hz)  # the window's SYNCs: 40 at 400 Hz
    window = session.truth[session.window_end - n : session.window_end]  # the last ticks before the close
    for r in readings:
        j = r.joint - 1
        assert r.link_counts.n == n
        q = np.mean([t[0][j] for t in window])
        assert r.link_counts.mean == pytest.approx(q / COUNT_RAD, abs=3.0)  # counts: the plant's angle
        assert r.motor_counts.mean == pytest.approx(np.mean([t[1][j] for t in window]) / COUNT_RAD, abs=3.0)
        assert r.spring_nm.mean == pytest.approx(np.mean([t[2][j] for t in window]), abs=0.02)
    drives = session.hal.drive_set.drives  # type: ignore[attr-defined]
    assert [d.power_state for d in drives] == [PowerState.SWITCH_ON_DISABLED] * 4
    assert not [e for e in session.hal.world.drive_events() if e[2] == "power stage on"]  # type: ignore[attr-defined]


def test_a_robot_that_moves_is_not_zeroed() -> None:
    session = _session()
    readings, problems = measure_still(session, CalibrationLimits(rest_timeout_s=0.05))  # the arm still falling
    assert readings == []
    assert len(problems) == 1
    assert problems[0].startswith("the robot moves: a joint at ")


def test_unsteady_readings_are_refused() -> None:
    session = _session()
    limits = CalibrationLimits(window_s=0.1)
    readings, _ = measure_still(session, limits)
    strict = CalibrationLimits(max_spread_counts=0.0, max_spread_nm=0.0)
    assert len(spread_problems(readings, "zero", strict)) >= 4  # some encoder of every joint spreads a count
    assert len(spread_problems(readings, "tare", strict)) == 4
    assert "the spring torque spreads" in spread_problems(readings, "tare", strict)[0]


# --- the robot file -------------------------------------------------------------------------------------


def test_the_calibration_is_written_into_each_node_keeping_every_other_line(tmp_path: Path) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(ROBOT)
    backup = store_calibrations(
        robot,
        {1: {"motor_zero_counts": 12, "link_zero_counts": -3, "zeroed_utc": "2026-11-28T09:00:00Z"},
         2: {"torque_tare_nm": 0.125, "tared_utc": "2026-11-28T09:05:00Z"},
         3: {"torque_tare_nm": -0.5, "tared_utc": "2026-11-28T09:05:00Z"}},
        stamp="20261128T090500Z",
    )  # fmt: skip
    assert backup == tmp_path / "robot.yaml.20261128T090500Z.bak"
    assert backup.read_text() == ROBOT
    new = robot.read_text()
    assert read_calibrations(robot) == {
        1: {"motor_zero_counts": 12, "link_zero_counts": -3, "zeroed_utc": "2026-11-28T09:00:00Z"},
        2: {"motor_zero_counts": 100, "link_zero_counts": -200, "zeroed_utc": "2026-01-01T00:00:00Z",
            "torque_tare_nm": 0.125, "tared_utc": "2026-11-28T09:05:00Z"},  # the earlier zero kept
        3: {"torque_tare_nm": -0.5, "tared_utc": "2026-11-28T09:05:00Z"},
        4: {},
    }  # fmt: skip
    old_block = ROBOT.splitlines()[14:18]  # node 2's calibration: replaced
    assert old_block[0].startswith("    calibration:")
    assert old_block[-1].startswith("      zeroed_utc")
    kept = [line for line in ROBOT.splitlines() if line not in old_block]
    assert [line for line in new.splitlines() if line in kept] == kept  # every other line, in its order
    assert "# The lab's robot (a comment the operator wrote)" in new
    assert "# node_id first" in new
    assert new.index("    sdo_init: []\n    calibration:") > 0  # after node 1's last line, at its indentation
    assert "      motor_zero_counts: 12\n" in new


def test_a_second_store_keeps_the_other_keys_and_a_second_backup(tmp_path: Path) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(ROBOT)
    store_calibrations(robot, {1: {"torque_tare_nm": 0.5, "tared_utc": "t1"}}, stamp="S")
    first = robot.read_text()
    backup = store_calibrations(robot, {1: {"motor_zero_counts": 7, "zeroed_utc": "t2"}}, stamp="S")
    assert backup == tmp_path / "robot.yaml.S.2.bak"
    assert backup.read_text() == first
    assert read_calibrations(robot)[1] == {"motor_zero_counts": 7, "zeroed_utc": "t2", "torque_tare_nm": 0.5,
                                           "tared_utc": "t1"}  # fmt: skip


def test_a_flow_mapping_node_is_refused_and_nothing_is_written(tmp_path: Path) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(ROBOT)
    with pytest.raises(HalConfigError, match=r"line 23: node 4 is written as a flow mapping"):
        store_calibrations(robot, {4: {"torque_tare_nm": 0.1}})
    assert robot.read_text() == ROBOT
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot.yaml"]


def test_a_refused_verification_leaves_the_file_and_no_other(tmp_path: Path) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(ROBOT)

    def refuse(path: Path) -> None:
        raise HalConfigError(f"{path}: refused")

    with pytest.raises(HalConfigError, match="refused"):
        store_calibrations(robot, {1: {"torque_tare_nm": 0.1}}, verify=refuse)
    assert robot.read_text() == ROBOT
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot.yaml"]


def test_a_file_that_could_not_hold_a_calibration_is_refused_before_anything_is_measured(tmp_path: Path) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(ROBOT)
    seen: list[str] = []

    def loads(path: Path) -> None:
        seen.append(path.read_text())

    check_storable(robot, [1, 2, 3], verify=loads)  # storable: the trial file had every node's calibration
    assert seen[0].count("calibration:") == 3
    assert robot.read_text() == ROBOT
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot.yaml"]

    def refuse(path: Path) -> None:
        raise HalConfigError(f"{path}: line 12, field nodes.0.calibration: Extra inputs are not permitted")

    with pytest.raises(HalConfigError) as caught:
        check_storable(robot, [1], verify=refuse)
    assert str(caught.value) == (
        f"{robot}: with a calibration: per node the file would not load; nothing was written "
        f"({robot}: line 12, field nodes.0.calibration: Extra inputs are not permitted)"
    )  # the file named, not the temporary one
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot.yaml"]


def test_unknown_nodes_and_the_short_form_are_one_line(tmp_path: Path) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(ROBOT)
    with pytest.raises(HalConfigError, match=r"no node with node_id \[9\] in nodes:; expected one of \[1, 2, 3, 4\]"):
        store_calibrations(robot, {9: {"torque_tare_nm": 0.1}})
    short = tmp_path / "short.yaml"
    short.write_text("backend: can\nnode_ids: [1, 2, 3, 4]\n")
    with pytest.raises(HalConfigError, match=r"short.yaml: no nodes: list; calibration is stored per node"):
        read_calibrations(short)


def test_utc_now_is_iso_8601_to_the_second() -> None:
    stamp = utc_now()
    assert len(stamp) == 20
    assert stamp[10] == "T"
    assert stamp.endswith("Z")


# --- the commands' refusals ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["zero"], "confirm that the robot is in its zero pose"),
        (["tare"], "confirm that the arm is unloaded"),
        (["zero", "--at-zero-pose"], "no nodes: list; calibration is stored per node"),
        (["tare", "--arm-unloaded", "--clock", "lockstep"], "no nodes: list"),
    ],
)
def test_zero_and_tare_refusals_send_nothing(
    tmp_path: Path, argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    channel = f"zero-hw-{next(_CHANNELS)}"
    robot = tmp_path / "robot.yaml"
    robot.write_text(f"backend: can\ninterface: virtual\nchannel: {channel}\n")
    sniffer = can.Bus(interface="virtual", channel=channel)
    try:
        assert main(["can", *argv[:1], "--hal-config", str(robot), *argv[1:]]) == 2
        assert sniffer.recv(timeout=0.05) is None
    finally:
        sniffer.shutdown()
    err = capsys.readouterr().err
    assert err.startswith(f"daror can {argv[0]}: error: ")
    assert message in err
    assert err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot.yaml"]


# --- applied to the readings (hal/canopen/calibration.py) -----------------------------------------------


def test_the_calibration_moves_the_angles_and_the_torque() -> None:
    c = Calibration(motor_zero_counts=1000, link_zero_counts=-16384, torque_tare_nm=0.25)
    assert angle_rad(1000.0, c.motor_zero_counts, COUNT_RAD) == 0.0
    assert angle_rad(0.0, c.link_zero_counts, COUNT_RAD) == pytest.approx(math.pi / 2)
    counts = np.array([1000.0, 17384.0])
    assert angle_rad(counts, c.motor_zero_counts, COUNT_RAD) == pytest.approx([0.0, math.pi / 2])
    assert spring_torque_nm(1.0, c.torque_tare_nm) == 0.75
    assert spring_torque_nm(np.array([0.25, -0.75]), np.array([0.25, -0.25])) == pytest.approx([0.0, -0.5])
    with pytest.raises(ValueError, match="torque_tare_nm = nan"):
        Calibration(torque_tare_nm=float("nan"))


def _sim_robot_file(tmp_path: Path) -> Path:
    """A can-sim robot file of four DAROR drives in the per-node form, with the operator's comments."""
    from hal.canopen.dictionary import DEFAULT_EDS

    node = """\
  - joint: {j}                     # joint {j}
    node_id: {j}
    eds: {eds}
    motor_position: {{index: 0x6064, counts_per_rev: 65536}}
    link_position: {{index: 0x2010, counts_per_rev: 65536, resolution_index: 0x2011}}
    spring_torque: {{index: 0x6077}}
    estop: {{index: 0x6041, operator_bit: 14, pilot_bit: 15}}
"""
    robot = tmp_path / "robot.yaml"
    robot.write_text("# the simulated robot\nbackend: can-sim\nnodes:\n" + "".join(
        node.format(j=j, eds=DEFAULT_EDS) for j in range(1, 5)))  # fmt: skip
    return robot


def test_daror_can_zero_and_tare_store_what_the_drives_read(tmp_path: Path) -> None:
    robot = _sim_robot_file(tmp_path)
    before = robot.read_text()
    assert main(["can", "zero", "--hal-config", str(robot), "--at-zero-pose"]) == 0
    assert main(["can", "tare", "--hal-config", str(robot), "--arm-unloaded"]) == 0
    readings, _ = measure_still(_session(), CalibrationLimits())  # the same deterministic simulation, read again
    stored = read_calibrations(robot)
    for r in readings:
        assert stored[r.node_id]["motor_zero_counts"] == round(r.motor_counts.mean)
        assert stored[r.node_id]["link_zero_counts"] == round(r.link_counts.mean)
        assert stored[r.node_id]["torque_tare_nm"] == pytest.approx(r.spring_nm.mean, abs=1e-4)
    assert all(line in robot.read_text().splitlines() for line in before.splitlines())  # comments kept
    assert len(list(tmp_path.glob("robot.yaml.*.bak"))) == 2
