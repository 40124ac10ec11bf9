"""The robot file (issue 25): drives described by their own EDS, resolved into profiles, and a start-up real drives survive.

What is tested here, on the simulated bus (lock-step, :class:`hal.canopen.backend.SimulatedCanHal`):

* the short form resolves to exactly the shipped DAROR-01 file's profiles, and their derived PDOs
  are the DAROR mapping;
* the maxon EPOS4 file (its vendor's EDS) derives its PDOs from what the node sends (the e-stops'
  0x60FD only on the node that reads them), fits the bus's worst cycle only at 400 Hz (500 Hz is
  refused with the numbers), and its drives get the cycle in 0x60C2 (their EDS has no 0x1006), the
  robot file's sdo_init, cyclic synchronous torque, and joint 1's reports the e-stops on 0x60FD;
* start-up refuses in one line: a drive without a torque mode (naming the modes its 0x6502 has),
  units other than the robot file's, another identity; a robot file's mistakes are one line too.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.hil import hil_config
from hal.canopen import objects as obj
from hal.canopen.backend import SimulatedCanHal
from hal.canopen.mapping import DAROR_MAPPING
from hal.canopen.profile import decode_supported_modes, resolve_profiles
from hal.config import CanSimHalConfig, hal_config, load_hal_config
from hal.errors import HalConfigError, HalError
from hal.interface import Command, DriveReaction, DriveState

ROOT = Path(__file__).resolve().parents[3]
DAROR01 = ROOT / "examples" / "robot" / "daror01.yaml"
EPOS4 = ROOT / "examples" / "robot" / "epos4.yaml"
NO_TORQUE_MODE_EDS = ROOT / "tests" / "data" / "no_torque_mode.eds"
DAROR_EDS = ROOT / "hal" / "canopen" / "daror_sea.eds"
K_NM_PER_RAD = 289.0


def _sim_config(robot_file: Path) -> CanSimHalConfig:
    return hil_config(robot_file, None, None, Path("unused.log.gz")).model_copy(update={"traffic_log": None})


def _daror_node(number: int, **changes: str) -> str:
    fields = {
        "joint": str(number),
        "node_id": str(number),
        "eds": str(DAROR_EDS),
        "rated_torque_mnm": "10000",
        "motor_position": "{index: 0x6064, counts_per_rev: 65536}",
        "link_position": "{index: 0x2010, counts_per_rev: 65536, resolution_index: 0x2011}",
        "spring_torque": "{index: 0x6077}",
        "estop": "{index: 0x6041, operator_bit: 14, pilot_bit: 15}",
        "enable_timeout_ms": "20",
    }
    fields.update(changes)
    return "  - " + "\n    ".join(f"{k}: {v}" for k, v in fields.items())


def _robot_file(tmp_path: Path, changes: dict[int, dict[str, str]] | None = None, head: str = "") -> Path:
    nodes = "\n".join(_daror_node(j, **(changes or {}).get(j, {})) for j in range(1, 5))
    path = tmp_path / "robot.yaml"
    path.write_text(f"backend: can-sim\n{head}nodes:\n{nodes}\n", encoding="utf-8")
    return path


def _open(config: CanSimHalConfig) -> SimulatedCanHal:
    hal = SimulatedCanHal(config)
    hal.open()
    return hal


# --------------------------------------------------------------------------- profiles and PDOs


def test_the_short_form_is_the_daror01_file() -> None:
    short = resolve_profiles(hal_config("can"), K_NM_PER_RAD)
    assert short == resolve_profiles(load_hal_config(DAROR01), K_NM_PER_RAD)
    assert [p.pdos for p in short] == [DAROR_MAPPING] * 4
    assert [p.enable_timeout_s for p in short] == [0.02] * 4
    assert [(p.estop_operator_mask, p.estop_pilot_mask) for p in short] == [(1 << 14, 1 << 15)] * 4


def test_the_epos4_pdos_are_derived_from_what_the_node_sends() -> None:
    profiles = resolve_profiles(load_hal_config(EPOS4), K_NM_PER_RAD)
    pdos = profiles[0].pdos
    assert [(m.index, m.sub, m.bits) for m in pdos.rpdo.objects] == [(0x6040, 0, 16), (0x6071, 0, 16)]
    assert [[(m.index, m.sub, m.bits) for m in t.objects] for t in pdos.tpdos] == [
        [(0x6041, 0, 16), (0x6064, 0, 32)],
        [(0x60E4, 2, 32), (0x60FD, 0, 32)],
    ]
    # the other joints' drives read no e-stop: their TPDO2 is the link encoder alone
    for profile in profiles[1:]:
        assert [[(m.index, m.sub) for m in t.objects] for t in profile.pdos.tpdos] == [
            [(0x6041, 0), (0x6064, 0)],
            [(0x60E4, 2)],
        ]
    assert profiles[0].torque is None
    assert profiles[0].spring_k_nm_per_rad == K_NM_PER_RAD
    assert profiles[0].nm_per_permille == pytest.approx(0.160 * 100 / 1000)


def test_a_rate_over_the_bus_budget_is_refused_with_the_numbers() -> None:
    config = _sim_config(EPOS4).model_copy(update={"rate_hz": 500.0})
    with pytest.raises(HalConfigError) as info:
        SimulatedCanHal(config)
    message = str(info.value)
    # SYNC 55 + 4 RPDOs of 4 B (95) + 4 TPDO1 of 6 B (115) + 3 TPDO2 of 4 B (95) + 1 of 8 B (135) = 1315 bits,
    # + 5 heartbeats (65) in one cycle = 1640 bits: 82.0 % of 2000 at 500 Hz; 0.7 x 1e6 / 1640 = 426.8 Hz
    assert "worst cycle would be 82.0 % loaded" in message, message
    assert "1315 worst-case bits" in message, message
    assert "expected rate_hz at most 426 Hz" in message, message
    assert SimulatedCanHal(_sim_config(EPOS4)).rate_hz == 400.0  # the default: the highest that fits


def test_supported_modes_decode_as_cia_402_names() -> None:
    assert decode_supported_modes(0x1A5) == ["pp", "pv", "hm", "csp", "csv"]
    assert decode_supported_modes(0x208) == ["tq", "cst"]


# --------------------------------------------------------------------------- start-up


def test_a_drive_without_a_torque_mode_is_refused_in_one_line_naming_its_modes(tmp_path: Path) -> None:
    path = _robot_file(tmp_path, {3: {"eds": str(NO_TORQUE_MODE_EDS)}})
    hal = SimulatedCanHal(load_hal_config(path))  # type: ignore[arg-type]
    with pytest.raises(HalError) as info:
        hal.open()
    assert str(info.value) == (
        "CAN bus: node 3 (joint 3): its 0x6502 supported drive modes are pp, pv, hm, csp, csv: "
        "no cst (cyclic synchronous torque) or tq (profile torque)"
    )
    assert hal.drive_set.drives[2].value(obj.MODES_OF_OPERATION) != obj.MODE_CYCLIC_SYNCHRONOUS_TORQUE


def test_units_other_than_the_robot_files_are_refused_naming_both(tmp_path: Path) -> None:
    path = _robot_file(tmp_path, {2: {"rated_torque_mnm": "12000"}})
    with pytest.raises(HalError) as info:
        _open(load_hal_config(path))  # type: ignore[arg-type]
    assert str(info.value) == (
        "CAN bus: node 2 (joint 2): reports 0x6076 motor rated torque (mNm) 10000, its robot file says 12000: "
        "torques and angles would be converted wrong"
    )


def test_another_identity_is_refused(tmp_path: Path) -> None:
    path = _robot_file(tmp_path, {4: {"identity": "{vendor_id: 0x1A3}"}})
    with pytest.raises(
        HalError, match=re.escape("CAN bus: node 4 (joint 4): 0x1018 vendor id is 0x0; its robot file expects 0x1A3")
    ):
        _open(load_hal_config(path))  # type: ignore[arg-type]


def test_the_epos4_drives_get_the_cycle_the_mode_and_the_sdo_init_and_report_the_estops() -> None:
    hal = _open(_sim_config(EPOS4))
    try:
        drive = hal.drive_set.drives[0]
        with pytest.raises(KeyError):  # this EDS has no 0x1006 (the master writes it only where the EDS has it)
            drive.value(obj.COMMUNICATION_CYCLE_PERIOD)
        assert (drive.value(obj.INTERPOLATION_TIME_PERIOD, 1), drive.value(obj.INTERPOLATION_TIME_PERIOD, 2)) == (
            25,
            -4,
        )
        assert drive.value(obj.MODES_OF_OPERATION_DISPLAY) == obj.MODE_CYCLIC_SYNCHRONOUS_TORQUE
        assert drive.value(obj.MOTOR_RATED_TORQUE) == 160
        assert (
            drive.value(obj.DISABLE_OPERATION_OPTION_CODE) == 0
        )  # its EDS's default is 1 (a ramp): the runtime's at once
        assert drive.value(obj.DIGITAL_INPUTS) == 0b11 << 16  # normally closed, nothing pressed
        for _ in range(10):
            sample = hal.read()
            hal.write(Command(np.array([0.8, 0.0, 0.0, 0.0]), True))
        assert sample.drives == (DriveState.ENABLED,) * 4
        assert drive.value(obj.TARGET_TORQUE) == 50  # 0.8 Nm at 0.016 Nm per mille (160 mNm x 100)
        assert hal.applied_motor_torque_nm[0] == pytest.approx(0.8)
        hal.world.press_estop(1, True)
        hal.write(Command(np.zeros(4), False))
        hal.write(Command(np.zeros(4), False))
        assert drive.value(obj.DIGITAL_INPUTS) == 0b01 << 16  # the pilot's bit cleared
        assert hal.read().estop == (False, True)
    finally:
        hal.close()


# --------------------------------------------------------------------------- the robot file's mistakes


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        (
            {2: {"link_position": "{index: 0x60E4, subindex: 1, counts_per_rev: 65536}"}},
            "node 2 (joint 2): link_position 0x60E4:1 is not in its EDS",
        ),
        (
            {1: {"sdo_init": "[{index: 0x6007, value: 2}]"}},
            "node 1 (joint 1): sdo_init writes 0x6007:0, the drive's reaction to losing the master",
        ),
        (
            {3: {"estop": "{index: 0x6041, operator_bit: 14, pilot_bit: 16}"}},
            "estop bit 16 of 0x6041:0, which has 16 bits",
        ),
    ],
)
def test_a_node_the_eds_cannot_serve_is_refused_in_one_line(
    tmp_path: Path, changes: dict[int, dict[str, str]], expected: str
) -> None:
    with pytest.raises(HalConfigError) as info:
        SimulatedCanHal(load_hal_config(_robot_file(tmp_path, changes)))  # type: ignore[arg-type]
    assert expected in str(info.value)
    assert "\n" not in str(info.value)


def test_a_robot_file_with_a_joint_twice_is_refused_naming_file_line_and_field(tmp_path: Path) -> None:
    path = _robot_file(tmp_path, {4: {"joint": "3"}})
    with pytest.raises(HalConfigError) as info:
        load_hal_config(path)
    assert str(info.value).startswith(f"{path}: line 3, field nodes: ")
    assert "expected each of joints 1-4 once" in str(info.value)


# --------------------------------------------------------------------------- commissioning's calibration


def _readings(config: CanSimHalConfig, ticks: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    hal = _open(config)
    try:
        for _ in range(ticks):
            sample = hal.read()
            hal.write(Command(np.zeros(4), False))
        return sample.q_rad.copy(), sample.theta_rad.copy(), sample.tau_nm.copy()
    finally:
        hal.close()


def test_the_stored_zeros_and_tare_are_applied_to_every_reading(tmp_path: Path) -> None:
    """A node's calibration (daror can zero / tare) shifts its readings by exactly the stored counts and torque."""
    plain = _readings(load_hal_config(_robot_file(tmp_path)))  # type: ignore[arg-type]
    calibration = (
        "{motor_zero_counts: 1200, link_zero_counts: -300, torque_tare_nm: 0.25, zeroed_utc: '2026-11-28T09:30:00Z'}"
    )
    (tmp_path / "c").mkdir()
    path = _robot_file(tmp_path / "c", {2: {"calibration": calibration}})
    calibrated = _readings(load_hal_config(path))  # type: ignore[arg-type]
    rad_per_count = 2 * np.pi / 65536
    q, theta, tau = (c - p for c, p in zip(calibrated, plain, strict=True))
    assert q == pytest.approx([0.0, 300 * rad_per_count, 0.0, 0.0], abs=1e-12)
    assert theta == pytest.approx([0.0, -1200 * rad_per_count, 0.0, 0.0], abs=1e-12)
    assert tau == pytest.approx([0.0, -0.25, 0.0, 0.0], abs=1e-12)
    assert np.array_equal(np.delete(calibrated[0], 1), np.delete(plain[0], 1))  # the others bit for bit


def test_a_calibration_of_the_wrong_type_is_one_line(tmp_path: Path) -> None:
    path = _robot_file(tmp_path, {3: {"calibration": "{link_zero_counts: 1.5}"}})
    with pytest.raises(HalConfigError) as info:
        load_hal_config(path)
    message = str(info.value)
    assert "\n" not in message
    assert "calibration.link_zero_counts" in message, message


def _eds_with_disable_operation(tmp_path: Path) -> Path:
    """The DAROR SEA drive's EDS with a writable 0x605C disable operation option code (its own has none)."""
    text = DAROR_EDS.read_text(encoding="utf-8")
    text = text.replace(
        "[OptionalObjects]\nSupportedObjects=27\n", "[OptionalObjects]\nSupportedObjects=28\n28=0x605C\n"
    )
    text += "\n[605C]\nParameterName=Disable operation option code\nObjectType=0x7\nDataType=0x0003\nAccessType=rw\n"
    text += "DefaultValue=1\nLowLimit=0x0000\nHighLimit=0x0001\nPDOMapping=0\n"
    path = tmp_path / "daror_sea_605c.eds"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize(("ramp_s", "expected"), [(None, 0), (2.0, 1)])
def test_a_disabled_operation_ends_as_the_runtime_declared_its_reaction(
    tmp_path: Path, ramp_s: float | None, expected: int
) -> None:
    """0x605C follows the declared reaction: 0 (at once) for category 0, 1 (the slow-down ramp, 0x6087) for a ramp."""
    eds = _eds_with_disable_operation(tmp_path)
    path = _robot_file(tmp_path, {j: {"eds": str(eds)} for j in range(1, 5)})
    hal = SimulatedCanHal(load_hal_config(path))  # type: ignore[arg-type]
    hal.set_drive_reaction(DriveReaction(ramp_s))
    hal.open()
    try:
        for drive in hal.drive_set.drives:
            assert drive.value(obj.DISABLE_OPERATION_OPTION_CODE) == expected  # the EDS's default is 1
            assert drive.value(obj.ABORT_CONNECTION_OPTION_CODE) == (
                obj.ABORT_QUICK_STOP if ramp_s else obj.ABORT_DISABLE_VOLTAGE
            )
    finally:
        hal.close()
