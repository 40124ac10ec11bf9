"""The tick's compiled kernels called through resolved entry points (issue 11), and what makes that safe.

An entry point (``hal.kernels.entry_point``) checks no argument types: each call site passes only
arrays of the types it was resolved for, or goes through numba's dispatcher. These tests spy on
every entry point the tick calls and check each argument against the signature
(``hal.kernels.misfits``), check the types that carry the guarantee (``CheckedSample``,
``CheckedCommand``), and check that the fast paths give exactly what the dispatcher paths give.
"""

from __future__ import annotations

import copy
import pickle
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.signal

from daror_runtime.clocks import LockStepClock
from daror_runtime.control.motor_position import TABLE_SIGNATURE, MotorPositionPD
from daror_runtime.control.position import LinkBounds
from daror_runtime.data import lowpass
from daror_runtime.data.recorder import Recorder
from daror_runtime.data.recording_reader import read_recording
from daror_runtime.data.schema import RawLog
from daror_runtime.data.stationary import ReductionSettings, _norm_below, filtered_velocity
from daror_runtime.data.tick_row import N_RECORD_COLUMNS, RECORD_COLUMNS
from daror_runtime.errors import ShapeError as RuntimeShapeError
from daror_runtime.identification.trajectory_planning import build_trajectory, prepend_approach
from daror_runtime.identification.waypoints import load_waypoints
from daror_runtime.loop import FILL_SIGNATURE, ControlLoop, FixedSupervisor
from daror_runtime.models.linear import APModel
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import IN_BOUNDS_SIGNATURE, STATUS_SIGNATURE, SafetyMonitor
from hal.errors import ShapeError
from hal.interface import TORQUE_OFF, CheckedCommand, CheckedSample, Command, DriveState, Sample
from hal.kernels import SAMPLE_VECTOR, misfits
from hal.sim import dynamics
from hal.sim.backend import SimHal

REPO = Path(__file__).resolve().parents[2]


class Spy:
    """Stands in for an entry point: records every call's arguments, then calls it."""

    def __init__(self, entry: Callable[..., Any]) -> None:
        self.entry = entry
        self.calls: list[tuple[object, ...]] = []

    def __call__(self, *args: object) -> Any:
        self.calls.append(args)
        return self.entry(*args)


def assert_all_fit(signature: tuple[Any, ...], spy: Spy) -> None:
    assert spy.calls, "the entry point was never called"
    for args in spy.calls:
        assert misfits(signature, args) == []


def identification_loop(tmp_path: Path, ticks_before: int = 0) -> tuple[SimHal, ControlLoop, MotorPositionPD]:
    """The loop ``daror identify`` runs: SimHal, monitor, motor position PD on the training table, recorder."""
    hal = SimHal("exo_dummy_arm")
    hal.open()
    first = hal.read()
    trajectory = prepend_approach(build_trajectory(load_waypoints(), "training"), first.q_rad, 2.0, 0.5)
    feedforward = APModel.from_description(hal.description, dummy_arm=True, elbow_stiffness=True)
    controller = MotorPositionPD(
        hal.description, trajectory, LinkBounds.from_description(hal.description), feedforward=feedforward
    )
    controller.reset(first)
    recorder = Recorder(tmp_path / "run.rec", RECORD_COLUMNS)
    recorder.start()
    monitor = SafetyMonitor(SafetyLimits.from_description(hal.description))
    loop = ControlLoop(hal, monitor, FixedSupervisor(controller), LockStepClock(1e-3), recorder)
    return hal, loop, controller


# --- the types that carry the guarantee ----------------------------------------------------------


def _sample(q: object) -> tuple[object, ...]:
    z = np.zeros(4)
    return (1, 0.001, q, z, z, z, (False, False), (DriveState.ENABLED,) * 4)


@pytest.mark.parametrize(
    "bad", [np.zeros(3), np.zeros(4, dtype=np.int64), np.zeros((4, 1)), [0.0] * 4, np.zeros(4, dtype=np.float32)]
)
def test_a_checked_sample_or_command_refuses_arrays_of_another_type(bad: object) -> None:
    with pytest.raises(ShapeError, match="float64"):
        CheckedSample(*_sample(bad))
    with pytest.raises(ShapeError, match="float64"):
        CheckedCommand(bad, True)


def test_a_checked_sample_is_a_sample_and_a_replaced_field_makes_a_plain_one() -> None:
    fields = _sample(np.arange(4.0))
    checked = CheckedSample(*fields)
    assert isinstance(checked, Sample)
    assert checked == Sample(*fields)  # the same fields: equal
    assert type(checked._replace(q_rad=np.zeros((2, 2)))) is Sample  # the new value is not checked
    assert type(CheckedCommand(np.arange(4.0), True)._replace(enable=False)) is Command
    for clone in (copy.copy(checked), copy.deepcopy(checked), pickle.loads(pickle.dumps(checked))):
        assert type(clone) is CheckedSample  # rebuilt through the checking constructor
    assert type(TORQUE_OFF) is CheckedCommand
    assert Command.torque_off() is TORQUE_OFF


def test_sim_samples_are_checked_samples_of_read_only_rows_that_never_change(tmp_path: Path) -> None:
    """Every kind of sample SimHal makes (fresh, after a refused command, with a NaN, stale, across
    blocks of readings) is a CheckedSample whose arrays fit SAMPLE_VECTOR, cannot be written or made
    writable, and keep their values however many ticks follow."""
    hal = SimHal("exo_dummy_arm")
    hal.open()
    kept: list[tuple[Sample, list[np.ndarray]]] = []

    def keep(sample: Sample) -> None:
        assert type(sample) is CheckedSample
        arrays = [sample.q_rad, sample.dq_rad_s, sample.theta_rad, sample.tau_nm]
        assert misfits((SAMPLE_VECTOR,) * 4, arrays) == []
        for array in arrays:
            assert array.shape == (4,)
            assert array.dtype == np.float64
            assert array.flags.c_contiguous
            assert not array.flags.writeable
            with pytest.raises(ValueError, match="WRITEABLE"):
                array.flags.writeable = True
        kept.append((sample, [a.copy() for a in arrays]))

    hold = CheckedCommand(hal.plant.holding_torque_nm(hal.truth().q_rad), True)
    keep(hal.read())
    for n in range(600):  # more than two blocks of 256 ticks
        hal.write(hold)
        if n == 100:
            with pytest.raises(ShapeError):
                hal.write(Command(np.zeros(3), True))  # refused: the tick's sample is built again
        if n == 200:
            hal.inject_fault("nan", joint=2)
        if n == 300:
            hal.inject_fault("stale", value=3)
        keep(hal.read())
    assert np.isnan(kept[201][0].q_rad[1])  # iteration n keeps kept[n + 1]: the NaN shows at once
    assert not np.isnan(kept[202][0].q_rad[1])  # in that sample only
    for sample, values in kept:  # nothing written since: every sample is as it was made
        for array, value in zip([sample.q_rad, sample.dq_rad_s, sample.theta_rad, sample.tau_nm], values, strict=True):
            np.testing.assert_array_equal(array, value)


# --- what the tick passes to each entry point ----------------------------------------------------


def test_what_the_tick_passes_fits_every_resolved_signature(tmp_path: Path) -> None:
    hal, loop, controller = identification_loop(tmp_path)
    monitor = loop.monitor
    spies = {
        "hal": (dynamics.HAL_TICK_SIGNATURE, Spy(hal._tick_kernel)),
        "in_bounds": (IN_BOUNDS_SIGNATURE, Spy(monitor._in_bounds_checked)),
        "status": (STATUS_SIGNATURE, Spy(monitor._status_checked)),
        "table": (TABLE_SIGNATURE, Spy(controller._table_checked)),
        "fill": (FILL_SIGNATURE, Spy(loop._fill_checked)),
    }
    hal._tick_kernel = spies["hal"][1]
    monitor._in_bounds_checked = spies["in_bounds"][1]
    monitor._status_checked = spies["status"][1]
    controller._table_checked = spies["table"][1]
    loop._fill_checked = spies["fill"][1]
    last = loop.run(600)  # past the noise refill (256 ticks) and two blocks of readings
    assert last is not None
    assert not last.faults
    for signature, spy in spies.values():
        assert_all_fit(signature, spy)
    # a plain command's torque (a list, a view with strides) is converted before the kernel
    hal.write(Command([0.0, 0.0, 0.0, 0.0], True))
    hal.write(Command(np.zeros(8)[::2], True))
    hal.write(TORQUE_OFF)
    assert_all_fit(dynamics.HAL_TICK_SIGNATURE, spies["hal"][1])
    loop.recorder.close()  # type: ignore[union-attr]


@pytest.mark.slow
def test_plain_samples_and_commands_take_the_dispatcher_and_give_the_same_results(tmp_path: Path) -> None:
    """The same ticks with every sample and command made plain (no CheckedSample, no CheckedCommand):
    the entry points are never called, and the recording, the commands and the faults are the same
    to the bit."""

    def run(plain: bool, folder: Path) -> tuple[np.ndarray, list[np.ndarray]]:
        folder.mkdir()
        hal, loop, controller = identification_loop(folder)
        if plain:
            read, update = hal.read, controller.update
            hal.read = lambda: Sample(*read())  # type: ignore[method-assign]
            controller.update = lambda s, dt: Command(*update(s, dt))  # type: ignore[method-assign]
            for name, owner in (("_in_bounds_checked", loop.monitor), ("_status_checked", loop.monitor),
                                ("_table_checked", controller), ("_fill_checked", loop)):  # fmt: skip
                setattr(owner, name, _never_called)
        commands = []
        for _ in range(400):
            result = loop.tick()
            assert not result.faults
            commands.append(np.array(result.command.motor_torque_nm))
        loop.recorder.close()  # type: ignore[union-attr]
        return read_recording(folder / "run.rec")[1], commands

    fast_rows, fast_commands = run(False, tmp_path / "fast")
    plain_rows, plain_commands = run(True, tmp_path / "plain")
    np.testing.assert_array_equal(fast_rows, plain_rows)
    np.testing.assert_array_equal(np.array(fast_commands), np.array(plain_commands))


def _never_called(*args: object) -> None:
    raise AssertionError("an entry point was called with a plain sample or command")


@pytest.mark.slow
def test_a_recorder_without_push_into_gets_the_same_row(tmp_path: Path) -> None:
    """The loop's own row through ``push`` (any recorder) and the row filled straight into a
    ``Recorder``'s block (``push_into``): the same ticks record the same bytes."""

    class PlainRecorder:
        def __init__(self) -> None:
            self.rows: list[np.ndarray] = []

        def push(self, row: np.ndarray) -> bool:
            self.rows.append(np.array(row))
            return True

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    _, into, _ = identification_loop(tmp_path / "a")
    _, plain_loop, _ = identification_loop(tmp_path / "b")
    plain_loop.recorder.close()  # type: ignore[union-attr]
    plain = PlainRecorder()
    plain_loop.recorder = plain
    into.run(300)
    plain_loop.run(300)
    into.recorder.close()  # type: ignore[union-attr]
    rows = read_recording(tmp_path / "a" / "run.rec")[1]
    assert rows.shape == (300, N_RECORD_COLUMNS)
    np.testing.assert_array_equal(rows, np.array(plain.rows))


# --- Recorder.push_into ---------------------------------------------------------------------------


def test_push_into_records_what_push_records_and_checks_the_row_length(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    rows = rng.normal(size=(2500, N_RECORD_COLUMNS))

    def fill(block: np.ndarray, index: int, row: np.ndarray) -> None:
        block[index] = row

    with Recorder(tmp_path / "a.rec", RECORD_COLUMNS, block_rows=100, max_queued_blocks=40) as a:
        for row in rows:
            assert a.push(row)
    with Recorder(tmp_path / "b.rec", RECORD_COLUMNS, block_rows=100, max_queued_blocks=40) as b:
        for row in rows:
            assert b.push_into(fill, N_RECORD_COLUMNS, row)
        with pytest.raises(RuntimeShapeError):
            b.push_into(fill, N_RECORD_COLUMNS - 1, rows[0][:-1])
        assert b.rows_accepted == len(rows)
    np.testing.assert_array_equal(read_recording(tmp_path / "a.rec")[1], read_recording(tmp_path / "b.rec")[1])


# --- the stationary reduction's low-pass without scipy.signal -------------------------------------


@pytest.mark.parametrize(
    ("cutoff_hz", "rate_hz"),
    [(2.0, 1000.0), (2.0, 999.9999999999991), (2.0, 1000.0000000000009), (0.5, 100.0), (49.0, 100.0), (3.3, 1234.5)],
)
def test_the_low_pass_is_scipys_to_the_bit(cutoff_hz: float, rate_hz: float) -> None:
    sos = scipy.signal.butter(2, cutoff_hz, fs=rate_hz, output="sos")
    ours = lowpass.butter2_lowpass_sos(cutoff_hz, rate_hz)
    np.testing.assert_array_equal(ours, sos)
    x = np.random.default_rng(1).normal(size=(3000, 4)).cumsum(axis=0) * 1e-3
    expected = scipy.signal.sosfiltfilt(sos, x, axis=0, padtype="even")
    got = lowpass.sosfiltfilt_even(ours, x)
    np.testing.assert_array_equal(got, expected)
    assert got.strides == expected.strides  # the same layout: a reduction over it adds in the same order
    np.testing.assert_array_equal(np.linalg.norm(got, axis=1), np.linalg.norm(expected, axis=1))
    threshold = float(np.median(np.linalg.norm(expected, axis=1)))
    np.testing.assert_array_equal(_norm_below(got, threshold), np.linalg.norm(expected, axis=1) < threshold)


def test_another_filter_order_is_left_to_scipy() -> None:
    t = np.arange(2000) * 1e-3
    dq = np.random.default_rng(2).normal(size=(2000, 4)) * 0.01
    raw = RawLog(t, np.zeros((2000, 4)), dq, np.zeros((2000, 4)))
    settings = ReductionSettings(filter_order=3)
    expected = scipy.signal.sosfiltfilt(
        scipy.signal.butter(3, settings.cutoff_hz, fs=1.0 / float(np.median(np.diff(t))), output="sos"),
        dq,
        axis=0,
        padtype="even",
    )
    np.testing.assert_array_equal(filtered_velocity(raw, settings), expected)


@pytest.mark.subprocess
def test_identify_needs_neither_scipy_signal_nor_the_torque_loop() -> None:
    """What ``daror identify`` imports and runs must not pull in scipy.signal (~0.5 s, ~50 MB) or the
    SEA torque controller's kernel; the control package's other names still import on first use."""
    code = (
        "import sys\n"
        "import daror_runtime.identification.protocol, daror_runtime.data.stationary\n"
        "assert 'scipy.signal' not in sys.modules, 'scipy.signal imported'\n"
        "assert 'daror_runtime.control.sea_torque' not in sys.modules, 'the torque loop imported'\n"
        "from daror_runtime.control import SeaTorqueController, MinimalImpedance, SeaPlant, LinkBounds\n"
        "assert SeaTorqueController.__name__ == 'SeaTorqueController'\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=False)
    assert done.returncode == 0, done.stderr
