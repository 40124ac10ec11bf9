"""The simulated HAL backend (hal.sim.backend.SimHal): the Hal contract, the sensor model, the
command path of the drives and the fault hooks, checked against the plant stepped by hand."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest

from hal.config import SimHalConfig
from hal.errors import DescriptionError, HalError, InputError, ShapeError
from hal.interface import Command, DriveState, HalFaultError, Sample, hal_class, open_hal
from hal.robot import N_JOINTS, load_description
from hal.sim.backend import DEFAULT_DRIVE_FAULT_CODE, SimHal
from hal.sim.plant import DynamicPlant
from hal.sim.scenario import Scenario, load_scenario

DESCRIPTION = load_description()
SCENARIO = load_scenario("exo_dummy_arm")
RESOLUTION = DESCRIPTION.sea.encoder_resolution_rad
OFF = Command.torque_off()


def with_drive(scenario: Scenario, **changes: object) -> Scenario:
    assert scenario.drive_train is not None
    return scenario.model_copy(update={"drive_train": scenario.drive_train.model_copy(update=changes)})


def with_sensors(scenario: Scenario, **changes: object) -> Scenario:
    return scenario.model_copy(update={"sensors": scenario.sensors.model_copy(update=changes)})


def opened(scenario: Scenario = SCENARIO, rate_hz: float = 1000.0) -> SimHal:
    hal = SimHal(scenario, rate_hz, DESCRIPTION)
    hal.open()
    return hal


def holding(hal: SimHal) -> np.ndarray:
    """The motor torque that holds the plant where it is (from the truth: tests only)."""
    return hal.plant.holding_torque_nm(hal.truth().q_rad)


def by_hand(scenario: Scenario, applied: Sequence[np.ndarray], external: np.ndarray | None = None) -> DynamicPlant:
    """The plant stepped directly with the torques the drives should have applied, tick by tick."""
    plant = DynamicPlant(scenario, DESCRIPTION)
    for torque in applied:
        plant.step(torque, 1e-3, external)
    return plant


def assert_same_truth(hal: SimHal, plant: DynamicPlant) -> None:
    for got, expected in zip(hal.truth(), plant.truth(), strict=True):
        np.testing.assert_array_equal(got, expected)


# --- the contract ---------------------------------------------------------------------------------


def test_registered_as_the_sim_backend() -> None:
    assert hal_class("sim") is SimHal
    hal = open_hal(SimHalConfig(scenario="exo", rate_hz=500.0))
    assert isinstance(hal, SimHal)
    assert hal.kind == "sim"
    assert hal.rate_hz == 500.0
    assert hal.scenario.name == "exo"


def test_sample_shapes_types_and_immutability() -> None:
    hal = opened()
    sample = hal.read()
    assert isinstance(sample, Sample)
    assert sample.seq == 0
    assert sample.t_s == 0.0
    for array in (sample.q_rad, sample.dq_rad_s, sample.theta_rad, sample.tau_nm):
        assert array.shape == (N_JOINTS,)
        assert array.dtype == np.float64
        assert np.all(np.isfinite(array))
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 1.0
    assert sample.estop == (False, False)
    assert not sample.any_estop
    assert sample.drives == (DriveState.DISABLED,) * N_JOINTS
    assert sample.drive_fault_codes == (0,) * N_JOINTS
    np.testing.assert_array_equal(sample.dq_rad_s, 0.0)


def test_seq_and_time_advance_by_one_tick_per_write() -> None:
    hal = opened(rate_hz=500.0)
    first = hal.read()
    assert hal.read() is first  # one reading per tick
    for n in range(1, 6):
        hal.write(OFF)
        sample = hal.read()
        assert sample.seq == n
        assert sample.t_s == pytest.approx(n / 500.0, abs=1e-15)
        assert hal.time_s == sample.t_s == hal.plant.time_s


def test_readings_are_quantised_noisy_and_centred_on_the_truth() -> None:
    hal = opened()
    readings, truths = [], []
    torque = holding(hal)
    for _ in range(2000):
        hal.write(Command(torque, True))
        sample, truth = hal.read(), hal.truth()
        readings.append([sample.q_rad, sample.theta_rad])
        truths.append([truth.q_rad, truth.theta_rad])
    counts = np.array(readings) / RESOLUTION
    np.testing.assert_allclose(counts, np.rint(counts), rtol=0, atol=1e-6)
    # Noise std 0.5e-4 rad plus quantisation (uniform, 1e-4 / sqrt(12)): 5.8e-5 rad.
    expected = np.hypot(SCENARIO.sensors.encoder_noise_rad, RESOLUTION / np.sqrt(12))
    error = np.array(readings) - np.array(truths)  # (ticks, q/theta, joint)
    assert np.abs(error.mean(axis=0)).max() < 1e-5
    np.testing.assert_allclose(error.std(axis=0), expected, rtol=0.1)


def test_without_noise_and_quantisation_readings_are_the_truth() -> None:
    scenario = with_sensors(SCENARIO, encoder_noise_rad=0.0, quantise=False, direction_error_nm=[0.0] * N_JOINTS)
    hal = opened(scenario)
    for _ in range(20):
        hal.write(OFF)  # falling: everything changes
    sample, truth = hal.read(), hal.truth()
    np.testing.assert_array_equal(sample.q_rad, truth.q_rad)
    np.testing.assert_array_equal(sample.theta_rad, truth.theta_rad)
    k = DESCRIPTION.sea.spring_stiffness_nm_per_rad
    np.testing.assert_allclose(sample.tau_nm, k * (truth.theta_rad - truth.q_rad), rtol=0, atol=1e-12)


def test_velocity_estimate_is_the_low_passed_encoder_difference() -> None:
    scenario = with_sensors(SCENARIO, encoder_noise_rad=0.0, quantise=False, velocity_filter_hz=30.0)
    hal = opened(scenario)
    alpha = 1.0 - np.exp(-2 * np.pi * 30.0 * 1e-3)
    estimate, previous = np.zeros(N_JOINTS), hal.truth().q_rad
    for _ in range(300):
        hal.write(OFF)
        q = hal.truth().q_rad
        estimate = estimate + alpha * ((q - previous) / 1e-3 - estimate)
        previous = q
        np.testing.assert_allclose(hal.read().dq_rad_s, estimate, rtol=1e-9, atol=1e-12)
    assert np.abs(hal.truth().dq_rad_s).max() > 0.1  # it was moving


# --- torque measurement -------------------------------------------------------------------------------


def test_measured_torque_at_rest_is_the_holding_torque() -> None:
    # No command delay: the holding torque acts from the first tick, nothing ever moves.
    hal = opened(with_drive(SCENARIO, command_delay_ticks=0))
    torque = holding(hal)
    measured = []
    for _ in range(1000):
        hal.write(Command(torque, True))
        measured.append(hal.read().tau_nm)
    assert np.abs(hal.truth().dq_rad_s).max() < 1e-9
    # Torque noise per reading: k sqrt(2) 5.8e-5 = 0.024 Nm; the mean of 1000 within 0.003 Nm.
    np.testing.assert_allclose(np.mean(measured, axis=0), torque, rtol=0, atol=0.003)
    assert np.std(measured, axis=0).max() < 0.035


def _move_joint_and_return(hal: SimHal, joint: int, offset_rad: float) -> np.ndarray:
    """Move ``joint`` (1-4) by ``offset_rad`` and back with a motor-side PD on the truth; mean
    measured torque minus the true holding torque over the last 0.5 s at rest."""
    k = DESCRIPTION.sea.spring_stiffness_nm_per_rad
    home = hal.truth().q_rad
    away = home.copy()
    away[joint - 1] += offset_rad

    def hold(target: np.ndarray, start: np.ndarray, ticks: int) -> None:
        for n in range(ticks):
            s = min(n / 800.0, 1.0)  # 0.8 s minimum-jerk move, then hold
            reference = start + (10 * s**3 - 15 * s**4 + 6 * s**5) * (target - start)
            g = hal.plant.holding_torque_nm(reference)
            truth = hal.truth()
            torque = g + 200.0 * (reference + g / k - truth.theta_rad) - 20.0 * truth.dtheta_rad_s
            hal.write(Command(torque, True))

    hold(away, home, 2000)
    hold(home, away, 2500)
    errors = []
    for _ in range(500):
        hold(home, home, 1)
        errors.append(hal.read().tau_nm - hal.plant.holding_torque_nm(hal.truth().q_rad))
    assert np.abs(hal.truth().dq_rad_s).max() < 1e-3
    return np.mean(errors, axis=0)


def test_direction_error_depends_on_how_the_joint_arrived() -> None:
    """Sec. 2.2.2: same pose, measured torque differs by twice the error (0.75 Nm on joint 2)."""
    hal = opened(with_drive(SCENARIO, command_delay_ticks=0))
    error = SCENARIO.sensors.direction_error_nm[1]
    from_above = _move_joint_and_return(hal, 2, +0.15)  # arrives moving down: dir -1
    from_below = _move_joint_and_return(hal, 2, -0.15)  # arrives moving up: dir +1
    assert from_above[1] == pytest.approx(-error, abs=0.01)
    assert from_below[1] == pytest.approx(+error, abs=0.01)
    assert from_below[1] - from_above[1] == pytest.approx(2 * error, abs=0.02)


# --- the command path -----------------------------------------------------------------------------


@pytest.mark.parametrize("delay", [0, 1, 3])
def test_a_torque_step_acts_after_the_command_delay(delay: int) -> None:
    scenario = with_drive(SCENARIO, command_delay_ticks=delay)
    hal = opened(scenario)
    base = holding(hal)
    step = base + np.array([0.0, 3.0, 0.0, -2.0])
    commands = [base] * 5 + [step] * 5
    for torque in commands:
        hal.write(Command(torque, True))
    # Tick n applies the command of tick n - delay; before the first command: no torque.
    applied = [np.zeros(N_JOINTS)] * delay + commands[: len(commands) - delay]
    assert_same_truth(hal, by_hand(scenario, applied))
    other = by_hand(scenario, [np.zeros(N_JOINTS)] * delay + [base] * (len(commands) - delay))
    assert not np.array_equal(hal.truth().dtheta_rad_s, other.truth().dtheta_rad_s)


@pytest.mark.parametrize("delay", [1, 3])
def test_a_disable_acts_at_once_and_discards_queued_commands(delay: int) -> None:
    scenario = with_drive(SCENARIO, command_delay_ticks=delay)
    hal = opened(scenario)
    base = holding(hal)
    for _ in range(6):
        hal.write(Command(base, True))
    assert hal.read().drives == (DriveState.ENABLED,) * N_JOINTS
    hal.write(OFF)
    assert hal.read().drives == (DriveState.DISABLED,) * N_JOINTS
    for _ in range(delay + 2):
        hal.write(Command(base, True))
    zero = np.zeros(N_JOINTS)
    # The disable removes torque in its own tick; the commands queued before it never act; the
    # commands after it act with the delay again.
    applied = [zero] * delay + [base] * (6 - delay) + [zero] + [zero] * delay + [base] * 2
    assert_same_truth(hal, by_hand(scenario, applied))


def test_drive_states_follow_the_commands_that_act() -> None:
    hal = opened()  # delay 1
    torque = holding(hal)
    assert hal.read().drives == (DriveState.DISABLED,) * N_JOINTS
    hal.write(Command(torque, True))
    assert hal.read().drives == (DriveState.DISABLED,) * N_JOINTS  # still on its way
    hal.write(Command(torque, True))
    assert hal.read().drives == (DriveState.ENABLED,) * N_JOINTS


def test_a_disabled_command_is_accepted_whatever_its_torque() -> None:
    hal = opened()
    hal.write(Command(np.array([np.nan, 1.0]), False))  # switching off must always work
    assert hal.read().drives == (DriveState.DISABLED,) * N_JOINTS


def test_bad_enabled_commands_remove_torque_and_raise() -> None:
    scenario = with_drive(SCENARIO, command_delay_ticks=3)
    hal = opened(scenario)
    base = holding(hal)
    for _ in range(4):
        hal.write(Command(base, True))
    with pytest.raises(HalError, match="not finite"):
        hal.write(Command(np.array([0.0, np.inf, 0.0, 0.0]), True))
    assert hal.read().seq == 4  # the tick did not advance
    with pytest.raises(ShapeError):
        hal.write(Command(np.zeros(3), True))
    # The queued commands were discarded: the next ticks apply no torque.
    hal.write(Command(base, True))
    zero = np.zeros(N_JOINTS)
    assert_same_truth(hal, by_hand(scenario, [zero] * 3 + [base] + [zero]))
    assert hal.read().drives == (DriveState.DISABLED,) * N_JOINTS


# --- faults -------------------------------------------------------------------------------------------


def test_nan_fault_spoils_the_next_q_reading_of_one_joint() -> None:
    hal = opened()
    hal.inject_fault("nan", joint=2)
    sample = hal.read()
    assert np.isnan(sample.q_rad[1])
    assert np.all(np.isfinite(np.delete(sample.q_rad, 1)))
    assert np.all(np.isfinite(sample.tau_nm))
    assert np.all(np.isfinite(sample.dq_rad_s))
    hal.write(OFF)
    assert np.all(np.isfinite(hal.read().q_rad))


def test_jump_fault_offsets_the_q_reading_until_cleared() -> None:
    scenario = with_sensors(SCENARIO, encoder_noise_rad=0.0, quantise=False, direction_error_nm=[0.0] * N_JOINTS)
    hal = opened(with_drive(scenario, command_delay_ticks=0))
    torque = holding(hal)
    hal.inject_fault("jump", joint=3, value=0.01)
    hal.write(Command(torque, True))
    sample, truth = hal.read(), hal.truth()
    offset = sample.q_rad - truth.q_rad
    np.testing.assert_allclose(offset, [0.0, 0.0, 0.01, 0.0], atol=1e-12)
    k = DESCRIPTION.sea.spring_stiffness_nm_per_rad
    assert sample.tau_nm[2] - torque[2] == pytest.approx(-k * 0.01, abs=1e-9)  # the drive sees a jump
    assert sample.dq_rad_s[2] > 1.0  # and its velocity estimate spikes
    hal.clear_faults()
    hal.write(Command(torque, True))
    np.testing.assert_allclose(hal.read().q_rad, hal.truth().q_rad, atol=1e-12)


def test_stale_fault_repeats_the_same_sample_object() -> None:
    hal = opened()
    for _ in range(3):
        hal.write(OFF)
    latest = hal.read()
    hal.inject_fault("stale", value=4)
    for _ in range(4):
        hal.write(OFF)
        assert hal.read() is latest
    hal.write(OFF)
    fresh = hal.read()
    assert fresh is not latest
    assert fresh.seq == latest.seq + 5  # the drives kept counting


def test_drive_fault_removes_that_joints_torque_until_cleared() -> None:
    scenario = with_drive(SCENARIO, command_delay_ticks=0)
    hal = opened(scenario)
    torque = holding(hal)
    hal.write(Command(torque, True))
    hal.inject_fault("drive_fault", joint=2)
    sample = hal.read()
    assert sample.drives == (DriveState.ENABLED, DriveState.FAULT, DriveState.ENABLED, DriveState.ENABLED)
    assert sample.drive_fault_codes == (0, DEFAULT_DRIVE_FAULT_CODE, 0, 0)
    for _ in range(5):
        hal.write(Command(torque, True))
        assert hal.read().drives[1] == DriveState.FAULT
    faulted = torque * np.array([1.0, 0.0, 1.0, 1.0])
    assert_same_truth(hal, by_hand(scenario, [torque] + [faulted] * 5))
    hal.clear_faults()
    sample = hal.read()
    assert sample.drives[1] == DriveState.FAULT  # this tick's reading was taken before the reset
    hal.write(OFF)
    assert hal.read().drives == (DriveState.DISABLED,) * N_JOINTS
    assert hal.read().drive_fault_codes == (0,) * N_JOINTS
    hal.write(Command(torque, True))
    assert hal.read().drives == (DriveState.ENABLED,) * N_JOINTS


def test_drive_fault_on_every_joint_with_a_code() -> None:
    hal = opened()
    hal.inject_fault("drive_fault", value=0x2310)
    hal.write(Command(holding(hal), True))
    sample = hal.read()
    assert sample.drives == (DriveState.FAULT,) * N_JOINTS
    assert sample.drive_fault_codes == (0x2310,) * N_JOINTS


def test_bus_fault_raises_on_the_next_read_only() -> None:
    hal = opened()
    hal.inject_fault("bus")
    with pytest.raises(HalFaultError, match="bus"):
        hal.read()
    assert hal.read().seq == 0


@pytest.mark.parametrize(
    ("kind", "joint", "value"),
    [
        ("melt", None, None),
        ("nan", 0, None),
        ("nan", 5, None),
        ("jump", 1, None),
        ("jump", 1, float("nan")),
        ("stale", None, 0),
        ("stale", None, 1.5),
        ("jump", 1, "far"),
        ("drive_fault", 1, 0x1_0000),
        ("drive_fault", 1, True),
    ],
)
def test_invalid_fault_injections_are_refused(kind: str, joint: int | None, value: float | None) -> None:
    hal = opened()
    with pytest.raises(InputError):
        hal.inject_fault(kind, joint=joint, value=value)  # type: ignore[arg-type]


# --- e-stop, the pilot, determinism ---------------------------------------------------------------


def test_estop_inputs_are_reported_and_an_sto_wiring_cuts_the_power_at_once() -> None:
    """The DAROR-01's buttons are wired to the drives' safe torque off (D80): a press is reported and cuts every
    power stage in the same tick, whatever the command; the release gives the power back."""
    hal = opened(with_drive(SCENARIO, command_delay_ticks=0))
    assert hal.description.estop.wiring == "sto"
    torque = holding(hal)
    hal.write(Command(torque, True))
    assert hal.read().drives == (DriveState.ENABLED,) * N_JOINTS
    hal.press_estop(1, True)
    hal.write(Command(torque, True))
    sample = hal.read()
    assert sample.estop == (False, True)
    assert sample.any_estop
    assert hal.power_cut
    assert DriveState.ENABLED not in sample.drives
    np.testing.assert_array_equal(hal.applied_motor_torque_nm, 0.0)
    hal.press_estop(0, True)
    hal.press_estop(1, False)
    hal.write(Command(torque, True))
    assert hal.read().estop == (True, False)
    assert hal.power_cut  # one button still pressed
    hal.press_estop(0, False)
    hal.write(Command(torque, True))
    assert not hal.power_cut
    assert hal.read().drives == (DriveState.ENABLED,) * N_JOINTS
    np.testing.assert_allclose(hal.applied_motor_torque_nm, torque)
    for which in (2, -1, True):
        with pytest.raises(InputError):
            hal.press_estop(which, True)


def test_an_ss1_relay_cuts_the_power_after_its_delay_unless_the_button_is_released() -> None:
    """Safe stop 1: a press is reported at once, the drives keep their power for the relay's delay (the runtime's
    controlled stop), then the relay cuts it whatever the commands; a release before the delay keeps the power."""
    scenario = with_drive(SCENARIO, command_delay_ticks=0)
    description = scenario.description().model_copy(
        update={"estop": scenario.description().estop.model_validate({"wiring": "ss1", "relay_delay_s": 0.05})}
    )
    hal = SimHal(scenario, description=description)
    hal.open()
    torque = holding(hal)
    hal.write(Command(torque, True))
    hal.press_estop(0, True)
    for _ in range(50):  # the ticks that start within 50 ms of the press: inside the delay
        hal.write(Command(torque, True))
        sample = hal.read()
        assert sample.estop == (True, False)
        assert sample.drives == (DriveState.ENABLED,) * N_JOINTS
        np.testing.assert_allclose(hal.applied_motor_torque_nm, torque)
    hal.write(Command(torque, True))  # the tick that starts 50 ms after the press
    assert hal.power_cut
    assert DriveState.ENABLED not in hal.read().drives
    np.testing.assert_array_equal(hal.applied_motor_torque_nm, 0.0)
    hal.press_estop(0, False)
    hal.write(Command(torque, True))
    assert hal.read().drives == (DriveState.ENABLED,) * N_JOINTS
    # a press released before the delay: the relay never opens
    hal.press_estop(1, True)
    for _ in range(20):
        hal.write(Command(torque, True))
    hal.press_estop(1, False)
    for _ in range(60):
        hal.write(Command(torque, True))
        assert not hal.power_cut
    assert hal.read().drives == (DriveState.ENABLED,) * N_JOINTS


def test_external_torque_moves_the_link() -> None:
    scenario = with_drive(SCENARIO, command_delay_ticks=0)
    pushed, still = opened(scenario), opened(scenario)
    torque = holding(pushed)
    push = np.array([0.0, 0.0, 0.0, 2.0])
    pushed.set_external_torque(push)
    for _ in range(200):
        pushed.write(Command(torque, True))
        still.write(Command(torque, True))
    moved = pushed.truth().q_rad - still.truth().q_rad
    assert moved[3] > 0.01
    assert np.abs(still.truth().q_rad - still.plant.initial_q_rad).max() < 1e-9
    assert_same_truth(pushed, by_hand(scenario, [torque] * 200, push))


def test_external_torque_callable_is_called_once_per_tick_with_the_truth() -> None:
    scenario = with_drive(SCENARIO, command_delay_ticks=0)
    hal = opened(scenario)
    calls: list[tuple[float, np.ndarray, np.ndarray]] = []

    def pilot(t_s: float, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        calls.append((t_s, q, dq))
        return np.array([0.5, 0.0, 0.0, 1.0])

    hal.set_external_torque(pilot)
    torque = holding(hal)
    for n in range(50):
        truth = hal.truth()
        hal.write(Command(torque, True))
        t_s, q, dq = calls[-1]
        assert t_s == pytest.approx(n * 1e-3)
        np.testing.assert_array_equal(q, truth.q_rad)
        np.testing.assert_array_equal(dq, truth.dq_rad_s)
    assert len(calls) == 50
    assert_same_truth(hal, by_hand(scenario, [torque] * 50, np.array([0.5, 0.0, 0.0, 1.0])))
    hal.set_external_torque(lambda t, q, dq: np.zeros(3))
    with pytest.raises(ShapeError):
        hal.write(Command(torque, True))
    with pytest.raises(ShapeError):
        hal.set_external_torque(np.zeros(5))
    hal.set_external_torque(None)
    hal.write(Command(torque, True))


def _run(hal: SimHal, ticks: int) -> list[Sample]:
    samples = []
    torque = holding(hal)
    for n in range(ticks):
        samples.append(hal.read())
        hal.write(Command(torque + np.sin(n / 50.0), True))
    return samples


def _assert_same_samples(a: list[Sample], b: list[Sample]) -> None:
    assert [(x.seq, x.t_s, x.estop, x.drives) for x in a] == [(y.seq, y.t_s, y.estop, y.drives) for y in b]
    for field in ("q_rad", "dq_rad_s", "theta_rad", "tau_nm"):
        np.testing.assert_array_equal(
            np.array([getattr(x, field) for x in a]), np.array([getattr(y, field) for y in b])
        )


def test_same_scenario_same_samples_and_a_reopen_replays() -> None:
    first, second = opened(), opened()
    run = _run(first, 5000)  # more than one block of pre-drawn noise
    _assert_same_samples(run, _run(second, 5000))
    first.open()
    _assert_same_samples(run, _run(first, 5000))
    other_seed = opened(SCENARIO.model_copy(update={"seed": SCENARIO.seed + 1}))
    assert not np.array_equal(_run(other_seed, 10)[5].q_rad, run[5].q_rad)


# --- life cycle and refusals ----------------------------------------------------------------------


def test_life_cycle() -> None:
    hal = SimHal(SCENARIO, description=DESCRIPTION)
    with pytest.raises(HalError, match="not open"):
        hal.read()
    with pytest.raises(HalError, match="not open"):
        hal.write(OFF)
    with hal:
        hal.write(Command(holding(hal), True))
        hal.write(Command(holding(hal), True))
        assert hal.read().drives == (DriveState.ENABLED,) * N_JOINTS
    with pytest.raises(HalError, match="not open"):
        hal.read()
    hal.close()  # twice is fine
    hal.open()
    sample = hal.read()
    assert sample.seq == 0
    assert sample.drives == (DriveState.DISABLED,) * N_JOINTS
    np.testing.assert_array_equal(hal.truth().q_rad, np.deg2rad(SCENARIO.initial_q_deg))


def test_unusable_scenarios_and_rates_are_refused() -> None:
    with pytest.raises(DescriptionError, match="drive_train"):
        SimHal(SCENARIO.model_copy(update={"drive_train": None}), description=DESCRIPTION)
    # Coulomb friction smoothed over 1e-5 rad/s is far too stiff for RK4 at 1 kHz.
    with pytest.raises(DescriptionError, match="stable step"):
        SimHal(with_drive(SCENARIO, coulomb_smoothing_rad_s=1e-5), description=DESCRIPTION)
    for rate in (0.0, -1.0, float("inf")):
        with pytest.raises(InputError):
            SimHal(SCENARIO, rate_hz=rate, description=DESCRIPTION)
    with pytest.raises(DescriptionError, match="unknown scenario"):
        SimHal("no_such_scenario")


def test_drive_state_survives_noise_refills() -> None:
    """Regression: refilling the noise block must not touch the drive state stored after it."""
    from hal.sim import dynamics

    hal = opened(SCENARIO)
    substeps = hal._drive_vector[dynamics.S_SUBSTEPS]
    for _ in range(3 * dynamics.NOISE_BLOCK_TICKS + 5):
        hal.write(Command(holding(hal), True))
    assert hal._drive_vector[dynamics.S_SUBSTEPS] == substeps
    assert np.all(np.abs(hal._drive_vector[dynamics.S_DIRECTION : dynamics.S_DIRECTION + 4]) <= 1.0)
